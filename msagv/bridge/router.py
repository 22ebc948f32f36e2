"""A Zenoh router for plants and controllers on several machines (``msagv router``).

There is no ``zenohd`` on PyPI or Debian here; a Python session opened in ``router`` mode
routes between its peers and clients just as well (DESIGN.md). Plants and controllers
connect to it (``--connect tcp/HOST:7447``, as peers or with ``--mode client``), and any
number of vehicles share it by id. Multicast scouting is off: clients name the endpoint.
"""

from __future__ import annotations

import logging
import sys
import threading

from .process import EXIT_OK, EXIT_USAGE
from .session import ROUTER_PORT, SessionError, SessionOptions
from .zenoh_transport import ZenohTransport

log = logging.getLogger("msagv.router")


def serve(opts: SessionOptions, stop: threading.Event) -> int:
    """Route until ``stop`` is set; returns the exit code (2: the session cannot open)."""
    try:
        with ZenohTransport.open(opts, "router") as t:
            eps = opts.listen or [f"tcp/127.0.0.1:{ROUTER_PORT}"]
            log.info("router %s listening on %s", t.id, ", ".join(eps))
            print(f"msagv router: listening on {', '.join(eps)}", file=sys.stderr, flush=True)
            while not stop.wait(0.2):
                pass
    except SessionError as e:
        print(f"msagv router: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        pass
    log.info("router stopped")
    return EXIT_OK
