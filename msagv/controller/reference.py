"""Reference trajectories: the paper's Case 1 (winding road) and Case 2 (straight line with
a 60 degree initial heading error), any ``t,x,y,phi`` CSV, and paths driven at a speed
profile given in km/h.

A :class:`Reference` is sampled at arbitrary times and returns the pose ``x, y, phi`` and
the velocity ``vx, vy`` (in G) and yaw rate ``r`` the controller's feed-forward uses.
Times beyond the last sample either hold the final pose with zero velocity
(``after_end="hold"``, the default of the class) or continue it in a straight line at the
last heading and velocity (``after_end="continue"``, what a scenario uses, see
:class:`experiments.scenario.Scenario`).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from msagv.plant.signals import BODY_FIELDS, CONTROL_PERIOD, foreign_separator

KMH = 1.0 / 3.6
AFTER_END = ("hold", "continue")
HEADING_JUMP = math.pi / 2  # rad: a larger heading change between two CSV rows is refused


class ReferenceError(ValueError):
    """A malformed trajectory or speed profile (the message names the problem)."""


class SpeedProfile:
    """Speed over time, piecewise linear between ``(t [s], v [km/h])`` breakpoints.

    ``SpeedProfile.parse("15")`` is a constant 15 km/h; ``"0:5,10:15,20:15"`` ramps from
    5 km/h at t = 0 to 15 km/h at t = 10 s and holds. Speeds must be >= 0.
    """

    def __init__(self, points: Sequence[tuple[float, float]]):
        pts = [(float(t), float(v)) for t, v in points]
        if not pts:
            raise ReferenceError("speed profile: no points")
        for t, v in pts:
            if not (math.isfinite(t) and math.isfinite(v)):
                raise ReferenceError("speed profile: values must be finite")
            if v < 0:
                raise ReferenceError(f"speed profile: speed must be >= 0 km/h, got {v}")
        ts = [p[0] for p in pts]
        if any(b <= a for a, b in zip(ts, ts[1:])):
            raise ReferenceError("speed profile: times must increase strictly")
        self.t = np.array(ts)
        self.v = np.array([p[1] for p in pts]) * KMH  # m/s

    @classmethod
    def parse(cls, text: str | float) -> "SpeedProfile":
        if isinstance(text, (int, float)):
            return cls([(0.0, float(text))])
        text = str(text).strip()
        if ":" not in text:
            try:
                v = float(text)
            except ValueError:
                raise ReferenceError(f"speed: '{text}' is not a number of km/h") from None
            return cls([(0.0, v)])
        pts = []
        for part in text.split(","):
            try:
                t, v = part.split(":")
                pts.append((float(t), float(v)))
            except ValueError:
                raise ReferenceError(f"speed profile: expected t:kmh pairs, got '{part}'") from None
        return cls(pts)

    def speed(self, t):
        return np.interp(t, self.t, self.v)

    def distance(self, t):
        """Distance travelled by time t [m] (exact integral of the piecewise-linear speed)."""
        t = np.asarray(t, dtype=float)
        tk = np.concatenate([[min(0.0, self.t[0])], self.t])
        vk = np.concatenate([[self.v[0]], self.v])
        seg = np.concatenate([[0.0], np.cumsum(0.5 * (vk[1:] + vk[:-1]) * np.diff(tk))])
        i = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 1)
        v_t = self.speed(t)
        return seg[i] + 0.5 * (vk[i] + v_t) * (t - tk[i])


@dataclass
class Reference:
    """A time-parametrised trajectory, tabulated densely (interpolated linearly).

    Arrays ``t, x, y, phi, vx, vy, r`` of equal length; ``phi`` unwrapped.
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    phi: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    r: np.ndarray
    name: str = "trajectory"
    #: the run length the case is defined by [s]; the table may extend beyond it so the
    #: horizon never sees the trajectory's end (None: the whole table)
    nominal_duration: float | None = None
    #: beyond the last sample: "hold" the final pose at zero velocity, or "continue" at the
    #: last heading and velocity in a straight line (yaw rate 0)
    after_end: str = "hold"

    def __post_init__(self):
        if self.after_end not in AFTER_END:
            raise ReferenceError(f"after_end: expected one of {', '.join(AFTER_END)}, got "
                                 f"'{self.after_end}'")
        n = len(self.t)
        for k in BODY_FIELDS:  # the reference's fields are the body's
            a = np.asarray(getattr(self, k), dtype=float)
            if a.shape != (n,):
                raise ReferenceError(f"reference: {k} must have the length of t ({n})")
            if not np.all(np.isfinite(a)):
                raise ReferenceError(f"reference: {k} contains NaN or inf")
            setattr(self, k, a)
        self.t = np.asarray(self.t, dtype=float)
        if n < 2 or np.any(np.diff(self.t) <= 0) or not np.all(np.isfinite(self.t)):
            raise ReferenceError("reference: t must have >= 2 finite, strictly increasing values")
        self._table = np.stack([self.x, self.y, self.phi, self.vx, self.vy, self.r], axis=1)

    @property
    def duration(self) -> float:
        """The run length: ``nominal_duration`` if set, else the table's span."""
        if self.nominal_duration is not None:
            return float(self.nominal_duration)
        return float(self.t[-1] - self.t[0])

    @property
    def end_time(self) -> float:
        """Vehicle time at which the trajectory ends: ``t[0] + duration`` (the last row of a
        CSV; the end of a case's path, before the tail its table carries)."""
        return float(self.t[0]) + self.duration

    def sample(self, times) -> np.ndarray:
        """Rows ``(x, y, phi, vx, vy, r)`` at ``times`` (shape (..., 6)). Beyond the last
        sample: the final pose standing still (``after_end="hold"``), or the final pose
        moved on at the final velocity, heading kept, yaw rate 0 (``"continue"``)."""
        times = np.asarray(times, dtype=float)
        tt = self.t
        idx = np.clip(np.searchsorted(tt, times, side="right") - 1, 0, len(tt) - 2)
        w = np.clip((times - tt[idx]) / (tt[idx + 1] - tt[idx]), 0.0, 1.0)[..., None]
        out = self._table[idx] * (1 - w) + self._table[idx + 1] * w
        after = times > tt[-1]
        if np.any(after):
            last = self._table[-1]
            out[after] = last
            if self.after_end == "continue":
                dt = times[after] - tt[-1]
                out[after, 0] = last[0] + last[3] * dt
                out[after, 1] = last[1] + last[4] * dt
                out[after, 5] = 0.0
            else:
                out[after, 3:] = 0.0
        return out

    def with_after_end(self, after_end: str) -> "Reference":
        """The same trajectory with another behaviour beyond its last sample."""
        return Reference(self.t, self.x, self.y, self.phi, self.vx, self.vy, self.r,
                         name=self.name, nominal_duration=self.nominal_duration,
                         after_end=after_end)

    def smoothed(self, sigma: float) -> "Reference":
        """The trajectory smoothed along its path: ``x``, ``y`` and ``phi`` as functions of
        the arc length ``s`` convolved with a Gaussian of standard deviation ``sigma`` [m],
        each time keeping its arc length (velocities by finite differences again).

        On an arc of curvature kappa this moves the path toward the inside by about
        ``sigma^2 kappa / 2`` (exactly ``A (1 - exp(-k^2 sigma^2 / 2))`` on ``A sin(k s)``):
        a controller tracking it cuts corners in proportion to their curvature, without
        knowing anything of wear (``MPCSettings.ref_smoothing``). The ends are padded by
        odd reflection, so a straight start or end stays straight and a path that starts
        curving keeps its start. ``sigma = 0`` returns the trajectory itself."""
        if not (math.isfinite(sigma) and sigma >= 0):
            raise ReferenceError(f"smoothing: sigma must be a finite length >= 0 m, got {sigma}")
        s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(self.x), np.diff(self.y)))])
        if sigma == 0 or s[-1] <= sigma * 1e-3:
            return self
        from scipy.ndimage import gaussian_filter1d

        grid = np.linspace(0.0, s[-1], int(math.ceil(10.0 * s[-1] / sigma)) + 1)
        ds = grid[1] - grid[0]  # about sigma / 10
        keep = np.concatenate([[True], np.diff(s) > 0])  # standing still: one sample
        pad = min(int(math.ceil(4.0 * sigma / ds)), grid.size - 1)

        def smooth(a):
            g = np.interp(grid, s[keep], a[keep])
            left, right = 2 * g[0] - g[pad:0:-1], 2 * g[-1] - g[-2:-pad - 2:-1]
            f = gaussian_filter1d(np.concatenate([left, g, right]), sigma / ds, mode="nearest")
            return np.interp(s, grid, f[pad:pad + grid.size])

        x, y, phi = smooth(self.x), smooth(self.y), smooth(self.phi)
        return Reference(self.t, x, y, phi, np.gradient(x, self.t), np.gradient(y, self.t),
                         np.gradient(phi, self.t), name=f"{self.name} (smoothed {sigma:g} m)",
                         nominal_duration=self.nominal_duration, after_end=self.after_end)

    def initial_state(self, vehicle) -> dict[str, float]:
        """The plant state that starts exactly on the reference at t[0], moving with it,
        every wheel steered kinematically (pure rolling)."""
        x, y, phi, vx, vy, r = self.sample(self.t[0])
        st = {"x": x, "y": y, "phi": phi, "vx": vx, "vy": vy, "r": r}
        st.update(rolling_wheels(vehicle, phi, vx, vy, r)[0])
        return {k: float(v) for k, v in st.items()}

    def to_csv(self, path: str | Path) -> None:
        with Path(path).open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", "x", "y", "phi"])
            for row in zip(self.t, self.x, self.y, self.phi):
                w.writerow([repr(float(v)) for v in row])

    def to_message(self) -> dict:
        """As DESIGN.md's ``reference`` payload (t, x, y, phi arrays)."""
        return {"t": self.t.tolist(), "x": self.x.tolist(), "y": self.y.tolist(),
                "phi": self.phi.tolist()}


