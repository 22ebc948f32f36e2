"""``msagv ros2 plant`` as a ROS 2 team runs a simulator node (issue 32 item 5): its
options as ROS parameters (a params file, ``-p``, changes at run time), ``/diagnostics``
and ``~/reset``. Real rclpy on loopback (a random domain id), the plant a process of its
own, stopped by its id.

The peer answers every state with the same commands (the wheels at 2.2 m/s at the rim, the
steering held where it starts), so every state the plant publishes is the plant's
equations stepped that many times from the start: the independent reference is the
stepping plant run in this process. A reset that left anything of the run before it (the
pose, a speed, a steering angle, a wheel speed, the wear) departs from it.
"""

from __future__ import annotations

import math

import pytest
import yaml

import test_ros2_nodes as ros_nodes
from helpers import ROOT, msagv
from msagv.bridge.process import EXIT_RUNTIME
from test_ros2_nodes import Peer, _call, _ros, _stamp, _yaw, node_calls
from test_ros2_plant_lifecycle import assert_poses_from_start

T = 0.2  # the period (as test_ros2_plant_lifecycle: a loaded machine's stall is no issue)
N = 12  # the periods run in each part
ros_env = ros_nodes.ros_env  # the fixture: loopback discovery, a domain of this test alone
R_W = 0.5  # the paper vehicle's wheel radius (plant/data/paper-2axle.toml)
DELTA0 = [0.05, 0.0, 0.0, 0.0]  # the initial steering angles (--initial delta_11=0.05)
EXAMPLE = ROOT / "scenarios" / "ros2" / "plant.params.yaml"


# ---- parameters at start ------------------------------------------------------------------
def test_the_params_file_example_is_read_and_an_integer_is_a_double(procs, ros_env,
                                                                     tmp_path):
    """scenarios/ros2/plant.params.yaml read as a params file: every value of it is in
    force (the summary's parameters are the file's, as PyYAML reads it), ``-p wait:=1`` (an
    integer for a double) overrides the file's 60 s: with no controller the plant gives up
    after 1 s (exit 3, EXIT_RUNTIME) with its summary. The recording's header (what
    ``msagv report``, the bag and Foxglove time the run by) has the parameters' period and
    mode, not the options'."""
    from msagv.bridge.recording import read_recording

    _ros()
    rec = tmp_path / "plant.rec"
    procs.start("plant", msagv("ros2", "plant", "--case", "line", "--speed", "10", "--json",
                               "--record", rec,
                               "--ros-args", "--params-file", EXAMPLE, "-p", "wait:=1"))
    assert procs.wait("plant", 120) == EXIT_RUNTIME, procs.err("plant")[-2000:]
    s = procs.json("plant")
    assert s["error"].startswith("no controller within 1 s"), s["error"]
    want = dict(yaml.safe_load(EXAMPLE.read_text())["/**"]["ros__parameters"], wait=1.0)
    assert s["parameters"] == want
    assert isinstance(s["parameters"]["duration"], float)  # 20 in the file: an integer
    assert s["run_mode"] == want["run_mode"] and s["period"] == want["period"]
    assert s["periods"]["max_missed"] == int(want["stale_ms"] / 1000 / want["period"])
    h, _, _ = read_recording(rec)
    assert (h["period"], h["run_mode"]) == (want["period"], want["run_mode"])
    assert h["steps"] == round(want["duration"] / want["period"])


