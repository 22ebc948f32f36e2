"""The benchmark suite behind ``msagv bench``: every benchmark, as percentiles and ratios.

Sections (each is also its own module, runnable with ``python -m benchmarks.<name>``):

* ``plant``: real-time factor of the stepping plant (Dormand-Prince, rtol 1e-8, T = 0.01 s)
  for 2 / 4 / 6 axles (:mod:`benchmarks.plant_bench`);
* ``rollout``: predicted wheel-steps per second of the batch rollout, the SIMD prediction
  (one thread and all cores) and the same kernels on the math library, against a
  single-thread C implementation of the same equations, per axle count (2 / 4 / 6 / 8)
  (:mod:`benchmarks.rollout_bench`);
* ``controller``: SA-MPC solve time p50 / p99 / max in the closed loop, 2 / 4 / 6 / 8 axles
  (:mod:`benchmarks.controller_bench`);
* ``optimality``: the annealer's cost over IPOPT's converged cost on states sampled from
  closed-loop runs of Cases 1 and 2, 2 / 4 / 6 / 8 axles (200 states for 2, 40 for the
  others) (:mod:`benchmarks.optimality_bench`; needs CasADi);
* ``nmpc``: acados SQP-RTI (the real-time gradient NMPC) beside the annealer on the same
  sampled states (solve times, both answers by the exact cost) and in the closed loop on
  Case 1 at 15 and 35 km/h (W_tw, tracking), 2 / 4 / 6 / 8 axles
  (:mod:`benchmarks.nmpc_bench`; needs acados);
* ``transport``: Zenoh state-to-command round trip without a solve, at 100 Hz, between
  two processes (:mod:`benchmarks.transport_bench`);
* ``fmu``: the plant FMU stepped by fmpy against the native plant, per step
  (:mod:`benchmarks.fmu_bench`).

Timing is never asserted anywhere: the machines are shared and noisy. Each section prints
what it measured and the machine's core count; ``--json`` prints one object with a key per
section. ``--quick`` shortens every section (for a smoke test, not for figures).
"""

from __future__ import annotations

import os
import platform
import sys
import time

SECTIONS = ("plant", "rollout", "controller", "optimality", "nmpc", "transport", "fmu")


def _machine() -> dict:
    from .rollout_bench import _cpu_name

    try:
        load = os.getloadavg()
    except OSError:
        load = None
    return {"cores": os.cpu_count(), "cpu": _cpu_name(), "python": platform.python_version(),
            "machine": platform.machine(), "loadavg_at_start": load,
            "date": time.strftime("%Y-%m-%dT%H:%M:%S")}


def run_section(name: str, quick: bool) -> dict:
    if name == "plant":
        from .plant_bench import bench_plant

        r = bench_plant(seconds=2.0 if quick else 20.0, repeats=1 if quick else 5)
        out = {n: a["rtf"]["p50"] for n, a in r["axles"].items()}
        return {"rtf": out, "detail": r}
    if name == "rollout":
        from .rollout_bench import bench_rollout

        return bench_rollout(batch=32, repeats=100 if quick else 2000)
    if name == "controller":
        from .controller_bench import bench_controller

        r = bench_controller(axles=(2, 4, 6, 8), seconds=0.5 if quick else 5.0,
                             repeats=1 if quick else 3)
        return {n: {"solve_ms": a["solve_ms"], "detail": a} for n, a in r["axles"].items()} | \
            {"settings": r["settings"]}
    if name == "optimality":
        try:
            import casadi  # noqa: F401
        except ImportError:
            return {"skipped": "CasADi is not installed (pip install 'msagv[ipopt]')"}
        from .optimality_bench import bench_optimality

        r = bench_optimality(8 if quick else 200, axles=(2, 4, 6, 8),
                             states_other=4 if quick else 40)
        r.pop("rows", None)
        for a in r["axles"].values():
            a.pop("rows", None)
        return r
    if name == "nmpc":
        from msagv.controller.interface import ControllerError

        try:
            from msagv.controller.acados_rti import require_acados

            require_acados()
        except ControllerError as e:
            return {"skipped": str(e)}
        from .nmpc_bench import bench_nmpc

        r = bench_nmpc(axles=(2,) if quick else (2, 4, 6, 8), n_states=4 if quick else 40,
                       seconds=0.5 if quick else None)
        for a in r["axles"].values():
            a.pop("rows", None)
        return r
    if name == "transport":
        from .transport_bench import bench_transport

        return bench_transport(seconds=1.0 if quick else 10.0)
    if name == "fmu":
        from .fmu_bench import bench_fmu

        return bench_fmu(seconds=1.0 if quick else 10.0, repeats=1 if quick else 3)
    raise ValueError(f"unknown section '{name}'")


