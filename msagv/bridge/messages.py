"""The bus messages: msgpack maps with a schema version, and the validation of everything
that arrives.

Every message is a msgpack map with string keys and a schema version ``v``
(:data:`VERSION`). Floats travel as msgpack float64 (an integer is accepted where a float
is expected), arrays as plain lists of numbers in the wheel order 11, 12, 21, 22, ...
(2n entries). docs/PROTOCOL.md is the normative description; this module implements it.

Decoding never trusts the sender: :func:`decode_state`, :func:`decode_cmd`,
:func:`decode_reference` and :func:`decode_params` either return a clean dict of Python
floats/ints/lists or raise :class:`MessageError` with a short ``reason`` code (the
counters' key) and a human-readable ``detail``. Nothing that fails reaches a model.
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Any, Mapping

import msgpack

from msagv.plant.signals import BODY_FIELDS, WEAR_FIELDS, WHEEL_WEAR_FIELDS

VERSION = 1
CONTENT_TYPE = "application/msgpack"

MAX_STATE_BYTES = 64 * 1024
MAX_CMD_BYTES = 64 * 1024
MAX_PARAMS_BYTES = 1024 * 1024
MAX_REFERENCE_BYTES = 1024 * 1024  # the largest message: Zenoh's own limit is just above it
MAX_REFERENCE_SAMPLES = 25_000  # (36 bytes a sample: a 25,000-sample reference is ~0.9 MB)

# reason codes (docs/PROTOCOL.md, "Validation and rejection")
NOT_MSGPACK = "not_msgpack"  # undecodable bytes, trailing bytes, empty
TOO_LARGE = "too_large"  # larger than the message's limit (Zenoh drops what exceeds its own)
NOT_A_MAP = "not_a_map"  # valid msgpack but not a map (non-string keys are not_msgpack)
VERSION_MISMATCH = "version"  # v missing, not an integer, or not VERSION
MISSING_FIELD = "missing_field"
EXTRA_FIELD = "extra_field"
BAD_TYPE = "type"  # a field of the wrong type (e.g. a string, a bool for a number)
BAD_LENGTH = "length"  # an array whose length is not the vehicle's 2n (or the reference's)
NON_FINITE = "non_finite"  # NaN or inf
NEGATIVE_WHEEL_SPEED = "negative_wheel_speed"
BAD_VALUE = "value"  # out of the field's domain (negative seq, t not increasing, ...)
UNKNOWN_STATE = "unknown_state"  # a command answering a state the plant never published
T_MISMATCH = "t_mismatch"  # a command's t is not the t of the state it answers
NOT_OWNER = "not_owner"  # a command from an identity that does not own the vehicle
NOT_BOUND = "not_bound"  # a state from a plant the controller is not bound to
BAD_MAC = "bad_mac"  # an owner's command or a bound plant's state without the grant's mac
REFERENCES_OFF = "references_off"  # a reference to a controller that takes none from this bus
REASONS = (NOT_MSGPACK, TOO_LARGE, NOT_A_MAP, VERSION_MISMATCH, MISSING_FIELD, EXTRA_FIELD,
           BAD_TYPE, BAD_LENGTH, NON_FINITE, NEGATIVE_WHEEL_SPEED, BAD_VALUE, UNKNOWN_STATE,
           T_MISMATCH, NOT_OWNER, NOT_BOUND, BAD_MAC, REFERENCES_OFF)

# field tables: name -> kind. kinds: "int" (>= 0), "float" (finite), "wheels" (2n finite
# floats), "wheels+" (2n finite floats >= 0), "bool", "float+" (finite, >= 0), "str",
# "bin" (bytes, at most MAX_BIN of them)
# the state's field names are the plant's (msagv.plant.signals): the body's
# BODY_FIELDS, the wear work WEAR_FIELDS, and the per-wheel wear work WHEEL_WEAR_FIELDS
# (arrays in the wheel order), sent only to peers that asked for it (docs/PROTOCOL.md,
# "Per-wheel wear"), as a peer of the first version rejects them
STATE_REQUIRED = {"v": "int", "seq": "int", "t": "float", **dict.fromkeys(BODY_FIELDS, "float"),
                  "delta": "wheels", "omega_w": "wheels+"}
STATE_OPTIONAL = {**dict.fromkeys(WEAR_FIELDS, "float"), "safe": "bool", "end": "bool",
                  **dict.fromkeys(WHEEL_WEAR_FIELDS, "wheels"), "mac": "bin"}
CMD_REQUIRED = {"v": "int", "seq": "int", "t": "float", "state_seq": "int",
                "omega_w": "wheels+", "omega_s": "wheels"}
CMD_OPTIONAL = {"solve_ms": "float+", "cost": "float", "mac": "bin"}
MAX_BIN = 64  # a binary field's bytes (a mac, a public key)
REFERENCE_REQUIRED = {"v": "int", "t": "series", "x": "series", "y": "series", "phi": "series"}
REFERENCE_OPTIONAL = {"name": "str", "relative": "bool"}
PARAMS_REQUIRED = {"v": "int", "id": "str", "vehicle": "map", "period": "float+",
                   "run_mode": "str", "n_wheels": "int"}
PARAMS_OPTIONAL: dict[str, str] = {}
RUN_MODES = ("lockstep", "realtime")


class MessageError(ValueError):
    """A rejected message: ``reason`` is one of :data:`REASONS`, ``detail`` says what."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


