"""The study's analysis: fronts per family, wear at matched accuracy, bootstrap confidence
intervals, wear above the floors; tables, figures and one JSON document.

Per scenario instance (a path, speed, vehicle, load, plant and annealer seed):

* every run is a point ``(e_lat, W_tw)``: its RMS lateral error [cm] and its tire wear
  work [J];
* the *wear-blind front* is the lower envelope of the points of every family without a
  wear term (FF, NTWO, NTWO-wheel at each R_ow, Kinematic, DH, TCT, NTWO-raw); the
  *wear-aware front* that of TWO and TWO-energy at each weight (and TWO-energy-raw);
* the *matched accuracy* is a tolerance on the RMS lateral error, ``e* = max(1 cm, the
  lateral error of the paper's NTWO)`` (and, second, 5 cm): each front's wear there,
  ``W(e*)``, is the least wear its family reaches within that tolerance
  (:func:`wear_at_accuracy`: linear between the front's neighbouring points, a point
  more accurate than needed counts at its own wear; a front whose every point is less
  accurate than ``e*`` cannot match it and the scenario is counted as unmatched);
* the ratio ``r = W_aware(e*) / W_blind(e*)``: below 1 the wear term bought less wear
  within the same tolerance than anything without it.

Across scenarios the ratios are summarised by their geometric mean, with a 95 % percentile
bootstrap confidence interval that resamples paths (the instances of one path, e.g. its
annealer seeds, move together: they are not independent), per scenario class and pooled.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from .tables import fmt, lower_front

METRICS = ("W_tw", "W_s", "W_alpha", "W_t", "e_lat_rms_cm", "e_lat_max_cm", "e_phi_deg",
           "e_bar", "Omega", "W_tw_per_km")  # W_tw_per_km: controller.metrics.work_per_km
BOOTSTRAP = 2000
TOLERANCES_CM = (1.0, 5.0)  # matched accuracy: lateral RMS tolerances (never below NTWO's)
CLASS_ORDER = ("case1", "case2", "lane", "turn", "random", "load", "4-axle", "robust", "user")
FAMILY_STYLE = {"FF": ("0.4", "x"), "NTWO": ("C0", "o"), "NTWO-wheel": ("C9", "s"),
                "NTWO-wheel-Q": ("C6", "d"),
                "Kinematic": ("C7", "v"), "DH": ("C2", "D"), "TCT": ("C4", "P"),
                "TWO": ("C3", "^"), "TWO-energy": ("C1", "*"), "NTWO-raw": ("C8", "<"),
                "TWO-energy-raw": ("C5", ">")}


def lower_envelope(points):
    """The non-dominated ``(e, W)`` points (both minimised), sorted by e."""
    return lower_front(points)


def wear_at_accuracy(front, e):
    """The wear the front needs for an accuracy of ``e`` or better: between two of its
    points linear, beyond its least accurate point that point's (lowest) wear; None if
    every point is less accurate than ``e`` (no extrapolation)."""
    if not front or e < front[0][0]:
        return None
    if e >= front[-1][0]:
        return float(front[-1][1])
    es, ws = zip(*front)
    return float(np.interp(e, es, ws))


FLOOR_MIN_J = 1.0  # J: a floor below this (a straight path) is reported but not divided by


def _row(r: dict, floors: dict) -> dict:
    t = r["spec"]["tags"]
    m = r.get("metrics") or {}
    fl = (floors.get(t["path_key"]) or {}).get("floors", {})
    row = {"family": t["family"], "label": r["spec"]["label"], "lever": t["lever"],
           "level": t["level"], "aware": t["aware"], "scenario": t["scenario"],
           "class": t["class"], "plant": t["plant"], "seed": t["seed"],
           "path_key": t["path_key"], "status": r["status"], "error": r.get("error"),
           "key": r["key"], "wall_s": r.get("wall_s")}
    row.update({k: m.get(k) for k in METRICS})
    row.update(fl)
    if m.get("W_tw") is not None and fl:
        row["W_above_floor"] = m["W_tw"] - fl["W_tw_floor"]
        # a straight path's floor is zero (the recovery from an initial error is not part of
        # it): there the ratio is undefined, not astronomically large
        row["W_over_floor"] = (m["W_tw"] / fl["W_tw_floor"] if fl["W_tw_floor"] >= FLOOR_MIN_J
                               else None)
    return row


def matched(rows: list[dict]) -> list[dict]:
    """Per scenario instance: e*, both fronts' wear there and their ratio."""
    out = []
    by = {}
    for r in rows:
        by.setdefault(r["scenario"], []).append(r)
    for name, rs in by.items():
        ok = [r for r in rs if r["status"] == "ok" and r["W_tw"] is not None]
        ref = [r for r in ok if r["family"] == "NTWO"]
        if not ref:
            continue
        e_ntwo = ref[0]["e_lat_rms_cm"]
        e_star, e2 = (max(tol, e_ntwo) for tol in TOLERANCES_CM)
        blind = lower_envelope([(r["e_lat_rms_cm"], r["W_tw"]) for r in ok if not r["aware"]])
        aware = lower_envelope([(r["e_lat_rms_cm"], r["W_tw"]) for r in ok if r["aware"]])
        wb, wa = wear_at_accuracy(blind, e_star), wear_at_accuracy(aware, e_star)
        wb2, wa2 = wear_at_accuracy(blind, e2), wear_at_accuracy(aware, e2)
        floor = ok[0].get("W_tw_floor")
        d = {"scenario": name, "class": rs[0]["class"], "plant": rs[0]["plant"],
             "path_key": rs[0]["path_key"], "seed": rs[0]["seed"], "e_ntwo_cm": e_ntwo,
             "e_star_cm": e_star, "e_star_5cm": e2,
             "W_blind": wb, "W_aware": wa, "W_tw_floor": floor,
             "ratio": None if (wa is None or wb is None) else wa / wb,
             "W_blind_5cm": wb2, "W_aware_5cm": wa2,
             "ratio_5cm": None if (wa2 is None or wb2 is None) else wa2 / wb2,
             "best_blind": _best(ok, False, e_star), "best_aware": _best(ok, True, e_star),
             "blind_front": blind, "aware_front": aware}
        # each wear-aware family on its own against the whole wear-blind front: which cost
        # form carries the result (the paper's quadratic or the wear energy)
        for fam in sorted({r["family"] for r in ok if r["aware"]}):
            front = lower_envelope([(r["e_lat_rms_cm"], r["W_tw"]) for r in ok
                                    if r["family"] == fam])
            wf = wear_at_accuracy(front, e_star)
            d[f"ratio:{fam}"] = None if (wf is None or wb is None) else wf / wb
        if d["ratio"] is not None and floor is not None:
            # the wear above the exact-tracking floor (negative where a front cuts corners:
            # the floor holds for exact tracking only)
            d["W_blind_above_floor"] = wb - floor
            d["W_aware_above_floor"] = wa - floor
        out.append(d)
    return out


