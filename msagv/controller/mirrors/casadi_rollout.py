"""MIRROR of :mod:`controller.rollout` (model 0, MF) and its cost, as a CasADi SX graph.

IPOPT needs exact first and second derivatives of the horizon problem, which numba's
kernels cannot give, so the policy, the MF prediction (linearly implicit trapezoidal
step) are written here again, operation for operation, with CasADi operations:
:func:`symbolic_rollout` mirrors the prediction of :data:`controller.rollout.EXACT` with
``model = MODEL_MF`` (:func:`_policy` mirrors ``commands_from_policy``, the tire block
``tire_forces`` with :mod:`plant.tire`'s slip, Magic Formula and wear functions). The cost
is not mirrored: :func:`symbolic_cost` calls :mod:`controller.cost_terms`' functions, the
numba kernels' own, on the CasADi expressions (and the heading wrap is
:func:`controller.cost_terms.wrap`). The indices are
:mod:`plant.layout`'s. Pinned to the numba kernels by ``tests/test_ipopt.py`` (poses,
wear powers and first commands to 1e-9 relative; the cost to 1e-9): a change to one side
that the other does not follow fails there.

Departures, for the gradient-based solver only (see :mod:`controller.ipopt`): the wear
powers' |.| is smoothed as ``sqrt(p^2 + eps^2 + TINY_W2)``; square roots of speeds that
can reach 0 get ``TINY_SQ`` under the root; atan2 at the origin is guarded.
"""

from __future__ import annotations

import math

from msagv.plant.layout import (S_DIST_R, S_DIST_U, S_DIST_V, CMD_S, CMD_W, P_DELTA_MAX,
                               P_DELTA_MIN, P_G, N_REF, P_K_T, P_LAT_B, P_LAT_C, P_LAT_E,
                               P_LAT_MU, P_LON_B, P_LON_C, P_LON_E, P_LON_MU, P_MASS,
                               P_OMEGA_S_MAX, P_OMEGA_S_MIN, P_OMEGA_W_MAX, P_V_EPS,
                               P_WHEEL_RADIUS, P_YAW_INERTIA, POSE_PHI, POSE_X, POSE_Y,
                               REF_PHI, REF_R, REF_VX, REF_VY, REF_X, REF_Y, S_DT, S_K_ALPHA,
                               S_K_PHI, S_K_POS, S_K_SERVO, S_R_FB_MAX, S_V_FB_MAX,
                               WEAR_ALPHA, WEAR_S, WEAR_T, X0_DELTA, X0_PHI, X0_R, X0_VX,
                               X0_VY, X0_X, X0_Y)

from ..cost_terms import candidate_cost, wrap as _wrap
from ..rollout import THETA

try:  # CasADi is an optional dependency (pip install msagv[ipopt])
    import casadi as ca
except ImportError:  # pragma: no cover - exercised only without casadi
    ca = None

TINY_SQ = 1e-20  # (m/s)^2 under the square roots of speeds (zero-speed derivative guard)
TINY_W2 = 1e-20  # W^2 under the smoothed |.| of the wear powers (eps_w = 0 guard)
assert CMD_W == 0 and CMD_S == 1  # the commands are returned as the pair (om_w, om_s)


def _number(v):
    """A plain float, or the CasADi expression itself (``float()`` of a symbol is NaN)."""
    return v if isinstance(v, (ca.SX, ca.MX)) else float(v)


def _sabs(p, eps):
    """|p| smoothed: sqrt(p^2 + eps^2 + TINY_W2) [W] (|p| to 1e-10 W for eps = 0, with
    finite derivatives everywhere: ``eps`` may be a CasADi parameter equal to 0)."""
    return ca.sqrt(p * p + eps * eps + TINY_W2)


def _atan2_guarded(y, x):
    """atan2(y, x), with atan2(0, 0) = 0 reached through a branch with finite derivatives
    (CasADi's atan2 derivative is 0/0 at the origin, and 0 * NaN poisons the chain rule)."""
    at0 = x * x + y * y <= 0.0
    return ca.atan2(ca.if_else(at0, 0.0, y), ca.if_else(at0, 1.0, x))


def _clip(v, lo, hi):
    return ca.fmin(ca.fmax(v, lo), hi)


