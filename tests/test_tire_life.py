"""Wear per kilometre and tire life (issue 21, item 6; docs/WEAR.md): the ``[tire.wear]``
calibration is read and checked naming its keys; every run reports its wear work per km
driven; with a calibration the tread loss, life and cost per km of each tire, axle and the
vehicle match a hand computation from the run's own per-wheel wear work and distance
(Archard: V = k_a W); without one no life is ever printed."""

from __future__ import annotations

import csv
import json
import math
import re

import numpy as np
import pytest

from helpers import THREE_AXLE_TOML

from msagv.cli import main
from msagv.plant.vehicle import TireWear, VehicleError, load_vehicle, vehicle_from_dict

REFERENCE = ["tread_width = 250.0", "usable_depth = 14.0", "reference_life_km = 80000.0",
             "reference_work_per_km = 9000.0"]


def run(capsys, *args):
    rc = main([str(a) for a in args])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def with_wear(lines, text=THREE_AXLE_TOML) -> str:
    """``text`` with a ``[tire.wear]`` table of ``lines`` (before ``[limits]``)."""
    out = text.replace("[limits]", "[tire.wear]\n" + "\n".join(lines) + "\n\n[limits]")
    assert out != text
    return out


def vehicle_file(tmp_path, lines, name="v.toml"):
    p = tmp_path / name
    p.write_text(with_wear(lines) if lines is not None else THREE_AXLE_TOML)
    return p


# ---- the calibration ---------------------------------------------------------------------
def test_the_usable_tread_and_the_abradability_from_a_known_life(tmp_path):
    v = load_vehicle(vehicle_file(tmp_path, REFERENCE + ["price = 450.0"]))
    tw = v.tire_wear
    # the tread band of a tire 2 x 0.45 m across: pi x 900 mm x 250 mm x 14 mm
    V = math.pi * 900.0 * 250.0 * 14.0
    assert tw.usable_volume(v.wheel_radius) == pytest.approx(V, rel=1e-12)
    assert tw.k_a(v.wheel_radius) == pytest.approx(V / (80000.0 * 9000.0), rel=1e-12)
    assert tw.price == 450.0
    given = TireWear(tread_width=250.0, usable_depth=14.0, abradability=0.02)
    assert given.k_a(0.45) == 0.02
    # the table survives the vehicle's round trip (FMU configurations, recordings' headers)
    assert vehicle_from_dict(v.to_dict()) == v
    assert v.to_dict()["tire"]["wear"] == {"tread_width": 250.0, "usable_depth": 14.0,
                                            "reference_life_km": 80000.0,
                                            "reference_work_per_km": 9000.0, "price": 450.0}


@pytest.mark.parametrize("lines, words", [
    (REFERENCE + ["abradability = 0.02"], "tire.wear.abradability: give the abradability or "
                                          "a reference life"),
    (REFERENCE[:3], "tire.wear.reference_work_per_km: missing"),
    (REFERENCE[:2], "tire.wear.abradability: missing"),
    (REFERENCE[1:], "tire.wear.tread_width: missing"),
    (["tread_width = 250.0", "usable_depth = -3.0", "abradability = 0.02"],
     "tire.wear.usable_depth: must be > 0, got -3.0"),
    (["tread_width = 250.0", "usable_depth = 600.0", "abradability = 0.02"],
     "tire.wear.usable_depth: 600 mm is not less than the wheel radius (450 mm)"),
    (["tread_width = 250.0", "usable_depth = 14.0", "abradability = 0.0"],
     "tire.wear.abradability: must be > 0, got 0.0"),
    (REFERENCE + ["price = -1.0"], "tire.wear.price: must be >= 0, got -1.0"),
    (REFERENCE + ["prise = 400.0"], "tire.wear.prise: unknown key"),
    (REFERENCE[:3] + ["reference_work_per_km = 'lots'"],
     "tire.wear.reference_work_per_km: expected a number, got 'lots'"),
])
def test_a_bad_calibration_is_refused_naming_the_key(lines, words, tmp_path, capsys):
    f = vehicle_file(tmp_path, lines)
    with pytest.raises(VehicleError, match="^" + re.escape(f"{f}: {words}")):
        load_vehicle(f)
    rc, out, err = run(capsys, "vehicle", "show", "--vehicle", f)
    assert rc == 2 and err.startswith(f"msagv vehicle show: {f}: {words}")
    assert len(err.strip().splitlines()) == 1


def test_a_tread_in_metres_warns(tmp_path, capsys):
    f = vehicle_file(tmp_path, ["tread_width = 0.25", "usable_depth = 14.0",
                                "abradability = 0.02"])
    rc, out, err = run(capsys, "vehicle", "show", "--vehicle", f)
    assert rc == 0 and "warning: tire.wear.tread_width: 0.25 mm: metres typed as mm? (0.25 m " \
                       "is 250 mm)" in err