def rolling_wheels(vehicle, phi: float, vx: float, vy: float, r: float
                   ) -> tuple[dict[str, float], dict[str, float]]:
    """Pure rolling for the body motion ``(vx, vy)`` (in G) and yaw rate ``r`` at heading
    ``phi``: ``({delta_ij}, {omega_w_ij})``, each wheel steered along its velocity (within
    the steering limits; 0 for a wheel at rest) and turning at its speed over r_w."""
    c, s = math.cos(phi), math.sin(phi)
    ub, vb = c * vx + s * vy, -s * vx + c * vy
    lim = vehicle.limits
    delta, omega = {}, {}
    for k, xw, yw in zip(vehicle.wheel_names, vehicle.wheel_x, vehicle.wheel_y):
        wvx, wvy = ub - r * yw, vb + r * xw
        speed = math.hypot(wvx, wvy)
        d = math.atan2(wvy, wvx) if speed > 1e-9 else 0.0
        delta[f"delta_{k}"] = float(min(max(d, lim.delta_min), lim.delta_max))
        omega[f"omega_w_{k}"] = float(speed / vehicle.wheel_radius)
    return delta, omega


def wheel_velocities(reference: Reference, vehicle, t0: float, t1: float, dt: float = CONTROL_PERIOD
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(times, wx, wy)``: the velocity [m/s] every wheel needs to roll along the reference
    between ``t0`` and ``t1``, in the body frame B (the body's velocity plus the yaw rate's
    share at each wheel), each shape (K, 2n). Rolling along it takes a steering angle
    ``atan2(wy, wx)`` and a rim speed ``hypot(wx, wy)``."""
    times = np.arange(t0, t1 + dt / 2, dt)
    R = reference.sample(times)
    c, s = np.cos(R[:, 2]), np.sin(R[:, 2])
    ub, vb = c * R[:, 3] + s * R[:, 4], -s * R[:, 3] + c * R[:, 4]
    r = R[:, 5:6]
    wx = ub[:, None] - r * np.asarray(vehicle.wheel_y)[None, :]
    wy = vb[:, None] + r * np.asarray(vehicle.wheel_x)[None, :]
    return times, wx, wy


def wheel_speeds(reference: Reference, vehicle, t0: float, t1: float, dt: float = CONTROL_PERIOD
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``(times, speeds)``: the rim speed [m/s] every wheel needs to roll along the
    reference between ``t0`` and ``t1``, shape (K, 2n) (:func:`wheel_velocities`)."""
    times, wx, wy = wheel_velocities(reference, vehicle, t0, t1, dt)
    return times, np.hypot(wx, wy)


def _wrap_round(a):
    """Angle differences to [-pi, pi] by the nearest turn (np.round; the cost's heading wrap
    to (-pi, pi] is controller.cost_terms.wrap)."""
    return a - 2 * np.pi * np.round(a / (2 * np.pi))


def check_headings(t, x, y, phi, where: str = "trajectory", lines=None) -> None:
    """Refuse headings that cannot be radians of a drivable path (``ReferenceError``
    naming ``where`` and the CSV line): headings that follow the direction of travel when
    read as degrees but not as radians, or a jump of more than 90 degrees between rows."""
    t, x, y, phi = (np.asarray(a, dtype=float) for a in (t, x, y, phi))
    if t.size < 2 or not np.all(np.diff(t) > 0):
        return
    if _looks_like_degrees(t, x, y, phi):
        raise ReferenceError(
            f"{where}: phi looks like degrees (read as degrees it follows the direction of "
            f"travel, read as radians it does not): give phi in radians")
    d = _wrap_round(np.diff(phi))
    big = np.flatnonzero(np.abs(d) > HEADING_JUMP)
    if big.size:
        k = int(big[0])
        at = f"{where}:{lines[k + 1]}" if lines is not None else f"{where}: row {k + 2}"
        raise ReferenceError(
            f"{at}: phi jumps by {math.degrees(abs(d[k])):.0f} deg from the previous row (at "
            f"most 90 deg between rows; phi is the heading in radians)")


def _looks_like_degrees(t, x, y, phi) -> bool:
    """True when, on the moving segments where reading phi as degrees or as radians makes
    a difference (> 5 deg), the degrees follow the direction of travel (median within
    2 deg) and the radians do not (median more than 30 deg off)."""
    dx, dy, dt = np.diff(x), np.diff(y), np.diff(t)
    course = np.arctan2(dy, dx)

    def mid(h):  # the heading half-way along each segment
        return h[:-1] + 0.5 * _wrap_round(np.diff(h))

    as_rad, as_deg = mid(phi), mid(np.radians(phi))
    use = (np.hypot(dx, dy) / dt > 0.1) & (np.abs(_wrap_round(as_rad - as_deg)) > math.radians(5))
    if np.count_nonzero(use) < 3:
        return False
    off_rad = math.degrees(float(np.median(np.abs(_wrap_round(as_rad - course)[use]))))
    off_deg = math.degrees(float(np.median(np.abs(_wrap_round(as_deg - course)[use]))))
    return off_deg < 2.0 and off_rad > 30.0


def from_samples(t, x, y, phi, name: str = "trajectory") -> Reference:
    """A reference from ``t, x, y, phi`` samples; velocities by finite differences
    (second order, ``numpy.gradient``) of x, y and the unwrapped heading."""
    t = np.asarray(t, dtype=float)
    for k, a in (("t", t), ("x", x), ("y", y), ("phi", phi)):
        a = np.asarray(a, dtype=float)
        if a.ndim != 1 or a.size != t.size:
            raise ReferenceError(f"reference: {k} must be a 1-d array as long as t")
        if not np.all(np.isfinite(a)):
            raise ReferenceError(f"reference: {k} contains NaN or inf")
    if t.size < 3:
        raise ReferenceError("reference: needs at least 3 samples")
    if np.any(np.diff(t) <= 0):
        raise ReferenceError("reference: t must increase strictly")
    x, y = np.asarray(x, float), np.asarray(y, float)
    phi = np.unwrap(np.asarray(phi, float))
    return Reference(t, x, y, phi, np.gradient(x, t), np.gradient(y, t), np.gradient(phi, t),
                     name=name)


MS_MIN_SPAN = 600.0  # s: a CSV read as seconds that lasts this long ...
MS_MAX_SPEED = 0.1  # m/s: ... at this average speed or slower ...
MS_PLAUSIBLE = (0.2, 50.0)  # m/s: ... but plausible read as milliseconds: t was in ms


def check_time_unit(t, x, y, where: str = "trajectory") -> None:
    """Refuse a ``t`` column that looks like milliseconds (``ReferenceError`` naming
    ``where``): read as seconds the path lasts at least :data:`MS_MIN_SPAN` at a crawl
    (:data:`MS_MAX_SPEED` or slower on average) while read as milliseconds its speed is a
    vehicle's (:data:`MS_PLAUSIBLE`)."""
    t, x, y = (np.asarray(a, dtype=float) for a in (t, x, y))
    span = float(t[-1] - t[0]) if t.size > 1 else 0.0
    if span < MS_MIN_SPAN:
        return
    length = float(np.sum(np.hypot(np.diff(x), np.diff(y))))
    v = length / span
    if v <= MS_MAX_SPEED and MS_PLAUSIBLE[0] <= 1000.0 * v <= MS_PLAUSIBLE[1]:
        raise ReferenceError(
            f"{where}: t looks like milliseconds: read as seconds the path is {length:.1f} m "
            f"in {span:.0f} s ({span / 3600:.1f} h at {3.6 * v:.3f} km/h), read as "
            f"milliseconds it is {span / 1000:.1f} s at {3600 * v:.1f} km/h: give t in "
            f"seconds")


def from_csv(path: str | Path) -> Reference:
    """Read a ``t,x,y,phi`` CSV (header required; comma-separated; t in s, phi in rad).
    Errors name the line; a file separated by something else than commas is refused naming
    the separator, a ``t`` in milliseconds naming the unit (:func:`check_time_unit`)."""
    path = Path(path)
    if not path.is_file():
        raise ReferenceError(f"{path}: no such file")
    rows, lines = [], []
    with path.open(newline="") as f:
        rd = csv.reader(f)
        try:
            raw = next(rd)
        except StopIteration:
            raise ReferenceError(f"{path}: empty file") from None
        header = [h.strip() for h in raw]
        miss = [c for c in ("t", "x", "y", "phi") if c not in header]
        if miss:
            sep = foreign_separator(raw, ("t", "x", "y", "phi"))
            if sep is not None:
                raise ReferenceError(f"{path}:1: the columns are separated by {sep} "
                                     f"('{','.join(raw).strip()}'): msagv reads comma-separated "
                                     f"files (t,x,y,phi; decimal points, not commas)")
            raise ReferenceError(f"{path}:1: missing column(s) {', '.join(miss)}")
        idx = [header.index(c) for c in ("t", "x", "y", "phi")]
        for ln, row in enumerate(rd, start=2):
            if not row:
                continue
            try:
                vals = [float(row[i]) for i in idx]
            except (ValueError, IndexError):
                raise ReferenceError(f"{path}:{ln}: expected numbers in t, x, y, phi") from None
            if not all(math.isfinite(v) for v in vals):
                raise ReferenceError(f"{path}:{ln}: values must be finite")
            if rows and vals[0] <= rows[-1][0]:
                raise ReferenceError(f"{path}:{ln}: t must increase strictly")
            rows.append(vals)
            lines.append(ln)
    if len(rows) < 3:
        raise ReferenceError(f"{path}: needs at least 3 rows")
    a = np.array(rows)
    check_time_unit(a[:, 0], a[:, 1], a[:, 2], where=str(path))
    check_headings(a[:, 0], a[:, 1], a[:, 2], a[:, 3], where=str(path), lines=lines)
    return from_samples(a[:, 0], a[:, 1], a[:, 2], a[:, 3], name=path.stem)


# the control periods a speed profile is given to reach a path's end: 1e5 s (the length of
# np.arange(0.0, 1e5, CONTROL_PERIOD))
_REACH_STEPS = math.ceil(1e5 / CONTROL_PERIOD)


def _reach_times(n: int) -> np.ndarray:
    """The first ``n`` of the times ``np.arange(0.0, 1e5, CONTROL_PERIOD)``, the same floats
    (numpy fills an arange as ``start + i * step``)."""
    return np.arange(n, dtype=float) * CONTROL_PERIOD


def _reach_step(speed: SpeedProfile, d: float) -> int:
    """The first step ``k`` whose time (:func:`_reach_times`) has the profile at distance
    ``d`` or beyond; :data:`_REACH_STEPS` if none has. The same index as a search of the whole
    1e5 s table, found on its first steps only (tables of 4x the length until one reaches
    ``d``): the whole table, 10 million steps, took 0.3-1.4 s per reference, and a run,
    a plant or a controller built the reference of a case for each."""
    n = min(4096, _REACH_STEPS)
    while True:
        k = int(np.searchsorted(speed.distance(_reach_times(n)), d))
        if k < n or n == _REACH_STEPS:  # (the distance never decreases: speeds are >= 0)
            return k
        n = min(4 * n, _REACH_STEPS)


def path_reference(path_xy: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], length: float,
                   speed: SpeedProfile, dt: float = CONTROL_PERIOD, ds: float = 0.02,
                   name: str = "path", duration: float | None = None,
                   tail: float = 0.0) -> Reference:
    """Drive a parametric path ``u -> (x(u), y(u))``, u in [0, length] (roughly arc length),
    at a speed profile. The path is re-parametrised by true arc length; heading is the
    tangent, yaw rate ``v * curvature``. The trajectory ends at the path's end (or at
    ``duration``). ``tail`` [m] extends the path beyond ``length`` (same formula) so that a
    run of the nominal duration never has the trajectory's end inside its horizon."""
    if length <= 0:
        raise ReferenceError("path length must be > 0")
    u = np.linspace(0.0, length + tail, int(math.ceil((length + tail) / ds)) + 1)
    px, py = path_xy(u)
    seg = np.hypot(np.diff(px), np.diff(py))
    s = np.concatenate([[0.0], np.cumsum(seg)])
    dx = np.gradient(px, s)
    dy = np.gradient(py, s)
    heading = np.unwrap(np.arctan2(dy, dx))
    kappa = np.gradient(heading, s)
    total = s[-1]
    nominal = s[np.searchsorted(u, length)]  # arc length at u = length
    if duration is None:
        # time to reach the end of the nominal path
        k = _reach_step(speed, nominal)
        if k == _REACH_STEPS:
            raise ReferenceError("speed profile never reaches the end of the path")
        duration = float(_reach_times(k + 1)[k])
    k = min(_reach_step(speed, total), _REACH_STEPS - 1)
    t_table = float(_reach_times(k + 1)[k])
    t = np.arange(0.0, max(duration, t_table) + dt / 2, dt)
    st = np.minimum(speed.distance(t), total)
    v = speed.speed(t) * (speed.distance(t) < total)
    hx = np.interp(st, s, heading)
    return Reference(t, np.interp(st, s, px), np.interp(st, s, py), hx, v * np.cos(hx),
                     v * np.sin(hx), v * np.interp(st, s, kappa), name=name,
                     nominal_duration=duration)