def _mf_and_slope(xi, B, C, D, E):
    """Magic Formula value and slope, as plant.tire.magic_formula_and_slope."""
    Bx = B * xi
    arg = Bx - E * (Bx - ca.atan(Bx)) if E != 0.0 else Bx
    ca_ = C * ca.atan(arg)
    darg = B * (1.0 - E) + E * B / (1.0 + Bx * Bx)
    return D * ca.sin(ca_), D * ca.cos(ca_) * C * darg / (1.0 + arg * arg)


def _policy(X, delta, refk, z, base, nw, P, S, wx, wy, dt):
    """Symbolic :func:`controller.rollout.commands_from_policy`; returns (om_w, om_s) lists."""
    r_w = P[P_WHEEL_RADIUS]
    phi = X[POSE_PHI]
    cx = S[S_K_POS] * (refk[REF_X] - X[POSE_X])
    cy = S[S_K_POS] * (refk[REF_Y] - X[POSE_Y])
    cn = ca.sqrt(cx * cx + cy * cy + TINY_SQ)
    sc = ca.if_else(cn > S[S_V_FB_MAX], S[S_V_FB_MAX] / cn, 1.0)
    vdx = refk[REF_VX] + sc * cx
    vdy = refk[REF_VY] + sc * cy
    cr = _clip(S[S_K_PHI] * _wrap(refk[REF_PHI] - phi), -S[S_R_FB_MAX], S[S_R_FB_MAX])
    rd = refk[REF_R] + cr
    c = ca.cos(phi)
    s = ca.sin(phi)
    ub = c * vdx + s * vdy
    vb = -s * vdx + c * vdy
    kservo = (1.0 - math.exp(-S[S_K_SERVO] * dt)) / dt
    dmin, dmax = P[P_DELTA_MIN], P[P_DELTA_MAX]
    k_alpha = S[S_K_ALPHA]
    acorner = k_alpha * ca.sqrt(vdx * vdx + vdy * vdy + TINY_SQ) * rd \
            if isinstance(k_alpha, ca.SX) or k_alpha != 0.0 else 0.0
    om_w, om_s = [], []
    for k in range(nw):
        wvx = ub - rd * wy[k]
        wvy = vb + rd * wx[k]
        dff0 = _atan2_guarded(wvy, wvx) + acorner
        out = ca.logic_or(dff0 > dmax, dff0 < dmin)
        dff = _clip(dff0, dmin, dmax)
        wff_clip = ca.fmax((wvx * ca.cos(dff) + wvy * ca.sin(dff)) / r_w, 0.0)
        wff_free = ca.sqrt(wvx * wvx + wvy * wvy + TINY_SQ) / r_w
        wff = ca.if_else(out, wff_clip, wff_free)
        w = _clip(wff + z[base + k], 0.0, P[P_OMEGA_W_MAX])
        tgt = _clip(dff + z[base + nw + k], dmin, dmax)
        ws = kservo * (tgt - delta[k])
        lo = ca.fmax(P[P_OMEGA_S_MIN], (dmin - delta[k]) / dt)
        hi = ca.fmin(P[P_OMEGA_S_MAX], (dmax - delta[k]) / dt)
        ws = ca.if_else(lo > hi, 0.0, _clip(ws, lo, hi))
        om_w.append(w)
        om_s.append(ws)
    return om_w, om_s


def _solve3(A, b):
    """Cramer's rule, as controller.rollout._solve3."""
    a, bb, c = A[0][0], A[0][1], A[0][2]
    d, e, f = A[1][0], A[1][1], A[1][2]
    g, h, i = A[2][0], A[2][1], A[2][2]
    det = a * (e * i - f * h) - bb * (d * i - f * g) + c * (d * h - e * g)
    return ((b[0] * (e * i - f * h) - bb * (b[1] * i - f * b[2]) + c * (b[1] * h - e * b[2])) / det,
            (a * (b[1] * i - f * b[2]) - b[0] * (d * i - f * g) + c * (d * b[2] - b[1] * g)) / det,
            (a * (e * b[2] - b[1] * h) - bb * (d * b[2] - b[1] * g) + b[0] * (d * h - e * g)) / det)


