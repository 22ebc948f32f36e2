"""Batch rollout kernels: many candidate decision vectors predicted at once (numba).

Layouts (indices named in :mod:`plant.layout`)
---------------------------------------------
``x0`` (6 + 2n,): ``X0_*``: ``x, y, phi, vx, vy, r`` (velocities in G, eq. 20) then
``delta_ij`` from ``X0_DELTA`` - the head of the plant's state.

``ref`` (N_p + 1, 6): reference rows ``REF_*`` (``x, y, phi, vx, vy, r``) at
``t0 + k dt``, k = 0..N_p.

``Z`` (B, D), ``D = n_blocks * stride``: per move block b the decision variables of the
parametrisation ``S[S_POLICY]`` (:func:`commands_from_policy`); for the default offsets,
per wheel k, ``Z[b*4n + k] = d_omega_w`` [rad/s] and ``Z[b*4n + 2n + k] = d_delta``
[rad] from the kinematic feed-forward. Step k of the horizon uses block ``block[k]``;
blocks after N_c repeat the last one (controls held after N_c).

``P`` is the plant's parameter vector (:func:`plant.dynamics.pack_params`, ``P_*``: every
vehicle value the plant uses, limits included) followed by the model's own parameters
(:mod:`plant.model_params`, packed by ``controller.models.PredictionModel.pack``; DH's are
``P_DUGOFF_*`` below); ``S`` the MPC's settings vector
(:func:`controller.models.pack_settings`, ``S_*``: dt, gains, feedback limits, the
cornering feed-forward gain k_alpha, the parametrisation).

Outputs: ``poses`` (B, N_p, 3) predicted ``x, y, phi`` (``POSE_*``) at k+1, ``wear``
(B, N_p, 3) the wear powers ``P_s, P_alpha, P_t`` [W] (``WEAR_*``) over step k (eq. 16),
and ``cmds`` (B, 2, 2n) the first step's ``omega_w, omega_s`` (rows ``CMD_*``).

Models (``model`` argument), all sharing the policy:

* ``MODEL_MF`` (0): the paper's model, eq. (17)-(21) with Magic Formula tires.
* ``MODEL_DUGOFF`` (1): DH baseline, the same rigid body with Dugoff tires.
* ``MODEL_KINEMATIC`` (2): Kinematic baseline, pure rolling (no slip, no forces).
* ``MODEL_TCT`` (3): TCT baseline, lateral and yaw dynamics only, longitudinal speed held
  at the reference speed.

The three dynamic models share one step (:func:`wheel_lane`'s rigid-body branch,
:func:`wheel_terms` and :func:`rigid_body_update`), with the tire model chosen inside
(:func:`tire_forces`: MF or Dugoff); the kinematic model has its own
(:func:`kinematic_update`). The kernels are compiled per kind of step
(:func:`step_kind`), each on first use. Slips, Magic Formula and wear
powers are :mod:`plant.tire`'s equations (:func:`plant.tire.make_tire`), inlined.

SIMD layout
-----------
The batch is cut into *tiles* of :data:`LANES` candidates, and each tile is predicted in
structure-of-arrays form: every per-candidate quantity (pose, velocity, each wheel's
angle, the decision variables, the force and Jacobian sums) is a row of ``LANES`` doubles
in one workspace vector, and the innermost loops run across the row. Those loops touch
that one vector only, at compile-time-constant offsets (the per-wheel rows are copied
into fixed rows around them), so LLVM proves them free of aliasing and vectorises them;
with the math library's transcendentals they would still be scalar calls, so the
prediction is built with the branch-free approximations of :mod:`controller.approx`
(:data:`FAST`). :data:`EXACT` is the same code built with the math library: the
reference the mirrors (``controller/mirrors/``) are pinned to, and what
``tests/test_rollout_simd.py`` compares the prediction with. A candidate's result does not
depend on its lane, its tile or the batch it is in (a short tile repeats its last
candidate in the spare lanes), so any split of a batch over threads gives identical
results.

DEVIATION(eq. 19-21): the velocity update of the dynamic models is a *linearly implicit
trapezoidal* step in the body frame, ``(I - dt/2 J) du = dt f(u)``, with f the body-frame
form of eq. (17) and J its Jacobian with respect to the body velocity (tire forces and
transport terms); heading and position are advanced with the mean of the old and new
velocities, and the tire forces use the step's mid steering angle. Forward Euler (the
paper's) is unstable at a coarse prediction step at low speed, where the tires'
relaxation time ``m v / (2n C)`` falls to ~18 ms (5 km/h), and at 35 km/h its path error
over a 1 s horizon was 41 cm at dt = 0.1 s; this form is stable at every speed, costs one
3x3 solve per step, and its error at 35 km/h is given in docs/CONTROLLER.md. It reduces
to eq. (19)-(21) as dt -> 0.

The cost (:func:`controller.cost_terms.candidate_cost`) is the sum of named terms, each
written once in :mod:`controller.cost_terms` for these kernels and the CasADi mirror alike:
the tiles accumulate its per-step terms (:func:`~controller.cost_terms.pose_error`,
:func:`~controller.cost_terms.tracking_term`, :func:`~controller.cost_terms.wear_term` with
its :class:`~controller.cost_terms.WearWeights`) and add the smoothing and the ridge
(:func:`~controller.cost_terms.smoothing_row`, :func:`~controller.cost_terms.ridge_row`);
:func:`batch_cost` scores a batch of predictions.

Mirrors of this module (the CasADi graph for IPOPT, the C reference) live in
``controller/mirrors/``, pinned to :data:`EXACT` by tests.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import msagv.plant.tire as _tire
from msagv.plant import layout as lay
from msagv.plant import model_params as _mp
from msagv.plant.layout import (CMD_S, CMD_W, P_DELTA_MAX, P_DELTA_MIN, P_G, P_K_T,
                          P_LAT_B, P_LAT_C, P_LAT_E, P_LAT_MU, P_LON_B, P_LON_C, P_LON_E,
                          P_LON_MU, P_MASS, P_OMEGA_S_MAX, P_OMEGA_S_MIN, P_OMEGA_W_MAX,
                          N_L, P_V_EPS, P_WHEEL_RADIUS, P_YAW_INERTIA, POLICY_RAW, POLICY_TWIST,
                          POSE_PHI, POSE_X, POSE_Y, Q_PHI, Q_X, Q_Y,
                          REF_PHI, REF_R, REF_VX, REF_VY, REF_X, REF_Y, S_DT, S_K_ALPHA,
                          S_DIST_R, S_DIST_U, S_DIST_V, S_K_PHI, S_K_POS, S_K_SERVO, S_POLICY,
                          S_R_FB_MAX, S_STRIDE,
                          S_V_FB_MAX, WEAR_ALPHA, WEAR_S, WEAR_T, X0_DELTA, X0_PHI, X0_R,
                          X0_VX, X0_VY, X0_X, X0_Y)

from . import approx as _approx
from . import cost_terms as _cost
# the cost's terms (controller.cost_terms: numba compiles them into these kernels)
from .cost_terms import (candidate_cost, pose_error, ridge_row, smoothing_row, tracking_term,
                         wear_term, wear_weights)
from .cost_terms import wrap as _wrap

# The names the kernels below call are bound per set of primitives by make_prediction
# (plant.tire.bind_globals); these module-level ones are the math library's, for reading.
from msagv.plant.tire import (dugoff_forces, magic_formula_and_slope, slip_angle,  # noqa: E402,F401
                        slip_jacobian, slip_ratio, wear_power_angle, wear_power_slip,
                        wear_power_steer, wheel_to_body, wheel_velocity)
from .approx import atan2_exact as atan2, cos_exact as cos, sin_exact as sin  # noqa: E402

MODEL_MF, MODEL_DUGOFF, MODEL_KINEMATIC, MODEL_TCT = 0, 1, 2, 3
# DH's Dugoff parameters (plant.model_params.DUGOFF), after the shared P in its model's P
P_DUGOFF_C_S = lay.N_PARAMS + _mp.DUGOFF.offset("C_s")
P_DUGOFF_C_ALPHA = lay.N_PARAMS + _mp.DUGOFF.offset("C_alpha")
P_DUGOFF_MU = lay.N_PARAMS + _mp.DUGOFF.offset("mu")
THETA = 0.5  # the trapezoidal rule's weight of the new velocity
LANES = 8  # candidates per tile (a multiple of the widest SIMD register in doubles)
L = LANES  # (short, in the kernels' row indices)
H = LANES // 2  # the wheel loop's iterations (two lanes each)

# stale-cache guard (plant.layout): the layout, the model parameters' offsets and the inlined
# plant.tire, approx, cost_terms
_STAMP = lay.kernel_stamp(_mp.__file__, _tire.__file__, _approx.__file__, _cost.__file__)


@njit(cache=True)
def _layout_stamp():
    return _STAMP


lay.drop_stale_cache(_layout_stamp, _STAMP, __file__)

# numba's fastmath flags of both predictions: none (controller.approx, FASTMATH: with any,
# a kernel compiled in the process and the same kernel loaded from the cache gave results
# differing in the last bits, issue 29)
_EXACT_FLAGS = set(_approx.FASTMATH)
_FAST_FLAGS = set(_approx.FASTMATH)


@njit(cache=True, inline="always", error_model="numpy")
def _solve3(a, bb, c, d, e, f, g, h, i, b0, b1, b2):
    """Solve the 3x3 system [[a, bb, c], [d, e, f], [g, h, i]] x = (b0, b1, b2) by
    Cramer's rule (the matrix is well conditioned here)."""
    det = a * (e * i - f * h) - bb * (d * i - f * g) + c * (d * h - e * g)
    return ((b0 * (e * i - f * h) - bb * (b1 * i - f * b2) + c * (b1 * h - e * b2)) / det,
            (a * (b1 * i - f * b2) - b0 * (d * i - f * g) + c * (d * b2 - b1 * g)) / det,
            (a * (e * b2 - b1 * h) - bb * (d * b2 - b1 * g) + b0 * (d * h - e * g)) / det)


