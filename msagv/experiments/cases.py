"""The paper's experiments, ``msagv experiment case1|case2|case3|pareto|ridge``: Section 4 and more.

* ``case1``: the Case 1 curve, 12 t, 35/25/15/5 km/h, all five methods (paper Table 1).
* ``case2``: the straight line, 12 t, 10 km/h, heading 60 degrees off at the start
  (Table 2).
* ``case3``: the Case 1 curve at 30 km/h, 8/12/16/20 t (Table 3, Omega against load).
* ``ridge``: NTWO and TWO on the Case 1 curve at 5/15/25/35 km/h with the command ridge
  (R_ow, R_od) off, at its default and ten times stronger: how TWO's wear cut depends on
  how well NTWO is regularised (``ridge.md``, ``ridge.csv``, ``ridge.json``).
* ``pareto``: on the Case 1 curve at 15 and 35 km/h, TWO with its wear weights L scaled
  against NTWO with its command regularisation scaled (the only other lever that lowers
  wear), the three baselines as points: does the wear term buy less wear at the same
  accuracy than smoothing the commands does?

The five methods (paper Section 4.2) share one MPC, annealer, plant and every setting
except: NTWO = Magic Formula model, L = 0; TWO = Magic Formula model with L; Kinematic, DH
and TCT = their own prediction model with L = 0 (their sources have no wear term).

Runs go in parallel over the cores (``--jobs``), with a progress bar, and resume: a
finished run is stored under ``OUT/runs/`` keyed by a hash of its whole configuration and
is not redone (``--force`` redoes it). Outputs in ``OUT`` (default ``runs/<experiment>``):
``table.md``/``table.csv`` in the paper's layout (best per group and column in bold,
second underlined), ``summary.json`` (rows, the issue's targets, timings),
``trajectories.png``, ``errors.png``, ``omega_vs_speed.png`` (Case 1) or
``omega_vs_load.png`` (Case 3); for ``pareto``: ``pareto.md``, ``pareto.csv``,
``pareto.json``, ``pareto.png``. ``--json`` prints the table (or the fronts) as data.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from .families import FAMILIES, RIDGE_BASE, case_rows
from .results import stamp
from .runs import RunSpec, run_all

EXPERIMENTS = ("case1", "case2", "case3", "pareto", "ridge")
CASE1_SPEEDS = (35.0, 25.0, 15.0, 5.0)  # km/h, the paper's row order
CASE2_SPEED = 10.0
CASE3_SPEED = 30.0
CASE3_MASSES_T = (8.0, 12.0, 16.0, 20.0)
PARETO_SPEEDS = (15.0, 35.0)
RIDGE_SPEEDS = (5.0, 15.0, 25.0, 35.0)  # the ridge experiment: Case 1 speeds
RIDGE_LEVELS = (0.0, 0.1, 1.0)  # x RIDGE_BASE; 0.1 is the default
# pareto's levels: TWO's L = scale x the default L; NTWO-smooth's (R_dw, R_dd) = scale x
# their defaults (the smoothing of the offsets between blocks and solves; the default ridge
# kept); NTWO-ridge's (R_ow, R_od) = scale x RIDGE_BASE (pulls the offsets toward the
# kinematic feed-forward; x0.1 is the default, x0 none). The levers are the families' in
# experiments.families; see docs/RESULTS.md.
TWO_SCALES = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
SMOOTH_SCALES = FAMILIES["NTWO-smooth"].levels
RIDGE_SCALES = FAMILIES["NTWO-ridge"].levels
PARETO_BASELINES = ("Kinematic", "DH", "TCT", "FF", "NTWO-wheel")  # points beside the fronts

def _kmh(v: float) -> str:
    return f"{v:g} km/h"


def _tonnes(m: float) -> str:
    return f"{m:g} t"


def _methods(selected):
    """The rows of a case table (:func:`experiments.families.case_rows`): the paper's five
    in its order, then the references; ``selected``: a subset by name."""
    known = [f.name for f in case_rows()]
    names = known if not selected else list(selected)
    bad = [m for m in names if m not in known]
    if bad:
        raise ValueError(f"--methods: unknown method(s) {', '.join(bad)} (known: {', '.join(known)})")
    return [m for m in known if m in names]


def _spec(m: str, group: str, case: str, v: float, mass: float, duration, vehicle) -> RunSpec:
    """The run of case-table row ``m`` (a family at its ``case_level``)."""
    fam = FAMILIES[m]
    return RunSpec(m, group, case, v, mass, fam.settings_at(fam.case_level), duration, vehicle,
                   {} if fam.paper else {"reference": True}, fam.extra())


def case_specs(experiment: str, *, speeds=None, masses_t=None, methods=None,
               duration=None, vehicle=None) -> list[RunSpec]:
    """The runs of ``case1``, ``case2`` or ``case3`` in the paper's table order."""
    ms = _methods(methods)
    specs = []
    if experiment == "case1":
        for v in (speeds or CASE1_SPEEDS):
            specs += [_spec(m, _kmh(v), "curve", float(v), 12000.0, duration, vehicle)
                      for m in ms]
    elif experiment == "case2":
        for v in (speeds or (CASE2_SPEED,)):
            specs += [_spec(m, _kmh(v), "line", float(v), 12000.0, duration, vehicle)
                      for m in ms]
    elif experiment == "case3":
        v = float((speeds or (CASE3_SPEED,))[0])
        for t in (masses_t or CASE3_MASSES_T):
            specs += [_spec(m, _tonnes(t), "curve", v, 1000.0 * float(t), duration, vehicle)
                      for m in ms]
    else:
        raise ValueError(f"unknown experiment '{experiment}'")
    return specs


