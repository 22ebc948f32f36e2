"""``msagv``: tire-wear-aware trajectory tracking for multi-axle swerve-drive AGVs.

The import path is the file path: ``msagv/plant/`` (the vehicle), ``msagv/controller/`` (the
MPC), ``msagv/bridge/`` (Zenoh transport and the processes), ``msagv/fmu_build/`` (the FMU),
``msagv/experiments/``, ``msagv/benchmarks/``, ``msagv/ros2/`` and ``msagv/cli/`` (the command
line: :mod:`msagv.cli` dispatches, :mod:`msagv.cli.args` holds the shared option builders).
They import only downwards:
``plant <- controller <- (bridge, fmu_build) <- experiments <- benchmarks <- cli``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("msagv")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"
