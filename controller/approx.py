"""Vectorisable approximations of the prediction's transcendental functions.

The prediction kernel (:mod:`controller.rollout`) runs its innermost loops across
candidates so that the compiler turns them into SIMD instructions. A call into the math
library (``atan``, ``atan2``, ``sin``, ``cos``, ``tan``) is a scalar call that no loop
around it can vectorise, so the prediction uses these instead: branch-free (every branch
is a select), built from additions, multiplications, divisions and ``floor`` /
``copysign`` / ``abs``, all of which LLVM vectorises. The plant keeps the math library
(:mod:`plant.tire`'s functions are generic over these primitives; see
:func:`plant.tire.make_tire`).

Methods and accuracy (maximum errors measured against the math library by
``tests/test_approx.py`` over the whole input range: every finite double, signed zeros,
infinities and NaN for ``atan``/``atan2``; ``|x| <= SINCOS_DOMAIN`` for ``sin``/``cos``):

* :func:`atan`: Cephes' ``atan`` (S. L. Moshier): the argument reduced to
  ``[0, 0.66]`` by ``atan x = pi/2 + atan(-1/x)`` above ``tan(3 pi/8)`` and
  ``pi/4 + atan((x - 1)/(x + 1))`` above 0.66 (one division, the branches as selects),
  then ``t + t z P(z)/Q(z)``, ``z = t^2``, a degree 4/5 rational minimax form; the
  reduction's constants carry the low bits of pi/2 and pi/4 (``MOREBITS``). Relative error
  at most ``ATAN_MAX_ULP`` units in the last place.
* :func:`atan2`: from the same core on ``min(|x|, |y|) / max(|x|, |y|)`` in ``[0, 1]``
  (reduced above 0.66 with ``(lo - hi) / (lo + hi)``: one division for the reduction),
  the octant restored with ``pi/2 - a`` and ``pi - a`` and the sign of ``y``; signed
  zeros and infinities follow C99 (``atan2(+-0, -0) = +-pi``, ``atan2(inf, inf) =
  pi/4``). Absolute error at most ``ATAN2_MAX_ABS`` rad.
* :func:`sincos` (and :func:`sin`, :func:`cos`, :func:`tan`): ``n = round(2x/pi)``, the
  remainder ``r = x - n pi/2`` by a three-part Cody-Waite reduction (pi/2 split into
  33 + 33 + 53 bits, exact products up to ``|n| < 2^20``), then fdlibm's minimax
  polynomials on ``[-pi/4, pi/4]`` (``__kernel_sin``, ``__kernel_cos``: degree 13 and 14)
  and the quadrant by selects. Absolute error at most ``SINCOS_MAX_ABS`` for
  ``|x| <= SINCOS_DOMAIN`` (the prediction's angles: headings, steering angles,
  ``C atan(.)`` of the Magic Formula, are far inside it); ``tan = sin / cos``.

The kernels that use these compile with ``fastmath`` limited to ``contract`` (fused
multiply-add), ``nsz`` and ``arcp``: no reassociation, which would undo the Cody-Waite
reduction and the ``MOREBITS`` corrections, and no ``nnan``/``ninf``, so infinities and NaN
keep their IEEE meaning in the selects. The functions are compiled with these flags as
ordinary numba functions, and LLVM inlines them into the loops that call them (they are
small), where the loops vectorise: numba's own ``inline="always"`` (IR-level inlining,
every call site typed again) made the prediction take 90 s to compile, this 15 s.

:data:`EXACT` and :data:`FAST` are the two sets of primitives the kernels are built with
(:func:`controller.rollout.make_prediction`): the math library's (scalar calls) and these.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from numba import njit

# The flags of every kernel that inlines these (see the module docstring).
FASTMATH = frozenset({"contract", "nsz", "arcp"})

_inline = njit(cache=True, error_model="numpy", fastmath=set(FASTMATH))

# documented bounds, checked by tests/test_approx.py
ATAN_MAX_ULP = 2.0
ATAN2_MAX_ABS = 5.0e-16
SINCOS_MAX_ABS = 3.4e-16
SINCOS_DOMAIN = 1.0e6

# ---- atan (Cephes) ---------------------------------------------------------------------
_P0, _P1, _P2, _P3, _P4 = (-8.750608600031904122785e-01, -1.615753718733365076637e+01,
                           -7.500855792314704667340e+01, -1.228866684490136173410e+02,
                           -6.485021904942025371773e+01)
_Q0, _Q1, _Q2, _Q3, _Q4 = (2.485846490142306297962e+01, 1.650270098316988542046e+02,
                           4.328810604912902668951e+02, 4.853903996359136964868e+02,
                           1.945506571482613964425e+02)
_T3P8 = 2.41421356237309504880  # tan(3 pi / 8)
_MOREBITS = 6.123233995736765886130e-17  # pi/2 - double(pi/2)
_PIO2 = 1.57079632679489661923
_PIO4 = 7.85398163397448309616e-01
_PI = 3.14159265358979323846
_UP, _DOWN, _TINY, _HUGE = 2.0 ** 100, 2.0 ** -100, 2.0 ** -900, 2.0 ** 900


@_inline
def _atan_core(t):
    """atan(t) - t for |t| <= 0.66 (Cephes' rational form), as ``t z P(z) / Q(z)``."""
    z = t * t
    p = (((_P0 * z + _P1) * z + _P2) * z + _P3) * z + _P4
    q = ((((z + _Q0) * z + _Q1) * z + _Q2) * z + _Q3) * z + _Q4
    return t * (z * p / q)


@_inline
def atan(x):
    """Arc tangent [rad] of any double (branch-free Cephes ``atan``)."""
    ax = abs(x)
    big = ax > _T3P8
    mid = ax > 0.66
    num = -1.0 if big else (ax - 1.0 if mid else ax)
    den = ax if big else (ax + 1.0 if mid else 1.0)
    t = num / den
    y0 = _PIO2 if big else (_PIO4 if mid else 0.0)
    mb = _MOREBITS if big else (0.5 * _MOREBITS if mid else 0.0)
    r = y0 + ((_atan_core(t) + mb) + t)
    return math.copysign(r, x)


@_inline
def atan2(y, x):
    """``atan2(y, x)`` [rad] in [-pi, pi], C99's special cases included."""
    ax = abs(x)
    ay = abs(y)
    swap = ay > ax
    lo = ax if swap else ay
    hi = ay if swap else ax
    # exact power-of-two scaling keeps 0.66 hi and lo + hi away from under- and overflow
    sc = _UP if hi < _TINY else (_DOWN if hi > _HUGE else 1.0)
    lo *= sc
    hi *= sc
    # atan(lo / hi), lo / hi in [0, 1], with one division: above 0.66 as atan does,
    # pi/4 + atan(t), t = (lo - hi) / (lo + hi) in (-0.21, 0]; 0/0 -> 0, inf/inf -> pi/4
    big = lo == math.inf
    mid = lo > 0.66 * hi or big
    den = lo + hi if mid else (hi if hi > 0.0 else 1.0)  # (never a division by 0)
    t = (lo - hi if mid else lo) / den
    t = 0.0 if big else t
    r = (_PIO4 if mid else 0.0) + ((_atan_core(t) + (0.5 * _MOREBITS if mid else 0.0)) + t)
    r = (_PIO2 - r) + _MOREBITS if swap else r
    r = (_PI - r) + 2.0 * _MOREBITS if math.copysign(1.0, x) < 0.0 else r
    r = math.copysign(r, y)
    return x + y if (x != x or y != y) else r  # NaN in, NaN out


# ---- sin, cos (fdlibm kernels, Cody-Waite reduction) -------------------------------------
_S1, _S2, _S3, _S4, _S5, _S6 = (-1.66666666666666324348e-01, 8.33333333332248946124e-03,
                                -1.98412698298579493134e-04, 2.75573137070700676789e-06,
                                -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_C1, _C2, _C3, _C4, _C5, _C6 = (4.16666666666666019037e-02, -1.38888888888741095749e-03,
                                2.48015872894767294178e-05, -2.75573143513906633035e-07,
                                2.08757232129817482790e-09, -1.13596475577881948265e-11)
_INVPIO2 = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e+00   # first 33 bits of pi/2
_PIO2_2 = 6.07710050630396597660e-11   # next 33 bits
_PIO2_2T = 2.02226624879595063154e-21  # pi/2 - (PIO2_1 + PIO2_2)


@_inline
def sincos(x):
    """``(sin x, cos x)`` for ``|x| <= SINCOS_DOMAIN`` (one reduction for both)."""
    n = math.floor(x * _INVPIO2 + 0.5)
    r = (x - n * _PIO2_1) - n * _PIO2_2
    r = r - n * _PIO2_2T
    z = r * r
    s = r + r * z * (_S1 + z * (_S2 + z * (_S3 + z * (_S4 + z * (_S5 + z * _S6)))))
    c = (1.0 - 0.5 * z) + z * z * (_C1 + z * (_C2 + z * (_C3 + z * (_C4 + z * (_C5 + z * _C6)))))
    q = n - 4.0 * math.floor(0.25 * n)  # the quadrant, 0..3, kept in floating point
    odd = q == 1.0 or q == 3.0
    sn = c if odd else s
    cs = s if odd else c
    sn = -sn if q >= 2.0 else sn
    cs = -cs if (q == 1.0 or q == 2.0) else cs
    inf = abs(x) == math.inf  # sin(+-inf), cos(+-inf): NaN
    return (x - x if inf else sn), (x - x if inf else cs)


@_inline
def sin(x):
    """``sin x`` (:func:`sincos`; inlined next to a ``cos`` of the same angle, the compiler
    shares the reduction and the polynomials)."""
    return sincos(x)[0]


@_inline
def cos(x):
    """``cos x`` (:func:`sincos`)."""
    return sincos(x)[1]


@_inline
def tan(x):
    """``tan x = sin x / cos x``."""
    s, c = sincos(x)
    return s / c


# ---- the math library's, for the exact kernels --------------------------------------------
_libm = njit(cache=True, inline="always", error_model="numpy")


@_libm
def atan_exact(x):
    return math.atan(x)


@_libm
def atan2_exact(y, x):
    return math.atan2(y, x)


@_libm
def sin_exact(x):
    return math.sin(x)


@_libm
def cos_exact(x):
    return math.cos(x)


@_libm
def tan_exact(x):
    return math.tan(x)


class Primitives(NamedTuple):
    """The transcendental functions a kernel is built with."""

    name: str
    atan: object
    atan2: object
    sin: object
    cos: object
    tan: object


EXACT = Primitives("exact", atan_exact, atan2_exact, sin_exact, cos_exact, tan_exact)
FAST = Primitives("fast", atan, atan2, sin, cos, tan)