# ---- the paper's cases ------------------------------------------------------------------
CASE1_AMPLITUDE = 4.0  # m
CASE1_WAVELENGTH = 60.0  # m
CASE1_LENGTH = 150.0  # m of x


def case1_curve(speed_kmh: float | str | SpeedProfile = 15.0, duration: float | None = None) -> Reference:
    """Case 1: a winding road ``y = A sin(2 pi x / lambda)``, A = 4 m, lambda = 60 m, over
    x in [0, 150] m (2.5 periods).

    The paper's figure of the path is missing; we choose a winding road whose curvature is
    feasible for the steering limits: the tightest radius is lambda^2 / (4 pi^2 A) = 22.8 m,
    i.e. kinematic steering angles of atan(3 / 22.8) = 7.5 deg at the axles, and a lateral
    acceleration of 4.1 m/s^2 at 35 km/h (within mu g = 7.8 m/s^2).
    """
    sp = speed_kmh if isinstance(speed_kmh, SpeedProfile) else SpeedProfile.parse(speed_kmh)
    k = 2 * math.pi / CASE1_WAVELENGTH

    def path(u):
        return u, CASE1_AMPLITUDE * np.sin(k * u)

    # 20 m of tail: the horizon (1 s, <= 10 m at 35 km/h) never sees the end
    return path_reference(path, CASE1_LENGTH, sp, name="case1-curve", duration=duration,
                          tail=20.0)


