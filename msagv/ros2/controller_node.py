"""``msagv ros2 controller``: the MPC as a ROS 2 node (docs/ROS2.md).

In: ``odom`` (nav_msgs/Odometry: pose in odom, twist in base_link as REP-105 says),
``joint_states`` (sensor_msgs/JointState: positions of ``steer_ij``, velocities of
``wheel_ij``) and ``plan`` (nav_msgs/Path, the reference). Out: ros2_control's
forward-command topics ``steering_controller/commands`` (steering angle targets [rad]: the
angle the commanded rate reaches in one period, :func:`bridge.ros_msgs.steering_targets`)
and ``wheel_controller/commands`` (wheel speeds [rad/s]), ``predicted_path`` (the MPC's
horizon) and ``wear_estimate`` (each wheel's wear power under the command at the observed
state, by the plant's tire model reset there - pose, steering, measured wheel speeds -, and
its integral; the plant publishes its own, measured, on ``wear``).

One solve per odometry message: when the joint states stamped no earlier than it have
arrived (a plant that stamps both alike, as ``msagv ros2 plant``, is answered state by
state), or after half a period with the newest joint states. A repeated stamp (a plant
sending its state again) is not answered again: a command names no state, so a second
answer would be taken for the next state's (counted ``repeated``).

Safety, the same state machine as the plant's (:class:`bridge.loss.CommandWatch`), run on
the node's timer at 1/T over the inputs instead of the commands - on ROS time under
``use_sim_time`` (a simulator's /clock, at whatever pace it runs), else on a steady wall
clock: more than
``stale_ms`` without a fresh odometry + joint-states pair puts the node in its safe
behaviour - steering targets held at the last measured angles, wheel speeds ramped down
at ``safe_decel`` - until fresh inputs come for ``resume_periods`` periods. Nothing is
published before the first state (nothing to hold). A plan (:func:`plan_reference`):
timed by its stamps, or, unstamped as Nav2 sends it, smoothed and timed by a speed profile
(:class:`SpeedProfile`); headings from the path's tangent where the orientations are the
identity (NavFn's), the goal's orientation turned to near the goal; a replan of the route
being driven leaves the reference as it is. A plan's end: past its last pose the reference
holds that pose, and once its time is up with the vehicle at or past the goal the node
holds it there without the MPC (:meth:`RosController._at_goal`) until a plan to another
goal; an empty plan stops the vehicle as the safe behaviour does. Below ``low_speed_kmh``
the plain feed-forward commands instead of the MPC (:meth:`RosController._controller_for`).

A managed node (``rclpy.lifecycle``: configure, activate, deactivate, cleanup, shutdown);
parameters changed at run time where safe (:data:`RUNTIME`), refused with the reason where
not; its status on ``/diagnostics`` (diagnostic_msgs) once a second; ``~/rearm`` and
``~/reset`` (std_srvs/Trigger). docs/ROS2.md, "A managed node".
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from typing import Callable

import numpy as np

from msagv.bridge import messages as M
from msagv.bridge import ros_msgs as R
from msagv.bridge.controller_node import mpc_estimate
from msagv.bridge.controller_run import ControllerRun
from msagv.bridge.loss import RESUME_PERIODS, SAFE, SAFE_DECEL, STALE_MS, CommandWatch
from msagv.bridge.plant_node import percentiles_ms
from msagv.bridge.recording import NullRecorder
from msagv.controller.adaptation import SWITCH_KEYS
from msagv.controller.reference import Reference, from_samples

from msagv.plant.signals import CONTROL_PERIOD
from .runtime import (OK, STALE, WARN, Context, Diagnostics, Lifecycle, declare_parameters,
                      destroy, parameter_changes, set_parameters_result, trigger_services)

log = logging.getLogger("msagv.ros2.controller")


# ---- the plan -> the reference ---------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SpeedProfile:
    """How an unstamped plan is timed along its arc length: up to ``speed`` [m/s], speeding
    up at most at ``accel`` and slowing down at most at ``decel`` [m/s^2] (along the path),
    at most ``lat_accel`` [m/s^2] across it (v^2 kappa on the path's curvature), from the
    measured speed ``v0`` [m/s] at the first pose to standing still at the last."""
    speed: float
    accel: float = 1.0
    decel: float = 1.0
    lat_accel: float = 1.5
    v0: float = 0.0

    def check(self) -> None:
        for k in ("speed", "accel", "decel", "lat_accel"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"the plan's {k} must be > 0, got {v:g}")


TANGENT_SPAN = 0.5  # m: a heading is the chord from this far behind a pose to this far ahead
GOAL_TURN = 3.0  # m: the goal's orientation is blended in over the path's last 3 m
PLAN_STEP = 0.05  # m: an unstamped plan is resampled this densely along its arc length ...
SMOOTH = 1.0  # m: ... and averaged over this far behind and ahead (ends kept), in
SMOOTH_PASSES = 3  # this many box filters of a third of it each


def smooth_path(x, y):
    """An unstamped plan as the reference drives it: resampled every :data:`PLAN_STEP`
    along its arc length, then :data:`SMOOTH_PASSES` times each point the mean of the
    points within ``SMOOTH / SMOOTH_PASSES`` behind and ahead (a window that shrinks to
    keep the first and the last point where they are).
    A grid planner's one-cell steps (NavFn's) would otherwise be steps of heading and of
    curvature: a steering that chatters at its rate limit (scrub wear) and a lateral
    speed limit on curvature that is not the path's. Returns ``(x, y, s)``."""
    s = np.r_[0.0, np.cumsum(np.hypot(np.diff(x), np.diff(y)))]
    n = max(3, int(math.ceil(s[-1] / PLAN_STEP)) + 1)
    su = np.linspace(0.0, s[-1], n)
    xu, yu = _along(x, y, s, su)
    h = np.minimum(int(round(SMOOTH / SMOOTH_PASSES / (su[1] - su[0]))),
                   np.minimum(np.arange(n), np.arange(n)[::-1]))
    i = np.arange(n)
    xs, ys = xu, yu
    for _ in range(SMOOTH_PASSES):  # box filters in a row: heading and curvature smooth
        cx, cy = np.r_[0.0, np.cumsum(xs)], np.r_[0.0, np.cumsum(ys)]
        xs = (cx[i + h + 1] - cx[i - h]) / (2 * h + 1)
        ys = (cy[i + h + 1] - cy[i - h]) / (2 * h + 1)
    keep = np.r_[True, np.hypot(np.diff(xs), np.diff(ys)) > 1e-9]
    xs, ys = xs[keep], ys[keep]
    return xs, ys, np.r_[0.0, np.cumsum(np.hypot(np.diff(xs), np.diff(ys)))]


def _along(x, y, s, at):
    """Points of the polyline (x, y) with arc lengths ``s`` at the arc lengths ``at``."""
    return np.interp(at, s, x), np.interp(at, s, y)


