"""Case 2 compared honestly (issue 29 item 2): the recovery metrics against hand-computed
values on synthetic error traces and against the controller's own metrics on a real run's
log, the matched recovery and the interpolated fronts by hand, the unmatched starts counted
in every Case 2 column, and the blind side's recovery levers' settings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from msagv.controller.models import MPCSettings
from msagv.experiments.families import FAMILIES, study_families
from msagv.experiments.recovery import (front_ratio, lateral_error, matched_recovery, recovery,
                                        recovery_of_log, wear_interpolated)
from msagv.experiments.study_analysis import (CASE2_LEVERS, compare, most_accurate_ratio,
                                              pooled, summarise, wear_within)


# ---- the recovery metrics on synthetic traces -----------------------------------------------
def test_recovery_of_a_heading_start_by_hand():
    """Off to the left up to 1 m, back across to -0.2 m, a last excursion of 6 cm at t = 6:
    in the 5 cm band for good from t = 7 (the sample after the last one outside); the wear
    spent until then is W(7) - W(0)."""
    t = np.arange(11.0)
    lat = [0.0, 1.0, 0.5, -0.2, 0.04, -0.03, 0.06, 0.02, 0.01, 0.0, 0.0]
    W = 5.0 + 10.0 * t ** 2
    r = recovery(t, lat, W)
    assert r["t_settle"] == 7.0 and r["W_settle"] == pytest.approx(490.0)
    assert r["peak"] == 1.0 and r["overshoot"] == pytest.approx(0.2)
    # a wider band: the 6 cm excursion is inside it, settled from t = 4
    w = recovery(t, lat, W, band=0.065)
    assert w["t_settle"] == 4.0 and w["W_settle"] == pytest.approx(160.0)
    # times count from the first sample
    assert recovery(t + 3.0, lat, W)["t_settle"] == 7.0


def test_recovery_of_an_offset_start_and_the_edge_cases():
    # starts 2 m to the right (the peak), swings 10 cm to the left
    r = recovery([0.0, 0.5, 1.0, 1.5, 2.0], [-2.0, -1.0, -0.3, 0.1, 0.0], [0.0, 1, 2, 3, 4])
    assert r["peak"] == 2.0 and r["overshoot"] == pytest.approx(0.1) and r["t_settle"] == 2.0
    # never crosses: no overshoot; in the band from the start: settled at 0 with no wear
    assert recovery([0, 1, 2], [0.3, 0.2, 0.0], [0, 1, 2])["overshoot"] == 0.0
    z = recovery([0, 1], [0.01, -0.01], [3.0, 4.0])
    assert z["t_settle"] == 0.0 and z["W_settle"] == 0.0
    # ends outside the band: not recovered
    n = recovery([0, 1, 2], [0.0, 0.3, 0.2], [0, 1, 2])
    assert n["t_settle"] is None and n["W_settle"] is None
    with pytest.raises(ValueError, match="one value per sample"):
        recovery([0, 1], [0.0], [0, 1])
    with pytest.raises(ValueError, match="band"):
        recovery([0, 1], [0, 0], [0, 1], band=0.0)


def test_recovery_of_a_log_file_by_hand(tmp_path):
    """A reference heading along +y (phi = pi/2): the lateral error is -(x - x_ref)."""
    t = np.arange(5) * 0.5
    x = np.array([0.0, -0.4, 0.1, 0.02, 0.0])
    cols = {"t": t, "x": x, "y": t, "phi": np.full(5, math.pi / 2), "x_ref": np.zeros(5),
            "y_ref": t, "phi_ref": np.full(5, math.pi / 2), "W_s": np.arange(5.0),
            "W_alpha": 2 * np.arange(5.0), "W_t": np.zeros(5), "cost": np.zeros(5)}
    p = tmp_path / "log.csv"
    np.savetxt(p, np.column_stack(list(cols.values())), delimiter=",",
               header=",".join(cols), comments="")
    r = recovery_of_log(p)[0.05]
    # lateral: 0, 0.4, -0.1, -0.02, 0 -> peak 0.4, overshoot 0.1, in the band from t = 1.5
    assert r["peak"] == pytest.approx(0.4) and r["overshoot"] == pytest.approx(0.1)
    assert r["t_settle"] == 1.5 and r["W_settle"] == pytest.approx(9.0)
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x\n0,0\n")
    with pytest.raises(ValueError, match="without the columns"):
        recovery_of_log(bad)


def test_recovery_of_a_real_run_agrees_with_the_controllers_metrics(tmp_path):
    """The feed-forward recovering from a 0.3 m offset on Case 2's line: the peak of the
    log's lateral error is the controller's own e_lat_max_cm."""
    from msagv.controller.loop import closed_loop
    from msagv.experiments.study import StudyScenario

    sc = StudyScenario("case2", "line", 10.0, offset_m=0.3)
    b = sc.scenario({"method": "ntwo", "model": "mf"}, solver="ff").build()
    log = closed_loop(b.plant, b.controller, b.reference, 3.0, period=0.01, progress=False,
                      outputs=False)
    log.to_csv(tmp_path / "run.csv")
    r = recovery_of_log(tmp_path / "run.csv")[0.05]
    m = log.metrics()
    assert 100 * r["peak"] == pytest.approx(m["e_lat_max_cm"], rel=1e-6)
    a = log.arrays()
    lat = lateral_error(a["pose"], a["ref"])
    assert r["t_settle"] is not None and 0 < r["t_settle"] < 3.0
    k = int(round(r["t_settle"] / 0.01))
    assert np.all(np.abs(lat[k:]) <= 0.05) and abs(lat[k - 1]) > 0.05


# ---- matched recovery and interpolated fronts by hand ---------------------------------------
def test_matched_recovery_by_hand():
    """(t_settle, peak, overshoot, W). Aware: (3, 50, 10, 100), (4, 50, 5, 80) and
    (5, 50, 20, 90), the last one beaten by the second on all four (off the front). Blind:
    (2, 50, 8, 200), (3.5, 40, 4, 120), (6, 50, 1, 50), and (1, 60, 0, 10), which strays
    further than every aware run. (3, 50, 10, 100) is matched by (2, 50, 8, 200): 0.5;
    (4, 50, 5, 80) by (3.5, 40, 4, 120): 2/3."""
    aware = [(3, 50, 10, 100), (4, 50, 5, 80), (5, 50, 20, 90)]
    blind = [(2, 50, 8, 200), (3.5, 40, 4, 120), (6, 50, 1, 50), (1, 60, 0, 10)]
    m = matched_recovery(aware, blind)
    assert m["n"] == 2 and m["matched"] == 2
    assert m["ratio"] == pytest.approx(math.sqrt(0.5 * 80 / 120))
    # an aware run that recovers better than every blind one: against the cheapest (10),
    # counted unmatched
    u = matched_recovery([(1, 30, 0, 70)], blind)
    assert u["matched"] == 0 and u["ratio"] == pytest.approx(70 / 10)
    # 1 unit of slack: (3.5, 40, 4, 120) now matches (4, 39, 3, 60) -> 0.5
    assert matched_recovery([(4, 39, 3, 60)], blind)["ratio"] == pytest.approx(60 / 10)
    assert matched_recovery([(4, 39, 3, 60)], blind, slack=1.0)["ratio"] == pytest.approx(0.5)
    assert matched_recovery([], blind)["ratio"] is None


def test_interpolated_front_and_its_ratio_by_hand():
    front = [(1.0, 100.0), (4.0, 50.0)]
    # half-way in log e between 1 and 4 is 2: half-way in log W, sqrt(100 * 50)
    assert wear_interpolated(front, 2.0) == pytest.approx(math.sqrt(5000.0))
    assert wear_interpolated(front, 0.5) is None and wear_interpolated(front, 9.0) == 50.0
    assert wear_interpolated(front, 1.0) == pytest.approx(100.0)
    aware = [(2.0, 60.0)]
    assert front_ratio(aware, front) == pytest.approx(60 / math.sqrt(5000.0))
    assert front_ratio(aware, front, wear_at=wear_within) == pytest.approx(0.6)  # step
    # 2 cm of slack: the blind side read at 4 cm: 60 / 50
    assert front_ratio(aware, front, slack=2.0) == pytest.approx(1.2)
    assert front_ratio([(0.5, 60.0)], [(1.0, 100.0)]) is None  # no shared error
    assert most_accurate_ratio(aware, front, slack=2.0) == pytest.approx(60 / 50)


# ---- Case 2's columns count every start -----------------------------------------------------
def _case2_rows(scenario, unit, blind, aware, levers=(), seed=0):
    """One Case 2 instance: NTWO and FF at (e, W) of ``blind``, the lever runs ``levers``,
    TWO at ``aware``; the recovery metrics follow the error (t_settle = peak = overshoot =
    e)."""
    base = {"status": "ok", "scenario": scenario, "class": "case2", "plant": "nominal",
            "path_key": unit, "unit": unit, "seed": seed, "W_tw_floor": 0.0}

    def row(fam, aware_, e, w, i):
        return dict(base, family=fam, label=f"{fam} {i}", aware=aware_, e_lat_rms_cm=e,
                    W_tw=w, t_settle_s=e, overshoot_cm=e, peak_cm=e, W_settle=w,
                    t_settle_slack_s=e,
                    W_settle_slack=w)

    rows = [row("NTWO" if i == 0 else "FF", False, e, w, i) for i, (e, w) in enumerate(blind)]
    rows += [row("FF-yaw", False, e, w, i) for i, (e, w) in enumerate(levers)]
    rows += [row("TWO", True, e, w, i) for i, (e, w) in enumerate(aware)]
    return rows


def test_case2_unmatched_starts_are_counted_in_every_column():
    """Start 1: aware (40, 60) against blind (45, 100), (50, 90): more accurate than every
    blind run, unmatched: every form enters at its fill (60 / 90, against the cheapest),
    flagged; with the lever runs (38, 80) and (42, 70) it is matched: 60 / 80 (the blind
    runs at least as accurate). Start 2 matched throughout. The Case 2 group's columns have
    both starts (n = 2), and say how many entered unmatched."""
    rows = _case2_rows("case2, 10 km/h, heading 60 deg, seed 0", "u1",
                       [(45.0, 100.0), (50.0, 90.0)], [(40.0, 60.0)],
                       levers=[(38.0, 80.0), (42.0, 70.0)])
    rows += _case2_rows("case2, 10 km/h, heading 30 deg, seed 0", "u2",
                        [(10.0, 100.0), (30.0, 50.0)], [(20.0, 60.0)])
    cs = {d["unit"]: d for d in compare(rows)}
    c = cs["u1"]
    assert c["c2:step:base:unmatched"] and c["c2:step:base"] == pytest.approx(60 / 90)
    assert not c["c2:step:levers:unmatched"] and c["c2:step:levers"] == pytest.approx(60 / 80)
    assert c["c2:recovery:base:unmatched"] and c["c2:recovery:base"] == pytest.approx(60 / 90)
    assert c["c2:recovery:levers"] == pytest.approx(60 / 80)
    assert not c["c2:recovery:levers:unmatched"]
    assert not c["c2:ff_wins"]  # FF (50, 90) is less accurate than TWO (40, 60)
    assert c["c2:ff_beats"] == [0, 1]
    # a matched start: the step form with the levers is the study's own ratio at equal error
    assert cs["u2"]["reason"] is None
    assert cs["u2"]["c2:step:levers"] == pytest.approx(cs["u2"]["ratio"])
    s = summarise(list(cs.values()))["case2"]
    for col in (s["equal_error"], s["at"]["1"], s["tolerance"]["0.5"]):
        assert col["n"] == 2 and col["missing"] == 0
    forms = s["case2"]["forms"]
    for form in ("recovery", "step", "interp"):
        assert forms[form]["base"]["n"] == 2 and forms[form]["base"]["unmatched"] == 1
        assert forms[form]["levers"]["unmatched"] == 0
    assert set(s["case2"]["starts"]) == {"case2, 10 km/h, heading 60 deg",
                                         "case2, 10 km/h, heading 30 deg"}
    g = s["case2"]["goal"]["step"]
    assert g["base"] == pytest.approx(pooled(list(cs.values()), "c2:step:base")["gmean"])


def test_the_plain_feed_forward_wins_where_it_is_better_and_cheaper():
    rows = _case2_rows("case2, 20 km/h, heading 15 deg, seed 0", "u",
                       [(50.0, 100.0), (10.0, 20.0)], [(12.0, 30.0), (15.0, 25.0)])
    c = compare(rows)[0]
    assert c["c2:ff_wins"] and c["c2:ff_wins_recovery"]
    assert c["c2:ff_beats"] == [2, 2] and c["c2:ff_beats_recovery"] == [2, 2]
    # a wear-aware run cheaper than the FF: it beats one of the three
    rows += _case2_rows("case2, 20 km/h, heading 15 deg, seed 0", "u", [],
                        [(11.0, 15.0)])
    c = compare(rows)[0]
    assert not c["c2:ff_wins"] and c["c2:ff_beats"] == [2, 3]


# ---- the levers ---------------------------------------------------------------------------
@pytest.mark.parametrize("name, level, field, want", [
    ("FF-yaw", 0.6, "r_fb_max", 0.6), ("FF-pos", 1.5, "K_pos", 1.5),
    ("FF-speed", 0.75, "v_fb_max", 0.75), ("NTWO-heading", 3.0, "Q", (200.0, 200.0, 3000.0))])
def test_case2_levers_set_their_field(name, level, field, want):
    f = FAMILIES[name]
    s = MPCSettings(**{k: tuple(v) if isinstance(v, list) else v
                       for k, v in f.settings_at(level).items()})
    assert getattr(s, field) == want and s.method == "ntwo" and not f.wear_aware
    assert (f.solver == "ff") == name.startswith("FF")
    assert len(f.levels) >= 4 and name in CASE2_LEVERS


def test_the_levers_are_case2s_and_the_feed_forward_shares_its_runs_across_seeds():
    from msagv.experiments import study
    from msagv.experiments.runs import code_digest, run_key

    in_case2 = {f.name for f in study_families(cls="case2")}
    assert CASE2_LEVERS <= in_case2 and "NTWO-wheel-cut" not in in_case2
    assert not CASE2_LEVERS & {f.name for f in study_families(cls="case1")}
    assert "NTWO-wheel-cut" in {f.name for f in study_families(cls="case1")}
    c2 = [sc for sc in study.design(False) if sc.cls == "case2"]
    starts: dict = {}
    for sc in c2:
        starts.setdefault(sc.unit_key, set()).add(sc.seed)
    assert len(starts) == 14 and all(len(v) >= 5 for v in starts.values())
    a, b = (study.StudyScenario("case2", "line", 10.0, heading_deg=60.0, seed=k,
                                duration=study.CASE2_DURATION) for k in (0, 3))
    dg = code_digest()
    keys = [{s.label: run_key(s, dg) for s in study.run_specs([sc])} for sc in (a, b)]
    assert keys[0]["FF-yaw r_fb_max=0.6"] == keys[1]["FF-yaw r_fb_max=0.6"]
    assert keys[0]["NTWO"] != keys[1]["NTWO"]  # the annealer's seed matters


def test_the_feed_forward_draws_no_random_numbers():
    """Why its runs are shared: the same run at two annealer seeds gives the same log."""
    from msagv.controller.loop import closed_loop
    from msagv.experiments.study import StudyScenario

    sc = StudyScenario("case2", "line", 10.0, heading_deg=30.0)
    logs = []
    for seed in (0, 3):
        b = sc.scenario({"method": "ntwo", "model": "mf", "seed": seed}, solver="ff").build()
        logs.append(closed_loop(b.plant, b.controller, b.reference, 0.5, period=0.01,
                                progress=False, outputs=False).arrays())
    assert np.array_equal(logs[0]["pose"], logs[1]["pose"])
    assert np.array_equal(logs[0]["omega_w"], logs[1]["omega_w"])
