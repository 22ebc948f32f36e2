"""docs/PROTOCOL.md is enough to write a controller: a minimal one, from the page alone.

The client below uses only ``zenoh``, ``msgpack`` and the standard library (nothing from
bridge/, controller/ or plant/). The harness (tests/helpers.py: a free port, starting and
stopping processes) runs a real ``msagv plant`` in lockstep on a free loopback port, and
the client does what section 7 says (protocol version 2):

- names itself by its session id and asks ``params/*/{me}``; binds to the plant named by
  the reply's key (states from any other identity are ignored);
- subscribes ``state/*``, publishes on ``cmd/{me}``, declares its token, claims the vehicle
  from that plant asking for the per-wheel wear, and answers every state with a constant
  wheel speed and zero steering rate;
- sends one malformed command for each documented reason code, plus one duplicate and
  one stale command, and a command on version 1's bare key;
- checks what the page says of a second claimer (refused, never told the owner), of a
  client of version 1 (an error reply that says why), of the release (the vehicle latched).

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


def get_params(session, vid: str, deadline_s: float) -> tuple[dict, str, float]:
    """Sections 3.4 and 7: a get on msagv/{id}/params/*/{me} (every plant, no
    consolidation, with source info), retried until exactly one plant answers; returns
    the params, the plant's identity (the reply key's second-to-last chunk) and the time
    from the first try to the answer."""
    me = str(session.zid())
    t0 = time.monotonic()
    while time.monotonic() - t0 < deadline_s:
        replies = {}
        for reply in session.get(f"msagv/{vid}/params/*/{me}", target=zenoh.QueryTarget.ALL,
                                 consolidation=zenoh.ConsolidationMode.NONE, timeout=1.0,
                                 source_info=zenoh.SourceInfo(session.id, 0)):
            if reply.ok is not None:
                key = str(reply.ok.key_expr).split("/")
                assert key[:3] == ["msagv", vid, "params"] and key[4] == me
                assert key[3] == str(reply.replier_id.zid)  # a plain bus: the same session
                replies[key[3]] = msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
        if len(replies) == 1:
            (plant, params), = replies.items()
            return params, plant, time.monotonic() - t0
        time.sleep(0.1)
    raise AssertionError(f"no params reply from exactly one plant within {deadline_s} s")


def ask(session, key: str, payload: dict) -> list[dict]:
    """A get with source info; the ok replies' maps (sections 3.7, 3.8)."""
    return [msgpack.unpackb(r.ok.payload.to_bytes(), raw=False)
            for r in session.get(key, payload=msgpack.packb(payload), timeout=1.0,
                                 source_info=zenoh.SourceInfo(session.id, 0))
            if r.ok is not None]


def claim(session, vid: str, plant: str, deadline_s: float) -> dict:
    """Sections 3.7 and 7: claim the vehicle from the bound plant until it grants it."""
    me = str(session.zid())
    t0 = time.monotonic()
    while time.monotonic() - t0 < deadline_s:
        for grant in ask(session, f"msagv/{vid}/claim/{plant}/{me}",
                         {"v": 2, "action": "claim", "wheel_wear": True}):
            if grant["granted"]:
                return grant
        time.sleep(0.25)
    raise AssertionError(f"the vehicle was not granted within {deadline_s} s")


WHEEL_WEAR = ("W_s_ij", "W_alpha_ij", "W_t_ij")


def check_state(st: dict, nw: int, period: float) -> None:
    """The state table of section 3.2, for a lockstep plant whose owner asked for the
    per-wheel wear."""
    required = {"v", "seq", "t", "x", "y", "phi", "vx", "vy", "r", "delta", "omega_w"}
    optional = {"W_s", "W_alpha", "W_t", "safe", "end", *WHEEL_WEAR}
    assert required <= set(st) and set(st) <= required | optional, sorted(st)
    assert st["v"] == 1 and isinstance(st["seq"], int) and st["seq"] >= 0
    assert st["t"] == st["seq"] * period  # t = seq T exactly
    for k in ("x", "y", "phi", "vx", "vy", "r"):
        assert isinstance(st[k], float) and math.isfinite(st[k])
    assert len(st["delta"]) == nw and len(st["omega_w"]) == nw
    assert all(w >= 0 for w in st["omega_w"])
    assert "safe" not in st  # realtime only
    assert st.get("end", True) is True  # absent, or true on the last state
    for k in WHEEL_WEAR:  # asked for in the claim: in every state, summing to the total
        assert len(st[k]) == nw and math.isclose(sum(st[k]), st[k[:-3]], rel_tol=1e-9,
                                                 abs_tol=1e-9)


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
        (b"\x80" + b"\x00" * 65536, "too_large"),
    ]


