"""The SA-MPC: cost, bounds, annealer, rollout accuracy, references, metrics, closed loop."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from msagv.controller import rollout as ro
from msagv.controller.loop import closed_loop
from msagv.controller.metrics import compute_metrics, omega_index, tracking_errors, wrap_angle
from msagv.controller.models import MPCSettings, make_model
from msagv.controller.mpc import MPC, ControllerError
from msagv.controller.reference import (ReferenceError, SpeedProfile, case1_curve, case2_line,
                                  from_csv, make_case)
from msagv.plant import Plant, default_vehicle, n_axle_vehicle

try:
    from .annealer_reference import anneal
except ImportError:  # tests/ run as top-level modules
    from annealer_reference import anneal

VEH = default_vehicle()
MSAGV = str(Path(sys.executable).with_name("msagv"))


def _x0(state: dict, vehicle=VEH) -> np.ndarray:
    return np.r_[[state[k] for k in ("x", "y", "phi", "vx", "vy", "r")],
                 [state[f"delta_{w}"] for w in vehicle.wheel_names]]


# ---- cost (eq. 22-26) on hand-made rollouts ---------------------------------------------
def test_cost_on_hand_made_rollout():
    nw = 4
    Np = 2
    ref = np.zeros((Np + 1, 6))
    ref[:, 0] = [0.0, 1.0, 2.0]
    poses = np.zeros((1, Np, 3))
    poses[0, 0] = [1.1, 0.2, 0.0]  # e = (0.1, 0.2, 0)
    poses[0, 1] = [2.0, 0.0, 2 * math.pi - 0.1]  # heading error wraps to -0.1
    wear = np.zeros((1, Np, 3))
    wear[0, 0] = [1000.0, 2000.0, 0.0]  # kW: 1, 2, 0
    wear[0, 1] = [0.0, 0.0, 3000.0]  # kW: 0, 0, 3
    Q = np.array([10.0, 20.0, 30.0])
    L = np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])  # quadratic weights, no energy term
    R = np.zeros(4)
    Z = np.zeros((1, 2 * nw))
    out = np.empty(1)
    ro.batch_cost(poses, wear, ref, Z, np.zeros(2 * nw), Q, L, R, 2 * nw, nw, out)
    # tracking: 10*0.01 + 20*0.04 + 30*0.01 = 0.1 + 0.8 + 0.3 = 1.2
    # wear: 1*1 + 2*4 + 3*9 = 1 + 8 + 27 = 36 ; J = (1.2 + 36) / N_p = 18.6
    assert out[0] == pytest.approx(18.6, rel=1e-12)
    # NTWO (L = 0) sees only the tracking part
    ro.batch_cost(poses, wear, ref, Z, np.zeros(2 * nw), Q, np.zeros(6), R, 2 * nw, nw, out)
    assert out[0] == pytest.approx(0.6, rel=1e-12)


def test_regularisation_terms_by_hand():
    nw = 2
    ref = np.zeros((2, 6))
    poses = np.zeros((1, 1, 3))
    wear = np.zeros((1, 1, 3))
    # two blocks of (d_omega_1, d_omega_2, d_delta_1, d_delta_2)
    Z = np.array([[1.0, 0.0, 0.1, 0.0, 3.0, 0.0, 0.1, 0.2]])
    zprev = np.array([0.0, 0.0, 0.0, 0.0])
    R = np.array([2.0, 100.0, 0.5, 10.0])
    out = np.empty(1)
    ro.batch_cost(poses, wear, ref, Z, zprev, np.zeros(3), np.zeros(6), R, 2 * nw, nw, out)
    # smoothness: block0 vs prev: w: 1^2 -> 2*1 = 2; d: 0.1^2 -> 100*0.01 = 1
    #             block1 vs block0: w: (3-1)^2 = 4 -> 8; d: 0^2 + 0.2^2 = 0.04 -> 4
    # ridge: w: 1 + 9 = 10 -> 5; d: 0.01 + 0.01 + 0.04 = 0.06 -> 0.6
    assert out[0] == pytest.approx(2 + 1 + 8 + 4 + 5 + 0.6, rel=1e-12)


def test_settings_validation_names_field():
    with pytest.raises(ValueError, match="method"):
        MPCSettings(method="fast")
    with pytest.raises(ValueError, match="N_c"):
        MPCSettings(N_p=3, blocks=(2, 2))
    with pytest.raises(ValueError, match="Q"):
        MPCSettings(Q=(1.0, -1.0, 1.0))
    with pytest.raises(ValueError, match="deadline_ms"):
        MPCSettings(deadline_ms=0.0)
    assert MPCSettings(method="ntwo").effective_L == (0.0,) * 6
    assert MPCSettings(method="two", L=(1, 2, 3), E=(4, 5, 6)).effective_L == (1, 2, 3, 0, 0, 0)
    assert MPCSettings(method="two-energy", L=(1, 2, 3), E=(4, 5, 6)).effective_L == \
        (0, 0, 0, 4, 5, 6)
    for bad in ({"method": "twe"}, {"policy": "wheels"}, {"E": (1.0, -1.0, 0.0)},
                {"dugoff_stiffness": "fixed"}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            MPCSettings(**bad)
    assert MPCSettings(method="two").effective_L == MPCSettings().L + (0.0, 0.0, 0.0)


# ---- bounds of eq. 27: never violated --------------------------------------------------
@settings(max_examples=200, deadline=None)
@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-7, 7), st.floats(-15, 15),
       st.floats(-15, 15), st.floats(-2, 2), st.lists(st.floats(-1.5708, 1.5708), min_size=4, max_size=4),
       st.lists(st.floats(-10, 10), min_size=8, max_size=8))
def test_policy_commands_within_bounds(x, y, phi, vx, vy, r, delta, z):
    m = make_model(VEH, MPCSettings())
    lim = VEH.limits
    refk = np.array([x + 3.0, y - 2.0, phi + 1.0, 9.0, -4.0, 0.5])
    om_w = np.empty(4)
    om_s = np.empty(4)
    d = np.array(delta)
    for T in (0.01, 0.1):
        ro.commands_from_policy(np.array([x, y, phi]), d, refk, np.array(z), 0, 4, m.P, m.S,
                                m.wx, m.wy, T, om_w, om_s)
        assert np.all(om_w >= 0) and np.all(om_w <= lim.omega_w_max)
        assert np.all(om_s >= lim.omega_s_min) and np.all(om_s <= lim.omega_s_max)
        nxt = d + T * om_s
        assert np.all(nxt >= lim.delta_min - 1e-12) and np.all(nxt <= lim.delta_max + 1e-12)


@settings(max_examples=15, deadline=None)
@given(st.floats(-3, 3), st.floats(-1.0, 1.0), st.floats(0, 12), st.floats(-0.5, 0.5),
       st.lists(st.floats(-1.5708, 1.5708), min_size=4, max_size=4))
def test_mpc_commands_within_bounds_from_random_states(ey, ephi, v, r, delta):
    ref = case1_curve(25.0, duration=5.0)
    mpc = MPC(VEH, MPCSettings(iterations=5, chains=8), ref)
    state = {"t": 1.0, "x": 5.0, "y": 1.0 + ey, "phi": 0.3 + ephi, "vx": v, "vy": 0.1 * v,
             "r": r, "delta": delta}
    cmd = mpc.step(state)
    lim = VEH.limits
    assert np.all(cmd.omega_w >= 0) and np.all(cmd.omega_w <= lim.omega_w_max)
    assert np.all(cmd.omega_s >= lim.omega_s_min) and np.all(cmd.omega_s <= lim.omega_s_max)
    nxt = np.array(delta) + 0.01 * cmd.omega_s
    assert np.all(nxt >= lim.delta_min - 1e-12) and np.all(nxt <= lim.delta_max + 1e-12)


def test_mpc_rejects_bad_state_without_changing_state():
    ref = case1_curve(15.0, duration=3.0)
    mpc = MPC(VEH, MPCSettings(iterations=3, chains=4), ref)
    good = {"t": 0.0, **{k: v for k, v in ref.initial_state(VEH).items() if not k.startswith("delta")},
            "delta": [0.0] * 4}
    mpc.step(good)
    z_before = mpc.z.copy()
    rng_before = mpc.solver.rng.bit_generator.state
    bad = [
        {k: v for k, v in good.items() if k != "vy"},
        dict(good, x=float("nan")),
        dict(good, delta=[0.0] * 3),
        dict(good, delta="abc"),
    ]
    for b in bad:
        with pytest.raises(ControllerError):
            mpc.step(b)
        assert np.array_equal(mpc.z, z_before)
        assert mpc.solver.rng.bit_generator.state == rng_before
    with pytest.raises(ControllerError, match="reference"):
        MPC(VEH, MPCSettings(iterations=2, chains=2)).step(good)


def test_on_solve_sees_each_solve_with_the_previous_solution():
    """The observer hook: called once per solve with the state given to step, the decision
    vector before the solve and the returned command; not called for a refused state."""
    ref = case1_curve(15.0, duration=3.0)
    calls = []
    mpc = MPC(VEH, MPCSettings(iterations=3, chains=4), ref,
              on_solve=lambda st, z, cmd: calls.append((st, z.copy(), cmd)))
    st = {"t": 0.0, **{k: v for k, v in ref.initial_state(VEH).items()
                       if not k.startswith("delta")}, "delta": [0.0] * 4}
    befores, cmds = [], []
    for k in range(3):
        befores.append(mpc.z.copy())
        cmds.append(mpc.step(dict(st, t=0.01 * k)))
    with pytest.raises(ControllerError):
        mpc.step(dict(st, x=float("nan")))
    assert len(calls) == 3
    for (st_k, z_k, cmd_k), before, cmd in zip(calls, befores, cmds):
        np.testing.assert_array_equal(z_k, before)
        assert cmd_k is cmd
    assert calls[2][0]["t"] == 0.02
    assert not np.array_equal(calls[2][1], mpc.z)  # the new solution is mpc.z
    # settable as an attribute too (the benchmarks do so)
    mpc.on_solve = None
    mpc.step(st)
    assert len(calls) == 3


# ---- the annealer ---------------------------------------------------------------------
def test_annealer_finds_known_minimum_of_small_problem():
    # a multimodal 4-d problem: a bowl around x* = (0.5, -1, 0.25, 2) with ripples that
    # make a local minimum near every integer offset from x* (global minimum 0 at x*)
    xs = np.array([0.5, -1.0, 0.25, 2.0])

    def f(X):
        d = X - xs
        return np.sum(d * d + 2.0 * (1.0 - np.cos(2 * np.pi * d)), axis=1)

    lo, hi = -np.full(4, 4.0), np.full(4, 4.0)
    # a plain local descent from the origin stalls in a ripple
    assert f(np.zeros((1, 4)))[0] > 1.0
    res = anneal(f, np.zeros(4), lo, hi, np.full(4, 1.0), np.random.default_rng(1), chains=64,
                 iterations=400, sigma_final=0.01, t_start=1.0, t_end=1e-4, restart_every=0)
    # every other local minimum costs >= 0.97
    assert res.cost < 0.01
    assert np.allclose(res.x, xs, atol=0.05)
    assert np.all(res.x >= lo) and np.all(res.x <= hi)


def test_annealer_seeded_and_deadline():
    f = lambda X: np.sum((X - 0.3) ** 2, axis=1)  # noqa: E731
    args = (f, np.zeros(6), -np.ones(6), np.ones(6), np.full(6, 0.2))
    a = anneal(*args, np.random.default_rng(7), iterations=20)
    b = anneal(*args, np.random.default_rng(7), iterations=20)
    assert np.array_equal(a.x, b.x) and a.cost == b.cost
    slow = lambda X: (__import__("time").sleep(0.002), f(X))[1]  # noqa: E731
    c = anneal(slow, *args[1:], np.random.default_rng(7), iterations=10000, deadline_s=0.05)
    assert 1 <= c.iterations < 10000
    assert c.cost <= f(np.zeros((1, 6)))[0]


@pytest.mark.parametrize("threads", [1, 2])
def test_compiled_annealer_equals_the_generic_one_on_the_mpc_cost(threads):
    """The MPC's compiled solver loop (controller.sa_kernel) is the generic annealer run on
    the MPC's batch cost: same seed, same random draws, same answer."""
    from msagv.controller import rollout as ro

    v = default_vehicle()
    ref, init = make_case("curve", 25.0)
    mpc = MPC(v, MPCSettings(threads=threads, chains=6, iterations=25), ref)
    st = init(v)
    x0 = np.r_[[st[k] for k in ("x", "y", "phi", "vx", "vy", "r")], np.full(4, 0.02)]
    s = mpc.settings
    R = np.ascontiguousarray(ref.sample(s.dt * np.arange(s.N_p + 1)))
    warm = np.random.default_rng(3).normal(size=mpc.model.dim) * 0.05
    zprev = warm[:8].copy()
    got = mpc.solver.kernel.solve(x0, R, zprev, warm, np.random.default_rng(5))
    buf, costs = mpc.model.allocate(s.chains), np.empty(s.chains)

    def cost(Z):
        mpc.model.rollout(x0, R, Z, out=buf)
        ro.batch_cost(buf.poses, buf.wear, R, Z, zprev, mpc.horizon.Q, mpc.horizon.L, mpc.horizon.R, 8, 4, costs)
        return costs

    want = anneal(cost, warm, mpc.horizon.lower, mpc.horizon.upper, mpc.horizon.sigma, np.random.default_rng(5),
                  chains=s.chains, iterations=s.iterations, sigma_final=s.sigma_final,
                  t_start=s.t_start, t_end=s.t_end, ladder=s.ladder, adapt_up=s.adapt_up,
                  adapt_down=s.adapt_down, pool=mpc.solver.kernel.pool, proposals=mpc.solver.kernel.proposals,
                  restart_every=mpc.solver.kernel.restart_every)
    assert got.cost == pytest.approx(want.cost, rel=1e-12)
    assert np.allclose(got.x, want.x, rtol=0, atol=1e-12)
    assert got.iterations == want.iterations == 25
    assert got.accepted == pytest.approx(want.accepted)
    # the warm start is among the candidates: annealing never returns worse than it
    assert got.cost <= cost(np.clip(warm, mpc.horizon.lower, mpc.horizon.upper)[None, :])[0]
    # a deadline stops early with the best point so far, inside the box
    late = mpc.solver.kernel.solve(x0, R, zprev, warm, np.random.default_rng(5), deadline_s=1e-4)
    assert 1 <= late.iterations < 25
    assert np.all(late.x >= mpc.horizon.lower) and np.all(late.x <= mpc.horizon.upper)