def symbolic_step(X, V, delta, refk, z, base, P, S, wx, wy, eps=0.0, dist=None):
    """One step of the MF prediction (the loop body of :func:`symbolic_rollout`): from the
    pose ``X`` (x, y, phi in :mod:`plant.layout`'s POSE order), the global-frame velocity
    ``V`` (vx, vy, r) and the steering angles ``delta`` (lists of CasADi expressions), the
    reference row ``refk`` (6) and the offsets ``z[base : base + 2n]`` of the step's block.
    ``P``, ``S``, ``wx``, ``wy`` are plain numbers (entries of ``P`` and ``S`` may be CasADi
    symbols: the tires ``--adapt`` moves are parameters of a solve). Returns ``(X, V, delta, wear, cmds)``
    after the step: the new pose, velocity and angles (lists), the step's wear powers
    ``(P_s, P_alpha, P_t)`` [W] in WEAR order and its commands ``(om_w, om_s)``. ``dist``:
    the offset-free disturbance (body-frame accelerations, three numbers or expressions);
    None: ``S``'s (:data:`plant.layout.S_DIST_U` ..)."""
    nw = len(wx)
    P = [_number(p) for p in P]
    S = [_number(v) for v in S]
    dt = S[S_DT]
    m, Iz, r_w, k_t, v_eps = (P[i] for i in (P_MASS, P_YAW_INERTIA, P_WHEEL_RADIUS, P_K_T,
                                             P_V_EPS))
    FN = m * P[P_G] / nw  # Assumption 2
    wx = [float(v) for v in wx]
    wy = [float(v) for v in wy]
    th = THETA
    X = list(X)
    om_w, om_s = _policy(X, delta, refk, z, base, nw, P, S, wx, wy, dt)
    phi = X[POSE_PHI]
    c = ca.cos(phi)
    s = ca.sin(phi)
    ub = c * V[0] + s * V[1]
    vb = -s * V[0] + c * V[1]
    r = V[2]
    ps = 0.0
    pa = 0.0
    pt = 0.0
    for j in range(nw):
        pt += _sabs(k_t * FN * om_s[j], eps)  # eq. (15)
    A = [[0.0] * 3 for _ in range(3)]
    F = [0.0, 0.0, 0.0]
    for j in range(nw):
        dm = delta[j] + 0.5 * dt * om_s[j]
        cd = ca.cos(dm)
        sd = ca.sin(dm)
        vbx_w = ub - r * wy[j]  # eq. (6)
        vby_w = vb + r * wx[j]  # eq. (7)
        vwx = cd * vbx_w + sd * vby_w  # eq. (8)
        vwy = -sd * vbx_w + cd * vby_w
        # tire (controller.rollout.tire_forces, Magic Formula)
        d2 = vwx * vwx + v_eps * v_eps
        d = ca.sqrt(d2)
        slip = om_w[j] * r_w - vwx
        sl = slip / d  # eq. (10), regularised
        al = -ca.atan(vwy / d)  # eq. (9)
        ds_dx = -1.0 / d - slip * vwx / (d2 * d)
        q = d2 + vwy * vwy
        da_dx = vwy * vwx / (d * q)
        da_dy = -d / q
        Fx, dFx_ds = _mf_and_slope(sl, P[P_LON_B], P[P_LON_C], P[P_LON_MU] * FN,
                                   P[P_LON_E])  # eq. (11)
        Fy, dFy_da = _mf_and_slope(al, P[P_LAT_B], P[P_LAT_C], P[P_LAT_MU] * FN,
                                   P[P_LAT_E])  # eq. (12)
        k11, k12 = dFx_ds * ds_dx, 0.0
        k21, k22 = dFy_da * da_dx, dFy_da * da_dy
        ps += _sabs(Fx * slip, eps)  # eq. (13)
        pa += _sabs(Fy * vwy, eps)  # eq. (14)
        fbx = cd * Fx - sd * Fy
        fby = sd * Fx + cd * Fy
        F[0] += fbx
        F[1] += fby
        F[2] += wx[j] * fby - wy[j] * fbx
        a11 = cd * k11 - sd * k21
        a12 = cd * k12 - sd * k22
        a21 = sd * k11 + cd * k21
        a22 = sd * k12 + cd * k22
        m11 = a11 * cd - a12 * sd
        m12 = a11 * sd + a12 * cd
        m21 = a21 * cd - a22 * sd
        m22 = a21 * sd + a22 * cd
        yw, xw = wy[j], wx[j]
        A[0][0] += m11
        A[0][1] += m12
        A[0][2] += -m11 * yw + m12 * xw
        A[1][0] += m21
        A[1][1] += m22
        A[1][2] += -m21 * yw + m22 * xw
        A[2][0] += -yw * m11 + xw * m21
        A[2][1] += -yw * m12 + xw * m22
        A[2][2] += (-yw * (-m11 * yw + m12 * xw) + xw * (-m21 * yw + m22 * xw))
    for i in range(3):
        inv = 1.0 / Iz if i == 2 else 1.0 / m
        for jj in range(3):
            A[i][jj] = -th * dt * inv * A[i][jj]
        A[i][i] += 1.0
        F[i] = dt * inv * F[i]
    F[0] += dt * r * vb
    F[1] -= dt * r * ub
    if dist is None:
        dist = [S[S_DIST_U], S[S_DIST_V], S[S_DIST_R]]
    for i in range(3):
        F[i] += dt * dist[i]
    A[0][1] -= th * dt * r
    A[0][2] -= th * dt * vb
    A[1][0] += th * dt * r
    A[1][2] += th * dt * ub
    du = _solve3(A, F)
    v0x, v0y = V[0], V[1]
    r1 = r + du[2]
    X[POSE_PHI] = X[POSE_PHI] + 0.5 * dt * (r + r1)
    c1 = ca.cos(X[POSE_PHI])
    s1 = ca.sin(X[POSE_PHI])
    V = [c1 * (ub + du[0]) - s1 * (vb + du[1]), s1 * (ub + du[0]) + c1 * (vb + du[1]), r1]
    X[POSE_X] = X[POSE_X] + 0.5 * dt * (v0x + V[0])
    X[POSE_Y] = X[POSE_Y] + 0.5 * dt * (v0y + V[1])
    delta = [delta[j] + dt * om_s[j] for j in range(nw)]  # eq. (19)
    wk = [None] * 3
    wk[WEAR_S], wk[WEAR_ALPHA], wk[WEAR_T] = ps, pa, pt
    return X, V, delta, tuple(wk), (om_w, om_s)


