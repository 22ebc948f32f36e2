"""Recordings: every message a process sends or receives, with its time, in MCAP.

A recording is an MCAP file (https://mcap.dev, written with the ``mcap`` library), profile
``msagv``, readable by ``msagv report``, ``msagv view``, the ``mcap`` library and CLI and
robotics viewers (docs/PROTOCOL.md section 9 is the normative description):

* metadata ``msagv.recording`` (``format``, ``version``, ``recording_id``, ``part``) and
  ``msagv.header`` (the process's header: ``role``, ``id``, ``vehicle``, ``period``,
  ``run_mode``, ``reference``, ...; each value JSON-encoded);
* one channel per key expression and direction (topic = the key, e.g. ``msagv/agv0/state``,
  channel metadata ``dir`` = ``tx`` | ``rx``), message encoding ``msgpack``, with the JSON
  schema of the message's map (schema encoding ``jsonschema``, named ``msagv.state``,
  ``msagv.cmd``, ``msagv.reference``, ``msagv.params``; other keys have no schema). Each
  message's data is the raw payload exactly as sent or received (exact replay); its
  ``log_time``/``publish_time`` is the send or receive time [ns, Unix epoch];
* ``recorder/rejected`` (JSON): a rejected payload as its size and SHA-256 with the reason
  and key, never the payload itself (a 50 MB attack does not become 50 MB on disk);
* ``recorder/events`` (JSON): ``{"ev": name, ...}`` (liveliness, safe mode, new run, ...);
* ``recorder/summary`` (JSON) and metadata ``msagv.summary``: the process's summary and
  the recorder's own counters, written at exit (also on Ctrl-C/SIGTERM).

The recorder never stops control: :meth:`Recorder.message` and :meth:`Recorder.event` only
put a record on a bounded queue (a full queue drops the record and counts it); one writer
thread writes, flushes every ``flush_s`` seconds (a killed process loses at most that), and
rotates to ``NAME.1.mcap``, ``NAME.2.mcap``, ... when a file passes ``max_bytes`` (``keep``
> 0 deletes the oldest parts beyond that many). A write error (a full disk, a file-size
limit) is logged and counted, never raised: the recorder stops writing and counts what it
drops. :func:`check_writable` refuses an unusable path before a process starts.

Beside the file, :mod:`bridge.ros_bag` writes the same run as ROS 2 messages in rosbag2's
layout (``NAME_ros2/``, in a child process fed by the writer thread: :meth:`Recorder.predicted_path` adds the
controller's horizon); ``msagv recover`` (:mod:`bridge.recover`) makes a recording cut short
by a kill readable by the standard reader.

Recordings of the first format (a msgpack stream: header, ``{"ts", "dir", "key", "p"}``
messages, events, summary) are still read by :func:`iter_records`/:func:`read_recording`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import queue
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import msgpack

from . import messages as M

log = logging.getLogger("msagv.recording")

MAGIC = "msagv-recording"  # the msgpack-stream format's header tag and the MCAP metadata's
REC_VERSION = 1  # the msgpack-stream format
MCAP_VERSION = 2  # the MCAP layout described above
MCAP_MAGIC = b"\x89MCAP0\r\n"
PROFILE = "msagv"
META_RECORDING = "msagv.recording"
META_HEADER = "msagv.header"
META_SUMMARY = "msagv.summary"
TOPIC_EVENTS = "recorder/events"
TOPIC_REJECTED = "recorder/rejected"
TOPIC_SUMMARY = "recorder/summary"

DEFAULT_MAX_BYTES = 1 << 30  # rotate after 1 GiB per file
DEFAULT_QUEUE_ITEMS = 100_000  # ~ 8 min of a plant's messages at 100 Hz
DEFAULT_QUEUE_BYTES = 256 << 20  # raw payloads waiting to be written


class RecordingError(ValueError):
    """A file that is not a recording, or a path a recording cannot be written to (the
    message says why)."""


# ---- schemas -------------------------------------------------------------------------------
_KIND_SCHEMA = {
    "int": {"type": "integer", "minimum": 0},
    "float": {"type": "number"},
    "float+": {"type": "number", "minimum": 0},
    "wheels": {"type": "array", "items": {"type": "number"}},
    "wheels+": {"type": "array", "items": {"type": "number", "minimum": 0}},
    "bool": {"type": "boolean"},
    "str": {"type": "string"},
    "map": {"type": "object"},
    "series": {"type": "array", "items": {"type": "number"}},
    # msgpack bin (a mac, a key): JSON has no bytes type
    "bin": {"description": "msgpack bin (bytes)"},
}
_MESSAGES = {  # key suffix -> (required, optional, description)
    "state": (M.STATE_REQUIRED, M.STATE_OPTIONAL, "the plant's state (docs/PROTOCOL.md 3.2)"),
    "cmd": (M.CMD_REQUIRED, M.CMD_OPTIONAL, "a command (docs/PROTOCOL.md 3.3)"),
    "params": (M.PARAMS_REQUIRED, M.PARAMS_OPTIONAL, "the plant's params (docs/PROTOCOL.md 3.4)"),
    "reference": (M.REFERENCE_REQUIRED, M.REFERENCE_OPTIONAL,
                  "a reference trajectory (docs/PROTOCOL.md 3.5)"),
}


def message_schema(kind: str) -> dict:
    """The JSON schema of a bus message's msgpack map (``kind``: state, cmd, params,
    reference), from the field tables of :mod:`bridge.messages`."""
    required, optional, text = _MESSAGES[kind]
    props = {k: dict(_KIND_SCHEMA[v]) for k, v in {**required, **optional}.items()}
    if "v" in props:
        props["v"] = {"const": M.VERSION}
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": f"msagv.{kind}", "description": f"{text}; a msgpack map",
            "type": "object", "properties": props, "required": list(required),
            "additionalProperties": False}


_RECORDER_SCHEMAS = {
    TOPIC_EVENTS: {"title": "msagv.event", "type": "object",
                   "properties": {"ts": {"type": "number"}, "ev": {"type": "string"}},
                   "required": ["ts", "ev"]},
    TOPIC_REJECTED: {"title": "msagv.rejected", "type": "object",
                     "properties": {"ts": {"type": "number"}, "dir": {"enum": ["rx", "tx"]},
                                    "key": {"type": "string"}, "why": {"type": "string"},
                                    "size": {"type": "integer"},
                                    "sha256": {"type": "string"}},
                     "required": ["ts", "dir", "key", "why", "size", "sha256"]},
    TOPIC_SUMMARY: {"title": "msagv.summary", "type": "object",
                    "properties": {"ts": {"type": "number"}, "summary": {"type": "object"},
                                   "recorder": {"type": "object"}},
                    "required": ["ts", "summary"]},
}


def _kind(key: str) -> str | None:
    last = key.rsplit("/", 1)[-1]
    return last if last in _MESSAGES else None


def part_path(path: str | Path, n: int) -> Path:
    """The n-th file of a rotated recording: the path itself, then ``NAME.1.mcap``, ..."""
    p = Path(path)
    return p if n == 0 else p.with_name(f"{p.stem}.{n}{p.suffix}")


def check_writable(path: str | Path) -> None:
    """Refuse a recording path that cannot be written (before a process starts): opens
    it for appending (creating it, then removing it again if it did not exist). Raises
    :class:`RecordingError` with a one-line reason."""
    p = Path(path)
    if p.is_dir():
        raise RecordingError(f"{p}: is a directory, expected a file name")
    existed = p.exists()
    try:
        with open(p, "ab"):
            pass
    except OSError as e:
        raise RecordingError(f"{p}: cannot be written ({e.strerror or e})") from None
    if not existed:
        try:
            p.unlink()
        except OSError:
            pass


# ---- writing -------------------------------------------------------------------------------
@dataclass
class RecorderStats:
    """The recorder's counters (also in the summary it writes and returns)."""

    path: str = ""
    files: list = field(default_factory=list)
    records: int = 0  # written to a file
    bytes: int = 0  # on disk, over all files
    dropped: int = 0  # never written: the queue was full, or after a write error
    rejected: int = 0  # rejected payloads, written as size and hash
    errors: int = 0
    last_error: str | None = None
    queue_peak: int = 0
    ros2_bag: str | None = None  # the bag of the ROS 2 channels (bridge.ros_bag)
    ros2_messages: int = 0

    def to_dict(self) -> dict:
        return {"path": self.path, "files": list(self.files), "records": self.records,
                "bytes": self.bytes, "dropped": self.dropped, "rejected": self.rejected,
                "errors": self.errors, "last_error": self.last_error,
                "queue_peak": self.queue_peak, "ros2_bag": self.ros2_bag,
                "ros2_messages": self.ros2_messages}


