"""The paper's metrics (eq. 28-33) and solve-time percentiles.

Units as the paper reports them: wear work in J, e_x and e_y in cm, e_phi in degrees;
``e_bar`` is the plain mean of those three numbers (the paper's mixed units, eq. 32) and
``Omega`` its two-branch balance index (eq. 33).
"""

from __future__ import annotations

import math

import numpy as np

from msagv.plant.signals import WEAR_FIELDS

METRIC_KEYS = ["W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg", "e_bar",
               "Omega", "e_lat_rms_cm", "e_lat_max_cm", "solve_ms", "steps"]


def wrap_angle(a):
    """Angle wrapped to (-pi, pi]."""
    a = np.asarray(a, dtype=float)
    return a - 2.0 * np.pi * np.ceil((a - np.pi) / (2.0 * np.pi))


def omega_index(W_tw: float, e_bar: float) -> float:
    """Performance Balance Index, paper eq. (33):
    ``W_tw^0.5 e_bar^0.1`` if e_bar < 50, else ``W_tw^0.5 e_bar^0.5``."""
    if W_tw < 0 or e_bar < 0:
        raise ValueError("Omega: W_tw and e_bar must be >= 0")
    return math.sqrt(W_tw) * e_bar ** (0.1 if e_bar < 50 else 0.5)


def tracking_errors(pose: np.ndarray, ref_pose: np.ndarray) -> dict[str, float]:
    """RMSE in x, y [cm] and heading [deg] (heading error wrapped), e_bar (eq. 32), and the
    RMS and largest lateral (cross-track) error [cm]."""
    pose = np.asarray(pose, dtype=float)
    ref_pose = np.asarray(ref_pose, dtype=float)
    ex = 100.0 * math.sqrt(np.mean((pose[:, 0] - ref_pose[:, 0]) ** 2))
    ey = 100.0 * math.sqrt(np.mean((pose[:, 1] - ref_pose[:, 1]) ** 2))
    ep = math.degrees(math.sqrt(np.mean(wrap_angle(pose[:, 2] - ref_pose[:, 2]) ** 2)))
    # lateral (cross-track) error: the position error across the reference's heading, the
    # physical accuracy a path-tracking engineer asks for (e_x, e_y mix along- and
    # cross-track error with the path's direction)
    c, s_ = np.cos(ref_pose[:, 2]), np.sin(ref_pose[:, 2])
    lat = -(pose[:, 0] - ref_pose[:, 0]) * s_ + (pose[:, 1] - ref_pose[:, 1]) * c
    return {"e_x_cm": ex, "e_y_cm": ey, "e_phi_deg": ep, "e_bar": (ex + ey + ep) / 3.0,
            "e_lat_rms_cm": 100.0 * math.sqrt(np.mean(lat ** 2)),
            "e_lat_max_cm": 100.0 * float(np.abs(lat).max())}


def percentiles(values, scale: float = 1.0, count: bool = False) -> dict:
    """``{"p50", "p99", "max"}`` (plus ``"n"`` with ``count``) of ``values`` times ``scale``
    (e.g. 1000 for seconds to milliseconds); None (JSON null) when there are no values."""
    v = np.asarray(values, dtype=float).reshape(-1) * scale
    if v.size == 0:
        out = {"p50": None, "p99": None, "max": None}
    else:
        out = {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)),
               "max": float(v.max())}
    if count:
        out["n"] = int(v.size)
    return out


def compute_metrics(pose, ref_pose, W_start, W_end, solve_ms=()) -> dict:
    """All metrics of a run.

    ``pose``/``ref_pose``: (N, 3) at the control instants; ``W_start``/``W_end``: the
    plant's integrated wear work (W_s, W_alpha, W_t) at the start and end (eq. 28-30 are
    the sampled sums of the powers; the plant integrates the powers exactly, which is
    their limit). ``solve_ms``: solve times for the percentiles.
    """
    W = np.asarray(W_end, dtype=float) - np.asarray(W_start, dtype=float)
    out = {"W_s": float(W[0]), "W_alpha": float(W[1]), "W_t": float(W[2])}
    out["W_tw"] = out["W_s"] + out["W_alpha"] + out["W_t"]  # eq. (31)
    out.update(tracking_errors(pose, ref_pose))
    out["Omega"] = omega_index(out["W_tw"], out["e_bar"])
    out["solve_ms"] = percentiles(solve_ms)
    out["steps"] = int(len(pose))
    return {k: out[k] for k in METRIC_KEYS}


