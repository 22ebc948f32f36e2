"""Invariants and a hand-computed right-hand side of the n-axle dynamics (plant/dynamics.py),
plus the plant-only options (steering stops, load transfer, actuator lags)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msagv.plant import Plant, VehicleError, default_vehicle, n_axle_vehicle, vehicle_from_dict
from msagv.plant import dynamics as dyn

G = 9.81


def rhs(vehicle, state, u_w, u_s):
    """(dy, aux) of the kernel at a state given by name (others 0)."""
    P, wx, wy = dyn.pack_params(vehicle)
    nw = vehicle.n_wheels
    y = np.zeros(dyn.state_size(nw))
    for i, k in enumerate(["x", "y", "phi", "vx", "vy", "r"]):
        y[i] = state.get(k, 0.0)
    y[6:6 + nw] = state.get("delta", np.zeros(nw))
    if "omega_w_actual" in state:
        y[9 + nw:9 + 2 * nw] = state["omega_w_actual"]
    aux = np.zeros((nw, dyn.N_AUX))
    dy = np.zeros_like(y)
    dyn.evaluate(y, np.asarray(u_w, float), np.asarray(u_s, float), P, wx, wy, aux, dy)
    return dy, aux


def with_plant_options(vehicle, **opts):
    d = vehicle.to_dict()
    d["plant"] = dict(d["plant"], **opts)
    return vehicle_from_dict(d)


# ---- pure rolling -----------------------------------------------------------------------
def kinematic_state(vehicle, c_x, c_y, r, phi=0.4):
    """Every wheel rolling without slip about the instantaneous centre (c_x, c_y) in B.

    The velocity of a body point p is r x (p - c) = (-r (p_y - c_y), r (p_x - c_x)); each
    wheel is steered along its own velocity and spins at |v| / r_w.
    """
    u, v = r * c_y, -r * c_x  # velocity of the CG (p = 0)
    vbx = -r * (vehicle.wheel_y - c_y)
    vby = r * (vehicle.wheel_x - c_x)
    delta = np.arctan2(vby, vbx)
    omega_w = np.hypot(vbx, vby) / vehicle.wheel_radius
    c, s = math.cos(phi), math.sin(phi)
    state = {"phi": phi, "vx": c * u - s * v, "vy": s * u + c * v, "r": r, "delta": delta}
    return state, omega_w


@pytest.mark.parametrize("n", [2, 4])
@pytest.mark.parametrize("c_x, c_y, r", [
    (0.0, 20.0, 0.3),    # turning left about a centre abeam the CG
    (-3.0, 15.0, 0.4),   # about a point abeam the rear axle (Ackermann-like)
    (5.0, -30.0, -0.2),  # turning right, centre ahead of the CG
    (2.0, 50.0, 0.12),   # wide turn
])
def test_pure_rolling_gives_zero_force_and_wear(n, c_x, c_y, r):
    v = default_vehicle() if n == 2 else n_axle_vehicle(n)
    state, omega_w = kinematic_state(v, c_x, c_y, r)
    assert np.all(np.abs(state["delta"]) < math.pi / 2)  # all wheels rolling forward
    dy, aux = rhs(v, state, omega_w, np.zeros(v.n_wheels))
    np.testing.assert_allclose(aux[:, dyn.AUX_VWY], 0.0, atol=1e-12)
    np.testing.assert_allclose(aux[:, dyn.AUX_S], 0.0, atol=1e-12)
    np.testing.assert_allclose(aux[:, dyn.AUX_ALPHA], 0.0, atol=1e-12)
    np.testing.assert_allclose(aux[:, dyn.AUX_FX], 0.0, atol=1e-6)
    np.testing.assert_allclose(aux[:, dyn.AUX_FY], 0.0, atol=1e-6)
    for col in (dyn.AUX_PS, dyn.AUX_PALPHA, dyn.AUX_PT):
        np.testing.assert_allclose(aux[:, col], 0.0, atol=1e-9)
    np.testing.assert_allclose(dy[3:6], 0.0, atol=1e-9)  # no acceleration at this instant
    nw = v.n_wheels
    np.testing.assert_allclose(dy[6 + nw:9 + nw], 0.0, atol=1e-9)  # no wear power


def test_crab_motion_is_pure_rolling():
    # translation (no yaw): every wheel steered to the direction of travel
    v = default_vehicle()
    ang = 0.7
    state = {"phi": -0.3, "vx": 4.0 * math.cos(ang - 0.3), "vy": 4.0 * math.sin(ang - 0.3),
             "delta": np.full(4, ang)}
    dy, aux = rhs(v, state, np.full(4, 8.0), np.zeros(4))
    np.testing.assert_allclose(aux[:, [dyn.AUX_FX, dyn.AUX_FY]], 0.0, atol=1e-6)
    np.testing.assert_allclose(dy[3:6], 0.0, atol=1e-9)


def test_mismatched_steering_is_not_pure_rolling():
    # the same turn with the rear wheels left straight does produce lateral force
    v = default_vehicle()
    state, omega_w = kinematic_state(v, 0.0, 20.0, 0.3)
    state["delta"] = state["delta"] * np.array([1, 1, 0, 0])
    _, aux = rhs(v, state, omega_w, np.zeros(4))
    assert np.all(np.abs(aux[2:, dyn.AUX_FY]) > 100.0)


# ---- left-right symmetry ----------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 3])
def test_symmetric_command_makes_no_yaw(n):
    v = default_vehicle() if n == 2 else n_axle_vehicle(n)
    nw = v.n_wheels
    phi0 = 0.7
    p = Plant(v, initial={"phi": phi0, "vx": 3.0 * math.cos(phi0), "vy": 3.0 * math.sin(phi0)})
    rng = np.random.default_rng(3)
    for k in range(200):  # 2 s of mirror-symmetric commands: toe in/out, per-axle speeds
        axle_speed = 6.0 + 2.0 * rng.standard_normal(n) + 4.0 * k / 200
        omega_w = np.repeat(np.maximum(axle_speed, 0.0), 2)           # same left and right
        toe_rate = 0.3 * rng.standard_normal(n)
        omega_s = np.column_stack([toe_rate, -toe_rate]).reshape(-1)  # delta_i1 = -delta_i2
        p.set_inputs(omega_w, omega_s)
        p.do_step(p.t, 0.01)
        d = p.delta.reshape(n, 2)
        np.testing.assert_allclose(d[:, 0], -d[:, 1], atol=1e-14)
    o = p.outputs()
    assert abs(o["r"]) < 1e-9
    assert abs(o["phi"] - phi0) < 1e-9
    # no drift off the initial heading line
    assert abs(-math.sin(phi0) * o["x"] + math.cos(phi0) * o["y"]) < 1e-9
    assert o["x"] > 1.0  # it did move


def test_asymmetric_command_does_yaw():
    # control for the test above: faster right wheels turn the vehicle left
    p = Plant(default_vehicle(), initial={"vx": 3.0})
    p.set_inputs([6.0, 6.6, 6.0, 6.6], np.zeros(4))
    for _ in range(50):
        p.do_step(p.t, 0.01)
    assert p.get("r") > 1e-3


# ---- momentum balance -------------------------------------------------------------------
def _summed_force(vehicle, o):
    """Sum of tire forces in G and yaw moment, from the plant's outputs (eq. 4, 5, 17)."""
    w = vehicle.wheel_names
    d = np.array([o[f"delta_{k}"] for k in w])
    Fx = np.array([o[f"Fx_{k}"] for k in w])
    Fy = np.array([o[f"Fy_{k}"] for k in w])
    FBx = np.cos(d) * Fx - np.sin(d) * Fy
    FBy = np.sin(d) * Fx + np.cos(d) * Fy
    Mz = np.sum(vehicle.wheel_x * FBy - vehicle.wheel_y * FBx)
    c, s = math.cos(o["phi"]), math.sin(o["phi"])
    return np.array([c * FBx.sum() - s * FBy.sum(), s * FBx.sum() + c * FBy.sum(), Mz])


