"""A run as standard ROS 2 messages: the one mapping between the project's state, commands,
wear, reference and prediction and the ROS 2 messages of docs/ROS2.md, and their CDR
encoding.

Messages are built as the types of rosbags' typestore (the ROS 2 Kilted definitions,
:func:`typestore`) and serialised to CDR by it (:func:`encode`), so a recording needs no
ROS 2 installation; the ROS 2 nodes (:mod:`msagv.ros2`) publish the same bytes with rclpy,
and a test pins the bytes to ``rclpy.serialization``. A rosbags message and an rclpy message
have the same field names, so :func:`state_from_ros` reads either.

Conventions (docs/ROS2.md): frames ``odom`` (the world frame G of the state) and
``base_link`` (the body frame B); wheels in the project's order 11, 12, 21, 22, ... (i the
axle from the front, j 1 left, 2 right), joints ``steer_ij`` (steering angle delta_ij
[rad]) and ``wheel_ij`` (wheel angular speed omega_w_ij [rad/s]); stamps are the run's
vehicle time t (ROS simulated time, published on ``clock``). Field names come from
:mod:`msagv.plant.signals`, never retyped.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Mapping, Sequence

import numpy as np

from msagv.plant.signals import (BODY_FIELDS, CONTROL_PERIOD, WEAR_POWER_FIELDS,
                                 WHEEL_WEAR_FIELDS, wheel_suffixes)

FRAME_ODOM = "odom"
FRAME_BASE = "base_link"

# topic -> message type (relative names: a node's namespace and remapping apply; a
# recording stores them absolute, '/' + name)
ODOM = "odom"
JOINT_STATES = "joint_states"
TF = "tf"
WEAR = "wear"
# the controller's wear estimate (the plant's tire model at the observed state under the
# command sent): same type and layout as WEAR, its own topic so the two are never mixed;
# published by `msagv ros2 controller` only, not a recording's channel
WEAR_ESTIMATE = "wear_estimate"
MARKERS = "markers"
PLAN = "plan"
PREDICTED_PATH = "predicted_path"
STEERING_COMMANDS = "steering_controller/commands"
WHEEL_COMMANDS = "wheel_controller/commands"
CLOCK = "clock"
TYPES = {
    ODOM: "nav_msgs/msg/Odometry",
    JOINT_STATES: "sensor_msgs/msg/JointState",
    TF: "tf2_msgs/msg/TFMessage",
    WEAR: "std_msgs/msg/Float64MultiArray",
    MARKERS: "visualization_msgs/msg/MarkerArray",
    PLAN: "nav_msgs/msg/Path",
    PREDICTED_PATH: "nav_msgs/msg/Path",
    STEERING_COMMANDS: "std_msgs/msg/Float64MultiArray",
    WHEEL_COMMANDS: "std_msgs/msg/Float64MultiArray",
    CLOCK: "rosgraph_msgs/msg/Clock",
}
# the wear topic's rows (layout.dim[0]); its columns (dim[1]) are the wheels in order
WEAR_ROWS = ("P_tw", "W_tw")  # wear power [W] (mean over the last period), work [J]

MARKER_EVERY = 10  # the markers of every tenth state (10 Hz at T = 10 ms; tf moves them at
# every state, as they are drawn in base_link)
BODY_COLOR = (125 / 255, 45 / 255, 200 / 255, 0.8)  # as the Rerun view's body
PATH_COLOR = (0.35, 0.35, 0.35, 1.0)
COOL, HOT = np.array([60, 180, 75]) / 255, np.array([220, 30, 40]) / 255


class RosMessageError(ValueError):
    """A ROS message that cannot be turned into the project's state or commands (the
    message says which field and why)."""


# ---- the typestore and CDR ------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def typestore():
    """rosbags' typestore of ROS 2 Kilted (the registry's rclpy wheels are Kilted)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_KILTED)