def _best(rows, aware: bool, e_star: float) -> str | None:
    """The run of the family (aware or not) with the least wear among those at least as
    accurate as e* (None if none is)."""
    c = [r for r in rows if r["aware"] == aware and r["e_lat_rms_cm"] <= e_star * 1.0000001]
    return min(c, key=lambda r: r["W_tw"])["label"] if c else None


def bootstrap_ratio(items: list[dict], rng_seed: int = 0, B: int = BOOTSTRAP,
                    key: str = "ratio") -> dict:
    """Geometric mean of the ratios ``key`` of ``items`` and its 95 % CI, resampling
    paths."""
    items = [dict(d, ratio=d[key]) for d in items]
    ok = [d for d in items if d["ratio"] is not None and d["ratio"] > 0]
    res = {"n": len(ok), "unmatched": len(items) - len(ok),
           "paths": len({d["path_key"] for d in ok})}
    if not ok:
        return dict(res, gmean=None, ci95=[None, None], below_1=None)
    clusters = {}
    for d in ok:
        clusters.setdefault(d["path_key"], []).append(math.log(d["ratio"]))
    keys = sorted(clusters)
    logs = [np.array(clusters[k]) for k in keys]
    point = float(np.exp(np.mean(np.concatenate(logs))))
    rng = np.random.default_rng(rng_seed)
    stats = np.empty(B)
    for b in range(B):
        pick = rng.integers(0, len(keys), len(keys))
        stats[b] = np.mean(np.concatenate([logs[i] for i in pick]))
    lo, hi = np.exp(np.percentile(stats, [2.5, 97.5]))
    return dict(res, gmean=point, ci95=[float(lo), float(hi)],
                below_1=sum(1 for d in ok if d["ratio"] < 1.0),
                median=float(np.median([d["ratio"] for d in ok])))


