"""The ``msagv`` entry point: a thin dispatcher to each part's own ``main(argv)``.

Each sub-command's module is imported only when it runs, so ``msagv vehicle show`` does
not pay for numba compilation of the controller or for importing zenoh.
"""

from __future__ import annotations

import importlib
import sys

# command -> (module, function, one-line help)
COMMANDS = {
    "demo": ("bridge.demo", "main", "plant and controller as two processes over Zenoh (Case 1, 15 km/h)"),
    "vehicle": ("plant.cli", "vehicle_main", "vehicle show [--vehicle FILE] [--json]"),
    "plant": ("bridge.plant_node", "main", "the plant as a Zenoh process; 'plant replay' for open-loop CSV replay"),
    "controller": ("bridge.controller_node", "main", "the MPC as a Zenoh process"),
    "router": ("bridge.router", "main", "a Zenoh router for plants and controllers on several machines"),
    "run": ("bridge.run_cmd", "main", "in-process closed loop (controller at 100 Hz on the stepping plant)"),
    "report": ("bridge.report", "main", "the paper's metrics and plots from a recording"),
    "experiment": ("bridge.experiments", "main", "the paper's Cases 1-3, the Pareto front and the ridge study"),
    "fmu": ("fmu_build.cli", "main", "fmu build | fmu simulate"),
    "bench": ("benchmarks.cli", "main", "benchmarks (plant, rollout, controller, optimality, transport, fmu)"),
}


def _usage() -> str:
    lines = ["usage: msagv COMMAND [options]   (msagv COMMAND --help for a command's options)", "",
             "commands:"]
    for name, (_, _, text) in COMMANDS.items():
        lines.append(f"  {name:<11} {text}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd == "plant" and rest[:1] == ["replay"]:
        module, func, rest = "plant.cli", "replay_main", rest[1:]
    elif cmd in COMMANDS:
        module, func, _ = COMMANDS[cmd]
    else:
        print(f"msagv: unknown command '{cmd}'\n\n{_usage()}", file=sys.stderr)
        return 2
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        print(f"msagv {cmd}: not available in this installation ({e})", file=sys.stderr)
        return 2
    rc = getattr(mod, func)(rest)
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
