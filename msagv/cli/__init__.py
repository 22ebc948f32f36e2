"""The ``msagv`` entry point: one dispatcher over every sub-command.

Each command's module is imported only when that command runs (``msagv vehicle show``
does not pay for compiling the controller or importing zenoh); the imports are plain
``import`` statements, so the import graph stays visible to tools. The small commands
(``vehicle``, ``plant replay``, ``fmu``, ``bench``) live here; ``run``, ``report``,
``plant``/``controller``/``router``, ``experiment`` and ``demo`` in their own modules.
"""

from __future__ import annotations

import argparse
import json
import sys

COMMANDS = {
    "demo": "plant and controller as two processes over Zenoh (Case 1, 15 km/h)",
    "vehicle": "vehicle show [--vehicle FILE] [--json]",
    "plant": "the plant as a Zenoh process; 'plant replay' for open-loop CSV replay",
    "controller": "the MPC as a Zenoh process",
    "ros2": "ros2 controller | ros2 plant: the MPC and the plant as ROS 2 nodes (docs/ROS2.md)",
    "router": "a Zenoh router for plants and controllers on several machines",
    "arm": "arm --id ID [--controller NAME]: re-arm a vehicle latched after losing its controller",
    "certs": "certs DIR: a CA and per-role certificates for --secure (mutual TLS, access control)",
    "run": "in-process closed loop (controller at 100 Hz on the stepping plant)",
    "report": "the paper's metrics and plots from a recording",
    "calibrate": "calibrate RECORDING -o tuned.toml: the vehicle's tires and lags from a recording",
    "view": "view FILE: a recording in Rerun's 3D viewer (vehicle, wheel wear, paths, errors)",
    "recover": "recover FILE: a recording cut short by a kill or a full disk made readable",
    "experiment": "the paper's Cases 1-3, the Pareto front, the ridge study; the study (the "
                  "paper's question at equal error) and mismatch (with tires it does not know)",
    "fmu": "fmu build | fmu simulate",
    "bench": "benchmarks (plant, rollout, controller, optimality, nmpc, transport, fmu)",
}


SUBCOMMANDS = {"fmu": ("build", "simulate"), "plant": ("replay",), "vehicle": ("show",)}
PROCESSES = ("plant", "controller", "router", "arm")  # they log their own way


def _usage() -> str:
    lines = ["usage: msagv COMMAND [options]   (msagv COMMAND --help for a command's options)",
             "       msagv --version", "",
             "commands:"]
    for name, text in COMMANDS.items():
        lines.append(f"  {name:<11} {text}")
    return "\n".join(lines)


def _dispatch(cmd: str, rest: list[str]) -> int:
    if cmd == "demo":
        from .demo import main
        return main(rest)
    if cmd == "vehicle":
        return vehicle_main(rest)
    if cmd == "plant":
        if rest[:1] == ["replay"]:
            return replay_main(rest[1:])
        from .nodes import plant_main
        return plant_main(rest)
    if cmd == "controller":
        from .nodes import controller_main
        return controller_main(rest)
    if cmd == "ros2":
        from .ros2_cli import main as ros2_main
        return ros2_main(rest)
    if cmd == "arm":
        from .nodes import arm_main
        return arm_main(rest)
    if cmd == "certs":
        from .certs import main as certs_main
        return certs_main(rest)
    if cmd == "router":
        from .nodes import router_main
        return router_main(rest)
    if cmd == "run":
        from .run import main
        return main(rest)
    if cmd == "view":
        from .view import main as view_main
        return view_main(rest)
    if cmd == "report":
        from .report import main as report_main
        return report_main(rest)
    if cmd == "recover":
        return recover_main(rest)
    if cmd == "calibrate":
        from .calibrate import main as calibrate_main
        return calibrate_main(rest)
    if cmd == "experiment":
        from .experiment import main
        return main(rest)
    if cmd == "fmu":
        return fmu_main(rest)
    if cmd == "bench":
        return bench_main(rest)
    raise AssertionError(cmd)


