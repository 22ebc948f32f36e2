"""The Gauss-Newton polish after the annealing (controller.sa_kernel, CompiledAnnealer.polish).

* its pieces against the cost they stand for: the smoothing and ridge terms as a quadratic
  form ``z'Az + b'z + c`` against ``cost_terms.smoothing_cost + ridge_cost``, and
  ``|r|^2 + e + z'Az + b'z + c`` from the residuals against ``rollout.batch_cost``, for
  every wear method and both policies with offsets (random states, random decisions);
* the damped step solves its linear system (against numpy's solver) and refuses a matrix
  that is not positive definite; its factorisation by panels and the Hessian by blocks of
  residuals are the plain one-at-a-time sums to the bit;
* the compiled polish is the plain one of tests/annealer_reference.py on the MPC's
  problem (same steps, same candidates, same answer), and that one solves a problem with a
  known minimum (linear residuals: one step, the least-squares solution);
* through the MPC: never worse than the annealing alone, inside the box, with a deadline
  it stops early; bad settings are refused.
"""

from __future__ import annotations

import numpy as np
import pytest

from msagv.controller import MPCSettings, make_case
from msagv.controller import cost_terms as ct
from msagv.controller import rollout as ro
from msagv.controller import sa_kernel as sk
from msagv.controller.adaptation import TIRE_P
from msagv.controller.mpc import MPC
from msagv.plant import default_vehicle, layout as lay, n_axle_vehicle

from annealer_reference import gauss_newton_polish  # noqa: E402 (tests/ is on sys.path)
from test_rollout_ref import _random_case  # noqa: E402


def _vehicle(n):
    return default_vehicle() if n == 2 else n_axle_vehicle(n)


def _problem(axles=2, seed=0, **kw):
    v = _vehicle(axles)
    ref, _ = make_case("curve", 25.0)
    mpc = MPC(v, MPCSettings(**kw), ref)
    rng = np.random.default_rng(seed)
    x0, R = _random_case(rng, v, mpc.settings)
    lo, hi = mpc.horizon.lower, mpc.horizon.upper
    zprev = rng.uniform(lo, hi)[: mpc.model.stride].copy()
    return mpc, x0, R, zprev, rng


@pytest.mark.parametrize("method", ["two", "two-energy", "ntwo"])
@pytest.mark.parametrize("axles", [2, 3])
def test_quadratic_form_and_residuals_are_the_cost(method, axles):
    mpc, x0, R, zprev, rng = _problem(axles, seed=axles, method=method)
    m = mpc.model
    D = m.dim
    Z = np.ascontiguousarray(np.vstack([np.zeros(D), rng.uniform(mpc.horizon.lower, mpc.horizon.upper, (6, D))]))
    A, b = np.empty((D, D)), np.empty(D)
    c = sk.quadratic_terms(m.stride, m.nsplit, mpc.horizon.R, zprev, A, b)
    assert np.array_equal(A, A.T)
    out = m.rollout(x0, R, Z)
    want = np.empty(len(Z))
    ro.batch_cost(out.poses, out.wear, R, Z, zprev, mpc.horizon.Q, mpc.horizon.L, mpc.horizon.R, m.stride, m.nsplit, want)
    r = np.empty((len(Z), 6 * m.settings.N_p))
    for i, z in enumerate(Z):
        quad = ct.smoothing_cost(z, zprev, mpc.horizon.R, m.stride, m.nsplit) + ct.ridge_cost(
            z, mpc.horizon.R, m.stride, m.nsplit)
        assert z @ A @ z + b @ z + c == pytest.approx(quad, rel=1e-12, abs=1e-14)
        e = sk.residuals(out.poses, out.wear, R, mpc.horizon.Q, mpc.horizon.L, i, r, i)
        if method != "two-energy":
            assert e == 0.0
        assert r[i] @ r[i] + e + sk.quadratic_value(A, b, c, z) == pytest.approx(want[i], rel=1e-12)


def test_damped_step_solves_and_refuses_indefinite():
    rng = np.random.default_rng(3)
    D = 13
    G = rng.normal(size=(20, D))
    H = G.T @ G
    g = rng.normal(size=D)
    Lc, dz = np.empty((D, D)), np.empty(D)
    for mu in (0.0, 0.1, 10.0):
        assert sk.damped_step(H, g, mu, Lc, dz)
        want = np.linalg.solve(H + mu * np.diag(np.diag(H)), -g)
        assert np.allclose(dz, want, rtol=1e-9, atol=1e-12)
    H[4, 4] = -1.0
    assert not sk.damped_step(H, g, 0.1, Lc, dz)