@njit(cache=True, inline="always", error_model="numpy")
def _clip(v, lo, hi):
    """``v`` clipped to [lo, hi] (lo first: NaN stays NaN)."""
    return hi if v > hi else (lo if v < lo else v)


# ---- the cost: its terms are controller.cost_terms' (one definition for every kernel and
# the CasADi mirror); batch_cost scores a batch --------------------------------------------
@njit(cache=True, error_model="numpy")
def batch_cost(poses, wear, ref, Z, zprev, Q, L, R, stride, nsplit, costs):
    """:func:`controller.cost_terms.candidate_cost` of every row of ``Z`` into ``costs`` (B,)."""
    for b in range(Z.shape[0]):
        costs[b] = candidate_cost(poses[b], wear[b], ref, Z[b], zprev, Q, L, R, stride, nsplit)


# ---- the tile workspace: rows of LANES doubles --------------------------------------------
(W_X, W_Y, W_PHI, W_VX, W_VY, W_R,           # state
 W_UBD, W_VBD, W_RD, W_ACO,                  # the policy's desired twist, cornering angle
 W_UB, W_VB,                                 # body velocity at the step's start
 W_A00, W_A01, W_A02, W_A10, W_A11, W_A12, W_A20, W_A21, W_A22,  # tire force Jacobian sum
 W_F0, W_F1, W_F2,                           # generalised force sum
 W_PS, W_PA, W_PT,                           # wear powers of the step
 W_DEL, W_ZW, W_ZD, W_T0, W_T1, W_T2,        # the current wheel's angle and variables
 W_OMW, W_OMS,                               # the current wheel's commands
 W_JT, W_JW, W_J,                            # cost sums
 N_FIXED_ROWS) = range(39)


@njit(cache=True)
def workspace_size(nw, dim):
    """Doubles of one tile's workspace: fixed rows, one per wheel angle, one per decision
    variable, each ``LANES`` wide."""
    return (N_FIXED_ROWS + nw + dim) * LANES


KINDS = ("kin", "rigid", "rigid_e0", "dugoff")  # the kernels' variants per kind of step


def step_kind(model: int, P) -> str:
    """The kind of step (:data:`KINDS`) the kernels of ``model`` use with parameters ``P``:
    the kinematic step, the rigid body with Dugoff tires, or with Magic Formula tires
    (``rigid_e0`` when the longitudinal curvature E is 0, which drops an arc tangent)."""
    if model == MODEL_KINEMATIC:
        return "kin"
    if model == MODEL_DUGOFF:
        return "dugoff"
    return "rigid_e0" if P[P_LON_E] == 0.0 else "rigid"


class Prediction:
    """The prediction's kernels built over one set of primitives (:func:`make_prediction`),
    one compiled variant per kind of step (:func:`step_kind`), each compiled on first use
    (a variant holds one wheel loop: compiling all four for every use cost minutes).

    ``rollout_batch(model, x0, ref, Z, block, P, S, wx, wy, poses, wear, cmds)`` (and
    ``rollout_batch_parallel``) and ``evaluate_serial`` / ``evaluate_parallel`` (``(model,
    x0, ref, Z, block, P, S, wx, wy, Q, L, R, nsplit, zprev, ws, J)``) pick the variant;
    ``kernels[kind]`` holds each variant's compiled ``tile``, ``rollout_batch``,
    ``rollout_batch_parallel``, ``evaluate_serial``, ``evaluate_parallel``, and
    ``rollout_from`` / ``rollout_from_parallel`` (:func:`rollout_from`: the rollout of
    rows that differ from a nominal one only from some step on, and the trace of the
    states, for the polish's differences)."""

    def __init__(self, name: str, commands_from_policy, kernels: dict):
        self.name = name
        self.commands_from_policy = commands_from_policy
        self.kernels = kernels

    def _k(self, model, P, what):
        return self.kernels[step_kind(model, P)][what]

    def rollout_batch(self, model, x0, ref, Z, block, P, S, *rest):
        return self._k(model, P, "rollout_batch")(model, x0, ref, Z, block, P, S, *rest)

    def rollout_batch_parallel(self, model, x0, ref, Z, block, P, S, *rest):
        return self._k(model, P, "rollout_batch_parallel")(model, x0, ref, Z, block, P, S, *rest)

    def evaluate_serial(self, model, x0, ref, Z, block, P, *rest):
        return self._k(model, P, "evaluate_serial")(model, x0, ref, Z, block, P, *rest)

    def evaluate_parallel(self, model, x0, ref, Z, block, P, *rest):
        return self._k(model, P, "evaluate_parallel")(model, x0, ref, Z, block, P, *rest)


