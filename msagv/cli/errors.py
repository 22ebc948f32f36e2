"""The errors a command reports in one line with exit code 2 (bad options or input).

Every part raises its own subclass of ValueError for bad input (``VehicleError``,
``ReferenceError``, ``PlantError``, ``ControllerError``, ``ScenarioError``,
``OptionError``, ``SessionError``, ...); a missing file is ``FileNotFoundError``; an FMU
that cannot be hosted is :class:`fmu_build.host.FmuHostError`.
"""

from __future__ import annotations

from msagv.fmu_build.host import FmuHostError

USAGE_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, FmuHostError)