@pytest.mark.parametrize("D", [5, 24, 96])
def test_linear_algebra_is_numpys(D):
    """The polish's products (Jacobian stored by residual, ``JrT`` (M, D)) against numpy:
    the gradient, the Gauss-Newton Hessian, Broyden's update of the Jacobian and the
    Hessian with it, the quadratic form, and the damped step at D = 96 (8 axles)."""
    rng = np.random.default_rng(D)
    M = 60
    JrT = rng.normal(size=(M, D))
    B = rng.normal(size=(D, D))
    A = B @ B.T / D
    z, b, r0, ge = (rng.normal(size=n) for n in (D, D, M, D))
    g, H = np.empty(D), np.empty((D, D))
    sk.gauss_newton_gradient(JrT, r0, ge, A, z, b, g)
    assert np.allclose(g, 2 * JrT.T @ r0 + ge + 2 * A @ z + b, rtol=1e-12, atol=1e-12)
    sk.gauss_newton_hessian(JrT, A, H)
    assert np.array_equal(H, H.T)
    assert np.allclose(H, 2 * JrT.T @ JrT + 2 * A, rtol=1e-12, atol=1e-11)
    assert sk.quadratic_value(A, b, 0.5, z) == pytest.approx(z @ A @ z + b @ z + 0.5, rel=1e-12)
    dz, dr = 1e-2 * rng.normal(size=D), rng.normal(size=M)
    J1, ge1, H1 = JrT.copy(), ge.copy(), H.copy()
    sk.broyden_update(J1, ge1, H1, dz, dr, 0.3)
    t = (dr - JrT @ dz) / (dz @ dz)
    want = JrT + np.outer(t, dz)
    assert np.allclose(J1, want, rtol=1e-10, atol=1e-10)
    assert np.allclose(J1 @ dz, dr, rtol=1e-9, atol=1e-9)  # the secant condition
    assert np.allclose(ge1, ge + (0.3 - ge @ dz) * dz / (dz @ dz), rtol=1e-10, atol=1e-12)
    assert np.allclose(H1, 2 * want.T @ want + 2 * A, rtol=1e-9, atol=1e-8)
    Lc, x = np.empty((D, D)), np.empty(D)
    for mu in (0.0, 0.01, 10.0):
        assert sk.damped_step(H, g, mu, Lc, x)
        assert np.allclose(x, np.linalg.solve(H + mu * np.diag(np.diag(H)), -g), rtol=1e-8,
                           atol=1e-10)


def _plain_factor(H, mu):
    """Right-looking Cholesky of ``H + mu diag H``, one pivot at a time, in numpy's
    elementwise IEEE operations: the order of operations the polish's factorisation keeps."""
    U = H.copy()
    D = len(U)
    U[np.arange(D), np.arange(D)] *= 1.0 + mu
    for k in range(D):
        d = np.sqrt(U[k, k])
        U[k, k] = d
        U[k, k + 1:] *= 1.0 / d
        for i in range(k + 1, D):
            U[i, i:] += -U[k, i] * U[k, i:]
    return np.triu(U)


@pytest.mark.parametrize("D", [5, 8, 13, 24, 97])
def test_panel_factorisation_and_hessian_are_the_plain_ones_to_the_bit(D):
    """The factorisation by panels of eight pivots and the Hessian by eight residuals a
    pass (sa_kernel._axpy8) add the same terms in the same order as one pivot (one
    residual) at a time: the same numbers to the bit, with whole panels, a partial last
    one (13, 97) and none (5)."""
    rng = np.random.default_rng(D)
    M = 60
    JrT = rng.normal(size=(M, D))
    B = rng.normal(size=(D, D))
    A = B @ B.T / D
    H = np.empty((D, D))
    sk.gauss_newton_hessian(JrT, A, H)
    want = np.zeros((D, D))
    for i in range(D):
        for m in range(M):
            want[i, i:] += JrT[m, i] * JrT[m, i:]
    want = np.triu(want) + np.triu(want, 1).T
    assert np.array_equal(H, 2.0 * want + 2.0 * A)
    U, dz = np.empty((D, D)), np.empty(D)
    for mu in (0.0, 0.1):
        assert sk.damped_step(H, rng.normal(size=D), mu, U, dz)
        assert np.array_equal(np.triu(U), _plain_factor(H, mu))