CASE2_HEADING_ERROR = math.radians(60.0)


def case2_line(speed_kmh: float | str | SpeedProfile = 10.0, duration: float = 20.0) -> Reference:
    """Case 2: a straight line along +x from the origin, driven at the speed profile. The
    vehicle starts at the origin with its heading 60 degrees off the line (see
    :func:`case2_initial_state`)."""
    sp = speed_kmh if isinstance(speed_kmh, SpeedProfile) else SpeedProfile.parse(speed_kmh)
    # 5 s beyond the run: see case1_curve
    t = np.arange(0.0, duration + 5.0 + 0.5 * CONTROL_PERIOD, CONTROL_PERIOD)
    v = sp.speed(t)
    return Reference(t, sp.distance(t), np.zeros_like(t), np.zeros_like(t), v,
                     np.zeros_like(t), np.zeros_like(t), name="case2-line",
                     nominal_duration=duration)


def case2_initial_state(reference: Reference, vehicle) -> dict[str, float]:
    """Case 2's start: on the line's origin, heading 60 degrees off it, moving along its own
    heading at the reference speed with the wheels straight (pure rolling)."""
    st = reference.initial_state(vehicle)
    v = math.hypot(st["vx"], st["vy"])
    phi = CASE2_HEADING_ERROR
    st.update(phi=phi, vx=v * math.cos(phi), vy=v * math.sin(phi), r=0.0)
    for k in vehicle.wheel_names:
        st[f"delta_{k}"] = 0.0
    return st


def make_case(case: str, speed_kmh=None, duration: float | None = None):
    """``(reference, initial_state_fn)`` for ``case`` in {'curve', 'line'}."""
    if case in ("curve", "case1"):
        ref = case1_curve(15.0 if speed_kmh is None else speed_kmh, duration=duration)
        return ref, ref.initial_state
    if case in ("line", "case2"):
        ref = case2_line(10.0 if speed_kmh is None else speed_kmh,
                         duration=20.0 if duration is None else duration)
        return ref, lambda veh: case2_initial_state(ref, veh)
    raise ReferenceError(f"unknown case '{case}' (expected curve or line)")
