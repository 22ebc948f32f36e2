"""The IPOPT backend (controller/ipopt.py) against independent references.

* the symbolic rollout against the numba rollout (poses, wear powers, first commands) and
  the symbolic cost against ``batch_cost``, at random states and decision vectors that
  drive the policy's clips, for 2 and 3 axles;
* the reference-optimum property: IPOPT run to convergence from the annealer's own warm
  start never ends above the annealer's cost, at states of a closed-loop run;
* ``MPC(solver='ipopt').step`` inside the bounds of eq. (27), a short closed loop that tracks;
* the command line (``--solver ipopt``) and the errors without CasADi or with a baseline
  model.
"""

from __future__ import annotations

import functools
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from msagv.controller import make_case
from msagv.controller import rollout as ro
from msagv.controller.loop import closed_loop
from msagv.controller.models import MPCSettings, make_model
from msagv.controller.mpc import MPC, ControllerError
from msagv.plant import Plant, default_vehicle, n_axle_vehicle
from msagv.plant import layout as lay

DIST = [lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]
from helpers import assert_commands_within_bounds

try:
    import casadi  # noqa: F401

    HAVE_CASADI = True
except ImportError:  # pragma: no cover
    HAVE_CASADI = False

needs_casadi = pytest.mark.skipif(not HAVE_CASADI, reason="casadi not installed (msagv[ipopt])")

VEH = default_vehicle()
METRIC_KEYS = {"W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg", "e_bar",
               "Omega", "e_lat_rms_cm", "e_lat_max_cm", "e_pos_max_cm", "e_phi_max_deg",
               "solve_ms", "steps", "distance_m", "W_tw_per_km"}


@functools.lru_cache(maxsize=None)
def _vehicle(axles: int):
    return VEH if axles == 2 else n_axle_vehicle(axles)


@functools.lru_cache(maxsize=None)
def _nlp(axles: int, settings: MPCSettings):
    """(numba model, HorizonNLP) of one configuration, built once per test session."""
    from msagv.controller.ipopt import HorizonNLP

    model = make_model(_vehicle(axles), settings)
    return model, HorizonNLP(model, settings)


def _random_case(rng, model, ref, kind: str):
    """A state x0, reference rows R, decision vector z and previous first block zprev.

    kind 'near': near the reference, moderate offsets (the tracking regime);
    'far': large pose and heading errors (pose-feedback saturation), offsets over the
    whole box, steering angles near the limits (rate clips);
    'wrap': the heading one turn off the reference (the cost's wrap);
    'crawl': as 'near' with the first block's wheel-speed offsets at -offset_w_max, which
    on a slow reference (feed-forward below offset_w_max) clips the wheel speeds at 0."""
    s = model.settings
    nw = model.n_wheels
    t = rng.uniform(0.0, 8.0)
    R = np.ascontiguousarray(ref.sample(t + s.dt * np.arange(s.N_p + 1)))
    box = np.tile(np.r_[np.full(nw, s.offset_w_max), np.full(nw, s.offset_d_max)], len(s.blocks))
    lim = model.vehicle.limits
    if kind == "far":
        pose = R[0, :3] + rng.normal(0.0, [3.0, 3.0, 0.6])
        vel = R[0, 3:6] * rng.uniform(-0.5, 1.5) + rng.normal(0.0, [2.0, 2.0, 0.3])
        delta = rng.uniform(lim.delta_min, lim.delta_max, nw)
        delta[0] = lim.delta_max - 1e-3
        delta[-1] = lim.delta_min + 2e-3
        z = rng.uniform(-1.0, 1.0, box.size) * box
    else:
        pose = R[0, :3] + rng.normal(0.0, [0.2, 0.2, 0.03])
        if kind == "wrap":
            pose[2] += 2.0 * math.pi
        vel = R[0, 3:6] + rng.normal(0.0, [0.2, 0.2, 0.02])
        delta = rng.normal(0.0, 0.05, nw)
        z = rng.uniform(-0.3, 0.3, box.size) * box
        if kind == "crawl":
            z[:nw] = -box[:nw]
    x0 = np.r_[pose, vel, delta]
    zprev = rng.uniform(-0.3, 0.3, 2 * nw) * box[: 2 * nw]
    return x0, R, z, zprev