# ---- rollout vs plant --------------------------------------------------------------------
def _plant_vs_rollout(speed, dt, t_start=1.0):
    ref, init = make_case("curve", speed)
    s = MPCSettings(dt=dt, N_p=int(round(1.0 / dt)), blocks=(1,))
    m = make_model(VEH, s)
    z = np.zeros(m.dim)
    p = Plant(VEH, initial=init(VEH))

    def policy(plant, T):
        st = plant.state_message()
        x0 = np.r_[[st[k] for k in ("x", "y", "phi", "vx", "vy", "r")], st["delta"]]
        ow, os_ = np.empty(4), np.empty(4)
        ro.commands_from_policy(x0[:3].copy(), x0[6:].copy(), ref.sample(st["t"]), z, 0, 4,
                                m.P, m.S, m.wx, m.wy, T, ow, os_)
        return x0, ow, os_

    while p.t < t_start - 1e-9:
        _, ow, os_ = policy(p, 0.01)
        p.set_inputs(ow, os_)
        p.do_step(p.t, 0.01)
    x0, _, _ = policy(p, 0.01)
    R = ref.sample(p.t + dt * np.arange(s.N_p + 1))
    pred = m.rollout(x0, R, z[None]).poses[0]
    poses = []
    for _ in range(s.N_p):  # the plant under the same zero-order-held policy
        _, ow, os_ = policy(p, dt)
        p.set_inputs(ow, os_)
        for _ in range(int(round(dt / 0.01))):
            p.do_step(p.t, 0.01)
        poses.append(p.pose)
    return np.abs(np.array(poses)[:, :2] - pred[:, :2]).max()