@pytest.mark.parametrize("n", [2, 4])
def test_momentum_change_equals_impulse(n):
    v = default_vehicle() if n == 2 else n_axle_vehicle(n)
    nw = v.n_wheels
    rng = np.random.default_rng(11)
    delta0 = rng.uniform(-0.3, 0.3, nw)
    p = Plant(v, initial={"phi": 0.9, "vx": 3.0, "vy": 4.0, "r": 0.2,
                          **{f"delta_{k}": d for k, d in zip(v.wheel_names, delta0)}})
    p.set_inputs(rng.uniform(8.0, 12.0, nw), rng.uniform(-0.5, 0.5, nw))
    h = 1e-4
    o0 = p.outputs()
    F0 = _summed_force(v, o0)
    assert np.all(np.abs(F0[:2]) > 1e3)  # a state with real forces
    p.do_step(p.t, h)
    o1 = p.outputs()
    F1 = _summed_force(v, o1)
    dmom = np.array([v.mass * (o1["vx"] - o0["vx"]), v.mass * (o1["vy"] - o0["vy"]),
                     v.yaw_inertia * (o1["r"] - o0["r"])])
    # first order: m dv = F dt (error O(h) relative to the force's rate of change)
    np.testing.assert_allclose(dmom, F0 * h, rtol=2e-2)
    # trapezoid: second order
    np.testing.assert_allclose(dmom, 0.5 * (F0 + F1) * h, rtol=1e-5)
    # position: dx = v dt + O(h^2)
    assert o1["x"] - o0["x"] == pytest.approx(0.5 * (o0["vx"] + o1["vx"]) * h, rel=1e-8)


