"""Paths for the study: a lane change, a tight turn and seeded random paths, each built from
a curvature profile that the vehicle's steering can follow at the speed it is driven.

A path is its curvature ``kappa(s)`` along the arc length s, integrated to the heading and
position, then driven at a constant speed (:func:`controller.reference.path_reference`).
The paper asks of a reference that it be "pre-generated ... with feasible turning radii
and curvature, such that they conform to the vehicle's mechanical constraints, including
the maximum steering angle and steering rate" (Section 3.5); :func:`feasible_bounds` turns
that into numbers for a vehicle and a speed:

* steering angle: a wheel at ``x_i`` from the centre of mass steers about
  ``atan(x_i kappa)`` on a path of curvature ``kappa`` (the body along the tangent), so
  ``|kappa| <= tan(delta_use) / max|x_i|`` with ``delta_use`` = half the steering range
  (at most 30 deg), leaving the controller room to correct;
* friction: the lateral acceleration ``v^2 kappa`` stays below ``a_lat`` (default 0.4
  ``mu g``, well inside the tires' peak);
* steering rate: ``d delta / dt ~ max|x_i| v d kappa / ds`` stays below half the
  steering-rate limit.

Random paths are sums of a few sinusoids in s with random wavelengths (25-90 m), phases
and weights, scaled so that both the curvature and its rate meet the bounds; the same
seed gives the same path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .reference import Reference, ReferenceError, SpeedProfile, path_reference

DS = 0.02  # m, integration step along the path
TAIL = 30.0  # m of straight beyond the nominal path: the horizon never sees the end


@dataclass(frozen=True)
class Bounds:
    """Largest curvature [1/m] and curvature rate along the path [1/m^2] a vehicle can
    follow at a speed (module docstring)."""

    kappa: float
    kappa_rate: float


def feasible_bounds(vehicle, speed_kmh: float, a_lat: float | None = None) -> Bounds:
    """:class:`Bounds` for ``vehicle`` at ``speed_kmh`` (module docstring)."""
    v = max(speed_kmh / 3.6, 0.5)
    lim = vehicle.limits
    x_max = max(abs(x) for x in vehicle.axle_x) or 1.0
    d_use = min(0.5 * min(-lim.delta_min, lim.delta_max), math.radians(30.0))
    mu = min(vehicle.tire_lateral.mu, vehicle.tire_longitudinal.mu)
    a = 0.4 * mu * 9.81 if a_lat is None else a_lat
    kappa = min(math.tan(d_use) / x_max, a / (v * v))
    rate = 0.5 * min(-lim.omega_s_min, lim.omega_s_max) / (x_max * v)
    return Bounds(kappa, rate)


def _integrate(kappa: np.ndarray, ds: float = DS):
    """Heading and position of a curvature profile sampled every ``ds`` from the origin,
    heading 0."""
    phi = np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)])
    c, s = np.cos(phi), np.sin(phi)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (c[1:] + c[:-1]) * ds)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (s[1:] + s[:-1]) * ds)])
    return x, y


def path_from_curvature(kappa: np.ndarray, speed_kmh: float, name: str,
                        ds: float = DS) -> Reference:
    """Drive the path of curvature ``kappa`` (sampled every ``ds`` m, followed by a straight
    tail of :data:`TAIL` m) at a constant speed; the run's nominal duration ends where the
    profile ends."""
    length = ds * (len(kappa) - 1)
    tail = np.zeros(int(round(TAIL / ds)))
    k = np.concatenate([kappa, tail])
    x, y = _integrate(k, ds)
    u_grid = np.arange(len(k)) * ds

    def xy(u):
        return np.interp(u, u_grid, x), np.interp(u, u_grid, y)

    return path_reference(xy, length, SpeedProfile([(0.0, speed_kmh)]), name=name,
                          tail=TAIL - ds)


def _ramp(k0: float, k1: float, length: float, ds: float = DS) -> np.ndarray:
    n = max(int(round(length / ds)), 1)
    return np.linspace(k0, k1, n, endpoint=False)


def lane_change(vehicle, speed_kmh: float, width: float = 3.5, straight: float = 15.0
                ) -> Reference:
    """A lane change of ``width`` [m] to the left: y follows the smooth step
    ``width (u - sin(2 pi u) / (2 pi))`` over a length L (u = x / L), whose curvature
    ``~ 2 pi width / L^2 sin(2 pi u)`` is zero at both ends (no jump in the yaw rate), L
    chosen so that the curvature and its rate stay within :func:`feasible_bounds` (at least
    30 m), between straights."""
    b = feasible_bounds(vehicle, speed_kmh)
    # peak curvature 2 pi width / L^2, peak rate 4 pi^2 width / L^3
    L = max(30.0, math.sqrt(2 * math.pi * width / b.kappa),
            (4 * math.pi ** 2 * width / b.kappa_rate) ** (1 / 3))
    x = np.arange(0.0, L, DS / 4)
    u = x / L
    dy = width / L * (1 - np.cos(2 * math.pi * u))
    d2y = width * 2 * math.pi / L ** 2 * np.sin(2 * math.pi * u)
    kappa_x = d2y / (1 + dy ** 2) ** 1.5  # curvature of y(x)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(np.cumsum(dy) * DS / 4)))])
    kappa = np.interp(np.arange(0.0, s[-1], DS), s, kappa_x)
    flat = np.zeros(int(round(straight / DS)))
    return path_from_curvature(np.concatenate([flat, kappa, flat]), speed_kmh, "lane-change")


def tight_turn(vehicle, speed_kmh: float, angle_deg: float = 90.0, straight: float = 12.0
               ) -> Reference:
    """A left turn of ``angle_deg`` at the tightest radius :func:`feasible_bounds` allows,
    entered and left through clothoids at the largest feasible curvature rate."""
    b = feasible_bounds(vehicle, speed_kmh)
    k = b.kappa
    ramp = k / b.kappa_rate  # clothoid length
    turn = math.radians(angle_deg)
    if ramp * k >= turn:  # the clothoids alone turn enough: a shorter peak
        ramp = math.sqrt(turn / b.kappa_rate)
        k = ramp * b.kappa_rate
        arc = 0.0
    else:
        arc = (turn - ramp * k) / k
    flat = np.zeros(int(round(straight / DS)))
    kappa = np.concatenate([flat, _ramp(0.0, k, ramp), np.full(int(round(arc / DS)), k),
                            _ramp(k, 0.0, ramp), flat])
    return path_from_curvature(kappa, speed_kmh, "tight-turn")


def random_path(vehicle, speed_kmh: float, seed: int, length: float | None = None,
                duration: float = 20.0, waves: int = 4) -> Reference:
    """A seeded random path of ``length`` [m] (default: ``duration`` s of driving) whose
    curvature is a sum of ``waves`` sinusoids in s (wavelengths 25-90 m), scaled to the
    largest amplitude :func:`feasible_bounds` allows for the curvature and its rate."""
    if waves < 1:
        raise ReferenceError("random path: waves must be >= 1")
    rng = np.random.default_rng(seed)
    v = speed_kmh / 3.6
    L = length if length is not None else max(v * duration, 20.0)
    s = np.arange(0.0, L, DS)
    lam = rng.uniform(25.0, 90.0, waves)
    ph = rng.uniform(0.0, 2 * math.pi, waves)
    w = rng.uniform(0.3, 1.0, waves)
    kappa = (w[:, None] * np.sin(2 * math.pi * s[None, :] / lam[:, None] + ph[:, None])).sum(0)
    rate = np.gradient(kappa, DS)
    b = feasible_bounds(vehicle, speed_kmh)
    scale = min(b.kappa / np.abs(kappa).max(), b.kappa_rate / np.abs(rate).max())
    kappa = kappa * scale
    # fade in over the first 10 m: the run starts on a straight, on the reference
    fade = np.clip(s / 10.0, 0.0, 1.0)
    return path_from_curvature(kappa * fade, speed_kmh, f"random-{seed}")
