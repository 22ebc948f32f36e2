"""Wear floors of a path: the least tire wear of any motion that keeps to the path.

Part of every run's wear is fixed by the path, whatever the controller does: to follow a
curve at speed the tires must produce the centripetal force, and producing a lateral force
with a tire takes a slip angle, which dissipates ``|F_y v_wy|`` (paper eq. 14); and the
wheels must turn to follow the curve, which costs ``k_t F_N |omega_s|`` (eq. 15). Only the
wear above this floor is the controller's to save, and that is where a wear term in the
MPC can act (docs/RESULTS.md reports every run's wear above it).

The floor is the least wear work ``W_tw = int (P_s + P_alpha + P_t) dt`` of the plant's own
equations over a window ``[t0, t1]`` (eq. 4-17: the rigid body; the Magic Formula tires of
eq. 9-12 at the paper's constant loads ``F_N = m g / (2n)``, with the plant's regularised
``|v_wx|``; the wear powers of eq. 13-15) for a vehicle whose centre stays within ``tol``
(1 cm) of the reference's position and whose heading stays within ``tol_phi`` (2 deg) of
the reference's at every node, with its velocities, wheel angles and commands free within
the vehicle's limits (``0 <= omega_w <= omega_w_max``, ``omega_s`` within its rates,
``delta`` within its stops); it starts with the reference's heading and velocities (as a
run does) and ends free. Any run that keeps within these tolerances is such a motion, so
it cannot wear less, to the transcription's accuracy and as far as IPOPT's optimum is the
least (the problem is not convex: docs/WEAR.md "Wear floors" measures both).

Why an optimum and not a formula (issue 29, measured in docs/WEAR.md): the floor of exact,
quasi-steady tracking (the reference's heading and accelerations, the forces allocated
sample by sample) was beaten by up to a third by real runs on lane changes: a vehicle
within a millimetre of the path may yaw less than the reference, spread a curvature step's
yaw acceleration over a longer time and let its slip angles cancel part of its steering.
Those are trajectory choices, coupled in time; the least wear over them is the optimum of
a trajectory problem, here a direct transcription (trapezoidal collocation at ``dt``, each
command held over its interval) solved by IPOPT through casadi. ``benchmarks/floor_bound.py``
checks it against an independent transcription (world-frame states, another steering
split) on transient paths at 2-8 axles.

A window longer than ``window`` seconds is solved in equal parts, each with free ends: the
sum of the parts' optima is at most the whole's (the whole's optimum, cut at the joints, is
feasible for every part), so it stays a lower bound; what it gives away is the cost of
carrying state across a joint (measured in docs/WEAR.md).

The split of the optimum's slip wear between ``W_s`` and ``W_alpha`` is the optimum's, not a
bound on either: a run may trade one for the other (``broken_floor`` compares their sum).
A run that cuts corners (more than ``tol`` from the path) can go below the floor, which is
why wear is compared at matched accuracy.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from msagv.plant.vehicle import Vehicle


BROKEN_RATIO = 0.995  # a run's wear below this times its floor: the floor is broken
NO_FLOOR_J = 1.0  # J: a floor below this (a straight path: the solver's rounding) is none
FLOOR_TOL_M = 0.01  # m: the floor holds the path to this (the study's "within 1 cm")
FLOOR_TOL_PHI_DEG = 2.0  # deg: and the heading to this (runs track it within a fraction)
FLOOR_WINDOW_S = 30.0  # s: longer windows are solved in equal parts (free ends, a relaxation)




class FloorError(RuntimeError):
    """No floor for this path: IPOPT did not solve its problem (a run then has no floor to
    be compared with; the study and ``msagv run`` say so and go on)."""

def broken_floor(metrics: dict, floors: dict, ratio: float = BROKEN_RATIO) -> list[dict]:
    """The floor a run's wear ``metrics`` (``W_tw`` [J]) lies below ``ratio`` times of
    (``floors``: :meth:`Floors.as_dict`), as ``[{part, W, floor, ratio}]`` (empty: none).
    Only ``W_tw`` is compared: the floor is the least total wear, and its split between
    ``W_s``, ``W_alpha`` and ``W_t`` is the optimum's, not a bound on any one of them (a
    run may trade slip for steering: docs/WEAR.md). A run below it within ``tol`` of the
    path means the floor is not a lower bound there (or the run cut the path: see its
    error). Floors under ``NO_FLOOR_J`` (a straight path's rounding) are not compared."""
    w, f = metrics.get("W_tw"), floors.get("W_tw_floor")
    if w is None or f is None or f < NO_FLOOR_J or not w < ratio * f:
        return []
    return [{"part": "W_tw", "W": w, "floor": f, "ratio": w / f}]


def _sum(a, b):
    return None if a is None or b is None else a + b


def broken_floor_warning(broken: list[dict], what: str = "the run") -> str:
    """A one-line warning for :func:`broken_floor`'s (non-empty) result."""
    parts = ", ".join(f"{p['part']} {p['W']:.4g} J = {p['ratio']:.3f} x its floor "
                      f"{p['floor']:.4g} J" for p in broken)
    return (f"broken floor: {what} wears less than {BROKEN_RATIO} x the wear floor of any motion "
            f"within {100.0 * FLOOR_TOL_M:g} cm and {FLOOR_TOL_PHI_DEG:g} deg of the path "
            f"({parts}): the floor is not a lower bound here "
            f"(docs/WEAR.md, "
            f"Wear floors)")


@dataclass(frozen=True)
class Floors:
    """The wear floor of a reference over a time window [J], and its optimum's series."""

    W_s: float
    W_alpha: float
    W_t: float
    t: np.ndarray  # node times [s]
    P: np.ndarray  # (len(t), 3) the optimum's powers P_s, P_alpha, P_t [W]
    delta: np.ndarray  # (len(t), 2n) the optimum's steering angles [rad]
    tol: float = FLOOR_TOL_M  # the position tolerance it holds the path to [m]
    tol_phi_deg: float | None = FLOOR_TOL_PHI_DEG  # and the heading's [deg] (None: free)
    cpu_s: float = 0.0  # the solver's CPU time [s]

    @property
    def W_tw(self) -> float:
        return self.W_s + self.W_alpha + self.W_t

    def as_dict(self) -> dict:
        return {"W_s_floor": self.W_s, "W_alpha_floor": self.W_alpha, "W_t_floor": self.W_t,
                "W_tw_floor": self.W_tw}


def _mf(xi, B, C, D, E, ca):
    """The Magic Formula (eq. 11-12) on casadi symbols."""
    Bx = B * xi
    return D * ca.sin(C * ca.atan(Bx - E * (Bx - ca.atan(Bx))))


def _plant_function(vehicle: Vehicle):
    """A casadi function (X, U) -> (dX/dt, P_s, P_alpha) of the plant's equations in the
    body frame: X = (x, y, phi, u, v, r, delta_1..2n), (u, v) the velocity in B; U =
    (omega_w, omega_s, b) per wheel, b >= |omega_s| the steering rate's bound."""
    import casadi as ca

    from msagv.plant.dynamics import V_EPS_DEFAULT

    n = vehicle.n_wheels
    wx, wy = vehicle.wheel_x, vehicle.wheel_y
    m, Iz, rw = vehicle.mass, vehicle.yaw_inertia, vehicle.wheel_radius
    FN = vehicle.normal_load
    lo, la = vehicle.tire_longitudinal, vehicle.tire_lateral
    X = ca.SX.sym("X", 6 + n)
    U = ca.SX.sym("U", 3 * n)
    phi, u, v, r = X[2], X[3], X[4], X[5]
    fx = fy = mz = ps = pa = 0
    for i in range(n):
        d, om = X[6 + i], U[i]
        cd, sd = ca.cos(d), ca.sin(d)
        bx, by = u - r * wy[i], v + r * wx[i]  # eq. (6)-(7)
        vwx, vwy = cd * bx + sd * by, -sd * bx + cd * by  # in the wheel's frame
        den = ca.sqrt(vwx * vwx + V_EPS_DEFAULT * V_EPS_DEFAULT)  # the plant's |v_wx|
        slip = om * rw - vwx
        Fx = _mf(slip / den, lo.B, lo.C, lo.mu * FN, lo.E, ca)  # eq. (10)-(11)
        Fy = _mf(-ca.atan(vwy / den), la.B, la.C, la.mu * FN, la.E, ca)  # eq. (9), (12)
        ps += Fx * slip  # eq. (13): >= 0, the force has the slip's sign
        pa -= Fy * vwy  # eq. (14): >= 0 likewise
        Fbx, Fby = cd * Fx - sd * Fy, sd * Fx + cd * Fy  # eq. (4)
        fx += Fbx
        fy += Fby
        mz += wx[i] * Fby - wy[i] * Fbx  # eq. (5)
    c, s = ca.cos(phi), ca.sin(phi)
    dX = ca.vertcat(c * u - s * v, s * u + c * v, r,
                    fx / m + r * v, fy / m - r * u, mz / Iz,  # eq. (17) in the body frame
                    U[n:2 * n])
    return ca.Function("plant", [X, U], [dX, ps, pa])


def _solve_window(reference, vehicle: Vehicle, t0: float, t1: float, tol: float, dt: float,
                  max_iter: int, tol_phi: float | None = None, guess=None,
                  fixed_start: bool = False):
    """One window's optimum: (t, P (N+1, 3), delta (N+1, 2n), (W_s, W_alpha, W_t), cpu, the
    states (N+1, 6+2n), the commands (N, 6n))."""
    import casadi as ca

    n = vehicle.n_wheels
    N = max(int(math.ceil((t1 - t0) / dt - 1e-9)), 1)
    h = (t1 - t0) / N
    t = t0 + h * np.arange(N + 1)
    R = reference.sample(t)
    f = _plant_function(vehicle)
    nx, nu = 6 + n, 3 * n
    X = ca.MX.sym("X", nx, N + 1)
    U = ca.MX.sym("U", nu, N)
    fm = f.map(N)
    d0, ps0, pa0 = fm(X[:, :N], U)
    d1, ps1, pa1 = fm(X[:, 1:], U)
    kt_FN = vehicle.steer_loss_kt * vehicle.normal_load
    J_s = 0.5 * h * ca.sum2(ps0 + ps1)
    J_a = 0.5 * h * ca.sum2(pa0 + pa1)
    J_t = h * kt_FN * ca.sum1(ca.sum2(U[2 * n:, :]))  # eq. (15) with b = |omega_s|
    xr, yr = ca.DM(R[:, 0]).T, ca.DM(R[:, 1]).T
    g = ca.vertcat(ca.vec(X[:, 1:] - X[:, :N] - 0.5 * h * (d0 + d1)),  # trapezoidal
                   ca.vec((X[0, :] - xr) ** 2 + (X[1, :] - yr) ** 2),  # within tol
                   ca.vec(U[2 * n:, :] - U[n:2 * n, :]), ca.vec(U[2 * n:, :] + U[n:2 * n, :]))
    lbg = np.zeros(nx * N + (N + 1) + 2 * n * N)
    ubg = np.concatenate([np.zeros(nx * N), np.full(N + 1, tol * tol), np.full(2 * n * N, np.inf)])
    if tol_phi is not None:  # the heading within tol_phi of the reference's
        g = ca.vertcat(g, ca.vec(X[2, :] - ca.DM(np.unwrap(R[:, 2])).T))
        lbg = np.concatenate([lbg, np.full(N + 1, -tol_phi)])
        ubg = np.concatenate([ubg, np.full(N + 1, tol_phi)])
    lim = vehicle.limits
    inf = np.inf
    lbx = np.concatenate([np.tile(np.r_[np.full(6, -inf), np.full(n, lim.delta_min)], N + 1),
                          np.tile(np.r_[np.zeros(n), np.full(n, lim.omega_s_min), np.zeros(n)], N)])
    ubx = np.concatenate([np.tile(np.r_[np.full(6, inf), np.full(n, lim.delta_max)], N + 1),
                          np.tile(np.r_[np.full(n, lim.omega_w_max), np.full(n, lim.omega_s_max),
                                        np.full(n, inf)], N)])
    # the start of the search: the reference's motion, each wheel along its velocity
    phi, r = R[:, 2], R[:, 5]
    c, s = np.cos(phi), np.sin(phi)
    ub, vb = c * R[:, 3] + s * R[:, 4], -s * R[:, 3] + c * R[:, 4]
    bx = ub[:, None] - r[:, None] * vehicle.wheel_y[None, :]
    by = vb[:, None] + r[:, None] * vehicle.wheel_x[None, :]
    theta = np.clip(np.unwrap(np.arctan2(by, bx), axis=0), lim.delta_min, lim.delta_max)
    X0 = np.column_stack([R[:, 0], R[:, 1], np.unwrap(phi), ub, vb, r, theta])
    rate = np.clip(np.diff(theta, axis=0) / h, lim.omega_s_min, lim.omega_s_max)
    U0 = np.column_stack([np.clip(np.hypot(bx, by)[:-1] / vehicle.wheel_radius, 0.0,
                                  lim.omega_w_max), rate, np.abs(rate)])
    if guess is not None:
        X0, U0 = guess(t)
    if fixed_start:  # heading, velocities and yaw rate the reference's (a run starts there)
        lbx[2:6] = ubx[2:6] = [phi[0], ub[0], vb[0], r[0]]
    w = ca.vertcat(ca.vec(X), ca.vec(U))
    J = ca.Function("J", [w], [J_s, J_a, J_t])
    solver = ca.nlpsol("floor", "ipopt", {"x": w, "f": J_s + J_a + J_t, "g": g}, {
        "print_time": False, "ipopt": {"print_level": 0, "sb": "yes", "max_iter": max_iter,
                                       "tol": 1e-9, "acceptable_tol": 1e-7}})
    tc = time.process_time()
    sol = solver(x0=np.concatenate([X0.ravel(), U0.ravel()]), lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
    cpu = time.process_time() - tc
    status = solver.stats()["return_status"]
    if status not in ("Solve_Succeeded", "Solved_To_Acceptable_Level"):
        raise FloorError(f"wear_floors: IPOPT did not solve the window [{t0:g}, {t1:g}] s "
                           f"({status}): no floor")
    wo = np.asarray(sol["x"]).ravel()
    Xo = wo[:nx * (N + 1)].reshape(N + 1, nx)
    Uo = wo[nx * (N + 1):].reshape(N, nu)
    _, ps, pa = f.map(N + 1)(Xo.T, np.column_stack([Uo.T, Uo[-1]]))
    P = np.zeros((N + 1, 3))
    P[:, 0], P[:, 1] = np.asarray(ps).ravel(), np.asarray(pa).ravel()
    P[:N, 2] = kt_FN * Uo[:, 2 * n:].sum(axis=1)  # held over each interval (the last: none)
    W = tuple(float(x) for x in J(wo))
    return t, P, Xo[:, 6:], W, cpu, Xo, Uo


def wear_floors(reference, vehicle: Vehicle, t0: float, t1: float, dt: float = 0.05,
                tol: float = FLOOR_TOL_M, tol_phi_deg: float | None = FLOOR_TOL_PHI_DEG,
                window: float = FLOOR_WINDOW_S, max_iter: int = 3000,
                fixed_start: bool = True) -> Floors:
    """The wear floor of keeping within ``tol`` [m] of ``reference``'s position and within
    ``tol_phi_deg`` of its heading (None: any heading) with ``vehicle`` over [t0, t1],
    starting with the reference's heading and velocities (module docstring; with
    ``fixed_start`` false from any, within the tolerances: the floor of a run that starts
    elsewhere, e.g. at rest, a lower bound for any start): ``dt`` the
    collocation step [s], ``window`` the longest part solved at once [s]. Raises
    ValueError on an empty window or a bad step or tolerance, RuntimeError if IPOPT does
    not solve a part."""
    if not t1 > t0:
        raise ValueError(f"wear_floors: empty window [{t0}, {t1}]")
    if not (dt > 0.0 and tol > 0.0 and window > 0.0
            and (tol_phi_deg is None or tol_phi_deg > 0.0)):
        raise ValueError(f"wear_floors: need dt > 0, tol > 0, tol_phi_deg > 0, window > 0 "
                         f"(got {dt}, {tol}, {tol_phi_deg}, {window})")
    tol_phi = None if tol_phi_deg is None else math.radians(tol_phi_deg)
    parts = max(int(math.ceil((t1 - t0) / window - 1e-9)), 1)
    edges = np.linspace(t0, t1, parts + 1)
    ts, Ps, ds, W, cpu = [], [], [], np.zeros(3), 0.0
    for j in range(parts):
        t, P, d, Wj, c, _, _ = _solve_window(reference, vehicle, float(edges[j]),
                                             float(edges[j + 1]), tol, dt, max_iter, tol_phi,
                                             fixed_start=fixed_start and j == 0)
        keep = slice(0 if j == 0 else 1, None)  # a joint's node once (the later part's)
        ts.append(t[keep])
        Ps.append(P[keep])
        ds.append(d[keep])
        W += Wj
        cpu += c
    return Floors(float(W[0]), float(W[1]), float(W[2]), np.concatenate(ts), np.concatenate(Ps),
                  np.concatenate(ds), tol, tol_phi_deg, cpu)
