"""Per-wheel wear (issue 14 item 1): each wheel's wear powers and integrated wear work as
plant outputs and state fields, summing to the totals; the per-wheel states leave the
integrator's step-size control alone."""

from __future__ import annotations

import numpy as np
import pytest

from msagv.plant import Plant, default_vehicle, n_axle_vehicle, vehicle_from_dict
from msagv.plant import dynamics as dyn
from msagv.plant import layout as lay
from msagv.plant.signals import WHEEL_POWERS, WHEEL_WORK, signal_names, wheel_wear_names


def _vehicle(n, **plant_opts):
    v = default_vehicle() if n == 2 else n_axle_vehicle(n)
    if plant_opts:
        d = v.to_dict()
        d["plant"] = dict(d["plant"], **plant_opts)
        v = vehicle_from_dict(d)
    return v


def _drive(plant, steps, h=0.01, seed=0):
    """A slalom with slipping wheels: every wear power is non-zero."""
    v = plant.vehicle
    rng = np.random.default_rng(seed)
    sign = np.where(v.wheel_x >= 0, 1.0, -1.0)
    for k in range(steps):
        t = plant.t
        w = 6.0 / v.wheel_radius * (1.0 + 0.05 * rng.standard_normal(v.n_wheels))
        s = 0.4 * np.cos(2 * np.pi * t / 2.0) * sign
        plant.set_inputs(np.maximum(w, 0.0), s)
        plant.do_step(t, h)


@pytest.mark.parametrize("n, opts", [(2, {}), (3, {"wheel_lag": 0.05, "cg_height": 1.2})])
def test_per_wheel_signals_sum_to_the_totals(n, opts):
    p = Plant(_vehicle(n, **opts), initial={"vx": 6.0})
    _drive(p, 150)
    o = p.outputs()
    w = p.vehicle.wheel_names
    assert wheel_wear_names(p.vehicle) == [f"{q}_{k}" for q in WHEEL_POWERS + WHEEL_WORK for k in w]
    assert set(wheel_wear_names(p.vehicle)) <= set(signal_names(p.vehicle))
    for q in ("P_s", "P_alpha", "P_t", "W_s", "W_alpha", "W_t", "W_tw"):
        per = [o[f"{q}_{k}"] for k in w]
        assert o[q] > 0, q
        assert sum(per) == pytest.approx(o[q], rel=1e-12, abs=1e-9), q
        assert all(x >= 0 for x in per), q  # each wheel's powers are >= 0 (eq. 13-15)
    for k in w:
        assert o[f"W_tw_{k}"] == pytest.approx(o[f"W_s_{k}"] + o[f"W_alpha_{k}"] + o[f"W_t_{k}"],
                                               rel=1e-14)
    # wheels wear differently in a slalom with load transfer: the split is not uniform
    per_tw = np.array([o[f"W_tw_{k}"] for k in w])
    assert per_tw.max() > 1.05 * per_tw.min()


def test_per_wheel_work_is_the_integral_of_the_per_wheel_power():
    """An independent reference: the trapezoidal integral of the per-wheel powers read as
    outputs every 1 ms (the state is never read)."""
    p = Plant(_vehicle(2), initial={"vx": 5.0})
    v = p.vehicle
    w = v.wheel_names
    sign = np.where(v.wheel_x >= 0, 1.0, -1.0)
    acc = {f"{q}_{k}": 0.0 for q in ("s", "alpha", "t") for k in w}
    h = 0.001
    for i in range(1000):
        p.set_inputs(np.full(v.n_wheels, 5.3 / v.wheel_radius), 0.2 * sign)
        before = p.outputs()
        p.do_step(p.t, h)
        after_inputs = p.outputs()  # same inputs: the power at the end of the step
        for q in ("s", "alpha", "t"):
            for k in w:
                acc[f"{q}_{k}"] += 0.5 * h * (before[f"P_{q}_{k}"] + after_inputs[f"P_{q}_{k}"])
    o = p.outputs()
    for q in ("s", "alpha", "t"):
        for k in w:
            assert o[f"W_{q}_{k}"] == pytest.approx(acc[f"{q}_{k}"], rel=2e-3, abs=1e-3), (q, k)
            assert o[f"W_{q}_{k}"] > 0


def test_per_wheel_states_do_not_change_the_step_size_control():
    """The integrator sees the same error norm with the per-wheel wear at 0 or at 1e9: the
    same accepted and rejected steps and bit-identical dynamics and totals."""
    v = _vehicle(3)
    P, wx, wy = dyn.pack_params(v)
    nw = v.n_wheels
    y0 = np.zeros(lay.state_size(nw))
    y0[lay.Y_VX] = 8.0
    u_w = np.full(nw, 8.4 / v.wheel_radius)
    u_s = np.where(v.wheel_x >= 0, 0.3, -0.3)
    results = []
    for fill in (0.0, 1e9, -3.0):
        y = y0.copy()
        i0 = lay.y_wheel_wear(nw, 0)
        y[i0:] = fill
        stats = np.zeros(2, dtype=np.int64)
        h = dyn.integrate(y, 0.0, 0.5, u_w, u_s, P, wx, wy, 1e-8, 1e-9, 0.0, 100000, stats)
        results.append((y, stats.copy(), h))
    (ya, sa, ha), (yb, sb, hb), (yc, sc, hc) = results
    ne = lay.n_error_states(nw)
    assert sa.tolist() == sb.tolist() == sc.tolist() and sa[0] > 5
    assert ha == hb == hc
    assert np.array_equal(ya[:ne], yb[:ne]) and np.array_equal(ya[:ne], yc[:ne])
    # the per-wheel increments are the same, too
    i0 = lay.y_wheel_wear(nw, 0)
    assert np.allclose(yb[i0:] - 1e9, ya[i0:], atol=1e-6)
    assert np.allclose(yc[i0:] + 3.0, ya[i0:], rtol=1e-12, atol=1e-9)


def test_state_message_carries_the_per_wheel_work():
    p = Plant(_vehicle(2), initial={"vx": 4.0})
    _drive(p, 50)
    st, o = p.state_message(), p.outputs()
    w = p.vehicle.wheel_names
    for q in ("W_s", "W_alpha", "W_t"):
        assert st[f"{q}_ij"] == [o[f"{q}_{k}"] for k in w]
        assert sum(st[f"{q}_ij"]) == pytest.approx(st[q], rel=1e-12)
    p.reset()
    st = p.state_message()
    assert st["W_s_ij"] == [0.0] * 4 and st["W_s"] == 0.0