# ---- the policy, per candidate (scalars in, scalars out) ----------------------------
def policy_head(x, y, phi, c, s, rx, ry, rphi, rvx, rvy, rr, k_pos, v_fb_max, k_phi,
                r_fb_max, k_alpha, twist, t0, t1, t2):
    """The policy's desired body twist in B and cornering angle at pose ``(x, y, phi)``
    (``c, s = cos phi, sin phi``) against the reference row ``r*``: ``(u, v, r,
    alpha_corner)``; with ``twist`` the decision offsets ``(t0, t1, t2)`` are added."""
    cx = k_pos * (rx - x)
    cy = k_pos * (ry - y)
    cn = math.sqrt(cx * cx + cy * cy)
    g = v_fb_max / cn if cn > v_fb_max else 1.0
    vdx = rvx + cx * g
    vdy = rvy + cy * g
    rd = rr + _clip(k_phi * _wrap(rphi - phi), -r_fb_max, r_fb_max)
    ub = c * vdx + s * vdy
    vb = -s * vdx + c * vdy
    if twist:
        ub += t0
        vb += t1
        rd += t2
        vdx = c * ub - s * vb
        vdy = s * ub + c * vb
    return ub, vb, rd, k_alpha * math.sqrt(vdx * vdx + vdy * vdy) * rd


def policy_wheel(ub, vb, rd, acorner, delta, zw, zd, xw, yw, r_w, dmin, dmax, cmin, smin,
                 cmax, smax, w_max, ws_min, ws_max, kservo, dt):
    """One wheel's ``(omega_w, omega_s)`` of the feed-forward policy plus the offsets
    ``zw`` [rad/s], ``zd`` [rad] (0 for the twist parametrisation); ``cmin, smin, cmax,
    smax`` are cos and sin of the steering stops."""
    wvx = ub - rd * yw
    wvy = vb + rd * xw
    dff = atan2(wvy, wvx) + acorner
    hi_ = dff > dmax
    lo_ = dff < dmin
    # at a stop: the speed projected on the stop's direction, >= 0
    inv_rw = 1.0 / r_w  # (loop-invariant: a multiplication in the lanes' loop)
    wclip = (wvx * (cmax if hi_ else cmin) + wvy * (smax if hi_ else smin)) * inv_rw
    wclip = wclip if wclip > 0.0 else 0.0
    wff = math.sqrt(wvx * wvx + wvy * wvy) * inv_rw
    wff = wclip if hi_ else (wclip if lo_ else wff)
    dff = dmax if hi_ else (dmin if lo_ else dff)
    w = _clip(wff + zw, 0.0, w_max)
    tgt = _clip(dff + zd, dmin, dmax)
    ws = kservo * (tgt - delta)
    inv_dt = 1.0 / dt
    lo = (dmin - delta) * inv_dt
    hi = (dmax - delta) * inv_dt
    lo = lo if lo > ws_min else ws_min
    hi = hi if hi < ws_max else ws_max
    held = lo > hi  # numerically at a stop: hold
    return w, (0.0 if held else _clip(ws, lo, hi))


def policy_raw(delta, zw, zs, dmin, dmax, w_max, ws_min, ws_max, dt):
    """One wheel's commands of the raw parametrisation: the decision itself clipped to
    eq. (27)'s bounds and so that delta stays inside its stops after ``dt``."""
    inv_dt = 1.0 / dt
    lo = (dmin - delta) * inv_dt
    hi = (dmax - delta) * inv_dt
    lo = lo if lo > ws_min else ws_min
    hi = hi if hi < ws_max else ws_max
    held = lo > hi
    return _clip(zw, 0.0, w_max), (0.0 if held else _clip(zs, lo, hi))


def commands_from_policy(x, delta, refk, z, base, nw, P, S, wx, wy, dt, om_w, om_s):
    """Wheel-speed and steering-rate commands of the policy at one state (eq. 27 bounds).

    The decision parametrisation ``S[S_POLICY]`` says what a block's variables
    ``z[base:base + stride]`` are: ``POLICY_OFFSETS`` (ours, default), per-wheel offsets
    of wheel speed and steering target from the feed-forward below (2n + 2n);
    ``POLICY_TWIST``, offsets ``(du, dv, dr)`` [m/s, m/s, rad/s] of the desired body
    twist in B, every wheel then following the feed-forward's kinematics of that twist,
    so all wheels are steered about one instantaneous centre (the paper's Kinematic
    baseline); ``POLICY_RAW``, the commands themselves, ``omega_w`` (2n) and ``omega_s``
    (2n), the paper's decision vector U of eq. 27 (clipped to its bounds and to the
    steering stops).

    Kinematic feed-forward with a saturated pose feedback: desired velocity in G
    ``v_ref + K_pos (p_ref - p)`` (correction limited to ``v_fb_max``), desired yaw rate
    ``r_ref + K_phi wrap(phi_ref - phi)`` (limited to ``r_fb_max``); each wheel's
    desired velocity ``v + r x p_w`` gives its feed-forward angle (atan2, clipped to
    the steering limits) and speed (projected on that angle, >= 0). A dynamic model
    adds the steady cornering slip angle ``k_alpha v r`` (the centripetal force m v r
    shared equally by the 2n wheels over the model's cornering stiffness; 0 for the
    kinematic model). The decision offsets ``z[base:]`` are added; the steering rate is
    a first-order servo toward the target angle with the exact discrete gain
    ``(1 - exp(-K dt)) / dt``, then clipped to the rate limits and so that delta stays
    inside its limits after ``dt``. ``x = (x, y, phi)`` (``POSE_*``).
    """
    r_w = P[P_WHEEL_RADIUS]
    policy = int(S[S_POLICY])
    dmin, dmax = P[P_DELTA_MIN], P[P_DELTA_MAX]
    w_max, ws_min, ws_max = P[P_OMEGA_W_MAX], P[P_OMEGA_S_MIN], P[P_OMEGA_S_MAX]
    if policy == POLICY_RAW:
        for k in range(nw):
            om_w[k], om_s[k] = policy_raw(delta[k], z[base + k], z[base + nw + k], dmin,
                                          dmax, w_max, ws_min, ws_max, dt)
        return
    twist = policy == POLICY_TWIST
    phi = x[POSE_PHI]
    c = cos(phi)
    s = sin(phi)
    t0 = z[base] if twist else 0.0
    t1 = z[base + 1] if twist else 0.0
    t2 = z[base + 2] if twist else 0.0
    ub, vb, rd, acorner = policy_head(
        x[POSE_X], x[POSE_Y], phi, c, s, refk[REF_X], refk[REF_Y], refk[REF_PHI],
        refk[REF_VX], refk[REF_VY], refk[REF_R], S[S_K_POS], S[S_V_FB_MAX], S[S_K_PHI],
        S[S_R_FB_MAX], S[S_K_ALPHA], twist, t0, t1, t2)
    kservo = (1.0 - math.exp(-S[S_K_SERVO] * dt)) / dt
    cmin, smin, cmax, smax = math.cos(dmin), math.sin(dmin), math.cos(dmax), math.sin(dmax)
    for k in range(nw):
        zw = 0.0 if twist else z[base + k]
        zd = 0.0 if twist else z[base + nw + k]
        om_w[k], om_s[k] = policy_wheel(ub, vb, rd, acorner, delta[k], zw, zd, wx[k], wy[k],
                                        r_w, dmin, dmax, cmin, smin, cmax, smax, w_max,
                                        ws_min, ws_max, kservo, dt)


