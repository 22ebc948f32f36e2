"""``msagv ros2 plant --managed`` driven as Nav2's lifecycle_manager drives a managed node
(issue 32 item 5): real rclpy on loopback (a random domain id), the plant a process of its
own, stopped by its id.

The peer is the lifecycle manager (``~/change_state`` and ``~/get_state``, lifecycle_msgs)
and the controller: it answers every state with the same commands (the wheels at 2.2 m/s
at the rim, the steering held where it starts), so every state the plant publishes is the
plant's equations stepped that many times from the start, whichever command a step took:
the independent reference is the stepping plant run in this process. A state that moved
while the plant was inactive, or a run that went safe over the pause, departs from it.
"""

from __future__ import annotations

import json

import pytest

import test_ros2_nodes as ros_nodes
from helpers import msagv
from test_ros2_nodes import Peer, _ros, _yaw, answer_each_state, node_calls

T = 0.2  # the period, and --stale-ms below: long enough that a loaded machine's stall of the
# plant's own loop (seen: 380 ms and 1.14 s at a load of 4-10 on 2 cores) is no re-anchor
# (10 periods) and no staleness, as the node's pauses (3.5 s) would be on a clock that ran
N = 15  # the periods run between two transitions
ros_env = ros_nodes.ros_env  # the fixture: loopback discovery, a domain of this test alone
R_W = 0.5  # the paper vehicle's wheel radius (plant/data/paper-2axle.toml)
DELTA0 = [0.05, 0.0, 0.0, 0.0]  # the initial steering angles (--initial delta_11=0.05)


