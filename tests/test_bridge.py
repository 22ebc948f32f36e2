"""The bridge's logic without processes: the plant and controller nodes fed directly,
session configuration, recordings and the report (docs/PROTOCOL.md)."""

from __future__ import annotations

import json
import time

import msgpack
import numpy as np
import pytest

from msagv.bridge import faults
from msagv.bridge import messages as M
from msagv.bridge.controller_node import ControllerConfig, ControllerNode
from msagv.bridge.plant_node import PlantConfig, PlantNode
from msagv.bridge.recording import Recorder, RecordingError, read_recording
from msagv.bridge.session import Keys, SessionError, SessionOptions, check_id, make_config
from msagv.plant import Plant, default_vehicle

T = 0.01


@pytest.fixture(scope="module")
def vehicle():
    return default_vehicle()


@pytest.fixture
def plant_node(vehicle):
    p = Plant(vehicle, initial={"vx": 4.0})
    node = PlantNode(p, Keys("t0"), PlantConfig(run_mode="lockstep", steps=10))
    node.publish_state(0)
    return node


def _cmd(seq, state_seq, w=8.0, s=0.0, t=None, nw=4, **kw):
    return M.encode_cmd(seq, state_seq * T if t is None else t, state_seq, [w] * nw, [s] * nw,
                        solve_ms=1.0, **kw)


# ---- plant node ---------------------------------------------------------------------------
def test_plant_state_has_t_seq_times_T(plant_node):
    m = M.decode_state(plant_node.published[-1], 4)
    assert m["seq"] == 0 and m["t"] == 0.0 and m["vx"] == 4.0 and "safe" not in m


def test_plant_accepts_the_answer_to_its_state(plant_node):
    c = plant_node.handle_cmd(_cmd(0, 0), time.perf_counter())
    assert c is not None and plant_node.stats.accepted == 1
    assert plant_node._newest.state_seq == 0


def test_every_malformed_command_is_counted_and_changes_nothing(plant_node):
    node = plant_node
    before_y = node.plant.state_vector
    before_u = [u.copy() for u in node.plant.inputs]
    cases = faults.cmd_cases(4)
    for payload, reason in cases:
        assert node.handle_cmd(payload, time.perf_counter()) is None
    assert node.rej.total == len(cases)
    expected: dict[str, int] = {}
    for _, r in cases:
        expected[r] = expected.get(r, 0) + 1
    assert node.rej.summary()["by_reason"] == expected
    assert node._newest is None and node.stats.accepted == 0
    np.testing.assert_array_equal(node.plant.state_vector, before_y)
    for u, b in zip(node.plant.inputs, before_u):
        np.testing.assert_array_equal(u, b)


def test_unknown_state_and_t_mismatch(plant_node):
    node = plant_node
    assert node.handle_cmd(_cmd(0, 1), time.perf_counter()) is None  # state 1 not published
    assert node.handle_cmd(_cmd(0, 0, t=0.5), time.perf_counter()) is None
    assert node.rej.summary()["by_reason"] == {M.UNKNOWN_STATE: 1, M.T_MISMATCH: 1}


def test_stale_and_duplicate_commands_are_ignored_not_applied(plant_node):
    node = plant_node
    node.publish_state(1)
    node.publish_state(2)
    assert node.handle_cmd(_cmd(0, 2, w=5.0), time.perf_counter()) is not None
    assert node.handle_cmd(_cmd(1, 1, w=6.0), time.perf_counter()) is None  # older
    assert node.handle_cmd(_cmd(2, 2, w=7.0), time.perf_counter()) is None  # same state
    assert node._newest.omega_w == [5.0] * 4
    assert node.stats.stale == 1 and node.stats.duplicate == 1 and node.rej.total == 0


