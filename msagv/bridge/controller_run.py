"""What a controller does with a plant's state, whatever carries it: the controller's side
of the run core (:mod:`bridge.run_core` is the plant's).

:class:`ControllerRun` holds the steps that the Zenoh controller
(:class:`bridge.controller_node.ControllerNode`) and the ROS 2 one
(:class:`ros2.controller_node.RosController`) both take for a state, in the same order:

1. a new plant run (the node decides when: a state sequence or a stamp that goes back, the
   first state, a plant that came back): every controller forgets its warm start, its
   disturbance estimate and its adapted tires (:meth:`new_run`);
2. the solve (:meth:`solve`), its time kept;
3. the age bound: a state received longer ago than ``max_age_ms`` (on the node's clock:
   ROS time under ``use_sim_time``) is solved but never answered (:meth:`too_old`);
4. the answer sent: recorded as the ``cmd`` message the protocol names (its sequence
   number the run's), counted, and the horizon's poses recorded (:meth:`sent`).

What is not here is each transport's own: the Zenoh node's grant, presence and re-sends of
a lockstep state (a state names its sequence number), the ROS 2 node's plans, goals and
safe behaviour on stale inputs (a ROS state names only its stamp). The counts of
:class:`AnswerCounts` are the fields of both nodes' summaries of the same names.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np

from . import messages as M
from .recording import NullRecorder
from .ros_msgs import predicted_poses


@dataclasses.dataclass
class AnswerCounts:
    """The counts every controller node reports (its summary's fields of these names)."""

    answered: int = 0  # states answered with a command
    new_runs: int = 0  # plant runs begun (the controllers reset)
    dropped_stale: int = 0  # solved, but received longer ago than max_age_ms: not sent
    solve_ms: list = dataclasses.field(default_factory=list)  # each solve's time [ms]


class ControllerRun:
    """One controller node's answers (see the module docstring).

    ``controllers()``: the controllers a new run resets (the MPC, and the ROS 2 node's
    low-speed feed-forward); ``max_age_ms()``: the age bound in force (None: none);
    ``now()``: the clock a state's receive time was taken on [s]; ``counts``: where the
    counts go (a node's own stats object with :class:`AnswerCounts`' fields, or a new one);
    ``recorder``: a recorder, or None (nothing recorded)."""

    def __init__(self, controllers: Callable[[], list], max_age_ms: Callable[[], float | None],
                 now: Callable[[], float] = time.perf_counter, counts: AnswerCounts | None = None,
                 recorder=None):
        self.controllers = controllers
        self.max_age_ms = max_age_ms
        self.now = now
        self.counts = counts if counts is not None else AnswerCounts()
        self.recording = recorder is not None
        self.rec = recorder if recorder is not None else NullRecorder()
        self.cmd_seq = 0  # the next command's sequence number

    def new_run(self, **event) -> None:
        """A new plant run: every controller reset (as ``closed_loop`` does after its
        warm-up); recorded as the event ``new_run`` with ``event``'s fields."""
        for c in self.controllers():
            c.reset()
        self.counts.new_runs += 1
        self.rec.event("new_run", **event)

    def solve(self, ctl, st: dict, reference=None):
        """``ctl``'s command for the state ``st`` (``reference``: None, the one it tracks)."""
        cmd = ctl.step(st, reference)
        self.counts.solve_ms.append(cmd.solve_ms)
        return cmd

    def too_old(self, rx: float) -> bool:
        """True (counted ``dropped_stale``) when a state received at ``rx`` (on
        :attr:`now`'s clock) is older than the age bound now: not to be answered."""
        bound = self.max_age_ms()
        if bound is not None and (self.now() - rx) * 1000.0 > bound:
            self.counts.dropped_stale += 1
            return True
        return False

    def encode(self, st: dict, state_seq: int, cmd, mac_key: bytes | None = None) -> bytes:
        """The protocol's ``cmd`` message answering ``st`` (its sequence ``state_seq``) with
        ``cmd``, numbered as the next command."""
        return M.encode_cmd(self.cmd_seq, st["t"], state_seq, cmd.omega_w, cmd.omega_s,
                            solve_ms=cmd.solve_ms, cost=cmd.cost, mac_key=mac_key)

    def sent(self, ctl, st: dict, key: str, payload: bytes,
             poses: bool = False) -> np.ndarray | None:
        """The answer ``payload`` (:meth:`encode`) went out on ``key``: recorded, counted,
        the next command numbered. ``poses``: the horizon's predicted poses are wanted
        beside the recording (a node that publishes them); they are returned (None: none,
        or not wanted and not recording) and recorded."""
        self.rec.message("tx", key, payload)
        self.cmd_seq += 1
        self.counts.answered += 1
        if not (poses or self.recording):
            return None
        p = predicted_poses(ctl)
        if p is not None:
            self.rec.predicted_path(st["t"], ctl.settings.dt, p)
        return p