# ---- encoding -----------------------------------------------------------------------------
def _floats(a) -> list[float]:
    # np.float32 and arrays are not packable (DESIGN.md); every entry becomes a Python float
    return [float(v) for v in (a.tolist() if hasattr(a, "tolist") else a)]


def pack(msg: Mapping[str, Any]) -> bytes:
    return msgpack.packb(dict(msg), use_bin_type=True)


def _signed(m: dict, mac_key: bytes | None) -> bytes:
    if mac_key is not None:
        from .link_key import LinkKeys

        m["mac"] = LinkKeys.tag(mac_key, m)
    return pack(m)


def encode_state(seq: int, state: Mapping[str, Any], *, safe: bool | None = None,
                 end: bool | None = None, wheel_wear: bool = True,
                 mac_key: bytes | None = None) -> bytes:
    """A ``state`` message from ``Plant.state_message()``-style fields (``t`` included).
    ``wheel_wear``: include the per-wheel wear work ``W_s_ij, W_alpha_ij, W_t_ij`` when the
    fields have them (False: leave them out, for a peer that does not know them).
    ``mac_key``: the grant's state key (:mod:`bridge.link_key`): the state carries ``mac``."""
    m = {"v": VERSION, "seq": int(seq), "t": float(state["t"])}
    for k in BODY_FIELDS:
        m[k] = float(state[k])
    m["delta"] = _floats(state["delta"])
    m["omega_w"] = _floats(state["omega_w"])
    for k in WEAR_FIELDS:
        if k in state:
            m[k] = float(state[k])
    if wheel_wear:
        for k in WHEEL_WEAR_FIELDS:
            if k in state:
                m[k] = _floats(state[k])
    if safe is not None:
        m["safe"] = bool(safe)
    if end is not None:
        m["end"] = bool(end)
    return _signed(m, mac_key)


def encode_cmd(seq: int, t: float, state_seq: int, omega_w, omega_s, *,
               solve_ms: float | None = None, cost: float | None = None,
               mac_key: bytes | None = None) -> bytes:
    """A ``cmd`` message; ``mac_key``: the grant's command key (:mod:`bridge.link_key`):
    the command carries ``mac``."""
    m = {"v": VERSION, "seq": int(seq), "t": float(t), "state_seq": int(state_seq),
         "omega_w": _floats(omega_w), "omega_s": _floats(omega_s)}
    if solve_ms is not None:
        m["solve_ms"] = float(solve_ms)
    if cost is not None and math.isfinite(cost):
        m["cost"] = float(cost)
    return _signed(m, mac_key)


def encode_reference(t, x, y, phi, *, name: str | None = None,
                     relative: bool | None = None) -> bytes:
    m = {"v": VERSION, "t": _floats(t), "x": _floats(x), "y": _floats(y), "phi": _floats(phi)}
    if name is not None:
        m["name"] = str(name)
    if relative is not None:
        m["relative"] = bool(relative)
    return pack(m)


def encode_params(vid: str, vehicle_dict: Mapping, period: float, run_mode: str,
                  n_wheels: int) -> bytes:
    return pack({"v": VERSION, "id": vid, "vehicle": dict(vehicle_dict), "period": float(period),
                 "run_mode": run_mode, "n_wheels": int(n_wheels)})


