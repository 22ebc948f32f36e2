"""The table of named controller configurations (experiments/families.py): its rows are the
paper's definitions (Section 4.2) and the references', levers set what they say, the case
tables, the study and the command line read it, and a bad entry is refused at once."""

from __future__ import annotations

import pytest

from msagv.controller.models import METHODS, MPCSettings
from msagv.controller.solvers import SOLVERS
from msagv.experiments.families import (FAMILIES, RIDGE_BASE, Family, Lever, case_rows,
                                        paper_methods, study_families, wear_aware)

D = MPCSettings()


def test_the_case_tables_rows_are_the_papers_five_then_the_references():
    assert [f.name for f in case_rows()] == ["Kinematic", "DH", "TCT", "NTWO", "TWO", "FF",
                                             "NTWO-wheel", "TWO-energy"]
    assert paper_methods() == ["Kinematic", "DH", "TCT", "NTWO", "TWO"]


def test_the_papers_five_as_the_paper_defines_them():
    """Section 4.2: one MPC; the baselines their own model without a wear term; TWO the
    paper's model with L; the kinematic method steers about one centre (the twist)."""
    at = {f.name: MPCSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in
                                 f.settings_at(f.case_level).items()}) for f in case_rows()}
    assert {n: (s.model, s.method) for n, s in at.items() if n in paper_methods()} == {
        "Kinematic": ("kinematic", "ntwo"), "DH": ("dugoff", "ntwo"), "TCT": ("tct", "ntwo"),
        "NTWO": ("mf", "ntwo"), "TWO": ("mf", "two")}
    assert at["Kinematic"].policy == "twist" and at["TWO"].L == D.L
    # the references: no optimisation; 10x the default ridge on the wheel-speed offsets
    # only; the wear energy at its default weights
    assert FAMILIES["FF"].solver == "ff" and FAMILIES["FF"].extra() == {"solver": "ff"}
    assert at["NTWO-wheel"].R == (D.R[0], D.R[1], 10 * D.R[2], D.R[3])
    assert at["TWO-energy"].method == "two-energy" and at["TWO-energy"].E == D.E


def test_levers_set_what_they_say_by_hand():
    two, energy, wheel = FAMILIES["TWO"], FAMILIES["TWO-energy"], FAMILIES["NTWO-wheel"]
    assert two.settings_at(4.0)["L"] == pytest.approx([4 * x for x in D.L])
    assert energy.settings_at(0.03)["E"] == [0.03, 0.03, 0.03]
    assert wheel.settings_at(1.0)["R"] == [D.R[0], D.R[1], 1.0, D.R[3]]
    # NTWO-wheel-Q keeps NTWO-wheel's ridge and scales the tracking weights
    q = FAMILIES["NTWO-wheel-Q"].settings_at(0.1)
    assert q["Q"] == pytest.approx([0.1 * x for x in D.Q]) and q["R"][2] == 0.05
    assert FAMILIES["NTWO-wheel-cut"].settings_at(0.7)["ref_smoothing"] == 0.7
    ridge = FAMILIES["NTWO-ridge"].settings_at(0.1)["R"]
    assert ridge == pytest.approx([D.R[0], D.R[1], 0.1 * RIDGE_BASE[0], 0.1 * RIDGE_BASE[1]])
    # x0.1 of the ridge base is the shipped default
    assert tuple(ridge) == pytest.approx(D.R)
    smooth = FAMILIES["NTWO-smooth"].settings_at(4.0)["R"]
    assert smooth == pytest.approx([4 * D.R[0], 4 * D.R[1], D.R[2], D.R[3]])
    assert two.label(0.25) == "TWO L x=0.25" and two.label() == "TWO"


def test_every_family_is_consistent_with_the_tables_it_names():
    for f in FAMILIES.values():
        assert f.solver in SOLVERS
        assert f.settings["method"] in METHODS  # named, never the product's default
        for lv in f.levels + (f.quick_levels or ()):
            MPCSettings(**{k: tuple(v) if isinstance(v, list) else v
                           for k, v in f.settings_at(lv).items()})
    assert wear_aware() == {"TWO", "TWO-energy", "TWO-energy-raw"}
    assert {f.name for f in study_families()} == {
        "Kinematic", "DH", "TCT", "NTWO", "TWO", "FF", "NTWO-wheel", "TWO-energy",
        "NTWO-wheel-Q", "NTWO-wheel-cut"}
    assert {f.name for f in study_families(raw=True)} - {f.name for f in study_families()} \
        == {"NTWO-raw", "TWO-energy-raw"}


@pytest.mark.parametrize("make, words", [
    (lambda: Lever("nonsense", "x"), "unknown MPCSettings field"),
    (lambda: Lever("R", "R", components=(7,)), "outside"),
    (lambda: Lever("R", "R", components=(0, 1), base=(1.0,)), "base needs 2"),
    (lambda: Lever("dt", "dt", components=(0,)), "scalar"),
    (lambda: Family("X", "x", {"model": "mf", "method": "ntwo"}, solver="mppi"), "solver"),
    (lambda: Family("X", "x", {"model": "mf"}), "method"),
    (lambda: Family("X", "x", {"method": "ntwo"}, levels=(1.0,)), "lever"),
    (lambda: Family("X", "x", {"method": "two"}, lever=Lever("L", "L x", scale=True),
                    levels=(-1.0,)), "L: need 3 finite weights"),
])
def test_a_bad_entry_is_refused_naming_it(make, words):
    with pytest.raises(ValueError, match=words):
        make()


def test_the_command_line_offers_the_tables_rows(capsys):
    from msagv.cli import experiment

    with pytest.raises(SystemExit):
        experiment.main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    for f in case_rows():
        assert f"{f.name}: {f.summary}"[:40] in out.replace("- ", "-")