def pareto_specs(*, speeds=None, duration=None, vehicle=None, two_scales=TWO_SCALES,
                 smooth_scales=SMOOTH_SCALES, ridge_scales=RIDGE_SCALES,
                 baselines=PARETO_BASELINES) -> list[RunSpec]:
    """TWO with L scaled, NTWO with (R_dw, R_dd) and with (R_ow, R_od) scaled, baselines
    and the wear-blind references (FF, NTWO-wheel) as points."""
    sweeps = (("TWO", "L", "TWO L x", two_scales),
              ("NTWO-smooth", "R_dw, R_dd", "NTWO R_dw,R_dd x", smooth_scales),
              ("NTWO-ridge", "R_ow, R_od", "NTWO R_ow,R_od x", ridge_scales))
    specs = []
    for v in (speeds or PARETO_SPEEDS):
        g = _kmh(v)
        for name, lever, label, scales in sweeps:
            fam = FAMILIES[name]
            specs += [RunSpec(f"{label}{s:g}", g, "curve", float(v), 12000.0,
                              fam.settings_at(s), duration, vehicle,
                              {"family": name, "scale": s, "lever": lever}) for s in scales]
        for m in baselines:
            sp = _spec(m, g, "curve", float(v), 12000.0, duration, vehicle)
            sp.tags = {"family": "baseline"}
            specs.append(sp)
    return specs


def ridge_specs(*, speeds=None, levels=RIDGE_LEVELS, duration=None, vehicle=None) -> list[RunSpec]:
    """NTWO and TWO (their case-table settings) with (R_ow, R_od) = level x RIDGE_BASE
    (NTWO-ridge's lever; everything else default)."""
    ridge = FAMILIES["NTWO-ridge"].lever
    specs = []
    for lv in levels:
        for v in (speeds or RIDGE_SPEEDS):
            for m in ("NTWO", "TWO"):
                fam = FAMILIES[m]
                specs.append(RunSpec(f"{m} ridge x{lv:g}", _kmh(v), "curve", float(v), 12000.0,
                                     ridge.apply(fam.settings_at(fam.case_level), lv),
                                     duration, vehicle, {"family": m, "ridge": lv}))
    return specs


# ---- reports ----------------------------------------------------------------------------------
def _group_value(group: str) -> float:
    return float(group.split()[0])


def _vehicle_name(results: list[dict]) -> str:
    """The name of the vehicle the runs drove (for titles)."""
    from .runs import RunSpec

    if not results:
        return ""
    return RunSpec.from_dict(results[0]["spec"]).scenario().resolve_vehicle().name