@pytest.mark.parametrize("args,says", [
    (["-p", "stale_mss:=50.0"], "ROS parameter stale_mss: unknown"),  # misspelt
    (["-p", "resume_periods:=2.5"], "ROS parameter resume_periods: expected an integer"),
    (["-p", "run_mode:=fast"], "run mode: expected lockstep or realtime, got 'fast'"),
    ("misspelt file", "ROS parameter safe_decell: unknown"),
])
def test_a_bad_parameter_is_refused_at_start_in_one_line(procs, ros_env, tmp_path, args,
                                                         says):
    """Exit 2 and one line naming it, no traceback, before anything runs: a recording
    asked for is not opened (a file already there left as it was, no bag beside it)."""
    _ros()
    if args == "misspelt file":
        bad = tmp_path / "bad.yaml"
        bad.write_text(EXAMPLE.read_text().replace("safe_decel:", "safe_decell:"))
        args = ["--params-file", bad]
    (tmp_path / "rec").mkdir()
    old = tmp_path / "rec" / "old.rec"
    old.write_bytes(b"a recording of another run")
    procs.start("plant", msagv("ros2", "plant", "--case", "line", "--json", "--record", old,
                               "--ros-args", *args))
    assert procs.wait("plant", 120) == 2
    assert old.read_bytes() == b"a recording of another run"
    assert [p.name for p in old.parent.iterdir()] == ["old.rec"]
    err = procs.err("plant")
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("msagv ros2 plant: error: ") and says in last, err


