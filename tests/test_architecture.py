"""docs/ARCHITECTURE.md's worked example: adding a solver is one module and one line.

The test takes the two code blocks from the page as a user would (the module, the
registration), runs ``msagv run --solver random`` in-process and checks what a solver must
give: commands inside eq. (27)'s bounds, a cost never above the warm start's (the module
keeps the warm start among its candidates), the solver's name in the result.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from msagv.controller import make_case, solvers
from msagv.controller.models import MPCSettings
from msagv.controller.mpc import MPC
from msagv.plant import default_vehicle
from helpers import assert_commands_within_bounds

DOC = Path(__file__).resolve().parent.parent / "docs" / "ARCHITECTURE.md"


def _block(marker: str) -> str:
    """The fenced python block right after ``<!-- example: marker ... -->``."""
    text = DOC.read_text()
    m = re.search(r"<!-- example: " + re.escape(marker) + r"[^>]*-->\s*```python\n(.*?)```",
                  text, re.S)
    assert m, f"docs/ARCHITECTURE.md has no example '{marker}'"
    return m.group(1)


@pytest.fixture
def random_solver(tmp_path, monkeypatch):
    pkg = tmp_path / "mysolvers"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "random_search.py").write_text(_block("solver module"))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(solvers, "SOLVERS", dict(solvers.SOLVERS))  # undone after the test
    exec(compile(_block("solver registration"), "ARCHITECTURE.md", "exec"), {})
    yield "random"
    for m in [m for m in sys.modules if m.startswith("mysolvers")]:
        del sys.modules[m]


def test_the_documented_solver_is_one_module_and_one_line(random_solver, capsys):
    from msagv.cli import run as run_cmd

    assert random_solver in solvers.SOLVERS
    rc = run_cmd.main(["--case", "curve", "--speed", "15", "--duration", "1.0",
                       "--solver", "random", "--json"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    doc = json.loads(out.out)
    assert doc["scenario"]["solver"] == "random"
    assert doc["metrics"]["steps"] == 100
    assert doc["metrics"]["e_y_cm"] < 2.0  # it tracks (0.11 cm; the annealer 0.02 cm)


def test_the_documented_solver_keeps_the_bounds_and_the_warm_start(random_solver):
    v = default_vehicle()
    ref, init = make_case("curve", 15.0)
    mpc = MPC(v, MPCSettings(), ref, solver=random_solver)
    assert mpc.name == "random"
    assert_commands_within_bounds(mpc, v)
    st0 = init(v)
    st = {"t": 1.0, **{k: st0[k] for k in ("x", "y", "phi", "vx", "vy", "r")},
          "delta": [st0[f"delta_{w}"] for w in v.wheel_names]}
    mpc.reset()
    mpc.step(dict(st, t=0.99))
    x0, R, zprev, warm = mpc.horizon_problem(st)
    J_warm = mpc.horizon.cost(x0, R, mpc.horizon.clip(warm), zprev)
    cmd = mpc.step(st)
    assert cmd.cost <= J_warm * (1 + 1e-12)
    assert cmd.cost == pytest.approx(mpc.horizon.cost(x0, R, mpc.z, zprev), rel=1e-12)
    assert np.all(mpc.z >= mpc.horizon.lower) and np.all(mpc.z <= mpc.horizon.upper)


def test_a_taken_or_malformed_solver_name_is_refused(monkeypatch):
    monkeypatch.setattr(solvers, "SOLVERS", dict(solvers.SOLVERS))
    before = dict(solvers.SOLVERS)
    with pytest.raises(ValueError, match="already registered"):
        solvers.register("sa", "x.y:Z", "again")
    with pytest.raises(ValueError, match="module:Class"):
        solvers.register("mine", "no_colon", "x")
    with pytest.raises(ValueError, match="letters, digits"):
        solvers.register("a b", "x.y:Z", "x")
    assert solvers.SOLVERS == before
    with pytest.raises(ValueError, match="expected one of"):
        MPC(default_vehicle(), MPCSettings(), solver="nope")


def test_the_scenario_default_solver_is_the_tables():
    """experiments.scenario does not import the controller at import time (every command
    reads its options through it); its default solver must be the table's."""
    from msagv.experiments.scenario import Scenario

    assert Scenario().solver == solvers.DEFAULT_SOLVER


