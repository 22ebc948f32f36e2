"""The three baseline prediction models (controller/models.py, controller/rollout.py) against
the simplification that defines each of them, through the models' own interface
``model.rollout(x0, ref, Z) -> Rollout(poses, wear, first_commands)`` (no closed loop):

* Kinematic (Zhang et al. 2016): pure rolling. The predicted slip wear is zero and the body
  moves exactly as the commanded wheel velocities dictate.
* DH (Du et al. 2024): the rigid body with Dugoff tires. Its forces match Dugoff's formula
  at hand-computed points (checked through the predicted slip wear) and never exceed
  mu F_N.
* TCT (Tang et al. 2024): lateral and yaw dynamics only. The predicted body-frame
  longitudinal speed is the reference speed, whatever the wheel-speed commands.

Every expected number was worked out by hand (steps in the comments) for the built-in
vehicle: m = 12000 kg, r_w = 0.5 m, F_N = 12000 * 9.81 / 4 = 29430 N, mu F_N = 23544 N,
Dugoff C_s = 353160 N, C_alpha = 235440 N/rad, mu = 0.8; slip regularisation v_eps = 0.1 m/s.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from msagv.controller.models import MODELS, MPCSettings, make_model
from msagv.plant import default_vehicle
from msagv.plant.tire import dugoff_forces

VEH = default_vehicle()
R_W = 0.5
F_N = 29430.0
MU_FN = 23544.0
DUG = (353160.0, 235440.0, 0.8)  # C_s, C_alpha, mu
K_T = 0.03


def model_of(name: str, **kw):
    return make_model(VEH, MPCSettings(model=name, method="ntwo", **kw))


def straight_case(model, speed=10.0, ref_speed=None):
    """Vehicle on the x axis heading +x at ``speed`` [m/s], wheels straight; reference the
    x axis driven at ``ref_speed`` (default ``speed``) from the vehicle's position."""
    s = model.settings
    ref_speed = speed if ref_speed is None else ref_speed
    x0 = np.zeros(6 + VEH.n_wheels)
    x0[3] = speed
    ref = np.zeros((s.N_p + 1, 6))
    ref[:, 0] = ref_speed * s.dt * np.arange(s.N_p + 1)
    ref[:, 3] = ref_speed
    return x0, ref


def curve_case(model, speed=8.0, radius=30.0):
    """Vehicle on a left circle of ``radius`` at ``speed``, wheels steered kinematically
    (consistent instantaneous centre); reference the same circle (G velocities, yaw rate)."""
    s = model.settings
    r = speed / radius
    x0 = np.zeros(6 + VEH.n_wheels)
    x0[3], x0[5] = speed, r
    x0[6:] = np.arctan2(r * VEH.wheel_x, speed - r * VEH.wheel_y)
    t = s.dt * np.arange(s.N_p + 1)
    th = r * t
    ref = np.stack([radius * np.sin(th), radius * (1 - np.cos(th)), th, speed * np.cos(th),
                    speed * np.sin(th), np.full_like(t, r)], axis=1)
    return x0, ref


def random_Z(model, batch=16, seed=1):
    """Offsets of every block inside the optimiser's box (wheel +-3 rad/s, steer +-0.3 rad)."""
    rng = np.random.default_rng(seed)
    nw = VEH.n_wheels
    box = np.tile(np.r_[np.full(nw, 3.0), np.full(nw, 0.3)], len(model.settings.blocks))
    return rng.uniform(-1.0, 1.0, (batch, model.dim)) * box


# ---- the interface every model shares ------------------------------------------------------
@pytest.mark.parametrize("name", sorted(MODELS))
def test_rollout_shapes_and_batch_rows_are_independent(name):
    m = model_of(name)
    x0, ref = curve_case(m)
    Z = random_Z(m, batch=8)
    out = m.rollout(x0, ref, Z)
    Np, nw = m.settings.N_p, VEH.n_wheels
    assert out.poses.shape == (8, Np, 3) and out.wear.shape == (8, Np, 3)
    assert out.first_commands.shape == (8, 2, nw)
    assert np.all(np.isfinite(out.poses)) and np.all(out.wear >= 0)
    one = m.rollout(x0, ref, Z[3])
    np.testing.assert_array_equal(one.poses[0], out.poses[3])
    np.testing.assert_array_equal(one.wear[0], out.wear[3])


