"""``msagv run``: the in-process closed loop (controller at 100 Hz on the stepping plant).

Also the shared command-line plumbing for choosing a case, a vehicle and MPC settings,
used by ``msagv run``, ``msagv controller``, ``msagv demo`` and ``msagv fmu simulate``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from controller.metrics import format_table
from controller.models import MPCSettings
from controller.reference import ReferenceError, SpeedProfile, from_csv, make_case
from plant.stepping import PlantError, parse_initial
from plant.vehicle import VehicleError, load_vehicle

SOLVERS = ("sa", "ipopt")  # --solver: the annealer (controller.mpc) or IPOPT (controller.ipopt)


def add_case_args(ap: argparse.ArgumentParser, default_case: str = "curve") -> None:
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--case", choices=["curve", "line"], default=None,
                   help=f"the paper's Case 1 (curve) or Case 2 (line) (default: {default_case})")
    g.add_argument("--trajectory", metavar="FILE", help="a t,x,y,phi CSV to track instead")
    ap.add_argument("--speed", metavar="KMH",
                    help="speed in km/h, or a profile 't:kmh,t:kmh,...' (default: 15 curve, 10 line)")
    ap.add_argument("--mass", type=float, metavar="KG", help="override the vehicle's mass")
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in paper-2axle)")
    ap.add_argument("--duration", type=float, metavar="S",
                    help="vehicle time to run (default: the whole reference)")
    ap.add_argument("--initial", metavar="name=value,...",
                    help="override initial-state values (default: start on the reference)")


def add_mpc_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--method", choices=["two", "ntwo"], default="two",
                    help="two: with the wear term (the paper's); ntwo: L = 0")
    ap.add_argument("--model", choices=["mf", "dugoff", "kinematic", "tct"], default="mf",
                    help="prediction model (mf: the paper's; others: the baselines)")
    ap.add_argument("--seed", type=int, default=0, help="annealer seed")
    ap.add_argument("--iterations", type=int, help="annealing iterations per solve")
    ap.add_argument("--chains", type=int, help="annealing chains")
    ap.add_argument("--deadline-ms", type=float,
                    help="wall-clock budget per solve (anytime); default: fixed iterations only")
    ap.add_argument("--threads", type=int, help="numba threads for the rollout (default 1)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="any MPCSettings field, e.g. --set L=0.05,0.05,0.05 --set N_p=12")
    ap.add_argument("--solver", choices=SOLVERS, default="sa",
                    help="horizon solver: sa (simulated annealing, default) or ipopt (CasADi + "
                         "IPOPT, exact derivatives; --model mf only, needs msagv[ipopt]; the "
                         "annealer options are ignored, --deadline-ms is IPOPT's wall-time limit)")


def solver_from_args(a, settings: MPCSettings) -> str:
    """The ``--solver`` of ``a``, checked against ``settings``: ``ValueError`` (a
    ``ControllerError``) with a message if IPOPT is asked for without CasADi or with a
    prediction model other than 'mf'."""
    solver = getattr(a, "solver", None) or "sa"
    if solver not in SOLVERS:
        raise ValueError(f"--solver: expected one of {', '.join(SOLVERS)}, got '{solver}'")
    if solver == "ipopt":
        from controller import ipopt

        ipopt.check_supported(settings)
    return solver


def make_mpc(solver: str, vehicle, settings: MPCSettings, reference, period: float = 0.01):
    """The MPC for ``--solver``: :class:`controller.mpc.MPC` (sa) or
    :class:`controller.ipopt.IpoptMPC` (ipopt), same interface."""
    if solver == "ipopt":
        from controller.ipopt import IpoptMPC

        return IpoptMPC(vehicle, settings, reference, period=period)
    from controller.mpc import MPC

    return MPC(vehicle, settings, reference, period=period)


def settings_from_args(a) -> MPCSettings:
    kw = {"method": a.method, "model": a.model, "seed": a.seed}
    for k in ("iterations", "chains", "threads"):
        if getattr(a, k, None) is not None:
            kw[k] = getattr(a, k)
    if getattr(a, "deadline_ms", None) is not None:
        kw["deadline_ms"] = a.deadline_ms
    base = MPCSettings()
    for item in getattr(a, "set", []) or []:
        if "=" not in item:
            raise ValueError(f"--set: expected NAME=VALUE, got '{item}'")
        k, v = item.split("=", 1)
        k = k.strip()
        if k not in MPCSettings.field_names():
            raise ValueError(f"--set: unknown setting '{k}' (known: {', '.join(MPCSettings.field_names())})")
        cur = getattr(base, k)
        try:
            if isinstance(cur, tuple):
                kw[k] = tuple(type(cur[0])(x) for x in v.split(","))
            elif isinstance(cur, bool):
                kw[k] = v.lower() in ("1", "true", "yes", "on")
            elif cur is None:
                kw[k] = float(v)
            else:
                kw[k] = type(cur)(v)
        except ValueError:
            raise ValueError(f"--set: {k}: cannot parse '{v}'") from None
    return MPCSettings(**kw)


def scenario_from_args(a, default_case: str = "curve", vehicle=None):
    """``(vehicle, reference, initial_state)`` from the case/vehicle options.

    ``vehicle``: use this vehicle instead of loading ``--vehicle`` (e.g. the one inside an
    FMU, or the one a plant serves as its params); ``--mass`` still applies.
    """
    vehicle = load_vehicle(a.vehicle) if vehicle is None else vehicle
    if a.mass is not None:
        vehicle = vehicle.replace(mass=a.mass)
    if a.trajectory:
        if a.speed is not None:
            raise ReferenceError("--speed applies to --case; a --trajectory CSV carries its own timing")
        ref = from_csv(a.trajectory)
        initial = ref.initial_state(vehicle)
    else:
        case = a.case or default_case
        speed = SpeedProfile.parse(a.speed) if a.speed is not None else None
        ref, init = make_case(case, speed)
        initial = init(vehicle)
    initial.update(parse_initial(a.initial))
    return vehicle, ref, initial


def plot_run(log, reference, path, title: str = "") -> None:
    """PNG: path vs reference, tracking errors and wear power over time."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from controller.metrics import wrap_angle

    a = log.arrays()
    t, pose, ref = a["t"], a["pose"], a["ref"]
    W = a["W"]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    dense = reference.sample(np.linspace(reference.t[0], reference.t[-1], 2000))
    ax[0].plot(dense[:, 0], dense[:, 1], "k--", lw=1, label="reference")
    ax[0].plot(pose[:, 0], pose[:, 1], "C0", lw=1.5, label="vehicle")
    ax[0].set_xlabel("x [m]")
    ax[0].set_ylabel("y [m]")
    ax[0].axis("equal")
    ax[0].legend()
    ax[0].set_title("path")
    ax[1].plot(t, 100 * (pose[:, 0] - ref[:, 0]), label="e_x [cm]")
    ax[1].plot(t, 100 * (pose[:, 1] - ref[:, 1]), label="e_y [cm]")
    ax[1].plot(t, np.degrees(wrap_angle(pose[:, 2] - ref[:, 2])), label="e_phi [deg]")
    ax[1].set_xlabel("t [s]")
    ax[1].legend()
    ax[1].set_title("tracking errors")
    if len(t) > 1:
        dt = np.diff(t)
        P = np.diff(W, axis=0) / dt[:, None] / 1000.0
        for i, name in enumerate(("P_s", "P_alpha", "P_t")):
            ax[2].plot(t[:-1], P[:, i], label=f"{name} [kW]")
    ax[2].set_xlabel("t [s]")
    ax[2].legend()
    ax[2].set_title("wear power (mean over each period)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str], prog: str = "msagv run", fmu: bool = False) -> int:
    """``msagv run`` (``fmu=False``) and ``msagv fmu simulate`` (``fmu=True``: the same
    closed loop with fmpy stepping an FMU as the plant)."""
    desc = (__doc__.splitlines()[0] if not fmu else
            "Closed loop with fmpy stepping an FMU (set inputs, doStep 0.01 s, get outputs) "
            "and the MPC in the same process; the same metrics as msagv run.")
    ap = argparse.ArgumentParser(prog=prog, description=desc)
    if fmu:
        from fmu_build.cli import add_fmu_args
        add_fmu_args(ap)
    add_case_args(ap)
    add_mpc_args(ap)
    ap.add_argument("--json", action="store_true", help="print the metrics as one JSON object")
    ap.add_argument("--plot", metavar="FILE", help="write a PNG (path, errors, wear power)")
    ap.add_argument("--log", metavar="FILE", help="write the per-step log as CSV")
    ap.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                    help="progress bar (default: on a terminal for runs > 10 s)")
    a = ap.parse_args(argv)
    from controller.loop import closed_loop
    from plant.stepping import Plant

    errors: tuple = (VehicleError, ReferenceError, PlantError, ValueError, FileNotFoundError)
    plant = None
    try:
        settings = settings_from_args(a)
        solver = solver_from_args(a, settings)
        if fmu:
            from fmu_build.cli import fmu_plant_from_args
            from fmu_build.host import FmuHostError
            errors = errors + (FmuHostError,)
            given = load_vehicle(a.vehicle) if a.vehicle else None
            plant = fmu_plant_from_args(a, given)
            vehicle, ref, initial = scenario_from_args(a, vehicle=plant.vehicle)
            plant.reset(initial)
        else:
            vehicle, ref, initial = scenario_from_args(a)
            plant = Plant(vehicle, initial=initial)
        duration = a.duration if a.duration is not None else ref.duration
        if not duration > 0:
            raise ValueError("--duration must be > 0")
        mpc = make_mpc(solver, vehicle, settings, ref)
        log = closed_loop(plant, mpc, ref, duration, progress=a.progress)
    except errors as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    finally:
        if fmu and plant is not None:
            plant.close()
    m = log.metrics()
    if a.log:
        log.to_csv(a.log)
    if a.plot:
        plot_run(log, ref, a.plot, title=f"{ref.name} {settings.method.upper()} ({settings.model}"
                                        f"{', ipopt' if solver == 'ipopt' else ''})")
    if a.json:
        print(json.dumps(m))
    else:
        where = f"FMU {Path(a.fmu).name}" if fmu else f"{vehicle.name} {vehicle.mass:g} kg"
        how = f"{settings.model}, ipopt" if solver == "ipopt" else settings.model
        print(format_table(m, f"{ref.name}, {settings.method.upper()} ({how}), {where}"))
        if a.plot:
            print(f"  plot       {Path(a.plot)}")
    return 0
