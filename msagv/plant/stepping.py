"""The stepping plant: FMU-style (set inputs, ``do_step(t, h)``, read outputs, reset,
get/set state) over the compiled dynamics, integrated with adaptive Dormand-Prince."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from . import dynamics as dyn
from . import layout as lay
from .interface import PlantError, check_inputs, check_step, saturate, state_message
from .signals import BODY_FIELDS, signal_names, state_names
from .tire import V_EPS_DEFAULT
from .vehicle import Vehicle, default_vehicle

__all__ = ["Plant", "PlantError", "PlantSnapshot"]


@dataclass(frozen=True)
class PlantSnapshot:
    """A copy of the plant's full state (``get_state``/``set_state``)."""

    t: float
    y: np.ndarray
    omega_w: np.ndarray
    omega_s: np.ndarray
    h_next: float


class Plant:
    """The vehicle as a stepping model (FMU co-simulation semantics).

    Parameters
    ----------
    vehicle : Vehicle, optional
        Defaults to the paper's 2-axle vehicle.
    initial : mapping, optional
        Initial values by signal name (``x, y, phi, vx, vy, r, delta_ij``; with actuator
        lags also the actual ``omega_w_ij``/``omega_s_ij``). Others start at 0.
    rtol, atol : float
        Tolerances of the Dormand-Prince integrator (default 1e-8, 1e-9).
    v_eps : float
        Regularisation speed of the slip definitions [m/s], see :mod:`plant.tire`.

    Inputs (held over a step): ``omega_w`` (2n,) wheel speeds [rad/s] and ``omega_s``
    (2n,) steering rates [rad/s]. Commands beyond the actuators' limits saturate at them
    (``omega_w`` in [0, omega_w_max], ``omega_s`` in [omega_s_min, omega_s_max]); a
    negative, non-finite or wrongly shaped command is refused with :class:`PlantError`.
    """

    def __init__(self, vehicle: Vehicle | None = None, initial: Mapping[str, float] | None = None,
                 rtol: float = 1e-8, atol: float = 1e-9, v_eps: float = V_EPS_DEFAULT,
                 max_substeps: int = 100000):
        self.vehicle = vehicle or default_vehicle()
        if not (rtol > 0 and atol > 0 and v_eps > 0):
            raise PlantError("rtol, atol and v_eps must be > 0")
        self.rtol, self.atol = float(rtol), float(atol)
        self.max_substeps = int(max_substeps)
        self._P, self._wx, self._wy = dyn.pack_params(self.vehicle, v_eps)
        self.nw = self.vehicle.n_wheels
        self._initial = dict(initial or {})
        self._names = signal_names(self.vehicle)
        self._index = {n: i for i, n in enumerate(self._names)}
        self._check_initial(self._initial)
        self._aux = np.zeros((self.nw, lay.N_AUX))
        self._stats = np.zeros(2, dtype=np.int64)
        self.steps_accepted = 0
        self.steps_rejected = 0
        self.reset()

    # ---- set-up ----------------------------------------------------------------------
    def _check_initial(self, initial: Mapping[str, float]) -> None:
        allowed = set(state_names(self.vehicle))
        for k, v in initial.items():
            if k not in allowed:
                raise PlantError(f"initial: unknown signal '{k}' (settable: "
                                 f"{', '.join(state_names(self.vehicle))})")
            try:
                fv = float(v)
            except (TypeError, ValueError):
                raise PlantError(f"initial: {k} must be a number, got {v!r}") from None
            if not math.isfinite(fv):
                raise PlantError(f"initial: {k} must be finite, got {v}")
        lim = self.vehicle.limits
        for k in self.vehicle.wheel_names:
            d = float(initial.get(f"delta_{k}", 0.0))
            if not lim.delta_min <= d <= lim.delta_max:
                raise PlantError(f"initial: delta_{k} = {d} outside the steering limits "
                                 f"[{lim.delta_min}, {lim.delta_max}]")
            if float(initial.get(f"omega_w_{k}", 0.0)) < 0:
                raise PlantError(f"initial: omega_w_{k} must be >= 0")

    def reset(self, initial: Mapping[str, float] | None = None) -> None:
        """Back to t = 0 at the initial state (the constructor's, or ``initial``)."""
        if initial is not None:
            initial = dict(initial)
            self._check_initial(initial)
            self._initial = initial
        nw = self.nw
        y = np.zeros(lay.state_size(nw))
        ini = self._initial
        for i, k in enumerate(BODY_FIELDS):
            y[i] = float(ini.get(k, 0.0))
        w = self.vehicle.wheel_names
        for j, k in enumerate(w):
            y[lay.Y_DELTA + j] = float(ini.get(f"delta_{k}", 0.0))
            y[lay.y_omega_w(nw) + j] = float(ini.get(f"omega_w_{k}", 0.0))
            y[lay.y_omega_s(nw) + j] = float(ini.get(f"omega_s_{k}", 0.0))
        self._y = y
        self.t = 0.0
        self._u_w = np.array([float(ini.get(f"omega_w_{k}", 0.0)) for k in w])
        self._u_s = np.zeros(nw)
        self._h = 0.0
        self.steps_accepted = 0
        self.steps_rejected = 0
        self._refresh()

    # ---- inputs ----------------------------------------------------------------------
    def set_inputs(self, omega_w, omega_s) -> None:
        """Set the held commands: wheel speeds and steering rates, each shape (2n,)
        (:func:`plant.interface.check_inputs`, then :func:`plant.interface.saturate`)."""
        w, s = check_inputs(self.vehicle, omega_w, omega_s)
        self._u_w, self._u_s = saturate(self.vehicle, w, s)
        self._refresh()

    @property
    def inputs(self) -> tuple[np.ndarray, np.ndarray]:
        return self._u_w.copy(), self._u_s.copy()

    # ---- stepping --------------------------------------------------------------------
    def do_step(self, t: float, h: float) -> None:
        """Advance from ``t`` (must equal the plant's time) by ``h`` > 0 seconds."""
        check_step(self.t, t, h)
        y = self._y.copy()
        h_next = dyn.integrate(y, self.t, self.t + h, self._u_w, self._u_s, self._P, self._wx,
                               self._wy, self.rtol, self.atol, self._h, self.max_substeps,
                               self._stats)
        if self._stats[0] + self._stats[1] >= self.max_substeps or not np.all(np.isfinite(y)):
            raise PlantError(f"do_step: integration failed at t = {self.t} (substep limit "
                             f"{self.max_substeps} reached or non-finite state); state unchanged")
        self._y = y
        self._h = h_next
        self.t = self.t + h
        self.steps_accepted += int(self._stats[0])
        self.steps_rejected += int(self._stats[1])
        self._refresh()

    def warmup(self) -> None:
        """Compile (or load from numba's cache) the integrator by stepping a copy of the
        state; the plant itself is unchanged. A real-time host calls this before its clock
        starts, so the first period is not spent compiling (~10 ms)."""
        y = self._y.copy()
        stats = np.zeros(2, dtype=np.int64)
        dyn.integrate(y, self.t, self.t + 1e-3, self._u_w, self._u_s, self._P, self._wx,
                      self._wy, self.rtol, self.atol, 0.0, self.max_substeps, stats)

    def close(self) -> None:
        """Nothing to free: the native plant holds only arrays (:class:`PlantInterface`)."""

    def _refresh(self) -> None:
        self._dy = dyn.outputs(self._y, self._u_w, self._u_s, self._P, self._wx, self._wy,
                               self._aux)

    # ---- outputs ---------------------------------------------------------------------
    @property
    def state_vector(self) -> np.ndarray:
        """Copy of the raw state vector (layout in :mod:`plant.dynamics`)."""
        return self._y.copy()

    @property
    def pose(self) -> np.ndarray:
        return self._y[lay.Y_X:lay.Y_PHI + 1].copy()

    @property
    def delta(self) -> np.ndarray:
        return self._y[lay.Y_DELTA:lay.Y_DELTA + self.nw].copy()

    def output_vector(self) -> np.ndarray:
        """All signals, in the order of :func:`signal_names`."""
        nw, y, a = self.nw, self._y, self._aux
        iw = lay.y_wear(nw)
        W = y[iw:iw + lay.N_WEAR]
        P = a[:, lay.AUX_PS:lay.AUX_PT + 1].sum(axis=0)
        Wk = self._wheel_wear()  # (N_WEAR, nw)
        return np.concatenate([
            y[lay.Y_X:lay.Y_R + 1], y[lay.Y_DELTA:lay.Y_DELTA + nw], a[:, lay.AUX_OMEGA_W],
            a[:, lay.AUX_DDELTA], a[:, lay.AUX_S], a[:, lay.AUX_ALPHA], a[:, lay.AUX_FX],
            a[:, lay.AUX_FY], a[:, lay.AUX_FN], P, W, [W.sum()],
            a[:, lay.AUX_PS], a[:, lay.AUX_PALPHA], a[:, lay.AUX_PT],
            Wk.ravel(), Wk.sum(axis=0),
        ])

    def _wheel_wear(self) -> np.ndarray:
        """Each wheel's wear work, shape (N_WEAR, nw): rows W_s, W_alpha, W_t."""
        nw = self.nw
        i0 = lay.y_wheel_wear(nw, 0)
        return self._y[i0:i0 + lay.N_WEAR * nw].reshape(nw, lay.N_WEAR).T

    def outputs(self) -> dict[str, float]:
        """All signals by name (``omega_w_ij``/``omega_s_ij`` are the actual rates)."""
        return dict(zip(self._names, self.output_vector().tolist()))

    def get(self, name: str) -> float:
        try:
            return float(self.output_vector()[self._index[name]])
        except KeyError:
            raise PlantError(f"unknown signal '{name}'") from None

    @property
    def signal_names(self) -> list[str]:
        return list(self._names)

    # ---- state save/restore ----------------------------------------------------------
    def get_state(self) -> PlantSnapshot:
        return PlantSnapshot(self.t, self._y.copy(), self._u_w.copy(), self._u_s.copy(), self._h)

    def set_state(self, snap: PlantSnapshot) -> None:
        if not isinstance(snap, PlantSnapshot) or snap.y.shape != self._y.shape:
            raise PlantError("set_state: snapshot does not belong to this vehicle")
        self.t = snap.t
        self._y = snap.y.copy()
        self._u_w = snap.omega_w.copy()
        self._u_s = snap.omega_s.copy()
        self._h = snap.h_next
        self._refresh()

    def state_message(self) -> dict:
        """The state as DESIGN.md's ``state`` fields (:func:`plant.interface.state_message`)."""
        y, nw = self._y, self.nw
        iw = lay.y_wear(nw)
        return state_message(self.t, y[lay.Y_X:lay.Y_R + 1], y[lay.Y_DELTA:lay.Y_DELTA + nw],
                             self._aux[:, lay.AUX_OMEGA_W], y[iw:iw + lay.N_WEAR],
                             self._wheel_wear())
