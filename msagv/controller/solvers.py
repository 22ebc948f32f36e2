"""The horizon solvers, in one table: the scenario, the command line's ``--solver``
choices, the experiments and the controller processes all read :data:`SOLVERS`.

Each entry names the module and class of a solver (a
:class:`controller.horizon.HorizonSolver`) and says in one line what it is. Modules are
imported on first use, so a solver whose library is missing (CasADi, acados) costs nothing
until it is asked for, and then fails with its own clear message.

Adding a solver is one module and one line (docs/ARCHITECTURE.md, "Adding a solver"):
write the class, then add its entry here. From outside the package: one line in your own
package's ``pyproject.toml``,

    [project.entry-points."msagv.solvers"]
    mine = "mypackage.mymodule:MySolver"

(every ``msagv`` command then offers ``--solver mine``), or ``register("mine", "mypackage.mymodule:MySolver", "what it is")`` in a
program of your own.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import logging
from dataclasses import dataclass

from .interface import ControllerError
from .models import MPCSettings


@dataclass(frozen=True)
class SolverEntry:
    """One registered solver: ``target`` is ``"module:Class"``; ``help`` one line."""

    target: str
    help: str

    def load(self) -> type:
        module, _, cls = self.target.partition(":")
        return getattr(importlib.import_module(module), cls)


SOLVERS: dict[str, SolverEntry] = {
    "sa": SolverEntry("msagv.controller.annealer:Annealer",
                      "simulated annealing (every prediction model and parametrisation)"),
    "ipopt": SolverEntry("msagv.controller.ipopt:Ipopt",
                         "CasADi + IPOPT, exact derivatives (--model mf, --policy offsets; "
                         "needs msagv[ipopt]; the annealer options are ignored, --deadline-ms "
                         "is IPOPT's wall-time limit)"),
    "acados": SolverEntry("msagv.controller.acados_rti:Acados",
                          "acados SQP-RTI: one Gauss-Newton iteration per period, compiled "
                          "(--model mf, --policy offsets; needs comma-deps-acados installed "
                          "apart, see docs/CONTROLLER.md)"),
    "ff": SolverEntry("msagv.controller.feedforward:FeedForward",
                      "no optimisation: the feed-forward policy alone"),
}
DEFAULT_SOLVER = "sa"
ENTRY_POINTS = "msagv.solvers"  # the entry-point group of solvers from other packages

_log = logging.getLogger("msagv.controller")


def names() -> tuple[str, ...]:
    """The registered solvers' names, in the table's order."""
    return tuple(SOLVERS)


def register(name: str, target: str, help: str) -> None:
    """Add a solver under ``name`` (``target``: ``"module:Class"``); a name already taken
    is refused."""
    if not name or not isinstance(name, str) or not name.replace("-", "").isalnum():
        raise ValueError(f"solver name: letters, digits and '-' only, got {name!r}")
    if name in SOLVERS:
        raise ValueError(f"solver '{name}' is already registered ({SOLVERS[name].target})")
    if ":" not in target:
        raise ValueError(f"solver target: expected 'module:Class', got {target!r}")
    SOLVERS[name] = SolverEntry(target, help)


def solver_class(name: str) -> type:
    """The class of solver ``name``; :class:`ControllerError` for an unknown name."""
    entry = SOLVERS.get(name)
    if entry is None:
        raise ControllerError(f"solver: expected one of {', '.join(SOLVERS)}, got '{name}'")
    return entry.load()


def check_supported(name: str, settings: MPCSettings) -> None:
    """Raise :class:`ControllerError` unless solver ``name`` can solve the MPC of
    ``settings`` (its library installed, its prediction model and parametrisation)."""
    solver_class(name).check_supported(settings)


def _plugins() -> None:
    """Add the solvers other installed packages declare under :data:`ENTRY_POINTS` (a
    name already taken is skipped with a warning: ours are not replaced)."""
    try:
        eps = importlib.metadata.entry_points(group=ENTRY_POINTS)
    except Exception as e:  # a broken installation's metadata
        _log.warning("solver plugins not read: %s", e)
        return
    for ep in eps:
        if ep.name in SOLVERS:
            _log.warning("solver plugin '%s' (%s) ignored: the name is taken", ep.name, ep.value)
            continue
        dist = ep.dist.name if ep.dist is not None else "another package"
        SOLVERS[ep.name] = SolverEntry(ep.value, f"{ep.value}, from {dist}")


_plugins()
