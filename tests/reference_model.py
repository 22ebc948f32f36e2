"""An independent pure-numpy reference of the paper's vehicle model (eq. 2-18), for tests.

Written from the paper, not from ``plant``: it imports neither ``plant.dynamics`` nor
``plant.tire``. It reads the vehicle only as plain data (``Vehicle.to_dict()``, the TOML
layout), builds its own wheel geometry and integrates with ``scipy.integrate.solve_ivp``.

Model (paper numbering; the regularisations are the documented ones of the plant):

* eq. (6)-(7): wheel velocity in B, ``v_Bx = u - r y_w``, ``v_By = v + r x_w``
* eq. (8): into W_ij, ``[v_wx, v_wy] = R(delta)^T [v_Bx, v_By]``
* eq. (9): ``alpha = -atan2(v_wy, sqrt(v_wx^2 + v_eps^2))``
* eq. (10): ``s = (omega_w r_w - v_wx) / sqrt(v_wx^2 + v_eps^2)``
* eq. (11)-(12): Magic Formula, ``D = mu F_N``, ``F_N = m g / (2n)``
* eq. (4)-(5): forces into B, sums, yaw moment ``x_w F_By - y_w F_Bx``
* eq. (17): ``[xdd, ydd] = R(phi) F_B / m``, ``phidd = M_z / I_vz``
* eq. (19) in continuous time: ``delta_dot = omega_s``
* eq. (13)-(15): wear powers, integrated into the work ``W_s, W_alpha, W_t``

State ``z`` (frame="global", the paper's): ``x, y, phi, vx, vy, r`` (velocities in G),
``delta`` (2n), ``W_s, W_alpha, W_t``. With frame="body" the velocities are the body-frame
``u, v`` and Newton's law carries the Coriolis terms (``u' = F_Bx/m + r v``,
``v' = F_By/m - r u``): a second, differently written formulation of the same physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

G = 9.81  # m/s^2 (DESIGN.md)
V_EPS = 0.1  # m/s, regularisation speed of eq. (9)-(10) (plant's documented default)


@dataclass(frozen=True)
class RefVehicle:
    """The numbers the model needs, taken from a vehicle's plain-data description."""

    m: float
    I_vz: float
    r_w: float
    k_t: float
    x_w: np.ndarray  # (2n,) wheel x in B, order 11, 12, 21, 22, ...
    y_w: np.ndarray  # (2n,) wheel y in B
    lon: tuple[float, float, float, float]  # B, C, mu, E over slip ratio
    lat: tuple[float, float, float, float]  # B, C, mu, E over slip angle

    @property
    def n_wheels(self) -> int:
        return self.x_w.shape[0]

    @property
    def F_N(self) -> float:
        return self.m * G / self.n_wheels  # Assumption 2: m g / (2n)

    @classmethod
    def from_description(cls, d: dict) -> "RefVehicle":
        xs, ys = [], []
        for xi in d["axle_x"]:
            for j in (1, 2):  # j = 1 left (y > 0), j = 2 right
                xs.append(float(xi))
                ys.append(d["half_track"] if j == 1 else -d["half_track"])
        lo, la = d["tire"]["longitudinal"], d["tire"]["lateral"]
        return cls(m=d["mass"], I_vz=d["yaw_inertia"], r_w=d["wheel_radius"],
                   k_t=d["steer_loss_kt"], x_w=np.array(xs), y_w=np.array(ys),
                   lon=(lo["B"], lo["C"], lo["mu"], lo["E"]),
                   lat=(la["B"], la["C"], la["mu"], la["E"]))


def mf(xi, B, C, D, E):
    """Magic Formula f of the paper (after eq. 12)."""
    Bx = B * xi
    return D * np.sin(C * np.arctan(Bx - E * (Bx - np.arctan(Bx))))


def wheel_quantities(rv: RefVehicle, u, v, r, delta, omega_w, v_eps=V_EPS):
    """Per-wheel ``v_wx, v_wy, s, alpha, Fx, Fy`` for body velocity (u, v, r)."""
    vbx = u - r * rv.y_w  # eq. (6)
    vby = v + r * rv.x_w  # eq. (7)
    cd, sd = np.cos(delta), np.sin(delta)
    vwx = cd * vbx + sd * vby  # eq. (8) inverted: R(delta)^T
    vwy = -sd * vbx + cd * vby
    den = np.sqrt(vwx ** 2 + v_eps ** 2)
    alpha = -np.arctan2(vwy, den)  # eq. (9), regularised
    s = (omega_w * rv.r_w - vwx) / den  # eq. (10), regularised
    FN = rv.F_N
    Fx = mf(s, rv.lon[0], rv.lon[1], rv.lon[2] * FN, rv.lon[3])  # eq. (11)
    Fy = mf(alpha, rv.lat[0], rv.lat[1], rv.lat[2] * FN, rv.lat[3])  # eq. (12)
    return vwx, vwy, s, alpha, Fx, Fy