def run_controller(port: int, vid: str, plant: subprocess.Popen, bad_at: int = 3) -> dict:
    """Run a lockstep controller to the plant's end state. Returns what it saw and did."""
    states: queue.Queue = queue.Queue()
    seen: list[dict] = []
    sent_bad: dict[str, int] = {}
    other: dict = {}
    with zenoh.open(client_config(port)) as session:
        me = str(session.zid())
        params, plant_id, first_answer_s = get_params(session, vid, deadline_s=60.0)
        nw, period = params["n_wheels"], params["period"]

        def on_state(s):  # only the bound plant's states (sections 2, 4.7)
            if str(s.key_expr) == f"msagv/{vid}/state/{plant_id}" and s.source_info is not None \
                    and str(s.source_info.source_id.zid) == plant_id:
                states.put(s.payload.to_bytes())

        # subscriber and publisher first, then the token, then the claim (sections 4, 7)
        sub = session.declare_subscriber(f"msagv/{vid}/state/*", on_state)
        # the quality of service of section 1: with zenoh's default (drop), a burst behind
        # the 64 KiB payload was dropped on a loaded machine, and the run lived on re-sends
        qos = dict(congestion_control=zenoh.CongestionControl.BLOCK,
                   priority=zenoh.Priority.REAL_TIME, express=True)
        pub = session.declare_publisher(f"msagv/{vid}/cmd/{me}", **qos)
        token = session.liveliness().declare_token(f"msagv/{vid}/alive/controller/{me}")
        grant = claim(session, vid, plant_id, deadline_s=30.0)
        assert grant == {"v": 2, "granted": True, "reason": "granted"}
        alive = [str(r.ok.key_expr) for r in
                 session.liveliness().get(f"msagv/{vid}/alive/plant/{plant_id}", timeout=2.0)
                 if r.ok is not None]
        # a second controller is refused, and not told who owns the vehicle (section 3.7);
        # a client of version 1 gets an error reply that says why (section 2)
        t_open = time.monotonic()
        with zenoh.open(client_config(port)) as second:
            # how soon a fresh session's query reaches the running plant (section 3.4)
            _, _, _ = get_params(second, vid, deadline_s=30.0)
            other["answer_after_open_s"] = time.monotonic() - t_open
            t0 = time.monotonic()
            while not other.get("grant") and time.monotonic() - t0 < 30:
                g = ask(second, f"msagv/{vid}/claim/*/{second.zid()}", {"v": 2, "action": "claim"})
                other["grant"] = g[0] if g else None
            other["v1"] = [r.err.payload.to_bytes().decode() for r in
                           second.get(f"msagv/{vid}/params", timeout=1.0) if r.err is not None
                           and r.replier_id is not None]
        n_cmd = 0

        def put(payload: bytes) -> None:  # every command with our source info (section 2)
            pub.put(payload, source_info=zenoh.SourceInfo(pub.id, n_cmd))

        last_cmd = None  # the accepted answer to the previous state
        resent = 0
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
                if len(seen) > 1 and st["seq"] == seen[-2]["seq"]:
                    # a state that comes again: the same command, byte for byte (section 4.1)
                    put(msgpack.packb(last_cmd))
                    resent += 1
                    continue
                prev = last_cmd
                if st["seq"] == bad_at:
                    # the accepted answer to state bad_at - 1 again: a duplicate
                    put(msgpack.packb(prev))
                    sent_bad["duplicate"] = 1
                    for payload, reason in malformed(cmd(n_cmd, st, nw), nw, period):
                        put(payload)
                        sent_bad[reason] = sent_bad.get(reason, 0) + 1
                    # a valid command on version 1's bare key: no identity, not the owner's
                    session.put(f"msagv/{vid}/cmd", msgpack.packb(cmd(n_cmd, st, nw)), **qos)
                    sent_bad["not_owner"] = 1
                last_cmd = cmd(n_cmd, st, nw)
                put(msgpack.packb(last_cmd))
                n_cmd += 1
                if st["seq"] == bad_at:
                    # and once more after the answer to bad_at: now stale
                    put(msgpack.packb(prev))
                    sent_bad["stale"] = 1
            # release the vehicle: during the run, it is latched (section 4.7)
            other["release"] = ask(session, f"msagv/{vid}/claim/{plant_id}/{me}",
                                   {"v": 2, "action": "release"})
        finally:
            token.undeclare()
            sub.undeclare()
            pub.undeclare()
    return {"params": params, "states": seen, "sent": n_cmd, "resent": resent, "bad": sent_bad,
            "plant_token": alive, "plant_zid": plant_id, "first_answer_s": first_answer_s,
            "other": other}