@pytest.mark.parametrize("speed", [5.0, 35.0])
def test_rollout_matches_plant_to_order_of_step(speed):
    e1 = _plant_vs_rollout(speed, 0.1)
    e2 = _plant_vs_rollout(speed, 0.05)
    # over a 1 s horizon on the winding road the prediction stays within millimetres
    assert e1 < 5e-3
    # and the error falls at least linearly with the step (it is second order here)
    assert e2 < 0.6 * e1


# ---- references ---------------------------------------------------------------------------
def test_case1_curvature_feasible_for_steering_limits():
    ref = case1_curve(35.0)
    v = np.hypot(ref.vx, ref.vy)
    kappa = np.abs(ref.r[v > 0] / v[v > 0])
    # kinematic steering angle of the outermost axle about the curve's centre
    assert math.atan(max(abs(x) for x in VEH.axle_x) * kappa.max()) < VEH.limits.delta_max
    assert kappa.max() == pytest.approx(4.0 * (2 * math.pi / 60.0) ** 2, rel=0.02)
    # constant speed along the path
    assert np.allclose(v[: int(ref.duration / 0.01) - 5], 35 / 3.6, rtol=1e-3)


def test_initial_state_is_pure_rolling():
    from msagv.plant.stepping import Plant as P
    ref = case1_curve(25.0)
    p = P(VEH, initial=ref.initial_state(VEH))
    # wheel speeds for pure rolling: v_wx / r_w with the kinematic angles
    st = ref.initial_state(VEH)
    c, s = math.cos(st["phi"]), math.sin(st["phi"])
    ub, vb = c * st["vx"] + s * st["vy"], -s * st["vx"] + c * st["vy"]
    om = [math.hypot(ub - st["r"] * yw, vb + st["r"] * xw) / VEH.wheel_radius
          for xw, yw in zip(VEH.wheel_x, VEH.wheel_y)]
    p.set_inputs(om, [0.0] * 4)
    o = p.outputs()
    assert max(abs(o[f"Fy_{w}"]) for w in VEH.wheel_names) < 1e-6 * VEH.normal_load
    assert o["P_s"] + o["P_alpha"] < 1e-6


