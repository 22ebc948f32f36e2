"""msagv calibrate (plant.identify, experiments.calibrate, cli.calibrate): the estimator on
runs of the plant itself with known tires, lags and measurement noise; a straight line that
identifies no tire; bad recordings refused in one line; the command end to end on a
recording written by the project's recorder (and its ROS 2 bag)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from msagv.plant import Plant, default_vehicle
from msagv.plant.identify import IdentifyError, RunData, calibrate, values_of, vehicle_with
from msagv.plant.vehicle import load_vehicle

ROOT = Path(__file__).resolve().parents[1]
T = 0.01


def _truth():
    """The built-in vehicle with tires 30 % off (lateral slope and peak x0.7, longitudinal
    slope x1.3) and actuator lags the base vehicle does not have."""
    base = default_vehicle()
    v = values_of(base)
    return base, vehicle_with(base, {"lateral.K": 0.7 * v["lateral.K"],
                                     "lateral.mu": 0.7 * v["lateral.mu"],
                                     "longitudinal.K": 1.3 * v["longitudinal.K"],
                                     "wheel_lag": 0.04, "steer_lag": 0.03}, name="truth")


def drive(vehicle, seconds, noise=0.0, seed=0, lateral=True, speed_swing=True, v0=5.0):
    """A run of the stepping plant under open-loop commands: wheel speeds swinging about
    ``v0`` (or constant), the front wheels steered one way and the rear the other on a
    steering servo (or straight), sampled every period; measurement noise of ``noise``
    m/s on the velocities and wheel rims (a fifth of it on r, a tenth on the angles)."""
    rng = np.random.default_rng(seed)
    nw, r_w = vehicle.n_wheels, vehicle.wheel_radius
    p = Plant(vehicle, initial={"vx": v0,
                                **{f"omega_w_{w}": v0 / r_w for w in vehicle.wheel_names}})
    n = int(round(seconds / T))
    t = np.arange(n + 1) * T
    body, delta, om = np.zeros((n + 1, 6)), np.zeros((n + 1, nw)), np.zeros((n + 1, nw))
    cw, cs = np.zeros((n + 1, nw)), np.zeros((n + 1, nw))
    front = np.repeat(np.asarray(vehicle.axle_x) > 0, 2)
    for k in range(n + 1):
        st = p.state_message()
        body[k] = [st[f] for f in ("x", "y", "phi", "vx", "vy", "r")]
        delta[k], om[k] = st["delta"], st["omega_w"]
        if k == n:
            break
        tk = t[k]
        v = v0 + (2.0 * np.sin(2 * np.pi * tk / 10.0) + np.sin(2 * np.pi * tk / 2.5)
                  if speed_swing else 0.0)
        w = np.full(nw, v / r_w)
        target = (0.12 * np.sin(2 * np.pi * tk / 3.0) + 0.05 * np.sin(2 * np.pi * tk / 1.3)
                  if lateral else 0.0)
        s = np.clip((np.where(front, target, -target) - np.asarray(st["delta"])) * 5.0, -0.8, 0.8)
        cw[k], cs[k] = w, s
        p.set_inputs(w, s)
        p.do_step(p.t, T)
    if noise:
        body[:, 3:5] += rng.normal(0, noise, (n + 1, 2))
        body[:, 5] += rng.normal(0, noise / 5, n + 1)
        delta += rng.normal(0, noise / 10, delta.shape)
        om += rng.normal(0, noise / r_w, om.shape)
    return RunData(t, body, delta, om, cw, cs)


def test_recovers_tires_and_lags_within_their_standard_errors():
    """Noisy measurements of a plant whose tires are 30 % off the base file: every slope,
    peak and lag the run excites comes back within five standard errors (the estimator's
    own, widened for correlated residuals) plus 1 % (the windows start from smoothed
    measurements: a bias of their own), and the slopes within 5 %; the shapes C and E,
    which this run cannot separate, keep the base values and say so."""
    base, truth = _truth()
    cal = calibrate(drive(truth, 20.0, noise=0.01), base)
    tv = values_of(truth)
    for name in ("lateral.K", "longitudinal.K", "wheel_lag", "steer_lag", "lateral.mu",
                 "longitudinal.mu"):
        e = cal.estimates[name]
        assert e.identified, (name, e.why)
        assert e.se is not None and e.se > 0
        assert abs(e.value - tv[name]) <= 5 * e.se + 0.01 * abs(tv[name]), (name, e.value, e.se)
    for name in ("lateral.K", "longitudinal.K"):
        assert cal.estimates[name].value == pytest.approx(tv[name], rel=0.05)
    for name in ("lateral.C", "lateral.E"):
        e = cal.estimates[name]
        assert not e.identified and e.why and e.value == values_of(base)[name]
    assert all(cal.rms_after[k] < cal.rms_before[k] for k in ("v", "r", "omega_w"))
    # the tuned vehicle carries the fitted values (B = K / (C mu)) and validates
    la = cal.vehicle.tire_lateral
    assert la.B * la.C * la.mu == pytest.approx(cal.estimates["lateral.K"].value)
    assert cal.vehicle.plant.wheel_lag == pytest.approx(cal.estimates["wheel_lag"].value)


def test_standard_errors_grow_with_the_noise():
    """The same run with four times the measurement noise: the standard errors of the
    slopes grow (by about the noise ratio: a least-squares error scales with the noise)."""
    base, truth = _truth()
    lo = calibrate(drive(truth, 10.0, noise=0.005, seed=1), base)
    hi = calibrate(drive(truth, 10.0, noise=0.02, seed=1), base)
    for name in ("lateral.K", "longitudinal.K"):
        assert hi.estimates[name].se > 2.0 * lo.estimates[name].se, name


def test_fit_body_finds_the_yaw_inertia_and_says_the_mass_cannot_be_found():
    """--fit-body on a plant 20 % heavier in yaw: the yaw inertia comes back within five
    standard errors plus 1 %; the mass is not identified (every tire force scales with the
    load m g / 2n, so no acceleration depends on it) and keeps the base value."""
    base, truth = _truth()
    truth = vehicle_with(truth, {"yaw_inertia": 1.2 * base.yaw_inertia})
    cal = calibrate(drive(truth, 12.0, noise=0.005), base, fit_body=True)
    e = cal.estimates["yaw_inertia"]
    assert e.identified and abs(e.value - truth.yaw_inertia) <= 5 * e.se + 0.01 * truth.yaw_inertia
    m = cal.estimates["mass"]
    assert not m.identified and m.value == base.mass and "not excited" in m.why


def test_a_straight_line_identifies_no_lateral_tire():
    """Straight ahead at constant speed (the wheels at a steady speed, no steering): no
    lateral parameter is identified; the tuned vehicle keeps the base lateral tire and
    the reason names the missing excitation."""
    base, truth = _truth()
    cal = calibrate(drive(truth, 10.0, noise=0.01, lateral=False, speed_swing=False), base)
    for name in ("lateral.K", "lateral.mu", "lateral.C", "lateral.E"):
        e = cal.estimates[name]
        assert not e.identified and e.se is None
        assert "not excited" in e.why, e.why
    assert cal.vehicle.tire_lateral == base.tire_lateral
    assert not cal.estimates["longitudinal.K"].identified  # constant speed: no slip either


def test_bad_data_refused_with_one_line():
    base = default_vehicle()
    good = drive(base, 3.0)
    bad = drive(base, 3.0)
    bad.body[50, 4] = np.nan
    with pytest.raises(IdentifyError, match="NaN or inf"):
        calibrate(bad, base)
    short = RunData(good.t[:50], good.body[:50], good.delta[:50], good.omega_w[:50],
                    good.cmd_w[:50], good.cmd_s[:50])
    with pytest.raises(IdentifyError, match="too short"):
        calibrate(short, base)
    with pytest.raises(IdentifyError, match="wheels"):
        calibrate(good, load_vehicle(ROOT / "scenarios/vehicles/agv-3axle.toml"))
    still = RunData(good.t, np.zeros_like(good.body), good.delta, good.omega_w, good.cmd_w,
                    good.cmd_s)
    with pytest.raises(IdentifyError, match="never moves"):
        calibrate(still, base)


# ---- the command line -------------------------------------------------------------------------
def write_recording(path: Path, vehicle_dict: dict, data: RunData, ros2: bool = False,
                    flush_every: int = 0) -> None:
    """``data`` as the plant process records a lockstep run: each state sent (tx), then the
    command answering it received (rx), with increasing record times; with
    ``flush_every``, flushed every so many states (a running plant flushes every 0.5 s of
    wall time, which closes a chunk of the file)."""
    from msagv.bridge import messages as M
    from msagv.bridge.recording import Recorder

    rec = Recorder(path, {"role": "plant", "id": "agv0", "vehicle": vehicle_dict, "period": T,
                          "run_mode": "lockstep"}, ros2=ros2)
    ts = 1.7e9
    n = data.n
    for k in range(n):
        st = {"t": float(data.t[k]), **dict(zip(("x", "y", "phi", "vx", "vy", "r"),
                                                 data.body[k].tolist())),
              "delta": data.delta[k].tolist(), "omega_w": np.maximum(data.omega_w[k], 0).tolist()}
        rec.message("tx", "msagv/agv0/state", M.encode_state(k, st, end=k == n - 1), ts=ts)
        if k < n - 1:
            rec.message("rx", "msagv/agv0/cmd", M.encode_cmd(k, data.t[k], k, data.cmd_w[k],
                                                             data.cmd_s[k]), ts=ts + 0.001)
        ts += T
        if flush_every and k % flush_every == flush_every - 1:
            assert rec.flush()
    rec.close()


def msagv(*args, cwd=None, timeout=600):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "msagv", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, env=env, timeout=timeout)


def test_cli_end_to_end(tmp_path):
    """A recording of a plant with other tires -> msagv calibrate -> a vehicle file that
    msagv vehicle show loads, with the slopes of the plant; the bag beside the recording
    gives the same slopes; --plot writes the figure."""
    base, truth = _truth()
    data = drive(truth, 12.0, noise=0.005)
    rec = tmp_path / "rec.mcap"
    write_recording(rec, base.to_dict(), data, ros2=True)  # the controller's file, as a real run
    out, fig = tmp_path / "tuned.toml", tmp_path / "fit.png"
    r = msagv("calibrate", rec, "-o", out, "--plot", fig, "--json")
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    tv = values_of(truth)
    tuned = load_vehicle(out)
    tk = values_of(tuned)
    for name in ("lateral.K", "longitudinal.K"):
        assert doc["parameters"][name]["identified"]
        assert tk[name] == pytest.approx(tv[name], rel=0.05)
        assert doc["parameters"][name]["value"] == pytest.approx(tk[name], rel=1e-9)
    assert fig.stat().st_size > 10_000
    shown = msagv("vehicle", "show", "--vehicle", out, "--json")
    assert shown.returncode == 0, shown.stderr
    assert json.loads(shown.stdout)["tire"]["lateral"]["B"] == pytest.approx(tuned.tire_lateral.B)
    bag = tmp_path / "rec_ros2"
    assert (bag / "metadata.yaml").is_file()
    rb = msagv("calibrate", bag, "--json")
    assert rb.returncode == 0, rb.stderr
    for name in ("lateral.K", "longitudinal.K"):
        assert json.loads(rb.stdout)["parameters"][name]["value"] == pytest.approx(
            doc["parameters"][name]["value"], rel=0.02)


def test_cli_refuses_bad_recordings(tmp_path):
    """Empty, garbage, missing, cut short, without commands: exit 2 and one line on stderr,
    no traceback, no output file."""
    base = default_vehicle()
    data = drive(base, 3.0)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"\x00\x01 not a recording" * 100)
    full = tmp_path / "full.mcap"
    write_recording(full, base.to_dict(), data)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[:600])
    short = tmp_path / "short.mcap"
    few = RunData(data.t[:20], data.body[:20], data.delta[:20], data.omega_w[:20],
                  data.cmd_w[:20], data.cmd_s[:20])
    write_recording(short, base.to_dict(), few)
    nocmd = tmp_path / "nocmd.mcap"
    from msagv.bridge import messages as M
    from msagv.bridge.recording import Recorder

    r = Recorder(nocmd, {"role": "plant", "id": "agv0", "vehicle": base.to_dict(), "period": T},
                 ros2=False)
    for k in range(300):
        r.message("tx", "msagv/agv0/state", M.encode_state(k, {
            "t": k * T, "x": 5.0 * k * T, "y": 0.0, "phi": 0.0, "vx": 5.0, "vy": 0.0, "r": 0.0,
            "delta": [0.0] * 4, "omega_w": [10.0] * 4}), ts=1.7e9 + k * T)
    r.close()
    out = tmp_path / "tuned.toml"
    for path, why in ((empty, "empty"), (garbage, "not an msagv recording"),
                      (tmp_path / "missing.mcap", "no such file"), (cut, ""),
                      (short, "too short"), (nocmd, "no commands")):
        p = msagv("calibrate", path, "-o", out, timeout=300)
        assert p.returncode == 2, (path.name, p.stderr)
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("msagv calibrate: "), (path.name, p.stderr)
        assert why in lines[0] and "Traceback" not in p.stderr
        assert not out.exists()


def test_cli_uses_a_recording_cut_after_its_start_and_says_so(tmp_path):
    """A recording whose writer was killed (no summary, its last chunk cut) is fitted on the
    states before the cut, with one warning line saying so; the fit still finds the
    plant's lateral slope."""
    base, truth = _truth()
    data = drive(truth, 8.0, noise=0.005)
    full = tmp_path / "full.mcap"
    write_recording(full, base.to_dict(), data, flush_every=50)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[:int(full.stat().st_size * 0.6)])
    r = msagv("calibrate", cut, "--json", timeout=300)
    assert r.returncode == 0, r.stderr
    warnings = [ln for ln in r.stderr.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and "ends without its summary" in warnings[0], r.stderr
    used = float(warnings[0].split("using the ")[1].split(" s")[0])
    assert 2.0 < used < 0.8 * (data.t[-1] - data.t[0])
    doc = json.loads(r.stdout)
    assert doc["seconds"] <= used + 0.5
    assert doc["parameters"]["lateral.K"]["value"] == pytest.approx(
        values_of(truth)["lateral.K"], rel=0.05)
    full_run = msagv("calibrate", full, "--json", timeout=300)
    assert full_run.returncode == 0 and "warning" not in full_run.stderr, full_run.stderr


def test_maneuver_stays_within_the_vehicle_and_excites(tmp_path):
    """--maneuver: a trajectory the scenario loader accepts, whose lateral acceleration
    passes half the peak friction at two speeds and whose wheel speeds stay within the
    vehicle's limit."""
    v = default_vehicle()
    out = tmp_path / "m.toml"
    r = msagv("calibrate", "--maneuver", "-o", out)
    assert r.returncode == 0, r.stderr
    traj = np.loadtxt(tmp_path / "m.csv", delimiter=",", skiprows=1)
    t, x, y, phi = traj.T
    vx, vy = np.gradient(x, t), np.gradient(y, t)
    speed = np.hypot(vx, vy)
    a_lat = -np.sin(phi) * np.gradient(vx, t) + np.cos(phi) * np.gradient(vy, t)
    g_lat = v.tire_lateral.mu * 9.81
    assert speed.max() < v.limits.omega_w_max * v.wheel_radius
    past_half = speed[np.abs(a_lat) > 0.5 * g_lat]  # the speeds at which it passes half
    assert past_half.size and past_half.max() - past_half.min() > 2.0  # at two speeds
    assert np.abs(a_lat).max() < 0.8 * g_lat
    assert 20.0 < t[-1] < 60.0
    from msagv.experiments.scenario import Scenario

    Scenario.from_file(out).build().close()  # the scenario file is one msagv run accepts
    printed = msagv("calibrate", "--maneuver")
    assert printed.returncode == 0 and printed.stdout.startswith("t,x,y,phi")


@pytest.mark.slow
def test_cli_on_a_recorded_run_over_zenoh(tmp_path):
    """The whole path a user takes: --maneuver, the plant (tires x0.7 on B and mu) and the
    controller (the base vehicle) as two processes over Zenoh in lockstep on a loopback
    port, the plant's recording, msagv calibrate: each table's slope B C mu within 5 % and
    its peak within 10 % of the plant's (the run passes half the peak)."""
    from msagv.bridge.process import free_port
    from msagv.cli.demo import msagv_cmd, stop_process
    from msagv.experiments.calibrate import vehicle_toml

    base = default_vehicle()
    d = base.to_dict()
    for part in ("lateral", "longitudinal"):
        d["tire"][part]["B"] *= 0.7
        d["tire"][part]["mu"] *= 0.7
    from msagv.plant.vehicle import vehicle_from_dict

    plant_v = vehicle_from_dict(dict(d, name="plant"))
    (tmp_path / "plant.toml").write_text(vehicle_toml(plant_v))
    (tmp_path / "base.toml").write_text(vehicle_toml(base))
    assert msagv("calibrate", "--maneuver", "-o", tmp_path / "man.csv").returncode == 0
    ep = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    rec = tmp_path / "rec.mcap"
    plant = subprocess.Popen(msagv_cmd("plant", "--vehicle", str(tmp_path / "plant.toml"),
                                       "--trajectory", str(tmp_path / "man.csv"), "--listen", ep,
                                       "--record", str(rec), "--record-ros2", "-q", "--json"),
                             stdout=subprocess.PIPE, text=True, env=env)
    ctl = subprocess.Popen(msagv_cmd("controller", "--vehicle", str(tmp_path / "base.toml"),
                                     "--trajectory", str(tmp_path / "man.csv"), "--connect", ep,
                                     "--exit-at-end", "-q"),
                           stdout=subprocess.PIPE, text=True, env=env)
    try:
        plant.communicate(timeout=900)
        assert plant.returncode == 0
        ctl.communicate(timeout=60)
    finally:
        stop_process(plant)
        stop_process(ctl)
    r = msagv("calibrate", rec, "--vehicle", tmp_path / "base.toml", "-o", tmp_path / "t.toml",
              "--json", timeout=1800)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)["parameters"]
    tv = values_of(plant_v)
    for name, tol in (("lateral.K", 0.05), ("longitudinal.K", 0.05), ("lateral.mu", 0.10),
                      ("longitudinal.mu", 0.10)):
        assert doc[name]["identified"], (name, doc[name]["why"])
        assert doc[name]["value"] == pytest.approx(tv[name], rel=tol), name
