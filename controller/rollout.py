"""Batch rollout kernels: many candidate decision vectors predicted at once (numba).

Layouts
-------
``x0`` (6 + 2n,): ``x, y, phi, vx, vy, r`` (velocities in G, eq. 20) then ``delta_ij``.

``ref`` (N_p + 1, 6): reference ``x, y, phi, vx, vy, r`` at ``t0 + k dt``, k = 0..N_p.

``Z`` (B, D), ``D = n_blocks * 4n``: per move block b, per wheel k, the offsets
``Z[b*4n + k] = d_omega_w`` [rad/s] and ``Z[b*4n + 2n + k] = d_delta`` [rad] from the
kinematic feed-forward (see :func:`commands_from_policy`). Step k of the horizon uses
block ``block[k]``; blocks after N_c repeat the last one (controls held after N_c).

``P`` is the plant's parameter vector (:func:`plant.dynamics.pack_params`); ``S`` the
controller settings vector built by :func:`controller.models.pack_settings`::

    0 dt [s]        1 K_servo [1/s]   2 K_pos [1/s]     3 K_phi [1/s]
    4 v_fb_max [m/s]  5 r_fb_max [rad/s]  6 omega_w_max   7 omega_s_min   8 omega_s_max
    9 delta_min    10 delta_max      11 Dugoff C_s [N]  12 Dugoff C_alpha [N/rad]
    13 Dugoff mu    14 k_alpha [s^2/m... rad per (m/s)(rad/s)]: cornering feed-forward gain

Outputs: ``poses`` (B, N_p, 3) predicted ``x, y, phi`` at k+1, and ``wear`` (B, N_p, 3)
the wear powers ``P_s, P_alpha, P_t`` [W] over step k (eq. 16).

Models (``model`` argument), all sharing the policy and the rigid-body structure:

* ``MODEL_MF`` (0): the paper's model, eq. (17)-(21) with Magic Formula tires.
* ``MODEL_DUGOFF`` (1): DH baseline, the same rigid body with Dugoff tires.
* ``MODEL_KINEMATIC`` (2): Kinematic baseline, pure rolling (no slip, no forces).
* ``MODEL_TCT`` (3): TCT baseline, lateral and yaw dynamics only, longitudinal speed held
  at the reference speed.

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
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from plant.tire import dugoff_forces

MODEL_MF, MODEL_DUGOFF, MODEL_KINEMATIC, MODEL_TCT = 0, 1, 2, 3
N_SETTINGS = 15
THETA = 0.5


@njit(cache=True, inline="always", error_model="numpy")
def _wrap(a):
    """Angle wrapped to (-pi, pi]."""
    return a - 2.0 * math.pi * math.ceil((a - math.pi) / (2.0 * math.pi))


@njit(cache=True, fastmath=True, error_model="numpy")
def commands_from_policy(x, delta, refk, z, base, nw, P, S, wx, wy, dt,
                         om_w, om_s):
    """Wheel-speed and steering-rate commands of the policy at one state (eq. 27 bounds).

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
    that delta stays inside its limits after ``dt``. ``x = (x, y, phi)``.
    """
    r_w = P[2]
    phi = x[2]
    ex = refk[0] - x[0]
    ey = refk[1] - x[1]
    cx = S[2] * ex
    cy = S[2] * ey
    cn = math.sqrt(cx * cx + cy * cy)
    if cn > S[4]:
        cx *= S[4] / cn
        cy *= S[4] / cn
    vdx = refk[3] + cx
    vdy = refk[4] + cy
    cr = S[3] * _wrap(refk[2] - phi)
    if cr > S[5]:
        cr = S[5]
    elif cr < -S[5]:
        cr = -S[5]
    rd = refk[5] + cr
    c = math.cos(phi)
    s = math.sin(phi)
    ub = c * vdx + s * vdy
    vb = -s * vdx + c * vdy
    kservo = (1.0 - math.exp(-S[1] * dt)) / dt
    dmin, dmax = S[9], S[10]
    acorner = S[14] * math.sqrt(vdx * vdx + vdy * vdy) * rd
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
        w = wff + z[base + k]
        if w < 0.0:
            w = 0.0
        elif w > S[6]:
            w = S[6]
        tgt = dff + z[base + nw + k]
        if tgt > dmax:
            tgt = dmax
        elif tgt < dmin:
            tgt = dmin
        ws = kservo * (tgt - delta[k])
        lo = S[7]
        hi = S[8]
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


@njit(cache=True, error_model="numpy")
def _solve3(A, b, out):
    """Solve the 3x3 system A out = b by Cramer's rule (A well conditioned here)."""
    a, bb, c = A[0, 0], A[0, 1], A[0, 2]
    d, e, f = A[1, 0], A[1, 1], A[1, 2]
    g, h, i = A[2, 0], A[2, 1], A[2, 2]
    det = a * (e * i - f * h) - bb * (d * i - f * g) + c * (d * h - e * g)
    out[0] = (b[0] * (e * i - f * h) - bb * (b[1] * i - f * b[2]) + c * (b[1] * h - e * b[2])) / det
    out[1] = (a * (b[1] * i - f * b[2]) - b[0] * (d * i - f * g) + c * (d * b[2] - b[1] * g)) / det
    out[2] = (a * (e * b[2] - b[1] * h) - bb * (d * b[2] - b[1] * g) + b[0] * (d * h - e * g)) / det


