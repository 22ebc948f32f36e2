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
run's clock with the newest commands, and :class:`bridge.loss.CommandWatch` puts it in the
safe behaviour (steering held, wheels ramped down) after ``stale_ms`` without an answer,
exactly as the Zenoh plant: both are ports of one run, :class:`bridge.run_core.PlantRun`.
The run's clock is the wall clock; under ``use_sim_time`` a realtime plant follows ROS time
(a simulator's ``/clock``, at its own pace: its steps, waits, staleness and safe-state
decisions count that clock's periods) and does not publish ``clock`` itself. A lockstep
plant is the simulator: it publishes ``clock``, and its waits stay on the wall clock (its
own time stands while it waits). A malformed command (wrong length, not finite, a negative wheel
speed) is rejected, counted by reason and never applied.

One publisher per command topic drives: the first whose valid command arrives once state 0
is out while it is the topic's only publisher (its GID, from rclpy's message info; with two
publishers neither binds), and both topics from one node (the node of that GID in the ROS
graph: the steering of one controller and the wheel speeds of another are not taken
together). Another publisher's commands are
rejected as ``not_owner`` before they are read and counted, also after the bound one fell
silent or left (the safe behaviour or the lockstep timeout follows, never a takeover), until
an operator calls ``~/rearm`` (std_srvs/Trigger): then the next publisher to send binds.
This keeps a second, stale or misconfigured controller from driving; it authenticates
nobody (a process may publish under any node name): SROS2's access control decides who may
publish on the command topics at all (docs/ROS2.md).

With ``managed`` (``--managed``) it is an ``rclpy.lifecycle`` managed node, as the
controller: unconfigured it has no topics; ``configure`` declares them, ``/diagnostics``,
``~/rearm`` and ``~/reset``;
only while active does the run go (its first state once active and a controller is
there); ``deactivate`` holds the run between two steps on a clock that stands
(:class:`bridge.run_core.PausableClock`): the vehicle stands, the pause is no time of the
run's (no period missed, no command aged, no wait's bound used, no watchdog), and
``activate`` takes it up with the state that was due; ``cleanup`` takes the topics down
and unbinds the command topics (in lockstep with the current state's answer owed, that
answer is lost with them: the run starts again at state 0, as ``~/reset``);
``shutdown`` (or a signal) ends the run and the process, and so does the run's end (a
deactivate after the end state is out does not hold it).
The transitions run in the run's thread (the node's callbacks run only in its idle), so
never in the middle of a step. docs/ROS2.md, "A managed plant".

Its run's options are ROS parameters (:data:`PARAMETERS`; those of :data:`RUNTIME` change
at run time, the others are refused with the reason of :data:`FIXED`); its status goes
on ``/diagnostics`` once a second (:meth:`RosPlant.diagnostics`); ``~/reset`` puts the
vehicle back at its initial state and starts the run again at state 0, t = 0
(:meth:`RosPlant._on_reset`). docs/ROS2.md, "The plant's parameters, diagnostics and
reset".
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from msagv.bridge import messages as M
from msagv.bridge import ros_msgs as R
from msagv.bridge.run_core import (RESEND_S, Command, PausableClock, PlantRun, PlantRunError,
                                   RunConfig, WallClock)

from .runtime import (ERROR, OK, STALE, WARN, Context, Diagnostics, Lifecycle, Ros2Unavailable,
                      declare_parameters, destroy, parameter_changes, set_parameters_result,
                      trigger_services)

log = logging.getLogger("msagv.ros2.plant")

def _gid(info) -> bytes:
    """A publisher's GID from rclpy's message info (``publisher_gid``: a dict with the
    bytes as ``data``), as bytes; b"" where the middleware gives none."""
    g = (info or {}).get("publisher_gid") if isinstance(info, dict) else None
    if isinstance(g, dict):
        g = g.get("data")
    return bytes(g) if g is not None else b""


UNKNOWN_NODE = ("_NODE_NAME_UNKNOWN_", "_NODE_NAMESPACE_UNKNOWN_")  # rmw_dds_common's names
# for an endpoint whose node the graph has not learnt yet