def test_reference_polish_solves_linear_least_squares_in_one_step():
    """Linear residuals r = M z - y in a box wide enough: the undamped step is the
    least-squares solution (the Gauss-Newton model is then exact)."""
    rng = np.random.default_rng(5)
    M, y = rng.normal(size=(12, 4)), rng.normal(size=12)
    A, b = 0.01 * np.eye(4), np.zeros(4)
    want = np.linalg.solve(M.T @ M + A, M.T @ y)

    def res(Z):
        return Z @ M.T - y, np.zeros(len(Z))

    z0 = np.zeros(4)
    J0 = float(y @ y)
    z, J, n, _ = gauss_newton_polish(res, A, b, 0.0, z0, J0, np.full(4, -10.0), np.full(4, 10.0),
                                  np.full(4, 1e-6), steps=3, mus=[0.0, 1.0], alphas=[1.0],
                                  tol=1e-12, refresh=0)
    assert np.allclose(z, want, atol=1e-6)
    assert J == pytest.approx(float(np.sum((M @ want - y) ** 2) + want @ A @ want), rel=1e-9)


@pytest.mark.parametrize("axles", [2, 4, 12])  # 12: D = 144 > 2 M, the Woodbury steps
def test_compiled_polish_is_the_plain_one(axles):
    mpc, x0, R, zprev, rng = _problem(axles, seed=10 + axles, iterations=4, polish=6)
    sa, m = mpc.solver.kernel, mpc.model
    warm = np.clip(rng.normal(size=m.dim) * mpc.horizon.sigma, mpc.horizon.lower, mpc.horizon.upper)
    res = sa.solve(x0, R, zprev, warm, np.random.default_rng(1))
    got = sa.polish(x0, R, zprev, res)
    D = m.dim
    A, b = np.empty((D, D)), np.empty(D)
    c = sk.quadratic_terms(m.stride, m.nsplit, mpc.horizon.R, zprev, A, b)

    def residuals(Z):
        out = m.rollout(x0, R, np.ascontiguousarray(Z))
        r = np.empty((len(Z), 6 * m.settings.N_p))
        e = np.array([sk.residuals(out.poses, out.wear, R, mpc.horizon.Q, mpc.horizon.L, i, r, i)
                      for i in range(len(Z))])
        return r, e

    z, J, n, refreshes = gauss_newton_polish(
        residuals, A, b, c, res.x, res.cost, mpc.horizon.lower, mpc.horizon.upper, sa._h, steps=6,
        mus=sk.GN_MUS, alphas=sk.GN_ALPHAS, tol=sk.GN_TOL, refresh=sk.GN_REFRESH)
    assert got.polish_steps == n >= 1
    assert got.evaluations == res.evaluations + 1 + (1 + refreshes) * D + n * sk.GN_CANDIDATES
    assert got.cost == pytest.approx(J, rel=1e-9)
    # at 12 axles the steps are less well conditioned: 1.3e-7 from numpy's by Cholesky
    # (GN_LOWRANK raised) as by Woodbury
    assert np.allclose(got.x, z, rtol=0, atol=1e-7 if axles <= 4 else 1e-6)
    assert got.cost < res.cost  # from 4 iterations of annealing there is room
    assert np.all(got.x >= mpc.horizon.lower) and np.all(got.x <= mpc.horizon.upper)
    assert got.iterations == res.iterations


def test_polish_through_the_mpc_never_worse_and_deadline():
    ref, init = make_case("curve", 25.0)
    v = default_vehicle()
    st = dict(init(v), t=4.0)
    st["delta"] = [st.pop(f"delta_{w}") for w in v.wheel_names]
    st["x"] += 0.3
    costs = {}
    for polish in (0, 4):
        mpc = MPC(v, MPCSettings(iterations=8, polish=polish), ref)
        cmd = mpc.step(st)
        costs[polish] = cmd.cost
        assert np.all(mpc.z >= mpc.horizon.lower) and np.all(mpc.z <= mpc.horizon.upper)
    assert costs[4] < costs[0]  # same seed, same annealing: the polish only lowers it
    # a deadline the annealing already spends leaves at most one polishing step
    mpc = MPC(v, MPCSettings(iterations=8, polish=50), ref)
    x0, R, zprev, warm = mpc.horizon_problem(st)
    res = mpc.solver.kernel.solve(x0, R, zprev, warm, np.random.default_rng(0))
    assert mpc.solver.kernel.polish(x0, R, zprev, res, deadline_s=1e-9).polish_steps <= 1
    assert mpc.solver.kernel.polish(x0, R, zprev, res).polish_steps >= 1