_STOP = object()


class NullRecorder:
    """A recorder that records nothing: the nodes' default, so that they call their
    recorder unconditionally (:class:`Recorder`'s producer interface: ``message``,
    ``predicted_path``, ``event``, ``maybe_flush``, ``flush``, ``close``)."""

    stats = None

    def message(self, direction: str, key: str, payload, ts: float | None = None,
                why: str | None = None) -> None:
        pass

    def predicted_path(self, t0: float, dt: float, poses) -> None:
        pass

    def event(self, name: str, /, **fields) -> None:
        pass

    def maybe_flush(self) -> None:
        pass

    def flush(self, timeout: float = 10.0) -> bool:
        return True

    def close(self, summary: dict | None = None, timeout: float = 10.0) -> dict:
        return {}


class Recorder:
    """Thread-safe, non-blocking MCAP recorder (see the module docstring).

    ``header``: the process's header map (JSON-serialisable). ``ros2``: also write the
    run's ROS 2 channels, a rosbag2 bag beside the file (:mod:`bridge.ros_bag`; needs the
    header's ``vehicle``). ``max_bytes``: rotate to a
    new file after this many bytes (None: never). ``keep``: keep at most this many files,
    deleting the oldest (0: all). ``queue_items``/``queue_bytes``: the bound of what waits
    to be written. Opening the first file fails with :class:`RecordingError`; everything
    after that only logs and counts.
    """

    def __init__(self, path: str | Path, header: dict, flush_s: float = 0.5,
                 max_bytes: int | None = DEFAULT_MAX_BYTES, keep: int = 0,
                 queue_items: int = DEFAULT_QUEUE_ITEMS, queue_bytes: int = DEFAULT_QUEUE_BYTES,
                 ros2: bool = True):
        if max_bytes is not None and max_bytes < 4096:
            raise RecordingError(f"the recording's file size limit must be >= 4096 bytes, "
                                 f"got {max_bytes}")
        if keep < 0:
            raise RecordingError(f"the number of recording files to keep must be >= 0, got {keep}")
        self.path = Path(path)
        self.header = {"rec": MAGIC, "v": MCAP_VERSION, "started": time.time(), **header}
        self._flush_s = flush_s
        self._max_bytes = max_bytes
        self._keep = keep
        self._queue_bytes_max = queue_bytes
        self._q: queue.Queue = queue.Queue(maxsize=queue_items)
        self._lock = threading.Lock()
        self._queued_bytes = 0
        self._id = uuid.uuid4().hex
        self.stats = RecorderStats(path=str(self.path))
        self._part = 0
        self._failed = False
        self._closed = False
        self._f = None
        self._w = None
        self._channels: dict = {}
        self._schemas: dict = {}
        self._seq: dict = {}
        self._ros = None
        try:
            self._open_part()
        except OSError as e:
            raise RecordingError(f"{self.path}: cannot be written ({e.strerror or e})") from None
        if ros2 and "vehicle" in self.header:  # the same run as ROS 2 messages, beside it
            self._ros = self._open_bag()
        self._thread = threading.Thread(target=self._run, name="msagv-recorder", daemon=True)
        self._thread.start()

    # ---- producers (any thread; never block, never raise) --------------------------------
    def _put(self, item, size: int = 0) -> None:
        with self._lock:
            if self._closed or self._queued_bytes + size > self._queue_bytes_max:
                self.stats.dropped += 1
                return
            try:
                self._q.put_nowait(item)
            except queue.Full:
                self.stats.dropped += 1
                return
            self._queued_bytes += size
            n = self._q.qsize()
            if n > self.stats.queue_peak:
                self.stats.queue_peak = n

    def message(self, direction: str, key: str, payload, ts: float | None = None,
                why: str | None = None) -> None:
        """Record a message sent (``tx``) or received (``rx``) on ``key``; ``why``: the
        rejection reason of a rejected one (recorded as its size and SHA-256 only)."""
        ts = time.time() if ts is None else ts
        try:
            if isinstance(payload, memoryview):
                payload = payload.tobytes()
            if why is not None:
                data = payload if isinstance(payload, (bytes, bytearray)) else bytes(payload)
                rec = {"ts": ts, "dir": direction, "key": key, "why": str(why),
                       "size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
                self._put(("rej", rec))
            else:
                data = bytes(payload)
                self._put(("msg", direction, key, data, ts), len(data))
        except Exception as e:  # a payload that is not bytes-like: counted, never raised
            self._error(f"cannot record a message on {key}: {e}")

    def predicted_path(self, t0: float, dt: float, poses) -> None:
        """The controller's predicted poses (x, y, phi) at t0, t0 + dt, ... (the ROS 2
        channel ``predicted_path`` only)."""
        if self._ros is not None:
            self._put(("pred", float(t0), float(dt), [list(map(float, p)) for p in poses],
                       time.time()))

    def event(self, name: str, /, **fields) -> None:
        rec = {"ts": time.time(), "ev": name}
        rec.update(fields)
        self._put(("ev", rec))

    def maybe_flush(self) -> None:
        """Kept for callers of the first recorder: the writer thread flushes by itself."""

    def flush(self, timeout: float = 10.0) -> bool:
        """Wait until everything queued so far is written and flushed (False: timed out)."""
        done = threading.Event()
        self._put(("sync", done))
        return done.wait(timeout)

    hurry: threading.Event | None = None
    """Set (by the command line: its signal event) when the run was stopped by a signal:
    :meth:`close` then leaves the ROS 2 bag's child to finish on its own instead of waiting
    for it (over a second under load), so the process ends within a second."""

    def close(self, summary: dict | None = None, timeout: float = 10.0) -> dict:
        """Write the summary (with the recorder's counters), finish the file and stop the
        writer. Returns the counters (:class:`RecorderStats` as a dict); never raises."""
        with self._lock:
            if self._closed:
                return self.stats.to_dict()
        item = ("summary", {"ts": time.time(), "summary": summary if summary is not None else {}})
        try:
            self._q.put(item, timeout=timeout)
            self._q.put(_STOP, timeout=timeout)
        except queue.Full:
            self._error("the recording queue stayed full at exit: summary not written")
        with self._lock:
            self._closed = True
        self._thread.join(timeout)
        if self._thread.is_alive():
            self._error(f"the recording writer did not finish within {timeout:g} s")
        return self.stats.to_dict()

    # ---- the writer thread ---------------------------------------------------------------
    def _error(self, text: str) -> None:
        with self._lock:
            self.stats.errors += 1
            self.stats.last_error = text
            n = self.stats.errors
        if n <= 5 or n % 1000 == 0:
            log.error("recording %s: %s (%d recording error(s) so far; control goes on)",
                      self.path, text, n)

    def _run(self) -> None:
        last_flush = time.monotonic()
        while True:
            try:
                item = self._q.get(timeout=self._flush_s)
            except queue.Empty:
                item = None
            if item is _STOP:
                self._finish()
                return
            if item is not None:
                size = len(item[3]) if item[0] == "msg" else 0
                if item[0] == "sync":
                    self._flush()
                    item[1].set()
                else:
                    self._write(item)
                if size:
                    with self._lock:
                        self._queued_bytes -= size
            if time.monotonic() - last_flush >= self._flush_s:
                self._flush()
                last_flush = time.monotonic()

    def _open_part(self) -> None:
        from mcap.writer import Writer

        p = part_path(self.path, self._part)
        f = open(p, "wb")
        # chunks of at most 1 MiB (uncompressed), and small enough that a file ends within
        # about an eighth of its size limit
        chunk = 1 << 20 if self._max_bytes is None else min(1 << 20, max(4096, self._max_bytes // 8))
        self._chunk_size = chunk
        w = Writer(f, chunk_size=chunk)
        w.start(profile=PROFILE, library=f"msagv {_package_version()}")
        w.add_metadata(META_RECORDING, {"format": MAGIC, "version": str(MCAP_VERSION),
                                        "recording_id": self._id, "part": str(self._part)})
        w.add_metadata(META_HEADER, {k: json.dumps(v, default=str) for k, v in self.header.items()})
        self._f, self._w = f, w
        self._channels, self._schemas, self._seq = {}, {}, {}
        self.stats.files.append(str(p))
        if self._keep and len(self.stats.files) > self._keep:
            old = self.stats.files.pop(0)
            try:
                os.unlink(old)
            except OSError as e:
                self._error(f"cannot delete the old part {old}: {e}")

    def _channel(self, topic: str, direction: str | None, encoding: str, schema) -> int:
        ck = (topic, direction)
        cid = self._channels.get(ck)
        if cid is None:
            sid = 0
            if schema is not None:
                name, body = schema
                sid = self._schemas.get(name)
                if sid is None:
                    sid = self._w.register_schema(name=name, encoding="jsonschema",
                                                  data=json.dumps(body).encode())
                    self._schemas[name] = sid
            meta = {"dir": direction} if direction else {}
            meta["role"] = str(self.header.get("role", ""))
            cid = self._w.register_channel(topic=topic, message_encoding=encoding,
                                           schema_id=sid, metadata=meta)
            self._channels[ck] = cid
        return cid

    def _add(self, cid: int, data: bytes, ts: float) -> None:
        n = self._seq.get(cid, 0)
        self._seq[cid] = n + 1
        t = int(ts * 1e9)
        self._w.add_message(channel_id=cid, log_time=t, publish_time=t, data=data, sequence=n)

    def _open_bag(self):
        from .ros_bag import BagProcess, bag_path

        try:
            bag = BagProcess(bag_path(self.path), self.header, chunk_size=self._chunk_size,
                             max_bytes=self._max_bytes, keep=self._keep,
                             library=f"msagv {_package_version()}")
        except Exception as e:  # no interpreter to start: the recording goes on
            log.warning("recording %s: no ROS 2 bag (%s: %s)", self.path, type(e).__name__, e)
            return None
        self.stats.ros2_bag = str(bag.path)
        return bag

    def _bag(self, method: str, *args) -> None:
        """Feed the ROS 2 bag's writer (a child process, :class:`bridge.ros_bag.BagProcess`);
        an error stops the bag (logged, counted), never the recording."""
        if self._ros is None:
            return
        try:
            getattr(self._ros, method)(*args)
            self.stats.ros2_messages = self._ros.messages
        except Exception as e:
            self._error(f"the ROS 2 bag stopped ({type(e).__name__}: {e}); msagv recover "
                        f"{self.path} repairs what was written")
            self._ros.abandon()
            self._ros = None

    def _write(self, item) -> None:
        if self._failed:
            with self._lock:
                self.stats.dropped += 1
            return
        if item[0] == "pred":
            self._bag("predicted", *item[1:])
            return
        try:
            kind = item[0]
            if kind == "msg":
                _, direction, key, data, ts = item
                k = _kind(key)
                schema = (f"msagv.{k}", message_schema(k)) if k else None
                self._add(self._channel(key, direction, "msgpack", schema), data, ts)
                if k is not None:
                    self._bag("record", key, data, ts)
            elif kind in ("rej", "ev", "summary"):
                topic = {"rej": TOPIC_REJECTED, "ev": TOPIC_EVENTS, "summary": TOPIC_SUMMARY}[kind]
                rec = dict(item[1])
                if kind == "summary":
                    rec["recorder"] = self._final_stats()
                name = _RECORDER_SCHEMAS[topic]["title"]
                cid = self._channel(topic, None, "json", (name, _RECORDER_SCHEMAS[topic]))
                self._add(cid, json.dumps(rec, default=str).encode(), rec["ts"])
                if kind == "rej":
                    self.stats.rejected += 1
                if kind == "summary":
                    self._w.add_metadata(META_SUMMARY, {"summary": json.dumps(rec["summary"],
                                                                              default=str),
                                                        "recorder": json.dumps(rec["recorder"])})
            self.stats.records += 1
            if kind != "summary":
                self._maybe_rotate()
        except Exception as e:  # OSError (disk full, file too large), anything else
            self._fail(e)

    def _maybe_rotate(self) -> None:
        # the size on disk grows by whole chunks (at each flush, or every 1 MiB)
        if self._max_bytes is not None and self._f.tell() >= self._max_bytes:
            self._rotate()

    def _final_stats(self) -> dict:
        d = self.stats.to_dict()
        d["records"] += 1  # this summary
        return d

    def _rotate(self) -> None:
        self._w.finish()
        self.stats.bytes += self._f.tell()
        self._f.close()
        self._part += 1
        log.info("recording: %s reached %d bytes, continuing in %s", part_path(self.path, self._part - 1),
                 self._max_bytes, part_path(self.path, self._part))
        self._open_part()

    def _fail(self, e: Exception) -> None:
        self._failed = True
        msg = f"{type(e).__name__}: {e}" if not isinstance(e, OSError) else \
            f"{e.strerror or e}" + (f" (errno {e.errno})" if e.errno else "")
        self._error(f"writing failed, recording stopped after {self.stats.records} records: "
                    f"{msg}")
        try:
            self.stats.bytes += self._f.tell()
        except Exception:
            pass
        try:
            self._f.close()
        except Exception:
            pass
        if self._ros is not None:
            self._ros.abandon()
            self._ros = None

    def _flush(self) -> None:
        if self._failed:
            return
        try:
            self._w.flush()
            self._maybe_rotate()
        except Exception as e:
            self._fail(e)
        self._bag("flush")

    def _finish(self) -> None:
        if self._failed:
            return
        try:
            self._w.finish()
            self.stats.bytes += self._f.tell()
            self._f.close()
        except Exception as e:
            self._fail(e)
        self._bag("detach" if self.hurry is not None and self.hurry.is_set() else "close")


def _package_version() -> str:
    try:
        from importlib.metadata import version

        return version("msagv")
    except Exception:
        return "0+unknown"


# ---- reading -------------------------------------------------------------------------------
def recording_format(path: str | Path) -> str:
    """``"mcap"`` or ``"msgpack"`` (the first format), by the file's first bytes."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such file")
    with p.open("rb") as f:
        head = f.read(len(MCAP_MAGIC))
    return "mcap" if head == MCAP_MAGIC else "msgpack"


def iter_records(path: str | Path) -> Iterator[dict]:
    """Every record of a recording as a map, header first (the shapes of the first
    format: ``{"ts", "dir", "key", "p"}`` for a message, plus ``"why"``, ``"size"``,
    ``"sha256"`` and no ``"p"`` for a rejected one; ``{"ts", "ev", ...}``;
    ``{"ts", "summary"}``). A truncated end (a killed writer, a full disk) ends the
    iteration quietly; anything else malformed raises :class:`RecordingError`. An MCAP
    recording's rotated parts (``NAME.1.mcap``, ...) follow its first file."""
    if recording_format(path) == "mcap":
        yield from _iter_mcap(Path(path))
    else:
        yield from _iter_msgpack(Path(path))


def _iter_msgpack(p: Path) -> Iterator[dict]:
    with p.open("rb") as f:
        up = msgpack.Unpacker(f, raw=False, strict_map_key=False, max_buffer_size=64 << 20)
        first = True
        while True:
            try:
                rec = up.unpack()
            except msgpack.OutOfData:
                if first:
                    raise RecordingError(f"{p}: empty or truncated header") from None
                return
            except Exception as e:
                raise RecordingError(f"{p}: corrupt record ({type(e).__name__}: {e})") from None
            if first:
                if not (isinstance(rec, dict) and rec.get("rec") == MAGIC):
                    raise RecordingError(f"{p}: not an msagv recording (no header)")
                if rec.get("v") != REC_VERSION:
                    raise RecordingError(f"{p}: recording format version {rec.get('v')!r}, "
                                         f"expected {REC_VERSION}")
                first = False
            elif not isinstance(rec, dict):
                raise RecordingError(f"{p}: corrupt record (not a map)")
            yield rec


def _mcap_records(p: Path):
    """(kind, record) of one MCAP file in file order, stopping quietly at a truncated end."""
    from mcap.exceptions import EndOfFile, McapError
    from mcap.records import Channel, Message, Metadata
    from mcap.stream_reader import StreamReader

    size = p.stat().st_size
    with p.open("rb") as f:
        reader = StreamReader(f, skip_magic=False, record_size_limit=1 << 31)
        it = iter(reader.records)
        while True:
            try:
                r = next(it)
            except StopIteration:
                return
            except EndOfFile:
                return
            except (McapError, ValueError, KeyError, EOFError, OSError) as e:
                if f.tell() >= size:  # the last record was cut short
                    return
                raise RecordingError(f"{p}: corrupt MCAP ({type(e).__name__}: {e})") from None
            except Exception as e:  # a truncated compressed chunk (zstd, lz4)
                if f.tell() >= size - (1 << 21):
                    return
                raise RecordingError(f"{p}: corrupt MCAP ({type(e).__name__}: {e})") from None
            if isinstance(r, (Channel, Message, Metadata)):
                yield r


def _parts(p: Path, rid: str | None) -> list[Path]:
    """The first file and the rotated parts that carry the same recording id."""
    out = [p]
    n = 1
    while rid is not None and part_path(p, n).is_file():
        q = part_path(p, n)
        try:
            meta = next((r for r in _mcap_records(q) if type(r).__name__ == "Metadata"
                         and r.name == META_RECORDING), None)
        except RecordingError:
            break
        if meta is None or meta.metadata.get("recording_id") != rid:
            break
        out.append(q)
        n += 1
    return out


def _iter_mcap(p: Path) -> Iterator[dict]:
    from mcap.records import Channel, Message, Metadata

    first = True
    rid = None
    files = [p]
    i = 0
    while i < len(files):
        channels: dict[int, Channel] = {}
        for r in _mcap_records(files[i]):
            if isinstance(r, Metadata):
                if r.name == META_RECORDING:
                    if r.metadata.get("format") != MAGIC:
                        raise RecordingError(f"{files[i]}: not an msagv recording (an MCAP "
                                             f"file of another tool)")
                    if i == 0:
                        rid = r.metadata.get("recording_id")
                        files = _parts(p, rid)
                elif r.name == META_HEADER and first:
                    try:
                        header = {k: json.loads(v) for k, v in r.metadata.items()}
                    except ValueError as e:
                        raise RecordingError(f"{p}: corrupt header ({e})") from None
                    if header.get("v") != MCAP_VERSION:
                        raise RecordingError(f"{p}: recording layout version "
                                             f"{header.get('v')!r}, expected {MCAP_VERSION}")
                    first = False
                    yield header
                continue
            if first:
                raise RecordingError(f"{p}: not an msagv recording (no {META_HEADER} metadata "
                                     f"before the first record)")
            if isinstance(r, Channel):
                channels[r.id] = r
                continue
            ch = channels.get(r.channel_id)
            if ch is None:
                raise RecordingError(f"{files[i]}: a message on unknown channel {r.channel_id}")
            ts = r.log_time / 1e9
            if ch.topic in (TOPIC_EVENTS, TOPIC_REJECTED, TOPIC_SUMMARY):
                try:
                    rec = json.loads(r.data)
                except ValueError as e:
                    raise RecordingError(f"{files[i]}: corrupt {ch.topic} record ({e})") from None
                if ch.topic == TOPIC_SUMMARY:
                    rec = {"ts": rec.get("ts", ts), "summary": rec.get("summary"),
                           "recorder": rec.get("recorder")}
                yield rec
            else:
                yield {"ts": ts, "dir": ch.metadata.get("dir"), "key": ch.topic,
                       "p": bytes(r.data)}
        i += 1
    if first:
        raise RecordingError(f"{p}: empty or truncated header")


def read_recording(path: str | Path) -> tuple[dict, list[dict], dict | None]:
    """``(header, records, summary)``; summary is None if the writer did not close."""
    it = iter_records(path)
    try:
        header = next(it)
    except StopIteration:
        raise RecordingError(f"{path}: empty file") from None
    recs, summary = [], None
    for r in it:
        if "summary" in r:
            summary = r["summary"]
        else:
            recs.append(r)
    return header, recs, summary


# ---- the runs of a recording ---------------------------------------------------------------
@dataclass
class RecordedRun:
    """One plant run (seq from 0) as seen in a recording."""

    states: dict = field(default_factory=dict)  # seq -> decoded state
    cmds: dict = field(default_factory=dict)  # state_seq -> first decoded command answering it
    cmd_ts: dict = field(default_factory=dict)  # state_seq -> its record time
    state_ts: dict = field(default_factory=dict)  # seq -> record time
    references: list = field(default_factory=list)  # (first seq it applies to, message)
    end_seq: int | None = None


def split_runs(header: dict, records: list[dict]) -> list[RecordedRun]:
    """Valid states and commands of each run (a run starts at seq 0 after later states, or
    when seq decreases; state 0 sent again before any step, as a realtime plant does while
    no command has come, is the run it began). Records carrying a rejection reason
    (``why``) are skipped, as the process skipped them."""
    nw = len(header["vehicle"]["axle_x"]) * 2
    runs: list[RecordedRun] = []
    cur: RecordedRun | None = None
    last = None
    pending_refs: list = []
    for r in records:
        key = r.get("key")
        if key is None or "why" in r or "p" not in r:
            continue
        if key.endswith("/state"):
            try:
                st = M.decode_state(r["p"], nw)
            except M.MessageError:
                continue
            seq = st["seq"]
            if cur is None or (seq == 0 and any(cur.states)) or (last is not None
                                                                   and seq < last):
                cur = RecordedRun()
                runs.append(cur)
            last = seq
            if seq in cur.states:  # a state sent again (lockstep, controller restarted)
                continue
            cur.states[seq] = st
            cur.state_ts[seq] = r["ts"]
            for m in pending_refs:
                cur.references.append((seq, m))
            pending_refs = []
            if st.get("end"):
                cur.end_seq = seq
        elif key.endswith("/cmd"):
            try:
                c = M.decode_cmd(r["p"], nw)
            except M.MessageError:
                continue
            if cur is not None and c["state_seq"] in cur.states and c["state_seq"] not in cur.cmds:
                cur.cmds[c["state_seq"]] = c
                cur.cmd_ts[c["state_seq"]] = r["ts"]
        elif key.endswith("/reference"):
            try:
                pending_refs.append(M.decode_reference(r["p"]))
            except M.MessageError:
                continue
    return [r for r in runs if r.states]
