"""Online adaptation of the prediction's tires (``--adapt``): cornering stiffness, longitudinal
stiffness and friction re-estimated while driving.

The offset-free disturbance (:mod:`controller.disturbance`) removes a *constant* model error;
a tire that is stiffer or softer than the file errs in proportion to its slip, so the error
changes with every curve and the disturbance lags it. The adaptation estimates three scale
factors of the prediction's Magic Formula tires,

    theta = (c_lat, c_lon, f):   B_lat = B_lat0 c_lat / f,   B_lon = B_lon0 c_lon / f,
                                  mu_lat = mu_lat0 f,         mu_lon = mu_lon0 f,

so that the cornering stiffness ``B C D`` of each curve scales with ``c`` alone and its peak
``D = mu F_N`` with ``f`` alone (a run that never reaches past the linear part of the curve
identifies ``c`` and leaves ``f`` where it was). With the Dugoff model (DH) the same three
factors scale its own cornering and longitudinal stiffnesses and its friction
(``C_alpha c_lat``, ``C_s c_lon``, ``mu f``); TCT's lateral Magic Formula as ``mf``'s (it
holds the reference's forward speed, so nothing informs ``c_lon``). Every ``W`` control
periods (``AdaptOptions.window``, default 1), from the state measured at ``t - W T``, the
commands sent in each period since and the state measured at ``t``, a Kalman filter on
``theta`` (a random walk, :class:`AdaptOptions`) takes the velocity prediction error of the
prediction model *without* the offset-free disturbance over the window,

    e = v_meas(t) - g(x(t - W T), u(t - W T), ..., u(t - T); theta),
    J = dg/dtheta (central differences),
    P <- P + Q W T;  K = P J^T (J P J^T + R)^-1;  theta <- theta + K e;  P <- (I - K J) P,

(body frame; ``R`` the velocity measurement's variance), bounded to
``[theta_min, theta_max]``; a parameter whose column of ``J`` carries less information than
``R`` in a period (``|J_i|^2 < R``: a straight line at constant speed for ``c_lat``, a run far
from the friction limit for ``f``) is not updated in that period (frozen; its covariance
kept). With noisy measurements the prediction's start carries the noise into ``g``
through the tires' response, correlated with ``J``: a window of about the tires' relaxation
time (10 periods) keeps it from biasing the factors (docs/CONTROLLER.md, "Noisy odometry");
:meth:`TireAdaptation.velocity_noise` measures the noise; when it exceeds 3x ``sigma_v``
(and 4 mm/s) the filter restarts with it as ``R`` and a window of ten periods
(``noise="auto"``, the default), or warns (``"fixed"``). The estimate goes into the model's parameters (and the feed-forward's cornering
slip gain ``m / (n C_alpha)``), so every solve after it predicts with the adapted tires; the
disturbance then removes what the three factors cannot explain.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from msagv.plant import layout as lay

from . import rollout as _ro
from .disturbance import LastPeriod, body_frame
from .models import ADAPTABLE, MODELS

NAMES = ("c_lat", "c_lon", "f")
# The velocity noise the measurements carry, estimated from their second differences over
# consecutive periods (white noise of deviation s gives them deviation s sqrt(6); a vehicle's
# own motion changes its velocity smoothly, by jerk T^2 = 1e-4 m/s in the second difference
# at 1 m/s^3 of jerk): the median of the last NOISE_SAMPLES (u's and v's: half as many
# periods), once NOISE_MIN of them are in; warned about (once) when above NOISE_WARN times
# adapt_sigma_v.
NOISE_SAMPLES, NOISE_MIN, NOISE_WARN = 400, 200, 3.0
# ``noise="auto"`` (the default): from NOISE_AUTO_MIN samples on (20 periods, 0.2 s), checked
# every NOISE_AUTO_EVERY periods, measurements noisier than NOISE_WARN times sigma_v and than
# NOISE_AUTO_FLOOR switch the filter to the measured noise (R = s^2, followed from then on)
# and to a window of at least NOISE_AUTO_WINDOW periods, the factors restarted from the prior
# (what they learnt from the noise with the wrong R is dropped). The floor is above what a
# vehicle's own motion puts into the estimate without noise (about 1e-6 m/s at a steady
# speed, up to a few mm/s starting from rest: tests/test_offset_free.py -k from_rest), so a
# noise-free run never switches and its factors are the fixed filter's to the bit.
NOISE_AUTO_MIN, NOISE_AUTO_EVERY, NOISE_AUTO_WINDOW, NOISE_AUTO_FLOOR = 40, 10, 10, 4e-3
NOISE_MODES = ("auto", "fixed")
SWITCH_KEYS = ("t", "velocity_noise", "window")  # as_dict()["noise_switch"] once it switched
# the longest window: its update predicts it seven times within one control period's solve
WINDOW_MAX = 100
# The prediction's entries the adaptation writes with the Magic Formula tires (``_apply`` and
# the feed-forward's gain): a solver that builds the prediction into its own code (IPOPT,
# acados) takes them as parameters of each solve when ``--adapt`` is on (:func:`values`).
TIRE_P = (lay.P_LAT_B, lay.P_LON_B, lay.P_LAT_MU, lay.P_LON_MU)
TIRE_S = (lay.S_K_ALPHA,)
N_TIRE = len(TIRE_P) + len(TIRE_S)


def values(model) -> np.ndarray:
    """The adapted entries' values in the model now (``TIRE_P`` then ``TIRE_S``)."""
    return np.r_[model.P[list(TIRE_P)], model.S[list(TIRE_S)]].astype(float)


