"""The plant's run, written once for every transport: lockstep, real time, the safe
behaviour and its watchdog, on the run's clock.

:class:`PlantRun` takes a plant (anything with :class:`plant.interface.PlantInterface`)
through one run and knows nothing of a bus. What it needs of a transport is the small
application-level port :class:`PlantPort` (send a state, the command answering a state,
the newest command, the controller's presence, wait for news); the Zenoh plant
(:class:`bridge.plant_node.PlantNode`: ownership, claims, liveliness, re-sends) and the ROS 2
plant (:class:`ros2.plant_node.RosPlant`: topics, steering targets) are its two ports, and a
test drives it with a port of a few lines.

Time is the injected :class:`Clock`: its ``now()`` paces the real-time steps, measures
their lateness, bounds the waits (``wait_s``, ``timeout_s``) and the watchdog's deadline;
the linger after the end state alone is wall time (a simulator's clock may stop with the
run). :class:`WallClock` (the default) is the wall clock; the ROS 2 plant
under ``use_sim_time`` gives ROS time (a simulator's ``/clock``, at whatever pace it runs).
The staleness bound is counted in periods of that clock (:class:`bridge.loss.CommandWatch`),
so a clock at 0.2x or 5x real time changes nothing but the wall time a run takes. The
round-trip times (state sent -> command received) stay on the wall clock: they measure
the machine, not the run.

Modes (docs/PROTOCOL.md, "Modes"):

* ``lockstep``: send state k, step when the command answering k arrives; no answer within
  ``timeout_s`` ends the run (:class:`PlantRunError`).
* ``realtime``: after the first answer, step at every period of the clock with the newest
  command; :class:`bridge.loss.CommandWatch` decides every period (run, hold, safe: steering
  held, wheels ramped down at ``safe_decel``). A watchdog thread runs the safe behaviour
  while the loop itself is more than ``stale_ms`` past a deadline (stuck in the bus).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from msagv.controller.metrics import StreamPercentiles, percentiles
from msagv.plant.signals import BODY_FIELDS, CONTROL_PERIOD, WEAR_FIELDS, WHEEL_WEAR_FIELDS

from . import messages as M
from .loss import RESUME_PERIODS, SAFE_DECEL, STALE_MS, CommandWatch
from .recording import NullRecorder

WAIT_CONTROLLER_S = 0.02  # how often the wait for a controller looks again (at most)
WAIT_ANSWER_S = 0.05  # how often the wait for an answer looks again (at most)


RESEND_S = 1.0  # an unanswered state is published again after this long (lockstep; ROS 2
#                realtime: state 0 while no command has come)


class PlantRunError(RuntimeError):
    """The run cannot go on (no controller, a lockstep timeout, a failed step)."""


class _Restart(Exception):
    """Raised out of a wait after :meth:`PlantRun.reset`: the run starts again at state 0."""


@dataclass
class RunConfig:
    """How a plant runs, whatever the transport (the defaults, written once: the command
    lines read them).

    run_mode : 'lockstep' or 'realtime'.
    period : control period T [s]; state k has t = k T exactly.
    steps : periods to run; the last state (seq = steps) is the end state.
    timeout_s : lockstep: the longest wait for a command answering the current state;
        realtime: for the first command (answering state 0). Exceeded: the run ends.
    wait_s : how long to wait for a controller at start (0: forever).
    stale_ms : realtime: more than ``stale_ms / T`` consecutive periods without an answer
        put the plant in its safe behaviour.
    safe_decel : realtime safe behaviour: wheel-speed ramp-down [m/s^2 at the rim].
    linger_s : after the end state, how long to go on taking messages (the last ones are
        delivered, late commands still counted) before closing; wall-clock time.
    resume_periods : realtime: consecutive periods in which the controller keeps up (its
        newest command answers the current or the previous state) before the safe
        behaviour ends.
    The other times are on the run's clock (:class:`Clock`).
    """

    run_mode: str = "lockstep"
    period: float = CONTROL_PERIOD
    steps: int = 100
    timeout_s: float = 10.0
    wait_s: float = 60.0
    stale_ms: float = STALE_MS
    safe_decel: float = SAFE_DECEL
    linger_s: float = 0.2
    resume_periods: int = RESUME_PERIODS

    def __post_init__(self):
        if self.run_mode not in M.RUN_MODES:
            raise ValueError(f"run mode: expected lockstep or realtime, got '{self.run_mode}'")
        if not (self.period > 0 and math.isfinite(self.period)):
            raise ValueError(f"--period must be > 0, got {self.period}")
        if self.steps < 1:
            raise ValueError("--duration must be at least one period")
        for name, v in (("--timeout", self.timeout_s), ("--stale-ms", self.stale_ms),
                        ("--safe-decel", self.safe_decel)):
            if not (v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be > 0, got {v}")
        if not self.wait_s >= 0:
            raise ValueError(f"--wait must be >= 0, got {self.wait_s}")
        if not self.linger_s >= 0:
            raise ValueError(f"linger_s must be >= 0, got {self.linger_s}")
        if not 1 <= self.resume_periods <= 1000:
            raise ValueError(f"--resume-periods must be 1..1000, got {self.resume_periods}")

    @property
    def max_missed(self) -> int:
        """Consecutive periods without an answer the realtime plant tolerates (DCP's maximum
        consecutive missed PDUs): ``floor(stale_ms / T)``."""
        return int(math.floor(self.stale_ms / 1000.0 / self.period + 1e-9))


# ---- the clock ------------------------------------------------------------------------------
class Clock(Protocol):
    """The run's time."""

    def now(self) -> float:
        """The time [s], never decreasing."""

    def wall(self, dt: float) -> float:
        """The longest wall-clock wait [s] in which at most ``dt`` of this clock passes (a
        wait for a time of this clock looks again after at most this long)."""