def main(argv: list[str] | None = None) -> int:
    """Exit codes, the same for every command: 0 done, 1 the work failed, 2 bad options or
    input (nothing done), 130 interrupted (Ctrl-C; what was done is printed)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print(_usage(), file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    if argv[0] in ("--version", "-V"):
        from .. import __version__

        print(f"msagv {__version__}")
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        print(f"msagv: unknown command '{cmd}'\n\n{_usage()}", file=sys.stderr)
        return 2
    from .args import warning_style

    sub = rest[0] if rest and rest[0] in SUBCOMMANDS.get(cmd, ()) else None
    prog = f"msagv {cmd}" + (f" {sub}" if sub else "")
    # the Zenoh processes log their own way (bridge.process.setup_logging)
    logs = not (cmd in PROCESSES and sub is None)
    try:
        with warning_style(prog, verbose=bool({"-v", "--verbose"} & set(rest)), logs=logs):
            return int(_dispatch(cmd, rest) or 0)
    except KeyboardInterrupt:
        print(f"msagv {cmd}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (msagv ... | head): not an error of ours
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


# ---- msagv vehicle show -----------------------------------------------------------------
def vehicle_main(argv: list[str]) -> int:
    from msagv.plant.vehicle import VehicleError, load_vehicle, plausibility_warnings

    from .args import add_common_args, fail, warn

    ap = argparse.ArgumentParser(prog="msagv vehicle", description="Show a vehicle description.")
    ap.add_argument("action", choices=["show"])
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in paper-2axle)")
    ap.add_argument("--json", action="store_true", help="print the resolved description as JSON")
    add_common_args(ap)
    a = ap.parse_args(argv)
    try:
        v = load_vehicle(a.vehicle)
    except (VehicleError, FileNotFoundError) as e:
        return fail("msagv vehicle show", e, a)
    warn("msagv vehicle show", plausibility_warnings(v))
    d = v.to_dict()
    d["derived"] = {"n_axles": v.n_axles, "n_wheels": v.n_wheels, "normal_load_N": v.normal_load,
                    "wheel_x": v.wheel_x.tolist(), "wheel_y": v.wheel_y.tolist()}
    if v.tire_wear is not None:
        d["derived"].update(abradability_mm3_per_J=v.tire_wear.k_a(v.wheel_radius),
                            usable_tread_mm3=v.tire_wear.usable_volume(v.wheel_radius))
    if a.json:
        print(json.dumps(d, indent=2))
    else:
        print(f"{v.name}: {v.n_axles} axles, {v.mass:g} kg, I_vz {v.yaw_inertia:g} kg m^2, "
              f"r_w {v.wheel_radius:g} m, F_N {v.normal_load:.0f} N per wheel")
        print(f"  axles at x = {list(v.axle_x)} m, wheels at y = +/-{v.half_track:g} m")
        for part in [k for k in d["tire"] if k != "wear"]:  # the models' own too
            print(f"  tire.{part}: {d['tire'][part]}")
        print(f"  limits: {d['limits']}")
        tw = v.tire_wear
        print(f"  tire.wear: {d['tire']['wear']} (k_a {tw.k_a(v.wheel_radius):.4g} mm^3/J, "
              f"usable tread {tw.usable_volume(v.wheel_radius) / 1e6:.4g} dm^3 per tire)"
              if tw is not None else "  tire.wear: none (no tire life; docs/WEAR.md)")
        print(f"  k_t = {v.steer_loss_kt:g} m; plant options: {d['plant']}")
    return 0


# ---- msagv plant replay -----------------------------------------------------------------
def replay_main(argv: list[str]) -> int:
    from msagv.plant.replay import read_inputs, replay, write_signals
    from msagv.plant.vehicle import load_vehicle, plausibility_warnings

    from .args import add_common_args, check_output, fail, note, parse_assignments, warn
    from .errors import USAGE_ERRORS

    ap = argparse.ArgumentParser(
        prog="msagv plant replay",
        description="Open-loop replay: held commands from a CSV through the stepping plant.")
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in)")
    ap.add_argument("--inputs", metavar="U.csv", required=True,
                    help="columns t, omega_w_ij, omega_s_ij; row k held until row k+1")
    ap.add_argument("-o", "--out", metavar="S.csv", required=True,
                    help="signals at the input times")
    ap.add_argument("--initial", metavar="name=value,...", help="initial state, e.g. vx=5,phi=0.2")
    ap.add_argument("--rtol", type=float, default=1e-8, help="integrator relative tolerance")
    add_common_args(ap)
    a = ap.parse_args(argv)
    try:
        check_output(a.out, "--out")
        v = load_vehicle(a.vehicle)
        warn("msagv plant replay", plausibility_warnings(v))
        t, U = read_inputs(a.inputs, v)
        names, S = replay(v, t, U, parse_assignments(a.initial), rtol=a.rtol)
    except USAGE_ERRORS as e:
        return fail("msagv plant replay", e, a)
    write_signals(a.out, names, S)
    note(a, f"wrote {len(t)} rows x {len(names)} signals to {a.out}")
    return 0


def recover_main(argv: list[str]) -> int:
    """``msagv recover FILE``: every file of a recording (its rotated parts, its ROS 2 bag)
    made a complete MCAP file, and the bag's metadata.yaml written (bridge.recover)."""
    from msagv.bridge.recover import recover_recording
    from msagv.bridge.recording import RecordingError

    from .args import add_common_args, fail

    prog = "msagv recover"
    ap = argparse.ArgumentParser(
        prog=prog, description="Make a recording cut short (a killed process, a full disk) "
                               "readable by the standard readers: each file of it (FILE, its "
                               "rotated parts FILE.1.mcap, ..., its ROS 2 bag NAME_ros2/) is "
                               "rewritten in place with every complete record up to the cut; "
                               "the bag's metadata.yaml is written. Complete files are left "
                               "as they are.")
    ap.add_argument("recording", metavar="FILE", help="the recording (msagv ... --record FILE)")
    ap.add_argument("--json", action="store_true", help="print what was recovered as JSON")
    add_common_args(ap)
    a = ap.parse_args(argv)
    try:
        out = recover_recording(a.recording)
    except (RecordingError, OSError) as e:
        return fail(prog, e, a)
    if a.json:
        print(json.dumps(out))
        return 0
    for f in out["files"]:
        topics = ", ".join(f"{n} {t.rsplit('/', 1)[-1] or t}" for t, n in
                           sorted(f["by_topic"].items()) if t.endswith(("/state", "/cmd", "odom")))
        print(f"{f['path']}: {'complete, nothing to do' if f['complete'] else 'repaired'}; "
              f"{f['messages']} messages{' (' + topics + ')' if topics else ''}")
    if out["bag"]:
        b = out["bag"]
        print(f"{b['path']}/metadata.yaml: written ({b['messages']} messages on "
              f"{b['topics']} topics)")
    return 0


