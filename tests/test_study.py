"""The study (experiments/study.py, study_report.py, controller/floors.py, paths.py): wear
floors against a hand computation, the paths' feasibility, matched-accuracy fronts and the
bootstrap on hand-made data, and a reduced study end to end (the full quick design with a
user's vehicle and path is ``slow``)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from msagv.controller.floors import wear_floors
from msagv.controller.paths import feasible_bounds, lane_change, path_from_curvature, random_path, tight_turn
from msagv.experiments.study_report import bootstrap_ratio, lower_envelope, matched, wear_at_accuracy
from msagv.plant import default_vehicle, n_axle_vehicle, vehicle_from_dict
from msagv.plant.tire import magic_formula

VEH = default_vehicle()


def _one_narrow_axle(vehicle):
    """One axle through the centre of mass, its wheels 1 cm either side of the centre line:
    on a circle every wheel then runs at the body's speed along the body's x axis, so only
    lateral forces can hold the circle (a longitudinal force points along the path) and the
    least-dissipation allocation is equal."""
    d = n_axle_vehicle(1, base=vehicle).to_dict()
    d["half_track"] = 0.01
    return vehicle_from_dict(d)


@pytest.mark.parametrize("speed_kmh, radius", [(20.0, 40.0), (10.0, 15.0)])
def test_floor_on_a_circle_is_the_hand_computed_slip_angle_wear(speed_kmh, radius):
    """On a circle of radius R at speed v each of the 2n wheels must carry m v^2 / (2n R)
    of lateral force (one axle at the centre of mass, wheels along the body's x axis),
    at the slip angle alpha with f_lat(alpha) = F, dissipating F v tan(alpha) (eq. 14):
    W_alpha = 2n F v tan(alpha) T over T seconds; the wheels do not turn: W_t = 0."""
    v_ = _one_narrow_axle(VEH)
    ref = path_from_curvature(np.full(int(200.0 / 0.02), 1.0 / radius), speed_kmh, "circle")
    v = speed_kmh / 3.6
    F = v_.mass * v * v / radius / v_.n_wheels
    la = v_.tire_lateral
    D = la.mu * v_.normal_load
    lo, hi = 0.0, 0.5  # bisection for f(alpha) = F by hand (f increasing below its peak)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if magic_formula(mid, la.B, la.C, D, la.E) < F else (lo, mid)
    alpha = 0.5 * (lo + hi)
    T = 4.0
    f = wear_floors(ref, v_, 3.0, 3.0 + T, dt=0.05)
    want = v_.n_wheels * F * v * math.tan(alpha) * T
    assert f.W_alpha == pytest.approx(want, rel=2e-3)
    assert f.W_s < 1e-3 * want and f.W_t < 1e-3 * want
    # and the floor's steering angles are the velocity's plus that slip angle
    assert np.allclose(f.delta[:, 0] - f.delta[0, 0], 0.0, atol=1e-6)


def test_floor_is_zero_on_a_straight_line_and_rejects_an_empty_window():
    ref = path_from_curvature(np.zeros(int(100 / 0.02)), 20.0, "line")
    f = wear_floors(ref, VEH, 1.0, 5.0)
    assert f.W_tw < 1e-6
    with pytest.raises(ValueError, match="window"):
        wear_floors(ref, VEH, 5.0, 5.0)
    # the report divides by a floor only where there is one: a line's W / floor is n/a
    from msagv.experiments.study_report import _row

    tags = {"family": "NTWO", "lever": "none", "level": None, "aware": False,
            "scenario": "case2", "class": "case2", "plant": "nominal", "seed": 0,
            "path_key": "p"}
    res = {"spec": {"tags": tags, "label": "NTWO"}, "status": "ok", "key": "k",
           "metrics": {"W_tw": 2.0e5}}
    row = _row(res, {"p": {"floors": {"W_tw_floor": f.W_tw}}})
    assert row["W_over_floor"] is None and row["W_above_floor"] == pytest.approx(2.0e5)
    row = _row(res, {"p": {"floors": {"W_tw_floor": 1.0e5}}})
    assert row["W_over_floor"] == pytest.approx(2.0)


@pytest.mark.parametrize("make", [lane_change, tight_turn,
                                  lambda v, s: random_path(v, s, seed=3)])
@pytest.mark.parametrize("speed", [5.0, 20.0, 35.0])
def test_paths_stay_within_the_steering_and_friction_bounds(make, speed):
    ref = make(VEH, speed)
    b = feasible_bounds(VEH, speed)
    t = ref.t[ref.t <= ref.duration]
    R = ref.sample(t)
    vv = np.hypot(R[:, 3], R[:, 4])
    kappa = R[:, 5] / vv
    s = np.concatenate([[0.0], np.cumsum(vv[1:] * np.diff(t))])
    assert np.abs(kappa).max() <= b.kappa * 1.01
    rate = np.abs(np.diff(kappa) / np.maximum(np.diff(s), 1e-9))
    assert np.percentile(rate, 99.5) <= b.kappa_rate * 1.05
    # a path starts on a straight: the run starts on the reference without a jump
    assert abs(kappa[0]) < 0.01 * b.kappa


def test_random_paths_are_seeded():
    a, b, c = (random_path(VEH, 20.0, s) for s in (1, 1, 2))
    assert np.array_equal(a.y, b.y) and not np.allclose(a.y[:len(c.y)], c.y[:len(a.y)])


# ---- fronts and statistics on hand-made data ---------------------------------------------------
def test_front_and_wear_at_accuracy_by_hand():
    pts = [(1.0, 10.0), (2.0, 8.0), (1.5, 12.0), (4.0, 5.0), (3.0, 9.0)]
    front = lower_envelope(pts)
    assert front == [(1.0, 10.0), (2.0, 8.0), (4.0, 5.0)]
    assert wear_at_accuracy(front, 3.0) == pytest.approx(6.5)  # between (2, 8) and (4, 5)
    assert wear_at_accuracy(front, 9.0) == 5.0  # less accuracy than asked: the best point
    assert wear_at_accuracy(front, 0.5) is None  # nothing that accurate: no extrapolation


def _rows(scenario, path, blind, aware, ntwo_e=1.0, seed=0):
    rows = [{"family": "NTWO", "label": "NTWO", "aware": False, "status": "ok",
             "e_lat_rms_cm": ntwo_e, "W_tw": blind(ntwo_e), "scenario": scenario,
             "class": "c", "plant": "nominal", "path_key": path, "seed": seed,
             "W_tw_floor": 50.0}]
    for e in (0.5, 2.0):
        rows.append(dict(rows[0], family="NTWO-wheel", label=f"w{e}", e_lat_rms_cm=e,
                         W_tw=blind(e)))
        rows.append(dict(rows[0], family="TWO-energy", label=f"a{e}", aware=True,
                         e_lat_rms_cm=e, W_tw=aware(e)))
    return rows


def test_matched_ratio_and_bootstrap_by_hand():
    # blind wear 100 - 10 e, aware 90 - 10 e: within 1 cm (NTWO's own error), 90 vs 80
    rows = _rows("s1", "p1", lambda e: 100 - 10 * e, lambda e: 90 - 10 * e)
    rows += _rows("s2", "p2", lambda e: 200 - 10 * e, lambda e: 200 - 10 * e)
    m = {d["scenario"]: d for d in matched(rows)}
    assert m["s1"]["W_blind"] == pytest.approx(90.0) and m["s1"]["W_aware"] == pytest.approx(80.0)
    assert m["s1"]["ratio"] == pytest.approx(80 / 90)
    assert m["s1"]["W_blind_above_floor"] == pytest.approx(40.0)  # the floor is 50 J
    assert m["s2"]["ratio"] == pytest.approx(1.0)
    b = bootstrap_ratio(list(m.values()))
    assert b["gmean"] == pytest.approx(math.sqrt(80 / 90))
    lo, hi = b["ci95"]
    assert lo == pytest.approx(80 / 90) and hi == pytest.approx(1.0)  # the two extremes
    assert b["n"] == 2 and b["paths"] == 2 and b["below_1"] == 1
    # within 5 cm both fronts' least wear is their least accurate point's: 80 and 70
    assert m["s1"]["ratio_5cm"] == pytest.approx(70 / 80)
    # the tolerance is never tighter than NTWO's own error: NTWO at 1.5 cm -> e* = 1.5
    m4 = matched(_rows("s4", "p4", lambda e: 100 - 10 * e, lambda e: 90 - 10 * e, ntwo_e=1.5))
    assert m4[0]["e_star_cm"] == 1.5 and m4[0]["W_aware"] == pytest.approx(75.0)
    # an aware front less accurate than the tolerance everywhere is counted as unmatched
    rows3 = [r for r in _rows("s3", "p3", lambda e: 100.0, lambda e: 90.0)
             if not (r["aware"] and r["e_lat_rms_cm"] < 1.0)]
    assert matched(rows3)[0]["ratio"] is None
    assert bootstrap_ratio(matched(rows3))["unmatched"] == 1


def test_reduced_study_end_to_end(tmp_path, monkeypatch):
    """Two short scenarios (one path, two seeds), every family, in this process: the JSON
    has every family, the floors, the physical-unit errors and a ratio with its CI."""
    from msagv.experiments import study

    small = [study.StudyScenario("case1", "curve", 30.0, duration=1.5, seed=s, raw=s == 0)
             for s in (0, 1)]
    monkeypatch.setattr(study, "design", lambda quick, vehicle, trajectory: small)
    doc = study.run_study(tmp_path, quick=True, jobs=1, progress=False)
    fams = {r["family"] for r in doc["rows"]}
    assert fams == set(study.FAMILIES) | set(study.RAW_FAMILIES)
    assert all(r["status"] == "ok" for r in doc["rows"]), [r["error"] for r in doc["rows"]]
    for r in doc["rows"]:
        for k in ("e_lat_rms_cm", "e_lat_max_cm", "e_phi_deg", "W_tw", "W_tw_floor",
                  "W_above_floor"):
            assert isinstance(r[k], float) and math.isfinite(r[k]), k
    s = doc["summary"]["case1"]
    assert s["n"] + s["unmatched"] == 2 and "ci95" in s and "within_5cm" in s
    assert json.loads((tmp_path / "study.json").read_text())["version"]
    for f in ("study.md", "study.csv", "fronts.png", "ratios.png"):
        assert (tmp_path / f).is_file(), f
    again = study.run_study(tmp_path, quick=True, jobs=1, progress=False)
    assert again["runs"]["executed"] == 0  # resumed: every run reused


def test_design_names_every_scenario_once(tmp_path):
    """Runs are grouped by scenario name for the matched comparison: two paths under one
    name (the 4-axle curve and lane at 15 km/h once were) would be compared as one."""
    from msagv.experiments import study

    veh = tmp_path / "v.toml"
    veh.write_text("")
    for quick in (False, True):
        names = [sc.name for sc in study.design(quick, str(veh), None)]
        assert len(names) == len(set(names)), sorted(names)
    assert len(study.design(False)) >= 50


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_quick_study_with_a_users_vehicle_and_path(tmp_path):
    """The issue's check: `msagv experiment study --quick --json` with a vehicle and a path
    that are not in the repository."""
    from helpers import THREE_AXLE_TOML, run_msagv

    veh = tmp_path / "v.toml"
    veh.write_text(THREE_AXLE_TOML)
    t = np.arange(0.0, 20.0, 0.1)
    x = 3.0 * t
    y = 2.0 * np.sin(2 * np.pi * x / 50.0)
    phi = np.arctan(2.0 * 2 * np.pi / 50.0 * np.cos(2 * np.pi * x / 50.0))
    path = tmp_path / "p.csv"
    path.write_text("t,x,y,phi\n" + "\n".join(f"{a},{b},{c},{d}" for a, b, c, d in
                                              zip(t, x, y, phi)) + "\n")
    r = run_msagv("experiment", "study", "--quick", "--json", "--vehicle", veh,
                  "--trajectory", path, "--out", tmp_path / "out", timeout=3500)
    assert r.returncode == 0, r.stderr[-3000:]
    doc = json.loads(r.stdout)
    fams = {row["family"] for row in doc["rows"]}
    assert fams >= {"FF", "NTWO", "NTWO-wheel", "NTWO-wheel-Q", "TWO", "TWO-energy", "Kinematic",
                    "DH", "TCT"}
    assert "user" in doc["summary"] and "ci95" in doc["summary"]["all nominal"]
    user = [row for row in doc["rows"] if row["class"] == "user"]
    assert user and all(row["W_tw_floor"] is not None and row["e_lat_rms_cm"] is not None
                        for row in user)