def symbolic(P, S, sym):
    """``(P, S)`` as lists with the adapted entries replaced by ``sym[0..N_TIRE-1]`` (the
    symbolic parameters of a solver's generated prediction)."""
    P, S = list(P), list(S)
    for i, k in enumerate(TIRE_P):
        P[k] = sym[i]
    for i, k in enumerate(TIRE_S):
        S[k] = sym[len(TIRE_P) + i]
    return P, S


@dataclass(frozen=True)
class AdaptOptions:
    """The adaptation's filter.

    sigma_v [m/s]: standard deviation of a measured body velocity (the filter's R).
    drift [1/sqrt(s)]: how fast the true factors may wander (the random walk's Q = drift^2).
    sigma0: the factors' initial standard deviation (their prior: 1, the file's tires).
    bounds: the factors stay in [bounds[0], bounds[1]].
    window: the control periods one update compares (the module docstring).
    noise: ``"auto"``: follow the measured velocity noise when it is over NOISE_WARN times
      ``sigma_v`` and NOISE_AUTO_FLOOR (:data:`NOISE_AUTO_MIN`); ``"fixed"``: keep
      ``sigma_v`` and ``window``, and warn once.
    """

    sigma_v: float = 1e-3
    drift: float = 0.02
    sigma0: float = 0.3
    bounds: tuple[float, float] = (0.5, 2.0)
    window: int = 1
    noise: str = "auto"

    def __post_init__(self):
        if not (self.sigma_v > 0 and self.drift >= 0 and self.sigma0 > 0
                and 0 < self.bounds[0] < 1 < self.bounds[1]):
            raise ValueError("AdaptOptions: sigma_v, sigma0 > 0, drift >= 0, "
                             "0 < bounds[0] < 1 < bounds[1]")
        if not (isinstance(self.window, int) and 1 <= self.window <= WINDOW_MAX):
            raise ValueError(f"AdaptOptions: window must be a whole number of periods in "
                             f"1..{WINDOW_MAX}, got {self.window!r}")
        if self.noise not in NOISE_MODES:
            raise ValueError(f"AdaptOptions: noise must be one of {NOISE_MODES}, "
                             f"got {self.noise!r}")


