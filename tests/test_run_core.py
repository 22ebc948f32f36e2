"""The plant's run core (bridge/run_core.py) on an injected clock, with no transport.

The clock here is a discrete-event one: its time moves only while the run waits (the
port's ``idle``), by the wall time waited times its rate, and never past the next answer,
so a run takes no wall time at all and every figure is exact. A controller that needs a
fixed wall time per answer is, on a clock at 0.2x real time, on time every period, and on a
clock at 5x ten periods late: the run steps, ages the commands and goes safe on the clock
it is given, and the counts below are worked out by hand from that alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from msagv.bridge.run_core import Command, PlantRun, PlantRunError, RunConfig
from msagv.plant import Plant, default_vehicle

T = 0.01
W = 8.0  # the controller's wheel speeds [rad/s]


class SimClock:
    """Run time that passes only in :meth:`FakePort.idle`: ``rate`` clock seconds per wall
    second (0.2: a simulator slower than real time; 5: faster)."""

    def __init__(self, rate: float):
        self.rate = rate
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def wall(self, dt: float) -> float:
        return dt / self.rate


class FakePort:
    """A controller that answers every state ``solve_wall`` s of wall time after it was
    sent (pipelined), with wheel speeds W and no steering; ``answers=False``: never."""

    def __init__(self, clock: SimClock, solve_wall: float, answers: bool = True,
                 ready: bool = True):
        self.clock, self.delay = clock, solve_wall * clock.rate  # in clock time
        self.answers, self.is_ready = answers, ready
        self.sent: dict[int, float] = {}  # state -> clock time sent
        self.states: dict[int, dict] = {}
        self.steps: list[tuple[int, np.ndarray, bool]] = []  # (k, omega_w, commanded)

    def _visible(self) -> list[int]:
        now = self.clock.now()
        return [k for k, t in self.sent.items() if self.answers and t + self.delay <= now]

    def _next_answer(self) -> float:
        pending = [t + self.delay for t in self.sent.values()
                   if self.answers and t + self.delay > self.clock.now()]
        return min(pending, default=float("inf"))

    # the port
    def ready(self) -> bool:
        return self.is_ready

    def send_state(self, k, st, end):
        self.sent[k] = self.clock.now()
        self.states[k] = st

    def answer(self, k):
        return Command(k, [W] * 4, [0.0] * 4) if k in self._visible() else None

    def newest(self):
        v = self._visible()
        return Command(max(v), [W] * 4, [0.0] * 4) if v else None

    def present(self) -> bool:
        return True

    def idle(self, seconds: float, wake: bool = True) -> None:
        c = self.clock
        c.t = min(c.t + seconds * c.rate, max(self._next_answer(), c.t))

    def unanswered(self, k, first):
        pass

    def applied(self, k, omega_w, omega_s, commanded):
        self.steps.append((k, np.array(omega_w, dtype=float), commanded))

    def waiting(self) -> str:
        return "waiting"

    def no_controller(self) -> str:
        return "no controller"

    def no_answer(self, k, timeout) -> str:
        return f"no answer to state {k}"


def _run(rate: float, solve_wall: float, steps: int = 40, **cfg):
    vehicle = default_vehicle()
    clock = SimClock(rate)
    port = FakePort(clock, solve_wall)
    cfg = RunConfig(run_mode="realtime", period=T, steps=steps, stale_ms=50.0,
                    resume_periods=3, **cfg)
    run = PlantRun(Plant(vehicle, initial={"vx": 4.0}), cfg, port, clock=clock)
    try:
        run.run()
    finally:
        run.close()
    return run, port, vehicle


@pytest.mark.parametrize("rate", [0.2, 5.0])
def test_the_run_steps_and_goes_safe_on_the_clock_it_is_given(rate):
    """The same controller (21 ms of wall time per answer) against a run on a clock at
    ``rate`` times real time: 4.2 ms of clock time at 0.2x, every state answered within
    its period; 105 ms at 5x, more than the 50 ms staleness bound (5 periods)."""
    n = 40
    run, port, vehicle = _run(rate, 0.021, steps=n)
    s = run.summary()
    d = 0.021 * rate
    assert s["completed"] and s["steps"] == n and s["t_end"] == pytest.approx(n * T)
    # the clock starts with the answer to state 0 (d after it was sent) and state k + 1 is
    # sent at the clock's w0 + (k + 1) T exactly: time as the clock says, nothing late
    w0 = d
    for k in range(1, n + 1):
        assert port.sent[k] == pytest.approx(w0 + k * T, abs=1e-12)
        assert port.states[k]["t"] == pytest.approx(k * T, abs=1e-15)
    assert s["missed_periods"] == 0 and s["lateness_ms"]["max"] == pytest.approx(0.0, abs=1e-9)
    assert [k for k, _, _ in port.steps] == list(range(n))
    ramp = run.cfg.safe_decel / vehicle.wheel_radius * T
    if rate == 0.2:
        # step k at w0 + (k + 1) T: the answer to state k (sent at w0 + k T) came d < T
        # later, so the newest command answers the current state every period
        assert s["periods"]["on_time"] == n and s["periods"]["held"] == 0
        assert s["safe"]["events"] == 0 and s["safe"]["periods"] == 0
        assert all(c and np.all(w == W) for _, w, c in port.steps)
    else:
        # d = 10.5 periods: up to step 9 the newest answer is state 0's (age k), then state
        # k - 10's (age 10). Age 0 at step 0 runs, ages 1..5 hold (bound 5 periods), age 6
        # at step 6 goes safe, and an age of 10 never resumes (it needs age <= 1)
        assert s["periods"]["on_time"] == 1 and s["periods"]["held"] == 5
        assert s["periods"]["safe"] == n - 6 and s["periods"]["max_consecutive_missed"] == 6
        assert s["safe"]["events"] == 1 and s["safe"]["periods"] == n - 6
        assert s["safe"]["resumes"] == 0
        for k, w, commanded in port.steps:
            if k < 6:
                assert commanded and np.all(w == W)
            else:  # steering held, wheels ramped down from W at safe_decel, period by period
                assert not commanded
                assert np.allclose(w, max(W - (k - 5) * ramp, 0.0), atol=1e-12)


@pytest.mark.parametrize("rate", [0.2, 5.0])
def test_the_lockstep_timeout_and_the_wait_count_the_clocks_time(rate):
    """A controller that never answers: the run ends after ``timeout_s`` of the clock's
    time, not the wall's (at 0.2x that is five times as long on the wall); one that never
    comes: after ``wait_s``."""
    vehicle = default_vehicle()
    clock = SimClock(rate)
    port = FakePort(clock, 0.0, answers=False)
    run = PlantRun(Plant(vehicle), RunConfig(run_mode="lockstep", steps=5, timeout_s=2.0),
                   port, clock=clock)
    with pytest.raises(PlantRunError, match="no answer to state 0"):
        run.run()
    assert 2.0 < clock.now() <= 2.0 + 0.05 + 1e-9  # the last look came within one wait
    assert run.summary()["error"] == "no answer to state 0" and not run.summary()["completed"]

    clock = SimClock(rate)
    port = FakePort(clock, 0.0, ready=False)
    run = PlantRun(Plant(vehicle), RunConfig(wait_s=3.0, steps=5), port, clock=clock)
    with pytest.raises(PlantRunError, match="no controller"):
        run.run()
    assert 3.0 < clock.now() <= 3.0 + 0.02 + 1e-9
    assert port.sent == {}  # no state before a controller


def test_a_lockstep_run_applies_each_answer_to_its_state():
    """Lockstep on the injected clock: state k + 1 goes out when state k's answer came, its
    time k T whatever the clock says; the inputs applied are the controller's."""
    clock = SimClock(1.0)
    port = FakePort(clock, 0.003)
    run = PlantRun(Plant(default_vehicle(), initial={"vx": 4.0}),
                   RunConfig(run_mode="lockstep", steps=10, linger_s=0.0), port, clock=clock)
    run.run()
    s = run.summary()
    assert s["completed"] and s["periods"] is None and s["safe"]["events"] == 0
    for k in range(1, 11):  # answered 3 ms after it was sent, the next one sent then
        assert port.sent[k] == pytest.approx(k * 0.003, abs=1e-12)
        assert port.states[k]["t"] == pytest.approx(k * T, abs=1e-15)
    assert [(k, c) for k, _, c in port.steps] == [(k, True) for k in range(10)]