def path_headings(x, y, s) -> np.ndarray:
    """The path's tangent heading at each pose (unwrapped): the chord from
    :data:`TANGENT_SPAN` behind to as far ahead along the path, so a planner's grid steps
    (NavFn's are one costmap cell) do not zigzag it."""
    h = min(TANGENT_SPAN, s[-1] / 4)
    xa, ya = _along(x, y, s, np.clip(s - h, 0.0, s[-1]))
    xb, yb = _along(x, y, s, np.clip(s + h, 0.0, s[-1]))
    return np.unwrap(np.arctan2(yb - ya, xb - xa))


def speed_profile(s, kappa, prof: SpeedProfile) -> np.ndarray:
    """The speed at arc lengths ``s`` of curvature ``kappa``: the largest under
    ``prof.speed`` and the lateral limit that a start at ``prof.v0`` reaches at ``accel`` and
    that stops at the end at ``decel`` (a forward and a backward pass)."""
    with np.errstate(divide="ignore"):
        cap = np.minimum(prof.speed, np.sqrt(prof.lat_accel / np.abs(kappa)))
    v = cap.copy()
    v[0] = min(max(prof.v0, 0.0), cap[0])
    ds = np.diff(s)
    for i in range(len(s) - 1):
        v[i + 1] = min(v[i + 1], math.sqrt(v[i] ** 2 + 2 * prof.accel * ds[i]))
    v[-1] = 0.0
    for i in range(len(s) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * prof.decel * ds[i]))
    return v


REPLAN_SAME = 0.10  # m: a plan to the same goal whose poses all lie this close to the
# path being driven is that path again (Nav2 replanning): the reference goes on unchanged


def _to_segments(px, py, ax, ay, dx, dy) -> np.ndarray:
    """Distances of the points ``(px, py)`` (shape (m, 1)) from the segments starting at
    ``(ax, ay)`` with extents ``(dx, dy)`` (shape (m, k) or (k,)): shape (m, k)."""
    n2 = np.maximum(dx * dx + dy * dy, 1e-18)
    u = np.clip(((px - ax) * dx + (py - ay) * dy) / n2, 0.0, 1.0)
    return np.hypot(ax + u * dx - px, ay + u * dy - py)


def off_path(px, py, x, y, k: int = 8) -> float:
    """The largest distance of the points (px, py) from the polyline (x, y), exactly, in
    about O((m + n) log n) for m points and n vertices (a replan against a long path at
    Nav2's 1-20 Hz; every point against every segment took 40-105 ms for a 1181-pose plan
    on a loaded 2-core machine, 2-4 periods of a simulator at 0.4x).

    Each point is measured against the segments next to its ``k`` nearest vertices (a
    k-d tree, scipy). That is exact where the k-th nearest vertex lies farther than the
    distance found plus half the longest segment (the nearest point of any closer segment
    has an endpoint within that radius, so among the k); the other points are measured
    against every segment."""
    from scipy.spatial import cKDTree

    px, py = np.asarray(px, float), np.asarray(py, float)
    x, y = np.asarray(x, float), np.asarray(y, float)
    if len(x) < 2:
        return float(np.max(np.hypot(px - x[0], py - y[0])))
    ax, ay, dx, dy = x[:-1], y[:-1], np.diff(x), np.diff(y)
    k = min(k, len(x))
    r, idx = cKDTree(np.column_stack([x, y])).query(np.column_stack([px, py]), k=k)
    r, idx = r.reshape(len(px), k), idx.reshape(len(px), k)
    segs = np.clip(np.concatenate([idx - 1, idx], axis=1), 0, len(ax) - 1)
    d = _to_segments(px[:, None], py[:, None], ax[segs], ay[segs], dx[segs],
                     dy[segs]).min(axis=1)
    if k < len(x):
        half = 0.5 * float(np.max(np.hypot(dx, dy)))
        rest = r[:, -1] <= d + half
        if rest.any():
            d[rest] = _to_segments(px[rest, None], py[rest, None], ax, ay, dx,
                                   dy).min(axis=1)
    return float(np.max(d))


def plan_start_speed(st: dict, current: Reference | None) -> float:
    """The speed a new plan starts from: the measured one, but no faster than the reference
    being tracked asks for now (a plan again along the same route - Nav2 replanning at 1-20
    Hz - goes on at the speed the last one had reached, not at a speed the vehicle overshot
    to while tracking it)."""
    v = math.hypot(st["vx"], st["vy"])
    if current is not None and current.t[0] <= st["t"] <= current.t[-1]:
        r = current.sample([st["t"]])[0]
        v = min(v, math.hypot(r[3], r[4]))
    return v


def plan_reference(t, x, y, phi, t_now: float, profile: SpeedProfile) -> tuple[Reference, str]:
    """The reference of a path's poses: timed by their stamps where those increase
    strictly; else along the arc length by ``profile`` (:class:`SpeedProfile`) from
    ``t_now`` (Nav2's planners leave the stamps zero). Headings from the poses'
    orientations; where the orientations are the identity - all of them, or all but the
    last (Nav2's NavFn gives only the goal an orientation) - from the path's tangent
    (:func:`path_headings`; of the smoothed path, :func:`smooth_path`, when unstamped),
    the last pose's orientation turned to over the last
    :data:`GOAL_TURN` metres. Past the last pose the reference holds it. Returns
    ``(reference, how it was timed)``."""
    t, x, y, phi = (np.asarray(a, dtype=float) for a in (t, x, y, phi))
    if x.size < 2:
        raise ValueError(f"a plan needs at least 2 poses, got {x.size}")
    stamped = bool(np.all(np.diff(t) > 0))
    identity = bool(np.all(phi[:-1] == 0.0))
    if not stamped or identity:
        keep = np.r_[True, np.hypot(np.diff(x), np.diff(y)) > 1e-9]
        keep[-1] = True  # the goal (its orientation) stays, a repeat before it goes
        if x.size > 1 and not np.hypot(x[-1] - x[-2], y[-1] - y[-2]) > 1e-9:
            keep[-2] = False
        t, x, y, phi = t[keep], x[keep], y[keep], phi[keep]
        if x.size < 2:
            raise ValueError("a plan without stamps or orientations needs two distinct points")
    s = np.r_[0.0, np.cumsum(np.hypot(np.diff(x), np.diff(y)))]
    tangent = None
    if not stamped:  # resampled and smoothed (the profile's speed is 0 at the end)
        goal = phi[-1]
        x2, y2, s2 = smooth_path(x, y)
        phi = np.interp(s2 * (s[-1] / s2[-1]), s, np.unwrap(phi))
        phi[-1] = goal
        x, y, s = x2, y2, s2
        tangent = np.unwrap(np.arctan2(np.gradient(y, s), np.gradient(x, s)))
    if identity and s[-1] > 0:
        goal = phi[-1]
        head = tangent if tangent is not None else path_headings(x, y, s)
        if goal != 0.0:  # NavFn: the goal's orientation, turned to near the goal only
            turn = (goal - head[-1] + math.pi) % (2 * math.pi) - math.pi
            # by the distance left to the goal: a plan again from where the vehicle is
            # (Nav2 replanning) asks for the heading the last one asked for there
            u = np.clip(1.0 - (s[-1] - s) / GOAL_TURN, 0.0, 1.0)
            head = head + turn * u * u * (3 - 2 * u)  # smoothstep: no yaw-rate jump
        phi = head
    if stamped:
        how = "its stamps"
    else:
        profile.check()
        kappa = np.gradient(tangent, s)
        v = speed_profile(s, kappa, profile)
        dt = 2.0 * np.diff(s) / (v[:-1] + v[1:])
        t = t_now + np.r_[0.0, np.cumsum(dt)]
        how = (f"its arc length at up to {profile.speed * 3.6:g} km/h (from "
               f"{v[0]:.2f} m/s, {profile.accel:g}/{profile.decel:g} m/s^2 along, "
               f"{profile.lat_accel:g} m/s^2 across, standing at the goal)")
    if x.size == 2:  # from_samples needs three samples: the midpoint
        t, x, y, phi = (np.r_[a[0], 0.5 * (a[0] + a[1]), a[1]] for a in (t, x, y, phi))
    ref = from_samples(t, x, y, phi, name="plan")
    ref.after_end = "hold"
    return ref, how


