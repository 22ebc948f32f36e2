"""The C reference rollout (controller/mirrors/rollout_ref.c) predicts exactly what the numba kernel
on the math library (controller.rollout.EXACT, the reference of the mirrors) does: poses, wear powers and first commands of model 0 (Magic Formula) on random states,
references and decision vectors, for 1, 2 and 3 axles.

The strict build (no -ffast-math, no FMA contraction) follows the numba kernel's
expression order, so the two agree to rounding: the test asks for 1e-9 of each
quantity's scale (per column: x and y [m], phi [rad], P_s, P_alpha, P_t [W], omega_w,
omega_s). Skipped when no C compiler (gcc or $CC) is available.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from msagv.benchmarks.rollout_bench import (CBuildError, build_c_rollout, case_inputs,
                                      find_compiler, proposal_batches)
from msagv.controller import MPCSettings, make_case
from msagv.controller import rollout as _ro
from msagv.controller.models import MagicFormulaModel
from msagv.plant import default_vehicle, n_axle_vehicle

RTOL = 1e-9

pytestmark = pytest.mark.skipif(
    find_compiler() is None,
    reason="no C compiler (gcc, or $CC) on PATH: the C reference rollout cannot be built")


@pytest.fixture(scope="module")
def c_strict(tmp_path_factory):
    return build_c_rollout("strict", tmp_path_factory.mktemp("rollout_ref"))


def _vehicle(n: int):
    return default_vehicle() if n == 2 else n_axle_vehicle(n)


SPEEDS_KMH = (10, 30, 45)  # 45 km/h: wheel speeds reach omega_w_max


@functools.lru_cache(maxsize=None)
def _reference(speed_kmh):
    return make_case("curve", float(speed_kmh))[0]  # ~0.8 s to tabulate: built once


def _random_case(rng, vehicle, settings, standstill=False, past_stops=False):
    """A random state near a random stretch of the curve case (heading and position off
    by up to 0.6 rad and 3 m, random speed, yaw rate, sideslip and wheel angles).
    ``standstill``: vehicle and reference at rest. ``past_stops``: half the wheels start
    0.2 rad beyond a steering limit (the policy's "hold" branch)."""
    reference = _reference(int(rng.choice(SPEEDS_KMH)))
    t0 = reference.t[-1] + 1.0 if standstill else rng.uniform(0.0, 15.0)
    ref = np.ascontiguousarray(reference.sample(t0 + settings.dt * np.arange(settings.N_p + 1)))
    x, y, phi = ref[0, :3]
    phi = phi + rng.uniform(-0.6, 0.6)
    lim = vehicle.limits
    if standstill:
        v, beta, r = 0.0, 0.0, 0.0
    else:
        v, beta, r = rng.uniform(0.0, 12.0), rng.normal(0.0, 0.05), rng.uniform(-0.4, 0.4)
    delta = rng.uniform(0.9 * lim.delta_min, 0.9 * lim.delta_max, vehicle.n_wheels)
    if past_stops:
        delta[::2] = np.where(rng.random(delta[::2].size) < 0.5, lim.delta_min - 0.2,
                              lim.delta_max + 0.2)
    x0 = np.r_[x + rng.uniform(-3, 3), y + rng.uniform(-3, 3), phi,
               v * math.cos(phi + beta), v * math.sin(phi + beta), r, delta]
    return x0, ref


def _random_Z(rng, model, settings, rows):
    """Zero row, rows spread over 1.2x the offset box (clipped: some at the bounds) and
    annealer-like proposals."""
    nw, nb = model.n_wheels, len(settings.blocks)
    hi = np.tile(np.r_[np.full(nw, settings.offset_w_max), np.full(nw, settings.offset_d_max)], nb)
    wide = np.clip(rng.uniform(-1.2, 1.2, (rows // 2, model.dim)) * hi, -hi, hi)
    prop = proposal_batches(model, settings, rows - rows // 2 - 1, 1, int(rng.integers(1 << 30)))[0]
    return np.ascontiguousarray(np.vstack([np.zeros((1, model.dim)), wide, prop]))


def _both(c, model, x0, ref, Z):
    B, Np, nw = Z.shape[0], model.settings.N_p, model.n_wheels
    outs = []
    for run in ("numba", "c"):
        o = (np.full((B, Np, 3), np.nan), np.full((B, Np, 3), np.nan), np.full((B, 2, nw), np.nan))
        args = (x0, ref, Z, model.block, model.P, model.S, model.wx, model.wy, *o)
        if run == "numba":
            _ro.rollout_batch_exact(_ro.MODEL_MF, *args)  # the math library's kernels
        else:
            c(*args)
        outs.append(o)
    return outs


def _check(got, want, rtol=RTOL, what=""):
    for name, a, b in zip(("poses", "wear", "first commands"), got, want):
        assert np.all(np.isfinite(a)), f"{what}: C {name} not finite"
        assert np.all(np.isfinite(b)), f"{what}: numba {name} not finite"
        cols = a.shape[-1]
        a2 = a.reshape(-1, cols) if name != "first commands" else a.transpose(1, 0, 2).reshape(2, -1).T
        b2 = b.reshape(-1, cols) if name != "first commands" else b.transpose(1, 0, 2).reshape(2, -1).T
        scale = np.maximum(np.max(np.abs(b2), axis=0), 1e-12)
        err = np.max(np.abs(a2 - b2), axis=0) / scale
        assert np.all(err <= rtol), f"{what}: {name} differ by {err} of their scale (> {rtol})"


SETTINGS = {
    "default": MPCSettings(),
    "other": MPCSettings(dt=0.05, N_p=12, blocks=(2, 3, 1, 2), K_servo=6.0, K_pos=1.5,
                         ff_cornering=False),
}


@pytest.mark.parametrize("axles", [1, 2, 3])
@pytest.mark.parametrize("which", sorted(SETTINGS))
def test_c_reference_matches_numba(c_strict, axles, which):
    settings = SETTINGS[which]
    vehicle = _vehicle(axles)
    model = MagicFormulaModel(vehicle, settings)
    rng = np.random.default_rng(1000 * axles + len(which))
    for trial in range(5):
        x0, ref = _random_case(rng, vehicle, settings, standstill=trial == 4,
                               past_stops=trial == 3)
        Z = _random_Z(rng, model, settings, 16)
        got, want = _both(c_strict, model, x0, ref, Z)
        _check(got, want, what=f"{axles} axles, {which}, trial {trial}")


def test_c_reference_on_benchmark_inputs(c_strict):
    """The benchmark's inputs (state on the 25 km/h curve), 2 axles: also bit-for-bit
    close, and the C outputs are laid out as the numba ones (B, N_p, 3), (B, 2, 2n)."""
    settings = MPCSettings()
    vehicle = default_vehicle()
    model = MagicFormulaModel(vehicle, settings)
    x0, ref = case_inputs(vehicle, settings)
    Z = proposal_batches(model, settings, 20, 1, seed=3)[0]
    got, want = _both(c_strict, model, x0, ref, Z)
    _check(got, want, what="benchmark inputs")
    # the first commands are the policy's commands at x0 (controller.rollout layout)
    om_w = np.empty(model.n_wheels)
    om_s = np.empty(model.n_wheels)
    _ro.commands_from_policy(x0[:3].copy(), x0[6:].copy(), ref[0], Z[5], 0, model.n_wheels,
                             model.P, model.S, model.wx, model.wy, settings.dt, om_w, om_s)
    np.testing.assert_allclose(got[2][5, 0], om_w, rtol=RTOL, atol=1e-12)
    np.testing.assert_allclose(got[2][5, 1], om_s, rtol=RTOL, atol=1e-12)


def test_c_reference_fast_math_build_close(tmp_path):
    """The benchmark's -ffast-math build: same prediction up to reassociation."""
    try:
        c_fast = build_c_rollout("fast", tmp_path)
    except CBuildError as e:  # pragma: no cover - the strict build worked
        pytest.fail(str(e))
    settings = MPCSettings()
    vehicle = n_axle_vehicle(3)
    model = MagicFormulaModel(vehicle, settings)
    rng = np.random.default_rng(7)
    x0, ref = _random_case(rng, vehicle, settings)
    Z = _random_Z(rng, model, settings, 16)
    got, want = _both(c_fast, model, x0, ref, Z)
    _check(got, want, rtol=1e-7, what="fast-math build")


def test_checked_call_rejects_bad_shapes(c_strict):
    settings = MPCSettings()
    vehicle = default_vehicle()
    model = MagicFormulaModel(vehicle, settings)
    x0, ref = case_inputs(vehicle, settings)
    Z = np.zeros((3, model.dim + 1))
    o = model.allocate(3)
    with pytest.raises(ValueError, match="inconsistent"):
        c_strict(x0, ref, Z, model.block, model.P, model.S, model.wx, model.wy, *o)


def test_loading_the_fast_math_build_leaves_subnormals_alone():
    """A -ffast-math shared library can switch the whole process to flush-to-zero when it
    is loaded (gcc's crtfastmath.o); the build links without it, so other code (hypothesis,
    numba, numpy) keeps IEEE subnormals."""
    try:
        build_c_rollout("fast")
    except CBuildError as e:
        pytest.skip(f"no C build: {e}")
    tiny = np.float64(5e-324)
    assert tiny * np.float64(1.0) == tiny and tiny / np.float64(2.0) == 0.0
    assert np.float64(2.2250738585072014e-308) / np.float64(4.0) > 0.0
