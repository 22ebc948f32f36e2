"""The simulated annealer as a horizon solver (``--solver sa``, the default).

The compiled kernel is :class:`controller.sa_kernel.CompiledAnnealer` (parallel chains,
each proposing one SIMD tile of moves per iteration); this module binds it to a
:class:`controller.horizon.Horizon` and keeps what carries from one solve to the next:
the random stream (seeded: the same seed gives the same commands) and the chains' step
factors (:data:`CARRY_SCALES`).
"""

from __future__ import annotations

import time

import numba
import numpy as np

from . import rollout as _ro
from .horizon import Horizon, Solution
from .models import MPCSettings
from .sa_kernel import CompiledAnnealer

CARRY_SCALES = True  # each solve starts its chains' step factors where the last one ended
RESTART_EVERY = 5  # the worst quarter of the chains restarts from the best every 5 iterations


class Annealer:
    """Simulated annealing over the decision vector (docs/CONTROLLER.md, "The annealer").

    Uses every annealer field of the settings (chains, iterations, sigma_*, t_*, ladder,
    adapt_*, seed, threads, polish: the Gauss-Newton steps after the annealing,
    deadline_ms: a wall-clock budget per solve, anytime). No
    options of its own (``options`` must be None).
    """

    name = "sa"

    @classmethod
    def check_supported(cls, settings: MPCSettings) -> None:
        """Every prediction model and parametrisation: nothing to refuse."""

    def __init__(self, horizon: Horizon, options=None):
        if options is not None:
            raise ValueError("the annealer takes no options (its settings are MPCSettings')")
        self.horizon = horizon
        self.options = None
        s = horizon.settings
        self.kernel = CompiledAnnealer(
            horizon.model, horizon.Q, horizon.L, horizon.R, horizon.lower, horizon.upper,
            horizon.sigma, chains=s.chains, iterations=s.iterations,
            sigma_final=s.sigma_final, t_start=s.t_start, t_end=s.t_end,
            parallel=s.threads > 1, ladder=s.ladder, adapt_up=s.adapt_up,
            adapt_down=s.adapt_down, pool_seed=s.seed,
            proposals=max(1, _ro.LANES // s.chains), restart_every=RESTART_EVERY,
            polish=s.polish)
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """A fresh random stream (``seed``: the settings' seed unless given) and the
        chains' step factors back to their ladder."""
        self.rng = np.random.default_rng(self.horizon.settings.seed if seed is None else seed)
        self.scale = None  # the chains' step factors: the ladder until a first solve

    def solve(self, x0, R, zprev, warm, t0: float) -> Solution:
        s, h = self.horizon.settings, self.horizon
        if s.threads > 1:
            numba.set_num_threads(min(s.threads, numba.config.NUMBA_NUM_THREADS))
        deadline = (None if s.deadline_ms is None
                    else s.deadline_ms / 1000.0 - (time.perf_counter() - t0))
        origin = None if h.model.policy != "raw" else h.origin(x0, R[0])
        res = self.kernel.solve(x0, R, zprev, warm, self.rng, deadline, origin=origin,
                                scale0=self.scale if CARRY_SCALES else None)
        self.scale = self.kernel.scale.copy()
        # the Gauss-Newton polish of the best point (MPCSettings.polish; 0: none)
        res = self.kernel.polish(x0, R, zprev, res, None if deadline is None else
                                 s.deadline_ms / 1000.0 - (time.perf_counter() - t0))
        return Solution(res.x, res.cost, res.iterations)
