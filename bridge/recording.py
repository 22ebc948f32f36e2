"""Recordings: every message a process sends or receives, with its time, as a msgpack stream.

A recording is a file of concatenated msgpack maps (no framing beyond msgpack's own):

1. a header ``{"rec": "msagv-recording", "v": 1, "role", "id", "started", "vehicle",
   "period", "run_mode", "reference", ...}``;
2. one map per message: ``{"ts": receive or send time [s, Unix epoch], "dir": "rx"|"tx",
   "key": key expression, "p": the raw payload bytes}`` plus ``"why"`` (the rejection
   reason) for a rejected message; payloads are kept raw, so a rejected or foreign message
   is recorded exactly as it arrived;
3. events ``{"ts", "ev": name, ...}`` (liveliness changes, safe mode, new run, ...);
4. a summary ``{"ts", "summary": {...}}`` written on a clean exit (also on Ctrl-C/SIGTERM).

The file is flushed at least every ``flush_s`` seconds, so a killed process loses at most
that much; a truncated last record is ignored on reading. docs/PROTOCOL.md describes the
format for other tools.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import msgpack

from . import messages as M

MAGIC = "msagv-recording"
REC_VERSION = 1


class RecordingError(ValueError):
    """A file that is not a recording (the message says why)."""


class Recorder:
    """Append-only, thread-safe msgpack-stream writer (see the module docstring)."""

    def __init__(self, path: str | Path, header: dict, flush_s: float = 0.5):
        self.path = Path(path)
        self._f = self.path.open("wb", buffering=1 << 20)
        self._lock = threading.Lock()
        self._flush_s = flush_s
        self._last_flush = time.monotonic()
        self._packer = msgpack.Packer(use_bin_type=True)
        self.count = 0
        h = {"rec": MAGIC, "v": REC_VERSION, "started": time.time()}
        h.update(header)
        self._write(h)
        self.flush()

    def _write(self, rec: dict) -> None:
        data = self._packer.pack(rec)
        with self._lock:
            if self._f is None:
                return
            self._f.write(data)
            self.count += 1

    def message(self, direction: str, key: str, payload: bytes, ts: float | None = None,
                why: str | None = None) -> None:
        rec: dict[str, Any] = {"ts": time.time() if ts is None else ts, "dir": direction,
                               "key": key, "p": bytes(payload)}
        if why is not None:
            rec["why"] = why
        self._write(rec)

    def event(self, name: str, **fields) -> None:
        rec = {"ts": time.time(), "ev": name}
        rec.update(fields)
        self._write(rec)

    def maybe_flush(self) -> None:
        """Flush if ``flush_s`` has passed (call from an idle point of a loop)."""
        if time.monotonic() - self._last_flush >= self._flush_s:
            self.flush()

    def flush(self) -> None:
        with self._lock:
            if self._f is not None:
                self._f.flush()
        self._last_flush = time.monotonic()

    def close(self, summary: dict | None = None) -> None:
        if summary is not None:
            self._write({"ts": time.time(), "summary": summary})
        with self._lock:
            f, self._f = self._f, None
        if f is not None:
            f.flush()
            f.close()


def iter_records(path: str | Path) -> Iterator[dict]:
    """Every record of a recording, header first. A truncated last record (a killed
    writer) ends the iteration quietly; anything else malformed raises RecordingError."""
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such file")
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
    """Valid states and commands of each run (a run starts at seq 0 or when seq decreases).
    Records carrying a rejection reason (``why``) are skipped, as the process skipped them."""
    nw = len(header["vehicle"]["axle_x"]) * 2
    runs: list[RecordedRun] = []
    cur: RecordedRun | None = None
    last = None
    pending_refs: list = []
    for r in records:
        key = r.get("key")
        if key is None or "why" in r:
            continue
        if key.endswith("/state"):
            try:
                st = M.decode_state(r["p"], nw)
            except M.MessageError:
                continue
            seq = st["seq"]
            if cur is None or seq == 0 and cur.states or (last is not None and seq < last):
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