def report_case(experiment: str, results: list[dict], out: Path, run_summary: dict) -> dict:
    from .paper import paper_table
    from .tables import (check_targets, markdown_table, plot_errors, plot_omega,
                                     plot_trajectories, table_rows, targets_markdown, write_csv)

    rows = table_rows(results)
    speed_of = (lambda g: CASE3_SPEED) if experiment == "case3" else _group_value
    if experiment == "case3" and results:
        sp = results[0]["spec"]["speed_kmh"]
        speed_of = lambda g: sp  # noqa: E731
    targets = check_targets(experiment, rows, speed_of)
    paper = paper_table(experiment)
    vname = _vehicle_name(results)
    titles = {"case1": f"Case 1 (curve, {vname}, 12 t)",
              "case2": f"Case 2 (line, {vname}, 12 t, 60 deg off)",
              "case3": f"Case 3 (curve, {results[0]['spec']['speed_kmh']:g} km/h, {vname})"
              if results else "Case 3"}
    title = titles[experiment]
    partial = [r for r in rows if r.get("partial")]
    caveat = (f"\n**Partial runs**: {len(partial)} of {len(rows)} rows ran only part of the path "
              f"(--duration; marked 'ran of whole s'); the paper's numbers are for the whole "
              f"path, so these rows are not comparable with them.\n" if partial else "")
    md = [f"# {title}\n", caveat, markdown_table(rows),
          "\n## Against the paper (paper rows in italics)\n", caveat,
          markdown_table(rows, paper), "\n## Targets\n", targets_markdown(targets)]
    (out / "table.md").write_text("\n".join(md))
    write_csv(rows, out / "table.csv")
    figures = []
    if any(r["status"] == "ok" for r in results):
        plot_trajectories(results, out, out / "trajectories.png", title)
        plot_errors(results, out, out / "errors.png", title)
        figures += ["trajectories.png", "errors.png"]
        if experiment == "case1":
            plot_omega(rows, _group_value, "speed [km/h]", out / "omega_vs_speed.png",
                       f"{title}: balance index against speed")
            figures.append("omega_vs_speed.png")
        elif experiment == "case3":
            plot_omega(rows, _group_value, "gross vehicle weight [t]", out / "omega_vs_load.png",
                       f"{title}: balance index against load")
            figures.append("omega_vs_load.png")
    from .results import spec_info

    for row, r in zip(rows, results):
        row["scenario"] = spec_info(r["spec"], r.get("duration"))
        row["warnings"] = list(r.get("warnings", []))
    summary = {"experiment": experiment, "columns": list(rows[0]["metrics"]) if rows else [],
               "rows": rows, "targets": targets, "runs": run_summary, "figures": figures,
               "out": str(out)}
    summary = stamp(summary, results)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def report_pareto(results: list[dict], out: Path, run_summary: dict) -> dict:
    from .tables import fmt, lower_front, plot_pareto, wear_at

    fronts: dict[str, dict] = {}
    for r in results:
        sp = r["spec"]["group"]
        fr = fronts.setdefault(sp, {"families": {}, "baselines": {}, "lever": {}})
        tags = r["spec"]["tags"]
        m = r.get("metrics") or {}
        point = {"label": r["spec"]["label"], "status": r["status"], "error": r.get("error"),
                 "W_tw": m.get("W_tw"), "e_bar": m.get("e_bar"), "Omega": m.get("Omega"),
                 "W_s": m.get("W_s"), "W_alpha": m.get("W_alpha"), "W_t": m.get("W_t"),
                 "key": r["key"]}
        if tags.get("family") == "baseline":
            fr["baselines"][r["spec"]["label"]] = point
        else:
            point["scale"] = tags["scale"]
            for k in ("L", "R"):
                if k in r["spec"]["settings"]:
                    point[k] = list(r["spec"]["settings"][k])
            fr["families"].setdefault(tags["family"], []).append(point)
            fr["lever"][tags["family"]] = tags["lever"]
    lines = ["# Pareto fronts: wear against accuracy (Case 1 curve, 12 t)\n"]
    csv_rows = []
    for sp, fr in fronts.items():
        two = [(p["e_bar"], p["W_tw"]) for p in fr["families"].get("TWO", []) if p["status"] == "ok"]
        front = lower_front(two)
        fr["two_front"] = [{"e_bar": e, "W_tw": w} for e, w in front]
        comp = []
        for fam, pts in fr["families"].items():
            if fam == "TWO":
                continue
            for p in sorted(pts, key=lambda q: q["scale"]):
                if p["status"] != "ok":
                    continue
                w2 = wear_at(front, p["e_bar"])
                comp.append({"family": fam, "scale": p["scale"], "e_bar": p["e_bar"],
                             "W_tw": p["W_tw"], "W_tw_TWO_same_e_bar": w2,
                             "ratio": None if w2 is None else w2 / p["W_tw"]})
        fr["comparison"] = comp
        lines.append(f"\n## {sp}\n")
        lines.append("| family | lever | scale | W_tw (J) | e_bar | Omega |")
        lines.append("|---|---|---:|---:|---:|---:|")
        for fam, pts in fr["families"].items():
            for p in sorted(pts, key=lambda q: q["scale"]):
                lines.append(f"| {fam} | {fr['lever'][fam]} | x{p['scale']:g} | "
                             f"{fmt('W_tw', p['W_tw'])} | {fmt('e_bar', p['e_bar'])} | "
                             f"{fmt('Omega', p['Omega'])} |")
                csv_rows.append([sp, fam, fr["lever"][fam], p["scale"], p["W_tw"], p["e_bar"],
                                 p["Omega"], p["status"]])
        for name, p in fr["baselines"].items():
            lines.append(f"| {name} | (baseline) | | {fmt('W_tw', p['W_tw'])} | "
                         f"{fmt('e_bar', p['e_bar'])} | {fmt('Omega', p['Omega'])} |")
            csv_rows.append([sp, name, "", "", p["W_tw"], p["e_bar"], p["Omega"], p["status"]])
        lines.append(f"\nTWO's front (non-dominated points): "
                     + ", ".join(f"({e:.2f}, {fmt('W_tw', w)})" for e, w in front))
        lines.append("\n| NTWO point | e_bar | W_tw NTWO (J) | W_tw TWO at same e_bar (J) | TWO / NTWO |")
        lines.append("|---|---:|---:|---:|---:|")
        for c in comp:
            w2 = c["W_tw_TWO_same_e_bar"]
            two_w = fmt("W_tw", w2) if w2 is not None else "outside TWO's range"
            ratio = "" if c["ratio"] is None else f"{c['ratio']:.3f}"
            lines.append(f"| {c['family']} x{c['scale']:g} | {c['e_bar']:.2f} | "
                         f"{fmt('W_tw', c['W_tw'])} | {two_w} | {ratio} |")
    (out / "pareto.md").write_text("\n".join(lines) + "\n")
    import csv

    with (out / "pareto.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["speed", "family", "lever", "scale", "W_tw", "e_bar", "Omega", "status"])
        w.writerows(csv_rows)
    figures = []
    if any(r["status"] == "ok" for r in results):
        plot_pareto(fronts, out / "pareto.png", _vehicle_name(results))
        figures.append("pareto.png")
    summary = stamp({"experiment": "pareto", "fronts": fronts, "runs": run_summary,
                      "figures": figures, "out": str(out)}, results)
    (out / "pareto.json").write_text(json.dumps(summary, indent=1))
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def report_ridge(results: list[dict], out: Path, run_summary: dict) -> dict:
    from .tables import fmt

    cells: dict[tuple, dict] = {}
    for r in results:
        sp, m = r["spec"], r.get("metrics") or {}
        cells[(sp["tags"]["ridge"], sp["group"], sp["tags"]["family"])] = {
            "W_tw": m.get("W_tw"), "e_bar": m.get("e_bar"), "Omega": m.get("Omega"),
            "status": r["status"], "key": r["key"]}
    levels = sorted({k[0] for k in cells})
    groups = list(dict.fromkeys(r["spec"]["group"] for r in results))
    rows = []
    for lv in levels:
        for g in groups:
            n, t = cells.get((lv, g, "NTWO"), {}), cells.get((lv, g, "TWO"), {})
            ok = n.get("W_tw") is not None and t.get("W_tw") is not None
            rows.append({"ridge": lv, "R_ow": lv * RIDGE_BASE[0], "R_od": lv * RIDGE_BASE[1],
                         "group": g, "NTWO": n, "TWO": t,
                         "cut_percent": 100.0 * (1.0 - t["W_tw"] / n["W_tw"]) if ok else None})
    lines = ["# TWO's wear cut against NTWO as the command ridge grows (Case 1 curve, 12 t)\n",
             "`W_tw` in J, `e_bar` as the paper; NTWO and TWO share every setting but L.\n",
             "| ridge (R_ow, R_od) | speed | NTWO W_tw | NTWO e_bar | TWO W_tw | TWO e_bar | cut |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        cut = "n/a" if r["cut_percent"] is None else f"{r['cut_percent']:.1f} %"
        lines.append(f"| x{r['ridge']:g} ({r['R_ow']:g}, {r['R_od']:g}) | {r['group']} | "
                     f"{fmt('W_tw', r['NTWO'].get('W_tw'))} | {fmt('e_bar', r['NTWO'].get('e_bar'))} | "
                     f"{fmt('W_tw', r['TWO'].get('W_tw'))} | {fmt('e_bar', r['TWO'].get('e_bar'))} | {cut} |")
    (out / "ridge.md").write_text("\n".join(lines) + "\n")
    import csv

    with (out / "ridge.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["ridge", "R_ow", "R_od", "speed", "NTWO_W_tw", "NTWO_e_bar", "TWO_W_tw",
                    "TWO_e_bar", "cut_percent"])
        for r in rows:
            w.writerow([r["ridge"], r["R_ow"], r["R_od"], r["group"], r["NTWO"].get("W_tw"),
                        r["NTWO"].get("e_bar"), r["TWO"].get("W_tw"), r["TWO"].get("e_bar"),
                        r["cut_percent"]])
    summary = stamp({"experiment": "ridge", "rows": rows, "runs": run_summary,
                      "out": str(out)}, results)
    (out / "ridge.json").write_text(json.dumps(summary, indent=1))
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def run_experiment(name: str, out: str | Path | None = None, *, jobs: int | None = None,
                   force: bool = False, progress: bool = True, duration: float | None = None,
                   speeds=None, masses_t=None, methods=None, vehicle: str | None = None,
                   two_scales=None, smooth_scales=None, ridge_scales=None,
                   scheduler: str | None = None) -> dict:
    """Run (or resume) one experiment and write its outputs; returns its summary."""
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment '{name}' (expected {', '.join(EXPERIMENTS)})")
    if duration is not None and not duration > 0:
        raise ValueError("--duration must be > 0")
    out = Path(out) if out is not None else Path("runs") / name
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if name == "pareto":
        kw = {k: v for k, v in (("two_scales", two_scales), ("smooth_scales", smooth_scales),
                                ("ridge_scales", ridge_scales)) if v is not None}
        if methods:
            kw["baselines"] = [m for m in _methods(methods) if m in PARETO_BASELINES]
        specs = pareto_specs(speeds=speeds, duration=duration, vehicle=vehicle, **kw)
    elif name == "ridge":
        kw = {"levels": ridge_scales} if ridge_scales is not None else {}
        specs = ridge_specs(speeds=speeds, duration=duration, vehicle=vehicle, **kw)
    else:
        specs = case_specs(name, speeds=speeds, masses_t=masses_t, methods=methods,
                           duration=duration, vehicle=vehicle)
    results, summ = run_all(specs, out, jobs=jobs, force=force, progress=progress, desc=name,
                            scheduler=scheduler)
    summ["total_wall_s"] = time.perf_counter() - t0
    summ["jobs"] = int(jobs or os.cpu_count() or 1)
    if name == "pareto":
        return report_pareto(results, out, summ)
    if name == "ridge":
        return report_ridge(results, out, summ)
    return report_case(name, results, out, summ)
