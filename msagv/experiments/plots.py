"""Figures of one run: the driven path against the reference, tracking errors, wear power.

Used by ``msagv run --plot``, ``msagv report --plot`` and ``msagv demo``; the experiments'
own figures (tables of runs, fronts) are in :mod:`experiments.tables`.
"""

from __future__ import annotations


def run_title(info: dict, how: str | None = None) -> str:
    """A figure title naming the scenario from a result's ``scenario`` block: reference,
    speed, vehicle (axles, mass), method (model, solver) and, optionally, ``how`` it ran."""
    parts = [info.get("reference") or info.get("case") or "run"]
    sp = info.get("speed_kmh")
    if sp is not None:
        parts[0] += f" at {sp:g} km/h" if isinstance(sp, (int, float)) else f" at {sp} km/h"
    v = info.get("vehicle") or {}
    if v:
        parts.append(f"{v.get('name')} ({v.get('axles')} axles, {v.get('mass_kg', 0) / 1000:g} t)")
    if info.get("method"):
        name = info.get("solver")
        solver = ("" if name in (None, "sa") else
                  ", " + {"ipopt": "IPOPT", "acados": "acados RTI"}.get(name, name))
        parts.append(f"{str(info['method']).upper()} ({info.get('model')}{solver})")
    if how:
        parts.append(how)
    return ", ".join(parts)


# ---- the house style of a report figure ---------------------------------------------------
# Sized for print: a figure 7.2 in (18 cm) wide is printed at about its own size, so 9-10 pt
# text stays 9-10 pt on paper; PNGs at 200 dpi.
STYLE = {"font.size": 9.5, "axes.titlesize": 10, "axes.labelsize": 9.5,
         "xtick.labelsize": 8.5, "ytick.labelsize": 8.5, "legend.fontsize": 8.5,
         "figure.titlesize": 10.5, "axes.grid": True, "grid.alpha": 0.3,
         "legend.framealpha": 0.85, "savefig.dpi": 200, "savefig.bbox": "tight"}
WIDTH = 7.2  # in


def pyplot():
    """matplotlib's pyplot on the non-interactive backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def style():
    """``with style(): ...``: the report style for the figures made inside."""
    return pyplot().rc_context(STYLE)


def path_axes(ax, xs, ys, margin: float = 0.06) -> None:
    """Limits that show a path's shape: equal scales when the path is not much longer
    than wide; otherwise each axis fitted to the path (the y scale stretched, said in the
    axis label), never a y range set by the x range."""
    import numpy as np

    xs = np.concatenate([np.asarray(x, float).ravel() for x in xs])
    ys = np.concatenate([np.asarray(y, float).ravel() for y in ys])
    ok = np.isfinite(xs) & np.isfinite(ys)
    xs, ys = xs[ok], ys[ok]
    if xs.size == 0:
        return
    x0, x1, y0, y1 = xs.min(), xs.max(), ys.min(), ys.max()
    w, h = max(x1 - x0, 1e-3), max(y1 - y0, 1e-3)
    if h / w >= 0.2 and w / h >= 0.2:
        # equal scales: the limits follow the data (plus the margin) and the aspect widens
        # one of them; fixing both as well would make matplotlib ignore one, with a warning
        ax.set_aspect("equal", adjustable="datalim")
        ax.margins(margin)
        return
    else:
        h = max(h, 0.5)  # a straight line still shows +-0.25 m
        ym = 0.5 * (y0 + y1)
        y0, y1 = ym - h / 2, ym + h / 2
        ax.set_ylabel(ax.get_ylabel() + " (not to scale)")
    ax.set_xlim(x0 - margin * w, x1 + margin * w)
    ax.set_ylim(y0 - margin * h, y1 + margin * h)


def robust_ylim(ax, t, series, unit: str = "", start: float = 0.5, ratio: float = 4.0) -> None:
    """Keep a start-up transient from owning the y axis: when the first ``start`` seconds
    reach more than ``ratio`` times as far as the rest of the run, fit the axis to the rest
    and note the start-up's extreme on the axes."""
    import numpy as np

    t = np.asarray(t, float)
    late = t >= t[0] + start if t.size else t.astype(bool)
    if t.size < 10 or not late.any() or late.all():
        return
    vals = [np.asarray(y, float) for y in series]
    lo = min(np.nanmin(y[late]) for y in vals)
    hi = max(np.nanmax(y[late]) for y in vals)
    span = max(hi - lo, 1e-12)
    peak = max(np.nanmax(np.abs(y[~late])) for y in vals)
    if peak > ratio * max(abs(lo), abs(hi), span):
        pad = 0.1 * span
        ax.set_ylim(lo - pad, hi + pad)
        ax.text(0.99, 0.97, f"start-up peak {peak:.3g} {unit} (off scale)".replace("  ", " "),
                transform=ax.transAxes,
                ha="right", va="top", fontsize=8, color="0.35")