# ---- the right-hand side by hand --------------------------------------------------------
def test_rhs_by_hand_2axle():
    """One state of the paper vehicle, eq. (2)-(8), (9)-(15), (17) worked by hand.

    State: phi = 0.5, body velocity u = 5, v = 0, yaw rate r = 0.1, delta = (0.1, 0.1, 0, 0),
    omega_w = (10, 10, 10.4, 10.4) rad/s, omega_s = (0.2, 0.2, 0, 0) rad/s.
    In G: vx = 5 cos .5 = 4.3879128095, vy = 5 sin .5 = 2.3971276930.
    F_N = 29430 N, D = 23544 N; cos .1 = 0.9950041653, sin .1 = 0.0998334166.

    Wheel 11 (x=3, y=1): eq. 6-7: v_B = (5 - 0.1*1, 0 + 0.1*3) = (4.9, 0.3)
      eq. 8: v_wx = 4.9 cos.1 + 0.3 sin.1 = 4.9054704349, v_wy = -4.9 sin.1 + 0.3 cos.1 = -0.1906824920
      den = sqrt(4.9054704349^2 + 0.01) = 4.9064895992
      alpha = -atan2(-0.1906824920, 4.9064895992) = 0.0388437753
      s = (10*0.5 - 4.9054704349) / 4.9064895992 = 0.0192662316
      Fx: B s = 0.1751300456, atan = 0.1733718449, *1.65 = 0.2860635442, sin = 0.2821779346,
          Fx = 23544 * 0.2821779346 = 6643.5973
      Fy: B a = 0.2987086317, atan = 0.2902716323, arg = 0.2987086317 + 0.5 (0.2987086317 -
          0.2902716323) = 0.3029271314, atan = 0.2941400680, *1.3 = 0.3823820884,
          sin = 0.3731315762, Fy = 8785.0098
      eq. 4: F_B = (cos.1 Fx - sin.1 Fy, sin.1 Fx + cos.1 Fy) = (5733.3694, 9404.3744)
      eq. 5: M = 3 * 9404.3744 - 1 * 5733.3694 = 22479.7537
      P_s = 6643.5973 * 0.0945295651 = 628.0164, P_a = 8785.0098 * 0.1906824920 = 1675.1476,
      P_t = 0.03 * 29430 * 0.2 = 176.58
    Wheel 12 (x=3, y=-1): v_B = (5.1, 0.3); v_w = (5.1044712679, -0.2106491753), den = 5.1054507073
      alpha = 0.0412362739, s = (5 - 5.1044712679) / 5.1054507073 = -0.0204626925
      Fx: B s = -0.1860058749, atan = -0.1839041790, *1.65 = -0.3034418953, sin = -0.2988066179,
          Fx = -7035.1030
      Fy: B a = 0.3171069462, atan = 0.3070764218, arg = 0.3221222084, atan = 0.3116268372,
          *1.3 = 0.4051148884, sin = 0.3941243520, Fy = 9279.2637
      F_B = (-7926.3374, 8530.5677); M = 3 * 8530.5677 + 1 * (-7926.3374) = 17665.3657
      P_s = 734.9661, P_a = 1954.6693, P_t = 176.58
    Wheel 21 (x=-3, y=1, delta=0): v_B = v_w = (4.9, -0.3), den = sqrt(24.01 + 0.01) = 4.9010203019
      alpha = -atan2(-0.3, 4.9010203019) = 0.0611354644, s = (5.2 - 4.9) / 4.9010203019 = 0.0612117440
      Fx: B s = 0.5564147528, atan = 0.5077548213, *1.65 = 0.8377954552, sin = 0.7431698600,
          Fx = 17497.1912
      Fy: B a = 0.4701317215, atan = 0.4394687706, arg = 0.4854631969, atan = 0.4519506825,
          *1.3 = 0.5875358873, sin = 0.5543118044, Fy = 13050.7171
      F_B = (17497.1912, 13050.7171); M = -3 * 13050.7171 - 1 * 17497.1912 = -56649.3426
      P_s = 17497.1912 * 0.3 = 5249.1574, P_a = 13050.7171 * 0.3 = 3915.2151
    Wheel 22 (x=-3, y=-1): v_w = (5.1, -0.3), den = 5.1009802979
      alpha = 0.0587445571, s = 0.1 / 5.1009802979 = 0.0196040749
      Fx: B s = 0.1782010412, atan = 0.1763498915, *1.65 = 0.2909773210, sin = 0.2868886002,
          Fx = 6754.5052
      Fy: B a = 0.4517456440, atan = 0.4243046564, arg = 0.4654661377, atan = 0.4356408706,
          *1.3 = 0.5663331318, sin = 0.5365412878, Fy = 12632.3281
      F_B = (6754.5052, 12632.3281); M = -3 * 12632.3281 + 6754.5052 = -31142.4790
      P_s = 675.4505, P_a = 3789.6984
    Sums: F_B = (22058.7284, 43617.9873), M_z = -47646.7021
    eq. 17: cos .5 = 0.8775825619, sin .5 = 0.4794255386
      xdd = (0.8775825619 * 22058.7284 - 0.4794255386 * 43617.9873) / 12000 = -0.1294351
      ydd = (0.4794255386 * 22058.7284 + 0.8775825619 * 43617.9873) / 12000 = 4.0711586
      phidd = -47646.7021 / 80000 = -0.5955838
    Wear: P_s = 7287.5904, P_alpha = 11334.7304, P_t = 353.16
    """
    v = default_vehicle()
    state = {"phi": 0.5, "vx": 5 * math.cos(0.5), "vy": 5 * math.sin(0.5), "r": 0.1,
             "x": 12.0, "y": -4.0, "delta": np.array([0.1, 0.1, 0.0, 0.0])}
    dy, aux = rhs(v, state, [10.0, 10.0, 10.4, 10.4], [0.2, 0.2, 0.0, 0.0])
    rel = 1e-8
    assert dy[0] == pytest.approx(4.387912809451864, rel=1e-14)
    assert dy[1] == pytest.approx(2.397127693021015, rel=1e-14)
    assert dy[2] == pytest.approx(0.1, rel=1e-14)
    assert dy[3] == pytest.approx(-0.12943513812578022, rel=rel)
    assert dy[4] == pytest.approx(4.071158565662538, rel=rel)
    assert dy[5] == pytest.approx(-0.5955837767586137, rel=rel)
    np.testing.assert_allclose(dy[6:10], [0.2, 0.2, 0.0, 0.0], rtol=0, atol=0)
    np.testing.assert_allclose(dy[10:13], [7287.590369941179, 11334.730382244965, 353.16],
                               rtol=rel)
    np.testing.assert_allclose(aux[:, dyn.AUX_ALPHA],
                               [0.0388437753, 0.0412362739, 0.0611354644, 0.0587445571],
                               atol=1e-10)
    np.testing.assert_allclose(aux[:, dyn.AUX_S],
                               [0.0192662316, -0.0204626925, 0.0612117440, 0.0196040749],
                               atol=1e-10)
    np.testing.assert_allclose(aux[:, dyn.AUX_FX],
                               [6643.597293, -7035.103012, 17497.191183, 6754.505204],
                               rtol=1e-9)
    np.testing.assert_allclose(aux[:, dyn.AUX_FY],
                               [8785.009830, 9279.263743, 13050.717123, 12632.328080],
                               rtol=1e-9)
    np.testing.assert_allclose(aux[:, dyn.AUX_FN], 29430.0)


