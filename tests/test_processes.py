"""Plant and controller as real processes over Zenoh on free loopback ports.

Every test starts its processes with time limits and stops them in a fixture's finally.
The test itself joins the bus with its own session (listening on a port the processes
also connect to: peers do not route for each other), to watch states and to inject
malformed messages. Assertions are on counts and behaviour; timing figures are printed
(``pytest -s``), and asserted only in the ``slow`` soak, which states the targets.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from msagv.bridge import faults
from msagv.bridge import messages as M
from msagv.bridge.presence import Presence
from msagv.bridge.recording import read_recording
from msagv.bridge.session import DEFAULT_LEASE_MS, Keys, SessionOptions, open_session
from msagv.bridge.zenoh_transport import ZenohTransport
from msagv.experiments.recorded import evaluate
from helpers import ep, free_port, msagv

PY = sys.executable
T = 0.01


class Bus:
    """The test's own session: listens on ``port``; collects states and commands of ``vid``
    (protocol 2: on ``state/*`` and ``cmd/*``, the senders' identities in the last chunk)."""

    def __init__(self, port: int, vid: str = "agv0", lease_ms: int = DEFAULT_LEASE_MS):
        self.port = port
        self.keys = Keys(vid)
        self.session = open_session(SessionOptions(id=vid, listen=[ep(port)], lease_ms=lease_ms),
                                    "tool")
        self.states: list[tuple[float, dict]] = []
        self.cmds: list[tuple[float, dict]] = []
        self.on_state = None  # called with each state, on Zenoh's thread
        self._cond = threading.Condition()
        self._subs = [
            self.session.declare_subscriber(f"{self.keys.state}/*", self._on_state),
            self.session.declare_subscriber(f"{self.keys.cmd}/*", self._on_cmd)]
        self.transport = ZenohTransport(self.session, owns=False)  # for the faults' floods
        # any plant's and any controller's token (alive/plant/{zid}, alive/controller/{zid})
        bus = ZenohTransport(self.session, owns=False)
        self.plant = Presence(bus, self.keys.plant_token())
        self.controller = Presence(bus, self.keys.controller_token())

    def _on_state(self, s):
        try:
            m = M.decode_state(s.payload.to_bytes(), 4)
        except M.MessageError:
            return
        hook = self.on_state
        if hook is not None:
            hook(m)
        with self._cond:
            self.states.append((time.monotonic(), m))
            self._cond.notify_all()

    def _on_cmd(self, s):
        try:
            m = M.decode_cmd(s.payload.to_bytes(), 4)
        except M.MessageError:
            return
        with self._cond:
            self.cmds.append((time.monotonic(), m))

    def wait_for(self, pred, timeout: float, what: str):
        """Wait until ``pred(states)`` is true (re-checked at every state)."""
        t0 = time.monotonic()
        with self._cond:
            while not pred(self.states):
                left = timeout - (time.monotonic() - t0)
                if left <= 0:
                    raise AssertionError(f"timed out after {timeout} s waiting for {what}")
                self._cond.wait(min(left, 0.2))

    def wait_present(self, which: str, timeout: float) -> None:
        pres = getattr(self, which)
        t0 = time.monotonic()
        while not pres.present:
            if time.monotonic() - t0 > timeout:
                raise AssertionError(f"no {which} token within {timeout} s")
            time.sleep(0.02)

    def close(self):
        self.plant.close()
        self.controller.close()
        for s in self._subs:
            s.undeclare()
        self.session.close()


@pytest.fixture
def bus():
    b = Bus(free_port())
    try:
        yield b
    finally:
        b.close()


LONG_LEASE_MS = 20_000  # a process stopped (or stalled) must not be taken for dead (1 s)


@pytest.fixture
def held_bus():
    """The bus, for a run held by stopping a process: a lease that outlasts the hold."""
    b = Bus(free_port(), lease_ms=LONG_LEASE_MS)
    try:
        yield b
    finally:
        b.close()


def _commands_in(recording) -> dict[int, dict]:
    """The accepted commands of a plant recording, by the state they answer."""
    h, recs, _ = read_recording(recording)
    out = {}
    for r in recs:
        if r.get("key", "").endswith("/cmd") and r["dir"] == "rx" and "why" not in r:
            c = M.decode_cmd(r["p"], 4)
            out.setdefault(c["state_seq"], c)
    return out


_IN_PROCESS: dict[float, tuple] = {}


def in_process(duration: float):
    """``msagv run --duration D`` in this process: commands by step and the log (cached)."""
    if duration in _IN_PROCESS:
        return _IN_PROCESS[duration]
    from msagv.controller.loop import closed_loop
    from msagv.cli.args import add_case_args, add_mpc_args, scenario_from_args

    ap = argparse.ArgumentParser()
    add_case_args(ap)
    add_mpc_args(ap)
    a = ap.parse_args(["--duration", str(duration)])
    b = scenario_from_args(a).build()
    cmds = {}
    log = closed_loop(b.plant, b.controller, b.reference, duration,
                      on_step=lambda k, st, c: cmds.__setitem__(
                          k, (c.omega_w.tolist(), c.omega_s.tolist())))
    _IN_PROCESS[duration] = (cmds, log)
    return cmds, log


@pytest.fixture(scope="module")
def in_process_1s():
    return in_process(1.0)


def _assert_same_as_in_process(rec, plant_summary, in_process):
    cmds, log = in_process
    got = _commands_in(rec)
    assert sorted(got) == list(range(len(cmds)))
    for k in range(len(cmds)):
        assert got[k]["omega_w"] == cmds[k][0], f"omega_w differs at step {k}"
        assert got[k]["omega_s"] == cmds[k][1], f"omega_s differs at step {k}"
    fs = plant_summary["final_state"]
    for key in ("x", "y", "phi", "vx", "vy", "r", "W_s", "W_alpha", "W_t"):
        assert fs[key] == log.final_state[key], key
    m, info, _, _ = evaluate(rec)
    want = log.metrics()
    for key in ("W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg", "e_bar",
                "Omega", "steps"):
        assert m[key] == want[key], key


# ---- lockstep -----------------------------------------------------------------------------
@pytest.mark.timeout(240)
def test_lockstep_over_zenoh_is_identical_to_msagv_run(procs, bus, tmp_path, in_process_1s):
    P = free_port()
    rec = tmp_path / "plant.rec"
    procs.start("run", msagv("run", "--duration", 1, "--json"))
    procs.start("plant", msagv("plant", "--duration", 1, "--listen", ep(P), "--connect",
                               ep(bus.port), "--record", rec, "--json"))
    procs.start("ctl", msagv("controller", "--connect", ep(P), "--connect", ep(bus.port),
                             "--exit-at-end", "--record", tmp_path / "ctl.rec", "--json"))
    assert procs.wait("plant", 180) == 0, procs.err("plant")
    assert procs.wait("ctl", 30) == 0, procs.err("ctl")
    s = procs.json("plant")
    assert s["completed"] and s["steps"] == 100 and s["rejected"]["total"] == 0
    assert s["commands"]["accepted"] == 100 and s["commands"]["lost"] == 0
    _assert_same_as_in_process(rec, s, in_process_1s)
    # msagv report on either recording == msagv run --json (but the solve times)
    assert procs.wait("run", 120) == 0
    run = procs.json("run")
    for r in (rec, tmp_path / "ctl.rec"):
        out = subprocess.run(msagv("report", r, "--json"), capture_output=True, text=True,
                             timeout=120)
        assert out.returncode == 0, out.stderr
        rep = json.loads(out.stdout)
        for key in run["metrics"]:
            if key != "solve_ms":
                assert rep["metrics"][key] == run["metrics"][key], (r.name, key)
        # the per-wheel wear travelled in the states (the controller asked for it) and
        # is the in-process run's, wheel by wheel
        assert rep["wear"] is not None and rep["wear"] == run["wear"], r.name
    # the bus saw state k then the command answering k, never a command for a future state
    seen = {m["seq"] for _, m in bus.states}
    assert all(c["state_seq"] in seen for _, c in bus.cmds)
    print(f"\nlockstep latency (state -> command without the solve) [ms]: {s['latency_ms']}")


def _flood_run(procs, bus, tmp_path, n: int, duration: float):
    """n malformed commands at the plant before the run and n during it, n malformed
    states and n references at the controller during the run: both keep running, every
    message is counted, and the run is identical to the clean in-process one.

    The flood during the run is sent while the run is held: the controller is stopped
    (SIGSTOP) as the first state reaches the test's session, so the lockstep plant waits
    for its answer (and sends that state again every second) until the flood is in and the
    controller is continued. Without the hold, a loaded machine could end the 1 s run
    before the flood reached the plant (CI: 900 of 1000 counted). Every session has a
    lease longer than the hold (the default 1 s would take the stopped controller for
    dead: its token gone, the vehicle latched, the flood at it sent to nobody)."""
    P = free_port()
    rec = tmp_path / "plant.rec"
    steps = int(round(duration / T))
    procs.start("plant", msagv("plant", "--duration", duration, "--timeout", 60,
                               "--lease-ms", LONG_LEASE_MS, "--listen", ep(P), "--connect",
                               ep(bus.port), "--record", rec, "--json", "-q"))
    bus.wait_present("plant", 60)
    time.sleep(0.2)  # let the plant's subscriber be known to our publisher
    sent_plant = faults.flood(bus.transport, "agv0", "cmd", 4, n)["sent"]
    held = threading.Event()

    def hold(st: dict) -> None:
        if not held.is_set():
            os.kill(procs.p["ctl"].pid, signal.SIGSTOP)
            held.set()

    # (--bus-references on: a plain bus's references are otherwise refused unread, as
    # references_off; here each malformation is to be counted)
    procs.start("ctl", msagv("controller", "--connect", ep(P), "--connect", ep(bus.port),
                             "--lease-ms", LONG_LEASE_MS, "--bus-references", "on", "--json",
                             "-q"))
    bus.on_state = hold
    try:
        bus.wait_for(lambda s: held.is_set(), 120, "the first state")
        # the controller answers at most the state it has: the plant is within a step of 0
        newest = bus.states[-1][1]["seq"]
        assert newest < steps - 1 and not bus.states[-1][1].get("end"), newest
        t0 = time.monotonic()
        sent_plant += faults.flood(bus.transport, "agv0", "cmd", 4, n)["sent"]
        time.sleep(0.5)  # the plant takes them in while it waits
    finally:
        bus.on_state = None
        os.kill(procs.p["ctl"].pid, signal.SIGCONT)
    sent_ctl = faults.flood(bus.transport, "agv0", "state", 4, n)["sent"]
    refs = faults.flood(bus.transport, "agv0", "reference", 4, n)
    sent_ctl += refs["sent"]
    flood_s = time.monotonic() - t0
    assert procs.wait("plant", 600) == 0, procs.err("plant")
    time.sleep(2.0)  # the controller takes what is still queued, then stops on SIGTERM
    assert procs.p["ctl"].poll() is None  # still running
    procs.p["ctl"].send_signal(signal.SIGTERM)
    assert procs.wait("ctl", 30) == 0, procs.err("ctl")
    ps, cs = procs.json("plant"), procs.json("ctl")
    # the sender is checked first: from the tool, every command is not_owner and every
    # state not_bound; references (taken from anyone here) are counted by their malformation
    assert ps["rejected"]["total"] == sent_plant == 2 * n
    assert ps["rejected"]["by_key"] == {"msagv/agv0/cmd": 2 * n}
    assert ps["rejected"]["by_reason"] == {M.NOT_OWNER: 2 * n}
    assert cs["rejected"]["total"] == sent_ctl == 2 * n
    assert cs["rejected"]["by_reason"] == dict(refs["by_reason"], **{M.NOT_BOUND: n})
    assert cs["references"] == 0 and cs["answered"] == steps and ps["steps"] == steps
    _assert_same_as_in_process(rec, ps, in_process(duration))
    assert "rejected" in procs.err("ctl")  # logged with the reason (rate-limited)
    print(f"\n{3 * n} malformed messages in {flood_s:.2f} s during the run\n"
          f"plant rejections {ps['rejected']['by_reason']}, held at state {newest} "
          f"(sent again {ps['resent_states']} times)\n"
          f"controller rejections {cs['rejected']['by_reason']}")


@pytest.mark.timeout(300)
def test_malformed_floods_are_counted_and_change_nothing(procs, held_bus, tmp_path,
                                                         in_process_1s):
    _flood_run(procs, held_bus, tmp_path, n=500, duration=1.0)


@pytest.mark.timeout(180)
def test_lockstep_timeout_and_missing_controller_end_the_run_with_a_clear_error(procs, bus,
                                                                                tmp_path):
    P = free_port()
    procs.start("lonely", msagv("plant", "--listen", ep(free_port()), "--wait", 1, "--record",
                                tmp_path / "lonely.rec"))
    rec = tmp_path / "plant.rec"
    procs.start("plant", msagv("plant", "--duration", 30, "--timeout", 2, "--listen", ep(P),
                               "--connect", ep(bus.port), "--record", rec, "--json"))
    ctl = procs.start("ctl", msagv("controller", "--connect", ep(P), "--connect", ep(bus.port)))
    assert procs.wait("lonely", 60) == 3
    assert "no controller for vehicle 'agv0' within 1 s" in procs.err("lonely")
    bus.wait_for(lambda st: st and st[-1][1]["seq"] >= 30, 120, "30 lockstep steps")
    ctl.kill()
    assert procs.wait("plant", 60) == 3
    err = procs.err("plant")
    assert "no command answering state" in err and "within 2 s" in err
    s = procs.json("plant")
    assert not s["completed"] and "no command answering state" in s["error"]
    h, recs, summary = read_recording(rec)
    assert summary is not None and summary["error"] == s["error"]


# ---- real time ----------------------------------------------------------------------------
@pytest.mark.timeout(240)
def test_realtime_short_run(procs, bus, tmp_path):
    P = free_port()
    rec = tmp_path / "plant.rec"
    procs.start("plant", msagv("plant", "--run-mode", "realtime", "--duration", 5, "--listen",
                               ep(P), "--connect", ep(bus.port), "--record", rec, "--json", "-q"))
    procs.start("ctl", msagv("controller", "--connect", ep(P), "--connect", ep(bus.port),
                             "--exit-at-end", "--json", "-q"))
    assert procs.wait("plant", 180) == 0, procs.err("plant")
    assert procs.wait("ctl", 30) == 0, procs.err("ctl")
    s, c = procs.json("plant"), procs.json("ctl")
    assert s["completed"] and s["steps"] == 500 and s["rejected"]["total"] == 0
    assert c["settings"]["deadline_ms"] == 7.0  # the realtime budget, from the plant's params
    cm = s["commands"]
    # every state is answered or superseded; a loaded machine may make some late
    assert cm["accepted"] + cm["lost"] >= 500 and cm["accepted"] >= 250
    assert c["answered"] >= cm["accepted"]
    m, info, _, _ = evaluate(rec)
    assert m["steps"] == 500 and m["e_bar"] < 50.0
    print(f"\nrealtime 5 s: missed periods {s['missed_periods']}, commands {cm}, "
          f"latency {s['latency_ms']}, jitter {s['period_jitter_ms']}, safe {s['safe']}, "
          f"e_bar {m['e_bar']:.3f}")


@pytest.mark.timeout(300)
def test_controller_killed_then_restarted_plant_goes_safe_and_resumes(procs, bus, tmp_path):
    """Realtime: SIGKILL the controller; the plant holds the steering and ramps the wheels
    down, reports it, and stays safe (latched: issue 22) while a new controller claims in
    vain; an operator's ``msagv arm`` naming the new controller lets it drive, and the plant
    resumes. Then SIGTERM stops the plant promptly with its recording intact."""
    P = free_port()
    rec = tmp_path / "plant.rec"
    procs.start("plant", msagv("plant", "--run-mode", "realtime", "--duration", 120,
                               "--listen", ep(P), "--connect", ep(bus.port), "--record", rec,
                               "--json"))
    a = procs.start("ctl_a", msagv("controller", "--connect", ep(P), "--connect", ep(bus.port),
                                   "-q"))
    bus.wait_for(lambda st: st and st[-1][1]["seq"] >= 150, 120, "1.5 s of realtime steps")
    a.kill()
    bus.wait_for(lambda st: st and st[-1][1].get("safe"), 30, "the plant to go safe")
    b = procs.start("ctl_b", msagv("controller", "--connect", ep(P), "--connect", ep(bus.port),
                                   "-q"))
    # latched: B is refused and told how to be re-armed; the plant stays safe meanwhile
    hint = re.compile(r"msagv arm --id agv0 --controller (\S+)")
    t0 = time.monotonic()
    while not hint.search(procs.err("ctl_b")):
        assert time.monotonic() - t0 < 180 and b.poll() is None, procs.err("ctl_b")[-2000:]
        time.sleep(0.05)
    b_id = hint.search(procs.err("ctl_b")).group(1)
    k_armed = bus.states[-1][1]["seq"]
    assert all(m.get("safe") for _, m in bus.states[-20:])
    arm = subprocess.run(msagv("arm", "--connect", ep(P), "--controller", b_id, "--json"),
                         capture_output=True, text=True, timeout=120)
    assert arm.returncode == 0, arm.stderr
    assert json.loads(arm.stdout)["answers"][0]["armed"] is True
    bus.wait_for(lambda st: not st[-1][1].get("safe") and st[-1][1]["seq"] > k_armed, 120,
                 "the plant to resume")
    resumed_at = bus.states[-1][1]["seq"]
    bus.wait_for(lambda st: st[-1][1]["seq"] >= resumed_at + 50, 30, "0.5 s after resuming")
    t0 = time.monotonic()
    procs.p["plant"].send_signal(signal.SIGTERM)
    assert procs.wait("plant", 30) == 0
    stop_s = time.monotonic() - t0
    s = procs.json("plant")
    assert s["stopped_by"] == "SIGTERM"
    assert s["safe"]["events"] >= 1 and s["safe"]["resumes"] >= 1 and s["controller_losses"] >= 1
    o = s["ownership"]
    assert o["owner"] == b_id and o["latches"] == 1 and o["grants"] == 2
    assert [x["controller"] for x in o["arms"]] == [b_id] and o["refused"] >= 1
    err = procs.err("plant")
    assert "SAFE at t =" in err and "resumed normal operation" in err
    # the safe behaviour, from the states on the bus: steering held, wheels ramped down
    states = [m for _, m in bus.states]
    safe = [m for m in states if m.get("safe")]
    first = next(i for i, m in enumerate(states) if m.get("safe"))
    run = [states[first - 1]] + [m for m in states[first:] if m.get("safe")][:100]
    for prev, cur in zip(run, run[1:]):
        if cur["seq"] != prev["seq"] + 1:
            break
        assert cur["delta"] == pytest.approx(prev["delta"], abs=1e-12)
        assert all(w1 <= w0 + 1e-9 for w0, w1 in zip(prev["omega_w"], cur["omega_w"]))
    assert len(safe) >= 1
    h, recs, summary = read_recording(rec)
    assert summary is not None and summary["stopped_by"] == "SIGTERM"
    assert any(r.get("ev") == "safe" and r["on"] for r in recs)
    evs = [r["ev"] for r in recs if r.get("ev") in ("latched", "armed", "owner")]
    # the grant to A, the loss (latched, no owner), the re-arm, the grant to B
    assert evs == ["owner", "latched", "owner", "armed", "owner"], evs
    assert [r for r in recs if r.get("ev") == "armed"][0]["controller"] == b_id
    print(f"\ncontroller kill/restart: safe {s['safe']}; plant stopped {stop_s:.2f} s after "
          f"SIGTERM (incl. process exit)")


@pytest.mark.timeout(300)
def test_plant_killed_controller_stops_commanding_exits_or_waits(procs, bus, tmp_path):
    P = free_port()
    procs.start("plant", msagv("plant", "--duration", 60, "--listen", ep(P), "--connect",
                               ep(bus.port), "-q"))
    ctl = {"ctl_exit": msagv("controller", "--connect", ep(P), "--connect", ep(bus.port),
                             "--on-plant-loss", "exit", "--json"),
           "ctl_wait": msagv("controller", "--id", "agv0", "--connect", ep(P), "--connect",
                             ep(bus.port), "--json")}
    for name, cmd in ctl.items():
        procs.start(name, cmd)
    bus.wait_for(lambda st: st and st[-1][1]["seq"] >= 30, 120, "30 lockstep steps")
    # In this mesh of four peers (gossip off), zenoh now and then leaves a new session
    # half-connected: its queries (the params) are answered, but no publication or token
    # reaches it (seen about once in eight runs; 0 states received). Such a controller
    # never saw a plant, so it cannot lose one: restart it once, as an operator would.
    for name, cmd in ctl.items():
        t1 = time.monotonic()
        while "plant agv0 present" not in procs.err(name) and time.monotonic() - t1 < 20:
            time.sleep(0.1)
        if "plant agv0 present" not in procs.err(name):
            print(f"\n{name} saw no plant (zenoh half-connected it): restarting it")
            procs.p[name].kill()
            procs.p[name].wait(10)
            procs.start(name, cmd)
            t1 = time.monotonic()
            while "plant agv0 present" not in procs.err(name) and time.monotonic() - t1 < 60:
                time.sleep(0.1)
            assert "plant agv0 present" in procs.err(name), procs.err(name)
    bus.wait_for(lambda st: st and st[-1][1]["seq"] >= 60, 120, "60 lockstep steps")
    procs.p["plant"].kill()
    t0 = time.monotonic()
    assert procs.wait("ctl_exit", 30) == 3
    print(f"\ncontroller exited {time.monotonic() - t0:.2f} s after the plant was killed")
    assert "plant 'agv0' gone" in procs.err("ctl_exit")
    assert procs.json("ctl_exit")["exit_reason"] == "plant gone"
    # the default: wait for the plant (its loss is confirmed within a few leases)
    t1 = time.monotonic()
    while "waiting for it to return" not in procs.err("ctl_wait") and time.monotonic() - t1 < 15:
        time.sleep(0.1)
    assert procs.p["ctl_wait"].poll() is None
    assert "waiting for it to return" in procs.err("ctl_wait")
    last_state = max(m["seq"] for _, m in bus.states)
    n_cmds = len(bus.cmds)
    time.sleep(1.0)
    assert len(bus.cmds) == n_cmds  # nothing commanded while the plant is gone
    assert all(c["state_seq"] <= last_state for _, c in bus.cmds)
    # a new plant run: the waiting controller answers it from a fresh MPC
    procs.start("plant2", msagv("plant", "--duration", 0.3, "--listen", ep(P), "--connect",
                                ep(bus.port), "--json", "-q"))
    assert procs.wait("plant2", 120) == 0, procs.err("plant2")
    assert procs.json("plant2")["commands"]["accepted"] == 30
    procs.p["ctl_wait"].send_signal(signal.SIGINT)
    assert procs.wait("ctl_wait", 30) == 0
    # plant2's run is a new one for it: its second, after the first plant's (solved and
    # sent as its owner, or solved and held as the other claimer: not_granted). Its first
    # if no state of the first plant reached it: Zenoh's half-connected session above,
    # seen once at load 5-6 with the plant's token delivered and its states not (then it
    # solved nothing before plant2's 30 states)
    s = procs.json("ctl_wait")
    saw_first = (s["answered"] > 30 or s["not_granted"] > 0 or s["duplicates"] > 0
                 or s["skipped"] > 0 or s["ignored_no_plant"] > 0)
    assert s["new_runs"] == (2 if saw_first else 1), s


# ---- several vehicles through a router ----------------------------------------------------
@pytest.mark.timeout(300)
def test_two_vehicles_through_a_router(procs, tmp_path):
    R = free_port()
    # five processes start at once on the suite's two cores: a lease longer than any stall
    # they may see (this test is about routing two vehicles; the 1 s lease and the latch
    # on a lost owner have their own tests). In one clean-clone run plant agv_b saw its
    # live controller's token go (and latched) 0.06 s into its run; not reproduced in 6
    # runs under load.
    lease = ("--lease-ms", LONG_LEASE_MS)
    procs.start("router", msagv("router", "--listen", ep(R), *lease))
    # zenoh >= 1.9 routes between a router's clients and between a client and a peer, not
    # between two peers that are not connected to each other: one side at least a client
    for vid, plant_mode in (("agv_a", "client"), ("agv_b", "peer")):
        procs.start(f"plant_{vid}", msagv("plant", "--id", vid, "--mode", plant_mode,
                                          "--connect", ep(R), "--duration", 0.5, "--json", "-q",
                                          "--record", tmp_path / f"{vid}.rec", *lease))
        procs.start(f"ctl_{vid}", msagv("controller", "--id", vid, "--mode", "client",
                                        "--connect", ep(R), "--exit-at-end", "--json", "-q",
                                        *lease))
    for vid in ("agv_a", "agv_b"):
        assert procs.wait(f"plant_{vid}", 240) == 0, procs.err(f"plant_{vid}")
        assert procs.wait(f"ctl_{vid}", 30) == 0, procs.err(f"ctl_{vid}")
        s = procs.json(f"plant_{vid}")
        assert s["id"] == vid and s["completed"] and s["rejected"]["total"] == 0
        assert s["commands"]["accepted"] == 50 and s["commands"]["duplicate"] == 0
        assert procs.json(f"ctl_{vid}")["answered"] == 50
        h, recs, _ = read_recording(tmp_path / f"{vid}.rec")
        assert {r["key"] for r in recs if "key" in r} == {f"msagv/{vid}/state", f"msagv/{vid}/cmd"}
    procs.p["router"].send_signal(signal.SIGTERM)
    assert procs.wait("router", 10) == 0


# ---- the FMU as the plant -----------------------------------------------------------------
@pytest.mark.timeout(300)
def test_plant_process_hosts_an_fmu(procs, tmp_path):
    from msagv.fmu_build.build import build_fmu

    fmu = build_fmu(tmp_path / "plant.fmu")
    P = free_port()
    procs.start("plant", msagv("plant", "--fmu", fmu, "--duration", 0.3, "--listen", ep(P),
                               "--json", "-q"))
    procs.start("ctl", msagv("controller", "--connect", ep(P), "--exit-at-end", "-q"))
    assert procs.wait("plant", 240) == 0, procs.err("plant")
    s = procs.json("plant")
    assert s["completed"] and s["commands"]["accepted"] == 30 and s["final_state"]["x"] > 1.0


# ---- command line errors ------------------------------------------------------------------
@pytest.mark.timeout(120)
@pytest.mark.parametrize("args,msg", [
    (["plant", "--id", "a/b"], "not a valid vehicle id"),
    (["plant", "--map", "m.toml"], "--map applies to --fmu"),
    (["plant", "--initial", "nonsense=1"], "unknown signal"),
    (["plant", "--stale-ms", "0"], "--stale-ms must be > 0"),
    (["plant", "--fmu", "missing.fmu"], "FMU not found"),
    (["controller", "--initial", "x=1"], "--initial applies to msagv plant"),
    (["controller", "--vehicle", "missing.toml"], "missing.toml"),
    (["plant", "--connect", "localhost"], "expected PROTOCOL/ADDRESS"),
])
def test_bad_options_exit_2_with_a_message(args, msg, tmp_path):
    r = subprocess.run(msagv(*args), capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 2 and msg in r.stderr, r.stderr


# ---- the demo -----------------------------------------------------------------------------
@pytest.mark.timeout(240)
def test_demo_json_short(tmp_path):
    png = tmp_path / "demo.png"
    r = subprocess.run(msagv("demo", "--json", "--duration", 2, "--plot", png),
                       capture_output=True, text=True, timeout=200, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)  # the result document (experiments/results.py)
    out, tr = doc["metrics"], doc["transport"]
    for k in ("W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg", "e_bar", "Omega",
              "solve_ms", "steps"):
        assert k in out, k
    for k in ("missed_periods", "latency_ms", "rejected"):
        assert k in tr, k
    assert out["steps"] == 200 and tr["rejected"] == 0
    assert set(tr["latency_ms"]) == {"p50", "p99", "max"}
    assert doc["command"] == "demo" and doc["scenario"]["speed_kmh"] == 15.0
    assert png.stat().st_size > 10_000
    print(f"\ndemo 2 s: missed {tr['missed_periods']}, latency {tr['latency_ms']}")


# ---- slow: the targets at full size -------------------------------------------------------
@pytest.mark.slow
@pytest.mark.timeout(600)
def test_realtime_soak_60s_targets(procs, bus, tmp_path):
    """60 s at 100 Hz with the 7 ms solve budget: zero missed periods, no lost commands,
    latency (state -> command without the solve) p99 < 2 ms. Needs a machine that is not
    saturated by other work (the figures are printed either way)."""
    P = free_port()
    rec = tmp_path / "plant.rec"
    procs.start("plant", msagv("plant", "--run-mode", "realtime", "--duration", 60, "--listen",
                               ep(P), "--connect", ep(bus.port), "--record", rec, "--json", "-q"))
    procs.start("ctl", msagv("controller", "--connect", ep(P), "--connect", ep(bus.port),
                             "--exit-at-end", "--deadline-ms", 7, "--json", "-q"))
    assert procs.wait("plant", 400) == 0, procs.err("plant")
    assert procs.wait("ctl", 30) == 0
    s = procs.json("plant")
    print(f"\nrealtime 60 s: missed {s['missed_periods']}, commands {s['commands']}, latency "
          f"{s['latency_ms']}, jitter {s['period_jitter_ms']}, lateness {s['lateness_ms']}, "
          f"safe {s['safe']}")
    assert s["completed"] and s["steps"] == 6000
    assert s["missed_periods"] == 0
    # no command lost; a "late" one (the answer to state k arriving after step k) is still
    # applied a period later and is reported, not failed
    assert s["commands"]["lost"] == 0 and s["commands"]["accepted"] == 6000
    assert s["latency_ms"]["p99"] < 2.0


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_malformed_floods_10000(procs, held_bus, tmp_path):
    _flood_run(procs, held_bus, tmp_path, n=10_000, duration=3.0)


# ---- a liveliness flood (issue 30, item 1) ------------------------------------------------
def _stock_session(port: int):
    """A stock zenoh-python peer (none of this project's code) connected to ``port``."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([ep(port)]))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(conf)


def _realtime_flood(procs, bus, what: str, flood, hold_periods: int):
    """A realtime plant and its controller; ``flood(port)`` declares liveliness tokens under
    the vehicle's controller prefix (as any process on the plain bus may) on the plant's
    port and returns the callable that takes them away. The plant's states keep coming
    while they are held and after they are gone, the live owner is never taken for lost,
    and SIGTERM ends the plant with its summary. Returns the summary and the seconds from
    SIGTERM to the process's exit."""
    P = free_port()
    procs.start("plant", msagv("plant", "--run-mode", "realtime", "--duration", 600,
                               "--listen", ep(P), "--connect", ep(bus.port), "--json"))
    procs.start("ctl", msagv("controller", "--connect", ep(P), "--connect", ep(bus.port)))
    bus.wait_for(lambda st: st and st[-1][1]["seq"] >= 100, 180, "1 s of realtime steps")
    undo = None
    try:
        undo = flood(P)
        k0 = bus.states[-1][1]["seq"]
        # the plant keeps stepping (event-driven: no bound on how fast, only that it does)
        bus.wait_for(lambda st: st[-1][1]["seq"] >= k0 + hold_periods, 120,
                     f"{hold_periods} more states during the flood of {what}")
        undo, u = None, undo
        u()
        k1 = bus.states[-1][1]["seq"]
        bus.wait_for(lambda st: st[-1][1]["seq"] >= k1 + 100, 120, "states after the flood")
    finally:
        if undo is not None:
            undo()
    assert procs.p["plant"].poll() is None, procs.err("plant")[-3000:]
    t0 = time.monotonic()
    procs.p["plant"].send_signal(signal.SIGTERM)
    assert procs.wait("plant", 10) == 0, procs.err("plant")[-3000:]
    stop_s = time.monotonic() - t0
    s = procs.json("plant")
    assert s["stopped_by"] == "SIGTERM"
    # the live owner was never taken for lost: no latch, no loss
    # (the message a plain string: pytest shortens a tuple's long members, which hid why a
    # loaded clean clone once latched here)
    assert s["ownership"]["latches"] == 0 and s["controller_losses"] == 0, (
        f"{s['ownership']}\npresence {s.get('presence')}\nplant:\n{procs.err('plant')[-4000:]}"
        f"\ncontroller:\n{procs.err('ctl')[-3000:]}")
    return s, stop_s


def _token_flood(procs, bus, n_tokens: int, hold_periods: int):
    """One stock session declares ``n_tokens`` tokens (:func:`_realtime_flood`)."""

    def flood(port: int):
        z = _stock_session(port)
        lv = z.liveliness()
        tokens = [lv.declare_token(f"msagv/agv0/alive/controller/flood{i:05d}")
                  for i in range(n_tokens)]

        def undo():
            for tok in tokens:
                tok.undeclare()
            z.close()
        return undo

    return _realtime_flood(procs, bus, f"{n_tokens} tokens", flood, hold_periods)


@pytest.mark.timeout(400)
def test_liveliness_token_flood_does_not_freeze_a_realtime_plant(procs, bus):
    s, stop_s = _token_flood(procs, bus, n_tokens=3000, hold_periods=300)
    pr = s["presence"]
    # the plant tracks at most its bound of tokens; the rest were counted, not kept
    assert pr["tracked_max"] <= pr["bound"] < 3000
    assert pr["untracked"] >= 3000 - pr["bound"]
    print(f"\n3000 tokens: presence {pr}; the plant stopped {stop_s:.2f} s after SIGTERM "
          f"(including the process's exit)")



@pytest.mark.slow
@pytest.mark.timeout(900)
def test_liveliness_token_flood_10000(procs, bus):
    """Issue 30's goal at full size: 10,000 tokens from one stock session."""
    s, stop_s = _token_flood(procs, bus, n_tokens=10_000, hold_periods=1000)
    pr = s["presence"]
    assert pr["tracked_max"] <= pr["bound"] and pr["untracked"] >= 10_000 - pr["bound"]
    print(f"\n10000 tokens: presence {pr}, safe {s['safe']}; the plant stopped {stop_s:.2f} s "
          f"after SIGTERM (including the process's exit; loop left behind: "
          f"{s.get('run_abandoned', False)}, close left behind: {s.get('close_abandoned', False)})")

# Stock zenoh-python only (none of this project's code): N peer sessions connected to a port,
# one token each under the controller prefix; prints one JSON line when they are open, and
# at SIGTERM undeclares them, closes them and prints another
_SESSIONS_SCRIPT = r"""
import json, os, signal, sys, threading, time
import zenoh

port, n = int(sys.argv[1]), int(sys.argv[2])
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *a: stop.set())
sessions, tokens = [], []
t0 = time.monotonic()
for i in range(n):
    if stop.is_set():
        break
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    z = zenoh.open(c)
    sessions.append(z)
    tokens.append(z.liveliness().declare_token(f"msagv/agv0/alive/controller/s{i:04d}"))
open_s = time.monotonic() - t0
linked = lambda: sum(1 for z in sessions if list(z.info.peers_zid()))
while linked() < len(sessions) and time.monotonic() - t0 < open_s + 60 and not stop.is_set():
    time.sleep(0.5)  # a session's open may return before its link is up (under load)
with open("/proc/self/status") as f:
    rss = next(int(ln.split()[1]) for ln in f if ln.startswith("VmRSS:")) / 1024
print(json.dumps({"opened": len(sessions), "open_s": open_s, "rss_mb": rss,
                  "linked": linked(), "linked_s": time.monotonic() - t0}), flush=True)
stop.wait()
t0 = time.monotonic()
for tok in tokens:
    tok.undeclare()
for z in sessions:
    z.close()
print(json.dumps({"closed": len(sessions), "close_s": time.monotonic() - t0}), flush=True)
"""
def _session_flood(procs, bus, n_sessions: int, hold_periods: int):
    """``n_sessions`` stock sessions, opened by one helper process, declare one token each
    (:func:`_realtime_flood`). Returns the summary, the seconds from SIGTERM to the plant's
    exit and what the helper said of its sessions."""
    opened: dict = {}

    def flood(port: int):
        procs.start("sessions", [PY, "-c", _SESSIONS_SCRIPT, str(port), str(n_sessions)])
        t0 = time.monotonic()
        while not procs.out("sessions").strip():  # a line once its sessions are open
            assert procs.p["sessions"].poll() is None, procs.err("sessions")[-3000:]
            assert time.monotonic() - t0 < 600, "the sessions were not open in 600 s"
            time.sleep(0.2)
        opened.update(json.loads(procs.out("sessions").splitlines()[0]))

        def undo():
            procs.p["sessions"].send_signal(signal.SIGTERM)
            assert procs.wait("sessions", 120) == 0, procs.err("sessions")[-3000:]
        return undo

    s, stop_s = _realtime_flood(procs, bus, f"{n_sessions} sessions", flood, hold_periods)
    linked, pr = opened["linked"], s["presence"]
    print(f"\n{n_sessions} sessions ({linked} linked; opened in {opened['open_s']:.1f} s, "
          f"helper RSS {opened['rss_mb']:.0f} MB): presence {pr}, safe {s['safe']}; the plant "
          f"stopped {stop_s:.2f} s after SIGTERM (including the process's exit; loop left "
          f"behind: {s.get('run_abandoned', False)}, close left behind: "
          f"{s.get('close_abandoned', False)}); load {os.getloadavg()[0]:.1f}")
    assert opened["opened"] == n_sessions
    # every session got its link to the plant, up to Zenoh's bound of a listener's sessions
    # (the controller and the test's bus hold two of them). With Zenoh's shared memory on
    # (its default) the plant linked 351 sessions and no more: 349 of 1000 here
    import zenoh

    limit = json.loads(zenoh.Config().get_json("transport/unicast/max_sessions"))
    assert linked == min(n_sessions, limit - 2), (opened, pr)
    # every linked session's token reached the plant: at most its bound tracked, the rest
    # counted (the owner's own token is among the tracked)
    assert pr["tracked_max"] <= pr["bound"] < linked
    assert pr["untracked"] >= linked - pr["bound"]
    return s, stop_s, opened


@pytest.mark.timeout(400)
def test_liveliness_session_flood_does_not_freeze_a_realtime_plant(procs, bus):
    """Issue 30, goal 1's other form, short: 150 stock sessions with one token each."""
    _session_flood(procs, bus, n_sessions=150, hold_periods=300)


@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_liveliness_session_flood_1000(procs, bus):
    """Issue 30's goal at full size: 1,000 stock sessions, one token each."""
    _session_flood(procs, bus, n_sessions=1000, hold_periods=1000)


# ---- the router setup holds its live owner (issue 30, item 4) -----------------------------
def _router_runs(procs, runs: int, duration: float):
    """``msagv router`` with a realtime plant and its controller as Zenoh clients, as
    docs/PROTOCOL.md sets it up, with the default 1 s lease: the plant never latches its
    live owner (Zenoh's token query through a router now and then misses a live token)."""
    R = free_port()
    procs.start("router", msagv("router", "--listen", ep(R)))
    out = []
    for i in range(runs):
        procs.start(f"plant{i}", msagv("plant", "--mode", "client", "--connect", ep(R),
                                       "--run-mode", "realtime", "--duration", duration,
                                       "--json", "-v"))
        procs.start(f"ctl{i}", msagv("controller", "--mode", "client", "--connect", ep(R),
                                     "--exit-at-end", "-q"))
        assert procs.wait(f"plant{i}", 240 + 2 * duration) == 0, procs.err(f"plant{i}")[-3000:]
        assert procs.wait(f"ctl{i}", 60) == 0, procs.err(f"ctl{i}")[-3000:]
        s = procs.json(f"plant{i}")
        err = procs.err(f"plant{i}")
        o = s["ownership"]
        assert s["completed"] and s["steps"] == int(round(duration / T))
        assert o["latches"] == 0 and o["losses"] == 0 and s["controller_losses"] == 0, (
            o, err[-3000:])
        assert o["grants"] == 1 and o["releases"] == 1  # the owner released it at the end
        out.append((s["presence"], err.count("missing from query"),
                    s["safe"], os.getloadavg()[0]))
    procs.p["router"].send_signal(signal.SIGTERM)
    assert procs.wait("router", 10) == 0
    for i, (pr, missing, safe, load) in enumerate(out):
        print(f"\nrouter run {i}: {duration:g} s, presence {pr}, 'missing from query' "
              f"logged {missing} times, safe {safe}, load {load:.1f}")


@pytest.mark.timeout(400)
def test_router_setup_never_latches_a_live_owner(procs):
    _router_runs(procs, runs=1, duration=15.0)


@pytest.mark.slow
@pytest.mark.timeout(3000)
def test_router_setup_never_latches_a_live_owner_in_repeated_minutes(procs):
    _router_runs(procs, runs=5, duration=60.0)
