"""msagv experiment mismatch (experiments.mismatch): the plants, the design's columns, the
interval that resamples paths as blocks, the paired difference, the command's refusals."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from msagv.experiments import mismatch as mm
from msagv.experiments.checks import ScenarioError
from msagv.experiments.study import run_specs
from msagv.plant.vehicle import default_vehicle, load_vehicle

ROOT = Path(__file__).resolve().parent.parent


def test_plants_scale_what_they_name_and_nothing_else():
    base = default_vehicle()
    for name, spec in mm.PLANTS.items():
        v = mm.plant_vehicle(base, name)
        for part, b, p in (("lateral", base.tire_lateral, v.tire_lateral),
                           ("longitudinal", base.tire_longitudinal, v.tire_longitudinal)):
            assert p.B == pytest.approx(b.B * spec.get("B", 1.0), rel=1e-12), (name, part)
            assert p.mu == pytest.approx(b.mu * spec.get("mu", 1.0), rel=1e-12), (name, part)
            assert (p.C, p.E) == (b.C, b.E)
        assert v.mass == base.mass and v.yaw_inertia == base.yaw_inertia
        plant = v.to_dict()["plant"]
        for k, val in base.to_dict()["plant"].items():
            assert plant[k] == spec.get("plant", {}).get(k, val), (name, k)


def test_inputs_are_files_every_column_shares(tmp_path):
    paths, files, man = mm.write_inputs(tmp_path, ("tires x0.8", "mu x1.2"), 2)
    again = mm.write_inputs(tmp_path, ("tires x0.8", "mu x1.2"), 2)
    assert [p.read_bytes() for p in paths] == [p.read_bytes() for p in again[0]]
    v = load_vehicle(files["tires x0.8"])
    assert v.tire_lateral.B == pytest.approx(0.8 * default_vehicle().tire_lateral.B)
    identified = {n: {"vehicle": str(files[n])} for n in files}  # stand-in files, read only
    scen = mm.design(paths, files, identified, seeds=(0,))
    assert len(scen) == 2 * 2 * 4
    assert {s.trajectory for s in scen} == {str(p) for p in paths}
    for s in scen:
        assert s.plant_vehicle == str(files[s.plant])
        assert s.vehicle == {"wrong": None, "adapted": None, "identified": str(files[s.plant]),
                             "true": str(files[s.plant])}[s.model]
    names = [s.name for s in scen]
    assert len(set(names)) == len(names)
    specs = run_specs(scen, quick=True)
    for sp in specs:
        st, fam_model = sp.settings, sp.settings.get("model", "mf")
        assert st["offset_free"] is True, sp.label  # the same action for every family
        # every family whose model has tires adapts them (the kinematic model has none)
        adapted = sp.tags["model"] == "adapted" and fam_model in ("mf", "dugoff", "tct")
        assert st.get("adapt", False) is adapted, (sp.label, sp.tags["model"])
        sc = sp.scenario()
        sc.mpc_settings()  # every column's settings are valid for every family
        # the plant is the plant's file whatever the controller believes
        assert sc.actual_vehicle(sc.resolve_vehicle()).tire_lateral.B == pytest.approx(
            load_vehicle(sp.extra["plant_vehicle"]).tire_lateral.B)


def test_a_design_under_measurement_noise(tmp_path):
    """--measurement-noise: every run's controller measures with it, its stream seeded by
    the annealer's seed (the four columns of a path, plant and seed read the same noise);
    the runs are not the exact design's (their keys differ); the identified column's logged
    run holds the measured states (their second differences show the noise)."""
    from msagv.experiments.runs import run_key
    from msagv.plant.sensors import MeasurementNoise

    paths, files, man = mm.write_inputs(tmp_path, ("tires x1.2",), 2)
    identified = {n: {"vehicle": str(files[n])} for n in files}
    noise = {"v": 0.01, "r": 0.002, "pos": 0.0, "phi": 0.0}
    exact = mm.design(paths, files, identified, seeds=(0, 1))
    noisy = mm.design(paths, files, identified, seeds=(0, 1), noise=noise)
    assert all(s.measurement_noise is None for s in exact)
    assert all(s.measurement_noise == dict(noise, seed=s.seed) for s in noisy)
    for a, b in zip(run_specs(exact, quick=True), run_specs(noisy, quick=True)):
        assert b.extra["measurement_noise"] == dict(noise, seed=b.tags["seed"])
        assert isinstance(b.scenario().measurement(), MeasurementNoise)
        assert run_key(a) != run_key(b)
    data = mm.logged_run(str(files["tires x1.2"]), str(man), noise=noise)

    def noise_of(x):  # the deviation of white noise on x, from its second differences
        return 1.4826 * np.median(np.abs(np.diff(x[:400], 2, axis=0))) / np.sqrt(6)

    # vx (G frame; the noise is isotropic, so its deviation holds) measured; the joint
    # states as the plant's encoders give them, exact: this plant (no lags) turns each
    # steering angle by T times its rate command and sets each wheel to its speed command
    assert noise_of(data.body[:, 3]) == pytest.approx(0.01, rel=0.3)
    T = mm.PERIOD
    assert np.abs(np.diff(data.delta, axis=0) - T * data.cmd_s[:-1]).max() < 1e-12
    assert np.array_equal(data.omega_w[1:], data.cmd_w[:-1])
    # the identification's cache key names the noise
    digest = "d"
    keys = {mm.identify_key(files["tires x1.2"], man, digest, None, n)
            for n in (None, noise, dict(noise, v=0.02))}
    assert len(keys) == 3


def _own_plant(tmp_path, vehicle: Path, name: str = "my_plant.toml", **tires) -> Path:
    """A plant of the user's own: ``vehicle``'s file with its lateral tire's values
    replaced (a file the experiment must take as it is)."""
    text = vehicle.read_text()
    head, lat = text.split("[tire.lateral]", 1)
    body, rest = (lat.split("\n[", 1) + [""])[:2]
    rows = [ln for ln in body.splitlines() if ln.split("=")[0].strip() not in tires]
    rows += [f"{k} = {v!r}" for k, v in tires.items()]
    out = tmp_path / name
    out.write_text(head + "[tire.lateral]" + "\n".join(rows) + "\n" + ("[" + rest if rest else ""))
    return out


def test_inputs_for_your_own_vehicle_plant_and_path(tmp_path):
    """--vehicle, a plant file and --trajectory: the path is the user's (copied, driven
    whole), the plant file is taken as it is, the factor plants and the manoeuvre are made
    from the user's vehicle, and the wrong and adapted columns believe the user's vehicle."""
    vehicle = _own_plant(tmp_path, ROOT / "scenarios" / "vehicles" / "agv-3axle.toml",
                         "my_agv.toml", mu=0.62)  # a vehicle of the user's own
    mine = load_vehicle(vehicle)
    plant = _own_plant(tmp_path, vehicle, B=mine.tire_lateral.B * 1.25, mu=0.55)
    traj = ROOT / "scenarios" / "paths" / sorted(p.name for p in (ROOT / "scenarios" / "paths")
                                                 .glob("*.csv"))[0]
    plants = (str(plant), "tires x1.2")
    assert mm.parse_plants(",".join(plants)) == plants
    assert mm.check_vehicles(plants, str(vehicle), str(traj)).name == mine.name
    out = tmp_path / "out"
    paths, files, man = mm.write_inputs(out, plants, 10, str(vehicle), str(traj))
    assert [p.read_bytes() for p in paths] == [traj.read_bytes()]
    assert files[str(plant)].read_bytes() == plant.read_bytes()
    assert load_vehicle(files[str(plant)]).tire_lateral.mu == 0.55
    scaled = load_vehicle(files["tires x1.2"])
    assert scaled.n_axles == 3
    assert scaled.tire_lateral.B == pytest.approx(1.2 * mine.tire_lateral.B, rel=1e-12)
    from msagv.experiments.calibrate import maneuver, maneuver_csv

    assert man.read_text() == maneuver_csv(maneuver(mine))  # the user vehicle's manoeuvre
    assert man.read_text() != maneuver_csv(maneuver(default_vehicle()))
    identified = {n: {"vehicle": str(files[n])} for n in files}
    scen = mm.design(paths, files, identified, seeds=(0,), vehicle=str(vehicle), duration=None)
    assert len(scen) == 2 * 4 and all(s.duration is None for s in scen)
    for sp in run_specs(scen, quick=True)[:40]:
        sc = sp.scenario()
        believed = sc.resolve_vehicle()
        if sp.tags["model"] in ("wrong", "adapted"):
            assert believed.tire_lateral.B == mine.tire_lateral.B and believed.n_axles == 3
        assert sc.actual_vehicle(believed).tire_lateral.B == pytest.approx(
            load_vehicle(sp.extra["plant_vehicle"]).tire_lateral.B)


def test_your_own_plant_must_have_the_vehicles_axles(tmp_path):
    plant = _own_plant(tmp_path, ROOT / "scenarios" / "vehicles" / "agv-4axle.toml", mu=0.6)
    with pytest.raises(ScenarioError, match="has 4 axles, the controller's vehicle .* 3"):
        mm.check_vehicles((str(plant),), str(ROOT / "scenarios" / "vehicles" / "agv-3axle.toml"))
    with pytest.raises(ScenarioError, match="named twice"):
        mm.parse_plants("tires x0.8,tires x0.8")
    with pytest.raises(ScenarioError, match="two plant files of one name"):
        mm.parse_plants("a/plant.toml,b/plant.toml")


def _items(values: dict[str, list[float]]) -> list[dict]:
    return [{"unit": f"{p}/{i}", "path": p, "ratio": v, "reason": None}
            for p, vs in values.items() for i, v in enumerate(vs)]


def test_blocked_interval_equals_the_bootstrap_of_the_path_means():
    """Blocks of equal size: the mean over resampled blocks is the mean of resampled block
    means, so the interval must equal scipy's bootstrap of the per-path means."""
    from scipy.stats import bootstrap

    from msagv.experiments.study_analysis import BOOTSTRAP, _bootstrap_kw

    rng = np.random.default_rng(3)
    values = {f"p{k}": list(np.exp(rng.normal(-0.05, 0.04, size=3))) for k in range(7)}
    res = mm.pooled_blocked(_items(values))
    logs = {p: np.log(v) for p, v in values.items()}
    means = np.array([m.mean() for m in logs.values()])
    assert res["gmean"] == pytest.approx(math.exp(means.mean()), rel=1e-12)
    ci = bootstrap((means,), np.mean, n_resamples=BOOTSTRAP, method="percentile",
                   **_bootstrap_kw()).confidence_interval
    assert res["ci95"] == pytest.approx([math.exp(ci.low), math.exp(ci.high)], rel=1e-9)
    assert res["n"] == 21 and res["paths"] == 7


