"""``msagv run`` and ``msagv fmu simulate``: the in-process closed loop.

The controller at 100 Hz on the plant in this process: the built-in stepping plant, or an
FMU stepped by fmpy (``msagv fmu simulate FILE.fmu``: the same loop and options with
:class:`fmu_build.host.FmuPlant` as the plant). The scenario comes from the options
(:func:`msagv.cli.args.scenario_from_args`), is assembled by
:meth:`experiments.scenario.Scenario.build` and run by :func:`controller.loop.closed_loop`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .args import (PLOT_SUFFIXES, OptionError, add_case_args, add_common_args, add_fmu_args,
                   add_measurement_noise_arg, add_plant_vehicle_arg,
                   add_mpc_args, add_tire_price_arg, check_distinct, check_output,
                   check_tire_price, fail, scenario_from_args, tire_price, warn)
from .foxglove_cli import add_foxglove_args, check_foxglove_args
from .view import add_view_args, announce, check_view_args, serve_until_stopped, view_kwargs

EXIT_INTERRUPTED = 130  # Ctrl-C: the shell's 128 + SIGINT
EXIT_FAILED = 1  # the run itself failed (a diverging plant, an FMU that stopped)


def build_parser(prog: str = "msagv run", fmu: bool = False) -> argparse.ArgumentParser:
    desc = ("In-process closed loop: the controller at 100 Hz on the stepping plant."
            if not fmu else
            "Closed loop with fmpy stepping an FMU (set inputs, doStep 0.01 s, get outputs) "
            "and the MPC in the same process; the same metrics as msagv run.")
    ap = argparse.ArgumentParser(prog=prog, description=desc)
    if fmu:
        add_fmu_args(ap, positional=True)
    else:
        ap.add_argument("scenario_file", nargs="?", metavar="SCENARIO.toml",
                        help="a scenario file (docs/SCENARIOS.md), as --scenario; the options "
                             "below override its values")
    add_case_args(ap)
    add_plant_vehicle_arg(ap)
    add_measurement_noise_arg(ap)
    add_mpc_args(ap)
    ap.add_argument("--json", action="store_true",
                    help="print the result as one JSON object (docs/SCENARIOS.md#results)")
    ap.add_argument("--json-out", metavar="FILE", help="also write the JSON result to FILE")
    ap.add_argument("--plot", metavar="FILE", help="write a figure (path, errors, wear power; "
                                                   ".png, .pdf, .svg)")
    ap.add_argument("--log", metavar="FILE", help="write the per-step log as CSV (columns named "
                                                  "as the signals)")
    ap.add_argument("--wear-plot", metavar="FILE",
                    help="write a figure of the wear per wheel and per axle (.png, .pdf, .svg)")
    add_tire_price_arg(ap)
    ap.add_argument("--floor", action=argparse.BooleanOptionalAction, default=True,
                    help="after the run, its wear floor: the least wear of any motion within "
                         "1 cm and 2 deg of the path over the window it drove (IPOPT, "
                         "docs/WEAR.md section 4), and a warning if the run wears less "
                         "(default on; --no-floor skips it: on a long or many-axle run it "
                         "can take longer than the run)")
    add_view_args(ap)  # --view, --view-save, --view-port: the run in Rerun
    add_foxglove_args(ap)  # --foxglove: the run in Foxglove, paced in real time
    ap.add_argument("--foxglove-wait", type=float, default=0.0, metavar="S",
                    help="with --foxglove: wait up to S seconds for a Foxglove client to "
                         "subscribe before the run starts (default 0: start at once)")
    ap.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                    help="progress bar on stderr (default: on a terminal for runs > 10 s)")
    add_common_args(ap)
    return ap


def main(argv: list[str], prog: str = "msagv run", fmu: bool = False) -> int:
    """``msagv run`` (``fmu=False``) and ``msagv fmu simulate`` (``fmu=True``).

    Exit codes: 0 done (warnings on stderr and in the JSON), 1 the run failed, 2 bad
    options or input (nothing run), 130 interrupted (the result so far is printed)."""
    from .errors import USAGE_ERRORS

    a = build_parser(prog, fmu).parse_args(argv)
    built = None
    try:
        scenario, want_view = _checked_options(a)
        built = scenario.build()
        check_tire_price(a, built.vehicle)
    except USAGE_ERRORS as e:
        if built is not None:
            built.close()
        return fail(prog, e, a)
    except KeyboardInterrupt:
        if built is not None:
            built.close()
        print(f"{prog}: interrupted before the run started", file=sys.stderr)
        return EXIT_INTERRUPTED
    warn(prog, built.warnings)
    view = None
    if want_view:
        from msagv.experiments.viewer import RunView, ViewerError

        try:
            view = RunView(built.vehicle, built.reference, name=prog, **view_kwargs(a))
        except (ViewerError, OSError) as e:
            built.close()
            return fail(prog, f"--view: {e}", a)
        announce(view, prog)
    try:
        fox = _foxglove(a, prog, scenario, built)
    except USAGE_ERRORS as e:
        built.close()
        return fail(prog, e, a)
    log, interrupted, error = _run(a, scenario, built, view, fox)
    if error is not None:
        return fail(prog, error, a, EXIT_FAILED)
    if view is not None:
        view.finish(log.final_state or None)
    if not log.t:
        print(f"{prog}: interrupted before the first step", file=sys.stderr)
        return EXIT_INTERRUPTED
    _report(a, prog, fmu, scenario, built, log, interrupted)
    if view is not None and not interrupted:
        if a.view:
            serve_until_stopped(view, prog)
        else:
            view.close()
    return EXIT_INTERRUPTED if interrupted else 0


def _checked_options(a):
    """Every option checked and every output path known to be writable, before anything
    is built: ``(scenario, want_view)``; raises a usage error naming the option."""
    if getattr(a, "scenario_file", None):
        if a.scenario:
            raise OptionError("give the scenario file once (positional or --scenario)")
        a.scenario = a.scenario_file
    check_output(a.plot, "--plot", suffixes=PLOT_SUFFIXES)
    check_output(a.log, "--log")
    check_output(a.json_out, "--json-out")
    check_output(a.wear_plot, "--wear-plot", suffixes=PLOT_SUFFIXES)
    check_distinct(("--plot", a.plot), ("--log", a.log), ("--json-out", a.json_out),
                   ("--wear-plot", a.wear_plot), ("--view-save", a.view_save))
    want_view = check_view_args(a)
    check_foxglove_args(a, "msagv run")
    if not a.foxglove_wait >= 0:
        raise OptionError(f"--foxglove-wait must be >= 0, got {a.foxglove_wait:g}")
    return scenario_from_args(a), want_view


def _foxglove(a, prog: str, scenario, built):
    """The Foxglove view of ``--foxglove`` (None without it), its address printed; waits
    ``--foxglove-wait`` for a client."""
    if not a.foxglove:
        return None
    from msagv.experiments.foxglove import FoxgloveError, FoxgloveView

    try:
        fox = FoxgloveView({"vehicle": built.vehicle.to_dict(), "period": scenario.period,
                            "reference": built.reference.to_message()},
                           host=a.foxglove_host, port=a.foxglove_port, name=prog)
    except FoxgloveError as e:
        raise OptionError(str(e)) from None
    print(f"{prog}: Foxglove: open connection {fox.address} (Foxglove WebSocket); the run "
          f"goes in real time", file=sys.stderr, flush=True)
    if a.foxglove_wait and not fox.wait_for_client(a.foxglove_wait):
        warn(prog, [f"no Foxglove client within {a.foxglove_wait:g} s: starting"])
    return fox


def _on_step(view, fox, built):
    """closed_loop's ``on_step``: the Rerun view's, and the Foxglove view's paced in real
    time (each state sent when the wall clock reaches its time) with the predicted path."""
    if fox is None:
        return view.on_step if view is not None else None
    import time

    from msagv.bridge.ros_msgs import predicted_poses

    t_start = []

    def on_step(k, st, cmd):
        if view is not None:
            view.on_step(k, st, cmd)
        if not t_start:
            t_start.append(time.monotonic() - st["t"])
        wait = t_start[0] + st["t"] - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        fox.on_step(k, st, cmd)
        poses = predicted_poses(built.controller)
        if poses is not None:
            fox.predicted_path(st["t"], built.controller.settings.dt, poses)

    return on_step


def _run(a, scenario, built, view, fox=None):
    """The closed loop: ``(log, interrupted, error)``; the plant is closed afterwards. A
    Ctrl-C keeps the rows so far (``interrupted``); a failed step is ``error`` (a line)."""
    from msagv.controller.loop import RunLog, closed_loop

    from .errors import USAGE_ERRORS

    log = RunLog()
    interrupted = False
    try:
        closed_loop(built.plant, built.controller, built.reference, built.duration,
                    period=scenario.period, progress=False if a.quiet else a.progress, log=log,
                    on_step=_on_step(view, fox, built), measure=built.measure)
    except KeyboardInterrupt:
        interrupted = True
        log.cut_short()
    except USAGE_ERRORS as e:
        t = log.t[-1] if log.t else 0.0
        return log, False, f"the run failed at t = {t:.2f} s: {e}"
    finally:
        built.close()
        if fox is not None:
            fox.close()
    return log, interrupted, None


def _floors(scenario, vehicle, ref, ran: float, metrics: dict):
    """The wear floor (the least wear within 1 cm and 2 deg of the path) over the ``ran``
    seconds of the run (:func:`controller.floors.wear_floors`, as the study's, with the plant's vehicle) and
    the floor the run's ``metrics`` lie below 0.995 x of: ``(floors, broken)``;
    ``(None, [])`` for a run too short to have any (under 0.3 s). A run that does not start
    on the reference (``--from-rest``, ``--initial``) gets the floor of any start: the
    floor's own starts with the reference's heading and velocities."""
    from msagv.controller.floors import broken_floor, wear_floors

    if ran < 0.3:
        return None, []
    t0 = float(ref.t[0])
    on_ref = not (scenario.from_rest or scenario.initial)
    f = wear_floors(ref, scenario.actual_vehicle(vehicle), t0, t0 + ran, dt=0.05,
                    fixed_start=on_ref).as_dict()
    return f, broken_floor(metrics, f)


def _report(a, prog: str, fmu: bool, scenario, built, log, interrupted: bool) -> None:
    """The result: warnings, the JSON document, the log, the figures, the table."""
    from msagv.controller.floors import FloorError, broken_floor_warning
    from msagv.experiments.results import off_path_floor_note, split_below_floor
    from msagv.controller.metrics import (format_per_km, format_table, format_wheel_wear,
                                          wear_per_km)
    from msagv.experiments.checks import solve_time_warnings
    from msagv.experiments.results import result, scenario_info

    ref, settings, vehicle = built.reference, built.controller.settings, built.vehicle
    info = scenario_info(scenario, vehicle, ref, settings, built.duration)
    late = solve_time_warnings(log.solve_ms, scenario.period)
    warn(prog, late)
    budget = built.controller.budget()
    warnings = list(built.warnings) + budget["warnings"] + late
    if interrupted:
        done = len(log.t) * scenario.period
        warnings.append(f"interrupted after {done:.2f} s of {built.duration:g} s: the metrics "
                        f"cover the {len(log.t)} steps run")
        warn(prog, warnings[-1:])
    m = log.metrics()
    floors, broken = None, []  # --no-floor: none computed (the JSON's floors: null)
    if a.floor:
        try:
            floors, broken = _floors(scenario, vehicle, ref, len(log.t) * scenario.period, m)
        except FloorError as e:  # no floor on this path: the run's figures stand without it
            warnings.append(f"no wear floor for this run: {e}")
            warn(prog, warnings[-1:])
    broken, below_off = split_below_floor(broken, m)
    if broken:
        warnings.append(broken_floor_warning(broken))
        warn(prog, warnings[-1:])
    if below_off:
        warnings.append(off_path_floor_note(below_off))
        warn(prog, warnings[-1:])
    wear = wear_per_km(log.wheel_wear(), log.distance(), vehicle.tire_wear,  # per wheel and
                       vehicle.wheel_radius, tire_price(a, vehicle))  # axle, per km
    doc = result(prog.split(" ", 1)[1], info, m, warnings, completed=not interrupted, wear=wear)
    doc["budget"] = budget  # the controller's time budget (Controller.budget)
    dist = getattr(built.controller, "disturbance", None)
    doc["disturbance"] = dist() if dist is not None else None  # offset-free estimate at the end
    tires = getattr(built.controller, "adapted_tires", None)
    doc["adapted_tires"] = tires() if tires is not None else None  # --adapt's factors
    if doc["adapted_tires"] and doc["adapted_tires"].get("warning"):  # (on stderr when given)
        doc["warnings"].append(doc["adapted_tires"]["warning"])
    doc["floors"] = floors  # the wear floor over the run (controller.floors)
    # the floors the run wears less than 0.995 x of: within their 1 cm of the path (broken),
    # and further off it (below them without breaking them)
    doc["broken_floor"] = broken
    doc["below_floor_off_path"] = below_off
    if a.log:
        log.to_csv(a.log)
    if a.plot:
        from msagv.experiments.plots import plot_run, run_title

        plot_run(log, ref, a.plot, title=run_title(info))
    if a.wear_plot:
        from msagv.experiments.plots import plot_wear, run_title

        plot_wear(log, a.wear_plot, title=run_title(info), wear=wear)
    if a.json_out:
        Path(a.json_out).write_text(json.dumps(doc, indent=1) + "\n")
    if a.json:
        print(json.dumps(doc))
        return
    where = f"FMU {Path(a.fmu).name}" if fmu else f"{vehicle.name} {vehicle.mass:g} kg"
    how = settings.model + (f", {scenario.solver}" if scenario.solver != "sa" else "")
    speed = f" at {info['speed_kmh']} km/h" if info["speed_kmh"] is not None else ""
    print(format_table(m, f"{ref.name}{speed}, {settings.method.upper()} ({how}), {where}"
                          f"{' (interrupted)' if interrupted else ''}"))
    print("\n".join(format_wheel_wear(wear) + format_per_km(wear)))
    if floors is not None:
        print(f"  floor      W_tw [J] {floors['W_tw_floor']:.4g}   (W_s {floors['W_s_floor']:.3g}, "
              f"W_alpha {floors['W_alpha_floor']:.3g}, W_t {floors['W_t_floor']:.3g}): the least "
              f"wear within 1 cm and 2 deg of the path"
              f"{'; BROKEN: the run wears less' if broken else ''}")
    for k, path in (("log", a.log), ("plot", a.plot), ("wear plot", a.wear_plot),
                    ("view", a.view_save), ("json", a.json_out)):
        if path:
            print(f"  {k:<10} {Path(path)}")
