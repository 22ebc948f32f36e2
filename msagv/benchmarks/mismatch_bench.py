"""Tires the model does not know: tracking and wear of the MPC on a plant whose tires differ
from the controller's file, with and without the offset-free disturbance and the online
adaptation, against the same MPC given the plant's own tires.

    python -m msagv.benchmarks.mismatch_bench [--scales 0.8,1.2] [--paths curve:25,lane:15,random:20]
        [--method ntwo] [--solver sa] [--duration 15] [--set NAME=VALUE ...] [--json]

Per path and plant tire factor (B and mu of both Magic Formula curves times the factor, as
``Scenario.plant_tire_scale``), four controllers:

- ``wrong``: the file's tires, no offset-free disturbance (the MPC before issue 28);
- ``offset-free``: the file's tires, the disturbance on (the default of the tire models;
  the kinematic model's is off, so it is switched on here);
- ``adapted``: the file's tires adapted online (``--adapt``) and the disturbance on (not
  run for a model without tires, ``kinematic``: its cells say ``n/a``);
- ``true``: the plant's own tires (the model right), the default settings, on the same path
  (a random path is drawn for the file's vehicle in all four).

Prints the lateral RMS error [cm] and the tire wear W_tw [J] of each, and the ratio of each
lateral RMS to the true model's. docs/CONTROLLER.md quotes it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

VARIANTS = ("wrong", "offset-free", "adapted", "true")


def run_one(case: str, speed: float, scale: float, variant: str, method: str,
            duration: float, path_seed: int = 0, extra: dict | None = None,
            solver: str = "sa", noise: dict | None = None) -> dict:
    """One closed loop: the metrics and the controller's estimates. ``extra``: MPC
    settings every variant gets (``--set``); ``solver``: the horizon solver; ``noise``:
    the controller's measurement noise (``Scenario.measurement_noise``, the same draws in
    every variant)."""
    from msagv.controller.loop import closed_loop
    from msagv.experiments.scenario import Scenario

    settings = {**(extra or {}), "method": method}
    if variant == "wrong":
        settings["offset_free"] = False
    elif variant == "offset-free":  # (on: the kinematic model's default is off)
        settings["offset_free"] = True
    elif variant == "adapted":
        settings["adapt"] = True
    sc = Scenario(case=case, speed=speed, path_seed=path_seed, settings=settings,
                  plant_tire_scale=scale, solver=solver, measurement_noise=dict(noise or {}))
    b = sc.build()
    if variant == "true":
        # the controller given the plant's own tires, on the same path (a random path is
        # drawn for the scenario's vehicle: its tires set its curvature limit)
        b.controller = sc.make_controller(sc.actual_vehicle(b.vehicle), b.reference)
    try:
        log = closed_loop(b.plant, b.controller, b.reference, min(duration, b.duration),
                          period=sc.period, progress=False, outputs=False, measure=b.measure)
    finally:
        b.close()
    m = log.metrics()
    return {"case": case, "speed_kmh": speed, "path_seed": path_seed, "scale": scale,
            "variant": variant, "solver": solver, "e_lat_rms_cm": m["e_lat_rms_cm"], "e_y_cm": m["e_y_cm"],
            "W_tw": m["W_tw"], "disturbance": b.controller.disturbance(),
            "adapted": b.controller.adapted_tires()}


def _paths(text: str) -> list[tuple[str, float, int]]:
    out = []
    for item in text.split(","):
        name, _, kmh = item.partition(":")
        case, _, seed = name.partition("#")
        out.append((case.strip(), float(kmh), int(seed or 0)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m msagv.benchmarks.mismatch_bench",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--scales", default="0.8,1.2", help="plant tire factors (default 0.8,1.2)")
    ap.add_argument("--paths", default="curve:25,lane:15,random:20,random#1:20,random#2:20",
                    help="CASE[#PATH_SEED]:KMH,... (default: the Case 1 curve at 25, the lane "
                         "change at 15, three random paths at 20 km/h)")
    ap.add_argument("--method", default="ntwo", help="the MPC's wear term (default ntwo)")
    ap.add_argument("--solver", default="sa", help="the horizon solver: sa (default), ipopt, "
                                                   "acados")
    ap.add_argument("--duration", type=float, default=15.0, help="seconds per run (default 15)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="an MPCSettings field for every variant, e.g. --set "
                         "disturbance_tau=0.02 (the variants' own switches stay theirs)")
    ap.add_argument("--noise", metavar="V,R[,POS,PHI]",
                    help="measurement noise of the controller's state (m/s, rad/s, m, rad; "
                         "msagv run --measurement-noise), the same draws in every run")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    a = ap.parse_args(argv)
    from msagv.plant.sensors import MeasurementNoise

    try:
        noise = None if a.noise is None else MeasurementNoise.parse(a.noise)
    except ValueError as e:
        ap.error(f"--noise: {e}")
    noise = None if noise is None else noise.as_dict()
    from msagv.controller.interface import ControllerError
    from msagv.controller.models import ADAPTABLE, MPCSettings
    from msagv.controller.solvers import SOLVERS, check_supported

    try:
        extra = MPCSettings.parse_assignments(a.set)
        MPCSettings(**extra)  # a bad value is named now, before any run
    except (ValueError, TypeError) as e:
        ap.error(f"--set: {e}")
    if a.solver not in SOLVERS:
        ap.error(f"--solver: one of {', '.join(SOLVERS)}, got {a.solver!r}")
    try:
        check_supported(a.solver, MPCSettings(**extra))
    except ControllerError as e:
        ap.error(f"--solver {a.solver}: {e}")
    variants = [v for v in VARIANTS
                if v != "adapted" or MPCSettings(**extra).model in ADAPTABLE]
    own = sorted(set(extra) & {"method", "offset_free", "adapt"})
    if own:
        ap.error(f"--set {', '.join(own)}: the variants' own switches (use --method; the "
                 f"disturbance and the adaptation are what the columns compare)")
    from tqdm import tqdm

    scales = [float(s) for s in a.scales.split(",")]
    jobs = [(c, v, s, p, var) for c, v, p in _paths(a.paths) for s in scales for var in variants]
    rows = []
    t0 = time.time()
    for c, v, s, p, var in tqdm(jobs, file=sys.stderr, disable=a.json or not sys.stderr.isatty()):
        rows.append(run_one(c, v, s, var, a.method, a.duration, p, extra, a.solver, noise))
    if a.json:
        print(json.dumps({"rows": rows, "wall_s": time.time() - t0, "noise": noise},
                         indent=1))
        return 0
    print(f"lateral RMS [cm] (ratio to the true model) and W_tw [J]; {a.method}, solver "
          f"{a.solver}, {a.duration:g} s per run" + (f"; {' '.join(a.set)}" if a.set else "")
          + (f"; measurement noise {a.noise}" if noise else ""))
    print(f"{'path':<16}{'tires':>6}" + "".join(f"{v:>22}" for v in VARIANTS))
    for c, v, p in _paths(a.paths):
        for s in scales:
            sel = {r["variant"]: r for r in rows if (r["case"], r["speed_kmh"], r["path_seed"],
                                                     r["scale"]) == (c, v, p, s)}
            true = sel["true"]["e_lat_rms_cm"]
            cells = "".join(f"{sel[k]['e_lat_rms_cm']:7.3f} ({sel[k]['e_lat_rms_cm'] / true:4.2f}) "
                            f"{sel[k]['W_tw']:6.0f}" if k in sel else f"{'n/a':>22}"
                            for k in VARIANTS)
            name = f"{c}{'#' + str(p) if p else ''} {v:g}"
            print(f"{name:<16}{s:>6g}{cells}")
    print(f"({len(rows)} runs in {time.time() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