@pytest.mark.parametrize("run_mode", ["lockstep", "realtime"])
def test_the_managed_plant_goes_through_its_lifecycle(procs, ros_env, run_mode):
    """Unconfigured: nothing published. Configured (inactive): its topics declared, no
    state published. Active: the run goes. Deactivated: no state, the vehicle stands where
    it was (the next state is the one that was due, stepped from the same state: a paused
    simulator), and a realtime plant does not count the pause as a silent controller (no
    safe behaviour, no watchdog, no clock re-anchored) although it lasts longer than
    ``--stale-ms``. Cleaned up: its topics gone. Configured and activated again: it goes
    on from where it stood. Shut down: the process ends, exit 0, with its summary."""
    _ros()
    from lifecycle_msgs.msg import Transition
    from std_msgs.msg import Float64MultiArray

    from msagv.experiments.scenario import Scenario

    stale_ms = 3000.0
    procs.start("plant", msagv("ros2", "plant", "--managed", "--run-mode", run_mode,
                               "--period", f"{T:g}",
                               "--case", "line", "--speed", "10", "--from-rest",
                               "--initial", "vx=2.0,delta_11=0.05", "--duration", "600",
                               "--stale-ms", f"{stale_ms:g}", "--wait", "60", "--json"))
    peer = Peer("lifecycle_manager")
    n = peer.node
    name = "/msagv_plant"
    state, transition, _ = node_calls(peer, name)
    steer = n.create_publisher(Float64MultiArray, "steering_controller/commands", 10)
    wheel = n.create_publisher(Float64MultiArray, "wheel_controller/commands", 10)
    def answer(k):
        steer.publish(Float64MultiArray(data=DELTA0))  # held: a rate of 0
        wheel.publish(Float64MultiArray(data=[2.2 / R_W] * 4))

    odoms, joints = answer_each_state(n, T, answer)

    def newest() -> int:
        return max(odoms, default=-1)

    def runs_to(k: int) -> None:
        assert peer.spin(120, until=lambda: newest() >= k), procs.err("plant")[-2000:]

    def publishers() -> int:
        return n.count_publishers("/odom")

    def paused() -> int:
        """The newest state once the states in flight are in; then none for longer than the
        staleness bound."""
        peer.spin(0.5)
        k = newest()
        peer.spin(3.0)  # (with the 0.5 s before: longer than --stale-ms)
        assert newest() == k, (k, newest())
        return k

    pauses = []
    try:
        assert state() == "unconfigured"
        peer.spin(1.0)
        assert publishers() == 0 and not odoms  # nothing declared, nothing published
        assert transition(Transition.TRANSITION_CONFIGURE)
        assert state() == "inactive"
        assert peer.spin(60, until=lambda: publishers() == 1)
        peer.spin(1.0)
        assert not odoms  # inactive: no state, though a controller is there
        assert transition(Transition.TRANSITION_ACTIVATE)
        assert state() == "active"
        runs_to(N)
        assert transition(Transition.TRANSITION_DEACTIVATE)
        assert state() == "inactive"
        pauses.append(paused())
        assert transition(Transition.TRANSITION_ACTIVATE)  # resumes
        runs_to(pauses[-1] + N)
        assert transition(Transition.TRANSITION_DEACTIVATE)
        pauses.append(paused())
        assert transition(Transition.TRANSITION_CLEANUP)
        assert state() == "unconfigured"
        assert peer.spin(60, until=lambda: publishers() == 0)  # its topics taken down
        assert transition(Transition.TRANSITION_CONFIGURE)
        assert transition(Transition.TRANSITION_ACTIVATE)  # on from where it stood
        runs_to(pauses[-1] + N)
        assert transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
        assert procs.wait("plant", 60) == 0, procs.err("plant")[-2000:]
    finally:
        peer.close()
    s = procs.json("plant")
    assert s["lifecycle"] == "finalized" and not s["completed"] and s["error"] is None
    assert [t["transition"] for t in s["transitions"]] == [
        "configure", "activate", "deactivate", "activate", "deactivate", "cleanup",
        "configure", "activate", "shutdown"]
    assert s["run_mode"] == run_mode and s["steps"] > pauses[-1]
    if run_mode == "lockstep":  # every step waited for the answer to its state
        assert s["commands"]["accepted"] >= s["steps"]
    else:  # every step took the newest command (a shutdown may come before the newest
        # state's answer; an answer after the next state is out answers that one)
        p = s["periods"]
        assert p["on_time"] + p["held"] == s["steps"] and p["safe"] == 0, json.dumps(s)
        assert s["commands"]["accepted"] > pauses[-1]
    # every state once, none lost over the pauses: each the plant's equations stepped k
    # times from the start (the vehicle stood while inactive)
    last = newest()
    assert sorted(odoms) == list(range(last + 1)) and s["steps"] == last
    plant, vehicle, _, _ = Scenario(case="line", speed=10, from_rest=True,
                                    initial={"vx": 2.0, "delta_11": 0.05}).make_plant()
    assert vehicle.wheel_radius == R_W
    for k in range(last + 1):
        st, o = plant.state_message(), odoms[k]
        assert o.pose.pose.position.x == pytest.approx(st["x"], abs=1e-9), k
        assert o.pose.pose.position.y == pytest.approx(st["y"], abs=1e-9), k
        assert _yaw(o.pose.pose.orientation) == pytest.approx(st["phi"], abs=1e-9), k
        pos = dict(zip(joints[k].name, joints[k].position))
        assert [pos[f"steer_{w}"] for w in ("11", "12", "21", "22")] == pytest.approx(
            st["delta"], abs=1e-12), k
        if k < last:
            plant.set_inputs([2.2 / R_W] * 4, [0.0] * 4)
            plant.do_step(plant.t, T)
    assert s["final_state"]["x"] == pytest.approx(plant.state_message()["x"], abs=1e-9)
    assert s["final_state"]["t"] == pytest.approx(last * T)
    # the pauses were no silence of the controller's: never safe, no watchdog, no re-anchor
    assert s["safe"] == {"events": 0, "periods": 0, "resumes": 0, "watchdog_trips": 0,
                         "watchdog_periods": 0}, s["safe"]
    assert s["clock_resyncs"] == 0


