"""Recordings in MCAP (issue 14 item 2) and a recorder that never stops control (issue 13
item 4): read back with the ``mcap`` library's own reader, raw wire bytes kept, rejected
payloads as size and hash, rotation, write errors counted and never raised, the first
(msgpack-stream) format still read, an unwritable path refused before start-up, and the
real-time plant under a full disk and a 50 MB command."""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import subprocess
import time

import msgpack
import pytest

from msagv.bridge import messages as M
from msagv.bridge.recording import (MCAP_MAGIC, Recorder, RecordingError, check_writable,
                              iter_records, part_path, read_recording, recording_format,
                              split_runs)
from helpers import ep, free_port, msagv
from msagv.plant import Plant, default_vehicle

KEY_STATE, KEY_CMD = "msagv/t/state", "msagv/t/cmd"


def _states(n: int, wheel_wear: bool = True) -> list[bytes]:
    p = Plant(initial={"vx": 3.0})
    r = p.vehicle.wheel_radius
    out = []
    for k in range(n):
        st = p.state_message()
        st["t"] = k * 0.01
        out.append(M.encode_state(k, st, wheel_wear=wheel_wear))
        p.set_inputs([3.1 / r] * 4, [0.05, 0.05, -0.05, -0.05])
        p.do_step(p.t, 0.01)
    return out


def _cmd(k: int) -> bytes:
    return M.encode_cmd(k, k * 0.01, k, [6.0] * 4, [0.0] * 4, solve_ms=1.5)


def _header() -> dict:
    return {"role": "plant", "id": "t", "vehicle": default_vehicle().to_dict(), "period": 0.01,
            "run_mode": "lockstep", "reference": {"t": [0, 1, 2], "x": [0, 1, 2],
                                                  "y": [0, 0, 0], "phi": [0, 0, 0]}}


def _record(path, states, **kw) -> dict:
    rec = Recorder(path, _header(), flush_s=0.05, **kw)
    for k, s in enumerate(states):
        rec.message("tx", KEY_STATE, s, ts=1000.0 + k * 0.01)
        rec.message("rx", KEY_CMD, _cmd(k), ts=1000.0 + k * 0.01 + 0.002)
    rec.event("safe", on=True, t=0.5, why="test")
    return rec.close({"steps": len(states)})


def test_an_mcap_recording_read_by_the_mcap_library(tmp_path):
    from mcap.reader import make_reader

    states = _states(60)
    path = tmp_path / "r.mcap"
    stats = _record(path, states)
    assert stats["errors"] == 0 and stats["dropped"] == 0 and stats["records"] == 122
    assert path.read_bytes()[:8] == MCAP_MAGIC and recording_format(path) == "mcap"
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        chans = {c.topic: c for c in summary.channels.values()}
        schemas = summary.schemas
        assert chans[KEY_STATE].message_encoding == "msgpack"
        assert chans[KEY_STATE].metadata["dir"] == "tx" and chans[KEY_CMD].metadata["dir"] == "rx"
        st_schema = schemas[chans[KEY_STATE].schema_id]
        assert (st_schema.name, st_schema.encoding) == ("msagv.state", "jsonschema")
        js = json.loads(st_schema.data)
        assert set(js["required"]) == set(M.STATE_REQUIRED)
        assert "W_s_ij" in js["properties"] and js["additionalProperties"] is False
        assert schemas[chans[KEY_CMD].schema_id].name == "msagv.cmd"
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert json.loads(meta["msagv.header"]["role"]) == "plant"
        assert json.loads(meta["msagv.summary"]["summary"]) == {"steps": 60}
        got = [(c.topic, m.log_time, m.data) for _, c, m in reader.iter_messages()
               if c.topic == KEY_STATE]
    # the raw wire bytes, each with its time
    assert [g[2] for g in got] == states
    assert [g[1] for g in got] == [int((1000.0 + k * 0.01) * 1e9) for k in range(60)]
    # the per-wheel wear decoded from a recorded state sums to the totals
    st = M.decode_state(got[-1][2], 4)
    for q in ("W_s", "W_alpha", "W_t"):
        assert sum(st[f"{q}_ij"]) == pytest.approx(st[q], rel=1e-12) and st[q] > 0