# ---- steering stops ---------------------------------------------------------------------
def test_wheel_at_its_stop_stops_turning_and_wears_nothing():
    v = default_vehicle()
    dmax, dmin = v.limits.delta_max, v.limits.delta_min
    p = Plant(v, initial={"vx": 2.0, "delta_11": dmax, "delta_22": dmin})
    # wheel 11 pushed further into its upper stop, 22 into its lower one, 12 and 21 held
    p.set_inputs(np.full(4, 4.0), [0.5, 0.0, 0.0, -0.5])
    o = p.outputs()
    assert o["omega_s_11"] == 0.0 and o["omega_s_22"] == 0.0
    assert o["P_t"] == 0.0
    for _ in range(20):
        p.do_step(p.t, 0.01)
        o = p.outputs()
        assert o["delta_11"] == dmax and o["delta_22"] == dmin
        assert o["P_t"] == 0.0
    assert o["W_t"] == 0.0
    # commanded away from the stop it turns again, and wears
    p.set_inputs(np.full(4, 4.0), [-0.5, 0.0, 0.0, 0.5])
    assert p.get("omega_s_11") == -0.5 and p.get("P_t") > 0
    p.do_step(p.t, 0.1)
    assert p.get("delta_11") == pytest.approx(dmax - 0.05, abs=1e-9)
    assert p.get("delta_22") == pytest.approx(dmin + 0.05, abs=1e-9)