def test_the_managed_plant_refuses_a_wrong_transition_and_waits_only_while_active(procs,
                                                                                   ros_env):
    """A transition the lifecycle has not from where the node stands (activate while
    unconfigured) is refused and changes nothing. ``--wait`` (3 s) counts the time the
    node is active: unconfigured and inactive for 4 s the plant waits on, and activated
    then it waits its 3 s afresh (still there 2 s later: a wait that had counted the 4 s
    would end at once, and its process exits in about half a second), then ends with its
    error for want of a controller. A signal while inactive is a shutdown: exit 0,
    finalized, the summary printed."""
    _ros()
    import signal

    from lifecycle_msgs.msg import Transition

    from msagv.bridge.process import EXIT_OK, EXIT_RUNTIME

    peer = Peer("lifecycle_manager")
    state, transition, _ = node_calls(peer, "/msagv_plant")

    try:
        for name, signalled in (("waits", False), ("signalled", True)):
            procs.start(name, msagv("ros2", "plant", "--managed", "--run-mode", "realtime",
                                    "--case", "line", "--speed", "10", "--wait", "3",
                                    "--json"))
            assert state() == "unconfigured"
            assert not transition(Transition.TRANSITION_ACTIVATE)
            assert state() == "unconfigured"
            peer.spin(2.0)
            assert transition(Transition.TRANSITION_CONFIGURE) and state() == "inactive"
            peer.spin(2.0)
            assert procs.p[name].poll() is None  # 4 s > --wait: not active, not waiting
            if signalled:
                procs.p[name].send_signal(signal.SIGTERM)
                assert procs.wait(name, 60) == EXIT_OK, procs.err(name)[-2000:]
                s = procs.json(name)
                assert s["stopped_by"] == "SIGTERM" and s["error"] is None
                assert [t["transition"] for t in s["transitions"]] == ["configure",
                                                                       "shutdown"]
            else:
                assert transition(Transition.TRANSITION_ACTIVATE)
                peer.spin(2.0)
                assert procs.p[name].poll() is None, procs.err(name)[-2000:]
                assert procs.wait(name, 60) == EXIT_RUNTIME, procs.err(name)[-2000:]
                s = procs.json(name)
                assert s["error"].startswith("no controller within 3 s"), s["error"]
                assert [t["transition"] for t in s["transitions"]] == [
                    "configure", "activate", "shutdown"]
            assert s["lifecycle"] == "finalized" and s["steps"] == 0
            assert all(t["result"] == "success" for t in s["transitions"])
    finally:
        peer.close()


def assert_poses_from_start(odoms: dict, n: int) -> None:
    """``odoms[k]`` for k = 0..n is the plant's state k: the equations stepped k periods
    from the start these tests give (line at 10 km/h, from rest at vx 2 m/s, delta_11
    0.05) with every wheel at 2.2 m/s and the steering held, as their peers answer."""
    from msagv.experiments.scenario import Scenario

    plant, _, _, _ = Scenario(case="line", speed=10, from_rest=True,
                              initial={"vx": 2.0, "delta_11": 0.05}).make_plant()
    for k in range(n + 1):
        st, o = plant.state_message(), odoms[k]
        assert o.pose.pose.position.x == pytest.approx(st["x"], abs=1e-9), k
        assert o.pose.pose.position.y == pytest.approx(st["y"], abs=1e-9), k
        assert _yaw(o.pose.pose.orientation) == pytest.approx(st["phi"], abs=1e-9), k
        plant.set_inputs([2.2 / R_W] * 4, [0.0] * 4)
        plant.do_step(plant.t, T)


def _lockstep_plant(procs, name: str, duration: float, period: float) -> None:
    procs.start(name, msagv("ros2", "plant", "--managed", "--run-mode", "lockstep",
                            "--period", f"{period:g}", "--case", "line", "--speed", "10",
                            "--from-rest", "--initial", "vx=2.0,delta_11=0.05",
                            "--duration", f"{duration:g}", "--timeout", "600",
                            "--wait", "60", "--json"))


def test_a_deactivate_in_the_runs_end_lets_the_plant_end(procs, ros_env):
    """The run's end (``--duration``): the plant publishes its end state, lingers a moment
    for the last messages and ends. A deactivate that comes in that linger (the manager
    saw the end state and pauses the simulator) is served (success) and the plant still
    ends: exit 0, the run completed, its summary printed, the deactivate in its
    transitions - a finished simulation is not kept standing by a pause. The deactivate is
    sent as soon as the end state is in; where it missed the linger (the process had ended
    before it came) the run is tried again, up to three times."""
    _ros()
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState
    from std_msgs.msg import Float64MultiArray

    steps = 10
    tries = []
    for i in range(3):
        name = f"plant{i}"
        _lockstep_plant(procs, name, steps * T, T)
        peer = Peer("lifecycle_manager")
        n = peer.node
        try:
            _, transition, _ = node_calls(peer, "/msagv_plant")
            change = n.create_client(ChangeState, "/msagv_plant/change_state")
            steer = n.create_publisher(Float64MultiArray, "steering_controller/commands", 10)
            wheel = n.create_publisher(Float64MultiArray, "wheel_controller/commands", 10)
            sent = []

            def answer(k):
                if k < steps:
                    steer.publish(Float64MultiArray(data=DELTA0))
                    wheel.publish(Float64MultiArray(data=[2.2 / R_W] * 4))
                elif not sent:  # the end state: pause the simulator at once
                    sent.append(change.call_async(ChangeState.Request(
                        transition=Transition(id=Transition.TRANSITION_DEACTIVATE))))

            odoms, _ = answer_each_state(n, T, answer)
            assert transition(Transition.TRANSITION_CONFIGURE)
            assert transition(Transition.TRANSITION_ACTIVATE)
            assert peer.spin(120, until=lambda: steps in odoms), procs.err(name)[-2000:]
            peer.spin(1.0)  # the deactivate's answer, if it came in the linger
            assert procs.wait(name, 30) == 0, procs.err(name)[-2000:]
        finally:
            peer.close()
        s = procs.json(name)
        done = [t["transition"] for t in s["transitions"]]
        tries.append(done)
        if "deactivate" in done:
            break
    else:
        pytest.fail(f"the deactivate never came in the linger: {tries}")
    assert sent[0].done() and sent[0].result().success
    assert done == ["configure", "activate", "deactivate", "shutdown"], done
    assert s["completed"] and s["error"] is None and s["steps"] == steps
    assert s["lifecycle"] == "finalized"
    assert sorted(odoms) == list(range(steps + 1))


