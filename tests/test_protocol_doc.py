"""docs/PROTOCOL.md is enough to write a controller: a minimal one, from the page alone.

The client below uses only ``zenoh``, ``msgpack`` and the standard library (nothing from
bridge/, controller/ or plant/). The harness (tests/helpers.py: a free port, starting and
stopping processes) runs a real ``msagv plant`` in lockstep on a free loopback port, and
the client does the following:

- fetches the vehicle from the params queryable and binds to the plant session that
  answered (states from any other session are ignored);
- claims the vehicle and answers every state with a constant wheel speed and zero
  steering rate, each command carrying its session's source info;
- sends one malformed command for each documented reason code, plus one duplicate and
  one stale command.

Then it checks the plant's ``--json`` summary against what the page says.
"""

from __future__ import annotations

import json
import math
import os
import queue
import subprocess
import time

import msgpack
import pytest
import zenoh

from helpers import free_port, msagv, stop

VID = "agv_doc"  # any id of 1-64 characters of A-Z a-z 0-9 _ . - (PROTOCOL.md section 2)
DURATION = 0.2


# ---- the client: PROTOCOL.md sections 1-5 and 7 -------------------------------------------
def client_config(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return conf


def get_params(session, vid: str, deadline_s: float) -> tuple[dict, str]:
    """Sections 3.4 and 4.7: a get on msagv/{id}/params (every replier, no consolidation),
    retried until exactly one plant session replies; returns the params and its zid."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < deadline_s:
        replies = {}
        for reply in session.get(f"msagv/{vid}/params", target=zenoh.QueryTarget.ALL,
                                 consolidation=zenoh.ConsolidationMode.NONE, timeout=1.0):
            if reply.ok is not None:
                assert str(reply.ok.key_expr) == f"msagv/{vid}/params"
                replies[str(reply.replier_id.zid)] = msgpack.unpackb(
                    reply.ok.payload.to_bytes(), raw=False)
        if len(replies) == 1:
            (zid, params), = replies.items()
            return params, zid
        time.sleep(0.1)
    raise AssertionError(f"no params reply from exactly one plant within {deadline_s} s")


def claim(session, vid: str, pub, plant_zid: str, deadline_s: float) -> dict:
    """Sections 3.7 and 4.7: claim the vehicle (a get on msagv/{id}/claim with our source info)
    until the bound plant grants it."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < deadline_s:
        for reply in session.get(f"msagv/{vid}/claim",
                                 payload=msgpack.packb({"v": 1, "action": "claim"}),
                                 source_info=zenoh.SourceInfo(pub.id, 0), timeout=1.0):
            if reply.ok is not None and str(reply.replier_id.zid) == plant_zid:
                grant = msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
                if grant["granted"]:
                    return grant
        time.sleep(0.25)
    raise AssertionError(f"the vehicle was not granted within {deadline_s} s")


def check_state(st: dict, nw: int, period: float) -> None:
    """The state table of section 3.2, for a lockstep plant."""
    required = {"v", "seq", "t", "x", "y", "phi", "vx", "vy", "r", "delta", "omega_w"}
    optional = {"W_s", "W_alpha", "W_t", "safe", "end"}
    assert required <= set(st) and set(st) <= required | optional, sorted(st)
    assert st["v"] == 1 and isinstance(st["seq"], int) and st["seq"] >= 0
    assert st["t"] == st["seq"] * period  # t = seq T exactly
    for k in ("x", "y", "phi", "vx", "vy", "r"):
        assert isinstance(st[k], float) and math.isfinite(st[k])
    assert len(st["delta"]) == nw and len(st["omega_w"]) == nw
    assert all(w >= 0 for w in st["omega_w"])
    assert "safe" not in st  # realtime only
    assert st.get("end", True) is True  # absent, or true on the last state


def cmd(seq: int, state: dict, nw: int) -> dict:
    """Section 3.3: constant wheel speed, zero steering rate."""
    return {"v": 1, "seq": seq, "t": state["t"], "state_seq": state["seq"],
            "omega_w": [8.0] * nw, "omega_s": [0.0] * nw}


def malformed(good: dict, nw: int, period: float) -> list[tuple[bytes, str]]:
    """The examples of section 5. ``good`` answers a state that has been published."""
    pk = msgpack.packb
    return [
        (b"\xc1", "not_msgpack"),
        (pk([1, 2, 3]), "not_a_map"),
        (pk(dict(good, v=2)), "version"),
        (pk({k: good[k] for k in good if k != "omega_s"}), "missing_field"),
        (pk(dict(good, surplus=1.0)), "extra_field"),
        (pk(dict(good, t=str(good["t"]))), "type"),
        (pk(dict(good, omega_s=[0.0] * (nw - 1))), "length"),
        (pk(dict(good, omega_w=[float("nan")] + [8.0] * (nw - 1))), "non_finite"),
        (pk(dict(good, omega_w=[-1.0] + [8.0] * (nw - 1))), "negative_wheel_speed"),
        (pk(dict(good, seq=-1)), "value"),
        (pk(dict(good, state_seq=10 ** 6, t=10 ** 6 * period)), "unknown_state"),
        (pk(dict(good, t=good["t"] + 0.25)), "t_mismatch"),
    ]


def run_controller(port: int, vid: str, plant: subprocess.Popen, bad_at: int = 3) -> dict:
    """Run a lockstep controller to the plant's end state. Returns what it saw and did."""
    states: queue.Queue = queue.Queue()
    seen: list[dict] = []
    sent_bad: dict[str, int] = {}
    with zenoh.open(client_config(port)) as session:
        params, plant_zid = get_params(session, vid, deadline_s=60.0)
        nw, period = params["n_wheels"], params["period"]

        def on_state(s):  # only the bound plant's states (section 4.7)
            if s.source_info is not None and str(s.source_info.source_id.zid) == plant_zid:
                states.put(s.payload.to_bytes())

        # subscriber and publisher first, then the token, then the claim (sections 4, 4.7)
        sub = session.declare_subscriber(f"msagv/{vid}/state", on_state)
        pub = session.declare_publisher(f"msagv/{vid}/cmd")
        token = session.liveliness().declare_token(
            f"msagv/{vid}/alive/controller/{session.zid()}")
        grant = claim(session, vid, pub, plant_zid, deadline_s=30.0)
        assert grant == {"v": 1, "granted": True, "owner": str(session.zid())}
        alive = [str(r.ok.key_expr) for r in
                 session.liveliness().get(f"msagv/{vid}/alive/plant/{plant_zid}", timeout=2.0)
                 if r.ok is not None]
        n_cmd = 0

        def put(payload: bytes) -> None:  # every command names our session (section 4.7)
            pub.put(payload, source_info=zenoh.SourceInfo(pub.id, n_cmd))

        last_cmd = None  # the accepted answer to the previous state
        try:
            while True:
                try:
                    raw = states.get(timeout=30.0)
                except queue.Empty:
                    raise AssertionError(f"no state for 30 s (plant exit code {plant.poll()})")
                st = msgpack.unpackb(raw, raw=False)
                check_state(st, nw, period)
                seen.append(st)
                if st.get("end"):
                    break  # the end state is not answered (section 4.1)
                prev = last_cmd
                if st["seq"] == bad_at:
                    # the accepted answer to state bad_at - 1 again: a duplicate
                    put(msgpack.packb(prev))
                    sent_bad["duplicate"] = 1
                    for payload, reason in malformed(cmd(n_cmd, st, nw), nw, period):
                        put(payload)
                        sent_bad[reason] = sent_bad.get(reason, 0) + 1
                    # a valid command without source info: not from the owner
                    pub.put(msgpack.packb(cmd(n_cmd, st, nw)))
                    sent_bad["not_owner"] = 1
                last_cmd = cmd(n_cmd, st, nw)
                put(msgpack.packb(last_cmd))
                n_cmd += 1
                if st["seq"] == bad_at:
                    # and once more after the answer to bad_at: now stale
                    put(msgpack.packb(prev))
                    sent_bad["stale"] = 1
        finally:
            token.undeclare()
            sub.undeclare()
            pub.undeclare()
    return {"params": params, "states": seen, "sent": n_cmd, "bad": sent_bad,
            "plant_token": alive, "plant_zid": plant_zid}


# ---- the test -----------------------------------------------------------------------------
@pytest.mark.timeout(120)
def test_a_controller_written_from_protocol_md_completes_a_lockstep_run(tmp_path):
    port = free_port()
    steps = int(round(DURATION / 0.01))
    out, err = tmp_path / "plant.out", tmp_path / "plant.err"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t0 = time.monotonic()
    with out.open("w") as fo, err.open("w") as fe:
        plant = subprocess.Popen(msagv("plant", "--run-mode", "lockstep", "--id", VID,
                                       "--duration", DURATION, "--listen",
                                       f"tcp/127.0.0.1:{port}", "--timeout", 20, "--wait", 60,
                                       "--json", "-q"),
                                 stdout=fo, stderr=fe, env=env, cwd=tmp_path)
    try:
        seen = run_controller(port, VID, plant)
        rc = plant.wait(30)
    finally:
        stop(plant)
    elapsed = time.monotonic() - t0
    assert rc == 0, err.read_text()[-3000:]

    # params (section 3.4)
    p = seen["params"]
    assert set(p) == {"v", "id", "vehicle", "period", "run_mode", "n_wheels"}
    assert p["v"] == 1 and p["id"] == VID and p["run_mode"] == "lockstep"
    assert p["period"] == 0.01 and p["n_wheels"] == 2 * len(p["vehicle"]["axle_x"]) == 4
    assert {"mass", "wheel_radius", "axle_x", "half_track", "tire", "limits"} <= set(p["vehicle"])
    assert seen["plant_token"] == [f"msagv/{VID}/alive/plant/{seen['plant_zid']}"]

    # the states (sections 3.2, 4.1): seq 0..steps once each, end only on the last
    sts = seen["states"]
    assert [s["seq"] for s in sts] == list(range(steps + 1))
    assert [bool(s.get("end")) for s in sts] == [False] * steps + [True]
    assert sts[-1]["x"] != sts[0]["x"]  # the vehicle moved
    assert seen["sent"] == steps

    # the plant's summary (sections 4.4, 5, 8)
    lines = [ln for ln in out.read_text().splitlines() if ln.startswith("{")]
    assert lines, err.read_text()[-3000:]
    s = json.loads(lines[-1])
    assert s["role"] == "plant" and s["id"] == VID and s["run_mode"] == "lockstep"
    assert s["completed"] is True and s["error"] is None
    assert s["steps"] == steps and s["t_end"] == pytest.approx(DURATION)
    c = s["commands"]
    assert c == {"accepted": steps, "stale": 1, "duplicate": 1, "late": 0, "lost": 0,
                 "seq_gaps": 0, "after_end": 0}, c
    bad = {k: v for k, v in seen["bad"].items() if k not in ("duplicate", "stale")}
    assert len(bad) == 13  # every reason code of section 5 the plant gives
    assert s["rejected"]["by_reason"] == bad
    assert s["rejected"]["total"] == sum(bad.values())
    assert s["rejected"]["by_key"] == {f"msagv/{VID}/cmd": sum(bad.values())}
    assert s["final_state"]["t"] == pytest.approx(DURATION)
    assert s["ownership"]["grants"] == 1 and s["ownership"]["refused"] == 0
    print(f"\nPROTOCOL.md client: {steps} steps, rejected {s['rejected']['by_reason']}, "
          f"{elapsed:.1f} s including the plant's start")