def shifted(ref: Reference, dt: float) -> Reference:
    """The reference ``dt`` seconds later (its time axis moved; the same samples)."""
    if dt == 0.0:
        return ref
    return dataclasses.replace(ref, t=np.asarray(ref.t) + dt)


# ---- the parameters -----------------------------------------------------------------------------
# ROS parameters (``--ros-args -p NAME:=VALUE`` or a params file), each also an option
PARAMETERS = {
    "method": str, "model": str, "policy": str, "solver": str, "seed": int,
    "iterations": int, "chains": int, "deadline_ms": float, "Q": list, "L": list, "E": list,
    "R": list, "plan_speed_kmh": float, "plan_accel": float, "plan_decel": float,
    "plan_lat_accel": float, "goal_tolerance": float, "goal_yaw_tolerance_deg": float,
    "stale_ms": float, "resume_periods": int, "safe_decel": float, "max_age_ms": float,
    "low_speed_kmh": float, "plan_frame": str,
}


# What may change while the node is configured (inactive or active); the others change the
# optimiser's structure and are taken while it is unconfigured (lifecycle cleanup, set,
# configure). Weights: the MPC is built again from them at once (for the annealer
# and the feed-forward; IPOPT and acados build them into their problem at configure).
WEIGHTS = ("Q", "L", "E", "R", "deadline_ms")
PLAN = ("plan_speed_kmh", "plan_accel", "plan_decel", "plan_lat_accel")  # the next plan
LIMITS = ("goal_tolerance", "goal_yaw_tolerance_deg", "low_speed_kmh", "stale_ms",
          "resume_periods", "safe_decel", "max_age_ms", "plan_frame")
RUNTIME = WEIGHTS + PLAN + LIMITS
REBUILT = ("sa", "ff")  # the solvers whose weights change at run time


# ---- wear -----------------------------------------------------------------------------------------
class WearEstimate:
    """Each wheel's wear power under a command at an observed state, by the plant's tire
    model (the plant reset to the state, its outputs read), and the work summed over the
    solves (power times the time to the next state)."""

    def __init__(self, vehicle):
        from msagv.plant import Plant

        self.plant = Plant(vehicle)
        self.names = vehicle.wheel_names
        self.reset()

    def reset(self) -> None:
        self.work = np.zeros(len(self.names))
        self._last: tuple[float, np.ndarray] | None = None

    def update(self, st: dict, omega_w, omega_s) -> tuple[np.ndarray, np.ndarray]:
        init = {k: st[k] for k in ("x", "y", "phi", "vx", "vy", "r")}
        # the wheels as measured (with a wheel lag the plant's wheel speeds are a state: left
        # at 0 they slipped at the vehicle's whole speed, an estimate 1000x the plant's),
        # the steering at the commanded rate
        for n, d, w, ws in zip(self.names, st["delta"], st["omega_w"], omega_s):
            init[f"delta_{n}"] = d
            init[f"omega_w_{n}"] = max(float(w), 0.0)
            init[f"omega_s_{n}"] = float(ws)
        self.plant.reset(init)
        self.plant.set_inputs(omega_w, omega_s)
        out = self.plant.outputs()
        p = np.array([out[f"P_s_{n}"] + out[f"P_alpha_{n}"] + out[f"P_t_{n}"]
                      for n in self.names])
        t = float(st["t"])
        if self._last is not None and t > self._last[0]:
            self.work = self.work + self._last[1] * (t - self._last[0])
        self._last = (t, p)
        return p, self.work


# ---- the node ---------------------------------------------------------------------------------
LOW_SPEED_KMH = 5.0  # below this (measured and asked) the policy's plain feed-forward commands
STOP_ACK_S = 1.0  # s: the longest wait for the subscribers to acknowledge the last stop


@dataclasses.dataclass
class RosControllerConfig:
    period: float = CONTROL_PERIOD
    stale_ms: float = STALE_MS
    resume_periods: int = RESUME_PERIODS
    safe_decel: float = SAFE_DECEL
    plan_speed_kmh: float = 15.0
    plan_accel: float = 1.0
    plan_decel: float = 1.0
    plan_lat_accel: float = 1.5
    goal_tolerance: float = 0.05
    goal_yaw_tolerance_deg: float = 2.0
    max_age_ms: float | None = None
    low_speed_kmh: float = LOW_SPEED_KMH
    plan_frame: str = ""  # the frame a plan must be in ("": the odometry's)
    node_name: str = "msagv_controller"
    vehicle_id: str = "agv0"