def _numba(model, x0, R, z):
    out = model.rollout(x0, R, z[None, :], exact=True)  # the mirrors' reference: EXACT
    return out.poses[0].copy(), out.wear[0].copy(), out.first_commands[0].copy()


# ---- (a) the symbolic rollout is the numba rollout ---------------------------------------
@needs_casadi
@pytest.mark.parametrize("axles,adapt", [(2, False), (3, False), (2, True)])
def test_symbolic_rollout_matches_numba(axles, adapt):
    """(With ``adapt``, the tires that the online adaptation moves are the NLP's parameters:
    each draw scales them in the model, as the adaptation does, and the NLP follows without a
    rebuild.)"""
    from msagv.controller import adaptation as ad

    model, nlp = _nlp(axles, MPCSettings(adapt=adapt))
    P0, S0 = model.P.copy(), model.S.copy()
    trng = np.random.default_rng(300)  # the tires' own draws (the states' stay the same)
    fast, _ = make_case("curve", 25.0)
    slow, _ = make_case("curve", 5.0)  # low feed-forward wheel speeds: offsets clip them at 0
    rng = np.random.default_rng(100 + axles)
    lim = model.vehicle.limits
    hit = {"om_s at a rate limit": False, "om_w clipped to 0": False}
    dist = [lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]
    for kind, ref in [("near", fast), ("near", slow), ("wrap", fast), ("crawl", slow),
                      ("far", fast), ("far", fast), ("far", slow), ("zero", fast)]:
        x0, R, z, _ = _random_case(rng, model, ref, "far" if kind == "zero" else kind)
        # the offset-free disturbance (body accelerations) carried by both, zero or not
        model.S[dist] = 0.0 if kind == "zero" else rng.uniform(-1.0, 1.0, 3) * [0.5, 0.5, 0.1]
        if adapt:  # tires between 0.6 and 1.6 times the file's
            model.P[list(ad.TIRE_P)] = P0[list(ad.TIRE_P)] * trng.uniform(0.6, 1.6, len(ad.TIRE_P))
            model.S[list(ad.TIRE_S)] = S0[list(ad.TIRE_S)] * trng.uniform(0.6, 1.6, len(ad.TIRE_S))
        poses, wear, cmds = _numba(model, x0, R, z)
        P, W, C = (np.asarray(v) for v in nlp.rollout_fn(x0, R, z, 0.0, nlp.disturbance(),
                                                         nlp.tires()))  # eps = 0: exact |.|
        if adapt:  # (the parameters were really taken: the file's tires predict otherwise)
            moved = np.asarray(nlp.rollout_fn(x0, R, z, 0.0, nlp.disturbance(),
                                              np.r_[P0[list(ad.TIRE_P)], S0[list(ad.TIRE_S)]])[0])
            assert np.abs(moved - poses).max() > 1e-6, kind
        assert np.all(np.isfinite(poses)) and np.all(np.isfinite(wear))
        np.testing.assert_allclose(P, poses, rtol=1e-9, atol=1e-9, err_msg=f"poses ({kind})")
        np.testing.assert_allclose(W, wear, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(wear).max()),
                                   err_msg=f"wear powers ({kind})")
        np.testing.assert_allclose(C, cmds, rtol=1e-9, atol=1e-12, err_msg=f"commands ({kind})")
        om_s = cmds[1]
        hit["om_s at a rate limit"] |= bool(np.any(np.isclose(om_s, lim.omega_s_max))
                                            or np.any(np.isclose(om_s, lim.omega_s_min)))
        hit["om_w clipped to 0"] |= bool(np.any(cmds[0] == 0.0))
    model.P[:], model.S[:] = P0, S0  # (the model is shared by the session's tests)
    model.S[dist] = 0.0
    # the draws really exercised the policy's clips (not only its smooth interior)
    assert all(hit.values()), hit


@needs_casadi
def test_smoothing_bounds_the_wear_powers():
    """eps > 0 overestimates each wheel's |p| by at most eps: the smoothed powers lie in
    [exact, exact + n_wheels * eps] (DEVIATION eq. 13-15 of the ipopt backend)."""
    model, nlp = _nlp(2, MPCSettings())
    ref, _ = make_case("curve", 25.0)
    rng = np.random.default_rng(7)
    for kind in ("near", "far"):
        x0, R, z, _ = _random_case(rng, model, ref, kind)
        _, wear, _ = _numba(model, x0, R, z)
        W = np.asarray(nlp.rollout_fn(x0, R, z, 1.0, nlp.disturbance(), nlp.tires())[1])
        assert np.all(W >= wear - 1e-9 * np.abs(wear).max())
        assert np.all(W <= wear + model.n_wheels * 1.0 + 1e-9 * np.abs(wear).max())


