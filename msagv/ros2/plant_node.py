"""``msagv ros2 plant``: the plant as a ROS 2 node, a stand-in for Gazebo under a ROS 2
stack.

Publishes, every control period T, ``clock`` (the vehicle time: run the stack with
``use_sim_time``), ``joint_states``, ``wear``, ``tf`` (odom -> base_link; only where
tf2_msgs is installed: the registry has no wheel of it, so a pip-only install publishes the
same pose on ``odom`` alone) and ``odom``, in that order, all stamped with the vehicle time
t = k T; ``markers`` (the body and the wheels, docs/ROS2.md) every tenth period. Takes
ros2_control's forward-command topics ``steering_controller/commands`` (steering angle
targets [rad]) and ``wheel_controller/commands`` (wheel speeds [rad/s]), one entry per
joint in the wheel order. A steering target becomes the rate that reaches it in one period
(:func:`bridge.ros_msgs.steering_rates`, inside the rate limits), the inverse of the
controller's conversion.

The plant publishes its first state once a controller is matched both ways (subscribed to
``odom`` and ``joint_states``, publishing both command topics). Two modes, as ``msagv
plant``: ``lockstep`` steps when both command topics have answered the current state (as
fast as the controller; a Float64MultiArray names no state, so a state is sent once and a
command received after state k was published answers state k); ``realtime`` steps on the
wall clock with the newest commands, and :class:`bridge.loss.CommandWatch` puts it in the
safe behaviour (steering held, wheels ramped down) after ``stale_ms`` without an answer,
exactly as the Zenoh plant. A malformed command (wrong length, not finite, a negative wheel
speed) is rejected, counted by reason and never applied.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from msagv.bridge import messages as M
from msagv.bridge import ros_msgs as R
from msagv.bridge.loss import STALE_MS, CommandWatch
from msagv.bridge.plant_node import percentiles_ms
from msagv.bridge.recording import NullRecorder

from msagv.plant.signals import CONTROL_PERIOD
from .runtime import Context, Ros2Unavailable

log = logging.getLogger("msagv.ros2.plant")


class RosPlantError(RuntimeError):
    """The run cannot go on (no controller, a lockstep timeout, a failed step)."""


@dataclass
class RosPlantConfig:
    """As :class:`bridge.plant_node.PlantConfig` (run_mode, period, steps, timeout_s,
    wait_s, stale_ms, safe_decel, resume_periods); ``node_name`` the ROS node's name."""

    run_mode: str = "lockstep"
    period: float = CONTROL_PERIOD
    steps: int = 100
    timeout_s: float = 10.0
    wait_s: float = 60.0
    stale_ms: float = STALE_MS
    safe_decel: float = 2.0
    resume_periods: int = 3
    node_name: str = "msagv_plant"
    vehicle_id: str = "agv0"  # the recording's keys (msagv/ID/state, .../cmd)

    def __post_init__(self):
        if self.run_mode not in M.RUN_MODES:
            raise ValueError(f"--run-mode: expected lockstep or realtime, got '{self.run_mode}'")
        for name, v in (("--period", self.period), ("--timeout", self.timeout_s),
                        ("--stale-ms", self.stale_ms), ("--safe-decel", self.safe_decel)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v}")
        if self.steps < 1:
            raise ValueError("--duration must be at least one period")
        if not self.wait_s >= 0:
            raise ValueError(f"--wait must be >= 0, got {self.wait_s}")
        if not 1 <= self.resume_periods <= 1000:
            raise ValueError(f"--resume-periods must be 1..1000, got {self.resume_periods}")

    @property
    def max_missed(self) -> int:
        return int(math.floor(self.stale_ms / 1000.0 / self.period + 1e-9))


