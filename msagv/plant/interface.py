"""The plant interface: what a closed loop, the Zenoh plant process and the FMU host need of
a plant, declared once, with the input checks and the state message every plant shares.

:class:`plant.stepping.Plant` (the built-in stepping plant) and
:class:`fmu_build.host.FmuPlant` (any FMI 2.0 co-simulation FMU stepped by fmpy) implement
:class:`PlantInterface`; both validate commands with :func:`check_inputs` and saturate them
with :func:`saturate`, check a step with :func:`check_step`, and build DESIGN.md's
``state`` fields with :func:`state_message`.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np

from .signals import BODY_FIELDS, WEAR_FIELDS, WHEEL_WEAR_FIELDS
from .vehicle import Vehicle

__all__ = ["PlantError", "PlantInterface", "check_inputs", "saturate", "check_step",
           "state_message", "BODY_FIELDS", "WEAR_FIELDS", "WHEEL_WEAR_FIELDS"]


class PlantError(ValueError):
    """Bad input to a plant (the plant's state is left unchanged)."""


@runtime_checkable
class PlantInterface(Protocol):
    """A plant with FMU co-simulation semantics (inputs held over a step).

    ``vehicle`` is the vehicle it simulates (the controller needs its geometry and limits);
    ``t`` its time [s]. Inputs are ``omega_w`` and ``omega_s`` of shape (2n,) in the wheel
    order 11, 12, 21, ...; a bad command raises :class:`PlantError` and changes nothing.
    """

    vehicle: Vehicle
    t: float

    def set_inputs(self, omega_w, omega_s) -> None:
        """Hold these commands from now on (validated, then saturated at the limits)."""

    @property
    def inputs(self) -> tuple[np.ndarray, np.ndarray]:
        """The held (saturated) commands."""

    def do_step(self, t: float, h: float) -> None:
        """Advance from ``t`` (the plant's time) by ``h`` > 0 seconds."""

    def outputs(self) -> dict[str, float]:
        """Every signal it provides, by DESIGN.md's signal name."""

    def state_message(self) -> dict:
        """DESIGN.md's ``state`` fields (without ``v``/``seq``): :func:`state_message`."""

    def reset(self, initial: Mapping[str, float] | None = None) -> None:
        """Back to t = 0 at the initial state (the constructor's, or ``initial``)."""

    def get_state(self) -> Any:
        """An opaque snapshot of the whole state (time, integrator state, held inputs)."""

    def set_state(self, snapshot: Any) -> None:
        """Restore a snapshot taken by :meth:`get_state` of this plant."""

    def warmup(self) -> None:
        """Get ready to step in real time (compile, load, allocate) without changing the
        state: a real-time host calls it before its clock starts. May do nothing."""

    def close(self) -> None:
        """Free what the plant holds (an FMU instance, files); it is not stepped after.
        May do nothing."""


def check_inputs(vehicle: Vehicle, omega_w, omega_s) -> tuple[np.ndarray, np.ndarray]:
    """Validate commands: shapes (2n,), finite, ``omega_w >= 0``. Returns them as float
    arrays (not yet saturated); raises :class:`PlantError` naming the problem."""
    nw = vehicle.n_wheels
    try:
        w = np.array(omega_w, dtype=float).reshape(-1)
        s = np.array(omega_s, dtype=float).reshape(-1)
    except (TypeError, ValueError) as e:
        raise PlantError(f"inputs: commands must be numbers ({e})") from None
    if w.shape != (nw,) or s.shape != (nw,):
        raise PlantError(f"inputs: expected {nw} wheel speeds and {nw} steering "
                         f"rates, got {w.size} and {s.size}")
    if not (np.all(np.isfinite(w)) and np.all(np.isfinite(s))):
        raise PlantError("inputs: commands must be finite (got NaN or inf)")
    if np.any(w < 0):
        raise PlantError(f"inputs: omega_w must be >= 0 (wheel "
                         f"{vehicle.wheel_names[int(np.argmin(w))]} got {w.min()})")
    return w, s


def saturate(vehicle: Vehicle, omega_w: np.ndarray, omega_s: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Commands beyond the actuators' limits saturate at them (eq. 27's bounds):
    ``omega_w`` in [0, omega_w_max], ``omega_s`` in [omega_s_min, omega_s_max]."""
    lim = vehicle.limits
    return (np.minimum(omega_w, lim.omega_w_max),
            np.clip(omega_s, lim.omega_s_min, lim.omega_s_max))


def check_step(t_plant: float, t: float, h: float) -> None:
    """A co-simulation step must start at the plant's time and be finite and positive."""
    if not (math.isfinite(h) and h > 0):
        raise PlantError(f"do_step: step size must be finite and > 0, got {h}")
    if not math.isfinite(t) or abs(t - t_plant) > 1e-9 * max(1.0, abs(t_plant)):
        raise PlantError(f"do_step: t = {t} does not match the plant's time {t_plant}")




def state_message(t: float, body: Sequence[float], delta: Sequence[float],
                  omega_w: Sequence[float], wear: Sequence[float] | None = None,
                  wheel_wear: Sequence[Sequence[float]] | None = None) -> dict:
    """DESIGN.md's ``state`` fields (without ``v``/``seq``): ``t``, the body's pose and
    velocity ``x, y, phi, vx, vy, r`` (velocities in G), ``delta`` and the actual
    ``omega_w`` (lists in the wheel order), the wear work ``W_s, W_alpha, W_t`` when
    the plant provides it, and each wheel's ``W_s_ij, W_alpha_ij, W_t_ij`` (lists in the
    wheel order; ``wheel_wear``: three rows of 2n) when it provides those."""
    msg = {"t": float(t)}
    for k, v in zip(BODY_FIELDS, body):
        msg[k] = float(v)
    msg["delta"] = [float(v) for v in delta]
    msg["omega_w"] = [float(v) for v in omega_w]
    if wear is not None:
        for k, v in zip(WEAR_FIELDS, wear):
            msg[k] = float(v)
    if wheel_wear is not None:
        for k, row in zip(WHEEL_WEAR_FIELDS, wheel_wear):
            msg[k] = [float(v) for v in row]
    return msg
