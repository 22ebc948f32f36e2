"""Tables, figures and checks of the experiments (from stored run results, never from
memory: a resumed experiment reports exactly like a fresh one).

Tables follow the paper's layout (Tables 1-3): per row group (speed or load) one row per
method with Omega, W_tw, W_alpha, W_s, W_t [J], e_bar, e_x, e_y [cm], e_phi [deg]; in each
group and column the best (lowest) value is marked in bold and the second best underlined,
as the paper marks them.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from .results import partial_run

COLUMNS = ("Omega", "W_tw", "W_alpha", "W_s", "W_t", "e_bar", "e_x_cm", "e_y_cm", "e_phi_deg")
HEADERS = {"Omega": "Omega", "W_tw": "W_tw (J)", "W_alpha": "W_alpha (J)", "W_s": "W_s (J)",
           "W_t": "W_t (J)", "e_bar": "e_bar", "e_x_cm": "e_x (cm)", "e_y_cm": "e_y (cm)",
           "e_phi_deg": "e_phi (deg)"}
SCIENTIFIC = {"Omega", "W_tw", "W_alpha", "W_s", "W_t"}



def _style(name: str, default: tuple) -> tuple:
    """A row's (colour, marker) in the figures: its family's (experiments.families)."""
    from .families import FAMILIES

    f = FAMILIES.get(name)
    return f.style if f is not None else default


# ---- tables ---------------------------------------------------------------------------------
def fmt(col: str, v) -> str:
    if v is None or not isinstance(v, (int, float)) or not math.isfinite(v):
        return "n/a"
    if col in SCIENTIFIC:
        if v == 0:
            return "0"
        e = int(math.floor(math.log10(abs(v))))
        m = v / 10 ** e
        if round(m, 2) >= 10:
            m, e = m / 10, e + 1
        return f"{m:.2f}e{e}"
    return f"{v:.2f}"


def table_rows(results: list[dict]) -> list[dict]:
    """Rows ``{group, method, metrics (the nine columns), best, second, status, key}`` in the
    order of ``results``, with each group's best and second-best column values marked."""
    rows = []
    for r in results:
        m = r.get("metrics") or {}
        rows.append({"group": r["spec"]["group"], "method": r["spec"]["label"],
                     "metrics": {c: m.get(c) for c in COLUMNS}, "best": [], "second": [],
                     "status": r["status"], "error": r.get("error"), "key": r["key"],
                     "wall_s": r.get("wall_s"), "steps": m.get("steps"),
                     "solve_ms": m.get("solve_ms"), "partial": partial_run(r)})
    groups: dict[str, list[dict]] = {}
    for row in rows:
        groups.setdefault(row["group"], []).append(row)
    for grp in groups.values():
        for c in COLUMNS:
            vals = sorted({row["metrics"][c] for row in grp
                           if row["status"] == "ok" and _finite(row["metrics"][c])})
            for row in grp:
                v = row["metrics"][c]
                if row["status"] != "ok" or not _finite(v):
                    continue
                if vals and v == vals[0]:
                    row["best"].append(c)
                elif len(vals) > 1 and v == vals[1]:
                    row["second"].append(c)
    return rows


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and math.isfinite(v)