def test_msagv_reads_its_mcap_recording_as_records_and_runs(tmp_path):
    states = _states(30)
    path = tmp_path / "r.mcap"
    _record(path, states)
    header, recs, summary = read_recording(path)
    assert header["role"] == "plant" and header["rec"] == "msagv-recording"
    assert summary == {"steps": 30}
    msgs = [r for r in recs if "p" in r]
    assert [r["p"] for r in msgs if r["key"] == KEY_STATE] == states
    assert [r for r in recs if r.get("ev") == "safe"][0]["why"] == "test"
    runs = split_runs(header, recs)
    assert len(runs) == 1 and sorted(runs[0].states) == list(range(30))
    assert runs[0].cmds[7]["omega_w"] == [6.0] * 4


def test_state_0_sent_again_before_any_step_is_one_run_and_a_new_state_0_another():
    """A realtime plant sends an unanswered state 0 again (every 1 s): still the run it
    began; a state 0 after later states (a plant reset, a new process) begins a new run."""
    states = _states(5)
    recs = [{"key": KEY_STATE, "p": s, "ts": float(i)}
            for i, s in enumerate([states[0], states[0], states[0]] + states[1:]
                                  + states[:3])]
    runs = split_runs(_header(), recs)
    assert [sorted(r.states) for r in runs] == [[0, 1, 2, 3, 4], [0, 1, 2]]
    assert runs[0].state_ts[0] == 0.0  # the first copy's time


def test_a_rejected_payload_is_recorded_as_size_and_hash_not_raw(tmp_path):
    path = tmp_path / "r.mcap"
    big = os.urandom(1 << 20) * 50  # 50 MiB
    rec = Recorder(path, _header())
    rec.message("rx", KEY_CMD, big, why=M.NOT_MSGPACK)
    rec.message("rx", KEY_CMD, b"\xc1", why=M.NOT_MSGPACK)
    stats = rec.close({})
    assert stats["rejected"] == 2 and stats["errors"] == 0
    assert path.stat().st_size < 64 * 1024
    _, recs, _ = read_recording(path)
    rej = [r for r in recs if "why" in r]
    assert [r["size"] for r in rej] == [len(big), 1]
    assert rej[0]["sha256"] == hashlib.sha256(big).hexdigest()
    assert all("p" not in r for r in rej)


def test_rotation_continues_in_numbered_parts_and_keeps_the_newest(tmp_path):
    states = _states(400)
    path = tmp_path / "r.mcap"
    stats = _record(path, states, max_bytes=16 * 1024)
    assert len(stats["files"]) >= 3 and stats["errors"] == 0
    assert stats["files"][:2] == [str(path), str(part_path(path, 1))]
    assert part_path(path, 2).name == "r.2.mcap"
    _, recs, summary = read_recording(path)  # the parts follow the first file
    assert [r["p"] for r in recs if r.get("key") == KEY_STATE] == states
    assert summary == {"steps": 400}
    # a stale part of an earlier recording is not taken for this one's
    stale = tmp_path / "s.mcap"
    _record(stale, states[:5])
    shutil.copy(part_path(path, 1), part_path(stale, 1))
    assert len([r for r in read_recording(stale)[1] if r.get("key") == KEY_STATE]) == 5
    # keep = 2: only the newest two files stay on disk
    kept = tmp_path / "k.mcap"
    stats = _record(kept, states, max_bytes=16 * 1024, keep=2)
    on_disk = {str(p) for p in tmp_path.glob("k*.mcap")}
    assert len(on_disk) == 2 and set(stats["files"]) == on_disk
    assert str(kept) not in on_disk  # the oldest went first
    # each part is a recording of its own (header, schemas, channels)
    last = stats["files"][-1]
    header, recs, summary = read_recording(last)
    assert header["role"] == "plant" and summary == {"steps": 400}
    assert [r["p"] for r in recs if r.get("key") == KEY_STATE] == states[-len(
        [r for r in recs if r.get("key") == KEY_STATE]):]