class WallClock:
    """The wall clock (``time.perf_counter``): the default."""

    def now(self) -> float:
        return time.perf_counter()

    def wall(self, dt: float) -> float:
        return dt


class PausableClock:
    """Another clock (``inner``) that stands while paused: the time of a run held between
    two steps (a managed node deactivated holds it in the port's ``idle``) is none of the
    run's. Resumed, it goes on from where it stood: no period missed, no command aged, no
    wait's bound (``wait_s``, ``timeout_s``) used, the watchdog not tripped, the real-time
    clock not re-anchored. ``paused``: it starts paused (a node not yet activated)."""

    def __init__(self, inner: Clock, paused: bool = False):
        self.inner = inner
        self._lock = threading.Lock()  # (the run's thread and the watchdog's read it)
        self._off = 0.0  # the inner clock's time spent paused
        self._since: float | None = inner.now() if paused else None  # paused since

    @property
    def paused(self) -> bool:
        return self._since is not None

    def now(self) -> float:
        with self._lock:
            t = self._since if self._since is not None else self.inner.now()
            return t - self._off

    def wall(self, dt: float) -> float:
        return self.inner.wall(dt)

    def pause(self) -> None:
        with self._lock:
            if self._since is None:
                self._since = self.inner.now()

    def resume(self) -> None:
        with self._lock:
            if self._since is not None:
                self._off += max(0.0, self.inner.now() - self._since)
                self._since = None


# ---- the port -------------------------------------------------------------------------------
@dataclass
class Command:
    """A command as the run applies it: the state it answers, wheel speeds [rad/s],
    steering rates [rad/s]."""

    state_seq: int
    omega_w: Any
    omega_s: Any