@njit(cache=True, fastmath=True, error_model="numpy")
def _mf_and_slope(xi, B, C, D, E):
    """Magic Formula value and slope sharing their transcendental terms (same maths as
    plant.tire.magic_formula / magic_formula_slope)."""
    Bx = B * xi
    arg = Bx - E * (Bx - math.atan(Bx)) if E != 0.0 else Bx
    ca = C * math.atan(arg)
    darg = B * (1.0 - E) + E * B / (1.0 + Bx * Bx)
    return D * math.sin(ca), D * math.cos(ca) * C * darg / (1.0 + arg * arg)


@njit(cache=True, fastmath=True, error_model="numpy")
def _tire_wheel(model, vwx, vwy, omw, FN, P, S, out):
    """Forces and their velocity Jacobian for one wheel in W_ij.

    out = (Fx, Fy, dFx/dvwx, dFx/dvwy, dFy/dvwx, dFy/dvwy, slip s, slip angle alpha).
    """
    r_w, v_eps = P[2], P[5]
    d2 = vwx * vwx + v_eps * v_eps
    d = math.sqrt(d2)
    sl = (omw * r_w - vwx) / d  # eq. (10), regularised as plant.tire.slip_ratio
    al = -math.atan(vwy / d)  # eq. (9), = plant.tire.slip_angle since d > 0
    ds_dx = -1.0 / d - (omw * r_w - vwx) * vwx / (d2 * d)
    q = d2 + vwy * vwy
    da_dx = vwy * vwx / (d * q)
    da_dy = -d / q
    if model == 1:  # Dugoff: Jacobian by central differences in (s, alpha)
        Fx, Fy = dugoff_forces(sl, al, FN, S[11], S[12], S[13])
        hs = 1e-6 + 1e-6 * abs(sl)
        ha = 1e-7 + 1e-6 * abs(al)
        fxp, fyp = dugoff_forces(sl + hs, al, FN, S[11], S[12], S[13])
        fxm, fym = dugoff_forces(sl - hs, al, FN, S[11], S[12], S[13])
        dFx_ds = (fxp - fxm) / (2 * hs)
        dFy_ds = (fyp - fym) / (2 * hs)
        fxp, fyp = dugoff_forces(sl, al + ha, FN, S[11], S[12], S[13])
        fxm, fym = dugoff_forces(sl, al - ha, FN, S[11], S[12], S[13])
        dFx_da = (fxp - fxm) / (2 * ha)
        dFy_da = (fyp - fym) / (2 * ha)
    else:
        Fx, dFx_ds = _mf_and_slope(sl, P[6], P[7], P[8] * FN, P[9])
        Fy, dFy_da = _mf_and_slope(al, P[10], P[11], P[12] * FN, P[13])
        dFx_da = 0.0
        dFy_ds = 0.0
    out[0] = Fx
    out[1] = Fy
    out[2] = dFx_ds * ds_dx + dFx_da * da_dx
    out[3] = dFx_da * da_dy
    out[4] = dFy_ds * ds_dx + dFy_da * da_dx
    out[5] = dFy_da * da_dy
    out[6] = sl
    out[7] = al