def plot_run(log, reference, path, title: str = "") -> None:
    """A report figure of one run (2 x 2): the path against the reference; the position
    error [cm]; the heading error [deg]; the wear powers [kW]. One quantity per axis."""
    import numpy as np

    from msagv.controller.metrics import wrap_angle

    plt = pyplot()
    a = log.arrays()
    t, pose, ref = a["t"], a["pose"], a["ref"]
    W = a["W"]
    with style():
        fig, ax = plt.subplots(2, 2, figsize=(WIDTH, 5.6))
        (ax_path, ax_pos), (ax_head, ax_wear) = ax
        t_end = t[-1] if len(t) else reference.t[-1]
        dense = reference.sample(np.linspace(reference.t[0], max(t_end, reference.t[0] + 1e-3),
                                             2000))
        ax_path.plot(dense[:, 0], dense[:, 1], "k--", lw=1, label="reference")
        ax_path.plot(pose[:, 0], pose[:, 1], "C0", lw=1.4, label="vehicle")
        if len(pose):
            ax_path.plot(pose[:1, 0], pose[:1, 1], "o", color="C0", ms=4, label="start")
        ax_path.set_xlabel("x [m]")
        ax_path.set_ylabel("y [m]")
        path_axes(ax_path, [dense[:, 0], pose[:, 0]], [dense[:, 1], pose[:, 1]])
        ax_path.legend(loc="best")
        ax_path.set_title("path")

        ex, ey = 100 * (pose[:, 0] - ref[:, 0]), 100 * (pose[:, 1] - ref[:, 1])
        ax_pos.plot(t, ex, "C0", lw=1, label="e_x")
        ax_pos.plot(t, ey, "C1", lw=1, label="e_y")
        ax_pos.set_xlabel("t [s]")
        ax_pos.set_ylabel("position error [cm]")
        ax_pos.legend(loc="best")
        ax_pos.set_title("position error (global frame)")
        robust_ylim(ax_pos, t, [ex, ey], "cm")

        ephi = np.degrees(wrap_angle(pose[:, 2] - ref[:, 2]))
        ax_head.plot(t, ephi, "C2", lw=1)
        ax_head.set_xlabel("t [s]")
        ax_head.set_ylabel("heading error [deg]")
        ax_head.set_title("heading error")
        robust_ylim(ax_head, t, [ephi], "deg")

        if len(t) > 1:
            P = np.diff(W, axis=0) / np.diff(t)[:, None] / 1000.0
            for i, (name, c) in enumerate((("P_s (slip)", "C0"), ("P_alpha (slip angle)", "C1"),
                                           ("P_t (steering)", "C2"))):
                ax_wear.plot(t[:-1], P[:, i], c, lw=1, label=name)
            robust_ylim(ax_wear, t[:-1], [P[:, i] for i in range(3)], "kW")
            ax_wear.legend(loc="best")
        ax_wear.set_xlabel("t [s]")
        ax_wear.set_ylabel("wear power [kW]")
        ax_wear.set_title("wear power (mean over each period)")
        if title:
            fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)