class RosPlant:
    """The plant node (see the module docstring). ``plant``: a plant with the plant
    interface at its initial state; ``recorder``: a recorder-like sink (``message``,
    ``event``, ``close``) that gets every state sent and command applied as the Zenoh
    plant's msgpack payloads, or None."""

    def __init__(self, plant, cfg: RosPlantConfig, ros_args: list[str], recorder=None,
                 stop: threading.Event | None = None):
        self.plant = plant
        self.vehicle = plant.vehicle
        self.nw = self.vehicle.n_wheels
        self.cfg = cfg
        self.rec = recorder if recorder is not None else NullRecorder()
        self.stop = stop or threading.Event()
        self.msgs = R.RunMessages(self.vehicle, cfg.period)
        self.rej = M.Rejections("ros2 plant", log)
        self.watch = CommandWatch(cfg.max_missed, cfg.resume_periods, cfg.period)
        self.ramp = cfg.safe_decel / self.vehicle.wheel_radius
        self.key_state = f"msagv/{cfg.vehicle_id}/state"
        self.key_cmd = f"msagv/{cfg.vehicle_id}/cmd"
        self.seq = -1
        self._delta = None  # the published state's steering angles (targets -> rates)
        self._steer: tuple[int, np.ndarray] | None = None  # (state it answers, targets)
        self._wheel: tuple[int, np.ndarray] | None = None
        self._pub_perf: dict[int, float] = {}
        self.accepted = 0
        self.after_end = 0
        self.roundtrip_s: list = []
        self.lateness_s: list = []
        self.missed_periods = 0
        self.safe_events = 0
        self.safe_periods = 0
        self.resumes = 0
        self.error: str | None = None
        self.final_state: dict | None = None
        self.tf_published = True
        self.ctx = Context(cfg.node_name, ros_args)
        self.pubs = {}
        for topic in (R.CLOCK, R.JOINT_STATES, R.WEAR, R.TF, R.ODOM, R.MARKERS):
            try:
                self.pubs[topic] = self.ctx.publisher(topic)
            except Ros2Unavailable as e:
                if topic != R.TF:
                    raise
                self.tf_published = False
                log.warning("not publishing tf: %s; the pose is on odom", e)
        self._subs = [self.ctx.subscription(R.STEERING_COMMANDS, self._on_steer),
                      self.ctx.subscription(R.WHEEL_COMMANDS, self._on_wheel)]

    # ---- commands --------------------------------------------------------------------
    def _check(self, msg, what: str, nonneg: bool) -> np.ndarray | None:
        try:
            v = np.asarray(msg.data, dtype=float)
            if v.shape != (self.nw,):
                raise M.MessageError(M.BAD_LENGTH, f"{what} has {v.size} entries, the vehicle "
                                                   f"has {self.nw} joints")
            if not np.all(np.isfinite(v)):
                raise M.MessageError(M.NON_FINITE, f"{what} has NaN or inf")
            if nonneg and np.any(v < 0):
                raise M.MessageError(M.NEGATIVE_WHEEL_SPEED, f"{what} has a negative speed")
        except M.MessageError as e:
            self.rej.add(e, what)
            return None
        return v

    def _on_steer(self, msg) -> None:
        v = self._check(msg, R.STEERING_COMMANDS, nonneg=False)
        if v is not None and self.seq >= 0:
            self._steer = (self.seq, v)
            self._answered()

    def _on_wheel(self, msg) -> None:
        v = self._check(msg, R.WHEEL_COMMANDS, nonneg=True)
        if v is not None and self.seq >= 0:
            self._wheel = (self.seq, v)
            self._answered()

    def _answered(self) -> None:
        s, w = self._steer, self._wheel
        if s is None or w is None or s[0] != w[0] or s[0] != self.seq:
            return
        if self.seq >= self.cfg.steps:
            self.after_end += 1  # the answer to the end state: never applied
            return
        self.accepted += 1
        tp = self._pub_perf.pop(self.seq, None)
        if tp is not None:
            self.roundtrip_s.append(time.perf_counter() - tp)

    def _answer(self, k: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The commands answering state k (both topics), as (omega_w, omega_s)."""
        s, w = self._steer, self._wheel
        if s is None or w is None or s[0] != k or w[0] != k:
            return None
        return w[1], R.steering_rates(self._delta, s[1], self.cfg.period, self.vehicle.limits)

    def _newest(self) -> tuple[int | None, np.ndarray | None, np.ndarray | None]:
        s, w = self._steer, self._wheel
        if s is None or w is None:
            return None, None, None
        return min(s[0], w[0]), w[1], R.steering_rates(self._delta, s[1], self.cfg.period,
                                                        self.vehicle.limits)

    # ---- state -----------------------------------------------------------------------
    def publish_state(self, k: int, end: bool = False) -> None:
        st = self.plant.state_message()
        st["t"] = k * self.cfg.period
        if k == 0:
            self.msgs.reset()
        msgs = dict(self.msgs.state_messages(st, markers=k % R.MARKER_EVERY == 0))
        for topic in (R.CLOCK, R.JOINT_STATES, R.WEAR, R.TF, R.ODOM):
            if topic in msgs and topic in self.pubs:
                self.pubs[topic].publish(R.encode(msgs[topic], R.TYPES[topic]))
        if R.MARKERS in msgs:
            self.pubs[R.MARKERS].publish(R.encode(msgs[R.MARKERS], R.TYPES[R.MARKERS]))
        self.seq = k
        self._delta = np.asarray(st["delta"], dtype=float)
        self._pub_perf[k] = time.perf_counter()
        if len(self._pub_perf) > 256:
            self._pub_perf.pop(min(self._pub_perf))
        self.rec.message("tx", self.key_state, M.encode_state(k, st, end=True if end else None))
        if end:
            self.final_state = st

    def _apply(self, k: int, omega_w, omega_s, record: bool = True) -> None:
        from msagv.plant.interface import PlantError

        if record:
            self.rec.message("rx", self.key_cmd,
                             M.encode_cmd(k, k * self.cfg.period, k, omega_w, omega_s))
        try:
            self.plant.set_inputs(omega_w, omega_s)
            self.plant.do_step(self.plant.t, self.cfg.period)
        except PlantError as e:
            raise RosPlantError(f"step at t = {self.plant.t:.2f} s failed: {e}") from None

    # ---- runs ------------------------------------------------------------------------
    def _wait_controller(self) -> None:
        """Spin until a controller is matched both ways: subscribed to ``odom`` and
        ``joint_states`` and publishing both command topics (then state 0 goes out once:
        a command names no state, so a state is never sent twice and every command received
        after state k answers k)."""
        t0 = time.monotonic()
        told = False
        wait = self.cfg.wait_s or float("inf")
        while not self.stop.is_set():
            if (self.pubs[R.ODOM].get_subscription_count() > 0
                    and self.pubs[R.JOINT_STATES].get_subscription_count() > 0
                    and all(s.get_publisher_count() > 0 for s in self._subs)):
                return
            if not told and time.monotonic() - t0 > 1.0:
                log.info("waiting for a controller (subscribed to odom and joint_states, "
                         "publishing %s and %s)", R.STEERING_COMMANDS, R.WHEEL_COMMANDS)
                told = True
            if time.monotonic() - t0 > wait:
                raise RosPlantError(f"no controller within {wait:g} s: nothing subscribed to "
                                    f"odom and joint_states and publishing "
                                    f"{R.STEERING_COMMANDS} and {R.WHEEL_COMMANDS}")
            self.ctx.spin_once(0.02)

    def _wait_answer(self, k: int, timeout: float):
        """Spin until both command topics answer state k."""
        t0 = time.monotonic()
        while not self.stop.is_set():
            a = self._answer(k)
            if a is not None:
                return a
            if time.monotonic() - t0 > timeout:
                raise RosPlantError(
                    f"{self.cfg.run_mode}: no commands on {R.STEERING_COMMANDS} and "
                    f"{R.WHEEL_COMMANDS} answering state {k} (t = {k * self.cfg.period:.2f} s) "
                    f"within {timeout:g} s")
            self.ctx.spin_once(0.005)
        return None

    def run(self) -> dict:
        try:
            if self.cfg.run_mode == "lockstep":
                self._run_lockstep()
            else:
                self._run_realtime()
        except RosPlantError as e:
            self.error = str(e)
            raise
        finally:
            if self.final_state is None:
                st = self.plant.state_message()
                st["t"] = max(self.seq, 0) * self.cfg.period
                self.final_state = st
        return self.summary()

    def _run_lockstep(self) -> None:
        cfg = self.cfg
        self._wait_controller()
        self.publish_state(0)
        for k in range(cfg.steps):
            a = self._wait_answer(k, cfg.timeout_s)
            if a is None:
                return
            self._apply(k, *a)
            self.publish_state(k + 1, end=k + 1 == cfg.steps)
        self._linger()

    def _run_realtime(self) -> None:
        cfg, T = self.cfg, self.cfg.period
        self._wait_controller()
        self.publish_state(0)
        if self._wait_answer(0, cfg.timeout_s) is None:
            return
        w0 = time.perf_counter()
        for k in range(cfg.steps):
            target = w0 + (k + 1) * T
            while not self.stop.is_set():
                left = target - time.perf_counter()
                if left <= 0:
                    break
                self.ctx.spin_once(min(left, 0.002))
            if self.stop.is_set():
                return
            j, om_w, om_s = self._newest()
            d = self.watch.step(k, j, True)
            if d.resumed:
                self.resumes += 1
                log.warning("resumed at t = %.2f s", k * T)
                self.rec.event("safe", on=False, t=k * T)
            if d.use_command:
                u_w, u_s = om_w, om_s
            else:
                if d.entered_safe is not None:
                    self.safe_events += 1
                    log.warning("SAFE at t = %.2f s: %s; holding steering, ramping the wheels "
                                "down at %g m/s^2", k * T, d.entered_safe, cfg.safe_decel)
                    self.rec.event("safe", on=True, t=k * T, why=d.entered_safe)
                self.safe_periods += 1
                held_w, _ = self.plant.inputs
                u_w = np.maximum(np.asarray(held_w) - self.ramp * T, 0.0)
                u_s = np.zeros(self.nw)
            self._apply(k, u_w, u_s, record=d.use_command)
            self.publish_state(k + 1, end=k + 1 == cfg.steps)
            late = time.perf_counter() - target
            self.lateness_s.append(late)
            if late > T:
                self.missed_periods += 1
        self._linger()

    def _linger(self, seconds: float = 0.2) -> None:
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds and not self.stop.is_set():
            self.ctx.spin_once(0.01)

    def close(self) -> None:
        self.ctx.close()

    def summary(self) -> dict:
        fs = self.final_state or {}
        steps = max(self.seq, 0)
        return {"role": "ros2 plant", "run_mode": self.cfg.run_mode, "period": self.cfg.period,
                "steps": steps, "t_end": steps * self.cfg.period,
                "completed": steps == self.cfg.steps and self.error is None,
                "error": self.error, "commands": {"accepted": self.accepted, "after_end": self.after_end},
                "rejected": self.rej.summary(),
                "roundtrip_ms": percentiles_ms(self.roundtrip_s),
                "lateness_ms": percentiles_ms(self.lateness_s),
                "missed_periods": self.missed_periods,
                "safe": {"events": self.safe_events, "periods": self.safe_periods,
                         "resumes": self.resumes},
                "tf": self.tf_published,
                "final_state": {k: fs[k] for k in ("t", "x", "y", "phi", "vx", "vy", "r", "W_s",
                                                   "W_alpha", "W_t") if k in fs}}
