"""``msagv vehicle show`` and ``msagv plant replay``."""

from __future__ import annotations

import argparse
import json
import sys

from .stepping import PlantError, parse_initial
from .vehicle import VehicleError, load_vehicle


def vehicle_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="msagv vehicle", description="Show a vehicle description.")
    ap.add_argument("action", choices=["show"])
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in paper-2axle)")
    ap.add_argument("--json", action="store_true", help="print the resolved description as JSON")
    a = ap.parse_args(argv)
    try:
        v = load_vehicle(a.vehicle)
    except (VehicleError, FileNotFoundError) as e:
        print(f"msagv vehicle show: {e}", file=sys.stderr)
        return 2
    d = v.to_dict()
    d["derived"] = {"n_axles": v.n_axles, "n_wheels": v.n_wheels, "normal_load_N": v.normal_load,
                    "wheel_x": v.wheel_x.tolist(), "wheel_y": v.wheel_y.tolist()}
    if a.json:
        print(json.dumps(d, indent=2))
    else:
        print(f"{v.name}: {v.n_axles} axles, {v.mass:g} kg, I_vz {v.yaw_inertia:g} kg m^2, "
              f"r_w {v.wheel_radius:g} m, F_N {v.normal_load:.0f} N per wheel")
        print(f"  axles at x = {list(v.axle_x)} m, wheels at y = +/-{v.half_track:g} m")
        for part in ("longitudinal", "lateral", "dugoff"):
            print(f"  tire.{part}: {d['tire'][part]}")
        print(f"  limits: {d['limits']}")
        print(f"  k_t = {v.steer_loss_kt:g} m; plant options: {d['plant']}")
    return 0


def replay_main(argv: list[str]) -> int:
    from .replay import ReplayError, read_inputs, replay, write_signals

    ap = argparse.ArgumentParser(
        prog="msagv plant replay",
        description="Open-loop replay: held commands from a CSV through the stepping plant.")
    ap.add_argument("--vehicle", metavar="FILE", help="vehicle TOML (default: built-in)")
    ap.add_argument("--inputs", metavar="U.csv", required=True,
                    help="columns t, omega_w_ij, omega_s_ij; row k held until row k+1")
    ap.add_argument("--out", metavar="S.csv", required=True, help="signals at the input times")
    ap.add_argument("--initial", metavar="name=value,...", help="initial state, e.g. vx=5,phi=0.2")
    ap.add_argument("--rtol", type=float, default=1e-8, help="integrator relative tolerance")
    a = ap.parse_args(argv)
    try:
        v = load_vehicle(a.vehicle)
        t, U = read_inputs(a.inputs, v)
        names, S = replay(v, t, U, parse_initial(a.initial), rtol=a.rtol)
    except (VehicleError, FileNotFoundError, ReplayError, PlantError) as e:
        print(f"msagv plant replay: {e}", file=sys.stderr)
        return 2
    write_signals(a.out, names, S)
    print(f"wrote {len(t)} rows x {len(names)} signals to {a.out}", file=sys.stderr)
    return 0
