"""Tire and wear models (plant/tire.py) against hand-computed values of the paper's equations.

Every expected number below was worked out by hand (a calculator, step by step, shown in
the comments), not by calling the code under test. The built-in truck tire is used:
F_N = 12000 * 9.81 / 4 = 29430 N, D = mu F_N = 0.8 * 29430 = 23544 N,
lateral (B, C, E) = (7.69, 1.3, -0.5), longitudinal (B, C, E) = (9.09, 1.65, 0).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msagv.plant import default_vehicle
from msagv.plant.tire import (dugoff_forces, magic_formula, magic_formula_and_slope, slip_angle,
                        slip_jacobian, slip_ratio, wear_power_angle, wear_power_slip,
                        wear_power_steer, wheel_to_body, wheel_velocity)

V_EPS = 0.1
D = 23544.0  # N, 0.8 * 29430
LAT = (7.69, 1.3, D, -0.5)  # B, C, D, E
LON = (9.09, 1.65, D, 0.0)

finite = dict(allow_nan=False, allow_infinity=False)


# ---- Magic Formula (paper, unnumbered f after eq. 12) -----------------------------------
@pytest.mark.parametrize("xi, B, C, Dp, E, expected", [
    # B=C=D=1, E=0, xi=1: sin(atan(1)) = sin(pi/4) = 0.7071067812
    (1.0, 1.0, 1.0, 1.0, 0.0, 0.7071067811865476),
    # E=1 removes the linear part: f = D sin(C atan(atan(B xi)));
    # B xi = 3, atan 3 = 1.2490457724, atan(1.2490457724) = 0.8956828297,
    # C = 2: sin(1.7913656593) = 0.9757730459
    (3.0, 1.0, 2.0, 1.0, 1.0, 0.975773045947223),
    # lateral, alpha = 0.05 rad: B a = 0.3845, atan(0.3845) = 0.3670733145,
    # arg = 0.3845 + 0.5 (0.3845 - 0.3670733145) = 0.3932133428,
    # atan(arg) = 0.3746421540, C * = 0.4870348002, sin = 0.4680075298, * 23544 = 11018.7693
    (0.05, *LAT, 11018.769281753352),
    # lateral, alpha = 0.2 rad: B a = 1.538, atan = 0.9942839947,
    # arg = 1.538 + 0.5 (1.538 - 0.9942839947) = 1.8098580027, atan = 1.0660131293,
    # C * = 1.3858170681, sin = 0.9829400657, * 23544 = 23142.3409 (near the peak D)
    (0.2, *LAT, 23142.340907102927),
    # lateral, alpha = 1 rad (past the peak): B a = 7.69, atan = 1.4414829596,
    # arg = 7.69 + 0.5 (7.69 - 1.4414829596) = 10.8142585202, atan = 1.4785880383,
    # C * = 1.9221644498, sin = 0.9389027075, * 23544 = 22105.5253
    (1.0, *LAT, 22105.525344802278),
    # longitudinal, s = 0.1: B s = 0.909, E = 0 so arg = 0.909, atan = 0.7377652841,
    # C * = 1.2173127188, sin = 0.9381724938, * 23544 = 22088.3332
    (0.1, *LON, 22088.333194742176),
    # longitudinal, s = -0.03: B s = -0.2727, atan = -0.2662266644, C * = -0.4392739962,
    # sin = -0.4252824997, * 23544 = -10012.8512
    (-0.03, *LON, -10012.8511734082),
])
def test_magic_formula_hand_values(xi, B, C, Dp, E, expected):
    assert magic_formula(xi, B, C, Dp, E) == pytest.approx(expected, rel=1e-10)


def test_magic_formula_slope_at_zero_is_BCD():
    # f'(0) = B C D: the cornering stiffness of the built-in tire is 7.69 * 1.3 * 23544
    # = 235369.97 N/rad, i.e. ~ 8 F_N per rad (8 * 29430 = 235440).
    h = 1e-7
    slope = (magic_formula(h, *LAT) - magic_formula(-h, *LAT)) / (2 * h)
    assert slope == pytest.approx(7.69 * 1.3 * 23544.0, rel=1e-6)
    assert magic_formula_and_slope(0.0, *LAT)[1] == pytest.approx(7.69 * 1.3 * 23544.0,
                                                                  rel=1e-12)
    assert magic_formula_and_slope(0.0, *LON)[1] == pytest.approx(9.09 * 1.65 * 23544.0,
                                                                  rel=1e-12)


@pytest.mark.parametrize("coef", [LAT, LON, (3.0, 2.0, 1.0, 1.0)], ids=["lat", "lon", "E=1"])
@pytest.mark.parametrize("xi", [-1.0, -0.2, -0.03, 0.0, 0.05, 0.2, 1.0, 4.0])
def test_magic_formula_and_slope_is_value_and_derivative(coef, xi):
    # the value is magic_formula's; the slope is its central difference (step 1e-6:
    # truncation ~ f''' h^2 / 6, far below the tolerance)
    f, df = magic_formula_and_slope(xi, *coef)
    assert f == pytest.approx(magic_formula(xi, *coef), rel=1e-13, abs=1e-9)
    h = 1e-6
    fd = (magic_formula(xi + h, *coef) - magic_formula(xi - h, *coef)) / (2 * h)
    assert df == pytest.approx(fd, rel=1e-6, abs=1e-6 * abs(coef[2]))


@settings(max_examples=200, deadline=None)
@given(xi=st.floats(-20, 20, **finite), B=st.floats(0.1, 30, **finite),
       C=st.floats(0.5, 2.0, **finite), Dp=st.floats(1.0, 1e5, **finite),
       E=st.floats(-3.0, 1.0, **finite))
def test_magic_formula_is_odd(xi, B, C, Dp, E):
    assert magic_formula(-xi, B, C, Dp, E) == pytest.approx(-magic_formula(xi, B, C, Dp, E),
                                                            rel=1e-12, abs=1e-9)


# ---- wheel velocity, eq. (6)-(8) --------------------------------------------------------
def test_wheel_velocity_hand_values():
    # body u = 10, v = 1, r = 0.2; wheel at (3, 1); delta = 0.3
    # eq. 6: v_Bx = 10 - 0.2 * 1 = 9.8;  eq. 7: v_By = 1 + 0.2 * 3 = 1.6
    # eq. 8 inverted (R(delta)^T): cos .3 = 0.9553364891, sin .3 = 0.2955202067
    # v_wx = 0.9553364891 * 9.8 + 0.2955202067 * 1.6 = 9.3622975934 + 0.4728323307 = 9.8351299241
    # v_wy = -0.2955202067 * 9.8 + 0.9553364891 * 1.6 = -2.8960980253 + 1.5285383826 = -1.3675596427
    vwx, vwy = wheel_velocity(10.0, 1.0, 0.2, 3.0, 1.0, 0.3)
    assert vwx == pytest.approx(9.835129924089083, rel=1e-12)
    assert vwy == pytest.approx(-1.367559642680158, rel=1e-12)


# ---- slip angle, eq. (9) ----------------------------------------------------------------
def test_slip_angle_equals_eq9_forward():
    # body-frame wheel velocity (10, 1.5), delta = 0.2:
    # eq. 9: alpha = 0.2 - atan(1.5 / 10) = 0.2 - 0.1488899476 = 0.0511100524
    # regularised: v_wx = 10 cos .2 + 1.5 sin .2 = 10.0986697746,
    # v_wy = -10 sin .2 + 1.5 cos .2 = -0.5165934412,
    # -atan2(-0.5165934412, sqrt(10.0986697746^2 + 0.01)) = 0.0511075511
    # (differs from eq. 9 by ~ tan(alpha) v_eps^2 / (2 v_wx^2) = 2.5e-6 rad)
    vwx, vwy = wheel_velocity(10.0, 1.5, 0.0, 0.0, 0.0, 0.2)
    a = slip_angle(vwx, vwy, V_EPS)
    assert a == pytest.approx(0.05110755112655809, abs=1e-12)
    assert a == pytest.approx(0.05111005239050276, abs=5e-6)


def test_slip_angle_equals_eq9_on_a_grid_of_forward_wheels():
    # eq. 9 as printed, for forward-moving wheels (v_Bx in [3, 20] m/s >> v_eps)
    rng = np.random.default_rng(1)
    vbx = rng.uniform(3.0, 20.0, (5, 7))
    vby = rng.uniform(-2.0, 2.0, (5, 7))
    delta = rng.uniform(-0.5, 0.5, (5, 7))
    eq9 = delta - np.arctan(vby / vbx)
    vwx, vwy = wheel_velocity(vbx, vby, 0.0, 0.0, 0.0, delta)
    a = slip_angle(vwx, vwy, V_EPS)
    # |regularised - eq. 9| <= |tan alpha| v_eps^2 / (2 v_wx^2)
    bound = np.abs(np.tan(eq9)) * V_EPS ** 2 / (2 * vwx ** 2) + 1e-12
    assert a.shape == (5, 7)
    assert np.all(np.abs(a - eq9) <= bound)


def test_slip_angle_reversing_sideways_and_at_rest():
    # reversing (v_wx = -5, v_wy = 1): eq. 9 would give -atan(1 / -5) = +0.1974, a force
    # pushing along the lateral velocity. Regularised: -atan2(1, sqrt(25.01)) =
    # -atan2(1, 5.0009999) = -0.1973571096: the force opposes the lateral velocity.
    assert slip_angle(-5.0, 1.0, V_EPS) == pytest.approx(-0.19735710955037208, abs=1e-12)
    # sideways (v_wx = 0, v_wy = 2): -atan2(2, 0.1) = -1.5208379311, finite
    assert slip_angle(0.0, 2.0, V_EPS) == pytest.approx(-1.5208379310729538, abs=1e-12)
    # at rest: 0
    assert slip_angle(0.0, 0.0, V_EPS) == 0.0


@settings(max_examples=300, deadline=None)
@given(vwx=st.floats(-30, 30, **finite), vwy=st.floats(-30, 30, **finite))
def test_lateral_force_opposes_lateral_velocity(vwx, vwy):
    a = slip_angle(vwx, vwy, V_EPS)
    assert math.isfinite(a) and abs(a) <= math.pi / 2
    Fy = magic_formula(a, *LAT)
    assert Fy * vwy <= 0.0
    if abs(vwy) > 1e-6:
        assert Fy != 0.0


# ---- slip ratio, eq. (10) ---------------------------------------------------------------
def test_slip_ratio_hand_values():
    # driving: omega_w = 20 rad/s, r_w = 0.5 m, v_wx = 9.5 m/s:
    # (20 * 0.5 - 9.5) / sqrt(9.5^2 + 0.1^2) = 0.5 / sqrt(90.26) = 0.5 / 9.5005263012 = 0.0526286633
    # (eq. 10 exactly: 0.5 / 9.5 = 0.0526315789; relative difference ~ (0.1/9.5)^2 / 2 = 5.5e-5)
    s = slip_ratio(20.0, 0.5, 9.5, V_EPS)
    assert s == pytest.approx(0.052628663312712695, rel=1e-12)
    assert s == pytest.approx(0.5 / 9.5, rel=6e-5)
    # locked wheel: (0 - 5) / sqrt(25.01) = -5 / 5.0009999 = -0.9998000600
    assert slip_ratio(0.0, 0.5, 5.0, V_EPS) == pytest.approx(-0.9998000599800071, rel=1e-12)
    # spinning on the spot: (2 * 0.5 - 0) / 0.1 = 10 (finite where eq. 10 divides by 0)
    assert slip_ratio(2.0, 0.5, 0.0, V_EPS) == pytest.approx(10.0, rel=1e-12)
    # a reversing wheel that does not turn (omega_w >= 0, so it cannot roll backwards):
    # (0 - (-3)) / sqrt(9 + 0.01) = 3 / 3.0016662 = 0.9994449
    assert slip_ratio(0.0, 0.5, -3.0, V_EPS) == pytest.approx(3.0 / math.sqrt(9.01), rel=1e-12)


@pytest.mark.parametrize("om, vwx, vwy", [(20.0, 9.5, 0.3), (0.0, 5.0, -1.0), (2.0, 0.0, 2.0),
                                           (0.0, -3.0, 0.5), (10.0, 0.02, -0.01)])
def test_slip_jacobian_is_the_derivative_of_the_slips(om, vwx, vwy):
    # central differences of slip_ratio and slip_angle in v_wx and v_wy
    ds_dx, da_dx, da_dy = slip_jacobian(om, 0.5, vwx, vwy, V_EPS)
    h = 1e-6
    fd = lambda f, a, b: (f(a) - f(b)) / (2 * h)  # noqa: E731
    assert ds_dx == pytest.approx(fd(lambda v: slip_ratio(om, 0.5, v, V_EPS), vwx + h, vwx - h),
                                  rel=1e-6, abs=1e-6)
    assert da_dx == pytest.approx(fd(lambda v: slip_angle(v, vwy, V_EPS), vwx + h, vwx - h),
                                  rel=1e-6, abs=1e-6)
    assert da_dy == pytest.approx(fd(lambda v: slip_angle(vwx, v, V_EPS), vwy + h, vwy - h),
                                  rel=1e-6, abs=1e-6)


def test_wheel_to_body_hand_values():
    # eq. (4): R(delta) (Fx, Fy); delta = 0.3: cos = 0.9553364891, sin = 0.2955202067
    # F_Bx = 0.9553364891 * 1000 - 0.2955202067 * 500 = 955.3364891 - 147.7601033 = 807.5763857
    # F_By = 0.2955202067 * 1000 + 0.9553364891 * 500 = 295.5202067 + 477.6682446 = 773.1884513
    fbx, fby = wheel_to_body(1000.0, 500.0, 0.3)
    assert fbx == pytest.approx(807.5763857, rel=1e-9)
    assert fby == pytest.approx(773.1884513, rel=1e-9)
    # and back: R(delta)^T undoes it (wheel_velocity with r = 0 is R(delta)^T)
    fx, fy = wheel_velocity(fbx, fby, 0.0, 0.0, 0.0, 0.3)
    assert (fx, fy) == pytest.approx((1000.0, 500.0), rel=1e-12)


# ---- wear powers, eq. (13)-(15) ---------------------------------------------------------
def test_wear_powers_hand_values():
    # eq. 13: |Fx (omega_w r_w - v_wx)| = |1000 * (20 * 0.5 - 9.5)| = 1000 * 0.5 = 500 W
    assert wear_power_slip(1000.0, 20.0, 0.5, 9.5) == pytest.approx(500.0, rel=1e-12)
    # braking: |-2000 * (0 - 5)| = 10000 W
    assert wear_power_slip(-2000.0, 0.0, 0.5, 5.0) == pytest.approx(10000.0, rel=1e-12)
    # eq. 14: |Fy v_wy| = |-1500 * 0.3| = 450 W
    assert wear_power_angle(-1500.0, 0.3) == pytest.approx(450.0, rel=1e-12)
    # eq. 15: |k_t F_N omega_s| = |0.03 * 29430 * (-0.5)| = 441.45 W
    assert wear_power_steer(0.03, 29430.0, -0.5) == pytest.approx(441.45, rel=1e-12)
    assert wear_power_steer(0.03, 29430.0, 0.0) == 0.0


# ---- Dugoff ------------------------------------------------------------------------------
DUG = (29430.0, 353160.0, 235440.0, 0.8)  # F_N, C_s, C_alpha, mu


@pytest.mark.parametrize("s, alpha, Fx, Fy", [
    # s = 0.05, alpha = 0.02: tan = 0.0200026671; C_s s = 17658; C_alpha tan = 4709.4279;
    # S = sqrt(17658^2 + 4709.4279^2) = 18275.2203; lambda = 0.8 * 29430 * 1.05 / (2 * 18275.2203)
    # = 24721.2 / 36550.4405 = 0.6763585; f = lambda (2 - lambda) = 0.8952562;
    # Fx = 17658 / 1.05 * 0.8952562 = 15055.6507; Fy = 4709.4279 / 1.05 * 0.8952562 = 4015.3756
    (0.05, 0.02, 15055.650729410514, 4015.375592199199),
    # s = 0.01, alpha = 0.005: C_s s = 3531.6, C_alpha tan(0.005) = 235440 * 0.0050000417
    # = 1177.2098; S = 3722.6364; lambda = 23544 * 1.01 / 7445.2727 = 3.1939 >= 1 -> f = 1;
    # Fx = 3531.6 / 1.01 = 3496.6337, Fy = 1177.2098 / 1.01 = 1165.5543 (linear range)
    (0.01, 0.005, 3496.6336633663364, 1165.5542674238623),
    # s = -0.2, alpha = -0.1: tan = -0.1003346721; C_s s = -70632; C_alpha tan = -23622.7952;
    # S = 74477.6200; lambda = 23544 * 1.2 / 148955.2399 = 0.1896731; f = 0.3433703;
    # Fx = -70632 / 1.2 * 0.3433703 = -20210.7754; Fy = -23622.7952 / 1.2 * 0.3433703 = -6759.4717
    (-0.2, -0.1, -20210.775390082814, -6759.4717378555115),
])
def test_dugoff_hand_values(s, alpha, Fx, Fy):
    fx, fy = dugoff_forces(s, alpha, *DUG)
    assert fx == pytest.approx(Fx, rel=1e-9)
    assert fy == pytest.approx(Fy, rel=1e-9)


@settings(max_examples=300, deadline=None)
@given(s=st.floats(-50, 50, **finite), alpha=st.floats(-3.0, 3.0, **finite),
       F_N=st.floats(1.0, 1e5, **finite), C_s=st.floats(1e2, 1e7, **finite),
       C_alpha=st.floats(1e2, 1e7, **finite), mu=st.floats(0.05, 1.5, **finite))
def test_dugoff_never_exceeds_friction_limit(s, alpha, F_N, C_s, C_alpha, mu):
    fx, fy = dugoff_forces(s, alpha, F_N, C_s, C_alpha, mu)
    assert math.isfinite(fx) and math.isfinite(fy)
    assert math.hypot(fx, fy) <= mu * F_N * (1.0 + 1e-12)
    # forces point along the slips
    assert fx * s >= 0.0


def tire_forces(vehicle, s, alpha, F_N=None):
    """Magic Formula forces (Fx, Fy) [N] of eq. (11), (12) with a vehicle's coefficients;
    ``F_N`` defaults to the static load m g / (2n)."""
    FN = vehicle.normal_load if F_N is None else F_N
    lo, la = vehicle.tire_longitudinal, vehicle.tire_lateral
    return (magic_formula(s, lo.B, lo.C, lo.mu * FN, lo.E),
            magic_formula(alpha, la.B, la.C, la.mu * FN, la.E))


def test_tire_forces_uses_vehicle_coefficients():
    v = default_vehicle()
    # s = 0.1, alpha = 0.05 at the static load: the hand values of the Magic Formula above
    fx, fy = tire_forces(v, 0.1, 0.05)
    assert fx == pytest.approx(22088.333194742176, rel=1e-10)
    assert fy == pytest.approx(11018.769281753352, rel=1e-10)
    # D scales with the load: half the load, half the force
    fx2, fy2 = tire_forces(v, 0.1, 0.05, F_N=29430.0 / 2)
    assert fx2 == pytest.approx(22088.333194742176 / 2, rel=1e-10)
    assert fy2 == pytest.approx(11018.769281753352 / 2, rel=1e-10)


# ---- scalars and batches give the same values elementwise -------------------------------
def _batch(rng, lo, hi, shape=(3, 4)):
    return rng.uniform(lo, hi, shape)


def test_batches_match_scalars():
    rng = np.random.default_rng(7)
    xi = _batch(rng, -1, 1)
    a, b, c, d, e, f = (_batch(rng, -10, 10) for _ in range(6))
    om = _batch(rng, 0, 25)
    cases = {
        "magic_formula": (lambda *z: magic_formula(z[0], *LAT), (xi,)),
        "slip_angle": (lambda p, q: slip_angle(p, q, V_EPS), (a, b)),
        "slip_ratio": (lambda w, v: slip_ratio(w, 0.5, v, V_EPS), (om, a)),
        "wear_power_slip": (lambda F, w, v: wear_power_slip(F, w, 0.5, v), (a * 1e3, om, b)),
        "wear_power_angle": (lambda F, v: wear_power_angle(F, v), (a * 1e3, b)),
        "wear_power_steer": (lambda w: wear_power_steer(0.03, 29430.0, w), (c,)),
        "wheel_velocity_x": (lambda *z: wheel_velocity(*z)[0], (a, b, c / 10, d, e, f / 10)),
        "wheel_velocity_y": (lambda *z: wheel_velocity(*z)[1], (a, b, c / 10, d, e, f / 10)),
        "dugoff_x": (lambda p, q: dugoff_forces(p, q, *DUG)[0], (xi, c / 10)),
        "dugoff_y": (lambda p, q: dugoff_forces(p, q, *DUG)[1], (xi, c / 10)),
    }
    for name, (fn, args) in cases.items():
        out = np.asarray(fn(*args))
        assert out.shape == (3, 4), name
        for idx in np.ndindex(3, 4):
            scalar = fn(*(float(x[idx]) for x in args))
            assert isinstance(scalar, float), name
            assert out[idx] == pytest.approx(scalar, rel=1e-13, abs=1e-12), (name, idx)


def test_batches_broadcast_against_parameters():
    # one slip against a column of loads: (2,) x (3, 1) -> (3, 2)
    xi = np.array([0.05, 0.2])
    Ds = np.array([[23544.0], [11772.0], [0.0]])
    out = magic_formula(xi, 7.69, 1.3, Ds, -0.5)
    assert out.shape == (3, 2)
    assert out[0] == pytest.approx([11018.769281753352, 23142.340907102927], rel=1e-10)
    assert out[1] == pytest.approx([11018.769281753352 / 2, 23142.340907102927 / 2], rel=1e-10)
    assert np.all(out[2] == 0.0)


# ---- combined slip (plant-only option) ------------------------------------------------------
def test_combined_slip_weights_by_hand():
    from msagv.plant.tire import combined_slip_weights

    s, a = 0.05, 0.05
    # MF 5.2 weighting functions with the documented coefficients, written out here
    b_xa = 13.046 * math.cos(math.atan(9.718 * s))
    b_ys = 10.622 * math.cos(math.atan(7.820 * a))
    want = (math.cos(0.9995 * math.atan(b_xa * a)), math.cos(1.0587 * math.atan(b_ys * s)))
    got = combined_slip_weights(s, a)
    assert got[0] == pytest.approx(want[0], rel=1e-12) and got[1] == pytest.approx(want[1], rel=1e-12)
    assert 0.5 < got[0] < 1.0 and 0.5 < got[1] < 1.0
    # no interaction without the other slip; symmetric in sign; weaker with more slip
    assert combined_slip_weights(0.1, 0.0)[0] == 1.0  # no slip angle: pure longitudinal
    assert combined_slip_weights(0.0, 0.1)[1] == 1.0  # no slip ratio: pure lateral
    assert combined_slip_weights(-s, -a) == pytest.approx(got)
    assert combined_slip_weights(s, 2 * a)[0] < got[0] and combined_slip_weights(2 * s, a)[1] < got[1]