def test_blocks_widen_the_interval_when_a_path_is_repeated():
    """Units of one path that agree are one observation, not many: the blocked interval of
    3 paths x 10 identical units is the 3 paths' interval, wider than 30 independent units
    would give."""
    values = {"a": [0.9] * 10, "b": [0.95] * 10, "c": [1.02] * 10}
    res = mm.pooled_blocked(_items(values))
    lo, hi = res["ci95"]
    assert lo == pytest.approx(0.9, rel=1e-9) and hi == pytest.approx(1.02, rel=1e-9)


def test_unmatched_enter_only_with_fill():
    items = _items({"a": [0.9, 0.95], "b": [1.0, 0.97]})
    items[0].update(ratio=None, reason="no shared error", most_accurate=1.3)
    plain = mm.pooled_blocked(items)
    filled = mm.pooled_blocked(items, fill="most_accurate")
    assert plain["n"] == 3 and plain["missing"] == 1
    assert filled["n"] == 4 and filled["missing"] == 0
    assert filled["gmean"] == pytest.approx((1.3 * 0.95 * 1.0 * 0.97) ** 0.25)


def test_paired_difference_hand_computed():
    comp = []
    for path, (r_id, r_true) in {"a": (0.9, 0.92), "b": (1.0, 0.95)}.items():
        for model, r in (("identified", r_id), ("true", r_true)):
            comp.append({"path": path, "plant": "x", "seed": 0, "model": model, "ratio": r})
    d = mm.paired_difference(comp, "identified")
    expect = math.sqrt(0.9 * 1.0) - math.sqrt(0.92 * 0.95)
    assert d["difference"] == pytest.approx(expect, rel=1e-12)
    assert d["pairs"] == 2 and d["paths"] == 2
    lo, hi = d["ci95"]
    assert lo <= d["difference"] <= hi


