"""The wear floor checked by a second transcription, solved by IPOPT.

The wear floor of :mod:`controller.floors` is the least wear work ``W_tw = int (P_s +
P_alpha + P_t) dt`` of the plant's equations over a window, for a vehicle within ``tol`` of
the path's position (and optionally ``tol_phi`` of its heading). This writes the same
problem a second time, independently (issue 29): world-frame states ``x, y, phi, vx, vy,
r, delta_i`` at the nodes (the floor's are body-frame), commands per interval,
``|omega_s|`` split into two non-negative parts (the floor bounds it by an epigraph
variable), built with casadi's Opti (the floor with ``nlpsol`` on mapped functions); the
rigid body, the Magic Formula tires of eq. 11-12 at the constant loads ``m g / (2n)``, the
wear powers of eq. 13-15 (``P_s = F_x (omega_w r_w - v_wx) >= 0`` and ``P_alpha = -F_y
v_wy >= 0``: the force has the slip's sign), trapezoidal collocation at ``dt`` with each
command held over its interval, the commands within the vehicle's limits. The ends are
free (the floor's problem), or with ``fixed_start`` the start's heading and velocities the
reference's (the floor's default, as a run starts), or with ``fixed_ends`` both ends' the
reference's with every wheel along its velocity. Started from the reference's kinematics.

``python -m msagv.benchmarks.floor_bound SCENARIO.toml T0 T1 [--tol-cm 1] [--tol-deg 2]
[--dt 0.05] [--fixed-start] [--log RUN.csv]`` prints the bound, the floor over the same
window and with ``--log`` (a ``msagv run --log``) that run's wear over it, as JSON;
``--sweep`` compares floor and bound on 20 transient scenarios at 2-8 axles and prints a
Markdown table (docs/WEAR.md, "Wear floors"). Both are IPOPT's local optima of a problem
that is not convex: agreeing, they check each other's equations, not global optimality.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def _mf(xi, B, C, D, E, ca):
    Bx = B * xi
    return D * ca.sin(C * ca.atan(Bx - E * (Bx - ca.atan(Bx))))


def lower_bound(reference, vehicle, t0: float, t1: float, tol: float = 0.01,
                dt: float = 0.02, max_iter: int = 3000, tol_phi: float | None = None,
                fixed_ends: bool = False, fixed_start: bool = False) -> dict:
    """The least ``W_tw`` [J] (and its parts) over ``[t0, t1]`` of a vehicle whose
    position stays within ``tol`` [m] of ``reference`` (and its heading within
    ``tol_phi`` [rad] of the reference's, if given) (module docstring)."""
    import casadi as ca

    from msagv.plant.dynamics import V_EPS_DEFAULT
    from msagv.plant.vehicle import G_ACCEL

    if not t1 > t0 or not tol > 0.0 or not dt > 0.0:
        raise ValueError(f"floor_bound: need t1 > t0, tol > 0, dt > 0 (got {t0}, {t1}, "
                         f"{tol}, {dt})")
    N = max(int(round((t1 - t0) / dt)), 1)
    h = (t1 - t0) / N
    t = t0 + h * np.arange(N + 1)
    R = reference.sample(t)
    R[:, 2] = np.unwrap(R[:, 2])
    n = vehicle.n_wheels
    wx, wy = vehicle.wheel_x, vehicle.wheel_y
    m, Iz, rw = vehicle.mass, vehicle.yaw_inertia, vehicle.wheel_radius
    FN = m * G_ACCEL / n
    lo, la = vehicle.tire_longitudinal, vehicle.tire_lateral
    lim = vehicle.limits
    kt = vehicle.steer_loss_kt
    v_eps = V_EPS_DEFAULT  # the plant's regularisation of |v_wx| (plant.tire.slip_ratio)

    def rhs(X, U):
        """(dX/dt, P_s, P_alpha) of the plant (eq. 4-21) at state X, commands U."""
        phi, vx, vy, r = X[2], X[3], X[4], X[5]
        c, s = ca.cos(phi), ca.sin(phi)
        ub, vb = c * vx + s * vy, -s * vx + c * vy
        fbx = fby = mz = 0
        ps = pa = 0
        for i in range(n):
            d = X[6 + i]
            om = U[i]
            vxb, vyb = ub - r * wy[i], vb + r * wx[i]
            cd, sd = ca.cos(d), ca.sin(d)
            vwx, vwy = cd * vxb + sd * vyb, -sd * vxb + cd * vyb
            den = ca.sqrt(vwx * vwx + v_eps * v_eps)
            sl = (om * rw - vwx) / den
            al = -ca.atan(vwy / den)
            Fx = _mf(sl, lo.B, lo.C, lo.mu * FN, lo.E, ca)
            Fy = _mf(al, la.B, la.C, la.mu * FN, la.E, ca)
            ps += Fx * (om * rw - vwx)
            pa += -Fy * vwy
            bx, by = cd * Fx - sd * Fy, sd * Fx + cd * Fy
            fbx += bx
            fby += by
            mz += wx[i] * by - wy[i] * bx
        dX = ca.vertcat(vx, vy, r, (c * fbx - s * fby) / m, (s * fbx + c * fby) / m, mz / Iz,
                        U[n:2 * n] - U[2 * n:3 * n])
        return dX, ps, pa

    Xs = ca.SX.sym("X", 6 + n)
    Us = ca.SX.sym("U", 3 * n)
    dX, ps, pa = rhs(Xs, Us)
    f = ca.Function("f", [Xs, Us], [dX, ps, pa])

    opti = ca.Opti()
    X = opti.variable(6 + n, N + 1)
    U = opti.variable(3 * n, N)
    J_s = J_a = J_t = 0
    for k in range(N):
        d0, ps0, pa0 = f(X[:, k], U[:, k])
        d1, ps1, pa1 = f(X[:, k + 1], U[:, k])
        opti.subject_to(X[:, k + 1] == X[:, k] + 0.5 * h * (d0 + d1))
        J_s += 0.5 * h * (ps0 + ps1)
        J_a += 0.5 * h * (pa0 + pa1)
        J_t += h * kt * FN * ca.sum1(U[n:3 * n, k])
    opti.subject_to(opti.bounded(0.0, ca.vec(U[:n, :]), lim.omega_w_max))
    opti.subject_to(opti.bounded(0.0, ca.vec(U[n:2 * n, :]), lim.omega_s_max))
    opti.subject_to(opti.bounded(0.0, ca.vec(U[2 * n:, :]), -lim.omega_s_min))
    opti.subject_to(opti.bounded(lim.delta_min, ca.vec(X[6:, :]), lim.delta_max))
    for k in range(N + 1):
        opti.subject_to((X[0, k] - R[k, 0]) ** 2 + (X[1, k] - R[k, 1]) ** 2 <= tol * tol)
        if tol_phi is not None:
            opti.subject_to(opti.bounded(R[k, 2] - tol_phi, X[2, k], R[k, 2] + tol_phi))
    opti.minimize(J_s + J_a + J_t)
    # the reference's motion, every wheel along its velocity: the start of the search, and
    # with ``fixed_ends`` the state at the window's ends (heading and velocities the
    # reference's, each wheel along its velocity); free ends are the floor's problem
    phi, r = R[:, 2], R[:, 5]
    c, s = np.cos(phi), np.sin(phi)
    ub, vb = c * R[:, 3] + s * R[:, 4], -s * R[:, 3] + c * R[:, 4]
    vwx = ub[:, None] - r[:, None] * wy[None, :]
    vwy = vb[:, None] + r[:, None] * wx[None, :]
    theta = np.unwrap(np.arctan2(vwy, vwx), axis=0)
    if fixed_start and not fixed_ends:  # the run's start: heading, velocities the reference's
        opti.subject_to(X[2:6, 0] == R[0, 2:6])
    if fixed_ends:
        for k in (0, N):
            opti.subject_to(X[2:6, k] == R[k, 2:6])
            opti.subject_to(X[6:, k] == theta[k])
    opti.set_initial(X[:6, :], R[:, :6].T)
    opti.set_initial(X[6:, :], theta.T)
    opti.set_initial(U[:n, :], (np.hypot(vwx, vwy)[:-1] / rw).T)
    rate = np.diff(theta, axis=0) / h
    opti.set_initial(U[n:2 * n, :], np.maximum(rate, 0.0).T)
    opti.set_initial(U[2 * n:, :], np.maximum(-rate, 0.0).T)
    opti.solver("ipopt", {"print_time": False},
                {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": 1e-8,
                 "acceptable_tol": 1e-6})
    t_start = time.process_time()
    sol = opti.solve()
    Ws, Wa, Wt = (float(sol.value(v)) for v in (J_s, J_a, J_t))
    return {"W_s": Ws, "W_alpha": Wa, "W_t": Wt, "W_tw": Ws + Wa + Wt, "t0": t0, "t1": t1,
            "tol_m": tol, "tol_phi_rad": tol_phi, "dt": h, "nodes": N + 1,
            "status": opti.stats()["return_status"], "cpu_s": time.process_time() - t_start}


def run_wear(log_csv: str, t0: float, t1: float) -> dict:
    """A run's wear over ``[t0, t1]`` from its ``msagv run --log`` (cumulative columns)."""
    d = np.genfromtxt(log_csv, delimiter=",", names=True)
    out = {}
    for k in ("W_s", "W_alpha", "W_t"):
        out[k] = float(np.interp(t1, d["t"], d[k]) - np.interp(t0, d["t"], d[k]))
    out["W_tw"] = out["W_s"] + out["W_alpha"] + out["W_t"]
    return out


def sweep_scenarios():
    """The transient scenarios of the sweep: ``[(name, vehicle, reference, t0, t1)]``, 2-8
    axles (``plant.n_axle_vehicle`` at the default vehicle's load per wheel, and the example
    vehicles), lane changes, tight turns, S-curves and random paths at 8-25 km/h; each
    window is its path's first 15 s at most (the transients start within it)."""
    from msagv.controller.paths import lane_change, random_path, tight_turn
    from msagv.experiments.scenario import Scenario
    from msagv.plant import default_vehicle, n_axle_vehicle

    base = default_vehicle()
    out = []

    def add(name, veh, ref):
        out.append((name, veh, ref, float(ref.t[0]), float(min(ref.t[0] + 15.0, ref.t[-1]))))

    for n, kmh in ((2, 20.0), (3, 15.0), (4, 25.0), (6, 10.0), (8, 15.0)):
        v = n_axle_vehicle(n, base=base)
        add(f"lane change {n}-axle {kmh:g} km/h", v, lane_change(v, kmh))
    for n, kmh in ((2, 10.0), (3, 20.0), (4, 15.0), (6, 8.0), (8, 10.0)):
        v = n_axle_vehicle(n, base=base)
        add(f"tight turn {n}-axle {kmh:g} km/h", v, tight_turn(v, kmh))
    for n, kmh, seed in ((2, 25.0, 1), (3, 15.0, 2), (4, 20.0, 3), (6, 12.0, 4), (8, 10.0, 5)):
        v = n_axle_vehicle(n, base=base)
        add(f"random path {seed} {n}-axle {kmh:g} km/h", v, random_path(v, kmh, seed))
    root = Path(__file__).resolve().parents[2] / "scenarios"
    for toml, veh_file in (("s-curve-4axle.toml", None), ("s-curve-4axle.toml", "agv-8axle.toml"),
                           ("lane-change-3axle.toml", None),
                           ("lane-change-3axle.toml", "agv-6axle.toml"),
                           ("tight-turn-6axle.toml", None)):
        sc = Scenario.from_file(root / toml)
        if veh_file is not None:
            sc = Scenario.from_dict(dict(sc.to_dict(), vehicle=str(root / "vehicles" / veh_file)))
        veh = sc.actual_vehicle(sc.resolve_vehicle())
        ref, _ = sc.reference()
        add(f"{toml.removesuffix('.toml')} ({veh.n_axles}-axle)", veh, ref)
    return out


def sweep(dt: float = 0.05, tol: float = 0.01, tol_deg: float | None = 2.0,
          only: int | None = None, file=sys.stdout) -> list[dict]:
    """The floor (:func:`controller.floors.wear_floors`) against this module's bound on
    every :func:`sweep_scenarios` window, the same problem (position within ``tol``,
    heading within ``tol_deg``, the start the reference's heading and velocities, the end
    free); prints a Markdown table row per scenario."""
    from msagv.controller.floors import wear_floors

    rows = []
    print("| scenario | axles | window [s] | floor W_tw [J] | bound W_tw [J] | floor / bound "
          "| floor CPU [s] | bound CPU [s] |", file=file)
    print("|---|---:|---|---:|---:|---:|---:|---:|", file=file, flush=True)
    for j, (name, veh, ref, t0, t1) in enumerate(sweep_scenarios()):
        if only is not None and j >= only:
            break
        fl = wear_floors(ref, veh, t0, t1, dt=dt, tol=tol, tol_phi_deg=tol_deg)
        b = lower_bound(ref, veh, t0, t1, tol=tol, dt=dt, fixed_start=True,
                        tol_phi=None if tol_deg is None else np.radians(tol_deg))
        row = {"scenario": name, "axles": veh.n_axles, "t0": t0, "t1": t1, "floor": fl.W_tw,
               "bound": b["W_tw"], "ratio": fl.W_tw / b["W_tw"], "floor_cpu_s": fl.cpu_s,
               "bound_cpu_s": b["cpu_s"], "bound_status": b["status"]}
        rows.append(row)
        print(f"| {name} | {veh.n_axles} | {t0:.1f}-{t1:.1f} | {fl.W_tw:.2f} | {b['W_tw']:.2f} "
              f"| {row['ratio']:.5f} | {fl.cpu_s:.1f} | {b['cpu_s']:.1f} |", file=file, flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    from msagv.controller.floors import wear_floors
    from msagv.experiments.scenario import Scenario

    ap = argparse.ArgumentParser(prog="python -m msagv.benchmarks.floor_bound",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", nargs="?", help="a scenario TOML (docs/SCENARIOS.md)")
    ap.add_argument("t0", type=float, nargs="?")
    ap.add_argument("t1", type=float, nargs="?")
    ap.add_argument("--tol-cm", type=float, default=1.0, help="position tolerance [cm]")
    ap.add_argument("--tol-deg", type=float, default=2.0,
                    help="heading tolerance [deg] (default 2, the floor's; 0: free)")
    ap.add_argument("--dt", type=float, default=0.05, help="collocation step [s]")
    ap.add_argument("--fixed-start", action="store_true",
                    help="the bound's heading and velocities at t0 the reference's "
                         "(as the floor's)")
    ap.add_argument("--fixed-ends", action="store_true",
                    help="the bound's heading, velocities and wheel angles at the window's ends "
                         "the reference's (default: free, the floor's problem)")
    ap.add_argument("--log", help="a msagv run --log CSV of the same scenario: its wear")
    ap.add_argument("--sweep", action="store_true",
                    help="the floor against the bound on the transient scenarios (a table)")
    ap.add_argument("--only", type=int, help="with --sweep: the first ONLY scenarios")
    a = ap.parse_args(argv)
    if a.sweep:
        sweep(a.dt, a.tol_cm / 100.0, a.tol_deg or None, a.only)
        return 0
    if a.scenario is None or a.t1 is None:
        ap.error("need SCENARIO T0 T1, or --sweep")
    sc = Scenario.from_file(a.scenario)
    veh = sc.actual_vehicle(sc.resolve_vehicle())
    ref, _ = sc.reference()
    tol_phi = None if not a.tol_deg else np.radians(a.tol_deg)
    out = {"scenario": a.scenario,
           "bound": lower_bound(ref, veh, a.t0, a.t1, a.tol_cm / 100.0, a.dt, tol_phi=tol_phi,
                                fixed_ends=a.fixed_ends, fixed_start=a.fixed_start),
           "floor": wear_floors(ref, veh, a.t0, a.t1, dt=a.dt, tol=a.tol_cm / 100.0,
                                tol_phi_deg=a.tol_deg or None).as_dict()}
    if a.log:
        out["run"] = run_wear(a.log, a.t0, a.t1)
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
