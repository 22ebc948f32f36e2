"""Batch rollout kernels: many candidate decision vectors predicted at once (numba).

Layouts (indices named in :mod:`plant.layout`)
---------------------------------------------
``x0`` (6 + 2n,): ``X0_*``: ``x, y, phi, vx, vy, r`` (velocities in G, eq. 20) then
``delta_ij`` from ``X0_DELTA`` - the head of the plant's state.

``ref`` (N_p + 1, 6): reference rows ``REF_*`` (``x, y, phi, vx, vy, r``) at
``t0 + k dt``, k = 0..N_p.

``Z`` (B, D), ``D = n_blocks * 4n``: per move block b, per wheel k, the offsets
``Z[b*4n + k] = d_omega_w`` [rad/s] and ``Z[b*4n + 2n + k] = d_delta`` [rad] from the
kinematic feed-forward (see :func:`commands_from_policy`). Step k of the horizon uses
block ``block[k]``; blocks after N_c repeat the last one (controls held after N_c).

``P`` is the plant's parameter vector (:func:`plant.dynamics.pack_params`, ``P_*``: every
vehicle value, limits and Dugoff coefficients included); ``S`` the MPC's settings vector
(:func:`controller.models.pack_settings`, ``S_*``: dt, gains, feedback limits, the
cornering feed-forward gain k_alpha).

Outputs: ``poses`` (B, N_p, 3) predicted ``x, y, phi`` (``POSE_*``) at k+1, ``wear``
(B, N_p, 3) the wear powers ``P_s, P_alpha, P_t`` [W] (``WEAR_*``) over step k (eq. 16),
and ``cmds`` (B, 2, 2n) the first step's ``omega_w, omega_s`` (rows ``CMD_*``).

Models (``model`` argument), all sharing the policy; :func:`_model_step` dispatches:

* ``MODEL_MF`` (0): the paper's model, eq. (17)-(21) with Magic Formula tires.
* ``MODEL_DUGOFF`` (1): DH baseline, the same rigid body with Dugoff tires.
* ``MODEL_KINEMATIC`` (2): Kinematic baseline, pure rolling (no slip, no forces).
* ``MODEL_TCT`` (3): TCT baseline, lateral and yaw dynamics only, longitudinal speed held
  at the reference speed.

The three dynamic models share one step, :func:`_rigid_body_step`, with the tire model
chosen inside (:func:`_tire_mf`, :func:`_tire_dugoff`); the kinematic model has its own,
:func:`_kinematic_step`. Slips, Magic Formula and wear powers are :mod:`plant.tire`'s
functions, inlined and compiled here with ``fastmath``.

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

The cost (:func:`candidate_cost`) is the sum of named terms, one small function each:
:func:`tracking_cost`, :func:`wear_cost`, :func:`smoothing_cost`, :func:`ridge_cost`.

Mirrors of this module (the CasADi graph for IPOPT, the C reference) live in
``controller/mirrors/``, pinned to it by tests.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

import plant.tire as _tire
from plant import layout as lay
from plant.layout import (CMD_S, CMD_W, L_ALPHA, L_S, L_T, P_DELTA_MAX, P_DELTA_MIN,
                          P_DUGOFF_C_ALPHA, P_DUGOFF_C_S, P_DUGOFF_MU, P_G, P_K_T, P_LAT_B,
                          P_LAT_C, P_LAT_E, P_LAT_MU, P_LON_B, P_LON_C, P_LON_E, P_LON_MU,
                          P_MASS, P_OMEGA_S_MAX, P_OMEGA_S_MIN, P_OMEGA_W_MAX, P_V_EPS,
                          P_WHEEL_RADIUS, P_YAW_INERTIA, POSE_PHI, POSE_X, POSE_Y, Q_PHI, Q_X,
                          Q_Y, R_DD, R_DW, R_OD, R_OW, REF_PHI, REF_R, REF_VX, REF_VY, REF_X,
                          REF_Y, S_DT, S_K_ALPHA, S_K_PHI, S_K_POS, S_K_SERVO, S_R_FB_MAX,
                          S_V_FB_MAX, S_POLICY, S_STRIDE, LE_S, LE_ALPHA, LE_T,
                          POLICY_TWIST, POLICY_RAW, WEAR_ALPHA, WEAR_S, WEAR_T, X0_DELTA,
                          X0_PHI, X0_R,
                          X0_VX, X0_VY, X0_X, X0_Y)
from plant.tire import (dugoff_forces, magic_formula_and_slope, slip_angle, slip_jacobian,
                        slip_ratio, wear_power_angle, wear_power_slip, wear_power_steer,
                        wheel_to_body, wheel_velocity)

MODEL_MF, MODEL_DUGOFF, MODEL_KINEMATIC, MODEL_TCT = 0, 1, 2, 3
THETA = 0.5  # the trapezoidal rule's weight of the new velocity
KW = 1e-3  # W -> kW: the cost's wear powers are in kW so that L has usable magnitudes

# stale-cache guard (plant.layout): the layout and the inlined plant.tire functions
_STAMP = lay.kernel_stamp(_tire.__file__)


@njit(cache=True)
def _layout_stamp():
    return _STAMP


lay.drop_stale_cache(_layout_stamp, _STAMP, __file__)

_FAST = dict(cache=True, fastmath=True, error_model="numpy")
_INLINE = dict(_FAST, inline="always")


@njit(cache=True, inline="always", error_model="numpy")
def _wrap(a):
    """Angle wrapped to (-pi, pi]."""
    return a - 2.0 * math.pi * math.ceil((a - math.pi) / (2.0 * math.pi))


@njit(**_FAST)
def commands_from_policy(x, delta, refk, z, base, nw, P, S, wx, wy, dt,
                         om_w, om_s):
    """Wheel-speed and steering-rate commands of the policy at one state (eq. 27 bounds).

    The decision parametrisation ``S[S_POLICY]`` says what a block's variables
    ``z[base:base + stride]`` are: ``POLICY_OFFSETS`` (ours, default), per-wheel offsets
    of wheel speed and steering target from the feed-forward below (2n + 2n);
    ``POLICY_TWIST``, offsets ``(du, dv, dr)`` [m/s, m/s, rad/s] of the desired body twist
    in B, every wheel then following the feed-forward's kinematics of that twist, so all
    wheels are steered about one instantaneous centre (the paper's Kinematic baseline);
    ``POLICY_RAW``, the commands themselves, ``omega_w`` (2n) and ``omega_s`` (2n), the
    paper's decision vector U of eq. 27 (clipped to its bounds and to the steering stops).

    Kinematic feed-forward with a saturated pose feedback: desired velocity in G
    ``v_ref + K_pos (p_ref - p)`` (correction limited to ``v_fb_max``), desired yaw rate
    ``r_ref + K_phi wrap(phi_ref - phi)`` (limited to ``r_fb_max``); each wheel's desired
    velocity ``v + r x p_w`` gives its feed-forward angle (atan2, clipped to the steering
    limits) and speed (projected on that angle, >= 0). A dynamic model adds the steady
    cornering slip angle ``k_alpha v r`` (the centripetal force m v r shared equally by
    the 2n wheels over the model's cornering stiffness; 0 for the kinematic model). The
    decision offsets ``z[base:]``
    are added; the steering rate is a first-order servo toward the target angle with the
    exact discrete gain ``(1 - exp(-K dt)) / dt``, then clipped to the rate limits and so
    that delta stays inside its limits after ``dt``. ``x = (x, y, phi)`` (``POSE_*``).
    """
    r_w = P[P_WHEEL_RADIUS]
    policy = int(S[S_POLICY])
    dmin, dmax = P[P_DELTA_MIN], P[P_DELTA_MAX]
    w_max, ws_min, ws_max = P[P_OMEGA_W_MAX], P[P_OMEGA_S_MIN], P[P_OMEGA_S_MAX]
    if policy == POLICY_RAW:
        for k in range(nw):
            w = z[base + k]
            om_w[k] = w_max if w > w_max else (0.0 if w < 0.0 else w)
            lo = max(ws_min, (dmin - delta[k]) / dt)
            hi = min(ws_max, (dmax - delta[k]) / dt)
            if lo > hi:  # numerically at a stop: hold
                lo = 0.0
                hi = 0.0
            ws = z[base + nw + k]
            om_s[k] = hi if ws > hi else (lo if ws < lo else ws)
        return
    phi = x[POSE_PHI]
    ex = refk[REF_X] - x[POSE_X]
    ey = refk[REF_Y] - x[POSE_Y]
    k_pos, v_fb_max, r_fb_max = S[S_K_POS], S[S_V_FB_MAX], S[S_R_FB_MAX]
    cx = k_pos * ex
    cy = k_pos * ey
    cn = math.sqrt(cx * cx + cy * cy)
    if cn > v_fb_max:
        cx *= v_fb_max / cn
        cy *= v_fb_max / cn
    vdx = refk[REF_VX] + cx
    vdy = refk[REF_VY] + cy
    cr = S[S_K_PHI] * _wrap(refk[REF_PHI] - phi)
    if cr > r_fb_max:
        cr = r_fb_max
    elif cr < -r_fb_max:
        cr = -r_fb_max
    rd = refk[REF_R] + cr
    c = math.cos(phi)
    s = math.sin(phi)
    ub = c * vdx + s * vdy
    vb = -s * vdx + c * vdy
    twist = policy == POLICY_TWIST
    if twist:
        ub += z[base]
        vb += z[base + 1]
        rd += z[base + 2]
        vdx = c * ub - s * vb
        vdy = s * ub + c * vb
    kservo = (1.0 - math.exp(-S[S_K_SERVO] * dt)) / dt
    acorner = S[S_K_ALPHA] * math.sqrt(vdx * vdx + vdy * vdy) * rd
    for k in range(nw):
        wvx = ub - rd * wy[k]
        wvy = vb + rd * wx[k]
        dff = math.atan2(wvy, wvx) + acorner
        if dff > dmax or dff < dmin:
            dff = dmax if dff > dmax else dmin
            wff = (wvx * math.cos(dff) + wvy * math.sin(dff)) / r_w
            if wff < 0.0:
                wff = 0.0
        else:
            wff = math.sqrt(wvx * wvx + wvy * wvy) / r_w
        w = wff if twist else wff + z[base + k]
        if w < 0.0:
            w = 0.0
        elif w > w_max:
            w = w_max
        tgt = dff if twist else dff + z[base + nw + k]
        if tgt > dmax:
            tgt = dmax
        elif tgt < dmin:
            tgt = dmin
        ws = kservo * (tgt - delta[k])
        lo = ws_min
        hi = ws_max
        lo2 = (dmin - delta[k]) / dt
        hi2 = (dmax - delta[k]) / dt
        if lo2 > lo:
            lo = lo2
        if hi2 < hi:
            hi = hi2
        if lo > hi:  # numerically at a stop: hold
            lo = 0.0
            hi = 0.0
        if ws < lo:
            ws = lo
        elif ws > hi:
            ws = hi
        om_w[k] = w
        om_s[k] = ws


@njit(cache=True, inline="always", error_model="numpy")
def _solve3(a, bb, c, d, e, f, g, h, i, b0, b1, b2):
    """Solve the 3x3 system [[a, bb, c], [d, e, f], [g, h, i]] x = (b0, b1, b2) by
    Cramer's rule (the matrix is well conditioned here)."""
    det = a * (e * i - f * h) - bb * (d * i - f * g) + c * (d * h - e * g)
    return ((b0 * (e * i - f * h) - bb * (b1 * i - f * b2) + c * (b1 * h - e * b2)) / det,
            (a * (b1 * i - f * b2) - b0 * (d * i - f * g) + c * (d * b2 - b1 * g)) / det,
            (a * (e * b2 - b1 * h) - bb * (d * b2 - b1 * g) + b0 * (d * h - e * g)) / det)


# ---- the prediction's tire models: forces in W_ij and their velocity Jacobian ----------
@njit(**_INLINE)
def _tire_mf(vwx, vwy, omw, FN, P):
    """Magic Formula forces (eq. 9-12) of one wheel and their Jacobian K with respect to
    the wheel velocity: ``(Fx, Fy, dFx/dvwx, dFx/dvwy, dFy/dvwx, dFy/dvwy)``."""
    r_w, v_eps = P[P_WHEEL_RADIUS], P[P_V_EPS]
    sl = slip_ratio(omw, r_w, vwx, v_eps)  # eq. (10)
    al = slip_angle(vwx, vwy, v_eps)  # eq. (9)
    ds_dx, da_dx, da_dy = slip_jacobian(omw, r_w, vwx, vwy, v_eps)
    Fx, dFx_ds = magic_formula_and_slope(sl, P[P_LON_B], P[P_LON_C], P[P_LON_MU] * FN,
                                         P[P_LON_E])  # eq. (11)
    Fy, dFy_da = magic_formula_and_slope(al, P[P_LAT_B], P[P_LAT_C], P[P_LAT_MU] * FN,
                                         P[P_LAT_E])  # eq. (12)
    return Fx, Fy, dFx_ds * ds_dx, 0.0, dFy_da * da_dx, dFy_da * da_dy


@njit(**_INLINE)
def _tire_dugoff(vwx, vwy, omw, FN, P):
    """As :func:`_tire_mf` with Dugoff's forces (DH baseline); the Jacobian by central
    differences in (s, alpha)."""
    r_w, v_eps = P[P_WHEEL_RADIUS], P[P_V_EPS]
    C_s, C_a, mu = P[P_DUGOFF_C_S], P[P_DUGOFF_C_ALPHA], P[P_DUGOFF_MU]
    sl = slip_ratio(omw, r_w, vwx, v_eps)
    al = slip_angle(vwx, vwy, v_eps)
    ds_dx, da_dx, da_dy = slip_jacobian(omw, r_w, vwx, vwy, v_eps)
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


# ---- one prediction step per motion model ----------------------------------------------
# The steps take and return the pose and velocity as scalars and keep their 3x3 systems in
# scalars: every array argument of an inlined function costs a reference-count pair per
# call, which at 2 axles was 10 % of the prediction.
@njit(**_INLINE)
def _rigid_body_step(model, x, y, phi, vx, vy, r, delta, om_w, om_s, vref, P, wx, wy, dt, FN):
    """One linearly implicit trapezoidal step of the rigid body with tire forces (eq. 4, 5,
    17; the module's DEVIATION) from pose ``(x, y, phi)`` and velocity ``(vx, vy, r)`` (in
    G), the tire model chosen by ``model`` (MF, Dugoff, or TCT: MF lateral forces only, the
    longitudinal speed held at the reference speed ``vref``). Returns the new pose and
    velocity and the step's wear powers: ``(x, y, phi, vx, vy, r, P_s, P_alpha)``
    (eq. 13, 14)."""
    m, Iz, r_w = P[P_MASS], P[P_YAW_INERTIA], P[P_WHEEL_RADIUS]
    c = math.cos(phi)
    s = math.sin(phi)
    ub = c * vx + s * vy
    vb = -s * vx + c * vy
    ps = 0.0
    pa = 0.0
    # A = sum_j Lw^T R K R^T Lw (the tire forces' Jacobian), F = sum_j Lw^T R F_W
    a00 = a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = 0.0
    f0 = f1 = f2 = 0.0
    tct = model == MODEL_TCT
    if tct:
        ub = vref  # TCT (Tang et al. 2024): longitudinal speed held at the reference speed
    for j in range(wx.shape[0]):
        # forces at the step's mid steering angle (the wheel turns during the step; using
        # the start angle delays the steering by dt / 2)
        dm = delta[j] + 0.5 * dt * om_s[j]
        cd = math.cos(dm)
        sd = math.sin(dm)
        xw = wx[j]
        yw = wy[j]
        vwx, vwy = wheel_velocity(ub, vb, r, xw, yw, dm)  # eq. (6)-(8)
        if model == MODEL_DUGOFF:
            Fx, Fy, k11, k12, k21, k22 = _tire_dugoff(vwx, vwy, om_w[j], FN, P)
        else:
            Fx, Fy, k11, k12, k21, k22 = _tire_mf(vwx, vwy, om_w[j], FN, P)
        ps += wear_power_slip(Fx, om_w[j], r_w, vwx)  # eq. (13)
        pa += wear_power_angle(Fy, vwy)  # eq. (14)
        if tct:
            Fx = 0.0  # lateral dynamics only
            k11 = 0.0
            k12 = 0.0
        # generalised force (F_Bx, F_By, M_z) = Lw^T R(delta) F_W
        fbx, fby = wheel_to_body(Fx, Fy, dm)  # eq. (4)
        f0 += fbx
        f1 += fby
        f2 += xw * fby - yw * fbx  # eq. (5)
        # Jacobian: Lw^T R K R^T Lw, K = d(Fx, Fy)/d(vwx, vwy); M = R K R^T
        b11 = cd * k11 - sd * k21
        b12 = cd * k12 - sd * k22
        b21 = sd * k11 + cd * k21
        b22 = sd * k12 + cd * k22
        m11 = b11 * cd - b12 * sd
        m12 = b11 * sd + b12 * cd
        m21 = b21 * cd - b22 * sd
        m22 = b21 * sd + b22 * cd
        # Lw = [[1, 0, -y], [0, 1, x]]
        a00 += m11
        a01 += m12
        a02 += -m11 * yw + m12 * xw
        a10 += m21
        a11 += m22
        a12 += -m21 * yw + m22 * xw
        a20 += -yw * m11 + xw * m21
        a21 += -yw * m12 + xw * m22
        a22 += (-yw * (-m11 * yw + m12 * xw) + xw * (-m21 * yw + m22 * xw))
    # (I - THETA dt M^-1 A) du = dt M^-1 F + transport terms of the body-frame eq. (17):
    # u' = F/m + (r vb, -r ub), r' = M_z / I_vz; the transport terms enter the Jacobian too
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
    f0 = dt / m * f0 + dt * r * vb
    f1 = dt / m * f1 - dt * r * ub
    f2 = dt / Iz * f2
    if tct:
        # the longitudinal row is not modelled: no longitudinal acceleration
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
    c1 = math.cos(phi1)
    s1 = math.sin(phi1)
    vx1 = c1 * (ub + du0) - s1 * (vb + du1)  # back to G (eq. 20)
    vy1 = s1 * (ub + du0) + c1 * (vb + du1)
    return (x + 0.5 * dt * (vx + vx1), y + 0.5 * dt * (vy + vy1), phi1, vx1, vy1, r1,
            ps, pa)


@njit(**_INLINE)
def _kinematic_step(x, y, phi, delta, om_w, P, wx, wy, dt):
    """Kinematic baseline (Zhang et al. 2016): the body twist is the least-squares rigid
    motion of the commanded wheel velocities omega_w r_w (cos delta, sin delta); wheels
    roll without slip (no slip wear). Returns the new pose and velocity (forward Euler)."""
    r_w = P[P_WHEEL_RADIUS]
    nw = wx.shape[0]
    sx = 0.0
    sy = 0.0
    sxx = 0.0
    syy = 0.0
    sw1 = 0.0
    sw2 = 0.0
    sw3 = 0.0
    for j in range(nw):
        vwx = om_w[j] * r_w * math.cos(delta[j])
        vwy = om_w[j] * r_w * math.sin(delta[j])
        sx += wx[j]
        sy += wy[j]
        sxx += wx[j] * wx[j]
        syy += wy[j] * wy[j]
        sw1 += vwx
        sw2 += vwy
        sw3 += wx[j] * vwy - wy[j] * vwx
    ub, vb, r = _solve3(nw, 0.0, -sy, 0.0, nw, sx, -sy, sx, sxx + syy, sw1, sw2, sw3)
    c = math.cos(phi)
    s = math.sin(phi)
    vx = c * ub - s * vb
    vy = s * ub + c * vb
    return x + dt * vx, y + dt * vy, phi + dt * r, vx, vy, r


@njit(**_INLINE)
def _model_step(model, x, y, phi, vx, vy, r, delta, om_w, om_s, vref, P, wx, wy, dt, FN):
    """One prediction step of ``model``: ``(x, y, phi, vx, vy, r, P_s, P_alpha)``."""
    if model == MODEL_KINEMATIC:
        x, y, phi, vx, vy, r = _kinematic_step(x, y, phi, delta, om_w, P, wx, wy, dt)
        return x, y, phi, vx, vy, r, 0.0, 0.0
    return _rigid_body_step(model, x, y, phi, vx, vy, r, delta, om_w, om_s, vref, P, wx, wy,
                            dt, FN)


@njit(**_FAST)
def _simulate(model, x0, ref, z, block, P, S, wx, wy, poses, wear, cmds):
    """Predict one candidate over the horizon; fills poses (N_p, 3), wear (N_p, 3) and the
    first step's commands ``cmds`` (2, 2n)."""
    nw = wx.shape[0]
    Np = block.shape[0]
    dt = S[S_DT]
    k_t = P[P_K_T]
    FN = P[P_MASS] * P[P_G] / nw  # Assumption 2
    stride = int(S[S_STRIDE])
    x, y, phi = x0[X0_X], x0[X0_Y], x0[X0_PHI]
    vx, vy, r = x0[X0_VX], x0[X0_VY], x0[X0_R]
    X = np.empty(3)  # the pose for the policy (POSE_*)
    delta = x0[X0_DELTA:X0_DELTA + nw].copy()
    om_w = np.empty(nw)
    om_s = np.empty(nw)
    for k in range(Np):
        X[POSE_X] = x
        X[POSE_Y] = y
        X[POSE_PHI] = phi
        commands_from_policy(X, delta, ref[k], z, block[k] * stride, nw, P, S, wx, wy, dt,
                             om_w, om_s)
        if k == 0:
            for j in range(nw):
                cmds[CMD_W, j] = om_w[j]
                cmds[CMD_S, j] = om_s[j]
        pt = 0.0
        for j in range(nw):
            pt += wear_power_steer(k_t, FN, om_s[j])  # eq. (15)
        vref = math.sqrt(ref[k, REF_VX] ** 2 + ref[k, REF_VY] ** 2)
        x, y, phi, vx, vy, r, ps, pa = _model_step(model, x, y, phi, vx, vy, r, delta, om_w,
                                                   om_s, vref, P, wx, wy, dt, FN)
        for j in range(nw):
            delta[j] += dt * om_s[j]  # eq. (19)
        poses[k, POSE_X] = x
        poses[k, POSE_Y] = y
        poses[k, POSE_PHI] = phi
        wear[k, WEAR_S] = ps
        wear[k, WEAR_ALPHA] = pa
        wear[k, WEAR_T] = pt


@njit(cache=True, error_model="numpy")
def rollout_batch(model, x0, ref, Z, block, P, S, wx, wy, poses, wear, cmds):
    """Predict every candidate row of ``Z``; writes ``poses``, ``wear`` (B, N_p, 3) and the
    first commands ``cmds`` (B, 2, 2n). Serial: predictable on a shared 2-core machine."""
    for b in range(Z.shape[0]):
        _simulate(model, x0, ref, Z[b], block, P, S, wx, wy, poses[b], wear[b], cmds[b])


@njit(cache=True, parallel=True)
def rollout_batch_parallel(model, x0, ref, Z, block, P, S, wx, wy, poses, wear, cmds):
    """As :func:`rollout_batch`, candidates spread over numba's threads (prange). Faster
    on an idle machine (docs/PERFORMANCE.md); with other busy processes on the cores its
    tail latency is worse (docs/CONTROLLER.md, "Threads"). Used by
    :meth:`controller.models.PredictionModel.rollout` with ``threads > 1``; the MPC's own
    threaded path is :func:`controller.sa_kernel.evaluate_parallel`."""
    for b in prange(Z.shape[0]):
        _simulate(model, x0, ref, Z[b], block, P, S, wx, wy, poses[b], wear[b], cmds[b])


# ---- the cost: one function per term ---------------------------------------------------
@njit(cache=True, inline="always", error_model="numpy")
def tracking_cost(poses, ref, Q):
    """``sum_k (Y_k - Yt_k)^T Q (Y_k - Yt_k)`` (eq. 22-24, W_Y = E (x) Q) over the
    predicted poses, against the reference rows 1..N_p; heading error wrapped."""
    J = 0.0
    for k in range(poses.shape[0]):
        ex = poses[k, POSE_X] - ref[k + 1, REF_X]
        ey = poses[k, POSE_Y] - ref[k + 1, REF_Y]
        ep = _wrap(poses[k, POSE_PHI] - ref[k + 1, REF_PHI])
        J += Q[Q_X] * ex * ex + Q[Q_Y] * ey * ey + Q[Q_PHI] * ep * ep
    return J


@njit(cache=True, inline="always", error_model="numpy")
def wear_cost(wear, L):
    """The wear term, the powers in kW: ``sum_k P_k^T L P_k`` (eq. 22, 25, W_P = E (x) L;
    weights ``L[L_S], L[L_ALPHA], L[L_T]`` [1/kW^2]: the paper's TWO) plus the wear-energy
    term ``sum_k lambda^T P_k`` (weights ``L[LE_S], L[LE_ALPHA], L[LE_T]`` [1/kW]; over the
    horizon, times the step, it is the predicted wear work that W_tw measures: TWO-energy).
    """
    J = 0.0
    for k in range(wear.shape[0]):
        p0 = wear[k, WEAR_S] * KW
        p1 = wear[k, WEAR_ALPHA] * KW
        p2 = wear[k, WEAR_T] * KW
        J += L[L_S] * p0 * p0 + L[L_ALPHA] * p1 * p1 + L[L_T] * p2 * p2
        J += L[LE_S] * p0 + L[LE_ALPHA] * p1 + L[LE_T] * p2
    return J


@njit(cache=True, inline="always", error_model="numpy")
def smoothing_cost(z, zprev, R, stride, nsplit):
    """Changes of the decision variables between consecutive blocks (``stride`` variables
    each) and from the previous solution's first block ``zprev``: R_dw on the first
    ``nsplit`` of a block (wheel speeds [1/(rad/s)^2]; all three twist offsets), R_dd on
    the rest (steering targets [1/rad^2]; raw steering rates)."""
    J = 0.0
    for blk in range(z.shape[0] // stride):
        for j in range(stride):
            prev = zprev[j] if blk == 0 else z[(blk - 1) * stride + j]
            dz = z[blk * stride + j] - prev
            J += (R[R_DW] if j < nsplit else R[R_DD]) * dz * dz
    return J


@njit(cache=True, inline="always", error_model="numpy")
def ridge_cost(z, R, stride, nsplit):
    """A ridge on the decision variables themselves: R_ow on the first ``nsplit`` of a
    block, R_od on the rest (as :func:`smoothing_cost`; raw commands get none)."""
    J = 0.0
    for blk in range(z.shape[0] // stride):
        for j in range(stride):
            zi = z[blk * stride + j]
            J += (R[R_OW] if j < nsplit else R[R_OD]) * zi * zi
    return J


@njit(cache=True, error_model="numpy")
def candidate_cost(poses, wear, ref, z, zprev, Q, L, R, stride, nsplit):
    """Cost of one candidate (paper eq. 22-26) plus the shared command regularisation.

    ``poses``, ``wear`` (N_p, 3) of the candidate, ``z`` (D,) its decision vector in
    blocks of ``stride`` (the first ``nsplit`` of each weighted as wheel speeds):
    ``(tracking + wear) / N_p + smoothing + ridge`` (:func:`tracking_cost`,
    :func:`wear_cost`, :func:`smoothing_cost`, :func:`ridge_cost`; weights ``Q``, ``L``
    (``plant.layout.L_*``, ``LE_*``), ``R = (R_dw, R_dd, R_ow, R_od)``).
    """
    Np = poses.shape[0]
    return ((tracking_cost(poses, ref, Q) + wear_cost(wear, L)) / Np
            + smoothing_cost(z, zprev, R, stride, nsplit) + ridge_cost(z, R, stride, nsplit))


@njit(cache=True, error_model="numpy")
def batch_cost(poses, wear, ref, Z, zprev, Q, L, R, stride, nsplit, costs):
    """:func:`candidate_cost` of every row of ``Z`` into ``costs`` (B,)."""
    for b in range(Z.shape[0]):
        costs[b] = candidate_cost(poses[b], wear[b], ref, Z[b], zprev, Q, L, R, stride, nsplit)
