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
def add_fmu_args(ap: argparse.ArgumentParser) -> None:
    """The options that choose an FMU as the plant (for ``msagv fmu simulate`` and the
    bridge): the FMU, a name mapping file and parameter values."""
    ap.add_argument("fmu", metavar="FILE.fmu", help="an FMI 2.0 co-simulation FMU")
    ap.add_argument("--map", metavar="FILE", dest="fmu_map",
                    help="name mapping (TOML: [map] our_name = \"their_name\", optional "
                         "prefix); see docs/FMU.md")
    ap.add_argument("--param", metavar="name=value,...", dest="fmu_params",
                    help="FMU parameters by our names, e.g. mass=16000,tire_lateral_mu=0.6")


def fmu_plant_from_args(a: argparse.Namespace, vehicle=None, initial=None):
    """An :class:`fmu_build.host.FmuPlant` from :func:`add_fmu_args`' options. ``vehicle``
    None: the FMU's own (ours) -- a foreign FMU needs it given."""
    from plant.stepping import parse_initial

    from .host import FmuPlant

    params = parse_initial(a.fmu_params)  # the same name=value,... syntax and checks
    return FmuPlant(a.fmu, vehicle, mapping=a.fmu_map, parameters=params, initial=initial)


def simulate_main(argv: list[str]) -> int:
    """``msagv fmu simulate FILE.fmu [msagv run's options]``: the closed loop with fmpy
    stepping the FMU (through :class:`fmu_build.host.FmuPlant`) and the MPC in the same
    process; the same metrics as ``msagv run`` (the loop and options are msagv run's)."""
    from bridge.run_cmd import main as run_main

    return run_main(argv, prog="msagv fmu simulate", fmu=True)
