"""``--foxglove``: the live Foxglove view's options (``run``, ``plant``, ``demo``,
``ros2 plant``) and its start (:class:`experiments.foxglove.FoxgloveView`)."""

from __future__ import annotations

import argparse
import sys

from .args import OptionError


def add_foxglove_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--foxglove", action="store_true",
                    help="serve the run live to Foxglove (its WebSocket protocol; needs "
                         "msagv[foxglove]); prints the address to open")
    ap.add_argument("--foxglove-port", type=int, default=8765, metavar="PORT",
                    help="the Foxglove server's port (default 8765; 0 = any free port)")
    ap.add_argument("--foxglove-host", default="127.0.0.1", metavar="ADDR",
                    help="the address the server listens on (default 127.0.0.1; another one "
                         "serves the run to other machines, unauthenticated: a warning)")


def check_foxglove_args(a, prog: str) -> bool:
    """Refuse bad Foxglove options before any work; True when the view is asked for."""
    if not getattr(a, "foxglove", False):
        return False
    if not 0 <= a.foxglove_port <= 65535:
        raise OptionError(f"--foxglove-port must be 0..65535, got {a.foxglove_port}")
    from msagv.experiments.foxglove import FoxgloveError, require_foxglove

    try:
        require_foxglove()
    except FoxgloveError as e:
        raise OptionError(str(e)) from None
    if a.foxglove_host not in ("127.0.0.1", "localhost", "::1"):
        print(f"{prog}: warning: --foxglove-host {a.foxglove_host}: the Foxglove server is "
              f"unauthenticated and unencrypted; anyone who reaches this address sees the run",
              file=sys.stderr)
    return True


def open_foxglove(a, prog: str, header: dict, recorder=None):
    """The view of ``--foxglove`` beside ``recorder`` (a Tee of both), or ``recorder``
    unchanged without ``--foxglove``. Prints the address on stderr."""
    if not getattr(a, "foxglove", False):
        return recorder
    from msagv.experiments.foxglove import FoxgloveError, FoxgloveView
    from msagv.experiments.viewer import Tee

    try:
        view = FoxgloveView(header, host=a.foxglove_host, port=a.foxglove_port, name=prog)
    except FoxgloveError as e:
        raise OptionError(str(e)) from None
    print(f"{prog}: Foxglove: open connection {view.address} (Foxglove WebSocket)",
          file=sys.stderr, flush=True)
    return Tee(recorder, view)