# ---- (b) the symbolic cost is batch_cost ------------------------------------------------
@needs_casadi
@pytest.mark.parametrize("axles,settings", [
    (2, MPCSettings(R=(0.05, 20.0, 0.2, 2.0))),  # TWO with smoothing and ridge
    (3, MPCSettings(method="ntwo")),  # L = 0
], ids=["2axles-two-ridge", "3axles-ntwo"])
def test_symbolic_cost_equals_batch_cost(axles, settings):
    model, nlp = _nlp(axles, settings)
    ref, _ = make_case("curve", 25.0)
    rng = np.random.default_rng(200 + axles)
    Q = np.array(settings.Q, float)
    L = np.array(settings.effective_L, float)
    Rw = np.array(settings.R, float)
    for kind in ["near", "near", "wrap", "far"]:
        x0, R, z, zprev = _random_case(rng, model, ref, kind)
        out = model.rollout(x0, R, z[None, :])
        J = np.empty(1)
        ro.batch_cost(out.poses, out.wear, R, z[None, :], zprev, Q, L, Rw, model.stride,
                      model.nsplit, J)
        Js = float(nlp.cost_fn(z, nlp.params(x0, R, zprev, eps=0.0)))
        assert Js == pytest.approx(J[0], rel=1e-9, abs=1e-12), kind


# ---- (c) the reference optimum: IPOPT from the annealer's warm start --------------------
@pytest.fixture(scope="module")
def annealer_run():
    """A short closed loop of the annealer MPC on Case 1 at 25 km/h; per step the state,
    the solution before (the warm start's source) and after, and the annealer's cost."""
    ref, init = make_case("curve", 25.0)
    plant = Plant(VEH, initial=init(VEH))
    mpc = MPC(VEH, MPCSettings(), ref)
    steps = []
    prev = [np.zeros(mpc.model.dim)]  # closed_loop resets the MPC after its warm-up

    def on_step(k, st, cmd):
        # (the offset-free disturbance the prediction carried in this solve, too)
        steps.append((dict(st), prev[0].copy(), mpc.z.copy(), cmd.cost,
                      mpc.model.S[DIST].copy()))
        prev[0] = mpc.z.copy()

    closed_loop(plant, mpc, ref, 0.6, on_step=on_step)
    return ref, steps


@needs_casadi
def test_ipopt_reaches_at_most_the_annealer_cost(annealer_run):
    from msagv.controller.ipopt import REFERENCE_OPTIONS

    ref, steps = annealer_run
    ip = MPC(VEH, MPCSettings(), ref, options=REFERENCE_OPTIONS, solver="ipopt")
    s = ip.settings
    gains = []
    for k in (5, 20, 40, 59):
        st, z_before, z_sa, J_sa, dist = steps[k]
        ip.model.S[DIST] = dist  # the same problem as the annealer's, disturbance and all
        t, x0 = ip._state_vector(st)
        R = np.ascontiguousarray(ref.sample(t + s.dt * np.arange(s.N_p + 1)))
        zprev = z_before[: 2 * ip.nw]
        # the annealer's reported cost is the exact cost of its answer
        assert ip.horizon.cost(x0, R, z_sa, zprev) == pytest.approx(J_sa, rel=1e-12)
        warm = np.clip(ip.horizon.shifted(z_before), ip.horizon.lower, ip.horizon.upper)  # the annealer's chain 0
        z_ip, stats = ip.solver.nlp.solve(x0, R, zprev, warm, ip.horizon.lower, ip.horizon.upper)
        assert stats["return_status"] == "Solve_Succeeded", (k, stats["return_status"])
        assert np.all(z_ip >= ip.horizon.lower - 1e-9) and np.all(z_ip <= ip.horizon.upper + 1e-9)
        J_ip = ip.horizon.cost(x0, R, np.clip(z_ip, ip.horizon.lower, ip.horizon.upper), zprev)
        assert J_ip <= J_sa + 1e-9 * (1.0 + J_sa), (k, J_ip, J_sa)
        gains.append(1.0 - J_ip / J_sa)
    assert max(gains) > 0.0  # not only ties: the reference optimum says something


