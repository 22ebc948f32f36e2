"""Where a solve's time goes, per axle count: the annealing, the polish's Jacobian, its steps.

States are sampled from closed-loop runs of the default annealer
(:func:`benchmarks.optimality_bench.sample_states`, Case 1 at 15, 25 and 35 km/h and
Case 2: :data:`benchmarks.optimality_bench.CASE_RUNS`, their first 6 s), each solved by
the default controller (``MPC.step``) with a timer around each compiled part of the
annealer (:class:`controller.sa_kernel.CompiledAnnealer`): the annealing (``solve``), the
polish's residuals at its start, its Jacobian by forward differences with the Hessian
(``_gn_jacobian``, once per solve plus each refresh) and its Gauss-Newton steps with the
refreshes inside them (``_gn_run``); with the steps and refreshes taken. Then the
polish's linear algebra alone on random data of the same size (D decision variables,
M residuals): one damped step (Cholesky and the two triangular solves), the same step
through the residuals' side (``lowrank_step``, Woodbury; the polish takes it when D > 2 M),
the Gauss-Newton Hessian, Broyden's update. And the differences alone at each state's
warm start (``CompiledAnnealer.differences``, CPU time, median over the states and
``repeats`` passes, the two alternating): each perturbed rollout started at its variable's
block's first step from the nominal rollout (the polish's), and from ``x0`` (every step:
the same Jacobian to the bit). Percentiles over ``repeats`` passes over the states (the first
pass, which loads the kernels, is not counted). Each part is timed twice: its wall time
(``*_ms``) and the CPU time of this thread (``*_cpu_ms``, ``time.thread_time``): on a
shared machine the wall time of a long call grows with every preemption (at load 10 on
2 cores a 2 ms call took several times its CPU time), its CPU time far less.

``--variants`` instead solves the same states with other splits of the polish's tile
(:data:`VARIANTS`: fewer damping factors, more step lengths; no refresh of the Jacobian)
and reports each one's cost over the default's per state and its solve time: what fewer
factorisations or differences per solve would cost in optimality.

Run ``python -m msagv.benchmarks.polish_bench [--axles 2,4,6,8] [--vehicle FILE] [--states 12]
[--variants]``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from . import BENCH_METHOD

PARTS = ("anneal", "start", "jacobian", "steps")
# name: (damping factors, step lengths, refreshes) of the polish (sa_kernel.GN_MUS,
# GN_ALPHAS, GN_REFRESH); each fills the same tile of GN_CANDIDATES candidates
VARIANTS = {"default": ((1e-2, 0.1, 1.0, 10.0), (1.0, 0.3), 1),
            "no refresh": ((1e-2, 0.1, 1.0, 10.0), (1.0, 0.3), 0),
            "2 factors x 4 lengths": ((1e-2, 1.0), (1.0, 0.6, 0.3, 0.1), 1),
            "2 x 4, no refresh": ((1e-2, 1.0), (1.0, 0.6, 0.3, 0.1), 0),
            "1 factor x 8 lengths": ((0.03,), (1.0, 0.7, 0.5, 0.35, 0.25, 0.15, 0.1, 0.05), 1)}


def _time(f, *a, repeats: int = 200) -> float:
    """Median wall time of ``f(*a)`` [us] (after one call)."""
    f(*a)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        f(*a)
        ts.append(time.perf_counter() - t)
    return 1e6 * float(np.median(ts))


def linear_algebra(D: int, M: int, seed: int = 0) -> dict:
    """The polish's linear algebra at size (D, M) on random data [us per call]."""
    from msagv.controller import sa_kernel as sk

    rng = np.random.default_rng(seed)
    JrT = rng.normal(size=(M, D))
    A = np.diag(rng.random(D) + 0.1)
    H, U, dz, g = np.empty((D, D)), np.empty((D, D)), np.empty(D), rng.normal(size=D)
    sk.gauss_newton_hessian(JrT, A, H)
    step = 1e-3 * rng.normal(size=D)
    JT, WT = np.ascontiguousarray(JrT.T), np.empty((D, M))
    return {"damped_step_us": _time(sk.damped_step, H, g, 0.1, U, dz),
            "lowrank_step_us": _time(sk.lowrank_step, H, JT, A, max(D // 3, 1), g, 0.1, WT, dz),
            "hessian_us": _time(sk.gauss_newton_hessian, JrT, A, H),
            "broyden_us": _time(sk.broyden_update, JrT.copy(), np.zeros(D), H.copy(), step,
                                rng.normal(size=M), 0.0)}


def bench_polish(vehicle, n_states: int = 12, repeats: int = 3) -> dict:
    """The parts of the default solve on ``n_states`` states of ``vehicle`` (module
    docstring)."""
    from msagv.controller import MPCSettings
    from msagv.controller.sa_kernel import CompiledAnnealer

    from .optimality_bench import (CASE_RUNS, CASE_SECONDS, make_solver, prime, references,
                                   sample_states)

    s = MPCSettings(method=BENCH_METHOD)
    samples = sample_states(n_states, s, seconds=CASE_SECONDS, vehicle=vehicle, runs=CASE_RUNS)
    refs = references(vehicle, CASE_RUNS)
    m = make_solver(s, vehicle=vehicle)
    m.warmup()
    k = m.solver.kernel
    assert isinstance(k, CompiledAnnealer)
    spent: dict[str, float] = {}

    def timed(name, f):
        def g(*a, **kw):
            t, c = time.perf_counter(), time.thread_time()
            try:
                return f(*a, **kw)
            finally:
                spent[name] = spent.get(name, 0.0) + time.perf_counter() - t
                spent[name + "_cpu"] = spent.get(name + "_cpu", 0.0) + time.thread_time() - c
        return g

    k.solve = timed("anneal", k.solve)
    k._gn_start = timed("start", k._gn_start)
    k._gn_jacobian = timed("jacobian", k._gn_jacobian)
    k._gn_run = timed("steps", k._gn_run)
    rows = []
    for rep in range(repeats + 1):
        for i, smp in enumerate(samples):
            spent.clear()
            prime(m, smp["z"], seed=1000 + i)
            cpu = time.thread_time()
            c = m.step(smp["state"], refs[smp["run"]])
            cpu = time.thread_time() - cpu
            if rep:
                rows.append({"solve_ms": c.solve_ms, "solve_cpu_ms": 1e3 * cpu,
                             **{p: 1e3 * spent.get(p, 0.0) for p in PARTS},
                             **{p + "_cpu": 1e3 * spent.get(p + "_cpu", 0.0) for p in PARTS},
                             "polish_steps": float(k._gn_state[1]),
                             "refreshes": float(k._gn_state[3])})
    D, M = m.model.dim, 6 * s.N_p
    out = {"vehicle": vehicle.name, "axles": vehicle.n_axles, "D": D, "M": M,
           "states": len(samples), "solves": len(rows)}
    for key in ("solve_ms", "solve_cpu_ms") + PARTS + tuple(p + "_cpu" for p in PARTS):
        v = np.array([r[key] for r in rows])
        out[key if key.endswith("_ms") else key + "_ms"] = {
            "p50": float(np.median(v)), "mean": float(v.mean()), "p99": float(np.percentile(v, 99))}
    out["polish_steps_mean"] = float(np.mean([r["polish_steps"] for r in rows]))
    out["refreshes_mean"] = float(np.mean([r["refreshes"] for r in rows]))
    out["linear_algebra"] = linear_algebra(D, M)
    out["differences_cpu_us"] = differences(m, samples, refs, repeats)
    return out


def differences(m, samples, refs, repeats: int) -> dict:
    """The polish's differences alone (module docstring) at each sample's warm start:
    median CPU time [us] started from the nominal rollout and from ``x0``."""
    from .optimality_bench import prime

    k = m.solver.kernel
    lo, hi = m.horizon.lower, m.horizon.upper
    probs = []
    for i, smp in enumerate(samples):
        prime(m, smp["z"], seed=1000 + i)
        x0, R, _, warm = m.horizon_problem(smp["state"], refs[smp["run"]])
        probs.append((x0, R, np.minimum(np.maximum(warm, lo), hi)))
    ts: dict[bool, list] = {True: [], False: []}
    for _ in range(repeats + 1):
        for p in probs:
            for nominal in (True, False):
                c = time.thread_time()
                k.differences(*p, from_nominal=nominal)
                ts[nominal].append(time.thread_time() - c)
    n = len(probs)  # (the first pass loads the kernels: not counted)
    return {"from_nominal": 1e6 * float(np.median(ts[True][n:])),
            "from_x0": 1e6 * float(np.median(ts[False][n:]))}


def bench_variants(vehicle, n_states: int = 12, repeats: int = 2) -> dict:
    """Each of :data:`VARIANTS` on the same states (module docstring): solve time p50 and
    its cost over the default's (both lifted by the optimality bench's cost floor)."""
    from msagv.controller import MPCSettings
    from msagv.controller import sa_kernel as sk

    from .optimality_bench import (CASE_RUNS, CASE_SECONDS, make_solver, prime, ratio,
                                   references, sample_states)

    s = MPCSettings(method=BENCH_METHOD)
    samples = sample_states(n_states, s, seconds=CASE_SECONDS, vehicle=vehicle, runs=CASE_RUNS)
    refs = references(vehicle, CASE_RUNS)
    m = make_solver(s, vehicle=vehicle)
    m.warmup()
    saved = sk.GN_MUS, sk.GN_ALPHAS, sk.GN_REFRESH
    costs: dict[str, list] = {}
    times: dict[str, list] = {}
    try:
        for _ in range(repeats):
            for name, (mus, alphas, refresh) in VARIANTS.items():
                assert len(mus) * len(alphas) == sk.GN_CANDIDATES
                sk.GN_MUS, sk.GN_ALPHAS = np.array(mus), np.array(alphas)
                sk.GN_REFRESH = refresh
                cs = []
                for i, smp in enumerate(samples):
                    prime(m, smp["z"], seed=1000 + i)
                    c = m.step(smp["state"], refs[smp["run"]])
                    cs.append(c.cost)
                    times.setdefault(name, []).append(c.solve_ms)
                costs[name] = cs  # (deterministic: the same every pass)
    finally:
        sk.GN_MUS, sk.GN_ALPHAS, sk.GN_REFRESH = saved
    out = {"vehicle": vehicle.name, "axles": vehicle.n_axles, "states": len(samples)}
    for name in VARIANTS:
        r = np.array([ratio(a, b) for a, b in zip(costs[name], costs["default"])])
        out[name] = {"solve_ms_p50": float(np.median(times[name])),
                     "cost_over_default": {"p50": float(np.median(r)),
                                           "p90": float(np.percentile(r, 90)),
                                           "max": float(r.max()), "min": float(r.min())}}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m msagv.benchmarks.polish_bench",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--axles", default="2,4,6,8", help="comma-separated axle counts ('': none)")
    ap.add_argument("--vehicle", action="append", default=[], metavar="FILE",
                    help="a vehicle file measured after the axle counts (repeatable)")
    ap.add_argument("--states", type=int, default=12, help="sampled states per vehicle")
    ap.add_argument("--repeats", type=int, default=3, help="timed passes over the states")
    ap.add_argument("--variants", action="store_true",
                    help="the polish's variants against the default instead (VARIANTS)")
    a = ap.parse_args(argv)
    from msagv.plant import VehicleError, default_vehicle, load_vehicle, n_axle_vehicle

    try:
        vs = [default_vehicle() if n == 2 else n_axle_vehicle(n)
              for n in (int(x) for x in a.axles.split(",") if x.strip())]
        vs += [load_vehicle(f) for f in a.vehicle]
    except (ValueError, OSError, VehicleError) as e:
        ap.error(str(e).splitlines()[0] if str(e) else repr(e))
    if not vs or a.states < 1 or a.repeats < 1:
        ap.error("nothing to measure: give --axles or --vehicle, --states and --repeats >= 1")
    f = bench_variants if a.variants else bench_polish
    print(json.dumps({v.name: f(v, a.states, a.repeats) for v in vs}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
