"""Scenario files (docs/SCENARIOS.md) and the examples in ``scenarios/``: every example
runs (briefly) without a warning; the docs' commands name files that exist; a bad file is
refused in one line naming the file and the key; options on the command line override
the file."""

from __future__ import annotations

import json
import re

import pytest

from helpers import ROOT

from msagv.controller.reference import from_csv
from msagv.experiments.scenario import Scenario, ScenarioError
from msagv.cli import main
from msagv.plant.vehicle import load_vehicle

SCEN = ROOT / "scenarios"
EXAMPLES = sorted(SCEN.glob("*.toml"))


def run(capsys, *args):
    rc = main([str(a) for a in args])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_the_examples_cover_3_4_and_6_axles_and_three_paths():
    axles = {load_vehicle(p).n_axles for p in (SCEN / "vehicles").glob("*.toml")}
    assert {3, 4, 6} <= axles
    assert {p.stem for p in (SCEN / "paths").glob("*.csv")} >= {"lane-change", "s-curve",
                                                                "tight-turn"}
    for p in (SCEN / "paths").glob("*.csv"):
        ref = from_csv(p)  # the contract: header, radians, no jumps
        assert ref.t[0] == 0.0


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_every_example_scenario_runs(path, capsys):
    sc = Scenario.from_file(path)
    rc, out, err = run(capsys, "run", path, "--duration", "0.3", "--json")
    assert rc == 0, err
    doc = json.loads(out)
    # no warning about the scenario (solve times depend on the machine and its load: the
    # warm-up's and the run's solve-time warnings name the control period)
    timing = "the control period"
    assert [w for w in doc["warnings"] if timing not in w] == []
    assert all(timing in line for line in err.splitlines())
    assert doc["metrics"]["steps"] == 30
    assert doc["scenario"]["vehicle"]["axles"] == sc.resolve_vehicle().n_axles
    # started on the path, or (case1-3axle-loaded) 1 m to its side: no further off
    offset_cm = 100 * abs(sc.initial.get("y", 0.0))
    assert doc["metrics"]["e_y_cm"] < offset_cm + 5 and doc["metrics"]["e_x_cm"] < 5


def test_the_docs_name_files_that_exist():
    """Every ``scenarios/...`` path in README.md and docs/*.md exists."""
    texts = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    named = set()
    for t in texts:
        named |= set(re.findall(r"scenarios/[\w./-]+\.(?:toml|csv)", t.read_text()))
    assert named, "the docs use no example"
    missing = sorted(n for n in named if not (ROOT / n).is_file())
    assert not missing, missing


def test_options_override_the_file(capsys):
    path = SCEN / "tight-turn-6axle.toml"
    rc, out, err = run(capsys, "run", path, "--method", "ntwo", "--duration", "0.2", "--seed", "4",
                       "--json")
    sc = json.loads(out)["scenario"]
    assert rc == 0 and (sc["method"], sc["seed"], sc["duration_s"]) == ("ntwo", 4, 0.2)
    assert sc["vehicle"]["name"] == "agv-6axle" and sc["reference"] == "tight-turn"
    # --case replaces the file's trajectory
    rc, out, err = run(capsys, "run", "--scenario", path, "--case", "line", "--duration", "0.1",
                       "--json")
    assert rc == 0 and json.loads(out)["scenario"]["reference"] == "case2-line"
    rc, out, err = run(capsys, "run", path, "--scenario", path)
    assert rc == 2 and "give the scenario file once" in err


