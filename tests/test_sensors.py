"""Measurement noise (plant.sensors): what a simulated controller measures of the plant's state,
as a real vehicle's odometry would give it."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from msagv.experiments.scenario import Scenario, ScenarioError
from msagv.plant.sensors import MeasurementNoise

STATE = {"t": 1.0, "x": 3.0, "y": -2.0, "phi": 0.3, "vx": 5.0, "vy": 0.1, "r": 0.05,
         "delta": [0.0] * 4, "omega_w": [10.0] * 4, "W_s": 7.0}


def test_the_noise_has_the_given_deviations_and_leaves_the_state_alone():
    noise = MeasurementNoise(v=0.01, r=0.002, pos=0.02, phi=0.001, seed=3)
    before = json.dumps(STATE)
    draws = [noise(STATE) for _ in range(20000)]
    assert json.dumps(STATE) == before  # a copy is perturbed, not the plant's message
    for m in draws:  # the velocity in the body frame of the measured heading
        c, sn = math.cos(m["phi"]), math.sin(m["phi"])
        m["u"], m["w"] = c * m["vx"] + sn * m["vy"], -sn * m["vx"] + c * m["vy"]
    c, sn = math.cos(STATE["phi"]), math.sin(STATE["phi"])
    truth = dict(STATE, u=c * STATE["vx"] + sn * STATE["vy"], w=-sn * STATE["vx"] + c * STATE["vy"])
    for key, sd in (("u", 0.01), ("w", 0.01), ("r", 0.002), ("x", 0.02), ("y", 0.02),
                    ("phi", 0.001)):
        d = np.array([m[key] for m in draws]) - truth[key]
        # 20000 draws: the sample deviation within 3 %, the mean within 4 standard errors
        assert np.std(d) == pytest.approx(sd, rel=0.03), key
        assert abs(np.mean(d)) < 4 * sd / math.sqrt(len(d)), key
    assert all(m["omega_w"] == STATE["omega_w"] and m["W_s"] == 7.0 and m["t"] == 1.0
               for m in draws[:10])
    # independent channels: the body velocity's two components uncorrelated
    du = np.array([m["u"] for m in draws]) - truth["u"]
    dw = np.array([m["w"] for m in draws]) - truth["w"]
    assert abs(np.corrcoef(du, dw)[0, 1]) < 0.03


def test_the_velocity_noise_is_the_body_frames():
    """Heading noise alone leaves the body-frame velocity a reader recovers with the
    measured heading exactly the true one (odometry measures the twist in the body); the
    velocity's noise is the same along and across the body whatever the heading."""
    import math as m

    noise = MeasurementNoise(phi=0.1, seed=2)
    st = noise(STATE)
    assert st["phi"] != STATE["phi"]

    def body(d):
        c, s = m.cos(d["phi"]), m.sin(d["phi"])
        return c * d["vx"] + s * d["vy"], -s * d["vx"] + c * d["vy"]

    assert body(st) == pytest.approx(body(STATE), abs=1e-12)
    noise = MeasurementNoise(v=0.01, seed=3)
    ub, vb = body(STATE)
    d = np.array([np.subtract(body(noise(STATE)), (ub, vb)) for _ in range(20000)])
    assert np.std(d, axis=0) == pytest.approx([0.01, 0.01], rel=0.03)


def test_the_same_seed_gives_the_same_noise_and_none_gives_none():
    a = MeasurementNoise(v=0.01, r=0.002, seed=1)
    b = MeasurementNoise(v=0.01, r=0.002, seed=1)
    c = MeasurementNoise(v=0.01, r=0.002, seed=2)
    sa, sb, sc = ([n(STATE)["vx"] for _ in range(5)] for n in (a, b, c))
    assert sa == sb and sa != sc
    assert MeasurementNoise.from_mapping({}) is None
    assert MeasurementNoise.from_mapping({"v": 0.0, "seed": 4}) is None
    assert MeasurementNoise.parse("0,0") is None
    assert MeasurementNoise.parse("0.01,0.002,0.03", seed=5).as_dict() == {
        "v": 0.01, "r": 0.002, "pos": 0.03, "phi": 0.0, "seed": 5}


