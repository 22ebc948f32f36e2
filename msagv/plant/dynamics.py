"""Planar n-axle swerve-drive dynamics (paper eq. 2-8, 17-18) as compiled kernels.

The kernels take plain arrays; their layouts are named in :mod:`plant.layout`: the
parameter vector ``P`` (built by :func:`pack_params`), the plant state ``y`` (``Y_*``,
:func:`~plant.layout.y_wear`, ...) and the per-wheel outputs ``aux`` (``AUX_*``). Wheel
positions ``wx, wy`` (nw,) are in the order 11, 12, 21, 22, ... The tire, slip and wear
equations are those of :mod:`plant.tire`, inlined.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from . import layout as lay
from .layout import (AUX_ALPHA, AUX_DDELTA, AUX_FN, AUX_FX, AUX_FY, AUX_OMEGA_W,  # noqa: F401
                     AUX_PALPHA, AUX_PS, AUX_PT, AUX_S, AUX_VWX, AUX_VWY, N_AUX, N_PARAMS,
                     P_CG_HEIGHT, P_COMBINED_SLIP, P_DELTA_MAX, P_DELTA_MIN, P_G, P_K_T, P_LAT_B,
                     P_LAT_C, P_LAT_E, P_LAT_MU, P_LON_B, P_LON_C, P_LON_E, P_LON_MU, P_MASS,
                     P_OMEGA_S_MAX, P_OMEGA_S_MIN,
                     P_OMEGA_W_MAX, P_STEER_LAG, P_V_EPS, P_WHEEL_LAG, P_WHEEL_RADIUS,
                     P_YAW_INERTIA, WEAR_ALPHA, WEAR_S, WEAR_T, Y_DELTA, Y_PHI, Y_R, Y_VX,
                     Y_VY, Y_X, Y_Y, n_error_states, state_size, y_omega_s, y_omega_w,
                     y_wear, y_wheel_wear)
from . import tire
from .tire import (V_EPS_DEFAULT, combined_slip_weights, magic_formula, slip_angle, slip_ratio, wear_power_angle,
                   wear_power_slip, wear_power_steer, wheel_to_body, wheel_velocity)
from .vehicle import G_ACCEL, Vehicle

# stale-cache guard (plant.layout): the layout and the inlined tire functions
_STAMP = lay.kernel_stamp(tire.__file__)


@njit(cache=True)
def _layout_stamp():
    return _STAMP


lay.drop_stale_cache(_layout_stamp, _STAMP, __file__)


def pack_params(vehicle: Vehicle, v_eps: float = V_EPS_DEFAULT) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(P, wx, wy)`` for the kernels from a :class:`Vehicle` (``P``: every value of the
    vehicle the plant uses once, layout ``plant.layout.P_*``; a prediction model appends
    its own parameters, ``controller.models.PredictionModel.pack``)."""
    lo, la = vehicle.tire_longitudinal, vehicle.tire_lateral
    lim, po = vehicle.limits, vehicle.plant
    P = np.full(N_PARAMS, np.nan)
    P[P_MASS] = vehicle.mass
    P[P_YAW_INERTIA] = vehicle.yaw_inertia
    P[P_WHEEL_RADIUS] = vehicle.wheel_radius
    P[P_G] = G_ACCEL
    P[P_K_T] = vehicle.steer_loss_kt
    P[P_V_EPS] = v_eps
    P[[P_LON_B, P_LON_C, P_LON_MU, P_LON_E]] = lo.B, lo.C, lo.mu, lo.E
    P[[P_LAT_B, P_LAT_C, P_LAT_MU, P_LAT_E]] = la.B, la.C, la.mu, la.E
    P[P_OMEGA_W_MAX] = lim.omega_w_max
    P[P_OMEGA_S_MIN] = lim.omega_s_min
    P[P_OMEGA_S_MAX] = lim.omega_s_max
    P[P_DELTA_MIN] = lim.delta_min
    P[P_DELTA_MAX] = lim.delta_max
    P[P_CG_HEIGHT] = po.cg_height
    P[P_WHEEL_LAG] = po.wheel_lag
    P[P_STEER_LAG] = po.steer_lag
    P[P_COMBINED_SLIP] = po.combined_slip
    return P, np.ascontiguousarray(vehicle.wheel_x), np.ascontiguousarray(vehicle.wheel_y)