def test_plant_summary_counts_lost_commands(plant_node):
    node = plant_node
    for k in range(1, 5):
        node.publish_state(k)
    node.handle_cmd(_cmd(0, 1), time.perf_counter())
    node.handle_cmd(_cmd(1, 3), time.perf_counter())
    s = node.summary()
    assert s["commands"]["lost"] == 2  # states 0 and 2 (4 is the newest, not yet due)
    assert s["commands"]["accepted"] == 2
    json.dumps(s)


def test_plant_config_rejects_bad_values():
    with pytest.raises(ValueError, match="run mode"):
        PlantConfig(run_mode="fast")
    with pytest.raises(ValueError, match="stale-ms"):
        PlantConfig(stale_ms=0)
    with pytest.raises(ValueError, match="duration"):
        PlantConfig(steps=0)


# ---- controller node ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def mpc(vehicle):
    from msagv.controller.models import MPCSettings
    from msagv.controller.mpc import MPC
    from msagv.controller.reference import case1_curve

    m = MPC(vehicle, MPCSettings(iterations=3, chains=4), case1_curve(15.0))
    m.warmup()
    return m


@pytest.fixture
def ctl(mpc):
    mpc.reset()
    mpc.set_reference(__import__("msagv.controller.reference", fromlist=["x"]).case1_curve(15.0))
    return ControllerNode(mpc, Keys("t0"), ControllerConfig())


def _state_payload(seq, vehicle, **kw):
    from msagv.controller.reference import case1_curve

    ini = case1_curve(15.0).initial_state(vehicle)
    st = {k: ini[k] for k in ("x", "y", "phi", "vx", "vy", "r")}
    st["delta"] = [ini[f"delta_{w}"] for w in vehicle.wheel_names]
    st["omega_w"] = [8.0] * 4
    st["t"] = seq * T
    return M.encode_state(seq, st, **kw)


def test_controller_answers_with_the_state_it_answers(ctl, vehicle):
    st = ctl.handle_state(_state_payload(0, vehicle), time.perf_counter())
    assert ctl.step(st, time.perf_counter()) == "sent"
    c = M.decode_cmd(ctl.sent[-1], 4)
    assert c["state_seq"] == 0 and c["t"] == 0.0 and c["seq"] == 0 and c["solve_ms"] > 0
    assert all(w >= 0 for w in c["omega_w"])


def test_controller_same_seed_same_commands_after_a_new_run(ctl, vehicle):
    out = []
    for _ in range(2):
        for k in range(3):
            st = M.decode_state(_state_payload(k, vehicle), 4)
            ctl.step(st, time.perf_counter())
        out.append([M.decode_cmd(b, 4)["omega_w"] for b in ctl.sent[-3:]])
    assert out[0] == out[1]  # seq 0 reset the warm start and the random stream
    assert ctl.stats.new_runs == 2


def test_controller_ignores_duplicates_and_does_not_answer_the_end(ctl, vehicle):
    st = M.decode_state(_state_payload(0, vehicle), 4)
    assert ctl.step(st, time.perf_counter()) == "sent"
    assert ctl.step(st, time.perf_counter()) == "duplicate"
    end = M.decode_state(_state_payload(1, vehicle, end=True), 4)
    assert ctl.step(end, time.perf_counter()) == "end"
    assert len(ctl.sent) == 1


def test_controller_never_commands_a_plant_that_is_gone(ctl, vehicle):
    ctl.plant_present = False
    assert ctl.handle_state(_state_payload(0, vehicle), time.perf_counter()) is None
    assert ctl.stats.ignored_no_plant == 1 and not ctl.sent


