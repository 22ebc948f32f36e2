"""Vectorisable approximations of the prediction's transcendental functions.

The prediction kernel (:mod:`controller.rollout`) runs its innermost loops across
candidates so that the compiler turns them into SIMD instructions. A call into the math
library (``atan``, ``atan2``, ``sin``, ``cos``, ``tan``) is a scalar call that no loop
around it can vectorise, so the prediction uses these instead: branch-free (every branch
is a select), built from additions, multiplications, divisions and ``floor`` /
``copysign`` / ``abs``, all of which LLVM vectorises. The plant keeps the math library
(:mod:`plant.tire`'s functions are generic over these primitives; see
:func:`plant.tire.make_tire`).

The prediction needs its poses to 1e-6 m over a horizon (``tests/test_rollout_simd.py``),
so these are sized to about 1e-11, not to the last bit of a double: the polynomials are
the shortest whose error is below that (fitted to Chebyshev nodes, near minimax), and
the argument reductions drop the corrections a correctly rounded result needs. Each
function is roughly a third shorter than a 1e-16 version (Cephes' and fdlibm's, which
this module held before: docs/PERFORMANCE.md has what the change bought).

Methods and accuracy (maximum errors measured against the math library by
``tests/test_approx.py``, over the domains stated):

* :func:`atan`: the argument reduced to ``|t| <= tan(pi/8)`` by ``atan x = pi/2 +
  atan(-1/x)`` above ``tan(3 pi/8)`` and ``pi/4 + atan((x - 1)/(x + 1))`` above
  ``tan(pi/8)`` (one division, the branches as selects), then ``t + t z P(z)``,
  ``z = t^2``, ``P`` of degree 5 (no second division, as a rational form needs).
  Relative error at most ``ATAN_MAX_REL``, for every double (infinities give +-pi/2,
  NaN gives NaN).
* :func:`atan2`: the same polynomial on ``min(|x|, |y|) / max(|x|, |y|)`` in ``[0, 1]``
  (reduced above ``tan(pi/8)`` with ``(lo - hi) / (lo + hi)``: one division for the
  reduction), the octant restored with ``pi/2 - a`` and ``pi - a`` and the sign of
  ``y``; signed zeros follow C99 (``atan2(+-0, -0) = +-pi``, ``atan2(+-0, +0) = +-0``),
  NaN gives NaN. Absolute error at most ``ATAN2_MAX_ABS`` rad for finite arguments up to
  ``ATAN2_DOMAIN`` in magnitude (no scaling against overflow; infinities are outside).
* :func:`sincos` (and :func:`sin`, :func:`cos`, :func:`tan`): ``n = round(2x/pi)``, the
  remainder ``r = x - n pi/2`` by a two-part Cody-Waite reduction (pi/2 split into 33 +
  53 bits, exact products up to ``|n| < 2^20``), then polynomials on ``[-pi/4, pi/4]``
  (``sin r = r + r z S(z)``, ``cos r = 1 - z/2 + z^2 C(z)``, ``S`` and ``C`` of degree 3)
  and the quadrant by selects. Absolute error at most ``SINCOS_MAX_ABS`` for
  ``|x| <= SINCOS_DOMAIN`` (the prediction's angles: headings, steering angles,
  ``C atan(.)`` of the Magic Formula, are far inside it); ``tan = sin / cos``.

The kernels that use these compile without ``fastmath`` (IEEE arithmetic, :data:`FASTMATH`
is empty): the polynomials' fused multiply-adds are written out (:func:`fma`, LLVM's
``llvm.fma``), not left to the compiler. With ``contract``, ``nsz`` and ``arcp`` (the
flags until issue 29) a function compiled into two kernels could round differently in
each (where LLVM fuses a multiply into an add, or hoists a reciprocal, depends on the
code around it after inlining), and numba's JIT binds every call of a function that is
not inlined (``tile``, ``wheel_loop``: each kernel's object carries its own weak copy)
to the first copy loaded into the process: the standalone kernel when the process
compiled it, the calling kernel's own copy when it came from the cache. A run that
compiled its kernels and one that loaded them then differed by 3e-10 to 4e-8 relative
(Case 1, 35 km/h, TWO: e_bar 1.7816685525470328 against 1.781668548591469). Without the
flags every copy gives the same bits, whichever is bound (``tests/test_determinism.py``);
the written-out fused multiply-adds keep most of what ``contract`` gave (the MF wheel
loop's vector arithmetic: 587 instructions, 497 with ``contract``, 701 with neither; the
rollout's time per call was within the noise of a loaded 2-core machine of the former),
and give the same bits on a CPU without FMA (the C library's ``fma``). No reassociation either,
which would undo the Cody-Waite reduction. The polynomials are evaluated by Estrin's
scheme (pairs of terms, then pairs of pairs), not by Horner's rule: the prediction's wheel loop
is bound by the latency of its chains of dependent operations (a wheel-step chains three
arc tangents and two sine-cosine pairs), and for ``P`` of degree 5 Estrin is four
dependent steps deep where Horner is six (docs/PERFORMANCE.md: 10-13 % more
wheel-steps per second). A shorter ``P`` for ``atan`` (degree 3, relative error 2e-8)
was 6 % faster again but moved the predicted poses by up to 6e-6 m over a horizon
(the dynamics amplify it), more than the 1e-6 m asked: not kept. The functions are
compiled as ordinary numba functions marked ``forceinline`` (LLVM's
``alwaysinline``), so LLVM inlines them into the loops that call them, where the loops
vectorise. Left to LLVM's inlining
heuristic they were inlined on one machine (an Intel Xeon) and not on another (an AMD
EPYC, Zen 3: the cost model priced ``atan2`` over its threshold), where every lane called
them as scalar functions and the prediction ran 1.4x *slower* than on the math library
(docs/PERFORMANCE.md); ``tests/test_approx.py`` checks that no call is left.
numba's own ``inline="always"`` (IR-level inlining, every call site typed again) gives the
same code but made one kind of step take 170 s to compile, this 20 s.

:data:`EXACT` and :data:`FAST` are the two sets of primitives the kernels are built with
(:func:`controller.rollout.make_prediction`): the math library's (scalar calls) and these.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, types
from numba.extending import intrinsic

# The flags of every kernel that inlines these (see the module docstring): none. IEEE
# arithmetic, so a function gives the same bits wherever it is compiled (fused
# multiply-adds only where written, with fma below).
FASTMATH = frozenset()


@intrinsic
def fma(typingctx, a, b, c):
    """``a * b + c`` rounded once (LLVM's ``llvm.fma``: one instruction on a CPU with FMA,
    the C library's ``fma`` elsewhere; the same bits either way)."""
    if not all(isinstance(t, types.Float) for t in (a, b, c)):
        return None

    def codegen(context, builder, signature, args):
        x, y, z = (context.cast(builder, v, t, types.float64)
                   for v, t in zip(args, signature.args))
        return builder.fma(x, y, z)

    return types.float64(a, b, c), codegen

_inline = njit(cache=True, forceinline=True, error_model="numpy", fastmath=set(FASTMATH))

# documented bounds, checked by tests/test_approx.py
ATAN_MAX_REL = 3.0e-11
ATAN2_MAX_ABS = 3.0e-11
ATAN2_DOMAIN = 1.0e300
SINCOS_MAX_ABS = 5.0e-12
SINCOS_DOMAIN = 1.0e6

# ---- atan ------------------------------------------------------------------------------
# atan t = t + t z P(z), |t| <= tan(pi/8), z = t^2: P fitted to Chebyshev nodes (relative
# error 2.4e-11)
_A0, _A1, _A2, _A3, _A4, _A5 = (-0.3333333246849672, 0.19999901780729068, -0.14281956632108628,
                                0.11044137122877089, -0.08473484179557228, 0.047387768055643376)
_TP8 = 0.41421356237309504880  # tan(pi / 8)
_T3P8 = 2.41421356237309504880  # tan(3 pi / 8)
_PIO2 = 1.57079632679489661923
_PIO4 = 7.85398163397448309616e-01
_PI = 3.14159265358979323846


@_inline
def _atan_poly(t):
    """atan(t) for |t| <= tan(pi/8), as ``t + t z P(z)``, ``P`` by Estrin's scheme."""
    z = t * t
    z2 = z * z
    tz = t * z
    p = fma(z2, fma(z2, fma(z, _A5, _A4), fma(z, _A3, _A2)), fma(z, _A1, _A0))
    return fma(tz, p, t)


@_inline
def atan(x):
    """Arc tangent [rad] of any double (branch-free)."""
    ax = abs(x)
    big = ax > _T3P8
    mid = ax > _TP8
    num = -1.0 if big else (ax - 1.0 if mid else ax)
    den = ax if big else (ax + 1.0 if mid else 1.0)
    t = num / den
    y0 = _PIO2 if big else (_PIO4 if mid else 0.0)
    return math.copysign(y0 + _atan_poly(t), x)


@_inline
def atan2(y, x):
    """``atan2(y, x)`` [rad] in [-pi, pi] for finite arguments (C99's signed zeros)."""
    ax = abs(x)
    ay = abs(y)
    swap = ay > ax
    lo = ax if swap else ay
    hi = ay if swap else ax
    # atan(lo / hi), lo / hi in [0, 1], with one division: above tan(pi/8) as atan does,
    # pi/4 + atan(t), t = (lo - hi) / (lo + hi) in (-tan(pi/8), 0]; 0/0 -> 0
    mid = lo > _TP8 * hi
    den = lo + hi if mid else (hi if hi > 0.0 else 1.0)  # (never a division by 0)
    t = (lo - hi if mid else lo) / den
    r = (_PIO4 if mid else 0.0) + _atan_poly(t)
    r = _PIO2 - r if swap else r
    r = _PI - r if math.copysign(1.0, x) < 0.0 else r
    r = math.copysign(r, y)
    xy = x + y  # NaN when either is (infinities are outside the domain)
    return xy if xy != xy else r  # NaN in, NaN out


# ---- sin, cos (Cody-Waite reduction, short polynomials) ----------------------------------
# sin r = r + r z S(z), cos r = 1 - z/2 + z^2 C(z) on |r| <= pi/4, z = r^2: S, C fitted to
# Chebyshev nodes (absolute error 3.8e-12 and 1.1e-13)
_S0, _S1, _S2, _S3 = (-0.16666666640956831, 0.008333329329551676, -0.0001983932054494796,
                      2.7181986981100565e-06)
_C0, _C1, _C2, _C3 = (0.041666666621059355, -0.001388888362806273, 2.4799491835259546e-05,
                      -2.720820578971886e-07)
_INVPIO2 = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e+00   # first 33 bits of pi/2
_PIO2_2 = 6.07710050650619224932e-11   # pi/2 - PIO2_1 (53 bits)


@_inline
def sincos(x):
    """``(sin x, cos x)`` for ``|x| <= SINCOS_DOMAIN`` (one reduction for both)."""
    # (np.floor: a float; math.floor is an int, whose conversions do not vectorise)
    n = np.floor(x * _INVPIO2 + 0.5)
    r = (x - n * _PIO2_1) - n * _PIO2_2
    z = r * r
    z2 = z * z  # (Estrin's scheme, as in atan)
    s = fma(r * z, fma(z2, fma(z, _S3, _S2), fma(z, _S1, _S0)), r)
    c = fma(z2, fma(z2, fma(z, _C3, _C2), fma(z, _C1, _C0)), fma(-0.5, z, 1.0))
    q = n - 4.0 * np.floor(0.25 * n)  # the quadrant, 0..3, kept in floating point
    # one comparison per mask (a boolean | of two masks cost packing instructions):
    # q in {1, 3} <=> |q - 2| = 1; q in {1, 2} <=> |q - 1.5| = 0.5
    odd = abs(q - 2.0) == 1.0
    sn = c if odd else s
    cs = s if odd else c
    sn = -sn if q >= 2.0 else sn
    cs = -cs if abs(q - 1.5) == 0.5 else cs
    return sn, cs


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
