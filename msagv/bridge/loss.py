"""Loss handling as explicit state machines with bounded counters (docs/PROTOCOL.md,
"Loss handling").

:class:`CommandWatch` is the realtime plant's view of its controller, one decision per
period, in the manner of DCP's maximum number of consecutive missed PDUs:

========  ====================================================================
``run``   the newest command answers the current state (on time)
``hold``  the newest command answers an earlier state, at most ``max_missed``
          periods old: it is applied again (the controller missed or was late)
``safe``  the safe behaviour: steering held, wheels ramped down
========  ====================================================================

Transitions, evaluated at every step k with j = the state the newest command answers:

* ``run``/``hold`` -> ``safe``: the owner's token is gone, no command, or
  ``k - j > max_missed`` (more than ``max_missed`` consecutive periods without an answer);
* ``safe`` -> ``run``/``hold``: the owner present and ``k - j <= 1`` in ``resume_periods``
  consecutive periods (the controller keeps up with the states again);
* ``run`` <-> ``hold`` as the age of the newest command changes.

:class:`LossTimer` is the controller's view of its plant: ``present`` -> ``suspect`` when
the plant's token is gone (it stops commanding) -> ``lost`` only after ``confirm_s`` of
its own running time without the token or a state from that plant. A pause of the
controller itself (a stall: its loop did not run for ``stall_s``) restarts that time, so a
controller that was stopped and finds its plant alive carries on.
"""

from __future__ import annotations

from dataclasses import dataclass

from msagv.plant.signals import CONTROL_PERIOD

RUN, HOLD, SAFE = "run", "hold", "safe"

STALE_MS = 50.0
"""The realtime plant's default staleness bound [ms of vehicle time]: more than
``STALE_MS / T`` consecutive periods without an answer put it in its safe behaviour
(``msagv plant --stale-ms``), and a controller facing a realtime plant never sends a
command for a state older than this (``msagv controller --max-age-ms``'s default)."""

RESUME_PERIODS = 3
"""The safe behaviour ends after this many consecutive periods in which the controller keeps
up again (``--resume-periods``)."""

SAFE_DECEL = 2.0
"""The safe behaviour ramps the wheels down at this [m/s^2 at the rim] (``--safe-decel``)."""


@dataclass
class Decision:
    state: str
    use_command: bool  # False: apply the safe behaviour
    entered_safe: str | None = None  # why, on the run/hold -> safe transition
    resumed: bool = False  # on the safe -> run/hold transition


class CommandWatch:
    """The realtime plant's state machine over its commands (see the module)."""

    def __init__(self, max_missed: int, resume_periods: int = RESUME_PERIODS,
                 period: float = CONTROL_PERIOD):
        if max_missed < 0:
            raise ValueError(f"max_missed must be >= 0, got {max_missed}")
        if resume_periods < 1:
            raise ValueError(f"resume_periods must be >= 1, got {resume_periods}")
        self.max_missed = max_missed
        self.resume_periods = resume_periods
        self.period = period
        self.state = RUN
        self.streak = 0  # safe: consecutive periods that qualify for resuming (<= resume_periods)
        self.on_time = 0
        self.held = 0
        self.safe = 0
        self.max_consecutive_missed = 0  # the largest k - j seen (<= max_missed + 1)

    def step(self, k: int, newest: int | None, owner_present: bool) -> Decision:
        age = None if newest is None else k - newest
        if age is not None:
            self.max_consecutive_missed = max(self.max_consecutive_missed,
                                              min(age, self.max_missed + 1))
        if self.state != SAFE:
            if not owner_present:
                return self._to_safe("controller token lost")
            if age is None:
                return self._to_safe("no command")
            if age > self.max_missed:
                return self._to_safe(f"no answer for {age} periods (newest command answers "
                                     f"state {newest}, {age * self.period * 1000:.0f} ms old; "
                                     f"bound {self.max_missed} periods)")
            return self._running(age)
        ok = owner_present and age is not None and age <= 1
        self.streak = min(self.streak + 1, self.resume_periods) if ok else 0
        if self.streak >= self.resume_periods:
            self.streak = 0
            d = self._running(age)
            d.resumed = True
            return d
        self.safe += 1
        return Decision(SAFE, False)

    def force_safe(self, why: str) -> Decision:
        """The safe behaviour this period whatever the commands say (the plant's own loop
        missed its deadline: its watchdog already went safe); resuming as in :meth:`step`."""
        if self.state != SAFE:
            return self._to_safe(why)
        self.streak = 0
        self.safe += 1
        return Decision(SAFE, False)

    def _running(self, age: int) -> Decision:
        if age == 0:
            self.state = RUN
            self.on_time += 1
        else:
            self.state = HOLD
            self.held += 1
        return Decision(self.state, True)

    def _to_safe(self, why: str) -> Decision:
        self.state = SAFE
        self.streak = 0
        self.safe += 1
        return Decision(SAFE, False, entered_safe=why)

    def summary(self) -> dict:
        return {"state": self.state, "on_time": self.on_time, "held": self.held,
                "safe": self.safe, "max_missed": self.max_missed,
                "resume_periods": self.resume_periods,
                "max_consecutive_missed": self.max_consecutive_missed}


PRESENT, SUSPECT, LOST = "present", "suspect", "lost"


class LossTimer:
    """The controller's state machine over its plant's presence (see the module)."""

    def __init__(self, confirm_s: float = 2.0, stall_s: float = 0.5):
        self.confirm_s = confirm_s
        self.stall_s = stall_s
        self.state = PRESENT
        self._since = 0.0  # running time counts from here while suspect
        self._last_tick: float | None = None
        self.stalls = 0
        self.suspicions = 0

    def update(self, now: float, present: bool) -> str:
        """Advance to ``now`` (monotonic s) with the plant ``present`` or not; returns the
        state. Call at least every ``stall_s / 2`` while running."""
        stalled = self._last_tick is not None and now - self._last_tick > self.stall_s
        self._last_tick = now
        if stalled:
            self.stalls += 1
        if present:
            self.state = PRESENT
        elif self.state == PRESENT:
            self.state, self._since = SUSPECT, now
            self.suspicions += 1
        elif self.state == SUSPECT:
            if stalled:
                self._since = now  # we were not running: the plant had no chance to show
            elif now - self._since >= self.confirm_s:
                self.state = LOST
        return self.state

    def reset(self) -> None:
        self.state = PRESENT
        self._last_tick = None