def test_controller_falls_back_to_states_when_the_plants_token_never_shows(ctl, vehicle):
    # zenoh now and then does not deliver a token to a session in a mesh of peers: the
    # plant's states are then the evidence of its presence, their silence of its loss
    from types import SimpleNamespace

    from msagv.bridge.controller_node import FALLBACK_LOSS_S

    ctl.plant_present, ctl.plant_seen = False, False
    ctl._plant_presence = SimpleNamespace(generation=0)
    st = ctl.handle_state(_state_payload(0, vehicle), time.perf_counter())
    assert st is not None and ctl.plant_present and ctl.plant_seen and ctl._fallback
    assert ctl.step(st, time.perf_counter()) == "sent"
    now = time.monotonic()
    ctl.check_fallback_loss(now)
    assert ctl.plant_present  # states are fresh
    ctl.check_fallback_loss(now + FALLBACK_LOSS_S + 0.1)
    assert not ctl.plant_present  # silence: gone, never commanded again until a state comes
    # once the token is seen, liveliness decides again
    ctl._plant_presence.generation = 1
    ctl._on_plant_change(True)
    assert ctl.plant_present and not ctl._fallback
    ctl.check_fallback_loss(now + 100.0)
    assert ctl.plant_present


def test_controller_answers_a_state_that_came_just_before_the_plants_token(ctl, vehicle):
    # state and liveliness travel on different paths: a new plant's state 0 can arrive
    # before its token; it is held, answered once the token is seen, dropped if it goes
    ctl.plant_present = False
    ctl.handle_state(_state_payload(0, vehicle), time.perf_counter())
    ctl._on_plant_change(True)
    st, rx = ctl._pending
    assert st["seq"] == 0 and ctl.step(st, rx) == "sent"
    ctl._on_plant_change(False)
    ctl.handle_state(_state_payload(1, vehicle), time.perf_counter())
    ctl._on_plant_change(False)
    ctl._on_plant_change(True)
    assert ctl._pending is None or ctl._pending[0]["seq"] == 1
    ctl._on_plant_change(False)
    assert ctl._pending is None and ctl._held is None


def test_controller_does_not_send_a_stale_command(mpc, vehicle):
    node = ControllerNode(mpc, Keys("t0"), ControllerConfig(max_age_ms=1.0))
    st = M.decode_state(_state_payload(0, vehicle), 4)
    assert node.step(st, time.perf_counter() - 0.5) == "stale"
    assert not node.sent and node.stats.dropped_stale == 1


def test_controller_rejects_malformed_states_and_references(ctl):
    cases = faults.state_cases(4) + faults.reference_cases()
    for p, _ in faults.state_cases(4):
        assert ctl.handle_state(p, time.perf_counter()) is None
    for p, _ in faults.reference_cases():
        assert ctl.handle_reference(p) is None
    assert ctl.rej.total == len(cases)
    assert ctl._pending is None and ctl._pending_ref is None


def test_controller_takes_a_new_reference_relative_to_the_next_state(ctl, vehicle):
    t = np.linspace(0, 5, 51)
    assert ctl.handle_reference(M.encode_reference(t, t, 0 * t, 0 * t, name="line",
                                                   relative=True))
    st = M.decode_state(_state_payload(7, vehicle), 4)
    ctl.step(st, time.perf_counter())
    ref = ctl.mpc.reference
    assert ref.name == "line" and ref.t[0] == pytest.approx(0.07) and ctl.stats.references == 1


