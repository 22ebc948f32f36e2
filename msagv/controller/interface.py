"""The controller interface: what a closed loop, the Zenoh controller process, the ROS 2
node and the experiments need of a controller, declared once (as
:class:`plant.interface.PlantInterface` is for plants).

:class:`controller.mpc.MPC` implements :class:`Controller` for every horizon solver of the
registry (:mod:`controller.solvers`: the annealer, IPOPT, acados SQP-RTI, the feed-forward
alone). A controller of another kind (a tracking law, a learned policy) implements the
same few members and runs in every loop unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping, Protocol, runtime_checkable

import numpy as np

from msagv.plant.vehicle import Vehicle


class ControllerError(ValueError):
    """Bad input to a controller (its state is left unchanged)."""


@dataclass(frozen=True)
class Command:
    """One control period's commands and how they were found."""

    omega_w: np.ndarray  # (2n,) rad/s, in [0, omega_w_max]
    omega_s: np.ndarray  # (2n,) rad/s, in [omega_s_min, omega_s_max]
    solve_ms: float  # wall time of the solve
    cost: float  # the cost of the returned solution (NaN: the controller has none)
    iterations: int  # the solver's iterations (0: none)


@runtime_checkable
class Controller(Protocol):
    """A controller with the MPC's interface.

    ``state`` is a mapping with DESIGN.md's ``state`` fields (``t``, the body fields
    :data:`plant.interface.BODY_FIELDS`, ``delta`` in the wheel order 11, 12, 21, ...); a
    bad state raises :class:`ControllerError` and changes nothing.
    """

    name: str  # the solver's registry name ('sa', 'ipopt', 'acados', 'ff', ...)
    vehicle: Vehicle  # whose limits bound every command
    settings: Any  # controller.models.MPCSettings (or the controller's own settings)
    period: float  # s, the time a command is held by the plant
    reference: Any  # controller.reference.Reference or None
    on_solve: Callable[[Mapping, np.ndarray, Command], None] | None

    def step(self, state: Mapping, reference=None) -> Command:
        """Commands to hold over the next control period (``reference``: None uses the
        one set by :meth:`set_reference`)."""

    def reset(self) -> None:
        """Forget every warm start and reseed: the next step behaves as the first."""

    def warmup(self, state: Mapping | None = None) -> float:
        """Compile and time a few solves before a run (then :meth:`reset`); seconds taken."""

    def set_reference(self, reference) -> None:
        """Track ``reference`` from now on."""

    def budget(self) -> dict:
        """The time budget as measured: ``period_ms``, ``warmup_solve_ms``,
        ``run_solve_ms`` (percentile dicts or None), ``over_period``, ``warnings``."""

    def predicted_poses(self) -> np.ndarray | None:
        """The last solve's predicted poses ``(N_p + 1, 3)`` (x, y, phi; row 0 the state
        it started from), None before the first solve or for a controller that predicts
        nothing."""
