"""fmu_build.host.FmuPlant: an FMU behind plant.Plant's interface, and the name mapping.

Our FMU (built once for the module) is hosted in this process: the build bundles the
plant under a code-hashed package name, so it does not collide with the project's
``plant`` that pytest has imported. A prefixed build and a small foreign FMU (pythonfmu,
other names, only the required signals) exercise the mapping file.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from msagv.fmu_build.build import build_fmu
from msagv.fmu_build.drive import varied_inputs
from msagv.fmu_build.host import FmuHostError, FmuPlant, NameMap, load_mapping
from msagv.fmu_build.variables import fmu_variables
from msagv.plant import Plant, PlantError, VehicleError, default_vehicle

PREFIX = "agv0."


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("host")


@pytest.fixture(scope="module")
def fmu2(paper_fmu) -> Path:
    return paper_fmu


@pytest.fixture(scope="module")
def fmu_prefixed(work) -> Path:
    return build_fmu(work / "prefixed.fmu", prefix=PREFIX)


@pytest.fixture
def fp(fmu2):
    with FmuPlant(fmu2) as p:
        yield p


def _drive(p, U, h=0.01):
    """set_inputs / do_step over U; the outputs after every step."""
    nw = p.vehicle.n_wheels
    rows = []
    for k in range(len(U)):
        p.set_inputs(U[k, :nw], U[k, nw:])
        p.do_step(p.t, h)
        rows.append(p.outputs())
    return rows


def _assert_same(a: dict, b: dict, tol=1e-9):
    assert set(a) == set(b)
    worst = max(abs(a[k] - b[k]) for k in a)
    assert worst <= tol, worst


# ---- our FMU -------------------------------------------------------------------------------
def test_vehicle_comes_from_the_fmu(fp):
    assert fp.vehicle == default_vehicle()
    assert fp.t == 0.0
    assert fp.signal_names == Plant().signal_names


def test_same_interface_and_numbers_as_the_plant(fp):
    p = Plant(fp.vehicle)
    U = varied_inputs(4, 100, seed=3)
    got, want = _drive(fp, U), _drive(p, U)
    for a, b in zip(got, want):
        _assert_same(a, b)
    assert fp.t == p.t == pytest.approx(1.0)
    m_fmu, m_nat = fp.state_message(), p.state_message()
    assert list(m_fmu) == list(m_nat)
    for k, v in m_nat.items():
        if isinstance(v, list):
            assert np.allclose(m_fmu[k], v, rtol=0, atol=1e-9), k
        else:
            assert abs(m_fmu[k] - v) <= 1e-9, k
    assert all(type(x) is float for x in m_fmu["delta"] + m_fmu["omega_w"])


def test_both_plants_declare_the_plant_interface(fp):
    from msagv.plant.interface import PlantInterface

    assert isinstance(Plant(), PlantInterface) and isinstance(fp, PlantInterface)


def test_get_and_set_state_rewind_the_fmu_as_the_plant(fp):
    """A snapshot taken mid-run and restored gives the same continuation, on the FMU
    (fmi2GetFMUstate / fmi2SetFMUstate) as on the native plant."""
    p = Plant(fp.vehicle)
    U = varied_inputs(4, 60, seed=4)
    for q in (fp, p):
        _drive(q, U[:20])
    snaps = fp.get_state(), p.get_state()
    first = _drive(fp, U[20:]), _drive(p, U[20:])
    fp.set_state(snaps[0])
    p.set_state(snaps[1])
    assert fp.t == p.t == pytest.approx(0.2)
    again = _drive(fp, U[20:]), _drive(p, U[20:])
    for a, b, c in zip(first[0], again[0], again[1]):
        _assert_same(a, b, tol=0.0)  # the same FMU continuation, bit for bit
        _assert_same(b, c)  # and the native plant's
    with pytest.raises(PlantError, match="does not belong"):
        fp.set_state(snaps[1])


def test_direct_feedthrough_before_stepping(fp):
    """Slips and forces follow a new command at once, as Plant.outputs does."""
    p = Plant(fp.vehicle)
    for q in (fp, p):
        q.set_inputs([5.0, 5.0, 5.0, 5.0], [0.1, 0.0, 0.0, -0.1])
    _assert_same(fp.outputs(), p.outputs())
    assert fp.outputs()["Fx_11"] > 1000.0


@pytest.mark.parametrize("w, s", [
    ([1.0, 1.0, 1.0], [0.0] * 4),                   # wrong shape
    ([1.0, float("nan"), 1.0, 1.0], [0.0] * 4),     # not finite
    ([1.0, 1.0, 1.0, 1.0], [0.0, float("inf"), 0.0, 0.0]),
    ([1.0, -0.5, 1.0, 1.0], [0.0] * 4),             # negative wheel speed
])
def test_input_validation_as_the_plant(fp, w, s):
    with pytest.raises(PlantError) as e_nat:
        Plant(fp.vehicle).set_inputs(w, s)
    with pytest.raises(PlantError) as e_fmu:
        fp.set_inputs(w, s)
    assert str(e_fmu.value) == str(e_nat.value)
    fp.set_inputs([1.0] * 4, [0.0] * 4)  # still usable
    fp.do_step(0.0, 0.01)


def test_do_step_checks_time_and_step(fp):
    with pytest.raises(PlantError, match="does not match"):
        fp.do_step(0.5, 0.01)
    with pytest.raises(PlantError, match="step size"):
        fp.do_step(0.0, 0.0)
    fp.do_step(0.0, 0.01)
    assert fp.t == 0.01


def test_saturated_commands_and_actual_wheel_speed(fp):
    fp.set_inputs([40.0] * 4, [2.0] * 4)
    fp.do_step(fp.t, 0.01)
    out = fp.outputs()
    assert out["omega_w_11"] == fp.vehicle.limits.omega_w_max
    assert out["omega_s_11"] == fp.vehicle.limits.omega_s_max
    w, s = fp.inputs
    assert w.tolist() == [25.0] * 4 and s.tolist() == [0.8] * 4


def test_reset_and_initial_state(fp):
    fp.set_inputs([3.0] * 4, [0.2] * 4)
    for _ in range(20):
        fp.do_step(fp.t, 0.01)
    assert fp.state_message()["x"] > 0
    fp.reset()
    m = fp.state_message()
    assert fp.t == 0.0 and m["x"] == 0.0 and m["W_s"] == 0.0
    fp.reset(initial={"vx": 2.0, "phi": 0.5, "delta_21": -0.3})
    m = fp.state_message()
    assert (m["vx"], m["phi"], m["delta"][2]) == (2.0, 0.5, -0.3)
    fp.reset()  # keeps the last initial state, as Plant.reset() does
    assert fp.state_message()["vx"] == 2.0
    with pytest.raises(PlantError, match="unknown signal"):
        fp.reset(initial={"speed": 1.0})
    with pytest.raises(PlantError, match="steering limits"):
        fp.reset(initial={"delta_11": 3.0})


def test_parameters_change_the_vehicle_and_the_fmu(fmu2):
    with FmuPlant(fmu2, parameters={"mass": 16000.0, "tire_lateral_mu": 0.6},
                  initial={"vx": 1.0}) as f:
        assert f.vehicle.mass == 16000.0 and f.vehicle.tire_lateral.mu == 0.6
        p = Plant(f.vehicle, initial={"vx": 1.0})
        U = varied_inputs(4, 50, seed=4)
        for a, b in zip(_drive(f, U), _drive(p, U)):
            _assert_same(a, b)
        assert f.outputs()["F_N_11"] == pytest.approx(16000.0 * 9.81 / 4)


def test_bad_parameters_are_refused_before_the_fmu(fmu2):
    with pytest.raises(VehicleError, match="mass"):
        FmuPlant(fmu2, parameters={"mass": -1.0})
    with pytest.raises(FmuHostError, match="not one of our parameter names"):
        FmuPlant(fmu2, parameters={"weight": 1.0})
    with pytest.raises(FmuHostError, match="not one of our parameter names"):
        FmuPlant(fmu2, parameters={"x": 1.0})  # an output, not a parameter


def test_close_removes_the_unpack_dir(fmu2):
    f = FmuPlant(fmu2)
    d = f._unzip
    assert d.is_dir()
    f.close()
    assert not d.exists()
    f.close()  # idempotent


def test_unpack_dir_is_reused(fmu2, tmp_path):
    with FmuPlant(fmu2, unpack_dir=tmp_path / "u") as f:
        f.do_step(0.0, 0.01)
    stamp = (tmp_path / "u" / "modelDescription.xml").stat().st_mtime_ns
    with FmuPlant(fmu2, unpack_dir=tmp_path / "u") as f:
        f.do_step(0.0, 0.01)
    assert (tmp_path / "u" / "modelDescription.xml").stat().st_mtime_ns == stamp


# ---- mapping ------------------------------------------------------------------------------
def test_prefixed_fmu_needs_a_mapping(fmu_prefixed):
    with pytest.raises(FmuHostError) as e:
        FmuPlant(fmu_prefixed)
    msg = str(e.value)
    assert "has no variable 'omega_w_11'" in msg and "[map]" in msg


def test_mapping_file_with_prefix(fmu_prefixed, fmu2, tmp_path):
    m = tmp_path / "map.toml"
    m.write_text(f'prefix = "{PREFIX}"\n')
    U = varied_inputs(4, 60, seed=5)
    with FmuPlant(fmu_prefixed, mapping=m, initial={"vx": 1.5}) as a, \
            FmuPlant(fmu2, initial={"vx": 1.5}) as b:
        for x, y in zip(_drive(a, U), _drive(b, U)):
            _assert_same(x, y, tol=0.0)
        assert a.state_message() == b.state_message()


def test_mapping_file_with_every_name_listed(fmu_prefixed, tmp_path):
    """A [map] table naming each variable explicitly (what a foreign FMU needs)."""
    names = [v.name for v in fmu_variables(default_vehicle(), output_start=False)]
    m = tmp_path / "map.toml"
    m.write_text("# our name = the FMU's name\n[map]\n"
                 + "".join(f'{n} = "{PREFIX}{n}"\n' for n in names))
    nm = load_mapping(m)
    assert nm.prefix == "" and nm.their("x") == PREFIX + "x"
    with FmuPlant(fmu_prefixed, mapping=nm, parameters={"mass": 14000.0}) as f:
        f.set_inputs([4.0] * 4, [0.0] * 4)
        f.do_step(0.0, 0.01)
        assert f.state_message()["vx"] > 0 and f.vehicle.mass == 14000.0
        assert f.outputs()["F_N_11"] == pytest.approx(14000.0 * 9.81 / 4)


def test_missing_mapped_variable_is_a_clear_error(fmu_prefixed, tmp_path):
    m = tmp_path / "map.toml"
    m.write_text(f'prefix = "{PREFIX}"\n[map]\nvx = "{PREFIX}speed_x"\n')
    with pytest.raises(FmuHostError) as e:
        FmuPlant(fmu_prefixed, mapping=m)
    msg = str(e.value)
    assert str(m) in msg and f"vx -> '{PREFIX}speed_x'" in msg and "has no variable" in msg


@pytest.mark.parametrize("text, match", [
    ('[map]\nspeed = "vx"\n', "'speed' is not one of our variable names"),
    ('[map]\nx = 3\n', "map.x: expected the FMU's variable name"),
    ('maps = "x"\n', "unknown key 'maps'"),
    ("[map\n", "not valid TOML"),
])
def test_bad_mapping_files(fmu2, tmp_path, text, match):
    m = tmp_path / "bad.toml"
    m.write_text(text)
    with pytest.raises(FmuHostError, match=match):
        FmuPlant(fmu2, mapping=m)


def test_mapping_to_a_variable_of_the_wrong_kind(fmu2):
    with pytest.raises(FmuHostError, match="causality parameter, expected output"):
        FmuPlant(fmu2, mapping={"map": {"x": "mass"}})
    with pytest.raises(FmuHostError, match="expected input"):
        FmuPlant(fmu2, mapping=NameMap({"omega_s_22": "x"}))


def test_missing_file_and_non_fmu(tmp_path):
    with pytest.raises(FmuHostError, match="not found"):
        FmuPlant(tmp_path / "none.fmu")
    bad = tmp_path / "bad.fmu"
    bad.write_text("not a zip")
    with pytest.raises(FmuHostError):
        FmuPlant(bad)
    with pytest.raises(FmuHostError, match="mapping file not found"):
        load_mapping(tmp_path / "none.toml")


# ---- a foreign FMU: other names, only the required signals ---------------------------------
TOY_SLAVE = textwrap.dedent('''
    """A kinematic toy vehicle with its own naming, for testing the host's mapping."""
    import math
    from pythonfmu import Fmi2Slave
    from pythonfmu.enums import Fmi2Causality, Fmi2Variability
    from pythonfmu.variables import Real

    WHEELS = ("fl", "fr", "rl", "rr")


    class ToyCart(Fmi2Slave):
        def __init__(self, **kwargs):
            super().__init__(**kwargs)
            self.s = {n: 0.0 for n in ("px", "py", "yaw", "ux", "uy", "wz")}
            self.d = {w: 0.0 for w in WHEELS}
            self.cmd = {f"{k}_{w}": 0.0 for k in ("spin", "turn") for w in WHEELS}
            self.v0 = 0.0
            for k in self.cmd:
                self.register_variable(Real(
                    "cmd." + k, causality=Fmi2Causality.input, variability=Fmi2Variability.continuous,
                    start=0.0, getter=lambda k=k: self.cmd[k],
                    setter=lambda x, k=k: self.cmd.__setitem__(k, x)), nested=False)
            for k in self.s:
                self.register_variable(Real(
                    "body." + k, causality=Fmi2Causality.output, variability=Fmi2Variability.continuous,
                    getter=lambda k=k: self.s[k]), nested=False)
            for w in WHEELS:
                self.register_variable(Real(
                    "steer." + w, causality=Fmi2Causality.output, variability=Fmi2Variability.continuous,
                    getter=lambda w=w: self.d[w]), nested=False)
            self.register_variable(Real(
                "speed0", causality=Fmi2Causality.parameter, variability=Fmi2Variability.fixed,
                start=0.0, getter=lambda: self.v0, setter=lambda x: setattr(self, "v0", x)),
                nested=False)

        def exit_initialization_mode(self):
            self.s["ux"] = self.v0

        def do_step(self, t, h):
            v = 0.5 * sum(self.cmd["spin_" + w] for w in WHEELS) / 4
            self.s["ux"], self.s["uy"] = v * math.cos(self.s["yaw"]), v * math.sin(self.s["yaw"])
            self.s["px"] += h * self.s["ux"]
            self.s["py"] += h * self.s["uy"]
            for w in WHEELS:
                self.d[w] += h * self.cmd["turn_" + w]
            return True