# ---- msagv fmu build | simulate ----------------------------------------------------------
FMU_USAGE = """usage: msagv fmu build [--vehicle FILE] -o FILE.fmu [--prefix P] [--initial name=value,...]
       msagv fmu simulate FILE.fmu [msagv run's options]   (the closed loop against an FMU)"""


def fmu_main(argv: list[str]) -> int:
    if not argv:
        print(FMU_USAGE, file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help", "help"):
        print(FMU_USAGE)
        return 0
    if argv[0] in ("--version", "-V"):
        return main(["--version"])
    sub, rest = argv[0], argv[1:]
    if sub == "build":
        return fmu_build_main(rest)
    if sub == "simulate":
        from .run import main as run_main

        return run_main(rest, prog="msagv fmu simulate", fmu=True)
    print(f"msagv fmu: unknown sub-command '{sub}'\n{FMU_USAGE}", file=sys.stderr)
    return 2


def fmu_build_main(argv: list[str]) -> int:
    from msagv.fmu_build.build import FmuBuildError, build_fmu
    from msagv.plant.vehicle import load_vehicle, plausibility_warnings

    from .args import add_common_args, check_output, fail, note, parse_assignments, warn
    from .errors import USAGE_ERRORS

    ap = argparse.ArgumentParser(
        prog="msagv fmu build",
        description="Package the plant as an FMI 2.0 co-simulation FMU (pythonfmu). The FMU "
                    "bundles the plant package and the vehicle; it runs in the importer's "
                    "Python, which needs numpy and numba (see docs/FMU.md).")
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in paper-2axle)")
    ap.add_argument("-o", "--out", "--output", dest="output", metavar="FILE.fmu", required=True,
                    help="the FMU to write")
    ap.add_argument("--prefix", default="",
                    help="put in front of every variable name (e.g. 'agv0.'); the host then "
                         "needs a mapping file")
    ap.add_argument("--initial", metavar="name=value,...",
                    help="start values of the initial-state parameters, e.g. vx=2,phi=0.1")
    add_common_args(ap)
    a = ap.parse_args(argv)
    try:
        check_output(a.output, "-o", suffixes=(".fmu",))
        vehicle = load_vehicle(a.vehicle)
        warn("msagv fmu build", plausibility_warnings(vehicle))
        initial = parse_assignments(a.initial)
        out = build_fmu(a.output, vehicle, prefix=a.prefix, initial=initial)
    except USAGE_ERRORS + (FmuBuildError,) as e:
        return fail("msagv fmu build", e, a)
    note(a, f"wrote {out} ({vehicle.name}, {vehicle.n_axles} axles)")
    return 0


# ---- msagv bench --------------------------------------------------------------------------
def bench_main(argv: list[str] | None = None) -> int:
    from msagv.benchmarks import suite

    from .args import add_common_args, check_output, fail, warn

    ap = argparse.ArgumentParser(prog="msagv bench", description=suite.__doc__.splitlines()[0])
    ap.add_argument("sections", nargs="*", metavar="SECTION",
                    help=f"which benchmarks (default all): {', '.join(suite.SECTIONS)}")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--quick", action="store_true",
                    help="short runs (a smoke test; the figures are not meaningful)")
    ap.add_argument("--json-out", metavar="FILE", help="also write the JSON to FILE")
    ap.add_argument("--out", metavar="FILE", help=argparse.SUPPRESS)  # deprecated: --json-out
    add_common_args(ap)
    a = ap.parse_args(argv)
    if a.out:
        warn("msagv bench", ["--out is deprecated, use --json-out (the same file)"])
        a.json_out = a.json_out or a.out
    quiet = a.json or a.quiet
    echo = (lambda line: print(line, file=sys.stderr, flush=True)) if quiet else \
        (lambda line: print(line, flush=True))
    try:
        check_output(a.json_out, "--json-out")
        result = suite.run(a.sections, a.quick, echo)
    except ValueError as e:
        return fail("msagv bench", e, a)
    if a.json_out:
        with open(a.json_out, "w") as f:
            json.dump(result, f, indent=1)
    if a.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
