"""The tire-wear-aware MPC: ``MPC.step(state, reference) -> Command``.

Knows nothing of processes or transport: it takes a state mapping (the fields of
DESIGN.md's ``state`` message) and a :class:`controller.reference.Reference`, and returns
wheel-speed and steering-rate commands inside the bounds of eq. (27).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Callable, Mapping

import numba
import numpy as np

from msagv.plant import layout as lay
from msagv.plant.vehicle import Vehicle

from . import rollout as _ro
from .sa_kernel import CompiledAnnealer
from .models import MPCSettings, make_model
from .reference import Reference

T_CONTROL = 0.01  # s, the paper's control period
CARRY_SCALES = True  # each solve starts its chains' step factors where the last one ended
RESTART_EVERY = 5  # the worst quarter of the chains restarts from the best every 5 iterations
BUDGET_SOLVES = 20  # timed warm-up solves (MPC.warmup)
BUDGET_SECONDS = 0.5  # ... for at most this long
BUDGET_CHECK = 100  # during a run, check the solve p99 every this many solves
BUDGET_WINDOW = 500  # ... over the last this many

_log = logging.getLogger("msagv.controller")


class ControllerError(ValueError):
    """Bad input to the controller (its state is left unchanged)."""


@dataclass(frozen=True)
class Command:
    omega_w: np.ndarray  # (2n,) rad/s, in [0, omega_w_max]
    omega_s: np.ndarray  # (2n,) rad/s, in [omega_s_min, omega_s_max]
    solve_ms: float  # wall time of the solve
    cost: float  # best cost found
    iterations: int  # annealing iterations run


class MPC:
    """Simulated-annealing MPC over a batch prediction model.

    Parameters
    ----------
    vehicle : the vehicle description (its limits bound every command).
    settings : :class:`MPCSettings` (method 'two' or 'ntwo', model, horizon, budgets).
    reference : optional default reference for :meth:`step`.
    period : control period T [s] (the time a command is held by the plant).
    on_solve : optional observer, also settable as the attribute ``on_solve``: called after
        every solve of :meth:`step` as ``on_solve(state, z_prev, command)`` with the state
        mapping given to ``step``, the previous solution ``z_prev`` (the decision vector
        before the solve: the warm start's source; do not modify it) and the returned
        :class:`Command`; the new solution is ``self.z``. Its time is not in ``solve_ms``.
    """

    def __init__(self, vehicle: Vehicle, settings: MPCSettings | None = None,
                 reference: Reference | None = None, period: float = T_CONTROL,
                 on_solve: Callable[[Mapping, np.ndarray, "Command"], None] | None = None):
        self.vehicle = vehicle
        self.on_solve = on_solve
        self.settings = settings or MPCSettings()
        self.reference = reference
        if not period > 0:
            raise ControllerError("period must be > 0")
        self.period = float(period)
        self.model = make_model(vehicle, self.settings)
        s = self.settings
        nw = vehicle.n_wheels
        self.nw = nw
        self.lower, self.upper, self.sigma = self.model.box()
        self.Q = np.array(s.Q, dtype=float)
        self.L = np.array(s.effective_L, dtype=float)
        self.R = np.array(s.R, dtype=float)
        self._sa = CompiledAnnealer(self.model, self.Q, self.L, self.R, self.lower, self.upper,
                                    self.sigma, chains=s.chains, iterations=s.iterations,
                                    sigma_final=s.sigma_final, t_start=s.t_start,
                                    t_end=s.t_end, parallel=s.threads > 1, ladder=s.ladder,
                                    adapt_up=s.adapt_up, adapt_down=s.adapt_down,
                                    pool_seed=s.seed,
                                    proposals=max(1, _ro.LANES // s.chains),
                                    restart_every=RESTART_EVERY)
        self.warmup_solve_ms: list[float] = []
        self.budget_warnings: list[str] = []
        self.reset()

    # ---- state -------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the warm start and reseed (same seed -> same commands)."""
        self.rng = np.random.default_rng(self.settings.seed)
        self.z = np.zeros(self.model.dim)
        self._fresh = True  # no solution yet: the warm start is the plain feed-forward
        self._scale = None  # the annealer's step factors: its ladder until a first solve
        self.solve_times_ms: list[float] = []
        self._run_warned = False

    def set_reference(self, reference: Reference) -> None:
        if not isinstance(reference, Reference):
            raise ControllerError("set_reference: expected a Reference")
        self.reference = reference

    def _state_vector(self, state: Mapping) -> tuple[float, np.ndarray]:
        try:
            t = float(state["t"])
            base = [float(state[k]) for k in ("x", "y", "phi", "vx", "vy", "r")]
            delta = np.asarray(state["delta"], dtype=float).reshape(-1)
        except KeyError as e:
            raise ControllerError(f"state: missing field {e.args[0]!r}") from None
        except (TypeError, ValueError):
            raise ControllerError("state: fields must be numbers (delta a list)") from None
        if delta.size != self.nw:
            raise ControllerError(f"state: delta must have {self.nw} entries, got {delta.size}")
        x0 = np.empty(6 + delta.size)  # (np.r_ cost ~15 us)
        x0[:6] = base
        x0[6:] = delta
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
        t, x0 = self._state_vector(state)
        s = self.settings
        R = np.ascontiguousarray(ref.sample(t + s.dt * np.arange(s.N_p + 1)))
        if self._fresh:
            self.z = self.model.origin(x0, R[0], self.period)
            self._fresh = False
        return x0, R, self.z[: self.model.stride].copy(), self._shifted(self.z)

    def step(self, state: Mapping, reference: Reference | None = None) -> Command:
        """One MPC solve: commands to hold over the next control period."""
        t0 = time.perf_counter()
        x0, R, zprev, warm = self.horizon_problem(state, reference)
        z_prev = self.z
        self.z, cost, iterations = self._solve(x0, R, zprev, warm, t0)
        om_w, om_s = self.commands_for(x0, R[0], self.z)
        ms = (time.perf_counter() - t0) * 1000.0
        self.solve_times_ms.append(ms)
        self._check_budget()
        cmd = Command(om_w, om_s, ms, cost, iterations)
        if self.on_solve is not None:
            self.on_solve(state, z_prev, cmd)
        return cmd

    def _solve(self, x0, R, zprev, warm, t0: float) -> tuple[np.ndarray, float, int]:
        """The solver of :meth:`step` (the annealer): ``(z, cost, iterations)`` for the
        horizon problem; ``t0`` is the solve's start (the deadline counts from it)."""
        s = self.settings
        if s.threads > 1:
            numba.set_num_threads(min(s.threads, numba.config.NUMBA_NUM_THREADS))
        deadline = None if s.deadline_ms is None else s.deadline_ms / 1000.0 - (time.perf_counter() - t0)
        origin = None if self.model.policy != "raw" else self.model.origin(x0, R[0], self.period)
        res = self._sa.solve(x0, R, zprev, warm, self.rng, deadline, origin=origin,
                             scale0=self._scale if CARRY_SCALES else None)
        self._scale = self._sa.scale.copy()
        return res.x, res.cost, res.iterations

    def commands_for(self, x0: np.ndarray, ref0: np.ndarray, z: np.ndarray):
        """The policy's commands at state ``x0`` over one control period T (bounded)."""
        om_w = np.empty(self.nw)
        om_s = np.empty(self.nw)
        _ro.commands_from_policy(x0[lay.X0_X:lay.X0_PHI + 1].copy(), x0[lay.X0_DELTA:].copy(),
                                 ref0, np.ascontiguousarray(z), 0, self.nw,
                                 self.model.P, self.model.S, self.model.wx, self.model.wy,
                                 self.period, om_w, om_s)
        return om_w, om_s

    def _shifted(self, z: np.ndarray) -> np.ndarray:
        """Warm start: the previous solution shifted by one control period T.

        Blocks are piecewise constant in time; moving the horizon by T < block length
        moves a fraction T / len_b of block b+1 into block b (linear blend), the last
        block is held.
        """
        s = self.settings
        nb = len(s.blocks)
        Zb = z.reshape(nb, self.model.stride)
        out = Zb.copy()
        for b in range(nb - 1):
            f = min(self.period / (s.blocks[b] * s.dt), 1.0)
            out[b] = (1 - f) * Zb[b] + f * Zb[b + 1]
        return out.reshape(-1)

    def warmup(self, state: Mapping | None = None) -> float:
        """Compile the kernels (first call) with a throw-away solve, then time up to
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


class FeedForward(MPC):
    """The policy with no optimisation at all: every solve returns the plain feed-forward
    (zero offsets; for ``policy='raw'`` the feed-forward's own commands), the simplest
    controller that could win (docs/RESULTS.md). Same interface as :class:`MPC`;
    ``Command.cost`` is NaN and ``iterations`` 0."""

    solver_name = "ff"

    def _solve(self, x0, R, zprev, warm, t0: float) -> tuple[np.ndarray, float, int]:
        return self.model.origin(x0, R[0], self.period), float("nan"), 0