def format_table(m: dict, title: str = "") -> str:
    """A small human-readable table of one run's metrics."""
    lines = [title] if title else []
    if m["W_tw"] is None:  # a plant without the optional wear fields
        lines.append("  Omega      n/a (no wear work recorded)")
        lines.append("  W_tw [J]   n/a (no wear work recorded)")
    else:
        lines.append(f"  Omega      {m['Omega']:.4g}")
        lines.append(f"  W_tw [J]   {m['W_tw']:.4g}   (W_s {m['W_s']:.3g}, W_alpha "
                     f"{m['W_alpha']:.3g}, W_t {m['W_t']:.3g})")
    lines.append(f"  e_bar      {m['e_bar']:.3f}   (e_x {m['e_x_cm']:.2f} cm, e_y {m['e_y_cm']:.2f} cm, "
                 f"e_phi {m['e_phi_deg']:.2f} deg)")
    sm = m["solve_ms"]
    if sm.get("p50") is not None:
        lines.append(f"  solve [ms] p50 {sm['p50']:.2f}  p99 {sm['p99']:.2f}  max {sm['max']:.2f}")
    lines.append(f"  steps      {m['steps']}")
    return "\n".join(lines)


WHEEL_WEAR_KEYS = WEAR_FIELDS  # the rows of a per-wheel wear array


def wear_by_wheel(dW, n_wheels: int | None = None) -> dict:
    """Each wheel's and each axle's wear work over a run, from ``dW``: the per-wheel wear
    work at the end minus at the start, shape (3, 2n) with rows W_s, W_alpha, W_t in the
    wheel order 11, 12, 21, ... Returns ``{"wheels": {"11": {"W_s", "W_alpha", "W_t",
    "W_tw"}, ...}, "axles": {"1": {...}, ...}}`` [J]; an axle's values are the sums over
    its two wheels, and the sums over all wheels are the run's W_s ... W_tw."""
    dW = np.asarray(dW, dtype=float)
    nw = dW.shape[1] if n_wheels is None else n_wheels
    if dW.shape != (3, nw) or nw % 2:
        raise ValueError(f"wear_by_wheel: expected (3, 2n) per-wheel wear, got {dW.shape}")

    def entry(cols) -> dict:
        w = dW[:, cols].sum(axis=1)
        return {"W_s": float(w[0]), "W_alpha": float(w[1]), "W_t": float(w[2]),
                "W_tw": float(w.sum())}

    wheels = {f"{k // 2 + 1}{k % 2 + 1}": entry([k]) for k in range(nw)}
    axles = {str(i + 1): entry([2 * i, 2 * i + 1]) for i in range(nw // 2)}
    return {"wheels": wheels, "axles": axles}


def format_wheel_wear(wear: dict | None) -> list[str]:
    """Lines for a run's table: W_tw per axle and per wheel [J] with each one's share."""
    if not wear:
        return ["  per wheel  n/a (no per-wheel wear work recorded)"]
    total = sum(a["W_tw"] for a in wear["axles"].values())

    def share(x):
        return f" ({100.0 * x / total:.0f} %)" if total > 0 else ""

    axles = ", ".join(f"{i}: {a['W_tw']:.4g}{share(a['W_tw'])}" for i, a in wear["axles"].items())
    wheels = ", ".join(f"{k}: {w['W_tw']:.4g}" for k, w in wear["wheels"].items())
    return [f"  per axle   W_tw [J] {axles}", f"  per wheel  W_tw [J] {wheels}"]