def summarise(match: list[dict]) -> dict:
    """The ratio per class, for the nominal plant pooled, and for the plants unlike the
    model."""
    classes = [c for c in CLASS_ORDER if any(d["class"] == c for d in match)]
    classes += sorted({d["class"] for d in match} - set(classes))
    groups = {c: [d for d in match if d["class"] == c] for c in classes}
    groups["all nominal"] = [d for d in match if d["plant"] == "nominal"]
    if any(d["plant"] != "nominal" for d in match):
        groups["plant unlike the model"] = [d for d in match if d["plant"] != "nominal"]
        for p in sorted({d["plant"] for d in match} - {"nominal"}):
            groups[f"plant: {p}"] = [d for d in match if d["plant"] == p]
    out = {}
    for k, items in groups.items():
        out[k] = bootstrap_ratio(items)
        out[k]["within_5cm"] = bootstrap_ratio(items, key="ratio_5cm")
        fams = sorted({f[6:] for d in items for f in d if f.startswith("ratio:")})
        out[k]["by_family"] = {f: bootstrap_ratio([d for d in items if f"ratio:{f}" in d],
                                                  key=f"ratio:{f}") for f in fams}
    return out


def family_table(rows: list[dict]) -> list[dict]:
    """Per class, family and lever level: the means over its scenarios of the lateral error,
    the wear, the wear over the floor."""
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
    fam = {f: i for i, f in enumerate(FAMILY_STYLE)}
    out.sort(key=lambda d: (order.get(d["class"], 99), fam.get(d["family"], 99),
                            d["level"] if d["level"] is not None else -1))
    return out


# ---- outputs -----------------------------------------------------------------------------
def _ratio_text(s: dict) -> str:
    if s.get("gmean") is None:
        return "n/a"
    lo, hi = s["ci95"]
    return f"{s['gmean']:.3f} [{lo:.3f}, {hi:.3f}]"