RosPlantError = PlantRunError  # the run cannot go on (no controller, a timeout, a failed step)
SIM_LOOK_S = 0.002  # under use_sim_time the clock's pace is the simulator's: look this often
HOLD_LOOK_S = 0.05  # a managed node held inactive looks for its transitions this often


# ROS parameters (``--ros-args -p NAME:=VALUE`` or a params file), each also an option
# (``--run-mode``, ``--period``, ``--duration``, ``--timeout``, ``--wait``, ``--stale-ms``,
# ``--resume-periods``, ``--safe-decel``); the vehicle and the path are options alone (the
# plant is built from them before the node is)
PARAMETERS = {"run_mode": str, "period": float, "duration": float, "timeout": float,
              "wait": float, "stale_ms": float, "resume_periods": int, "safe_decel": float}
# what may change while configured: the safe behaviour's settings and the wait for an
# answer, from the next period on (:meth:`bridge.run_core.PlantRun.reconfigure`)
RUNTIME = ("stale_ms", "resume_periods", "safe_decel", "timeout")
FIXED = {  # the others, and why they are set at start only
    "run_mode": "the run's mode is its contract with the controller (lockstep answers every "
                "state, realtime steps at 1/T with the newest command)",
    "period": "state k is stamped k T: another period would bend the run's time axis",
    "duration": "the run's end state (seq = duration / period) is fixed when it starts",
    "wait": "the wait for a controller is the run's start",
}


def _run_config(cfg, p: dict):
    """The run's settings ``cfg`` with the parameters ``p``, or ValueError naming the bad
    value (:class:`bridge.run_core.RunConfig`'s checks)."""
    if not (p["duration"] > 0 and p["period"] > 0):
        raise ValueError(f"duration and period must be > 0, got {p['duration']:g} and "
                         f"{p['period']:g}")
    return dataclasses.replace(
        cfg, run_mode=p["run_mode"], period=p["period"],
        steps=int(round(p["duration"] / p["period"])), timeout_s=p["timeout"], wait_s=p["wait"],
        stale_ms=p["stale_ms"], resume_periods=p["resume_periods"], safe_decel=p["safe_decel"])


@dataclass
class RosPlantConfig(RunConfig):
    """The run's settings (:class:`bridge.run_core.RunConfig`, as ``msagv plant``'s) and
    the node's: ``node_name`` the ROS node's name, ``vehicle_id`` the recording's keys."""

    node_name: str = "msagv_plant"
    vehicle_id: str = "agv0"  # the recording's keys (msagv/ID/state, .../cmd)


class RosTime:
    """The node's ROS time (``/clock`` under ``use_sim_time``) as the run's clock."""

    def __init__(self, node):
        self._clock = node.get_clock()

    def now(self) -> float:
        return self._clock.now().nanoseconds * 1e-9

    def wall(self, dt: float) -> float:
        return min(dt, SIM_LOOK_S)