class Window:
    """The prediction model over ``steps`` control periods from a measured state under the
    commands sent in each (the kernels' raw-command policy, one block a period), without
    the disturbance: the body-frame velocity at the window's end."""

    def __init__(self, model, period: float, steps: int):
        if model.model_id == _ro.MODEL_KINEMATIC:  # (its pose update is forward Euler)
            raise ValueError("the adaptation's window needs a dynamic model (mf, dugoff, tct)")
        nw = model.n_wheels
        self.model = model
        self.period = float(period)
        self.steps = int(steps)
        self.S = model.S.copy()
        self.S[lay.S_DT] = self.period
        self.S[lay.S_POLICY] = lay.POLICY_RAW
        self.S[lay.S_STRIDE] = 2 * nw
        self.S[[lay.S_DIST_U, lay.S_DIST_V, lay.S_DIST_R]] = 0.0
        self._block = np.arange(self.steps, dtype=np.int64)
        self.poses = np.empty((1, self.steps, lay.N_POSE))
        self._wear = np.empty((1, self.steps, lay.N_WEAR))
        self._cmds = np.empty((1, 2, nw))
        self.ref = np.zeros((self.steps + 1, lay.N_REF))

    def velocity(self, x0: np.ndarray, Z: np.ndarray, P: np.ndarray) -> np.ndarray:
        """``(u, v, r)`` in the body frame after the window, from ``x0`` under ``Z`` (1,
        steps * 2n: each period's omega_w then omega_s) with the parameters ``P`` (the
        reference rows :attr:`ref` set by the caller, for TCT). The velocity is read off the
        predicted poses by inverting the trapezoidal update step by step."""
        _ro.EXACT.rollout_batch(self.model.model_id, x0, self.ref, Z, self._block, P, self.S,
                                self.model.wx, self.model.wy, self.poses, self._wear,
                                self._cmds)
        T = self.period
        px, py, pphi = x0[lay.X0_X], x0[lay.X0_Y], x0[lay.X0_PHI]
        vx, vy, r = x0[lay.X0_VX], x0[lay.X0_VY], x0[lay.X0_R]
        for k in range(self.steps):
            x1, y1, phi1 = self.poses[0, k]
            vx, vy, r = 2.0 * (x1 - px) / T - vx, 2.0 * (y1 - py) / T - vy, 2.0 * (phi1 - pphi) / T - r
            px, py, pphi = x1, y1, phi1
        return body_frame(pphi, vx, vy, r)


