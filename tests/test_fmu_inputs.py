"""docs/FMU.md's account of fmpy's input handling, checked: ``simulate_fmu`` interpolates
a table's inputs between rows, ``msagv plant replay`` holds each row; with the output
interval at the rows' spacing, or with the table written as steps, fmpy holds them too."""

from __future__ import annotations

import csv

import numpy as np
import pytest

fmpy = pytest.importorskip("fmpy")

WHEELS = ("11", "12", "21", "22")
NAMES = [f"omega_w_{w}" for w in WHEELS] + [f"omega_s_{w}" for w in WHEELS]
START = {"vx": 5.0}  # 5 m/s along x, wheels straight


def _table():
    """Commands every 0.5 s for 5 s: wheel speeds stepping around 10 rad/s (5 m/s at
    r_w = 0.5 m), steering rates switching sign."""
    t = np.arange(0.0, 5.0 + 1e-9, 0.5)
    k = np.arange(t.size)
    U = np.zeros((t.size, 8))
    U[:, :4] = 10.0 + 2.0 * ((k % 3) - 1)[:, None]
    U[:, 4:] = 0.2 * np.where(k % 2 == 0, 1.0, -1.0)[:, None] * np.array([1, 1, -1, -1])
    return t, U


def _signals(t, U, steps=False):
    if steps:  # each time stamp twice: the previous row's values, then the new ones
        tt = np.repeat(t, 2)[1:]
        UU = np.repeat(U, 2, axis=0)[:-1]
    else:
        tt, UU = t, U
    sig = np.zeros(tt.size, dtype=[("time", float)] + [(n, float) for n in NAMES])
    sig["time"] = tt
    for i, n in enumerate(NAMES):
        sig[n] = UU[:, i]
    return sig


def test_fmpy_holds_inputs_only_when_told(paper_fmu, tmp_path):
    from msagv.plant.replay import read_inputs, replay
    from msagv.plant.vehicle import default_vehicle

    t, U = _table()
    u_csv = tmp_path / "U.csv"
    with u_csv.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", *NAMES])
        w.writerows([[ti, *row] for ti, row in zip(t, U)])
    v = default_vehicle()
    names, S = replay(v, *read_inputs(u_csv, v), dict(START))
    held = S[-1, [names.index("x"), names.index("y")]]  # the state at t = 5 s

    def end(**kw):
        res = fmpy.simulate_fmu(str(paper_fmu), start_values={"vx_0": START["vx"]},
                                stop_time=float(t[-1]), output=["x", "y"], **kw)
        assert res["time"][-1] == pytest.approx(t[-1])
        return np.array([res["x"][-1], res["y"][-1]])

    # fmpy's default: interpolated between the rows, a different path
    assert np.hypot(*(end(input=_signals(t, U)) - held)) > 0.05
    # communication points on the rows: each row held, as plant replay
    np.testing.assert_allclose(end(input=_signals(t, U), output_interval=0.5), held, atol=1e-9)
    # the table as steps: held for any output interval
    np.testing.assert_allclose(end(input=_signals(t, U, steps=True)), held, atol=1e-6)