def start_plant(tmp_path, vid: str, port: int, timeout: float):
    """``msagv plant`` in lockstep for ``vid`` on ``port``: ``(process, stdout file, stderr
    file)``."""
    out, err = tmp_path / "plant.out", tmp_path / "plant.err"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with out.open("w") as fo, err.open("w") as fe:
        plant = subprocess.Popen(msagv("plant", "--run-mode", "lockstep", "--id", vid,
                                       "--duration", DURATION, "--listen",
                                       f"tcp/127.0.0.1:{port}", "--timeout", timeout,
                                       "--wait", 60, "--json", "-q"),
                                 stdout=fo, stderr=fe, env=env, cwd=tmp_path)
    return plant, out, err


# ---- the test -----------------------------------------------------------------------------
@pytest.mark.timeout(120)
def test_a_controller_written_from_protocol_md_completes_a_lockstep_run(tmp_path):
    port = free_port()
    steps = int(round(DURATION / 0.01))
    t0 = time.monotonic()
    plant, out, err = start_plant(tmp_path, VID, port, timeout=20)
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
    # (a repeated seq is a re-send of an unanswered state, section 4.1: the same state again)
    sts = [s for i, s in enumerate(seen["states"])
           if i == 0 or s["seq"] != seen["states"][i - 1]["seq"]]
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
    # a state re-sent under load (section 4.1) was answered twice: the second copy is a
    # duplicate when the first arrived after all
    assert seen["resent"] <= s["resent_states"]
    assert 1 <= c["duplicate"] <= 1 + seen["resent"], (c, seen["resent"])
    assert c == {"accepted": steps, "stale": 1, "duplicate": c["duplicate"], "late": 0,
                 "lost": 0, "seq_gaps": 0, "after_end": 0}, c
    bad = {k: v for k, v in seen["bad"].items() if k not in ("duplicate", "stale")}
    assert len(bad) == 14  # every reason code of section 5 the plant gives
    assert s["rejected"]["by_reason"] == bad
    assert s["rejected"]["total"] == sum(bad.values())
    assert s["rejected"]["by_key"] == {f"msagv/{VID}/cmd": sum(bad.values())}
    assert s["final_state"]["t"] == pytest.approx(DURATION)
    # ownership (sections 3.7, 4.7): one grant; the second claimer refused and not told
    # who owns the vehicle; the release during the run latches it; the version-1 query
    o = s["ownership"]
    assert o["grants"] == 1 and o["refused"] >= 1 and o["owner"] is None
    assert o["state"] == "latched" and o["releases"] == 1
    assert seen["other"]["grant"] == {"v": 2, "granted": False, "reason": "owned"}
    assert seen["other"]["release"] == [{"v": 2, "granted": False, "reason": "released"}]
    v1 = seen["other"]["v1"]
    assert len(v1) == 1 and v1[0].startswith("msagv protocol 2 (docs/PROTOCOL.md)")
    assert f"ask msagv/{VID}/params/*/{{your identity}}" in v1[0] and s["old_clients"] == 1
    print(f"\nPROTOCOL.md client: {steps} steps, rejected {s['rejected']['by_reason']}, "
          f"{elapsed:.1f} s including the plant's start; a fresh session's params query "
          f"answered {seen['other']['answer_after_open_s'] * 1000:.0f} ms after it opened")