@njit(cache=True, fastmath=True, error_model="numpy")
def _simulate(model, x0, ref, z, block, P, S, wx, wy, poses, wear, cmds):
    """Predict one candidate over the horizon; fills poses (N_p, 3), wear (N_p, 3) and the
    first step's commands ``cmds`` (2, 2n)."""
    nw = wx.shape[0]
    Np = block.shape[0]
    dt = S[0]
    m, Iz, r_w, g, k_t = P[0], P[1], P[2], P[3], P[4]
    FN = m * g / nw  # Assumption 2
    X = np.empty(3)
    V = np.empty(3)
    X[0], X[1], X[2] = x0[0], x0[1], x0[2]
    V[0], V[1], V[2] = x0[3], x0[4], x0[5]
    delta = x0[6:6 + nw].copy()
    om_w = np.empty(nw)
    om_s = np.empty(nw)
    tw = np.empty(8)
    A = np.empty((3, 3))
    F = np.empty(3)
    du = np.empty(3)
    for k in range(Np):
        base = block[k] * 2 * nw
        commands_from_policy(X, delta, ref[k], z, base, nw, P, S, wx, wy, dt, om_w, om_s)
        if k == 0:
            for j in range(nw):
                cmds[0, j] = om_w[j]
                cmds[1, j] = om_s[j]
        phi = X[2]
        c = math.cos(phi)
        s = math.sin(phi)
        ub = c * V[0] + s * V[1]
        vb = -s * V[0] + c * V[1]
        r = V[2]
        ps = 0.0
        pa = 0.0
        pt = 0.0
        for j in range(nw):
            pt += abs(k_t * FN * om_s[j])  # eq. (15)
        if model == 2:
            # Kinematic (Zhang et al. 2016): the body twist is the least-squares rigid
            # motion of the commanded wheel velocities omega_w r_w (cos delta, sin delta);
            # wheels roll without slip, so P_s = P_alpha = 0.
            sx = 0.0
            sy = 0.0
            sxx = 0.0
            syy = 0.0
            sxw = 0.0
            syw = 0.0
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
            A[0, 0] = nw
            A[0, 1] = 0.0
            A[0, 2] = -sy
            A[1, 0] = 0.0
            A[1, 1] = nw
            A[1, 2] = sx
            A[2, 0] = -sy
            A[2, 1] = sx
            A[2, 2] = sxx + syy
            F[0] = sw1
            F[1] = sw2
            F[2] = sw3
            _solve3(A, F, du)
            V[0] = c * du[0] - s * du[1]
            V[1] = s * du[0] + c * du[1]
            V[2] = du[2]
            X[0] += dt * V[0]
            X[1] += dt * V[1]
            X[2] += dt * V[2]
        else:
            # rigid body with tire forces (eq. 4, 5, 17), linearly implicit in the velocity
            for i in range(3):
                F[i] = 0.0
                for jj in range(3):
                    A[i, jj] = 0.0
            tct = model == 3
            if tct:
                # TCT (Tang et al. 2024): longitudinal speed held at the reference speed
                ub = math.sqrt(ref[k, 3] ** 2 + ref[k, 4] ** 2)
            for j in range(nw):
                # forces at the step's mid steering angle (the wheel turns during the
                # step; using the start angle delays the steering by dt / 2)
                dm = delta[j] + 0.5 * dt * om_s[j]
                cd = math.cos(dm)
                sd = math.sin(dm)
                vbx_w = ub - r * wy[j]  # eq. (6)
                vby_w = vb + r * wx[j]  # eq. (7)
                vwx = cd * vbx_w + sd * vby_w  # eq. (8)
                vwy = -sd * vbx_w + cd * vby_w
                _tire_wheel(model, vwx, vwy, om_w[j], FN, P, S, tw)
                Fx, Fy = tw[0], tw[1]
                ps += abs(Fx * (om_w[j] * r_w - vwx))  # eq. (13)
                pa += abs(Fy * vwy)  # eq. (14)
                if tct:
                    Fx = 0.0  # lateral dynamics only
                    tw[2] = 0.0
                    tw[3] = 0.0
                # generalised force (F_Bx, F_By, M_z) = Lw^T R(delta) F_W
                fbx = cd * Fx - sd * Fy
                fby = sd * Fx + cd * Fy
                F[0] += fbx
                F[1] += fby
                F[2] += wx[j] * fby - wy[j] * fbx
                # Jacobian: Lw^T R K R^T Lw, K = d(Fx, Fy)/d(vwx, vwy)
                k11, k12, k21, k22 = tw[2], tw[3], tw[4], tw[5]
                # M = R K R^T
                a11 = cd * k11 - sd * k21
                a12 = cd * k12 - sd * k22
                a21 = sd * k11 + cd * k21
                a22 = sd * k12 + cd * k22
                m11 = a11 * cd - a12 * sd
                m12 = a11 * sd + a12 * cd
                m21 = a21 * cd - a22 * sd
                m22 = a21 * sd + a22 * cd
                # Lw = [[1, 0, -y], [0, 1, x]]
                yw = wy[j]
                xw = wx[j]
                A[0, 0] += m11
                A[0, 1] += m12
                A[0, 2] += -m11 * yw + m12 * xw
                A[1, 0] += m21
                A[1, 1] += m22
                A[1, 2] += -m21 * yw + m22 * xw
                A[2, 0] += -yw * m11 + xw * m21
                A[2, 1] += -yw * m12 + xw * m22
                A[2, 2] += (-yw * (-m11 * yw + m12 * xw) + xw * (-m21 * yw + m22 * xw))
            for i in range(3):
                inv = 1.0 / Iz if i == 2 else 1.0 / m
                for jj in range(3):
                    A[i, jj] = -THETA * dt * inv * A[i, jj]
                A[i, i] += 1.0
                F[i] = dt * inv * F[i]
            # body-frame form of eq. (17): u' = F/m + (r vb, -r ub), r' = M_z / I_vz; the
            # transport terms enter the Jacobian too
            F[0] += dt * r * vb
            F[1] -= dt * r * ub
            A[0, 1] -= THETA * dt * r
            A[0, 2] -= THETA * dt * vb
            A[1, 0] += THETA * dt * r
            A[1, 2] += THETA * dt * ub
            if tct:
                # the longitudinal row is not modelled: no longitudinal acceleration
                A[0, 0] = 1.0
                A[0, 1] = 0.0
                A[0, 2] = 0.0
                F[0] = 0.0
            _solve3(A, F, du)
            v0x, v0y, v0r = V[0], V[1], V[2]
            r1 = r + du[2]
            # DEVIATION(eq. 21): trapezoidal heading and position updates (mean of old and
            # new velocity); eq. (21)'s old velocity alone misplaces a vehicle turning at
            # speed by ~v r dt / 2 per step (41 cm over 1 s at 35 km/h with dt = 0.1 s)
            X[2] += 0.5 * dt * (r + r1)
            c1 = math.cos(X[2])
            s1 = math.sin(X[2])
            V[0] = c1 * (ub + du[0]) - s1 * (vb + du[1])  # back to G (eq. 20)
            V[1] = s1 * (ub + du[0]) + c1 * (vb + du[1])
            V[2] = r1
            X[0] += 0.5 * dt * (v0x + V[0])
            X[1] += 0.5 * dt * (v0y + V[1])
        for j in range(nw):
            delta[j] += dt * om_s[j]  # eq. (19)
        poses[k, 0] = X[0]
        poses[k, 1] = X[1]
        poses[k, 2] = X[2]
        wear[k, 0] = ps
        wear[k, 1] = pa
        wear[k, 2] = pt


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