# ---- (d) the IPOPT MPC: bounds of eq. 27, closed loop ----------------------------------------
@needs_casadi
def test_ipopt_mpc_commands_within_bounds():
    from msagv.controller.ipopt import IpoptOptions

    ref, _ = make_case("curve", 25.0)
    mpc = MPC(VEH, MPCSettings(), ref, options=IpoptOptions(max_iter=30), solver="ipopt")
    assert_commands_within_bounds(mpc, VEH)


@needs_casadi
def test_ipopt_mpc_on_solve():
    """The IPOPT MPC calls the MPC's observer hook with the state, the previous solution and the
    command (whose cost is the exact cost of the new solution)."""
    from msagv.controller.ipopt import IpoptOptions

    ref, init = make_case("curve", 25.0)
    calls = []
    mpc = MPC(VEH, MPCSettings(), ref, solver="ipopt", options=IpoptOptions(max_iter=20),
              on_solve=lambda st, z, cmd: calls.append((st, z.copy(), cmd)))
    st0 = init(VEH)
    st = {"t": 0.0, **{k: st0[k] for k in ("x", "y", "phi", "vx", "vy", "r")},
          "delta": [st0[f"delta_{w}"] for w in VEH.wheel_names]}
    z0 = mpc.z.copy()
    cmd = mpc.step(st)
    assert len(calls) == 1
    assert calls[0][0] is st and calls[0][2] is cmd
    np.testing.assert_array_equal(calls[0][1], z0)
    t, x0 = mpc._state_vector(st)
    s = mpc.settings
    R = np.ascontiguousarray(ref.sample(t + s.dt * np.arange(s.N_p + 1)))
    assert cmd.cost == pytest.approx(mpc.horizon.cost(x0, R, mpc.z, z0[: 2 * mpc.nw]), rel=1e-12)


@needs_casadi
def test_ipopt_gradient_finite_at_standstill():
    """At rest on a reference at rest (steering rates exactly 0), |0| in the wear powers
    must not give NaN derivatives, even with eps = 0: before the guard IPOPT stopped there
    with Invalid_Number_Detected."""
    import casadi as ca

    model, nlp = _nlp(2, MPCSettings())
    ref, _ = make_case("curve", "0:0,3:0,4:5")  # at rest over the whole horizon
    R = np.ascontiguousarray(ref.sample(0.1 * np.arange(11)))
    x0 = np.r_[R[0, :3], 0.0, 0.0, 0.0, np.zeros(4)]
    z = ca.SX.sym("z", model.dim)
    p = ca.SX.sym("p", nlp.params(x0, R, np.zeros(8)).size)
    J = nlp.cost_fn(z, p)
    grad = ca.Function("g", [z, p], [ca.gradient(J, z), ca.hessian(J, z)[0]])
    for eps in (0.0, 1.0):
        pv = nlp.params(x0, R, np.zeros(8), eps)
        g, H = (np.asarray(v) for v in grad(np.zeros(model.dim), pv))
        assert np.all(np.isfinite(g)) and np.all(np.isfinite(H)), eps


@needs_casadi
def test_ipopt_closed_loop_tracks():
    from msagv.controller.mpc import MPC

    ref, init = make_case("curve", 25.0)
    plant = Plant(VEH, initial=init(VEH))
    mpc = MPC(VEH, MPCSettings(), ref, solver="ipopt")
    log = closed_loop(plant, mpc, ref, 1.0)
    m = log.metrics()
    assert m["steps"] == 100
    assert m["e_bar"] < 0.5, m
    assert m["W_tw"] > 0
    assert np.all(np.isfinite(log.cost))
    assert mpc.solver.last_stats["return_status"] == "Solve_Succeeded"