def test_bad_polish_setting_refused():
    with pytest.raises(ValueError, match="polish"):
        MPCSettings(polish=-1)
    mpc = MPC(default_vehicle(), MPCSettings())
    with pytest.raises(ValueError, match="polish"):
        sk.CompiledAnnealer(mpc.model, mpc.horizon.Q, mpc.horizon.L, mpc.horizon.R, mpc.horizon.lower, mpc.horizon.upper, mpc.horizon.sigma,
                            chains=2, iterations=2, sigma_final=0.1, t_start=1e-2,
                            t_end=1e-4, polish=-2)


_FIRST_COMMAND = """
import argparse, json
from msagv.cli.args import add_case_args, add_mpc_args, scenario_from_args
from msagv.controller.loop import closed_loop
ap = argparse.ArgumentParser(); add_case_args(ap); add_mpc_args(ap)
b = scenario_from_args(ap.parse_args(["--duration", "0.02"])).build()
out = []
closed_loop(b.plant, b.controller, b.reference, 0.02,
            on_step=lambda k, st, c: out.append(c.omega_w.tolist() + c.omega_s.tolist()))
print(json.dumps(out))
"""


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_compiled_and_cached_kernels_command_the_same(tmp_path):
    """The first run after a change compiles the kernels, the next ones load them from
    numba's cache: both must command the same, bit for bit (with numba's full fastmath the
    polish's sums were vectorised differently, 4e-14 rad/s apart at step 0). Slow: a cold
    compile of the kernels takes about a minute; a clean clone's make test checks the same
    through tests/test_processes.py, whose in-process run compiles and whose processes
    load the cache."""
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    runs = [subprocess.run([sys.executable, "-c", _FIRST_COMMAND], env=env, text=True,
                           capture_output=True, timeout=280) for _ in range(2)]
    for r in runs:
        assert r.returncode == 0, r.stderr
    assert any((tmp_path / "numba").rglob("*.nbc"))
    first, second = (json.loads(r.stdout) for r in runs)
    assert first == second


@pytest.mark.parametrize("D, stride", [(24, 8), (144, 48), (192, 64)])
def test_lowrank_step_is_the_damped_step(D, stride):
    """The damped step through the residuals' side (Woodbury, for D well above M) solves
    the same system as the Cholesky step, on the polish's own quadratic terms (the
    smoothing couples each offset across the move blocks) with a Jacobian of widely spread
    column scales; both against numpy's solver. A matrix E = 2A + mu diag H that is not
    positive definite is refused."""
    rng = np.random.default_rng(D)
    M = 60
    JrT = rng.normal(size=(M, D)) * np.exp(rng.normal(size=D))
    A, b = np.empty((D, D)), np.empty(D)
    sk.quadratic_terms(stride, stride // 2, np.array([0.01, 0.5, 1e-3, 1e-2]),
                       rng.normal(size=stride), A, b)
    assert A[stride, 0] != 0.0  # the blocks are coupled
    H = np.empty((D, D))
    sk.gauss_newton_hessian(JrT, A, H)
    g = rng.normal(size=D)
    JT, WT = np.ascontiguousarray(JrT.T), np.empty((D, M))
    dz, dz2, U = np.empty(D), np.empty(D), np.empty((D, D))
    for mu in (0.01, 0.1, 1.0, 10.0):
        assert sk.lowrank_step(H, JT, A, stride, g, mu, WT, dz)
        assert sk.damped_step(H, g, mu, U, dz2)
        want = np.linalg.solve(H + mu * np.diag(np.diag(H)), -g)
        scale = np.abs(want).max()
        assert np.abs(dz - want).max() < 1e-11 * scale
        assert np.abs(dz - dz2).max() < 1e-11 * scale
    A[3, 3] = -1.0
    assert not sk.lowrank_step(H, JT, A, stride, g, 0.01, WT, dz)


