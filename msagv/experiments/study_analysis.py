"""The study's analysis: the wear-aware and wear-blind fronts compared at equal tracking
error, the tolerance forms beside it, unmatched scenarios counted, bootstrap confidence
intervals over scenarios; tables, figures and one JSON document.

Per scenario instance (a path, speed, vehicle, load, plant, start and annealer seed):

* every finished run is a point ``(e, W)``: its RMS lateral error [cm] and its tire wear
  work [J]; errors below :data:`RESOLUTION_CM` (1 mm) count as 1 mm, so runs that all
  track within a millimetre are compared on their wear, not on differences of hundredths
  of a millimetre;
* the *wear-blind front* is the lower envelope of the points of every family without a
  wear term (FF, NTWO, NTWO-wheel, NTWO-wheel-Q, NTWO-wheel-cut, Kinematic, DH, TCT,
  NTWO-raw), the *wear-aware front* that of TWO and TWO-energy (and TWO-energy-raw);
* a front's wear at an error ``e`` is **the least wear of its runs with an error of e or
  less** (:func:`wear_within`, a step: no wear is credited that no run reached, and
  nothing is extrapolated);
* **at equal error**: over the range of errors both fronts cover (from the larger of their
  most accurate runs to the smaller of their least accurate ones) the ratio
  ``W_aware(e) / W_blind(e)``, reported as its geometric mean over that range (on a grid
  of :data:`GRID` points evenly spaced in log e) and at the levels :data:`LEVELS_CM` that
  lie in it. Below 1: the wear term bought less wear at the same accuracy than anything
  without it. Where the ranges do not overlap the instance is *unmatched*, with the
  reason;
* **tolerance forms**: the same ratio at ``e = NTWO's error + d`` for ``d`` in
  :data:`TOLERANCES_CM` (each side may spend the slack it can reach);
* **most accurate**: the aware front's most accurate run against the least wear of the
  blind runs at least as accurate (the cheapest blind run if none is): the conservative
  ratio an unmatched instance enters the pooled number with.

Case 2 (a recovery from an initial error, :func:`case2_compare`) is compared three ways,
every start counted in every column (an unmatched one at its conservative fill): on the
recovery itself (:mod:`experiments.recovery`: the wear until the vehicle is in a 5 cm band
for good, against the blind runs that settle no later and stray and overshoot no
further), at equal RMS error by the step rule, and on fronts read between their runs;
each without the blind side's Case 2 levers, with them, and with them and 0.5 cm of
matching slack (issue 29's check: does the ratio move by less than its interval?).

Across scenarios: an instance's ratios are averaged (in logs) over its annealer seeds first
(a scenario counts once however many seeds it has), then the geometric mean over the
scenarios of a group and a 95 % percentile bootstrap interval that resamples scenarios
(``scipy.stats.bootstrap``); the spread across seeds within a scenario is reported apart as
the solver's noise.
"""

from __future__ import annotations

import csv
import inspect
import json
import math
from pathlib import Path

import numpy as np

from msagv.controller.floors import (BROKEN_RATIO, FLOOR_TOL_M, FLOOR_TOL_PHI_DEG, NO_FLOOR_J,
                                     broken_floor)
from msagv.experiments.results import floor_errors, split_below_floor, within_floor_bounds

from .families import FAMILIES
from .recovery import BAND_M, front_ratio, matched_recovery, recovery_of_log
from .tables import fmt, lower_front

METRICS = ("W_tw", "W_s", "W_alpha", "W_t", "e_lat_rms_cm", "e_lat_max_cm", "e_pos_max_cm",
           "e_phi_deg", "e_phi_max_deg", "e_bar", "Omega",
           "W_tw_per_km")  # W_tw_per_km: controller.metrics.work_per_km
WITHIN = f"{100.0 * FLOOR_TOL_M:g} cm and {FLOOR_TOL_PHI_DEG:g} deg"  # what a floor holds to
BEYOND = f"{100.0 * FLOOR_TOL_M:g} cm or {FLOOR_TOL_PHI_DEG:g} deg"  # and what leaves it
BOOTSTRAP = 2000
LEVELS_CM = (0.25, 0.5, 1.0, 2.0)  # equal-error levels [cm of lateral RMS]
TOLERANCES_CM = (0.5, 1.0, 5.0)  # the tolerance forms: NTWO's error + these [cm]
GRID = 50  # points of the equal-error mean, evenly spaced in log e over the shared range
RESOLUTION_CM = 0.1  # cm: lateral RMS errors below this count as this (1 mm: finer
#                      differences are no distinction between controllers)
NO_WEAR_J = NO_FLOOR_J  # J: a floor below this (a straight path) is not divided by; a scenario
#                  whose every run wears less has nothing to compare
CLASS_ORDER = ("case1", "case2", "lane", "turn", "random", "fresh", "load", "4-axle", "robust",
               "user")
NOMINAL = "all nominal"
NOMINAL_NO_CASE2 = "all nominal without case2"


def lower_envelope(points):
    """The non-dominated ``(e, W)`` points (both minimised), sorted by e (W falling)."""
    return lower_front(points)


def wear_within(front, e):
    """The least wear of the front's runs with an error of ``e`` or less (the step rule);
    None if every run is less accurate than ``e``."""
    w = [pw for pe, pw in front if pe <= e * (1 + 1e-9)]
    return float(min(w)) if w else None


def shared_range(aware, blind):
    """``(lo, hi)``: the errors both fronts cover, or None where they do not overlap."""
    if not aware or not blind:
        return None
    lo, hi = max(aware[0][0], blind[0][0]), min(aware[-1][0], blind[-1][0])
    return (lo, hi) if lo <= hi else None


def equal_error(aware, blind) -> dict:
    """The ratio of two fronts at equal error (module docstring): ``{range, mean, at}``;
    ``mean`` None where the fronts share no range."""
    rng = shared_range(aware, blind)
    out = {"range": rng, "mean": None, "at": {lv: None for lv in LEVELS_CM}}
    if rng is None:
        return out
    lo, hi = rng
    grid = np.geomspace(max(lo, 1e-9), max(hi, 1e-9), GRID) if hi > lo else np.array([lo])
    logs = [math.log(wear_within(aware, e) / wear_within(blind, e)) for e in grid]
    out["mean"] = float(np.exp(np.mean(logs)))
    for lv in LEVELS_CM:
        if lo <= lv <= hi:
            out["at"][lv] = wear_within(aware, lv) / wear_within(blind, lv)
    return out


def most_accurate_ratio(aware_pts, blind_pts, slack: float = 0.0) -> float | None:
    """The aware side's most accurate run against the least wear of the blind runs at least
    as accurate (or at most ``slack`` less), or of every blind run if none is (conservative
    for the wear term)."""
    if not aware_pts or not blind_pts:
        return None
    e0, w0 = min(aware_pts)
    ok = [w for e, w in blind_pts if e <= e0 * (1 + 1e-9) + slack]
    return w0 / min(ok or [w for _, w in blind_pts])