class RosController:
    """The controller node (see the module docstring). ``make_mpc(parameters)`` builds the
    controller from the parameters in force (:data:`PARAMETERS`; ``defaults`` their
    command-line values); ``reference``: the reference to track from the first state on
    (None: wait for a plan); ``recorder``: a recorder-like sink or None.

    A managed node (``rclpy.lifecycle``): the parameters are declared (unknown ones
    refused) when it is made; ``configure`` reads them, builds and warms the MPC and
    declares the topics, services and timers; ``activate`` lets it command;
    ``deactivate`` sends one stop (steering held, wheels 0) and stops commanding;
    ``cleanup`` takes all of it down again; ``shutdown`` ends :meth:`run`. With
    ``managed=False`` it configures and activates itself at once (a ValueError names a
    bad value)."""

    def __init__(self, make_mpc: Callable[[dict], object], defaults: dict, vehicle,
                 cfg: RosControllerConfig, ros_args: list[str], reference: Reference | None,
                 recorder=None, stop: threading.Event | None = None, managed: bool = False):
        self.ctx = Context(cfg.node_name, ros_args, lifecycle=True)
        self.params = declare_parameters(self.ctx.node, PARAMETERS, defaults)
        self.make_mpc = make_mpc
        self.cfg0 = cfg
        self.cfg = cfg
        self.vehicle = vehicle
        self.nw = vehicle.n_wheels
        self.rec = recorder if recorder is not None else NullRecorder()
        self.stop = stop or threading.Event()
        self.base_reference = reference
        self.managed = managed
        self.configured = False
        self.active = False
        self._ended = False
        # answered, new_runs, dropped_stale and the solve times: the run core's counts
        self.run_core = ControllerRun(self._controllers, lambda: self.cfg.max_age_ms,
                                      now=self._now, recorder=recorder)
        self.stats = {"repeated": 0, "safe_events": 0, "safe_periods": 0,
                      "resumes": 0, "plans": 0, "rejected": 0,
                      "no_reference": 0, "goals_reached": 0,
                      "held_at_goal": 0, "plans_at_goal": 0, "plans_same_route": 0,
                      "low_speed": 0, "rearms": 0, "resets": 0, "parameter_changes": 0,
                      "parameters_refused": 0, "plans_wrong_frame": 0}
        self.goal_errors: list = []  # (distance [m], heading [deg]) at each goal reached
        self.rej = M.Rejections("ros2 controller", log)
        self.mpc = self.low = None
        self._estimates = {"disturbance": None, "adapted_tires": None}  # the last MPC's
        self.reference: Reference | None = None
        self._safe = False
        node = self.ctx.node
        self.lifecycle = Lifecycle(node, {
            "configure": self._configure, "activate": self._activate,
            "deactivate": self._deactivate, "cleanup": self._cleanup,
            "shutdown": self._shutdown, "error": self._cleanup},
            log, say=managed)  # (unmanaged, the command line says a failure: exit 2)
        node.add_on_set_parameters_callback(self._on_set_parameters)
        if not managed:  # configured and activated at once, as a plain node would be
            node.trigger_configure()
            if not self.configured:
                self.close()
                raise ValueError(self.lifecycle.error or "configure failed")
            node.trigger_activate()

    def _config_from(self, p: dict) -> RosControllerConfig:
        """The node's configuration of the parameters ``p``, or ValueError naming the bad
        value."""
        cfg = dataclasses.replace(
            self.cfg0, stale_ms=p["stale_ms"], resume_periods=p["resume_periods"],
            safe_decel=p["safe_decel"], plan_speed_kmh=p["plan_speed_kmh"],
            plan_accel=p["plan_accel"], plan_decel=p["plan_decel"],
            plan_lat_accel=p["plan_lat_accel"], goal_tolerance=p["goal_tolerance"],
            goal_yaw_tolerance_deg=p["goal_yaw_tolerance_deg"],
            max_age_ms=p["max_age_ms"] or None, low_speed_kmh=p["low_speed_kmh"],
            plan_frame=p["plan_frame"].strip())
        positive = ("stale_ms", "safe_decel", "plan_speed_kmh", "plan_accel", "plan_decel",
                    "plan_lat_accel", "goal_tolerance", "goal_yaw_tolerance_deg")
        bad = [f"{k} must be > 0, got {getattr(cfg, k):g}" for k in positive
               if not (math.isfinite(getattr(cfg, k)) and getattr(cfg, k) > 0)]
        if not (math.isfinite(cfg.low_speed_kmh) and cfg.low_speed_kmh >= 0):
            bad.append(f"low_speed_kmh must be >= 0, got {cfg.low_speed_kmh:g}")
        if cfg.max_age_ms is not None and not (math.isfinite(cfg.max_age_ms)
                                               and cfg.max_age_ms > 0):
            bad.append(f"max_age_ms must be > 0 (0: none), got {cfg.max_age_ms:g}")
        if cfg.resume_periods < 1:
            bad.append(f"resume_periods must be >= 1, got {cfg.resume_periods}")
        if bad:
            raise ValueError("; ".join(bad))
        return cfg

    def _low_speed_mpc(self, p: dict, cfg: RosControllerConfig):
        """The feed-forward that commands at walking pace (:meth:`_controller_for`)."""
        if cfg.low_speed_kmh > 0 and p["solver"] != "ff":
            return self.make_mpc(dict(p, solver="ff"))
        return None

    # ---- the lifecycle ---------------------------------------------------------------------
    def _configure(self) -> None:
        """Read the parameters, build and warm the MPC (before any topic is declared: a
        plant that sees this node is answered at once), declare the topics, services and
        timers."""
        p = self.params
        cfg = self._config_from(p)
        self.cfg = cfg
        self.mpc = self.make_mpc(p)
        self.low = self._low_speed_mpc(p, cfg)  # at walking pace (see _controller_for)
        t0 = time.perf_counter()
        for c in self._controllers():
            c.warmup()
        log.info("MPC warm (%.2f s)", time.perf_counter() - t0)
        self.reference = None
        self.msgs = R.RunMessages(self.vehicle, cfg.period)
        self.wear = WearEstimate(self.vehicle)
        self._warm_extras()
        self.watch = CommandWatch(self._max_missed(cfg), cfg.resume_periods, cfg.period)
        self.key_state = f"msagv/{cfg.vehicle_id}/state"
        self.key_cmd = f"msagv/{cfg.vehicle_id}/cmd"
        self._odom = None
        self._odom_rx = 0.0
        self._fresh_rx: float | None = None  # when the newest fresh pair came (node clock)
        self._joints = None
        self._last_t: float | None = None  # the newest state solved
        self._last_cmd: tuple | None = None  # (t, steering targets, wheel speeds)
        self._delta = None  # the newest measured steering angles
        self._tick = 0
        self._fresh_tick: int | None = None
        self._plan_msg = None
        self._unanswered: tuple | None = None  # (state, rx, seq) received while safe
        self._safe = False
        self._safe_why = ""
        self._seq = 0
        self._told_arc = False
        self._odom_frame = ""  # the newest state's header.frame_id
        self._told_frames: set[str] = set()  # plan frames refused (each said once)
        self._retime = False  # the plan's limits changed: the next plan is timed afresh
        self._restart = False  # ~/reset: the next state starts a new run
        self._odom_lost = False  # the odometry had no publisher: its next stamp is new
        self._goal_held: tuple | None = None  # the goal (x, y, phi) reached and held
        self._hold: tuple | None = None  # (steering held, wheel speeds ramping down)
        self._diag_from = len(self.run_core.counts.solve_ms)
        c = self.ctx
        node = c.node
        self.pub_steer = c.publisher(R.STEERING_COMMANDS)
        self.pub_wheel = c.publisher(R.WHEEL_COMMANDS)
        self.pub_pred = c.publisher(R.PREDICTED_PATH)
        self.pub_wear = c.publisher(R.WEAR_ESTIMATE, R.TYPES[R.WEAR])  # not the plant's wear
        self._subs = [c.subscription(R.ODOM, self._on_odom, matched=self._on_odom_matched),
                      c.subscription(R.JOINT_STATES, self._on_joints),
                      c.subscription(R.PLAN, self._on_plan)]
        from rclpy.clock import Clock, ClockType

        # under use_sim_time the run's clock is the simulator's (/clock): the timer, the
        # staleness bound and every safe-state decision count its periods, so a simulator
        # slower or faster than real time is answered state by state, never stale for
        # being slow; otherwise the wall clock (a steady one)
        self.sim_time = bool(node.get_parameter("use_sim_time").value)
        self._clock = node.get_clock() if self.sim_time else None
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._timers = [node.create_timer(cfg.period, self._on_tick,
                                          clock=self._clock if self.sim_time else steady)]
        self._services = []
        # diagnostics once a second on a steady clock (also when /clock stalls)
        self.diag = Diagnostics(node, "controller", self.vehicle.name, self.diagnostics, log)
        self._services = trigger_services(node, {"rearm": self._on_rearm,
                                                 "reset": self._on_reset}, log)
        self.configured = True

    def _activate(self) -> None:
        self._odom = self._joints = None  # only states received from now on are answered
        self._unanswered = None
        self.active = True

    def _deactivate(self) -> None:
        """Stop commanding; one last command stops the wheels and holds the steering where
        it is measured (a ros2_control forward command controller holds the last command
        it got: left alone it would keep the wheels running)."""
        if self.active and self._last_t is not None and self._delta is not None:
            self._publish_cmd(self._delta, np.zeros(self.nw))
            self._last_cmd = (self._last_t, self._delta, np.zeros(self.nw))
            # delivered before the publishers go (cleanup, shutdown, a signal): a reliable
            # writer destroyed at once may drop what its readers have not acknowledged
            from rclpy.duration import Duration

            for pub in (self.pub_steer, self.pub_wheel):
                if not pub.wait_for_all_acked(Duration(seconds=STOP_ACK_S)):
                    log.warning("the stop command was not acknowledged within %g s",
                                STOP_ACK_S)
        self.active = False

    def _cleanup(self) -> None:
        """Back to unconfigured: the topics, services, timers and the MPC taken down."""
        if self.active:
            self._deactivate()
        if not self.configured:
            return
        destroy(self.ctx.node, self._timers, self._subs, self._services,
                (self.pub_steer, self.pub_wheel, self.pub_pred, self.pub_wear))
        self.diag.destroy()
        self._timers, self._subs, self._services = [], [], []
        self._estimates = self.estimates()  # (the summary keeps them past a cleanup)
        self.mpc = self.low = None
        self.configured = False

    def _shutdown(self) -> None:
        self._cleanup()
        self._ended = True
        self.stop.set()

    @staticmethod
    def _max_missed(cfg: RosControllerConfig) -> int:
        return int(math.floor(cfg.stale_ms / 1000 / cfg.period + 1e-9))

    # ---- parameters at run time -----------------------------------------------------------
    def _on_set_parameters(self, params):
        """Every change of the parameters (``ros2 param set``, the SetParameters service):
        checked all together and applied all together, or refused with the reason.
        Unconfigured, any parameter (taken at the next configure); configured, those of
        :data:`RUNTIME`: weights rebuild the MPC at once (the annealer's and the
        feed-forward's; the disturbance estimate starts again), the plan's limits time the
        next plan afresh (also a replan of the same route), the other limits apply from the
        next period."""
        try:
            new, changed = parameter_changes(PARAMETERS, self.params, params, self.configured)
            if self.configured and changed:
                self._apply(new, changed)
            elif changed:
                self._config_from(new)  # a value out of range is refused now, not at configure
        except Exception as e:  # noqa: BLE001 - refused with its reason, nothing changed
            reason = str(e).removeprefix("ROS parameter ")
            self.stats["parameters_refused"] += 1
            log.warning("parameter change refused: %s", reason)
            return set_parameters_result(False, reason)
        if changed:
            self.stats["parameter_changes"] += 1
            log.info("parameters changed: %s", ", ".join(f"{k}={new[k]}" for k in changed))
        self.params = new
        return set_parameters_result(True)

    def _apply(self, new: dict, changed: list) -> None:
        """Apply a change while configured (see :meth:`_on_set_parameters`), or raise
        before anything changed."""
        fixed = [k for k in changed if k not in RUNTIME]
        if fixed:
            raise ValueError(f"{fixed[0]}: changes the optimiser's structure; set it while "
                             f"the node is unconfigured (lifecycle cleanup, then configure)")
        cfg = self._config_from(new)
        mpc, low = self.mpc, self.low
        weights = [k for k in changed if k in WEIGHTS]
        if weights:
            if new["solver"] not in REBUILT:
                raise ValueError(f"{weights[0]}: the {new['solver']} solver builds the "
                                 f"weights into its problem at configure; set it while the "
                                 f"node is unconfigured (lifecycle cleanup, then configure)")
            mpc = self.make_mpc(new)
        if weights or "low_speed_kmh" in changed:
            low = self._low_speed_mpc(new, cfg)
        # nothing raised: apply
        if mpc is not self.mpc or low is not self.low:
            self.mpc, self.low = mpc, low
            if self.reference is not None:
                for c in self._controllers():
                    c.set_reference(self.reference)
        self.cfg = cfg
        self.watch.max_missed = self._max_missed(cfg)
        self.watch.resume_periods = cfg.resume_periods
        if any(k in PLAN for k in changed):
            self._retime = True

    # ---- services --------------------------------------------------------------------------
    def _on_rearm(self, request, response):
        """``~/rearm`` (std_srvs/Trigger): leave the safe behaviour now, without waiting
        ``resume_periods`` periods, when the inputs are fresh and there is a plan; refused
        with the reason otherwise."""
        why = None
        if not self.active:
            why = "not active"
        elif not self._safe:
            why = "not in the safe behaviour"
        elif self.reference is None:
            why = "no plan"
        elif self._fresh_tick is None or self._tick - self._fresh_tick > self.watch.max_missed:
            why = "the odometry and joint states are stale"
        if why is not None:
            response.success, response.message = False, f"rearm refused: {why}"
            return response
        self.watch = CommandWatch(self.watch.max_missed, self.watch.resume_periods,
                                  self.cfg.period)
        self._safe = False
        self.stats["rearms"] += 1
        log.warning("re-armed: commanding")
        self.rec.event("safe", on=False, why="rearm")
        response.success, response.message = True, "re-armed: commanding"
        self._answer_unanswered()
        return response

    def _answer_unanswered(self) -> None:
        """Leaving the safe behaviour: the newest state, if it came after the last hold, is
        answered now, not at the next state, which a simulator in lockstep sends only once
        this one is answered (it waited out the staleness bound, then went safe again,
        every time)."""
        held, self._unanswered = self._unanswered, None
        if held is not None and self.reference is not None:
            self._answer(*held)

    def _on_reset(self, request, response):
        """``~/reset`` (std_srvs/Trigger): forget the run - the MPC's warm start, its
        disturbance estimate and adapted tires, the wear estimate, a goal reached, the
        plan (the vehicle then stops as without a plan; a ``--case`` reference starts
        again from the next state)."""
        if not self.configured:
            response.success, response.message = False, "reset refused: not configured"
            return response
        for c in self._controllers():
            c.reset()
        self.wear.reset()
        self._goal_held = None
        self._plan_msg = None
        self.reference = None
        self._restart = True  # the next state starts a new run; meanwhile, no plan: the
        self.stats["resets"] += 1  # timer's safe behaviour ramps the wheels down
        self._unanswered = None  # a state of the run forgotten
        log.warning("reset: the run is forgotten; waiting for a plan")
        self.rec.event("reset")
        response.success, response.message = True, "reset: waiting for a plan"
        return response

    def _warm_extras(self) -> None:
        """Compile what runs with each command beside the MPC (whose ``warmup`` compiles
        its horizon's rollout), before any topic is declared: the tire model of the wear
        estimate (compiled at the first state, it held that state's successor for
        seconds) and the CDR encoders of every message an answer publishes (the typestore's
        serializers are generated at their first use: 0.2-0.8 s on a loaded 2-core machine
        at the first state, while a free-running simulator at 0.4x real time sent 8-32
        states more, the oldest of them dropped from the keep-last-10 queue unanswered)."""
        st = {"t": 0.0, "x": 0.0, "y": 0.0, "phi": 0.0, "vx": 1.0, "vy": 0.0, "r": 0.0,
              "delta": [0.0] * self.nw, "omega_w": [0.0] * self.nw}
        p, work = self.wear.update(st, [1.0] * self.nw, [0.0] * self.nw)
        self.wear.reset()
        zeros = np.zeros(self.nw)
        for topic in (R.STEERING_COMMANDS, R.WHEEL_COMMANDS):
            R.encode(R.float_array(zeros), R.TYPES[topic])
        R.encode(R.predicted_path(0.0, self.cfg.period, np.zeros((2, 3))),
                 R.TYPES[R.PREDICTED_PATH])
        R.encode(self._wear_msg(p, work), R.TYPES[R.WEAR])

    # ---- inputs ------------------------------------------------------------------------
    def _now(self) -> float:
        """The node's time [s]: ROS time under use_sim_time, else a steady wall clock."""
        if self._clock is not None:
            return self._clock.now().nanoseconds * 1e-9
        return time.perf_counter()

    def _on_odom(self, msg) -> None:
        if not self.active:
            return  # inactive: states are not kept (one kept would be answered late)
        self._odom, self._odom_rx = msg, self._now()
        self._try()

    def _on_odom_matched(self, info) -> None:
        """The odometry's last publisher gone (a plant's cleanup or its end): the next state
        starts a new run, also at the stamp of the last one answered - a plant whose
        answer was lost with its command topics sends its state 0 again at t = 0, which
        would otherwise be a repeat, never answered. No answer of ours can be in flight
        to the old run: the topics it went on are gone with the plant."""
        if info.current_count == 0 and self._last_t is not None and not self._odom_lost:
            self._restart = self._odom_lost = True
            log.info("odometry: no publisher left; the next state starts a new run")

    def _on_joints(self, msg) -> None:
        if not self.active:
            return
        self._joints = msg
        self._try()

    def _on_plan(self, msg) -> None:
        self._plan_msg = msg  # taken at the next state (its time is the plan's start)
        self.stats["plans"] += 1

    def _try(self, force: bool = False) -> None:
        o, j = self._odom, self._joints
        if o is None or j is None or not self.active:
            return
        to = R.stamp_seconds(o.header.stamp)
        if self._last_t is not None and to == self._last_t and not self._odom_lost:
            self._odom = None  # the same state again: answered once (a command names no
            self.stats["repeated"] += 1  # state, so a second answer would answer the next)
            return
        if not force and R.stamp_seconds(j.header.stamp) < to:
            return  # the joint states of this period are on their way
        self._odom = None
        self._odom_lost = False
        self._odom_frame = o.header.frame_id
        try:
            st = R.state_from_ros(o, j, self.nw)
        except R.RosMessageError as e:
            self.rej.add(M.MessageError(M.BAD_VALUE, str(e)), R.ODOM)
            self.stats["rejected"] += 1
            return
        self._solve(st, self._odom_rx)

    def _take_plan(self, st: dict) -> None:
        msg, self._plan_msg = self._plan_msg, None
        if len(msg.poses) == 0:
            log.warning("an empty plan: stopping (the safe behaviour) until a plan comes")
            self.reference = None
            self._goal_held = None
            return
        c = self.cfg
        frame = msg.header.frame_id
        odom = self._odom_frame or R.FRAME_ODOM  # (odometry naming no frame: odom)
        if frame and frame not in (odom, c.plan_frame):
            # nothing here transforms (no tf2): a plan in map taken as odom would drive the
            # vehicle to wherever map's coordinates fall in odom
            self.stats["plans_wrong_frame"] += 1
            if frame not in self._told_frames:  # once per frame (Nav2 replans at 1-20 Hz)
                self._told_frames.add(frame)
                also = f" or plan_frame '{c.plan_frame}'" if c.plan_frame else ""
                log.warning("plan: in frame '%s', not the odometry's '%s'%s: refused (this node "
                            "does not transform plans: publish it in '%s', or set "
                            "plan_frame:=%s where the two frames coincide); counted "
                            "plans_wrong_frame", frame, odom, also, odom, frame)
            return
        arrays = R.path_arrays(msg)
        if self._goal_held is not None and self._same_goal(
                (arrays[1][-1], arrays[2][-1], arrays[3][-1]), self._goal_held):
            self.stats["plans_at_goal"] += 1  # replanning to the goal it stands at: it stays
            return
        cur = self.reference
        if (cur is not None and cur.name == "plan" and self._goal_held is None
                and not self._retime
                and self._same_goal((arrays[1][-1], arrays[2][-1], arrays[3][-1]),
                                    (cur.x[-1], cur.y[-1], cur.phi[-1]))
                and off_path(arrays[1], arrays[2], cur.x, cur.y) <= REPLAN_SAME):
            # Nav2 replanning (1-20 Hz) the route being driven: the reference goes on as it
            # is timed, no restart of the profile, no jump
            self.stats["plans_same_route"] += 1
            return
        prof = SpeedProfile(c.plan_speed_kmh / 3.6, c.plan_accel, c.plan_decel,
                            c.plan_lat_accel, v0=plan_start_speed(st, self.reference))
        try:
            ref, how = plan_reference(*arrays, st["t"], prof)
        except ValueError as e:
            self.rej.add(M.MessageError(M.BAD_VALUE, f"plan: {e}"), R.PLAN)
            return
        self._goal_held = None
        self._retime = False
        if how.startswith("its arc") and not self._told_arc:
            log.warning("plan: the pose stamps do not increase (Nav2's planners leave them "
                        "zero): timing the path along %s", how)
            self._told_arc = True
        self._set_reference(ref)
        log.info("new plan: %d poses, %.1f m, t %.2f..%.2f s (timed by %s)", len(msg.poses),
                 float(np.hypot(np.diff(ref.x), np.diff(ref.y)).sum()), ref.t[0], ref.t[-1], how)

    # ---- the solve ---------------------------------------------------------------------
    def _solve(self, st: dict, rx_perf: float) -> None:
        t = st["t"]
        if self._last_t is None or t < self._last_t or self._restart:  # a new run
            self._restart = False
            self.run_core.new_run(t=t)
            self.wear.reset()
            self._goal_held = None
            self._seq = 0
            if self.base_reference is not None:
                self._set_reference(shifted(self.base_reference, t))
        self._last_t = t
        self._delta = np.asarray(st["delta"], dtype=float)
        self._fresh_tick = self._tick
        self._fresh_rx = rx_perf
        if self._plan_msg is not None:
            self._take_plan(st)
        seq = self._seq
        self._seq += 1
        self.rec.message("rx", self.key_state, M.encode_state(seq, st))
        if self.reference is None:
            self.stats["no_reference"] += 1
            return
        if self._safe:
            # the timer decides when the inputs are fresh again; its next hold answers this
            # state, or, resuming, the solve does (a simulator in lockstep waits for it)
            self._unanswered = (st, rx_perf, seq)
            return
        self._answer(st, rx_perf, seq)

    def _answer(self, st: dict, rx_perf: float, seq: int) -> None:
        """Command the state ``st`` (its sequence number ``seq``): the goal's hold, or the
        controller's solve."""
        t = st["t"]
        if self._at_goal(st):
            return
        ctl = self._controller_for(st)
        cmd = self.run_core.solve(ctl, st, self.reference)
        if self.run_core.too_old(rx_perf):
            return
        tgt = R.steering_targets(st["delta"], cmd.omega_s, self.cfg.period, self.vehicle.limits)
        w = np.asarray(cmd.omega_w, dtype=float)
        self._publish_cmd(tgt, w)
        self._last_cmd = (t, tgt, w)
        # after the commands: the horizon (recorded there) and the wear, not on their path
        poses = self.run_core.sent(ctl, st, self.key_cmd, self.run_core.encode(st, seq, cmd),
                                   poses=True)
        if poses is not None:
            self.pub_pred.publish(R.encode(R.predicted_path(t, ctl.settings.dt, poses),
                                           R.TYPES[R.PREDICTED_PATH]))
        p, work = self.wear.update(st, cmd.omega_w, cmd.omega_s)
        self.pub_wear.publish(R.encode(self._wear_msg(p, work), R.TYPES[R.WEAR]))

    def _controllers(self) -> list:
        return [c for c in (self.mpc, self.low) if c is not None]

    def _set_reference(self, ref: Reference) -> None:
        self.reference = ref
        for c in self._controllers():
            c.set_reference(ref)

    def _controller_for(self, st: dict):
        """The solver's MPC, or below ``low_speed_kmh`` - the vehicle's speed and the
        reference's both - the policy's plain feed-forward (``--solver ff``). At walking
        pace the MPC's prediction misjudges the wear it minimises: it charges each
        prediction step's slip wear at the step's first instant, held over its dt (0.1 s),
        while at low speed the tires take up a wheel-speed change within milliseconds
        (their relaxation time m v / (2n C)); so it scores the feed-forward's speeding up
        from rest as dear and picks wheel speeds that fight each other, which the plant
        wears for real (docs/ROS2.md, "What the profile costs in wear")."""
        if self.low is None:
            return self.mpc
        lim = self.cfg.low_speed_kmh / 3.6
        if math.hypot(st["vx"], st["vy"]) >= lim:
            return self.mpc
        r = self.reference.sample([st["t"]])[0]
        if math.hypot(r[3], r[4]) >= lim:
            return self.mpc
        self.stats["low_speed"] += 1
        return self.low

    def _same_goal(self, a, b) -> bool:
        """Two goals (x, y, phi) within the goal tolerances of each other."""
        yaw = abs((a[2] - b[2] + math.pi) % (2 * math.pi) - math.pi)
        return (math.hypot(a[0] - b[0], a[1] - b[1]) <= self.cfg.goal_tolerance
                and math.degrees(yaw) <= self.cfg.goal_yaw_tolerance_deg)

    def _at_goal(self, st: dict) -> bool:
        """A goal reached stays reached. When the plan has ended (its time is up, its
        reference holds the goal) and the vehicle is at the goal or past it along the
        path's last direction (within ``goal_tolerance``), the node stops commanding the
        MPC - whose answers at a standstill reference are a random walk of steering and a
        creep forward - and brings the vehicle to rest: the wheels ramped down at
        ``plan_decel`` at the rim, the steering held at the angles it had. It stays so
        until a plan to another goal comes. A vehicle still short of the goal is left to
        the MPC. True when holding."""
        ref = self.reference
        if self._goal_held is None:
            if ref.after_end != "hold" or st["t"] < ref.t[-1]:
                return False
            gx, gy, gphi = float(ref.x[-1]), float(ref.y[-1]), float(ref.phi[-1])
            ux, uy = gx - float(ref.x[-2]), gy - float(ref.y[-2])
            n = math.hypot(ux, uy)
            short = ((gx - st["x"]) * ux + (gy - st["y"]) * uy) / n if n > 0 else 0.0
            if short > self.cfg.goal_tolerance:
                return False
            self._goal_held = (gx, gy, gphi)
            self._hold = (np.asarray(st["delta"], dtype=float),
                          np.asarray(self._last_cmd[2] if self._last_cmd is not None
                                     else st["omega_w"], dtype=float))
            self.stats["goals_reached"] += 1
            dist = math.hypot(st["x"] - gx, st["y"] - gy)
            yaw = math.degrees(abs((st["phi"] - gphi + math.pi) % (2 * math.pi) - math.pi))
            self.goal_errors.append((dist, yaw))
            log.info("goal reached: %.3f m and %.2f deg from it; stopping and holding until "
                     "a plan to another goal", dist, yaw)
            self.rec.event("goal_reached", x=gx, y=gy, phi=gphi, distance=dist,
                           yaw_deg=yaw)
        tgt, w = self._hold
        w = np.maximum(w - self.cfg.plan_decel / self.vehicle.wheel_radius * self.cfg.period,
                       0.0)
        self._hold = (tgt, w)
        self._publish_cmd(tgt, w)
        self._last_cmd = (st["t"], tgt, w)
        self.stats["held_at_goal"] += 1
        return True

    def _wear_msg(self, p, work):
        m = R.float_array(np.r_[p, work])
        m.layout.dim = [R.new("std_msgs/msg/MultiArrayDimension", label="|".join(R.WEAR_ROWS),
                              size=2, stride=2 * self.nw),
                        R.new("std_msgs/msg/MultiArrayDimension",
                              label="|".join(R.wheel_names(self.nw)), size=self.nw,
                              stride=self.nw)]
        return m

    def _publish_cmd(self, targets, wheels) -> None:
        self.pub_steer.publish(R.encode(R.float_array(targets), R.TYPES[R.STEERING_COMMANDS]))
        self.pub_wheel.publish(R.encode(R.float_array(wheels), R.TYPES[R.WHEEL_COMMANDS]))

    # ---- the timer: stale inputs -------------------------------------------------------
    def _on_tick(self) -> None:
        if not self.active:
            return
        self._tick += 1
        if self._odom is not None and self._now() - self._odom_rx > self.cfg.period / 2:
            self._try(force=True)  # joint states stamped differently: the newest ones
        if self._last_t is None:
            return  # nothing received yet: nothing to hold
        no_ref = self.reference is None
        d = self.watch.step(self._tick, None if no_ref else self._fresh_tick, True)
        if d.resumed and self._safe:
            self._safe = False
            self.stats["resumes"] += 1
            log.warning("inputs fresh again: commanding")
            self.rec.event("safe", on=False)
            self._answer_unanswered()
        if d.state != SAFE:
            return
        if d.entered_safe is not None and not self._safe:
            self._safe = True
            self.stats["safe_events"] += 1
            age = self._tick - (self._fresh_tick or 0)
            why = ("no plan" if no_ref else
                   f"no fresh odometry and joint states for {age} periods "
                   f"({age * self.cfg.period * 1000:.0f} ms; bound {self.watch.max_missed})")
            log.warning("SAFE: %s; holding the steering, ramping the wheels down at %g m/s^2",
                        why, self.cfg.safe_decel)
            self.rec.event("safe", on=True, why=why)
            self._safe_why = why
        self.stats["safe_periods"] += 1
        held = self._last_cmd[2] if self._last_cmd is not None else np.zeros(self.nw)
        w = np.maximum(held - self.cfg.safe_decel / self.vehicle.wheel_radius
                       * self.cfg.period, 0.0)
        tgt = self._delta if self._delta is not None else np.zeros(self.nw)
        self._last_cmd = (self._last_t, tgt, w)
        self._publish_cmd(tgt, w)
        self._unanswered = None  # the hold answers the newest state

    # ---- running -------------------------------------------------------------------------
    def run(self) -> dict:
        log.info("ROS 2 controller ready: %s", ", ".join(
            f"{k}={v}" for k, v in self.params.items() if k in ("method", "model", "solver")))
        while not self.stop.is_set():
            self.ctx.spin_once(0.05)
        return self.summary()

    def close(self) -> None:
        """Shut the node down (the lifecycle's shutdown: an active node sends its stop
        first), then its context."""
        try:
            if not self._ended:
                self.ctx.node.trigger_shutdown()
        finally:
            try:
                if self.configured:  # the transition failed: taken down all the same
                    self._cleanup()
            finally:
                self.ctx.close()

    def state_label(self) -> str:
        """The lifecycle state: unconfigured, inactive, active or finalized."""
        return Lifecycle.label(self.configured, self.active, self._ended)

    # ---- diagnostics ---------------------------------------------------------------------
    def diagnostics(self) -> tuple[int, str, dict]:
        """``(level, message, values)`` of the node's diagnostic status now (see
        docs/ROS2.md, "Diagnostics"): level 0 OK, 1 WARN, 3 STALE; values as strings."""
        cfg = self.cfg
        solves = self.run_core.counts.solve_ms
        new = np.asarray(solves[self._diag_from:], dtype=float)
        self._diag_from = len(solves)
        age = None if self._fresh_rx is None else (self._now() - self._fresh_rx) * 1000
        v = {"lifecycle": self.state_label(), "safe": str(self._safe).lower(),
             "safe_reason": self._safe_why if self._safe else "",
             "input_age_ms": "none" if age is None else f"{age:.1f}",
             "stale_ms": f"{cfg.stale_ms:g}", "solves": str(new.size),
             "solve_ms_p50": f"{np.percentile(new, 50):.3f}" if new.size else "none",
             "solve_ms_max": f"{new.max():.3f}" if new.size else "none",
             "period_ms": f"{cfg.period * 1000:g}",
             "reference": "none" if self.reference is None else self.reference.name,
             "goal": "reached" if self._goal_held is not None else "",
             "answered": str(self.run_core.counts.answered),
             "low_speed": str(self.stats["low_speed"]),
             "safe_events": str(self.stats["safe_events"]),
             "rejected": str(self.stats["rejected"])}
        dist = self.mpc.disturbance() if self.mpc is not None else None
        for k in ("d_u", "d_v", "d_r"):
            v[f"disturbance_{k}"] = "off" if dist is None else f"{dist[k]:.6g}"
        tires = self.mpc.adapted_tires() if self.mpc is not None else None
        v["adapt"] = "off" if tires is None else "on"
        flat = {}
        for k, x in (tires or {}).items():
            if k == "noise_switch":  # (None until it switched: the same keys, empty)
                flat.update({f"{k}_{kk}": (x or {}).get(kk) for kk in SWITCH_KEYS})
            else:
                flat[k] = x
        for k, x in flat.items():
            v[f"tires_{k}"] = (f"{x:.6g}" if isinstance(x, float) else
                               "" if x is None else str(x))
        if not self.active:
            return WARN, self.state_label(), v
        if self._safe:
            stale = self._fresh_tick is None or \
                self._tick - self._fresh_tick > self.watch.max_missed
            return (STALE if stale else WARN), f"safe: {self._safe_why}", v
        if self.reference is None:
            return WARN, "waiting for a plan", v
        if new.size and new.max() > cfg.period * 1000:
            return WARN, f"a solve took {new.max():.1f} ms, over the period", v
        return OK, "goal reached" if self._goal_held is not None else "commanding", v

    def summary(self) -> dict:
        c = self.run_core.counts
        return {"role": "ros2 controller", "answered": c.answered, **self.stats,
                "new_runs": c.new_runs, "dropped_stale": c.dropped_stale,
                "solve_ms": percentiles_ms(np.asarray(c.solve_ms) / 1000.0),
                "rejected_by_reason": self.rej.summary(),
                "goal_errors": [{"distance_m": d, "yaw_deg": y} for d, y in self.goal_errors],
                "parameters": self.params, "safe": self._safe,
                "lifecycle": self.state_label(),
                "transitions": self.lifecycle.summary(),
                **self.estimates()}

    def estimates(self) -> dict:
        """The offset-free disturbance and the adapted tires (None: off), as ``msagv
        controller``'s summary has them: the MPC's now, or the last MPC's after a
        cleanup."""
        if self.mpc is None:
            return dict(self._estimates)
        return {k: mpc_estimate(self.mpc, k) for k in ("disturbance", "adapted_tires")}
