"""The stepping plant (plant/stepping.py) against an independent implementation of the
paper's equations (tests/reference_model.py, integrated with scipy), and its FMU-style
contract: state save/restore, reset, refusal of bad input, wear work."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msagv.plant import Plant, PlantError, default_vehicle, n_axle_vehicle

try:
    from . import reference_model as ref
except ImportError:  # tests/ is not a package: pytest puts tests/ on sys.path
    import reference_model as ref

T = 0.01


def run_plant(plant, U_w, U_s):
    """Step ``plant`` over held commands; rows of the returned array are state vectors."""
    Y = [plant.state_vector]
    for k in range(U_w.shape[0]):
        plant.set_inputs(U_w[k], U_s[k])
        plant.do_step(plant.t, T)
        Y.append(plant.state_vector)
    return np.array(Y)


def _initial(speed=5.0, heading=0.3, r=0.05):
    return {"phi": heading, "vx": speed * math.cos(heading), "vy": speed * math.sin(heading),
            "r": r}


# ---- THE KEY TEST: plant == independent reference of eq. 2-18 ---------------------------
@pytest.mark.parametrize("n", [1, 2, 4])
def test_plant_matches_independent_reference(n):
    v = n_axle_vehicle(n)
    rv = ref.RefVehicle.from_description(v.to_dict())
    K = 1000  # 10 s
    U_w, U_s = ref.varied_inputs(rv, K, seed=100 + n)
    # inside the steering limits (no stops) and the actuator limits (no saturation)
    assert np.all(np.abs(T * np.cumsum(U_s, axis=0)) < v.limits.delta_max)
    assert np.all(U_w <= v.limits.omega_w_max) and np.all(np.abs(U_s) <= v.limits.omega_s_max)
    init = _initial()
    Z = ref.simulate(rv, ref.initial_state(rv, **init), U_w, U_s)
    Y = run_plant(Plant(v, initial=init), U_w, U_s)
    nw = v.n_wheels
    # the run is a real manoeuvre: it travels and turns
    assert np.hypot(*(Z[-1, :2] - Z[0, :2])) > 30.0
    assert np.ptp(Z[:, 2]) > 0.2
    assert Z[-1, 6 + nw] > 1e3 and Z[-1, 7 + nw] > 1e3  # slip and scrub wear happened
    np.testing.assert_allclose(Y[:, 0:2], Z[:, 0:2], rtol=0, atol=1e-6)  # position [m]
    np.testing.assert_allclose(Y[:, 2], Z[:, 2], rtol=0, atol=1e-7)  # heading [rad]
    np.testing.assert_allclose(Y[:, 3:6], Z[:, 3:6], rtol=0, atol=1e-6)  # velocities
    np.testing.assert_allclose(Y[:, 6:6 + nw], Z[:, 6:6 + nw], rtol=0, atol=1e-12)  # delta
    np.testing.assert_allclose(Y[:, 6 + nw:9 + nw], Z[:, 6 + nw:9 + nw], rtol=1e-6, atol=1e-3)


def test_reference_model_frames_agree():
    # the reference's two formulations (Newton in G, and in B with Coriolis terms) agree,
    # so the reference is not merely copying one way of writing the plant
    v = default_vehicle()
    rv = ref.RefVehicle.from_description(v.to_dict())
    U_w, U_s = ref.varied_inputs(rv, 200, seed=9)
    init = _initial(speed=6.0, heading=-0.4, r=0.1)
    Zg = ref.simulate(rv, ref.initial_state(rv, **init), U_w, U_s)
    zb = ref.initial_state(rv, phi=-0.4, vx=6.0, vy=0.0, r=0.1)
    Zb = ref.simulate(rv, zb, U_w, U_s, frame="body")
    np.testing.assert_allclose(Zg[:, :3], Zb[:, :3], atol=1e-9)
    np.testing.assert_allclose(Zg[:, 6:], Zb[:, 6:], rtol=1e-9, atol=1e-6)
    # and the plant matches it on the paper vehicle too
    Y = run_plant(Plant(v, initial=init), U_w, U_s)
    np.testing.assert_allclose(Y[:, :2], Zb[:, :2], atol=1e-6)


def test_outputs_match_reference_wheel_quantities():
    v = n_axle_vehicle(3)
    rv = ref.RefVehicle.from_description(v.to_dict())
    rng = np.random.default_rng(4)
    nw = v.n_wheels
    delta = rng.uniform(-0.4, 0.4, nw)
    init = {**_initial(speed=7.0, heading=1.1, r=-0.15),
            **{f"delta_{k}": d for k, d in zip(v.wheel_names, delta)}}
    p = Plant(v, initial=init)
    omega_w, omega_s = rng.uniform(10, 18, nw), rng.uniform(-0.5, 0.5, nw)
    p.set_inputs(omega_w, omega_s)
    o = p.outputs()
    c, s = math.cos(1.1), math.sin(1.1)
    u = c * init["vx"] + s * init["vy"]
    w = -s * init["vx"] + c * init["vy"]
    vwx, vwy, sl, al, Fx, Fy = ref.wheel_quantities(rv, u, w, -0.15, delta, omega_w)
    for name, val in (("s", sl), ("alpha", al), ("Fx", Fx), ("Fy", Fy)):
        got = np.array([o[f"{name}_{k}"] for k in v.wheel_names])
        np.testing.assert_allclose(got, val, rtol=1e-12, atol=1e-9, err_msg=name)
    assert o["P_s"] == pytest.approx(np.sum(np.abs(Fx * (omega_w * rv.r_w - vwx))), rel=1e-12)
    assert o["P_alpha"] == pytest.approx(np.sum(np.abs(Fy * vwy)), rel=1e-12)
    assert o["P_t"] == pytest.approx(np.sum(np.abs(rv.k_t * rv.F_N * omega_s)), rel=1e-12)


# ---- state save / restore, reset --------------------------------------------------------
def test_get_set_state_round_trip():
    v = default_vehicle()
    rv = ref.RefVehicle.from_description(v.to_dict())
    U_w, U_s = ref.varied_inputs(rv, 150, seed=2)
    p = Plant(v, initial=_initial())
    run_plant(p, U_w[:50], U_s[:50])
    snap = p.get_state()
    t_snap = p.t
    first = run_plant(p, U_w[50:], U_s[50:])
    out_first = p.output_vector()
    # the snapshot is a copy: running on did not change it
    assert snap.t == t_snap
    p.set_state(snap)
    assert p.t == t_snap
    np.testing.assert_array_equal(p.state_vector, first[0])
    again = run_plant(p, U_w[50:], U_s[50:])
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(p.output_vector(), out_first)
    # into a fresh plant of the same vehicle
    q = Plant(v)
    q.set_state(snap)
    np.testing.assert_array_equal(run_plant(q, U_w[50:], U_s[50:]), first)
    # restoring also restores the held inputs
    p.set_state(snap)
    np.testing.assert_array_equal(p.inputs[0], U_w[49])


def test_warmup_changes_nothing():
    v = default_vehicle()
    p = Plant(v, initial=_initial())
    p.set_inputs([9.0] * 4, [0.1, -0.1, 0.1, -0.1])
    before = (p.t, p.state_vector, p.output_vector(), p.inputs)
    p.warmup()
    assert p.t == before[0]
    np.testing.assert_array_equal(p.state_vector, before[1])
    np.testing.assert_array_equal(p.output_vector(), before[2])
    np.testing.assert_array_equal(p.inputs[0], before[3][0])
    # and the run after it is the run without it
    q = Plant(v, initial=_initial())
    q.set_inputs([9.0] * 4, [0.1, -0.1, 0.1, -0.1])
    p.do_step(0.0, 0.01)
    q.do_step(0.0, 0.01)
    np.testing.assert_array_equal(p.state_vector, q.state_vector)


def test_set_state_from_another_vehicle_is_refused():
    p = Plant(default_vehicle())
    q = Plant(n_axle_vehicle(3))
    before = p.state_vector
    with pytest.raises(PlantError):
        p.set_state(q.get_state())
    with pytest.raises(PlantError):
        p.set_state("not a snapshot")
    np.testing.assert_array_equal(p.state_vector, before)


def test_reset():
    v = default_vehicle()
    rv = ref.RefVehicle.from_description(v.to_dict())
    U_w, U_s = ref.varied_inputs(rv, 100, seed=3)
    init = _initial()
    p = Plant(v, initial=init)
    y0 = p.state_vector
    first = run_plant(p, U_w, U_s)
    assert p.t == pytest.approx(1.0)
    p.reset()
    assert p.t == 0.0
    np.testing.assert_array_equal(p.state_vector, y0)
    np.testing.assert_array_equal(p.inputs[0], 0.0)
    np.testing.assert_array_equal(run_plant(p, U_w, U_s), first)
    # reset to a new initial state: x = 5, standing
    p.reset({"x": 5.0})
    assert p.t == 0.0 and p.get("x") == 5.0 and p.get("vx") == 0.0
    p.reset()  # the new initial state is kept
    assert p.get("x") == 5.0


# ---- bad input: PlantError, state unchanged ---------------------------------------------
def _bad_calls(nw):
    good_w, good_s = np.full(nw, 10.0), np.zeros(nw)
    nan_w = good_w.copy()
    nan_w[1] = np.nan
    inf_s = good_s.copy()
    inf_s[2] = np.inf
    neg_w = good_w.copy()
    neg_w[3] = -0.1
    return {
        "too few wheel speeds": lambda p: p.set_inputs(good_w[:-1], good_s),
        "too many steering rates": lambda p: p.set_inputs(good_w, np.zeros(nw + 1)),
        "empty": lambda p: p.set_inputs([], []),
        "scalar": lambda p: p.set_inputs(10.0, 0.0),
        "NaN wheel speed": lambda p: p.set_inputs(nan_w, good_s),
        "inf steering rate": lambda p: p.set_inputs(good_w, inf_s),
        "negative wheel speed": lambda p: p.set_inputs(neg_w, good_s),
        "not numbers": lambda p: p.set_inputs(["a"] * nw, good_s),
        "wrong t": lambda p: p.do_step(p.t + 0.5, T),
        "t behind": lambda p: p.do_step(p.t - T, T),
        "NaN t": lambda p: p.do_step(float("nan"), T),
        "h = 0": lambda p: p.do_step(p.t, 0.0),
        "h < 0": lambda p: p.do_step(p.t, -T),
        "h NaN": lambda p: p.do_step(p.t, float("nan")),
        "h inf": lambda p: p.do_step(p.t, float("inf")),
        "unknown initial": lambda p: p.reset({"speed": 3.0}),
        "initial delta above": lambda p: p.reset({"delta_11": 2.0}),
        "initial delta below": lambda p: p.reset({"delta_12": -1.6}),
        "initial NaN": lambda p: p.reset({"x": float("nan")}),
        "initial not a number": lambda p: p.reset({"x": "fast"}),
        "initial negative wheel speed": lambda p: p.reset({"omega_w_21": -1.0}),
    }


@pytest.mark.parametrize("case", sorted(_bad_calls(4)))
def test_bad_input_raises_and_leaves_state_unchanged(case):
    v = default_vehicle()
    rv = ref.RefVehicle.from_description(v.to_dict())
    U_w, U_s = ref.varied_inputs(rv, 30, seed=8)
    p = Plant(v, initial=_initial())
    run_plant(p, U_w[:20], U_s[:20])
    t, y, inputs, out = p.t, p.state_vector, p.inputs, p.output_vector()
    bad = _bad_calls(v.n_wheels)[case]
    with pytest.raises(PlantError):
        bad(p)
    assert p.t == t
    np.testing.assert_array_equal(p.state_vector, y)
    np.testing.assert_array_equal(p.inputs[0], inputs[0])
    np.testing.assert_array_equal(p.inputs[1], inputs[1])
    np.testing.assert_array_equal(p.output_vector(), out)
    # and it carries on exactly like a plant that never saw the bad call
    q = Plant(v, initial=_initial())
    run_plant(q, U_w[:20], U_s[:20])
    np.testing.assert_array_equal(run_plant(p, U_w[20:], U_s[20:]),
                                  run_plant(q, U_w[20:], U_s[20:]))


def test_bad_constructor_arguments():
    with pytest.raises(PlantError, match="speed"):
        Plant(default_vehicle(), initial={"speed": 3.0})
    with pytest.raises(PlantError, match="delta_11"):
        Plant(default_vehicle(), initial={"delta_11": 1.6})
    with pytest.raises(PlantError):
        Plant(default_vehicle(), rtol=0.0)


def test_commands_beyond_actuator_limits_saturate():
    v = default_vehicle()
    p = Plant(v)
    p.set_inputs([30.0, 10.0, 0.0, 25.0], [2.0, -2.0, 0.5, -0.8])
    w, s = p.inputs
    np.testing.assert_array_equal(w, [25.0, 10.0, 0.0, 25.0])
    np.testing.assert_array_equal(s, [0.8, -0.8, 0.5, -0.8])
    assert p.get("omega_s_11") == 0.8


# ---- wear work --------------------------------------------------------------------------
def test_wear_work_is_the_integral_of_wear_power():
    v = default_vehicle()
    rv = ref.RefVehicle.from_description(v.to_dict())
    U_w, U_s = ref.varied_inputs(rv, 200, seed=21)
    p = Plant(v, initial=_initial())
    h = 0.001  # fine steps; inputs change every 0.01 s
    integral = np.zeros(3)
    W_prev = np.zeros(3)
    for k in range(200):
        p.set_inputs(U_w[k], U_s[k])
        for _ in range(10):
            o0 = p.outputs()
            p.do_step(p.t, h)
            o1 = p.outputs()  # same held inputs, end of the step
            P0 = np.array([o0["P_s"], o0["P_alpha"], o0["P_t"]])
            P1 = np.array([o1["P_s"], o1["P_alpha"], o1["P_t"]])
            integral += 0.5 * (P0 + P1) * h
            W = np.array([o1["W_s"], o1["W_alpha"], o1["W_t"]])
            assert np.all(W >= W_prev)  # non-decreasing
            W_prev = W
    o = p.outputs()
    assert o["W_tw"] == pytest.approx(o["W_s"] + o["W_alpha"] + o["W_t"], rel=1e-12)
    assert np.all(integral > 10.0)
    np.testing.assert_allclose(W_prev, integral, rtol=2e-3)