def _row(r: dict, floors: dict, described: dict | None = None) -> dict:
    """One run as a row of the study's table: its family, scenario, metrics and floors."""
    t = r["spec"]["tags"]
    m = r.get("metrics") or {}
    fl = (floors.get(t["path_key"]) or {}).get("floors", {})
    row = {"family": t["family"], "label": r["spec"]["label"], "lever": t["lever"],
           "level": t["level"], "aware": t["aware"], "scenario": t["scenario"],
           "class": t["class"], "plant": t["plant"], "seed": t["seed"],
           "path_key": t["path_key"], "unit": t.get("unit", t["path_key"]),
           "status": r["status"], "error": r.get("error"), "key": r["key"],
           "wall_s": r.get("wall_s")}
    d = (described or {}).get(t["scenario"]) or {}
    row.update({k: d.get(k) for k in ("vehicle", "speed_kmh")})
    row.update({k: m.get(k) for k in METRICS})
    row.update(fl)
    if m.get("W_tw") is not None and fl:
        row["W_above_floor"] = m["W_tw"] - fl["W_tw_floor"]
        # a straight path's floor is zero (the recovery from an initial error is not part of
        # it): there the ratio is undefined, not astronomically large
        row["W_over_floor"] = (m["W_tw"] / fl["W_tw_floor"] if fl["W_tw_floor"] >= NO_WEAR_J
                               else None)
        # below 0.995 of its floor within its 1 cm: the floor is broken on this path (never
        # silently); further off the path a run is below it without breaking it (said too)
        broken, off = split_below_floor(broken_floor(m, fl), m)
        row["floor_broken"] = [b["part"] for b in broken] or None
        row["below_floor_off_path"] = [b["part"] for b in off] or None
    return row


def floor_check(rows: list[dict]) -> dict:
    """The floor held against every run that had one: how many runs kept within what it
    bounds (:func:`experiments.results.split_below_floor`: 1 cm of the reference's position
    and 2 deg of its heading), the least ``W_tw / floor`` among them (its run), and how many
    runs went below ``BROKEN_RATIO`` of it within (broken) and off the path. Each run
    once (the feed-forward's, shared by a scenario's seeds, has a row per seed)."""
    runs = list({r["key"]: r for r in rows
                 if r.get("W_tw") is not None and r.get("W_tw_floor") is not None
                 and r["W_tw_floor"] >= NO_WEAR_J}.values())
    within = [r for r in runs if within_floor_bounds(r)]
    least = min(within, key=lambda r: r["W_tw"] / r["W_tw_floor"], default=None)
    return {"runs": len(runs), "within": len(within),
            "least_within": None if least is None else {
                "W_over_floor": least["W_tw"] / least["W_tw_floor"], "label": least["label"],
                "scenario": least["scenario"], "e_pos_max_cm": least.get("e_pos_max_cm"),
                "e_phi_max_deg": least.get("e_phi_max_deg")},
            "broken": sum(1 for r in runs if r.get("floor_broken")),
            "below_off_path": sum(1 for r in runs if r.get("below_floor_off_path"))}


def floor_check_line(fc: dict) -> str | None:
    """:func:`floor_check` in one sentence (None without runs against a floor)."""
    if not fc["runs"]:
        return None
    lw = fc["least_within"]
    least = ("" if lw is None else
             f"; the least W_tw / floor among them {lw['W_over_floor']:.3f} ({lw['label']}, "
             f"{lw['scenario']})")
    return (f"The wear floor against {fc['runs']} runs: {fc['within']} kept within "
            f"{WITHIN} of the path{least}; {fc['broken']} below {BROKEN_RATIO} x it within "
            f"(broken), {fc['below_off_path']} below it off the path.")


def _stray_range(rs: list[dict]) -> str:
    """The off-path runs' largest distances from the path [cm] and heading errors [deg], as
    ranges ("4.0-7.1 cm, 0.84-1.4 deg"; rows that predate them: their lateral error)."""
    def rng(vals, unit):
        v = [x for x in vals if x is not None]
        if not v:
            return []
        lo, hi = min(v), max(v)
        return [f"{_f(lo, 3)} {unit}" if lo == hi else f"{_f(lo, 3)}-{_f(hi, 3)} {unit}"]

    errs = [floor_errors(r) for r in rs]
    return ", ".join(rng([e for e, _ in errs], "cm") + rng([h for _, h in errs], "deg"))


def broken_floor_warnings(rows: list[dict]) -> list[str]:
    """One warning per scenario instance with runs below 0.995 of their floor within what it
    bounds (1 cm and 2 deg of the path: :func:`experiments.results.split_below_floor`):
    how many, which parts, the lowest ratio and that run's lateral error; and one line per
    instance whose runs went below it only off the path (they do not break it: said, never
    silent)."""
    out = []
    for field, off in (("floor_broken", False), ("below_floor_off_path", True)):
        by: dict[str, list[dict]] = {}
        for r in rows:
            if r.get(field):
                by.setdefault(r["scenario"], []).append(r)
        for sc, rs in by.items():
            n = sum(1 for r in rows if r["scenario"] == sc and r.get("W_tw") is not None)
            parts = sorted({p for r in rs for p in r[field]})
            ratios = []
            for r in rs:
                for p in r[field]:
                    w = r["W_s"] + r["W_alpha"] if p == "W_slip" else r[p]
                    f = (r["W_s_floor"] + r["W_alpha_floor"] if p == "W_slip"
                         else r[p + "_floor"])
                    ratios.append((w / f, p, r))
            q, p, worst = min(ratios, key=lambda x: x[0])
            head = (f"{len(rs)} of {n} runs wear less than {BROKEN_RATIO} x the wear floor of "
                    f"any motion within {WITHIN} of the path ({', '.join(parts)}; lowest {p} "
                    f"{q:.3f} x its floor, {worst['label']}, lateral RMS "
                    f"{_f(worst.get('e_lat_rms_cm'), 3)} cm")
            if off:
                out.append(f"below the floor off the path: {sc}: {head}), each straying "
                           f"beyond {BEYOND} ({_stray_range(rs)}): the floor bounds only "
                           f"motions within {WITHIN}, so these runs do not break it")
            else:
                out.append(f"broken floor: {sc}: {head}): the floor is not a lower bound "
                           f"on this path, and its W_tw / floor figures are not wear above "
                           f"a floor")
    return out


# ---- one scenario instance ------------------------------------------------------------------
def compare(rows: list[dict]) -> list[dict]:
    """Per scenario instance: both fronts, the ratio at equal error, the tolerance forms,
    the most-accurate ratio, each wear-aware family alone, and why an instance is
    unmatched."""
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r["scenario"], []).append(r)
    return [_compare_one(name, rs) for name, rs in by.items()]


def _points(rows, pick) -> list[tuple[float, float]]:
    """``(e, W)`` of the rows ``pick`` selects, the error at :data:`RESOLUTION_CM` or more."""
    return [(max(r["e_lat_rms_cm"], RESOLUTION_CM), r["W_tw"]) for r in rows if pick(r)]


def _compare_one(name: str, rs: list[dict]) -> dict:
    ok = [r for r in rs if r["status"] == "ok" and r["W_tw"] is not None
          and r["e_lat_rms_cm"] is not None]
    first = rs[0]
    ntwo = [r for r in ok if r["family"] == "NTWO"]
    e_ntwo = ntwo[0]["e_lat_rms_cm"] if ntwo else None
    a_pts, b_pts = _points(ok, lambda r: r["aware"]), _points(ok, lambda r: not r["aware"])
    aware, blind = lower_envelope(a_pts), lower_envelope(b_pts)
    eq = equal_error(aware, blind)
    d = {"scenario": name, "class": first["class"], "plant": first["plant"],
         "unit": first["unit"], "path_key": first["path_key"], "seed": first["seed"],
         "vehicle": first.get("vehicle"), "speed_kmh": first.get("speed_kmh"),
         "e_ntwo_cm": e_ntwo, "W_tw_floor": first.get("W_tw_floor"),
         "range_cm": eq["range"], "ratio": eq["mean"],
         **{f"at:{lv:g}": eq["at"][lv] for lv in LEVELS_CM},
         "most_accurate": most_accurate_ratio(a_pts, b_pts),
         "blind_front": blind, "aware_front": aware}
    d["reason"] = _unmatched_reason(ok, aware, blind)
    if d["reason"] is not None:
        d["ratio"] = None
    for tol in TOLERANCES_CM:
        e = None if e_ntwo is None else e_ntwo + tol
        wa = None if e is None else wear_within(aware, e)
        wb = None if e is None else wear_within(blind, e)
        d[f"tol:{tol:g}"] = (None if wa is None or wb is None or d["reason"] == _NO_WEAR
                             else wa / wb)
    e1 = None if e_ntwo is None else e_ntwo + 1.0
    d["best_blind"] = _best(ok, False, e1)
    d["best_aware"] = _best(ok, True, e1)
    # each wear-aware family on its own against the whole wear-blind front: which cost form
    # carries the result (the paper's quadratic or the wear energy)
    for fam in sorted({r["family"] for r in ok if r["aware"]}):
        front = lower_envelope(_points(ok, lambda r, f=fam: r["family"] == f))
        d[f"family:{fam}"] = None if d["reason"] == _NO_WEAR else equal_error(front, blind)["mean"]
    if first["class"] == "case2":
        d.update(case2_compare(ok, aware, a_pts))
        # the paper's quadratic term alone (the page's Case 2 sentence is about it)
        two = [r for r in ok if not r["aware"] or r["family"] == "TWO"]
        d.update(case2_compare(two, lower_envelope(_points(two, lambda r: r["aware"])),
                               _points(two, lambda r: r["aware"]), prefix="c2TWO"))
    return d


