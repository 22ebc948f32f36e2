"""The ROS 2 channels of a recording (issue 19 item 4) and its recovery after a kill (issue
22 item 6): the bag beside a recording is opened by ``rosbags`` and by the ``mcap`` reader
with ``mcap-ros2-support``'s decoders (no code of ours), every message decodes, and the
values are the recorded states' under docs/ROS2.md's conventions (REP-105 twist, joint
names, wear rows, steering targets); the CDR bytes are rclpy's own; a recording whose
writer was SIGKILLed is refused by the standard reader and read whole after ``msagv
recover``."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from helpers import msagv, run_msagv
from msagv.bridge import messages as M
from msagv.bridge import ros_msgs as R
from msagv.bridge.recording import Recorder
from msagv.plant import Plant, default_vehicle

KEY_STATE, KEY_CMD = "msagv/t/state", "msagv/t/cmd"
T = 0.01


def _run(n: int):
    """n states of a turning plant (per-wheel wear included) and the commands answering
    them: (state payloads, command payloads, decoded states, commands)."""
    p = Plant(initial={"vx": 3.0})
    r = p.vehicle.wheel_radius
    states, cmds, dec, raw_cmds = [], [], [], []
    for k in range(n):
        st = p.state_message()
        st["t"] = k * T
        states.append(M.encode_state(k, st))
        dec.append(M.decode_state(states[-1], 4))
        om_w, om_s = [3.1 / r] * 4, [0.05 + 0.01 * k % 3, 0.05, -0.05, -0.04]
        cmds.append(M.encode_cmd(k, k * T, k, om_w, om_s, solve_ms=1.0))
        raw_cmds.append((om_w, om_s))
        p.set_inputs(om_w, om_s)
        p.do_step(p.t, T)
    return states, cmds, dec, raw_cmds


def _header() -> dict:
    return {"role": "plant", "id": "t", "vehicle": default_vehicle().to_dict(), "period": T,
            "run_mode": "lockstep", "reference": {"t": [0, 1, 2], "x": [0, 1, 2],
                                                  "y": [0, 0.5, 0], "phi": [0, 0.3, 0]}}


def _record(path: Path, n: int = 40):
    states, cmds, dec, raw = _run(n)
    rec = Recorder(path, _header(), flush_s=0.05)
    for k in range(n):
        rec.message("tx", KEY_STATE, states[k], ts=1000.0 + k * T)
        rec.message("rx", KEY_CMD, cmds[k], ts=1000.0 + k * T + 0.002)
    rec.predicted_path(0.0, 0.1, [[0, 0, 0], [0.3, 0.01, 0.02], [0.6, 0.03, 0.04]])
    stats = rec.close({"steps": n})
    return stats, dec, raw


def test_the_bag_beside_a_recording_is_read_by_rosbags(tmp_path):
    from rosbags.highlevel import AnyReader

    stats, dec, raw = _record(tmp_path / "run.mcap")
    bag = tmp_path / "run_ros2"
    assert stats["ros2_bag"] == str(bag) and stats["errors"] == 0
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "run_ros2_0.mcap"]
    got: dict[str, list] = {}
    with AnyReader([bag], default_typestore=R.typestore()) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for c, _, data in reader.messages():
            got.setdefault(c.topic, []).append(reader.deserialize(data, c.msgtype))
    assert types == {"/" + k: v for k, v in R.TYPES.items()}
    n = len(dec)
    assert len(got["/markers"]) == (n + R.MARKER_EVERY - 1) // R.MARKER_EVERY  # 10 Hz
    for topic in ("/odom", "/tf", "/joint_states", "/wear", "/clock",
                  "/steering_controller/commands", "/wheel_controller/commands"):
        assert len(got[topic]) == n, topic
    assert stats["ros2_messages"] == sum(len(v) for v in got.values())
    for st, od, tf, js in zip(dec, got["/odom"], got["/tf"], got["/joint_states"]):
        # pose in odom, the stamp the vehicle time
        assert (od.header.frame_id, od.child_frame_id) == ("odom", "base_link")
        assert R.stamp_seconds(od.header.stamp) == pytest.approx(st["t"], abs=1e-9)
        assert (od.pose.pose.position.x, od.pose.pose.position.y) == (st["x"], st["y"])
        q = od.pose.pose.orientation
        assert 2 * math.atan2(q.z, q.w) == pytest.approx(st["phi"], abs=1e-12)
        # REP-105: the twist in base_link; the state's velocity is in the global frame
        c, s = math.cos(st["phi"]), math.sin(st["phi"])
        assert od.twist.twist.linear.x == pytest.approx(c * st["vx"] + s * st["vy"], abs=1e-12)
        assert od.twist.twist.linear.y == pytest.approx(-s * st["vx"] + c * st["vy"], abs=1e-12)
        assert od.twist.twist.angular.z == st["r"]
        tr = tf.transforms[0]
        assert (tr.header.frame_id, tr.child_frame_id) == ("odom", "base_link")
        assert tr.transform.translation.x == st["x"]
        assert list(js.name) == ["steer_11", "steer_12", "steer_21", "steer_22",
                                 "wheel_11", "wheel_12", "wheel_21", "wheel_22"]
        assert list(js.position[:4]) == st["delta"]
        assert list(js.velocity[4:]) == st["omega_w"]
    # the wheels' angles integrate their speeds (trapezoid), from 0 at the first state
    a = got["/joint_states"][-1].position[4:]
    om = np.array([s["omega_w"] for s in dec])
    np.testing.assert_allclose(a, T * (om[1:] + om[:-1]).sum(axis=0) / 2, rtol=1e-12)
    # wear: rows P_tw [W] (the last period's mean), W_tw [J]; columns the wheels
    w = got["/wear"][-1]
    assert [d.label for d in w.layout.dim] == ["P_tw|W_tw", "11|12|21|22"]
    W = lambda st: np.sum([st[k] for k in ("W_s_ij", "W_alpha_ij", "W_t_ij")], axis=0)  # noqa: E731
    np.testing.assert_allclose(w.data[4:], W(dec[-1]), rtol=1e-12)
    np.testing.assert_allclose(w.data[:4], (W(dec[-1]) - W(dec[-2])) / T, rtol=1e-9)
    assert w.data[4:].sum() == pytest.approx(dec[-1]["W_s"] + dec[-1]["W_alpha"] + dec[-1]["W_t"])
    # steering angle targets: the angle after one period at the commanded rate
    for st, (om_w, om_s), sc, wc in zip(dec, raw, got["/steering_controller/commands"],
                                        got["/wheel_controller/commands"]):
        np.testing.assert_allclose(sc.data, np.array(st["delta"]) + T * np.array(om_s),
                                   rtol=0, atol=1e-15)
        assert list(wc.data) == om_w
    # the vehicle drawn: a body and four wheels at their steering angles, in base_link
    mk = got["/markers"][-1].markers
    last = dec[(n - 1) // R.MARKER_EVERY * R.MARKER_EVERY]
    assert [(m.ns, m.type) for m in mk] == [("body", 1)] + [("wheel", 3)] * 4
    assert all(m.header.frame_id == "base_link" and m.frame_locked for m in mk)
    for m, d in zip(mk[1:], last["delta"]):
        # the cylinder's axis (its z) lies along the wheel's axle, turned by delta
        qx, qy, qz, qw = (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
                          m.pose.orientation.w)
        axis = (2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx), 1 - 2 * (qx * qx + qy * qy))
        np.testing.assert_allclose(axis, [math.sin(d), -math.cos(d), 0.0], atol=1e-12)
    # the plan (the header's reference) and the predicted path
    plan = got["/plan"][0]
    assert [p.pose.position.y for p in plan.poses] == [0, 0.5, 0]
    assert [R.stamp_seconds(p.header.stamp) for p in plan.poses] == [0, 1, 2]
    pred = got["/predicted_path"][0]
    assert [p.pose.position.x for p in pred.poses] == [0, 0.3, 0.6]
    assert [round(R.stamp_seconds(p.header.stamp), 9) for p in pred.poses] == [0, 0.1, 0.2]


def test_the_bag_decodes_with_mcap_ros2_support(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    _, dec, _ = _record(tmp_path / "run.mcap")
    path = tmp_path / "run_ros2" / "run_ros2_0.mcap"
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        odom = []
        n = 0
        for schema, channel, _, msg in reader.iter_decoded_messages():
            assert (schema.encoding, channel.message_encoding) == ("ros2msg", "cdr")
            n += 1
            if channel.topic == "/odom":
                odom.append((msg.pose.pose.position.x, msg.pose.pose.position.y))
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert odom == [(st["x"], st["y"]) for st in dec]
    assert n > 7 * len(dec)
    assert json.loads(meta["msagv.header"]["role"]) == "plant"


def _rclpy():
    try:
        import rclpy.serialization  # noqa: F401
    except Exception as e:  # noqa: BLE001 - missing wheels or a broken install
        pytest.skip(f"rclpy not available on this platform ({type(e).__name__}: {e})")
    import importlib

    return importlib


def _same(ours, theirs, where: str) -> None:
    """A typestore message and an rclpy message hold the same values, field by field."""
    if hasattr(ours, "__dataclass_fields__"):
        for f in (f for f in ours.__dataclass_fields__ if not f.startswith("__")):
            _same(getattr(ours, f), getattr(theirs, f), f"{where}.{f}")
    elif isinstance(ours, (list, tuple, np.ndarray)):
        assert len(ours) == len(theirs), where
        for i, (a, b) in enumerate(zip(ours, theirs)):
            _same(a, b, f"{where}[{i}]")
    else:
        # (float32 fields: rclpy holds the float32 value)
        assert ours == theirs or (ours != ours and theirs != theirs) or \
            (isinstance(ours, float) and float(np.float32(ours)) == theirs), (where, ours, theirs)


def test_cdr_bytes_decode_in_rclpy_to_the_same_values(tmp_path):
    """Every type we write: our CDR (rosbags) deserialised by rclpy holds the values we
    encoded, field by field, and so does rclpy's own serialisation of it."""
    importlib = _rclpy()
    from rclpy.serialization import deserialize_message, serialize_message

    states, _, dec, raw = _run(5)
    rm = R.RunMessages(default_vehicle(), T)
    msgs = []
    for st in dec:
        msgs += rm.state_messages(st)
    msgs += rm.commands(dec[-1]["t"], dec[-1]["delta"], *raw[-1])
    msgs += [(R.PLAN, R.reference_path(_header()["reference"])),
             (R.PREDICTED_PATH, R.predicted_path(0.5, 0.1, [[1, 2, 0.1], [1.1, 2.05, 0.12]]))]
    checked = set()
    for topic, m in msgs:
        typ = R.TYPES[topic]
        pkg, _, name = typ.split("/")
        try:
            cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
        except ImportError:
            assert typ == "tf2_msgs/msg/TFMessage"  # no wheel of tf2_msgs in the registry
            continue
        data = R.encode(m, typ)
        _same(m, deserialize_message(data, cls), typ)
        # rclpy's own bytes of that message: the same values as ours (not the same bytes:
        # CDR leaves padding unspecified, Fast-CDR neither zeroes it nor stops at the last
        # field, so a byte comparison would test padding, not the encoding)
        _same(m, deserialize_message(serialize_message(deserialize_message(data, cls)), cls),
              typ)
        checked.add(typ)
    assert checked | {"tf2_msgs/msg/TFMessage"} == set(R.TYPES.values())
    # and the other way: rclpy's bytes decoded by rosbags
    from nav_msgs.msg import Odometry

    o = Odometry()
    o.header.frame_id, o.pose.pose.position.x, o.twist.twist.angular.z = "odom", 1.5, -0.25
    d = R.decode(serialize_message(o), "nav_msgs/msg/Odometry")
    assert (d.header.frame_id, d.pose.pose.position.x, d.twist.twist.angular.z) == \
        ("odom", 1.5, -0.25)