def test_a_write_error_is_counted_never_raised(tmp_path):
    """/dev/full fails every write with ENOSPC (a full disk)."""
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    rec = Recorder("/dev/full", _header(), flush_s=0.02)
    for k, s in enumerate(_states(20)):
        rec.message("tx", KEY_STATE, s)
        time.sleep(0.005)
    stats = rec.close({"steps": 20})
    assert stats["errors"] >= 1 and "No space left" in stats["last_error"]
    assert stats["records"] + stats["dropped"] >= 20


def test_a_full_queue_drops_and_counts_never_blocks(tmp_path):
    rec = Recorder(tmp_path / "r.mcap", _header(), queue_items=8)
    payload = _states(1)[0]
    t0 = time.perf_counter()
    for _ in range(20000):
        rec.message("tx", KEY_STATE, payload)
    put_s = time.perf_counter() - t0
    stats = rec.close({})
    assert stats["dropped"] > 0 and stats["records"] + stats["dropped"] == 20001
    assert stats["queue_peak"] <= 8
    assert put_s < 20.0  # the producer never waited on the writer (a loose sanity bound)


def test_a_killed_writer_leaves_a_readable_recording(tmp_path):
    states = _states(50)
    path = tmp_path / "r.mcap"
    rec = Recorder(path, _header(), flush_s=0.05)
    for k, s in enumerate(states):
        rec.message("tx", KEY_STATE, s)
    assert rec.flush()
    cut = tmp_path / "cut.mcap"
    shutil.copy(path, cut)  # the file as a SIGKILL would leave it (no footer)
    rec.close({})
    header, recs, summary = read_recording(cut)
    assert summary is None and [r["p"] for r in recs] == states
    data = cut.read_bytes()
    (tmp_path / "cut2.mcap").write_bytes(data[:-7])  # and cut inside the last chunk
    assert read_recording(tmp_path / "cut2.mcap")[0]["role"] == "plant"


def test_the_first_msgpack_stream_format_is_still_read(tmp_path):
    """A recording of the first format, written here from PROTOCOL.md's old section 9."""
    states = _states(10, wheel_wear=False)
    path = tmp_path / "old.msgpack"
    pk = msgpack.Packer(use_bin_type=True)
    with path.open("wb") as f:
        f.write(pk.pack(dict(_header(), rec="msagv-recording", v=1, started=1.0)))
        for k, s in enumerate(states):
            f.write(pk.pack({"ts": 5.0 + k, "dir": "tx", "key": KEY_STATE, "p": s}))
        f.write(pk.pack({"ts": 3.0, "dir": "rx", "key": KEY_CMD, "p": b"\xc1", "why": "not_msgpack"}))
        f.write(pk.pack({"ts": 20.0, "summary": {"steps": 10}}))
    assert recording_format(path) == "msgpack"
    header, recs, summary = read_recording(path)
    assert header["v"] == 1 and summary == {"steps": 10}
    assert [r["p"] for r in recs if "why" not in r] == states
    assert len(split_runs(header, recs)[0].states) == 10
    assert next(iter_records(path))["role"] == "plant"


@pytest.mark.parametrize("content, why", [(b"", "empty"), (b"hello world", "not an msagv"),
                                          (MCAP_MAGIC + b"\x00" * 3, "empty or truncated")])
def test_not_a_recording_is_one_clear_error(tmp_path, content, why):
    p = tmp_path / "x.mcap"
    p.write_bytes(content)
    with pytest.raises(RecordingError, match=why):
        read_recording(p)


def test_unwritable_paths_are_refused_in_one_line(tmp_path):
    with pytest.raises(RecordingError, match="is a directory"):
        check_writable(tmp_path)
    with pytest.raises(RecordingError, match="cannot be written"):
        check_writable("/proc/msagv-test.mcap")
    ok = tmp_path / "new.mcap"
    check_writable(ok)
    assert not ok.exists()  # the check leaves nothing behind
    with pytest.raises(RecordingError, match="cannot be written"):
        Recorder("/proc/msagv-test.mcap", _header())