def test_diagonal_only_hessian_and_update_are_the_full_ones_diagonal():
    """Above the Woodbury threshold the polish keeps H's diagonal alone (all lowrank_step
    reads): the Hessian and Broyden's update of it with ``full=False`` give the full
    ones' diagonal to the bit."""
    rng = np.random.default_rng(7)
    M, D = 60, 144
    JrT = rng.normal(size=(M, D))
    B = rng.normal(size=(D, D))
    A = B @ B.T / D
    H, Hd = np.empty((D, D)), np.full((D, D), np.nan)
    sk.gauss_newton_hessian(JrT, A, H)
    sk.gauss_newton_hessian(JrT, A, Hd, False)
    assert np.array_equal(np.diag(Hd), np.diag(H))
    dz, dr, ge = 1e-2 * rng.normal(size=D), rng.normal(size=M), rng.normal(size=D)
    J1, J2 = JrT.copy(), JrT.copy()
    sk.broyden_update(J1, ge.copy(), H, dz, dr, 0.3)
    sk.broyden_update(J2, ge.copy(), Hd, dz, dr, 0.3, False)
    assert np.array_equal(np.diag(Hd), np.diag(H))
    assert np.array_equal(J1, J2)
    assert not np.array_equal(np.diag(Hd), np.diag(2 * JrT.T @ JrT + 2 * A))  # it moved


# ---- the differences from the nominal rollout (rollout.rollout_from) -------------------
def _changed_after(rng, model, z0, rows):
    """Rows of ``z0`` each changed (uniformly in the box) in the blocks first used at a
    random step or later: ``(Z, first)``, with rows changed from step 0 and rows not
    changed at all (first = N_p) among them."""
    Np, stride = model.settings.N_p, model.stride
    Z = np.tile(z0, (rows, 1))
    first = rng.integers(0, Np + 1, rows)
    first[:2] = (0, Np)
    for i, k in enumerate(first):
        before = set(int(b) for b in model.block[:k])
        for b in set(int(b) for b in model.block[k:]) - before:
            Z[i, b * stride:(b + 1) * stride] += rng.normal(0.0, 0.3, stride)
    return np.ascontiguousarray(Z), first.astype(np.int64)


@pytest.mark.parametrize("axles, model, policy, blocks", [
    (2, "mf", "offsets", (1, 2, 3)), (3, "mf", "twist", (2, 2, 2)), (2, "dugoff", "raw", (1, 1, 1, 1)),
    (3, "kinematic", "offsets", (3, 4)), (2, "tct", "offsets", (1, 2, 3)), (8, "mf", "offsets", (1, 2, 3))])
def test_rollout_from_the_nominal_is_the_full_rollout_to_the_bit(axles, model, policy, blocks):
    """Rows that differ from a nominal one only from some step on, predicted from the
    nominal's saved states there, are the full rollout's to the bit: poses, wear and first
    commands, serial and over threads, FAST and EXACT; bad inputs refused."""
    v = _vehicle(axles)
    ref, _ = make_case("curve", 25.0)
    mpc = MPC(v, MPCSettings(model=model, policy=policy, blocks=blocks), ref)
    m = mpc.model
    rng = np.random.default_rng(axles + len(blocks))
    x0, R = _random_case(rng, v, mpc.settings)
    z0 = rng.uniform(mpc.horizon.lower, mpc.horizon.upper)
    Z, first = _changed_after(rng, m, z0, 21)  # three tiles, the last one short
    perm = rng.permutation(len(Z))  # tiles mixing rows of different first steps
    Z, first = np.ascontiguousarray(Z[perm]), np.ascontiguousarray(first[perm])
    Np, nw = mpc.settings.N_p, v.n_wheels
    nx = lay.X0_DELTA + nw
    for pred in (ro.FAST, ro.EXACT):
        kern = pred.kernels[ro.step_kind(m.model_id, m.P)]
        full = m.allocate(len(Z))
        pred.rollout_batch(m.model_id, x0, R, Z, m.block, m.P, m.S, m.wx, m.wy, full.poses,
                           full.wear, full.first_commands)
        nom = m.allocate(1)
        trace = np.full((1, Np, nx), np.nan)
        none = (np.empty((Np, nx)), np.empty((Np, 3)), np.empty((Np, 3)), np.empty((2, nw)))
        kern["rollout_from"](m.model_id, x0, R, z0[None, :].copy(), m.block, m.P, m.S, m.wx, m.wy,
                             nom.poses, nom.wear, nom.first_commands, np.zeros(1, np.int64),
                             *none, trace)
        assert np.array_equal(trace[0, 0], x0[:nx])  # the state at the first step's start
        nominal = (trace[0], nom.poses[0], nom.wear[0], nom.first_commands[0])
        for variant in ("rollout_from", "rollout_from_parallel"):
            got = m.allocate(len(Z))
            kern[variant](m.model_id, x0, R, Z, m.block, m.P, m.S, m.wx, m.wy, got.poses,
                          got.wear, got.first_commands, first, *nominal, np.empty((0, 0, 0)))
            assert np.array_equal(got.poses, full.poses)
            assert np.array_equal(got.wear, full.wear)
            assert np.array_equal(got.first_commands, full.first_commands)
    args = (m.model_id, x0, R, Z, m.block, m.P, m.S, m.wx, m.wy, got.poses, got.wear,
            got.first_commands)
    with pytest.raises(ValueError, match="first must be >= 0"):
        kern["rollout_from"](*args, np.where(first == first.max(), -1, first), *nominal,
                             np.empty((0, 0, 0)))
    with pytest.raises(ValueError, match="trace0"):
        kern["rollout_from"](*args, first, nominal[0][:-1], *nominal[1:], np.empty((0, 0, 0)))
    with pytest.raises(ValueError, match="trace must be"):
        kern["rollout_from"](*args, first, *nominal, np.empty((len(Z), Np, nx + 1)))


