"""What every bridge process shares: exit codes, signal handling, logging, real-time set-up.

The plant, controller and router processes (``bridge.plant_node``, ``bridge.controller_node``,
``bridge.router``) use these; the command line that starts them lives in :mod:`msagv`.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import socket
import sys
import threading

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_RUNTIME = 0, 1, 2, 3
"""Exit codes of every process: 0 done, 1 failed, 2 bad options or input (nothing ran),
3 the run could not go on (no peer, a lockstep timeout, the peer lost with ``exit``)."""


class LogStyle(logging.Formatter):
    """The command line's one style: ``prog: [vid] message`` for information,
    ``prog: warning: [vid] message`` (``error``, ``debug``) for the rest."""

    def __init__(self, prog: str, vid: str):
        super().__init__()
        self.prog, self.vid = prog, vid

    def format(self, record: logging.LogRecord) -> str:
        level = "" if record.levelno == logging.INFO else f"{record.levelname.lower()}: "
        text = f"{self.prog}: {level}[{self.vid}] {record.getMessage()}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


def setup_logging(prog: str, vid: str, quiet: bool = False, verbose: bool = False) -> None:
    """Log lines ``prog: [vid] message`` (warnings ``prog: warning: [vid] message``) on
    stderr; warnings only with ``quiet``, debug with ``verbose``."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose else logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(LogStyle(prog, vid))
    logging.basicConfig(level=level, handlers=[handler], force=True)
    logging.getLogger("numba").setLevel(max(level, logging.INFO))


class StopOnSignal:
    """SIGINT/SIGTERM set ``event`` (the loops check it at least every 50 ms) instead of
    killing the process, so recordings are closed and tokens undeclared. A second signal
    raises KeyboardInterrupt (stop at once)."""

    def __init__(self, event: threading.Event):
        self.event = event
        self.signum: int | None = None

    def install(self) -> None:
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, self._handler)

    def _handler(self, signum, frame) -> None:
        if self.event.is_set():
            raise KeyboardInterrupt
        self.signum = signum
        self.event.set()

    @property
    def name(self) -> str | None:
        return None if self.signum is None else signal.Signals(self.signum).name


def set_realtime_priority(priority: int) -> str | None:
    """Run this process (and the threads it starts later, e.g. zenoh's) under SCHED_FIFO
    at ``priority`` (1-99), so a loaded machine cannot delay its periods. Call before
    opening the session. Returns None on success, else why not (e.g. no CAP_SYS_NICE);
    the process then runs at normal priority."""
    if not 1 <= priority <= 99:
        return f"--rt-priority must be 1..99, got {priority}"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, PermissionError, OSError) as e:
        return f"cannot use SCHED_FIFO ({e}); running at normal priority"
    return None


def freeze_heap() -> None:
    """Move everything allocated so far (numba, numpy, the model) out of the garbage
    collector's view: a full collection would otherwise stall a period (one here took
    ~80 ms). Call once, before the subscriptions exist, so no message waits for it."""
    gc.collect()
    gc.freeze()


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now (for loopback endpoints)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