def errors(session, key: str, payload: dict | None, source_info: bool = True) -> list[str]:
    """The texts of the error replies to a get (section 2)."""
    kw = {"source_info": zenoh.SourceInfo(session.id, 0)} if source_info else {}
    return [r.err.payload.to_bytes().decode()
            for r in session.get(key, payload=None if payload is None else msgpack.packb(payload),
                                 timeout=1.0, **kw)
            if r.err is not None and r.replier_id is not None]


@pytest.mark.timeout(120)
def test_claims_and_arms_are_answered_as_protocol_md_says(tmp_path):
    """Issue 27, item 3: what a client written from the page had to guess, now in the page,
    against a real ``msagv plant``: the error text of an unnamed claim and arm (section 2);
    an unknown ``action`` (3.7) and an arm for a name that is no identity (3.8); the one ban
    rule and the reason a banned identity is told in each state (4.7)."""
    port = free_port()
    vid = "agv_doc_ban"
    plant, out, err = start_plant(tmp_path, vid, port, timeout=60)
    got = {}
    sent_cmds: list = []  # the senders of the rejected commands, one entry per copy
    try:
        with zenoh.open(client_config(port)) as a, zenoh.open(client_config(port)) as b, \
                zenoh.open(client_config(port)) as o:
            _, plant_id, _ = get_params(a, vid, deadline_s=60.0)
            for s in (b, o):  # every session has learnt the plant's queryables
                assert get_params(s, vid, deadline_s=30.0)[1] == plant_id

            def me(s):
                return str(s.zid())

            def claim_(s, action="claim"):
                r = ask(s, f"msagv/{vid}/claim/{plant_id}/{me(s)}", {"v": 2, "action": action})
                assert len(r) == 1 and r[0]["v"] == 2, r
                return (r[0]["granted"], r[0]["reason"])

            def arm_(s, **m):
                r = ask(s, f"msagv/{vid}/arm/{plant_id}/{me(s)}", {"v": 2, **m})
                assert len(r) == 1 and r[0]["v"] == 2, r
                return (r[0]["armed"], r[0]["reason"])

            def command(s):
                # a command of s's own, not the owner's: rejected, and s banned - if the plant
                # handles it while the other still owns the vehicle. The owner's release that
                # follows comes on another session's link and may overtake it (a clean
                # clone's make test saw the release first, and no ban, once), and nothing on
                # the bus shows when the plant has taken a rejected command: the command is
                # sent again while 1.5 s go by, each copy able to ban on its own
                t_end = time.monotonic() + 1.5
                while time.monotonic() < t_end:
                    sent_cmds.append(me(s))
                    s.put(f"msagv/{vid}/cmd/{me(s)}", msgpack.packb({"v": 1}),
                          source_info=zenoh.SourceInfo(s.id, 0),
                          congestion_control=zenoh.CongestionControl.BLOCK)
                    time.sleep(0.1)

            # section 2: an unnamed query is answered with an error naming the key to ask
            hint = ("msagv protocol 2 (docs/PROTOCOL.md): this query carried no identity, as "
                    "a client of the first version asks; ask msagv/{}/{}/*/{{your identity}} "
                    "instead")
            got["bare claim"] = errors(b, f"msagv/{vid}/claim", {"v": 2, "action": "claim"})
            got["bare arm"] = errors(b, f"msagv/{vid}/arm", {"v": 2})
            got["wildcard claim"] = errors(b, f"msagv/{vid}/claim/*/*",
                                           {"v": 2, "action": "claim"})
            got["claim without source info"] = errors(
                b, f"msagv/{vid}/claim/{plant_id}/{me(b)}", {"v": 2, "action": "claim"},
                source_info=False)
            assert got["bare claim"] == [hint.format(vid, "claim")]
            assert got["bare arm"] == [hint.format(vid, "arm")]
            assert got["wildcard claim"] == got["claim without source info"] == got["bare claim"]
            # 3.7: an unknown action is a malformed claim; 3.8: an arm for no identity
            assert claim_(b, "grab") == (False, "bad_claim")
            assert arm_(o, controller="*") == (False, "bad_arm")
            assert arm_(o, controller="") == (False, "bad_arm")
            # 4.7: B commands while A owns the vehicle (before the run: A has no token)
            assert claim_(a) == (True, "granted")
            command(b)
            assert claim_(b) == (False, "owned")  # owned: the state's reason first
            assert claim_(a, "release") == (False, "released")  # before the run: free
            assert claim_(b) == (False, "banned")
            assert arm_(o) == (True, "armed")  # for the first claimer
            assert claim_(b) == (False, "banned")
            assert arm_(o, controller=me(a)) == (True, "armed")
            assert claim_(b) == (False, "armed_for_another")
            assert arm_(o, controller=me(b)) == (True, "armed")  # by name: the ban is lifted
            assert claim_(b) == (True, "granted")
            # the run starts with B (its state subscriber and token); O commands meanwhile
            states: queue.Queue = queue.Queue()
            sub = b.declare_subscriber(f"msagv/{vid}/state/*", lambda s: states.put(1))
            token = b.liveliness().declare_token(f"msagv/{vid}/alive/controller/{me(b)}")
            states.get(timeout=30.0)  # state 0: the run has started
            command(o)
            assert claim_(o) == (False, "owned")
            assert claim_(b, "release") == (False, "released")  # during the run: latched
            assert claim_(o) == (False, "latched")
            assert arm_(a) == (True, "armed")
            assert claim_(o) == (False, "banned")
            token.undeclare()
            sub.undeclare()
    finally:
        stop(plant)
    lines = [ln for ln in out.read_text().splitlines() if ln.startswith("{")]
    assert lines, err.read_text()[-3000:]
    s = json.loads(lines[-1])
    # the bad claim and the two bad arms by their reason and key (section 5), the four
    # unnamed queries as old clients; one identity still banned (B's ban the arm lifted)
    assert s["rejected"]["by_reason"] == {"value": 3, "not_owner": len(sent_cmds)}
    assert s["rejected"]["by_key"] == {f"msagv/{vid}/claim": 1, f"msagv/{vid}/arm": 2,
                                       f"msagv/{vid}/cmd": len(sent_cmds)}
    assert s["old_clients"] == 4
    assert s["ownership"]["banned"] == 1 and s["ownership"]["latches"] == 1