@pytest.mark.parametrize("text, key_message", [
    ('case = "curve"\nspeeed = 10\n', "speeed: unknown key"),
    ('case = "curve"\nduration = "ten"\n', "duration: expected a number of seconds, got 'ten'"),
    ('case = "curve"\nduration = -2\n', "duration: must be > 0"),
    ('trajectory = "nowhere.csv"\n', "trajectory: no such file"),
    ('trajectory = "paths/lane-change.csv"\nspeed = 10\n', "speed applies to a case"),
    ('case = "circle"\n', "case: expected one of curve, line"),
    ('case = "curve"\nspeed = "fast"\n', "speed: speed: 'fast' is not a number"),
    ('case = "curve"\nmethod = "mppi"\n', "settings: "),
    ('case = "curve"\n[settings]\nN_q = 3\n', "settings: unknown setting 'N_q'"),
    ('case = "curve"\nmethod = "two"\n[settings]\nmethod = "ntwo"\n',
     "method: given at the top level and under [settings]"),
    ('case = "curve"\nafter_end = "hold"\n', "after_end: expected one of continue, stop"),
    ('case = "curve"\n[initial]\nvx = "fast"\n', "initial.vx: expected a number"),
    ('case = "curve"\nvehicle = "vehicles/none.toml"\n', "vehicle: no such file"),
    ('case = "curve"\n[vehicle]\nname = "x"\n', "vehicle."),
    ('case = "curve"\nfrom_rest = 1\n', "from_rest: expected true or false"),
    ('case = "curve\n', "not valid TOML"),
])
def test_a_bad_scenario_file_is_refused_naming_file_and_key(text, key_message, tmp_path, capsys):
    (tmp_path / "paths").mkdir()
    (tmp_path / "paths" / "lane-change.csv").write_text(
        (SCEN / "paths" / "lane-change.csv").read_text())
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(ScenarioError) as e:
        Scenario.from_file(bad)
    assert str(e.value).startswith(f"{bad}: ") and key_message in str(e.value)
    rc, out, err = run(capsys, "run", bad, "--duration", "0.1")
    assert rc == 2 and out == "" and err == f"msagv run: {e.value}\n"


def test_a_scenario_round_trips_through_its_dict():
    sc = Scenario.from_file(SCEN / "case1-3axle-loaded.toml")
    assert sc.mass_kg == 24000.0 and sc.speed == 25 and sc.initial == {"y": -1.0}
    assert sc.settings == {"method": "two"}
    again = Scenario.from_dict(sc.to_dict())
    assert again.to_dict() == sc.to_dict()


def test_a_run_reports_its_wear_floors_and_flags_a_broken_one(capsys):
    """``msagv run`` computes the wear floors of exact tracking over the window it ran
    (controller.floors, as the study does) and names every floor the run wears less than
    0.995 x of, in the JSON and as a warning (never silently)."""
    from msagv.controller.floors import broken_floor, broken_floor_warning, wear_floors
    from msagv.experiments.results import off_path_floor_note, split_below_floor

    path = SCEN / "lane-change-3axle.toml"
    rc, out, err = run(capsys, "run", path, "--duration", "1", "--json")
    assert rc == 0, err
    doc = json.loads(out)
    sc = Scenario.from_file(path)
    ref, _ = sc.reference()
    f = wear_floors(ref, sc.actual_vehicle(sc.resolve_vehicle()), 0.0, 1.0, dt=0.05).as_dict()
    assert doc["floors"] == pytest.approx(f, rel=1e-9)
    assert doc["floors"]["W_tw_floor"] < 1e-3  # the first second is straight: no floor
    broken, off = split_below_floor(broken_floor(doc["metrics"], doc["floors"]), doc["metrics"])
    assert doc["broken_floor"] == broken and doc["below_floor_off_path"] == off
    flagged = [w for w in doc["warnings"] if w.startswith(("broken floor", "below the floor"))]
    assert flagged == ([broken_floor_warning(broken)] if broken else []) + \
        ([off_path_floor_note(off)] if off else [])
    # a run that does not start on the reference (--initial, --from-rest) is held to the
    # floor of any start (the floor's own starts with the reference's velocities): lower
    # or equal, a relaxation
    rc, out, err = run(capsys, "run", "--case", "curve", "--speed", "15", "--duration", "1",
                       "--initial", "u=3.0", "--json")
    assert rc == 0, err
    doc = json.loads(out)
    sc = Scenario(case="curve", speed=15.0)
    ref, _ = sc.reference()
    veh = sc.actual_vehicle(sc.resolve_vehicle())
    free = wear_floors(ref, veh, 0.0, 1.0, dt=0.05, fixed_start=False).as_dict()
    fixed = wear_floors(ref, veh, 0.0, 1.0, dt=0.05).as_dict()
    assert doc["floors"] == pytest.approx(free, rel=1e-9)
    assert free["W_tw_floor"] <= fixed["W_tw_floor"] * (1 + 1e-6)
