"""``--foxglove`` (issue 19 item 5): a client of the Foxglove WebSocket protocol, written here
with the ``websockets`` library from the protocol's description (no Foxglove code), connects
to ``msagv run --foxglove`` and ``msagv ros2 plant --foxglove``, is advertised the run's ROS 2
channels (cdr, ros2msg schemas) and receives their messages at the run's rate; the payloads
decode with ``mcap-ros2-support``'s decoder built from the advertised schema; a bad option
is refused in one line."""

from __future__ import annotations

import json
import struct
import time

import pytest

from helpers import free_port, msagv, run_msagv

websockets = pytest.importorskip("websockets")
pytest.importorskip("foxglove")

CHANNELS = {"/odom": "nav_msgs/msg/Odometry", "/tf": "tf2_msgs/msg/TFMessage",
            "/joint_states": "sensor_msgs/msg/JointState",
            "/wear": "std_msgs/msg/Float64MultiArray",
            "/markers": "visualization_msgs/msg/MarkerArray", "/plan": "nav_msgs/msg/Path",
            "/predicted_path": "nav_msgs/msg/Path", "/clock": "rosgraph_msgs/msg/Clock",
            "/steering_controller/commands": "std_msgs/msg/Float64MultiArray",
            "/wheel_controller/commands": "std_msgs/msg/Float64MultiArray"}


def _client(port: int, seconds: float, connect_timeout: float = 120.0):
    """Connect (retrying while the server starts), subscribe to every advertised channel,
    collect (topic, log time [ns], payload) for ``seconds`` or until the server closes."""
    from websockets.sync.client import connect

    t0 = time.monotonic()
    while True:
        try:
            ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                         open_timeout=5)
            break
        except (OSError, TimeoutError, websockets.exceptions.InvalidHandshake):
            if time.monotonic() - t0 > connect_timeout:
                raise
            time.sleep(0.2)
    channels: dict[int, dict] = {}
    subs: dict[int, int] = {}
    got = []
    end = time.monotonic() + seconds
    with ws:
        while time.monotonic() < end:
            try:
                m = ws.recv(timeout=max(0.05, end - time.monotonic()))
            except TimeoutError:
                continue
            except websockets.exceptions.ConnectionClosed:
                break
            if isinstance(m, str):
                op = json.loads(m)
                if op.get("op") == "advertise":
                    new = []
                    for ch in op["channels"]:
                        channels[ch["id"]] = ch
                        subs[len(subs) + 1] = ch["id"]
                        new.append({"id": len(subs), "channelId": ch["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
            elif m[0] == 0x01:  # message data: u32 subscription id, u64 log time, payload
                sid, ts = struct.unpack_from("<IQ", m, 1)
                got.append((channels[subs[sid]]["topic"], ts, bytes(m[13:])))
    return channels, got


def _decoders(channels):
    from mcap_ros2._dynamic import generate_dynamic

    out = {}
    for ch in channels.values():
        assert (ch["encoding"], ch["schemaEncoding"]) == ("cdr", "ros2msg"), ch
        out[ch["topic"]] = generate_dynamic(ch["schemaName"], ch["schema"])[ch["schemaName"]]
    return out


def test_a_foxglove_client_receives_the_run_live(procs):
    port = free_port()
    procs.start("run", msagv("run", "--case", "curve", "--speed", "15", "--duration", "2",
                             "--foxglove", "--foxglove-port", port, "--foxglove-wait", "120",
                             "--json", "-q"))
    channels, got = _client(port, 60)
    assert procs.wait("run", 60) == 0, procs.err("run")
    assert f"Foxglove: open connection ws://127.0.0.1:{port}" in procs.err("run")
    assert {c["topic"]: c["schemaName"] for c in channels.values()} == CHANNELS
    dec = _decoders(channels)
    odom = [(ts, dec["/odom"](p)) for topic, ts, p in got if topic == "/odom"]
    # the run's rate: one odometry per period, sent as the wall clock reaches its time
    assert len(odom) >= 190
    span = (odom[-1][0] - odom[0][0]) / 1e9
    rate = (len(odom) - 1) / span
    assert 90 < rate < 110, rate
    stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for _, m in odom]
    assert all(b - a == pytest.approx(0.01, abs=1e-9) for a, b in zip(stamps, stamps[1:]))
    # the run's poses: the last odometry is the run's state at its stamp
    run = procs.json("run")
    assert run["completed"] and odom[-1][1].header.frame_id == "odom"
    assert {t for t, _, _ in got} >= {"/odom", "/tf", "/joint_states", "/wear", "/markers",
                                      "/plan", "/predicted_path", "/steering_controller/commands"}
    mk = [dec["/markers"](p) for t, _, p in got if t == "/markers"][-1]
    assert [m.ns for m in mk.markers] == ["body", "wheel", "wheel", "wheel", "wheel"]


def test_the_ros2_plant_serves_foxglove(procs, monkeypatch):
    pytest.importorskip("rclpy")
    import random

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(random.randint(1, 100)))
    port = free_port()
    procs.start("plant", msagv("ros2", "plant", "--duration", "1", "--foxglove",
                               "--foxglove-port", port, "--json", "-q"))
    procs.start("ctl", msagv("ros2", "controller", "--case", "curve", "-q"))
    channels, got = _client(port, 90)
    assert procs.wait("plant", 60) == 0, procs.err("plant")
    assert {c["topic"] for c in channels.values()} == set(CHANNELS)
    dec = _decoders(channels)
    odom = [dec["/odom"](p) for t, _, p in got if t == "/odom"]
    wheels = [dec["/wheel_controller/commands"](p) for t, _, p in got
              if t == "/wheel_controller/commands"]
    assert len(odom) >= 90 and len(wheels) >= 90
    final = procs.json("plant")["final_state"]
    assert odom[-1].pose.pose.position.x == pytest.approx(final["x"], abs=1e-12)


def test_foxglove_options_are_checked_first():
    r = run_msagv("run", "--duration", "1", "--foxglove", "--foxglove-port", "70000")
    assert r.returncode == 2 and r.stderr.strip() == \
        "msagv run: --foxglove-port must be 0..65535, got 70000"
    r = run_msagv("run", "--duration", "0.05", "--foxglove", "--foxglove-port", "0",
                  "--foxglove-host", "127.0.0.2", "--json", "-q")
    assert r.returncode == 0, r.stderr
    assert "msagv run: warning: --foxglove-host 127.0.0.2: the Foxglove server is " \
           "unauthenticated" in r.stderr