def test_wheel_running_into_its_stop():
    v = default_vehicle()
    dmax = v.limits.delta_max
    p = Plant(v, initial={"delta_11": dmax - 0.01})
    p.set_inputs(np.zeros(4), [0.5, 0.0, 0.0, 0.0])
    for _ in range(10):  # 0.1 s at 0.5 rad/s would turn 0.05 rad; the stop allows 0.01
        p.do_step(p.t, 0.01)
    assert p.get("delta_11") == dmax
    assert p.get("omega_s_11") == 0.0
    # steering work only for the 0.01 rad actually turned: k_t F_N |d delta|
    # = 0.03 * 29430 * 0.01 = 8.829 J
    assert p.get("W_t") == pytest.approx(8.829, rel=1e-4)


# ---- load transfer ----------------------------------------------------------------------
def _loads(vehicle, state, u_w, u_s):
    dy, aux = rhs(vehicle, state, u_w, u_s)
    return aux[:, dyn.AUX_FN].copy(), aux


@pytest.mark.parametrize("n", [2, 3])
def test_load_transfer_under_acceleration(n):
    base = default_vehicle() if n == 2 else n_axle_vehicle(n)
    h = 1.2
    v = with_plant_options(base, cg_height=h)
    nw = v.n_wheels
    state = {"vx": 5.0}
    u_w = np.full(nw, 11.0)  # wheels driving faster than the ground: forward acceleration
    FN, aux = _loads(v, state, u_w, np.zeros(nw))
    assert FN.sum() == pytest.approx(v.mass * G, rel=1e-12)
    front, rear = FN[:2], FN[-2:]
    assert np.all(rear > front)
    # the documented model: static forces -> a_x -> minimum-norm loads balancing m h a_x
    _, aux0 = rhs(base, state, u_w, np.zeros(nw))
    ax0 = aux0[:, dyn.AUX_FX].sum() / v.mass  # delta = 0: F_Bx = Fx
    assert ax0 > 1.0
    xc = v.wheel_x - v.wheel_x.mean()
    expected = v.mass * G / nw - v.mass * h * ax0 * xc / np.sum(xc ** 2)
    np.testing.assert_allclose(FN, expected, rtol=1e-12)
    # pitch balance about the CG: sum F_N x = -m h a_x
    assert np.sum(FN * v.wheel_x) == pytest.approx(-v.mass * h * ax0, rel=1e-10)
    # forces were recomputed with the new loads (D = mu F_N grows on the rear)
    assert aux[-1, dyn.AUX_FX] > aux0[-1, dyn.AUX_FX] > aux[0, dyn.AUX_FX]