''')

TOY_MAP = """\
# our name = "the toy's name"
[map]
x = "body.px"
y = "body.py"
phi = "body.yaw"
vx = "body.ux"
vy = "body.uy"
r = "body.wz"
delta_11 = "steer.fl"
delta_12 = "steer.fr"
delta_21 = "steer.rl"
delta_22 = "steer.rr"
omega_w_11 = "cmd.spin_fl"
omega_w_12 = "cmd.spin_fr"
omega_w_21 = "cmd.spin_rl"
omega_w_22 = "cmd.spin_rr"
omega_s_11 = "cmd.turn_fl"
omega_s_12 = "cmd.turn_fr"
omega_s_21 = "cmd.turn_rl"
omega_s_22 = "cmd.turn_rr"
vx_0 = "speed0"
"""


@pytest.fixture(scope="module")
def toy(work) -> tuple[Path, Path]:
    src = work / "toy"
    src.mkdir()
    (src / "toy_cart.py").write_text(TOY_SLAVE)
    r = subprocess.run([sys.executable, "-m", "pythonfmu", "build", "-f", "toy_cart.py",
                        "-d", str(work)], cwd=src, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    m = work / "toy_map.toml"
    m.write_text(TOY_MAP)
    return work / "ToyCart.fmu", m


def test_foreign_fmu_needs_the_vehicle(toy):
    fmu, m = toy
    with pytest.raises(FmuHostError, match="pass the vehicle"):
        FmuPlant(fmu, mapping=m)


def test_foreign_fmu_through_a_mapping(toy):
    fmu, m = toy
    with FmuPlant(fmu, default_vehicle(), mapping=m, initial={"vx": 0.7}) as f:
        assert f.state_message()["vx"] == 0.7
        f.set_inputs([2.0, 2.0, 2.0, 2.0], [0.1, 0.1, 0.0, 0.0])
        for _ in range(10):
            f.do_step(f.t, 0.01)
        msg = f.state_message()
        assert msg["x"] == pytest.approx(0.1) and msg["vx"] == pytest.approx(1.0)
        assert msg["delta"] == pytest.approx([0.01, 0.01, 0.0, 0.0])
        # no actual wheel speed, no wear in this FMU: the held command, no wear fields
        assert msg["omega_w"] == [2.0] * 4
        assert not {"W_s", "W_alpha", "W_t"} & set(msg)
        assert set(f.outputs()) == {"x", "y", "phi", "vx", "vy", "r", "delta_11",
                                    "delta_12", "delta_21", "delta_22"}
        with pytest.raises(FmuHostError, match="no parameter 'mass'"):
            FmuPlant(fmu, default_vehicle(), mapping=m, parameters={"mass": 1.0})


def test_foreign_fmu_without_a_required_mapping(toy, tmp_path):
    fmu, m = toy
    partial = tmp_path / "partial.toml"
    partial.write_text(m.read_text().replace('delta_22 = "steer.rr"\n', ""))
    with pytest.raises(FmuHostError) as e:
        FmuPlant(fmu, default_vehicle(), mapping=partial)
    assert "has no variable 'delta_22'" in str(e.value) and "required" in str(e.value)


def test_foreign_fmu_stripped_of_our_config_is_foreign(fmu2, tmp_path):
    """An FMU without resources/msagv_fmu.json is treated as foreign: vehicle needed."""
    stripped = tmp_path / "stripped.fmu"
    with zipfile.ZipFile(fmu2) as zin, zipfile.ZipFile(stripped, "w") as zout:
        for item in zin.infolist():
            if not item.filename.endswith("msagv_fmu.json"):
                zout.writestr(item, zin.read(item.filename))
    with pytest.raises(FmuHostError, match="pass the vehicle"):
        FmuPlant(stripped)


# ---- the closed loop, unchanged, on the FMU ----------------------------------------------
def test_closed_loop_runs_unchanged_on_the_fmu(fmu_prefixed, tmp_path):
    """The SA-MPC closed loop (controller.loop.closed_loop, as msagv run sets it up) on the
    prefixed FMU through a mapping file gives the same run as on the native plant."""
    pytest.importorskip("msagv.controller.loop")
    import argparse

    from msagv.controller.loop import closed_loop
    from msagv.cli.args import add_case_args, add_mpc_args, scenario_from_args

    ap = argparse.ArgumentParser()
    add_case_args(ap)
    add_mpc_args(ap)
    a = ap.parse_args([])
    sc = scenario_from_args(a)
    vehicle = sc.resolve_vehicle()
    ref, start = sc.reference()
    initial = sc.initial_state(vehicle, start)
    m = tmp_path / "map.toml"
    m.write_text(f'prefix = "{PREFIX}"\n')
    finals = []
    for plant in (Plant(vehicle, initial=initial),
                  FmuPlant(fmu_prefixed, vehicle, mapping=m, initial=initial)):
        log = closed_loop(plant, sc.make_controller(vehicle, ref), ref, 0.5, progress=False)
        finals.append(log.final_state)
    native, fmu = finals
    assert fmu["x"] > 1.0
    for k in ("x", "y", "phi", "vx", "vy", "r", "W_s", "W_alpha", "W_t"):
        assert abs(float(fmu[k]) - float(native[k])) <= 1e-9, k


def test_cli_options_make_an_fmu_plant(fmu_prefixed, tmp_path):
    """msagv.cli.args.add_fmu_args / scenario_from_args: FILE.fmu --map FILE --param ..."""
    import argparse

    from msagv.cli.args import add_fmu_args, scenario_from_args

    def fmu_plant_from_args(a, initial=None):
        sc = scenario_from_args(a)
        sc.from_rest, sc.initial = True, dict(initial or {})
        return sc.make_plant()[0]

    m = tmp_path / "map.toml"
    m.write_text(f'prefix = "{PREFIX}"\n')
    ap = argparse.ArgumentParser()
    add_fmu_args(ap, positional=True)
    a = ap.parse_args([str(fmu_prefixed), "--map", str(m), "--param", "mass=15000,rtol=1e-9"])
    with fmu_plant_from_args(a, initial={"vx": 1.0}) as f:
        assert f.vehicle.mass == 15000.0 and f.state_message()["vx"] == 1.0
    a = ap.parse_args([str(fmu_prefixed), "--param", "mass=15000"])
    with pytest.raises(FmuHostError, match="omega_w_11"):
        fmu_plant_from_args(a)


# ---- the FMU's log messages, in a process that hosts other FMUs too ------------------------
LOG_ROUTING = textwrap.dedent("""
    import gc, json, sys
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave
    from msagv.fmu_build.host import FmuPlant
    from msagv.plant import PlantError

    fmu = sys.argv[1]

    def fail(p):  # a negative wheel speed past the host's checks: the FMU logs why it fails
        p._fmu.setReal(p._in_vr[:1], [-1.0])
        try:
            p.do_step(p.t, 0.01)
        except PlantError:
            pass

    a, b = FmuPlant(fmu), FmuPlant(fmu)
    fail(a)
    logs = {"a": list(a.log), "b": list(b.log)}
    a.close(); b.close(); del a, b; gc.collect()
    # an instance of fmpy's own, with fmpy's default callbacks, after the hosts are gone
    md = read_model_description(fmu)
    f = FMU2Slave(guid=md.guid, unzipDirectory=extract(fmu), modelIdentifier="MsagvPlant",
                  instanceName="plain")
    f.instantiate(loggingOn=True)
    f.setupExperiment(startTime=0.0); f.enterInitializationMode(); f.exitInitializationMode()
    vr = {v.name: v.valueReference for v in md.modelVariables}
    f.setReal([vr["omega_w_11"]], [-1.0])  # and it fails: the FMU logs why
    try:
        f.doStep(0.0, 0.01)
    except Exception:
        pass
    f.terminate(); f.freeInstance()
    print(json.dumps(logs))
""")


def test_each_instance_keeps_its_own_log_and_a_closed_one_leaves_no_logger_behind(fmu2):
    """fmpy formats an FMU's messages in one process-wide proxy that calls the logger last
    given to it. Two hosts: the messages of one land in its own log only; after both are
    closed and collected, an instance with fmpy's default callbacks logs (pythonfmu logs at
    every setReal with logging on) without calling a logger that is gone. The host had given
    its own logger to the proxy and left it there: this process crashed (SIGSEGV in ctypes'
    closure), in the suite as soon as test_fmu's fmpy slave followed this module's hosts."""
    r = subprocess.run([sys.executable, "-c", LOG_ROUTING, str(fmu2)], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, (r.returncode, r.stderr[-3000:])
    logs = __import__("json").loads(r.stdout.strip().splitlines()[-1])
    assert any("[error]" in m for m in logs["a"]), logs
    assert not any("[error]" in m for m in logs["b"]), logs