# ---- at run time: parameters, diagnostics, reset -------------------------------------------
def test_parameters_diagnostics_and_reset_of_the_managed_plant(procs, ros_env):
    """A managed lockstep plant driven by a peer with fixed commands.

    * Parameters at run time: ``stale_ms`` as an integer is taken (the diagnostics show
      the new bound in periods, as the run's command watch holds it); ``run_mode`` is
      refused with its reason, and so is ``use_sim_time``; a change of ``safe_decel``
      together with ``period`` is refused whole: neither changes.
    * ``~/reset`` while active is refused (lockstep: the state's answer is outstanding) and
      changes nothing: the states go on, each the equations stepped once more.
    * Deactivated (the answer in), ``~/reset`` is honoured; activated, the plant publishes
      state 0 again stamped 0, the initial state, and the next N states are the first
      run's, to the bit, and the equations' from the start (the wear zero again: the final
      state's wear work is the equations' over the second run alone).
    * ``/diagnostics``: one status of the plant, OK and "running" while it runs; deactivated,
      WARN "inactive", its values equal the summary printed at the end (state k, commands
      accepted and rejected by reason, resets, missed periods) and the node that drove is
      this one."""
    _ros()
    try:
        from diagnostic_msgs.msg import DiagnosticArray
        from std_srvs.srv import Trigger
    except ImportError as e:
        pytest.skip(f"diagnostic_msgs or std_srvs not installed: {e}")
    from lifecycle_msgs.msg import Transition
    from nav_msgs.msg import Odometry
    from rcl_interfaces.srv import GetParameters, SetParametersAtomically
    from rclpy.parameter import Parameter, parameter_value_to_python
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from msagv.experiments.scenario import Scenario

    procs.start("plant", msagv("ros2", "plant", "--managed", "--run-mode", "lockstep",
                               "--period", f"{T:g}", "--case", "line", "--speed", "10",
                               "--from-rest", "--initial", "vx=2.0,delta_11=0.05",
                               "--duration", "600", "--json"))
    peer = Peer("lifecycle_manager")
    n = peer.node
    name = "/msagv_plant"
    _, transition, set_params = node_calls(peer, name)
    getp = n.create_client(GetParameters, f"{name}/get_parameters")
    seta = n.create_client(SetParametersAtomically, f"{name}/set_parameters_atomically")
    reset = n.create_client(Trigger, f"{name}/reset")
    steer = n.create_publisher(Float64MultiArray, "steering_controller/commands", 10)
    wheel = n.create_publisher(Float64MultiArray, "wheel_controller/commands", 10)
    runs = [({}, {})]  # per run: (odometry, joint states) by k
    answered = set()

    def took(i):
        def on(m):
            k = round(_stamp(m.header) / T)
            run = runs[-1]
            run[i][k] = m
            if (len(runs), k) not in answered and k in run[0] and k in run[1]:
                answered.add((len(runs), k))
                steer.publish(Float64MultiArray(data=DELTA0))  # held: a rate of 0
                wheel.publish(Float64MultiArray(data=[2.2 / R_W] * 4))
        return on

    n.create_subscription(Odometry, "odom", took(0), 10)
    n.create_subscription(JointState, "joint_states", took(1), 10)
    diags = []
    n.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)

    def get_params(*names) -> list:
        r = _call(peer, getp, GetParameters.Request(names=list(names)), again=True)
        return [parameter_value_to_python(v) for v in r.values]

    def newest() -> int:
        return max(runs[-1][0], default=-1)

    def runs_to(k: int) -> None:
        assert peer.spin(120, until=lambda: newest() >= k), procs.err("plant")[-2000:]

    def paused() -> int:
        peer.spin(1.0)  # the states and answers in flight are in
        k = newest()
        peer.spin(1.0)
        assert newest() == k, (k, newest())
        return k

    def diag(until) -> dict:
        """The plant's newest status satisfying ``until(values)``."""
        found = {}

        def ok():
            for m in diags:
                assert len(m.status) == 1
                s = m.status[0]
                if s.name == "msagv_plant: plant":
                    v = {kv.key: kv.value for kv in s.values}
                    if until(v):
                        found.clear()
                        found.update(v, _level=s.level, _message=s.message)
            diags.clear()
            return bool(found)
        assert peer.spin(60, until=ok), "no matching diagnostics"
        return found

    try:
        assert transition(Transition.TRANSITION_CONFIGURE)
        assert transition(Transition.TRANSITION_ACTIVATE)
        runs_to(3)
        # parameters at run time: an integer for a double, taken from the next period
        assert set_params(Parameter("stale_ms", value=400)) == [(True, "")]
        d = diag(lambda v: v["stale_ms"] == "400")
        assert d["max_missed"] == "2"  # floor(0.4 s / 0.2 s), the run's watch
        assert d["_level"] == b"\x00" and d["_message"] == "running", d
        assert d["lifecycle"] == "active" and d["run_mode"] == "lockstep"
        assert d["clock"] == "wall" and d["lateness_ms_p99"] == "none"  # lockstep: no due
        # refused with the reason, nothing changed (all of a change or none of it)
        (ok, why), = set_params(Parameter("run_mode", value="realtime"))
        assert not ok and why.startswith("run_mode: the run's mode is its contract"), why
        (ok, why), = set_params(Parameter("use_sim_time", value=True))
        assert not ok and why.startswith("use_sim_time: chooses the run's clock"), why
        r = _call(peer, seta, SetParametersAtomically.Request(parameters=[
            Parameter("safe_decel", value=3.0).to_parameter_msg(),
            Parameter("period", value=0.1).to_parameter_msg()])).result
        assert not r.successful and r.reason.startswith("period: state k is stamped k T"), r
        assert get_params("run_mode", "period", "safe_decel", "stale_ms") == [
            "lockstep", T, 2.0, 400.0]
        # reset while active in lockstep: refused, the run goes on
        k = newest()
        res = _call(peer, reset, Trigger.Request())
        assert not res.success and "answer is outstanding" in res.message, res.message
        runs_to(k + 3)
        runs_to(N)
        assert transition(Transition.TRANSITION_DEACTIVATE)
        first = paused()
        # a malformed command while inactive: rejected, counted by reason
        wheel.publish(Float64MultiArray(data=[1.0] * 3))
        peer.spin(0.5)
        res = _call(peer, reset, Trigger.Request())
        assert res.success and f"was at state {first}" in res.message, res.message
        runs.append(({}, {}))
        d = diag(lambda v: v["resets"] == "1")
        assert d["k"] == "-1" and d["lifecycle"] == "inactive" and d["_level"] == b"\x01"
        assert transition(Transition.TRANSITION_ACTIVATE)
        runs_to(N)
        assert transition(Transition.TRANSITION_DEACTIVATE)
        second = paused()
        final = diag(lambda v: v["lifecycle"] == "inactive" and v["k"] == str(second))
        assert transition(Transition.TRANSITION_INACTIVE_SHUTDOWN)
        assert procs.wait("plant", 60) == 0, procs.err("plant")[-2000:]
    finally:
        peer.close()
    s = procs.json("plant")
    assert s["resets"] == 1 and s["steps"] == second and s["error"] is None
    assert s["parameters"]["stale_ms"] == 400.0 and s["parameter_changes"] == 1
    assert s["parameters_refused"] == 3 and s["parameters"]["safe_decel"] == 2.0
    # the diagnostics said what the summary says
    assert final["_level"] == b"\x01" and final["_message"] == "inactive"
    assert final["clock"] == "wall" and s["clock"] == "wall"  # use_sim_time refused
    assert final["commands_accepted"] == str(s["commands"]["accepted"])
    assert final["commands_rejected"] == str(s["rejected"]["total"]) == "1"
    assert {k.removeprefix("rejected_"): int(v) for k, v in final.items()
            if k.startswith("rejected_")} == s["rejected"]["by_reason"]
    # the node that drove (the shutdown's cleanup unbinds it: the summary's is None)
    assert final["source_node"] == "/lifecycle_manager" and s["source_node"] is None
    assert final["missed_periods"] == str(s["missed_periods"]) and final["resets"] == "1"
    assert final["t"] == f"{second * T:.6g}"
    # every state of both runs the equations' from the start (the wear too, by the end)
    first_run, second_run = runs
    assert sorted(first_run[0]) == list(range(first + 1))
    assert sorted(second_run[0]) == list(range(second + 1))
    plant, vehicle, _, _ = Scenario(case="line", speed=10, from_rest=True,
                                    initial={"vx": 2.0, "delta_11": 0.05}).make_plant()
    assert vehicle.wheel_radius == R_W
    for k in range(max(first, second) + 1):
        st = plant.state_message()
        for run in runs:
            if k not in run[0]:
                continue
            o, j = run[0][k], run[1][k]
            assert o.pose.pose.position.x == pytest.approx(st["x"], abs=1e-9), k
            assert o.pose.pose.position.y == pytest.approx(st["y"], abs=1e-9), k
            assert _yaw(o.pose.pose.orientation) == pytest.approx(st["phi"], abs=1e-9), k
            tw = o.twist.twist.linear  # (in base_link: the speed is the plant's)
            assert math.hypot(tw.x, tw.y) == pytest.approx(math.hypot(st["vx"], st["vy"]),
                                                           abs=1e-9), k
            pos = dict(zip(j.name, j.position))
            vel = dict(zip(j.name, j.velocity))
            w = ("11", "12", "21", "22")
            assert [pos[f"steer_{x}"] for x in w] == pytest.approx(st["delta"], abs=1e-12)
            assert [vel[f"wheel_{x}"] for x in w] == pytest.approx(st["omega_w"], abs=1e-9)
        if k in first_run[0] and k in second_run[0]:  # the second run is the first again
            a, b = first_run[0][k].pose.pose.position, second_run[0][k].pose.pose.position
            assert (a.x, a.y) == (b.x, b.y), k
        if k == second:
            for f in ("x", "y", "W_s", "W_alpha", "W_t"):
                assert s["final_state"][f] == pytest.approx(st[f], rel=1e-9, abs=1e-9), f
        plant.set_inputs([2.2 / R_W] * 4, [0.0] * 4)
        plant.do_step(plant.t, T)