def test_bad_run_settings_are_refused_with_one_line():
    for kw, says in ((dict(run_mode="fast"), "run mode"), (dict(period=0.0), "--period"),
                     (dict(steps=0), "--duration"), (dict(timeout_s=-1.0), "--timeout"),
                     (dict(stale_ms=float("nan")), "--stale-ms"), (dict(wait_s=-1), "--wait"),
                     (dict(resume_periods=0), "--resume-periods"),
                     (dict(safe_decel=0.0), "--safe-decel")):
        with pytest.raises(ValueError, match=says) as e:
            RunConfig(**kw)
        assert "\n" not in str(e.value)
    assert RunConfig(stale_ms=50.0, period=0.01).max_missed == 5


class PausingPort(FakePort):
    """A port that, in its wait before step ``at``, holds the run for ``pause`` s of the
    clock's time (as a managed node deactivated holds it in its callbacks), with the run's
    clock paused while it does if ``pausable`` is that clock. The controller was held as
    well: the answer it owed at the pause comes ``solve_wall`` after the run resumes."""

    def __init__(self, clock: SimClock, pausable, at: int, pause: float):
        super().__init__(clock, 0.003)
        self.pausable, self.at, self.pause = pausable, at, pause
        self.paused_at: float | None = None
        self.held: set[int] = set()  # the states unanswered at the pause

    def _due(self, k: int) -> float:
        return self.sent[k] + self.delay + (self.pause if k in self.held else 0.0)

    def _visible(self) -> list[int]:
        return [k for k in self.sent if self._due(k) <= self.clock.now()]

    def _next_answer(self) -> float:
        return min((d for d in map(self._due, self.sent) if d > self.clock.now()),
                   default=float("inf"))

    def idle(self, seconds: float, wake: bool = True) -> None:
        c = self.clock
        if self.paused_at is None and self.steps and self.steps[-1][0] == self.at - 1:
            self.paused_at = c.now()
            self.held = {k for k in self.sent if self._due(k) > c.now()}
            if self.pausable is not None:
                self.pausable.pause()
            c.t += self.pause
            if self.pausable is not None:
                self.pausable.resume()
            return
        t = c.t
        super().idle(seconds, wake)
        if seconds > 0 and c.t == t < self._next_answer():
            # a wait shorter than the float's resolution at this time (the paused clock,
            # 2 s behind, asks for steps finer than it) moves the time one step on, as a real
            # clock would: else the run would wait for a time that never comes
            c.t = float(np.nextafter(t, np.inf))