# ---- one wheel of one step of the dynamic models -------------------------------------------
def tire_forces(dugoff, vwx, vwy, omw, FN, r_w, v_eps, lonB, lonC, lonD, lonE, latB,
                latC, latD, latE, C_s, C_a, mu):
    """Tire forces (eq. 9-12) of one wheel and their Jacobian K with respect to the
    wheel velocity: ``(Fx, Fy, dFx/dvwx, dFx/dvwy, dFy/dvwx, dFy/dvwy)``; Magic
    Formula, or Dugoff's forces (DH baseline, the Jacobian by central differences in
    (s, alpha))."""
    sl = slip_ratio(omw, r_w, vwx, v_eps)  # eq. (10)
    al = slip_angle(vwx, vwy, v_eps)  # eq. (9)
    ds_dx, da_dx, da_dy = slip_jacobian(omw, r_w, vwx, vwy, v_eps)
    if dugoff:
        Fx, Fy = dugoff_forces(sl, al, FN, C_s, C_a, mu)
        hs = 1e-6 + 1e-6 * abs(sl)
        ha = 1e-7 + 1e-6 * abs(al)
        fxp, fyp = dugoff_forces(sl + hs, al, FN, C_s, C_a, mu)
        fxm, fym = dugoff_forces(sl - hs, al, FN, C_s, C_a, mu)
        dFx_ds = (fxp - fxm) / (2 * hs)
        dFy_ds = (fyp - fym) / (2 * hs)
        fxp, fyp = dugoff_forces(sl, al + ha, FN, C_s, C_a, mu)
        fxm, fym = dugoff_forces(sl, al - ha, FN, C_s, C_a, mu)
        dFx_da = (fxp - fxm) / (2 * ha)
        dFy_da = (fyp - fym) / (2 * ha)
        return (Fx, Fy, dFx_ds * ds_dx + dFx_da * da_dx, dFx_da * da_dy,
                dFy_ds * ds_dx + dFy_da * da_dx, dFy_da * da_dy)
    # eq. (11); LON_E0 (bound per wheel loop): the tire's longitudinal E is 0, so the
    # compiler drops the inner arctan (the vector code would compute it and discard it)
    Fx, dFx_ds = magic_formula_and_slope(sl, lonB, lonC, lonD, 0.0 if LON_E0 else lonE)
    Fy, dFy_da = magic_formula_and_slope(al, latB, latC, latD, latE)  # eq. (12)
    return Fx, Fy, dFx_ds * ds_dx, 0.0, dFy_da * da_dx, dFy_da * da_dy


def wheel_terms(dugoff, tct, ub, vb, r, delta, om_w, om_s, xw, yw, dt, FN, r_w, v_eps,
                lonB, lonC, lonD, lonE, latB, latC, latD, latE, C_s, C_a, mu):
    """One wheel's share of the rigid-body step (eq. 4-14): its wear powers and the
    force and Jacobian terms ``(P_s, P_alpha, F_Bx, F_By, M11, M12, M21, M22)`` with
    ``M = R K R^T`` in B, at the step's mid steering angle (the wheel turns during the
    step; using the start angle delays the steering by dt / 2)."""
    dm = delta + 0.5 * dt * om_s
    cd = cos(dm)
    sd = sin(dm)
    vwx, vwy = wheel_velocity(ub, vb, r, xw, yw, dm)  # eq. (6)-(8)
    Fx, Fy, k11, k12, k21, k22 = tire_forces(dugoff, vwx, vwy, om_w, FN, r_w, v_eps, lonB,
                                             lonC, lonD, lonE, latB, latC, latD, latE,
                                             C_s, C_a, mu)
    ps = wear_power_slip(Fx, om_w, r_w, vwx)  # eq. (13)
    pa = wear_power_angle(Fy, vwy)  # eq. (14)
    if tct:  # lateral dynamics only
        Fx = 0.0
        k11 = 0.0
        k12 = 0.0
    fbx, fby = wheel_to_body(Fx, Fy, dm)  # eq. (4)
    b11 = cd * k11 - sd * k21
    b12 = cd * k12 - sd * k22
    b21 = sd * k11 + cd * k21
    b22 = sd * k12 + cd * k22
    return (ps, pa, fbx, fby, b11 * cd - b12 * sd, b11 * sd + b12 * cd,
            b21 * cd - b22 * sd, b21 * sd + b22 * cd)


def rigid_body_update(tct, x, y, phi, vx, vy, r, ub, vb, a00, a01, a02, a10, a11, a12,
                      a20, a21, a22, f0, f1, f2, m, Iz, dt, du, dv, dr):
    """The linearly implicit trapezoidal step (the module's DEVIATION) from the sums of
    the wheels' terms: ``A = sum Lw^T M Lw``, ``F = sum Lw^T R F_W``, plus the offset-free
    disturbance ``(du, dv, dr)`` (body-frame accelerations [m/s^2, rad/s^2], constant over
    the horizon: :mod:`controller.disturbance`); returns the new ``(x, y, phi, vx, vy,
    r)``."""
    # (I - THETA dt M^-1 A) du = dt M^-1 F + transport terms of the body-frame eq. (17):
    # u' = F/m + (r vb, -r ub), r' = M_z / I_vz; the transport terms enter the Jacobian
    hm = THETA * dt / m
    hi = THETA * dt / Iz
    a00 = 1.0 - hm * a00
    a01 = -hm * a01 - THETA * dt * r
    a02 = -hm * a02 - THETA * dt * vb
    a10 = -hm * a10 + THETA * dt * r
    a11 = 1.0 - hm * a11
    a12 = -hm * a12 + THETA * dt * ub
    a20 = -hi * a20
    a21 = -hi * a21
    a22 = 1.0 - hi * a22
    f0 = dt / m * f0 + dt * r * vb + dt * du
    f1 = dt / m * f1 - dt * r * ub + dt * dv
    f2 = dt / Iz * f2 + dt * dr
    if tct:  # the longitudinal row is not modelled: no longitudinal acceleration
        a00 = 1.0
        a01 = 0.0
        a02 = 0.0
        f0 = 0.0
    du0, du1, du2 = _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, f0, f1, f2)
    r1 = r + du2
    # DEVIATION(eq. 21): trapezoidal heading and position updates (mean of old and new
    # velocity); eq. (21)'s old velocity alone misplaces a vehicle turning at speed by
    # ~v r dt / 2 per step (41 cm over 1 s at 35 km/h with dt = 0.1 s)
    phi1 = phi + 0.5 * dt * (r + r1)
    c1 = cos(phi1)
    s1 = sin(phi1)
    vx1 = c1 * (ub + du0) - s1 * (vb + du1)  # back to G (eq. 20)
    vy1 = s1 * (ub + du0) + c1 * (vb + du1)
    return x + 0.5 * dt * (vx + vx1), y + 0.5 * dt * (vy + vy1), phi1, vx1, vy1, r1


def kinematic_update(x, y, phi, nw, sx, sy, sxx, syy, sw1, sw2, sw3, dt, du, dv, dr):
    """Kinematic baseline (Zhang et al. 2016): the body twist is the least-squares rigid
    motion of the commanded wheel velocities (sums ``sw*`` of ``omega_w r_w (cos delta,
    sin delta)``, their moments about the centre); wheels roll without slip (no slip
    wear). The offset-free disturbance ``(du, dv, dr)`` is a body-frame twist offset
    [m/s, rad/s] (:mod:`controller.disturbance`). Returns the new pose and velocity
    (forward Euler)."""
    ub, vb, r = _solve3(nw, 0.0, -sy, 0.0, nw, sx, -sy, sx, sxx + syy, sw1, sw2, sw3)
    ub += du
    vb += dv
    r += dr
    c = cos(phi)
    s = sin(phi)
    vx = c * ub - s * vb
    vy = s * ub + c * vb
    return x + dt * vx, y + dt * vy, phi + dt * r, vx, vy, r



