"""The bus messages (bridge.messages): round trips, the schema, and the rejection of every
kind of malformed message with its reason code (docs/PROTOCOL.md)."""

from __future__ import annotations

import logging
import math

import msgpack
import numpy as np
import pytest

from msagv.bridge import faults
from msagv.bridge import messages as M

NW = 4


def state_fields(**over):
    d = {"t": 0.25, "x": 1.0, "y": -2.0, "phi": 0.3, "vx": 4.0, "vy": 0.5, "r": 0.01,
         "delta": [0.01, 0.02, -0.01, -0.02], "omega_w": [8.0, 8.1, 8.0, 8.1],
         "W_s": 1.0, "W_alpha": 2.0, "W_t": 3.0}
    d.update(over)
    return d


# ---- round trips ------------------------------------------------------------------------
def test_state_round_trip_is_exact():
    st = state_fields(x=1.0 / 3.0)
    m = M.decode_state(M.encode_state(25, st, safe=False, end=True), NW)
    assert m["v"] == M.VERSION and m["seq"] == 25 and m["safe"] is False and m["end"] is True
    for k in ("t", "x", "y", "phi", "vx", "vy", "r", "W_s", "W_alpha", "W_t"):
        assert m[k] == st[k]  # float64 on the wire: bit-exact
    assert m["delta"] == st["delta"] and m["omega_w"] == st["omega_w"]


def test_encode_accepts_numpy_and_float32():
    st = state_fields(delta=np.array([0.1, 0.2, 0.3, 0.4], dtype=np.float32),
                      omega_w=np.arange(4.0), x=np.float64(2.5))
    m = M.decode_state(M.encode_state(0, st), NW)
    assert m["delta"] == pytest.approx([0.1, 0.2, 0.3, 0.4], rel=1e-7)
    assert m["omega_w"] == [0.0, 1.0, 2.0, 3.0] and m["x"] == 2.5


def test_cmd_round_trip():
    b = M.encode_cmd(3, 0.07, 7, [1.0, 2.0, 3.0, 4.0], [0.0, -0.1, 0.1, 0.0], solve_ms=4.5,
                     cost=12.0)
    m = M.decode_cmd(b, NW)
    assert m == {"v": 1, "seq": 3, "t": 0.07, "state_seq": 7, "omega_w": [1.0, 2.0, 3.0, 4.0],
                 "omega_s": [0.0, -0.1, 0.1, 0.0], "solve_ms": 4.5, "cost": 12.0}


def test_cmd_leaves_out_an_infinite_cost():
    m = M.decode_cmd(M.encode_cmd(0, 0.0, 0, [0.0] * 4, [0.0] * 4, cost=math.inf), NW)
    assert "cost" not in m


def test_reference_and_params_round_trip():
    m = M.decode_reference(M.encode_reference([0, 1, 2], [0, 1, 2], [0, 0, 1], [0, 0, 0.5],
                                              name="s", relative=True))
    assert m["t"] == [0.0, 1.0, 2.0] and m["name"] == "s" and m["relative"] is True
    p = M.decode_params(M.encode_params("agv0", {"name": "x"}, 0.01, "realtime", 4))
    assert p["vehicle"] == {"name": "x"} and p["run_mode"] == "realtime" and p["n_wheels"] == 4


def test_integers_are_accepted_for_floats():
    raw = {"v": 1, "seq": 0, "t": 0, "x": 0, "y": 0, "phi": 0, "vx": 0, "vy": 0, "r": 0,
           "delta": [0, 0, 0, 0], "omega_w": [0, 0, 0, 0]}
    m = M.decode_state(msgpack.packb(raw), NW)
    assert m["x"] == 0.0 and isinstance(m["x"], float) and m["delta"] == [0.0] * 4


def test_hand_built_bytes_decode():
    """The bytes of a minimal 1-axle state, written by hand from docs/PROTOCOL.md."""
    b = bytes([0x8b, 0xa1, 0x76, 0x01, 0xa3, 0x73, 0x65, 0x71, 0x02])  # {v: 1, seq: 2,
    b += bytes([0xa1, 0x74]) + bytes([0xcb]) + np.float64(0.02).byteswap().tobytes()  # t: 0.02
    for k in (b"x", b"y", b"phi", b"vx", b"vy", b"r"):
        b += bytes([0xa0 | len(k)]) + k + bytes([0x00])  # fixint 0
    b += bytes([0xa5]) + b"delta" + bytes([0x92, 0x00, 0x00])
    b += bytes([0xa7]) + b"omega_w" + bytes([0x92, 0xcb]) + np.float64(1.5).byteswap().tobytes()
    b += bytes([0xcb]) + np.float64(1.5).byteswap().tobytes()
    m = M.decode_state(b, 2)
    assert m["seq"] == 2 and m["t"] == 0.02 and m["omega_w"] == [1.5, 1.5]


# ---- rejections -------------------------------------------------------------------------
def _decode(kind, payload, plant_newest=1000):
    if kind == "state":
        return M.decode_state(payload, NW)
    if kind == "reference":
        return M.decode_reference(payload)
    c = M.decode_cmd(payload, NW)
    # the plant's own checks (bridge.plant_node.PlantNode.handle_cmd)
    if c["state_seq"] > plant_newest:
        raise M.MessageError(M.UNKNOWN_STATE, "")
    if abs(c["t"] - c["state_seq"] * 0.01) > 1e-6:
        raise M.MessageError(M.T_MISMATCH, "")
    return c


