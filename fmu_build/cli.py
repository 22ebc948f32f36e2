"""``msagv fmu build`` (and the ``msagv fmu simulate`` hook)."""

from __future__ import annotations

import argparse
import importlib.util
import sys

USAGE = """usage: msagv fmu build [--vehicle FILE] -o FILE.fmu [--prefix P] [--initial name=value,...]
       msagv fmu simulate ...   (the closed loop against an FMU; see docs/FMU.md)"""


def main(argv: list[str]) -> int:
    argv = list(argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        return 0
    sub, rest = argv[0], argv[1:]
    if sub == "build":
        return build_main(rest)
    if sub == "simulate":
        return simulate_main(rest)
    print(f"msagv fmu: unknown sub-command '{sub}'\n{USAGE}", file=sys.stderr)
    return 2


def build_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(
        prog="msagv fmu build",
        description="Package the plant as an FMI 2.0 co-simulation FMU (pythonfmu). The FMU "
                    "bundles the plant package and the vehicle; it runs in the importer's "
                    "Python, which needs numpy and numba (see docs/FMU.md).")
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in paper-2axle)")
    ap.add_argument("-o", "--output", metavar="FILE.fmu", required=True, help="the FMU to write")
    ap.add_argument("--prefix", default="",
                    help="put in front of every variable name (e.g. 'agv0.'); the host then "
                         "needs a mapping file")
    ap.add_argument("--initial", metavar="name=value,...",
                    help="start values of the initial-state parameters, e.g. vx=2,phi=0.1")
    a = ap.parse_args(argv)

    from plant.stepping import PlantError, parse_initial
    from plant.vehicle import VehicleError, load_vehicle

    from .build import FmuBuildError, build_fmu

    try:
        vehicle = load_vehicle(a.vehicle)
        initial = parse_initial(a.initial)
        out = build_fmu(a.output, vehicle, prefix=a.prefix, initial=initial)
    except (VehicleError, FileNotFoundError, PlantError, FmuBuildError) as e:
        print(f"msagv fmu build: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({vehicle.name}, {vehicle.n_axles} axles)", file=sys.stderr)
    return 0


# ---- msagv fmu simulate: hook for the closed loop --------------------------------------
def simulate_main(argv: list[str]) -> int:
    """``msagv fmu simulate``: the closed loop (controller.loop) against an FMU plant.

    Not wired yet: the closed loop takes any object with the Plant interface, and
    :class:`fmu_build.host.FmuPlant` is one, so wiring is ``FmuPlant(fmu, mapping=...)``
    passed where ``msagv run`` passes its ``Plant``.
    """
    if importlib.util.find_spec("controller.loop") is None:
        raise SystemExit("msagv fmu simulate: needs the controller (not yet wired)")
    return _simulate_closed_loop(argv)


def _simulate_closed_loop(argv: list[str]) -> int:
    """To be written by the closed loop's owner (see :func:`simulate_main`)."""
    raise SystemExit("msagv fmu simulate: controller.loop exists but is not wired to "
                     "fmu_build.host.FmuPlant yet (fmu_build.cli._simulate_closed_loop)")
