"""``--foxglove`` (issue 19 item 5): a client of the Foxglove WebSocket protocol, written here
with the ``websockets`` library from the protocol's description (no Foxglove code), connects
to ``msagv run --foxglove`` and ``msagv ros2 plant --foxglove``, is advertised the run's ROS 2
channels (cdr, ros2msg schemas) and receives their messages at the run's rate; the payloads
decode with ``mcap-ros2-support``'s decoder built from the advertised schema; a bad option
is refused in one line.

Issue 32 item 6: the official client, ``FoxgloveClient`` of npm ``@foxglove/ws-protocol``
(which offers ``foxglove.websocket.v1``), run in Node (``tests/node/``, installed by ``make
test`` with ``npm ci``), receives every advertised channel at the run's rate, and a client
that leaves costs the server no error; both names of the protocol are accepted, anything
else refused at the handshake."""

from __future__ import annotations

import base64
import json
import shutil
import struct
import subprocess
import time

import pytest

from helpers import ROOT, free_port, msagv, ros_domain_id, run_msagv

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

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain_id()))
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


# ---- the official client: npm @foxglove/ws-protocol in Node ---------------------------------
NODE_DIR = ROOT / "tests" / "node"


@pytest.fixture(scope="module")
def npm_client():
    """The command line of tests/node/foxglove_client.mjs; its packages installed (npm ci) if
    `make test` has not; skips only when Node or npm is not on this machine."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (Debian: apt-get install nodejs npm; `make test` "
                    "installs it as root)")
    if not (NODE_DIR / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        npm = shutil.which("npm")
        if npm is None:
            pytest.skip("npm is not installed (Debian: apt-get install npm)")
        r = subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=NODE_DIR,
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, f"npm ci in tests/node failed:\n{r.stderr[-3000:]}"
    return [node, str(NODE_DIR / "foxglove_client.mjs")]


def _npm_result(path):
    got = json.loads(path.read_text())
    got["messages"] = [(t, int(ts), base64.b64decode(p)) for t, ts, p in got["messages"]]
    return got


def _stamp(msg) -> float:
    h = msg.header if hasattr(msg, "header") else msg.transforms[0].header
    return h.stamp.sec + h.stamp.nanosec * 1e-9


def test_the_official_npm_client_receives_every_channel_at_the_run_rate(procs, npm_client,
                                                                        tmp_path):
    from msagv.bridge.ros_msgs import MARKER_EVERY

    port = free_port()
    procs.start("run", msagv("run", "--case", "curve", "--speed", "15", "--duration", "2.5",
                             "--foxglove", "--foxglove-port", port, "--foxglove-wait", "240",
                             "--json", "-q"))
    url = ["--url", f"ws://127.0.0.1:{port}", "--connect-timeout", "240"]
    # a viewer for the whole run, and one that closes its tab after 150 messages
    procs.start("npm", npm_client + url + ["--out", tmp_path / "got.json", "--seconds", "300"])
    procs.start("leaves", npm_client + url + ["--out", tmp_path / "left.json",
                                              "--seconds", "300", "--close-after", "150"])
    assert procs.wait("npm", 330) == 0, procs.err("npm")
    assert procs.wait("leaves", 60) == 0, procs.err("leaves")
    assert procs.wait("run", 60) == 0, procs.err("run")
    got = _npm_result(tmp_path / "got.json")
    # the handshake: the client's own protocol name, the server's info and channels
    assert got["protocol"] == "foxglove.websocket.v1" and got["error"] is None
    assert got["closed"] == "server"  # it stayed until the run ended
    assert got["serverInfo"]["name"] == "msagv run"
    assert {c["topic"]: c["schemaName"] for c in got["channels"]} == CHANNELS
    dec = _decoders({c["id"]: c for c in got["channels"]})
    by_topic: dict[str, list] = {t: [] for t in CHANNELS}
    for topic, ts, payload in got["messages"]:
        by_topic[topic].append((ts, dec[topic](payload)))
    # every advertised channel at the run's rate: each state's messages, from the first the
    # client was subscribed for to the run's last state (it subscribed before the run began:
    # --foxglove-wait), in order, none missing
    run = procs.json("run")
    period, n = run["scenario"]["period_s"], round(run["scenario"]["duration_s"]
                                                   / run["scenario"]["period_s"])
    last = (n - 1) * period
    for topic in ("/odom", "/tf", "/joint_states", "/clock"):
        stamps = [_stamp(m) if topic != "/clock" else m.clock.sec + m.clock.nanosec * 1e-9
                  for _, m in by_topic[topic]]
        assert stamps, topic
        k0 = round(stamps[0] / period)
        assert stamps == pytest.approx([k * period for k in range(k0, n)], abs=1e-9), topic
    # /odom from (about) the run's first state: the run starts when the first of the two
    # clients subscribes, the other one's subscriptions may land a few states later
    assert len(by_topic["/odom"]) >= n - 10
    # a state's messages and its command share their log time: the topics without a stamp
    # carry one message per state of /odom's, the last ones included
    odom_t = [ts for ts, _ in by_topic["/odom"]]
    for topic in ("/wear", "/steering_controller/commands", "/wheel_controller/commands"):
        log_t = [ts for ts, _ in by_topic[topic]]
        assert log_t and log_t == odom_t[len(odom_t) - len(log_t):], topic
    assert len(by_topic["/predicted_path"]) >= 1
    assert all(len(m.poses) > 1 for _, m in by_topic["/predicted_path"])
    marks = [_stamp(m.markers[0]) for _, m in by_topic["/markers"]]
    k0 = round(marks[0] / period)
    assert marks == pytest.approx([k * period for k in range(k0, n, MARKER_EVERY)], abs=1e-9)
    assert [m.ns for m in by_topic["/markers"][-1][1].markers] == \
        ["body", "wheel", "wheel", "wheel", "wheel"]
    plans = [m for _, m in by_topic["/plan"]]
    assert plans and all(len(p.poses) > 2 and p.header.frame_id == "odom" for p in plans)
    # sent as the run's clock reaches each state, never ahead of it: log times [ns] spread
    # at least as far as the stamps
    log_t = [ts for ts, _ in by_topic["/odom"]]
    assert all((b - log_t[0]) / 1e9 >= (k * period) - 2e-3 for k, b in enumerate(log_t))
    assert last == pytest.approx(_stamp(by_topic["/odom"][-1][1]), abs=1e-9)
    # the client that left: served until it closed, and the server printed nothing about it
    left = _npm_result(tmp_path / "left.json")
    assert left["protocol"] == "foxglove.websocket.v1" and left["closed"] == "client"
    assert len(left["messages"]) >= 150
    err = procs.err("run")
    for word in ("Error", "Traceback", "on_unsubscribe", "Dropping client"):
        assert word not in err, err


def test_both_names_of_the_protocol_and_nothing_else():
    """The handshake as websockets' client sees it: foxglove.websocket.v1 and foxglove.sdk.v1
    each answered with the name offered (the newer one when both are), any other name
    refused with HTTP 400; the view's close ends the connections it serves."""
    from websockets.sync.client import connect

    from msagv.experiments.foxglove import FoxgloveView
    from msagv.plant.vehicle import default_vehicle

    view = FoxgloveView({"vehicle": default_vehicle().to_dict(), "period": 0.01},
                        port=0, name="handshake")
    url = view.address
    try:
        for offer, chosen in ((["foxglove.websocket.v1"], "foxglove.websocket.v1"),
                              (["foxglove.sdk.v1"], "foxglove.sdk.v1"),
                              (["foxglove.websocket.v1", "foxglove.sdk.v1"], "foxglove.sdk.v1")):
            with connect(url, subprotocols=offer, open_timeout=30) as ws:
                assert ws.subprotocol == chosen, offer
                info = json.loads(ws.recv(timeout=30))
                assert info["op"] == "serverInfo" and info["name"] == "handshake"
        with pytest.raises(websockets.exceptions.InvalidStatus) as e:
            connect(url, subprotocols=["foxglove.websocket.v2"], open_timeout=30)
        assert e.value.response.status_code == 400
        with connect(url, subprotocols=["foxglove.websocket.v1"], open_timeout=30) as ws:
            ws.recv(timeout=30)
            view.close()
            with pytest.raises(websockets.exceptions.ConnectionClosed):
                while True:
                    ws.recv(timeout=30)
    finally:
        view.close()
