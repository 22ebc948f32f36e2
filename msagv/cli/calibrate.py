"""``msagv calibrate``: identify the vehicle's tires, actuator lags (and on request mass and
yaw inertia) from a recording, and write the tuned vehicle file; ``--maneuver``: the
excitation run to record for it. docs/CALIBRATE.md."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from .args import PLOT_SUFFIXES, add_common_args, check_distinct, check_output, fail, note, warn

PROG = "msagv calibrate"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=PROG,
        description="Identify the vehicle from a recording: fit the Magic Formula coefficients "
                    "the run excites, the actuator lags (and with --fit-body the mass and yaw "
                    "inertia) by least squares on the plant's multi-step prediction error, print "
                    "each with its standard error, say which the run did not identify (those "
                    "keep the base vehicle's value) and write the tuned vehicle file. "
                    "--maneuver: the excitation run to record.")
    ap.add_argument("recording", nargs="?", metavar="RECORDING",
                    help="an msagv recording of the plant (msagv plant --record FILE) or a "
                         "rosbag2 bag directory (odom, joint_states, the two command topics)")
    ap.add_argument("-o", "--out", metavar="FILE",
                    help="write the tuned vehicle file (TOML); with --maneuver the scenario "
                         "file (FILE.toml, its trajectory beside it as FILE.csv) or the "
                         "trajectory alone (FILE.csv)")
    ap.add_argument("--vehicle", metavar="FILE",
                    help="the base vehicle (default: the vehicle the recording names)")
    ap.add_argument("--maneuver", action="store_true",
                    help="print (or with -o write) the excitation manoeuvre for the vehicle")
    ap.add_argument("--fit-body", action="store_true",
                    help="also fit the mass and the yaw inertia")
    ap.add_argument("--run", type=int, default=-1,
                    help="which plant run of an msagv recording, 0 = first (default: the last)")
    ap.add_argument("--window", type=float, default=0.5, metavar="S",
                    help="length of each multi-step prediction window [s] (default 0.5)")
    ap.add_argument("--plot", metavar="FILE", help="a figure of measured against predicted")
    ap.add_argument("--json", action="store_true", help="print the result as one JSON object")
    ap.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                    help="progress bar on stderr (default: on a terminal)")
    add_common_args(ap)
    return ap


def main(argv: list[str]) -> int:
    from msagv.experiments import calibrate as C
    from msagv.plant.identify import IdentifyError, calibrate
    from msagv.plant.vehicle import VehicleError, load_vehicle, plausibility_warnings

    from .errors import USAGE_ERRORS

    a = _parser().parse_args(argv)
    if a.maneuver:
        return _maneuver(a)
    try:
        if a.recording is None:
            raise ValueError("give a RECORDING (or --maneuver)")
        if not (a.window > 0 and math.isfinite(a.window)):
            raise ValueError(f"--window must be > 0 s, got {a.window:g}")
        check_output(a.out, "-o", suffixes=(".toml",))
        check_output(a.plot, "--plot", suffixes=PLOT_SUFFIXES)
        check_distinct(("the recording", a.recording), ("-o", a.out), ("--plot", a.plot))
        data, recorded, notes = C.read_run(a.recording, a.run)
        base = C.base_vehicle(a.vehicle, recorded)
        warn(PROG, plausibility_warnings(base) + notes)
        C.check_data(data, base)
        window = max(2, int(round(a.window / data.period)))
    except USAGE_ERRORS as e:
        return fail(PROG, e, a)
    progress = a.progress if a.progress is not None else (sys.stderr.isatty() and not a.quiet)
    name = Path(a.out).stem if a.out else f"{base.name}-calibrated"
    try:
        cal = calibrate(data, base, fit_body=a.fit_body, window=window, progress=progress,
                        name=name)
    except (IdentifyError, VehicleError) as e:
        return fail(PROG, e, a)
    if a.out:
        comment = (f"{cal.vehicle.name}: {base.name} calibrated by msagv calibrate from "
                   f"{Path(a.recording).name}\n({cal.windows} windows, {cal.seconds:.0f} s; "
                   f"parameters not identified keep {base.name}'s values)")
        Path(a.out).write_text(C.vehicle_toml(cal.vehicle, comment))
        load_vehicle(a.out)  # what was written loads back
    if a.plot:
        C.plot_calibration(cal, a.plot, title=f"{Path(a.recording).name}: measured and predicted")
    if a.json:
        print(json.dumps(dict(cal.to_dict(), recording=str(a.recording), out=a.out)))
    else:
        _print(cal, a)
    return 0


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def _print(cal, a) -> None:
    print(f"{cal.base.name} calibrated from {a.recording}: {cal.windows} windows of "
          f"{cal.seconds / max(cal.windows, 1):.2f} s ({cal.seconds:.0f} s), "
          f"{cal.evaluations} simulations")
    print(f"  excitation: longitudinal {cal.excitation['longitudinal']:.0%}, lateral "
          f"{cal.excitation['lateral']:.0%} of the base peak friction (measured acceleration); "
          f"tires at up to {cal.reach['longitudinal']:.0%} / {cal.reach['lateral']:.0%} of "
          f"their peak (model)")
    print(f"  {'parameter':<16} {'base':>10} {'fitted':>10} {'std err':>10}")
    for e in cal.estimates.values():
        if e.identified:
            print(f"  {e.name:<16} {_fmt(e.base):>10} {_fmt(e.value):>10} {_fmt(e.se):>10}  "
                  f"{e.unit}")
        else:
            print(f"  {e.name:<16} {_fmt(e.base):>10} {'-':>10} {'-':>10}  not identified: "
                  f"{e.why}; keeps {_fmt(e.base)}")
    for ax in cal.cornering_stiffness():
        print(f"  axle {ax['axle']}: load {ax['load_N']:.0f} N per wheel, cornering stiffness "
              f"{ax['cornering_stiffness_N_per_rad']:.4g} N/rad, slip stiffness "
              f"{ax['slip_stiffness_N']:.4g} N")
    print("  rms error  " + ", ".join(
        f"{k} {cal.rms_before[k]:.3g} -> {cal.rms_after[k]:.3g}" for k in cal.rms_after)
        + "  (base -> tuned)")
    if a.out:
        print(f"  vehicle    {a.out}")
    if a.plot:
        print(f"  plot       {a.plot}")


def _maneuver(a) -> int:
    from msagv.experiments import calibrate as C
    from msagv.plant.vehicle import load_vehicle

    from .errors import USAGE_ERRORS

    try:
        if a.recording is not None:
            raise ValueError("--maneuver takes no RECORDING")
        check_output(a.out, "-o", suffixes=(".toml", ".csv"))
        v = load_vehicle(a.vehicle)
    except USAGE_ERRORS as e:
        return fail(PROG, e, a)
    m = C.maneuver(v)
    csv = C.maneuver_csv(m)
    if a.out is None:
        sys.stdout.write(csv)
        note(a, f"{PROG}: the manoeuvre's trajectory ({m['t'][-1]:.0f} s) for msagv run/plant "
                f"--trajectory; -o FILE.toml writes a scenario file with it")
        return 0
    out = Path(a.out)
    if out.suffix.lower() == ".csv":
        out.write_text(csv)
        note(a, f"wrote {out} ({m['t'][-1]:.0f} s)")
        return 0
    traj = out.with_suffix(".csv")
    traj.write_text(csv)
    vpath = None
    if a.vehicle:
        vp = Path(a.vehicle).absolute()
        try:
            vpath = str(vp.relative_to(out.absolute().parent))
        except ValueError:
            vpath = str(vp)
    out.write_text(C.maneuver_scenario(m, vpath, traj.name))
    note(a, f"wrote {out} and {traj} ({m['t'][-1]:.0f} s)")
    return 0