@functools.lru_cache(maxsize=None)
def msgdef(typename: str) -> str:
    """The ``ros2msg`` definition of ``typename`` with its dependencies (the schema text of
    rosbag2's MCAP storage and of Foxglove's ``ros2msg`` channels)."""
    text, _ = typestore().generate_msgdef(typename, ros_version=2)
    return text


@functools.lru_cache(maxsize=None)
def type_hash(typename: str) -> str:
    """The type's RIHS01 hash (rosbag2's ``type_description_hash``)."""
    return typestore().hash_rihs01(typename)


def encode(msg, typename: str | None = None) -> bytes:
    """CDR (little endian, with the encapsulation header) of a typestore message."""
    return bytes(typestore().serialize_cdr(msg, typename or msg.__msgtype__))


def decode(data: bytes, typename: str):
    """A typestore message from its CDR bytes."""
    return typestore().deserialize_cdr(bytes(data), typename)


_PRIMITIVE = {"float64": np.float64, "float32": np.float32, "int8": np.int8, "uint8": np.uint8,
              "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
              "int64": np.int64, "uint64": np.uint64, "byte": np.uint8, "char": np.uint8}


def _default(node) -> Any:
    kind, what = node
    kind = int(kind)
    if kind == 1:  # BASE
        name = what[0]
        return "" if name in ("string", "wstring") else False if name == "bool" else \
            0.0 if name.startswith("float") else 0
    if kind == 2:  # NAME: a nested message
        return new(what)
    sub, n = what
    if kind == 3:  # ARRAY of n
        if int(sub[0]) == 1 and sub[1][0] in _PRIMITIVE:
            return np.zeros(n, dtype=_PRIMITIVE[sub[1][0]])
        return [_default(sub) for _ in range(n)]
    if int(sub[0]) == 1 and sub[1][0] in _PRIMITIVE:  # SEQUENCE
        return np.zeros(0, dtype=_PRIMITIVE[sub[1][0]])
    return []


@functools.lru_cache(maxsize=None)
def _layout(typename: str):
    """Per field of ``typename``: (name, numpy dtype of a primitive array or None, node)."""
    _, defs = typestore().fielddefs[typename]
    out = []
    for name, node in defs:
        dt = None
        if int(node[0]) in (3, 4) and int(node[1][0][0]) == 1 and node[1][0][1][0] in _PRIMITIVE:
            dt = _PRIMITIVE[node[1][0][1][0]]
        out.append((name, dt, node))
    return tuple(out), typestore().types[typename]


def new(typename: str, **fields):
    """A typestore message of ``typename``: the given fields, every other one zero/empty
    (as a freshly constructed ROS 2 message)."""
    layout, cls = _layout(typename)
    kw = {}
    for name, dt, node in layout:
        if name in fields:
            v = fields.pop(name)
            kw[name] = v if dt is None else np.asarray(v, dtype=dt)
        else:
            kw[name] = _default(node)
    if fields:
        raise TypeError(f"{typename} has no field(s) {', '.join(sorted(fields))}")
    return cls(**kw)


# ---- conventions -------------------------------------------------------------------------------
def wheel_names(n_wheels: int) -> list[str]:
    """``['11', '12', '21', ...]``: the wheel order (:func:`plant.signals.wheel_suffixes`)."""
    return wheel_suffixes(n_wheels)


def steer_joints(n_wheels: int) -> list[str]:
    return [f"steer_{w}" for w in wheel_names(n_wheels)]


def wheel_joints(n_wheels: int) -> list[str]:
    return [f"wheel_{w}" for w in wheel_names(n_wheels)]


def time_msg(t: float):
    """builtin_interfaces/Time of ``t`` seconds (t >= 0; nanoseconds rounded)."""
    ns = int(round(float(t) * 1e9))
    return new("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000,
               nanosec=ns % 1_000_000_000)


def stamp_seconds(stamp) -> float:
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def yaw_quaternion(phi: float):
    return new("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(phi / 2),
               w=math.cos(phi / 2))


