"""Per-step cost of the plant FMU stepped by fmpy vs the native plant.

``bench_fmu(seconds, repeats)`` builds the FMU for the built-in vehicle (or uses
``fmu_path``), then times, step by step over ``seconds`` of simulated time at
T = 0.01 s with :func:`fmu_build.drive.varied_inputs`:

* ``native``: ``Plant.set_inputs``, ``Plant.do_step``, ``Plant.output_vector``;
* ``fmpy``: ``FMU2Slave.setReal`` (inputs), ``doStep``, ``getReal`` (every output);
* ``host``: :class:`fmu_build.host.FmuPlant` ``set_inputs``, ``do_step``,
  ``state_message`` (what the closed loop and the bridge call).

Each engine is warmed up (numba compilation excluded) and the step times of all repeats
are pooled. ``python -m msagv.benchmarks.fmu_bench [--seconds S] [--repeats R] [--fmu F]``
prints the result as JSON.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from msagv.plant.signals import CONTROL_PERIOD

WARMUP_STEPS = 20


def _stats(samples: list[float]) -> dict[str, float]:
    a = np.asarray(samples) * 1e6
    return {"p50_us": float(np.percentile(a, 50)), "p99_us": float(np.percentile(a, 99)),
            "mean_us": float(a.mean()), "steps": int(a.size)}


def _native(vehicle, U: np.ndarray, h: float) -> list[float]:
    from msagv.plant.stepping import Plant

    p = Plant(vehicle)
    nw = vehicle.n_wheels
    clock, out = time.perf_counter, []
    for k in range(len(U)):
        t0 = clock()
        p.set_inputs(U[k, :nw], U[k, nw:])
        p.do_step(p.t, h)
        p.output_vector()
        out.append(clock() - t0)
    return out[WARMUP_STEPS:]


def _fmpy(fmu_path: Path, U: np.ndarray, h: float) -> list[float]:
    from msagv.fmu_build.drive import run_fmpy

    timing: list[float] = []
    run_fmpy(fmu_path, U, h, timing=timing)
    return timing[WARMUP_STEPS:]


def _host(fmu_path: Path, U: np.ndarray, h: float) -> list[float]:
    from msagv.fmu_build.host import FmuPlant

    clock, out = time.perf_counter, []
    with FmuPlant(fmu_path) as p:
        nw = p.vehicle.n_wheels
        for k in range(len(U)):
            t0 = clock()
            p.set_inputs(U[k, :nw], U[k, nw:])
            p.do_step(p.t, h)
            p.state_message()
            out.append(clock() - t0)
    return out[WARMUP_STEPS:]


def bench_fmu(seconds: float = 10.0, repeats: int = 3, fmu_path: str | Path | None = None,
              h: float = CONTROL_PERIOD) -> dict:
    """Per-step wall time (p50/p99/mean in microseconds) of the FMU under fmpy and the
    native plant, and their ratios (FMU / native, by p50 and by mean)."""
    from msagv.fmu_build.build import build_fmu
    from msagv.fmu_build.drive import varied_inputs
    from msagv.plant.vehicle import default_vehicle

    vehicle = default_vehicle()
    tmp = None
    if fmu_path is None:
        tmp = Path(tempfile.mkdtemp(prefix="msagv-fmu-bench-"))
        fmu_path = build_fmu(tmp / "plant.fmu", vehicle)
    try:
        n = int(round(seconds / h)) + WARMUP_STEPS
        U = varied_inputs(vehicle.n_wheels, n, h, seed=0)
        res = {"native": [], "fmpy": [], "host": []}
        for _ in range(repeats):
            res["native"] += _native(vehicle, U, h)
            res["fmpy"] += _fmpy(Path(fmu_path), U, h)
            res["host"] += _host(Path(fmu_path), U, h)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    out = {k: _stats(v) for k, v in res.items()}
    nat = out["native"]
    out["ratio_fmpy_native_p50"] = out["fmpy"]["p50_us"] / nat["p50_us"]
    out["ratio_fmpy_native_mean"] = out["fmpy"]["mean_us"] / nat["mean_us"]
    out["ratio_host_native_p50"] = out["host"]["p50_us"] / nat["p50_us"]
    out["overhead_fmpy_p50_us"] = out["fmpy"]["p50_us"] - nat["p50_us"]
    out["config"] = {"seconds": seconds, "repeats": repeats, "h": h,
                     "vehicle": vehicle.name, "python": sys.version.split()[0]}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m msagv.benchmarks.fmu_bench", description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per repeat")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--fmu", help="an FMU built by msagv fmu build (default: build one)")
    a = ap.parse_args(argv)
    print(json.dumps(bench_fmu(a.seconds, a.repeats, a.fmu), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
