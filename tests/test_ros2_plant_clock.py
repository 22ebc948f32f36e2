"""``msagv ros2 plant --run-mode realtime`` under ``use_sim_time`` (issue 32 item 1): its time
is a simulator's ``/clock``, here one written with rclpy that runs at 0.2x real time.

Real rclpy on loopback (a random domain id), the plant a process of its own, stopped by its
id. The peer is the clock and the controller: it advances ``/clock`` by 1 ms every 5 ms of
wall time and answers every state at once. A plant on the wall clock sends a state every
10 ms of wall time, 2 ms of the simulator's; on the simulator's clock, every 10 ms of it.
"""

from __future__ import annotations

import time

import test_ros2_nodes as ros_nodes
from helpers import msagv
from test_ros2_nodes import Peer, _ros, answer_each_state

T = 0.01
ros_env = ros_nodes.ros_env  # the fixture: loopback discovery, a domain of this test alone


def test_a_realtime_plant_under_sim_time_steps_on_the_simulators_clock(procs, ros_env):
    _ros()
    from rosgraph_msgs.msg import Clock
    from std_msgs.msg import Float64MultiArray

    n, rate, tick = 30, 0.2, 0.001  # steps; the simulator's pace; its clock's resolution [s]
    procs.start("plant", msagv("ros2", "plant", "--run-mode", "realtime", "--case", "line",
                               "--speed", "10", "--duration", f"{n * T:g}", "--json",
                               "--ros-args", "-p", "use_sim_time:=true"))
    peer = Peer("sim")
    pub_clock = peer.node.create_publisher(Clock, "clock", 10)
    steer = peer.node.create_publisher(Float64MultiArray, "steering_controller/commands", 10)
    wheel = peer.node.create_publisher(Float64MultiArray, "wheel_controller/commands", 10)
    sim = {"t": 0.0}
    seen_at = {}

    def answer(k):
        seen_at[k] = sim["t"]  # the simulator's time when state k came
        pos = dict(zip(joints[k].name, joints[k].position))
        delta = [pos[f"steer_{w}"] for w in ("11", "12", "21", "22")]
        steer.publish(Float64MultiArray(data=delta))  # hold the steering
        wheel.publish(Float64MultiArray(data=[5.0] * 4))

    odoms, joints = answer_each_state(peer.node, T, answer)
    clock_publishers = None
    try:
        due, t_end = time.monotonic(), time.monotonic() + 180
        while n not in seen_at and time.monotonic() < t_end:
            if time.monotonic() >= due:  # the simulator: 1 ms of its time per 5 ms of ours
                sim["t"] += tick
                c = Clock()
                c.clock.sec, c.clock.nanosec = divmod(round(sim["t"] * 1e9), 1_000_000_000)
                pub_clock.publish(c)
                due += tick / rate
            if clock_publishers is None and 0 in seen_at:
                clock_publishers = peer.node.count_publishers("/clock")
            peer.ex.spin_once(timeout_sec=0.001)
    finally:
        peer.close()
    assert n in seen_at, procs.err("plant")[-2000:]
    assert procs.wait("plant", 60) == 0, procs.err("plant")[-2000:]
    s = procs.json("plant")
    assert s["completed"] and s["clock"] == "ros" and s["run_mode"] == "realtime"
    assert clock_publishers == 1  # the simulator's alone: the plant left /clock to it
    # states 1..n came one period of the simulator's clock apart (a plant on the wall clock:
    # 0.2 of a period); each within a few ticks of its time, on a loaded machine too
    spacing = (seen_at[n] - seen_at[1]) / (n - 1)
    assert 0.8 * T < spacing < 1.2 * T, spacing
    # answered at once in the simulator's time: never stale, never safe
    assert s["safe"]["events"] == 0 and s["periods"]["safe"] == 0, s