class PlantPort(Protocol):
    """What the run needs of a transport. Called from the run's thread; ``newest`` and
    ``present`` under the run's :attr:`PlantRun.lock` (they must not take it)."""

    def ready(self) -> bool:
        """A controller is there to run with (the run then sends state 0)."""

    def send_state(self, k: int, state: dict, end: bool) -> None:
        """Send state ``k`` (``state['t'] = k T``); ``end``: the last one."""

    def answer(self, k: int) -> Command | None:
        """The valid command answering state ``k``, if it came."""

    def newest(self) -> Command | None:
        """The newest valid command (realtime: applied at the next step)."""

    def present(self) -> bool:
        """Whether the controller is present (a transport without presence: True)."""

    def idle(self, seconds: float, wake: bool = True) -> None:
        """Wait up to ``seconds`` (wall), running the transport's callbacks where it needs
        that; ``wake``: return early on news (a command, the controller's presence).
        ``wake=False`` is the real-time step's wait for its time: the step reads the newest
        command when it comes, so a transport whose callbacks run on threads of their own
        may just sleep."""

    def unanswered(self, k: int, first: bool) -> None:
        """Called while the run waits for state ``k``'s answer (``first``: as it starts):
        where the transport may lose a state, it sends it again here."""

    def applied(self, k: int, omega_w, omega_s, commanded: bool) -> None:
        """The inputs of step ``k`` (``commanded``: a controller's, else the safe
        behaviour's), before the plant steps with them."""

    def waiting(self) -> str:
        """The log line while no controller is there (said once, after a second)."""

    def no_controller(self) -> str:
        """The error when no controller came within ``wait_s``."""

    def no_answer(self, k: int, timeout: float) -> str:
        """The error when state ``k`` was not answered within ``timeout``."""


# ---- the run --------------------------------------------------------------------------------
@dataclass
class PlantStats:
    """The run's counters (the command counters are kept by the port, which validates)."""

    accepted: int = 0
    stale: int = 0  # valid but older than the newest accepted (out of order)
    duplicate: int = 0
    after_end: int = 0  # valid answers to the end state (never applied)
    late: int = 0  # realtime: accepted commands that arrived after their state's step
    cmd_seq_gaps: int = 0
    safe_events: int = 0
    safe_periods: int = 0
    resumes: int = 0
    missed_periods: int = 0
    clock_resyncs: int = 0
    watchdog_trips: int = 0  # the loop missed its deadline by more than stale_ms
    watchdog_periods: int = 0  # periods of safe behaviour run by the watchdog
    resent: int = 0  # states sent again because their answer did not come
    # the durations [s] of every period or answer, in bounded memory (a run of hours adds
    # one per period: exact up to 4096 values, then within 0.5 %, controller.metrics)
    latency_s: StreamPercentiles = field(default_factory=StreamPercentiles)  # state sent ->
    # command received, minus the controller's solve
    roundtrip_s: StreamPercentiles = field(default_factory=StreamPercentiles)  # state sent ->
    # command received (wall)
    lateness_s: StreamPercentiles = field(default_factory=StreamPercentiles)  # state sent -
    # its due time (run's clock)
    jitter_s: StreamPercentiles = field(default_factory=StreamPercentiles)  # |interval
    # between two states sent - T|


def percentiles_ms(values_s) -> dict:
    """Percentiles in ms of durations given in s (:func:`controller.metrics.percentiles`, or
    a :class:`controller.metrics.StreamPercentiles`'s)."""
    if isinstance(values_s, StreamPercentiles):
        return values_s.percentiles(scale=1000.0, count=True)
    return percentiles(values_s, scale=1000.0, count=True)