@njit(cache=True, inline="always", error_model="numpy")
def _accumulate(w, i, yw, xw, dt, om_w, om_s, pt, ps, pa, t0, t1, t2, m11, m12, m21, m22):
    """Lane ``i``: one wheel's results (:func:`wheel_lane`) added to the step's sums in
    ``w``, its commands stored, its angle advanced (eq. 19)."""
    w[W_PT * L + i] += pt
    w[W_PS * L + i] += ps
    w[W_PA * L + i] += pa
    w[W_F0 * L + i] += t0
    w[W_F1 * L + i] += t1
    w[W_F2 * L + i] += t2
    # the Jacobian sum Lw^T M Lw, Lw = [[1, 0, -y], [0, 1, x]]
    w[W_A00 * L + i] += m11
    w[W_A01 * L + i] += m12
    w[W_A02 * L + i] += -m11 * yw + m12 * xw
    w[W_A10 * L + i] += m21
    w[W_A11 * L + i] += m22
    w[W_A12 * L + i] += -m21 * yw + m22 * xw
    w[W_A20 * L + i] += -yw * m11 + xw * m21
    w[W_A21 * L + i] += -yw * m12 + xw * m22
    w[W_A22 * L + i] += (-yw * (-m11 * yw + m12 * xw) + xw * (-m21 * yw + m22 * xw))
    w[W_OMW * L + i] = om_w
    w[W_OMS * L + i] = om_s
    w[W_DEL * L + i] = w[W_DEL * L + i] + dt * om_s  # eq. (19)


# ---- one wheel of one step, across the lanes: the vectorised loops --------------------
def wheel_lane(raw, tct, delta, zw, zd, ubd, vbd, rd, aco, ub, vb, r, xw, yw, dt, FN, k_t, r_w,
               v_eps, lon, lat, dug, lim, kservo):
    """One candidate's wheel in one step: the policy's commands (raw or feed-forward), the
    steering wear (eq. 15) and the wheel's terms of the model's step (``KINEMATIC``,
    ``DUGOFF``: bound per wheel loop): ``(omega_w, omega_s, P_t, P_s, P_alpha, t0, t1, t2,
    M11, M12, M21, M22)``; ``t`` is the generalised force of eq. (4)-(5) for the rigid
    body, the wheel's velocity and its moment for the kinematic model. ``lon``, ``lat``:
    the Magic Formula's (B, C, D, E); ``dug``: Dugoff's (C_s, C_alpha, mu); ``lim``: the
    steering stops, their cos and sin and the rate limits (as :func:`policy_wheel`)."""
    lonB, lonC, lonD, lonE = lon
    latB, latC, latD, latE = lat
    C_s, C_a, mu = dug
    dmin, dmax, cmin, smin, cmax, smax, w_max, ws_min, ws_max = lim
    rw_, rs_ = policy_raw(delta, zw, zd, dmin, dmax, w_max, ws_min, ws_max, dt)
    fw_, fs_ = policy_wheel(ubd, vbd, rd, aco, delta, zw, zd, xw, yw, r_w, dmin, dmax, cmin,
                            smin, cmax, smax, w_max, ws_min, ws_max, kservo, dt)
    om_w = rw_ if raw else fw_
    om_s = rs_ if raw else fs_
    pt = wear_power_steer(k_t, FN, om_s)  # eq. (15)
    if KINEMATIC:
        vwx = om_w * r_w * cos(delta)
        vwy = om_w * r_w * sin(delta)
        return om_w, om_s, pt, 0.0, 0.0, vwx, vwy, xw * vwy - yw * vwx, 0.0, 0.0, 0.0, 0.0
    ps, pa, fbx, fby, m11, m12, m21, m22 = wheel_terms(
        DUGOFF, tct, ub, vb, r, delta, om_w, om_s, xw, yw, dt, FN, r_w, v_eps, lonB, lonC,
        lonD, lonE, latB, latC, latD, latE, C_s, C_a, mu)
    return om_w, om_s, pt, ps, pa, fbx, fby, xw * fby - yw * fbx, m11, m12, m21, m22  # eq. (5)


def wheel_loop(w, raw, tct, xw, yw, dt, FN, k_t, r_w, v_eps, lonB, lonC, lonD, lonE,
               latB, latC, latD, latE, C_s, C_a, mu, dmin, dmax, cmin, smin, cmax,
               smax, w_max, ws_min, ws_max, kservo):
    """The loop over the lanes of one wheel and one step (:func:`wheel_lane`, bound per
    model by :func:`make_prediction`): the commands, the wear powers and the wheel's terms
    added to the step's sums, the angle advanced (eq. 19). Reads and writes the fixed rows
    of ``w`` only. Each iteration does two lanes, ``b`` and ``b + LANES/2``: two
    independent chains of dependent operations in one loop body (one lane's chain is
    hundreds of cycles long; interleaved, the core keeps twice as many in flight)."""
    lon = (lonB, lonC, lonD, lonE)
    lat = (latB, latC, latD, latE)
    dug = (C_s, C_a, mu)
    lim = (dmin, dmax, cmin, smin, cmax, smax, w_max, ws_min, ws_max)
    for b in range(H):
        i = b + H
        (w0, s0, pt0, ps0, pa0, f00, f10, f20, m110, m120, m210, m220) = wheel_lane(
            raw, tct, w[W_DEL * L + b], w[W_ZW * L + b], w[W_ZD * L + b], w[W_UBD * L + b],
            w[W_VBD * L + b], w[W_RD * L + b], w[W_ACO * L + b], w[W_UB * L + b],
            w[W_VB * L + b], w[W_R * L + b], xw, yw, dt, FN, k_t, r_w, v_eps, lon, lat, dug, lim,
            kservo)
        (w1, s1, pt1, ps1, pa1, f01, f11, f21, m111, m121, m211, m221) = wheel_lane(
            raw, tct, w[W_DEL * L + i], w[W_ZW * L + i], w[W_ZD * L + i], w[W_UBD * L + i],
            w[W_VBD * L + i], w[W_RD * L + i], w[W_ACO * L + i], w[W_UB * L + i],
            w[W_VB * L + i], w[W_R * L + i], xw, yw, dt, FN, k_t, r_w, v_eps, lon, lat, dug, lim,
            kservo)
        _accumulate(w, b, yw, xw, dt, w0, s0, pt0, ps0, pa0, f00, f10, f20, m110, m120, m210,
                    m220)
        _accumulate(w, i, yw, xw, dt, w1, s1, pt1, ps1, pa1, f01, f11, f21, m111, m121, m211,
                    m221)


# ---- the tile: LANES candidates in structure-of-arrays form --------------------------
@njit(cache=True, inline="always", error_model="numpy")
def _save_state(w, trace, b0, nb, k, nw):
    """Lanes ``0 .. nb - 1``'s state (body and wheel angles) into ``trace[b0 + b, k]``, in
    ``x0``'s layout (``X0_*``): what a tile needs to start at step ``k``."""
    wdel = N_FIXED_ROWS
    for b in range(nb):
        t = trace[b0 + b, k]
        t[X0_X] = w[W_X * L + b]
        t[X0_Y] = w[W_Y * L + b]
        t[X0_PHI] = w[W_PHI * L + b]
        t[X0_VX] = w[W_VX * L + b]
        t[X0_VY] = w[W_VY * L + b]
        t[X0_R] = w[W_R * L + b]
        for j in range(nw):
            t[X0_DELTA + j] = w[(wdel + j) * L + b]


def set_body(w, b, x, y, phi, vx, vy, r):
    """Lane ``b``'s body state (pose and world-frame velocity) into ``w``."""
    w[W_X * L + b] = x
    w[W_Y * L + b] = y
    w[W_PHI * L + b] = phi
    w[W_VX * L + b] = vx
    w[W_VY * L + b] = vy
    w[W_R * L + b] = r


