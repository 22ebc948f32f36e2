"""``python -m msagv.faults``: malformed messages of every kind at a running plant and/or
controller (:mod:`bridge.faults`), for fault-injection by hand.

It opens a session as a tool, waits for the receivers' declarations, puts ``--count``
malformed messages of each kind, and prints the counts by the reason of their
malformation as JSON. The receivers check the sender first: from this tool's identity
every command is ``not_owner`` and every state ``not_bound`` (a reference, which anyone
may send, is counted by its malformation); malformed messages of the owner itself are
counted by their malformation (the tests send them on the loopback bus)."""

from __future__ import annotations

import argparse
import json
import sys
import time


def main(argv: list[str] | None = None) -> int:
    from msagv.bridge.faults import flood
    from msagv.bridge.process import EXIT_USAGE
    from msagv.bridge.session import open_session
    from msagv.bridge.zenoh_transport import ZenohTransport

    from .cli.args import add_session_args, options_from_args
    from .cli.errors import USAGE_ERRORS

    ap = argparse.ArgumentParser(prog="python -m msagv.faults",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=10000, help="messages per target kind")
    ap.add_argument("--at", choices=["plant", "controller", "both"], default="both",
                    help="plant: cmd messages; controller: state and reference messages")
    ap.add_argument("--wheels", type=int, default=4, help="2n of the vehicle (default 4)")
    ap.add_argument("--rate", type=float, help="messages per second per kind (default: as fast "
                                               "as the receivers take them)")
    add_session_args(ap)
    a = ap.parse_args(argv)
    try:
        opts = options_from_args(a)
        if a.count < 1:
            raise ValueError(f"--count must be >= 1, got {a.count}")
        session = open_session(opts, "tool")
    except USAGE_ERRORS as e:
        print(f"msagv faults: {e}", file=sys.stderr)
        return EXIT_USAGE
    kinds = {"plant": ["cmd"], "controller": ["state", "reference"],
             "both": ["cmd", "state", "reference"]}[a.at]
    with ZenohTransport(session) as t:
        time.sleep(0.3)  # let the declarations of the receivers arrive
        out = [flood(t, opts.id, k, a.wheels, a.count, a.rate) for k in kinds]
        time.sleep(0.3)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
