"""Identifying a vehicle from what it logged: the tire, actuator and body parameters that make
the plant's own equations reproduce a recorded run (``msagv calibrate``, docs/CALIBRATE.md).

The model is the plant itself: :func:`plant.dynamics.integrate` (the same kernel, the same
parameter vector ``P``) started at the measured state at the beginning of each window of
``window`` control periods and driven by the recorded commands, held over each period as
the plant holds them. The residuals are the multi-step prediction errors over each window
of the body velocity (``u, v`` in the body frame, yaw rate ``r``), the steering angles and
the actual wheel speeds, each divided by its channel's noise level. Their sum of squares is
minimised by ``scipy.optimize.least_squares`` (trust region reflective, with bounds; the
Jacobian by finite differences).

Parameters are fitted in a well-conditioned form: each Magic Formula table as its slope
at zero slip per newton of load ``K = B C mu`` (so the cornering stiffness of a wheel is
``K F_N``, eq. 12's slope), its peak friction ``mu`` and its shapes ``C`` and ``E``
(``B = K / (C mu)``); then the actuator lags, and on request the mass and yaw inertia.
A parameter is fitted only when the run excites it (:func:`select`): its table's tire
force must rise above the noise (the measured acceleration in its direction; a straight
line at constant speed identifies no lateral parameter), a peak friction needs the fitted
model's tires past half of their peak, and its standard error must be small against its
value. Everything else keeps the base vehicle's value and is reported as not identified,
with the reason. The standard errors come from the Jacobian at the optimum,
``s^2 (J^T J)^-1``, widened for the residuals' serial correlation within a window (an
AR(1) effective sample size), and hold for the model's own structure: they do not cover a
plant whose equations differ from these.

Imports nothing of the project beyond :mod:`plant` (scipy and tqdm at call time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from . import dynamics as dyn
from . import layout as lay
from . import tire
from .layout import (AUX_FN, AUX_FX, AUX_FY, N_AUX, P_LAT_MU, P_LON_MU, P_WHEEL_LAG, Y_DELTA,
                     Y_PHI, Y_R, Y_VX, Y_VY, y_omega_s, y_omega_w)
from .vehicle import G_ACCEL, Vehicle, vehicle_from_dict

# stale-cache guard (plant.layout): this kernel compiles the dynamics' kernels into its own
_STAMP = lay.kernel_stamp(tire.__file__, dyn.__file__)


@njit(cache=True)
def _identify_stamp():
    return _STAMP


lay.drop_stale_cache(_identify_stamp, _STAMP, __file__)


class IdentifyError(ValueError):
    """Data the estimator cannot use (the message says why, in one line)."""


# ---- the data --------------------------------------------------------------------------------
@dataclass
class RunData:
    """A recorded run as arrays, one row per state ``k`` (times ``t`` strictly increasing):
    ``body`` (N, 6) ``x, y, phi, vx, vy, r`` (velocities in G, as the state message),
    ``delta`` and ``omega_w`` (N, nw) the measured steering angles and actual wheel speeds,
    ``cmd_w`` and ``cmd_s`` (N, nw) the commands held from ``t[k]`` to ``t[k+1]`` (the last
    row's are unused), ``valid`` (N,) False where a step must not be used (no command in
    effect, the plant's safe behaviour)."""

    t: np.ndarray
    body: np.ndarray
    delta: np.ndarray
    omega_w: np.ndarray
    cmd_w: np.ndarray
    cmd_s: np.ndarray
    valid: np.ndarray | None = None

    def __post_init__(self):
        self.t = np.asarray(self.t, dtype=float)
        n = self.t.size
        self.body = np.asarray(self.body, dtype=float).reshape(n, 6)
        self.delta = np.asarray(self.delta, dtype=float).reshape(n, -1)
        nw = self.delta.shape[1]
        self.omega_w = np.asarray(self.omega_w, dtype=float).reshape(n, nw)
        self.cmd_w = np.asarray(self.cmd_w, dtype=float).reshape(n, nw)
        self.cmd_s = np.asarray(self.cmd_s, dtype=float).reshape(n, nw)
        self.valid = (np.ones(n, dtype=bool) if self.valid is None
                      else np.asarray(self.valid, dtype=bool).reshape(n))

    @property
    def n(self) -> int:
        return self.t.size

    @property
    def n_wheels(self) -> int:
        return self.delta.shape[1]

    @property
    def period(self) -> float:
        return float(np.median(np.diff(self.t)))

    def check(self, vehicle: Vehicle, min_seconds: float = 2.0) -> None:
        """Refuse data the estimator cannot use, with one line: wrong wheel count, too
        short, non-finite values, times not increasing, a vehicle that never moves."""
        if self.n_wheels != vehicle.n_wheels:
            raise IdentifyError(f"the recording has {self.n_wheels} wheels, the vehicle "
                                f"{vehicle.name} {vehicle.n_wheels}")
        if self.n < 3:
            raise IdentifyError(f"the recording holds {self.n} state(s): nothing to fit")
        dt = np.diff(self.t)
        if not np.all(np.isfinite(self.t)) or np.any(dt <= 0):
            raise IdentifyError("the recorded times are not finite and strictly increasing")
        span = float(self.t[-1] - self.t[0])
        if span < min_seconds:
            raise IdentifyError(f"the recording covers {span:.2f} s of driving, too short to "
                                f"fit (at least {min_seconds:g} s)")
        for name, a in (("the states", self.body), ("the steering angles", self.delta),
                        ("the wheel speeds", self.omega_w)):
            if not np.all(np.isfinite(a)):
                k = int(np.argwhere(~np.isfinite(a))[0][0])
                raise IdentifyError(f"{name} hold NaN or inf (first at t = {self.t[k]:.3f} s)")
        used = self.valid[:-1]
        for name, a in (("wheel speed", self.cmd_w), ("steering rate", self.cmd_s)):
            if not np.all(np.isfinite(a[:-1][used])):
                raise IdentifyError(f"the {name} commands hold NaN or inf")
        speed = np.hypot(self.body[:, 3], self.body[:, 4])
        if not np.any(speed > MIN_SPEED):
            raise IdentifyError(f"the vehicle never moves faster than {MIN_SPEED:g} m/s: "
                                f"nothing to identify")


LAG_MIN = 0.001  # s: the smallest lag fitted (a fit at this bound is written as 0, no lag)
MIN_SPEED = 0.5  # m/s: windows slower than this anywhere are left out (slip regularised)


def smooth(a: np.ndarray, half: int) -> np.ndarray:
    """Centred moving average over ``2 half + 1`` rows (edges: the nearest rows repeated);
    exact on straight lines, so it adds no lag."""
    a = np.asarray(a, dtype=float)
    if half <= 0:
        return a.copy()
    pad = np.concatenate([np.repeat(a[:1], half, axis=0), a, np.repeat(a[-1:], half, axis=0)])
    c = np.cumsum(np.concatenate([np.zeros((1,) + a.shape[1:]), pad]), axis=0)
    return (c[2 * half + 1:] - c[:-2 * half - 1]) / (2 * half + 1)


def body_accelerations(data: RunData, half: int = 5) -> np.ndarray:
    """(N, 2) the measured acceleration of the centre of mass in the body frame (forward,
    left) [m/s^2]: the central difference of the smoothed global velocity, rotated into B.
    It is what the tires' summed force gives the vehicle, ``F_B = m a_B``."""
    v = smooth(data.body[:, 3:5], half)
    a = np.gradient(v, data.t, axis=0)
    a = smooth(a, half)
    phi = data.body[:, 2]
    c, s = np.cos(phi), np.sin(phi)
    return np.stack([c * a[:, 0] + s * a[:, 1], -s * a[:, 0] + c * a[:, 1]], axis=1)


# ---- the model: the plant's kernel over windows ------------------------------------------------
@njit(cache=True)
def simulate_windows(P, wx, wy, Y0, t, UW, US, starts, length, rtol, atol, out, util):
    """Integrate the plant from each window's initial state ``Y0[w]`` at ``t[starts[w]]``
    over ``length`` periods with the recorded commands held (``UW``, ``US`` rows), writing
    each period's end into ``out[w * length + i]``: ``u, v`` (body velocity), ``r``, the
    steering angles, the actual wheel speeds; and into ``util`` the largest longitudinal
    and lateral force of any wheel against its peak ``mu F_N``."""
    nw = wx.shape[0]
    stats = np.zeros(2, np.int64)
    aux = np.empty((nw, N_AUX))
    ilw = y_omega_w(nw)
    lagged = P[P_WHEEL_LAG] > 0.0
    for w in range(starts.shape[0]):
        y = Y0[w].copy()
        k0 = starts[w]
        h = 0.0
        for i in range(length):
            k = k0 + i
            uw = UW[k]
            us = US[k]
            h = dyn.integrate(y, t[k], t[k + 1], uw, us, P, wx, wy, rtol, atol, h, 200000, stats)
            dyn.outputs(y, uw, us, P, wx, wy, aux)
            row = w * length + i
            phi = y[Y_PHI]
            c, s = np.cos(phi), np.sin(phi)
            out[row, 0] = c * y[Y_VX] + s * y[Y_VY]
            out[row, 1] = -s * y[Y_VX] + c * y[Y_VY]
            out[row, 2] = y[Y_R]
            ux = 0.0
            uy = 0.0
            for j in range(nw):
                out[row, 3 + j] = y[Y_DELTA + j]
                out[row, 3 + nw + j] = y[ilw + j] if lagged else uw[j]
                fn = aux[j, AUX_FN]
                if fn > 0.0:
                    ux = max(ux, abs(aux[j, AUX_FX]) / (P[P_LON_MU] * fn))
                    uy = max(uy, abs(aux[j, AUX_FY]) / (P[P_LAT_MU] * fn))
            util[row, 0] = ux
            util[row, 1] = uy


# ---- the parameters --------------------------------------------------------------------------
# name -> (text, unit, kind); kind: "rel" (positive, scaled by its base value) or "abs"
PARAMETERS = {
    "lateral.K": ("lateral slope B C mu (cornering stiffness per newton of load)", "1/rad"),
    "longitudinal.K": ("longitudinal slope B C mu (slip stiffness per newton of load)", "-"),
    "wheel_lag": ("wheel-speed lag", "s"),
    "steer_lag": ("steering-rate lag", "s"),
    "lateral.mu": ("lateral peak friction", "-"),
    "longitudinal.mu": ("longitudinal peak friction", "-"),
    "yaw_inertia": ("yaw inertia", "kg m^2"),
    "mass": ("mass", "kg"),
    "lateral.C": ("lateral shape factor C", "-"),
    "lateral.E": ("lateral curvature factor E", "-"),
    "longitudinal.C": ("longitudinal shape factor C", "-"),
    "longitudinal.E": ("longitudinal curvature factor E", "-"),
}
ORDER = tuple(PARAMETERS)  # the order in which select() admits them
PRIMARY = ("lateral.K", "longitudinal.K", "wheel_lag", "steer_lag", "yaw_inertia")
TIRE_ONLY = ("lateral.K", "longitudinal.K", "wheel_lag", "steer_lag", "lateral.mu",
             "longitudinal.mu", "lateral.C", "lateral.E", "longitudinal.C", "longitudinal.E")

MAX_REL_SE = 0.10  # a parameter is identified when its standard error is below 10 % ...
MAX_ABS_SE = {"lateral.E": 0.1, "longitudinal.E": 0.1, "wheel_lag": 0.002, "steer_lag": 0.002}
MIN_EXCITATION = 0.05  # ... its table's force reaches 5 % of the peak (measured a / (mu g))
MIN_PEAK_REACH = 0.5  # ... and, for a peak friction, the model's tires pass half the peak
MIN_SHAPE_REACH = 0.95  # ... for a shape C or E, the tires at their peak
MIN_COMMAND_SWING = {"wheel_lag": 0.05, "steer_lag": 0.01}  # ... for a lag, commands that move
TRIAL_PEAK_REACH = 0.3  # (tried from here: the reach is measured against the current peak)


def values_of(v: Vehicle) -> dict[str, float]:
    """The parameters of :data:`PARAMETERS` of a vehicle."""
    la, lo = v.tire_lateral, v.tire_longitudinal
    return {"lateral.K": la.B * la.C * la.mu, "longitudinal.K": lo.B * lo.C * lo.mu,
            "wheel_lag": v.plant.wheel_lag, "steer_lag": v.plant.steer_lag,
            "lateral.mu": la.mu, "longitudinal.mu": lo.mu, "yaw_inertia": v.yaw_inertia,
            "mass": v.mass, "lateral.C": la.C, "lateral.E": la.E, "longitudinal.C": lo.C,
            "longitudinal.E": lo.E}


def vehicle_with(v: Vehicle, values: dict[str, float], name: str | None = None) -> Vehicle:
    """A validated copy of ``v`` with these parameter values (``B = K / (C mu)``)."""
    cur = values_of(v)
    cur.update(values)
    d = v.to_dict()
    if name:
        d["name"] = name
    before = values_of(v)
    for part in ("lateral", "longitudinal"):
        K, C, mu, E = (cur[f"{part}.{k}"] for k in ("K", "C", "mu", "E"))
        same = all(cur[f"{part}.{k}"] == before[f"{part}.{k}"] for k in ("K", "C", "mu"))
        B = d["tire"][part]["B"] if same else K / (C * mu)  # unchanged: B exactly as it was
        d["tire"][part] = {"B": B, "C": C, "mu": mu, "E": E}
    d["mass"] = cur["mass"]
    d["yaw_inertia"] = cur["yaw_inertia"]
    d["plant"] = dict(d["plant"], wheel_lag=cur["wheel_lag"], steer_lag=cur["steer_lag"])
    return vehicle_from_dict(d)


def _bounds(name: str, base: float) -> tuple[float, float, float]:
    """(lower, upper, scale) of a parameter around its base value."""
    if name.endswith(".E"):
        return -5.0, 1.0, 1.0
    if name.endswith(".C"):
        return 0.5, 3.0, max(base, 0.5)
    if name.endswith("_lag"):  # a lag far below the period is stiff and unobservable
        return LAG_MIN, 1.0, max(base, 0.05)
    return base / 4.0, base * 4.0, base


# ---- the fit ---------------------------------------------------------------------------------
@dataclass
class Estimate:
    """One parameter's result: ``value`` (the fitted value, or the base vehicle's when not
    identified), ``se`` its standard error (None when not fitted), ``identified``, and
    ``why`` (the reason it was not)."""

    name: str
    base: float
    value: float
    se: float | None
    identified: bool
    why: str = ""

    @property
    def text(self) -> str:
        return PARAMETERS[self.name][0]

    @property
    def unit(self) -> str:
        return PARAMETERS[self.name][1]


@dataclass
class Calibration:
    """The result of :func:`calibrate`: the tuned vehicle, each parameter's estimate, the
    fit's figures (``rms`` per channel before and after, ``excitation``), the measured and
    predicted channels (for a figure)."""

    vehicle: Vehicle
    base: Vehicle
    estimates: dict[str, Estimate]
    rms_before: dict[str, float]
    rms_after: dict[str, float]
    excitation: dict[str, float]
    reach: dict[str, float]
    windows: int
    seconds: float
    evaluations: int
    t: np.ndarray = field(repr=False, default=None)
    measured: np.ndarray = field(repr=False, default=None)
    predicted: np.ndarray = field(repr=False, default=None)
    predicted_base: np.ndarray = field(repr=False, default=None)

    def cornering_stiffness(self) -> list[dict]:
        """Per axle: the slopes ``B C D`` of one wheel's lateral and longitudinal force at
        zero slip [N/rad, N] (the loads are ``m g / 2n`` on every wheel, as the plant's)."""
        v = self.vehicle
        fn = v.normal_load
        out = []
        for i in range(v.n_axles):
            out.append({"axle": i + 1, "load_N": fn,
                        "cornering_stiffness_N_per_rad": self.estimates["lateral.K"].value * fn,
                        "slip_stiffness_N": self.estimates["longitudinal.K"].value * fn})
        return out

    def to_dict(self) -> dict:
        return {"vehicle": self.vehicle.name, "base": self.base.name,
                "parameters": {k: {"value": e.value, "base": e.base, "se": e.se,
                                   "identified": e.identified, "why": e.why or None,
                                   "unit": e.unit}
                               for k, e in self.estimates.items()},
                "axles": self.cornering_stiffness(), "rms_before": self.rms_before,
                "rms_after": self.rms_after, "excitation": self.excitation,
                "reach": self.reach, "windows": self.windows, "seconds": self.seconds,
                "evaluations": self.evaluations}


CHANNELS = ("u", "v", "r", "delta", "omega_w")
NOISE_FLOOR = {"u": 1e-4, "v": 1e-4, "r": 1e-5, "delta": 1e-5, "omega_w": 1e-4}
NOISE_START = {"u": 0.02, "v": 0.02, "r": 0.005, "delta": 0.002, "omega_w": 0.02}


class _Problem:
    """The windows, the measured channels and the residual function of one fit."""

    def __init__(self, data: RunData, base: Vehicle, window: int, rtol: float, smooth_half: int):
        self.data, self.base, self.window = data, base, window
        self.rtol = rtol
        nw = data.n_wheels
        self.nw = nw
        lim = base.limits
        self.UW = np.ascontiguousarray(np.clip(data.cmd_w, 0.0, lim.omega_w_max))
        self.US = np.ascontiguousarray(np.clip(data.cmd_s, lim.omega_s_min, lim.omega_s_max))
        speed = np.hypot(data.body[:, 3], data.body[:, 4])
        n = data.n
        starts = []
        for k0 in range(0, n - window, window):
            sl = slice(k0, k0 + window + 1)
            if np.all(data.valid[k0:k0 + window]) and np.all(speed[sl] > MIN_SPEED):
                starts.append(k0)
        if not starts:
            raise IdentifyError(f"no stretch of {window * data.period:.2f} s in which the vehicle "
                                f"moves faster than {MIN_SPEED:g} m/s under recorded commands")
        self.starts = np.asarray(starts, dtype=np.int64)
        # initial states from the smoothed measurements (noise in a window's start would
        # otherwise bias the fit: errors in the variables)
        sm_body = smooth(data.body, smooth_half)
        sm_delta = smooth(data.delta, smooth_half)
        sm_w = smooth(data.omega_w, smooth_half)
        rate = np.gradient(sm_delta, data.t, axis=0)
        ny = lay.state_size(nw)
        Y0 = np.zeros((len(starts), ny))
        for w, k in enumerate(starts):
            Y0[w, :6] = sm_body[k]
            Y0[w, Y_DELTA:Y_DELTA + nw] = sm_delta[k]
            Y0[w, y_omega_w(nw):y_omega_w(nw) + nw] = sm_w[k]
            Y0[w, y_omega_s(nw):y_omega_s(nw) + nw] = rate[k]
        self.Y0 = Y0
        rows = (self.starts[:, None] + np.arange(1, window + 1)[None, :]).ravel()
        self.rows = rows
        phi = data.body[rows, 2]
        c, s = np.cos(phi), np.sin(phi)
        vx, vy = data.body[rows, 3], data.body[rows, 4]
        self.measured = np.column_stack([c * vx + s * vy, -s * vx + c * vy, data.body[rows, 5],
                                         data.delta[rows], data.omega_w[rows]])
        self.groups = {"u": [0], "v": [1], "r": [2], "delta": list(range(3, 3 + nw)),
                       "omega_w": list(range(3 + nw, 3 + 2 * nw))}
        self.sigma = dict(NOISE_START)
        self.wx = np.ascontiguousarray(base.wheel_x)
        self.wy = np.ascontiguousarray(base.wheel_y)
        self.nfev = 0
        self.bar = None

    def weights(self) -> np.ndarray:
        w = np.empty(self.measured.shape[1])
        for g, cols in self.groups.items():
            w[cols] = 1.0 / self.sigma[g]
        return w

    def predict(self, vehicle: Vehicle) -> tuple[np.ndarray, np.ndarray]:
        P, _, _ = dyn.pack_params(vehicle)
        m = self.measured.shape
        out = np.empty(m)
        util = np.empty((m[0], 2))
        simulate_windows(P, self.wx, self.wy, self.Y0, self.data.t, self.UW, self.US,
                         self.starts, self.window, self.rtol, self.rtol * 0.1, out, util)
        self.nfev += 1
        if self.bar is not None:
            self.bar.update(1)
        return out, util

    def residuals(self, vehicle: Vehicle) -> np.ndarray:
        out, _ = self.predict(vehicle)
        r = (out - self.measured) * self.weights()
        r[~np.isfinite(r)] = 1e6
        return r.ravel()

    def rms(self, pred: np.ndarray) -> dict[str, float]:
        e = pred - self.measured
        return {g: float(np.sqrt(np.mean(e[:, cols] ** 2))) for g, cols in self.groups.items()}

    def reestimate_noise(self, pred: np.ndarray) -> None:
        """Each channel's noise level from the residuals of a fit (floored)."""
        for g, v in self.rms(pred).items():
            self.sigma[g] = max(v, NOISE_FLOOR[g])


def _ar1_inflation(r: np.ndarray, window: int) -> float:
    """sqrt((1 + rho) / (1 - rho)) of the residuals' lag-1 correlation within windows:
    how much serially correlated residuals widen a least-squares standard error."""
    if r.shape[0] < 2 * window:
        return 1.0
    x = r.reshape(-1, window, r.shape[1])
    a, b = x[:, 1:, :].ravel(), x[:, :-1, :].ravel()
    den = float(np.sqrt(np.dot(a, a) * np.dot(b, b)))
    rho = float(np.dot(a, b) / den) if den > 0 else 0.0
    rho = min(max(rho, 0.0), 0.98)
    return math.sqrt((1.0 + rho) / (1.0 - rho))


def gate(name: str, values, excitation, reach, peak: float = MIN_PEAK_REACH) -> str:
    """Why the run cannot identify ``name`` whatever the fit ('' when it may): its tire
    table's force stays in the noise, or (a peak friction) the tires never pass half of
    their peak."""
    part = name.split(".")[0] if "." in name else None
    if part in ("lateral", "longitudinal") and excitation[part] < MIN_EXCITATION:
        return (f"not excited: the {part} acceleration reaches {excitation[part]:.1%} of the "
                f"peak friction (needs {MIN_EXCITATION:.0%})")
    if name.endswith(".mu") and reach[part] < peak:
        return (f"not reached: the tires use at most {reach[part]:.0%} of their {part} peak "
                f"(needs {MIN_PEAK_REACH:.0%})")
    if name.endswith((".C", ".E")) and reach[part] < MIN_SHAPE_REACH:
        return (f"not reached: the tires use at most {reach[part]:.0%} of their {part} peak; "
                f"the curve's shape is told from its peak only at the peak (needs "
                f"{MIN_SHAPE_REACH:.0%})")
    if name in ("wheel_lag", "steer_lag") and excitation[name] < MIN_COMMAND_SWING[name]:
        return (f"not excited: the {'wheel speed' if name == 'wheel_lag' else 'steering rate'} "
                f"commands swing by {excitation[name]:.3g} rad/s rms within a window (needs "
                f"{MIN_COMMAND_SWING[name]:g})")
    return ""


def select(candidates, values, jac, excitation, reach, peak: float = MIN_PEAK_REACH
           ) -> tuple[dict[str, str], dict[str, float]]:
    """Which parameters the run identifies, admitted greedily in the order of
    ``candidates``: a parameter passes its :func:`gate` and its standard error, estimated
    jointly with those admitted before it, is small against its value. Returns
    ``({name: ''} for the identified, {name: reason} for the others; the standard errors of
    the identified, jointly)``. ``jac``: :func:`_jacobian`'s result for (at least) the
    candidates that pass their gate."""
    why = {p: gate(p, values, excitation, reach, peak) for p in candidates}
    admitted: list[str] = []
    for p in candidates:
        if why[p]:
            continue
        se = _se(jac, admitted + [p])
        s, v = se[p], values[p]
        lim = max(MAX_REL_SE * abs(v), MAX_ABS_SE.get(p, 0.0))
        if not math.isfinite(s):
            why[p] = "not excited: the run does not change the prediction with it"
        elif s > lim:
            why[p] = f"poorly excited: standard error {s:.3g} against {v:.4g} (needs <= {lim:.3g})"
        else:
            admitted.append(p)
    return why, (_se(jac, admitted) if admitted else {})


def calibrate(data: RunData, base: Vehicle, *, fit_body: bool = False, window: int = 50,
              rtol: float = 1e-7, max_rounds: int = 4, max_nfev: int = 40,
              smooth_half: int = 2, progress: bool = False, name: str | None = None
              ) -> Calibration:
    """Fit ``base``'s tire, lag (and with ``fit_body`` mass and yaw inertia) parameters to a
    run: see the module docstring. Raises :class:`IdentifyError` for data it cannot use."""
    from scipy.optimize import least_squares

    data.check(base)
    if window < 2:
        raise IdentifyError(f"the window must be at least 2 periods, got {window}")
    prob = _Problem(data, base, window, rtol, smooth_half)
    candidates = [p for p in ORDER if fit_body or p in TIRE_ONLY]
    base_values = values_of(base)
    values = dict(base_values)
    acc = body_accelerations(data, smooth_half)
    moving = np.zeros(data.n, dtype=bool)
    moving[prob.rows] = True
    g = G_ACCEL
    excitation = {
        "longitudinal": float(np.percentile(np.abs(acc[moving, 0]), 99)) / (
            base.tire_longitudinal.mu * g),
        "lateral": float(np.percentile(np.abs(acc[moving, 1]), 99)) / (base.tire_lateral.mu * g)}
    # how much the commands move within the windows (a lag shows only when they do)
    for key, cmd in (("wheel_lag", prob.UW), ("steer_lag", prob.US)):
        c = cmd[(prob.starts[:, None] + np.arange(window)[None, :]).ravel()]
        c = c.reshape(len(prob.starts), window, -1)
        excitation[key] = float(np.sqrt(np.mean((c - c.mean(axis=1, keepdims=True)) ** 2)))
    if progress:
        from tqdm import tqdm

        prob.bar = tqdm(desc="msagv calibrate", unit=" sim", total=None, leave=False)
    try:
        pred0, util0 = prob.predict(base)
        rms_before = prob.rms(pred0)
        reach = {"longitudinal": float(np.percentile(util0[:, 0], 99.5)),
                 "lateral": float(np.percentile(util0[:, 1], 99.5))}
        active: list[str] = []
        se: dict[str, float] = {}
        why: dict[str, str] = {}
        # a first fit of the slopes and lags the run excites (their standard errors at the
        # base values would measure the base vehicle's misfit, not the data's noise) ...
        first = [p for p in PRIMARY if p in candidates and not gate(p, values, excitation, reach)]
        fitted = False
        for _ in range(max_rounds):
            if not fitted and first:
                active = first
            else:
                # ... then what the run identifies at the current fit, admitted by their
                # standard errors
                # (a peak friction is tried from TRIAL_PEAK_REACH: the reach is measured
                # against the current peak, which may be the base vehicle's, too high)
                trial = [p for p in candidates
                         if not gate(p, values, excitation, reach, TRIAL_PEAK_REACH)]
                jac = _jacobian(prob, base, values, trial)
                why, se = select(candidates, values, jac, excitation, reach, TRIAL_PEAK_REACH)
                new = [p for p in candidates if not why[p]]
                if fitted and new == active:
                    break
                active = new
            if not active:
                break
            values.update(_fit(prob, base, values, base_values, active, max_nfev, least_squares))
            fitted = True
            pred, util = prob.predict(vehicle_with(base, values))
            prob.reestimate_noise(pred)
            reach = {"longitudinal": float(np.percentile(util[:, 0], 99.5)),
                     "lateral": float(np.percentile(util[:, 1], 99.5))}
        for _ in range(2):  # the verdict at the optimum; what fails it is dropped, refitted
            if not fitted or not active:
                break
            jac = _jacobian(prob, base, values, active)
            why2, se = select(active, values, jac, excitation, reach)
            why.update(why2)
            keep = [p for p in active if not why2[p]]
            if keep == active:
                break
            for p in active:
                if p not in keep:
                    values[p] = base_values[p]
            active = keep
            if active:
                values.update(_fit(prob, base, values, base_values, active, max_nfev,
                                   least_squares))
        for p in candidates:  # anything not identified keeps the base value
            if why[p]:
                values[p] = base_values[p]
        tuned = vehicle_with(base, values, name=name)
        pred, _ = prob.predict(tuned)
    finally:
        if prob.bar is not None:
            prob.bar.close()
    estimates = {}
    for p in ORDER:
        if p in candidates:
            estimates[p] = Estimate(p, base_values[p], values[p], se.get(p) if not why[p] else None,
                                    not why[p], why[p])
        else:
            estimates[p] = Estimate(p, base_values[p], base_values[p], None, False,
                                    "not fitted (--fit-body fits the mass and yaw inertia)")
    return Calibration(
        vehicle=tuned, base=base, estimates=estimates, rms_before=rms_before,
        rms_after=prob.rms(pred), excitation=excitation, reach=reach,
        windows=len(prob.starts), seconds=len(prob.starts) * window * data.period,
        evaluations=prob.nfev, t=data.t[prob.rows], measured=prob.measured, predicted=pred,
        predicted_base=pred0)


def _vector(values, names):
    return np.array([values[p] for p in names])


def _fit(prob: _Problem, base: Vehicle, values: dict, base_values: dict, active: list[str],
         max_nfev: int, least_squares) -> dict[str, float]:
    """Least squares over ``active`` from ``values``; returns the fitted values."""
    lo, hi, sc = zip(*(_bounds(p, base_values[p]) for p in active))
    lo, hi, sc = np.array(lo), np.array(hi), np.array(sc)
    start = {p: (max(values[p], 0.02) if p.endswith("_lag") else values[p]) for p in active}
    x0 = np.clip(_vector(start, active), lo, hi) / sc

    def fun(x):
        vals = dict(values)
        vals.update(zip(active, x * sc))
        try:
            v = vehicle_with(base, vals)
        except ValueError:
            return np.full(prob.measured.size, 1e6)
        return prob.residuals(v)

    r = least_squares(fun, x0, bounds=(lo / sc, hi / sc), method="trf", diff_step=1e-5,
                      x_scale="jac", max_nfev=max_nfev, xtol=1e-8, ftol=1e-8)
    out = dict(zip(active, (r.x * sc).tolist()))
    for p in active:  # a lag at its lower bound: none
        if p.endswith("_lag") and out[p] <= 1.5 * LAG_MIN:
            out[p] = 0.0
    return out


def _jacobian(prob: _Problem, base: Vehicle, values: dict, names: list[str]) -> dict:
    """The Jacobian of the weighted residuals with respect to ``names`` at ``values`` (central
    differences; one-sided at a bound), with what the standard errors need: the residuals'
    variance ``s2`` and their serial-correlation inflation (:func:`_ar1_inflation`)."""
    r0 = prob.residuals(vehicle_with(base, values))
    m = r0.size
    J = np.empty((m, len(names)))
    for i, p in enumerate(names):
        lo, hi, sc = _bounds(p, values[p])
        h = 1e-4 * sc
        if p.endswith("_lag"):
            h = max(h, 0.2 * LAG_MIN)
        vp, vm = dict(values), dict(values)
        vp[p] = values[p] + h
        vm[p] = values[p] - h
        if vm[p] < lo:
            if p.endswith("_lag") and values[p] < LAG_MIN:  # no lag: the first lag tried
                vp[p] = LAG_MIN
                h = LAG_MIN - values[p]
            J[:, i] = (prob.residuals(vehicle_with(base, vp)) - r0) / h
        elif vp[p] > hi:
            J[:, i] = (r0 - prob.residuals(vehicle_with(base, vm))) / h
        else:
            J[:, i] = (prob.residuals(vehicle_with(base, vp))
                       - prob.residuals(vehicle_with(base, vm))) / (2 * h)
    dof = max(m - len(names), 1)
    return {"names": list(names), "J": J, "s2": float(np.dot(r0, r0)) / dof,
            "inflation": _ar1_inflation(r0.reshape(-1, prob.measured.shape[1]), prob.window)}


def _se(jac: dict, names: list[str]) -> dict[str, float]:
    """Standard errors of ``names`` estimated jointly: ``sqrt(diag(s2 (J^T J)^-1))`` on the
    Jacobian's columns of those names (column-scaled), times the inflation; inf for a
    parameter the residuals do not depend on, or one fully confounded with the others."""
    idx = [jac["names"].index(p) for p in names]
    J = jac["J"][:, idx]
    norms = np.linalg.norm(J, axis=0)
    out = {p: math.inf for p in names}
    good = [i for i in range(len(names)) if norms[i] > 0 and np.isfinite(norms[i])]
    if not good:
        return out
    Js = J[:, good] / norms[good]
    A = Js.T @ Js
    w, V = np.linalg.eigh(A)
    if w.min() <= 1e-12 * max(w.max(), 1e-300):  # confounded: the weakest direction's members
        weak = np.abs(V[:, np.argmin(w)]) > 0.1
        keep = [good[i] for i in range(len(good)) if not weak[i]]
        if len(keep) == len(good):
            return out
        sub = _se(jac, [names[i] for i in keep]) if keep else {}
        out.update(sub)
        return out
    cov = np.linalg.inv(A) * jac["s2"]
    d = np.sqrt(np.maximum(np.diag(cov), 0.0)) / norms[good] * jac["inflation"]
    for j, i in enumerate(good):
        out[names[i]] = float(d[j])
    return out
