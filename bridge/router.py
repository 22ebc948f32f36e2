"""``msagv router``: a Zenoh router for plants and controllers on several machines.

There is no ``zenohd`` on PyPI or Debian here; a Python session opened in ``router`` mode
routes between its peers and clients just as well (DESIGN.md). Plants and controllers
connect to it (``--connect tcp/HOST:7447``, as peers or with ``--mode client``), and any
number of vehicles share it by id. Multicast scouting is off: clients name the endpoint.
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading

from .plant_node import EXIT_OK, EXIT_USAGE, StopOnSignal, setup_logging

log = logging.getLogger("msagv.router")


def main(argv: list[str]) -> int:
    from .session import ROUTER_PORT, SessionError, add_session_args, open_session, options_from_args

    ap = argparse.ArgumentParser(
        prog="msagv router",
        description=f"A Zenoh router (a session in router mode); listens on "
                    f"tcp/127.0.0.1:{ROUTER_PORT} unless --listen is given (use "
                    f"--listen tcp/0.0.0.0:{ROUTER_PORT} for other machines).")
    ap.add_argument("-q", "--quiet", action="store_true", help="log warnings only")
    add_session_args(ap, router=True)
    a = ap.parse_args(argv)
    setup_logging("msagv router", "-", a.quiet)
    stop = threading.Event()
    StopOnSignal(stop).install()
    try:
        opts = options_from_args(a, router=True)
        with open_session(opts, "router") as session:
            eps = opts.listen or [f"tcp/127.0.0.1:{ROUTER_PORT}"]
            log.info("router %s listening on %s", session.zid(), ", ".join(eps))
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