# ---- per km and life: the arithmetic ------------------------------------------------------
def test_per_km_and_life_by_hand():
    from msagv.controller.metrics import wear_by_wheel, wear_per_km

    # two axles; wheel 22 does no wear work at all
    dW = np.array([[100.0, 50.0, 20.0, 0.0], [300.0, 10.0, 5.0, 0.0], [0.0, 40.0, 25.0, 0.0]])
    wear = wear_by_wheel(dW)
    cal = TireWear(tread_width=200.0, usable_depth=10.0, abradability=0.05)
    out = wear_per_km(wear, 250.0, cal, 0.5, price=300.0)
    D, w, d = 1000.0, 200.0, 10.0  # mm
    V = math.pi * D * w * d
    for k, W in zip(("11", "12", "21", "22"), dW.sum(axis=0)):
        e = out["per_km"]["wheels"][k]
        E = W / 0.25  # J/km over 250 m
        assert e["W_tw_per_km"] == pytest.approx(E)
        assert e["tread_loss_mm_per_1000km"] == pytest.approx(1000 * 0.05 * E / (math.pi * D * w))
        if W > 0:
            assert e["life_km"] == pytest.approx(V / (0.05 * E))
            assert e["cost_per_km"] == pytest.approx(300.0 / (V / (0.05 * E)))
        else:
            assert e["life_km"] is None and e["cost_per_km"] == 0.0
    a1, a2, veh = out["per_km"]["axles"]["1"], out["per_km"]["axles"]["2"], out["per_km"]["vehicle"]
    wheels = out["per_km"]["wheels"]
    assert a1["W_tw_per_km"] == pytest.approx((400.0 + 100.0) / 0.25)
    assert a1["life_km"] == min(wheels["11"]["life_km"], wheels["12"]["life_km"])
    assert a2["life_km"] == wheels["21"]["life_km"]  # 22 never wears out
    assert veh["first_worn"] == "11" and veh["life_km"] == wheels["11"]["life_km"]
    assert veh["cost_per_km"] == pytest.approx(sum(e["cost_per_km"] for e in wheels.values()))
    assert out["calibration"]["abradability_mm3_per_J"] == 0.05
    # no calibration: the J/km only, no life anywhere; too short a run: nothing per km
    bare = wear_per_km(wear, 250.0)
    assert bare["calibration"] is None and set(bare["per_km"]["wheels"]["11"]) == {"W_tw_per_km"}
    assert wear_per_km(wear, 0.4, cal, 0.5)["per_km"] is None


# ---- a run on a route the test draws ----------------------------------------------------------
def s_bend(path, kmh=10.0, dt=0.1):
    """An S-bend: 2.5 m straight, 10 m of a sine of 0.75 m amplitude, 2.5 m straight (about
    5 s at 10 km/h); heading along the path."""
    v = kmh / 3.6
    xs = np.linspace(0.0, 15.0, 1501)
    ys = np.where((xs > 2.5) & (xs < 12.5), 0.75 * np.sin(2 * np.pi * (xs - 2.5) / 10.0), 0.0)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(xs), np.diff(ys)))])
    t = np.arange(0.0, s[-1] / v, dt)
    x, y = np.interp(v * t, s, xs), np.interp(v * t, s, ys)
    phi = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x", "y", "phi"])
        w.writerows(zip(np.round(t, 6), x, y, phi))
    return path, float(s[-1])


@pytest.mark.parametrize("form", ["reference", "abradability"])
def test_the_life_of_a_run_matches_a_hand_computation_from_its_wear_work(form, tmp_path,
                                                                         capsys):
    route, length = s_bend(tmp_path / "route.csv")
    lines = REFERENCE if form == "reference" else [
        "tread_width = 250.0", "usable_depth = 14.0", "abradability = 0.015"]
    f = vehicle_file(tmp_path, lines)
    plot = tmp_path / "wear.png"
    # (--no-floor: the wear floor's IPOPT solve took 34 s of this run's 35 s)
    rc, out, err = run(capsys, "run", "--trajectory", route, "--vehicle", f, "--json",
                       "--tire-price", "450", "--iterations", "20", "--wear-plot", plot,
                       "--no-floor")
    assert rc == 0, err
    doc = json.loads(out)
    assert doc["floors"] is None and doc["broken_floor"] == []  # none computed
    wear, m = doc["wear"], doc["metrics"]
    d = wear["distance_m"]
    assert d == m["distance_m"] and d == pytest.approx(length, abs=0.5)  # it drove the route
    km = d / 1000.0
    r_w, w, depth = 0.45, 250.0, 14.0
    band = math.pi * 2000.0 * r_w * w
    V = band * depth
    k_a = V / (80000.0 * 9000.0) if form == "reference" else 0.015
    assert wear["calibration"]["abradability_mm3_per_J"] == pytest.approx(k_a, rel=1e-12)
    lives, costs = {}, []
    for k, wheel in wear["wheels"].items():
        E = wheel["W_tw"] / km
        e = wear["per_km"]["wheels"][k]
        assert e["W_tw_per_km"] == pytest.approx(E, rel=1e-12)
        assert e["tread_loss_mm_per_1000km"] == pytest.approx(1000.0 * k_a * E / band, rel=1e-12)
        lives[k] = V / (k_a * E)
        if form == "reference":  # the life scales inversely with the route's J/km
            assert lives[k] == pytest.approx(80000.0 * 9000.0 / E, rel=1e-12)
        assert e["life_km"] == pytest.approx(lives[k], rel=1e-12)
        assert e["cost_per_km"] == pytest.approx(450.0 / lives[k], rel=1e-12)
        costs.append(450.0 / lives[k])
    veh = wear["per_km"]["vehicle"]
    assert veh["life_km"] == pytest.approx(min(lives.values()), rel=1e-12)
    assert veh["first_worn"] == min(lives, key=lives.get)
    assert veh["cost_per_km"] == pytest.approx(sum(costs), rel=1e-12)
    assert veh["W_tw_per_km"] == pytest.approx(m["W_tw_per_km"], rel=1e-9)
    assert m["W_tw_per_km"] == pytest.approx(m["W_tw"] / km, rel=1e-12)
    for a, axle in wear["per_km"]["axles"].items():
        pair = [f"{a}1", f"{a}2"]
        assert axle["life_km"] == pytest.approx(min(lives[k] for k in pair), rel=1e-12)
    assert plot.stat().st_size > 10_000


