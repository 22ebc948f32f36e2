"""The tire-wear-aware MPC: ``MPC.step(state, reference) -> Command``.

Knows nothing of processes or transport: it takes a state mapping (the fields of
DESIGN.md's ``state`` message) and a :class:`controller.reference.Reference`, and returns
wheel-speed and steering-rate commands inside the bounds of eq. (27).

One class for every horizon solver: :class:`MPC` holds the horizon problem
(:class:`controller.horizon.Horizon`), the warm start, the reference and the time budget,
and hands each period's problem to its solver (``solver='sa'``, ``'ipopt'``, ``'acados'``,
``'ff'`` or any other entry of :mod:`controller.solvers`). It implements
:class:`controller.interface.Controller`.
"""

from __future__ import annotations

import logging
import math
import time
from typing import Callable, Mapping

import numpy as np

from msagv.plant import layout as lay
from msagv.plant.interface import BODY_FIELDS
from msagv.plant.signals import CONTROL_PERIOD
from msagv.plant.vehicle import Vehicle

from . import solvers
from .adaptation import AdaptOptions, TireAdaptation
from .disturbance import DisturbanceObserver
from .horizon import Horizon
from .interface import Command, ControllerError
from .models import MPCSettings
from .reference import Reference

__all__ = ["MPC", "Command", "ControllerError", "T_CONTROL"]

T_CONTROL = CONTROL_PERIOD  # s, the paper's control period (plant.signals)
BUDGET_SOLVES = 20  # timed warm-up solves (MPC.warmup)
BUDGET_SECONDS = 0.5  # ... for at most this long
BUDGET_CHECK = 100  # during a run, check the solve p99 every this many solves
BUDGET_WINDOW = 500  # ... over the last this many
DIST_MAX_ACCEL = 5.0  # m/s^2: bound of the offset-free disturbance's accelerations (0.5 g)
DIST_MAX_YAW_ACCEL = 2.0  # rad/s^2: ... and of its yaw acceleration

_log = logging.getLogger("msagv.controller")