@njit(cache=True)
def _tire_pass(y, om_w, om_s, FN, P, wx, wy, aux):
    """Slips, forces (eq. 9-12) and wear powers (eq. 13-15) of every wheel for given loads.

    Returns the summed force and moment in B (eq. 5): (F_Bx, F_By, M_z).
    """
    nw = wx.shape[0]
    phi, vx, vy, r = y[Y_PHI], y[Y_VX], y[Y_VY], y[Y_R]
    c, s = np.cos(phi), np.sin(phi)
    vbx = c * vx + s * vy  # body velocity in B (R(phi)^T of eq. 2)
    vby = -s * vx + c * vy
    r_w, k_t, v_eps = P[P_WHEEL_RADIUS], P[P_K_T], P[P_V_EPS]
    dmin, dmax = P[P_DELTA_MIN], P[P_DELTA_MAX]
    combined = P[P_COMBINED_SLIP] > 0.0
    fbx = 0.0
    fby = 0.0
    mz = 0.0
    for k in range(nw):
        d = y[Y_DELTA + k]
        vwx, vwy = wheel_velocity(vbx, vby, r, wx[k], wy[k], d)
        sl = slip_ratio(om_w[k], r_w, vwx, v_eps)
        al = slip_angle(vwx, vwy, v_eps)
        Fx = magic_formula(sl, P[P_LON_B], P[P_LON_C], P[P_LON_MU] * FN[k], P[P_LON_E])  # eq. (11)
        Fy = magic_formula(al, P[P_LAT_B], P[P_LAT_C], P[P_LAT_MU] * FN[k], P[P_LAT_E])  # eq. (12)
        if combined:  # plant-only option: the forces of eq. (11), (12) interact
            g_x, g_y = combined_slip_weights(sl, al)
            Fx *= g_x
            Fy *= g_y
        Fbx, Fby = wheel_to_body(Fx, Fy, d)  # eq. (4)
        fbx += Fbx
        fby += Fby
        mz += wx[k] * Fby - wy[k] * Fbx  # eq. (5)
        # steering stop: a wheel at its limit stops turning (no rate into the stop)
        dd = om_s[k]
        if (d >= dmax and dd > 0.0) or (d <= dmin and dd < 0.0):
            dd = 0.0
        aux[k, AUX_VWX] = vwx
        aux[k, AUX_VWY] = vwy
        aux[k, AUX_S] = sl
        aux[k, AUX_ALPHA] = al
        aux[k, AUX_FX] = Fx
        aux[k, AUX_FY] = Fy
        aux[k, AUX_FN] = FN[k]
        aux[k, AUX_DDELTA] = dd
        aux[k, AUX_PS] = wear_power_slip(Fx, om_w[k], r_w, vwx)  # eq. (13)
        aux[k, AUX_PALPHA] = wear_power_angle(Fy, vwy)  # eq. (14)
        aux[k, AUX_PT] = wear_power_steer(k_t, FN[k], dd)  # eq. (15), actual rate
        aux[k, AUX_OMEGA_W] = om_w[k]
    return fbx, fby, mz


@njit(cache=True, inline="always")
def _lagged(u, actual, tau):
    """A command ``u`` behind a first-order lag with state ``actual``: ``(the value in
    effect, d actual/dt)``; without a lag the command itself and 0."""
    if tau > 0.0:
        return actual, (u - actual) / tau
    return u, 0.0


