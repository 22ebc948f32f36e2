"""``msagv plant``, ``msagv controller``, ``msagv router`` and ``msagv arm``: the Zenoh
processes, and the operator's re-arm of a latched vehicle.

Each command parses its options, builds its part of the scenario
(:class:`experiments.scenario.Scenario`) and hands typed objects to the transport
(:func:`bridge.plant_node.serve`, :func:`bridge.controller_node.serve`,
:func:`bridge.router.serve`), which knows nothing of the command line.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
import threading
import time

from msagv.bridge import messages as M
from msagv.bridge.loss import STALE_MS
from msagv.bridge.process import (EXIT_OK, EXIT_USAGE, StopOnSignal, set_realtime_priority,
                            setup_logging)

from msagv.plant.signals import CONTROL_PERIOD
from .args import (OptionError, add_case_args, add_common_args, add_fmu_args, add_mpc_args,
                   add_measurement_noise_arg,
                   add_session_args, check_output, options_from_args, scenario_from_args)
from .errors import USAGE_ERRORS
from .foxglove_cli import add_foxglove_args, check_foxglove_args, open_foxglove
from .view import add_view_args, announce, check_view_args, view_kwargs


def _realtime_priority(a, log: logging.Logger) -> None:
    if a.rt_priority:
        why = set_realtime_priority(a.rt_priority)
        if why:
            log.warning("%s", why)


def add_record_args(ap: argparse.ArgumentParser) -> None:
    """``--record FILE`` (an MCAP recording, docs/PROTOCOL.md section 9) and its limits."""
    ap.add_argument("--record", metavar="FILE",
                    help="record every message with its time (MCAP; a full disk or a slow "
                         "disk never stops the process: errors and drops are counted)")
    ap.add_argument("--record-max-mb", type=float, default=1024.0, metavar="MB",
                    help="continue the recording in FILE.1.mcap, FILE.2.mcap, ... after this "
                         "many MB per file (default 1024)")
    ap.add_argument("--record-keep", type=int, default=0, metavar="N",
                    help="keep only the newest N files of the recording, 0 = all (default)")
    ap.add_argument("--record-ros2", action=argparse.BooleanOptionalAction, default=True,
                    help="also write the run as a ROS 2 bag beside the recording, FILE_ros2/ "
                         "(docs/ROS2.md; default on)")


def check_record_args(a) -> None:
    """Refuse bad recording options and an unwritable --record path, before start-up."""
    from msagv.bridge.recording import RecordingError, check_writable

    if not a.record_max_mb * (1 << 20) >= 4096:
        raise OptionError(f"--record-max-mb must be at least 0.004 (4 KiB), got {a.record_max_mb:g}")
    if a.record_keep < 0:
        raise OptionError(f"--record-keep must be >= 0, got {a.record_keep}")
    if a.record:
        check_output(a.record, "--record")
        try:
            check_writable(a.record)
        except RecordingError as e:
            raise OptionError(f"--record {e}") from None


def open_recording(a, header: dict):
    """The :class:`bridge.recording.Recorder` of ``--record`` (None without it)."""
    from msagv.bridge.recording import Recorder, RecordingError

    if not a.record:
        return None
    try:
        return Recorder(a.record, header, max_bytes=int(a.record_max_mb * (1 << 20)),
                        keep=a.record_keep, ros2=a.record_ros2)
    except RecordingError as e:
        raise OptionError(f"--record {e}") from None


# ---- msagv plant --------------------------------------------------------------------------
def add_run_args(ap: argparse.ArgumentParser) -> None:
    """The run's options of ``msagv plant`` and ``msagv ros2 plant``: their defaults from
    :class:`bridge.run_core.RunConfig`, where they are written once."""
    from msagv.bridge.run_core import RunConfig

    d = RunConfig()
    ap.add_argument("--period", type=float, default=d.period,
                    help=f"control period T [s] (default {d.period:g})")
    ap.add_argument("--timeout", type=float, default=d.timeout_s, metavar="S",
                    help="lockstep: longest wait for a command; realtime: for the first one "
                         f"(default {d.timeout_s:g})")
    ap.add_argument("--wait", type=float, default=d.wait_s, metavar="S",
                    help="wait this long for a controller at start, 0 = forever "
                         f"(default {d.wait_s:g})")
    ap.add_argument("--stale-ms", type=float, default=d.stale_ms,
                    help="realtime: more than stale-ms/T consecutive periods without an "
                         f"answer put the plant in its safe behaviour (default {d.stale_ms:g})")
    ap.add_argument("--resume-periods", type=int, default=d.resume_periods, metavar="N",
                    help="realtime: the safe behaviour ends after N consecutive periods in "
                         f"which the controller keeps up (default {d.resume_periods})")
    ap.add_argument("--safe-decel", type=float, default=d.safe_decel, metavar="M/S2",
                    help="realtime safe behaviour: wheel ramp-down at the rim "
                         f"(default {d.safe_decel:g})")
    add_measurement_noise_arg(ap)  # the states published are the measured ones


def run_options(a, duration: float) -> dict:
    """The run's settings (:class:`bridge.run_core.RunConfig`'s fields) from the options of
    :func:`add_run_args` and ``--run-mode``, for a run of ``duration`` s."""
    return dict(run_mode=a.run_mode, period=a.period,
                steps=int(round(duration / a.period)) if duration > 0 else 0,
                timeout_s=a.timeout, wait_s=a.wait, stale_ms=a.stale_ms,
                safe_decel=a.safe_decel, resume_periods=a.resume_periods)


def plant_parser() -> argparse.ArgumentParser:
    from msagv.bridge.plant_node import WHEEL_WEAR_MODES, PlantConfig

    d = PlantConfig()  # the defaults, written once
    ap = argparse.ArgumentParser(
        prog="msagv plant",
        description="The plant as a Zenoh process (state out, commands in, params queryable, "
                    "liveliness token). 'msagv plant replay' is the open-loop CSV replay.")
    ap.add_argument("--run-mode", choices=list(M.RUN_MODES), default=d.run_mode,
                    help="lockstep: step when the command for the current state arrives "
                         "(deterministic); realtime: step on the wall clock at 1/T "
                         f"(default {d.run_mode})")
    add_case_args(ap)
    ap.add_argument("--from-rest", action="store_true",
                    help="start at rest at the origin (+ --initial), as 'plant replay', "
                         "instead of on the reference")
    add_fmu_args(ap, positional=False)
    add_run_args(ap)
    ap.add_argument("--wheel-wear", choices=list(WHEEL_WEAR_MODES), default=d.wheel_wear,
                    help="per-wheel wear work in the state (W_s_ij, ...): auto = when the "
                         "owner's claim asks for it, on, off "
                         f"(default {d.wheel_wear})")
    ap.add_argument("--rearm", default=d.rearm, metavar="POLICY",
                    help="how a vehicle that lost its controller is driven again: manual = "
                         "only by an operator's 'msagv arm'; same:N = also by the same "
                         "controller identity claiming it again N periods after the loss "
                         f"(default {d.rearm}; docs/PROTOCOL.md section 4.7)")
    add_record_args(ap)
    add_view_args(ap)  # --view, --view-save, --view-port: the running plant in Rerun
    add_foxglove_args(ap)  # --foxglove: the running plant in Foxglove
    ap.add_argument("--json", action="store_true", help="print the run's summary as JSON")
    add_common_args(ap)  # -q: log warnings only; -v: debug
    add_session_args(ap)
    return ap


def plant_main(argv: list[str]) -> int:
    from msagv.bridge.plant_node import PlantConfig, serve
    a = plant_parser().parse_args(argv)
    setup_logging("msagv plant", a.id, a.quiet, a.verbose)
    log = logging.getLogger("msagv.plant")
    _realtime_priority(a, log)
    sig = StopOnSignal(threading.Event())
    sig.install()
    plant = None
    try:
        opts = options_from_args(a)
        check_record_args(a)
        want_view = check_view_args(a)
        check_foxglove_args(a, "msagv plant")
        scenario = scenario_from_args(a)
        plant, vehicle, ref, initial = scenario.make_plant()
        for w in scenario.check(vehicle, ref, initial):  # a speed no wheel reaches: exit 2
            log.warning("%s", w)
        duration = scenario.run_duration(ref)
        cfg = PlantConfig(**run_options(a, duration), wheel_wear=a.wheel_wear, rearm=a.rearm)
        from msagv.experiments.results import scenario_info

        header = {"role": "plant", "id": opts.id, "vehicle": vehicle.to_dict(),
                  "period": cfg.period, "run_mode": cfg.run_mode, "steps": cfg.steps,
                  "initial": initial, "reference": dict(ref.to_message(), name=ref.name),
                  "fmu": a.fmu, "argv": list(argv),
                  # what was run, as msagv run --json says it: msagv report reads it from here
                  "scenario": dict(scenario_info(scenario, vehicle, ref, None, duration),
                                   period_s=cfg.period)}
        rec = open_recording(a, header)
        if rec is not None:
            rec.hurry = sig.event  # stopped by a signal: the ROS 2 bag finishes on its own
        rec = open_foxglove(a, "msagv plant", header, rec)
        if want_view:  # beside the recorder: it only queues, a thread logs
            from msagv.experiments.viewer import RunView, Tee, ViewSink

            view = RunView(vehicle, ref, name=f"msagv plant {opts.id}", **view_kwargs(a))
            announce(view, "msagv plant")
            rec = Tee(rec, ViewSink(view, plant))
    except USAGE_ERRORS as e:
        print(f"msagv plant: {e}", file=sys.stderr)
        if plant is not None:
            plant.close()
        return EXIT_USAGE
    summary = None
    try:
        summary, rc = serve(plant, cfg, opts, recorder=rec, signals=sig,
                            measure=scenario.measurement())
    finally:
        # a loop left behind may still step the plant (an FMU): not freed under it, the
        # process leaves with os._exit below
        if summary is None or not summary.get("run_abandoned"):
            plant.close()
    _plant_report(summary, a.json)
    if a.fmu or summary.get("close_abandoned") or summary.get("run_abandoned"):
        # Everything is flushed and closed: leave without the interpreter's and the shared
        # libraries' exit handlers. A pythonfmu binary and Zenoh's static destructors in one
        # process intermittently aborted at exit ('corrupted double-linked list', in
        # zenoh_shm's cleanup) after a complete, correct run. A session whose close was
        # abandoned after a signal (bridge.plant_node.CLOSE_S), or a loop the bus held past
        # the stop (RUN_STOP_S), is left the same way: the summary is out, and the
        # interpreter's exit would wait for Zenoh.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    return rc


def _plant_report(s: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(s), flush=True)
        return
    c, r = s["commands"], s["rejected"]
    lines = [f"plant {s['id']}: {s['run_mode']}, {s['steps']} steps ({s['t_end']:.2f} s)"
             f"{'' if s['completed'] else ' (incomplete)'}",
             f"  commands   accepted {c['accepted']}, late {c['late']}, lost {c['lost']}, "
             f"stale {c['stale']}, duplicate {c['duplicate']}",
             f"  rejected   {r['total']} {r['by_reason'] if r['total'] else ''}"]
    lat = s["latency_ms"]
    if lat["n"]:
        lines.append(f"  latency    p50 {lat['p50']:.3f} ms  p99 {lat['p99']:.3f} ms  "
                     f"max {lat['max']:.3f} ms (state -> command, without the solve)")
    if s["run_mode"] == "realtime":
        j = s["period_jitter_ms"]
        lines.append(f"  periods    missed {s['missed_periods']}, jitter p50 "
                     f"{(j['p50'] or 0):.3f} p99 {(j['p99'] or 0):.3f} max {(j['max'] or 0):.3f} ms")
        sf = s["safe"]
        lines.append(f"  safe       events {sf['events']}, periods {sf['periods']}, "
                     f"resumes {sf['resumes']}")
    o = s["ownership"]
    lines.append(f"  ownership  {o['state']}; grants {o['grants']}, refused {o['refused']}, "
                 f"losses {o['losses']}, latches {o['latches']}, arms {len(o['arms'])}"
                 + "".join(f"; armed at t = {x['t']:.2f} s by {x['by']} for "
                           f"{x['controller'] or 'the first claimer'}" for x in o["arms"][:3]))
    rec = s.get("recording")
    if rec:
        lines.append(f"  recording  {rec['path']}: {rec['records']} records in {len(rec['files'])} "
                     f"file(s), {rec['bytes'] / 1e6:.2f} MB; dropped {rec['dropped']}, errors "
                     f"{rec['errors']}" + (f" ({rec['last_error']})" if rec["errors"] else ""))
    print("\n".join(lines), file=sys.stderr, flush=True)


# ---- msagv controller ---------------------------------------------------------------------
def controller_parser() -> argparse.ArgumentParser:
    from msagv.bridge.controller_node import BUS_REFERENCES, ON_PLANT_LOSS, ControllerConfig

    d = ControllerConfig()
    ap = argparse.ArgumentParser(
        prog="msagv controller",
        description="The MPC as a Zenoh process: answers each state with a command.")
    add_case_args(ap)
    add_mpc_args(ap)
    ap.add_argument("--wait", type=float, default=60.0, metavar="S",
                    help="wait this long for the plant's params at start, 0 = forever "
                         "(default 60; not needed with --vehicle)")
    ap.add_argument("--max-age-ms", type=float, metavar="MS",
                    help="never send a command for a state older than this (default: "
                         f"{STALE_MS:g} against a realtime plant, none in lockstep)")
    ap.add_argument("--on-plant-loss", choices=list(ON_PLANT_LOSS), default=d.on_plant_loss,
                    help="when the plant's token disappears: wait for it or exit 3 "
                         f"(default {d.on_plant_loss})")
    ap.add_argument("--exit-at-end", action="store_true",
                    help="exit after the plant's last state (end = true)")
    ap.add_argument("--bus-references", choices=list(BUS_REFERENCES),
                    default=d.bus_references,
                    help="take new references from the bus (msagv/ID/reference): 'auto' only "
                         "with --secure, where only this controller's and the operator's "
                         "certificates may send them; 'on' from anyone (a plain bus cannot "
                         "tell who sent one); 'off' never. Refused ones are counted as "
                         f"references_off (default {d.bus_references})")
    add_record_args(ap)
    ap.add_argument("--json", action="store_true", help="print the summary as JSON at exit")
    add_common_args(ap)  # -q: log warnings only; -v: debug
    add_session_args(ap)
    return ap


def controller_main(argv: list[str]) -> int:
    from msagv.bridge.controller_node import ControllerConfig, realtime_defaults, serve
    a = controller_parser().parse_args(argv)
    setup_logging("msagv controller", a.id, a.quiet, a.verbose)
    log = logging.getLogger("msagv.controller")
    _realtime_priority(a, log)
    if a.initial is not None:
        print("msagv controller: --initial applies to msagv plant", file=sys.stderr)
        return EXIT_USAGE
    if a.duration is not None:
        print("msagv controller: --duration applies to msagv plant", file=sys.stderr)
        return EXIT_USAGE
    try:
        opts = options_from_args(a)
        check_record_args(a)
        scenario = scenario_from_args(a)
        scenario.check_solver()  # ipopt without CasADi or with model != mf: exit 2
        if a.vehicle:
            scenario.resolve_vehicle()  # a bad file fails before any network
    except USAGE_ERRORS as e:
        print(f"msagv controller: {e}", file=sys.stderr)
        return EXIT_USAGE

    def make_mpc(params):
        vehicle = scenario.resolve_vehicle(params.vehicle if params else None)
        ref, _ = scenario.reference()
        deadline, _ = realtime_defaults(params.run_mode if params else None,
                                        a.deadline_ms, a.max_age_ms)
        override = {} if deadline is None else {"deadline_ms": deadline}
        if deadline is not None and a.deadline_ms is None:
            log.info("realtime plant: solve budget %g ms (--deadline-ms)", deadline)
        return scenario.make_controller(vehicle, ref,
                                        period=params.period if params else CONTROL_PERIOD,
                                        **override)

    def open_recorder(mpc, params):
        ref = mpc.reference
        try:
            from msagv.experiments.results import scenario_info

            return open_recording(a, {
                "role": "controller", "id": opts.id, "vehicle": mpc.vehicle.to_dict(),
                "period": mpc.period, "run_mode": params.run_mode if params else None,
                "reference": dict(ref.to_message(), name=ref.name),
                "settings": dataclasses.asdict(mpc.settings), "solver": scenario.solver,
                "argv": list(argv),
                "scenario": scenario_info(scenario, mpc.vehicle, ref, mpc.settings)})
        except OptionError as e:  # checked before start-up; gone since: control goes on
            log.error("%s; running without a recording", e)
            return None

    sig = StopOnSignal(threading.Event())
    cfg = ControllerConfig(a.max_age_ms, a.on_plant_loss, a.exit_at_end, a.bus_references)
    summary, rc = serve(opts, make_mpc, cfg, fetch=not a.vehicle, wait_s=a.wait,
                        open_recorder=open_recorder, stop=sig.event,
                        on_signal_install=sig.install)
    if a.json:
        print(json.dumps(summary), flush=True)
    elif "answered" in summary:
        sm = summary["solve_ms"]
        print(f"controller {opts.id}: answered {summary['answered']}, skipped "
              f"{summary['skipped']}, rejected {summary['rejected']['total']}, solve p50 "
              f"{(sm['p50'] or 0):.2f} p99 {(sm['p99'] or 0):.2f} ms ({summary['exit_reason']})",
              file=sys.stderr)
        rec = summary.get("recording")
        if rec:
            print(f"  recording  {rec['path']}: {rec['records']} records, dropped "
                  f"{rec['dropped']}, errors {rec['errors']}"
                  + (f" ({rec['last_error']})" if rec["errors"] else ""), file=sys.stderr)
    return rc


# ---- msagv router -------------------------------------------------------------------------
def router_main(argv: list[str]) -> int:
    from msagv.bridge.router import serve
    from msagv.bridge.session import ROUTER_PORT, SessionError

    ap = argparse.ArgumentParser(
        prog="msagv router",
        description=f"A Zenoh router (a session in router mode); listens on "
                    f"tcp/127.0.0.1:{ROUTER_PORT} unless --listen is given (use "
                    f"--listen tcp/0.0.0.0:{ROUTER_PORT} for other machines).")
    add_common_args(ap)  # -q: log warnings only; -v: debug
    add_session_args(ap, router=True)
    a = ap.parse_args(argv)
    setup_logging("msagv router", "-", a.quiet, a.verbose)
    sig = StopOnSignal(threading.Event())
    sig.install()
    try:
        opts = options_from_args(a, router=True)
    except (SessionError, OptionError) as e:
        print(f"msagv router: {e}", file=sys.stderr)
        return EXIT_USAGE
    return serve(opts, sig.event) or EXIT_OK


# ---- msagv arm ----------------------------------------------------------------------------
ARM_WAIT_S = 10.0


def arm_main(argv: list[str]) -> int:
    """``msagv arm --id ID [--controller NAME]``: an operator re-arms a latched vehicle."""
    from msagv.bridge.ownership import ARMED, arm
    from msagv.bridge.process import EXIT_RUNTIME
    from msagv.bridge.session import Keys
    from msagv.bridge.zenoh_transport import ZenohTransport

    ap = argparse.ArgumentParser(
        prog="msagv arm",
        description="Re-arm a vehicle that is latched after losing its controller "
                    "(docs/PROTOCOL.md section 4.7): the named controller (or, without "
                    "--controller, the first controller that claims it) may then drive it. "
                    "With --secure the operator's certificate is used (msagv certs).")
    ap.add_argument("--controller", metavar="NAME",
                    help="the identity of the controller that may claim the vehicle next (its "
                         "certificate's common name with --secure, else its session id, as "
                         "the controller and the plant log it)")
    ap.add_argument("--wait", type=float, default=ARM_WAIT_S, metavar="S",
                    help=f"wait this long for the plant to answer (default {ARM_WAIT_S:g})")
    ap.add_argument("--json", action="store_true", help="print the plants' answers as JSON")
    add_common_args(ap)
    add_session_args(ap)
    a = ap.parse_args(argv)
    setup_logging("msagv arm", a.id, a.quiet, a.verbose)
    try:
        opts = options_from_args(a)
        if a.controller is not None:
            from msagv.bridge.ownership import identity_error

            why = identity_error(a.controller)
            if why is not None:
                raise OptionError(f"--controller: not an identity: {why}")
        if not a.wait > 0:
            raise OptionError(f"--wait must be > 0, got {a.wait:g}")
        t = ZenohTransport.open(opts, "operator")
    except USAGE_ERRORS as e:
        print(f"msagv arm: {e}", file=sys.stderr)
        return EXIT_USAGE
    keys = Keys(opts.id)
    answers: list = []
    with t:
        deadline = time.monotonic() + a.wait
        while not answers and time.monotonic() < deadline:
            answers = arm(t, keys, a.controller, timeout=min(2.0, a.wait))
            if not answers:
                time.sleep(0.25)
    out = [{"plant": p, "armed": bool(r and r["armed"]), "reason": r["reason"] if r else
            "malformed reply"} for p, r in answers]
    if a.json:
        print(json.dumps({"id": opts.id, "controller": a.controller, "by": t.id,
                          "answers": out}), flush=True)
    if not out:
        print(f"msagv arm: no plant of vehicle '{opts.id}' answered within {a.wait:g} s",
              file=sys.stderr)
        return EXIT_RUNTIME
    for x in out:
        print(f"msagv arm: vehicle {opts.id}, plant {x['plant']}: "
              + (f"re-armed for {a.controller or 'the first controller that claims it'}"
                 if x["armed"] else f"refused ({x['reason']}: "
                 + ("a controller owns it" if x["reason"] == "owned" else x["reason"]) + ")"),
              file=sys.stderr)
    return EXIT_OK if all(x["armed"] and x["reason"] == ARMED for x in out) else EXIT_RUNTIME
