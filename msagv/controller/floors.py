"""Wear floors of a path: the tire wear that tracking the reference exactly cannot avoid.

Part of every run's wear is fixed by the path, whatever the controller does: to follow a
curve at speed the tires must produce the centripetal force, and producing a lateral force
with a tire takes a slip angle, which dissipates ``|F_y v_wy|`` (paper eq. 14); and the
wheels must turn to follow the curve, which costs ``k_t F_N |omega_s|`` (eq. 15). Only the
wear above these floors is the controller's to save, and that is where a wear term in the
MPC can act (docs/RESULTS.md reports every run's wear above them).

Derivation (docs/RESULTS.md, "Wear floors"), for the vehicle tracking the reference
exactly and quasi-steadily (tire forces follow the slips at once, as in the paper's
model), at every sample of the reference:

1. The body force and yaw moment the motion needs, from the reference's accelerations in
   the body frame: ``F_B = m (u' - r v, v' + r u)`` (eq. 17 read backwards, with (u, v) the
   reference velocity in B; it contains the centripetal force ``m v^2 kappa``) and
   ``M_z = I_vz r'``, the derivatives by a Savitzky-Golay filter over 0.2 s.
2. Each wheel moves with the velocity the rigid body gives it (eq. 6-7), at speed ``v_i``
   and heading ``theta_i``. A wheel producing a lateral force ``F_y`` (perpendicular to
   its velocity) runs at the slip angle ``alpha = f_lat^-1(F_y)`` and dissipates
   ``P_alpha = |F_y| v_i tan|alpha|`` (eq. 14 with ``v_wy = v_wx tan alpha``); a
   longitudinal force ``F_x`` needs the slip ratio ``s = f_lon^-1(F_x)`` and dissipates
   ``P_s = |F_x| v_i |s|`` (eq. 13). Both are convex and increasing in the force.
3. The floor is the least total dissipation over all per-wheel force allocations whose
   sum is ``(F_B, M_z)``, with each wheel's forces along and across its velocity (the
   slip angles are small, so the wheel's own axes are taken as its velocity's; they
   differ by ``alpha``, a few degrees at most): a small convex problem per sample, solved
   with scipy (SLSQP). Loads are the paper's constant ``F_N = m g / (2n)``.
4. The steering floor: each wheel must point along its velocity plus its slip angle,
   ``delta_i = theta_i + alpha_i``; following that angle costs
   ``W_t = sum_i k_t F_N integral |d delta_i / dt| dt`` (eq. 15), the least steering
   travel of an exactly tracking vehicle.

So ``W_alpha_floor`` is the slip-angle wear of the centripetal (and yaw) forces,
``W_s_floor`` the slip-ratio wear of the longitudinal forces (the cornering drag of the
slip angles, and the path's own acceleration), ``W_t_floor`` the steering-travel wear.
These bound a controller that tracks exactly; one that cuts corners (large tracking error)
can go below them, which is why wear is compared at matched accuracy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.signal import savgol_filter

from msagv.plant.tire import magic_formula
from msagv.plant.vehicle import G_ACCEL, Vehicle


BROKEN_RATIO = 0.995  # a run's wear below this times its floor: the floor is broken
NO_FLOOR_J = 1.0  # J: a floor below this (a straight path: the allocation's rounding) is none


def broken_floor(metrics: dict, floors: dict, ratio: float = BROKEN_RATIO) -> list[dict]:
    """The floors a run's wear ``metrics`` (``W_tw``, ``W_s``, ``W_alpha``, ``W_t`` [J]) lies
    below ``ratio`` times of (``floors``: :meth:`Floors.as_dict`), as ``[{part, W, floor,
    ratio}]`` (empty: none). The parts: ``W_tw``; ``W_slip`` = W_s + W_alpha, the sum the
    force allocation bounds (its split between W_s and W_alpha is the floor's optimum, not
    a bound on either: a run may trade one for the other); ``W_t``, the steering travel's.
    A floor of exact tracking bounds a run that tracks: a run below it means the floor is
    not a lower bound on this path (or the run cut the path short: see its error). Floors
    under ``NO_FLOOR_J`` (a straight path's, 1e-4 J of rounding) are not compared."""
    parts = (("W_tw", metrics.get("W_tw"), floors.get("W_tw_floor")),
             ("W_slip", _sum(metrics.get("W_s"), metrics.get("W_alpha")),
              _sum(floors.get("W_s_floor"), floors.get("W_alpha_floor"))),
             ("W_t", metrics.get("W_t"), floors.get("W_t_floor")))
    return [{"part": name, "W": w, "floor": f, "ratio": w / f} for name, w, f in parts
            if w is not None and f is not None and f >= NO_FLOOR_J and w < ratio * f]


def _sum(a, b):
    return None if a is None or b is None else a + b


def broken_floor_warning(broken: list[dict], what: str = "the run") -> str:
    """A one-line warning for :func:`broken_floor`'s (non-empty) result."""
    parts = ", ".join(f"{p['part']} {p['W']:.4g} J = {p['ratio']:.3f} x its floor "
                      f"{p['floor']:.4g} J" for p in broken)
    return (f"broken floor: {what} wears less than {BROKEN_RATIO} x the wear floor of exact "
            f"tracking ({parts}): the floor is not a lower bound here (docs/RESULTS.md, "
            f"Wear floors)")


@dataclass(frozen=True)
class Floors:
    """The wear floors of a reference over a time window [J], and their time series."""

    W_s: float
    W_alpha: float
    W_t: float
    t: np.ndarray  # sample times [s]
    P: np.ndarray  # (len(t), 3) floor powers P_s, P_alpha, P_t [W]
    delta: np.ndarray  # (len(t), 2n) the floor's steering angles [rad]

    @property
    def W_tw(self) -> float:
        return self.W_s + self.W_alpha + self.W_t

    def as_dict(self) -> dict:
        return {"W_s_floor": self.W_s, "W_alpha_floor": self.W_alpha, "W_t_floor": self.W_t,
                "W_tw_floor": self.W_tw}


def _inverse_mf(F, B, C, D, E, xmax):
    """The slip ``xi`` in [0, xmax] with ``f(xi) = F`` (F >= 0, f increasing there), by
    bisection; F beyond the peak gives xmax (the force cannot be produced)."""
    lo = np.zeros_like(F)
    hi = np.full_like(F, xmax)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = magic_formula(mid, B, C, D, E) < F
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def _peak(B, C, D, E, xmax):
    """The slip of the Magic Formula's peak within (0, xmax] (a fine grid, then its cell)."""
    xs = np.linspace(0.0, xmax, 4001)
    f = magic_formula(xs, B, C, D, E)
    return float(xs[int(np.argmax(f))])


class _Tire:
    """Dissipation of one wheel producing a longitudinal / lateral force (convex curves
    tabulated once, interpolated in the optimisation)."""

    def __init__(self, vehicle: Vehicle, n_grid: int = 400):
        FN = vehicle.normal_load
        lo, la = vehicle.tire_longitudinal, vehicle.tire_lateral
        self.s_peak = _peak(lo.B, lo.C, lo.mu * FN, lo.E, 1.0)
        self.a_peak = _peak(la.B, la.C, la.mu * FN, la.E, 0.5 * math.pi)
        self.Fx_max = float(magic_formula(self.s_peak, lo.B, lo.C, lo.mu * FN, lo.E))
        self.Fy_max = float(magic_formula(self.a_peak, la.B, la.C, la.mu * FN, la.E))
        self.Fx = np.linspace(0.0, self.Fx_max, n_grid)
        self.Fy = np.linspace(0.0, self.Fy_max, n_grid)
        self.s = _inverse_mf(self.Fx, lo.B, lo.C, lo.mu * FN, lo.E, self.s_peak)
        self.alpha = _inverse_mf(self.Fy, la.B, la.C, la.mu * FN, la.E, self.a_peak)
        # dissipation per unit wheel speed: |F| |s| and |F| tan|alpha|
        self.qx = self.Fx * self.s
        self.qy = self.Fy * np.tan(self.alpha)

    def slip_angle(self, Fy):
        return np.sign(Fy) * np.interp(np.abs(Fy), self.Fy, self.alpha)

    def cost(self, Fx, Fy, v):
        """(P_s, P_alpha) [W] of forces Fx, Fy at wheel speeds v, with their gradients."""
        ax, ay = np.abs(Fx), np.abs(Fy)
        qx = np.interp(ax, self.Fx, self.qx)
        qy = np.interp(ay, self.Fy, self.qy)
        dqx = np.interp(ax, self.Fx[1:], np.diff(self.qx) / np.diff(self.Fx)) * np.sign(Fx)
        dqy = np.interp(ay, self.Fy[1:], np.diff(self.qy) / np.diff(self.Fy)) * np.sign(Fy)
        return v * qx, v * qy, v * dqx, v * dqy


def wear_floors(reference, vehicle: Vehicle, t0: float, t1: float, dt: float = 0.02) -> Floors:
    """The wear floors of tracking ``reference`` exactly with ``vehicle`` over [t0, t1]
    (module docstring). ``dt``: the sample step of the integral [s]."""
    if not t1 > t0:
        raise ValueError(f"wear_floors: empty window [{t0}, {t1}]")
    # the motion's accelerations from a fine sampling of the reference, differentiated in
    # the body frame (the speed along and across the heading varies slowly, unlike vx, vy)
    # with a Savitzky-Golay filter over 0.2 s: finite differences of the linearly
    # interpolated table would add noise, and noise adds dissipation (the costs are convex)
    # The filter's window stays within the reference's table: past its last row a reference
    # continues straight (yaw rate 0) or stops, a jump no vehicle tracking the table makes
    # (it put a spurious yaw moment into the floor of a trajectory CSV that ends with the
    # run); the filter fits its polynomial up to the table's ends instead.
    fine = 0.01
    lo = max(t0 - 0.2, float(reference.t[0]))
    hi = max(min(t1 + 0.2, float(reference.t[-1])), lo + 0.3)
    tf = np.arange(lo, hi + 0.5 * fine, fine)
    Rf = reference.sample(tf)
    phi_f, r_f = Rf[:, 2], Rf[:, 5]
    cf, sf = np.cos(phi_f), np.sin(phi_f)
    u_f = cf * Rf[:, 3] + sf * Rf[:, 4]
    v_f = -sf * Rf[:, 3] + cf * Rf[:, 4]
    win = 21
    du = savgol_filter(u_f, win, 3, deriv=1, delta=fine)
    dv = savgol_filter(v_f, win, 3, deriv=1, delta=fine)
    dr_f = savgol_filter(r_f, win, 3, deriv=1, delta=fine)
    t = np.arange(t0, t1 + 0.5 * dt, dt)
    R = reference.sample(t)
    phi, r = R[:, 2], R[:, 5]
    c, s = np.cos(phi), np.sin(phi)
    ub = c * R[:, 3] + s * R[:, 4]
    vb = -s * R[:, 3] + c * R[:, 4]
    m, Iz = vehicle.mass, vehicle.yaw_inertia
    FBx = m * (np.interp(t, tf, du) - r * vb)  # eq. (17) in B: m (u' - r v)
    FBy = m * (np.interp(t, tf, dv) + r * ub)  # m (v' + r u): the centripetal force
    Mz = Iz * np.interp(t, tf, dr_f)
    wx, wy = vehicle.wheel_x, vehicle.wheel_y
    nw = vehicle.n_wheels
    vwx = ub[:, None] - r[:, None] * wy[None, :]  # eq. (6)
    vwy = vb[:, None] + r[:, None] * wx[None, :]  # eq. (7)
    v = np.hypot(vwx, vwy)
    theta = np.arctan2(vwy, vwx)
    tire = _Tire(vehicle)
    P = np.zeros((len(t), 3))
    delta = np.zeros((len(t), nw))
    z = np.zeros(2 * nw)
    for k in range(len(t)):
        ct, st = np.cos(theta[k]), np.sin(theta[k])
        # body force of wheel i: (ct Fx - st Fy, st Fx + ct Fy); moment x Fby - y Fbx
        A = np.zeros((3, 2 * nw))
        A[0, :nw], A[0, nw:] = ct, -st
        A[1, :nw], A[1, nw:] = st, ct
        A[2, :nw] = wx * st - wy * ct
        A[2, nw:] = wx * ct + wy * st
        b = np.array([FBx[k], FBy[k], Mz[k]])
        vk = v[k]

        def f(zz, vk=vk):
            ps, pa, gx, gy = tire.cost(zz[:nw], zz[nw:], vk)
            return ps.sum() + pa.sum(), np.concatenate([gx, gy])

        # least-norm allocation as the start (exact for a linear tire of equal stiffness)
        z0 = np.linalg.lstsq(A, b, rcond=None)[0] if k == 0 else z
        res = minimize(f, z0, jac=True, method="SLSQP",
                       constraints=[{"type": "eq", "fun": lambda zz, A=A, b=b: A @ zz - b,
                                     "jac": lambda zz, A=A: A}],
                       options={"maxiter": 200, "ftol": 1e-10})
        z = res.x
        ps, pa, _, _ = tire.cost(z[:nw], z[nw:], vk)
        P[k, 0], P[k, 1] = ps.sum(), pa.sum()
        delta[k] = theta[k] + tire.slip_angle(z[nw:])
    lim = vehicle.limits
    delta = np.clip(np.unwrap(delta, axis=0), lim.delta_min, lim.delta_max)
    rate = np.abs(np.gradient(delta, t, axis=0))
    P[:, 2] = vehicle.steer_loss_kt * (m * G_ACCEL / nw) * rate.sum(axis=1)  # eq. (15)
    W = np.trapezoid(P, t, axis=0) if hasattr(np, "trapezoid") else np.trapz(P, t, axis=0)
    return Floors(float(W[0]), float(W[1]), float(W[2]), t, P, delta)