# ---- (e) errors: no CasADi, a baseline model --------------------------------------------
def test_without_casadi_a_clear_error(monkeypatch, capsys):
    import msagv.controller.ipopt as ip
    from msagv.cli import run as run_cmd

    monkeypatch.setattr(ip, "ca", None)
    ref, _ = make_case("curve", 15.0)
    with pytest.raises(ControllerError, match="CasADi"):
        MPC(VEH, MPCSettings(), ref, solver="ipopt")
    with pytest.raises(ControllerError, match="CasADi"):
        ip.HorizonNLP(make_model(VEH, MPCSettings()), MPCSettings())
    rc = run_cmd.main(["--case", "curve", "--duration", "0.1", "--solver", "ipopt", "--json"])
    out = capsys.readouterr()
    assert rc == 2 and out.out == ""
    assert "CasADi" in out.err and "--solver sa" in out.err


@needs_casadi
def test_ipopt_rejects_baseline_models(capsys):
    from msagv.cli import run as run_cmd
    from msagv.controller.mpc import MPC

    with pytest.raises(ControllerError, match="'mf' only"):
        MPC(VEH, MPCSettings(model="dugoff"), solver="ipopt")
    rc = run_cmd.main(["--case", "curve", "--duration", "0.1", "--solver", "ipopt",
                       "--model", "kinematic", "--json"])
    out = capsys.readouterr()
    assert rc == 2 and out.out == "" and "'mf' only" in out.err


def test_controller_process_solver_errors_exit_2():
    """``msagv controller`` checks --solver before opening any session: exit 2 at once
    (without the check it would wait for a plant's params, then exit 3)."""
    code = ("import sys; sys.modules['casadi'] = None; from msagv.cli import main; "
            "sys.exit(main(sys.argv[1:]))")
    base = ["controller", "--solver", "ipopt", "--wait", "1", "-q"]
    no_ca = subprocess.run([sys.executable, "-c", code, *base], capture_output=True, text=True,
                           timeout=120)
    assert no_ca.returncode == 2 and "CasADi" in no_ca.stderr, no_ca.stderr
    if HAVE_CASADI:
        bad = subprocess.run([sys.executable, "-m", "msagv", *base, "--model", "tct"],
                             capture_output=True, text=True, timeout=120)
        assert bad.returncode == 2 and "'mf' only" in bad.stderr, bad.stderr


# ---- the command line -------------------------------------------------------------------
@needs_casadi
def test_msagv_run_solver_ipopt_json(capfd):
    """``msagv run --solver ipopt --json`` prints the metric keys of ``--solver sa``. capfd
    (file-descriptor level), so anything CasADi/IPOPT printed to stdout would break the JSON."""
    from msagv.cli import run as run_cmd

    argv = ["--case", "curve", "--speed", "15", "--duration", "1", "--json"]
    assert run_cmd.main(argv + ["--solver", "ipopt"]) == 0
    out = capfd.readouterr()
    doc_ip = json.loads(out.out)
    assert run_cmd.main(argv + ["--solver", "sa"]) == 0
    doc_sa = json.loads(capfd.readouterr().out)
    assert (doc_ip["scenario"]["solver"], doc_sa["scenario"]["solver"]) == ("ipopt", "sa")
    m_ip, m_sa = doc_ip["metrics"], doc_sa["metrics"]  # the result document's metrics
    assert set(m_ip) == set(m_sa) == METRIC_KEYS
    assert set(m_ip["solve_ms"]) == set(m_sa["solve_ms"]) == {"p50", "p99", "max"}
    assert m_ip["steps"] == m_sa["steps"] == 100
    assert m_ip["e_bar"] < 0.5 and m_ip["W_tw"] > 0


@needs_casadi
@pytest.mark.slow
def test_controller_process_ipopt_lockstep_equals_in_process(capfd):
    """``msagv controller --solver ipopt`` over Zenoh in lockstep gives the run of
    ``msagv run --solver ipopt`` in-process (same commands, so the same metrics)."""
    from msagv.cli import run as run_cmd
    from msagv.cli.demo import run_demo

    r = run_demo(duration=1.0, speed="15", run_mode="lockstep", deadline_ms=None,
                 extra_controller=["--solver", "ipopt"])
    assert r["controller"]["solver"] == "ipopt" and r["controller"]["answered"] == 100
    assert run_cmd.main(["--case", "curve", "--speed", "15", "--duration", "1", "--solver",
                         "ipopt", "--json"]) == 0
    m = json.loads(capfd.readouterr().out)["metrics"]
    for k in ("W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg"):
        assert r["metrics"][k] == pytest.approx(m[k], rel=1e-12, abs=1e-15), k
