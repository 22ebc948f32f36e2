"""The signals' names, in one place: every encoder, decoder, table, CSV header, FMU
variable and message field list reads them from here (DESIGN.md's signal table).

Wheels are named ``ij`` (axle i from the front, side j: 1 left, 2 right) in the order 11,
12, 21, 22, ...; a per-wheel signal is ``name_ij`` (``delta_11``, ``W_s_21``).
"""

from __future__ import annotations

from .vehicle import Vehicle

# the control period T [s] (the paper's 100 Hz): the one place this number lives; every
# default period of the plant, the controller, the bus, the FMU and the experiments is it
CONTROL_PERIOD = 0.01

# the body's pose and velocity (velocities in the global frame G, eq. 20): the state
# message's fields, the first signals, and the prediction's state (plant.layout X0_*)
BODY_FIELDS = ("x", "y", "phi", "vx", "vy", "r")
# the wear powers [W] and their work [J] by mechanism (eq. 13-15, 28-30), summed over wheels
WEAR_POWER_FIELDS = ("P_s", "P_alpha", "P_t")
WEAR_FIELDS = ("W_s", "W_alpha", "W_t")
WEAR_TOTAL = "W_tw"  # eq. 31: W_s + W_alpha + W_t
# the per-wheel wear work in the state message: arrays in the wheel order (the ``_ij``
# stands for "of every wheel ij"; the signals are W_s_11, W_s_12, ...)
WHEEL_WEAR_FIELDS = tuple(f"{k}_ij" for k in WEAR_FIELDS)
# per wheel: the powers P_s_ij ... [W] and the work W_s_ij ... W_tw_ij [J]
WHEEL_POWERS = WEAR_POWER_FIELDS
WHEEL_WORK = WEAR_FIELDS + (WEAR_TOTAL,)


def wheel_suffixes(n_wheels: int) -> list[str]:
    """``['11', '12', '21', ...]``: the suffixes of ``n_wheels`` wheels (as
    :attr:`plant.vehicle.Vehicle.wheel_names`)."""
    return [f"{i}{j}" for i in range(1, n_wheels // 2 + 1) for j in (1, 2)]


def state_names(vehicle: Vehicle) -> list[str]:
    """Names of the settable initial-state signals (``--initial name=value``)."""
    w = vehicle.wheel_names
    return (list(BODY_FIELDS) + [f"delta_{k}" for k in w]
            + [f"omega_w_{k}" for k in w] + [f"omega_s_{k}" for k in w])


def signal_names(vehicle: Vehicle) -> list[str]:
    """Every signal of DESIGN.md's table, in output order (CSV columns, FMU outputs)."""
    w = vehicle.wheel_names
    names = list(BODY_FIELDS)
    for q in ("delta", "omega_w", "omega_s", "s", "alpha", "Fx", "Fy", "F_N"):
        names += [f"{q}_{k}" for k in w]
    names += list(WEAR_POWER_FIELDS + WEAR_FIELDS) + [WEAR_TOTAL]
    names += wheel_wear_names(vehicle)
    return names


def wheel_wear_names(vehicle: Vehicle) -> list[str]:
    """The per-wheel wear signals, in output order: ``P_s_ij, P_alpha_ij, P_t_ij`` (each
    for every wheel), then ``W_s_ij, W_alpha_ij, W_t_ij, W_tw_ij``. Summed over the wheels
    they are the totals ``P_s`` ... ``W_tw``."""
    w = vehicle.wheel_names
    return [f"{q}_{k}" for q in WHEEL_POWERS + WHEEL_WORK for k in w]


def input_names(vehicle: Vehicle) -> list[str]:
    """The commands, in the FMU's input order: ``omega_w_ij`` then ``omega_s_ij``."""
    w = vehicle.wheel_names
    return [f"omega_w_{k}" for k in w] + [f"omega_s_{k}" for k in w]


# separators a CSV header may use by mistake (msagv's CSV files are comma-separated)
CSV_SEPARATORS = {";": "semicolons", "\t": "tabs", "|": "vertical bars", " ": "spaces"}


def foreign_separator(header: list[str], columns) -> str | None:
    """The separator a CSV's header line (as the csv module split it at commas) uses
    instead of commas, when split at it the header has ``columns``; else None. For the
    one-line error that names the separator rather than 'missing columns'."""
    line = ",".join(header)
    for sep, name in CSV_SEPARATORS.items():
        cols = [c.strip() for c in line.split(sep)]
        if all(c in cols for c in columns):
            return name
    return None
