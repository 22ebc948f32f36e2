"""The controller's steps for a state (bridge/controller_run.py), which the Zenoh and the
ROS 2 controller nodes share: checked on a real MPC (the paper's vehicle, the annealer)
against a recorder that keeps what it is given and a clock the test sets."""

import numpy as np
import pytest

from msagv.bridge import messages as M
from msagv.bridge.controller_run import AnswerCounts, ControllerRun


class Keep:
    """A recorder that keeps everything."""

    def __init__(self):
        self.messages, self.paths, self.events = [], [], []

    def message(self, direction, key, payload, ts=None, **kw):
        self.messages.append((direction, key, payload))

    def predicted_path(self, t0, dt, poses):
        self.paths.append((t0, dt, np.array(poses)))

    def event(self, name, /, **fields):
        self.events.append((name, fields))


@pytest.fixture(scope="module")
def mpc():
    from msagv.experiments.scenario import Scenario

    plant, vehicle, ref, _ = Scenario(case="curve", speed=15).make_plant()
    return Scenario(case="curve", speed=15).make_controller(vehicle, ref), plant


def test_a_state_is_solved_answered_recorded_and_counted(mpc):
    m, plant = mpc
    rec, clock = Keep(), [10.0]
    run = ControllerRun(lambda: [m], lambda: None, now=lambda: clock[0], recorder=rec)
    m.reset()
    st = plant.state_message()
    run.new_run(seq=0)
    cmd = run.solve(m, st)
    assert not run.too_old(rx=0.0)  # no age bound: never too old
    payload = run.encode(st, 7, cmd)
    poses = run.sent(m, st, "msagv/agv0/cmd", payload)
    c = run.counts
    assert (c.answered, c.new_runs, c.dropped_stale, c.solve_ms) == (1, 1, 0, [cmd.solve_ms])
    got = M.decode_cmd(payload, m.vehicle.n_wheels)
    assert got["seq"] == 0 and got["state_seq"] == 7 and got["t"] == st["t"]
    np.testing.assert_array_equal(got["omega_w"], cmd.omega_w)
    assert run.cmd_seq == 1  # the next command is numbered 1
    assert rec.messages == [("tx", "msagv/agv0/cmd", payload)]
    assert rec.events == [("new_run", {"seq": 0})]
    # recording: the horizon's poses recorded (N_p + 1 of them, from the state)
    assert poses is not None and len(rec.paths) == 1
    np.testing.assert_array_equal(rec.paths[0][2], poses)
    assert poses.shape == (m.settings.N_p + 1, 3) and poses[0, 0] == st["x"]


def test_the_age_bound_is_on_the_nodes_clock_and_read_when_asked():
    bound, clock = [50.0], [100.0]
    counts = AnswerCounts()
    run = ControllerRun(lambda: [], lambda: bound[0], now=lambda: clock[0], counts=counts)
    assert not run.too_old(rx=100.0 - 0.050)  # exactly at the bound: still answered
    assert run.too_old(rx=100.0 - 0.051)
    bound[0] = None  # a parameter changed at run time: no bound from now on
    assert not run.too_old(rx=0.0)
    assert counts.dropped_stale == 1 and run.counts is counts


def test_a_new_run_resets_every_controller_and_nothing_is_recorded_without_a_recorder():
    class C:
        resets = 0

        def reset(self):
            self.resets += 1

    a, b = C(), C()
    run = ControllerRun(lambda: [a, b], lambda: None)
    run.new_run(t=0.0)
    run.new_run(t=0.0)
    assert (a.resets, b.resets, run.counts.new_runs) == (2, 2, 2)
    # no recorder and no poses wanted: the horizon is not even asked for
    assert run.sent(object(), {"t": 0.0}, "k", b"") is None and run.counts.answered == 1