def symbolic_rollout(x0, ref, z, block, P, S, wx, wy, eps=0.0, dist=None):
    """The MF prediction of one candidate, symbolically (paper eq. 9-21 with the
    DEVIATIONs of :mod:`controller.rollout`: linearly implicit trapezoidal body-frame step),
    :func:`symbolic_step` once per prediction step.

    ``x0`` (6 + 2n) and ``ref`` ((N_p + 1) x 6, indexable as ref[k, i]) and ``z`` are CasADi
    expressions; ``block``, ``P``, ``S``, ``wx``, ``wy`` plain numbers (they are baked into
    the graph). ``eps`` [W]: smoothing of |.| in eq. (13)-(15) (0: exact). ``dist``: the
    offset-free disturbance (:func:`symbolic_step`; an expression to make it a parameter).
    Returns ``(poses, wear, cmds)``: lists of N_p ``(x, y, phi)``, N_p ``(P_s, P_alpha,
    P_t)`` [W] and the first step's ``(om_w, om_s)``.
    """
    if ca is None:
        raise ImportError("symbolic_rollout needs CasADi (pip install 'msagv[ipopt]')")
    nw = len(wx)
    Np = len(block)
    X = [None] * 3
    X[POSE_X], X[POSE_Y], X[POSE_PHI] = x0[X0_X], x0[X0_Y], x0[X0_PHI]
    V = [x0[X0_VX], x0[X0_VY], x0[X0_R]]
    delta = [x0[X0_DELTA + j] for j in range(nw)]
    poses, wear, cmds = [], [], None
    for k in range(Np):
        refk = [ref[k, i] for i in range(N_REF)]
        base = int(block[k]) * 2 * nw
        X, V, delta, wk, cmd = symbolic_step(X, V, delta, refk, z, base, P, S, wx, wy, eps,
                                             dist)
        if k == 0:
            cmds = cmd
        pose = [None] * 3
        pose[POSE_X], pose[POSE_Y], pose[POSE_PHI] = X[POSE_X], X[POSE_Y], X[POSE_PHI]
        poses.append(tuple(pose))
        wear.append(wk)
    return poses, wear, cmds


# ---- the cost: controller.cost_terms' functions on the symbols ---------------------------
def symbolic_cost(poses, wear, ref, z, zprev, Q, L, R, nw):
    """Symbolic cost of one candidate (eq. 22-26 + R): :func:`controller.cost_terms.candidate_cost`
    itself, called on the CasADi expressions (``poses``, ``wear``: the lists of
    :func:`symbolic_rollout`; blocks of ``2 nw`` offsets, the first ``nw`` wheel speeds)."""
    return candidate_cost(poses, wear, ref, z, zprev, Q, L, R, 2 * nw, nw)
