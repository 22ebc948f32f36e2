"""Writes the example paths of this folder (run from the repository root:
``.venv/bin/python scenarios/make_paths.py``); the CSVs are committed, this is how they
were made.

Each path is built from a curvature profile kappa(s) along the arc length s (straights,
clothoid ramps, arcs), integrated to the heading phi(s) and the position x(s), y(s), and
driven at a constant speed from t = 0. Rows every 0.1 s: ``t`` [s], ``x``, ``y`` [m],
``phi`` [rad] (the path's tangent; the vehicle drives forward). The trajectory CSV
contract is in docs/SCENARIOS.md.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent / "paths"
DS = 0.005  # m, integration step along the path
DT = 0.1  # s between rows


def curvature_path(pieces):
    """``pieces``: ``(length [m], kappa_start, kappa_end)`` with kappa linear in s over
    each piece (a clothoid where they differ). Returns s, x, y, phi on a DS grid."""
    kappa = []
    for length, k0, k1 in pieces:
        n = int(round(length / DS))
        kappa.append(np.linspace(k0, k1, n, endpoint=False))
    kappa = np.concatenate(kappa)
    phi = np.concatenate([[0.0], np.cumsum(kappa) * DS])
    # trapezoidal integration of the unit tangent
    c, s_ = np.cos(phi), np.sin(phi)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (c[1:] + c[:-1]) * DS)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (s_[1:] + s_[:-1]) * DS)])
    s = np.arange(len(phi)) * DS
    return s, x, y, phi


def lane_change_path():
    """A lane change of 3.5 m to the left over 40 m, between 20 m and 30 m of straight:
    y follows a smooth step (1 - cos) / 2, heading its tangent."""
    s = np.arange(0.0, 90.0 + DS, DS)
    x = s.copy()
    u = np.clip((x - 20.0) / 40.0, 0.0, 1.0)
    y = 3.5 * (1 - np.cos(math.pi * u)) / 2
    dy = np.where((x > 20.0) & (x < 60.0), 3.5 * math.pi / 80.0 * np.sin(math.pi * u), 0.0)
    phi = np.arctan(dy)
    # re-parametrise by arc length
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    return arc, x, y, phi


def double_lane_change_path():
    """Two lane changes of 3.5 m, to the left and back, each over 40 m and shaped as
    :func:`lane_change_path`'s (1 - cos) / 2 step, between 20 m, 15 m and 20 m of straight
    (a double lane change, issue 29: the curvature steps at each change's ends)."""
    s = np.arange(0.0, 135.0 + DS, DS)
    x = s.copy()
    y = np.zeros_like(x)
    dy = np.zeros_like(x)
    for start, sign in ((20.0, 1.0), (75.0, -1.0)):
        u = np.clip((x - start) / 40.0, 0.0, 1.0)
        y += sign * 3.5 * (1 - np.cos(math.pi * u)) / 2
        dy += np.where((x > start) & (x < start + 40.0),
                       sign * 3.5 * math.pi / 80.0 * np.sin(math.pi * u), 0.0)
    phi = np.arctan(dy)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    return arc, x, y, phi


def drive(s, x, y, phi, speed_kmh, name):
    v = speed_kmh / 3.6
    t = np.arange(0.0, s[-1] / v + 1e-9, DT)
    st = t * v
    rows = zip(t, np.interp(st, s, x), np.interp(st, s, y), np.interp(st, s, phi))
    path = HERE / f"{name}.csv"
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x", "y", "phi"])
        for row in rows:
            w.writerow([f"{row[0]:.2f}"] + [f"{v_:.6f}" for v_ in row[1:]])
    print(f"{path}: {len(t)} rows, {t[-1]:.1f} s, {s[-1]:.1f} m at {speed_kmh:g} km/h")


def main():
    HERE.mkdir(exist_ok=True)
    drive(*lane_change_path(), 15.0, "lane-change")
    drive(*double_lane_change_path(), 20.0, "double-lane-change")
    # S-curve: left then right, 30 m radius arcs of about 50 deg with 10 m clothoids
    R = 30.0
    drive(*curvature_path([(15.0, 0, 0), (10.0, 0, 1 / R), (16.0, 1 / R, 1 / R),
                           (10.0, 1 / R, 0), (10.0, 0, -1 / R), (16.0, -1 / R, -1 / R),
                           (10.0, -1 / R, 0), (20.0, 0, 0)]), 12.0, "s-curve")
    # tight turn: 90 deg to the left on a 10 m radius, 5 m clothoids, at walking pace
    R = 10.0
    arc = R * (math.pi / 2 - 5.0 / R)  # the clothoids turn 2 x 2.5 m / R
    drive(*curvature_path([(15.0, 0, 0), (5.0, 0, 1 / R), (arc, 1 / R, 1 / R),
                           (5.0, 1 / R, 0), (15.0, 0, 0)]), 8.0, "tight-turn")


if __name__ == "__main__":
    main()
