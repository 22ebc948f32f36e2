"""``msagv experiment``: the command line of :mod:`experiments.cases`."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from msagv.experiments import cases, families

from .args import OptionError, add_common_args, check_output, fail, note, warn

MIN_MASS_KG = 100.0  # --masses below this is taken for the old tonnes and refused


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


def _masses_kg(a) -> tuple | None:
    """``--masses`` in kg (as ``--mass`` everywhere); ``--masses-t`` the deprecated tonnes."""
    kg = _floats(a.masses, "--masses")
    if kg is not None and any(m < MIN_MASS_KG for m in kg):
        raise OptionError(f"--masses: in kg, got '{a.masses}' (below {MIN_MASS_KG:g} kg: "
                          f"tonnes? 8 t is 8000)")
    if a.masses_t is not None:
        if kg is not None:
            raise OptionError("give --masses (kg) or the deprecated --masses-t, not both")
        warn("msagv experiment", ["--masses-t (tonnes) is deprecated: use --masses in kg, "
                                  "as --mass"])
        kg = tuple(1000.0 * m for m in _floats(a.masses_t, "--masses-t"))
    return kg


PROG = "msagv experiment"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description="The paper's experiments (Section 4: "
                                 "case1, case2, case3; pareto, ridge) and the study (does a "
                                 "wear term save wear at equal tracking error?).")
    ap.add_argument("experiment", choices=cases.EXPERIMENTS + ("study", "mismatch"),
                    help="the paper's Cases 1-3, the Pareto and ridge experiments, the "
                         "study (experiments.study: every family on many scenarios, wear at "
                         "equal tracking error with confidence intervals), or mismatch (the "
                         "study's question on plants whose tires the controller does not "
                         "know: model wrong, identified, adapted, true; "
                         "experiments.mismatch)")
    ap.add_argument("-o", "--out", metavar="DIR",
                    help="output directory (default runs/<experiment>)")
    ap.add_argument("--jobs", type=int, metavar="N", help="parallel runs (default: all cores)")
    ap.add_argument("--json", action="store_true",
                    help="print the summary as JSON (rows: one result per run, with its "
                         "scenario and metrics; pareto: the fronts)")
    ap.add_argument("--json-out", metavar="FILE", help="also write the JSON summary to FILE")
    ap.add_argument("--duration", type=float, metavar="S",
                    help="shorten every run to S seconds of vehicle time (default: the whole reference)")
    ap.add_argument("--speeds", metavar="KMH,...",
                    help="case1-3, pareto, ridge: subset/override of the speeds; study: the "
                         "speeds of your vehicle's random path (with --vehicle, default 20)")
    ap.add_argument("--masses", metavar="KG,...",
                    help="case3: gross vehicle weights in kg (default 8000,12000,16000,20000)")
    ap.add_argument("--masses-t", metavar="T,...", help=argparse.SUPPRESS)  # deprecated
    ap.add_argument("--methods", metavar="NAME,...",
                    help=f"case1-3: a subset of the case tables' rows (default: all): "
                         f"{families.methods_help()} (experiments.families); pareto: of "
                         f"{', '.join(cases.PARETO_BASELINES)}")
    ap.add_argument("--vehicle", metavar="FILE",
                    help="vehicle TOML (default: built-in paper-2axle); study: the vehicle of "
                         "your own scenario (a random path at --speeds, or --trajectory); "
                         "mismatch: the controller's vehicle (the file's tires), which the "
                         "factor plants, the random paths and the manoeuvre are made for")
    ap.add_argument("--force", action="store_true", help="redo runs even if finished")
    ap.add_argument("--two-scales", metavar="S,...", help="pareto: factors on TWO's L")
    ap.add_argument("--smooth-scales", metavar="S,...", help="pareto: factors on NTWO's R_dw, R_dd")
    ap.add_argument("--ridge-scales", metavar="S,...",
                    help="pareto: factors of NTWO's R_ow, R_od; ridge: the levels (default 0,0.1,1)")
    ap.add_argument("--quick", action="store_true",
                    help="study: the reduced design, a smoke test (about a minute and a half "
                         "on 2 cores; the full design's times: docs/RESULTS.md); mismatch: 2 "
                         "plants (tires x0.8, x1.2), "
                         "2 paths, 1 seed, the quick levels")
    ap.add_argument("--trajectory", metavar="FILE",
                    help="study: add your own scenario on this t,x,y,phi CSV, run whole at "
                         "its own timing (with --vehicle: driven by that vehicle; the "
                         "design's scenarios keep the paper's), summarised on its own; "
                         "mismatch: the one path (driven whole) instead of --paths random ones")
    ap.add_argument("--classes", metavar="NAME,...",
                    help="study: run only these classes of the design (case1, case2, lane, "
                         "turn, random, fresh, load, 4-axle, robust; user: your own scenario)")
    ap.add_argument("--plants", metavar="NAME,...",
                    help="mismatch: the plants (default all: tires x0.7-x1.3, B or mu alone "
                         "x0.8/x1.2, combined-slip, load-transfer+lags), or vehicle files of "
                         "plants of your own (*.toml: its tires, mass, lags as they are)")
    ap.add_argument("--paths", type=int, metavar="N",
                    help="mismatch: random paths (default 10; --quick 2)")
    ap.add_argument("--seeds", type=int, metavar="N",
                    help="mismatch: annealer seeds per scenario (default 3; --quick 1)")
    ap.add_argument("--measurement-noise", metavar="V,R[,POS,PHI]",
                    help="mismatch and study: the controller measures the states with this "
                         "noise, as a real vehicle's odometry has (standard deviations of the "
                         "body's velocity along and across it [m/s], the yaw rate [rad/s], x "
                         "and y [m], the heading [rad]; seeded by the annealer's seed; the "
                         "mismatch's identified column's logged run measured so too; default "
                         "output runs/mismatch-noise, runs/study-noise), e.g. 0.01,0.002")
    ap.add_argument("--quick-levels", action="store_true",
                    help="mismatch: each family at its --quick levels (12 runs a scenario "
                         "instead of 25)")
    ap.add_argument("--scheduler", metavar="ADDRESS",
                    help="a Dask scheduler (tcp://HOST:8786) whose workers run the runs "
                         "(default: a local Dask cluster of --jobs processes)")
    ap.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                    help="progress bar over finished runs on stderr (default: on a terminal)")
    add_common_args(ap)
    return ap


def _run(a, progress: bool) -> dict:
    """Check the options, run the experiment, return its summary."""
    from msagv.experiments.study import default_out

    if a.jobs is not None and a.jobs < 1:
        raise OptionError("--jobs must be >= 1")
    noise = None
    if a.measurement_noise is not None:
        if a.experiment not in ("mismatch", "study"):
            raise OptionError("--measurement-noise applies to the mismatch experiment and "
                              "the study")
        from msagv.plant.sensors import MeasurementNoise

        try:
            m = MeasurementNoise.parse(a.measurement_noise)
        except ValueError as e:
            raise OptionError(f"--measurement-noise: {e}") from None
        noise = None if m is None else m.as_dict()  # (the experiment drops the seed)
    # the default output directory too: nothing runs before it is known to be writable
    a.out_dir = Path(a.out) if a.out else default_out(a.experiment, bool(a.quick), noise)
    check_output(a.out_dir, "--out", directory=True)
    check_output(a.json_out, "--json-out")
    methods = [m.strip() for m in a.methods.split(",") if m.strip()] if a.methods else None
    masses = _masses_kg(a)
    if a.experiment != "study" and a.classes is not None:
        raise OptionError("--classes applies to the study")
    if a.experiment != "mismatch":
        for name in ("plants", "paths", "seeds"):
            if getattr(a, name) is not None:
                raise OptionError(f"--{name.replace('_', '-')} applies to the mismatch "
                                  f"experiment")
        if a.quick_levels:
            raise OptionError("--quick-levels applies to the mismatch experiment")
    if a.experiment == "mismatch":
        from msagv.experiments.mismatch import parse_plants, run_mismatch

        for name in ("duration", "masses", "masses_t", "methods", "two_scales",
                     "smooth_scales", "ridge_scales", "speeds"):
            if getattr(a, name) is not None:
                raise OptionError(f"--{name.replace('_', '-')} does not apply to the mismatch "
                                  f"experiment (its design: --plants, --paths, --seeds, "
                                  f"--quick, --quick-levels, --vehicle, --trajectory, "
                                  f"--measurement-noise)")
        if a.paths is not None and a.paths < 2:
            raise OptionError(f"--paths: at least 2 (the interval resamples paths), got {a.paths}")
        if a.seeds is not None and a.seeds < 1:
            raise OptionError(f"--seeds: at least 1, got {a.seeds}")
        return run_mismatch(a.out, plants=parse_plants(a.plants) if a.plants else None,
                            n_paths=a.paths,
                            seeds=None if a.seeds is None else tuple(range(a.seeds)),
                            quick=a.quick, levels_quick=a.quick or a.quick_levels,
                            jobs=a.jobs, scheduler=a.scheduler, force=a.force,
                            progress=progress, vehicle=a.vehicle, trajectory=a.trajectory,
                            noise=noise)
    if a.experiment != "study" and (a.quick or a.trajectory):
        raise OptionError("--quick and --trajectory apply to the study")
    if a.experiment == "study":
        from msagv.experiments.study import run_study

        for name in ("duration", "masses", "masses_t", "methods", "two_scales",
                     "smooth_scales", "ridge_scales"):
            if getattr(a, name) is not None:
                raise OptionError(f"--{name.replace('_', '-')} applies to case1-3, pareto and "
                                  f"ridge, not to the study (its design is fixed; --vehicle, "
                                  f"--trajectory and --speeds add your own scenario)")
        classes = ([c.strip() for c in a.classes.split(",") if c.strip()]
                   if a.classes is not None else None)
        if classes is not None and not classes:
            raise OptionError("--classes: give at least one class")
        return run_study(a.out, quick=a.quick, jobs=a.jobs, scheduler=a.scheduler,
                         force=a.force, progress=progress, vehicle=a.vehicle,
                         trajectory=a.trajectory, speeds=_floats(a.speeds, "--speeds"),
                         classes=classes, noise=noise)
    return cases.run_experiment(
        a.experiment, a.out, jobs=a.jobs, force=a.force, progress=progress,
        duration=a.duration, speeds=_floats(a.speeds, "--speeds"),
        masses_t=None if masses is None else tuple(m / 1000.0 for m in masses),
        methods=methods, vehicle=a.vehicle, two_scales=_floats(a.two_scales, "--two-scales"),
        smooth_scales=_floats(a.smooth_scales, "--smooth-scales"),
        ridge_scales=_floats(a.ridge_scales, "--ridge-scales"), scheduler=a.scheduler)


def main(argv: list[str]) -> int:
    prog = PROG
    a = _parser().parse_args(argv)
    if a.verbose:
        import logging

        logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    progress = (sys.stderr.isatty() and not a.quiet) if a.progress is None else a.progress
    try:
        summary = _run(a, progress)
    except (ValueError, FileNotFoundError, RuntimeError) as e:
        return fail(prog, e, a)
    except KeyboardInterrupt:
        out = getattr(a, "out_dir", None) or Path(a.out or Path("runs") / a.experiment)
        done = len(list((out / "runs").glob("*.json"))) if (out / "runs").is_dir() else 0
        print(f"{prog}: interrupted; {done} finished runs are stored in {out / 'runs'} and "
              f"are reused when the same command is run again", file=sys.stderr)
        return 130
    out = Path(summary["out"])
    r = summary["runs"]
    warn(prog, summary.get("warnings", []))
    note(a, f"msagv experiment {a.experiment}: {r['runs']} runs ({r['executed']} run now, "
            f"{r['reused']} reused, {r['failed']} failed) in {r['total_wall_s']:.1f} s; "
            f"outputs in {out}")
    if a.json_out:
        Path(a.json_out).write_text(json.dumps(summary, indent=1) + "\n")
    if a.json:
        print(json.dumps(summary))
    elif a.experiment == "pareto":
        print((out / "pareto.md").read_text())
    elif a.experiment == "ridge":
        print((out / "ridge.md").read_text())
    elif a.experiment in ("study", "mismatch"):
        print((out / f"{a.experiment}.md").read_text())
    else:
        print((out / "table.md").read_text())
    return 0