def test_parse_plants():
    assert mm.parse_plants("all") == tuple(mm.PLANTS)
    assert mm.parse_plants("tires x0.8, mu x1.2") == ("tires x0.8", "mu x1.2")
    with pytest.raises(ScenarioError, match="unknown plant 'x9'"):
        mm.parse_plants("tires x0.8,x9")


@pytest.mark.parametrize("args, msg", [
    (["--plants", "tires x9"], "unknown plant 'tires x9'"),
    (["--paths", "1"], "--paths: at least 2"),
    (["--seeds", "0"], "--seeds: at least 1"),
    (["--speeds", "20"], "--speeds does not apply to the mismatch"),
    (["--plants", "nowhere.toml"], "--plants: "),
    (["--vehicle", "nowhere.toml"], "--vehicle: "),
    (["--trajectory", "nowhere.csv"], "--trajectory: "),
    (["--trajectory", str(ROOT / "scenarios" / "paths" / "lane-change.csv"), "--paths", "3"],
     "--paths does not apply with --trajectory"),
    (["--measurement-noise", "fast,0"], "--measurement-noise: "),
    (["--measurement-noise=-0.01,0"], "--measurement-noise: "),
])
def test_cli_refuses_bad_options_in_one_line(tmp_path, args, msg):
    r = subprocess.run([sys.executable, "-m", "msagv", "experiment", "mismatch", "-o",
                        str(tmp_path / "out"), *args], capture_output=True, text=True,
                       cwd=ROOT, timeout=120)
    assert r.returncode == 2, r.stderr
    assert msg in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "runs").exists()


