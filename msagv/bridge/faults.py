"""Malformed messages of every kind docs/PROTOCOL.md rejects, for fault-injection tests.

:func:`malformed` yields payloads that a conforming receiver must reject, each with the
reason code it must count; :func:`flood` puts them on the bus through a
:class:`bridge.transport.Transport`. ``python -m msagv.faults`` (the command line, in
:mod:`msagv.faults`) sends them at a running plant (``cmd``) and/or controller (``state``,
``reference``)::

    python -m msagv.faults --connect tcp/127.0.0.1:7448 --id agv0 --count 10000 --at both

A receiver checks the sender first (docs/PROTOCOL.md section 5): from the flood's own
identity every ``cmd`` is ``not_owner`` and every ``state`` ``not_bound``; the owner's
(or the bound plant's) malformed messages are counted by their malformation.
"""

from __future__ import annotations

import itertools
import math
import time
from typing import Iterator

import msgpack

from msagv.plant.signals import CONTROL_PERIOD

from . import messages as M


def _valid_state(nw: int, seq: int = 3) -> dict:
    return {"v": M.VERSION, "seq": seq, "t": seq * CONTROL_PERIOD, "x": 1.0, "y": 2.0,
            "phi": 0.1, "vx": 4.0, "vy": 0.2, "r": 0.01, "delta": [0.01] * nw,
            "omega_w": [8.0] * nw}


def _valid_cmd(nw: int, state_seq: int = 10 ** 9) -> dict:
    # answers a state no plant has published, so no variant can ever be applied
    return {"v": M.VERSION, "seq": 7, "t": state_seq * CONTROL_PERIOD, "state_seq": state_seq,
            "omega_w": [8.0] * nw, "omega_s": [0.0] * nw, "solve_ms": 1.0}


def _valid_reference() -> dict:
    return {"v": M.VERSION, "t": [0.0, 1.0, 2.0], "x": [0.0, 1.0, 2.0], "y": [0.0, 0.0, 0.0],
            "phi": [0.0, 0.0, 0.0]}


def _variants(base: dict, required: dict, arrays: tuple[str, ...], floats: tuple[str, ...], nonneg: str | None,
              extra: list[tuple[bytes, str]]) -> list[tuple[bytes, str]]:
    pk = M.pack
    good = pk(base)
    out: list[tuple[bytes, str]] = [
        (b"\xc1\x00garbage", M.NOT_MSGPACK),
        (good[:-3], M.NOT_MSGPACK),  # truncated
        (good + b"\x01", M.NOT_MSGPACK),  # trailing bytes
        (b"", M.NOT_MSGPACK),
        (b'{"v": 1, "seq": 0}', M.NOT_MSGPACK),  # JSON: '{' is msgpack's int 123, then junk
        (msgpack.packb([1, 2, 3]), M.NOT_A_MAP),
        (msgpack.packb(42), M.NOT_A_MAP),
        (pk(dict(base, v=M.VERSION + 1)), M.VERSION_MISMATCH),
        (pk(dict(base, v="1")), M.VERSION_MISMATCH),
        (pk({k: v for k, v in base.items() if k != "v"}), M.VERSION_MISMATCH),
        (pk(dict(base, surplus=1.0)), M.EXTRA_FIELD),
    ]
    for f in floats:
        out += [(pk(dict(base, **{f: "fast"})), M.BAD_TYPE),
                (pk(dict(base, **{f: True})), M.BAD_TYPE),
                (pk(dict(base, **{f: math.nan})), M.NON_FINITE),
                (pk(dict(base, **{f: -math.inf})), M.NON_FINITE)]
    for k in required:
        if k != "v":
            out.append((pk({kk: vv for kk, vv in base.items() if kk != k}), M.MISSING_FIELD))
    for a in arrays:
        n = len(base[a])
        out.append((pk(dict(base, **{a: base[a] + [1.0]})), M.BAD_LENGTH))
        out.append((pk(dict(base, **{a: base[a][:-1]})), M.BAD_LENGTH))
        out.append((pk(dict(base, **{a: [math.nan] + base[a][1:]})), M.NON_FINITE))
        out.append((pk(dict(base, **{a: [-math.inf] * n})), M.NON_FINITE))
        out.append((pk(dict(base, **{a: 3.0})), M.BAD_TYPE))
    if nonneg:
        out.append((pk(dict(base, **{nonneg: [-1.0] + base[nonneg][1:]})), M.NEGATIVE_WHEEL_SPEED))
    return out + extra