# ---- the page against the code, where a table can be read ----------------------------------
def _table(doc: str, header: str) -> list[list[str]]:
    """The rows (cells, backticks stripped) of the markdown table whose header row starts
    with ``header``."""
    lines = [ln.strip() for ln in doc.splitlines()]
    i = next(k for k, ln in enumerate(lines) if ln.startswith(header))
    rows = []
    for ln in lines[i + 2:]:
        if not ln.startswith("|"):
            break
        rows.append([c.strip().replace("`", "") for c in ln.strip("|").split("|")])
    return rows


def test_protocol_md_tables_match_the_code():
    """Reason codes, grant reasons, the claim and arm maps, size limits and the timing
    constants the page states are the code's (the client above checks the behaviour)."""
    from pathlib import Path

    from msagv.bridge import messages as Msg
    from msagv.bridge import ownership as O
    from msagv.bridge import plant_node, session

    doc = (Path(__file__).resolve().parents[1] / "docs" / "PROTOCOL.md").read_text()
    # section 5: every reason code, in the code's order
    assert [r[0] for r in _table(doc, "| reason | meaning |")] == list(Msg.REASONS)
    # section 3.7: the grant's reasons; the claim's and the grant's fields
    assert [r[0] for r in _table(doc, "| `reason` | `granted` | when |")] == list(O.GRANT_REASONS)
    claim_rows = _table(doc, "| field | type | req. | meaning |")  # the first: claim
    assert {r[0]: r[2] == "yes" for r in claim_rows} == {
        **{k: True for k in O.CLAIM_REQUIRED}, **{k: False for k in O.CLAIM_OPTIONAL}}
    # section 3.1: the size limits
    limits = {r[0]: r[1] for r in _table(doc, "| message | limit |")}
    kib = lambda n: f"{n // 1024} KiB" if n < 1 << 20 else f"{n >> 20} MiB"  # noqa: E731
    assert limits["state"] == kib(Msg.MAX_STATE_BYTES) and limits["cmd"] == kib(Msg.MAX_CMD_BYTES)
    assert limits["params"] == kib(Msg.MAX_PARAMS_BYTES)
    assert limits["reference"] == (f"{kib(Msg.MAX_REFERENCE_BYTES)} (at most "
                                   f"{Msg.MAX_REFERENCE_SAMPLES:,} samples)")
    assert limits["claim, grant, arm, armed"] == kib(O.MAX_CLAIM_BYTES)
    # section 1: Zenoh's limit, the client's connect timeout, shared memory
    cfg = {r[0]: r[1] for r in _table(doc, "| config key | value | why |")}
    assert cfg["transport/link/rx/max_message_size"].startswith(f"{session.MAX_MESSAGE_BYTES} ")
    assert cfg["connect/timeout_ms"].startswith(f"{session.CLIENT_CONNECT_TIMEOUT_MS} ")
    shm = session.make_config(session.SessionOptions(), "plant").get_json(
        "transport/shared_memory/enabled")
    assert cfg["transport/shared_memory/enabled"].startswith(f"{shm} ")
    # the timing the page states
    assert f"every {plant_node.RESEND_S:g} s" in doc  # lockstep re-send (4.1)
    assert f"claims every {O.CLAIM_RETRY_S:g} s until granted, then every {O.CLAIM_REFRESH_S:g} s" \
        in doc.replace("\n", " ").replace("   ", " ")
    assert f"appeared {O.GRANT_TOKEN_S:g} s later" in doc.replace("\n", " ")
    # section 3.6 and 4.2 (issue 30): the bounds of the plant's token watch, the quiet
    # bound of an owner's loss, the replies a query keeps, the close after a signal
    from msagv.bridge import presence, zenoh_transport

    flat = " ".join(doc.split())
    assert f"at most **{presence.MAX_TOKENS}** holders per vehicle" in flat
    assert f"(`--stale-ms`, at least {plant_node.QUIET_MIN_S:g} s)" in flat
    assert f"into a list (at most {zenoh_transport.MAX_REPLIES})" in flat
    assert f"given {plant_node.CLOSE_S:g} s to close" in flat
    assert f"then has {plant_node.RUN_STOP_S:g} s to see the stop" in flat
    assert f"every {presence.POLL_S:g} s, at once on a grant" in flat