def _listed_files_are_the_codes(what: str, item: str, names: str) -> tuple[str, set]:
    """Assert that the files ARCHITECTURE.md lists between ``<!-- files: what -->`` and
    ``<!-- end files -->`` (each matched by ``item``, multi-line) are exactly the package's
    modules whose text matches ``names``; return the page's text and that list."""
    text = DOC.read_text()
    m = re.search(rf"<!-- files: {what} -->(.*?)<!-- end files -->", text, re.S)
    assert m, f"docs/ARCHITECTURE.md has no list of files for '{what}'"
    listed = set(re.findall(item, m.group(1), re.M))
    pkg = DOC.parent.parent / "msagv"
    pattern = re.compile(names)
    found = {str(f.relative_to(pkg)) for f in pkg.rglob("*.py") if pattern.search(f.read_text())}
    assert found == listed, (f"in the code, not on the page: {sorted(found - listed)}; "
                             f"on the page, not in the code: {sorted(listed - found)}")
    return text, listed


def test_a_cost_terms_files_are_the_ones_listed_here():
    """ARCHITECTURE.md's count of what a cost term takes is the code's: the modules that
    call the shared per-step or row terms of controller.cost_terms (and so must call a new
    one) are exactly the page's list."""
    text, listed = _listed_files_are_the_codes(
        "cost", r"^- `([a-z_/]+\.py)`",  # (the items, not the tests named in them)
        r"\b(pose_error|tracking_term|wear_term|wear_kw|smoothing_row|ridge_row)\(")
    heading = re.search(r"### A cost term: (\w+) files", text)
    assert heading and {"three": 3, "four": 4, "five": 5}.get(heading.group(1)) == len(listed)


def test_the_dugoff_models_files_are_the_ones_listed_here():
    """ARCHITECTURE.md's count of what a prediction model with parameters of its own takes
    (DH's Dugoff model) is the code's: the modules that name Dugoff's declaration, parameter
    slots, model id, tire law or vehicle-file section are exactly the page's list; the
    heading's count is that list without the items the page calls not needed by a model."""
    text, listed = _listed_files_are_the_codes(
        "dugoff", r"`([a-z_/]+\.py)`",
        r"DUGOFF|dugoff_forces|tire_dugoff|[\"']dugoff[\"']")
    m = re.search(r"<!-- files: dugoff -->(.*?)<!-- end files -->", text, re.S)
    items = re.split(r"^- ", m.group(1), flags=re.M)[1:]
    needed = [i for i in items if "not needed" not in i]
    heading = re.search(r"### A prediction model: two files, (\w+) with", text)
    words = {"three": 3, "four": 4, "five": 5}
    assert heading and words.get(heading.group(1)) == len(needed), heading
    assert len(items) == len(listed)


def test_a_models_own_parameter_needs_no_file_but_its_declaration(tmp_path, monkeypatch,
                                                                 capsys):
    """What ARCHITECTURE.md says a model's own parameters take: one declaration in
    plant.model_params, read by everything else unedited. A toy section (one parameter, a
    default, scaled by --adapt's c_lat) is declared here only, and the vehicle file reads
    and writes it, `msagv vehicle show` prints it, the calibration's file writer and the
    FMU's variables carry it, a model naming it packs it after the shared P and the
    adaptation scales it."""
    from msagv.cli import vehicle_main
    from msagv.controller.adaptation import TireAdaptation
    from msagv.controller.models import MagicFormulaModel
    from msagv.experiments.calibrate import vehicle_toml
    from msagv.fmu_build.variables import fmu_variables
    from msagv.plant import dynamics, layout as lay, model_params
    from msagv.plant.vehicle import load_vehicle, vehicle_from_dict

    toy = model_params.ModelParams("toy", (model_params.Param(
        "k_toy", "N/rad", "a toy stiffness", default=7.0, adapt="c_lat"),))
    monkeypatch.setitem(model_params.SECTIONS, "toy", toy)
    v = default_vehicle()  # the built-in file has no [tire.toy]: the default
    assert v.to_dict()["tire"]["toy"] == {"k_toy": 7.0}
    path = tmp_path / "v.toml"
    path.write_text(vehicle_toml(v).replace("k_toy = 7.0", "k_toy = 9.5"))
    assert "[tire.toy]" in path.read_text()
    v9 = load_vehicle(path)
    assert v9.model_values("toy")["k_toy"] == 9.5 and vehicle_from_dict(v9.to_dict()) == v9
    assert vehicle_main(["show", "--vehicle", str(path)]) == 0
    assert "tire.toy: {'k_toy': 9.5}" in capsys.readouterr().out
    var = {x.name: x for x in fmu_variables(v9)}["tire_toy_k_toy"]
    assert (var.unit, var.start) == ("N/rad", 9.5) and "a toy stiffness" in var.description

    class Toy(MagicFormulaModel):
        name = "toy"
        params = toy

    m = Toy(v9, MPCSettings())
    np.testing.assert_array_equal(m.P, np.r_[dynamics.pack_params(v9)[0], 9.5])
    ad = TireAdaptation(m, 0.01)
    P = m.P.copy()
    ad._apply(np.array([1.25, 1.0, 1.0]), P)
    assert P[lay.N_PARAMS] == 9.5 * 1.25