class TireAdaptation:
    """Online estimate of the prediction model's tire factors (module docstring).

    Parameters
    ----------
    model : the controller's prediction model (its ``P`` is adapted in place).
    period : the control period T [s].
    options : :class:`AdaptOptions`.
    """

    def __init__(self, model, period: float, options: AdaptOptions | None = None):
        if model.model_id not in {MODELS[m].model_id for m in ADAPTABLE}:
            raise ValueError(f"tire adaptation needs a tire prediction model: "
                             f"{', '.join(ADAPTABLE)}")
        # the model's own parameters that --adapt scales (plant.model_params.Param.adapt):
        # (slot in P, index of the factor in theta)
        own = model.params.params if model.params is not None else ()
        self.own = tuple((lay.N_PARAMS + k, NAMES.index(p.adapt))
                         for k, p in enumerate(own) if p.adapt is not None)
        self.model = model
        self.period = float(period)
        self.options = options or AdaptOptions()
        self.P0 = model.P.copy()  # the file's tires
        self.k_alpha0 = float(model.S[lay.S_K_ALPHA])  # the feed-forward's m / (n C_alpha)
        self.window = Window(model, period, self.options.window)
        self.last = LastPeriod(period)
        self.hist: list = []  # the window's periods so far: (x0, z, ref, omega_w at start)
        self._Pk = model.P.copy()
        self.reset()

    def reset(self) -> None:
        """Back to the file's tires (theta = 1) and the prior covariance, the settings'
        filter and no noise measured."""
        self._restart()
        self.last.clear()
        self._v = deque(maxlen=2)  # the last measured body velocities (u, v), consecutive
        self._d2 = deque(maxlen=NOISE_SAMPLES)  # |second differences| of u and v
        self._n_d2 = 0
        self._t_noise = None
        self.warning = None  # (once) the measurements are noisier than adapt_sigma_v
        self.sigma_v = self.options.sigma_v  # the filter's sqrt(R) now
        self.noisy = None  # noise="auto": {t, velocity_noise, window} once it switched
        self.notice = None  # ... and what it says of it (logged once)
        if self.window.steps != self.options.window:
            self.window = Window(self.model, self.period, self.options.window)

    def _restart(self) -> None:
        """The factors back to the file's tires and their prior (the window's periods so
        far and the counts dropped): at a reset, and when ``noise="auto"`` switches."""
        self.theta = np.ones(3)
        self.cov = np.eye(3) * self.options.sigma0 ** 2
        self._apply(self.theta, self.model.P)
        self.model.S[lay.S_K_ALPHA] = self.k_alpha0
        self.hist = []
        self.updates = 0
        self.excited = np.zeros(3, dtype=np.int64)

    def _apply(self, theta, P) -> None:
        c_lat, c_lon, f = theta
        P0 = self.P0
        P[lay.P_LAT_B] = P0[lay.P_LAT_B] * c_lat / f
        P[lay.P_LON_B] = P0[lay.P_LON_B] * c_lon / f
        P[lay.P_LAT_MU] = P0[lay.P_LAT_MU] * f
        P[lay.P_LON_MU] = P0[lay.P_LON_MU] * f
        for k, i in self.own:  # the model's own (Dugoff's stiffnesses and friction)
            P[k] = P0[k] * theta[i]

    def _in_effect(self, zs: list, om_start) -> list:
        """The wheel speeds in effect over each period of the window: the commands
        themselves, or, where the vehicle file gives the wheels a first-order lag ``tau``
        ([plant] wheel_lag) and the state measured the wheels at the window's start, their
        mean over each period, ``u + (omega_k - u) (tau / T) (1 - exp(-T / tau))``, with
        ``omega_{k+1} = u + (omega_k - u) exp(-T / tau)``. The prediction model has no lag:
        without this the adaptation reads the lag as a softer longitudinal tire (``c_lon``
        at its lower bound on a vehicle whose tires are the file's). Like the body's state,
        the wheels are taken as measured at the window's start only and predicted from
        there (the speeds measured inside it would bring their noise back into the
        prediction)."""
        tau = float(self.P0[lay.P_WHEEL_LAG])
        nw = self.model.n_wheels
        if not (tau > 0 and om_start is not None and om_start.size == nw
                and np.all(np.isfinite(om_start))):
            return zs
        a = tau / self.period * -np.expm1(-self.period / tau)
        decay = np.exp(-self.period / tau)
        om = om_start.copy()
        out = []
        for z in zs:
            u = z[:nw]
            z = z.copy()
            z[:nw] = u + (om - u) * a
            om = u + (om - u) * decay
            out.append(z)
        return out

    def _velocity(self, theta, x0, Z) -> np.ndarray:
        """The body-frame velocity (u, v, r) a window after ``x0`` under the raw commands
        ``Z`` with the factors ``theta`` (no disturbance; :class:`Window`)."""
        self._apply(theta, self._Pk)
        return self.window.velocity(x0, Z, self._Pk)

    def update(self, t: float, x0: np.ndarray, omega_w=None) -> None:
        """Take the state measured at ``t`` (the MPC's state vector, and the actual wheel
        speeds ``omega_w`` where the state carries them); update the factors from the last
        period's state and command, and put them into the model's ``P``."""
        self._noise(t, x0)
        last = self.last.measured(t, x0, omega_w)
        if last is None:
            self.hist = []
            return
        self.hist.append(last)
        if len(self.hist) < self.window.steps:
            return
        hist, self.hist = self.hist, []
        xp = np.ascontiguousarray(hist[0][0])
        zs = self._in_effect([h[1] for h in hist], hist[0][3])
        Z = np.concatenate(zs).reshape(1, -1)
        for k, h in enumerate(hist):  # TCT holds the reference's forward speed
            if h[2] is not None:
                self.window.ref[k] = h[2][0]
                self.window.ref[k + 1] = h[2][1]
        g = self._velocity(self.theta, xp, Z)
        J = np.empty((3, 3))
        for i in range(3):
            h = 1e-4 * self.theta[i]
            tp, tm = self.theta.copy(), self.theta.copy()
            tp[i] += h
            tm[i] -= h
            J[:, i] = (self._velocity(tp, xp, Z) - self._velocity(tm, xp, Z)) / (2 * h)
        e = body_frame(x0[lay.X0_PHI], x0[lay.X0_VX], x0[lay.X0_VY], x0[lay.X0_R]) - g
        o = self.options
        Rn = self.sigma_v ** 2
        live = np.sum(J * J, axis=0) > Rn  # the parameters this period informs
        self.excited += live
        if not live.any():
            return
        idx = np.flatnonzero(live)
        Jl = J[:, idx]
        P = (self.cov[np.ix_(idx, idx)]
             + np.eye(len(idx)) * o.drift ** 2 * self.period * self.window.steps)
        S = Jl @ P @ Jl.T + np.eye(3) * Rn
        K = P @ Jl.T @ np.linalg.inv(S)
        th = self.theta.copy()
        th[idx] = np.clip(th[idx] + K @ e, o.bounds[0], o.bounds[1])
        P = (np.eye(len(idx)) - K @ Jl) @ P
        self.cov[np.ix_(idx, idx)] = 0.5 * (P + P.T)
        self.theta = th
        self.updates += 1
        self._apply(self.theta, self.model.P)
        # the feed-forward's steady cornering slip angle follows the cornering stiffness
        self.model.S[lay.S_K_ALPHA] = self.k_alpha0 / self.theta[0]

    def _noise(self, t: float, x0: np.ndarray) -> None:
        """Take the body velocity measured at ``t`` into the noise estimate
        (:data:`NOISE_SAMPLES`); a gap in the periods restarts the differences."""
        v = body_frame(x0[lay.X0_PHI], x0[lay.X0_VX], x0[lay.X0_VY], x0[lay.X0_R])[:2]
        if self._t_noise is None or abs((t - self._t_noise) - self.period) > 0.25 * self.period:
            self._v.clear()
        self._t_noise = t
        if len(self._v) == 2:
            self._d2.extend(np.abs(v - 2.0 * self._v[1] + self._v[0]))
            self._n_d2 += 1
        self._v.append(v)
        o = self.options
        if o.noise == "auto":
            self._follow_noise(t)
            return
        if self.warning is not None or self._n_d2 % 50:  # (a median every 50 periods)
            return
        s = self.velocity_noise()
        if s is not None and s > NOISE_WARN * self.options.sigma_v:
            self.warning = (
                f"--adapt: the measured velocities carry about {s:.3g} m/s of noise, "
                f"{s / self.options.sigma_v:.0f}x adapt_sigma_v ({self.options.sigma_v:g} "
                f"m/s): the tire factors follow the noise (docs/CONTROLLER.md); set "
                f"adapt_sigma_v={s:.2g} and adapt_window=10")

    def _follow_noise(self, t: float) -> None:
        """``noise="auto"``: switch to the measured noise once it is over NOISE_WARN times
        ``sigma_v`` and NOISE_AUTO_FLOOR (checked every NOISE_AUTO_EVERY periods from
        NOISE_AUTO_MIN samples on), and follow it from then on (every 50 periods; the
        switch's record keeps the noise that made it)."""
        if self._n_d2 % (50 if self.noisy is not None else NOISE_AUTO_EVERY):
            return
        s = self.velocity_noise(NOISE_AUTO_MIN)
        if s is None:
            return
        o = self.options
        if self.noisy is not None:
            self.sigma_v = max(o.sigma_v, s)
            return
        if s <= max(NOISE_WARN * o.sigma_v, NOISE_AUTO_FLOOR):
            return
        # the factors so far followed the noise with R far too small: back to the prior
        self._restart()
        self.sigma_v = s
        w = max(o.window, NOISE_AUTO_WINDOW)
        self.window = Window(self.model, self.period, w)
        self.noisy = dict(zip(SWITCH_KEYS, (float(t), s, w)))
        self.notice = (f"--adapt: the measured velocities carry about {s:.3g} m/s of noise "
                       f"(over {NOISE_WARN:g}x adapt_sigma_v {o.sigma_v:g} m/s and "
                       f"{NOISE_AUTO_FLOOR:g} m/s): the tire "
                       f"factors restart from the file's, the filter takes that noise and a "
                       f"window of {w} periods (adapt_noise=auto; docs/CONTROLLER.md)")

    def velocity_noise(self, min_samples: int = NOISE_MIN) -> float | None:
        """The measured velocities' noise [m/s] (:data:`NOISE_SAMPLES`), None before
        ``min_samples`` samples."""
        if len(self._d2) < min_samples:
            return None
        return float(1.4826 * np.median(self._d2) / np.sqrt(6.0))

    def commanded(self, om_w: np.ndarray, om_s: np.ndarray, ref: np.ndarray | None = None
                  ) -> None:
        """The command sent for the state of the last :meth:`update` (``ref``: that
        solve's reference rows, ``R[:2]`` taken)."""
        self.last.commanded(om_w, om_s, ref)

    def as_dict(self) -> dict:
        """The estimate for reports: each factor with its standard deviation, the periods
        that informed it, and the updates."""
        sd = np.sqrt(np.maximum(np.diag(self.cov), 0.0))
        out = {n: float(v) for n, v in zip(NAMES, self.theta)}
        out.update({f"{n}_sd": float(v) for n, v in zip(NAMES, sd)})
        out.update({f"{n}_excited": int(v) for n, v in zip(NAMES, self.excited)})
        out["updates"] = int(self.updates)
        out["window"] = int(self.window.steps)
        out["sigma_v"] = float(self.sigma_v)
        out["noise"] = self.options.noise
        out["noise_switch"] = None if self.noisy is None else dict(self.noisy)
        out["velocity_noise"] = self.velocity_noise(
            NOISE_AUTO_MIN if self.options.noise == "auto" else NOISE_MIN)
        out["warning"] = self.warning
        return out
