"""``msagv calibrate``'s inputs and outputs around the estimator (:mod:`plant.identify`): a
run read back from an msagv recording or a rosbag2 bag, the tuned vehicle written as a
vehicle file, the excitation manoeuvre to record on a real vehicle, the figure.

docs/CALIBRATE.md describes the command.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from msagv.plant.identify import IdentifyError, RunData
from msagv.plant.vehicle import Vehicle, vehicle_from_dict


class CalibrationInputError(ValueError):
    """A recording the calibration cannot read or use (one line, says why)."""


# ---- reading a run ---------------------------------------------------------------------------
def is_bag(path: str | Path) -> bool:
    """A rosbag2 bag: a directory with ``metadata.yaml`` (or one of its storage files)."""
    p = Path(path)
    return p.is_dir() or (p.suffix in (".mcap", ".db3") and (p.parent / "metadata.yaml").is_file()
                          and p.parent.name + "_0" in p.stem)


def read_run(path: str | Path, run_index: int = -1) -> tuple[RunData, dict | None, list[str]]:
    """``(data, recorded vehicle dict or None, notes)`` of a recording: an msagv recording
    (the plant's, ``msagv plant --record``; its states and the commands it received) or a
    rosbag2 bag (``odom``, ``joint_states`` and the two command topics of docs/ROS2.md).
    ``notes``: what the user should know about the file that does not stop the fit (a
    recording cut short is used up to its cut, and says so)."""
    p = Path(path)
    if not p.exists():
        raise CalibrationInputError(f"{p}: no such file or directory")
    if is_bag(p):
        return (*read_bag(p.parent if p.is_file() else p), [])
    return read_recording_run(p, run_index)


def read_recording_run(path: Path, run_index: int = -1) -> tuple[RunData, dict, list[str]]:
    """The states of one run of an msagv recording and, for each step ``k -> k+1``, the
    command in effect: the newest valid command recorded before state ``k+1`` (in lockstep
    the one answering state ``k``; in real time the one the plant's clock found)."""
    from msagv.bridge import messages as M
    from msagv.bridge.recording import RecordingError, read_recording, split_runs

    try:
        header, records, summary = read_recording(path)
    except (RecordingError, OSError) as e:
        raise CalibrationInputError(str(e)) from None
    try:
        vehicle = header["vehicle"]
        nw = 2 * len(vehicle["axle_x"])
    except (KeyError, TypeError):
        raise CalibrationInputError(f"{path}: the recording's header names no vehicle") from None
    runs = split_runs(header, records)
    if not runs:
        raise CalibrationInputError(f"{path}: no states recorded")
    try:
        run = runs[run_index]
    except IndexError:
        raise CalibrationInputError(f"{path}: --run {run_index}: the recording has "
                                    f"{len(runs)} run(s)") from None
    cmds = []  # (record time, omega_w, omega_s) of every valid command, in record order
    for r in records:
        key = r.get("key")
        if key is None or "why" in r or "p" not in r or not key.endswith("/cmd"):
            continue
        try:
            c = M.decode_cmd(r["p"], nw)
        except M.MessageError:
            continue
        cmds.append((r["ts"], c["omega_w"], c["omega_s"]))
    if not cmds:
        raise CalibrationInputError(f"{path}: no commands recorded (calibrate needs the plant's "
                                    f"recording, which holds the commands it received)")
    seqs = sorted(run.states)
    if run.end_seq is not None:
        seqs = [k for k in seqs if k <= run.end_seq]
    cts = np.array([c[0] for c in cmds])
    n = len(seqs)
    t = np.array([run.states[k]["t"] for k in seqs], dtype=float)
    body = np.array([[run.states[k][f] for f in ("x", "y", "phi", "vx", "vy", "r")]
                     for k in seqs], dtype=float)
    delta = np.array([run.states[k]["delta"] for k in seqs], dtype=float)
    om = np.array([run.states[k]["omega_w"] for k in seqs], dtype=float)
    cw = np.full((n, nw), np.nan)
    cs = np.full((n, nw), np.nan)
    valid = np.zeros(n, dtype=bool)
    for i in range(n - 1):
        if seqs[i + 1] != seqs[i] + 1 or run.states[seqs[i]].get("safe") \
                or run.states[seqs[i + 1]].get("safe"):
            continue  # a gap (a lost state) or the plant's safe behaviour: not used
        j = int(np.searchsorted(cts, run.state_ts[seqs[i + 1]], side="left")) - 1
        if j < 0 or cts[j] < run.state_ts[seqs[i]] - 1.0:
            continue  # no command yet, or only a stale one
        cw[i], cs[i] = cmds[j][1], cmds[j][2]
        valid[i] = True
    notes = []
    if summary is None:
        notes.append(f"{path}: the recording ends without its summary (its writer was stopped "
                     f"or its disk filled): using the {t[-1] - t[0]:.1f} s of states before "
                     f"the cut")
    return RunData(t, body, delta, om, cw, cs, valid), vehicle, notes


def read_bag(bag: Path) -> tuple[RunData, dict | None]:
    """A run from a rosbag2 bag (read with ``rosbags``): the state at each ``odom`` message
    (pose, the twist in base_link turned into the global frame) with the newest
    ``joint_states`` stamped no later (steering angles ``steer_ij``, wheel speeds
    ``wheel_ij``), the commands in effect from the log times of ``wheel_controller/commands``
    (wheel speeds) and ``steering_controller/commands`` (angle targets, turned back into
    rates over one period, as the plant does)."""
    from msagv.bridge import ros_msgs as R

    try:
        from rosbags.highlevel import AnyReader
    except ImportError:  # pragma: no cover - a dependency
        raise CalibrationInputError("reading a rosbag2 bag needs the rosbags package") from None
    topics = {"/" + R.ODOM: [], "/" + R.JOINT_STATES: [], "/" + R.STEERING_COMMANDS: [],
              "/" + R.WHEEL_COMMANDS: []}
    header = None
    try:
        with AnyReader([bag], default_typestore=R.typestore()) as reader:
            conns = [c for c in reader.connections if c.topic in topics]
            missing = sorted(set(topics) - {c.topic for c in conns})
            if missing:
                raise CalibrationInputError(f"{bag}: the bag has no {', '.join(missing)} "
                                            f"(calibrate needs odom, joint_states and the two "
                                            f"command topics of docs/ROS2.md)")
            for conn, ts, raw in reader.messages(connections=conns):
                topics[conn.topic].append((ts * 1e-9, reader.deserialize(raw, conn.msgtype)))
    except CalibrationInputError:
        raise
    except Exception as e:  # rosbags' own errors: an unreadable bag
        raise CalibrationInputError(f"{bag}: not a readable rosbag2 bag "
                                    f"({type(e).__name__}: {e})") from None
    header = _bag_header(bag)
    odom, joints = topics["/" + R.ODOM], topics["/" + R.JOINT_STATES]
    if len(odom) < 3:
        raise CalibrationInputError(f"{bag}: {len(odom)} odom message(s): nothing to fit")
    nw = _bag_wheels(joints[0][1]) if joints else 0
    if nw == 0:
        raise CalibrationInputError(f"{bag}: joint_states names no steer_ij / wheel_ij joints")
    jstamp = np.array([R.stamp_seconds(m.header.stamp) for _, m in joints])
    rows = []
    for ts, od in odom:
        st_t = R.stamp_seconds(od.header.stamp)
        j = int(np.searchsorted(jstamp, st_t + 1e-9, side="right")) - 1
        if j < 0:
            continue
        try:
            st = R.state_from_ros(od, joints[j][1], nw)
        except R.RosMessageError as e:
            raise CalibrationInputError(f"{bag}: {e}") from None
        rows.append((ts, st))
    if len(rows) < 3:
        raise CalibrationInputError(f"{bag}: fewer than three odom messages with joint states")
    t = np.array([st["t"] for _, st in rows])
    period = float(np.median(np.diff(t)))  # (at least three rows: checked above)
    body = np.array([[st[f] for f in ("x", "y", "phi", "vx", "vy", "r")] for _, st in rows])
    delta = np.array([st["delta"] for _, st in rows])
    om = np.array([st["omega_w"] for _, st in rows])
    wts = np.array([ts for ts, _ in topics["/" + R.WHEEL_COMMANDS]])
    sts = np.array([ts for ts, _ in topics["/" + R.STEERING_COMMANDS]])
    if wts.size == 0 or sts.size == 0:
        raise CalibrationInputError(f"{bag}: no commands recorded")
    n = len(rows)
    cw = np.full((n, nw), np.nan)
    cs = np.full((n, nw), np.nan)
    valid = np.zeros(n, dtype=bool)
    limits = None
    if header and isinstance(header.get("vehicle"), dict):
        try:
            limits = vehicle_from_dict(header["vehicle"]).limits
        except ValueError:
            limits = None
    for i in range(n - 1):
        nxt = rows[i + 1][0]
        jw = int(np.searchsorted(wts, nxt, side="left")) - 1
        js = int(np.searchsorted(sts, nxt, side="left")) - 1
        if jw < 0 or js < 0:
            continue
        w = np.asarray(topics["/" + R.WHEEL_COMMANDS][jw][1].data, dtype=float)
        tgt = np.asarray(topics["/" + R.STEERING_COMMANDS][js][1].data, dtype=float)
        if w.size != nw or tgt.size != nw:
            continue
        # the target was computed from the angles of the state it answers: the newest state
        # recorded before the command
        k = int(np.searchsorted(np.array([r[0] for r in rows]), sts[js], side="right")) - 1
        k = min(max(k, 0), n - 1)
        cw[i] = w
        cs[i] = R.steering_rates(delta[k], tgt, period, limits)
        valid[i] = True
    return RunData(t, body, delta, om, cw, cs, valid), (header or {}).get("vehicle")


def _bag_wheels(js) -> int:
    names = set(js.name)
    n = 0
    while f"steer_{n // 2 + 1}{n % 2 + 1}" in names and f"wheel_{n // 2 + 1}{n % 2 + 1}" in names:
        n += 1
    return n - n % 2


def _bag_header(bag: Path) -> dict | None:
    """The msagv header a bag written by ``--record`` carries (MCAP metadata), or None."""
    from msagv.bridge.ros_bag import META_HEADER

    try:
        from mcap.reader import make_reader

        for f in sorted(bag.glob("*.mcap")):
            with f.open("rb") as fh:
                for m in make_reader(fh).iter_metadata():
                    if m.name == META_HEADER:
                        return {k: json.loads(v) for k, v in m.metadata.items()}
    except Exception:  # a bag of another tool: no header
        return None
    return None


def base_vehicle(path: str | None, recorded: dict | None) -> Vehicle:
    """The base vehicle: ``--vehicle`` when given, else the vehicle the recording names."""
    from msagv.plant.vehicle import load_vehicle

    if path is not None:
        return load_vehicle(path)
    if recorded is None:
        raise CalibrationInputError("the recording names no vehicle: give --vehicle FILE")
    return vehicle_from_dict(recorded)


def check_data(data: RunData, vehicle: Vehicle) -> None:
    try:
        data.check(vehicle)
    except IdentifyError as e:
        raise CalibrationInputError(str(e)) from None


# ---- writing the vehicle file ------------------------------------------------------------------
def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        f = float(v)
        if not math.isfinite(f):
            raise ValueError(f"cannot write {v} to a vehicle file")
        return repr(f)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(type(v))


def vehicle_toml(v: Vehicle, comment: str = "") -> str:
    """A vehicle file (the layout of scenarios/vehicles/*.toml) of ``v``."""
    d = v.to_dict()
    lines = [f"# {c}" if c else "#" for c in comment.splitlines()] if comment else []
    for k in ("name", "mass", "yaw_inertia", "wheel_radius", "axle_x", "half_track",
              "steer_loss_kt"):
        lines.append(f"{k} = {_toml_value(d[k])}")
    for part, table in d["tire"].items():  # the models' own sections among them
        lines += ["", f"[tire.{part}]"]
        lines += [f"{k} = {_toml_value(x)}" for k, x in table.items()]
    for table in ("limits", "plant"):
        lines += ["", f"[{table}]"]
        lines += [f"{k} = {_toml_value(x)}" for k, x in d[table].items()]
    return "\n".join(lines) + "\n"


# ---- the excitation manoeuvre --------------------------------------------------------------
def maneuver(vehicle: Vehicle, reach: float = 0.65, dt: float = 0.1) -> dict:
    """A trajectory (``t, x, y, phi`` arrays) that excites what :func:`plant.identify.calibrate`
    fits, within the vehicle's limits: a slalom at two speeds whose peak lateral acceleration
    is ``reach`` x the lateral peak friction (past half the peak), a firm acceleration
    between them and a braking to a crawl at ``reach`` x the longitudinal peak, the heading
    along the path. About 40 s."""
    g = 9.81
    la, lo = vehicle.tire_lateral.mu, vehicle.tire_longitudinal.mu
    v_top = 0.8 * vehicle.limits.omega_w_max * vehicle.wheel_radius
    v1 = min(5.0, 0.45 * v_top)
    v2 = min(8.0, 0.75 * v_top)
    a_lat = reach * la * g
    a_acc = min(2.0, 0.5 * lo * g)
    a_brake = reach * lo * g
    # segments: (duration, acceleration, lateral acceleration amplitude, slalom period)
    segs = [(3.0, 0.0, 0.0, 0.0), (16.0, 0.0, a_lat, 4.0),
            ((v2 - v1) / a_acc, a_acc, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0),
            (16.0, 0.0, a_lat, 5.0), (2.0, 0.0, 0.0, 0.0),
            ((v2 - 1.0) / a_brake, -a_brake, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0)]
    t_all, v_all, k_all = [0.0], [v1], [0.0]
    t, v = 0.0, v1
    for dur, acc, alat, per in segs:
        n = max(int(round(dur / dt)), 1)
        h = dur / n
        for i in range(1, n + 1):
            tau = i * h
            v_i = v + acc * tau
            kappa = 0.0
            if alat > 0:
                # curvature a_lat / v^2 along a sine of the given period, its amplitude
                # faded in and out over one period
                env = min(1.0, tau / per, (dur - tau) / per)
                kappa = env * alat / (v_i * v_i) * math.sin(2 * math.pi * tau / per)
            t_all.append(t + tau)
            v_all.append(v_i)
            k_all.append(kappa)
        t += dur
        v = v + acc * dur
    t_a, v_a, k_a = np.array(t_all), np.array(v_all), np.array(k_all)
    ds = 0.5 * (v_a[1:] + v_a[:-1]) * np.diff(t_a)
    phi = np.concatenate([[0.0], np.cumsum(0.5 * (k_a[1:] + k_a[:-1]) * ds)])
    x = np.concatenate([[0.0], np.cumsum(ds * np.cos(0.5 * (phi[1:] + phi[:-1])))])
    y = np.concatenate([[0.0], np.cumsum(ds * np.sin(0.5 * (phi[1:] + phi[:-1])))])
    return {"t": t_a, "x": x, "y": y, "phi": phi, "v1": v1, "v2": v2, "a_lat": a_lat,
            "a_brake": a_brake}


def maneuver_csv(m: dict) -> str:
    lines = ["t,x,y,phi"]
    lines += [f"{t:.2f},{x:.6f},{y:.6f},{p:.6f}" for t, x, y, p in zip(m["t"], m["x"], m["y"],
                                                                         m["phi"])]
    return "\n".join(lines) + "\n"


def maneuver_scenario(m: dict, vehicle_path: str | None, trajectory: str) -> str:
    """The scenario file (docs/SCENARIOS.md) that drives the manoeuvre."""
    lines = [
        "# An excitation run for msagv calibrate (docs/CALIBRATE.md): a slalom at "
        f"{m['v1'] * 3.6:.0f} and {m['v2'] * 3.6:.0f} km/h",
        f"# reaching {m['a_lat']:.2f} m/s^2 sideways, an acceleration, a braking at "
        f"{m['a_brake']:.2f} m/s^2; {m['t'][-1]:.0f} s.",
        "# Record it with the plant:  msagv plant --scenario THIS.toml --record run.mcap ...",
        "# (or on the vehicle), then:  msagv calibrate run.mcap --vehicle YOUR.toml -o tuned.toml",
    ]
    if vehicle_path:
        lines.append(f"vehicle = {json.dumps(str(vehicle_path))}")
    lines += [f"trajectory = {json.dumps(trajectory)}", 'after_end = "stop"']
    return "\n".join(lines) + "\n"


# ---- the figure -----------------------------------------------------------------------------
def plot_calibration(cal, path: str | Path, title: str = "") -> None:
    """Measured against predicted (base vehicle and tuned vehicle) over the fitted windows:
    lateral velocity, yaw rate, forward velocity, the first wheel's speed."""
    from .plots import pyplot, style

    plt = pyplot()
    nw = cal.vehicle.n_wheels
    chans = [(1, "v (body) [m/s]"), (2, "r [rad/s]"), (0, "u (body) [m/s]"),
             (3 + nw, "omega_w_11 [rad/s]")]
    t = cal.t
    with style():
        fig, axes = plt.subplots(len(chans), 1, figsize=(8.0, 8.0), sharex=True)
        for ax, (c, label) in zip(axes, chans):
            ax.plot(t, cal.measured[:, c], ".", color="0.3", ms=1.5, label="measured")
            ax.plot(t, cal.predicted_base[:, c], "-", color="C1", lw=0.8, label="base vehicle")
            ax.plot(t, cal.predicted[:, c], "-", color="C0", lw=0.9, label="tuned vehicle")
            ax.set_ylabel(label)
        axes[0].legend(loc="best")
        axes[-1].set_xlabel("t [s]")
        axes[0].set_title(title or "multi-step prediction over each window")
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)