# ---- Case 2: the recovery compared (issue 29 item 2) ---------------------------------------
SLACK_CM = 0.5  # the matching slack the blind side gets in the robustness check [cm]
CASE2_LEVERS = frozenset(f.name for f in FAMILIES.values()
                         if f.classes == ("case2",) and not f.wear_aware)
# Case 2's measures: (key, what it is); each enters every instance (an unmatched one at its
# conservative fill, counted under KEY:unmatched)
CASE2_FORMS = (
    ("recovery", "recovery: wear until settled in the 5 cm band, against the cheapest blind "
                 "run settling no later, straying and overshooting no further (every aware "
                 "run on its front)"),
    ("step", "equal lateral RMS error, the step rule (the study's headline form)"),
    ("interp", "equal lateral RMS error, the fronts read between their runs (log-log)"),
)
# the three ways each form is measured: the blind side without the recovery levers and no
# slack (as the study reported), with the levers, with the levers and 0.5 cm of slack
CASE2_VARIANTS = (("base", "blind side without the recovery levers"),
                  ("levers", "with the recovery levers"),
                  ("slack", f"with the levers and {SLACK_CM:g} cm of matching slack"))


def _recovery_points(rows, pick, slack: bool = False) -> list[tuple[float, float, float]]:
    """``(t_settle [s], peak [cm], overshoot [cm], W_settle [J])`` of the rows ``pick``
    selects that recovered; ``slack``: settled into the band widened by :data:`SLACK_CM`."""
    ts, ws = ("t_settle_slack_s", "W_settle_slack") if slack else ("t_settle_s", "W_settle")
    return [(r[ts], r["peak_cm"], r["overshoot_cm"], r[ws]) for r in rows
            if pick(r) and r.get(ts) is not None and r.get(ws) is not None]


def case2_compare(ok: list[dict], aware: list, a_pts: list, prefix: str = "c2") -> dict:
    """A Case 2 instance's recovery compared three ways (:data:`CASE2_FORMS`), each
    without the blind side's recovery levers, with them, and with them and
    :data:`SLACK_CM` of slack (:data:`CASE2_VARIANTS`); every value filled for an
    unmatched instance (``c2:FORM:VARIANT:unmatched`` True), so no Case 2 column drops a
    start. And whether the plain feed-forward beats every wear-aware run (``c2:ff_wins``:
    at least as accurate and no more wear, on the lateral RMS and on the recovery).
    ``prefix``: the keys' first part (``c2``; ``c2TWO`` for the quadratic term alone)."""
    out: dict = {}
    base_pick = lambda r: not r["aware"] and r["family"] not in CASE2_LEVERS  # noqa: E731
    blind_pick = lambda r: not r["aware"]  # noqa: E731
    rec_a = _recovery_points(ok, lambda r: r["aware"])
    for var, pick, slack in (("base", base_pick, 0.0), ("levers", blind_pick, 0.0),
                             ("slack", blind_pick, SLACK_CM)):
        b_pts = _points(ok, pick)
        blind = lower_envelope(b_pts)
        ma = most_accurate_ratio(a_pts, b_pts, slack)
        for form, rule in (("step", wear_within), ("interp", None)):
            kw = {} if rule is None else {"wear_at": rule}
            v = front_ratio(aware, blind, slack, **kw) if aware and blind else None
            out[f"{prefix}:{form}:{var}"] = v if v is not None else ma
            out[f"{prefix}:{form}:{var}:unmatched"] = v is None
        rec_b = _recovery_points(ok, pick, slack=bool(slack))
        m = matched_recovery(rec_a, rec_b, slack=slack)
        out[f"{prefix}:recovery:{var}"] = m["ratio"]
        out[f"{prefix}:recovery:{var}:unmatched"] = m["n"] > 0 and m["matched"] == 0
        out[f"{prefix}:recovery:{var}:runs"] = [m["matched"], m["n"]]
    ff = [r for r in ok if r["family"] == "FF"]
    aw = [r for r in ok if r["aware"]]
    if ff and aw:
        f = ff[0]
        rms = [f["e_lat_rms_cm"] <= a["e_lat_rms_cm"] and f["W_tw"] <= a["W_tw"] for a in aw]
        rec = [f.get("t_settle_s") is not None and (
            a.get("t_settle_s") is None or
            (f["t_settle_s"] <= a["t_settle_s"] and f["overshoot_cm"] <= a["overshoot_cm"]
             and f["peak_cm"] <= a["peak_cm"] and f["W_settle"] <= a["W_settle"]))
            for a in aw]
        # the plain feed-forward beats how many of the wear-aware runs (at least as
        # accurate and no more wear), of how many; ff_wins: all of them
        out[f"{prefix}:ff_beats"] = [sum(rms), len(aw)]
        out[f"{prefix}:ff_beats_recovery"] = [sum(rec), len(aw)]
        out[f"{prefix}:ff_wins"] = all(rms)
        out[f"{prefix}:ff_wins_recovery"] = all(rec)
    return out


def add_recovery(rows: list[dict], out: Path) -> None:
    """The recovery metrics (:func:`experiments.recovery.recovery`) of every finished
    Case 2 run, from its per-step log under ``out/runs/``: ``t_settle_s``, ``W_settle``,
    ``overshoot_cm``, ``peak_cm`` at the 5 cm band, and ``t_settle_slack_s``,
    ``W_settle_slack`` at the band widened by :data:`SLACK_CM`."""
    wide = BAND_M + SLACK_CM / 100.0
    for r in rows:
        if r["class"] != "case2" or r["status"] != "ok":
            continue
        p = out / "runs" / f"{r['key']}.csv"
        if not p.is_file():
            continue
        rec = recovery_of_log(p, (BAND_M, wide))
        a, b = rec[BAND_M], rec[wide]
        r.update(t_settle_s=a["t_settle"], W_settle=a["W_settle"],
                 overshoot_cm=100.0 * a["overshoot"], peak_cm=100.0 * a["peak"],
                 t_settle_slack_s=b["t_settle"], W_settle_slack=b["W_settle"])