def markdown_table(rows: list[dict], paper: dict | None = None) -> str:
    """The paper's layout in Markdown; **best**, <u>second</u> per group and column. With
    ``paper`` (``{(group, method): {column: value}}``) each row is followed by the paper's."""
    head = "| | Method | " + " | ".join(HEADERS[c] for c in COLUMNS) + " |"
    lines = [head, "|---|---|" + "---:|" * len(COLUMNS)]
    last = None
    for row in rows:
        g = row["group"] if row["group"] != last else ""
        last = row["group"]
        cells = []
        for c in COLUMNS:
            s = fmt(c, row["metrics"][c])
            if c in row["best"]:
                s = f"**{s}**"
            elif c in row["second"]:
                s = f"<u>{s}</u>"
            cells.append(s)
        name = row["method"] if row["status"] == "ok" else f"{row['method']} (failed)"
        if row.get("partial"):  # --duration: only part of the path
            name += f" ({row['partial'][0]:g} of {row['partial'][1]:.0f} s)"
        lines.append(f"| {g} | {name} | " + " | ".join(cells) + " |")
        if paper is not None and (row["group"], row["method"]) in paper:
            p = paper[(row["group"], row["method"])]
            lines.append("| | *paper* | " + " | ".join(f"*{fmt(c, p[c])}*" for c in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def write_csv(rows: list[dict], path: Path) -> None:
    with Path(path).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["group", "method", *COLUMNS, "best", "second", "status", "steps", "key"])
        for row in rows:
            w.writerow([row["group"], row["method"],
                        *[("" if row["metrics"][c] is None else repr(float(row["metrics"][c])))
                          for c in COLUMNS],
                        ";".join(row["best"]), ";".join(row["second"]), row["status"],
                        row["steps"], row["key"]])


# ---- the targets ----------------------------------------------------------------------
def _by_group(rows, methods=None):
    out: dict[str, dict[str, dict]] = {}
    for r in rows:
        if r["status"] == "ok" and (methods is None or r["method"] in methods):
            out.setdefault(r["group"], {})[r["method"]] = r["metrics"]
    return out


def check_targets(experiment: str, rows: list[dict], speed_of_group=None) -> list[dict]:
    """The issue's targets, evaluated on a table: ``[{target, holds, detail}]``.

    * NTWO has the best e_bar and TWO the best Omega in every row group (every case).
    * Cases 1 and 3: Kinematic has the lowest W_tw in every group, and at speed
      (>= 25 km/h: Case 1's 25 and 35 km/h, all of Case 3 at 30 km/h) by far the largest
      e_bar, "by far" meaning at least twice the next largest.
    * Case 2: TWO's W_tw is at most 35 % of Kinematic's and below DH's and TCT's.
    A target is only evaluated where all the methods it names ran, and among the paper's
    five methods only (the reference rows FF, NTWO-wheel, TWO-energy are not the paper's).
    """
    from .families import paper_methods

    g = _by_group(rows, paper_methods())
    out = []

    def add(target, holds, detail):
        out.append({"target": target, "holds": bool(holds), "detail": detail})

    def best(ms, col):
        return min(ms, key=lambda k: ms[k][col])

    for col, who, name in (("e_bar", "NTWO", "NTWO best e_bar"), ("Omega", "TWO", "TWO best Omega")):
        groups = [k for k, ms in g.items() if who in ms and len(ms) > 1]
        if not groups:
            continue
        fails = [f"{k}: {best(g[k], col)} ({fmt(col, g[k][best(g[k], col)][col])} vs "
                 f"{who} {fmt(col, g[k][who][col])})" for k in groups if best(g[k], col) != who]
        add(f"{name} in every row", not fails, "; ".join(fails) or f"all {len(groups)} groups")
    if experiment in ("case1", "case3"):
        groups = [k for k, ms in g.items() if "Kinematic" in ms and len(ms) > 1]
        if groups:
            fails = [f"{k}: {best(g[k], 'W_tw')} {fmt('W_tw', g[k][best(g[k], 'W_tw')]['W_tw'])} < "
                     f"Kinematic {fmt('W_tw', g[k]['Kinematic']['W_tw'])}"
                     for k in groups if best(g[k], "W_tw") != "Kinematic"]
            add("Kinematic lowest W_tw in every row", not fails,
                "; ".join(fails) or f"all {len(groups)} groups")
            fast = [k for k in groups if speed_of_group is None or speed_of_group(k) >= 25]
            if fast:
                det, ok = [], True
                for k in fast:
                    eb = sorted(((ms["e_bar"], m) for m, ms in g[k].items()), reverse=True)
                    kin = g[k]["Kinematic"]["e_bar"]
                    nxt = eb[1][0] if eb[0][1] == "Kinematic" else eb[0][0]
                    ok_k = eb[0][1] == "Kinematic" and kin >= 2 * nxt
                    ok &= ok_k
                    det.append(f"{k}: Kinematic e_bar {kin:.2f} vs next largest {nxt:.2f}"
                               f" ({kin / nxt:.2g}x)" if nxt > 0 else f"{k}: n/a")
                add("Kinematic by far the largest e_bar at speed (>= 2x the next)", ok,
                    "; ".join(det))
    if experiment == "case2":
        for k, ms in g.items():
            if not all(m in ms for m in ("TWO", "Kinematic", "DH", "TCT")):
                continue
            two = ms["TWO"]["W_tw"]
            kin = ms["Kinematic"]["W_tw"]
            add("Case 2: TWO W_tw <= 35 % of Kinematic's", two <= 0.35 * kin,
                f"{k}: TWO {fmt('W_tw', two)} = {100 * two / kin:.1f} % of Kinematic "
                f"{fmt('W_tw', kin)}")
            add("Case 2: TWO W_tw below DH's and TCT's", two < ms["DH"]["W_tw"] and two < ms["TCT"]["W_tw"],
                f"{k}: TWO {fmt('W_tw', two)}, DH {fmt('W_tw', ms['DH']['W_tw'])}, "
                f"TCT {fmt('W_tw', ms['TCT']['W_tw'])}")
    return out


def targets_markdown(targets: list[dict]) -> str:
    lines = ["| target | holds | detail |", "|---|---|---|"]
    for t in targets:
        lines.append(f"| {t['target']} | {'yes' if t['holds'] else '**no**'} | {t['detail']} |")
    return "\n".join(lines) + "\n"


# ---- figures -----------------------------------------------------------------------------------
def load_log(out_dir: Path, result: dict) -> dict[str, np.ndarray] | None:
    """The per-step log of a stored run as columns (None if it failed or is missing)."""
    if result.get("status") != "ok" or not result.get("log"):
        return None
    p = Path(out_dir) / result["log"]
    if not p.is_file():
        return None
    with p.open() as f:
        header = f.readline().strip().split(",")
    data = np.loadtxt(p, delimiter=",", skiprows=1, ndmin=2)
    return {h: data[:, i] for i, h in enumerate(header)}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _groups_in_order(results):
    groups = []
    for r in results:
        if r["spec"]["group"] not in groups:
            groups.append(r["spec"]["group"])
    return groups


def _group_logs(results, out_dir: Path, grp: str):
    """``(result, per-step log)`` of every stored run of row group ``grp``."""
    for r in results:
        if r["spec"]["group"] != grp:
            continue
        log = load_log(out_dir, r)
        if log is not None:
            yield r, log


def _method_legend(fig, axes, top: float = 1.0) -> None:
    """One legend for the figure (the methods and the reference), above the panels, its
    top at ``top`` (figure fraction)."""
    handles, labels = {}, {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles[lab], labels[lab] = h, lab
    if handles:
        fig.legend(list(handles.values()), list(handles), loc="upper center",
                   ncol=min(6, len(handles)), bbox_to_anchor=(0.5, top), frameon=False)


def plot_trajectories(results: list[dict], out_dir: Path, path: Path, title: str) -> None:
    """Path of every method against the reference, one panel per row group, each fitted
    to the path (the y scale stretched where the path is long and flat)."""
    from .plots import WIDTH, path_axes, style

    plt = _plt()
    groups = _groups_in_order(results)
    with style():
        height = 2.5 * len(groups) + 0.4
        fig, axes = plt.subplots(len(groups), 1, figsize=(WIDTH, height), squeeze=False)
        for ax, grp in zip(axes[:, 0], groups):
            xs, ys, ref_done = [], [], False
            for r, log in _group_logs(results, out_dir, grp):
                if not ref_done:
                    ax.plot(log["x_ref"], log["y_ref"], "k--", lw=1.2, label="reference")
                    xs.append(log["x_ref"])
                    ys.append(log["y_ref"])
                    ref_done = True
                color, marker = _style(r["spec"]["label"], (None, None))
                ax.plot(log["x"], log["y"], lw=1.1, color=color, label=r["spec"]["label"])
                xs.append(log["x"])
                ys.append(log["y"])
            ax.set_title(f"{title}, {grp}")
            ax.set_xlabel("x [m]")
            ax.set_ylabel("y [m]")
            if xs:
                path_axes(ax, xs, ys)
        _method_legend(fig, axes[:, 0])
        fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / height))
        fig.savefig(path)
        plt.close(fig)