def test_the_params_vehicle_row_names_every_key_the_plant_sends():
    """Section 3.4's ``vehicle`` row lists the keys of the description a plant really sends
    (``Vehicle.to_dict``, with its ``tire`` and ``plant`` tables): a strict client written
    from the page must not meet a key the page does not name (``combined_slip`` once was)."""
    import re
    from pathlib import Path

    from msagv.plant import default_vehicle

    doc = (Path(__file__).resolve().parents[1] / "docs" / "PROTOCOL.md").read_text()
    row = next(line for line in doc.splitlines() if line.startswith("| `vehicle` | map |"))
    named = set(re.findall(r"[A-Za-z_]+", " ".join(re.findall(r"`([^`]*)`", row))))
    d = default_vehicle().to_dict()
    want = set(d) | set(d["tire"]) | set(d["plant"])
    assert want <= named, f"PROTOCOL.md 3.4's vehicle row does not name {sorted(want - named)}"


def _section_table(doc: str, heading: str, header: str = "| field |") -> list[list[str]]:
    """The rows of the first table whose header starts with ``header`` after the line
    that starts with ``heading`` (``### 3.2``), in the section (not past the next
    heading)."""
    lines = [ln.strip() for ln in doc.splitlines()]
    start = next(k for k, ln in enumerate(lines) if ln.startswith(heading))
    for k in range(start + 1, len(lines)):
        assert not lines[k].startswith("#"), f"no table {header!r} under {heading!r}"
        if lines[k].startswith(header):
            return _table("\n".join(lines[k:]), header)
    raise AssertionError(f"no table {header!r} under {heading!r}")


def _fields(rows: list[list[str]], type_col: int, req_col: int) -> dict[str, tuple[str, bool]]:
    """``{field: (type, required)}`` of a field table: a row may name several fields
    (``x, y``); its type is the cell's first word (``bin (16 bytes)``: ``bin``)."""
    out = {}
    for r in rows:
        for name in r[0].split(","):
            assert name.strip() not in out, f"{name.strip()} twice in one table"
            out[name.strip()] = (r[type_col].split()[0], r[req_col] == "yes")
    return out