class RosPlant:
    """The plant node (see the module docstring): the run's port
    (:class:`bridge.run_core.PlantPort`) on ROS 2 topics. ``plant``: a plant with the plant
    interface at its initial state; ``recorder``: a recorder-like sink (``message``,
    ``event``, ``maybe_flush``, ``close``) that gets every state sent and command applied as
    the Zenoh plant's msgpack payloads, or None. ``managed``: an ``rclpy.lifecycle`` node
    that starts unconfigured (see the module docstring); else a plain node, its topics
    declared at once."""

    def __init__(self, plant, cfg: RosPlantConfig, ros_args: list[str], recorder=None,
                 stop: threading.Event | None = None, managed: bool = False, measure=None):
        self.plant = plant
        self.vehicle = plant.vehicle
        self.nw = self.vehicle.n_wheels
        self.managed = managed
        self.ctx = Context(cfg.node_name, ros_args, lifecycle=managed)
        try:  # the parameters in force: -p and --params-file over the options
            self.params = declare_parameters(self.ctx.node, PARAMETERS, {
                "run_mode": cfg.run_mode, "period": cfg.period,
                "duration": cfg.steps * cfg.period, "timeout": cfg.timeout_s,
                "wait": cfg.wait_s, "stale_ms": cfg.stale_ms,
                "resume_periods": cfg.resume_periods, "safe_decel": cfg.safe_decel})
            cfg = _run_config(cfg, self.params)
        except Exception:
            self.ctx.close()
            raise
        self.cfg = cfg
        self.msgs = R.RunMessages(self.vehicle, cfg.period, noise=measure)
        self.rej = M.Rejections("ros2 plant", log)
        self.key_state = f"msagv/{cfg.vehicle_id}/state"
        self.key_cmd = f"msagv/{cfg.vehicle_id}/cmd"
        self._delta = None  # the published state's steering angles (targets -> rates)
        self._st0: dict | None = None  # state 0 as sent, and when (published again: below)
        self._sent0 = 0.0
        self.resent0 = 0
        self._steer: tuple[int, np.ndarray] | None = None  # (state it answers, targets)
        self._wheel: tuple[int, np.ndarray] | None = None
        self.tf_published = True
        self.diag = None
        self.parameter_changes = self.parameters_refused = 0
        # under use_sim_time a realtime plant's time is ROS time: someone else's /clock
        self.sim_time = (cfg.run_mode == "realtime"
                         and bool(self.ctx.node.get_parameter("use_sim_time").value))
        clock = RosTime(self.ctx.node) if self.sim_time else WallClock()
        if managed:  # the run's time stands while the node is not active
            clock = PausableClock(clock, paused=True)
        self.clock = clock
        self.core = PlantRun(plant, cfg, self, recorder=recorder, log=log, stop=stop,
                             clock=clock, measure=measure)
        self.rec, self.stop, self.stats = self.core.rec, self.core.stop, self.core.stats
        self.pubs: dict = {}
        self._subs: list = []
        self._services: list = []
        # the publisher (GID) each command topic is bound to (None: the next one to send)
        self.sources: dict[str, bytes | None] = {R.STEERING_COMMANDS: None,
                                                 R.WHEEL_COMMANDS: None}
        self.source_node: str | None = None  # the node both topics are taken from
        self._gid_apart_told = False
        self.rearms = 0
        self.configured = self.active = self._ended = False
        self.lifecycle = None
        if managed:  # unconfigured until a lifecycle manager says otherwise
            self.lifecycle = Lifecycle(self.ctx.node, {
                "configure": self._configure, "activate": self._activate,
                "deactivate": self._deactivate, "cleanup": self._cleanup_transition,
                "shutdown": self._shutdown, "error": self._cleanup_transition}, log)
        else:
            self._declare()
            self.active = True
        self.ctx.node.add_on_set_parameters_callback(self._on_set_parameters)


    def attach_recorder(self, recorder) -> None:
        """Record the run into ``recorder`` from now on (before :meth:`run`): the command
        line opens the recording once the parameters in force are known, so that its header
        says the run's period and mode as ``-p`` and ``--params-file`` set them."""
        self.core.rec = self.rec = recorder
    def _declare(self) -> None:
        """The node's topics, ``/diagnostics`` and its services ``~/rearm`` and
        ``~/reset``."""
        for topic in (R.CLOCK, R.JOINT_STATES, R.WEAR, R.TF, R.ODOM, R.MARKERS):
            if topic == R.CLOCK and self.sim_time:
                continue
            try:
                self.pubs[topic] = self.ctx.publisher(topic)
            except Ros2Unavailable as e:
                if topic != R.TF:
                    raise
                self.tf_published = False
                log.warning("not publishing tf: %s; the pose is on odom", e)
        self._subs = [self.ctx.subscription(R.STEERING_COMMANDS, self._on_steer),
                      self.ctx.subscription(R.WHEEL_COMMANDS, self._on_wheel)]
        self.diag = Diagnostics(self.ctx.node, "plant", self.vehicle.name, self.diagnostics,
                                log)
        self._services = trigger_services(self.ctx.node, {"rearm": self._on_rearm,
                                                          "reset": self._on_reset}, log)
        self.configured = True

    # ---- the lifecycle (managed: docs/ROS2.md, "A managed plant") ---------------------
    # The transitions run in the run's thread (its callbacks run only in the port's idle),
    # between two steps: a deactivated node holds the run in idle, on a clock that stands.
    def _configure(self) -> None:
        """Declare the topics and ``~/rearm``; no state published until activated. A
        failure takes down what was declared (the node stays unconfigured)."""
        try:
            self._declare()
        except Exception:
            self.configured = True
            self._cleanup()
            raise

    def _activate(self) -> None:
        """The run goes on: the clock from where it stood, the next state the one due."""
        self.active = True
        self.clock.resume()

    def _deactivate(self) -> None:
        """The run held between two steps, the clock with it: the vehicle stands, the pause
        is no silence of the controller's (no period missed, nothing stale, no watchdog)."""
        self.clock.pause()
        self.active = False

    def _cleanup(self) -> None:
        """Back to unconfigured: the topics and ``~/rearm`` taken down, the command topics
        unbound (the next configure's first publisher drives: the controller may be a new
        one). The run stands where it was."""
        if self.active:
            self._deactivate()
        if not self.configured:
            return
        destroy(self.ctx.node, (), self._subs, self._services, self.pubs.values())
        if self.diag is not None:
            self.diag.destroy()
        self.pubs, self._subs, self._services = {}, [], []
        self.sources = dict.fromkeys(self.sources)
        self.source_node = None
        self.configured = False

    def _cleanup_transition(self) -> None:
        """``cleanup`` (and ``error``, which ends unconfigured too): :meth:`_cleanup`; in
        lockstep with the current state's answer still owed, the run starts again at state
        0 as ``~/reset`` does. The answer is lost with the command topics (one sent while
        they are down reaches nobody), and a command names no state: waiting for it would
        wait for ever, and a later command (a controller's stop, another state's answer)
        would be taken for it. The reset's hazard - an answer in flight to the old state
        taken as the new state 0's - is gone with the subscriptions."""
        k = self.seq
        owed = (self.configured and self.cfg.run_mode == "lockstep" and 0 <= k < self.cfg.steps
                and self.core.resettable() is None and self.answer(k) is None)
        self._cleanup()
        if owed:
            log.warning("cleanup: state %d's answer was owed and is lost with the command "
                        "topics (a command names no state): the run starts again at state 0 "
                        "once active, as ~/reset does", k)
            self._reset_run()

    def _reset_run(self) -> None:
        """The run back to state 0 (:meth:`bridge.run_core.PlantRun.reset`), the answers
        held and state 0 as sent forgotten."""
        self.core.reset()
        self._steer = self._wheel = None
        self._st0 = None
        self._delta = None

    def _shutdown(self) -> None:
        """The run ends (the process prints its summary and exits)."""
        self._cleanup()
        self._ended = True
        self.stop.set()

    def state_label(self) -> str:
        """The lifecycle state: unconfigured, inactive, active or finalized."""
        return Lifecycle.label(self.configured, self.active, self._ended)

    seq = property(lambda self: self.core.seq)
    error = property(lambda self: self.core.error)
    final_state = property(lambda self: self.core.final_state)

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

    def _from_source(self, topic: str, info) -> bool:
        """The command may be read: it comes from the publisher ``topic`` is bound to, or
        the topic is not bound yet (it binds in :meth:`_bind`, once the command is valid);
        another publisher's is rejected as ``not_owner``."""
        bound = self.sources[topic]
        gid = _gid(info)
        if bound is None or gid == bound:
            return True
        self.rej.add(M.MessageError(
            M.NOT_OWNER, f"from publisher {gid.hex()[:16]}, not {bound.hex()[:16]} that "
            f"drives (a second controller? ~/rearm lets the next publisher drive)"), topic)
        return False

    def _bind(self, topic: str, info, sub) -> bool:
        """A valid command once state 0 is out: binds ``topic`` to its publisher if it is
        not bound. Not while more than one node publishes on the topic (which of two
        controllers drives is not for the first message to decide: neither is taken until
        one leaves or an operator re-arms; after ``~/rearm`` the next one binds whatever the
        count), nor without a GID from the middleware."""
        if self.sources[topic] is not None:
            return True
        gid, n = _gid(info), sub.get_publisher_count()
        # (after ~/rearm the operator said the next one drives: a killed controller's
        # publisher may stay in the graph for its lease)
        why = ("the middleware gives no publisher GID" if not gid else
               f"{n} publishers on {topic}" if n > 1 and not self.rearms else None)
        if why is not None:
            self.rej.add(M.MessageError(M.NOT_OWNER, f"{why}: none drives until one is "
                                                     f"left (or ~/rearm)"), topic)
            return False
        # both topics from one node: the steering of one controller and the wheel speeds
        # of another are no command of anyone's
        node = self._node_of(sub, gid)
        why = ("its publisher is not in the ROS graph yet" if node is None else
               f"its publisher is node {node}, while {self.source_node} drives the other "
               f"command topic (both commands must come from one node; ~/rearm lets the "
               f"next publisher drive)"
               if self.source_node is not None and node != self.source_node else None)
        if why is not None:
            self.rej.add(M.MessageError(M.NOT_OWNER, why), topic)
            return False
        self.sources[topic] = gid
        self.source_node = node
        log.info("commands on %s from publisher %s of node %s", topic, gid.hex()[:16], node)
        self.rec.event("source", topic=topic, gid=gid.hex(), node=node)
        return True

    def _node_of(self, sub, gid: bytes) -> str | None:
        """The fully qualified name of the node whose publisher on ``sub``'s topic has the
        GID ``gid`` (from the ROS graph), or None where the graph does not (yet) know it.
        Where no GID of the graph matches (Cyclone DDS gives the message's and the graph's
        GIDs apart: ros2/rmw_cyclonedds #377) and the topic has one publisher, that
        publisher's node (said once)."""
        try:
            infos = self.ctx.node.get_publishers_info_by_topic(sub.topic_name)
        except Exception as e:  # noqa: BLE001 - a closing context: taken as unknown
            log.debug("publishers of %s: %s", sub.topic_name, e)
            return None

        def name(i) -> str | None:
            if i.node_name in UNKNOWN_NODE or i.node_namespace in UNKNOWN_NODE:
                return None  # the graph has the endpoint, not yet its node
            return f"{i.node_namespace.rstrip('/')}/{i.node_name}"

        for i in infos:
            g = bytes(i.endpoint_gid)
            n = min(len(g), len(gid))
            if n and g[:n] == gid[:n]:
                return name(i)
        if len(infos) == 1:
            if not self._gid_apart_told:
                self._gid_apart_told = True
                log.warning("the middleware's publisher GIDs in messages and in the ROS graph "
                            "differ: %s's only publisher is taken as the one sending",
                            sub.topic_name)
            return name(infos[0])
        return None

    def _on_steer(self, msg, info) -> None:  # (two arguments: rclpy passes the info)
        if not self._from_source(R.STEERING_COMMANDS, info):
            return
        v = self._check(msg, R.STEERING_COMMANDS, nonneg=False)
        if v is not None and self.seq >= 0 and self._bind(R.STEERING_COMMANDS, info,
                                                          self._subs[0]):
            self._steer = (self.seq, v)
            self._answered()

    def _on_wheel(self, msg, info) -> None:
        if not self._from_source(R.WHEEL_COMMANDS, info):
            return
        v = self._check(msg, R.WHEEL_COMMANDS, nonneg=True)
        if v is not None and self.seq >= 0 and self._bind(R.WHEEL_COMMANDS, info,
                                                          self._subs[1]):
            self._wheel = (self.seq, v)
            self._answered()

    def _on_rearm(self, request, response):
        """``~/rearm`` (std_srvs/Trigger): the next publisher to send on each command topic
        drives (the safe behaviour ends as ever: once its commands keep up)."""
        was = {t: (g.hex()[:16] if g is not None else None) for t, g in self.sources.items()}
        self.sources = dict.fromkeys(self.sources)
        self.source_node = None
        self.rearms += 1
        log.warning("re-armed by an operator: the next publisher on %s and %s drives "
                    "(was %s)", R.STEERING_COMMANDS, R.WHEEL_COMMANDS, was)
        self.rec.event("armed", was=was)
        response.success, response.message = True, "re-armed: the next publisher drives"
        return response

    def _on_reset(self, request, response):
        """``~/reset`` (std_srvs/Trigger): the vehicle back at its initial state (pose,
        velocities, steering, wheel speeds, wear integrals zero) and the run started again
        at state 0, stamped t = 0, as a new run (:meth:`bridge.run_core.PlantRun.reset`).
        Refused with the reason, nothing changed: unconfigured; after the run's end or its
        failure; in lockstep while the current state's answer is outstanding (a command
        names no state: an answer in flight would be taken as the new state 0's; deactivate
        the managed plant, let the answer in, then reset). The command topics stay bound
        (a reset is no re-arm)."""
        k = self.seq
        why = ("not configured" if not self.configured else self.core.resettable())
        if why is None and k <= 0:  # nothing stepped: the vehicle is where it started (a
            # reset would send state 0 again with the same stamp, which a controller takes
            # for a repeat, not for a new run)
            response.success = True
            response.message = ("reset: nothing to do, the run is at state 0 (the vehicle "
                                "at its initial state)")
            return response
        if why is None and self.cfg.run_mode == "lockstep" and \
                self.answer(k) is None:
            why = (f"lockstep: state {k}'s answer is outstanding (an answer in flight would "
                   f"be taken as the new state 0's); deactivate the plant, then reset")
        if why is not None:
            log.warning("reset refused: %s", why)
            response.success, response.message = False, f"reset refused: {why}"
            return response
        self._reset_run()
        response.success = True
        response.message = (f"reset: the vehicle is at its initial state; the run starts "
                            f"again at state 0 (t = 0), was at state {k}")
        return response

    # ---- parameters at run time ------------------------------------------------------------
    def _on_set_parameters(self, params):
        """A change of the parameters (``ros2 param set``, the SetParameters service),
        checked and applied all together or refused with the reason, nothing changed:
        :data:`RUNTIME` from the next period on; the others (:data:`FIXED`) refused, at
        any lifecycle state (the run is made when the node is: a managed node's cleanup
        does not end it)."""
        try:
            new, changed = parameter_changes(
                PARAMETERS, self.params, params, True,
                "chooses the run's clock when the node starts; set it at start")
            fixed = [k for k in changed if k not in RUNTIME]
            if fixed:
                raise ValueError(f"{fixed[0]}: {FIXED[fixed[0]]}; set it at start "
                                 f"(--ros-args -p {fixed[0]}:=... or a params file)")
            cfg = _run_config(self.cfg, new)
            if changed:
                self.core.reconfigure(cfg)
        except Exception as e:  # noqa: BLE001 - refused with its reason, nothing changed
            reason = str(e).removeprefix("ROS parameter ")
            self.parameters_refused += 1
            log.warning("parameter change refused: %s", reason)
            return set_parameters_result(False, reason)
        if changed:
            self.cfg = cfg
            self.parameter_changes += 1
            log.info("parameters changed: %s", ", ".join(f"{k}={new[k]}" for k in changed))
        self.params = new
        return set_parameters_result(True)

    def _answered(self) -> None:
        s, w, k = self._steer, self._wheel, self.seq
        if s is None or w is None or s[0] != w[0] or s[0] != k:
            return
        if k >= self.cfg.steps:
            self.stats.after_end += 1  # the answer to the end state: never applied
            return
        self.stats.accepted += 1
        with self.core.lock:
            self.core.answered(k, time.perf_counter())

    def _rates(self, targets: np.ndarray) -> np.ndarray:
        return R.steering_rates(self._delta, targets, self.cfg.period, self.vehicle.limits)

    # ---- the run's port (bridge.run_core.PlantPort) ----------------------------------
    def answer(self, k: int) -> Command | None:
        """The commands answering state k (both topics)."""
        s, w = self._steer, self._wheel
        if s is None or w is None or s[0] != k or w[0] != k:
            return None
        return Command(k, w[1], self._rates(s[1]))

    def newest(self) -> Command | None:
        s, w = self._steer, self._wheel
        if s is None or w is None:
            return None
        return Command(min(s[0], w[0]), w[1], self._rates(s[1]))

    def present(self) -> bool:
        return True  # ROS 2 has no presence of ours: staleness alone decides

    def idle(self, seconds: float, wake: bool = True) -> None:
        self.ctx.spin_once(seconds)  # the callbacks run only here: always spun
        # managed, not active: held - not once the end state is out (a deactivate in the
        # end's linger is served, and the run ends as it would have: the process is not
        # kept standing for a run that has nothing left to step)
        while not self.active and not self.stop.is_set() and self.core.final_state is None:
            self.ctx.spin_once(HOLD_LOOK_S)

    def unanswered(self, k: int, first: bool) -> None:
        """A state is sent once: a command names no state, it answers the newest. One
        exception: realtime state 0, the only one a realtime run waits for, is published
        again every ``RESEND_S`` while no command at all has come, which no command can
        then mistake. A controller's publishers and another node's subscriptions can make
        the plant ready before the controller's own subscriptions are matched (discovery
        under load), and state 0 went to nobody: the run timed out after 10 s."""
        if self.cfg.run_mode != "realtime" or k != 0 or self._st0 is None:
            return
        now = time.monotonic()
        if first:
            self._sent0 = now
        elif now - self._sent0 >= RESEND_S:
            self.send_state(0, dict(self._st0), False)
            self._sent0 = now
            self.resent0 += 1
            if self.resent0 <= 3:
                log.info("state 0 unanswered for %g s: published again", RESEND_S)

    def send_state(self, k: int, st: dict, end: bool) -> None:
        if k == 0:
            self.msgs.reset()
            self._st0 = dict(st)
        msgs = dict(self.msgs.state_messages(st, markers=k % R.MARKER_EVERY == 0))
        for topic in (R.CLOCK, R.JOINT_STATES, R.WEAR, R.TF, R.ODOM, R.MARKERS):
            if topic in msgs and topic in self.pubs:
                self.pubs[topic].publish(R.encode(msgs[topic], R.TYPES[topic]))
        self._delta = np.asarray(st["delta"], dtype=float)
        self.rec.message("tx", self.key_state, M.encode_state(k, st, end=True if end else None))

    def applied(self, k: int, omega_w, omega_s, commanded: bool) -> None:
        if commanded:
            self.rec.message("rx", self.key_cmd,
                             M.encode_cmd(k, k * self.cfg.period, k, omega_w, omega_s))

    def ready(self) -> bool:
        """A controller is matched both ways: subscribed to ``odom`` and ``joint_states``
        and publishing both command topics (then state 0 goes out once: a command names no
        state, so a state is never sent twice and every command received after state k
        answers k)."""
        return (self.active and self.pubs[R.ODOM].get_subscription_count() > 0
                and self.pubs[R.JOINT_STATES].get_subscription_count() > 0
                and all(s.get_publisher_count() > 0 for s in self._subs))

    def waiting(self) -> str:
        return (f"waiting for a controller (subscribed to odom and joint_states, publishing "
                f"{R.STEERING_COMMANDS} and {R.WHEEL_COMMANDS})"
                + ("; the run's time is /clock's (use_sim_time)" if self.sim_time else ""))

    def no_controller(self) -> str:
        return (f"no controller within {self.cfg.wait_s:g} s: nothing subscribed to odom and "
                f"joint_states and publishing {R.STEERING_COMMANDS} and {R.WHEEL_COMMANDS}")

    def no_answer(self, k: int, timeout: float) -> str:
        return (f"{self.cfg.run_mode}: no commands on {R.STEERING_COMMANDS} and "
                f"{R.WHEEL_COMMANDS} answering state {k} (t = {k * self.cfg.period:.2f} s) "
                f"within {timeout:g} s")

    # ---- the run -----------------------------------------------------------------------
    def run(self) -> dict:
        self.core.run()
        return self.summary()

    def close(self) -> None:
        """The last status on ``/diagnostics`` (the run ended, or ERROR: it failed; the
        timer publishes only while the run waits), then a managed node not shut down yet
        is (a signal, the run's end), then its context closed."""
        try:
            if self.diag is not None and self.configured:
                self.diag.publish()
            if self.managed and not self._ended:
                self.ctx.node.trigger_shutdown()
        except Exception as e:  # (e.g. a second signal in mid-transition): the summary
            log.warning("lifecycle shutdown failed: %s", e)  # and the recording still go out
        finally:
            self.core.close()
            self.ctx.close()

    # ---- diagnostics ---------------------------------------------------------------------
    def diagnostics(self) -> tuple[int, str, dict]:
        """``(level, message, values)`` of the plant's status now (docs/ROS2.md,
        "Diagnostics"); values as strings. The lateness is that of the realtime steps since
        the last call (once a second: the last second's)."""
        core, cfg, T = self.core, self.cfg, self.cfg.period
        late = np.asarray(core.take_lateness(), dtype=float)
        k = self.seq
        rej = self.rej.summary()
        over = int(np.sum(late > T))
        v = {"lifecycle": self.state_label(), "run_mode": cfg.run_mode,
             "clock": "ros" if self.sim_time else "wall", "k": str(k),
             "t": f"{max(k, 0) * T:.6g}", "steps": str(cfg.steps),
             "period_ms": f"{T * 1000:g}",
             "safe": str(core.safe).lower(), "safe_reason": core.safe_why if core.safe else "",
             "commands_accepted": str(self.stats.accepted),
             "commands_rejected": str(rej["total"]),
             **{f"rejected_{r}": str(n) for r, n in sorted(rej["by_reason"].items())},
             "source_node": self.source_node or "", "rearms": str(self.rearms),
             "resets": str(core.resets), "missed_periods": str(self.stats.missed_periods),
             "steps_last_s": str(late.size),
             "lateness_ms_p99": f"{np.percentile(late, 99) * 1000:.3f}" if late.size else "none",
             "stale_ms": f"{cfg.stale_ms:g}", "max_missed": str(core.watch.max_missed),
             "resume_periods": str(core.watch.resume_periods),
             "safe_decel": f"{cfg.safe_decel:g}"}
        if core.error is not None:
            return ERROR, f"failed: {core.error}", v
        if not self.active:
            return WARN, self.state_label(), v
        if core.final_state is not None:
            return OK, "run ended", v
        if k < 0:
            return WARN, "waiting for a controller", v
        if core.safe:
            return STALE, f"safe: {core.safe_why}", v
        if over:
            return WARN, f"{over} of {late.size} steps over a period late in the last second", v
        return OK, "running", v

    def summary(self) -> dict:
        st = self.stats
        return {"role": "ros2 plant", **self.core.summary(),
                "parameters": self.params, "resets": self.core.resets,
                "parameter_changes": self.parameter_changes,
                "parameters_refused": self.parameters_refused,
                "clock": "ros" if self.sim_time else "wall",
                "commands": {"accepted": st.accepted, "after_end": st.after_end},
                "sources": {t: (g.hex() if g is not None else None)
                            for t, g in self.sources.items()},
                "source_node": self.source_node, "rearms": self.rearms,
                "state0_resent": self.resent0,
                "rejected": self.rej.summary(), "tf": self.tf_published,
                **({"lifecycle": self.state_label(), "transitions": self.lifecycle.summary()}
                   if self.managed else {})}
