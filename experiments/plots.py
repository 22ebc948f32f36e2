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
        solver = ", IPOPT" if info.get("solver") == "ipopt" else ""
        parts.append(f"{str(info['method']).upper()} ({info.get('model')}{solver})")
    if how:
        parts.append(how)
    return ", ".join(parts)


def plot_run(log, reference, path, title: str = "") -> None:
    """PNG: path vs reference, tracking errors and wear power over time."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from controller.metrics import wrap_angle

    a = log.arrays()
    t, pose, ref = a["t"], a["pose"], a["ref"]
    W = a["W"]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
    dense = reference.sample(np.linspace(reference.t[0], reference.t[-1], 2000))
    ax[0].plot(dense[:, 0], dense[:, 1], "k--", lw=1, label="reference")
    ax[0].plot(pose[:, 0], pose[:, 1], "C0", lw=1.5, label="vehicle")
    ax[0].set_xlabel("x [m]")
    ax[0].set_ylabel("y [m]")
    ax[0].axis("equal")
    ax[0].legend()
    ax[0].set_title("path")
    ax[1].plot(t, 100 * (pose[:, 0] - ref[:, 0]), label="e_x [cm]")
    ax[1].plot(t, 100 * (pose[:, 1] - ref[:, 1]), label="e_y [cm]")
    ax[1].plot(t, np.degrees(wrap_angle(pose[:, 2] - ref[:, 2])), label="e_phi [deg]")
    ax[1].set_xlabel("t [s]")
    ax[1].legend()
    ax[1].set_title("tracking errors")
    if len(t) > 1:
        dt = np.diff(t)
        P = np.diff(W, axis=0) / dt[:, None] / 1000.0
        for i, name in enumerate(("P_s", "P_alpha", "P_t")):
            ax[2].plot(t[:-1], P[:, i], label=f"{name} [kW]")
    ax[2].set_xlabel("t [s]")
    ax[2].legend()
    ax[2].set_title("wear power (mean over each period)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
