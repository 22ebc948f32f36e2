"""The real-time gradient NMPC (acados SQP-RTI) beside the annealer, per axle count.

Two measurements per axle count (2: the paper's vehicle; 4, 6, 8: its
``plant.n_axle_vehicle`` relatives), both solvers with their defaults:

* **Solves on the same states.** States sampled from closed-loop runs of the default
  annealer (:func:`benchmarks.optimality_bench.sample_states`: every scenario class of the
  study, :data:`benchmarks.optimality_bench.RUNS`), each with the annealer's previous
  solution, which defines the warm start and the smoothing term. At each state the same horizon problem is solved
  by the annealer (its fixed budget, a fresh random stream per state, its step factors from
  the ladder) and by acados SQP-RTI (one Gauss-Newton iteration and the line search), the
  two interleaved (the order alternates from state to state) so that both see the same
  machine. Both answers are scored by the exact cost (numba, true |.|): the ratio
  acados / annealer per state (< 1: acados found the lower cost; both costs lifted by
  :data:`benchmarks.optimality_bench.COST_FLOOR`), how many states each
  wins, and both solvers' solve-time percentiles (``MPC.step``'s wall time: everything a
  control period pays, state to command). Also acados with 3 SQP iterations in place of
  one, to tell how much of a gap is the single iteration's.
* **The closed loop.** The in-process loop of ``msagv run`` on the whole Case 1 curve at 15
  and 35 km/h per solver: ``W_tw``, the lateral error ``e_lat_rms_cm``, ``e_bar`` and the
  solve-time percentiles; the two solvers run one after the other per speed.

acados builds its solver once per configuration (cached, see controller/acados_rti.py); the
build time is reported when it happened here. Run
``python -m msagv.benchmarks.nmpc_bench [--axles 2,4,6,8] [--states 40] [--speeds 15,35]``
(also ``msagv bench nmpc``).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from msagv.plant.signals import CONTROL_PERIOD

from . import BENCH_METHOD

T = CONTROL_PERIOD


def _vehicle(n: int):
    from msagv.plant import default_vehicle, n_axle_vehicle

    return default_vehicle() if n == 2 else n_axle_vehicle(n)


def _pct(v) -> dict:
    v = np.asarray(v, float)
    return {"p50": float(np.median(v)), "p99": float(np.percentile(v, 99)),
            "max": float(v.max())}


def bench_states(n_axles: int, n_states: int, settings=None, sqp: int = 3) -> dict:
    """Both solvers on the same sampled states (see the module docstring); also acados with
    ``sqp`` SQP iterations in place of one (0: not), which tells how much of the RTI's gap
    to the annealer is the single iteration."""
    from msagv.controller import MPCSettings
    from msagv.controller.acados_rti import AcadosOptions

    from .optimality_bench import (RUNS, make_solver, prime, ratio, references, run_label,
                                   sample_states)

    s = settings or MPCSettings(method=BENCH_METHOD)
    vehicle = _vehicle(n_axles)
    samples = sample_states(n_states, s, vehicle=vehicle)
    refs = references(vehicle)
    m = make_solver(s, vehicle=vehicle)
    t0 = time.perf_counter()
    q = make_solver(s, solver="acados", vehicle=vehicle)
    setup_s = time.perf_counter() - t0
    built = q.solver.ocp.built
    w = (make_solver(s, solver="acados", vehicle=vehicle, options=AcadosOptions(iterations=sqp))
         if sqp > 1 else None)
    for c in (m, q, w):
        if c is not None:
            c.warmup()
    rows = []
    for i, smp in enumerate(samples):
        ref = refs[smp["run"]]

        def run_sa():
            prime(m, smp["z"], seed=1000 + i)
            return m.step(smp["state"], ref)

        def run_ac():
            prime(q, smp["z"])
            return q.step(smp["state"], ref)

        if i % 2:
            c_ac, c_sa = run_ac(), run_sa()
        else:
            c_sa, c_ac = run_sa(), run_ac()
        row = {"run": smp["run"], "cls": smp["cls"], "k": smp["k"], "J_sa": c_sa.cost,
               "J_acados": c_ac.cost, "sa_ms": c_sa.solve_ms,
               "acados_ms": c_ac.solve_ms, "acados_status": q.solver.last_status}
        if w is not None:
            prime(w, smp["z"])
            c = w.step(smp["state"], ref)
            row["J_sqp"], row["sqp_ms"] = c.cost, c.solve_ms
        rows.append(row)
    r = np.array([ratio(x["J_acados"], x["J_sa"]) for x in rows])  # (with the cost floor)
    tol = 1e-9
    return {"axles_n": n_axles, "states": len(rows),
            "sa_ms": _pct([x["sa_ms"] for x in rows]),
            "acados_ms": _pct([x["acados_ms"] for x in rows]),
            "ratio_acados_sa": {"p10": float(np.percentile(r, 10)), "p50": float(np.median(r)),
                                "p90": float(np.percentile(r, 90)), "min": float(r.min()),
                                "max": float(r.max())},
            "acados_lower": int(np.sum(r < 1 - tol)), "sa_lower": int(np.sum(r > 1 + tol)),
            "ties": int(np.sum(np.abs(r - 1) <= tol)),
            "acados_qp_failures": int(sum(x["acados_status"] not in (0, 2) for x in rows)),
            "sqp": ({"iterations": sqp, "ms": _pct([x["sqp_ms"] for x in rows]),
                     "ratio_sqp_sa_p50": float(np.median([ratio(x["J_sqp"], x["J_sa"])
                                                          for x in rows])),
                     "ratio_sqp_sa_p90": float(np.percentile([ratio(x["J_sqp"], x["J_sa"])
                                                              for x in rows], 90)),
                     "sqp_lower": int(sum(x["J_sqp"] < x["J_sa"] * (1 - tol) for x in rows)),
                     "sa_lower": int(sum(x["J_sa"] < x["J_sqp"] * (1 - tol) for x in rows))}
                    if w is not None else None),
            "acados_built_here": built, "acados_setup_s": setup_s,
            "runs": [run_label(r) for r in RUNS], "rows": rows}


def bench_closed_loop(n_axles: int, speeds=(15.0, 35.0), seconds: float | None = None,
                      solvers=("sa", "acados"), also: dict | None = None) -> dict:
    """The whole Case 1 curve (or ``seconds`` of it) per speed and solver: W_tw, tracking
    and solve times, as ``msagv run --json`` reports them; ``also``: settings fields of a
    second annealer run beside them (e.g. the former defaults), labelled ``sa[...]``."""
    from msagv.controller.loop import closed_loop
    from msagv.experiments.scenario import Scenario

    out = {}
    runs = [(s, {}, s) for s in solvers]
    if also:
        runs.append(("sa", dict(also), "sa[" + ",".join(f"{k}={v}" for k, v in also.items())
                     + "]"))
    for sp in speeds:
        for solver, settings, label in runs:
            sc = Scenario(vehicle=_vehicle(n_axles), case="curve", speed=float(sp),
                          solver=solver, period=T, duration=seconds, settings=settings)
            b = sc.build()
            log = closed_loop(b.plant, b.controller, b.reference, b.duration, period=T,
                              progress=False)
            m = log.metrics()
            out[f"{label} {sp:g} km/h"] = {
                "W_tw": m["W_tw"], "e_lat_rms_cm": m["e_lat_rms_cm"], "e_bar": m["e_bar"],
                "solve_ms": m["solve_ms"], "steps": m["steps"]}
    return out


def bench_nmpc(axles=(2, 4, 6, 8), n_states: int = 40, speeds=(15.0, 35.0),
               seconds: float | None = None, also: dict | None = None) -> dict:
    """Both measurements per axle count; ``seconds``: the closed loops' length (None: the
    whole path); ``also``: a second annealer in the closed loops (:func:`bench_closed_loop`)."""
    out = {"axles": {}, "settings": {"states": n_states, "speeds_kmh": list(speeds),
                                     "closed_loop_seconds": seconds}}
    for n in axles:
        t0 = time.perf_counter()
        r = bench_states(n, n_states)
        r["closed_loop"] = bench_closed_loop(n, speeds, seconds, also=also)
        r["wall_s"] = time.perf_counter() - t0
        out["axles"][str(n)] = r
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m msagv.benchmarks.nmpc_bench",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--axles", default="2,4,6,8", help="comma-separated axle counts")
    ap.add_argument("--states", type=int, default=40, help="sampled states per axle count")
    ap.add_argument("--speeds", default="15,35", help="closed-loop speeds [km/h], Case 1")
    ap.add_argument("--seconds", type=float, default=None,
                    help="closed-loop length [s] (default: the whole path)")
    ap.add_argument("--rows", action="store_true", help="include every state's costs")
    ap.add_argument("--also", default=None, metavar="NAME=VALUE,...",
                    help="a second annealer in the closed loops, these settings fields "
                         "changed, e.g. iterations=40,polish=0 (the former defaults)")
    a = ap.parse_args(argv)
    from .optimality_bench import also_option

    also = also_option(ap, a.also)
    res = bench_nmpc(tuple(int(x) for x in a.axles.split(",") if x.strip()), a.states,
                     tuple(float(x) for x in a.speeds.split(",") if x.strip()), a.seconds,
                     also=also)
    if not a.rows:
        for r in res["axles"].values():
            r.pop("rows", None)
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