# ---- decoding -----------------------------------------------------------------------------
def unpack(payload, max_bytes: int) -> dict:
    """msgpack bytes -> a map with string keys, or MessageError (not_msgpack, not_a_map)."""
    if isinstance(payload, memoryview):
        payload = payload.tobytes()
    if not isinstance(payload, (bytes, bytearray)):
        raise MessageError(NOT_MSGPACK, f"payload is {type(payload).__name__}, not bytes")
    if len(payload) > max_bytes:
        raise MessageError(TOO_LARGE, f"payload of {len(payload)} bytes exceeds {max_bytes}")
    if not payload:
        raise MessageError(NOT_MSGPACK, "empty payload")
    try:
        obj = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True, use_list=True)
    except msgpack.ExtraData:
        raise MessageError(NOT_MSGPACK, "trailing bytes after the msgpack object") from None
    except Exception as e:  # FormatError, StackError, UnicodeDecodeError, ValueError, ...
        raise MessageError(NOT_MSGPACK, f"cannot decode ({type(e).__name__}: {e})") from None
    if not isinstance(obj, dict):
        raise MessageError(NOT_A_MAP, f"expected a map, got {type(obj).__name__}")
    return obj


def _check_version(m: dict, version: int = VERSION) -> None:
    if "v" not in m:
        raise MessageError(VERSION_MISMATCH, "no schema version field 'v'")
    v = m["v"]
    if isinstance(v, bool) or not isinstance(v, int) or v != version:
        raise MessageError(VERSION_MISMATCH, f"schema version v = {v!r}, this side speaks {version}")


def _number(name: str, val) -> float:
    if isinstance(val, bool) or not isinstance(val, (int, float)):
        raise MessageError(BAD_TYPE, f"{name} must be a number, got {type(val).__name__}")
    f = float(val)
    if not math.isfinite(f):
        raise MessageError(NON_FINITE, f"{name} is {f}")
    return f


def _array(name: str, val, n: int, nonneg: bool) -> list[float]:
    if not isinstance(val, list):
        raise MessageError(BAD_TYPE, f"{name} must be an array, got {type(val).__name__}")
    if len(val) != n:
        raise MessageError(BAD_LENGTH, f"{name} has {len(val)} entries, the vehicle has {n} wheels")
    out = [_number(f"{name}[{i}]", x) for i, x in enumerate(val)]
    if nonneg:
        for i, x in enumerate(out):
            if x < 0:
                raise MessageError(NEGATIVE_WHEEL_SPEED, f"{name}[{i}] = {x} < 0")
    return out


def fields(m: dict, required: dict, optional: dict, n: int | None,
           version: int = VERSION) -> dict:
    """Validate the map ``m`` against its field tables (schema version ``version``, wheel
    arrays of ``n`` entries); the checks and their order of docs/PROTOCOL.md section 5."""
    _check_version(m, version)
    missing = [k for k in required if k not in m]
    if missing:
        raise MessageError(MISSING_FIELD, f"missing field(s) {', '.join(missing)}")
    extra = sorted(str(k) for k in m if k not in required and k not in optional)
    if extra:
        raise MessageError(EXTRA_FIELD, f"unknown field(s) {', '.join(extra)}")
    out: dict[str, Any] = {}
    for k, val in m.items():
        kind = required.get(k) or optional[k]
        if kind == "int":
            if isinstance(val, bool) or not isinstance(val, int):
                raise MessageError(BAD_TYPE, f"{k} must be an integer, got {type(val).__name__}")
            if val < 0 or val >= 2 ** 63:
                raise MessageError(BAD_VALUE, f"{k} = {val} outside [0, 2^63)")
            out[k] = int(val)
        elif kind == "float":
            out[k] = _number(k, val)
        elif kind == "float+":
            out[k] = _number(k, val)
            if out[k] < 0:
                raise MessageError(BAD_VALUE, f"{k} = {out[k]} < 0")
        elif kind in ("wheels", "wheels+"):
            out[k] = _array(k, val, n, nonneg=kind == "wheels+")
        elif kind == "bool":
            if not isinstance(val, bool):
                raise MessageError(BAD_TYPE, f"{k} must be true or false, got {type(val).__name__}")
            out[k] = val
        elif kind == "str":
            if not isinstance(val, str):
                raise MessageError(BAD_TYPE, f"{k} must be a string, got {type(val).__name__}")
            out[k] = val
        elif kind == "bin":
            if not isinstance(val, bytes):
                raise MessageError(BAD_TYPE, f"{k} must be binary, got {type(val).__name__}")
            if len(val) > MAX_BIN:
                raise MessageError(BAD_LENGTH, f"{k} has {len(val)} bytes (at most {MAX_BIN})")
            out[k] = val
        elif kind == "map":
            if not isinstance(val, dict):
                raise MessageError(BAD_TYPE, f"{k} must be a map, got {type(val).__name__}")
            out[k] = val
        elif kind == "series":
            if not isinstance(val, list):
                raise MessageError(BAD_TYPE, f"{k} must be an array, got {type(val).__name__}")
            out[k] = [_number(f"{k}[{i}]", x) for i, x in enumerate(val)]
        else:  # pragma: no cover - table error
            raise AssertionError(kind)
    return out