def markdown(summary: dict, fam: list[dict], match: list[dict], runs: dict) -> str:
    L = ["# The study: wear at matched accuracy\n",
         f"{runs['runs']} runs on {runs.get('scenarios')} scenario instances "
         f"({runs.get('design')} design; {runs['executed']} run now, {runs['reused']} reused, "
         f"{runs['failed']} failed).\n",
         "Ratio = the least wear of the wear-aware families over that of the wear-blind ones, "
         "each within a lateral RMS tolerance of 1 cm (or the paper's NTWO's error where it "
         "is larger), geometric mean over scenarios with a 95 % bootstrap CI over paths; "
         "last column: within 5 cm. Below 1: the wear term saves wear at that accuracy.\n",
         "| scenarios | n (paths) | unmatched | ratio within 1 cm [95 % CI] | below 1 | ratio within 5 cm [95 % CI] |",
         "|---|---:|---:|---|---:|---|"]
    for cls, s in summary.items():
        L.append(f"| {cls} | {s['n']} ({s['paths']}) | {s['unmatched']} | {_ratio_text(s)} | "
                 f"{s.get('below_1') if s.get('below_1') is not None else 'n/a'} | "
                 f"{_ratio_text(s['within_5cm'])} |")
    fams = [f for f in FAMILY_STYLE if any(f in s.get("by_family", {}) for s in summary.values())]
    if fams:
        L += ["\n## Each wear-aware family alone against the wear-blind front (within 1 cm)\n",
              "Geometric mean [95 % CI] over the scenarios where the family ran (n); which "
              "cost form carries the result.\n",
              "| scenarios | " + " | ".join(fams) + " |",
              "|---|" + "---|" * len(fams)]
        for cls, s in summary.items():
            bf = s.get("by_family", {})
            L.append(f"| {cls} | " + " | ".join(
                (f"{_ratio_text(bf[f])} (n = {bf[f]['n']})" if f in bf and bf[f]["n"] else "")
                for f in fams) + " |")
    L += ["\n## Families per scenario class (means over the class's scenarios)\n",
          "| class | run | wear-aware | e_lat RMS (cm) | e_phi RMS (deg) | W_tw (J) | W_tw per km (J/km) | W_tw / floor | above floor (J) |",
          "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for d in fam:
        L.append(f"| {d['class']} | {d['label']} | {'yes' if d['aware'] else ''} | "
                 f"{_f(d['e_lat_rms_cm'], 2)} | {_f(d['e_phi_deg'], 2)} | "
                 f"{fmt('W_tw', d['W_tw'])} | {fmt('W_tw', d.get('W_tw_per_km'))} | "
                 f"{_f(d['W_over_floor'], 3)} | "
                 f"{fmt('W_tw', d['W_above_floor'])} |")
    L += ["\n## Per scenario\n",
          "| scenario | NTWO's e_lat (cm) | e* (cm) | W floor (J) | W blind at e* (J) | best blind | W aware at e* (J) | best aware | ratio |",
          "|---|---:|---:|---:|---:|---|---:|---|---:|"]
    for d in match:
        L.append(f"| {d['scenario']} | {d['e_ntwo_cm']:.2f} | {d['e_star_cm']:.2f} | "
                 f"{fmt('W_tw', d['W_tw_floor'])} | "
                 f"{fmt('W_tw', d['W_blind'])} | {d['best_blind'] or ''} | "
                 f"{fmt('W_tw', d['W_aware'])} | {d['best_aware'] or 'unmatched'} | "
                 f"{_f(d['ratio'], 3)} |")
    return "\n".join(L) + "\n"


def _f(v, nd):
    return "n/a" if v is None else f"{v:.{nd}f}"


def plot_fronts(fam: list[dict], rows: list[dict], path: Path) -> None:
    """Per scenario class: each family's mean wear over the floor against its mean lateral
    error, one point per lever level (a line along the lever), with 95 % bootstrap bars
    over the class's scenarios; the floor (exact tracking) as the line W / floor = 1."""
    from .plots import WIDTH, pyplot, style

    plt = pyplot()
    classes = [c for c in CLASS_ORDER if any(d["class"] == c for d in fam)]
    if not classes:
        return
    ncol = min(3, len(classes))
    nrow = math.ceil(len(classes) / ncol)
    rng = np.random.default_rng(1)
    with style():
        fig, axes = plt.subplots(nrow, ncol, figsize=(WIDTH * 1.35, 3.3 * nrow + 0.6),
                                 squeeze=False)
        for ax, cls in zip(axes.flat, classes):
            # W over the floor; absolute W_tw where the class's paths have no floor (a line)
            key = ("W_over_floor" if any(d["class"] == cls and d["W_over_floor"] is not None
                                         for d in fam) else "W_tw")
            pts = []
            for family, (color, marker) in FAMILY_STYLE.items():
                ds = [d for d in fam if d["class"] == cls and d["family"] == family
                      and d[key] is not None]
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
                ax.axhline(1.0, color="k", lw=0.8, ls=":", label="floor (exact tracking)")
                ax.set_ylabel("W_tw / wear floor [-]")
            else:
                ax.set_ylabel("W_tw [J] (straight path: no floor)")
            ax.set_xscale("log")
            _plain_log_ticks(ax.xaxis)
            ax.set_xlabel("lateral error, RMS [cm]")
            ax.set_title(cls)
            ax.grid(alpha=0.3, which="both")
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
        fig.tight_layout(rect=(0, 0.08, 1, 0.97))
        fig.savefig(path)
        plt.close(fig)


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
    """The matched-accuracy ratio per scenario class with its 95 % CI (a forest plot):
    within 1 cm (filled) and within 5 cm (open) lateral RMS."""
    from .plots import WIDTH, pyplot, style

    plt = pyplot()
    items = [(k, s) for k, s in summary.items() if s.get("gmean") is not None]
    if not items:
        return
    with style():
        fig, ax = plt.subplots(figsize=(WIDTH, 0.42 * len(items) + 1.4))
        for i, (k, s) in enumerate(items):
            lo, hi = s["ci95"]
            ax.plot([lo, hi], [i - 0.12, i - 0.12], color="C3", lw=2)
            ax.plot([s["gmean"]], [i - 0.12], "o", color="C3",
                    label="within 1 cm" if i == 0 else None)
            right = hi
            w5 = s.get("within_5cm") or {}
            if w5.get("gmean") is not None:
                lo5, hi5 = w5["ci95"]
                ax.plot([lo5, hi5], [i + 0.18, i + 0.18], color="C0", lw=1.2)
                ax.plot([w5["gmean"]], [i + 0.18], "o", mfc="white", color="C0",
                        label="within 5 cm" if i == 0 else None)
                right = max(right, hi5)
            ax.annotate(f"{s['gmean']:.3f}  (n = {s['n']})", (right, i), xytext=(6, -3),
                        textcoords="offset points", fontsize=8)
        ax.axvline(1.0, color="k", lw=0.8, ls=":")
        ax.legend(loc="center left", fontsize=8)
        ax.set_yticks(range(len(items)), [k for k, _ in items])
        ax.invert_yaxis()
        ax.set_xlabel("least wear at matched lateral RMS: wear-aware / wear-blind [-]")
        ax.set_title("Does the wear term save wear at the same accuracy? (< 1: yes)")
        ax.grid(alpha=0.3, axis="x")
        x0, x1 = ax.get_xlim()
        ax.set_xlim(x0, x1 + 0.25 * (x1 - x0))
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)


