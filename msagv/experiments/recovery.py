"""A recovery from an initial error (the study's Case 2) measured as a recovery: how long the
vehicle takes to reach a band around the path and stay in it, how far it swings past the
path on the way, and the tire wear it spends until then; and fronts read between their runs.

Case 2's question is the recovery, not the tracking of a path: its lateral RMS error over a
run is nearly all the first seconds, and a front of a few runs compared at "equal RMS
error" hinges on the one run that happens to be matched (issue 29). These metrics compare
the recoveries themselves.

* :func:`recovery`: ``t_settle`` (the first time from which ``|lateral error| <= band`` to
  the run's end; None when the run ends outside the band), ``overshoot`` (the largest
  excursion to the other side of the path after the largest one), ``W_settle`` (the wear
  work spent until ``t_settle``), ``peak``.
* :func:`recovery_of_log`: the same from a run's per-step CSV log
  (:meth:`controller.loop.RunLog.to_csv`).
* :func:`matched_recovery`: each wear-aware recovery against the cheapest wear-blind one
  that is at least as good (settles no later, strays from the path and swings past it no
  further), the blind side optionally given a slack.
* :func:`wear_interpolated`: a front's wear at an error between two of its runs, read on
  the straight line between them in log-log (the step rule of the study credits only what
  a run reached; this one what a mix of two neighbouring runs would).
"""

from __future__ import annotations

import math

import numpy as np

BAND_M = 0.05  # m: the lateral band a recovery enters and stays in
WEAR_COLUMNS = ("W_s", "W_alpha", "W_t")


def lateral_error(pose, ref_pose) -> np.ndarray:
    """The signed cross-track error [m] of poses ``(x, y, phi)`` against the reference's
    (left of the reference's heading positive), as :func:`controller.metrics.tracking_errors`
    measures it."""
    pose, ref_pose = np.asarray(pose, float), np.asarray(ref_pose, float)
    c, s = np.cos(ref_pose[:, 2]), np.sin(ref_pose[:, 2])
    return -(pose[:, 0] - ref_pose[:, 0]) * s + (pose[:, 1] - ref_pose[:, 1]) * c


def recovery(t, lat, W, band: float = BAND_M) -> dict:
    """The recovery of one run from its samples: times ``t`` [s], lateral errors ``lat``
    [m] and the cumulative wear work ``W`` [J] at those times.

    ``t_settle`` [s from the first sample]: the first sample from which every later sample
    lies within ``band`` (None: the last sample is outside, the run did not recover);
    ``W_settle`` [J]: ``W`` there minus ``W`` at the first sample (None likewise);
    ``peak`` [m]: the largest ``|lat|``; ``overshoot`` [m]: the largest excursion to the
    other side of the path after the peak (0 when it never crosses)."""
    t, lat, W = (np.asarray(a, dtype=float).reshape(-1) for a in (t, lat, W))
    if not (len(t) == len(lat) == len(W)) or len(t) == 0:
        raise ValueError(f"recovery: t, lat and W need one value per sample, got "
                         f"{len(t)}, {len(lat)}, {len(W)}")
    if not band > 0:
        raise ValueError(f"recovery: the band must be > 0 m, got {band}")
    i = int(np.argmax(np.abs(lat)))
    side = 1.0 if lat[i] >= 0 else -1.0
    overshoot = max(0.0, float(np.max(-side * lat[i:])))
    out_ = np.nonzero(np.abs(lat) > band)[0]
    k = 0 if len(out_) == 0 else int(out_[-1]) + 1
    settled = k < len(t)
    return {"t_settle": float(t[k] - t[0]) if settled else None,
            "W_settle": float(W[k] - W[0]) if settled else None,
            "peak": float(abs(lat[i])), "overshoot": overshoot}


def recovery_of_log(path, bands=(BAND_M,)) -> dict[float, dict]:
    """:func:`recovery` of a run's per-step CSV log at each band: ``{band: recovery}``.
    The wear work is the sum of its ``W_s, W_alpha, W_t`` columns."""
    with open(path) as f:
        names = f.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    col = {n: i for i, n in enumerate(names)}
    missing = [n for n in ("t", "x", "y", "phi", "x_ref", "y_ref", "phi_ref") + WEAR_COLUMNS
               if n not in col]
    if missing:
        raise ValueError(f"{path}: a run log without the columns {', '.join(missing)}")
    pose = data[:, [col["x"], col["y"], col["phi"]]]
    ref = data[:, [col["x_ref"], col["y_ref"], col["phi_ref"]]]
    W = sum(data[:, col[n]] for n in WEAR_COLUMNS)
    lat = lateral_error(pose, ref)
    return {b: recovery(data[:, col["t"]], lat, W, b) for b in bands}