@pytest.mark.parametrize("axles", [2, 8])
@pytest.mark.parametrize("blocks", [(1, 2, 3), (4, 3, 3), (1,) * 10, (5,)])
@pytest.mark.parametrize("variant", ["plain", "disturbance", "adapted"])
def test_polish_differences_are_the_full_ones_to_the_bit(axles, blocks, variant):
    """The polish's Jacobian, its perturbed rollouts started at each variable's block's
    first step from the nominal one (sa_kernel._gn_jacobian), is the plain forward
    differences' of full rollouts from x0 to the bit: the zero rows before each block,
    the residuals' and the linear term's derivatives, with the offset-free disturbance and
    with adapted tires in the prediction."""
    mpc, x0, R, zprev, rng = _problem(axles, seed=axles + len(blocks), blocks=blocks,
                                      method="two-energy")
    m, sa = mpc.model, mpc.solver.kernel
    if variant == "disturbance":
        m.S[[lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]] = (0.4, -0.3, 0.05)
    elif variant == "adapted":
        m.P[list(TIRE_P)] *= (0.8, 1.15, 0.9, 1.1)
        m.S[lay.S_K_ALPHA] /= 0.8
    lo, hi = mpc.horizon.lower, mpc.horizon.upper
    z = rng.uniform(lo, hi)
    z[::7] = hi[::7]  # backward differences at the upper bound
    full = [np.copy(a) for a in sa.differences(x0, R, z, from_nominal=False)]
    r0, e0, JrT, ge = sa.differences(x0, R, z)
    assert np.array_equal(JrT, full[2]) and np.array_equal(ge, full[3])
    D, M = m.dim, 6 * mpc.settings.N_p
    hd = np.where(z + sa._h <= hi, sa._h, -sa._h)
    Zfd = np.tile(z, (D, 1))
    Zfd[np.arange(D), np.arange(D)] += hd
    out = m.rollout(x0, R, np.vstack([z, Zfd]))
    r = np.empty((D + 1, M))
    e = np.array([sk.residuals(out.poses, out.wear, R, mpc.horizon.Q, mpc.horizon.L, i, r, i)
                  for i in range(D + 1)])
    assert np.array_equal(r0, r[0]) and e0 == e[0]
    inv = 1.0 / (np.diag(Zfd) - z)
    assert np.array_equal(JrT, ((r[1:] - r[0]) * inv[:, None]).T)
    assert np.array_equal(ge, (e[1:] - e[0]) * inv)
    first = sk.first_steps(m.block, m.stride, D)
    assert list(first[::m.stride]) == [int(np.argmax(m.block == b)) for b in range(len(blocks))]
    for d in range(D):  # nothing before the variable's block moves
        assert not np.any(JrT[:6 * first[d], d])
    assert np.any(JrT[6 * first[-1]:])