@pytest.mark.parametrize("mode", ["realtime", "lockstep"])
def test_a_paused_run_takes_up_where_it_stood(mode):
    """A run held for 2 s of its clock (40 times the 50 ms staleness bound, twice the
    lockstep timeout) between two steps: on a :class:`PausableClock` paused meanwhile, the
    pause is no time of the run's - the states after it go out on the schedule of those
    before, nothing is late, stale, safe or re-anchored, the lockstep does not time out. On
    the bare clock the same pause is a stall: the realtime loop re-anchors its clock (the
    period across it 2 s long), the lockstep times out waiting for the held answer."""
    from msagv.bridge.run_core import PausableClock

    n, at, pause = 30, 12, 2.0
    cfg = RunConfig(run_mode=mode, period=T, steps=n, stale_ms=50.0, resume_periods=3,
                    timeout_s=1.0, linger_s=0.0)
    for pausing in (True, False):
        inner = SimClock(1.0)
        clock = PausableClock(inner) if pausing else inner
        port = PausingPort(inner, clock if pausing else None, at, pause)
        run = PlantRun(Plant(default_vehicle(), initial={"vx": 4.0}), cfg, port, clock=clock)
        try:
            if mode == "lockstep" and not pausing:
                with pytest.raises(PlantRunError, match=f"no answer to state {at}"):
                    run.run()
            else:
                run.run()
        finally:
            run.close()
        s = run.summary()
        assert port.paused_at is not None
        if not pausing:
            if mode == "realtime":  # the stall: re-anchored, one period across it 2 s long
                assert s["completed"] and s["clock_resyncs"] == 1
                assert s["period_jitter_ms"]["max"] == pytest.approx((pause - T) * 1000,
                                                                     abs=1e-6)
            else:
                assert not s["completed"] and s["steps"] == at
            continue
        assert s["completed"] and s["clock_resyncs"] == 0 and s["missed_periods"] == 0
        assert s["safe"]["events"] == 0 and s["safe"]["watchdog_trips"] == 0
        assert [(k, c) for k, _, c in port.steps] == [(k, True) for k in range(n)]
        # (the inner clock's times): one period (realtime) or one answer (lockstep) apart,
        # the pause's 2 s more across it
        gap = port.sent[2] - port.sent[1]
        assert gap == pytest.approx(T if mode == "realtime" else 0.003, abs=1e-12)
        for k in range(2, n + 1):
            across = port.sent[k - 1] <= port.paused_at < port.sent[k]
            assert port.sent[k] - port.sent[k - 1] == pytest.approx(
                gap + (pause if across else 0.0), abs=1e-9), k
        if mode == "realtime":
            assert s["periods"]["on_time"] == n
            assert s["lateness_ms"]["max"] == pytest.approx(0.0, abs=1e-6)
            assert s["period_jitter_ms"]["max"] == pytest.approx(0.0, abs=1e-6)