def matched_recovery(aware, blind, slack: float = 0.0, slack_t: float = 0.0) -> dict:
    """Each wear-aware recovery against the wear-blind ones at least as good.

    ``aware``, ``blind``: ``(t_settle, peak, overshoot, W_settle)`` of the runs that
    recovered. For a wear-aware run, the blind runs that settle no later (plus
    ``slack_t``), stray no further from the path (peak) and swing past it no further
    (overshoot; both plus ``slack``, in their unit) are its matches; its ratio is its wear
    over the least wear of its matches. A wear-aware run no blind run matches (it recovers
    better than every one) is compared with the cheapest blind run instead (conservative
    for the wear term) and counted as unmatched.

    Only the wear-aware runs on their own front count (no other aware run at least as good
    on all four), each once. Returns ``{ratio, n, matched, ratios}``: ``ratio`` the
    geometric mean over those runs (None without a run on either side), ``matched`` how
    many had a real match."""
    aware = [tuple(map(float, a)) for a in aware]
    blind = [tuple(map(float, b)) for b in blind]
    if not aware or not blind:
        return {"ratio": None, "n": 0, "matched": 0, "ratios": []}
    front = sorted({a for a in aware
                    if not any(all(x <= y for x, y in zip(b, a)) and b != a for b in aware)})
    cheapest = min(b[3] for b in blind)
    ratios, matched = [], 0
    for t, pk, o, w in front:
        ok = [b[3] for b in blind if b[0] <= t + slack_t + 1e-9
              and b[1] <= pk + slack + 1e-12 and b[2] <= o + slack + 1e-12]
        if ok:
            matched += 1
        ratios.append(w / min(ok) if ok else w / cheapest)
    good = [r for r in ratios if r > 0 and math.isfinite(r)]
    ratio = float(np.exp(np.mean(np.log(good)))) if good else None
    return {"ratio": ratio, "n": len(front), "matched": matched, "ratios": ratios}


def wear_interpolated(front, e: float) -> float | None:
    """A front's wear at the error ``e``, read between its runs: ``front`` the lower
    envelope ``[(e, W), ...]`` sorted by e (W falling). Between two neighbouring runs the
    straight line in (log e, log W); beyond the least accurate run its wear (it reaches
    any larger error); below the most accurate run None (nothing is extrapolated)."""
    if not front or e < front[0][0] * (1 - 1e-9):
        return None
    if e >= front[-1][0]:
        return float(front[-1][1])
    for (e0, w0), (e1, w1) in zip(front, front[1:]):
        if e0 * (1 - 1e-9) <= e <= e1:
            if e1 <= e0 or w0 <= 0 or w1 <= 0:
                return float(min(w0, w1) if e >= e1 else w0)
            f = (math.log(e) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return float(math.exp(math.log(w0) + f * (math.log(w1) - math.log(w0))))
    return float(front[-1][1])


def front_ratio(aware, blind, slack: float = 0.0, wear_at=wear_interpolated,
                grid: int = 50) -> float | None:
    """The geometric mean of ``W_aware(e) / W_blind(e + slack)`` over the errors ``e``
    both fronts cover (the aware front at e, the blind one at e + slack: the blind side may
    be ``slack`` less accurate), on ``grid`` points evenly spaced in log e. A front's wear
    at an error is ``wear_at(front, e)``: :func:`wear_interpolated` (default) or the
    study's step rule (:func:`experiments.study_analysis.wear_within`). ``aware``,
    ``blind``: lower envelopes ``[(e, W), ...]`` sorted by e. None where they share no
    error."""
    if not aware or not blind:
        return None
    lo = max(aware[0][0], blind[0][0] - slack)
    hi = min(aware[-1][0], blind[-1][0] - slack)
    if lo > hi or lo <= 0:
        return None
    es = np.geomspace(lo, hi, grid) if hi > lo else np.array([lo])
    logs = []
    for e in es:
        wa, wb = wear_at(aware, e), wear_at(blind, e + slack)
        if wa is None or wb is None or not (wa > 0 and wb > 0):
            continue
        logs.append(math.log(wa / wb))
    return float(np.exp(np.mean(logs))) if logs else None
