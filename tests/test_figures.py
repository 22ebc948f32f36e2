"""The report figures' axes (experiments/plots.py): a long flat path keeps its shape, a
start-up transient does not own the y axis, titles name the scenario."""

from __future__ import annotations

import numpy as np

from msagv.experiments.plots import path_axes, pyplot, robust_ylim, run_title


def test_a_lane_change_keeps_its_shape():
    plt = pyplot()
    fig, ax = plt.subplots()
    x = np.linspace(0, 90, 500)
    y = 3.5 * (1 - np.cos(np.pi * np.clip((x - 20) / 40, 0, 1))) / 2
    path_axes(ax, [x], [y])
    y0, y1 = ax.get_ylim()
    assert y0 < 0 < 3.5 < y1 and y1 - y0 < 5  # not +-45 m, as equal axes would give
    assert "not to scale" in ax.get_ylabel()
    fig2, ax2 = plt.subplots()
    th = np.linspace(0, np.pi / 2, 100)  # a quarter circle: to scale
    path_axes(ax2, [20 * np.sin(th)], [20 * (1 - np.cos(th))])
    assert ax2.get_aspect() == 1.0
    plt.close("all")


def test_a_start_up_peak_is_cut_off_and_noted():
    plt = pyplot()
    fig, ax = plt.subplots()
    t = np.arange(0, 10, 0.01)
    p = 0.1 + 0.05 * np.sin(t)
    p[:30] = 400.0  # 0.3 s of start-up
    ax.plot(t, p)
    robust_ylim(ax, t, [p], "kW")
    assert ax.get_ylim()[1] < 1.0
    assert any("start-up peak 400 kW" in txt.get_text() for txt in ax.texts)
    fig2, ax2 = plt.subplots()  # a large error that lasts is the result, not a spike
    e = 60.0 * np.exp(-t / 2)
    ax2.plot(t, e)
    robust_ylim(ax2, t, [e], "deg")
    assert ax2.get_ylim()[1] >= 60 and not ax2.texts
    plt.close("all")


def test_run_title_names_the_scenario():
    info = {"reference": "case1-curve", "speed_kmh": 25.0,
            "vehicle": {"name": "agv-3axle", "axles": 3, "mass_kg": 24000.0},
            "method": "two", "model": "mf", "solver": "ipopt"}
    assert run_title(info) == "case1-curve at 25 km/h, agv-3axle (3 axles, 24 t), TWO (mf, IPOPT)"