class PlantRun:
    """One run of ``plant`` (see the module). ``port``: the transport's side
    (:class:`PlantPort`); ``clock``: the run's time (:class:`WallClock` if None);
    ``recorder``: a recorder (:class:`bridge.recording.NullRecorder` if None), given the
    safe behaviour's events and flushed as the run goes; ``log``: the logger of the node
    that runs it; ``stop``: an event that ends the run early; ``stats``: the counters (a
    port may keep more of them in a subclass of :class:`PlantStats`)."""

    def __init__(self, plant, cfg: RunConfig, port: PlantPort, *, clock: Clock | None = None,
                 recorder=None, log: logging.Logger | None = None,
                 stop: threading.Event | None = None, stats: PlantStats | None = None,
                 measure=None):
        self.plant = plant
        # what the published states carry of the plant's (plant.sensors.MeasurementNoise):
        # state k's measurement, drawn once, so that a state sent again is the same message
        self.measure = measure
        self._measured: tuple[tuple, dict] | None = None
        self.cfg = cfg
        self.port = port
        self.nw = plant.vehicle.n_wheels
        self.clock = clock if clock is not None else WallClock()
        self.rec = recorder if recorder is not None else NullRecorder()
        self.log = log if log is not None else logging.getLogger("msagv.plant")
        self.stop = stop if stop is not None else threading.Event()
        self.stats = stats if stats is not None else PlantStats()
        self.watch = CommandWatch(cfg.max_missed, cfg.resume_periods, cfg.period)
        self.ramp = cfg.safe_decel / plant.vehicle.wheel_radius  # rad/s^2
        self.lock = threading.Lock()  # seq, stepped, pub_perf (the run and the port's threads)
        self.plant_lock = threading.Lock()  # the plant's inputs and step (loop, watchdog)
        self.closed = threading.Event()
        self.seq = -1  # the newest state sent
        self.stepped = -1  # realtime: the newest step taken (its command chosen)
        self.pub_perf: OrderedDict[int, float] = OrderedDict()  # state -> sent (wall)
        self.safe = False
        self.error: str | None = None
        self.final_state: dict | None = None
        self._due: float | None = None  # realtime: the clock's time the next step is due by
        self._wd_trip: str | None = None  # set by the watchdog, taken by the loop
        self._trip_lock = threading.Lock()
        self._wd_active = False
        self.safe_why = ""  # why the safe behaviour was entered (while :attr:`safe`)
        # realtime: each step's lateness [s] (as ``stats.lateness_s``), until a reader takes
        # them (a node's diagnostics, once a second: :meth:`take_lateness`)
        self._recent = deque(maxlen=4096)
        self.resets = 0
        self._restart = False  # reset: the waits raise _Restart, the run starts again
        self._gen = 0  # the run's generation (a reset's watchdog is a new one)

    # ---- states and steps ----------------------------------------------------------------
    def publish_state(self, k: int, end: bool = False) -> None:
        """Send state ``k`` (its time ``k T`` exactly: time never drifts)."""
        st = self.plant.state_message()
        st["t"] = k * self.cfg.period
        with self.lock:
            self.seq = k
            self.pub_perf[k] = time.perf_counter()
            while len(self.pub_perf) > 4096:
                self.pub_perf.popitem(last=False)
        if self.measure is not None:
            key = (k, st["x"], st["y"], st["phi"], st["vx"], st["vy"], st["r"])
            if self._measured is None or self._measured[0] != key:
                self._measured = (key, self.measure(st))
            sent = dict(self._measured[1])
        else:
            sent = st
        self.port.send_state(k, sent, end)
        if end:
            self.final_state = st

    def apply(self, k: int, omega_w, omega_s, commanded: bool = True) -> None:
        """Step the plant one period from state ``k`` with these inputs."""
        from msagv.plant.interface import PlantError

        self.port.applied(k, omega_w, omega_s, commanded)
        try:
            with self.plant_lock:
                self.plant.set_inputs(omega_w, omega_s)
                self.plant.do_step(self.plant.t, self.cfg.period)
        except PlantError as e:
            raise PlantRunError(f"step at t = {self.plant.t:.2f} s failed: {e}") from None

    def _safe_inputs(self) -> tuple[np.ndarray, np.ndarray]:
        """One period of the safe behaviour: steering held, wheels ramped down."""
        held_w, _ = self.plant.inputs
        return (np.maximum(np.asarray(held_w) - self.ramp * self.cfg.period, 0.0),
                np.zeros(self.nw))

    # ---- waits ---------------------------------------------------------------------------
    def _idle(self, seconds: float, wake: bool = True) -> None:
        """The port's idle (its callbacks run there); a reset in it starts the run again."""
        self.port.idle(seconds, wake)
        if self._restart:
            raise _Restart()

    def _idle_until(self, t: float) -> None:
        """Wait until the clock reaches ``t``, or the run is stopped."""
        while not self.stop.is_set():
            left = t - self.clock.now()
            if left <= 0:
                return
            self._idle(self.clock.wall(left), wake=False)

    def wait_controller(self) -> None:
        """Until the port is ready (a controller there); PlantRunError after ``wait_s``."""
        c, t0, told = self.clock, self.clock.now(), False
        while not self.stop.is_set():
            if self.port.ready():
                return
            waited = c.now() - t0
            if not told and waited > 1.0:
                self.log.info("%s", self.port.waiting())
                told = True
            if self.cfg.wait_s and waited > self.cfg.wait_s:
                raise PlantRunError(self.port.no_controller())
            self._idle(c.wall(WAIT_CONTROLLER_S))

    def wait_answer(self, k: int) -> Command | None:
        """The command answering state ``k`` (lockstep: every k; realtime: k = 0); None if
        stopped; PlantRunError after ``cfg.timeout_s`` (read as the wait goes: a
        :meth:`reconfigure` during it counts)."""
        c, t0 = self.clock, self.clock.now()
        self.port.unanswered(k, True)
        while True:
            if self.stop.is_set():  # (before the answer: a managed plant shut down while
                return None  # inactive, its answer in, stepped once more, unpublished)
            a = self.port.answer(k)
            if a is not None:
                return a
            timeout_s = self.cfg.timeout_s
            if c.now() - t0 > timeout_s:
                raise PlantRunError(self.port.no_answer(k, timeout_s))
            self.port.unanswered(k, False)
            self._idle(c.wall(WAIT_ANSWER_S))

    def linger(self) -> None:
        """After the end state: take messages for ``linger_s`` more, of the wall clock (the
        run's clock may stop with the run: a simulator's ``/clock``)."""
        end = time.monotonic() + self.cfg.linger_s
        while not self.stop.is_set() and (left := end - time.monotonic()) > 0:
            self._idle(left)

    # ---- runs ----------------------------------------------------------------------------
    def run(self) -> None:
        """Wait for a controller, run to the end (or until :attr:`stop`). Raises
        PlantRunError on a timeout or a failed step (also kept in :attr:`error`)."""
        try:
            while True:
                try:
                    self.wait_controller()
                    if not self.stop.is_set():
                        if self.cfg.run_mode == "lockstep":
                            self._run_lockstep()
                        else:
                            self._run_realtime()
                    break
                except _Restart:  # reset (in a wait): from state 0 again
                    self._restart = False
        except PlantRunError as e:
            self.error = str(e)
            raise
        finally:
            if self.final_state is None:
                st = self.plant.state_message()
                st["t"] = max(self.seq, 0) * self.cfg.period
                self.final_state = st

    def _run_lockstep(self) -> None:
        cfg = self.cfg
        self.publish_state(0)
        for k in range(cfg.steps):
            c = self.wait_answer(k)
            if c is None:
                return
            self.apply(k, c.omega_w, c.omega_s)
            self.publish_state(k + 1, end=k + 1 == cfg.steps)
            self.rec.maybe_flush()
        self.linger()

    def _run_realtime(self) -> None:
        cfg, T, st, clock, log = self.cfg, self.cfg.period, self.stats, self.clock, self.log
        self.publish_state(0)
        # the clock starts with the first command (the controller is warm by then)
        if self.wait_answer(0) is None:
            return
        w0 = clock.now()
        last_pub = w0
        self._due = w0 + 2 * T
        threading.Thread(target=self._watchdog, args=(self._gen,), daemon=True,
                         name="plant watchdog").start()
        for k in range(cfg.steps):
            target = w0 + (k + 1) * T
            self._idle_until(target)
            now = clock.now()
            if now - target > 10 * T:  # stalled (e.g. the machine froze): re-anchor
                st.clock_resyncs += 1
                w0 += (now - target)
                target = now
            if self.stop.is_set():
                return
            with self.lock:
                n = self.port.newest()
                present = self.port.present()
                self.stepped = k
            with self._trip_lock:  # (the watchdog's trip is never lost between the two)
                trip, self._wd_trip = self._wd_trip, None
            if trip is not None:
                d = self.watch.force_safe(trip)
            else:
                d = self.watch.step(k, n.state_seq if n is not None else None, present)
            if d.resumed:
                self.safe = False
                st.resumes += 1
                log.warning("resumed normal operation at t = %.2f s (the controller kept up "
                            "for %d periods; newest command answers state %d)", k * T,
                            self.cfg.resume_periods, n.state_seq)
                self.rec.event("safe", on=False, t=k * T)
            if d.use_command:
                u_w, u_s = n.omega_w, n.omega_s
            else:
                if d.entered_safe is not None:
                    self.safe = True
                    self.safe_why = d.entered_safe
                    st.safe_events += 1
                    log.warning("SAFE at t = %.2f s: %s; holding steering, ramping the wheels "
                                "down at %g m/s^2", k * T, d.entered_safe,
                                self.cfg.safe_decel)
                    self.rec.event("safe", on=True, t=k * T, why=d.entered_safe)
                st.safe_periods += 1
                u_w, u_s = self._safe_inputs()
            self.apply(k, u_w, u_s, commanded=d.use_command)
            self.publish_state(k + 1, end=k + 1 == cfg.steps)
            done = clock.now()
            st.lateness_s.add(done - target)
            self._recent.append(done - target)
            st.jitter_s.add(abs(done - last_pub - T))
            last_pub = done
            if done - target > T:
                st.missed_periods += 1
            # the next period is due one period after its target (a loop that is behind, and
            # catches up or re-anchors its clock next, gets two periods from now)
            self._due = max(w0 + (k + 3) * T, done + 2 * T)
            self._wd_active = False
            self.rec.maybe_flush()
        self._due = None
        self.linger()

    def _watchdog(self, gen: int) -> None:
        """Realtime: while the loop is more than ``stale_ms`` past a period's deadline, run
        the safe behaviour here (steering held, wheels ramped down at ``safe_decel``), one
        period at a time. It touches the plant (under the plant's own lock) and the log,
        nothing of the transport: a loop stuck in the bus does not stop it. It ends with
        its run (``gen``: a reset starts another)."""
        T, st = self.cfg.period, self.stats
        while not (self.stop.wait(self.clock.wall(T)) or self.closed.is_set()):
            if gen != self._gen:
                return
            bound = self.cfg.stale_ms / 1000.0  # (changed at run time: reconfigure)
            due = self._due
            if due is None:
                if self.final_state is not None:
                    return
                continue
            late = self.clock.now() - due
            if late <= bound:
                continue
            if not self._wd_active:
                why = (f"the plant's own loop is {late * 1000:.0f} ms past its deadline "
                       f"(bound {self.cfg.stale_ms:g} ms): the watchdog runs the safe "
                       f"behaviour")
                # the loop takes the trip at its next step and raises the published flag
                # itself: the flag of a state says what the step that made it applied (set
                # here, a state stepped with the held command could go out flagged safe)
                with self._trip_lock:  # (its own lock: never one the transport holds)
                    if gen != self._gen:  # a reset came since the look above: not its run
                        return
                    self._wd_active = True
                    self._wd_trip = why
                st.watchdog_trips += 1
                self.log.warning("SAFE (watchdog) at t = %.2f s: %s", max(self.seq, 0) * T, why)
            if self.plant_lock.acquire(timeout=self.clock.wall(T)):
                try:
                    if gen != self._gen:  # (reset under this lock: its plant is not ours)
                        return
                    self.plant.set_inputs(*self._safe_inputs())
                    st.watchdog_periods += 1
                except Exception as e:  # the plant refused: said once per trip, loop decides
                    self.log.error("watchdog: the safe behaviour failed: %s", e)
                finally:
                    self.plant_lock.release()

    def close(self) -> None:
        """The run's threads (the watchdog) end."""
        self.closed.set()

    # ---- changes from outside (a node's services and parameters, in the run's thread) ----
    def reconfigure(self, cfg: RunConfig) -> None:
        """Take the safe behaviour's settings of ``cfg`` (``stale_ms``, ``resume_periods``,
        ``safe_decel``, ``timeout_s``) from the next period on; the others must not differ
        (ValueError, nothing changed): they fix the run's time axis and contract."""
        fixed = [k for k in ("run_mode", "period", "steps", "wait_s", "linger_s")
                 if getattr(cfg, k) != getattr(self.cfg, k)]
        if fixed:
            raise ValueError(f"{fixed[0]} is fixed for the run")
        self.cfg = cfg
        self.watch.max_missed = cfg.max_missed
        self.watch.resume_periods = cfg.resume_periods
        self.ramp = cfg.safe_decel / self.plant.vehicle.wheel_radius

    def resettable(self) -> str | None:
        """Why :meth:`reset` cannot be honoured now, or None."""
        if self.error is not None:
            return f"the run failed ({self.error})"
        if self.final_state is not None:
            return "the run has ended (its end state is out)"
        return None

    def reset(self) -> None:
        """Back to the start: the plant at its initial state (``plant.reset()``: pose,
        velocities, steering, wheel speeds, its wear integrals zero, t = 0), no state sent,
        the safe behaviour and its counts of periods (``periods``) afresh; the run then
        starts again as a new one would (waits for a controller, sends state 0). Call it
        from the run's thread (a port's callback in ``idle``): the wait it is called in
        starts the run again. The port forgets the answers it holds itself (a command
        names the state it answers by its index: the run before's answer to state 0
        would answer the new state 0; the ROS 2 plant clears them in its ``~/reset``). The command counters and the round-trip statistics go on
        over the process (:attr:`resets` counts the resets)."""
        why = self.resettable()
        if why is not None:
            raise PlantRunError(why)
        with self._trip_lock:  # first: the watchdog of the run before ends (it looks at
            self._gen += 1  # the generation under this lock and under the plant's)
            self._wd_trip = None
            self._due = None
            self._wd_active = False
        with self.plant_lock:
            self.plant.reset()
        with self.lock:
            self.seq = self.stepped = -1
            self.pub_perf.clear()
        self.safe, self.safe_why = False, ""
        self.watch = CommandWatch(self.cfg.max_missed, self.cfg.resume_periods, self.cfg.period)
        self._recent.clear()
        self.resets += 1
        self._restart = True
        self.rec.event("reset")
        self.log.warning("reset: the plant is back at its initial state, the run starts again "
                         "at state 0 (t = 0)")

    def take_lateness(self) -> list[float]:
        """The realtime steps' lateness [s] since the last call."""
        out = list(self._recent)
        self._recent.clear()
        return out

    # ---- results -------------------------------------------------------------------------
    def answered(self, j: int, rx_perf: float, solve_ms: float | None = None) -> None:
        """A valid command answering state ``j`` was received at ``rx_perf``
        (``time.perf_counter``): its round trip (and, given the controller's solve time,
        the latency without it) is counted. Under :attr:`lock`."""
        tp = self.pub_perf.get(j)
        if tp is not None:
            rt = rx_perf - tp
            self.stats.roundtrip_s.add(rt)
            if solve_ms is not None:
                self.stats.latency_s.add(rt - solve_ms / 1000.0)

    def summary(self) -> dict:
        """The run's part of a node's summary (the node adds its own)."""
        st, T = self.stats, self.cfg.period
        steps_done = max(self.seq, 0)
        fs = self.final_state or {}
        return {
            "run_mode": self.cfg.run_mode, "period": T, "steps": steps_done,
            "t_end": steps_done * T,
            "completed": steps_done == self.cfg.steps and self.error is None,
            "error": self.error,
            "missed_periods": st.missed_periods, "clock_resyncs": st.clock_resyncs,
            "latency_ms": percentiles_ms(st.latency_s),
            "roundtrip_ms": percentiles_ms(st.roundtrip_s),
            "lateness_ms": percentiles_ms(st.lateness_s),
            "period_jitter_ms": percentiles_ms(st.jitter_s),
            "safe": {"events": st.safe_events, "periods": st.safe_periods, "resumes": st.resumes,
                     "watchdog_trips": st.watchdog_trips,
                     "watchdog_periods": st.watchdog_periods},
            "periods": self.watch.summary() if self.cfg.run_mode == "realtime" else None,
            "final_state": {k: fs[k] for k in ("t",) + BODY_FIELDS + WEAR_FIELDS
                            + WHEEL_WEAR_FIELDS if k in fs},
        }