@pytest.mark.parametrize("bad,words", [
    ({"v": -0.01}, "measurement_noise.v"), ({"r": float("nan")}, "measurement_noise.r"),
    ({"pos": True}, "measurement_noise.pos"), ({"phi": "small"}, "measurement_noise.phi"),
    ({"seed": -1}, "measurement_noise.seed"), ({"seed": 1.5}, "measurement_noise.seed"),
    ({"vel": 0.01}, "unknown vel"), ([0.01], "expected a table")])
def test_bad_noise_is_refused_by_name(bad, words):
    with pytest.raises(ValueError, match=words):
        MeasurementNoise.from_mapping(bad)
    with pytest.raises(ScenarioError, match=words):
        Scenario(case="curve", measurement_noise=bad)


@pytest.mark.parametrize("text", ["0.01", "0.01,0.002,0,0,9", "a,b", "-1,0"])
def test_bad_command_line_noise_is_refused(text):
    with pytest.raises(ValueError):
        MeasurementNoise.parse(text)


def test_a_scenario_file_takes_the_table_and_refuses_a_bad_one(tmp_path):
    good = tmp_path / "noisy.toml"
    good.write_text('case = "curve"\n[measurement_noise]\nv = 0.01\nr = 0.002\nseed = 7\n')
    sc = Scenario.from_file(good)
    m = sc.measurement()
    assert m is not None and (m.v, m.r, m.pos, m.seed) == (0.01, 0.002, 0.0, 7)
    assert Scenario.from_dict(sc.to_dict()).measurement_noise == sc.measurement_noise
    # a scenario without noise writes no such key (files of earlier runs stay as they were)
    assert "measurement_noise" not in Scenario(case="curve").to_dict()
    bad = tmp_path / "bad.toml"
    bad.write_text('case = "curve"\nmeasurement_noise = 0.01\n')
    with pytest.raises(ScenarioError, match="measurement_noise: expected a table"):
        Scenario.from_file(bad)


def test_the_controller_gets_the_measurement_and_the_log_keeps_the_truth():
    from msagv.controller.loop import closed_loop

    b = Scenario(case="curve", speed=15.0, settings={"method": "ntwo"},
                 measurement_noise={"pos": 0.01, "seed": 2}).build()
    assert isinstance(b.measure, MeasurementNoise)
    got = []
    step = b.controller.step

    def spy(state, reference):
        got.append(dict(state))
        return step(state, reference)

    b.controller.step = spy
    measure = b.measure
    sent = []

    def recording_measure(st):
        m = measure(st)
        sent.append((dict(st), m))
        return m

    log = closed_loop(b.plant, b.controller, b.reference, 0.2, period=0.01, progress=False,
                      outputs=False, measure=recording_measure)
    got = got[-len(sent):]  # (before them: the warm-up's solves on the initial state)
    assert len(sent) == 20
    for k, (true, m) in enumerate(sent):
        assert got[k]["x"] == m["x"] != true["x"]  # the controller saw the measurement
        assert log.pose[k][:2] == (true["x"], true["y"])  # the log keeps the plant's state