def test_a_realtime_plant_resets_while_running_and_takes_a_new_staleness_bound(procs,
                                                                            ros_env):
    """A realtime plant (not managed, ``--stale-ms`` of ten minutes) is reset while it
    runs: the next state it publishes is state 0 stamped 0, the initial state, and the
    states after it the equations' from the start again (the newest commands, the same
    every period; the ten-minute bound keeps a loaded machine's stall from making the
    safe behaviour part of them, so this test does not say whether a reset counts as
    silence: test_run_core's reset test does). Then the peer stops answering and sets ``stale_ms`` to 400 (an integer)
    at run time: the plant goes safe (STALE on /diagnostics), which the old bound would
    have kept it from for ten minutes. A SIGTERM ends it with its summary."""
    _ros()
    try:
        from diagnostic_msgs.msg import DiagnosticArray
        from std_srvs.srv import Trigger
    except ImportError as e:
        pytest.skip(f"diagnostic_msgs or std_srvs not installed: {e}")
    import signal

    from rclpy.parameter import Parameter

    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    procs.start("plant", msagv("ros2", "plant", "--run-mode", "realtime", "--period", f"{T:g}",
                               "--stale-ms", "600000", "--case", "line", "--speed", "10",
                               "--from-rest", "--initial", "vx=2.0,delta_11=0.05",
                               "--duration", "600", "--json"))
    peer = Peer("controller")
    n = peer.node
    reset = n.create_client(Trigger, "/msagv_plant/reset")
    steer = n.create_publisher(Float64MultiArray, "steering_controller/commands", 10)
    wheel = n.create_publisher(Float64MultiArray, "wheel_controller/commands", 10)
    runs = [({}, {})]  # per run: (odometry, joint states) by k; None: reset, no state 0 yet
    answered = set()
    quiet = []  # the peer stops answering once this holds anything
    _, _, set_params = node_calls(peer, "/msagv_plant")
    diags = []
    n.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)

    def took(i):
        def on(m):
            k = round(_stamp(m.header) / T)
            if runs[-1] is None:
                if k != 0:
                    return  # a state of the run before the reset, still on its way
                runs[-1] = ({}, {})
            run = runs[-1]
            run[i][k] = m
            if (len(runs), k) not in answered and k in run[0] and k in run[1] and not quiet:
                answered.add((len(runs), k))
                steer.publish(Float64MultiArray(data=DELTA0))
                wheel.publish(Float64MultiArray(data=[2.2 / R_W] * 4))
        return on

    n.create_subscription(Odometry, "odom", took(0), 10)
    n.create_subscription(JointState, "joint_states", took(1), 10)

    def runs_to(k: int) -> None:
        assert peer.spin(120, until=lambda: runs[-1] is not None and max(
            runs[-1][0], default=-1) >= k), procs.err("plant")[-2000:]

    try:
        runs_to(N)
        # from here on only a state 0 starts the new run: the plant may publish it before
        # the service's answer is taken (the peer spins for both), and a state 0 filed
        # under the old run would leave the new one waiting for a state 0 already gone
        runs.append(None)
        res = _call(peer, reset, Trigger.Request())
        assert res.success, res.message
        runs_to(N)
        quiet.append(True)
        assert set_params(Parameter("stale_ms", value=400)) == [(True, "")]

        def stale() -> bool:
            hit = any(m.status[0].level == b"\x03" and
                      {kv.key: kv.value for kv in m.status[0].values}["safe"] == "true"
                      for m in diags if m.status[0].name == "msagv_plant: plant")
            diags.clear()
            return hit
        assert peer.spin(60, until=stale), procs.err("plant")[-2000:]
        procs.p["plant"].send_signal(signal.SIGTERM)
        assert procs.wait("plant", 60) == 0, procs.err("plant")[-2000:]
    finally:
        peer.close()
    s = procs.json("plant")
    assert s["resets"] == 1 and s["error"] is None and s["parameters"]["stale_ms"] == 400.0
    assert s["safe"]["events"] >= 1 and s["periods"]["max_missed"] == 2, s  # 0.4 s / T
    second = runs[-1][0]
    assert s["steps"] >= max(second)
    assert sorted(second)[:N + 1] == list(range(N + 1))
    assert_poses_from_start(second, N)