def test_state_from_ros_inverts_the_mapping():
    _, _, dec, _ = _run(30)
    rm = R.RunMessages(default_vehicle(), T)
    for st in dec[::7]:
        rm.state_messages(st)
        back = R.state_from_ros(rm.odom(st), rm.joint_states(st), 4)
        for k in ("t", "x", "y", "phi", "r"):
            assert back[k] == pytest.approx(st[k], abs=1e-12)
        assert back["vx"] == pytest.approx(st["vx"], abs=1e-12)
        assert back["vy"] == pytest.approx(st["vy"], abs=1e-12)
        assert back["delta"] == st["delta"] and back["omega_w"] == st["omega_w"]
    # joints in another order, with extra joints: found by name
    js = R.new("sensor_msgs/msg/JointState", name=["x", "wheel_22", "steer_22", "wheel_21",
                                                   "steer_21", "wheel_12", "steer_12",
                                                   "wheel_11", "steer_11"],
               position=[9, 0, 0.4, 0, 0.3, 0, 0.2, 0, 0.1], velocity=[9, 4, 0, 3, 0, 2, 0, 1, 0])
    back = R.state_from_ros(rm.odom(dec[0]), js, 4)
    assert back["delta"] == [0.1, 0.2, 0.3, 0.4] and back["omega_w"] == [1, 2, 3, 4]
    bad = R.new("sensor_msgs/msg/JointState", name=["steer_11"], position=[0.1], velocity=[0])
    with pytest.raises(R.RosMessageError, match="no velocity of joint wheel_11"):
        R.state_from_ros(rm.odom(dec[0]), bad, 4)


