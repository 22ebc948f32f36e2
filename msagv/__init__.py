"""The ``msagv`` application: the command line and the in-process runner.

Every sub-command's parser lives here (:mod:`msagv.cli` dispatches, :mod:`msagv.cli.args` holds
the shared option builders); the work is done by the packages below it:
``plant <- controller <- (bridge, fmu_build) <- experiments <- benchmarks <- msagv``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("msagv")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"