def test_case2_starts_60_degrees_off():
    ref, init = make_case("line", 10.0)
    st = init(VEH)
    assert st["phi"] == pytest.approx(math.radians(60.0))
    assert math.hypot(st["vx"], st["vy"]) == pytest.approx(10 / 3.6)
    assert ref.duration == 20.0 and ref.t[-1] > ref.duration


def test_speed_profile_and_errors():
    sp = SpeedProfile.parse("0:0,10:36")
    assert sp.speed(5.0) == pytest.approx(5.0)
    assert sp.distance(10.0) == pytest.approx(50.0)
    for bad in ("fast", "-3", "0:5,0:6", "1:2:3"):
        with pytest.raises(ReferenceError):
            SpeedProfile.parse(bad)


@pytest.mark.parametrize("profile", ["15", "0:0,10:36", "0.5", "0:5,10:0"])
def test_a_path_reference_finds_its_end_where_the_whole_1e5_s_table_does(profile):
    """path_reference searches the first steps of its 1e5 s table only (the whole one, 10
    million steps, took seconds per reference): the same step, the same time, as a search
    of the whole table. 0.5 km/h reaches 150 m after 108,000 steps (the table grows four
    times); "0:5,10:0" stops after 6.9 m and never reaches 10 m."""
    from msagv.controller import reference as R

    sp = SpeedProfile.parse(profile)
    table = np.arange(0.0, 1e5, 0.01)
    dist = sp.distance(table)
    for d in (0.0, 1e-3, 6.9, 10.0, 150.0, 170.0):
        k = R._reach_step(sp, d)
        assert k == np.searchsorted(dist, d)
        if k < len(table):
            assert R._reach_times(k + 1)[k] == table[k]
    assert R._REACH_STEPS == len(table)
    if dist[-1] < 150.0:
        with pytest.raises(ReferenceError, match="never reaches the end of the path"):
            case1_curve(sp)
    else:  # the duration is one of the table's times, to the bit
        dur = case1_curve(sp).duration
        assert table[round(dur / 0.01)] == dur