def case2_summary(items: list[dict]) -> dict | None:
    """Case 2's pooled forms (every instance counted: the unmatched at their fill), the
    goal's check (does the form's ratio move by less than its own interval when the blind
    side gets the levers and the slack?) and where the plain feed-forward wins."""
    items = [d for d in items if any(k.startswith("c2:") for k in d)]
    if not items:
        return None
    out = {}
    for who, prefix in (("aware", "c2"), ("TWO", "c2TWO")):
        forms, goal = {}, {}
        for form, _ in CASE2_FORMS:
            f = {}
            for var, _ in CASE2_VARIANTS:
                key = f"{prefix}:{form}:{var}"
                p = pooled(items, key)
                p["unmatched"] = sum(1 for d in items if d.get(key + ":unmatched"))
                f[var] = p
            forms[form] = f
            b, s = f["base"], f["slack"]
            if b["gmean"] is not None and s["gmean"] is not None and b["ci95"][0] is not None:
                lo, hi = b["ci95"]
                goal[form] = {
                    "base": b["gmean"], "with_levers_and_slack": s["gmean"],
                    "change": s["gmean"] / b["gmean"] - 1.0, "base_ci95": [lo, hi],
                    "inside_ci": bool(lo <= s["gmean"] <= hi)}
        out["forms" if who == "aware" else "forms_TWO"] = forms
        out["goal" if who == "aware" else "goal_TWO"] = goal
    # the former headline's form: the quadratic term alone, the step rule, the matched
    # starts only (the unmatched dropped), as the blind side gets the levers and the slack
    out["former"] = {var: pooled([d for d in items if not d.get(f"c2TWO:step:{var}:unmatched")],
                                 f"c2TWO:step:{var}") for var, _ in CASE2_VARIANTS}
    starts: dict[str, dict] = {}
    for d in items:
        st = starts.setdefault(_start(d["scenario"]), {
            "seeds": 0, "ff_wins": 0, "ff_wins_recovery": 0, "ff_beats": [0, 0],
            "ff_beats_recovery": [0, 0]})
        st["seeds"] += 1
        st["ff_wins"] += bool(d.get("c2:ff_wins"))
        st["ff_wins_recovery"] += bool(d.get("c2:ff_wins_recovery"))
        for k in ("ff_beats", "ff_beats_recovery"):
            st[k] = [a + b for a, b in zip(st[k], d.get(f"c2:{k}") or (0, 0))]
    for name, st in starts.items():
        ds = [d for d in items if _start(d["scenario"]) == name]
        for form, _ in CASE2_FORMS:
            for var, _ in CASE2_VARIANTS:
                v = [d[f"c2:{form}:{var}"] for d in ds if d.get(f"c2:{form}:{var}")]
                st[f"{form}:{var}"] = float(np.exp(np.mean(np.log(v)))) if v else None
    out["starts"] = starts
    return out


def _start(scenario: str) -> str:
    """A Case 2 instance's start (its name without the seed)."""
    return scenario.rsplit(", seed ", 1)[0]


_NO_WEAR = f"no wear to compare: every run wears under {NO_WEAR_J:g} J"


def _unmatched_reason(ok, aware, blind) -> str | None:
    if not blind:
        return "no wear-blind run finished"
    if not aware:
        return "no wear-aware run finished"
    if max(r["W_tw"] for r in ok) < NO_WEAR_J:
        return _NO_WEAR
    if shared_range(aware, blind) is None:
        side = "less" if aware[0][0] > blind[-1][0] else "more"
        return (f"the fronts share no error: every wear-aware run ({aware[0][0]:.2f}-"
                f"{aware[-1][0]:.2f} cm) is {side} accurate than every wear-blind one "
                f"({blind[0][0]:.2f}-{blind[-1][0]:.2f} cm)")
    return None


def _best(rows, aware: bool, e: float | None) -> str | None:
    """The run (aware or not) with the least wear among those at least as accurate as e."""
    if e is None:
        return None
    c = [r for r in rows if r["aware"] == aware and r["e_lat_rms_cm"] <= e * (1 + 1e-9)]
    return min(c, key=lambda r: r["W_tw"])["label"] if c else None


# ---- across scenarios -----------------------------------------------------------------------
def _bootstrap_kw() -> dict:
    from scipy.stats import bootstrap

    seed = np.random.default_rng(0)
    name = "rng" if "rng" in inspect.signature(bootstrap).parameters else "random_state"
    return {name: seed}


def pooled(items: list[dict], key: str = "ratio", fill: str | None = None) -> dict:
    """The geometric mean of ``key`` over the scenarios of ``items`` (instances; a
    scenario's seeds averaged in logs first) with its 95 % bootstrap interval over
    scenarios. ``fill``: the key an instance without ``key`` enters with instead (None:
    such instances are left out, and counted)."""
    from scipy.stats import bootstrap

    units: dict[str, list[float]] = {}
    missing = 0
    for d in items:
        v = d.get(key)
        if (v is None or not v > 0) and fill is not None and d.get("reason") != _NO_WEAR:
            v = d.get(fill)
        if v is None or not v > 0:
            missing += 1
            continue
        units.setdefault(d["unit"], []).append(math.log(v))
    means = np.array([np.mean(v) for v in units.values()])
    res = {"n": len(means), "instances": sum(len(v) for v in units.values()),
           "missing": missing, "gmean": None, "ci95": [None, None], "below_1": None,
           "seed_sd_pct": _seed_sd(units)}
    if not len(means):
        return res
    res.update(gmean=float(np.exp(means.mean())), below_1=int(np.sum(means < 0)),
               median=float(np.exp(np.median(means))))
    if len(means) >= 2:
        if np.ptp(means) == 0:
            lo = hi = float(means[0])
        else:
            ci = bootstrap((means,), np.mean, n_resamples=BOOTSTRAP, method="percentile",
                           **_bootstrap_kw()).confidence_interval
            lo, hi = ci.low, ci.high
        res["ci95"] = [float(np.exp(lo)), float(np.exp(hi))]
    return res


def _seed_sd(units: dict[str, list[float]]) -> float | None:
    """The solver's noise: the pooled standard deviation of the log ratio across annealer
    seeds within a scenario, in percent (None without a scenario of 2 or more seeds)."""
    var = [np.var(v, ddof=1) for v in units.values() if len(v) >= 2]
    return None if not var else float(100.0 * (math.exp(math.sqrt(np.mean(var))) - 1.0))


def groups_of(comparisons: list[dict]) -> dict[str, list[dict]]:
    """The summary's groups: each class, the nominal plant pooled (with and without Case 2;
    never the user's scenario), and the plants unlike the model."""
    classes = [c for c in CLASS_ORDER if any(d["class"] == c for d in comparisons)]
    classes += sorted({d["class"] for d in comparisons} - set(classes))
    groups = {c: [d for d in comparisons if d["class"] == c] for c in classes}
    nominal = [d for d in comparisons if d["plant"] == "nominal" and d["class"] != "user"]
    groups[NOMINAL] = nominal
    if any(d["class"] == "case2" for d in nominal):
        groups[NOMINAL_NO_CASE2] = [d for d in nominal if d["class"] != "case2"]
    other = [d for d in comparisons if d["plant"] != "nominal" and d["class"] != "user"]
    if other:
        groups["plant unlike the model"] = other
        for p in sorted({d["plant"] for d in other}):
            groups[f"plant: {p}"] = [d for d in other if d["plant"] == p]
    return groups