def load_tile(w, Z, b0, nb, x0, nw):
    """The lanes' decision rows (spare lanes repeat candidate ``b0 + nb - 1``), the start
    state ``x0`` (body and wheel angles) in every lane, the cost sums zeroed."""
    wdel = N_FIXED_ROWS  # first wheel-angle row
    wz = N_FIXED_ROWS + nw  # first decision row
    last = nb - 1
    for d in range(Z.shape[1]):
        for b in range(L):
            w[(wz + d) * L + b] = Z[b0 + (b if b < last else last), d]
    x_, y_, phi_ = x0[X0_X], x0[X0_Y], x0[X0_PHI]
    vx_, vy_, r_ = x0[X0_VX], x0[X0_VY], x0[X0_R]
    for b in range(L):
        set_body(w, b, x_, y_, phi_, vx_, vy_, r_)  # noqa: F821 (bound by make_prediction)
        w[W_JT * L + b] = 0.0
        w[W_JW * L + b] = 0.0
    for j in range(nw):
        dj = x0[X0_DELTA + j]
        for b in range(L):
            w[(wdel + j) * L + b] = dj


def policy_rows(w, ref, k, tw, twist, tct, k_pos, v_fb_max, k_phi, r_fb_max, k_alpha):
    """Step ``k``'s head of the policy in every lane: the twist offsets (rows from ``tw``,
    or none), the desired body velocity and the body-frame velocity; the step's sums
    (Jacobian, forces, wear powers) zeroed for the wheels to add to."""
    rx, ry, rphi = ref[k, REF_X], ref[k, REF_Y], ref[k, REF_PHI]
    rvx, rvy, rr = ref[k, REF_VX], ref[k, REF_VY], ref[k, REF_R]
    vref = math.sqrt(rvx * rvx + rvy * rvy)
    if twist:
        for b in range(L):
            w[W_T0 * L + b] = w[tw + b]
            w[W_T1 * L + b] = w[tw + L + b]
            w[W_T2 * L + b] = w[tw + 2 * L + b]
    else:
        for b in range(L):
            w[W_T0 * L + b] = 0.0
            w[W_T1 * L + b] = 0.0
            w[W_T2 * L + b] = 0.0
    for b in range(L):  # vectorised: the policy's head, the body velocity
        phi = w[W_PHI * L + b]
        c = cos(phi)
        s = sin(phi)
        ubd, vbd, rd, aco = policy_head(
            w[W_X * L + b], w[W_Y * L + b], phi, c, s, rx, ry, rphi, rvx, rvy, rr,
            k_pos, v_fb_max, k_phi, r_fb_max, k_alpha, twist, w[W_T0 * L + b],
            w[W_T1 * L + b], w[W_T2 * L + b])
        w[W_UBD * L + b] = ubd
        w[W_VBD * L + b] = vbd
        w[W_RD * L + b] = rd
        w[W_ACO * L + b] = aco
        vx = w[W_VX * L + b]
        vy = w[W_VY * L + b]
        w[W_UB * L + b] = vref if tct else c * vx + s * vy
        w[W_VB * L + b] = -s * vx + c * vy
        w[W_A00 * L + b] = 0.0
        w[W_A01 * L + b] = 0.0
        w[W_A02 * L + b] = 0.0
        w[W_A10 * L + b] = 0.0
        w[W_A11 * L + b] = 0.0
        w[W_A12 * L + b] = 0.0
        w[W_A20 * L + b] = 0.0
        w[W_A21 * L + b] = 0.0
        w[W_A22 * L + b] = 0.0
        w[W_F0 * L + b] = 0.0
        w[W_F1 * L + b] = 0.0
        w[W_F2 * L + b] = 0.0
        w[W_PS * L + b] = 0.0
        w[W_PA * L + b] = 0.0
        w[W_PT * L + b] = 0.0


def store_body(w, b, x, y, phi, vx, vy, r, rx1, ry1, rphi1, qx, qy, qphi, ps, pa, lw):
    """Lane ``b``'s new body state into ``w``, its tracking term against the reference's
    next pose and its wear term (slip powers ``ps``, ``pa``; the step's ``P_t`` from
    ``w``; weights ``lw``, a :class:`controller.cost_terms.WearWeights`) added to its
    costs."""
    set_body(w, b, x, y, phi, vx, vy, r)  # noqa: F821
    ex, ey, ephi = pose_error(x, y, phi, rx1, ry1, rphi1)
    w[W_JT * L + b] += tracking_term(ex, ey, ephi, qx, qy, qphi)
    w[W_JW * L + b] = wear_term(w[W_JW * L + b], ps, pa, w[W_PT * L + b], lw)


def body_rows(w, ref, k, tct, nw, sx, sy, sxx, syy, m, Iz, dt, qx, qy, qphi, lw, du, dv,
              dr):
    """Step ``k``'s body update in every lane (``KINEMATIC``: bound per tile) from the
    wheels' sums, and its tracking and wear terms added to the lanes' costs."""
    rx1, ry1, rphi1 = ref[k + 1, REF_X], ref[k + 1, REF_Y], ref[k + 1, REF_PHI]
    if KINEMATIC:
        for b in range(L):  # vectorised: the kinematic body
            x, y, phi, vx, vy, r = kinematic_update(
                w[W_X * L + b], w[W_Y * L + b], w[W_PHI * L + b], nw, sx, sy, sxx, syy,
                w[W_F0 * L + b], w[W_F1 * L + b], w[W_F2 * L + b], dt, du, dv, dr)
            store_body(w, b, x, y, phi, vx, vy, r, rx1, ry1, rphi1, qx, qy, qphi, 0.0,  # noqa: F821
                       0.0, lw)
    else:
        for b in range(L):  # vectorised: the rigid body's step and the cost
            x, y, phi, vx, vy, r = rigid_body_update(
                tct, w[W_X * L + b], w[W_Y * L + b], w[W_PHI * L + b], w[W_VX * L + b],
                w[W_VY * L + b], w[W_R * L + b], w[W_UB * L + b], w[W_VB * L + b],
                w[W_A00 * L + b], w[W_A01 * L + b], w[W_A02 * L + b], w[W_A10 * L + b],
                w[W_A11 * L + b], w[W_A12 * L + b], w[W_A20 * L + b], w[W_A21 * L + b],
                w[W_A22 * L + b], w[W_F0 * L + b], w[W_F1 * L + b], w[W_F2 * L + b],
                m, Iz, dt, du, dv, dr)
            store_body(w, b, x, y, phi, vx, vy, r, rx1, ry1, rphi1, qx, qy, qphi,  # noqa: F821
                       w[W_PS * L + b], w[W_PA * L + b], lw)