@pytest.mark.parametrize("cmd", ["plant", "controller"])
def test_an_unwritable_record_path_is_refused_before_start_up(cmd):
    t0 = time.monotonic()
    out = subprocess.run(msagv(cmd, "--record", "/proc/msagv/x.mcap", "--wait", "1"),
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    err = out.stderr.strip().splitlines()
    assert len(err) == 1 and "--record" in err[0] and "Traceback" not in out.stderr, out.stderr
    out = subprocess.run(msagv(cmd, "--record", "/proc/x.mcap", "--wait", "1"),
                         capture_output=True, text=True, timeout=120)
    # (tried by the command line's check of every output path, before the recorder's own)
    assert out.returncode == 2 and "cannot write in /proc" in out.stderr, out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    assert time.monotonic() - t0 < 60


# ---- the real-time plant, over Zenoh ------------------------------------------------------
def _realtime_pair(procs, tmp_path, record, seconds, plant_prefix=(), extra=()):
    P = free_port()
    Plant().warmup()  # the kernels are in numba's cache before a limited process starts
    procs.start("plant", [*plant_prefix, *msagv(
        "plant", "--run-mode", "realtime", "--duration", seconds, "--listen", ep(P),
        "--record", record, "--json", "-q", *extra)])
    procs.start("ctl", msagv("controller", "--connect", ep(P), "--exit-at-end", "--json", "-q"))
    return P


def _full_disk_run(procs, tmp_path, seconds: float):
    """``ulimit -f`` in the plant's process at 80 % of the same run's recording on a
    writable disk (just before): the recording hits the limit about half-way through the
    real-time run (the header, which holds the whole reference, is ~290 KiB of the ~500
    KiB of a 6 s run; a fixed 300 KiB limit left room for only ~40 messages, too few to test
    the prefix on a loaded machine). Returns the plant's summaries (writable, full disk),
    the recording and its size limit."""
    base = tmp_path / "base.mcap"
    _realtime_pair(procs, tmp_path, base, seconds)
    assert procs.wait("plant", 240) == 0, procs.err("plant")[-3000:]
    # (the controller ended with SIGABRT here once in a cold clean clone's make test, not
    # reproduced in 12 runs after; its stderr is what tells why)
    assert procs.wait("ctl", 60) == 0, procs.err("ctl")[-3000:]
    s0 = procs.json("plant")
    assert s0["recording"]["errors"] == 0 and s0["recording"]["dropped"] == 0
    limit_kib = int(0.8 * os.path.getsize(base) / 1024)
    rec = tmp_path / "plant.mcap"
    _realtime_pair(procs, tmp_path, rec, seconds,
                   plant_prefix=("bash", "-c", f'ulimit -f {limit_kib}; exec "$@"', "bash"))
    rc = procs.wait("plant", 240)
    assert rc == 0, procs.err("plant")[-3000:]
    assert procs.wait("ctl", 60) == 0, procs.err("ctl")[-3000:]
    s = procs.json("plant")
    print(f"\nfull disk ({seconds:g} s): missed periods {s['missed_periods']} (writable disk: "
          f"{s0['missed_periods']}), jitter {s['period_jitter_ms']} (writable disk: "
          f"{s0['period_jitter_ms']}), recording {s['recording']}")
    return s0, s, rec, limit_kib


@pytest.mark.timeout(400)
def test_full_disk_mid_run_realtime_plant_keeps_stepping_and_exits_0(procs, tmp_path):
    """The plant logs and counts the write error, keeps stepping to the end of its run and
    exits 0 with its summary (before, it died with an OSError); what was written before
    the limit is a readable recording. What the design guarantees is asserted: the error
    ends the recording, never the run (its missed periods are printed: on a loaded 2-core
    machine they are the load's, not the disk's, and the slow test compares them)."""
    s0, s, rec, limit_kib = _full_disk_run(procs, tmp_path, 6)
    r = s["recording"]
    assert s["completed"] and s["steps"] == 600 and s["error"] is None
    assert r["errors"] >= 1 and "File too large" in r["last_error"], r
    assert r["dropped"] > 0 and os.path.getsize(rec) <= limit_kib * 1024
    assert "recording" in procs.err("plant") and "Traceback" not in procs.err("plant")
    header, recs, _ = read_recording(rec)
    assert header["role"] == "plant"
    assert sum(1 for x in recs if x.get("key") == "msagv/agv0/state") > 20


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_full_disk_realtime_plant_keeps_its_period(procs, tmp_path):
    """100 Hz kept with a full disk: within the writable run's missed periods plus noise
    (a timing comparison: slow, for a machine that is not saturated by other work)."""
    s0, s, _, _ = _full_disk_run(procs, tmp_path, 20)
    assert s["completed"] and s["recording"]["errors"] >= 1
    assert s["missed_periods"] <= 2 * s0["missed_periods"] + 20, (s["missed_periods"],
                                                                   s0["missed_periods"])


@pytest.mark.timeout(300)
def test_a_50mb_command_does_not_reach_the_recording(procs, tmp_path):
    import zenoh

    from msagv.bridge.session import SessionOptions, open_session

    rec = tmp_path / "plant.mcap"
    P = _realtime_pair(procs, tmp_path, rec, 5)
    big = b"\x00" * (50 << 20)
    with open_session(SessionOptions(id="agv0", connect=[ep(P)]), "tool") as s:
        pub = s.declare_publisher("msagv/agv0/cmd", congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(3.0)  # into the run
        pub.put(big)
        time.sleep(0.5)
        pub.undeclare()
    assert procs.wait("plant", 240) == 0, procs.err("plant")[-3000:]
    assert procs.wait("ctl", 60) == 0
    s = procs.json("plant")
    assert s["completed"] and s["recording"]["errors"] == 0
    size = sum(os.path.getsize(f) for f in s["recording"]["files"])
    assert size < 5 << 20, size  # 500 states and commands; never the 50 MB
    _, recs, _ = read_recording(rec)
    assert all(len(r.get("p", b"")) < 64 * 1024 for r in recs)
    # the plant rejected it (recorded as size and hash), or the transport dropped it first
    rej = [r for r in recs if "why" in r and "key" in r]  # (events carry a why, too)
    big_rej = [r for r in rej if r["size"] == len(big)]
    assert all(r["sha256"] == hashlib.sha256(big).hexdigest() for r in big_rej)
    # any other rejection is the controller's own last answer arriving after its release at
    # the run's end (seen on a loaded machine: the plant took the release, a query, before
    # the command queued ahead of it, 1 ms apart): not_owner, after the 'released' event
    t_released = min((r["ts"] for r in recs if r.get("ev") == "released"), default=math.inf)
    late = [r for r in rej if r["size"] != len(big)]
    assert all(r["why"] == "not_owner" and r["ts"] >= t_released and r["size"] < 4096
               for r in late), (late, t_released)
    print(f"\n50 MB cmd: rejected records {len(rej)}, missed periods {s['missed_periods']}, "
          f"recording {size} bytes")


def test_an_event_may_carry_a_field_called_name(tmp_path):
    """``event(name, **fields)`` takes ``name`` positionally only: the controller records a
    new reference as ``event("reference", t=..., name=ref.name)`` (before, a recording
    controller raised TypeError at its first new reference; so does the do-nothing one)."""
    from msagv.bridge.recording import NullRecorder, Recorder

    rec = Recorder(tmp_path / "r.mcap", header={"role": "controller"}, ros2=False)
    rec.event("reference", t=1.0, name="case1-curve")
    stats = rec.close({})
    assert stats["errors"] == 0 and stats["dropped"] == 0, stats
    NullRecorder().event("reference", t=1.0, name="case1-curve")


def test_a_detached_bag_writer_finishes_quietly_when_its_reader_is_gone():
    """The ROS 2 bag's writer process, detached by a plant stopped by a signal, finds no one
    reading its account at the end: it exits 0 without a traceback (a loaded clean clone's
    full-disk test saw 'BrokenPipeError' in the plant's stderr)."""
    import subprocess
    import sys

    p = subprocess.Popen([sys.executable, "-m", "msagv.bridge.ros_bag"], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    p.stdout.close()  # the reader is gone before the account is written
    _, err = p.communicate(b"", timeout=120)
    assert p.returncode == 0 and b"Traceback" not in err and b"BrokenPipe" not in err, err