def test_reference_from_csv(tmp_path):
    t = np.linspace(0, 4, 81)
    path = tmp_path / "traj.csv"
    path.write_text("t,x,y,phi\n" + "\n".join(f"{a},{2 * a},{0.5 * a},{math.atan2(0.5, 2)}" for a in t))
    ref = from_csv(path)
    row = ref.sample(1.0)
    assert row[:3] == pytest.approx([2.0, 0.5, math.atan2(0.5, 2)])
    assert row[3:] == pytest.approx([2.0, 0.5, 0.0], abs=1e-9)
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,y,phi\n0,0,0,0\n1,1,0,nan\n2,2,0,0\n")
    with pytest.raises(ReferenceError, match=":3"):
        from_csv(bad)
    bad.write_text("t,x,y\n0,0,0\n")
    with pytest.raises(ReferenceError, match="phi"):
        from_csv(bad)
    bad.write_text("t,x,y,phi\n0,0,0,0\n0,1,0,0\n2,2,0,0\n")
    with pytest.raises(ReferenceError, match="increase"):
        from_csv(bad)


# ---- metrics (eq. 28-33) -------------------------------------------------------------------
def test_metrics_by_hand():
    pose = np.array([[0.01, 0.0, 0.0], [0.0, -0.02, math.radians(2.0)], [0.0, 0.0, 0.0], [-0.01, 0.02, 0.0]])
    ref = np.zeros((4, 3))
    ref[:, 2] = [0.0, 0.0, 2 * math.pi, 0.0]  # a wrapped reference heading is no error
    e = tracking_errors(pose, ref)
    # e_x = 100 sqrt((1e-4 + 1e-4)/4) cm = 0.7071 cm; e_y = 100 sqrt((4e-4+4e-4)/4) = 1.4142
    # e_phi = sqrt(4/4) = 1 deg; e_bar = (0.7071 + 1.4142 + 1) / 3
    assert e["e_x_cm"] == pytest.approx(math.sqrt(0.5))
    assert e["e_y_cm"] == pytest.approx(math.sqrt(2.0))
    assert e["e_phi_deg"] == pytest.approx(1.0)
    assert e["e_bar"] == pytest.approx((math.sqrt(0.5) + math.sqrt(2.0) + 1.0) / 3)
    # lateral error: across the reference heading (0 here, so y): 0, -2, 0, 2 cm
    assert e["e_lat_rms_cm"] == pytest.approx(math.sqrt(2.0))
    assert e["e_lat_max_cm"] == pytest.approx(2.0)
    # the largest distance from the reference's position: sqrt(1 + 4) cm at the last pose
    # (the lateral error there is 2 cm, the along-track 1 cm); the largest heading error
    # 2 deg (the wrapped reference heading is none)
    assert e["e_pos_max_cm"] == pytest.approx(math.sqrt(5.0))
    assert e["e_phi_max_deg"] == pytest.approx(2.0)
    # along a reference heading of 90 deg the lateral error is -x
    e90 = tracking_errors([[0.03, 0.5, math.pi / 2]], [[0.0, 0.0, math.pi / 2]])
    assert e90["e_lat_rms_cm"] == pytest.approx(3.0) and e90["e_lat_max_cm"] == pytest.approx(3.0)
    # Omega's two branches (eq. 33): 1e8^0.5 * 10^0.1 and 1e8^0.5 * 100^0.5
    assert omega_index(1e8, 10.0) == pytest.approx(1e4 * 10 ** 0.1)
    assert omega_index(1e8, 100.0) == pytest.approx(1e5)
    assert omega_index(1e8, 50.0) == pytest.approx(1e4 * 50 ** 0.5)
    m = compute_metrics(pose, ref, (1.0, 2.0, 3.0), (11.0, 22.0, 33.0), [1.0, 2.0, 3.0])
    assert (m["W_s"], m["W_alpha"], m["W_t"], m["W_tw"]) == (10.0, 20.0, 30.0, 60.0)
    assert m["solve_ms"]["max"] == 3.0 and m["steps"] == 4
    assert wrap_angle(math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)