def quaternion_yaw(q) -> float:
    """The yaw of a quaternion (rotation about z; roll and pitch are ignored)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def body_twist(phi: float, vx: float, vy: float) -> tuple[float, float]:
    """The state's global-frame velocity (vx, vy in G, DESIGN.md) in base_link (REP-105)."""
    c, s = math.cos(phi), math.sin(phi)
    return c * vx + s * vy, -s * vx + c * vy


def global_velocity(phi: float, u: float, v: float) -> tuple[float, float]:
    """The inverse of :func:`body_twist`."""
    c, s = math.cos(phi), math.sin(phi)
    return c * u - s * v, s * u + c * v


def steering_targets(delta, omega_s, period: float, limits=None) -> np.ndarray:
    """Steering angle targets [rad] from steering rates: the angle the plant reaches after
    one period holding ``omega_s`` from ``delta`` (``delta + omega_s T``, inside the
    vehicle's angle limits when ``limits`` is given)."""
    tgt = np.asarray(delta, dtype=float) + np.asarray(omega_s, dtype=float) * period
    if limits is not None:
        tgt = np.clip(tgt, limits.delta_min, limits.delta_max)
    return tgt


def steering_rates(delta, targets, period: float, limits=None) -> np.ndarray:
    """The inverse of :func:`steering_targets`: the rate that reaches ``targets`` from
    ``delta`` in one period (inside the rate limits when ``limits`` is given)."""
    rate = (np.asarray(targets, dtype=float) - np.asarray(delta, dtype=float)) / period
    if limits is not None:
        rate = np.clip(rate, limits.omega_s_min, limits.omega_s_max)
    return rate


def header(t: float, frame: str):
    return new("std_msgs/msg/Header", stamp=time_msg(t), frame_id=frame)


def float_array(values, label: str = "joint"):
    v = np.asarray(values, dtype=float).reshape(-1)
    dim = new("std_msgs/msg/MultiArrayDimension", label=label, size=v.size, stride=v.size)
    return new("std_msgs/msg/Float64MultiArray",
               layout=new("std_msgs/msg/MultiArrayLayout", dim=[dim], data_offset=0), data=v)


def path_msg(t, x, y, phi, frame: str = FRAME_ODOM, stamp: float | None = None):
    """nav_msgs/Path of poses (x, y, phi) at times ``t`` (each pose stamped with its time)."""
    t = np.asarray(t, dtype=float)
    poses = [new("geometry_msgs/msg/PoseStamped", header=header(ti, frame),
                 pose=new("geometry_msgs/msg/Pose",
                          position=new("geometry_msgs/msg/Point", x=float(xi), y=float(yi), z=0.0),
                          orientation=yaw_quaternion(float(pi))))
             for ti, xi, yi, pi in zip(t, x, y, phi)]
    return new("nav_msgs/msg/Path", header=header(float(t[0]) if stamp is None and t.size
                                                  else (stamp or 0.0), frame), poses=poses)