def summarise(comparisons: list[dict]) -> dict:
    """Per group: the ratio at equal error (over matched scenarios, and with the unmatched
    entered at their most-accurate ratio), at each level, the tolerance forms, each
    wear-aware family alone, and the unmatched instances with their reasons."""
    out = {}
    for g, items in groups_of(comparisons).items():
        fams = sorted({k[7:] for d in items for k in d if k.startswith("family:")})
        out[g] = {
            "scenarios": len({d["unit"] for d in items}), "instances": len(items),
            "equal_error": pooled(items),
            "with_unmatched": pooled(items, fill="most_accurate"),
            "at": {f"{lv:g}": pooled(items, f"at:{lv:g}") for lv in LEVELS_CM},
            "tolerance": {f"{t:g}": pooled(items, f"tol:{t:g}") for t in TOLERANCES_CM},
            "most_accurate": pooled(items, "most_accurate"),
            "by_family": {f: pooled([d for d in items if f"family:{f}" in d], f"family:{f}")
                          for f in fams},
            "unmatched": [{"scenario": d["scenario"], "reason": d["reason"],
                           "most_accurate": d["most_accurate"]}
                          for d in items if d["reason"] is not None],
        }
        if g == "case2":
            # Case 2: no column drops an unmatched start (issue 29): each enters at its
            # most-accurate ratio, and the recovery forms beside them
            out[g].update(
                equal_error=pooled(items, fill="most_accurate"),
                at={f"{lv:g}": pooled(items, f"at:{lv:g}", fill="most_accurate")
                    for lv in LEVELS_CM},
                tolerance={f"{t:g}": pooled(items, f"tol:{t:g}", fill="most_accurate")
                           for t in TOLERANCES_CM},
                by_family={f: pooled([d for d in items if f"family:{f}" in d], f"family:{f}",
                                     fill="most_accurate") for f in fams},
                case2=case2_summary(items))
    return out


def family_table(rows: list[dict]) -> list[dict]:
    """Per class, family and lever level: the means over its scenarios of the lateral error,
    the wear, the wear per km (issue 21's tire-life figures would join here), the wear over
    the floor."""
    groups = {}
    for r in rows:
        if r["status"] != "ok":
            continue
        groups.setdefault((r["class"], r["label"]), []).append(r)
    out = []
    for (cls, label), rs in groups.items():
        def mean(k):
            v = [r[k] for r in rs if r.get(k) is not None]
            return float(np.mean(v)) if v else None
        out.append({"class": cls, "label": label, "family": rs[0]["family"],
                    "level": rs[0]["level"], "aware": rs[0]["aware"], "n": len(rs),
                    "e_lat_rms_cm": mean("e_lat_rms_cm"), "e_phi_deg": mean("e_phi_deg"),
                    "W_tw": mean("W_tw"), "W_tw_per_km": mean("W_tw_per_km"),
                    "W_over_floor": mean("W_over_floor"),
                    "W_above_floor": mean("W_above_floor"), "e_bar": mean("e_bar")})
    order = {c: i for i, c in enumerate(CLASS_ORDER)}
    fam = {f: i for i, f in enumerate(FAMILIES)}
    out.sort(key=lambda d: (order.get(d["class"], 99), d["aware"], fam.get(d["family"], 99),
                            d["level"] if d["level"] is not None else -1))
    return out


# ---- the report: Markdown -------------------------------------------------------------------
def _ratio_text(s: dict | None, n: bool = False) -> str:
    if not s or s.get("gmean") is None:
        return "n/a"
    lo, hi = s["ci95"]
    ci = "" if lo is None else f" [{lo:.3f}, {hi:.3f}]"
    return f"{s['gmean']:.3f}{ci}" + (f" (n = {s['n']})" if n else "")


def _f(v, nd):
    return "n/a" if v is None else f"{v:.{nd}f}"


def _group_label(g: str, items_desc: dict | None) -> str:
    return g if not items_desc else f"{g} ({items_desc})"


def noise_text(noise: dict) -> str:
    """A design's measurement noise as the reports print it: ``v 0.01 m/s, r 0.002 rad/s``
    (the nonzero deviations, with their units)."""
    from msagv.plant.sensors import FIELDS

    return ", ".join(f"{k} {v:g} {FIELDS[k][1]}" for k, v in noise.items() if v)


def _md_head(runs: dict, described: dict) -> list[str]:
    vehicles: dict[str, list[str]] = {}
    for name, d in described.items():
        key = d["vehicle"] + (f" ({d['vehicle_file']})" if d.get("vehicle_file") else
                              " (built in)")
        vehicles.setdefault(key, []).append(name)
    L = ["# The study: wear at equal tracking error\n",
         f"{runs['runs']} runs on {runs.get('scenarios')} scenario instances "
         f"({runs.get('design')} design; {runs['executed']} run now, {runs['reused']} reused, "
         f"{runs['failed']} failed).\n",
         "Vehicles: " + "; ".join(f"{v} in {len(n)} instance{'s' * (len(n) > 1)}"
                                  + (f" ({', '.join(n)})" if len(n) <= 3 else "")
                                  for v, n in vehicles.items()) + ".\n"]
    if runs.get("measurement_noise"):
        L.append("Every controller measured the states with noise, as a real vehicle's "
                 f"odometry has (standard deviations: {noise_text(runs['measurement_noise'])}; "
                 "each instance's stream seeded by its annealer seed, the same for its "
                 "wear-aware and blind runs). The floors are the paths' own.\n")
    cut = [n for n, d in described.items() if not d["whole_path"]]
    if cut:
        L.append(f"Part of the path ({len(cut)} instances, the design's choice): "
                 + ", ".join(f"{n}: {described[n]['duration_s']:g} s" for n in cut[:6])
                 + (" ..." if len(cut) > 6 else "") + ".\n")
    L.append("A front's wear at an error e is the least wear of its runs with a lateral "
             "RMS error of e or less (a step: no wear no run reached is credited; errors "
             f"below {RESOLUTION_CM:g} cm count as {RESOLUTION_CM:g} cm). "
             "**Equal error**: the ratio wear-aware / wear-blind over the errors both "
             "fronts cover, its geometric mean on a log grid of that range; a scenario "
             "whose fronts share no error is unmatched. Across scenarios: seeds averaged "
             "first, then the geometric mean with a 95 % bootstrap interval resampling "
             "scenarios. Below 1: the wear term saves wear at the same accuracy.\n")
    return L


def _md_headline(summary: dict, user: str | None, noisy: bool = False) -> list[str]:
    """``noisy``: the controllers measured with noise, whose stream each seed also draws
    afresh: the spread across seeds is then the solver's and the measurement's."""
    spread = ("solver and measurement noise (SD across seeds)" if noisy
              else "solver noise (SD across seeds)")
    L = ["| scenarios | scenarios (instances) | unmatched | ratio at equal error [95 % CI] "
         "| below 1 | with the unmatched at their most-accurate ratio [95 % CI] | "
         f"{spread} |",
         "|---|---:|---:|---|---:|---|---:|"]
    for g, s in summary.items():
        eq = s["equal_error"]
        noise = s["with_unmatched"]["seed_sd_pct"]
        L.append(f"| {_group_label(g, user if g == 'user' else None)} | {s['scenarios']} "
                 f"({s['instances']}) | {len(s['unmatched'])} | {_ratio_text(eq)} | "
                 f"{eq['below_1'] if eq['below_1'] is not None else 'n/a'} of {eq['n']} | "
                 f"{_ratio_text(s['with_unmatched'])} | "
                 f"{'n/a' if noise is None else f'{noise:.1f} %'} |")
    return L


def _md_forms(summary: dict) -> list[str]:
    L = ["\n## At stated errors, and the tolerance forms\n",
         "The ratio at equal error at a few lateral RMS errors (where both fronts cover "
         "them: n scenarios); the tolerance forms at NTWO's own error plus a slack, where "
         "each side spends what it can reach (the same step rule); and the wear-aware "
         "side's most accurate run against the least wear of the blind runs at least as "
         "accurate.\n",
         "| scenarios | " + " | ".join(f"at {lv:g} cm" for lv in LEVELS_CM) + " | "
         + " | ".join(f"NTWO + {t:g} cm" for t in TOLERANCES_CM) + " | most accurate |",
         "|---|" + "---|" * (len(LEVELS_CM) + len(TOLERANCES_CM) + 1)]
    for g, s in summary.items():
        cells = [_ratio_text(s["at"][f"{lv:g}"], n=True) for lv in LEVELS_CM]
        cells += [_ratio_text(s["tolerance"][f"{t:g}"], n=True) for t in TOLERANCES_CM]
        cells.append(_ratio_text(s["most_accurate"], n=True))
        L.append(f"| {g} | " + " | ".join(cells) + " |")
    return L