def test_load_transfer_in_a_turn():
    base = default_vehicle()
    h = 1.2
    v = with_plant_options(base, cg_height=h)
    # all wheels steered 0.1 rad left at 5 m/s: lateral force to the left, a turn to the
    # left, so the right (outside) wheels carry more
    state = {"vx": 5.0, "delta": np.full(4, 0.1)}
    u_w = np.full(4, 10.0)
    FN, _ = _loads(v, state, u_w, np.zeros(4))
    assert FN.sum() == pytest.approx(v.mass * G, rel=1e-12)
    left, right = FN[0::2], FN[1::2]
    assert np.all(right > left)
    _, aux0 = rhs(base, state, u_w, np.zeros(4))
    d = 0.1
    FBx = math.cos(d) * aux0[:, dyn.AUX_FX] - math.sin(d) * aux0[:, dyn.AUX_FY]
    FBy = math.sin(d) * aux0[:, dyn.AUX_FX] + math.cos(d) * aux0[:, dyn.AUX_FY]
    ax0, ay0 = FBx.sum() / v.mass, FBy.sum() / v.mass
    assert ay0 > 1.0
    # roll balance: sum F_N y = -m h a_y; pitch balance as before
    assert np.sum(FN * v.wheel_y) == pytest.approx(-v.mass * h * ay0, rel=1e-10)
    assert np.sum(FN * v.wheel_x) == pytest.approx(-v.mass * h * ax0, rel=1e-8, abs=1e-6)


def test_load_transfer_off_keeps_static_loads():
    v = default_vehicle()
    FN, _ = _loads(v, {"vx": 5.0, "delta": np.full(4, 0.1)}, np.full(4, 11.0), np.zeros(4))
    np.testing.assert_array_equal(FN, 29430.0)


def test_load_transfer_over_a_run_keeps_total_load():
    v = with_plant_options(default_vehicle(), cg_height=1.0)
    p = Plant(v, initial={"vx": 3.0})
    rng = np.random.default_rng(5)
    for _ in range(100):
        p.set_inputs(rng.uniform(5.0, 9.0, 4), rng.uniform(-0.5, 0.5, 4))
        p.do_step(p.t, 0.01)
        o = p.outputs()
        assert sum(o[f"F_N_{k}"] for k in v.wheel_names) == pytest.approx(v.mass * G, rel=1e-9)


