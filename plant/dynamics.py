"""Planar n-axle swerve-drive dynamics (paper eq. 2-8, 17-18) as compiled kernels.

Layouts (documented because the kernels take plain arrays):

* parameter vector ``P`` (float64), built by :func:`pack_params`::

    0 m [kg]        1 I_vz [kg m^2]   2 r_w [m]        3 g [m/s^2]     4 k_t [m]
    5 v_eps [m/s]   6..9 longitudinal MF (B, C, mu, E)  10..13 lateral MF (B, C, mu, E)
    14 cg_height [m]   15 wheel_lag [s]   16 steer_lag [s]   17 delta_min   18 delta_max

* wheel positions ``wx, wy`` (2n,), order 11, 12, 21, 22, ...

* plant state ``y`` (9 + 6n,)::

    0 x, 1 y, 2 phi, 3 vx, 4 vy, 5 r            (velocities in G, eq. 20)
    6 .. 6+2n              delta_ij
    6+2n, +1, +2           W_s, W_alpha, W_t    (wear work, integrated exactly)
    9+2n .. 9+4n           actual wheel speed   (only used with wheel_lag > 0)
    9+4n .. 9+6n           actual steering rate (only used with steer_lag > 0)

* per-wheel auxiliary outputs ``aux`` (2n, N_AUX), columns given by ``AUX_*``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .tire import magic_formula, slip_angle, slip_ratio, wheel_velocity
from .vehicle import G_ACCEL, Vehicle
from .tire import V_EPS_DEFAULT

N_PARAMS = 19
AUX_VWX, AUX_VWY, AUX_S, AUX_ALPHA, AUX_FX, AUX_FY, AUX_FN, AUX_DDELTA = range(8)
AUX_PS, AUX_PALPHA, AUX_PT, AUX_OMEGA_W = 8, 9, 10, 11
N_AUX = 12


def pack_params(vehicle: Vehicle, v_eps: float = V_EPS_DEFAULT) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(P, wx, wy)`` for the kernels from a :class:`Vehicle`."""
    lo, la, lim, po = vehicle.tire_longitudinal, vehicle.tire_lateral, vehicle.limits, vehicle.plant
    P = np.array([
        vehicle.mass, vehicle.yaw_inertia, vehicle.wheel_radius, G_ACCEL, vehicle.steer_loss_kt,
        v_eps, lo.B, lo.C, lo.mu, lo.E, la.B, la.C, la.mu, la.E,
        po.cg_height, po.wheel_lag, po.steer_lag, lim.delta_min, lim.delta_max,
    ], dtype=np.float64)
    return P, np.ascontiguousarray(vehicle.wheel_x), np.ascontiguousarray(vehicle.wheel_y)


def state_size(n_wheels: int) -> int:
    return 9 + 3 * n_wheels


@njit(cache=True)
def _tire_pass(y, om_w, om_s, FN, P, wx, wy, aux):
    """Slips, forces (eq. 9-12) and wear powers (eq. 13-15) of every wheel for given loads.

    Returns the summed force and moment in B (eq. 5): (F_Bx, F_By, M_z).
    """
    nw = wx.shape[0]
    phi, vx, vy, r = y[2], y[3], y[4], y[5]
    c, s = np.cos(phi), np.sin(phi)
    vbx = c * vx + s * vy  # body velocity in B (R(phi)^T of eq. 2)
    vby = -s * vx + c * vy
    r_w, k_t, v_eps = P[2], P[4], P[5]
    dmin, dmax = P[17], P[18]
    fbx = 0.0
    fby = 0.0
    mz = 0.0
    for k in range(nw):
        d = y[6 + k]
        vwx, vwy = wheel_velocity(vbx, vby, r, wx[k], wy[k], d)
        sl = slip_ratio(om_w[k], r_w, vwx, v_eps)
        al = slip_angle(vwx, vwy, v_eps)
        Fx = magic_formula(sl, P[6], P[7], P[8] * FN[k], P[9])    # eq. (11)
        Fy = magic_formula(al, P[10], P[11], P[12] * FN[k], P[13])  # eq. (12)
        cd, sd = np.cos(d), np.sin(d)
        Fbx = cd * Fx - sd * Fy  # eq. (4)
        Fby = sd * Fx + cd * Fy
        fbx += Fbx
        fby += Fby
        mz += wx[k] * Fby - wy[k] * Fbx  # eq. (5)
        # steering stop: a wheel at its limit stops turning (no rate into the stop)
        dd = om_s[k]
        if (d >= dmax and dd > 0.0) or (d <= dmin and dd < 0.0):
            dd = 0.0
        aux[k, 0] = vwx
        aux[k, 1] = vwy
        aux[k, 2] = sl
        aux[k, 3] = al
        aux[k, 4] = Fx
        aux[k, 5] = Fy
        aux[k, 6] = FN[k]
        aux[k, 7] = dd
        aux[k, 8] = abs(Fx * (om_w[k] * r_w - vwx))  # eq. (13)
        aux[k, 9] = abs(Fy * vwy)                    # eq. (14)
        aux[k, 10] = abs(k_t * FN[k] * dd)           # eq. (15), actual rate
        aux[k, 11] = om_w[k]
    return fbx, fby, mz