@njit(cache=True)
def evaluate(y, u_w, u_s, P, wx, wy, aux, dy):
    """Right-hand side dy/dt of the plant state; fills ``aux`` with per-wheel outputs."""
    nw = wx.shape[0]
    m, Iz, g = P[P_MASS], P[P_YAW_INERTIA], P[P_G]
    h_cg, tau_w, tau_s = P[P_CG_HEIGHT], P[P_WHEEL_LAG], P[P_STEER_LAG]
    iw = y_wear(nw)
    ilw = y_omega_w(nw)
    ils = y_omega_s(nw)
    om_w = np.empty(nw)
    om_s = np.empty(nw)
    for k in range(nw):
        om_w[k], dy[ilw + k] = _lagged(u_w[k], y[ilw + k], tau_w)
        om_s[k], dy[ils + k] = _lagged(u_s[k], y[ils + k], tau_s)
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
    phi = y[Y_PHI]
    c, s = np.cos(phi), np.sin(phi)
    dy[Y_X] = y[Y_VX]  # eq. (21) in continuous time
    dy[Y_Y] = y[Y_VY]
    dy[Y_PHI] = y[Y_R]
    dy[Y_VX] = (c * fbx - s * fby) / m  # eq. (17): R(phi) F_B / m
    dy[Y_VY] = (s * fbx + c * fby) / m
    dy[Y_R] = mz / Iz
    ps = 0.0
    pa = 0.0
    pt = 0.0
    for k in range(nw):
        dy[Y_DELTA + k] = aux[k, AUX_DDELTA]  # eq. (19) in continuous time, with the stop
        ps += aux[k, AUX_PS]
        pa += aux[k, AUX_PALPHA]
        pt += aux[k, AUX_PT]
        ik = y_wheel_wear(nw, k)  # each wheel's own wear work (eq. 13-15 integrated)
        dy[ik + WEAR_S] = aux[k, AUX_PS]
        dy[ik + WEAR_ALPHA] = aux[k, AUX_PALPHA]
        dy[ik + WEAR_T] = aux[k, AUX_PT]
    dy[iw + WEAR_S] = ps  # eq. (16), integrated: W = int P dt (eq. 28-30 without sampling)
    dy[iw + WEAR_ALPHA] = pa
    dy[iw + WEAR_T] = pt


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

    The per-wheel wear work (the tail of ``y`` from ``n_error_states``) is integrated with
    the same steps but is not in the error norm, and the stages skip it (no right-hand
    side reads wear work): the dynamics and the totals step exactly as without it.
    """
    n = y.shape[0]
    nw = wx.shape[0]
    ne = n_error_states(nw)  # the stages' and the error norm's states
    aux = np.empty((nw, N_AUX))
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    k5 = np.empty(n)
    k6 = np.empty(n)
    k7 = np.empty(n)
    yt = np.empty(n)
    y5 = np.empty(n)
    dmin, dmax = P[P_DELTA_MIN], P[P_DELTA_MAX]
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
        for i in range(ne):
            yt[i] = y[i] + h_try * _A21 * k1[i]
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k2)
        for i in range(ne):
            yt[i] = y[i] + h_try * (_A31 * k1[i] + _A32 * k2[i])
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k3)
        for i in range(ne):
            yt[i] = y[i] + h_try * (_A41 * k1[i] + _A42 * k2[i] + _A43 * k3[i])
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k4)
        for i in range(ne):
            yt[i] = y[i] + h_try * (_A51 * k1[i] + _A52 * k2[i] + _A53 * k3[i] + _A54 * k4[i])
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k5)
        for i in range(ne):
            yt[i] = y[i] + h_try * (_A61 * k1[i] + _A62 * k2[i] + _A63 * k3[i]
                                    + _A64 * k4[i] + _A65 * k5[i])
        evaluate(yt, u_w, u_s, P, wx, wy, aux, k6)
        for i in range(n):
            y5[i] = y[i] + h_try * (_B1 * k1[i] + _B3 * k3[i] + _B4 * k4[i]
                                    + _B5 * k5[i] + _B6 * k6[i])
        evaluate(y5, u_w, u_s, P, wx, wy, aux, k7)
        err = 0.0
        for i in range(ne):
            e = h_try * (_E1 * k1[i] + _E3 * k3[i] + _E4 * k4[i] + _E5 * k5[i]
                         + _E6 * k6[i] + _E7 * k7[i])
            sc = atol + rtol * max(abs(y[i]), abs(y5[i]))
            err += (e / sc) ** 2
        err = np.sqrt(err / ne)
        if err <= 1.0:
            t = t1 if last else t + h_try
            for i in range(n):
                y[i] = y5[i]
            clipped = False
            for k in range(Y_DELTA, Y_DELTA + nw):
                if y[k] > dmax:
                    y[k] = dmax
                    clipped = True
                elif y[k] < dmin:
                    y[k] = dmin
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