def test_all_models_share_the_policy_and_the_steering_wear():
    """Same state, same decision vectors -> the same first commands and the same steering
    wear P_t = sum_ij k_t F_N |omega_s,ij| (eq. 15) in every model: only the state
    evolution differs (the paper's 'unified framework'). The feed-forward's steady
    cornering angle is switched off here: it is the one part of the policy that uses each
    model's own cornering stiffness (0 for the kinematic model)."""
    ms = {n: model_of(n, ff_cornering=False) for n in MODELS}
    x0, ref = curve_case(ms["mf"])
    Z = random_Z(ms["mf"])
    outs = {n: m.rollout(x0, ref, Z) for n, m in ms.items()}
    c0 = outs["mf"].first_commands
    pt = K_T * F_N * np.abs(c0[:, 1, :]).sum(axis=1)  # eq. (15) summed over the 4 wheels
    assert np.all(pt > 0)
    for n, o in outs.items():
        np.testing.assert_array_equal(o.first_commands, c0, err_msg=n)
        np.testing.assert_allclose(o.wear[:, 0, 2], pt, rtol=1e-12, err_msg=n)


# ---- Kinematic: pure rolling, zero slip ----------------------------------------------------
def test_kinematic_predicts_zero_slip_wear_where_the_dynamic_model_does_not():
    km, mf = model_of("kinematic"), model_of("mf")
    for case in (straight_case, curve_case):
        x0, ref = case(km)
        Z = random_Z(km, batch=32)
        k = km.rollout(x0, ref, Z)
        assert np.all(k.wear[:, :, 0] == 0.0)  # P_s (eq. 13): no slip ratio
        assert np.all(k.wear[:, :, 1] == 0.0)  # P_alpha (eq. 14): no slip angle
        assert np.any(k.wear[:, :, 2] > 0.0)  # steering wear is still predicted
        d = mf.rollout(x0, ref, Z)
        assert np.all(d.wear[:, :, 0].sum(axis=1) > 0.0)
        assert np.all(d.wear[:, :, 1].sum(axis=1) > 0.0)


def test_kinematic_body_moves_as_the_wheels_roll():
    km = model_of("kinematic")
    # straight at 10 m/s: feed-forward 10 / 0.5 = 20 rad/s, offset +1 rad/s on the four
    # wheels in block 0 -> 21 rad/s, rolling without slip at 21 * 0.5 = 10.5 m/s, so the
    # first prediction step (dt = 0.1 s) moves 1.05 m, with no lateral motion or yaw
    x0, ref = straight_case(km)
    Z = np.zeros((1, km.dim))
    Z[0, :4] = 1.0
    out = km.rollout(x0, ref, Z)
    np.testing.assert_array_equal(out.first_commands[0, 0], [21.0] * 4)
    assert out.poses[0, 0] == pytest.approx([1.05, 0.0, 0.0], abs=1e-12)
    # the dynamic model accelerates through the tires instead: it does not reach 10.5 m/s
    # within one step
    d = model_of("mf").rollout(x0, ref, Z)
    assert 1.0 < d.poses[0, 0, 0] < 1.04
    # on the circle with every wheel steered about one centre and no offsets, the twist
    # fitted to the wheel velocities is exactly the reference twist: the first step is
    # x0 + dt * (vx, vy, r) = (0.8, 0, 0.02667)
    x0, ref = curve_case(km)
    out = km.rollout(x0, ref, np.zeros((1, km.dim)))
    assert np.abs(out.first_commands[0, 1]).max() < 1e-9  # already at the kinematic angles
    np.testing.assert_allclose(out.poses[0, 0], [0.8, 0.0, 0.8 / 30.0], atol=1e-12)


# ---- DH: Dugoff tires ----------------------------------------------------------------------
@pytest.mark.parametrize("offset, expected_Ps", [
    # straight at 10 m/s, wheels at 20 + offset rad/s. Offset 1: slip speed
    # 21 * 0.5 - 10 = 0.5 m/s, s = 0.5 / sqrt(10^2 + 0.1^2) = 0.5 / 10.0004999875
    # = 0.0499975002; C_s s = 17657.1172 N; lambda = 23544 * 1.0499975 / (2 * 17657.1172)
    # = 0.7000333; f = lambda (2 - lambda) = 0.9100200 (saturating);
    # Fx = 17657.1172 / 1.0499975 * 0.9100200 = 15303.2076 N per wheel;
    # P_s = 4 wheels * 15303.2076 N * 0.5 m/s = 30606.4152 W
    (1.0, 30606.41521961902),
    # offset 0.1: slip speed 0.05 m/s, s = 0.0049997500; lambda = 6.70 >= 1 -> f = 1
    # (linear range); Fx = 353160 * 0.00499975 / 1.00499975 = 1756.9275 N;
    # P_s = 4 * 1756.9275 * 0.05 = 351.3855 W
    (0.1, 351.3855036457986),
])
def test_dh_forces_are_dugoffs_at_hand_computed_points(offset, expected_Ps):
    dh = model_of("dugoff", dugoff_stiffness="file")  # the hand values use the file's C_s
    x0, ref = straight_case(dh)
    Z = np.zeros((1, dh.dim))
    Z[0, :4] = offset
    out = dh.rollout(x0, ref, Z)
    # wear over the first step, eq. (13): sum |Fx (omega_w r_w - v_wx)|; no lateral slip
    assert out.wear[0, 0, 0] == pytest.approx(expected_Ps, rel=1e-9)
    assert out.wear[0, 0, 1] == 0.0
    # ... and that is Dugoff, not the Magic Formula the paper's model uses
    mf = model_of("mf").rollout(x0, ref, Z)
    assert abs(mf.wear[0, 0, 0] - expected_Ps) > 1e-4 * expected_Ps