def decode_state(payload, n_wheels: int) -> dict:
    """Validate a ``state`` message for a vehicle with ``n_wheels`` (= 2n) wheels."""
    return fields(unpack(payload, MAX_STATE_BYTES), STATE_REQUIRED, STATE_OPTIONAL, n_wheels)


def decode_cmd(payload, n_wheels: int) -> dict:
    """Validate a ``cmd`` message (the state it answers is checked by the plant)."""
    return fields(unpack(payload, MAX_CMD_BYTES), CMD_REQUIRED, CMD_OPTIONAL, n_wheels)


def decode_reference(payload) -> dict:
    """Validate a ``reference`` message: equal lengths >= 3, t strictly increasing."""
    m = fields(unpack(payload, MAX_REFERENCE_BYTES), REFERENCE_REQUIRED, REFERENCE_OPTIONAL,
                None)
    n = len(m["t"])
    for k in ("x", "y", "phi"):
        if len(m[k]) != n:
            raise MessageError(BAD_LENGTH, f"{k} has {len(m[k])} samples, t has {n}")
    if not 3 <= n <= MAX_REFERENCE_SAMPLES:
        raise MessageError(BAD_LENGTH, f"a reference needs 3..{MAX_REFERENCE_SAMPLES} samples, got {n}")
    t = m["t"]
    for i in range(1, n):
        if not t[i] > t[i - 1]:
            raise MessageError(BAD_VALUE, f"t must increase strictly (t[{i}] = {t[i]} after {t[i - 1]})")
    return m


def decode_params(payload) -> dict:
    """Validate a ``params`` reply; the vehicle itself is checked by ``vehicle_from_dict``."""
    m = fields(unpack(payload, MAX_PARAMS_BYTES), PARAMS_REQUIRED, PARAMS_OPTIONAL, None)
    if m["run_mode"] not in RUN_MODES:
        raise MessageError(BAD_VALUE, f"run_mode '{m['run_mode']}' is not one of {RUN_MODES}")
    if not m["period"] > 0:
        raise MessageError(BAD_VALUE, f"period must be > 0, got {m['period']}")
    if m["n_wheels"] < 2 or m["n_wheels"] % 2:
        raise MessageError(BAD_VALUE, f"n_wheels must be 2n >= 2, got {m['n_wheels']}")
    return m


# ---- counting and logging rejections ------------------------------------------------------
class Rejections:
    """Counts rejected messages by reason and logs them (rate-limited).

    The first ``first`` rejections of each reason are logged with their detail, then one in
    ``every`` (with the running count), so a flood cannot swamp the log; the counts are
    exact. Thread-safe (zenoh calls back from its own threads).
    """

    def __init__(self, who: str, logger: logging.Logger | None = None, first: int = 5,
                 every: int = 1000):
        self.who = who
        self.log = logger or logging.getLogger("msagv.bridge")
        self.first = first
        self.every = every
        self.by_reason: dict[str, int] = {}
        self.by_key: dict[str, int] = {}
        self._lock = threading.Lock()

    def add(self, err: MessageError, key: str = "") -> None:
        self.add_reason(err.reason, key, err.detail)

    def add_reason(self, reason: str, key: str, detail) -> None:
        """Count a rejection; ``detail`` is a string or a function making it, called only
        when the rejection is logged (a flood then costs a count, not a message each)."""
        with self._lock:
            n = self.by_reason.get(reason, 0) + 1
            self.by_reason[reason] = n
            if key:
                self.by_key[key] = self.by_key.get(key, 0) + 1
        if n <= self.first or n % self.every == 0:
            suffix = "" if n <= self.first else f" ({n} so far)"
            self.log.warning("%s: rejected %s: %s: %s%s", self.who, key or "message", reason,
                             detail() if callable(detail) else detail, suffix)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.by_reason.values())

    def summary(self) -> dict:
        with self._lock:
            return {"total": sum(self.by_reason.values()), "by_reason": dict(self.by_reason),
                    "by_key": dict(self.by_key)}
