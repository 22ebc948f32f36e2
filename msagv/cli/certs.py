"""``msagv certs DIR``: a certificate authority and per-role, per-vehicle certificates for
``--secure``.

Creates (or completes) DIR with ``ca.pem``/``ca.key``; per ``--vehicle ID`` (default
``agv0``) a plant and a controller identity allowed that vehicle only (``plant-ID``,
``controller-ID``); a ``router`` and an ``operator`` (who re-arms a latched vehicle,
``msagv arm``) for every vehicle; one identity per ``--extra NAME[:ROLE[:ID,...]]`` (an
*observer* of every vehicle unless a role and vehicles are given); and ``roles.json``, the
identities the access-control rules name (:mod:`bridge.security`, docs/SECURITY.md).
"""

from __future__ import annotations

import argparse


def main(argv: list[str]) -> int:
    from msagv.bridge.security import (DEFAULT_VEHICLES, ROLES, SecurityError, create_certs,
                                       parse_extra)

    from .args import OptionError, add_common_args, check_output, fail, note

    ap = argparse.ArgumentParser(
        prog="msagv certs",
        description="Create a CA and the certificates of each vehicle's plant and controller, "
                    "a router and an operator (and any --extra identity) for msagv "
                    "plant/controller/router/arm --secure DIR.")
    ap.add_argument("dir", metavar="DIR", help="the directory to create or complete")
    ap.add_argument("--vehicle", action="append", default=[], metavar="ID",
                    help="a vehicle id: a plant and a controller certificate allowed this "
                         f"vehicle only (repeatable; default {DEFAULT_VEHICLES[0]})")
    ap.add_argument("--extra", action="append", default=[], metavar="NAME[:ROLE[:ID,...]]",
                    help=f"one more identity; ROLE is one of {', '.join(ROLES)} (default "
                         f"observer: may only read), for the vehicles ID,... (default: every "
                         f"vehicle, '*') (repeatable)")
    ap.add_argument("--san", action="append", default=[], metavar="HOST",
                    help="a host name or IP address the listening processes are reached at, "
                         "besides localhost/127.0.0.1/::1 (repeatable)")
    ap.add_argument("--days", type=int, default=825, help="validity of the identities' "
                                                           "certificates (default 825)")
    ap.add_argument("--force", action="store_true",
                    help="start a new CA and sign every identity again")
    add_common_args(ap)
    a = ap.parse_args(argv)
    try:
        check_output(a.dir, "DIR", directory=True)
        extras = [parse_extra(e) for e in a.extra]
        m = create_certs(a.dir, extras, a.san, a.days, a.force,
                         vehicles=a.vehicle or DEFAULT_VEHICLES)
    except (SecurityError, OptionError, OSError) as e:
        return fail("msagv certs", e, a)
    ids = ", ".join(f"{n} ({v['role']} of {','.join(v['vehicles'])}, CN {v['cn']})"
                    for n, v in m["identities"].items())
    note(a, f"msagv certs: {a.dir}: CA ca.pem; identities {ids}. Keep ca.key off the "
            f"vehicles; give each machine ca.pem, roles.json and its own NAME.pem/NAME.key.")
    return 0