def state_cases(nw: int) -> list[tuple[bytes, str]]:
    """Malformed ``state`` payloads for a vehicle with ``nw`` wheels, with their reasons."""
    base = _valid_state(nw)
    return _variants(base, M.STATE_REQUIRED, ("delta", "omega_w"), ("x", "t"), "omega_w", [
        (b"\x80" + b"\x00" * M.MAX_STATE_BYTES, M.TOO_LARGE),
        (M.pack(dict(base, seq=-1)), M.BAD_VALUE),
        (M.pack(dict(base, seq=1.5)), M.BAD_TYPE),
        (M.pack(dict(base, end="yes")), M.BAD_TYPE),
    ])


def cmd_cases(nw: int) -> list[tuple[bytes, str]]:
    """Malformed ``cmd`` payloads, including commands answering a state never published
    (any plant that has published fewer than 10^9 states rejects them)."""
    base = _valid_cmd(nw)
    return _variants(base, M.CMD_REQUIRED, ("omega_w", "omega_s"), ("t",), "omega_w", [
        (b"\x80" + b"\x00" * M.MAX_CMD_BYTES, M.TOO_LARGE),
        (M.pack(base), M.UNKNOWN_STATE),
        (M.pack(dict(base, state_seq=10 ** 12, t=10 ** 10)), M.UNKNOWN_STATE),
        # t not that of state 0 (UNKNOWN_STATE instead before the plant's first state)
        (M.pack(dict(base, state_seq=0, t=123.0)), M.T_MISMATCH),
        (M.pack(dict(base, state_seq=-3)), M.BAD_VALUE),
        (M.pack(dict(base, solve_ms=-1.0)), M.BAD_VALUE),
    ])


def reference_cases() -> list[tuple[bytes, str]]:
    base = _valid_reference()
    return _variants(base, M.REFERENCE_REQUIRED, ("t", "x"), (), None, [
        (M.pack(dict(base, x=[0.0, 1.0])), M.BAD_LENGTH),
        (M.pack(dict(base, t=[0.0, 0.0, 1.0])), M.BAD_VALUE),
        (M.pack(dict(base, t=[0.0, 1.0], x=[0.0, 1.0], y=[0.0, 0.0], phi=[0.0, 0.0])), M.BAD_LENGTH),
        (M.pack(dict(base, x=[0.0, math.nan, 1.0])), M.NON_FINITE),
    ])


def malformed(kind: str, nw: int, count: int) -> Iterator[tuple[bytes, str]]:
    """``count`` malformed payloads of ``kind`` in {'state', 'cmd', 'reference'}, cycling
    through every case."""
    cases = {"state": lambda: state_cases(nw), "cmd": lambda: cmd_cases(nw),
             "reference": reference_cases}[kind]()
    return itertools.islice(itertools.cycle(cases), count)


def flood(transport, vid: str, kind: str, nw: int, count: int,
          rate_hz: float | None = None) -> dict:
    """Put ``count`` malformed ``kind`` messages on ``msagv/{vid}/{kind}`` as ``transport``'s
    identity (:class:`bridge.transport.Transport`; over Zenoh reliable with blocking
    congestion control: none is dropped on the way). Returns the counts by the reason of
    their malformation."""
    key = f"msagv/{vid}/{kind}"
    pub = transport.publisher(key)
    t0 = time.monotonic()
    by: dict[str, int] = {}
    try:
        for i, (payload, reason) in enumerate(malformed(kind, nw, count)):
            pub.put(payload, i)
            by[reason] = by.get(reason, 0) + 1
            if rate_hz:
                delay = t0 + (i + 1) / rate_hz - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
    finally:
        pub.close()
    return {"key": key, "sent": count, "by_reason": by, "seconds": time.monotonic() - t0,
            "as": transport.id}