def test_a_lockstep_cleanup_with_the_answer_owed_starts_the_run_again(procs, ros_env):
    """Lockstep: the plant has sent state K and owes its step to the controller's answer.
    The manager deactivates it and cleans it up before the answer is in: the answer, sent
    while the command topics are down, is lost with them (a command names no state). Once
    configured and activated again the plant does not wait for it (it never comes) nor
    take a later command for it: it starts the run again at state 0, as ``~/reset`` does
    (the vehicle at its initial state), and says so. The reference: the second run's states
    are the plant's equations stepped from the start in this process, and the summary
    counts one reset."""
    _ros()
    from lifecycle_msgs.msg import Transition
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    K = 5
    _lockstep_plant(procs, "plant", 20, T)  # (the line case is 20 s long)
    peer = Peer("lifecycle_manager")
    n = peer.node
    state, transition, _ = node_calls(peer, "/msagv_plant")
    steer = n.create_publisher(Float64MultiArray, "steering_controller/commands", 10)
    wheel = n.create_publisher(Float64MultiArray, "wheel_controller/commands", 10)
    runs = [({}, {})]  # per run: (odometry, joint states) by k
    answered = set()

    def send():
        steer.publish(Float64MultiArray(data=DELTA0))
        wheel.publish(Float64MultiArray(data=[2.2 / R_W] * 4))

    def took(i):
        def on(m):
            k = round((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9) / T)
            if k == 0 and max((*runs[-1][0], *runs[-1][1]), default=0) > 0:
                runs.append(({}, {}))  # state 0 after later states: a new run
            runs[-1][i][k] = m
            r = len(runs) - 1
            if (r, k) not in answered and k in runs[-1][0] and k in runs[-1][1] and \
                    not (r == 0 and k >= K):  # the first run's state K: held
                answered.add((r, k))
                send()
        return on

    n.create_subscription(Odometry, "odom", took(0), 10)
    n.create_subscription(JointState, "joint_states", took(1), 10)
    try:
        assert transition(Transition.TRANSITION_CONFIGURE)
        assert transition(Transition.TRANSITION_ACTIVATE)
        assert peer.spin(120, until=lambda: K in runs[0][0] and K in runs[0][1]), \
            procs.err("plant")[-2000:]
        assert transition(Transition.TRANSITION_DEACTIVATE)
        assert transition(Transition.TRANSITION_CLEANUP) and state() == "unconfigured"
        assert peer.spin(60, until=lambda: n.count_subscribers(
            "/wheel_controller/commands") == 0)
        send()  # the answer to state K: nobody takes it
        peer.spin(1.0)
        assert transition(Transition.TRANSITION_CONFIGURE)
        assert transition(Transition.TRANSITION_ACTIVATE)
        assert peer.spin(60, until=lambda: len(runs) == 2 and 3 in runs[1][0]), \
            (sorted(runs[0][0]), procs.err("plant")[-2000:])
        assert transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
        assert procs.wait("plant", 60) == 0, procs.err("plant")[-2000:]
    finally:
        peer.close()
    assert sorted(runs[0][0]) == list(range(K + 1))
    s = procs.json("plant")
    assert s["resets"] == 1 and s["error"] is None, json.dumps(s)
    assert "cleanup" in procs.err("plant") and "state 0" in procs.err("plant")
    second = runs[1][0]
    assert_poses_from_start(second, max(second))
