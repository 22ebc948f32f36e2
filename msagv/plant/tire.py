"""Tire and wear models of the paper (eq. 6-10, 13-15, Magic Formula f) and Dugoff's model:
the one implementation of each, shared by the plant and the controller's prediction.

Every function is compiled with numba and written with elementwise operations, so the
same function serves one wheel (floats) and batches (arrays with any leading axes,
broadcast against each other; :func:`magic_formula_and_slope` and :func:`slip_jacobian`
are for scalars). The kernels of :mod:`plant.dynamics` and :mod:`controller.rollout` call
them on scalars; they are declared ``inline="always"``, so numba inlines them into each
kernel and compiles them with that kernel's flags.

The equations are written once, in :func:`make_tire`, over the transcendental functions
they use (arc tangent, sine, cosine, tangent). This module's functions are
``make_tire`` bound to numpy's (the math library's): the plant's exact maths, for scalars
and arrays. The prediction binds the same equations to the vectorisable approximations
of :mod:`controller.approx` (scalars only), so plant and prediction differ only in
those primitives.
"""

from __future__ import annotations

import types
from typing import NamedTuple

import numpy as np
from numba import njit

# Regularisation speed of the slip definitions [m/s]; see slip_ratio / slip_angle.
V_EPS_DEFAULT = 0.1


# Combined-slip weighting functions of the Magic Formula (MF-Tyre 5.2, Pacejka, "Tire and
# Vehicle Dynamics", 3rd ed., section 4.3.2, without the shifts), with the coefficients
# of the book's example 205/60R15 tire (Appendix 3; no truck-tire set was available):
RBX1, RBX2, RCX1 = 13.046, 9.718, 0.9995  # G_x(alpha, s)
RBY1, RBY2, RCY1 = 10.622, 7.820, 1.0587  # G_y(s, alpha)


# ---- the primitives: numpy's (elementwise, scalars and arrays) --------------------------
def atan(x):
    return np.arctan(x)


def sin(x):
    return np.sin(x)


def cos(x):
    return np.cos(x)


def tan(x):
    return np.tan(x)


# ---- the equations, over the primitives above (compiled by make_tire) -------------------


def magic_formula(xi, B, C, D, E):
    """Pacejka Magic Formula, paper's unnumbered f after eq. (12).

    ``f(xi) = D sin(C arctan(B xi - E (B xi - arctan(B xi))))``. ``xi`` is the slip
    ratio s [-] or the slip angle alpha [rad]; ``D = mu F_N`` [N]. Odd in ``xi``.
    """
    Bx = B * xi
    return D * sin(C * atan(Bx - E * (Bx - atan(Bx))))


def magic_formula_and_slope(xi, B, C, D, E):
    """``(f, df/dxi)`` of :func:`magic_formula` at a scalar ``xi``, sharing their
    transcendental terms (the prediction's Jacobian needs both); ``E = 0`` skips the inner
    arctan."""
    Bx = B * xi
    arg = Bx - E * (Bx - atan(Bx)) if E != 0.0 else Bx
    ca = C * atan(arg)
    darg = B * (1.0 - E) + E * B / (1.0 + Bx * Bx)
    return D * sin(ca), D * cos(ca) * C * darg / (1.0 + arg * arg)


def combined_slip_weights(s, alpha):
    """``(G_x, G_y)``: the factors (<= 1) by which a slip angle ``alpha`` lowers the pure
    longitudinal force ``f(s)`` and a slip ratio ``s`` lowers the pure lateral force
    ``f(alpha)`` (MF 5.2 combined slip):

        G_x = cos(RCX1 arctan(B_xa alpha)),  B_xa = RBX1 cos(arctan(RBX2 s))
        G_y = cos(RCY1 arctan(B_ys s)),      B_ys = RBY1 cos(arctan(RBY2 alpha))

    Used by the plant only, with ``[plant] combined_slip = 1`` (the paper's model, and
    every prediction model, keep the forces of eq. 11 and 12 independent)."""
    b_xa = RBX1 * cos(atan(RBX2 * s))
    b_ys = RBY1 * cos(atan(RBY2 * alpha))
    return cos(RCX1 * atan(b_xa * alpha)), cos(RCY1 * atan(b_ys * s))


def slip_denominator(v_wx, v_eps):
    """``sqrt(v_wx^2 + v_eps^2)``: the regularised |v_wx| of eq. (9) and (10)."""
    return np.sqrt(v_wx * v_wx + v_eps * v_eps)