def tile(model, x0, ref, Z, b0, nb, block, P, S, wx, wy, Q, Lw, R, zprev, nsplit, w,
         out, poses, wear, cmds, k0, trace):
    """Predict and cost candidates ``Z[b0 : b0 + nb]`` (``nb <= LANES``; spare lanes
    repeat the last one) in the workspace ``w`` (:func:`workspace_size`); the costs
    end in row ``W_J``. With ``out``, also writes their ``poses``, ``wear`` and
    first commands ``cmds`` (rows b0 ..). The lane loops touch ``w`` only. Each step:
    :func:`policy_rows`, then every wheel (:func:`wheel_loop`), then :func:`body_rows`.
    The steps ``k0 .. N_p - 1`` from the state ``x0`` at step ``k0``'s start (``k0 > 0``:
    :func:`rollout_from`; nothing of the steps before is written, and the costs are those
    of the steps taken); a non-empty ``trace`` receives each candidate's state at each
    step's start (:func:`_save_state`)."""
    nw = wx.shape[0]
    Np = block.shape[0]
    dt = S[S_DT]
    stride = int(S[S_STRIDE])
    policy = int(S[S_POLICY])
    raw = policy == POLICY_RAW
    twist = policy == POLICY_TWIST
    kin = KINEMATIC  # the kind of step this tile is bound to (make_prediction)
    tct = model == MODEL_TCT
    m, Iz, r_w, v_eps = P[P_MASS], P[P_YAW_INERTIA], P[P_WHEEL_RADIUS], P[P_V_EPS]
    k_t = P[P_K_T]
    FN = m * P[P_G] / nw  # Assumption 2
    lonB, lonC, lonD, lonE = P[P_LON_B], P[P_LON_C], P[P_LON_MU] * FN, P[P_LON_E]
    latB, latC, latD, latE = P[P_LAT_B], P[P_LAT_C], P[P_LAT_MU] * FN, P[P_LAT_E]
    C_s, C_a, mu = P[P_DUGOFF_C_S], P[P_DUGOFF_C_ALPHA], P[P_DUGOFF_MU]
    dmin, dmax = P[P_DELTA_MIN], P[P_DELTA_MAX]
    cmin, smin, cmax, smax = math.cos(dmin), math.sin(dmin), math.cos(dmax), math.sin(dmax)
    w_max, ws_min, ws_max = P[P_OMEGA_W_MAX], P[P_OMEGA_S_MIN], P[P_OMEGA_S_MAX]
    k_pos, v_fb_max, k_phi = S[S_K_POS], S[S_V_FB_MAX], S[S_K_PHI]
    r_fb_max, k_alpha = S[S_R_FB_MAX], S[S_K_ALPHA]
    kservo = (1.0 - math.exp(-S[S_K_SERVO] * dt)) / dt
    du, dv, dr = S[S_DIST_U], S[S_DIST_V], S[S_DIST_R]
    qx, qy, qphi = Q[Q_X], Q[Q_Y], Q[Q_PHI]
    lw = wear_weights(Lw)
    sx = 0.0
    sy = 0.0
    sxx = 0.0
    syy = 0.0
    for j in range(nw):
        sx += wx[j]
        sy += wy[j]
        sxx += wx[j] * wx[j]
        syy += wy[j] * wy[j]
    wdel = N_FIXED_ROWS  # first wheel-angle row
    wz = N_FIXED_ROWS + nw  # first decision row
    load_tile(w, Z, b0, nb, x0, nw)  # noqa: F821 (bound by make_prediction)
    traced = trace.shape[0] > 0
    for k in range(k0, Np):
        if traced:
            _save_state(w, trace, b0, nb, k, nw)
        base = block[k] * stride
        policy_rows(w, ref, k, (wz + base) * L, twist, tct, k_pos, v_fb_max, k_phi,  # noqa: F821
                    r_fb_max, k_alpha)
        for j in range(nw):
            jw = (wz + base + j) * L  # the wheel's variables (offsets / raw)
            jd = (wz + base + nw + j) * L
            if twist:
                for b in range(L):
                    w[W_DEL * L + b] = w[(wdel + j) * L + b]
                    w[W_ZW * L + b] = 0.0
                    w[W_ZD * L + b] = 0.0
            else:
                for b in range(L):  # the wheel's rows into the fixed rows
                    w[W_DEL * L + b] = w[(wdel + j) * L + b]
                    w[W_ZW * L + b] = w[jw + b]
                    w[W_ZD * L + b] = w[jd + b]
            wheel_loop(w, raw, tct, wx[j], wy[j], dt, FN, k_t, r_w, v_eps, lonB, lonC, lonD,  # noqa: F821
                       lonE, latB, latC, latD, latE, C_s, C_a, mu, dmin, dmax, cmin, smin, cmax,
                       smax, w_max, ws_min, ws_max, kservo)
            for b in range(L):
                w[(wdel + j) * L + b] = w[W_DEL * L + b]
            if out and k == 0:
                for b in range(nb):
                    cmds[b0 + b, CMD_W, j] = w[W_OMW * L + b]
                    cmds[b0 + b, CMD_S, j] = w[W_OMS * L + b]
        body_rows(w, ref, k, tct, nw, sx, sy, sxx, syy, m, Iz, dt, qx, qy, qphi, lw,  # noqa: F821
                  du, dv, dr)
        if out:
            for b in range(nb):
                poses[b0 + b, k, POSE_X] = w[W_X * L + b]
                poses[b0 + b, k, POSE_Y] = w[W_Y * L + b]
                poses[b0 + b, k, POSE_PHI] = w[W_PHI * L + b]
                wear[b0 + b, k, WEAR_S] = 0.0 if kin else w[W_PS * L + b]
                wear[b0 + b, k, WEAR_ALPHA] = 0.0 if kin else w[W_PA * L + b]
                wear[b0 + b, k, WEAR_T] = w[W_PT * L + b]
    for b in range(nb):
        w[W_J * L + b] = ((w[W_JT * L + b] + w[W_JW * L + b]) / Np
                          + smoothing_row(Z, b0 + b, zprev, R, stride, nsplit)
                          + ridge_row(Z, b0 + b, R, stride, nsplit))