@pytest.mark.parametrize("s, alpha, Fx, Fy", [
    # a cornering wheel of the DH prediction at 35 km/h: s = 0.02, alpha = 0.04 rad;
    # tan(0.04) = 0.0400213470; C_s s = 7063.2; C_alpha tan = 9422.6259;
    # S = sqrt(7063.2^2 + 9422.6259^2) = 11776.0211; lambda = 23544 * 1.02 / (2 * 11776.0211)
    # = 1.0196517 >= 1 -> f = 1 (linear): Fx = 7063.2 / 1.02 = 6924.7059,
    # Fy = 9422.6259 / 1.02 = 9237.8686
    (0.02, 0.04, 6924.705882352941, 9237.868565317598),
    # deep in the friction circle: s = 1, alpha = 0.5 rad; tan(0.5) = 0.5463024898;
    # C_s s = 353160; C_alpha tan = 128621.4582; S = 375852.9834;
    # lambda = 23544 * 2 / (2 * 375852.9834) = 0.0626415; f = lambda (2 - lambda) = 0.1213591;
    # Fx = 353160 / 2 * 0.1213591 = 21429.5844; Fy = 128621.4582 / 2 * 0.1213591 = 7804.6902
    (1.0, 0.5, 21429.584425693007, 7804.69021871587),
])
def test_dugoff_formula_hand_values(s, alpha, Fx, Fy):
    fx, fy = dugoff_forces(s, alpha, F_N, *DUG)
    assert fx == pytest.approx(Fx, rel=1e-8)
    assert fy == pytest.approx(Fy, rel=1e-8)


def test_dugoff_never_exceeds_mu_FN():
    s = np.linspace(-5.0, 5.0, 401)[:, None]
    a = np.linspace(-1.5, 1.5, 301)[None, :]
    for load in (F_N, 0.25 * F_N, 4.0 * F_N):
        fx, fy = dugoff_forces(s, a, load, *DUG)
        assert np.all(np.hypot(fx, fy) <= 0.8 * load * (1.0 + 1e-12))
    # and through the DH prediction: wheels spun far past the peak (20 + 10 rad/s, clipped
    # to omega_w_max = 25 rad/s: slip speed 25 * 0.5 - 10 = 2.5 m/s, s = 0.25) transmit at
    # most mu F_N = 23544 N each: P_s <= 4 * mu F_N * 2.5 m/s = 235440 W
    dh = model_of("dugoff")
    x0, ref = straight_case(dh)
    Z = np.zeros((1, dh.dim))
    Z[0, :4] = 10.0
    out = dh.rollout(x0, ref, Z)
    np.testing.assert_array_equal(out.first_commands[0, 0], [25.0] * 4)
    assert out.wear[0, 0, 0] <= 4 * MU_FN * 2.5 * (1 + 1e-12)
    # saturated, close to the limit: lambda = 23544 * 1.25 / (2 * 88290) = 0.1667,
    # f = 0.3056, Fx = 88290 / 1.25 * 0.3056 = 21582 N = 0.917 mu F_N
    assert out.wear[0, 0, 0] > 0.9 * 4 * MU_FN * 2.5