def slip_angle(v_wx, v_wy, v_eps):
    """Slip angle alpha_ij [rad], paper eq. (9).

    Eq. (9) reads ``alpha = delta - arctan(v_By / v_Bx)``, which equals
    ``-arctan(v_wy / v_wx)`` in the wheel frame W_ij. DEVIATION(eq. 9): we evaluate
    ``-arctan(v_wy / sqrt(v_wx^2 + v_eps^2))`` (= ``-atan2(v_wy, sqrt(...))``, the
    denominator being > 0): the lateral force then opposes the lateral velocity for
    forward *and* reversing wheels, a wheel moving sideways gets a finite angle, and a
    wheel at rest gets alpha = 0 with a finite slope (no division by zero). Above a few
    v_eps it is eq. (9) to within (v_eps / v_wx)^2 / 2.
    """
    return -atan(v_wy / slip_denominator(v_wx, v_eps))


def slip_ratio(omega_w, r_w, v_wx, v_eps):
    """Slip ratio s_ij [-], paper eq. (10): ``(omega_w r_w - v_wx) / |v_wx|``.

    DEVIATION(eq. 10): ``|v_wx|`` is replaced by ``sqrt(v_wx^2 + v_eps^2)`` so a wheel at
    rest gives a finite slip (a spinning wheel on a standing vehicle saturates the force
    instead of producing inf/NaN). For |v_wx| >> v_eps this is eq. (10).
    """
    return (omega_w * r_w - v_wx) / slip_denominator(v_wx, v_eps)


def slip_jacobian(omega_w, r_w, v_wx, v_wy, v_eps):
    """Derivatives of :func:`slip_ratio` and :func:`slip_angle` with respect to the wheel
    velocity at scalars: ``(ds/dv_wx, dalpha/dv_wx, dalpha/dv_wy)`` (ds/dv_wy = 0)."""
    d2 = v_wx * v_wx + v_eps * v_eps
    d = np.sqrt(d2)
    id_ = 1.0 / d  # two divisions in all (vector division is the prediction's slowest op)
    iq = 1.0 / (d2 + v_wy * v_wy)
    return (-id_ - (omega_w * r_w - v_wx) * v_wx * (id_ * id_ * id_), v_wy * v_wx * id_ * iq,
            -d * iq)


def wheel_velocity(vbx, vby, r, x_w, y_w, delta):
    """Velocity of wheel ij in its own frame W_ij, paper eq. (6)-(8).

    ``vbx, vby``: body velocity in B [m/s]; ``r``: yaw rate [rad/s]; ``(x_w, y_w)``:
    wheel position in B [m]; ``delta``: steering angle [rad]. Returns ``(v_wx, v_wy)``.
    """
    vx_b = vbx - r * y_w  # eq. (6)
    vy_b = vby + r * x_w  # eq. (7)
    c = cos(delta)
    s = sin(delta)
    return c * vx_b + s * vy_b, -s * vx_b + c * vy_b  # eq. (8), R(delta)^T


def wheel_to_body(Fx, Fy, delta):
    """Tire force (Fx, Fy) in W_ij rotated into B, paper eq. (4): ``R(delta) F_W``."""
    c = cos(delta)
    s = sin(delta)
    return c * Fx - s * Fy, s * Fx + c * Fy


def wear_power_slip(Fx, omega_w, r_w, v_wx):
    """Slip-ratio wear power P_s,ij [W], paper eq. (13): |Fx (omega_w r_w - v_wx)|."""
    return np.abs(Fx * (omega_w * r_w - v_wx))


def wear_power_angle(Fy, v_wy):
    """Slip-angle wear power P_alpha,ij [W], paper eq. (14): |Fy v_wy|."""
    return np.abs(Fy * v_wy)


def wear_power_steer(k_t, F_N, omega_s):
    """Steering wear power P_t,ij [W], paper eq. (15): |k_t F_N omega_s|.

    ``omega_s`` is the *actual* steering rate (0 for a wheel held at its stop).
    """
    return np.abs(k_t * F_N * omega_s)