def _summary(name: str, r: dict) -> str:
    if "skipped" in r:
        return f"{name:<11} skipped: {r['skipped']}"
    if name == "plant":
        return f"{name:<11} real-time factor (p50 step) " + ", ".join(
            f"{n} axles {v:,.0f}" for n, v in r["rtf"].items())
    if name == "controller":
        parts = [f"{n} axles p50 {a['solve_ms']['p50']:.2f} p99 {a['solve_ms']['p99']:.2f} "
                 f"max {a['solve_ms']['max']:.2f} ms" for n, a in r.items() if n.isdigit()]
        return f"{name:<11} solve " + "; ".join(parts)
    if name == "optimality":
        return f"{name:<11} annealer / IPOPT cost " + "; ".join(
            f"{n} axles p50 {a['ratio_p50']:.4f} p90 {a['ratio_p90']:.4f} ({a['states']} states, "
            f"annealer p99 {a['sa_ms']['p99']:.2f} ms, IPOPT p50 {a['ipopt_ms']['p50']:.0f} ms)"
            for n, a in r.get("axles", {"2": r}).items())
    if name == "nmpc":
        parts = []
        for n, a in r.get("axles", {}).items():
            cl = a["closed_loop"]
            loop = ", ".join(f"{k} W_tw {v['W_tw']:.0f} J e_lat {v['e_lat_rms_cm']:.2f} cm"
                             for k, v in cl.items())
            parts.append(f"{n} axles: solve p50/p99 acados {a['acados_ms']['p50']:.2f}/"
                         f"{a['acados_ms']['p99']:.2f} ms, annealer {a['sa_ms']['p50']:.2f}/"
                         f"{a['sa_ms']['p99']:.2f} ms; cost acados/annealer p50 "
                         f"{a['ratio_acados_sa']['p50']:.4f} (acados lower at "
                         f"{a['acados_lower']}, annealer at {a['sa_lower']} of {a['states']}); "
                         f"{loop}")
        return f"{name:<11} " + "\n            ".join(parts)
    if name == "transport":
        return (f"{name:<11} round trip p50 {r['p50_ms']:.3f} p99 {r['p99_ms']:.3f} max "
                f"{r['max_ms']:.3f} ms, lost {r['lost']} of {r['sent']}")
    if name == "fmu":
        return (f"{name:<11} FMU/native per step (p50) {r['ratio_fmpy_native_p50']:.2f}x "
                f"(+{r['overhead_fmpy_p50_us']:.0f} us)")
    if name == "rollout":
        lines = []
        for n, a in r.get("axles", {}).items():
            ns = a["impls"].get("numba_simd") or {}
            c = a["impls"].get("c_strict")
            thr = ns.get("wheel_steps_per_s")
            txt = f"{n} axles SIMD {thr / 1e6:.1f} M wheel-steps/s" if thr else f"{n} axles"
            if c and thr:
                txt += (f", C strict {c['wheel_steps_per_s'] / 1e6:.1f} M (SIMD/C "
                        f"{thr / c['wheel_steps_per_s']:.2f}x)")
            lines.append(txt)
        return f"{name:<11} " + "; ".join(lines)
    return name


def run(sections: list[str], quick: bool = False, echo=print) -> dict:
    """Run ``sections`` (all by default); ``echo(line)`` gets each section's one-line
    summary as it finishes. Returns one object with a key per section and the machine."""
    bad = [s for s in sections if s not in SECTIONS]
    if bad:
        raise ValueError(f"unknown section(s) {', '.join(bad)} (known: {', '.join(SECTIONS)})")
    sections = list(sections) or list(SECTIONS)
    result = {"machine": _machine()}
    print(f"msagv bench: {result['machine']['cores']} cores ({result['machine']['cpu']}), "
          f"load {result['machine']['loadavg_at_start']}", file=sys.stderr)
    for name in sections:
        t0 = time.perf_counter()
        print(f"msagv bench: {name} ...", file=sys.stderr, flush=True)
        r = run_section(name, quick)
        r["wall_s"] = time.perf_counter() - t0
        result[name] = r
        echo(_summary(name, r))
    return result
