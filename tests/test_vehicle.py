"""The vehicle description (plant/vehicle.py): the built-in vehicle, round trips, and
rejection of malformed TOML files with a message that names the field."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from helpers import BUILTIN_TOML, add_toml, drop_toml_table, edit_toml, run_msagv
from msagv.plant import (Plant, Vehicle, VehicleError, default_vehicle, load_vehicle, n_axle_vehicle,
                   vehicle_from_dict)

BUILTIN = BUILTIN_TOML


# ---- the built-in vehicle ---------------------------------------------------------------
def test_builtin_vehicle_has_the_papers_numbers():
    v = default_vehicle()
    # paper Section 4.1 and Case 1: 12 t, I_vz = 80000 kg m^2, r_w = 0.5 m,
    # x_wi in {3, -3}, y_wj in {1, -1}
    assert v.name == "paper-2axle"
    assert v.mass == 12000.0
    assert v.yaw_inertia == 80000.0
    assert v.wheel_radius == 0.5
    assert v.axle_x == (3.0, -3.0)
    assert v.half_track == 1.0
    assert v.n_axles == 2 and v.n_wheels == 4
    assert v.wheel_names == ["11", "12", "21", "22"]
    np.testing.assert_array_equal(v.wheel_x, [3.0, 3.0, -3.0, -3.0])
    np.testing.assert_array_equal(v.wheel_y, [1.0, -1.0, 1.0, -1.0])
    # Assumption 2: F_N = m g / (2n) = 12000 * 9.81 / 4 = 29430 N
    assert v.normal_load == pytest.approx(29430.0, rel=1e-12)
    # no plant-only realism by default
    assert (v.plant.cg_height, v.plant.wheel_lag, v.plant.steer_lag) == (0.0, 0.0, 0.0)


def test_builtin_tire_numbers_are_consistent_with_their_documented_derivation():
    v = default_vehicle()
    FN = 29430.0
    la, lo, dug = v.tire_lateral, v.tire_longitudinal, v.model_values("dugoff")
    # cornering stiffness BCD = 7.69 * 1.3 * 0.8 F_N = 7.9976 F_N per rad ~ 8 F_N
    assert la.B * la.C * la.mu == pytest.approx(8.0, rel=1e-3)
    # = 8 * pi / 180 = 0.1396 F_N per degree, inside the 0.1-0.2 /deg truck-tire range
    assert 0.1 < la.B * la.C * la.mu * math.pi / 180 < 0.2
    # longitudinal slip stiffness 9.09 * 1.65 * 0.8 = 11.9988 F_N ~ 12 F_N
    assert lo.B * lo.C * lo.mu == pytest.approx(12.0, rel=1e-3)
    assert (la.C, lo.C, la.mu, lo.mu) == (1.3, 1.65, 0.8, 0.8)
    # Dugoff stiffnesses at the nominal load: 8 * 29430 = 235440, 12 * 29430 = 353160
    assert dug["C_alpha"] == pytest.approx(8 * FN) and dug["C_s"] == pytest.approx(12 * FN)
    assert v.steer_loss_kt == 0.03
    lim = v.limits
    assert lim.delta_min == -1.5708 and lim.delta_max == 1.5708
    assert lim.omega_s_min == -0.8 and lim.omega_s_max == 0.8 and lim.omega_w_max == 25.0


def test_round_trip_to_dict_from_dict():
    v = default_vehicle()
    assert vehicle_from_dict(v.to_dict()) == v
    d = v.to_dict()
    d["plant"] = {"cg_height": 1.2, "wheel_lag": 0.05, "steer_lag": 0.02}
    d["axle_x"] = [4.0, 0.5, -3.0]
    w = vehicle_from_dict(d)
    assert w.plant.cg_height == 1.2 and w.n_axles == 3
    assert vehicle_from_dict(w.to_dict()) == w
    # and through JSON (plain data only)
    assert vehicle_from_dict(json.loads(json.dumps(w.to_dict()))) == w


def test_replace():
    v = default_vehicle()
    w = v.replace(mass=16000.0)
    assert w.mass == 16000.0 and v.mass == 12000.0
    assert w.normal_load == pytest.approx(16000.0 * 9.81 / 4)
    with pytest.raises(VehicleError, match="colour"):
        v.replace(colour="red")
    with pytest.raises(VehicleError, match="mass"):
        v.replace(mass=-1.0)


# ---- bad files ---------------------------------------------------------------------------
BAD_FILES = {
    # missing keys
    "missing mass": (edit_toml(BUILTIN, "", "mass", None), ["mass", "missing"]),
    "missing axle_x": (edit_toml(BUILTIN, "", "axle_x", None), ["axle_x", "missing"]),
    "missing lateral B": (edit_toml(BUILTIN, "tire.lateral", "B", None),
                          ["tire.lateral.B", "missing"]),
    "missing delta_max": (edit_toml(BUILTIN, "limits", "delta_max", None),
                          ["limits.delta_max", "missing"]),
    "missing dugoff table": (drop_toml_table(BUILTIN, "tire.dugoff"), ["tire.dugoff", "missing"]),
    "missing limits table": (drop_toml_table(BUILTIN, "limits"), ["limits", "missing"]),
    # unknown keys, top level and inside tables
    "unknown top": (add_toml(BUILTIN, "", 'colour = "red"'), ["colour", "unknown"]),
    "unknown in lateral": (add_toml(BUILTIN, "tire.lateral", "F = 1.0"),
                           ["tire.lateral.F", "unknown"]),
    "unknown in limits": (add_toml(BUILTIN, "limits", "omega_w_min = 0.0"),
                          ["limits.omega_w_min", "unknown"]),
    "unknown tire part": (BUILTIN + "\n[tire.vertical]\nk = 1.0\n", ["tire.vertical", "unknown"]),
    "unknown in plant": (BUILTIN + "\n[plant]\ncg_height = 1.0\nroll_stiffness = 2.0\n",
                         ["plant.roll_stiffness", "unknown"]),
    # non-positive
    "zero mass": (edit_toml(BUILTIN, "", "mass", "0.0"), ["mass", "> 0"]),
    "negative mass": (edit_toml(BUILTIN, "", "mass", "-12000.0"), ["mass", "> 0"]),
    "negative inertia": (edit_toml(BUILTIN, "", "yaw_inertia", "-1.0"), ["yaw_inertia"]),
    "zero radius": (edit_toml(BUILTIN, "", "wheel_radius", "0"), ["wheel_radius"]),
    "zero half track": (edit_toml(BUILTIN, "", "half_track", "0.0"), ["half_track"]),
    "negative kt": (edit_toml(BUILTIN, "", "steer_loss_kt", "-0.01"), ["steer_loss_kt"]),
    "zero mu": (edit_toml(BUILTIN, "tire.longitudinal", "mu", "0.0"), ["tire.longitudinal.mu"]),
    "negative C_alpha": (edit_toml(BUILTIN, "tire.dugoff", "C_alpha", "-5.0"),
                         ["tire.dugoff.C_alpha"]),
    "negative lag": (BUILTIN + "\n[plant]\nwheel_lag = -0.1\n", ["plant.wheel_lag"]),
    "zero omega_w_max": (edit_toml(BUILTIN, "limits", "omega_w_max", "0.0"),
                         ["limits.omega_w_max"]),
    # NaN / inf (TOML nan, inf)
    "nan mass": (edit_toml(BUILTIN, "", "mass", "nan"), ["mass", "finite"]),
    "inf inertia": (edit_toml(BUILTIN, "", "yaw_inertia", "inf"), ["yaw_inertia", "finite"]),
    "nan lateral E": (edit_toml(BUILTIN, "tire.lateral", "E", "nan"), ["tire.lateral.E", "finite"]),
    "nan delta_min": (edit_toml(BUILTIN, "limits", "delta_min", "nan"), ["limits.delta_min"]),
    "nan in axle_x": (edit_toml(BUILTIN, "", "axle_x", "[3.0, nan]"), ["axle_x[1]"]),
    # min > max
    "delta min > max": (edit_toml(edit_toml(BUILTIN, "limits", "delta_min", "0.5"), "limits",
                              "delta_max", "0.2"), ["limits.delta_min", "limits.delta_max"]),
    "omega_s min > max": (edit_toml(edit_toml(BUILTIN, "limits", "omega_s_min", "0.9"), "limits",
                                "omega_s_max", "-0.9"),
                          ["limits.omega_s_min", "limits.omega_s_max"]),
    # axle_x
    "empty axle_x": (edit_toml(BUILTIN, "", "axle_x", "[]"), ["axle_x"]),
    "increasing axle_x": (edit_toml(BUILTIN, "", "axle_x", "[-3.0, 3.0]"), ["axle_x[1]"]),
    "repeated axle": (edit_toml(BUILTIN, "", "axle_x", "[3.0, 0.0, 0.0]"), ["axle_x[2]"]),
    # wrong types
    "string mass": (edit_toml(BUILTIN, "", "mass", '"heavy"'), ["mass", "number"]),
    "bool mass": (edit_toml(BUILTIN, "", "mass", "true"), ["mass", "number"]),
    "string axle_x": (edit_toml(BUILTIN, "", "axle_x", '"front"'), ["axle_x"]),
    "string in axle_x": (edit_toml(BUILTIN, "", "axle_x", '[3.0, "rear"]'), ["axle_x[1]"]),
    "numeric name": (edit_toml(BUILTIN, "", "name", "7"), ["name"]),
    "limits not a table": (drop_toml_table(BUILTIN, "limits").replace(
        "name =", "limits = 3\nname =", 1), ["limits", "table"]),
    "array B": (edit_toml(BUILTIN, "tire.lateral", "B", "[7.69]"), ["tire.lateral.B", "number"]),
    # not TOML at all
    "not toml": ("mass = = 3\n", ["not valid TOML"]),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_file_is_rejected_naming_the_field(tmp_path, case):
    text, words = BAD_FILES[case]
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(VehicleError) as ei:
        load_vehicle(p)
    msg = str(ei.value)
    assert str(p) in msg
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"


def test_the_edited_base_file_itself_loads(tmp_path):
    # guards the helpers above: an edit that keeps the file valid still loads
    p = tmp_path / "ok.toml"
    p.write_text(edit_toml(add_toml(BUILTIN, "", "# comment"), "", "mass", "16000.0"))
    assert load_vehicle(p).mass == 16000.0
    p.write_text(BUILTIN + "\n[plant]\ncg_height = 1.1\n")
    v = load_vehicle(p)
    assert v.plant.cg_height == 1.1 and v.plant.wheel_lag == 0.0


def test_missing_file():
    with pytest.raises(FileNotFoundError):
        load_vehicle("/nonexistent/vehicle.toml")


def test_bad_dicts():
    d = default_vehicle().to_dict()
    with pytest.raises(VehicleError, match="must be a table"):
        vehicle_from_dict([1, 2])
    bad = dict(d, tire=dict(d["tire"], lateral=5))
    with pytest.raises(VehicleError, match=r"tire\.lateral"):
        vehicle_from_dict(bad)
    bad = dict(d, tire=7)
    with pytest.raises(VehicleError, match="tire"):
        vehicle_from_dict(bad)


# ---- n-axle vehicles --------------------------------------------------------------------
@pytest.mark.parametrize("n", [1, 3, 6])
def test_n_axle_vehicle(n):
    v = n_axle_vehicle(n)
    assert isinstance(v, Vehicle)
    assert v.n_axles == n and v.n_wheels == 2 * n
    ax = np.array(v.axle_x)
    assert np.all(np.diff(ax) < 0)  # front first, strictly decreasing
    assert ax.mean() == pytest.approx(0.0, abs=1e-12)  # centred on the CG
    if n > 1:
        np.testing.assert_allclose(np.diff(ax), -2.0)  # default spacing 2 m
    # the same load per wheel as the paper vehicle: 6000 kg per axle -> 29430 N per wheel
    assert v.mass == pytest.approx(6000.0 * n)
    assert v.normal_load == pytest.approx(29430.0)
    assert v.wheel_names == [f"{i}{j}" for i in range(1, n + 1) for j in (1, 2)]
    assert v.yaw_inertia > 0
    # the tires and limits are the base vehicle's
    assert v.tire_lateral == default_vehicle().tire_lateral
    # and a plant runs on it (straight rolling at 5 m/s stays at 5 m/s)
    p = Plant(v, initial={"vx": 5.0})
    p.set_inputs(np.full(2 * n, 10.0), np.zeros(2 * n))
    for _ in range(10):
        p.do_step(p.t, 0.01)
    assert p.get("x") == pytest.approx(0.5, rel=1e-9)


def test_n_axle_vehicle_rejects_zero_axles():
    with pytest.raises(VehicleError):
        n_axle_vehicle(0)


# ---- msagv vehicle show -----------------------------------------------------------------
def _run(*args, timeout=60):
    return run_msagv(*args, timeout=timeout)


def test_cli_vehicle_show_json_builtin():
    r = _run("vehicle", "show", "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    derived = d.pop("derived")
    assert vehicle_from_dict(d) == default_vehicle()
    assert derived["n_axles"] == 2 and derived["n_wheels"] == 4
    assert derived["normal_load_N"] == pytest.approx(29430.0)
    assert derived["wheel_x"] == [3.0, 3.0, -3.0, -3.0]
    assert derived["wheel_y"] == [1.0, -1.0, 1.0, -1.0]


def test_cli_vehicle_show_json_file(tmp_path):
    p = tmp_path / "three.toml"
    text = edit_toml(edit_toml(BUILTIN, "", "axle_x", "[4.0, 0.5, -3.0]"), "", "name", '"three"')
    p.write_text(text + "\n[plant]\ncg_height = 1.2\n")
    r = _run("vehicle", "show", "--vehicle", str(p), "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["name"] == "three" and d["axle_x"] == [4.0, 0.5, -3.0]
    assert d["plant"] == {"cg_height": 1.2, "wheel_lag": 0.0, "steer_lag": 0.0,
                          "combined_slip": 0.0}
    # F_N = 12000 * 9.81 / 6 = 19620 N
    assert d["derived"]["normal_load_N"] == pytest.approx(19620.0)
    # and the text form names the vehicle
    r = _run("vehicle", "show", "--vehicle", str(p))
    assert r.returncode == 0 and r.stdout.startswith("three: 3 axles")


def test_cli_vehicle_show_bad_file(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text(edit_toml(BUILTIN, "", "mass", "nan"))
    r = _run("vehicle", "show", "--vehicle", str(p), "--json")
    assert r.returncode == 2
    assert "mass" in r.stderr and r.stdout == ""


def test_a_models_section_is_read_as_its_declaration_says():
    """plant.model_params: a declared section's keys, checks and defaults (a key with a
    default may be left out; a section whose every key has one may be left out)."""
    from msagv.plant import vehicle as vm
    from msagv.plant.model_params import ModelParams, Param

    spec = ModelParams("toy", (Param("k", "N", "a stiffness"),
                               Param("e", None, "an exponent", positive=False, default=-1.0)))
    assert vm._model_params({"toy": {"k": 2}}, spec).as_dict() == {"k": 2.0, "e": -1.0}
    assert vm._model_params({"toy": {"k": 2, "e": 3}}, spec)["e"] == 3.0
    for tire, words in (({}, ["tire.toy", "missing"]), ({"toy": {"e": 1.0}}, ["tire.toy.k"]),
                        ({"toy": {"k": 0.0}}, ["tire.toy.k", "> 0"]),
                        ({"toy": {"k": 1.0, "f": 1.0}}, ["tire.toy.f", "unknown"])):
        with pytest.raises(VehicleError) as e:
            vm._model_params(tire, spec)
        assert all(w in str(e.value) for w in words), (tire, e.value)
    optional = ModelParams("opt", (Param("k", "N", "a stiffness", default=5.0),))
    assert vm._model_params({}, optional).values == (5.0,)
    with pytest.raises(ValueError, match="adapt"):
        Param("k", None, "x", adapt="c_vertical")


def test_vehicle_md_lists_each_models_section_as_declared():
    """docs/VEHICLE.md has a table per declared model section (plant.model_params) with
    each key and its unit, in the declared order."""
    import re
    from pathlib import Path

    from msagv.plant.model_params import SECTIONS

    text = (Path(__file__).resolve().parent.parent / "docs" / "VEHICLE.md").read_text()
    for spec in SECTIONS.values():
        m = re.search(rf"### `\[tire\.{spec.section}\]`[^\n]*\n(.*?)\n\n###", text, re.S)
        assert m, spec.section
        rows = re.findall(r"^\| `(\w+)` \| ([^|]+) \|", m.group(1), re.M)
        assert rows == [(p.name, p.unit or "-") for p in spec.params], rows