def _md_families(summary: dict) -> list[str]:
    fams = [f for f in FAMILIES if any(f in s["by_family"] for s in summary.values())]
    if not fams:
        return []
    L = ["\n## Each wear-aware family alone against the wear-blind front (at equal error)\n",
         "Geometric mean [95 % CI] over the scenarios where the family's front shares an "
         "error range with the blind front (n): which cost form carries the result.\n",
         "| scenarios | " + " | ".join(fams) + " |", "|---|" + "---|" * len(fams)]
    for g, s in summary.items():
        bf = s["by_family"]
        L.append(f"| {g} | " + " | ".join(
            _ratio_text(bf[f], n=True) if f in bf and bf[f]["n"] else "" for f in fams) + " |")
    return L


def _md_case2(summary: dict) -> list[str]:
    """Case 2's recovery compared (:func:`case2_summary`), when the design has Case 2."""
    c2 = (summary.get("case2") or {}).get("case2")
    if not c2:
        return []
    L = ["\n## Case 2: the recovery compared\n",
         "Wear-aware / wear-blind, geometric mean over the starts [95 % bootstrap CI], every "
         "start counted (an unmatched one at its conservative fill: the aware side's best "
         "against the cheapest blind run if no blind run is as good; u: how many seeds of "
         "all were unmatched). The recovery levers are the Case 2 families "
         f"{', '.join(sorted(CASE2_LEVERS))}; the slack lets the blind side be {SLACK_CM:g} "
         "cm less accurate (the recovery: a band and an overshoot that much wider).\n",
         "| wear-aware | form | " + " | ".join(v for _, v in CASE2_VARIANTS)
         + " | goal: the last within the first's interval |",
         "|---|---|" + "---|" * (len(CASE2_VARIANTS) + 1)]
    for who, fk, gk in (("TWO and TWO-energy", "forms", "goal"),
                        ("TWO alone", "forms_TWO", "goal_TWO")):
        for form, what in CASE2_FORMS:
            f = c2[fk][form]
            cells = [f"{_ratio_text(f[v])} (u {f[v]['unmatched']} of "
                     f"{f[v]['instances'] + f[v]['missing']})" for v, _ in CASE2_VARIANTS]
            g = c2[gk].get(form)
            verdict = ("n/a" if g is None else
                       f"{'yes' if g['inside_ci'] else 'no'} ({100 * g['change']:+.0f} %)")
            L.append(f"| {who} | {what} | " + " | ".join(cells) + f" | {verdict} |")
    fo = c2["former"]
    L.append("| TWO alone | the former headline's form: the step rule over the matched seeds "
             "only (the unmatched dropped; n: starts) | "
             + " | ".join(_ratio_text(fo[v], n=True) for v, _ in CASE2_VARIANTS) + " | |")
    L += ["\nPer start (seeds pooled in logs). The plain feed-forward (FF, no optimisation) "
          "beats a wear-aware run where it is at least as accurate and wears no more: on "
          "the lateral RMS error and the wear (RMS), and on the recovery (settles no later, "
          "strays and overshoots no further, wears no more until then); the wear-aware runs "
          "it beats, of all the start's (every seed), and the seeds where it beats all:\n",
          "| start | recovery (levers) | step (levers) | interp (levers) | interp (levers + "
          "slack) | FF beats (RMS) | FF beats (recovery) | FF beats all (RMS / recovery) |",
          "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, st in c2["starts"].items():
        L.append(f"| {name} | {_f(st['recovery:levers'], 3)} | {_f(st['step:levers'], 3)} | "
                 f"{_f(st['interp:levers'], 3)} | {_f(st['interp:slack'], 3)} | "
                 f"{st['ff_beats'][0]} of {st['ff_beats'][1]} | "
                 f"{st['ff_beats_recovery'][0]} of {st['ff_beats_recovery'][1]} | "
                 f"{st['ff_wins']} / {st['ff_wins_recovery']} of {st['seeds']} seeds |")
    return L


def _md_unmatched(comparisons: list[dict]) -> list[str]:
    rows = [d for d in comparisons if d["reason"] is not None]
    if not rows:
        return ["\nEvery scenario matched.\n"]
    order = {c: i for i, c in enumerate(CLASS_ORDER)}
    L = ["\n## Unmatched scenarios (counted, not dropped)\n",
         "| class | scenario | why | most-accurate ratio (enters the pooled number) |",
         "|---|---|---|---:|"]
    for d in sorted(rows, key=lambda d: order.get(d["class"], 99)):
        L.append(f"| {d['class']} | {d['scenario']} | {d['reason']} | "
                 f"{_f(d['most_accurate'], 3) if d['reason'] != _NO_WEAR else 'n/a'} |")
    return L


def _md_family_table(fam: list[dict]) -> list[str]:
    L = ["\n## Families per scenario class (means over the class's scenarios)\n",
         "| class | run | wear-aware | e_lat RMS (cm) | e_phi RMS (deg) | W_tw (J) | "
         "W_tw per km (J/km) | W_tw / floor | above floor (J) |",
         "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for d in fam:
        L.append(f"| {d['class']} | {d['label']} | {'yes' if d['aware'] else ''} | "
                 f"{_f(d['e_lat_rms_cm'], 2)} | {_f(d['e_phi_deg'], 2)} | "
                 f"{fmt('W_tw', d['W_tw'])} | {fmt('W_tw', d.get('W_tw_per_km'))} | "
                 f"{_f(d['W_over_floor'], 3)} | {fmt('W_tw', d['W_above_floor'])} |")
    return L


def _md_scenarios(comparisons: list[dict]) -> list[str]:
    L = ["\n## Per scenario\n",
         "| scenario | vehicle | speed (km/h) | NTWO's e_lat (cm) | shared range (cm) | "
         "W floor (J) | ratio at equal error | at 1 cm | NTWO + 1 cm | best blind within "
         "NTWO + 1 cm | best aware within NTWO + 1 cm | most accurate |",
         "|---|---|---:|---:|---|---:|---:|---:|---:|---|---|---:|"]
    for d in comparisons:
        rng = d["range_cm"]
        L.append(f"| {d['scenario']} | {d.get('vehicle') or ''} | {_f(d.get('speed_kmh'), 1)} | "
                 f"{_f(d['e_ntwo_cm'], 2)} | "
                 f"{'none' if rng is None else f'{rng[0]:.2f}-{rng[1]:.2f}'} | "
                 f"{fmt('W_tw', d['W_tw_floor'])} | "
                 f"{_f(d['ratio'], 3) if d['reason'] is None else 'unmatched'} | "
                 f"{_f(d['at:1'], 3)} | {_f(d['tol:1'], 3)} | {d['best_blind'] or ''} | "
                 f"{d['best_aware'] or ''} | {_f(d['most_accurate'], 3)} |")
    return L


def user_label(described: dict) -> str | None:
    """What the user's scenario is: its vehicle on its path (None without one)."""
    users = {(d["vehicle"], Path(d["trajectory"]).name if d["trajectory"] else
              f"a {d['speed_kmh']:.0f} km/h random path") for n, d in described.items()
             if n.startswith("user")}
    return "; ".join(f"{v} on {p}" for v, p in sorted(users)) or None


def markdown(summary: dict, fam: list[dict], comparisons: list[dict], runs: dict,
             described: dict, broken: list[str] = (), floor_line: str | None = None) -> str:
    user = user_label(described)
    warn = ([f"**{'Note' if w.startswith('below the floor off') else 'Warning'}: {w}.**\n"
             for w in broken] if broken else [])
    warn += [floor_line + "\n"] if floor_line else []
    noisy = bool(runs.get("measurement_noise"))
    L = (_md_head(runs, described) + warn + _md_headline(summary, user, noisy)
         + _md_forms(summary)
         + _md_families(summary) + _md_case2(summary) + _md_unmatched(comparisons)
         + _md_family_table(fam)
         + _md_scenarios(comparisons))
    return "\n".join(L) + "\n"


# ---- the report: figures --------------------------------------------------------------------
def plot_fronts(fam: list[dict], rows: list[dict], path: Path,
                titles: dict | None = None) -> None:
    """Per scenario class: each family's mean wear over the floor against its mean lateral
    error, one point per lever level (a line along the lever), with 95 % bootstrap bars
    over the class's scenarios; the floor (the least wear within 1 cm and 2 deg of the path)
    as the line W / floor = 1.
    ``titles``: a panel's title other than its class's name (the user's scenario)."""
    from .plots import WIDTH, pyplot, style

    plt = pyplot()
    classes = [c for c in CLASS_ORDER if any(d["class"] == c for d in fam)]
    if not classes:
        return
    ncol = min(3, len(classes))
    nrow = math.ceil(len(classes) / ncol)
    with style():
        fig, axes = plt.subplots(nrow, ncol, figsize=(WIDTH * 1.35, 3.3 * nrow + 0.7),
                                 squeeze=False)
        for ax, cls in zip(axes.flat, classes):
            _front_panel(ax, cls, fam, rows)
            ax.set_title((titles or {}).get(cls, cls), fontsize=9)
        for ax in list(axes.flat)[len(classes):]:
            ax.axis("off")
        seen = {}
        for ax in axes.flat[:len(classes)]:
            for hh, ll in zip(*ax.get_legend_handles_labels()):
                seen.setdefault(ll, hh)
        fig.legend(list(seen.values()), list(seen.keys()), loc="lower center",
                   ncol=min(6, len(seen)), fontsize=8, frameon=False)
        fig.suptitle("Wear against accuracy per family (means over each class's scenarios, "
                     "95 % bootstrap bars)", fontsize=10)
        fig.tight_layout(rect=(0, 0.09, 1, 0.97))
        fig.savefig(path)
        plt.close(fig)


def _front_panel(ax, cls: str, fam: list[dict], rows: list[dict]) -> None:
    """One class's panel of :func:`plot_fronts`."""
    # W over the floor; absolute W_tw where the class's paths have no floor (a line)
    key = ("W_over_floor" if any(d["class"] == cls and d["W_over_floor"] is not None
                                 for d in fam) else "W_tw")
    rng = np.random.default_rng(1)
    pts = []
    for family, f in FAMILIES.items():
        color, marker = f.style
        ds = [d for d in fam if d["class"] == cls and d["family"] == family
              and d[key] is not None and d["e_lat_rms_cm"]]
        if not ds:
            continue
        xs, ys, xe, ye = [], [], [], []
        for d in ds:
            rs = [r for r in rows if r["class"] == cls and r["label"] == d["label"]
                  and r["status"] == "ok" and r.get(key) is not None]
            ex = np.array([r["e_lat_rms_cm"] for r in rs])
            wy = np.array([r[key] for r in rs])
            xs.append(ex.mean())
            ys.append(wy.mean())
            if len(rs) > 1:
                idx = rng.integers(0, len(rs), (400, len(rs)))
                bx = np.percentile(ex[idx].mean(1), [2.5, 97.5])
                by = np.percentile(wy[idx].mean(1), [2.5, 97.5])
            else:
                bx = by = np.array([np.nan, np.nan])
            xe.append(bx)
            ye.append(by)
        pts += [(x, y, color) for x, y in zip(xs, ys)]
        xe, ye = np.array(xe), np.array(ye)
        ax.errorbar(xs, ys, xerr=np.abs(xe.T - xs), yerr=np.abs(ye.T - ys),
                    fmt=marker + ("-" if len(xs) > 1 else ""), color=color, ms=5,
                    lw=1.0, elinewidth=0.7, capsize=2, label=family)
    _clip_outliers(ax, pts, key == "W_over_floor")
    if key == "W_over_floor":
        ax.axhline(1.0, color="k", lw=0.8, ls=":",
                   label=f"floor (least wear within {100 * FLOOR_TOL_M:g} cm, "
                         f"{FLOOR_TOL_PHI_DEG:g} deg)")
        ax.set_ylabel("W_tw / wear floor [-]")
    else:
        ax.set_ylabel("W_tw [J] (straight path: no floor)")
    ax.set_xscale("log")
    _plain_log_ticks(ax.xaxis)
    ax.set_xlabel("lateral error, RMS [cm]")
    ax.set_title(cls)
    ax.grid(alpha=0.3, which="both")


def _plain_log_ticks(axis) -> None:
    """Log-axis labels as plain numbers at 1, 2 and 5 of each decade: the default labels
    the minor ticks in scientific notation, which overlap at print size."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def _clip_outliers(ax, pts: list, ratio: bool) -> None:
    """Keep the panel's scale for the bulk of the points ``pts`` = [(x, y, color)]: a point
    far above the others (the raw decision vector's NTWO wears ~3x the floor, the rest
    within 10 %) is drawn at the top edge with its value written beside it, so one run does
    not flatten the others."""
    pts = [p for p in pts if np.isfinite(p[1])]
    if len(pts) < 4:
        return
    ys = np.array([p[1] for p in pts])
    base = 1.0 if ratio else float(np.min(ys))
    q = float(np.percentile(ys, 85))
    cap = base + 2.5 * max(q - base, 1e-12)
    if not np.any(ys > cap):
        return
    lo = min(float(np.min(ys)), base)
    ax.set_ylim(lo - 0.05 * (cap - lo), cap)
    over = sorted((p for p in pts if p[1] > cap), key=lambda p: p[0])
    for i, (x, y, c) in enumerate(over):  # labels stacked downwards: near points overlap
        ax.plot([x], [cap], marker="^", color=c, ms=7, clip_on=False)
        ax.annotate(f"{y:.3g}" + ("x" if ratio else " J"), (x, cap), xytext=(5, -10 - 9 * i),
                    textcoords="offset points", fontsize=7, color=c)


def plot_ratios(summary: dict, path: Path) -> None:
    """A forest plot per group: the ratio at equal error (filled) with its 95 % CI, the
    same with the unmatched scenarios entered at their most-accurate ratio (open), and the
    tolerance form NTWO + 1 cm (grey)."""
    from .plots import WIDTH, pyplot, style

    plt = pyplot()
    items = [(k, s) for k, s in summary.items() if s["with_unmatched"].get("gmean") is not None]
    if not items:
        return
    series = (("equal_error", "at equal error (matched)", "C3", "o", "C3", -0.22),
              ("with_unmatched", "with the unmatched (most-accurate ratio)", "C0", "o",
               "white", 0.0),
              ("tol:1", "NTWO + 1 cm", "0.45", "s", "0.45", 0.22))
    with style():
        fig, ax = plt.subplots(figsize=(WIDTH, 0.5 * len(items) + 1.6))
        for i, (k, s) in enumerate(items):
            right = 0.0
            for key, label, color, marker, face, dy in series:
                r = s["tolerance"]["1"] if key == "tol:1" else s[key]
                if r.get("gmean") is None:
                    continue
                lo, hi = r["ci95"]
                if lo is not None:
                    ax.plot([lo, hi], [i + dy, i + dy], color=color, lw=1.6)
                ax.plot([r["gmean"]], [i + dy], marker, color=color, mfc=face, ms=5,
                        label=label if i == 0 else None)
                right = max(right, hi if hi is not None else r["gmean"])
            eq = s["equal_error"]
            txt = (f"{eq['gmean']:.3f}" if eq.get("gmean") is not None else "n/a")
            ax.annotate(f"{txt}  ({s['scenarios']} sc., {len(s['unmatched'])} unm.)",
                        (right, i), xytext=(6, -3), textcoords="offset points", fontsize=7.5)
        ax.axvline(1.0, color="k", lw=0.8, ls=":")
        ax.set_yticks(range(len(items)), [k for k, _ in items])
        ax.invert_yaxis()
        ax.set_xlabel("least wear at the same lateral RMS error: wear-aware / wear-blind [-]")
        ax.set_title("Does the wear term save wear at the same accuracy? (< 1: yes)")
        ax.grid(alpha=0.3, axis="x")
        x0, x1 = ax.get_xlim()
        ax.set_xlim(x0, x1 + 0.3 * (x1 - x0))
        ax.legend(loc="lower right", fontsize=7.5)
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)


def plot_case2(comparisons: list[dict], path: Path) -> bool:
    """Case 2's sweep: per speed, the ratio at equal error against the start (heading
    error, lateral offset), both wear-aware families together and each alone, and the
    recovery form (:func:`case2_compare`); an unmatched start at its most-accurate ratio
    (open). False when the design has no sweep."""
    import re

    from .plots import WIDTH, pyplot, style

    pat = re.compile(r"case2, ([\d.]+) km/h, (heading|offset) ([\d.]+) (deg|m)")
    pts: dict[float, dict[str, list]] = {}
    for d in comparisons:
        m = pat.match(d["scenario"])
        if m and d["class"] == "case2":
            x = f"{m[3]} {m[4]}"
            pts.setdefault(float(m[1]), {}).setdefault(x, []).append(d)
    if not pts or max(len(v) for v in pts.values()) < 2:
        return False
    plt = pyplot()
    starts = sorted({x for v in pts.values() for x in v},
                    key=lambda x: (x.endswith("m"), float(x.split()[0])))
    series = [("ratio", "both, at equal RMS error", "k", "o")]
    series += [(f"family:{f}", f, FAMILIES[f].style[0], FAMILIES[f].style[1])
               for f in ("TWO", "TWO-energy")]
    series += [("c2:recovery:levers", "both, on the recovery", "C2", "s"),
               ("c2TWO:recovery:levers", "TWO, on the recovery", "C5", "s")]
    with style():
        fig, axes = plt.subplots(1, len(pts), figsize=(WIDTH, 3.4), squeeze=False,
                                 sharey=True)
        for ax, (v, by) in zip(axes[0], sorted(pts.items())):
            for key, label, color, marker in series:
                xs, ys, open_x, open_y = [], [], [], []
                for i, x in enumerate(starts):
                    ds = by.get(x, [])
                    vals = [d[key] for d in ds if d.get(key)]
                    if vals:
                        xs.append(i)
                        ys.append(float(np.exp(np.mean(np.log(vals)))))
                    elif key == "ratio" and ds and all(d["most_accurate"] for d in ds):
                        open_x.append(i)
                        open_y.append(float(np.exp(np.mean([math.log(d["most_accurate"])
                                                            for d in ds]))))
                ax.plot(xs, ys, marker + "-", color=color, ms=5, lw=1, label=label)
                if open_x:
                    ax.plot(open_x, open_y, marker, color=color, mfc="white", ms=6, ls="none",
                            label="unmatched: most-accurate ratio")
            ax.axhline(1.0, color="k", lw=0.8, ls=":")
            ax.set_xticks(range(len(starts)), starts, rotation=45, fontsize=8)
            ax.set_title(f"Case 2's line at {v:g} km/h, started off it", fontsize=9)
            ax.set_xlabel("start: heading error or lateral offset")
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel("wear-aware / wear-blind [-]")
        axes[0][0].legend(fontsize=6.5, loc="upper right")
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)
    return True


# ---- the report -----------------------------------------------------------------------------
def report_study(results: list[dict], floors: dict, scenarios, described: dict, out: Path,
                 runs: dict) -> dict:
    """Write ``study.md``, ``study.csv``, ``study.json``, ``fronts.png``, ``ratios.png``
    (and ``case2.png`` with Case 2's sweep); return the JSON document (one row per run, a
    comparison per scenario instance, a summary per group, the scenarios as run)."""
    from .results import stamp

    rows = [_row(r, floors, described) for r in results]
    add_recovery(rows, out)
    comparisons = compare(rows)
    summary = summarise(comparisons)
    fam = family_table(rows)
    runs = dict(runs, scenarios=len(scenarios))
    broken = broken_floor_warnings(rows)
    fc = floor_check(rows)
    (out / "study.md").write_text(markdown(summary, fam, comparisons, runs, described, broken,
                                           floor_check_line(fc)))
    with (out / "study.csv").open("w", newline="") as f:
        cols = list(rows[0]) if rows else []
        cols += sorted({k for r in rows for k in r} - set(cols))
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    figures = []
    if any(r["status"] == "ok" for r in rows):
        user = user_label(described)
        plot_fronts(fam, rows, out / "fronts.png", {"user": f"user: {user}"} if user else None)
        plot_ratios(summary, out / "ratios.png")
        figures = ["fronts.png", "ratios.png"]
        if plot_case2(comparisons, out / "case2.png"):
            figures.append("case2.png")
    doc = {"experiment": "study", "rule": {
               "front": "lower envelope of each side's runs (lateral RMS error, wear work)",
               "wear_at_error": "step: the least wear of the side's runs with an error of e "
                                "or less (no interpolation, no extrapolation)",
               "resolution_cm": RESOLUTION_CM,
               "equal_error": f"geometric mean of the ratio over the shared error range on "
                              f"{GRID} log-spaced points; levels {list(LEVELS_CM)} cm",
               "tolerance": f"at NTWO's error + {list(TOLERANCES_CM)} cm",
               "unmatched": "no shared error range; entered in with_unmatched at the "
                            "most-accurate ratio",
               "ci": f"95 % percentile bootstrap ({BOOTSTRAP} resamples, scipy.stats."
                     f"bootstrap) over scenarios, each scenario's seeds averaged in logs"},
           "scenarios_described": described, "rows": rows, "comparisons": comparisons,
           "summary": summary, "families": fam,
           "floors": {k: v["floors"] for k, v in floors.items()},
           "broken_floors": [{"scenario": r["scenario"], "label": r["label"], "key": r["key"],
                              "parts": r["floor_broken"], "W_over_floor": r.get("W_over_floor"),
                              "e_lat_rms_cm": r.get("e_lat_rms_cm")}
                             for r in rows if r.get("floor_broken")],
           "floor_check": fc, "runs": runs, "figures": figures, "out": str(out)}
    doc = stamp(doc, results)
    no_floor = []  # a path whose floor IPOPT did not find: its runs stand without one
    for k, v in floors.items():
        if v.get("error"):
            names = sorted({r["scenario"] for r in rows if r["path_key"] == k})
            no_floor.append(f"no wear floor for the path of {', '.join(names)}: {v['error']}")
    doc["warnings"] = broken + no_floor + doc["warnings"]  # the floors' first
    text = json.dumps(doc, indent=1, default=_json_default)
    (out / "study.json").write_text(text)
    return json.loads(text)  # plain data, as a reader of the file gets it


def _json_default(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, tuple):
        return list(v)
    raise TypeError(f"not JSON: {type(v).__name__}")
