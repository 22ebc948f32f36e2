"""Plant stepping speed: wall time per 10 ms co-simulation step, and the real-time factor.

Each run drives a fresh :class:`plant.Plant` (Dormand-Prince, rtol 1e-8) for ``seconds``
of simulated time at T = 0.01 s, on a realistic manoeuvre: the vehicle starts at 10 m/s,
the wheel speeds follow 10 m/s with per-wheel variation (so the tires slip a little), and
the wheels steer sinusoidally, front and rear axles opposite (a slalom of changing
curvature). One timed step is what a co-simulation master does per tick:
``set_inputs`` + ``do_step``. The numba kernels are compiled (or loaded from cache) and
warmed up before anything is timed.

Run ``python benchmarks/plant_bench.py [--axles 2,4,6] [--seconds 20] [--repeats 5]``;
it prints the result of :func:`bench_plant` as JSON.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import platform
import time

import numpy as np

from msagv.plant import Plant, default_vehicle, n_axle_vehicle
from msagv.plant.signals import CONTROL_PERIOD

T = CONTROL_PERIOD  # s, control period (DESIGN.md)
RTOL = 1e-8
SPEED = 10.0  # m/s


def _vehicle(n: int):
    return default_vehicle() if n == 2 else n_axle_vehicle(n)


def manoeuvre(vehicle, steps: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Commands ``(omega_w, omega_s)``, each (steps, 2n), for the benchmark run.

    Wheel speeds: 10 m/s / r_w, +/-10 % over a 6 s cycle, times 1 +/- 1 % per wheel and
    step. Steering: delta = +/-0.15 sin(2 pi t / 4) rad, sign by axle position (front
    positive, rear negative), commanded as its rate plus noise, within the rate limits.
    """
    rng = np.random.default_rng(seed)
    nw = vehicle.n_wheels
    t = np.arange(steps) * T
    v = SPEED * (1.0 + 0.1 * np.sin(2 * math.pi * t / 6.0))
    omega_w = (v[:, None] / vehicle.wheel_radius) * (1.0 + 0.01 * rng.standard_normal((steps, nw)))
    x = vehicle.wheel_x
    span = np.ptp(x)
    sign = x / (span / 2.0) if span > 0 else np.ones(nw)
    rate = 0.15 * (2 * math.pi / 4.0) * np.cos(2 * math.pi * t / 4.0)
    omega_s = rate[:, None] * sign[None, :] + 0.02 * rng.standard_normal((steps, nw))
    lim = vehicle.limits
    return np.maximum(omega_w, 0.0), np.clip(omega_s, lim.omega_s_min, lim.omega_s_max)


def _one_run(vehicle, omega_w, omega_s) -> tuple[np.ndarray, int]:
    """Per-step wall times [s] of one run, and the integrator's accepted substeps."""
    plant = Plant(vehicle, initial={"vx": SPEED}, rtol=RTOL)
    dt = np.empty(omega_w.shape[0])
    clock = time.perf_counter
    for k in range(omega_w.shape[0]):
        t0 = clock()
        plant.set_inputs(omega_w[k], omega_s[k])
        plant.do_step(plant.t, T)
        dt[k] = clock() - t0
    return dt, plant.steps_accepted


def _spread(values) -> dict:
    """Percentiles of a metric over the repeats (min = p0, max = p100)."""
    a = np.asarray(values, dtype=float)
    return {"min": float(a.min()), "p50": float(np.median(a)), "max": float(a.max())}


def bench_plant(axles=(2, 4, 6), seconds: float = 20.0, repeats: int = 5) -> dict:
    """Time the stepping plant for each axle count.

    Returns ``{"settings": ..., "axles": {n: result}}`` where each result holds, over
    ``repeats`` runs of ``seconds`` simulated seconds: ``step_us_p50`` and ``step_us_p99``
    (per-step wall time percentiles of a run, microseconds), ``rtf`` (real-time factor
    0.01 s / that run's p50 step time), each as ``{min, p50, max}`` over the repeats, and
    ``substeps_per_step`` (accepted Dormand-Prince steps per 10 ms step).
    """
    steps = int(round(seconds / T))
    out = {"settings": {"T_s": T, "rtol": RTOL, "atol": 1e-9, "seconds": seconds,
                        "steps": steps, "repeats": repeats, "speed_mps": SPEED,
                        "timed": "set_inputs + do_step",
                        "python": platform.python_version(), "machine": platform.machine()},
           "axles": {}}
    for n in axles:
        vehicle = _vehicle(n)
        omega_w, omega_s = manoeuvre(vehicle, steps)
        _one_run(vehicle, omega_w[:200], omega_s[:200])  # warm-up: compile / load kernels
        p50, p99, rtf, sub = [], [], [], []
        for _ in range(repeats):
            gc.collect()
            dt, accepted = _one_run(vehicle, omega_w, omega_s)
            q50, q99 = np.percentile(dt, [50, 99])
            p50.append(q50 * 1e6)
            p99.append(q99 * 1e6)
            rtf.append(T / q50)
            sub.append(accepted / steps)
        out["axles"][str(n)] = {
            "n_wheels": vehicle.n_wheels,
            "step_us_p50": _spread(p50),
            "step_us_p99": _spread(p99),
            "rtf": _spread(rtf),
            "substeps_per_step": float(np.mean(sub)),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="plant_bench", description=__doc__.splitlines()[0])
    ap.add_argument("--axles", default="2,4,6", help="comma-separated axle counts")
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per run")
    ap.add_argument("--repeats", type=int, default=5)
    a = ap.parse_args(argv)
    axles = tuple(int(s) for s in a.axles.split(",") if s.strip())
    print(json.dumps(bench_plant(axles, a.seconds, a.repeats), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