def rhs(rv: RefVehicle, z, omega_w, omega_s, frame="global", v_eps=V_EPS):
    """dz/dt of the reference state (layout in the module docstring)."""
    nw = rv.n_wheels
    phi, a, b, r = z[2], z[3], z[4], z[5]
    delta = z[6:6 + nw]
    c, s_ = math.cos(phi), math.sin(phi)
    if frame == "global":
        u, v = c * a + s_ * b, -s_ * a + c * b  # R(phi)^T [xdot_G, ydot_G]
    else:
        u, v = a, b
    vwx, vwy, s, alpha, Fx, Fy = wheel_quantities(rv, u, v, r, delta, omega_w, v_eps)
    cd, sd = np.cos(delta), np.sin(delta)
    FBx = cd * Fx - sd * Fy  # eq. (4)
    FBy = sd * Fx + cd * Fy
    Fx_sum, Fy_sum = FBx.sum(), FBy.sum()  # eq. (5)
    Mz = float(np.sum(rv.x_w * FBy - rv.y_w * FBx))
    dz = np.empty_like(z)
    if frame == "global":
        dz[0], dz[1] = a, b
        dz[3] = (c * Fx_sum - s_ * Fy_sum) / rv.m  # eq. (17)
        dz[4] = (s_ * Fx_sum + c * Fy_sum) / rv.m
    else:
        dz[0], dz[1] = c * u - s_ * v, s_ * u + c * v
        dz[3] = Fx_sum / rv.m + r * v
        dz[4] = Fy_sum / rv.m - r * u
    dz[2] = r
    dz[5] = Mz / rv.I_vz
    dz[6:6 + nw] = omega_s
    FN = rv.F_N
    dz[6 + nw] = np.sum(np.abs(Fx * (omega_w * rv.r_w - vwx)))  # eq. (13)
    dz[7 + nw] = np.sum(np.abs(Fy * vwy))  # eq. (14)
    dz[8 + nw] = np.sum(np.abs(rv.k_t * FN * omega_s))  # eq. (15)
    return dz


def initial_state(rv: RefVehicle, x=0.0, y=0.0, phi=0.0, vx=0.0, vy=0.0, r=0.0, delta=None):
    nw = rv.n_wheels
    z = np.zeros(9 + nw)
    z[:6] = (x, y, phi, vx, vy, r)
    if delta is not None:
        z[6:6 + nw] = delta
    return z


def simulate(rv: RefVehicle, z0, U_w, U_s, T=0.01, method="DOP853", rtol=1e-10, atol=1e-12,
             frame="global"):
    """Hold row k of ``U_w, U_s`` (K, 2n) over [t_k, t_k+1], restarting solve_ivp each step.

    ``T`` is the step [s], a scalar or one per row (K,). Returns Z (K+1, 9+2n): the state
    at t = 0, t_1, ..., t_K.
    """
    z = np.array(z0, dtype=float)
    K = U_w.shape[0]
    t = np.concatenate([[0.0], np.cumsum(np.broadcast_to(np.asarray(T, float), (K,)))])
    Z = np.empty((K + 1, z.size))
    Z[0] = z
    for k in range(K):
        uw, us = np.asarray(U_w[k], float), np.asarray(U_s[k], float)
        sol = solve_ivp(lambda _t, q: rhs(rv, q, uw, us, frame), (t[k], t[k + 1]), z,
                        method=method, rtol=rtol, atol=atol)
        if not sol.success:
            raise RuntimeError(f"reference integration failed at step {k}: {sol.message}")
        z = sol.y[:, -1]
        Z[k + 1] = z
    return Z


def varied_inputs(rv: RefVehicle, K, seed, T=0.01, v_mean=6.0, delta_amp=0.35,
                  omega_s_max=0.8):
    """Deterministic, varied, piecewise-constant commands ``(U_w, U_s)``, each (K, 2n).

    Wheel speeds follow a speed profile between ~0.5 v_mean and 1.5 v_mean with per-wheel
    offsets and per-step noise (so slips are non-zero); steering rates track a sinusoidal
    angle profile (front and rear axles opposite, as for a tight turn) plus noise and stay
    within ``+/-omega_s_max``. Since steering is a pure integrator, the angles reached are
    exactly ``cumsum(T * U_s)``, kept within ``+/-(delta_amp + 0.15)`` rad. ``T`` is the
    step [s], a scalar or one per row (K,).
    """
    rng = np.random.default_rng(seed)
    nw = rv.n_wheels
    Tk = np.broadcast_to(np.asarray(T, float), (K,))
    t = np.concatenate([[0.0], np.cumsum(Tk)])  # t[k] is the start of row k
    v_ref = v_mean * (1.0 + 0.5 * np.sin(2 * np.pi * t[:K] / 7.0))
    wheel_off = 1.0 + 0.02 * rng.standard_normal(nw)
    U_w = (v_ref[:, None] / rv.r_w) * wheel_off[None, :] * (1.0 + 0.01 * rng.standard_normal((K, nw)))
    U_w = np.maximum(U_w, 0.0)
    span = rv.x_w.max() - rv.x_w.min()
    sign = rv.x_w / (span / 2.0) if span > 0 else np.ones(nw)  # +1 front, -1 rear
    phase = rng.uniform(0, 2 * np.pi, nw)
    delta = np.zeros(nw)
    U_s = np.empty((K, nw))
    for k in range(K):
        target = delta_amp * (sign * np.sin(2 * np.pi * t[k + 1] / 3.0)
                              + 0.15 * np.sin(2 * np.pi * t[k + 1] / 1.3 + phase))
        w_s = (target - delta) / (5 * Tk[k]) + 0.05 * rng.standard_normal(nw)
        w_s = np.clip(w_s, -omega_s_max, omega_s_max)
        U_s[k] = w_s
        delta = delta + Tk[k] * w_s
    return U_w, U_s