def test_study_options_refused_elsewhere(tmp_path):
    r = subprocess.run([sys.executable, "-m", "msagv", "experiment", "case1", "--paths", "3",
                        "-o", str(tmp_path / "o")], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 2 and "--paths applies to the mismatch experiment" in r.stderr
    r = subprocess.run([sys.executable, "-m", "msagv", "experiment", "case1",
                        "--measurement-noise", "0.01,0.002", "-o", str(tmp_path / "o")],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and ("--measurement-noise applies to the mismatch experiment "
                                  "and the study") in r.stderr
    r = subprocess.run([sys.executable, "-m", "msagv", "experiment", "study",
                        "--measurement-noise", "0.01,x", "-o", str(tmp_path / "o")],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "--measurement-noise: " in r.stderr and not (tmp_path / "o").exists()


def _result(sc, label, aware, e_cm, w, k):
    tags = {"family": label.split()[0], "lever": "none", "level": None, "aware": aware,
            "scenario": sc.name, "class": sc.cls, "plant": sc.plant, "seed": sc.seed,
            "path_key": sc.path_key, "unit": sc.unit_key, "model": sc.model}
    return {"key": f"k{k}", "status": "ok", "error": None, "wall_s": 1.0,
            "spec": {"label": label, "group": sc.name, "tags": tags},
            "metrics": {"W_tw": w, "e_lat_rms_cm": e_cm}}


def test_report_pools_the_columns_as_hand_computed(tmp_path):
    """Fronts built so that each scenario's equal-error ratio is known: the aware side is the
    blind side's wear times a factor at the same errors, per column and path; the report
    pools them as geometric means, says so in its sentence, and writes its files."""
    paths, files, _ = mm.write_inputs(tmp_path, ("tires x0.8",), 2)
    identified = {"tires x0.8": {"vehicle": str(files["tires x0.8"]), "estimates": {}}}
    scen = mm.design(paths, files, identified, seeds=(0,))
    factor = {("wrong", 0): 1.05, ("wrong", 1): 0.99, ("identified", 0): 0.96,
              ("identified", 1): 0.94, ("adapted", 0): 0.97, ("adapted", 1): 0.95,
              ("true", 0): 0.95, ("true", 1): 0.94}
    results, k = [], 0
    for sc in scen:
        f = factor[(sc.model, paths.index(Path(sc.trajectory)))]
        for e, w in ((0.2, 3000.0), (0.5, 2500.0), (1.0, 2000.0)):
            results.append(_result(sc, f"NTWO{e}", False, e, w, k))
            results.append(_result(sc, f"TWO-energy{e}", True, e, w * f, k + 1))
            k += 2
    design_doc = {"plants": ["tires x0.8"], "paths": [p.name for p in paths], "seeds": [0],
                  "levels": "quick", "duration_s": mm.DURATION, "speeds_kmh": [15, 20]}
    doc = mm.report(results, scen, identified, design_doc, tmp_path,
                    {"runs": len(results), "failed": 0})
    for m in mm.MODELS:
        s = doc["summary"]["by_model"][m]["equal_error"]
        assert s["gmean"] == pytest.approx(math.sqrt(factor[(m, 0)] * factor[(m, 1)]), rel=1e-9)
        assert s["paths"] == 2 and doc["summary"]["by_model"][m]["unmatched"] == 0
    d = doc["summary"]["against_true"]["identified"]["equal_error"]
    assert d["difference"] == pytest.approx(math.sqrt(0.96 * 0.94) - math.sqrt(0.95 * 0.94))
    assert f"{math.sqrt(1.05 * 0.99):.3f}" in doc["sentence"]
    text = (tmp_path / "mismatch.md").read_text()
    assert doc["sentence"] in text and "| tires x0.8 |" in text
    assert (tmp_path / "mismatch.png").stat().st_size > 1000


@pytest.mark.slow
def test_quick_design_end_to_end(tmp_path):
    """The command on one plant (tires x0.8), two paths, the quick levels: the plant's
    tires identified from its logged run (slopes within 5 %, peaks within 10 %), every run
    finished, a ratio per column, the files written."""
    r = subprocess.run([sys.executable, "-m", "msagv", "experiment", "mismatch", "--quick",
                        "--plants", "tires x0.8", "-o", str(tmp_path), "--json", "--jobs", "2"],
                       capture_output=True, text=True, cwd=ROOT, timeout=3600)
    assert r.returncode == 0, r.stderr
    import json

    doc = json.loads(r.stdout)
    est = doc["identified"]["tires x0.8"]["estimates"]
    for name, tol in (("lateral.K", 0.05), ("longitudinal.K", 0.05), ("lateral.mu", 0.10),
                      ("longitudinal.mu", 0.10)):
        assert est[name]["identified"], name
        assert est[name]["value"] == pytest.approx(est[name]["truth"], rel=tol), name
    assert all(row["status"] == "ok" for row in doc["rows"])
    for m in mm.MODELS:
        assert doc["summary"]["by_model"][m]["instances"] == 2
    assert (tmp_path / "mismatch.md").is_file() and (tmp_path / "mismatch.png").is_file()