@pytest.mark.parametrize("kind,cases", [("state", faults.state_cases(NW)),
                                        ("cmd", faults.cmd_cases(NW)),
                                        ("reference", faults.reference_cases())])
def test_every_malformed_case_is_rejected_with_its_reason(kind, cases):
    for payload, reason in cases:
        with pytest.raises(M.MessageError) as ei:
            _decode(kind, payload)
        assert ei.value.reason == reason, (payload[:60], ei.value)
        assert ei.value.reason in M.REASONS


def test_fault_cases_cover_every_kind_the_issue_names():
    reasons = {r for _, r in faults.cmd_cases(NW)} | {r for _, r in faults.state_cases(NW)}
    for r in (M.NOT_MSGPACK, M.TOO_LARGE, M.VERSION_MISMATCH, M.MISSING_FIELD, M.EXTRA_FIELD,
              M.BAD_LENGTH, M.NON_FINITE, M.NEGATIVE_WHEEL_SPEED, M.UNKNOWN_STATE):
        assert r in reasons


@pytest.mark.parametrize("payload,reason", [
    (b"\x93\x01\x02", M.NOT_MSGPACK),  # truncated array
    (msgpack.packb({"v": 1}) + b"\x00", M.NOT_MSGPACK),
    (b"\x00" * (M.MAX_STATE_BYTES + 1), M.TOO_LARGE),  # before any decoding
    (msgpack.packb("state"), M.NOT_A_MAP),
    (msgpack.packb({"v": 2}), M.VERSION_MISMATCH),
    (msgpack.packb({"v": True}), M.VERSION_MISMATCH),
    (msgpack.packb({"v": 1.0}), M.VERSION_MISMATCH),
])
def test_envelope_rejections(payload, reason):
    with pytest.raises(M.MessageError) as ei:
        M.decode_state(payload, NW)
    assert ei.value.reason == reason


def test_field_rejections_name_the_field():
    good = M.unpack(M.encode_state(0, state_fields()), 10 ** 6)
    for change, reason, word in [
        ({"delta": [0.0] * 6}, M.BAD_LENGTH, "delta"),
        ({"omega_w": [1.0, -0.5, 1.0, 1.0]}, M.NEGATIVE_WHEEL_SPEED, "omega_w[1]"),
        ({"phi": float("nan")}, M.NON_FINITE, "phi"),
        ({"vy": float("-inf")}, M.NON_FINITE, "vy"),
        ({"x": "1.0"}, M.BAD_TYPE, "x"),
        ({"seq": -1}, M.BAD_VALUE, "seq"),
        ({"seq": 2 ** 64 - 1}, M.BAD_VALUE, "seq"),
        ({"safe": 1}, M.BAD_TYPE, "safe"),
        ({"colour": "red"}, M.EXTRA_FIELD, "colour"),
    ]:
        m = dict(good, **change)
        with pytest.raises(M.MessageError) as ei:
            M.decode_state(msgpack.packb(m), NW)
        assert ei.value.reason == reason and word in ei.value.detail, (change, ei.value)
    m = dict(good)
    del m["vx"]
    with pytest.raises(M.MessageError, match="vx") as ei:
        M.decode_state(msgpack.packb(m), NW)
    assert ei.value.reason == M.MISSING_FIELD


def test_reference_rules():
    with pytest.raises(M.MessageError, match="increase") as ei:
        M.decode_reference(M.encode_reference([0, 2, 1], [0, 1, 2], [0, 0, 0], [0, 0, 0]))
    assert ei.value.reason == M.BAD_VALUE
    with pytest.raises(M.MessageError) as ei:
        M.decode_reference(M.encode_reference([0, 1, 2], [0, 1], [0, 0, 0], [0, 0, 0]))
    assert ei.value.reason == M.BAD_LENGTH


def test_params_rules():
    with pytest.raises(M.MessageError) as ei:
        M.decode_params(M.encode_params("a", {}, 0.01, "sometimes", 4))
    assert ei.value.reason == M.BAD_VALUE
    with pytest.raises(M.MessageError) as ei:
        M.decode_params(M.encode_params("a", {}, 0.01, "lockstep", 3))
    assert ei.value.reason == M.BAD_VALUE


# ---- counting -----------------------------------------------------------------------------
def test_rejections_count_exactly_and_log_rate_limited(caplog):
    rej = M.Rejections("test", logging.getLogger("msagv.test"), first=3, every=100)
    with caplog.at_level(logging.WARNING, logger="msagv.test"):
        for i in range(250):
            rej.add(M.MessageError(M.NON_FINITE, f"x is nan ({i})"), "msagv/a/state")
        rej.add(M.MessageError(M.BAD_LENGTH, "delta"), "msagv/a/cmd")
    s = rej.summary()
    assert s["total"] == 251 and rej.total == 251
    assert s["by_reason"] == {M.NON_FINITE: 250, M.BAD_LENGTH: 1}
    assert s["by_key"] == {"msagv/a/state": 250, "msagv/a/cmd": 1}
    logged = [r.getMessage() for r in caplog.records]
    assert len(logged) == 3 + 2 + 1  # first 3, then the 100th and 200th, and the other reason
    assert "non_finite" in logged[0] and "(200 so far)" in logged[4]
