"""Controller solve time: the SA-MPC's wall time per solve in a closed loop, per axle count.

Each run is the in-process closed loop of ``msagv run`` (``controller.loop.closed_loop``:
the MPC warmed up first, then one solve per 10 ms control period on the stepping plant)
on the Case 1 curve at 25 km/h, with the default settings (fixed iteration budget, serial
rollouts) unless told otherwise. The 2-axle vehicle is the paper's; 4 and 6 axles are its
``plant.n_axle_vehicle`` relatives (same load per wheel, same tires and limits).

Reported per axle count: solve time p50 / p99 / max over every solve of every repeat, the
spread of the per-repeat p50 and p99 over the repeats, the time per solve divided by the
2-axle time (so "no worse than linear" reads as ratio <= n / 2), and the tracking error of
the runs (a check that the timed controller is the working one).

A vehicle file (``--vehicle FILE``, repeatable; e.g. ``scenarios/vehicles/agv-16axle.toml``)
is measured after the axle counts, labelled by its name.

Run ``python -m msagv.benchmarks.controller_bench [--axles 2,4,6] [--vehicle FILE] [--seconds 5]
[--repeats 3]``.
"""

from __future__ import annotations

import argparse
import gc
import json
import os

import numpy as np

from msagv.plant.signals import CONTROL_PERIOD

from . import BENCH_METHOD

T = CONTROL_PERIOD  # s, control period
SPEED_KMH = 25.0


def _vehicle(n):
    """An axle count (2: the paper's vehicle, others its relatives) or a Vehicle as is."""
    from msagv.plant import default_vehicle, n_axle_vehicle

    if not isinstance(n, int):
        return n
    return default_vehicle() if n == 2 else n_axle_vehicle(n)


def run_once(n_axles, seconds: float, settings=None) -> dict:
    """One closed-loop run; returns its solve times [ms] and e_bar."""
    from dataclasses import asdict

    from msagv.controller.loop import closed_loop
    from msagv.experiments.scenario import Scenario

    sc = Scenario(vehicle=_vehicle(n_axles), case="curve", speed=SPEED_KMH, duration=seconds,
                  settings={} if settings is None else asdict(settings), period=T)
    b = sc.build()
    gc.collect()
    log = closed_loop(b.plant, b.controller, b.reference, seconds, period=T, progress=False)
    return {"solve_ms": list(log.solve_ms), "e_bar": log.metrics()["e_bar"]}


def bench_controller(axles=(2, 4, 6, 8), seconds: float = 5.0, repeats: int = 3,
                     settings=None) -> dict:
    """Solve-time percentiles per axle count (see the module docstring); an item of
    ``axles`` may be a :class:`plant.Vehicle` (labelled by its name)."""
    from msagv.controller import MPCSettings
    from msagv.controller.metrics import percentiles

    from .plant_bench import _spread

    s = settings or MPCSettings(method=BENCH_METHOD)
    out = {"settings": {"case": "curve", "speed_kmh": SPEED_KMH, "seconds": seconds,
                        "repeats": repeats, "chains": s.chains, "iterations": s.iterations,
                        "N_p": s.N_p, "dt": s.dt, "blocks": list(s.blocks),
                        "threads": s.threads, "deadline_ms": s.deadline_ms,
                        "cores": os.cpu_count()},
           "axles": {}}
    base = None
    for n in axles:
        run_once(n, 0.05, s)  # compile / load the kernels for this axle count
        allv, p50s, p99s, ebar = [], [], [], []
        for _ in range(repeats):
            r = run_once(n, seconds, s)
            allv += r["solve_ms"]
            p50s.append(float(np.percentile(r["solve_ms"], 50)))
            p99s.append(float(np.percentile(r["solve_ms"], 99)))
            ebar.append(r["e_bar"])
        v = _vehicle(n)
        res = {"n_wheels": v.n_wheels, "solve_ms": percentiles(allv), "p50_over_repeats": _spread(p50s),
               "p99_over_repeats": _spread(p99s), "solves": len(allv),
               "within_period": float(np.mean(np.asarray(allv) <= T * 1000.0)),
               "e_bar": _spread(ebar)}
        if base is None:
            base = (v.n_axles, res["solve_ms"]["p50"])
        res["p50_ratio_to_%d_axles" % base[0]] = res["solve_ms"]["p50"] / base[1]
        res["linear_ratio"] = v.n_axles / base[0]
        out["axles"][str(n) if isinstance(n, int) else v.name] = res
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m msagv.benchmarks.controller_bench",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--axles", default="2,4,6,8", help="comma-separated axle counts ('': none)")
    ap.add_argument("--vehicle", action="append", default=[], metavar="FILE",
                    help="a vehicle file measured after the axle counts (repeatable)")
    ap.add_argument("--seconds", type=float, default=5.0, help="vehicle seconds per run")
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)
    from msagv.plant import VehicleError, load_vehicle

    try:
        axles = tuple(int(x) for x in a.axles.split(",") if x.strip())
        axles += tuple(load_vehicle(f) for f in a.vehicle)
    except (ValueError, OSError, VehicleError) as e:
        ap.error(str(e).splitlines()[0] if str(e) else repr(e))
    if not axles:
        ap.error("nothing to measure: give --axles or --vehicle")
    print(json.dumps(bench_controller(axles, a.seconds, a.repeats), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