@njit(cache=True)
def evaluate(y, u_w, u_s, P, wx, wy, aux, dy):
    """Right-hand side dy/dt of the plant state; fills ``aux`` with per-wheel outputs."""
    nw = wx.shape[0]
    m, Iz, g = P[0], P[1], P[3]
    h_cg, tau_w, tau_s = P[14], P[15], P[16]
    iw = 6 + nw
    ilw = 9 + nw
    ils = 9 + 2 * nw
    om_w = np.empty(nw)
    om_s = np.empty(nw)
    for k in range(nw):
        if tau_w > 0.0:
            om_w[k] = y[ilw + k]
            dy[ilw + k] = (u_w[k] - y[ilw + k]) / tau_w
        else:
            om_w[k] = u_w[k]
            dy[ilw + k] = 0.0
        if tau_s > 0.0:
            om_s[k] = y[ils + k]
            dy[ils + k] = (u_s[k] - y[ils + k]) / tau_s
        else:
            om_s[k] = u_s[k]
            dy[ils + k] = 0.0
    FN = np.empty(nw)
    fn0 = m * g / nw  # Assumption 2: F_N = m g / (2n)
    for k in range(nw):
        FN[k] = fn0
    fbx, fby, mz = _tire_pass(y, om_w, om_s, FN, P, wx, wy, aux)
    if h_cg > 0.0:
        # Quasi-static load transfer (plant-only option, the paper's future work): the
        # minimum-norm linear load distribution that balances the pitch and roll moments
        # m h a of the CG acceleration in B; one fixed-point pass (forces -> accel ->
        # loads -> forces). Loads are floored at 0 (a lifted wheel carries nothing).
        ax = fbx / m
        ay = fby / m
        xbar = 0.0
        for k in range(nw):
            xbar += wx[k]
        xbar /= nw
        sxx = 0.0
        syy = 0.0
        for k in range(nw):
            sxx += (wx[k] - xbar) ** 2
            syy += wy[k] ** 2
        for k in range(nw):
            dF = -m * h_cg * ay * wy[k] / syy
            if sxx > 0.0:
                dF += -m * h_cg * ax * (wx[k] - xbar) / sxx
            FN[k] = max(fn0 + dF, 0.0)
        fbx, fby, mz = _tire_pass(y, om_w, om_s, FN, P, wx, wy, aux)
    phi = y[2]
    c, s = np.cos(phi), np.sin(phi)
    dy[0] = y[3]  # eq. (21) in continuous time
    dy[1] = y[4]
    dy[2] = y[5]
    dy[3] = (c * fbx - s * fby) / m  # eq. (17): R(phi) F_B / m
    dy[4] = (s * fbx + c * fby) / m
    dy[5] = mz / Iz
    ps = 0.0
    pa = 0.0
    pt = 0.0
    for k in range(nw):
        dy[6 + k] = aux[k, 7]  # eq. (19) in continuous time, with the steering stop
        ps += aux[k, 8]
        pa += aux[k, 9]
        pt += aux[k, 10]
    dy[iw] = ps  # eq. (16), integrated: W = int P dt (eq. 28-30 without sampling)
    dy[iw + 1] = pa
    dy[iw + 2] = pt


# Dormand-Prince 5(4) tableau (Dormand & Prince 1980), as MATLAB's ode45.
_C2, _C3, _C4, _C5 = 1 / 5, 3 / 10, 4 / 5, 8 / 9
_A21 = 1 / 5
_A31, _A32 = 3 / 40, 9 / 40
_A41, _A42, _A43 = 44 / 45, -56 / 15, 32 / 9
_A51, _A52, _A53, _A54 = 19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729
_A61, _A62, _A63, _A64, _A65 = 9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656
_B1, _B3, _B4, _B5, _B6 = 35 / 384, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84
_E1, _E3, _E4, _E5, _E6, _E7 = (71 / 57600, -71 / 16695, 71 / 1920, -17253 / 339200,
                                22 / 525, -1 / 40)