# ---- TCT: the longitudinal speed is the reference speed ------------------------------------
def body_speeds(model, x0, poses):
    """Body-frame (u, v) after each prediction step, recovered from the predicted poses by
    inverting the trapezoidal position update ``p_{k+1} = p_k + dt (V_k + V_{k+1}) / 2``
    (rollout.py's documented DEVIATION from eq. 21), starting from x0's velocity in G."""
    dt = model.settings.dt
    V = np.array(x0[3:5], dtype=float)
    p = np.array(x0[0:2], dtype=float)
    out = []
    for k in range(poses.shape[0]):
        V = 2.0 * (poses[k, :2] - p) / dt - V
        p = poses[k, :2]
        c, s = math.cos(poses[k, 2]), math.sin(poses[k, 2])
        out.append((c * V[0] + s * V[1], -s * V[0] + c * V[1]))
    return np.array(out)


@pytest.mark.parametrize("case", ["straight", "curve", "ramp"])
def test_tct_never_changes_the_longitudinal_speed(case):
    tct = model_of("tct")
    if case == "straight":
        x0, ref = straight_case(tct)
    elif case == "curve":
        x0, ref = curve_case(tct)
    else:
        # the plant is at 6 m/s, the reference asks for 6 -> 9 m/s over the horizon: TCT
        # predicts the reference speed from the first step on (it is held, not modelled)
        x0, ref = straight_case(tct, speed=6.0)
        ref[:, 3] = np.linspace(6.0, 9.0, tct.settings.N_p + 1)
        ref[:, 0] = np.r_[0.0, np.cumsum(0.5 * (ref[1:, 3] + ref[:-1, 3]) * tct.settings.dt)]
    Z = random_Z(tct, batch=12)
    out = tct.rollout(x0, ref, Z)
    v_ref = np.hypot(ref[:-1, 3], ref[:-1, 4])  # the reference speed at each step's start
    for b in range(Z.shape[0]):
        uv = body_speeds(tct, x0, out.poses[b])
        np.testing.assert_allclose(uv[:, 0], v_ref, rtol=0, atol=1e-9)
    # the steering offsets do move it (lateral + yaw dynamics are modelled) ...
    assert np.ptp(out.poses[:, -1, 2]) > 1e-3
    # ... the wheel-speed offsets do not (no longitudinal tire force in the dynamics)
    Zw = Z.copy()
    nw, nb = VEH.n_wheels, len(tct.settings.blocks)
    for blk in range(nb):
        Zw[:, blk * 2 * nw: blk * 2 * nw + nw] = 0.0
    np.testing.assert_allclose(tct.rollout(x0, ref, Zw).poses, out.poses, rtol=0, atol=1e-12)
    # the paper's model under the same offsets does change the longitudinal speed
    mf = model_of("mf")
    uv = body_speeds(mf, x0, mf.rollout(x0, ref, Z).poses[0])
    assert np.abs(uv[:, 0] - v_ref).max() > 0.05


def test_dh_stiffnesses_are_the_tires_and_scale_with_the_load():
    """DH's Dugoff stiffnesses are the Magic Formula's slopes at zero slip at the vehicle's
    load (B C mu F_N), so they scale with the mass; 'file' keeps the file's values."""
    from msagv.controller import rollout as ro
    from msagv.controller.models import dugoff_stiffness
    from msagv.plant import layout as lay

    lo, la = VEH.tire_longitudinal, VEH.tire_lateral
    for mass in (8000.0, 12000.0, 20000.0):
        v = VEH.replace(mass=mass)
        FN = mass * 9.81 / 4
        m = make_model(v, MPCSettings(model="dugoff", method="ntwo"))
        assert m.P[ro.P_DUGOFF_C_S] == pytest.approx(lo.B * lo.C * lo.mu * FN, rel=1e-12)
        assert m.P[ro.P_DUGOFF_C_ALPHA] == pytest.approx(la.B * la.C * la.mu * FN, rel=1e-12)
        # the cornering feed-forward sees the same stiffness: k_alpha = m / (2n C_alpha)
        assert m.S[lay.S_K_ALPHA] == pytest.approx(mass / (4 * la.B * la.C * la.mu * FN))
        f = dugoff_stiffness(v, MPCSettings(dugoff_stiffness="file"))
        assert f == (DUG[0], DUG[1])
    # at 12 t the file's values are these slopes (to the file's rounding)
    assert lo.B * lo.C * lo.mu * F_N == pytest.approx(DUG[0], rel=2e-4)


# ---- decision parametrisations: twist (single centre), raw (eq. 27's U) ---------------------
def _policy_commands(model, x0, refk, z, dt=0.01):
    from msagv.controller import rollout as ro

    nw = model.n_wheels
    om_w, om_s = np.empty(nw), np.empty(nw)
    ro.commands_from_policy(x0[:3].copy(), x0[6:].copy(), refk, np.ascontiguousarray(z), 0, nw,
                            model.P, model.S, model.wx, model.wy, dt, om_w, om_s)
    return om_w, om_s