def plot_wear(log, path, title: str = "", wear: dict | None = None) -> None:
    """A report figure of the wear per wheel and per axle (2 x 1, readable up to 8 axles
    and more): each wheel's wear work split into W_s, W_alpha, W_t [kJ], each axle's total
    and share above its pair, and on the right axis the same per km driven [J/km]; with a
    tire wear calibration each axle's projected tire life [km] under its share; below, each
    axle's wear power over time [kW] (mean over each period). ``wear``: the run's wear block
    with its per-km figures (:func:`controller.metrics.wear_per_km`; default the log's
    per-wheel wear, without them). Needs the per-wheel wear work in the log
    (:meth:`controller.loop.RunLog.wheel_wear`); raises ValueError without it."""
    import numpy as np

    wear = wear if wear is not None else log.wheel_wear()
    if wear is None:
        raise ValueError("the log has no per-wheel wear work (W_s_ij, W_alpha_ij, W_t_ij)")
    plt = pyplot()
    wheels = list(wear["wheels"])
    axles = list(wear["axles"])
    n = len(axles)
    comp = [("W_s", "W_s (slip)", "C0"), ("W_alpha", "W_alpha (slip angle)", "C1"),
            ("W_t", "W_t (steering)", "C2")]
    t = np.asarray(log.t, float)
    Wij = np.asarray(log.W_ij, float)  # (rows, 3, nw)
    total = sum(a["W_tw"] for a in wear["axles"].values())
    per_km = wear.get("per_km")
    calibrated = per_km is not None and wear.get("calibration") is not None
    small = 7.5 if n <= 4 else 6.5  # the axle notes: narrower groups at many axles
    with style():
        fig, (ax_w, ax_p) = plt.subplots(2, 1, figsize=(WIDTH, 6.4),
                                         gridspec_kw={"height_ratios": [1.25, 1.0]})
        x = np.arange(len(wheels)) + np.repeat(np.arange(n) * 0.6, 2)
        bottom = np.zeros(len(wheels))
        for key, label, c in comp:
            h = np.array([wear["wheels"][k][key] for k in wheels]) / 1000.0
            ax_w.bar(x, h, 0.8, bottom=bottom, color=c, label=label)
            bottom += h
        top = max(bottom.max(), 1e-9)
        for i, a in enumerate(axles):  # one row of notes at one height: they never collide
            tw = wear["axles"][a]["W_tw"] / 1000.0
            note = [f"axle {a}", f"{tw:.3g} kJ"]
            if total > 0:
                note.append(f"{100.0 * wear['axles'][a]['W_tw'] / total:.0f} %")
            if calibrated:
                life = per_km["axles"][a]["life_km"]
                note.append("no wear" if life is None else
                            f"{life:,.0f} km" if life >= 100 else f"{life:.3g} km")
            ax_w.text(x[2 * i:2 * i + 2].mean(), top * 1.04, "\n".join(note), ha="center",
                      va="bottom", fontsize=small, linespacing=1.1)
        ax_w.set_xticks(x, wheels)
        if n > 5:
            ax_w.tick_params(axis="x", labelsize=7)
        ax_w.set_xlim(x[0] - 0.7, x[-1] + 0.7)
        ax_w.set_xlabel("wheel ij (axle i from the front, j = 1 left, 2 right)")
        ax_w.set_ylabel("wear work [kJ]")
        rows = 3 + (total > 0) + calibrated  # the legend's line and the notes' lines
        ax_w.set_ylim(0, top * (1.12 + 0.12 * rows))
        ax_w.legend(loc="upper left", ncol=3, fontsize=7, handlelength=1.0, columnspacing=0.8,
                    frameon=False)
        what = "wear work per wheel"
        if per_km is not None:
            km = wear["distance_m"] / 1000.0
            sec = ax_w.secondary_yaxis("right", functions=(lambda v: v * 1000.0 / km,
                                                           lambda v: v * km / 1000.0))
            from matplotlib.ticker import EngFormatter

            sec.yaxis.set_major_formatter(EngFormatter(sep=""))  # 200k, not 200000
            sec.set_ylabel("per km driven [J/km]")
            what += f" over {wear['distance_m']:.0f} m driven"
            if calibrated:
                what += "; notes: projected tire life of the axle's faster-wearing tire"
        ax_w.set_title(what, fontsize=9)
        if len(t) > 1:
            per_wheel = Wij.sum(axis=1)  # W_tw_ij at each row
            P = np.diff(per_wheel, axis=0) / np.diff(t)[:, None] / 1000.0
            series = []
            for i, a in enumerate(axles):
                pa = P[:, 2 * i] + P[:, 2 * i + 1]
                series.append(pa)
                ax_p.plot(t[:-1], pa, lw=1, label=f"axle {a}")
            robust_ylim(ax_p, t[:-1], series, "kW")
            # beside the plot, never over the curves (one column up to 8 axles)
            ax_p.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7.5,
                        ncol=1 if n <= 10 else 2, frameon=False, handlelength=1.2)
        ax_p.set_xlabel("t [s]")
        ax_p.set_ylabel("wear power [kW]")
        ax_p.set_title("wear power per axle (mean over each period)", fontsize=9)
        if title:
            fig.suptitle(title)
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)