def plot_errors(results: list[dict], out_dir: Path, path: Path, title: str) -> None:
    """e_x, e_y [cm] and e_phi [deg] over time for every method, one row per group; one
    quantity per axis."""
    from msagv.controller.metrics import wrap_angle

    from .plots import WIDTH, robust_ylim, style

    plt = _plt()
    groups = _groups_in_order(results)
    with style():
        height = 2.5 * len(groups) + 0.7
        fig, axes = plt.subplots(len(groups), 3, figsize=(WIDTH * 1.4, height), squeeze=False)
        for row, grp in zip(axes, groups):
            series = [[], [], []]
            t_all = None
            for r, log in _group_logs(results, out_dir, grp):
                step = max(1, len(log["t"]) // 1500)
                t = log["t"][::step]
                color, _ = _style(r["spec"]["label"], (None, None))
                ex = 100 * (log["x"] - log["x_ref"])[::step]
                ey = 100 * (log["y"] - log["y_ref"])[::step]
                ep = np.degrees(wrap_angle(log["phi"] - log["phi_ref"]))[::step]
                for ax, e, acc in zip(row, (ex, ey, ep), series):
                    ax.plot(t, e, lw=0.9, color=color, label=r["spec"]["label"])
                    if t_all is None or len(t) == len(t_all):
                        acc.append(e)
                t_all = t if t_all is None else t_all
            for ax, name, unit, acc in zip(row, ("e_x", "e_y", "e_phi"), ("cm", "cm", "deg"),
                                           series):
                ax.set_title(f"{grp}: {name}")
                ax.set_ylabel(f"{name} [{unit}]")
                ax.set_xlabel("t [s]")
                if acc and t_all is not None:
                    robust_ylim(ax, t_all, acc, unit)
        fig.suptitle(f"{title}: tracking errors over time", y=1 - 0.05 / height, va="top")
        _method_legend(fig, axes.ravel(), top=1 - 0.3 / height)
        fig.tight_layout(rect=(0, 0, 1, 1 - 0.5 / height))
        fig.savefig(path)
        plt.close(fig)


def plot_omega(rows: list[dict], xvalue, xlabel: str, path: Path, title: str) -> None:
    """lg(Omega) against the group variable (speed or load) for every method."""
    from .plots import style

    plt = _plt()
    with style():
        fig, ax = plt.subplots(figsize=(5.8, 3.8))
        methods = []
        for r in rows:
            if r["method"] not in methods:
                methods.append(r["method"])
        for m in methods:
            pts = sorted((xvalue(r["group"]), math.log10(r["metrics"]["Omega"])) for r in rows
                         if r["method"] == m and r["status"] == "ok"
                         and _finite(r["metrics"]["Omega"]) and r["metrics"]["Omega"] > 0)
            if not pts:
                continue
            color, marker = _style(m, (None, "o"))
            ax.plot(*zip(*pts), marker=marker, color=color, label=m)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("lg Omega (eq. 33) [-]")
        ax.set_title(title)
        ax.legend()
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)