def test_steering_targets_and_rates_are_inverse():
    lim = default_vehicle().limits
    delta = np.array([0.1, -0.2, 0.0, 0.3])
    rates = np.array([0.5, -0.4, 0.0, 0.2])
    tgt = R.steering_targets(delta, rates, T, lim)
    np.testing.assert_allclose(tgt, delta + rates * T)
    np.testing.assert_allclose(R.steering_rates(delta, tgt, T, lim), rates, atol=1e-12)
    # beyond the rate limit: the largest rate toward the target
    far = R.steering_rates(delta, delta + 10.0, T, lim)
    np.testing.assert_allclose(far, lim.omega_s_max)
    # a target beyond the angle limit is clipped to it
    assert R.steering_targets([lim.delta_max], [5.0], T, lim)[0] == lim.delta_max


# ---- a kill ---------------------------------------------------------------------------------
WRITER = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {tests!r})
    from test_ros_recording import KEY_STATE, KEY_CMD, _run, _header
    from msagv.bridge.recording import Recorder
    states, cmds, _, _ = _run(300)
    rec = Recorder(sys.argv[1], _header(), flush_s=0.05)
    for k in range(300):
        rec.message("tx", KEY_STATE, states[k], ts=1000.0 + k * 0.01)
        rec.message("rx", KEY_CMD, cmds[k], ts=1000.0 + k * 0.01 + 0.002)
        if k % 50 == 49:
            rec.flush()
            print(k + 1, flush=True)
    time.sleep(120)