def dugoff_forces(s, alpha, F_N, C_s, C_alpha, mu):
    """Dugoff tire forces (Fx, Fy) [N] in W_ij, as used by the DH baseline (Du et al. 2024).

    With the slip ratio s of eq. (10) and slip angle alpha (tan alpha clamped at
    |alpha| <= 1.5 rad):

        S      = sqrt((C_s s)^2 + (C_alpha tan alpha)^2)
        lambda = mu F_N (1 + |s|) / (2 S)
        f      = lambda (2 - lambda) if lambda < 1 else 1
        Fx     = C_s s / (1 + |s|) f,   Fy = C_alpha tan(alpha) / (1 + |s|) f

    The resultant never exceeds mu F_N. (|s| in place of Dugoff's braking-only s makes
    driving and braking symmetric.)
    """
    a = np.minimum(np.maximum(alpha, -1.5), 1.5)
    ta = tan(a)
    one_s = 1.0 + np.abs(s)
    S = np.sqrt((C_s * s) ** 2 + (C_alpha * ta) ** 2)
    lam = mu * F_N * one_s / (2.0 * np.maximum(S, 1e-12))
    # f = lam (2 - lam) below 1, else 1. Written with min(lam, 1) rather than
    # 1 - max(1 - lam, 0)^2, which cancels catastrophically for small lam (large slips)
    # and let the resultant exceed mu F_N by up to ~1e-9 relative.
    lc = np.minimum(lam, 1.0)
    f = lc * (2.0 - lc)
    return C_s * s / one_s * f, C_alpha * ta / one_s * f


# ---- binding the equations to a set of primitives ----------------------------------------
_EQUATIONS = ("slip_denominator", "magic_formula", "magic_formula_and_slope",
              "combined_slip_weights", "slip_angle", "slip_ratio", "slip_jacobian",
              "wheel_velocity", "wheel_to_body", "wear_power_slip", "wear_power_angle",
              "wear_power_steer", "dugoff_forces")
_PRIMITIVES = ("atan", "sin", "cos", "tan")


class Tire(NamedTuple):
    """The tire, slip and wear functions of :func:`make_tire`, bound to one set of
    primitives."""

    slip_denominator: object
    magic_formula: object
    magic_formula_and_slope: object
    combined_slip_weights: object
    slip_angle: object
    slip_ratio: object
    slip_jacobian: object
    wheel_velocity: object
    wheel_to_body: object
    wear_power_slip: object
    wear_power_angle: object
    wear_power_steer: object
    dugoff_forces: object


def bind_globals(fn, g: dict, name: str):
    """A copy of the Python function ``fn`` named ``name`` whose global names resolve in
    ``g``: how a kernel is compiled over other kernels given at run time. Not a closure:
    numba keys a closure's on-disk cache entry by a pickle of the captured objects, which
    differs in every process (a closure over a dispatcher compiled again in every run),
    while a function's globals are frozen at compile time and its cache entry is keyed by
    its source file and name (hence the distinct ``name`` per binding)."""
    f = types.FunctionType(fn.__code__, g, name, fn.__defaults__)
    f.__qualname__ = name
    f.__doc__ = fn.__doc__
    f.__module__ = fn.__module__
    return f


def make_tire(atan=None, sin=None, cos=None, tan=None, fastmath=False, suffix: str = "") -> Tire:
    """The tire, slip and wear equations compiled over the given primitives: numba
    functions of one argument (``atan(x)``, ``sin(x)``, ``cos(x)``, ``tan(x)``,
    inlinable); those not given are numpy's (the plant's exact maths, scalars and arrays).
    Every returned function is ``inline="always"``, so inside a kernel it compiles with the
    kernel's flags; ``fastmath`` is the flags of a direct call from Python. ``suffix``
    names the binding (each binding's functions are cached under their own names)."""
    kernel = njit(cache=True, inline="always", fastmath=fastmath)
    g = dict(globals())
    given = {"atan": atan, "sin": sin, "cos": cos, "tan": tan}
    for name in _PRIMITIVES:
        g[name] = given[name] if given[name] is not None else kernel(
            bind_globals(_RAW[name], g, name + suffix))
    for name in _EQUATIONS:
        g[name] = kernel(bind_globals(_RAW[name], g, name + suffix))
    return Tire(*(g[name] for name in _EQUATIONS))


_RAW = {name: globals()[name] for name in _PRIMITIVES + _EQUATIONS}
EXACT = make_tire()
(slip_denominator, magic_formula, magic_formula_and_slope, combined_slip_weights, slip_angle,
 slip_ratio, slip_jacobian, wheel_velocity, wheel_to_body, wear_power_slip, wear_power_angle,
 wear_power_steer, dugoff_forces) = EXACT
