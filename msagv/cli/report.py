"""``msagv report``: the paper's metrics and plots from a recording.

Reads a recording of ``msagv plant`` or ``msagv controller`` (``--record FILE``), rebuilds
the run (:func:`experiments.recorded.evaluate`) and reports it as ``msagv run`` reports an
in-process run: the table or the JSON document, the per-step log, the figures, the Rerun
view.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from msagv.plant.signals import WEAR_FIELDS

from .args import (PLOT_SUFFIXES, add_common_args, add_tire_price_arg, check_distinct,
                   check_output, check_tire_price, fail, tire_price, warn)
from .view import (add_view_args, check_view_args, exposure_warning, serve_until_stopped,
                   view_kwargs)

PROG = "msagv report"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG,
                                 description="The paper's metrics and plots from a recording "
                                             "(msagv plant/controller --record FILE).")
    ap.add_argument("recording", metavar="FILE")
    ap.add_argument("--run", type=int, default=-1,
                    help="which plant run of the recording, 0 = first (default: the last)")
    ap.add_argument("--json", action="store_true",
                    help="print the result as JSON (the shape of msagv run --json, plus "
                         "'recording')")
    ap.add_argument("--json-out", metavar="FILE", help="also write the JSON result to FILE")
    ap.add_argument("--plot", metavar="FILE", help="write a figure (path, errors, wear power)")
    ap.add_argument("--log", metavar="FILE", help="write the per-step log as CSV")
    ap.add_argument("--wear-plot", metavar="FILE",
                    help="write a figure of the wear per wheel and per axle")
    add_tire_price_arg(ap)
    add_view_args(ap)  # --view, --view-save, --view-port: the run in Rerun (msagv view)
    add_common_args(ap)
    return ap


def _recording_scenario(info: dict, header: dict, log, ref) -> dict:
    """The result's ``scenario`` block from a recording's header: the block the process
    wrote (``scenario``, as ``msagv run --json`` has it; a plant knows no MPC settings, a
    controller's recording adds them), with the duration as recorded. A recording made
    before the header carried it is labelled from its reference and recorded command line,
    never guessed: a reference that is not one of the paper's cases is a trajectory."""
    from msagv.experiments.results import CASE_NAMES, DEFAULT_SPEED, speed_value, vehicle_info
    from msagv.plant.vehicle import vehicle_from_dict

    period = header.get("period")
    duration = None if period is None else len(log.t) * float(period)
    st = header.get("settings") or {}
    if isinstance(header.get("scenario"), dict):
        sc = dict(header["scenario"], reference=ref.name, duration_s=duration)
        if st:
            sc.update(method=st.get("method"), model=st.get("model"), seed=st.get("seed"),
                      solver=header.get("solver"))
        return sc
    argv = [str(x) for x in header.get("argv") or []]

    def opt(name):
        for i, x in enumerate(argv):
            if x == name and i + 1 < len(argv):
                return argv[i + 1]
            if x.startswith(name + "="):
                return x.split("=", 1)[1]
        return None

    case = {"case1-curve": "curve", "case2-line": "line"}.get(
        (header.get("reference") or {}).get("name", ref.name))
    traj = opt("--trajectory") if case is None else None
    speed = speed_value(opt("--speed")) if case is not None else None
    if speed is None and case is not None:
        speed = DEFAULT_SPEED[CASE_NAMES.get(case, case)]
    try:
        vehicle = vehicle_info(vehicle_from_dict(header["vehicle"]), opt("--vehicle"))
    except (KeyError, TypeError, ValueError):
        vehicle = None
    return {"case": case, "trajectory": traj, "reference": ref.name, "speed_kmh": speed,
            "vehicle": vehicle, "method": st.get("method"), "model": st.get("model"),
            "solver": header.get("solver"), "seed": st.get("seed"),
            "duration_s": duration, "period_s": period, "after_end": None,
            "plant": f"fmu {header['fmu']}" if header.get("fmu") else None,
            "initial": None}


def main(argv: list[str]) -> int:
    from msagv.bridge.recording import RecordingError, read_recording
    from msagv.controller.metrics import wear_per_km
    from msagv.experiments.recorded import ReportError, evaluate

    from .args import OptionError

    a = _parser().parse_args(argv)
    try:
        want_view = check_view_args(a)
        check_output(a.plot, "--plot", suffixes=PLOT_SUFFIXES)
        check_output(a.wear_plot, "--wear-plot", suffixes=PLOT_SUFFIXES)
        check_output(a.log, "--log")
        check_output(a.json_out, "--json-out")
        check_distinct(("the recording", a.recording), ("--plot", a.plot), ("--log", a.log),
                       ("--json-out", a.json_out), ("--wear-plot", a.wear_plot),
                       ("--view-save", a.view_save))
        m, info, log, ref = evaluate(a.recording, a.run)
        header = read_recording(a.recording)[0]
        vehicle = _vehicle(header)
        if vehicle is not None:
            check_tire_price(a, vehicle)
        elif a.tire_price is not None:
            raise OptionError("--tire-price: the recording does not say which vehicle it is")
    except (RecordingError, ReportError, OptionError, KeyError, TypeError) as e:
        return fail(PROG, e, a)
    m, warnings = _measured(m, info, log, a)
    scenario = _recording_scenario(info, header, log, ref)
    wear = log.wheel_wear()  # None: the plant did not send the per-wheel fields
    if vehicle is not None:
        wear = wear_per_km(wear, log.distance(), vehicle.tire_wear, vehicle.wheel_radius,
                           tire_price(a, vehicle))
    doc = _write_outputs(a, m, info, log, ref, scenario, warnings, wear)
    view = None
    if want_view:
        from msagv.experiments.viewer import ViewerError, view_recording

        try:
            view, _ = view_recording(a.recording, view_kwargs(a), a.run)
        except (ViewerError, OSError) as e:
            return fail(PROG, f"--view: {e}", a)
        warn(PROG, exposure_warning(view))
    if a.json_out:
        Path(a.json_out).write_text(json.dumps(doc, indent=1) + "\n")
    if a.json:
        print(json.dumps(doc))
    else:
        _print(a, m, info, wear, ref)
    if view is not None:
        if a.view:
            serve_until_stopped(view, PROG)
        else:
            view.close()
    return 0


def _measured(m: dict, info: dict, log, a) -> tuple[dict, list[str]]:
    """The metrics as far as the recording measures them, and the warnings saying what it
    does not (no wear work, a run cut short, unanswered states, no per-wheel wear)."""
    warnings = []
    if not any(k in log.final_state for k in WEAR_FIELDS):
        warnings.append("the recorded states carry no wear work (W_s, W_alpha, W_t are "
                        "optional fields of the state message): W_tw and Omega are not "
                        "measured")
        m = dict(m, W_tw=None, W_s=None, W_alpha=None, W_t=None, Omega=None)
    if not info["ended"]:
        warnings.append(f"the run has no end state (cut short): the metrics cover the "
                        f"{info['steps']} steps recorded")
    if info["unanswered"]:
        warnings.append(f"{info['unanswered']} of {info['steps']} states have no command "
                        f"in the recording")
    if log.wheel_wear() is None and m.get("W_tw") is not None:
        warnings.append("the recorded states carry no per-wheel wear work (W_s_ij, ...; "
                        "msagv plant sends it to controllers that ask, or with --wheel-wear "
                        "on): the wear per wheel and per axle is not measured"
                        + ("; --wear-plot not written" if a.wear_plot else ""))
    warn(PROG, warnings)
    return m, warnings


def _vehicle(header: dict):
    """The recorded vehicle (None when the header has none we can read)."""
    from msagv.plant.vehicle import VehicleError, vehicle_from_dict

    try:
        return vehicle_from_dict(header["vehicle"])
    except (KeyError, TypeError, VehicleError):
        return None


def _write_outputs(a, m, info, log, ref, scenario, warnings, wear) -> dict:
    """The result document; the per-step log and the figures the options ask for."""
    from msagv.experiments.results import result

    doc = result("report", scenario, m, warnings, completed=info["ended"], recording=info,
                 wear=wear)
    if a.log:
        log.to_csv(a.log)
    if a.plot:
        from msagv.experiments.plots import plot_run, run_title

        plot_run(log, ref, a.plot, title=run_title(
            scenario, f"over Zenoh ({info['run_mode']}, {info['role']} recording)"))
    if a.wear_plot and wear is not None:
        from msagv.experiments.plots import plot_wear, run_title

        plot_wear(log, a.wear_plot, title=run_title(scenario, f"{info['role']} recording"),
                  wear=wear)
    return doc


def _print(a, m, info, wear, ref) -> None:
    from msagv.controller.metrics import format_per_km, format_table, format_wheel_wear

    print(format_table(m, f"{ref.name}: {info['recording']} ({info['role']}, "
                          f"{info['run_mode']}, run {info['run']} of {info['runs']})"))
    print("\n".join(format_wheel_wear(wear) + format_per_km(wear)))
    lat = info["latency_ms"]
    print(f"  answered   {info['answered']} of {info['steps']} states; rejected messages "
          f"{info['rejected']}")
    if lat["p50"] is not None:
        print(f"  latency    p50 {lat['p50']:.3f}  p99 {lat['p99']:.3f}  max {lat['max']:.3f} ms "
              f"(state -> command, without the solve; as recorded)")
    for k, path in (("log", a.log), ("plot", a.plot), ("wear plot", a.wear_plot),
                    ("view", a.view_save), ("json", a.json_out)):
        if path:
            print(f"  {k:<10} {Path(path)}")
