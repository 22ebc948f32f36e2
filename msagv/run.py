"""``msagv run`` and ``msagv fmu simulate``: the in-process closed loop.

The controller at 100 Hz on the plant in this process: the built-in stepping plant, or an
FMU stepped by fmpy (``msagv fmu simulate FILE.fmu``: the same loop and options with
:class:`fmu_build.host.FmuPlant` as the plant). The scenario comes from the options
(:func:`msagv.args.scenario_from_args`), is assembled by
:meth:`experiments.scenario.Scenario.build` and run by :func:`controller.loop.closed_loop`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .args import add_case_args, add_fmu_args, add_mpc_args, scenario_from_args


def build_parser(prog: str = "msagv run", fmu: bool = False) -> argparse.ArgumentParser:
    desc = ("In-process closed loop: the controller at 100 Hz on the stepping plant."
            if not fmu else
            "Closed loop with fmpy stepping an FMU (set inputs, doStep 0.01 s, get outputs) "
            "and the MPC in the same process; the same metrics as msagv run.")
    ap = argparse.ArgumentParser(prog=prog, description=desc)
    if fmu:
        add_fmu_args(ap, positional=True)
    add_case_args(ap)
    add_mpc_args(ap)
    ap.add_argument("--json", action="store_true", help="print the metrics as one JSON object")
    ap.add_argument("--plot", metavar="FILE", help="write a PNG (path, errors, wear power)")
    ap.add_argument("--log", metavar="FILE", help="write the per-step log as CSV")
    ap.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                    help="progress bar (default: on a terminal for runs > 10 s)")
    return ap


def main(argv: list[str], prog: str = "msagv run", fmu: bool = False) -> int:
    """``msagv run`` (``fmu=False``) and ``msagv fmu simulate`` (``fmu=True``)."""
    a = build_parser(prog, fmu).parse_args(argv)
    from controller.loop import closed_loop
    from controller.metrics import format_table

    from .errors import USAGE_ERRORS

    built = None
    try:
        scenario = scenario_from_args(a)
        built = scenario.build()
        log = closed_loop(built.plant, built.controller, built.reference, built.duration,
                          period=scenario.period, progress=a.progress)
    except USAGE_ERRORS as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    finally:
        if built is not None:
            built.close()
    m = log.metrics()
    ref, settings, vehicle = built.reference, built.controller.settings, built.vehicle
    if a.log:
        log.to_csv(a.log)
    if a.plot:
        from experiments.plots import plot_run

        plot_run(log, ref, a.plot, title=f"{ref.name} {settings.method.upper()} "
                                         f"({settings.model}"
                                         f"{', ipopt' if scenario.solver == 'ipopt' else ''})")
    if a.json:
        print(json.dumps(m))
    else:
        where = f"FMU {Path(a.fmu).name}" if fmu else f"{vehicle.name} {vehicle.mass:g} kg"
        how = f"{settings.model}, ipopt" if scenario.solver == "ipopt" else settings.model
        print(format_table(m, f"{ref.name}, {settings.method.upper()} ({how}), {where}"))
        if a.plot:
            print(f"  plot       {Path(a.plot)}")
    return 0