# ---- closed loop -----------------------------------------------------------------------------
def _run(case, speed, duration, method="two", vehicle=VEH, **kw):
    ref, init = make_case(case, speed)
    plant = Plant(vehicle, initial=init(vehicle))
    mpc = MPC(vehicle, MPCSettings(method=method, **kw), ref)
    return closed_loop(plant, mpc, ref, duration), plant


def test_determinism_same_seed_same_commands():
    a, _ = _run("curve", 25.0, 0.3, seed=3)
    b, _ = _run("curve", 25.0, 0.3, seed=3)
    c, _ = _run("curve", 25.0, 0.3, seed=4)
    assert np.array_equal(np.array(a.omega_w), np.array(b.omega_w))
    assert np.array_equal(np.array(a.omega_s), np.array(b.omega_s))
    assert not np.array_equal(np.array(a.omega_w), np.array(c.omega_w))


@pytest.mark.parametrize("method", ["ntwo", "two"])
def test_short_closed_loop_curve_tracks(method):
    log, _ = _run("curve", 25.0, 3.0, method=method)
    m = log.metrics()
    assert m["e_bar"] < 1.5
    assert m["W_tw"] > 0


@pytest.mark.parametrize("method", ["ntwo", "two"])
def test_short_closed_loop_line_converges(method):
    log, plant = _run("line", 10.0, 6.0, method=method)
    st = plant.state_message()
    ref = case2_line(10.0)
    x, y, phi = ref.sample(6.0)[:3]
    assert abs(st["y"] - y) < 0.05  # onto the line (started 60 deg off)
    assert abs(wrap_angle(st["phi"] - phi)) < math.radians(1.0)