def test_without_a_calibration_no_life_is_printed_and_a_price_is_refused(tmp_path, capsys):
    route, _ = s_bend(tmp_path / "route.csv")
    f = vehicle_file(tmp_path, None)
    rc, out, err = run(capsys, "run", "--trajectory", route, "--vehicle", f, "--duration", "2",
                       "--iterations", "10", "--no-floor")
    assert rc == 0 and "per km     W_tw [J/km] 1: " in out
    assert "tire life  n/a: the vehicle file has no [tire.wear] calibration" in out
    assert "tread loss" not in out and "tire cost" not in out
    rc, out, err = run(capsys, "run", "--trajectory", route, "--vehicle", f, "--duration", "2",
                       "--iterations", "10", "--json", "--no-floor")
    doc = json.loads(out)
    assert doc["wear"]["calibration"] is None
    assert all(set(e) == {"W_tw_per_km"} for e in doc["wear"]["per_km"]["wheels"].values())
    rc, out, err = run(capsys, "run", "--trajectory", route, "--vehicle", f, "--tire-price",
                       "450")
    assert rc == 2 and out == "" and err.strip() == (
        "msagv run: --tire-price: test-3axle has no [tire.wear] calibration, so no tire life "
        "and no cost per km (docs/WEAR.md: the abradability, or a known life on a known duty)")


def test_report_projects_the_recorded_run_by_the_recorded_calibration(tmp_path, capsys):
    """A plant's recording carries its vehicle (with the calibration): the report's life is
    the hand computation from the recorded per-wheel wear work and distance."""
    from msagv.bridge import messages as M
    from msagv.bridge.recording import Recorder
    from msagv.controller.reference import make_case
    from msagv.plant import Plant

    v = load_vehicle(vehicle_file(tmp_path, ["tread_width = 250.0", "usable_depth = 14.0",
                                             "abradability = 0.015", "price = 300.0"]))
    ref = make_case("curve", 15.0)[0]
    rec = tmp_path / "p.mcap"
    r = Recorder(rec, {"role": "plant", "vehicle": v.to_dict(), "period": 0.01,
                       "reference": dict(ref.to_message(), name=ref.name)})
    p = Plant(v, initial=ref.initial_state(v))
    sign = np.where(v.wheel_x >= 0, 1.0, -1.0)
    for k in range(300):  # a slalom with slipping wheels: every wheel wears
        st = p.state_message()
        st["t"] = round(k * 0.01, 10)
        r.message("tx", "msagv/agv0/state", M.encode_state(k, st))
        p.set_inputs(np.full(v.n_wheels, 4.4 / v.wheel_radius) * (1 + 0.05 * sign),
                     0.3 * math.cos(k * 0.05) * sign)
        p.do_step(p.t, 0.01)
    r.close({})
    rc, out, err = run(capsys, "report", rec, "--json")
    assert rc == 0, err
    wear = json.loads(out)["wear"]
    band = math.pi * 900.0 * 250.0
    for k, wheel in wear["wheels"].items():
        E = wheel["W_tw"] / (wear["distance_m"] / 1000.0)
        life = band * 14.0 / (0.015 * E)
        assert wear["per_km"]["wheels"][k]["life_km"] == pytest.approx(life, rel=1e-12)
        assert wear["per_km"]["wheels"][k]["cost_per_km"] == pytest.approx(300.0 / life)
    # --tire-price overrides the file's price
    rc, out, err = run(capsys, "report", rec, "--json", "--tire-price", "600")
    assert json.loads(out)["wear"]["calibration"]["price_per_tire"] == 600.0
    rc, out, err = run(capsys, "report", rec)
    assert rc == 0 and "tire life  [km] 1: " in out and "tire cost " in out
