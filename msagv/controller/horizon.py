"""The horizon problem every MPC solver shares, and the interface of a solver.

One configuration of the MPC (vehicle, :class:`controller.models.MPCSettings`, control
period) defines one horizon problem (paper eq. 22-27): the decision vector ``z`` (the move
blocks' offsets, or the twist, or the raw commands: ``settings.policy``) inside its box,
pushed through the policy and the prediction model, scored by the cost (tracking, wear
term, regularisation). :class:`Horizon` holds that problem once - the model, the box, the
weights, the exact cost of candidates, the warm start's shift and the commands of a
solution - so that every solver (:mod:`controller.solvers`) solves the *same* problem and
is scored by the *same* function.

A solver is a class with the members of :class:`HorizonSolver`; it is built with the
horizon (``Solver(horizon, options)``) and answers one problem per control period.
"""

from __future__ import annotations

from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable

import numpy as np

from msagv.plant import layout as lay
from msagv.plant.vehicle import Vehicle

from . import rollout as _ro
from .interface import ControllerError
from .models import MPCSettings, make_model


class Solution(NamedTuple):
    """A solver's answer: the decision vector, its cost, the solver's iterations."""

    z: np.ndarray
    cost: float
    iterations: int


class Horizon:
    """The horizon problem of one MPC configuration (see the module docstring).

    Attributes: ``vehicle``, ``settings``, ``period``, ``model`` (the prediction model,
    :func:`controller.models.make_model`), ``nw`` (wheels), ``dim`` (decision variables),
    ``lower``/``upper`` (the box of ``z``), ``sigma`` (the annealer's initial proposal
    scales), ``Q``/``L``/``R`` (the cost's weights as the kernels take them: ``L`` is
    :attr:`MPCSettings.effective_L`).
    """

    def __init__(self, vehicle: Vehicle, settings: MPCSettings, period: float):
        if not period > 0:
            raise ControllerError("period must be > 0")
        self.vehicle = vehicle
        self.settings = settings
        self.period = float(period)
        self.model = make_model(vehicle, settings)
        self.nw = vehicle.n_wheels
        self.dim = self.model.dim
        self.lower, self.upper, self.sigma = self.model.box()
        self.Q = np.array(settings.Q, dtype=float)
        self.L = np.array(settings.effective_L, dtype=float)
        self.R = np.array(settings.R, dtype=float)
        self._bufs: dict[int, tuple] = {}  # batch size -> (rollout buffers, costs)

    def costs(self, x0: np.ndarray, R: np.ndarray, Z: np.ndarray, zprev: np.ndarray
              ) -> np.ndarray:
        """The cost of each row of ``Z`` (B, dim): the controller's prediction
        (:meth:`PredictionModel.rollout`) scored by :func:`controller.rollout.batch_cost`
        (eq. 22-26 with the true |.| of the wear powers, plus the regularisation R). Every
        solver's reported cost is this function, so solvers compare on one scale."""
        Z = np.ascontiguousarray(Z, dtype=float)
        if Z.ndim == 1:
            Z = Z[None, :]
        b = self._bufs.get(Z.shape[0])
        if b is None:
            b = self._bufs[Z.shape[0]] = (self.model.allocate(Z.shape[0]), np.empty(Z.shape[0]))
        buf, out = b
        r = self.model.rollout(x0, R, Z, out=buf)
        _ro.batch_cost(r.poses, r.wear, R, Z, np.ascontiguousarray(zprev), self.Q, self.L,
                       self.R, self.model.stride, self.model.nsplit, out)
        return out.copy()

    def cost(self, x0, R, z, zprev) -> float:
        """The cost of one decision vector ``z`` (:meth:`costs`)."""
        return float(self.costs(x0, R, np.asarray(z, float)[None, :], zprev)[0])

    def clip(self, z: np.ndarray) -> np.ndarray:
        """``z`` inside the box [lower, upper]."""
        return np.minimum(np.maximum(z, self.lower), self.upper)

    def better_start(self, x0, R, zprev, warm) -> tuple[np.ndarray, float]:
        """The better (by :meth:`costs`) of the shifted previous solution and the plain
        feed-forward (zero offsets), both clipped to the box: the start of the gradient
        solvers (the annealer's chains 0 and 1 start from the same two)."""
        warm = self.clip(warm)
        zero = self.clip(np.zeros_like(warm))
        J = self.costs(x0, R, np.stack([warm, zero]), zprev)
        return (zero, float(J[1])) if J[1] < J[0] else (warm, float(J[0]))

    def commands(self, x0: np.ndarray, ref0: np.ndarray, z: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The policy's commands at state ``x0`` over one control period (bounded by
        eq. 27's limits): ``(omega_w, omega_s)``."""
        m = self.model
        om_w = np.empty(self.nw)
        om_s = np.empty(self.nw)
        _ro.commands_from_policy(x0[lay.X0_X:lay.X0_PHI + 1].copy(), x0[lay.X0_DELTA:].copy(),
                                 ref0, np.ascontiguousarray(z), 0, self.nw, m.P, m.S, m.wx,
                                 m.wy, self.period, om_w, om_s)
        return om_w, om_s

    def shifted(self, z: np.ndarray) -> np.ndarray:
        """Warm start: the solution ``z`` shifted by one control period T.

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

    def origin(self, x0: np.ndarray, ref0: np.ndarray) -> np.ndarray:
        """The plain feed-forward's decision vector at ``x0``
        (:meth:`PredictionModel.origin`)."""
        return self.model.origin(x0, ref0, self.period)

    def poses(self, x0: np.ndarray, R: np.ndarray, z: np.ndarray) -> np.ndarray:
        """The poses ``(N_p + 1, 3)`` that ``z`` predicts from ``x0`` (row 0: x0's pose)."""
        r = self.model.rollout(x0, R, np.asarray(z, float)[None, :])
        return np.vstack([x0[lay.X0_X:lay.X0_PHI + 1], r.poses[0]])


@runtime_checkable
class HorizonSolver(Protocol):
    """A solver of the horizon problem (registered in :mod:`controller.solvers`).

    ``Solver(horizon, options=None)`` builds it for one :class:`Horizon` (``options``: the
    solver's own options object, None for its defaults); :meth:`check_supported` refuses
    settings it cannot solve before anything is built.
    """

    name: ClassVar[str]

    @classmethod
    def check_supported(cls, settings: MPCSettings) -> None:
        """Raise :class:`ControllerError` naming why ``settings`` cannot be solved (a
        missing library, an unsupported prediction model or parametrisation)."""

    def reset(self) -> None:
        """Forget what the last solves left (random stream, step sizes, iterates)."""

    def solve(self, x0: np.ndarray, R: np.ndarray, zprev: np.ndarray, warm: np.ndarray,
              t0: float) -> Solution:
        """One solve from the state vector ``x0``, against the reference rows ``R``
        (N_p + 1, 6), with ``zprev`` the previous solution's first block (the smoothing
        term's anchor) and ``warm`` the previous solution shifted by one period; ``t0`` is
        the solve's start (``time.perf_counter()``; a deadline counts from it)."""

    options: Any