""")


def test_a_killed_recording_is_refused_then_recovered_whole(tmp_path):
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    script = tmp_path / "w.py"
    script.write_text(WRITER.format(tests=str(Path(__file__).parent)))
    path = tmp_path / "run.mcap"
    p = subprocess.Popen([sys.executable, str(script), str(path)], stdout=subprocess.PIPE,
                         text=True)
    try:
        flushed = 0
        t0 = time.monotonic()
        while flushed < 300 and time.monotonic() - t0 < 60:
            line = p.stdout.readline()
            if not line:
                break
            flushed = int(line)
        assert flushed == 300, "the writer did not flush its states"
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        p.stdout.close()
    with path.open("rb") as f, pytest.raises(Exception):
        list(make_reader(f).iter_messages())
    # the bag's writer, a child process, finished the bag when its input ended with the kill
    bag = tmp_path / "run_ros2"
    for _ in range(100):
        if (bag / "metadata.yaml").exists():
            break
        time.sleep(0.1)
    assert (bag / "metadata.yaml").exists()
    r = run_msagv("recover", path, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    main, bagfile = out["files"]
    assert not main["complete"] and main["by_topic"] == {KEY_STATE: 300, KEY_CMD: 300}
    assert bagfile["complete"] and bagfile["by_topic"]["/odom"] == 300
    assert out["bag"]["messages"] == bagfile["messages"]
    with path.open("rb") as f:
        seqs = [M.decode_state(m.data, 4)["seq"] for _, c, m in make_reader(f).iter_messages()
                if c.topic == KEY_STATE]
    assert seqs == list(range(300))
    # msagv report reads the recovered recording; recover again: nothing to do
    assert run_msagv("report", path, "--json").returncode == 0
    again = json.loads(run_msagv("recover", path, "--json").stdout)
    assert all(f["complete"] for f in again["files"])
    # a bag cut as well (the whole process group killed, a power cut): its file without
    # its summary and footer, no metadata.yaml; recovered for rosbags
    f0 = bag / "run_ros2_0.mcap"
    data = f0.read_bytes()
    f0.write_bytes(data[: int(len(data) * 0.6)])
    (bag / "metadata.yaml").unlink()
    with f0.open("rb") as f, pytest.raises(Exception):
        list(make_reader(f).iter_messages())
    out = json.loads(run_msagv("recover", path, "--json").stdout)
    cut = out["files"][1]
    assert not cut["complete"] and 50 < cut["by_topic"]["/odom"] < 300
    with AnyReader([bag], default_typestore=R.typestore()) as reader:
        odom = [c for c in reader.connections if c.topic == "/odom"][0]
        assert odom.msgcount == cut["by_topic"]["/odom"]
        assert sum(1 for _ in reader.messages(connections=[odom])) == odom.msgcount


def test_recover_refuses_what_is_no_recording(tmp_path):
    r = run_msagv("recover", tmp_path / "missing.mcap")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == \
        [f"msagv recover: {tmp_path / 'missing.mcap'}: no such file"]
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    r = run_msagv("recover", junk)
    assert r.returncode == 2 and "not an MCAP file" in r.stderr and "Traceback" not in r.stderr
    assert junk.read_bytes() == b"not an mcap file at all"  # unchanged
