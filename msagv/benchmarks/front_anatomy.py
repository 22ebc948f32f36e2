"""Why a column's equal-error ratio moves: per path, the wear of each front matched over the
shared error range, the range itself, and the share of it where the wear-blind front stands
on a dear step, from an experiment's stored runs (``msagv experiment mismatch``'s ``-o DIR``).

    python -m msagv.benchmarks.front_anatomy DIR --plant "tires x0.9" [--columns wrong,true] [-v]

For each path and column: the shared error range [cm], the geometric mean of the wear-aware
(``Wa``) and wear-blind (``Wb``) fronts' wear over the study's log-spaced grid of that range
[kJ], the ratio (the study's, :func:`experiments.study_analysis.equal_error`), and the share of
the grid where the blind front's wear is above 1.3 times its cheapest run (a step between dear
accurate runs and cheap ones) with the ratio on and off that step. Then the pooled ratio per
column and the pooled ratio without each path. ``-v``: the runs that make each front.
docs/RESULTS.md ("Ten per cent off") quotes it.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import sys

import numpy as np

STEP = 1.3  # a blind front's wear above STEP times its cheapest run: the dear step
GRID = 50


def load(directory: str, plant: str) -> list[dict]:
    """The finished runs of ``plant`` in an experiment's output directory."""
    from msagv.experiments.study_analysis import RESOLUTION_CM

    rows = []
    for f in glob.glob(os.path.join(directory, "runs", "*.json")):
        with open(f) as fh:
            r = json.load(fh)
        t, m = r["spec"]["tags"], r.get("metrics") or {}
        if (r["status"] != "ok" or t.get("plant") != plant or m.get("W_tw") is None
                or m.get("e_lat_rms_cm") is None):
            continue
        rows.append({"family": t["family"], "level": t["level"], "column": t["model"],
                     "path": t["scenario"].split(",")[0].replace("mismatch ", ""),
                     "aware": t["aware"], "e": max(m["e_lat_rms_cm"], RESOLUTION_CM),
                     "W": m["W_tw"]})
    return rows


def anatomy(rows: list[dict]) -> dict:
    """One path and column: the fronts, the range, the matched wears, the step's share."""
    from msagv.experiments.study_analysis import equal_error, lower_envelope, wear_within

    a = lower_envelope([(r["e"], r["W"]) for r in rows if r["aware"]])
    b = lower_envelope([(r["e"], r["W"]) for r in rows if not r["aware"]])
    eq = equal_error(a, b)
    lo, hi = eq["range"]
    grid = np.geomspace(lo, hi, GRID) if hi > lo else np.array([lo])
    wa = np.array([wear_within(a, e) for e in grid])
    wb = np.array([wear_within(b, e) for e in grid])
    step = wb > STEP * min(w for _, w in b)
    lr = np.log(wa / wb)
    return {"ratio": eq["mean"], "lo": lo, "hi": hi, "Wa": float(np.exp(np.log(wa).mean())),
            "Wb": float(np.exp(np.log(wb).mean())), "share": float(step.mean()),
            "on": float(np.exp(lr[step].mean())) if step.any() else None,
            "off": float(np.exp(lr[~step].mean())) if (~step).any() else None,
            "a": a, "b": b}


def _front(rows, front) -> str:
    out = []
    for e, w in front:
        r = next(x for x in rows if x["e"] == e and x["W"] == w)
        out.append(f"{r['family']}@{r['level']} ({e:.3f} cm, {w / 1e3:.1f} kJ)")
    return ", ".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m msagv.benchmarks.front_anatomy",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("directory", help="an experiment's output directory (its runs/*.json)")
    ap.add_argument("--plant", required=True, help='the plant, e.g. "tires x0.9"')
    ap.add_argument("--columns", default="wrong,true", help="columns (default wrong,true)")
    ap.add_argument("-v", "--verbose", action="store_true", help="the runs of each front")
    a = ap.parse_args(argv)
    rows = load(a.directory, a.plant)
    if not rows:
        ap.error(f"no finished runs of plant {a.plant!r} in {a.directory}/runs")
    cols = [c.strip() for c in a.columns.split(",")]
    paths = sorted({r["path"] for r in rows},
                   key=lambda p: (int(p.split("-")[1]) if p.count("-") >= 2 else 0, p))
    logs = {c: [] for c in cols}
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    print(f"{a.plant}: per path and column: range [cm], Wa / Wb [kJ], ratio, dear-step share, "
          f"ratio on / off the step")
    for p in paths:
        for c in cols:
            sel = [r for r in rows if r["path"] == p and r["column"] == c]
            if not sel:
                continue
            d = anatomy(sel)
            logs[c].append(math.log(d["ratio"]))
            print(f"{p:<16} {c:<10} [{d['lo']:.3f}, {d['hi']:.3f}]  {d['Wa'] / 1e3:6.1f} / "
                  f"{d['Wb'] / 1e3:6.1f}  {d['ratio']:.3f}  {d['share']:.2f}  "
                  f"{fmt(d['on'])} / {fmt(d['off'])}")
            if a.verbose:
                print(f"    aware: {_front(sel, d['a'])}\n    blind: {_front(sel, d['b'])}")
    for c in cols:
        v = logs[c]
        if v:
            drop = " ".join(f"{math.exp(np.mean(v[:i] + v[i + 1:])):.3f}" for i in range(len(v)))
            print(f"{c}: pooled {math.exp(np.mean(v)):.3f}; without each path in turn: {drop}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