def rollout_batch(model, x0, ref, Z, block, P, S, wx, wy, poses, wear, cmds):
    """Predict every candidate row of ``Z``; writes ``poses``, ``wear`` (B, N_p, 3) and
    the first commands ``cmds`` (B, 2, 2n). Serial: predictable on a shared 2-core
    machine."""
    B = Z.shape[0]
    w = np.empty(workspace_size(wx.shape[0], Z.shape[1]))
    zp = np.zeros(Z.shape[1])
    no_q, no_l, no_r = np.zeros(3), np.zeros(N_L), np.zeros(4)
    for t in range((B + L - 1) // L):
        b0 = t * L
        tile(model, x0, ref, Z, b0, min(L, B - b0), block, P, S, wx, wy, no_q, no_l, no_r,
             zp, 0, w, True, poses, wear, cmds, 0, np.empty((0, 0, 0)))


def rollout_batch_parallel(model, x0, ref, Z, block, P, S, wx, wy, poses, wear, cmds):
    """As :func:`rollout_batch`, the tiles spread over numba's threads (prange); the
    results are those of the serial kernel."""
    B = Z.shape[0]
    n = (B + L - 1) // L
    size = workspace_size(wx.shape[0], Z.shape[1])
    ws = np.empty((n, size))
    zp = np.zeros(Z.shape[1])
    no_q, no_l, no_r = np.zeros(3), np.zeros(N_L), np.zeros(4)
    for t in prange(n):
        b0 = t * L
        tile(model, x0, ref, Z, b0, min(L, B - b0), block, P, S, wx, wy, no_q, no_l, no_r,
             zp, 0, ws[t], True, poses, wear, cmds, 0, np.empty((0, 0, 0)))


def evaluate(model, x0, ref, Z, block, P, S, wx, wy, Q, Lw, R, nsplit, zprev, ws, J):
    """The cost (:func:`controller.cost_terms.candidate_cost`) of every row of ``Z`` into
    ``J``, rollout and cost fused per tile; ``ws`` (tiles, :func:`workspace_size`) the
    tiles' workspaces."""
    B = Z.shape[0]
    n = (B + L - 1) // L
    none = np.empty((0, 0, 0))
    for t in prange(n):
        b0 = t * L
        nb = min(L, B - b0)
        w = ws[t]
        tile(model, x0, ref, Z, b0, nb, block, P, S, wx, wy, Q, Lw, R, zprev, nsplit, w,
             False, none, none, none, 0, none)
        for b in range(nb):
            J[b0 + b] = w[W_J * L + b]


def rollout_from(model, x0, ref, Z, block, P, S, wx, wy, poses, wear, cmds, first, trace0,
                 poses0, wear0, cmds0, trace):
    """:func:`rollout_batch`'s outputs for rows of ``Z`` that are a nominal decision vector
    changed only in the blocks first used at step ``first[b]`` or later (row ``b``; the
    steps before cannot differ from the nominal's), from the nominal's rollout: its state
    at each step's start ``trace0`` (N_p, ``X0_DELTA`` + n_w; a ``trace`` of this kernel),
    its ``poses0``, ``wear0`` (N_p, 3) and ``cmds0`` (2, n_w). Each tile starts at the
    smallest ``first`` of its rows, from the nominal's state there (from ``x0`` at 0), and
    its rows' outputs before that step are the nominal's: the steps it takes are the same
    operations on the same numbers as :func:`rollout_batch`'s (a candidate's result does
    not depend on its lane or tile), so the outputs are the same to the bit (the polish's
    finite differences, :func:`controller.sa_kernel._gn_jacobian`: a variable of block
    ``b`` changes nothing before that block's first step). With ``first`` all 0 it is
    :func:`rollout_batch`; a non-empty ``trace`` (B, N_p, ``X0_DELTA`` + n_w) receives
    each row's state at each step's start (at the steps taken)."""
    B = Z.shape[0]
    Np = block.shape[0]
    nw = wx.shape[0]
    if first.shape[0] != B or trace0.shape[0] != Np or trace0.shape[1] != X0_DELTA + nw:
        raise ValueError("rollout_from: need first (B,) and trace0 (N_p, X0_DELTA + n_w)")
    if trace.shape[0] > 0 and (trace.shape[0] != B or trace.shape[1] != Np
                               or trace.shape[2] != X0_DELTA + nw):
        raise ValueError("rollout_from: trace must be empty or (B, N_p, X0_DELTA + n_w)")
    for b in range(B):
        if first[b] < 0:
            raise ValueError("rollout_from: first must be >= 0")
    n = (B + L - 1) // L
    ws = np.empty((n, workspace_size(nw, Z.shape[1])))
    zp = np.zeros(Z.shape[1])
    no_q, no_l, no_r = np.zeros(3), np.zeros(N_L), np.zeros(4)
    for t in prange(n):
        b0 = t * L
        nb = min(L, B - b0)
        k0 = Np
        for b in range(nb):
            k0 = min(k0, first[b0 + b])
        if k0 == 0:
            tile(model, x0, ref, Z, b0, nb, block, P, S, wx, wy, no_q, no_l, no_r, zp, 0,
                 ws[t], True, poses, wear, cmds, 0, trace)
        elif k0 < Np:
            tile(model, trace0[k0], ref, Z, b0, nb, block, P, S, wx, wy, no_q, no_l, no_r,
                 zp, 0, ws[t], True, poses, wear, cmds, k0, trace)
        for b in range(nb):
            for k in range(k0):
                for q in range(3):
                    poses[b0 + b, k, q] = poses0[k, q]
                    wear[b0 + b, k, q] = wear0[k, q]
            if k0 > 0:
                for j in range(nw):
                    cmds[b0 + b, CMD_W, j] = cmds0[CMD_W, j]
                    cmds[b0 + b, CMD_S, j] = cmds0[CMD_S, j]


KINEMATIC = DUGOFF = LON_E0 = False  # bound per kind of step by make_prediction

_KERNELS = ("policy_head", "policy_wheel", "policy_raw", "tire_forces", "wheel_terms",
            "rigid_body_update", "kinematic_update")
_TILE_PARTS = ("set_body", "load_tile", "policy_rows", "store_body")  # inlined into the tile
_RAW_NAMES = _KERNELS + _TILE_PARTS + (
    "wheel_lane", "commands_from_policy", "wheel_loop", "body_rows", "tile", "rollout_batch",
    "rollout_batch_parallel", "evaluate", "rollout_from")


def make_prediction(prims: _approx.Primitives, fastmath) -> Prediction:
    """The policy, the four models' step and the tiled batch kernels, compiled over the
    transcendental functions ``prims`` (:data:`controller.approx.EXACT` or ``FAST``) with
    numba's ``fastmath`` flags ``fastmath``: the functions above, each bound to that set
    (:func:`plant.tire.bind_globals`; every kernel's name carries ``prims.name``: numba's
    on-disk cache is keyed by it)."""
    sfx = "_" + prims.name
    T = _tire.make_tire(prims.atan, prims.sin, prims.cos, prims.tan, fastmath=fastmath,
                        suffix=sfx)
    g = dict(globals())
    g.update(T._asdict())
    g.update(atan2=prims.atan2, sin=prims.sin, cos=prims.cos)
    inline = njit(cache=True, inline="always", fastmath=fastmath, error_model="numpy")

    def kernel(name, bound_name=None, gl=None, **kw):
        fn = _tire.bind_globals(_RAW[name], g if gl is None else gl, (bound_name or name) + sfx)
        return njit(cache=True, fastmath=fastmath, error_model="numpy", **kw)(fn)

    for name in _KERNELS + _TILE_PARTS:
        g[name] = inline(_tire.bind_globals(_RAW[name], g, name + sfx))
    cfp = kernel("commands_from_policy")
    kernels = {}
    for kind in KINDS:
        # the globals of this kind's kernels: its flags, its wheel loop, its tile
        gl = dict(g, KINEMATIC=kind == "kin", DUGOFF=kind == "dugoff", LON_E0=kind == "rigid_e0")
        for name in ("tire_forces", "wheel_terms", "wheel_lane", "body_rows"):  # they read the flags
            gl[name] = inline(_tire.bind_globals(_RAW[name], gl, f"{name}_{kind}{sfx}"))
        gl["wheel_loop"] = kernel("wheel_loop", "wheel_loop_" + kind, gl)
        gl["tile"] = kernel("tile", "tile_" + kind, gl)
        kernels[kind] = {
            "tile": gl["tile"],
            "rollout_batch": kernel("rollout_batch", "rollout_batch_" + kind, gl),
            "rollout_batch_parallel": kernel("rollout_batch_parallel",
                                             "rollout_batch_parallel_" + kind, gl, parallel=True),
            "evaluate_serial": kernel("evaluate", "evaluate_serial_" + kind, gl),
            "evaluate_parallel": kernel("evaluate", "evaluate_parallel_" + kind, gl,
                                        parallel=True),
            "rollout_from": kernel("rollout_from", "rollout_from_" + kind, gl),
            "rollout_from_parallel": kernel("rollout_from", "rollout_from_parallel_" + kind,
                                            gl, parallel=True)}
    return Prediction(prims.name, cfp, kernels)


_RAW = {name: globals()[name] for name in _RAW_NAMES}

EXACT = make_prediction(_approx.EXACT, _EXACT_FLAGS)
"""The prediction with the math library's transcendentals: the reference of the mirrors."""
FAST = make_prediction(_approx.FAST, _FAST_FLAGS)
"""The prediction the controller runs: SIMD lanes, :mod:`controller.approx`'s functions."""

commands_from_policy = EXACT.commands_from_policy  # the command sent: the math library's
rollout_batch = FAST.rollout_batch
rollout_batch_parallel = FAST.rollout_batch_parallel
rollout_batch_exact = EXACT.rollout_batch