def test_three_axle_vehicle_closed_loop():
    v3 = n_axle_vehicle(3)
    log, _ = _run("curve", 15.0, 1.5, vehicle=v3)
    assert log.metrics()["e_bar"] < 2.0
    assert np.array(log.omega_w).shape[1] == 6


def test_msagv_run_json(tmp_path):
    png = tmp_path / "run.png"
    out = subprocess.run([MSAGV, "run", "--case", "curve", "--speed", "20", "--duration", "0.5",
                          "--json", "--plot", str(png)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)  # the result document (experiments/results.py)
    m = doc["metrics"]
    for k in ("W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg", "e_bar", "Omega", "steps"):
        assert k in m
    assert set(m["solve_ms"]) == {"p50", "p99", "max"}
    assert m["steps"] == 50
    assert doc["scenario"]["speed_kmh"] == 20.0 and doc["scenario"]["case"] == "curve"
    assert doc["completed"] is True
    assert [w for w in doc["warnings"] if "control period" not in w] == []  # load-dependent
    assert png.stat().st_size > 10000
    bad = subprocess.run([MSAGV, "run", "--trajectory", str(tmp_path / "none.csv")],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "no such file" in bad.stderr


# ---- the targets, measured on full-length runs (slow) ------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("speed", [5.0, 15.0, 25.0, 35.0])
def test_case1_targets(speed):
    ntwo = _run("curve", speed, case1_curve(speed).duration, method="ntwo")[0].metrics()
    two = _run("curve", speed, case1_curve(speed).duration, method="two")[0].metrics()
    assert ntwo["e_bar"] < 2.0
    assert two["e_bar"] < 3.0
    assert two["W_tw"] <= ntwo["W_tw"]


def test_wear_energy_term_by_hand():
    """TWO-energy: the cost adds E . P_k [kW] per step (divided by N_p with the tracking)."""
    nw, Np = 4, 2
    ref = np.zeros((Np + 1, 6))
    poses = np.zeros((1, Np, 3))
    wear = np.zeros((1, Np, 3))
    wear[0, 0] = [1000.0, 2000.0, 0.0]
    wear[0, 1] = [0.0, 500.0, 3000.0]
    L = np.array([0.0, 0.0, 0.0, 0.5, 0.25, 2.0])
    out = np.empty(1)
    ro.batch_cost(poses, wear, ref, np.zeros((1, 2 * nw)), np.zeros(2 * nw), np.zeros(3), L,
                  np.zeros(4), 2 * nw, nw, out)
    # 0.5 * 1 + 0.25 * (2 + 0.5) + 2 * 3 = 7.125; / N_p = 3.5625
    assert out[0] == pytest.approx(3.5625, rel=1e-12)


def test_feed_forward_controller_is_the_policy_without_optimisation():
    
    ref, init = make_case("curve", 15.0)
    st = dict(init(VEH), t=0.5)
    st["delta"] = [st.pop(f"delta_{w}") for w in VEH.wheel_names]
    ff = MPC(VEH, MPCSettings(), ref, solver="ff")
    cmd = ff.step(st)
    mpc = MPC(VEH, MPCSettings(), ref)
    x0, R, _, _ = mpc.horizon_problem(st)
    w, s = mpc.horizon.commands(x0, R[0], np.zeros(mpc.model.dim))
    assert np.array_equal(cmd.omega_w, w) and np.array_equal(cmd.omega_s, s)
    assert cmd.iterations == 0 and math.isnan(cmd.cost)
