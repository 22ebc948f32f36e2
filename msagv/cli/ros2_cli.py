"""``msagv ros2 controller`` and ``msagv ros2 plant``: the MPC and the plant as ROS 2 nodes
(docs/ROS2.md).

Each parses the same options as its Zenoh twin (``msagv controller``, ``msagv plant``),
builds its part of the scenario (:func:`msagv.cli.args.scenario_from_args`) and hands a factory
or a plant to the node (:mod:`msagv.ros2`). Everything after ``--ros-args`` goes to rclpy:
remapping (``-r odom:=/robot/odom``), parameters (``-p method:=ntwo``), a params file.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import threading

from msagv.bridge.loss import RESUME_PERIODS, SAFE_DECEL, STALE_MS
from msagv.bridge.process import EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, StopOnSignal, setup_logging

from msagv.plant.signals import CONTROL_PERIOD
from .args import (OptionError, add_case_args, add_common_args, add_mpc_args,
                   scenario_from_args)
from .errors import USAGE_ERRORS
from .nodes import add_record_args, add_run_args, check_record_args, open_recording, run_options

USAGE = ("usage: msagv ros2 {controller,plant} [options] [--ros-args ...]\n"
         "  controller  the MPC as a ROS 2 node (odom, joint_states, plan in; "
         "ros2_control commands out)\n"
         "  plant       the plant as a ROS 2 node (odom, joint_states, tf, wear, clock out; "
         "commands in)")


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE, file=sys.stderr if not argv else sys.stdout)
        return EXIT_USAGE if not argv else EXIT_OK
    sub, rest = argv[0], argv[1:]
    if sub == "controller":
        return controller_main(rest)
    if sub == "plant":
        return plant_main(rest)
    print(f"msagv ros2: unknown command '{sub}'\n{USAGE}", file=sys.stderr)
    return EXIT_USAGE


def _safety_args(ap: argparse.ArgumentParser, who: str) -> None:
    ap.add_argument("--period", type=float, default=CONTROL_PERIOD,
                    help=f"control period T [s] ({CONTROL_PERIOD:g})")
    ap.add_argument("--stale-ms", type=float, default=STALE_MS,
                    help=f"{who}: more than this without fresh input starts the safe behaviour "
                         f"(default {STALE_MS:g})")
    ap.add_argument("--resume-periods", type=int, default=RESUME_PERIODS, metavar="N",
                    help="the safe behaviour ends after N periods of fresh input "
                         f"(default {RESUME_PERIODS})")
    ap.add_argument("--safe-decel", type=float, default=SAFE_DECEL, metavar="M/S2",
                    help=f"safe behaviour: wheel ramp-down at the rim (default {SAFE_DECEL:g})")


def _managed_arg(ap: argparse.ArgumentParser, held: str = "") -> None:
    ap.add_argument("--managed", action="store_true",
                    help="start unconfigured and wait for the lifecycle transitions "
                         "(configure, activate: Nav2's lifecycle_manager or ros2 lifecycle "
                         f"set){held}; without it the node configures and activates itself")


def _foxglove_args(ap: argparse.ArgumentParser) -> None:
    from .foxglove_cli import add_foxglove_args

    add_foxglove_args(ap)


def _ros_error(prog: str, e: BaseException) -> int:
    print(f"{prog}: error: {e}", file=sys.stderr)
    return EXIT_USAGE


# ---- msagv ros2 controller ------------------------------------------------------------------
def controller_parser() -> argparse.ArgumentParser:
    from msagv.ros2.controller_node import LOW_SPEED_KMH

    ap = argparse.ArgumentParser(
        prog="msagv ros2 controller",
        description="The MPC as a ROS 2 node: odom, joint_states and plan in; "
                    "steering_controller/commands, wheel_controller/commands, predicted_path, "
                    "wear_estimate and /diagnostics out; a managed (lifecycle) node with "
                    "~/rearm and ~/reset (docs/ROS2.md). Options after --ros-args go to ROS "
                    "(remapping, -p NAME:=VALUE for the parameters).",
        epilog="Without --case, --trajectory or --scenario the node waits for a plan on "
               "'plan'; with one of them it tracks that reference from its first state (its "
               "time 0 at the first odometry stamp) until a plan comes.")
    add_case_args(ap)
    add_mpc_args(ap)
    _safety_args(ap, "odometry and joint states")
    ap.add_argument("--max-age-ms", type=float, metavar="MS",
                    help="never send a command for a state received longer ago (default: none)")
    ap.add_argument("--node-name", default="msagv_controller", help="the ROS node's name")
    _managed_arg(ap)
    g = ap.add_argument_group("an unstamped plan (Nav2's): its speed profile and its goal")
    g.add_argument("--plan-accel", type=float, default=1.0, metavar="M/S2",
                   help="speeding up along the plan at most at this (default 1)")
    g.add_argument("--plan-decel", type=float, default=1.0, metavar="M/S2",
                   help="slowing down along the plan, to stand at its goal, at most at this "
                        "(default 1)")
    g.add_argument("--plan-lat-accel", type=float, default=1.5, metavar="M/S2",
                   help="at most this across the path in its curves (default 1.5)")
    g.add_argument("--plan-frame", default="", metavar="FRAME",
                   help="the frame a plan must be in (default: the odometry's "
                        "header.frame_id); a plan in another frame is refused: nothing is "
                        "transformed (set it to map where map and odom coincide)")
    g.add_argument("--low-speed", type=float, default=LOW_SPEED_KMH, metavar="KMH",
                   help="below this speed (the vehicle's and the reference's) the policy's "
                        "plain feed-forward commands instead of the solver: the MPC's "
                        "prediction misjudges the wear at walking pace (docs/ROS2.md; "
                        f"default {LOW_SPEED_KMH:g}, 0: never)")
    g.add_argument("--goal-tolerance", type=float, default=0.05, metavar="M",
                   help="standing this close to the plan's goal (and within "
                        "--goal-yaw-tolerance) is reached: held, no MPC (default 0.05)")
    g.add_argument("--goal-yaw-tolerance", type=float, default=2.0, metavar="DEG",
                   help="the goal's heading tolerance (default 2)")
    add_record_args(ap)
    ap.add_argument("--json", action="store_true", help="print the summary as JSON at exit")
    add_common_args(ap)
    return ap


def controller_main(argv: list[str]) -> int:
    from msagv.ros2.runtime import split_ros_args

    prog = "msagv ros2 controller"
    ours, ros_args = split_ros_args(argv)
    a = controller_parser().parse_args(ours)
    setup_logging(prog, "ros2", a.quiet, a.verbose)
    log = logging.getLogger("msagv.ros2.controller")
    try:
        if a.initial is not None or a.duration is not None:
            raise OptionError("--initial and --duration apply to msagv ros2 plant")
        check_record_args(a)
        scenario = scenario_from_args(a)
        scenario.check_solver()
        vehicle = scenario.resolve_vehicle()
        given = bool(a.case or a.trajectory or a.scenario)
        reference = scenario.reference()[0] if given else None
        for w in (scenario.check(vehicle, reference) if reference is not None else []):
            log.warning("%s", w)
        settings = scenario.mpc_settings()
        speed = _plan_speed(a.speed)
        defaults = {"method": settings.method, "model": settings.model,
                    "policy": settings.policy, "solver": scenario.solver, "seed": settings.seed,
                    "iterations": settings.iterations, "chains": settings.chains,
                    "deadline_ms": settings.deadline_ms, "Q": settings.Q, "L": settings.L,
                    "E": settings.E, "R": settings.R, "plan_speed_kmh": speed,
                    "plan_accel": a.plan_accel, "plan_decel": a.plan_decel,
                    "plan_lat_accel": a.plan_lat_accel, "goal_tolerance": a.goal_tolerance,
                    "goal_yaw_tolerance_deg": a.goal_yaw_tolerance,
                    "stale_ms": a.stale_ms, "resume_periods": a.resume_periods,
                    "safe_decel": a.safe_decel, "max_age_ms": a.max_age_ms,
                    "low_speed_kmh": a.low_speed, "plan_frame": a.plan_frame}
    except USAGE_ERRORS as e:
        return _ros_error(prog, e)

    def make_mpc(p: dict):
        """The controller from the parameters in force (ROS's -p over the options)."""
        import dataclasses

        s = dataclasses.replace(scenario, solver=p["solver"], settings=dict(
            scenario.settings, method=p["method"], model=p["model"], policy=p["policy"],
            seed=p["seed"], iterations=p["iterations"], chains=p["chains"],
            deadline_ms=p["deadline_ms"] or None, Q=tuple(p["Q"]), L=tuple(p["L"]),
            E=tuple(p["E"]), R=tuple(p["R"])))
        s.check_solver()
        return s.make_controller(vehicle, reference or _placeholder(), period=a.period)

    from msagv.ros2.controller_node import RosController, RosControllerConfig
    from msagv.ros2.runtime import Ros2Unavailable

    sig = StopOnSignal(threading.Event())
    sig.install()
    rec = node = None
    try:
        rec = open_recording(a, {"role": "controller", "id": "ros2", "vehicle": vehicle.to_dict(),
                                 "period": a.period, "run_mode": None,
                                 "reference": (dict(reference.to_message(), name=reference.name)
                                               if reference is not None else None),
                                 "transport": "ros2", "argv": list(argv)})
        cfg = RosControllerConfig(period=a.period, node_name=a.node_name)
        node = RosController(make_mpc, defaults, vehicle, cfg, ros_args, reference,
                             recorder=rec, stop=sig.event, managed=a.managed)
    except Ros2Unavailable as e:
        return _ros_error(prog, e)
    except USAGE_ERRORS as e:
        if rec is not None:
            rec.close({})
        return _ros_error(prog, e)
    try:
        summary = node.run()
    finally:
        node.close()
        if rec is not None:
            rec_stats = rec.close(node.summary())
    summary = node.summary()
    if rec is not None:
        summary["recording"] = rec_stats
    if a.json:
        print(json.dumps(summary, default=str), flush=True)
    else:
        sm = summary["solve_ms"]
        print(f"ros2 controller: answered {summary['answered']}, safe events "
              f"{summary['safe_events']}, plans {summary['plans']}, solve p50 "
              f"{(sm['p50'] or 0):.2f} p99 {(sm['p99'] or 0):.2f} ms", file=sys.stderr)
    return EXIT_OK


def _plan_speed(speed) -> float:
    """The speed an unstamped plan is timed at [km/h]: --speed when it is one number, else
    15 km/h."""
    try:
        v = float(speed)
    except (TypeError, ValueError):
        return 15.0
    if not v > 0:
        raise OptionError(f"--speed must be > 0 km/h to time a plan, got {speed}")
    return v


def _placeholder():
    """A reference for building the controller before any plan came (never tracked: the
    node commands nothing without a plan)."""
    from msagv.controller.reference import from_samples

    return from_samples([0.0, 1.0, 2.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0],
                        name="no plan yet")


# ---- msagv ros2 plant ---------------------------------------------------------------------------
def plant_parser() -> argparse.ArgumentParser:
    from msagv.bridge import messages as M
    from msagv.bridge.run_core import RunConfig

    from .args import add_fmu_args

    ap = argparse.ArgumentParser(
        prog="msagv ros2 plant",
        description="The plant as a ROS 2 node (a stand-in for Gazebo): clock, odom, "
                    "joint_states, tf, wear, markers and /diagnostics out; "
                    "steering_controller/commands and wheel_controller/commands in; "
                    "~/rearm and ~/reset (std_srvs/Trigger: reset puts the vehicle back at its "
                    "initial state and starts the run again at state 0, t = 0) "
                    "(docs/ROS2.md). Options after --ros-args go to ROS: remapping, and the "
                    "run's options as parameters (-p NAME:=VALUE, --params-file F: run_mode, "
                    "period, duration, timeout, wait, stale_ms, resume_periods, safe_decel; "
                    "stale_ms, resume_periods, safe_decel and timeout may change at run time), "
                    "example: scenarios/ros2/plant.params.yaml.")
    ap.add_argument("--run-mode", choices=list(M.RUN_MODES), default=RunConfig.run_mode,
                    help="lockstep: step when both command topics answer the current state "
                         "(as fast as the controller); realtime: step at 1/T on the wall "
                         "clock, on /clock's time under use_sim_time (default lockstep)")
    add_case_args(ap)
    ap.add_argument("--from-rest", action="store_true",
                    help="start at rest at the origin (+ --initial) instead of on the reference")
    add_fmu_args(ap, positional=False)
    add_run_args(ap)
    ap.add_argument("--node-name", default="msagv_plant", help="the ROS node's name")
    _managed_arg(ap, "; the run goes only while active, deactivated it stands on a clock "
                     "that stands (docs/ROS2.md)")
    add_record_args(ap)
    _foxglove_args(ap)
    ap.add_argument("--json", action="store_true", help="print the run's summary as JSON")
    add_common_args(ap)
    return ap


def plant_main(argv: list[str]) -> int:
    from msagv.ros2.runtime import split_ros_args

    prog = "msagv ros2 plant"
    ours, ros_args = split_ros_args(argv)
    a = plant_parser().parse_args(ours)
    setup_logging(prog, "ros2", a.quiet, a.verbose)
    log = logging.getLogger("msagv.ros2.plant")
    from .foxglove_cli import check_foxglove_args, open_foxglove

    plant = None
    try:
        check_record_args(a)
        check_foxglove_args(a, prog)
        scenario = scenario_from_args(a)
        plant, vehicle, ref, initial = scenario.make_plant()
        for w in scenario.check(vehicle, ref, initial):
            log.warning("%s", w)
        duration = scenario.run_duration(ref)
        from msagv.ros2.plant_node import RosPlantConfig

        cfg = RosPlantConfig(**run_options(a, duration), node_name=a.node_name)
    except USAGE_ERRORS as e:
        if plant is not None:
            plant.close()
        return _ros_error(prog, e)
    from msagv.ros2.plant_node import RosPlant, RosPlantError
    from msagv.ros2.runtime import Ros2Unavailable

    sig = StopOnSignal(threading.Event())
    sig.install()
    rec = node = None
    try:
        # the node first: its parameters (-p, --params-file) are the run's settings, and a
        # bad one is refused before a recording is opened (an existing file left as it was)
        node = RosPlant(plant, cfg, ros_args, stop=sig.event, managed=a.managed,
                        measure=scenario.measurement())
        cfg = node.cfg
        header = {"role": "plant", "id": "ros2", "vehicle": vehicle.to_dict(),
                  "period": cfg.period, "run_mode": cfg.run_mode, "steps": cfg.steps,
                  "initial": initial, "reference": dict(ref.to_message(), name=ref.name),
                  "transport": "ros2", "argv": list(argv)}
        rec = open_recording(a, header)
        rec = open_foxglove(a, prog, header, rec)
        if rec is not None:
            node.attach_recorder(rec)
    except (Ros2Unavailable, *USAGE_ERRORS) as e:
        if rec is not None:
            rec.close({})
        if node is not None:
            node.close()
        plant.close()
        return _ros_error(prog, e)
    rc = EXIT_OK
    try:
        plant.warmup()
        log.info("ROS 2 plant ready: %s, %s, %d steps of %g s", vehicle.name, cfg.run_mode,
                 cfg.steps, cfg.period)
        node.run()
    except RosPlantError as e:
        log.error("%s", e)
        rc = EXIT_RUNTIME
    finally:
        node.close()
        summary = node.summary()
        if sig.name is not None:
            summary["stopped_by"] = sig.name
        if rec is not None:
            summary["recording"] = rec.close(summary)
        plant.close()
    if a.json:
        print(json.dumps(summary, default=str), flush=True)
    else:
        print(f"ros2 plant: {summary['run_mode']}, {summary['steps']} steps "
              f"({summary['t_end']:.2f} s){'' if summary['completed'] else ' (incomplete)'}; "
              f"commands {summary['commands']['accepted']}, rejected "
              f"{summary['rejected']['total']}, safe events {summary['safe']['events']}",
              file=sys.stderr)
    return rc
