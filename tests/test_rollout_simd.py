"""The SIMD prediction (controller.rollout.FAST: tiles of LANES candidates, the approximations
of controller/approx.py) against the same kernels on the math library (controller.rollout.EXACT,
the reference the mirrors are pinned to), end to end, and the determinism of the tiles.

* poses agree to 1e-6 m (and rad) at every step of the horizon, the wear powers to 1e-6 of
  their scale and the first commands to 1e-9, for every model (mf, dugoff, kinematic, tct),
  every decision parametrisation (offsets, twist, raw) and 1, 2, 3 and 8 axles, on random
  states near and far from the reference (tests/test_rollout_ref.py's generator);
* a candidate's prediction does not depend on its lane, its tile or the batch around it
  (alone, in a full tile, at the end of a short tile: bit for bit);
* the annealer gives the same commands for any thread count (same seed, chains over two
  tiles, threads 1 and 2: bit for bit), and its costs are the exact kernel's to 1e-9.
"""

from __future__ import annotations

import numpy as np
import pytest

from msagv.controller import MPCSettings, make_case
from msagv.controller import rollout as ro
from msagv.controller.loop import closed_loop
from msagv.controller.models import make_model
from msagv.controller.mpc import MPC
from msagv.plant import Plant, default_vehicle, n_axle_vehicle

from test_rollout_ref import _random_case  # noqa: E402 (tests/ is on sys.path)


def _vehicle(n):
    return default_vehicle() if n == 2 else n_axle_vehicle(n)


def _Z(rng, model, rows, x0, ref):
    lo, hi, sig = model.box()
    base = model.origin(x0, ref[0], 0.01)
    wide = rng.uniform(lo, hi, (rows // 2, model.dim))
    near = np.clip(base + rng.standard_normal((rows - rows // 2, model.dim)) * sig, lo, hi)
    return np.ascontiguousarray(np.vstack([wide, near]))


@pytest.mark.parametrize("axles", [1, 2, 3, 8])
@pytest.mark.parametrize("model", ["mf", "dugoff", "kinematic", "tct"])
@pytest.mark.parametrize("policy", ["offsets", "twist", "raw"])
def test_fast_prediction_is_the_exact_one(axles, model, policy):
    vehicle = _vehicle(axles)
    settings = MPCSettings(model=model, policy=policy)
    m = make_model(vehicle, settings)
    rng = np.random.default_rng(7 * axles + len(model) + len(policy))
    for trial in range(4):
        x0, ref = _random_case(rng, vehicle, settings, standstill=trial == 3,
                               past_stops=trial == 2)
        Z = _Z(rng, m, 11, x0, ref)
        fast = m.rollout(x0, ref, Z)
        fast = tuple(a.copy() for a in fast)
        exact = m.rollout(x0, ref, Z, exact=True)
        assert all(np.all(np.isfinite(a)) for a in fast)
        # poses: 1e-6 m in x, y and 1e-6 rad in phi, at every step of the horizon
        assert np.max(np.abs(fast[0] - exact.poses)) <= 1e-6
        scale = max(np.max(np.abs(exact.wear)), 1.0)
        assert np.max(np.abs(fast[1] - exact.wear)) <= 1e-6 * scale
        np.testing.assert_allclose(fast[2], exact.first_commands, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("model", ["mf", "kinematic"])
def test_a_candidate_does_not_depend_on_its_lane_or_batch(model):
    vehicle = n_axle_vehicle(3)
    settings = MPCSettings(model=model)
    m = make_model(vehicle, settings)
    rng = np.random.default_rng(3)
    x0, ref = _random_case(rng, vehicle, settings)
    Z = _Z(rng, m, 2 * ro.LANES + 3, x0, ref)  # two full tiles and a short one
    whole = tuple(a.copy() for a in m.rollout(x0, ref, Z))
    for i in (0, 5, ro.LANES - 1, ro.LANES, 2 * ro.LANES + 2):
        alone = m.rollout(x0, ref, Z[i:i + 1])
        assert np.array_equal(alone.poses[0], whole[0][i])
        assert np.array_equal(alone.wear[0], whole[1][i])
        assert np.array_equal(alone.first_commands[0], whole[2][i])
    shifted = m.rollout(x0, ref, np.ascontiguousarray(Z[3:]))
    assert np.array_equal(shifted.poses, whole[0][3:])


@pytest.mark.parametrize("axles", [2, 4])
def test_same_commands_for_any_thread_count(axles):
    """Chains over two tiles, spread over 1 or 2 threads: the same solves, bit for bit."""
    vehicle = _vehicle(axles)
    runs = []
    for threads in (1, 2):
        ref, init = make_case("curve", 25.0)
        plant = Plant(vehicle, initial=init(vehicle))
        mpc = MPC(vehicle, MPCSettings(chains=2 * ro.LANES, iterations=12, threads=threads,
                                       seed=5), ref)
        log = closed_loop(plant, mpc, ref, 0.15, progress=False)
        runs.append((np.array(log.omega_w), np.array(log.omega_s), mpc.z.copy()))
    for a, b in zip(*runs):
        assert np.array_equal(a, b)


def test_annealer_costs_are_the_exact_kernels():
    """The fused rollout + cost of the annealer's tiles equals candidate_cost of the exact
    kernel's outputs to 1e-9 (and the serial and parallel evaluations are identical)."""
    vehicle = default_vehicle()
    ref, init = make_case("curve", 25.0)
    mpc = MPC(vehicle, MPCSettings(chains=2 * ro.LANES + 1), ref)
    st = dict(init(vehicle), t=2.0)
    st["delta"] = [st.pop(f"delta_{w}") for w in vehicle.wheel_names]
    x0, R, zprev, warm = mpc.horizon_problem(st)
    rng = np.random.default_rng(1)
    Z = np.ascontiguousarray(np.clip(warm + rng.standard_normal((2 * ro.LANES + 1, mpc.model.dim))
                                     * mpc.horizon.sigma, mpc.horizon.lower, mpc.horizon.upper))
    m = mpc.model
    J = {}
    for name, fn in (("serial", ro.FAST.evaluate_serial), ("parallel", ro.FAST.evaluate_parallel)):
        ws = np.empty((3, ro.workspace_size(m.n_wheels, m.dim)))
        J[name] = np.empty(Z.shape[0])
        fn(m.model_id, x0, R, Z, m.block, m.P, m.S, m.wx, m.wy, mpc.horizon.Q, mpc.horizon.L, mpc.horizon.R, m.nsplit,
           zprev, ws, J[name])
    assert np.array_equal(J["serial"], J["parallel"])
    out = m.rollout(x0, R, Z, exact=True)
    want = np.empty(Z.shape[0])
    ro.batch_cost(out.poses, out.wear, R, Z, zprev, mpc.horizon.Q, mpc.horizon.L, mpc.horizon.R, m.stride, m.nsplit, want)
    np.testing.assert_allclose(J["serial"], want, rtol=1e-9)