@pytest.mark.parametrize("axles", [2, 3])
def test_twist_policy_steers_every_wheel_about_one_centre(axles):
    """Kinematic as the paper defines it: whatever the decision (a body-twist offset),
    the target steering angles of all wheels have axes that meet in one point, the
    instantaneous centre of the commanded twist, and the wheel speeds are that twist's."""
    from msagv.controller.models import make_model
    from msagv.plant import n_axle_vehicle

    v = VEH if axles == 2 else n_axle_vehicle(3)
    m = make_model(v, MPCSettings(model="kinematic", method="ntwo", policy="twist"))
    assert m.dim == 3 * len(m.settings.blocks) and m.stride == 3
    rng = np.random.default_rng(1)
    kservo = (1 - math.exp(-m.settings.K_servo * 0.01)) / 0.01
    for _ in range(20):
        phi = rng.uniform(-1, 1)
        u, r = rng.uniform(2, 8), rng.uniform(-0.3, 0.3)
        refk = np.array([0.0, 0.0, phi, u * math.cos(phi), u * math.sin(phi), r])
        z = np.r_[rng.normal(0, 0.3, 3), np.zeros(m.dim - 3)]
        # the wheels start at angles near their targets, so the rate limits do not bind
        x0 = np.r_[0.0, 0.0, phi, 0.0, 0.0, 0.0, rng.normal(0, 0.002, v.n_wheels)]
        for _ in range(100):  # move delta onto the targets (the servo's fixed point)
            _, om_s = _policy_commands(m, x0, refk, z)
            x0[6:] += om_s / kservo
        assert np.abs(om_s).max() < 0.5  # the rate limits (0.8 rad/s) do not bind now
        om_w, om_s = _policy_commands(m, x0, refk, z)
        tgt = x0[6:] + om_s / kservo
        # the body twist in B after the offsets; each wheel's velocity from it
        ub, vb, rd = u + z[0], z[1], r + z[2]
        vwx, vwy = ub - rd * v.wheel_y, vb + rd * v.wheel_x
        assert np.allclose(om_w * v.wheel_radius, np.hypot(vwx, vwy), rtol=1e-9)
        # axes: (c - w_i) . (cos tgt_i, sin tgt_i) = 0 for one point c; rd != 0 here
        A = np.c_[np.cos(tgt), np.sin(tgt)]
        b = v.wheel_x * np.cos(tgt) + v.wheel_y * np.sin(tgt)
        c, *_ = np.linalg.lstsq(A, b, rcond=None)
        assert np.abs(A @ c - b).max() < 1e-6
        assert c == pytest.approx([-vb / rd, ub / rd], rel=1e-6)  # the twist's own centre


def test_raw_policy_commands_are_the_decision_clipped_to_eq_27():
    from msagv.controller.models import make_model

    m = make_model(VEH, MPCSettings(method="ntwo", policy="raw"))
    lo, hi, sig = m.box()
    lim = VEH.limits
    assert lo[:4].tolist() == [0.0] * 4 and hi[:4].tolist() == [lim.omega_w_max] * 4
    assert lo[4:8].tolist() == [lim.omega_s_min] * 4 and hi[4:8].tolist() == [lim.omega_s_max] * 4
    x0, ref = straight_case(m)
    z = np.r_[[3.0, 30.0, -1.0, 7.0], [0.2, -0.5, 2.0, 0.0]]
    z = np.r_[z, np.zeros(m.dim - 8)]
    om_w, om_s = _policy_commands(m, x0, ref[0], z)
    assert om_w.tolist() == [3.0, lim.omega_w_max, 0.0, 7.0]
    assert om_s.tolist() == [0.2, -0.5, lim.omega_s_max, 0.0]
    # a wheel at its stop cannot turn further into it
    x0[6] = lim.delta_max
    _, om_s = _policy_commands(m, x0, ref[0], np.r_[np.zeros(4), 0.5, 0, 0, 0, np.zeros(m.dim - 8)])
    assert om_s[0] == 0.0
    # the plain feed-forward is a raw decision too (a fresh controller's warm start)
    z0 = m.origin(x0, ref[0], 0.01)
    ff = make_model(VEH, MPCSettings(method="ntwo"))
    w_ff, s_ff = _policy_commands(ff, x0, ref[0], np.zeros(ff.dim))
    assert np.allclose(_policy_commands(m, x0, ref[0], z0)[0], w_ff)
    assert np.allclose(_policy_commands(m, x0, ref[0], z0)[1], s_ff)