@njit(cache=True)
def integrate(y, t0, t1, u_w, u_s, P, wx, wy, rtol, atol, h_init, max_steps, stats):
    """Integrate the plant state ``y`` in place from t0 to t1 with inputs held.

    Adaptive Dormand-Prince 5(4) with the usual error control (mixed rel/abs tolerance,
    RMS norm, safety 0.9, step ratio in [0.2, 5]). Steering angles are clipped to their
    stops after each accepted step. Returns the step size to try next time;
    ``stats`` receives (accepted, rejected) counts.
    """
    n = y.shape[0]
    nw = wx.shape[0]
    aux = np.empty((nw, 12))
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    k5 = np.empty(n)
    k6 = np.empty(n)
    k7 = np.empty(n)
    yt = np.empty(n)
    y5 = np.empty(n)
    dmin, dmax = P[17], P[18]
    t = t0
    h = h_init if h_init > 0.0 else (t1 - t0)
    evaluate(y, u_w, u_s, P, wx, wy, aux, k1)
    nacc = 0
    nrej = 0
    while t < t1 and nacc + nrej < max_steps:
        last = False
        if t + h >= t1 - 1e-14 * max(1.0, abs(t1)):
            h_try = t1 - t
            last = True
        else:
            h_try = h
        for i in range(n):
            yt[i] = y[i] + h_try * _A21 * k1[i]
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k2)
        for i in range(n):
            yt[i] = y[i] + h_try * (_A31 * k1[i] + _A32 * k2[i])
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k3)
        for i in range(n):
            yt[i] = y[i] + h_try * (_A41 * k1[i] + _A42 * k2[i] + _A43 * k3[i])
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k4)
        for i in range(n):
            yt[i] = y[i] + h_try * (_A51 * k1[i] + _A52 * k2[i] + _A53 * k3[i] + _A54 * k4[i])
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k5)
        for i in range(n):
            yt[i] = y[i] + h_try * (_A61 * k1[i] + _A62 * k2[i] + _A63 * k3[i]
                                    + _A64 * k4[i] + _A65 * k5[i])
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k6)
        for i in range(n):
            y5[i] = y[i] + h_try * (_B1 * k1[i] + _B3 * k3[i] + _B4 * k4[i]
                                    + _B5 * k5[i] + _B6 * k6[i])
        evaluate(y5, u_w, u_s, P, wx, wy, aux, k7)
        err = 0.0
        for i in range(n):
            e = h_try * (_E1 * k1[i] + _E3 * k3[i] + _E4 * k4[i] + _E5 * k5[i]
                         + _E6 * k6[i] + _E7 * k7[i])
            sc = atol + rtol * max(abs(y[i]), abs(y5[i]))
            err += (e / sc) ** 2
        err = np.sqrt(err / n)
        if err <= 1.0:
            t = t1 if last else t + h_try
            for i in range(n):
                y[i] = y5[i]
            clipped = False
            for k in range(nw):
                if y[6 + k] > dmax:
                    y[6 + k] = dmax
                    clipped = True
                elif y[6 + k] < dmin:
                    y[6 + k] = dmin
                    clipped = True
            if clipped:
                evaluate(y, u_w, u_s, P, wx, wy, aux, k1)
            else:
                for i in range(n):
                    k1[i] = k7[i]  # first same as last
            nacc += 1
            fac = 5.0 if err == 0.0 else min(5.0, max(0.2, 0.9 * err ** -0.2))
            if not last:
                h = h_try * fac
            else:
                h = max(h, h_try * fac) if h_try < h else h_try * fac
        else:
            nrej += 1
            h = h_try * max(0.2, 0.9 * err ** -0.2)
    stats[0] = nacc
    stats[1] = nrej
    return h


@njit(cache=True)
def outputs(y, u_w, u_s, P, wx, wy, aux):
    """Per-wheel outputs at state ``y`` (fills ``aux``); returns the derivative too."""
    dy = np.empty(y.shape[0])
    evaluate(y, u_w, u_s, P, wx, wy, aux, dy)
    return dy