def test_run_takes_measurement_noise_and_refuses_a_bad_one():
    """The noise reaches the controller (its adaptation measures it, 1 cm/s within 25 %, and
    follows it, the switch in the JSON; with adapt_noise=fixed it warns instead, the warning
    in the JSON and once on stderr) and is named in the scenario block; bad values are
    refused in one line."""
    cmd = [sys.executable, "-m", "msagv", "run", "--case", "curve", "--speed", "25",
           "--duration", "2.5", "--method", "ntwo", "--adapt", "--no-floor",
           "--measurement-noise", "0.01,0.002", "--json"]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout)
    assert out["scenario"]["measurement_noise"] == {"v": 0.01, "r": 0.002, "pos": 0.0,
                                                   "phi": 0.0, "seed": 0}
    assert out["adapted_tires"]["velocity_noise"] == pytest.approx(0.01, rel=0.25), out
    sw = out["adapted_tires"]["noise_switch"]
    assert sw["window"] == 10 and out["adapted_tires"]["window"] == 10, out["adapted_tires"]
    assert not [w for w in out["warnings"] if "measured velocities carry" in w], out["warnings"]
    p = subprocess.run(cmd + ["--set", "adapt_noise=fixed"], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    out = json.loads(p.stdout)
    assert out["adapted_tires"]["noise_switch"] is None and out["adapted_tires"]["window"] == 1
    warned = [w for w in out["warnings"] if "measured velocities carry" in w]
    assert len(warned) == 1 and p.stderr.count("measured velocities carry") == 1, p.stderr
    for bad in ("-0.01,0", "fast,0", "0.01"):
        p = subprocess.run(cmd[:-3] + [f"--measurement-noise={bad}", "--json"],
                           capture_output=True, text=True, timeout=300)
        assert p.returncode == 2 and "--measurement-noise" in p.stderr, p.stderr
        assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_a_plant_process_publishes_the_measured_state_and_sends_it_again_unchanged():
    """msagv plant and msagv ros2 plant (their run, bridge.run_core.PlantRun): the states
    published carry the measurement noise, a state sent again is the same message, the
    next state has fresh noise, and the run's final state is the plant's own."""
    from msagv.bridge.run_core import PlantRun, RunConfig

    sc = Scenario(case="curve", speed=15.0, measurement_noise={"v": 0.01, "pos": 0.02, "seed": 1})
    plant, _, _, _ = sc.make_plant()

    class Port:  # the run's port, as far as publishing goes
        def __init__(self):
            self.sent = []

        def send_state(self, k, st, end):
            self.sent.append((k, dict(st)))

    port = Port()
    run = PlantRun(plant, RunConfig(steps=3), port, measure=sc.measurement())
    true = plant.state_message()
    run.publish_state(0)
    run.publish_state(0)  # (a re-send: lockstep's, or state 0 while no controller answers)
    (_, a), (_, b) = port.sent
    assert a == b
    assert a["vx"] != true["vx"] and a["x"] != true["x"] and a["y"] != true["y"]
    assert a["W_s"] == true["W_s"] and list(a["delta"]) == list(true["delta"])
    run.publish_state(1, end=True)
    c = port.sent[-1][1]
    assert c["vx"] != a["vx"] and c["vx"] != true["vx"]
    assert run.final_state["vx"] == true["vx"] and run.final_state["x"] == true["x"]


@pytest.mark.parametrize("cmd", [["plant"], ["ros2", "plant"]])
def test_the_plant_processes_take_measurement_noise_and_refuse_a_bad_one(cmd):
    p = subprocess.run([sys.executable, "-m", "msagv", *cmd, "--help"], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0 and "--measurement-noise" in p.stdout, p.stderr[-2000:]
    p = subprocess.run([sys.executable, "-m", "msagv", *cmd, "--measurement-noise=0.01,-2",
                        "--duration", "1"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "--measurement-noise" in p.stderr, p.stderr[-2000:]
    assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_the_ros_odometry_carries_the_noise_as_its_covariance():
    """msagv ros2 plant with measurement noise: its nav_msgs/Odometry's pose and twist
    covariances carry the noise's variances on their diagonals (x, y, yaw; vx, vy, wz), as
    a consumer such as robot_localization reads them, through the CDR encoding; zero
    without noise."""
    from msagv.bridge import ros_msgs as R
    from msagv.plant import default_vehicle

    st = dict(STATE, delta=[0.0] * 4, omega_w=[10.0] * 4)
    noise = MeasurementNoise(v=0.01, r=0.002, pos=0.02, phi=0.001)
    for n, pose_diag, twist_diag in ((noise, (4e-4, 4e-4, 1e-6), (1e-4, 1e-4, 4e-6)),
                                     (None, (0, 0, 0), (0, 0, 0))):
        msg = R.RunMessages(default_vehicle(), noise=n).odom(st)
        back = R.decode(R.encode(msg, R.TYPES[R.ODOM]), R.TYPES[R.ODOM])
        pc = np.asarray(back.pose.covariance).reshape(6, 6)
        tc = np.asarray(back.twist.covariance).reshape(6, 6)
        assert np.diag(pc)[[0, 1, 5]] == pytest.approx(pose_diag, abs=1e-15)
        assert np.diag(tc)[[0, 1, 5]] == pytest.approx(twist_diag, abs=1e-15)
        assert np.count_nonzero(pc - np.diag(np.diag(pc))) == 0 and pc[2, 2] == pc[3, 3] == 0
        assert np.count_nonzero(tc - np.diag(np.diag(tc))) == 0
