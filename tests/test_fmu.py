"""The plant as an FMI 2.0 co-simulation FMU (fmu_build.build, fmu_build.slave, the CLI):
built from the built-in and a 3-axle vehicle, validated by fmpy, stepped by fmpy and by
libcosim in fresh processes and compared with the native plant in every output; bad
vehicles refused with exit code 2; numba without a writable cache.

FMUs run in subprocesses started from a neutral directory (FMUs in one process share
``sys.modules``), all with timeouts. The 20 s comparison is marked slow.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import pytest

from helpers import THREE_AXLE_TOML, edit_toml
from msagv.cli import main as dispatcher
from msagv.fmu_build.build import MAX_AXLES, FmuBuildError, build_fmu
from msagv.fmu_build.drive import libcosim_step_sizes, run_native, varied_inputs
from msagv.fmu_build.variables import (ATOL_DEFAULT, RTOL_DEFAULT, fmu_variables,
                                 variable_table_markdown)
from msagv.plant import Plant, default_vehicle, load_vehicle, n_axle_vehicle
from msagv.plant.tire import V_EPS_DEFAULT

ROOT = Path(__file__).resolve().parents[1]
TOL = 1e-9
PARAMS = {"mass": 16000.0, "tire_lateral_mu": 0.6, "vx_0": 2.0, "phi_0": 0.3,
          "delta_11_0": 0.2, "rtol": 1e-10}

# the shared 3-axle vehicle with other tires and asymmetric limits
THREE_AXLE = THREE_AXLE_TOML
for _table, _key, _value in [("", "name", '"fmu-3axle"'), ("tire.lateral", "mu", "0.75"),
                             ("tire.dugoff", "C_s", "400000.0"),
                             ("tire.dugoff", "C_alpha", "250000.0"), ("tire.dugoff", "mu", "0.8"),
                             ("limits", "omega_s_max", "0.9"), ("limits", "omega_w_max", "28.0"),
                             ("limits", "delta_min", "-1.2")]:
    THREE_AXLE = edit_toml(THREE_AXLE, _table, _key, _value)


def msagv(argv: list[str]) -> int:
    """``msagv fmu ...`` as the dispatcher runs it (msagv.cli.main -> fmu_main)."""
    assert argv[0] == "fmu"
    return dispatcher(argv)


def _vehicle_toml(v) -> str:
    """A vehicle as TOML (the loader's layout)."""
    d = v.to_dict()
    lines = [f"name = {json.dumps(d['name'])}"]
    for k in ("mass", "yaw_inertia", "wheel_radius", "half_track", "steer_loss_kt"):
        lines.append(f"{k} = {d[k]!r}")
    lines.append(f"axle_x = [{', '.join(repr(x) for x in d['axle_x'])}]")
    for part in ("longitudinal", "lateral", "dugoff"):
        lines.append(f"[tire.{part}]")
        lines += [f"{k} = {x!r}" for k, x in d["tire"][part].items()]
    for table in ("limits", "plant"):
        lines.append(f"[{table}]")
        lines += [f"{k} = {x!r}" for k, x in d[table].items()]
    return "\n".join(lines) + "\n"


def _run_jobs(tmp: Path, runs: list[dict], timeout: float = 300) -> dict:
    """Run fmu_build.drive in a fresh interpreter from a neutral directory."""
    job = tmp / f"job{len(list(tmp.glob('job*.json')))}.json"
    out = job.with_suffix(".npz")
    job.write_text(json.dumps({"runs": runs}))
    r = subprocess.run([sys.executable, "-m", "msagv.fmu_build.drive", str(job), str(out)],
                       cwd=tmp, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    with np.load(out) as z:
        return {k: z[k] for k in z.files}


def _max_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-column max |a - b|, with a non-finite value anywhere counted as inf."""
    d = np.abs(a - b)
    d[~np.isfinite(d)] = np.inf
    return d.max(axis=0)


def _assert_match(names, S_fmu, S_nat, tol=TOL):
    assert S_fmu.shape == S_nat.shape
    assert np.all(np.isfinite(S_nat))
    worst = _max_diff(S_fmu, S_nat)
    bad = {str(n): float(w) for n, w in zip(names, worst) if not w <= tol}
    assert not bad, f"outputs differ by more than {tol}: {bad}"
    return float(worst.max())


# ---- fixtures: one build per vehicle for the module ----------------------------------------
@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fmu")


@pytest.fixture(scope="module")
def fmu2(paper_fmu) -> Path:
    return paper_fmu


@pytest.fixture(scope="module")
def fmu3_vehicle_file(work) -> Path:
    p = work / "three.toml"
    p.write_text(THREE_AXLE)
    return p


@pytest.fixture(scope="module")
def fmu3(work, fmu3_vehicle_file) -> Path:
    out = work / "plant3.fmu"
    assert msagv(["fmu", "build", "--vehicle", str(fmu3_vehicle_file), "-o", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def fmpy_runs(work, fmu2, fmu3) -> dict:
    """One fresh process (the plant compiles once): default 2 s, parameters 1 s, 3-axle 2 s."""
    return _run_jobs(work, [
        {"engine": "fmpy", "fmu": str(fmu2), "seconds": 2.0},
        {"engine": "fmpy", "fmu": str(fmu2), "seconds": 1.0, "parameters": PARAMS, "seed": 1},
        {"engine": "fmpy", "fmu": str(fmu3), "seconds": 2.0, "seed": 2},
    ])


# ---- the build ----------------------------------------------------------------------------
def test_fmpy_validate_passes(fmu2, fmu3):
    from fmpy.validation import validate_fmu

    assert validate_fmu(str(fmu2)) == []
    assert validate_fmu(str(fmu3)) == []


def test_fmpy_validate_command_line(fmu2, work):
    r = subprocess.run([sys.executable, "-m", "fmpy", "validate", str(fmu2)], cwd=work,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "No problems found" in r.stdout, r.stdout + r.stderr


def test_fmu_bundles_the_plant_and_the_vehicle(fmu2):
    with zipfile.ZipFile(fmu2) as z:
        names = z.namelist()
        cfg = json.loads(z.read("resources/msagv_fmu.json"))
        slave_module = z.read("resources/slavemodule.txt").decode().strip()
    pkg = cfg["plant_package"]
    for f in ("__init__.py", "stepping.py", "dynamics.py", "tire.py", "vehicle.py"):
        assert f"resources/{pkg}/{f}" in names
    assert f"resources/{slave_module}.py" in names
    assert not [n for n in names if "__pycache__" in n or n.endswith((".nbi", ".nbc"))]
    assert "binaries/linux64/MsagvPlant.so" in names
    assert cfg["vehicle"] == default_vehicle().to_dict()
    assert cfg["n_axles"] == 2


def test_model_description_is_the_variable_table(fmu2):
    """Names, causality, variability, units, descriptions and exact start values."""
    from fmpy import read_model_description

    md = read_model_description(str(fmu2))
    got = {v.name: v for v in md.modelVariables}
    table = fmu_variables(default_vehicle())
    assert [v.name for v in md.modelVariables] == [v.name for v in table]
    units = {u.name for u in md.unitDefinitions}
    for v in table:
        m = got[v.name]
        assert (m.causality, m.variability, m.unit, m.description) == \
               (v.causality, v.variability, v.unit, v.description), v.name
        if v.initial:
            assert m.initial == v.initial, v.name
        assert float(m.start) == v.start, v.name  # outputs: the native plant's initial values
        assert v.unit is None or v.unit in units
    outputs = {u.variable.name for u in md.outputs}
    assert outputs == {v.name for v in table if v.causality == "output"}
    # every plant signal is an output; the actual rates carry _act_ (the inputs own the names)
    from msagv.plant.signals import signal_names

    assert [v.key for v in table if v.role == "output"] == signal_names(default_vehicle())
    assert got["omega_w_act_11"].causality == "output"
    assert got["omega_w_11"].causality == "input"
    assert float(got["F_N_11"].start) == 12000.0 * 9.81 / 4
    # the default experiment steps at the control period (one fact: plant.signals)
    from msagv.plant.signals import CONTROL_PERIOD

    assert float(md.defaultExperiment.stepSize) == CONTROL_PERIOD


def test_integrator_defaults_are_the_plants():
    p = Plant()
    assert (p.rtol, p.atol) == (RTOL_DEFAULT, ATOL_DEFAULT)
    import inspect

    assert inspect.signature(Plant).parameters["v_eps"].default == V_EPS_DEFAULT


def test_docs_list_the_generated_variable_table():
    text = (ROOT / "docs" / "FMU.md").read_text()
    assert variable_table_markdown(default_vehicle()) in text, \
        "docs/FMU.md's variable list is stale: paste fmu_build.variables.variable_table_markdown"


# ---- refusals (no pythonfmu run: they fail before it) -------------------------------------
def _build_cli(tmp_path, capsys, vehicle_text=None, extra=()):
    args = ["fmu", "build", "-o", str(tmp_path / "x.fmu"), *extra]
    if vehicle_text is not None:
        p = tmp_path / "v.toml"
        p.write_text(vehicle_text)
        args += ["--vehicle", str(p)]
    rc = msagv(args)
    err = capsys.readouterr().err
    return rc, err


def test_refuses_too_many_axles(tmp_path, capsys):
    rc, err = _build_cli(tmp_path, capsys, _vehicle_toml(n_axle_vehicle(MAX_AXLES + 1)))
    assert rc == 2
    assert "axle_x" in err and f"maximum of {MAX_AXLES}" in err
    assert not (tmp_path / "x.fmu").exists()


def test_builds_the_maximum_axle_count_table():
    """MAX_AXLES itself is expressible (names stay unique: wheel 101 is axle 10, side 1)."""
    names = [v.name for v in fmu_variables(n_axle_vehicle(MAX_AXLES), output_start=False)]
    assert len(names) == len(set(names))


def test_refuses_a_name_xml_cannot_carry(tmp_path, capsys):
    rc, err = _build_cli(tmp_path, capsys, THREE_AXLE.replace('"fmu-3axle"', '"bad\\u0001name"'))
    assert rc == 2 and "name" in err and "control characters" in err


@pytest.mark.parametrize("prefix", ["1agv_", "agv-", "agv..", "a b"])
def test_refuses_a_prefix_that_makes_invalid_names(tmp_path, capsys, prefix):
    rc, err = _build_cli(tmp_path, capsys, extra=["--prefix", prefix])
    assert rc == 2 and "not a valid FMI structured name" in err, err


def test_refuses_a_bad_vehicle_file_naming_the_field(tmp_path, capsys):
    rc, err = _build_cli(tmp_path, capsys, THREE_AXLE.replace("mass = 18500.0", "mass = -5.0"))
    assert rc == 2 and "mass" in err


def test_refuses_an_initial_state_outside_the_limits(tmp_path, capsys):
    rc, err = _build_cli(tmp_path, capsys, extra=["--initial", "delta_11=3.0"])
    assert rc == 2 and "delta_11" in err


def test_refuses_output_without_fmu_suffix(tmp_path):
    with pytest.raises(FmuBuildError, match=r"\.fmu"):
        build_fmu(tmp_path / "x.zip")


def test_fmu_help_and_unknown_subcommand(capsys):
    # the msagv dispatcher reaches the fmu command; without a sub-command it is a usage
    # error (exit 2, usage on stderr), as bare msagv is
    assert dispatcher(["fmu"]) == 2
    assert "msagv fmu build" in capsys.readouterr().err
    assert dispatcher(["fmu", "--help"]) == 0
    assert "msagv fmu build" in capsys.readouterr().out
    assert msagv(["fmu", "frobnicate"]) == 2


# ---- the FMU stepped by fmpy vs the native plant ------------------------------------------
def test_fmpy_matches_native_2s(fmpy_runs):
    names, S = fmpy_runs["names_0"], fmpy_runs["S_0"]
    _, S_nat = run_native(default_vehicle(), fmpy_runs["U_0"], 0.01)
    _assert_match(names, S, S_nat)
    assert not bool(fmpy_runs["plant_imported"]), "the FMU imported the project's plant"


def test_parameters_take_effect(fmpy_runs):
    names = list(fmpy_runs["names_1"])
    S = fmpy_runs["S_1"]
    _, S_nat = run_native(default_vehicle(), fmpy_runs["U_1"], 0.01, PARAMS)
    _assert_match(names, S, S_nat)
    row0 = dict(zip(names, S[0]))
    assert row0["vx"] == 2.0 and row0["phi"] == 0.3 and row0["delta_11"] == 0.2
    assert row0["F_N_11"] == pytest.approx(16000.0 * 9.81 / 4, rel=1e-15)
    # and they matter: the default vehicle under the same inputs ends elsewhere
    _, S_def = run_native(default_vehicle(), fmpy_runs["U_1"], 0.01)
    assert np.abs(S[-1] - S_def[-1]).max() > 1.0


def test_three_axle_vehicle_builds_and_matches(fmpy_runs, fmu3_vehicle_file):
    v = load_vehicle(fmu3_vehicle_file)
    names, S = fmpy_runs["names_2"], fmpy_runs["S_2"]
    assert len(names) == len(Plant(v).signal_names) and "Fx_32" in list(names)
    _, S_nat = run_native(v, fmpy_runs["U_2"], 0.01)
    _assert_match(names, S, S_nat)


@pytest.mark.slow
def test_fmpy_matches_native_20s(work, fmu2):
    runs = _run_jobs(work, [{"engine": "fmpy", "fmu": str(fmu2), "seconds": 20.0}], timeout=600)
    names, S, U = runs["names_0"], runs["S_0"], runs["U_0"]
    _, S_nat = run_native(default_vehicle(), U, 0.01)
    worst = _assert_match(names, S, S_nat)
    # the inputs reached the wheel-speed limit and the tires slipped hard
    col = {n: i for i, n in enumerate(names)}
    assert S_nat[:, col["omega_w_11"]].max() == default_vehicle().limits.omega_w_max
    assert np.abs(S_nat[:, col["s_11"]]).max() > 0.1
    lim = default_vehicle().limits  # and steered into both stops
    deltas = S_nat[:, [col[f"delta_{w}"] for w in ("11", "12", "21", "22")]]
    assert deltas.min() == lim.delta_min and deltas.max() == lim.delta_max
    print(f"\nmax |FMU - native| over 20 s, all {len(names)} outputs: {worst:.3g}")


# ---- libcosim (Open Simulation Platform) ---------------------------------------------------
def test_libcosim_simulates_the_fmu_like_fmpy(work, fmu2, fmpy_runs):
    """libcosim runs the FMU in this Python (no LD_PRELOAD needed: libpython is loaded).

    libcosim counts time in integer nanoseconds and hands the FMU t_(k+1) - t_k, which
    differs from 0.01 in the last bits; the native plant fed the same step sizes matches
    it exactly, and fmpy (steps of exactly 0.01) to integrator-tolerance level.
    """
    runs = _run_jobs(work, [{"engine": "libcosim", "fmu": str(fmu2), "seconds": 2.0}])
    names, S, U = runs["names_0"], runs["S_0"], runs["U_0"]
    assert np.array_equal(U, fmpy_runs["U_0"])
    _, S_nat = run_native(default_vehicle(), U, libcosim_step_sizes(len(U), 0.01))
    _assert_match(names, S[1:], S_nat[1:])
    _assert_match(names, S[1:], fmpy_runs["S_0"][1:], tol=1e-6)
    assert not bool(runs["plant_imported"])


# ---- numba with nowhere to cache next to the sources ----------------------------------------
READONLY_SCRIPT = textwrap.dedent("""
    import json, os, sys, zipfile, pathlib
    fmu, unzip, probe = sys.argv[1], pathlib.Path(sys.argv[2]), pathlib.Path(sys.argv[3])
    zipfile.ZipFile(fmu).extractall(unzip)
    cfg = json.loads((unzip / "resources" / "msagv_fmu.json").read_text())
    # no __pycache__ can be made next to the bundled sources (works even for root) ...
    (unzip / "resources" / cfg["plant_package"] / "__pycache__").write_text("not a directory")
    # ... and the precondition holds: numba alone cannot cache a function there
    (probe / "__pycache__").write_text("not a directory")
    (probe / "probe_mod.py").write_text(
        "from numba import njit\\n@njit(cache=True)\\ndef f(x):\\n    return x + 1\\n")
    sys.path.insert(0, str(probe))
    try:
        import probe_mod
        precondition = "numba cached anyway"
    except RuntimeError as e:
        precondition = str(e)
    sys.path.pop(0)
    from fmpy import read_model_description
    from fmpy.fmi2 import FMU2Slave
    md = read_model_description(fmu)
    vr = {v.name: v.valueReference for v in md.modelVariables}
    f = FMU2Slave(guid=md.guid, unzipDirectory=str(unzip), modelIdentifier="MsagvPlant",
                  instanceName="ro")
    f.instantiate(loggingOn=True)
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.exitInitializationMode()
    f.setReal([vr["omega_w_" + w] for w in ("11", "12", "21", "22")], [4.0] * 4)
    for k in range(10):
        f.doStep(k * 0.01, 0.01)
    vx = f.getReal([vr["vx"]])[0]
    tmp = sorted(p for p in os.listdir(os.environ["TMPDIR"]) if p.startswith("msagv-fmu-numba-"))
    f.terminate(); f.freeInstance()
    print(json.dumps({"vx": vx, "precondition": precondition, "tmp": tmp}))
""")


def test_fmu_runs_where_numba_cannot_cache(work, fmu2, tmp_path):
    blocked = tmp_path / "blocked"
    blocked.write_text("a file, so no cache directory can be made under it")
    (tmp_path / "tmp").mkdir()
    (tmp_path / "probe").mkdir()
    env = dict(os.environ, XDG_CACHE_HOME=str(blocked / "cache"), TMPDIR=str(tmp_path / "tmp"))
    env.pop("NUMBA_CACHE_DIR", None)
    r = subprocess.run([sys.executable, "-c", READONLY_SCRIPT, str(fmu2), str(tmp_path / "unzip"),
                        str(tmp_path / "probe")],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert "no locator available" in res["precondition"]
    assert res["tmp"], "the slave did not redirect numba's cache to a temporary directory"
    assert 0.1 < res["vx"] < 2.0


# ---- a non-Python importer (C, dlopen) -----------------------------------------------------
C_IMPORTER = textwrap.dedent(r"""
    /* A minimal FMI 2.0 co-simulation importer with no Python of its own. */
    #include <dlfcn.h>
    #include <stdarg.h>
    #include <stdio.h>
    #include <stdlib.h>

    typedef void *fmi2Component;
    typedef unsigned int fmi2ValueReference;
    typedef struct {
        void (*logger)(void *, const char *, int, const char *, const char *, ...);
        void *(*allocateMemory)(size_t, size_t);
        void (*freeMemory)(void *);
        void (*stepFinished)(void *, int);
        void *componentEnvironment;
    } fmi2CallbackFunctions;
    typedef fmi2Component (*Instantiate_t)(const char *, int, const char *, const char *,
                                           const fmi2CallbackFunctions *, int, int);
    typedef int (*Setup_t)(fmi2Component, int, double, double, int, double);
    typedef int (*Mode_t)(fmi2Component);
    typedef int (*SetReal_t)(fmi2Component, const fmi2ValueReference *, size_t, const double *);
    typedef int (*GetReal_t)(fmi2Component, const fmi2ValueReference *, size_t, double *);
    typedef int (*DoStep_t)(fmi2Component, double, double, int);
    typedef void (*Free_t)(fmi2Component);

    static void logger(void *env, const char *inst, int status, const char *cat,
                       const char *msg, ...) {
        va_list ap;
        va_start(ap, msg);
        fprintf(stderr, "[fmu %d] ", status);
        vfprintf(stderr, msg, ap);
        fprintf(stderr, "\n");
        va_end(ap);
    }

    #define SYM(T, name) T name = (T)dlsym(lib, #name); \
        if (!name) { fprintf(stderr, "missing %s\n", #name); return 4; }

    int main(int argc, char **argv) {
        /* library resources-uri guid steps omega_w vr_out vr_in x4 */
        if (argc != 11) return 2;
        void *lib = dlopen(argv[1], RTLD_NOW | RTLD_LOCAL);
        if (!lib) { fprintf(stderr, "dlopen failed: %s\n", dlerror()); return 3; }
        SYM(Instantiate_t, fmi2Instantiate) SYM(Setup_t, fmi2SetupExperiment)
        SYM(Mode_t, fmi2EnterInitializationMode) SYM(Mode_t, fmi2ExitInitializationMode)
        SYM(SetReal_t, fmi2SetReal) SYM(GetReal_t, fmi2GetReal) SYM(DoStep_t, fmi2DoStep)
        SYM(Mode_t, fmi2Terminate) SYM(Free_t, fmi2FreeInstance)
        fmi2CallbackFunctions cb = {logger, calloc, free, NULL, NULL};
        fmi2Component c = fmi2Instantiate("c", 1, argv[3], argv[2], &cb, 0, 1);
        if (!c) return 5;
        int steps = atoi(argv[4]);
        fmi2ValueReference out = (fmi2ValueReference)atoi(argv[6]), in[4];
        double u[4], t = 0.0, y;
        for (int i = 0; i < 4; i++) { in[i] = (fmi2ValueReference)atoi(argv[7 + i]); u[i] = atof(argv[5]); }
        if (fmi2SetupExperiment(c, 0, 0.0, 0.0, 0, 0.0) || fmi2EnterInitializationMode(c)
            || fmi2ExitInitializationMode(c) || fmi2SetReal(c, in, 4, u)) return 6;
        for (int k = 0; k < steps; k++, t += 0.01)
            if (fmi2DoStep(c, t, 0.01, 1)) return 7;
        if (fmi2GetReal(c, &out, 1, &y)) return 8;
        printf("%.17g\n", y);
        fmi2Terminate(c);
        fmi2FreeInstance(c);
        return 0;
    }
""")


def test_non_python_importer_needs_libpython_preloaded(fmu2, tmp_path):
    """A C importer: without libpython in LD_PRELOAD the FMU's binary does not load; with it
    (and the project's site-packages on PYTHONPATH) the FMU runs, matches the native plant
    and the importer exits cleanly (scipy's exit-time abort avoided, see fmu_build.slave)."""
    import shutil
    import sysconfig

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None or not sysconfig.get_config_var("Py_ENABLE_SHARED"):
        pytest.skip("needs a C compiler and a shared libpython")
    from fmpy import read_model_description

    (tmp_path / "imp.c").write_text(C_IMPORTER)
    r = subprocess.run([cc, "-O1", "-o", str(tmp_path / "imp"), str(tmp_path / "imp.c"), "-ldl"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    unzip = tmp_path / "u"
    zipfile.ZipFile(fmu2).extractall(unzip)
    md = read_model_description(str(fmu2))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    args = [str(tmp_path / "imp"), str(unzip / "binaries" / "linux64" / "MsagvPlant.so"),
            (unzip / "resources").as_uri(), md.guid, "50", "4.0", str(vr["vx"]),
            *[str(vr[f"omega_w_{w}"]) for w in ("11", "12", "21", "22")]]
    env = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", "PYTHONHOME")}
    env["PYTHONPATH"] = sysconfig.get_paths()["purelib"]
    r = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 3 and "undefined symbol" in r.stderr, r.stderr
    libpython = Path(sysconfig.get_config_var("LIBDIR")) / sysconfig.get_config_var("INSTSONAME")
    env["LD_PRELOAD"] = str(libpython)
    r = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    p = Plant()
    p.set_inputs([4.0] * 4, [0.0] * 4)
    for _ in range(50):
        p.do_step(p.t, 0.01)
    assert abs(float(r.stdout.strip()) - p.outputs()["vx"]) <= TOL


# ---- slave semantics through fmpy, in this process (the bundled plant has its own name) ----
@pytest.fixture
def slave(fmu2):
    """A raw fmpy FMU2Slave of the default FMU, initialized, with a log of its messages."""
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave
    import shutil

    md = read_model_description(str(fmu2))
    d = extract(str(fmu2))
    f = FMU2Slave(guid=md.guid, unzipDirectory=d, modelIdentifier="MsagvPlant", instanceName="s")
    f.instantiate(loggingOn=True)
    f.setupExperiment(startTime=0.0)
    f.enterInitializationMode()
    f.exitInitializationMode()
    f.vr = {v.name: v.valueReference for v in md.modelVariables}
    yield f
    f.terminate()
    f.freeInstance()
    shutil.rmtree(d, ignore_errors=True)


def _set_inputs(f, w, s):
    wheels = ("11", "12", "21", "22")
    f.setReal([f.vr[f"omega_w_{k}"] for k in wheels] + [f.vr[f"omega_s_{k}"] for k in wheels],
              list(w) + list(s))


def test_tunable_vehicle_value_takes_effect_at_the_next_step(slave):
    """mass changed at t = 0.5 s: the FMU continues from its state with the new vehicle."""
    U = varied_inputs(4, 100, seed=6)
    v1 = default_vehicle()
    v2 = v1.replace(mass=20000.0)
    p = Plant(v1)
    for k in range(100):
        if k == 50:
            slave.setReal([slave.vr["mass"]], [20000.0])
            q = Plant(v2)
            q.set_state(p.get_state())
            p = q
        _set_inputs(slave, U[k, :4], U[k, 4:])
        p.set_inputs(U[k, :4], U[k, 4:])
        slave.doStep(k * 0.01, 0.01)
        p.do_step(p.t, 0.01)
    names = p.signal_names
    from msagv.fmu_build.variables import output_name

    got = slave.getReal([slave.vr[output_name(n)] for n in names])
    assert np.abs(np.array(got) - p.output_vector()).max() <= TOL
    assert slave.getReal([slave.vr["F_N_11"]])[0] == pytest.approx(20000.0 * 9.81 / 4)


def test_rejected_values_fail_the_next_step_and_the_instance_survives(slave):
    from fmpy.fmi1 import FMICallException

    _set_inputs(slave, [2.0, -1.0, 2.0, 2.0], [0.0] * 4)     # negative wheel speed
    with pytest.raises(FMICallException):
        slave.doStep(0.0, 0.01)
    _set_inputs(slave, [2.0] * 4, [0.0] * 4)                 # fixed again: steps again
    slave.doStep(0.0, 0.01)
    slave.setReal([slave.vr["vx_0"]], [3.0])                 # fixed parameter after init
    with pytest.raises(FMICallException):
        slave.doStep(0.01, 0.01)
    slave.doStep(0.01, 0.01)                                 # reported once, then ignored
    assert slave.getReal([slave.vr["vx_0"]]) == [0.0]
    slave.setReal([slave.vr["mass"]], [-5.0])                # tunable, but invalid
    with pytest.raises(FMICallException):
        slave.doStep(0.02, 0.01)
    slave.setReal([slave.vr["mass"]], [12000.0])
    slave.doStep(0.02, 0.01)
    with pytest.raises(FMICallException):                    # not where the FMU's time is
        slave.doStep(0.5, 0.01)
    assert slave.getReal([slave.vr["vx"]])[0] > 0