# ---- session ------------------------------------------------------------------------------
def test_session_defaults_loopback_and_no_scouting():
    c = make_config(SessionOptions(), "plant")
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7448"]
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False
    assert json.loads(c.get_json("scouting/gossip/enabled")) is False
    assert json.loads(c.get_json("transport/link/tx/lease")) == 1000
    c = make_config(SessionOptions(), "controller")
    assert json.loads(c.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7448"]
    assert json.loads(c.get_json("listen/endpoints")) == []
    c = make_config(SessionOptions(connect=["tcp/10.0.0.1:7447"], mode="client"), "plant")
    assert json.loads(c.get_json("listen/endpoints")) == []
    assert json.loads(c.get_json("mode")) == "client"


def test_session_rejects_bad_options():
    for bad in ("a/b", "*", "", "x" * 65, "a b"):
        with pytest.raises(SessionError, match="--id"):
            check_id(bad)
    with pytest.raises(SessionError, match="endpoint"):
        make_config(SessionOptions(connect=["127.0.0.1:7447"]), "controller")
    with pytest.raises(SessionError, match="lease"):
        make_config(SessionOptions(lease_ms=5), "controller")


def test_keys():
    k = Keys("agv7")
    assert (k.state, k.cmd, k.params, k.reference, k.alive_plant, k.alive_controller) == (
        "msagv/agv7/state", "msagv/agv7/cmd", "msagv/agv7/params", "msagv/agv7/reference",
        "msagv/agv7/alive/plant", "msagv/agv7/alive/controller")


# ---- recordings and the report ------------------------------------------------------------
def test_recording_round_trip_and_truncated_tail(tmp_path):
    p = tmp_path / "r.rec"
    rec = Recorder(p, {"role": "plant", "id": "a"})
    rec.message("tx", "msagv/a/state", b"\x01\x02", ts=1.5)
    rec.message("rx", "msagv/a/cmd", b"\xc1", why=M.NOT_MSGPACK)
    rec.event("safe", on=True)
    rec.close({"steps": 3})
    h, recs, summary = read_recording(p)
    assert h["role"] == "plant" and summary == {"steps": 3}
    assert recs[0] == {"ts": 1.5, "dir": "tx", "key": "msagv/a/state", "p": b"\x01\x02"}
    assert recs[1]["why"] == M.NOT_MSGPACK and recs[2]["ev"] == "safe"
    data = p.read_bytes()
    # a killed writer: the file cut anywhere after its header still reads, giving a prefix
    # of the records (an MCAP file's footer, summary and index come last)
    full, lost_summary = recs, 0
    for cut in range(len(data) - 4, len(data) // 4, -61):
        p.write_bytes(data[:cut])
        h, recs, summary = read_recording(p)
        assert h["role"] == "plant" and recs == full[:len(recs)]
        lost_summary += summary is None
    assert lost_summary  # some cuts lose the summary (and the records after it)
    p.write_bytes(msgpack.packb({"hello": 1}))
    with pytest.raises(RecordingError, match="not an msagv recording"):
        read_recording(p)


def test_report_of_a_recorded_in_process_run_equals_its_metrics(tmp_path, vehicle):
    """A recording made of the in-process loop's messages is evaluated to the same metrics
    as the loop's own log (the report's code path, without any transport)."""
    from msagv.controller.loop import closed_loop
    from msagv.controller.models import MPCSettings
    from msagv.controller.mpc import MPC
    from msagv.controller.reference import case1_curve

    from msagv.experiments.recorded import evaluate

    ref = case1_curve(15.0)
    plant = Plant(vehicle, initial=ref.initial_state(vehicle))
    mpc = MPC(vehicle, MPCSettings(iterations=3, chains=4), ref)
    rec = Recorder(tmp_path / "x.rec", {"role": "plant", "id": "a", "vehicle": vehicle.to_dict(),
                                        "period": T, "run_mode": "lockstep",
                                        "reference": dict(ref.to_message(), name=ref.name)})

    def on_step(k, st, cmd):
        rec.message("tx", "msagv/a/state", M.encode_state(k, st))
        rec.message("rx", "msagv/a/cmd", M.encode_cmd(k, st["t"], k, cmd.omega_w, cmd.omega_s,
                                                      solve_ms=cmd.solve_ms))

    log = closed_loop(plant, mpc, ref, 0.3, on_step=on_step)
    rec.message("tx", "msagv/a/state", M.encode_state(30, log.final_state, end=True))
    rec.close()
    m, info, rlog, _ = evaluate(tmp_path / "x.rec")
    want = log.metrics()
    for k in ("W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg", "e_bar", "Omega",
              "steps", "solve_ms"):
        assert m[k] == want[k], k
    assert info["steps"] == 30 and info["answered"] == 30 and info["ended"]
    np.testing.assert_array_equal(np.asarray(rlog.omega_w), np.asarray(log.omega_w))