# ---- Pareto fronts ------------------------------------------------------------------------------
def lower_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The non-dominated subset of ``(e_bar, W_tw)`` points (both to be minimised), sorted
    by e_bar: each kept point has less wear than every point more accurate than it."""
    front = []
    for e, w in sorted(points):
        if not front or w < front[-1][1]:
            if front and e == front[-1][0]:
                continue
            front.append((e, w))
    return front


def wear_at(front: list[tuple[float, float]], e: float) -> float | None:
    """W_tw the front needs at accuracy ``e`` (linear interpolation between its points);
    None outside the front's e_bar range (no extrapolation)."""
    if not front or e < front[0][0] or e > front[-1][0]:
        return None
    es = [p[0] for p in front]
    ws = [p[1] for p in front]
    return float(np.interp(e, es, ws))


def plot_pareto(fronts: dict, path: Path, vehicle: str = "") -> None:
    """W_tw against e_bar: the TWO family (L scaled), the NTWO families (regularisation
    scaled), the three baselines as points; one panel per speed."""
    from .plots import WIDTH, style

    plt = _plt()
    speeds = list(fronts)
    with style():
        fig, axes = plt.subplots(1, len(speeds), figsize=(WIDTH * 0.75 * len(speeds), 4.4),
                                 squeeze=False)
        for ax, sp in zip(axes[0], speeds):
            fr = fronts[sp]
            for fam, pts in fr["families"].items():
                ok = [p for p in pts if p["status"] == "ok"]
                if not ok:
                    continue
                color, marker = _style(fam, ("C5", "x"))
                style_ = marker + "-"
                ok = sorted(ok, key=lambda p: p["scale"])
                ax.plot([p["e_bar"] for p in ok], [p["W_tw"] for p in ok], style_, color=color,
                        ms=5, lw=1, label=f"{fam} ({fr['lever'][fam]})")
                for p in ok:
                    ax.annotate(f"x{p['scale']:g}", (p["e_bar"], p["W_tw"]), fontsize=7.5,
                                xytext=(3, 3), textcoords="offset points", color=color)
            for name, p in fr["baselines"].items():
                if p["status"] != "ok":
                    continue
                color, marker = _style(name, ("k", "*"))
                ax.plot([p["e_bar"]], [p["W_tw"]], marker, color=color, ms=8, ls="none",
                        label=name)
            es = [p["e_bar"] for f in fr["families"].values() for p in f if p["status"] == "ok"]
            es += [p["e_bar"] for p in fr["baselines"].values() if p["status"] == "ok"]
            if es and max(es) / max(min(es), 1e-9) > 30:
                ax.set_xscale("log")
            ax.set_xlabel("e_bar (eq. 32, mean of e_x, e_y [cm] and e_phi [deg])")
            ax.set_ylabel("W_tw [J] (eq. 31)")
            who = f", {vehicle}" if vehicle else ""
            ax.set_title(f"Case 1 curve at {sp}{who}: wear against accuracy")
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)