@njit(cache=True, error_model="numpy")
def candidate_cost(poses, wear, ref, z, zprev, Q, L, R, nw):
    """Cost of one candidate (paper eq. 22-26) plus the shared command regularisation.

    ``poses``, ``wear`` (N_p, 3) of the candidate, ``z`` (D,) its decision vector.
    ``J = sum_k (Y_k - Yt_k)^T Q (Y_k - Yt_k) + P_k^T L P_k`` (eq. 22, W_Y = E (x) Q,
    W_P = E (x) L, P the wear powers in kW so L has usable magnitudes), heading error
    wrapped to (-pi, pi]; plus ``R = (R_dw, R_dd, R_ow, R_od)``: smoothness of the offsets
    between consecutive blocks and against the previous solution's first block
    (``zprev``), weighted R_dw [1/(rad/s)^2] for wheel speeds and R_dd [1/rad^2] for
    angles, and a ridge R_ow, R_od on the offsets themselves. The tracking and wear sum
    is divided by N_p; the regularisation is added unscaled.
    """
    Np = poses.shape[0]
    nb = z.shape[0] // (2 * nw)
    J = 0.0
    for k in range(Np):
        ex = poses[k, 0] - ref[k + 1, 0]
        ey = poses[k, 1] - ref[k + 1, 1]
        ep = _wrap(poses[k, 2] - ref[k + 1, 2])
        J += Q[0] * ex * ex + Q[1] * ey * ey + Q[2] * ep * ep
        p0 = wear[k, 0] * 1e-3
        p1 = wear[k, 1] * 1e-3
        p2 = wear[k, 2] * 1e-3
        J += L[0] * p0 * p0 + L[1] * p1 * p1 + L[2] * p2 * p2
    reg = 0.0
    for blk in range(nb):
        for j in range(2 * nw):
            zi = z[blk * 2 * nw + j]
            prev = zprev[j] if blk == 0 else z[(blk - 1) * 2 * nw + j]
            dz = zi - prev
            if j < nw:
                reg += R[0] * dz * dz + R[2] * zi * zi
            else:
                reg += R[1] * dz * dz + R[3] * zi * zi
    return J / Np + reg


@njit(cache=True, error_model="numpy")
def batch_cost(poses, wear, ref, Z, zprev, Q, L, R, nw, costs):
    """:func:`candidate_cost` of every row of ``Z`` into ``costs`` (B,)."""
    for b in range(Z.shape[0]):
        costs[b] = candidate_cost(poses[b], wear[b], ref, Z[b], zprev, Q, L, R, nw)
