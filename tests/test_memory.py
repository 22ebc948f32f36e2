"""What a long run keeps stays bounded (issue 30: the real-time plant grew about 2.8 MB a
minute): the run's per-period figures are kept in :class:`controller.metrics.StreamPercentiles`
(exact up to a number of values, then a log-scale histogram), checked here against numpy's
percentiles of every value, and a run of many periods on a simulated clock (no wall time)
keeps no container that grows with the periods."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msagv.bridge.run_core import Command, PlantRun, RunConfig
from msagv.controller.metrics import StreamPercentiles, percentiles
from msagv.plant import Plant, default_vehicle


def _bound(v: np.ndarray, q: float, rel: float) -> float:
    """How far the bucketed percentile may be from numpy's: ``rel`` times the interpolation
    of the magnitudes of the two order statistics around rank q (n - 1), plus the zero
    bucket's width."""
    s = np.sort(v)
    r = q * (len(s) - 1)
    lo, hi = math.floor(r), math.ceil(r)
    w = r - lo
    return rel * ((1 - w) * abs(s[lo]) + w * abs(s[hi])) + StreamPercentiles.TINY


@pytest.mark.parametrize("kind", ["lognormal", "signed", "constant", "few"])
def test_stream_percentiles_are_numpys_exactly_then_within_their_relative_width(kind):
    rng = np.random.default_rng(3)
    n = 30_000
    v = {"lognormal": rng.lognormal(-6.0, 1.5, n),  # durations around 2.5 ms
         "signed": np.concatenate([rng.normal(0.0, 1e-3, n - 100), np.zeros(100)]),
         "constant": np.full(n, 0.01),
         "few": rng.choice([1e-4, 2e-3, 0.05], n)}[kind]
    exact, rel = 1000, 0.005
    sp = StreamPercentiles(exact=exact, rel=rel)
    for i, x in enumerate(v):
        sp.add(x)
        if i + 1 == exact:  # up to `exact` values: the very figures of percentiles()
            assert sp.exact_now
            assert sp.percentiles(1000.0, True) == percentiles(v[:exact], 1000.0, True)
    assert not sp.exact_now
    got = sp.percentiles(count=True)
    assert got["n"] == n and got["max"] == float(v.max())
    for name, q in (("p50", 0.5), ("p99", 0.99)):
        want = float(np.percentile(v, 100 * q))
        assert abs(got[name] - want) <= _bound(v, q, rel), (name, got[name], want)
    # the memory held: `exact` is dropped, one bucket per factor gamma of the range at most
    gamma = (1 + rel) / (1 - rel)
    a = np.abs(v[np.abs(v) >= StreamPercentiles.TINY])
    per_sign = math.log(a.max() / a.min()) / math.log(gamma) + 2
    assert len(sp) <= 2 * per_sign + 1


def test_stream_percentiles_ignore_non_finite_values_and_say_none_when_empty():
    sp = StreamPercentiles(exact=2)
    assert sp.percentiles(count=True) == {"p50": None, "p99": None, "max": None, "n": 0}
    for x in (1.0, math.nan, math.inf, 3.0, 2.0):
        sp.add(x)
    got = sp.percentiles(count=True)
    assert got["n"] == 3 and got["max"] == 3.0
    assert abs(got["p50"] - 2.0) <= 0.005 * 2.0


class InstantPort:
    """A controller that answers every state the moment it is sent; the clock moves only
    while the run waits (no wall time passes)."""

    def __init__(self, clock):
        self.clock = clock
        self.k = -1

    def ready(self):
        return True

    def send_state(self, k, st, end):
        self.k = k

    def answer(self, k):
        return Command(k, [6.0] * 4, [0.0] * 4) if k <= self.k else None

    def newest(self):
        return Command(self.k, [6.0] * 4, [0.0] * 4)

    def present(self):
        return True

    def idle(self, seconds, wake=True):
        self.clock.t += seconds

    def unanswered(self, k, first):
        pass

    def applied(self, k, omega_w, omega_s, commanded):
        pass

    def waiting(self):
        return "waiting"

    def no_controller(self):
        return "no controller"

    def no_answer(self, k, timeout):
        return f"no answer to {k}"


class Clock:
    def __init__(self):
        self.t = 0.0

    def now(self):
        return self.t

    def wall(self, dt):
        return dt


def _containers(obj, seen=None, skip=()):
    """Every list, set, dict, bytearray or sized estimator reachable through attributes
    (not through objects of the types ``skip``)."""
    seen = set() if seen is None else seen
    if id(obj) in seen or isinstance(obj, skip):
        return
    seen.add(id(obj))
    if isinstance(obj, (list, set, dict, bytearray, StreamPercentiles)):
        yield obj
    if isinstance(obj, (list, tuple, set)):
        items = obj
    elif isinstance(obj, dict):
        items = obj.values()
    else:
        items = getattr(obj, "__dict__", {}).values()
    for x in items:
        if not isinstance(x, (str, bytes, int, float, np.ndarray)):
            yield from _containers(x, seen, skip)


def test_a_long_real_time_run_keeps_nothing_that_grows_with_its_periods():
    """20,000 periods (200 s of a 100 Hz run) answered at once: every figure counts all of
    them, and no container of the run holds more than the estimators' 4096 exact values
    (before issue 30's fix, the lateness, jitter, round-trip and latency lists held one
    float per period each)."""
    n = 20_000
    clock = Clock()
    port = InstantPort(clock)
    cfg = RunConfig(run_mode="realtime", period=0.01, steps=n)
    run = PlantRun(Plant(default_vehicle(), initial={"vx": 2.0}), cfg, port, clock=clock)
    try:
        run.run()
    finally:
        run.close()
    s = run.summary()
    assert s["completed"] and s["steps"] == n
    assert s["lateness_ms"]["n"] == n and s["period_jitter_ms"]["n"] == n
    sizes = sorted((len(c), type(c).__name__) for c in _containers(run))
    assert sizes and sizes[-1][0] <= 4096 + 100, sizes[-5:]


def test_a_plant_node_keeps_nothing_per_token_name_churned():
    """5,000 controller tokens under distinct names declared and undeclared (issue 30: 8,814
    names churned left the plant 14.5 MB larger): the Zenoh plant's own structures
    (presence, ownership, counters) hold no more than they did after the first 100 (the bus
    itself, here the loopback one, is not the plant's: what Zenoh keeps is measured in
    docs/PROTOCOL.md)."""
    from msagv.bridge.loopback import LoopbackBus, LoopbackTransport
    from msagv.bridge.plant_node import PlantConfig, PlantNode
    from msagv.bridge.session import Keys

    bus = LoopbackBus()
    keys = Keys("t0")
    node = PlantNode(Plant(default_vehicle(), initial={"vx": 2.0}), keys,
                     PlantConfig(run_mode="realtime", steps=10))
    node.open(bus.endpoint("p1"))
    rogue = bus.endpoint("rogue")

    def churn(names):
        for i in names:
            rogue.declare_token(keys.controller_token(f"z{i:05d}")).close()

    def largest():
        return max(len(c) for c in _containers(node, skip=(LoopbackTransport,)))

    try:
        churn(range(100))
        after_100 = largest()
        churn(range(100, 5000))
        assert largest() == after_100
        assert node._tokens.summary()["tracked"] == 0
    finally:
        node.close()
    assert not bus.errors, bus.errors
