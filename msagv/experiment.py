"""``msagv experiment``: the command line of :mod:`experiments.studies`."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from experiments import studies


def _floats(text: str | None, name: str):
    if text is None:
        return None
    try:
        vals = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ValueError(f"{name}: expected comma-separated numbers, got '{text}'") from None
    if not vals or any(not (math.isfinite(v) and v >= 0) for v in vals):
        raise ValueError(f"{name}: expected finite numbers >= 0, got '{text}'")
    return vals


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="msagv experiment", description=studies.__doc__.splitlines()[0])
    ap.add_argument("experiment", choices=studies.EXPERIMENTS)
    ap.add_argument("--out", metavar="DIR", help="output directory (default runs/<experiment>)")
    ap.add_argument("--jobs", type=int, metavar="N", help="parallel runs (default: all cores)")
    ap.add_argument("--json", action="store_true", help="print the table (pareto: the fronts) as JSON")
    ap.add_argument("--duration", type=float, metavar="S",
                    help="shorten every run to S seconds of vehicle time (default: the whole reference)")
    ap.add_argument("--speeds", metavar="KMH,...", help="subset/override of the speeds")
    ap.add_argument("--masses", metavar="T,...", help="case3: loads in tonnes (default 8,12,16,20)")
    ap.add_argument("--methods", metavar="NAME,...",
                    help=f"subset of {','.join(studies.METHODS)} (pareto: of the baselines)")
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in paper-2axle)")
    ap.add_argument("--force", action="store_true", help="redo runs even if finished")
    ap.add_argument("--two-scales", metavar="S,...", help="pareto: factors on TWO's L")
    ap.add_argument("--smooth-scales", metavar="S,...", help="pareto: factors on NTWO's R_dw, R_dd")
    ap.add_argument("--ridge-scales", metavar="S,...",
                    help="pareto: factors of NTWO's R_ow, R_od; ridge: the levels (default 0,0.1,1)")
    ap.add_argument("--progress", action=argparse.BooleanOptionalAction, default=True,
                    help="progress bar over finished runs on stderr (default on)")
    a = ap.parse_args(argv)
    try:
        if a.jobs is not None and a.jobs < 1:
            raise ValueError("--jobs must be >= 1")
        methods = [m.strip() for m in a.methods.split(",") if m.strip()] if a.methods else None
        summary = studies.run_experiment(
            a.experiment, a.out, jobs=a.jobs, force=a.force, progress=a.progress,
            duration=a.duration, speeds=_floats(a.speeds, "--speeds"),
            masses_t=_floats(a.masses, "--masses"), methods=methods, vehicle=a.vehicle,
            two_scales=_floats(a.two_scales, "--two-scales"),
            smooth_scales=_floats(a.smooth_scales, "--smooth-scales"),
            ridge_scales=_floats(a.ridge_scales, "--ridge-scales"))
    except (ValueError, FileNotFoundError) as e:
        print(f"msagv experiment: {e}", file=sys.stderr)
        return 2
    out = Path(summary["out"])
    r = summary["runs"]
    print(f"msagv experiment {a.experiment}: {r['runs']} runs ({r['executed']} run now, "
          f"{r['reused']} reused, {r['failed']} failed) in {r['total_wall_s']:.1f} s; "
          f"outputs in {out}", file=sys.stderr)
    if a.json:
        print(json.dumps(summary))
    elif a.experiment == "pareto":
        print((out / "pareto.md").read_text())
    elif a.experiment == "ridge":
        print((out / "ridge.md").read_text())
    else:
        print((out / "table.md").read_text())
    return 0