def test_protocol_md_field_tables_are_the_codecs_schema():
    """Issue 27, item 3: sections 3.2-3.5 and 3.7-3.8 list exactly the fields the codec
    (msagv.bridge.messages, msagv.bridge.ownership) accepts, with its types and which are
    required, and a plant's real messages carry no field the page does not name: a field
    added to the schema and not to the page fails here (as ``combined_slip`` in params
    once passed a strict client's reading of the page by)."""
    from pathlib import Path

    from msagv.bridge import link_key
    from msagv.bridge import messages as Msg
    from msagv.bridge import ownership as O
    from msagv.plant import Plant, default_vehicle

    doc = (Path(__file__).resolve().parents[1] / "docs" / "PROTOCOL.md").read_text()
    # the page's name of each of the codec's kinds (bridge.messages, "field tables")
    kinds = {"int": "int", "float": "float", "float+": "float", "wheels": "float[2n]",
             "wheels+": "float[2n]", "bool": "bool", "str": "str", "bin": "bin",
             "map": "map", "series": "float[N]"}

    def schema(required: dict, optional: dict) -> dict[str, tuple[str, bool]]:
        return {**{k: (kinds[v], True) for k, v in required.items()},
                **{k: (kinds[v], False) for k, v in optional.items()}}

    # the bus maps (unit column: field | type | unit | req. | meaning)
    tables = {"### 3.2": (Msg.STATE_REQUIRED, Msg.STATE_OPTIONAL),
              "### 3.3": (Msg.CMD_REQUIRED, Msg.CMD_OPTIONAL),
              "### 3.4": (Msg.PARAMS_REQUIRED, Msg.PARAMS_OPTIONAL),
              "### 3.5": (Msg.REFERENCE_REQUIRED, Msg.REFERENCE_OPTIONAL)}
    page = {}
    for heading, (req, opt) in tables.items():
        page[heading] = _fields(_section_table(doc, heading), 1, 3)
        assert page[heading] == schema(req, opt), heading
    # the handover maps (field | type | req. | meaning), in the order claim, grant / arm,
    # armed of their sections
    lines = doc.splitlines()
    for heading, pairs in (("### 3.7", [(O.CLAIM_REQUIRED, O.CLAIM_OPTIONAL),
                                        (O.GRANT_REQUIRED, O.GRANT_OPTIONAL)]),
                           ("### 3.8", [(O.ARM_REQUIRED, O.ARM_OPTIONAL),
                                        (O.ARMED_REQUIRED, {})])):
        start = next(k for k, ln in enumerate(lines) if ln.startswith(heading))
        rest = "\n".join(lines[start:])
        first = _section_table(rest, heading, "| field | type | req. | meaning |")
        after = rest.split("| field | type | req. | meaning |", 2)
        assert len(after) == 3, f"{heading}: two field tables expected"
        second = _table("| field | type | req. | meaning |" + after[2],
                        "| field | type | req. | meaning |")
        for rows, (req, opt) in zip((first, second), pairs):
            assert _fields(rows, 1, 2) == schema(req, opt), heading
    # section 3.5's sample bound is the codec's (and section 3.1's)
    t_row = next(r for r in _section_table(doc, "### 3.5") if r[0] == "t")
    assert t_row[4].startswith(f"3 <= N <= {Msg.MAX_REFERENCE_SAMPLES:,},"), t_row

    # what the encoders write: a real plant's state with every option, a command with
    # every option, the params of the built-in vehicle, a reference with its options
    plant = Plant(default_vehicle())
    nw = plant.vehicle.n_wheels
    key = bytes(32)
    msgs = {"### 3.2": Msg.encode_state(3, plant.state_message(), safe=False, end=True,
                                        wheel_wear=True, mac_key=key),
            "### 3.3": Msg.encode_cmd(3, 0.03, 3, [1.0] * nw, [0.0] * nw, solve_ms=1.0,
                                      cost=2.0, mac_key=key),
            "### 3.4": Msg.encode_params("agv0", plant.vehicle.to_dict(), 0.01, "lockstep",
                                         nw),
            "### 3.5": Msg.encode_reference([0.0, 1.0, 2.0], [0.0] * 3, [0.0] * 3,
                                            [0.0] * 3, name="line", relative=True)}
    for heading, payload in msgs.items():
        sent = set(msgpack.unpackb(payload, raw=False))
        assert sent == set(page[heading]), (heading, sorted(sent ^ set(page[heading])))
    assert len(link_key.LinkKeys.tag(key, {"v": 1})) == 16  # the page's "bin (16 bytes)"