def report_study(results: list[dict], floors: dict, scenarios, out: Path, runs: dict) -> dict:
    """Write ``study.md``, ``study.csv``, ``study.json``, ``fronts.png``, ``ratios.png``;
    return the JSON document (one row per run, a summary per scenario class)."""
    from .studies import _stamp

    rows = [_row(r, floors) for r in results]
    match = matched(rows)
    summary = summarise(match)
    fam = family_table(rows)
    runs = dict(runs, scenarios=len(scenarios))
    (out / "study.md").write_text(markdown(summary, fam, match, runs))
    with (out / "study.csv").open("w", newline="") as f:
        cols = list(rows[0]) if rows else []
        cols += sorted({k for r in rows for k in r} - set(cols))
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    figures = []
    if any(r["status"] == "ok" for r in rows):
        plot_fronts(fam, rows, out / "fronts.png")
        plot_ratios(summary, out / "ratios.png")
        figures = ["fronts.png", "ratios.png"]
    doc = {"experiment": "study", "rows": rows, "matched": match, "summary": summary,
           "families": fam, "floors": {k: v["floors"] for k, v in floors.items()},
           "runs": runs, "figures": figures, "out": str(out)}
    doc = _stamp(doc, results)
    (out / "study.json").write_text(json.dumps(doc, indent=1, default=float))
    return doc
