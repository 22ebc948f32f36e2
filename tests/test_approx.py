"""controller/approx.py, the prediction's vectorisable atan, atan2 and sin/cos, against the
math library over their domains, compiled as the prediction compiles them (inlined into a
loop with the kernels' fastmath flags), and with the documented error bounds.

* atan: every finite double (uniform on [-10, 10], log-uniform magnitudes 1e-310..1e308,
  the reduction's thresholds and their neighbours), signed zeros, infinities, NaN: at most
  ATAN_MAX_REL relative error;
* atan2: the same magnitudes up to ATAN2_DOMAIN for both arguments, every pair of the
  finite special values (signed zeros, +-1, subnormals): C99's results (zeros exact, signs
  equal), at most ATAN2_MAX_ABS away;
* sincos: uniform on [-10, 10] and on the documented domain [-1e6, 1e6], multiples of
  pi/2 (where the reduction cancels): at most SINCOS_MAX_ABS; inf and NaN give NaN.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from msagv.controller import approx as A

_FLAGS = set(A.FASTMATH)


@njit(fastmath=_FLAGS, error_model="numpy")
def _atan_all(x, out):
    for i in range(x.size):
        out[i] = A.atan(x[i])


@njit(fastmath=_FLAGS, error_model="numpy")
def _atan2_all(y, x, out):
    for i in range(x.size):
        out[i] = A.atan2(y[i], x[i])


@njit(fastmath=_FLAGS, error_model="numpy")
def _sincos_all(x, s, c):
    for i in range(x.size):
        s[i], c[i] = A.sincos(x[i])


@njit(fastmath=_FLAGS, error_model="numpy")
def _tan_all(x, out):
    for i in range(x.size):
        out[i] = A.tan(x[i])


RNG = np.random.default_rng(20261123)
MAGNITUDES = np.sign(RNG.uniform(-1, 1, 400_000)) * 10.0 ** RNG.uniform(-310, 308, 400_000)
SPECIAL = np.array([0.0, -0.0, np.inf, -np.inf, 1.0, -1.0, 5e-324, -5e-324, 2.2250738585072014e-308,
                    1.7976931348623157e308])


def _ulps(got, want):
    return np.abs(got - want) / np.spacing(np.abs(want))


def test_atan_over_every_double():
    thresholds = np.array([0.41421356237309503, 2.414213562373095])
    x = np.r_[RNG.uniform(-10, 10, 600_000), MAGNITUDES, SPECIAL, thresholds, -thresholds,
              np.nextafter(thresholds, 0), np.nextafter(thresholds, 10)]
    got = np.empty_like(x)
    _atan_all(x, got)
    want = np.arctan(x)
    nz = want != 0
    assert np.max(np.abs(got[nz] - want[nz]) / np.abs(want[nz])) <= A.ATAN_MAX_REL
    assert np.array_equal(got[~nz], want[~nz]) and np.array_equal(np.signbit(got), np.signbit(want))
    assert got[x == np.inf][0] == math.pi / 2 and got[x == -np.inf][0] == -math.pi / 2
    one = np.empty(1)
    _atan_all(np.array([np.nan]), one)
    assert np.isnan(one[0])


def test_atan2_over_every_pair_in_the_domain():
    n = 300_000
    mags = MAGNITUDES[np.abs(MAGNITUDES) <= A.ATAN2_DOMAIN]
    y = np.r_[RNG.uniform(-10, 10, n), mags[:n]]
    x = np.r_[RNG.uniform(-10, 10, n), RNG.permutation(mags)[:n]]
    finite = SPECIAL[np.abs(SPECIAL) <= A.ATAN2_DOMAIN]  # signed zeros, +-1, subnormals
    Y, X = np.meshgrid(finite, finite)
    y = np.r_[y, Y.ravel(), 1e-300, A.ATAN2_DOMAIN, -A.ATAN2_DOMAIN, 0.4142135623730951, 1.0]
    x = np.r_[x, X.ravel(), A.ATAN2_DOMAIN, 1e-300, 1.0, 1.0, -1.0]
    got = np.empty_like(x)
    _atan2_all(y, x, got)
    want = np.arctan2(y, x)
    assert np.max(np.abs(got - want)) <= A.ATAN2_MAX_ABS
    assert np.array_equal(np.signbit(got), np.signbit(want))  # signed zeros, C99's quadrants
    special = (np.isin(y, finite) & np.isin(x, finite))
    np.testing.assert_allclose(got[special], want[special], rtol=0, atol=A.ATAN2_MAX_ABS)
    assert np.array_equal(got[special] == 0, want[special] == 0)  # zeros exactly
    out = np.empty(2)
    _atan2_all(np.array([np.nan, 1.0]), np.array([1.0, np.nan]), out)
    assert np.all(np.isnan(out))


def test_sincos_over_the_domain():
    k = np.arange(-2000, 2001)
    x = np.r_[RNG.uniform(-10, 10, 600_000), RNG.uniform(-A.SINCOS_DOMAIN, A.SINCOS_DOMAIN, 600_000),
              k * (math.pi / 2), np.nextafter(k * (math.pi / 2), np.inf), 0.0, -0.0,
              A.SINCOS_DOMAIN, -A.SINCOS_DOMAIN]
    s = np.empty_like(x)
    c = np.empty_like(x)
    _sincos_all(x, s, c)
    assert np.max(np.abs(s - np.sin(x))) <= A.SINCOS_MAX_ABS
    assert np.max(np.abs(c - np.cos(x))) <= A.SINCOS_MAX_ABS
    s2 = np.empty(3)
    c2 = np.empty(3)
    _sincos_all(np.array([np.nan, np.inf, -np.inf]), s2, c2)
    assert np.all(np.isnan(s2)) and np.all(np.isnan(c2))


def test_tan_is_sin_over_cos():
    x = RNG.uniform(-1.5, 1.5, 100_000)
    got = np.empty_like(x)
    _tan_all(x, got)
    np.testing.assert_allclose(got, np.tan(x), rtol=4 * A.SINCOS_MAX_ABS / math.cos(1.5), atol=0)


@njit(fastmath=_FLAGS, error_model="numpy")
def _all_in_one_loop(x, y, out):
    for i in range(x.size):
        s, c = A.sincos(x[i])
        out[i] = A.atan2(y[i], x[i]) + A.atan(y[i]) + s * c + A.sin(y[i]) + A.cos(y[i]) + A.tan(x[i])


def test_the_functions_are_inlined_into_the_loop():
    """Every function is inlined where it is called (forceinline: LLVM's alwaysinline), so
    a loop of them has no call left and can vectorise. Left to LLVM's inlining heuristic,
    the Zen 3 cost model kept atan2 as a call: scalar lanes in the prediction."""
    x = np.linspace(-3.0, 3.0, 16)
    out = np.empty_like(x)
    _all_in_one_loop(x, x[::-1].copy(), out)
    want = (np.arctan2(x[::-1], x) + np.arctan(x[::-1]) + np.sin(x) * np.cos(x)
            + np.sin(x[::-1]) + np.cos(x[::-1]) + np.tan(x))
    assert np.max(np.abs(out - want)) <= 1e-9  # (the functions are good to 3e-11 each)
    (ir,) = _all_in_one_loop.inspect_llvm().values()
    calls = [ln for ln in ir.splitlines() if "call " in ln and "6approx" in ln]
    assert calls == [], calls[:3]