# ---- actuator lags ----------------------------------------------------------------------
def test_wheel_lag_is_first_order():
    tau = 0.2
    v = with_plant_options(default_vehicle(), wheel_lag=tau)
    p = Plant(v)  # standing, wheels at rest
    p.set_inputs(np.full(4, 10.0), np.zeros(4))
    assert p.get("omega_w_11") == 0.0  # the actual speed, not the command
    for t_end in (0.05, 0.2, 0.5):
        while p.t < t_end - 1e-12:
            p.do_step(p.t, 0.01)
        # omega(t) = 10 (1 - exp(-t / tau)): 0.05 s -> 2.2119922, 0.2 s -> 6.3212056,
        # 0.5 s -> 9.1791500
        expected = 10.0 * (1.0 - math.exp(-t_end / tau))
        for k in v.wheel_names:
            assert p.get(f"omega_w_{k}") == pytest.approx(expected, rel=1e-6)
    # with an initial actual speed, it decays towards a lower command
    p = Plant(v, initial={**{f"omega_w_{k}": 8.0 for k in v.wheel_names}, "vx": 4.0})
    p.set_inputs(np.full(4, 6.0), np.zeros(4))
    p.do_step(0.0, 0.1)
    # 6 + 2 exp(-0.5) = 7.2130613
    assert p.get("omega_w_12") == pytest.approx(6.0 + 2.0 * math.exp(-0.5), rel=1e-6)


def test_steer_lag_is_first_order():
    tau = 0.1
    v = with_plant_options(default_vehicle(), steer_lag=tau)
    p = Plant(v)
    p.set_inputs(np.zeros(4), np.full(4, 0.4))
    p.do_step(0.0, 0.3)
    # rate 0.4 (1 - exp(-t/tau)); angle = 0.4 (t - tau (1 - exp(-t/tau)))
    # t = 0.3: rate 0.4 * (1 - 0.0497871) = 0.3800852, angle 0.4 (0.3 - 0.0950213) = 0.0819915
    assert p.get("omega_s_11") == pytest.approx(0.4 * (1 - math.exp(-3.0)), rel=1e-6)
    assert p.get("delta_11") == pytest.approx(0.4 * (0.3 - 0.1 * (1 - math.exp(-3.0))), rel=1e-6)


def test_no_lag_tracks_the_command_at_once():
    p = Plant(default_vehicle())
    p.set_inputs(np.full(4, 10.0), np.full(4, 0.3))
    assert p.get("omega_w_21") == 10.0 and p.get("omega_s_21") == 0.3


# ---- combined slip (plant-only option) ------------------------------------------------------
def test_combined_slip_scales_each_force_by_its_weight():
    """With [plant] combined_slip = 1 every wheel's forces are the pure-slip forces times the
    weights of plant.tire.combined_slip_weights at that wheel's slips; the wear powers
    follow the forces (eq. 13, 14); 0 is the paper's model."""
    from msagv.plant.tire import combined_slip_weights

    v0 = default_vehicle()
    v1 = with_plant_options(v0, combined_slip=1.0)
    init = {"vx": 6.0, "vy": 0.8, "r": 0.1, "delta_11": 0.1, "delta_12": 0.05}
    outs = []
    for v in (v0, v1):
        p = Plant(v, initial=init)
        p.set_inputs([13.0, 11.0, 12.5, 12.0], [0.1, 0.0, -0.1, 0.0])
        outs.append(p.outputs())
    off, on = outs
    for w in v0.wheel_names:
        gx, gy = combined_slip_weights(off[f"s_{w}"], off[f"alpha_{w}"])
        assert gx < 0.999 and gy < 0.999  # the state has both slips on every wheel
        assert on[f"Fx_{w}"] == pytest.approx(gx * off[f"Fx_{w}"], rel=1e-12)
        assert on[f"Fy_{w}"] == pytest.approx(gy * off[f"Fy_{w}"], rel=1e-12)
    assert on["P_s"] < off["P_s"] and on["P_alpha"] < off["P_alpha"]


def test_combined_slip_must_be_0_or_1():
    with pytest.raises(VehicleError, match="combined_slip"):
        with_plant_options(default_vehicle(), combined_slip=0.5)
