"""No optimisation at all (``--solver ff``): the simplest controller that could win.

Every solve returns the policy's plain feed-forward - zero offsets, or for
``policy='raw'`` the feed-forward's own commands (docs/RESULTS.md, the FF rows).
``Command.cost`` is NaN and ``iterations`` 0.
"""

from __future__ import annotations

from .horizon import Horizon, Solution
from .models import MPCSettings


class FeedForward:
    """The feed-forward policy alone, as a horizon solver that never searches."""

    name = "ff"

    @classmethod
    def check_supported(cls, settings: MPCSettings) -> None:
        """Every prediction model and parametrisation (the model is not even used)."""

    def __init__(self, horizon: Horizon, options=None):
        if options is not None:
            raise ValueError("the feed-forward takes no options")
        self.horizon = horizon
        self.options = None

    def reset(self) -> None:
        """Nothing carries over between solves."""

    def solve(self, x0, R, zprev, warm, t0: float) -> Solution:
        return Solution(self.horizon.origin(x0, R[0]), float("nan"), 0)
