"""The FMU's variable table: names, causality, variability, units, descriptions, start values.

One function, :func:`fmu_variables`, decides every variable of the plant FMU for a given
vehicle. The build writes the table into the FMU (``resources/msagv_fmu.json``) and the
slave registers exactly those variables; the host (:mod:`fmu_build.host`) and the docs
(``docs/FMU.md``, :func:`variable_table_markdown`) read the same table, so the names in the
model description, the host's mapping and the documentation cannot drift apart.

Names follow DESIGN.md's signal table, with one necessary change: FMI variable names are
unique, and DESIGN.md uses ``omega_w_ij`` / ``omega_s_ij`` both for the commands (inputs)
and for the plant's actual rates (outputs: saturated, lagged, zero at a steering stop).
The inputs keep the names; the actual rates are the outputs ``omega_w_act_ij`` and
``omega_s_act_ij`` (see :data:`ACTUAL_RATE_OUTPUT`).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from typing import Any

from msagv.plant.signals import signal_names, state_names
from msagv.plant.stepping import Plant
from msagv.plant.tire import V_EPS_DEFAULT
from msagv.plant.vehicle import Vehicle

# The FMU's own configuration file in its resources/ (written by the build, read by the
# slave, the host and the driver) and its format. The slave (fmu_build/slave.py) runs as a
# standalone script inside the FMU and cannot import this module: it carries the same two
# values, pinned to these by tests/test_imports.py.
CONFIG_FILE = "msagv_fmu.json"
CONFIG_FORMAT = 1

# Integrator defaults of plant.Plant (kept equal; a test checks them against Plant()).
RTOL_DEFAULT = 1e-8
ATOL_DEFAULT = 1e-9

ROLES = ("input", "output", "vehicle", "initial", "option")

# FMI 2.0 unit definitions used by the FMU (SI base-unit exponents). Dimensionless
# quantities carry no unit attribute.
UNITS: dict[str, dict[str, int]] = {
    "m": {"m": 1},
    "rad": {"rad": 1},
    "s": {"s": 1},
    "kg": {"kg": 1},
    "kg.m2": {"kg": 1, "m": 2},
    "m/s": {"m": 1, "s": -1},
    "rad/s": {"rad": 1, "s": -1},
    "1/rad": {"rad": -1},
    "N": {"kg": 1, "m": 1, "s": -2},
    "N/rad": {"kg": 1, "m": 1, "s": -2, "rad": -1},
    "W": {"kg": 1, "m": 2, "s": -3},
    "J": {"kg": 1, "m": 2, "s": -2},
}

# signal (our name) -> FMU output name, for the two signals whose names the inputs take
ACTUAL_RATE_OUTPUT = {"omega_w": "omega_w_act", "omega_s": "omega_s_act"}

_BODY_SIGNALS = {
    "x": ("m", "x of the centre of mass B in the global frame G"),
    "y": ("m", "y of the centre of mass B in the global frame G"),
    "phi": ("rad", "yaw angle of the body frame B in G"),
    "vx": ("m/s", "velocity of B along x of G (paper eq. 20)"),
    "vy": ("m/s", "velocity of B along y of G (paper eq. 20)"),
    "r": ("rad/s", "yaw rate"),
    "P_s": ("W", "slip-ratio wear power summed over the wheels (paper eq. 13, 16)"),
    "P_alpha": ("W", "slip-angle wear power summed over the wheels (paper eq. 14, 16)"),
    "P_t": ("W", "steering wear power summed over the wheels (paper eq. 15, 16)"),
    "W_s": ("J", "slip-ratio wear work, integrated (paper eq. 28)"),
    "W_alpha": ("J", "slip-angle wear work, integrated (paper eq. 29)"),
    "W_t": ("J", "steering wear work, integrated (paper eq. 30)"),
    "W_tw": ("J", "total wear work W_s + W_alpha + W_t (paper eq. 31)"),
}

# per-wheel signal base -> (unit, description with {w} for the wheel index ij)
_WHEEL_SIGNALS = {
    "delta": ("rad", "steering angle of wheel {w}"),
    "omega_w": ("rad/s", "actual wheel speed of wheel {w}: the command saturated to "
                "[0, omega_w_max], lagged when wheel_lag > 0"),
    "omega_s": ("rad/s", "actual steering rate of wheel {w}: the command saturated to "
                "[omega_s_min, omega_s_max], lagged when steer_lag > 0, 0 at a steering stop"),
    "s": (None, "slip ratio of wheel {w} (paper eq. 10)"),
    "alpha": ("rad", "slip angle of wheel {w} (paper eq. 9)"),
    "Fx": ("N", "longitudinal tire force of wheel {w} in its wheel frame (paper eq. 11)"),
    "Fy": ("N", "lateral tire force of wheel {w} in its wheel frame (paper eq. 12)"),
    "F_N": ("N", "normal load of wheel {w}"),
    "P_s": ("W", "slip-ratio wear power of wheel {w} (paper eq. 13); summed: P_s"),
    "P_alpha": ("W", "slip-angle wear power of wheel {w} (paper eq. 14); summed: P_alpha"),
    "P_t": ("W", "steering wear power of wheel {w} (paper eq. 15); summed: P_t"),
    "W_s": ("J", "slip-ratio wear work of wheel {w}, integrated; summed: W_s"),
    "W_alpha": ("J", "slip-angle wear work of wheel {w}, integrated; summed: W_alpha"),
    "W_t": ("J", "steering wear work of wheel {w}, integrated; summed: W_t"),
    "W_tw": ("J", "total wear work of wheel {w}, W_s_{w} + W_alpha_{w} + W_t_{w}; summed: W_tw"),
}

_INPUTS = {
    "omega_w": ("rad/s", "commanded wheel speed of wheel {w} (>= 0; saturates at omega_w_max)"),
    "omega_s": ("rad/s", "commanded steering rate of wheel {w} (saturates at "
                "[omega_s_min, omega_s_max])"),
}

# vehicle parameter name -> (path in Vehicle.to_dict(), unit, description)
_VEHICLE_PARAMS: list[tuple[str, tuple, str | None, str]] = [
    ("mass", ("mass",), "kg", "gross vehicle mass m"),
    ("yaw_inertia", ("yaw_inertia",), "kg.m2", "yaw moment of inertia I_vz"),
    ("wheel_radius", ("wheel_radius",), "m", "wheel radius r_w"),
    ("half_track", ("half_track",), "m", "lateral wheel offset: wheels at y = +/-half_track"),
    ("steer_loss_kt", ("steer_loss_kt",), "m", "steering wear coefficient k_t (paper eq. 15)"),
    ("tire_longitudinal_B", ("tire", "longitudinal", "B"), None, "Magic Formula B over slip ratio"),
    ("tire_longitudinal_C", ("tire", "longitudinal", "C"), None, "Magic Formula C over slip ratio"),
    ("tire_longitudinal_mu", ("tire", "longitudinal", "mu"), None,
     "longitudinal peak friction coefficient (D = mu F_N)"),
    ("tire_longitudinal_E", ("tire", "longitudinal", "E"), None, "Magic Formula E over slip ratio"),
    ("tire_lateral_B", ("tire", "lateral", "B"), "1/rad", "Magic Formula B over slip angle"),
    ("tire_lateral_C", ("tire", "lateral", "C"), None, "Magic Formula C over slip angle"),
    ("tire_lateral_mu", ("tire", "lateral", "mu"), None,
     "lateral peak friction coefficient (D = mu F_N)"),
    ("tire_lateral_E", ("tire", "lateral", "E"), None, "Magic Formula E over slip angle"),
    ("omega_s_min", ("limits", "omega_s_min"), "rad/s", "lowest steering rate"),
    ("omega_s_max", ("limits", "omega_s_max"), "rad/s", "highest steering rate"),
    ("omega_w_max", ("limits", "omega_w_max"), "rad/s", "highest wheel speed"),
    ("delta_min", ("limits", "delta_min"), "rad", "lower steering stop"),
    ("delta_max", ("limits", "delta_max"), "rad", "upper steering stop"),
    ("cg_height", ("plant", "cg_height"), "m",
     "centre-of-gravity height; > 0 turns on quasi-static load transfer"),
    ("wheel_lag", ("plant", "wheel_lag"), "s", "wheel-speed tracking time constant (0 = ideal)"),
    ("steer_lag", ("plant", "steer_lag"), "s", "steering-rate tracking time constant (0 = ideal)"),
    ("combined_slip", ("plant", "combined_slip"), None,
     "1: combined-slip tire forces (plant.tire.combined_slip_weights), 0: off"),
]

_OPTIONS = [
    ("rtol", RTOL_DEFAULT, None, "relative tolerance of the plant's Dormand-Prince integrator"),
    ("atol", ATOL_DEFAULT, None, "absolute tolerance of the plant's Dormand-Prince integrator"),
    ("v_eps", V_EPS_DEFAULT, "m/s", "regularisation speed of the slip definitions (plant.tire)"),
]

_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*\Z")


@dataclass(frozen=True)
class FmuVariable:
    """One FMU variable.

    name : the FMU variable name (with the build's prefix).
    role : input | output | vehicle | initial | option.
    key : our name: the input or signal name (``plant.signal_names``), the vehicle
        parameter name, the state name of an initial value, or the option name.
    path : for role ``vehicle``, the key path into ``Vehicle.to_dict()`` (an int indexes
        ``axle_x``).
    """

    name: str
    role: str
    key: str
    causality: str
    variability: str
    initial: str | None
    unit: str | None
    description: str
    start: float
    path: tuple = field(default=())

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["path"] = list(self.path)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "FmuVariable":
        d = dict(d)
        d["path"] = tuple(d.get("path", ()))
        return cls(**d)


def output_name(signal: str) -> str:
    """Our FMU's output name of a plant signal (``omega_w_11`` -> ``omega_w_act_11``)."""
    for base, out in ACTUAL_RATE_OUTPUT.items():
        if signal.startswith(base + "_") and signal[len(base) + 1:].isdigit():
            return out + signal[len(base):]
    return signal


def signal_meta(vehicle: Vehicle) -> dict[str, tuple[str | None, str]]:
    """(unit, description) of every plant signal of ``vehicle``, by signal name."""
    meta = dict(_BODY_SIGNALS)
    for w in vehicle.wheel_names:
        for base, (unit, text) in _WHEEL_SIGNALS.items():
            meta[f"{base}_{w}"] = (unit, text.format(w=w))
    return meta


def get_path(d: dict, path: tuple) -> Any:
    for p in path:
        d = d[p]
    return d


def set_path(d: dict, path: tuple, value: Any) -> None:
    for p in path[:-1]:
        d = d[p]
    d[path[-1]] = value


def vehicle_paths(vehicle: Vehicle) -> list[tuple[str, tuple, str | None, str]]:
    """(parameter name, path, unit, description) of every vehicle parameter."""
    rows = []
    for name, path, unit, text in _VEHICLE_PARAMS:
        rows.append((name, path, unit, text))
        if name == "half_track":
            for i in range(vehicle.n_axles):
                rows.append((f"axle_x_{i + 1}", ("axle_x", i), "m",
                             f"x of axle {i + 1} in the body frame (axles front first)"))
        if name == "tire_lateral_E":  # the prediction models' own (plant.model_params)
            rows += [(f"tire_{pv.spec.section}_{p.name}", ("tire", pv.spec.section, p.name),
                      p.unit, f"{p.doc} (controller baseline only; unused by the plant)")
                     for pv in vehicle.model_params for p in pv.spec.params]
    return rows


class VariableTableError(ValueError):
    """The vehicle or prefix cannot be expressed as FMU variables; the message says why."""


def fmu_variables(vehicle: Vehicle, prefix: str = "",
                  initial: dict[str, float] | None = None,
                  output_start: bool = True) -> list[FmuVariable]:
    """Every variable of the plant FMU for ``vehicle``, in value-reference order.

    Inputs first (commands), then outputs (every signal of ``plant.signal_names``,
    ``initial="exact"`` as ``fmpy validate`` requires), then the vehicle's parameters
    (``tunable``: a change takes effect at the next ``doStep``, the state is kept), the
    initial state ``<state>_0`` and the integrator options (``fixed``: they take effect
    at ``exitInitializationMode``).

    ``prefix`` is put in front of every name (to build an FMU whose names differ from
    ours, e.g. to test a mapping). ``initial`` gives the start values of ``<state>_0``.
    With ``output_start`` the outputs' start values are those of a native
    :class:`plant.Plant` at the initial state with zero commands (what the FMU reports
    after initialization); without, they are 0 (cheaper; for name look-ups only).
    Raises :class:`VariableTableError` for a signal without a unit/description or a name
    that is not a valid FMI structured name.
    """
    initial = dict(initial or {})
    states = state_names(vehicle)
    unknown = sorted(set(initial) - set(states))
    if unknown:
        raise VariableTableError(f"initial: unknown state '{unknown[0]}' "
                                 f"(settable: {', '.join(states)})")
    out: list[FmuVariable] = []
    meta = signal_meta(vehicle)
    for base, (unit, text) in _INPUTS.items():
        for w in vehicle.wheel_names:
            out.append(FmuVariable(prefix + f"{base}_{w}", "input", f"{base}_{w}", "input",
                                   "continuous", None, unit, text.format(w=w), 0.0))
    starts: dict[str, float] = {}
    if output_start:
        starts = Plant(vehicle, initial=initial).outputs()
    for sig in signal_names(vehicle):
        if sig not in meta:
            raise VariableTableError(
                f"plant signal '{sig}' has no unit/description in fmu_build.variables; "
                f"add it there before building an FMU")
        unit, text = meta[sig]
        out.append(FmuVariable(prefix + output_name(sig), "output", sig, "output",
                               "continuous", "exact", unit, text, starts.get(sig, 0.0)))
    vd = vehicle.to_dict()
    for name, path, unit, text in vehicle_paths(vehicle):
        out.append(FmuVariable(prefix + name, "vehicle", name, "parameter", "tunable", "exact",
                               unit, text, float(get_path(vd, path)), path))
    for s in states:
        unit, text = meta[s]
        out.append(FmuVariable(prefix + f"{s}_0", "initial", s, "parameter", "fixed", "exact",
                               unit, f"initial value: {text}", float(initial.get(s, 0.0))))
    for name, value, unit, text in _OPTIONS:
        out.append(FmuVariable(prefix + name, "option", name, "parameter", "fixed", "exact",
                               unit, text, float(value)))
    seen: set[str] = set()
    for v in out:
        if not _IDENT.match(v.name):
            raise VariableTableError(
                f"variable name '{v.name}' is not a valid FMI structured name (identifiers "
                f"of letters, digits and '_' not starting with a digit, joined by '.')")
        if v.name in seen:
            raise VariableTableError(f"variable name '{v.name}' occurs twice")
        seen.add(v.name)
        if v.unit is not None and v.unit not in UNITS:
            raise VariableTableError(f"variable '{v.name}': unit '{v.unit}' not in UNITS")
    return out


def variable_table_markdown(vehicle: Vehicle, prefix: str = "") -> str:
    """The variable list as a Markdown table (name, causality, variability, unit, start,
    description), as printed in docs/FMU.md for the built-in vehicle."""
    lines = ["| name | causality | variability | unit | start | description |",
             "|---|---|---|---|---|---|"]
    for v in fmu_variables(vehicle, prefix):
        lines.append(f"| `{v.name}` | {v.causality} | {v.variability} | {v.unit or '-'} | "
                     f"{v.start:g} | {v.description} |")
    return "\n".join(lines) + "\n"