class MPC:
    """The MPC over a batch prediction model, with any registered horizon solver.

    Parameters
    ----------
    vehicle : the vehicle description (its limits bound every command).
    settings : :class:`MPCSettings` (method, model, policy, horizon, weights, budgets).
    reference : optional default reference for :meth:`step`.
    period : control period T [s] (the time a command is held by the plant).
    solver : the name of a solver in :data:`controller.solvers.SOLVERS` (default 'sa',
        the annealer); its :meth:`check_supported` refuses settings it cannot solve.
    options : the solver's own options (:class:`controller.ipopt.IpoptOptions`,
        :class:`controller.acados_rti.AcadosOptions`; None: its defaults).
    on_solve : optional observer, also settable as the attribute ``on_solve``: called after
        every solve of :meth:`step` as ``on_solve(state, z_prev, command)`` with the state
        mapping given to ``step``, the previous solution ``z_prev`` (the decision vector
        before the solve: the warm start's source; do not modify it) and the returned
        :class:`Command`; the new solution is ``self.z``. Its time is not in ``solve_ms``.

    Attributes: ``name`` (the solver's name), ``horizon`` (the problem every solver
    shares), ``model`` (its prediction model), ``solver`` (the solver object), ``z`` (the
    current solution).
    """

    def __init__(self, vehicle: Vehicle, settings: MPCSettings | None = None,
                 reference: Reference | None = None, period: float = T_CONTROL,
                 on_solve: Callable[[Mapping, np.ndarray, "Command"], None] | None = None,
                 *, solver: str = solvers.DEFAULT_SOLVER, options=None):
        self.vehicle = vehicle
        self.on_solve = on_solve
        self.settings = settings or MPCSettings()
        self.reference = reference
        if not period > 0:
            raise ControllerError("period must be > 0")
        self.period = float(period)
        cls = solvers.solver_class(solver)
        cls.check_supported(self.settings)
        self.name = solver
        self.horizon = Horizon(vehicle, self.settings, self.period)
        self.model = self.horizon.model
        self.nw = vehicle.n_wheels
        self.solver = cls(self.horizon, options)
        self.observer = None  # the offset-free disturbance (settings.offset_free)
        if self.settings.offset_free_on:
            kin = self.settings.model == "kinematic"
            self.observer = DisturbanceObserver(
                self.model, self.period, self.settings.disturbance_tau,
                (1.0, 0.5) if kin else (DIST_MAX_ACCEL, DIST_MAX_YAW_ACCEL))
        self.adaptation = None  # the online tire factors (settings.adapt)
        if self.settings.adapt:
            self.adaptation = TireAdaptation(
                self.model, self.period, AdaptOptions(sigma_v=self.settings.adapt_sigma_v,
                                                       window=self.settings.adapt_window,
                                                       noise=self.settings.adapt_noise))
        self.warmup_solve_ms: list[float] = []
        self._smooth: tuple[Reference, Reference] | None = None  # (given, smoothed)
        self.budget_warnings: list[str] = []
        self.reset()

    # ---- state -------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the warm start and reseed (same seed -> same commands)."""
        self.z = np.zeros(self.horizon.dim)
        self._fresh = True  # no solution yet: the warm start is the plain feed-forward
        self._last = None  # (x0, R) of the last solve, for predicted_poses
        self.solver.reset()
        if self.observer is not None:
            self.observer.reset()
        if self.adaptation is not None:
            self.adaptation.reset()
        self.solve_times_ms: list[float] = []
        self._run_warned = False

    def set_reference(self, reference: Reference) -> None:
        if not isinstance(reference, Reference):
            raise ControllerError("set_reference: expected a Reference")
        self.reference = reference

    def _state_vector(self, state: Mapping) -> tuple[float, np.ndarray]:
        try:
            t = float(state["t"])
            base = [float(state[k]) for k in BODY_FIELDS]
            delta = np.asarray(state["delta"], dtype=float).reshape(-1)
        except KeyError as e:
            raise ControllerError(f"state: missing field {e.args[0]!r}") from None
        except (TypeError, ValueError):
            raise ControllerError("state: fields must be numbers (delta a list)") from None
        if delta.size != self.nw:
            raise ControllerError(f"state: delta must have {self.nw} entries, got {delta.size}")
        x0 = np.empty(lay.x0_size(self.nw))  # (np.r_ cost ~15 us)
        x0[:lay.X0_DELTA] = base
        x0[lay.X0_DELTA:] = delta
        if not (math.isfinite(t) and np.all(np.isfinite(x0))):
            raise ControllerError("state: NaN or inf in the state")
        return t, x0

    # ---- the step ----------------------------------------------------------------------
    def horizon_problem(self, state: Mapping, reference: Reference | None = None):
        """The horizon problem of one solve: ``(x0, R, zprev, warm)`` - the state vector,
        the reference rows at the prediction times (N_p + 1, 6), the previous solution's
        first block (the smoothing term's anchor) and the warm start (the previous solution
        shifted by one period). Shared by every solver."""
        ref = reference if reference is not None else self.reference
        if ref is None:
            raise ControllerError("step: no reference (pass one or call set_reference)")
        if self.settings.ref_smoothing > 0:
            ref = self._smoothed(ref)
        t, x0 = self._state_vector(state)
        if self.adaptation is not None:
            warned, noted = self.adaptation.warning, self.adaptation.notice
            self.adaptation.update(t, x0, state.get("omega_w"))
            if self.adaptation.warning is not None and warned is None:
                _log.warning("%s", self.adaptation.warning)
            if self.adaptation.notice is not None and noted is None:
                _log.info("%s", self.adaptation.notice)
        if self.observer is not None:
            self.observer.update(t, x0)
        s = self.settings
        R = np.ascontiguousarray(ref.sample(t + s.dt * np.arange(s.N_p + 1)))
        if self._fresh:
            self.z = self.horizon.origin(x0, R[0])
            self._fresh = False
        return x0, R, self.z[: self.model.stride].copy(), self.horizon.shifted(self.z)

    def _smoothed(self, ref: Reference) -> Reference:
        """``ref`` smoothed by ``settings.ref_smoothing`` (computed once per reference)."""
        if self._smooth is None or self._smooth[0] is not ref:
            self._smooth = (ref, ref.smoothed(self.settings.ref_smoothing))
        return self._smooth[1]

    def step(self, state: Mapping, reference: Reference | None = None) -> Command:
        """One MPC solve: commands to hold over the next control period."""
        t0 = time.perf_counter()
        x0, R, zprev, warm = self.horizon_problem(state, reference)
        z_prev = self.z
        self.z, cost, iterations = self.solver.solve(x0, R, zprev, warm, t0)
        self._last = (x0, R)
        om_w, om_s = self.horizon.commands(x0, R[0], self.z)
        if self.observer is not None:
            self.observer.commanded(om_w, om_s, R)
        if self.adaptation is not None:
            self.adaptation.commanded(om_w, om_s, R)
        ms = (time.perf_counter() - t0) * 1000.0
        self.solve_times_ms.append(ms)
        self._check_budget()
        cmd = Command(om_w, om_s, ms, cost, iterations)
        if self.on_solve is not None:
            self.on_solve(state, z_prev, cmd)
        return cmd

    def disturbance(self) -> dict | None:
        """The offset-free disturbance estimate now (:meth:`DisturbanceObserver.as_dict`),
        None when ``settings.offset_free`` is off."""
        return None if self.observer is None else self.observer.as_dict()

    def adapted_tires(self) -> dict | None:
        """The online tire factors now (:meth:`TireAdaptation.as_dict`), None without
        ``settings.adapt``."""
        return None if self.adaptation is None else self.adaptation.as_dict()

    def predicted_poses(self) -> np.ndarray | None:
        """The last solve's predicted poses ``(N_p + 1, 3)``: x, y, phi from the state it
        started from (row 0) over the horizon (the controller's own prediction of its
        solution). None before the first solve."""
        if self._last is None:
            return None
        return self.horizon.poses(*self._last, self.z)

    def warmup(self, state: Mapping | None = None) -> float:
        """Compile the kernels (first call) with a throw-away solve and the rollout of
        :meth:`predicted_poses`, then time up to
        :data:`BUDGET_SOLVES` solves from the same state (at most :data:`BUDGET_SECONDS`):
        if their p99 exceeds the control period the controller warns (:meth:`budget`).
        Returns the seconds it took. The warm start and random stream are reset
        afterwards; ``on_solve`` does not see these solves."""
        t0 = time.perf_counter()
        ref = self.reference
        if ref is None:
            from .reference import case1_curve
            ref = case1_curve(15.0)
        st = dict(state) if state is not None else {
            "t": 0.0, **{k: v for k, v in ref.initial_state(self.vehicle).items()
                         if not k.startswith("delta")},
            "delta": [0.0] * self.nw}
        observer, self.on_solve = self.on_solve, None
        try:
            self.step(st, ref)
            self.predicted_poses()  # its rollout compiled too (a node draws the horizon)
            times = []
            t_end = time.perf_counter() + BUDGET_SECONDS
            t = float(st.get("t", 0.0))
            for i in range(BUDGET_SOLVES):
                times.append(self.step(dict(st, t=t + (i + 1) * self.period), ref).solve_ms)
                if time.perf_counter() > t_end:
                    break
        finally:
            self.on_solve = observer
        self.reset()
        self.warmup_solve_ms = times
        p99 = float(np.percentile(times, 99))
        if p99 > 1000.0 * self.period:
            self._budget_warning(
                f"warm-up: solve p99 {p99:.2f} ms over {len(times)} solves exceeds the control "
                f"period of {1000.0 * self.period:g} ms: this controller cannot keep its period "
                f"on this machine (fewer iterations or chains, a shorter horizon, or "
                f"--deadline-ms)")
        return time.perf_counter() - t0

    # ---- the budget ----------------------------------------------------------------------
    def _budget_warning(self, msg: str) -> None:
        self.budget_warnings.append(msg)
        _log.warning("%s", msg)

    def _check_budget(self) -> None:
        """During a run, every BUDGET_CHECK solves: warn (once) when the p99 of the last
        BUDGET_WINDOW solves exceeds the control period."""
        n = len(self.solve_times_ms)
        if n % BUDGET_CHECK or self._run_warned:
            return
        p99 = float(np.percentile(self.solve_times_ms[-BUDGET_WINDOW:], 99))
        if p99 > 1000.0 * self.period:
            self._run_warned = True
            self._budget_warning(
                f"solve p99 {p99:.2f} ms over the last {min(n, BUDGET_WINDOW)} solves exceeds "
                f"the control period of {1000.0 * self.period:g} ms")

    def budget(self) -> dict:
        """The controller's time budget as measured: the control period, the solve-time
        percentiles of the warm-up solves and of the run so far [ms], whether either p99
        exceeds the period, and the warnings given."""
        from .metrics import percentiles

        period = 1000.0 * self.period
        warm = percentiles(self.warmup_solve_ms) if self.warmup_solve_ms else None
        run = percentiles(self.solve_times_ms) if self.solve_times_ms else None
        over = any(p is not None and p["p99"] > period for p in (warm, run))
        return {"period_ms": period, "warmup_solve_ms": warm, "run_solve_ms": run,
                "over_period": bool(over), "warnings": list(self.budget_warnings)}
