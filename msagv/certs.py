"""``msagv certs DIR``: a certificate authority and per-role certificates for ``--secure``.

Creates (or completes) DIR with ``ca.pem``/``ca.key``, ``plant``, ``controller`` and
``router`` keys and certificates, one per ``--extra NAME[:ROLE]`` (an *observer* unless a
role is given), and ``roles.json``, the identities the access-control rules name
(:mod:`bridge.security`, docs/SECURITY.md).
"""

from __future__ import annotations

import argparse


def main(argv: list[str]) -> int:
    from msagv.bridge.security import ROLES, SecurityError, create_certs, parse_extra

    from .args import OptionError, add_common_args, check_output, fail, note

    ap = argparse.ArgumentParser(
        prog="msagv certs",
        description="Create a CA and the certificates of plant, controller, router (and any "
                    "--extra identity) for msagv plant/controller/router --secure DIR.")
    ap.add_argument("dir", metavar="DIR", help="the directory to create or complete")
    ap.add_argument("--extra", action="append", default=[], metavar="NAME[:ROLE]",
                    help=f"one more identity; ROLE is one of {', '.join(ROLES)} (default "
                         f"observer: may only read) (repeatable)")
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
        m = create_certs(a.dir, extras, a.san, a.days, a.force)
    except (SecurityError, OptionError, OSError) as e:
        return fail("msagv certs", e, a)
    ids = ", ".join(f"{n} ({v['role']}, CN {v['cn']})" for n, v in m["identities"].items())
    note(a, f"msagv certs: {a.dir}: CA ca.pem; identities {ids}. Keep ca.key off the "
            f"vehicles; give each machine ca.pem, roles.json and its own NAME.pem/NAME.key.")
    return 0