def path_arrays(msg) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(t, x, y, phi)`` of a nav_msgs/Path (t: each pose's stamp)."""
    n = len(msg.poses)
    t, x, y, phi = (np.empty(n) for _ in range(4))
    for i, p in enumerate(msg.poses):
        t[i] = stamp_seconds(p.header.stamp)
        x[i] = p.pose.position.x
        y[i] = p.pose.position.y
        phi[i] = quaternion_yaw(p.pose.orientation)
    return t, x, y, phi


# ---- the inverse: ROS messages -> the state of the controller --------------------------------
def state_from_ros(odom, joints, n_wheels: int, t: float | None = None) -> dict:
    """The state message fields (``t, x, y, phi, vx, vy, r, delta, omega_w``) from a
    nav_msgs/Odometry (pose in odom, twist in base_link: REP-105) and a
    sensor_msgs/JointState with positions of ``steer_ij`` and velocities of ``wheel_ij``
    (other joints are ignored). ``t``: the state's time (default: the odometry's stamp).
    Raises :class:`RosMessageError` naming a missing joint or a non-finite value."""
    p = odom.pose.pose
    phi = quaternion_yaw(p.orientation)
    tw = odom.twist.twist
    vx, vy = global_velocity(phi, tw.linear.x, tw.linear.y)
    names = list(joints.name)
    index = {n: i for i, n in enumerate(names)}
    pos, vel = list(joints.position), list(joints.velocity)
    delta, omega = [], []
    for s, w in zip(steer_joints(n_wheels), wheel_joints(n_wheels)):
        i, k = index.get(s), index.get(w)
        if i is None or i >= len(pos):
            raise RosMessageError(f"joint_states: no position of joint {s}")
        if k is None or k >= len(vel):
            raise RosMessageError(f"joint_states: no velocity of joint {w}")
        delta.append(float(pos[i]))
        omega.append(max(float(vel[k]), 0.0))
    st = {"t": stamp_seconds(odom.header.stamp) if t is None else float(t),
          "x": float(p.position.x), "y": float(p.position.y), "phi": phi, "vx": vx, "vy": vy,
          "r": float(tw.angular.z), "delta": delta, "omega_w": omega}
    bad = [k for k in ("t",) + BODY_FIELDS if not math.isfinite(st[k])]
    if bad or not all(math.isfinite(v) for v in delta + omega):
        raise RosMessageError(f"odom/joint_states: non-finite value(s) "
                              f"{', '.join(bad) or 'in the joints'}")
    return st


# ---- the state -> ROS messages ----------------------------------------------------------------
def wheel_colour(p_w: float, scale_w: float) -> tuple[float, float, float]:
    """Green at no wear power, red at ``scale_w`` and above."""
    a = 0.0 if not scale_w > 0 else min(max(p_w / scale_w, 0.0), 1.0)
    c = (1 - a) * COOL + a * HOT
    return float(c[0]), float(c[1]), float(c[2])


class RunMessages:
    """The ROS 2 messages of one run's states (see the module docstring), with the little
    state they need: the wheels' integrated angles (JointState positions of ``wheel_ij``),
    the previous per-wheel wear work (for the wear power) and the peak wear power (the
    wheels' colour scale). ``vehicle``: a :class:`plant.vehicle.Vehicle`; ``noise``: the
    measurement noise of the states (:class:`plant.sensors.MeasurementNoise`), whose
    variances the odometry's covariances then carry (zero without: the state is exact)."""

    def __init__(self, vehicle, period: float = CONTROL_PERIOD, noise=None):
        self.vehicle = vehicle
        self.period = float(period)
        # the odometry's covariances (6 x 6, row-major: x, y, z, roll, pitch, yaw; the
        # twist's in base_link), their diagonal the noise's variances
        self._pose_cov = np.zeros(36)
        self._twist_cov = np.zeros(36)
        if noise is not None:
            self._pose_cov[[0, 7, 35]] = (noise.pos ** 2, noise.pos ** 2, noise.phi ** 2)
            self._twist_cov[[0, 7, 35]] = (noise.v ** 2, noise.v ** 2, noise.r ** 2)
        self.nw = vehicle.n_wheels
        self.steer_names = steer_joints(self.nw)
        self.wheel_names = wheel_joints(self.nw)
        self._wx = np.asarray(vehicle.wheel_x, dtype=float)
        self._wy = np.asarray(vehicle.wheel_y, dtype=float)
        r_w = vehicle.wheel_radius
        span = float(self._wx.max() - self._wx.min())
        self._body = (span + 2 * r_w + 0.8, max(2 * float(np.abs(self._wy).max()) - 0.7, 0.6), 0.5)
        self._body_z = 2 * r_w + 0.3
        self._wheel_size = (2 * r_w, 0.36, 2 * r_w)
        self.reset()

    def reset(self) -> None:
        """A new run: forget the wheel angles, the wear work and the colour scale."""
        self._t_prev: float | None = None
        self._omega_prev: np.ndarray | None = None
        self._delta_prev: np.ndarray | None = None
        self._rate = np.zeros(self.nw)
        self._angle = np.zeros(self.nw)
        self._w_prev: np.ndarray | None = None
        self._p = np.zeros(self.nw)
        self._peak = 0.0

    # every message of one state
    def state_messages(self, st: Mapping, markers: bool = True) -> list[tuple[str, Any]]:
        """``[(topic, message), ...]`` of one state: clock, odom, tf, joint_states, wear
        (when the state carries the per-wheel wear work) and (``markers``) markers."""
        t = float(st["t"])
        self._advance(st, t)
        out = [(CLOCK, new("rosgraph_msgs/msg/Clock", clock=time_msg(t))),
               (ODOM, self.odom(st)), (TF, self.tf(st)), (JOINT_STATES, self.joint_states(st))]
        w = self.wear(st)
        if w is not None:
            out.append((WEAR, w))
        if markers:
            out.append((MARKERS, self.markers(st)))
        return out

    def _advance(self, st: Mapping, t: float) -> None:
        om = np.asarray(st["omega_w"], dtype=float)
        de = np.asarray(st["delta"], dtype=float)
        if self._t_prev is not None and t > self._t_prev:
            dt = t - self._t_prev
            self._angle = self._angle + 0.5 * (om + self._omega_prev) * dt
            self._rate = (de - self._delta_prev) / dt
        self._omega_prev, self._delta_prev, self._t_prev = om, de, t
        if all(k in st for k in WHEEL_WEAR_FIELDS):
            w = np.sum([np.asarray(st[k], dtype=float) for k in WHEEL_WEAR_FIELDS], axis=0)
            if self._w_prev is not None and self._w_prev[1] < t:
                self._p = (w - self._w_prev[0]) / (t - self._w_prev[1])
            self._w_prev = (w, t)
            self._peak = max(self._peak, float(np.max(self._p)) if self._p.size else 0.0)

    def odom(self, st: Mapping):
        phi = float(st["phi"])
        u, v = body_twist(phi, float(st["vx"]), float(st["vy"]))
        pose = new("geometry_msgs/msg/Pose",
                   position=new("geometry_msgs/msg/Point", x=float(st["x"]), y=float(st["y"]), z=0.0),
                   orientation=yaw_quaternion(phi))
        twist = new("geometry_msgs/msg/Twist",
                    linear=new("geometry_msgs/msg/Vector3", x=u, y=v, z=0.0),
                    angular=new("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=float(st["r"])))
        return new("nav_msgs/msg/Odometry", header=header(st["t"], FRAME_ODOM),
                   child_frame_id=FRAME_BASE,
                   pose=new("geometry_msgs/msg/PoseWithCovariance", pose=pose,
                            covariance=self._pose_cov),
                   twist=new("geometry_msgs/msg/TwistWithCovariance", twist=twist,
                             covariance=self._twist_cov))

    def tf(self, st: Mapping):
        tr = new("geometry_msgs/msg/Transform",
                 translation=new("geometry_msgs/msg/Vector3", x=float(st["x"]), y=float(st["y"]),
                                 z=0.0),
                 rotation=yaw_quaternion(float(st["phi"])))
        ts = new("geometry_msgs/msg/TransformStamped", header=header(st["t"], FRAME_ODOM),
                 child_frame_id=FRAME_BASE, transform=tr)
        return new("tf2_msgs/msg/TFMessage", transforms=[ts])

    def joint_states(self, st: Mapping):
        """Positions: ``steer_ij`` the steering angles, ``wheel_ij`` the wheels' angles
        (integrated from their speeds since the run's first state); velocities: the
        steering rates (mean over the last period) and the wheel speeds."""
        return new("sensor_msgs/msg/JointState", header=header(st["t"], FRAME_BASE),
                   name=self.steer_names + self.wheel_names,
                   position=np.r_[np.asarray(st["delta"], dtype=float), self._angle],
                   velocity=np.r_[self._rate, np.asarray(st["omega_w"], dtype=float)])

    def wear(self, st: Mapping):
        """Per-wheel wear power [W] and work [J] (rows :data:`WEAR_ROWS`, columns the
        wheels), None when the state has no per-wheel wear work."""
        if not all(k in st for k in WHEEL_WEAR_FIELDS):
            return None
        w = np.sum([np.asarray(st[k], dtype=float) for k in WHEEL_WEAR_FIELDS], axis=0)
        dims = [new("std_msgs/msg/MultiArrayDimension", label="|".join(WEAR_ROWS),
                    size=len(WEAR_ROWS), stride=len(WEAR_ROWS) * self.nw),
                new("std_msgs/msg/MultiArrayDimension",
                    label="|".join(wheel_names(self.nw)), size=self.nw, stride=self.nw)]
        return new("std_msgs/msg/Float64MultiArray",
                   layout=new("std_msgs/msg/MultiArrayLayout", dim=dims, data_offset=0),
                   data=np.r_[self._p, w])

    def markers(self, st: Mapping):
        """The body (a box) and each wheel (a cylinder at its steering angle, coloured by
        its wear power: green at none, red at the run's peak so far) in base_link."""
        hdr = header(st["t"], FRAME_BASE)
        zero = new("builtin_interfaces/msg/Duration")
        body = new("visualization_msgs/msg/Marker", header=hdr, ns="body", id=0, type=1,
                   action=0, frame_locked=True, lifetime=zero,
                   pose=new("geometry_msgs/msg/Pose",
                            position=new("geometry_msgs/msg/Point", x=0.0, y=0.0, z=self._body_z),
                            orientation=yaw_quaternion(0.0)),
                   scale=new("geometry_msgs/msg/Vector3", x=self._body[0], y=self._body[1],
                             z=self._body[2]),
                   color=new("std_msgs/msg/ColorRGBA", r=BODY_COLOR[0], g=BODY_COLOR[1],
                             b=BODY_COLOR[2], a=BODY_COLOR[3]))
        out = [body]
        delta = np.asarray(st["delta"], dtype=float)
        for k in range(self.nw):
            d = float(delta[k])
            # the cylinder's axis (z) turned onto the wheel's axle: roll 90 deg, then yaw delta
            c, s = math.cos(d / 2), math.sin(d / 2)
            r2 = math.sqrt(0.5)
            q = new("geometry_msgs/msg/Quaternion", x=r2 * c, y=r2 * s, z=r2 * s, w=r2 * c)
            r, g, b = wheel_colour(float(self._p[k]), self._peak)
            out.append(new("visualization_msgs/msg/Marker", header=hdr, ns="wheel", id=k + 1,
                           type=3, action=0, frame_locked=True, lifetime=zero,
                           pose=new("geometry_msgs/msg/Pose",
                                    position=new("geometry_msgs/msg/Point", x=float(self._wx[k]),
                                                 y=float(self._wy[k]),
                                                 z=self._wheel_size[0] / 2),
                                    orientation=q),
                           scale=new("geometry_msgs/msg/Vector3", x=self._wheel_size[0],
                                     y=self._wheel_size[2], z=self._wheel_size[1]),
                           color=new("std_msgs/msg/ColorRGBA", r=r, g=g, b=b, a=1.0)))
        return new("visualization_msgs/msg/MarkerArray", markers=out)

    def commands(self, t: float, delta, omega_w, omega_s) -> list[tuple[str, Any]]:
        """The two ros2_control command topics of a command (rates ``omega_s`` held from
        the steering angles ``delta`` of the state it answers): steering angle targets
        [rad] and wheel speeds [rad/s], one entry per joint in the wheel order."""
        tgt = steering_targets(delta, omega_s, self.period, self.vehicle.limits)
        return [(STEERING_COMMANDS, float_array(tgt)),
                (WHEEL_COMMANDS, float_array(np.asarray(omega_w, dtype=float)))]


def reference_path(ref_msg: Mapping, max_poses: int = 4000):
    """The ``plan`` (nav_msgs/Path) of a reference message (t, x, y, phi arrays), at most
    ``max_poses`` poses (evenly thinned, the last one kept)."""
    t = np.asarray(ref_msg["t"], dtype=float)
    idx = np.arange(t.size)
    if t.size > max_poses:
        idx = np.unique(np.r_[np.linspace(0, t.size - 1, max_poses).round().astype(int)])
    x, y, phi = (np.asarray(ref_msg[k], dtype=float)[idx] for k in ("x", "y", "phi"))
    return path_msg(t[idx], x, y, phi)


def predicted_path(t0: float, dt: float, poses: Sequence[Sequence[float]]):
    """``predicted_path`` (nav_msgs/Path) of the MPC's horizon: pose k at t0 + k dt."""
    p = np.asarray(poses, dtype=float).reshape(-1, 3)
    t = t0 + dt * np.arange(p.shape[0])
    return path_msg(t, p[:, 0], p[:, 1], p[:, 2], stamp=t0)


class RunChannels:
    """The ROS 2 messages of a process's msgpack traffic (what a recorder is handed): a
    valid state becomes its :meth:`RunMessages.state_messages` (and the ``plan`` at a run's
    first state and, with ``plan_every``, every that many states), a command answering a
    known state its two command topics, a reference the next ``plan``. Subclasses say where
    a message goes (:meth:`write`): a bag (:class:`bridge.ros_bag.RosBag`), a live view."""

    def __init__(self, vehicle, period: float, reference: Mapping | None = None,
                 plan_every: int | None = None):
        self.vehicle = vehicle
        self.nw = vehicle.n_wheels
        self.period = float(period)
        self.msgs = RunMessages(vehicle, self.period)
        self._ref_msg = reference
        self._plan_every = plan_every
        self._deltas: dict[int, list] = {}
        self._last_seq: int | None = None
        self._plan_due = True

    def write(self, topic: str, msg, ts: float) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def record(self, key: str, data: bytes, ts: float) -> None:
        """A msgpack payload on ``key`` at record time ``ts`` [s] (anything that is not a
        valid state, command or reference is not a ROS message and is left out)."""
        from . import messages as M

        kind = key.rsplit("/", 1)[-1]
        try:
            if kind == "state":
                self._state(M.decode_state(data, self.nw), ts)
            elif kind == "cmd":
                c = M.decode_cmd(data, self.nw)
                delta = self._deltas.get(c["state_seq"])
                if delta is not None:
                    for topic, msg in self.msgs.commands(c["t"], delta, c["omega_w"],
                                                         c["omega_s"]):
                        self.write(topic, msg, ts)
            elif kind == "reference":
                self._ref_msg = M.decode_reference(data)
                self._plan_due = True
        except M.MessageError:
            return

    def _state(self, st: dict, ts: float) -> None:
        seq = st["seq"]
        if self._last_seq is None or seq == 0 or seq < self._last_seq:
            self.msgs.reset()  # a new run
            self._plan_due = True
        if seq == self._last_seq:
            return  # sent again (lockstep, a controller that reappeared)
        self._last_seq = seq
        self._deltas[seq] = st["delta"]
        if len(self._deltas) > 512:
            del self._deltas[min(self._deltas)]
        if self._plan_every and seq % self._plan_every == 0:
            self._plan_due = True
        if self._plan_due and self._ref_msg is not None:
            ref = dict(self._ref_msg)
            if ref.get("relative"):
                ref["t"] = [v + st["t"] for v in ref["t"]]
            self.write(PLAN, reference_path(ref), ts)
            self._plan_due = False
        for topic, msg in self.msgs.state_messages(st, markers=seq % MARKER_EVERY == 0):
            self.write(topic, msg, ts)

    def predicted(self, t0: float, dt: float, poses, ts: float) -> None:
        """The controller's predicted path of the solve at ``t0`` (poses at t0 + k dt)."""
        self.write(PREDICTED_PATH, predicted_path(t0, dt, poses), ts)


def predicted_poses(controller) -> np.ndarray | None:
    """The last solve's predicted poses (N_p + 1, 3: x, y, phi; row 0 the state it started
    from) of a controller (:class:`controller.interface.Controller`), None when it has none."""
    fn = getattr(controller, "predicted_poses", None)
    poses = fn() if fn is not None else None
    return None if poses is None else np.asarray(poses, dtype=float)
