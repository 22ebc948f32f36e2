"""``msagv plant replay`` (plant/replay.py, msagv/cli/__init__.py) as a user runs it: a 3-axle vehicle
file, a CSV of random held commands, compared with the independent reference model; and
malformed CSVs rejected with exit code 2 and a message naming the line."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from msagv.plant import load_vehicle
from msagv.plant.signals import input_names, signal_names

import reference_model as ref  # tests/ is not a package: pytest puts it on sys.path
from helpers import THREE_AXLE_TOML, run_msagv


def _run(*args, timeout=120):
    return run_msagv(*args, timeout=timeout)


def _write_inputs(path, names, t, U):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t"] + names)
        for tk, row in zip(t, U):
            w.writerow([repr(float(tk))] + [repr(float(x)) for x in row])


def _read_signals(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], np.array(rows[1:], dtype=float)


def test_replay_matches_reference(tmp_path, three_axle_file):
    v = load_vehicle(three_axle_file)
    assert v.n_axles == 3
    rv = ref.RefVehicle.from_description(v.to_dict())
    rng = np.random.default_rng(20240611)
    K = 300
    dt = rng.uniform(0.005, 0.02, K - 1)  # irregular rows: each held until the next
    t = np.concatenate([[0.0], np.cumsum(dt)])
    U_w, U_s = ref.varied_inputs(rv, K, seed=77, T=np.append(dt, 0.01), v_mean=5.0,
                                 omega_s_max=0.7)
    assert np.all(np.abs(np.cumsum(dt[:, None] * U_s[:-1], axis=0)) < 1.4)
    names = input_names(v)
    U = np.hstack([U_w, U_s])
    inputs = tmp_path / "U.csv"
    out = tmp_path / "S.csv"
    _write_inputs(inputs, names, t, U)
    init = {"x": 2.0, "y": -1.0, "phi": 0.4, "vx": 4.0 * math.cos(0.4),
            "vy": 4.0 * math.sin(0.4), "r": 0.05, "delta_21": 0.1}
    r = _run("plant", "replay", "--vehicle", str(three_axle_file), "--inputs", str(inputs),
             "--out", str(out), "--initial", ",".join(f"{k}={val!r}" for k, val in init.items()))
    assert r.returncode == 0, r.stderr
    header, S = _read_signals(out)
    assert header == ["t"] + signal_names(v)
    assert S.shape == (K, len(header))
    col = {n: i for i, n in enumerate(header)}
    np.testing.assert_array_equal(S[:, 0], t)

    delta0 = np.zeros(6)
    delta0[2] = 0.1
    z0 = ref.initial_state(rv, x=2.0, y=-1.0, phi=0.4, vx=init["vx"], vy=init["vy"], r=0.05,
                           delta=delta0)
    Z = ref.simulate(rv, z0, U_w[:-1], U_s[:-1], T=dt)
    assert np.hypot(Z[-1, 0] - 2.0, Z[-1, 1] + 1.0) > 10.0  # it went somewhere

    def sig(prefix):
        return S[:, [col[f"{prefix}_{k}"] for k in v.wheel_names]]

    np.testing.assert_allclose(S[:, col["x"]], Z[:, 0], atol=1e-6)
    np.testing.assert_allclose(S[:, col["y"]], Z[:, 1], atol=1e-6)
    np.testing.assert_allclose(S[:, col["phi"]], Z[:, 2], atol=1e-7)
    np.testing.assert_allclose(S[:, [col["vx"], col["vy"], col["r"]]], Z[:, 3:6], atol=1e-6)
    np.testing.assert_allclose(sig("delta"), Z[:, 6:12], atol=1e-12)
    W = S[:, [col["W_s"], col["W_alpha"], col["W_t"]]]
    np.testing.assert_allclose(W, Z[:, 12:15], rtol=1e-6, atol=1e-3)
    np.testing.assert_allclose(S[:, col["W_tw"]], W.sum(axis=1), rtol=1e-12)

    # row k's slips and forces are those of the state at t[k] with row k's commands
    for k in (0, 1, 57, 150, K - 1):
        phi = Z[k, 2]
        c, s = math.cos(phi), math.sin(phi)
        u, w = c * Z[k, 3] + s * Z[k, 4], -s * Z[k, 3] + c * Z[k, 4]
        _, _, sl, al, Fx, Fy = ref.wheel_quantities(rv, u, w, Z[k, 5], Z[k, 6:12], U_w[k])
        np.testing.assert_allclose(sig("s")[k], sl, atol=1e-6)
        np.testing.assert_allclose(sig("alpha")[k], al, atol=1e-6)
        np.testing.assert_allclose(sig("Fx")[k], Fx, rtol=1e-5, atol=1e-2)
        np.testing.assert_allclose(sig("Fy")[k], Fy, rtol=1e-5, atol=1e-2)
        np.testing.assert_allclose(sig("omega_w")[k], U_w[k], rtol=1e-12)
        np.testing.assert_allclose(sig("omega_s")[k], U_s[k], rtol=1e-12)
    # the static load of this vehicle: 18500 * 9.81 / 6 = 30247.5 N
    np.testing.assert_allclose(sig("F_N"), 30247.5)


# ---- malformed CSVs ---------------------------------------------------------------------
def _good_rows(names, n_rows=6):
    rows = []
    for k in range(n_rows):
        rows.append([f"{0.01 * k:.2f}"] + ["10.0" if n.startswith("omega_w") else "0.0"
                                            for n in names])
    return rows


def _malformed(names, case):
    header = ["t"] + names
    rows = _good_rows(names)
    ci = header.index
    if case == "missing column":
        j = ci("omega_s_32")
        header = header[:j] + header[j + 1:]
        rows = [r[:j] + r[j + 1:] for r in rows]
        return header, rows, 1, "omega_s_32"
    if case == "NaN":
        rows[2][ci("omega_w_21")] = "nan"  # line 4 (header is line 1)
        return header, rows, 4, "omega_w_21"
    if case == "inf":
        rows[1][ci("omega_s_11")] = "-inf"  # line 3
        return header, rows, 3, "omega_s_11"
    if case == "non-increasing t":
        rows[3][0] = rows[2][0]  # line 5 repeats line 4's time
        return header, rows, 5, "t"
    if case == "decreasing t":
        rows[4][0] = "0.005"  # line 6
        return header, rows, 6, "t"
    if case == "negative wheel speed":
        rows[1][ci("omega_w_12")] = "-0.5"  # line 3
        return header, rows, 3, "omega_w_12"
    if case == "non-number":
        rows[4][ci("omega_s_22")] = "abc"  # line 6
        return header, rows, 6, "omega_s_22"
    if case == "short row":
        rows[0] = rows[0][:-2]  # line 2
        return header, rows, 2, "fields"
    raise AssertionError(case)


MALFORMED = ["missing column", "NaN", "inf", "non-increasing t", "decreasing t",
             "negative wheel speed", "non-number", "short row"]


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_csv_is_rejected_naming_the_line(tmp_path, three_axle_file, case):
    names = input_names(load_vehicle(three_axle_file))
    header, rows, line, word = _malformed(names, case)
    inputs = tmp_path / "U.csv"
    with open(inputs, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)
    out = tmp_path / "S.csv"
    r = _run("plant", "replay", "--vehicle", str(three_axle_file), "--inputs", str(inputs),
             "--out", str(out))
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert f"U.csv:{line}:" in r.stderr, r.stderr
    assert word in r.stderr
    assert not out.exists()


def test_the_unmodified_csv_is_accepted(tmp_path, three_axle_file):
    # control for the cases above: the base rows replay fine
    names = input_names(load_vehicle(three_axle_file))
    inputs = tmp_path / "U.csv"
    with open(inputs, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t"] + names)
        w.writerows(_good_rows(names))
    out = tmp_path / "S.csv"
    r = _run("plant", "replay", "--vehicle", str(three_axle_file), "--inputs", str(inputs),
             "--out", str(out))
    assert r.returncode == 0, r.stderr
    header, S = _read_signals(out)
    assert S.shape[0] == 6


@pytest.mark.parametrize("args, word", [
    (["--initial", "speed=3"], "speed"),
    (["--initial", "delta_11=2.0"], "delta_11"),
    (["--initial", "x=abc"], "x"),
])
def test_bad_initial_is_rejected(tmp_path, three_axle_file, args, word):
    names = input_names(load_vehicle(three_axle_file))
    inputs = tmp_path / "U.csv"
    with open(inputs, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t"] + names)
        w.writerows(_good_rows(names, 2))
    r = _run("plant", "replay", "--vehicle", str(three_axle_file), "--inputs", str(inputs),
             "--out", str(tmp_path / "S.csv"), *args)
    assert r.returncode == 2
    assert word in r.stderr


def test_bad_three_axle_file_is_rejected(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text(THREE_AXLE_TOML.replace("mass = 18500.0", "mass = -1.0"))
    inputs = tmp_path / "U.csv"
    inputs.write_text("t\n0.0\n")
    r = _run("plant", "replay", "--vehicle", str(p), "--inputs", str(inputs),
             "--out", str(tmp_path / "S.csv"))
    assert r.returncode == 2 and "mass" in r.stderr