class _ResettingPort(FakePort):
    """A FakePort that, in its idle, once the run has sent ``at`` states, calls ``action``
    (a reset, a reconfigure) as a node's service or parameter callback would."""

    def __init__(self, *a, at: int, action, **kw):
        super().__init__(*a, **kw)
        self.at, self.action, self.done = at, action, False
        self.log: list[tuple[int, dict]] = []  # every state sent, in order

    def send_state(self, k, st, end):
        super().send_state(k, st, end)
        self.log.append((k, st))

    def idle(self, seconds: float, wake: bool = True) -> None:
        super().idle(seconds, wake)
        if not self.done and len(self.log) >= self.at:
            self.done = True
            self.action(self)


def test_a_reset_starts_the_run_again_from_the_initial_state():
    """A reset in the middle of a realtime run (in the port's idle, as ``~/reset`` comes):
    the next state sent is state 0 again, the plant's initial state, the run then steps to
    its end as a new one would; a reset is no silence of the controller's (no safe event:
    the commands come 3 ms after each state, the bound is 50 ms) and the run before it
    leaves no watchdog behind."""
    vehicle = default_vehicle()
    clock = SimClock(1.0)
    cfg = RunConfig(run_mode="realtime", period=T, steps=30, stale_ms=50.0,
                    resume_periods=3, linger_s=0.0)
    holder = {}

    def reset(port):
        port.sent.clear()  # (a node forgets the commands that answered the run before)
        holder["run"].reset()

    port = _ResettingPort(clock, 0.003, at=12, action=reset)
    run = holder["run"] = PlantRun(Plant(vehicle, initial={"vx": 4.0}), cfg, port,
                                   clock=clock)
    try:
        run.run()
    finally:
        run.close()
    ks = [k for k, _ in port.log]
    assert ks == list(range(12)) + list(range(31)), ks
    first, again = port.log[0][1], port.log[12][1]
    for f in ("x", "y", "phi", "vx", "vy", "r", "W_s", "W_alpha", "W_t"):
        assert again[f] == first[f], f
    assert port.log[11][1]["x"] > first["x"]  # it had moved before the reset
    s = run.summary()
    assert s["completed"] and s["steps"] == 30 and run.resets == 1
    assert s["safe"]["events"] == 0 and s["safe"]["watchdog_trips"] == 0
    assert not run.safe


def test_a_timeout_changed_during_the_wait_counts_in_it():
    """``reconfigure`` from the port's idle (a ROS parameter set at run time) while a
    lockstep run waits for an answer that never comes: the new ``timeout_s`` (2 s) ends
    the wait, not the one it began with (0.5 s)."""
    from dataclasses import replace

    clock = SimClock(1.0)
    cfg = RunConfig(run_mode="lockstep", steps=5, timeout_s=0.5)
    holder = {}
    port = _ResettingPort(clock, 0.0, answers=False, at=1,
                          action=lambda p: holder["run"].reconfigure(
                              replace(holder["run"].cfg, timeout_s=2.0)))
    run = holder["run"] = PlantRun(Plant(default_vehicle()), cfg, port, clock=clock)
    with pytest.raises(PlantRunError, match="no answer to state 0"):
        run.run()
    assert 2.0 < clock.now() <= 2.0 + 0.05 + 1e-9
