"""The layout of the house: which package may import which (README, docs/ARCHITECTURE.md).

Everything installs as one top-level package, ``msagv``, and the import path is the file path:
``msagv/plant/tire.py`` is ``msagv.plant.tire`` (the design card's folders at the top of the
repository are links into ``msagv/``). Imports are read from
the source with ``ast`` (every ``import`` and ``from ... import``, also those inside
functions, and the ``module:Class`` targets of the solver table), so the rules hold for
lazily imported modules too:

    plant <- controller <- (bridge, fmu_build) <- experiments <- benchmarks <- app
    plant, controller <- bridge <- ros2 <- app      (the ROS 2 nodes)

An arrow points from a package to those that may import it (``app``: the command line,
``msagv/cli/``, and the modules at the top of ``msagv/``); nothing imports upwards; there are no cycles between
packages, nor between files. bridge/ is transport only: no matplotlib, no experiments, no
app. No module imports a top-level ``plant``, ``controller``, ... (a user's own module of
that name would be found instead).
"""

from __future__ import annotations

import ast
import json
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "msagv"
SUBPACKAGES = ("plant", "controller", "bridge", "fmu_build", "experiments", "benchmarks",
               "ros2")
PACKAGES = SUBPACKAGES + ("app",)
ALLOWED = {
    "plant": set(),
    "controller": {"plant"},
    "bridge": {"plant", "controller"},
    "fmu_build": {"plant"},
    "experiments": {"plant", "controller", "bridge", "fmu_build"},
    "benchmarks": {"plant", "controller", "bridge", "fmu_build", "experiments"},
    # the ROS 2 nodes: transport like bridge/, on rclpy; imported only by the command line
    "ros2": {"plant", "controller", "bridge"},
    "app": {"plant", "controller", "bridge", "fmu_build", "experiments", "benchmarks", "ros2"},
}
# 'module:attribute' strings in the solver table are imports too
_TARGET = re.compile(r"""["'](msagv(?:\.\w+)+):\w+["']""")


def module_name(path: Path) -> str:
    """The dotted module name of a source file: its path below the repository's root
    (``msagv/plant/tire.py`` is ``msagv.plant.tire``)."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _resolve(node: ast.ImportFrom, mod: str, is_pkg: bool) -> str:
    if not node.level:
        return node.module or ""
    base = mod.split(".")
    if not is_pkg:
        base = base[:-1]
    if node.level > 1:
        base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _file_of(module: str) -> Path | None:
    """The source file of a dotted module name of ours (None: not a module of ours)."""
    parts = module.split(".")
    if parts[0] != "msagv":
        return None
    p = ROOT.joinpath(*parts)
    for f in (p.with_suffix(".py"), p / "__init__.py"):
        if f.is_file():
            return f
    return None


def imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports (dotted, relative imports resolved). ``from X import
    y``: ``X.y`` when y is a module of ours (``from . import rollout`` depends on the
    module, not on the package's ``__init__``), else ``X``."""
    mod = module_name(path)
    is_pkg = path.name == "__init__.py"
    text = path.read_text()
    tree = ast.parse(text, filename=str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(node, mod, is_pkg)
            subs = {f"{base}.{a.name}" for a in node.names if a.name != "*"}
            mods = {m for m in subs if _file_of(m) is not None}
            out |= mods
            if len(mods) < len(node.names) or _file_of(base) is None:
                out.add(base)
    out.update(_TARGET.findall(text))
    return out


def package_of(module: str) -> str | None:
    """The floor of a dotted module name of ours (None: not ours)."""
    parts = module.split(".")
    if parts[0] != "msagv" or module == "msagv":  # the root (its version only) is below all
        return None
    if len(parts) > 1 and parts[1] in SUBPACKAGES:
        return parts[1]
    return "app"


def _sources(package: str):
    """The source files of a floor: a subpackage's folder, or for ``app`` the command line
    (``msagv/cli/``) and the modules at the top of ``msagv/``."""
    if package == "app":
        return sorted([*(ROOT / "msagv" / "cli").rglob("*.py"), *(ROOT / "msagv").glob("*.py")])
    return sorted((PKG / package).rglob("*.py"))


def all_sources():
    return [f for p in PACKAGES for f in _sources(p)]


def import_graph() -> dict[str, set[str]]:
    graph = {p: set() for p in PACKAGES}
    for pkg in PACKAGES:
        for f in _sources(pkg):
            graph[pkg] |= {q for q in map(package_of, imported_modules(f)) if q} - {pkg}
    return graph


def file_graph() -> dict[str, set[str]]:
    """Module -> the modules of ours it imports (only names that are files of ours)."""
    mods = {module_name(f): f for f in all_sources()}
    graph = {}
    for m, f in mods.items():
        graph[m] = {q for q in imported_modules(f) if q in mods and q != m}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    seen, stack, on = set(), [], set()

    def visit(p):
        if p in on:
            return stack[stack.index(p):] + [p]
        if p in seen:
            return None
        stack.append(p)
        on.add(p)
        for q in sorted(graph.get(p, ())):
            c = visit(q)
            if c:
                return c
        stack.pop()
        on.discard(p)
        seen.add(p)
        return None

    for p in sorted(graph):
        c = visit(p)
        if c:
            return c
    return None


def test_every_package_imports_only_what_lies_below_it():
    graph = import_graph()
    bad = {p: sorted(graph[p] - ALLOWED[p]) for p in PACKAGES if graph[p] - ALLOWED[p]}
    assert not bad, f"upward or sideways imports: {bad}"


def test_the_import_graph_has_no_cycle_between_packages():
    c = find_cycle(import_graph())
    assert c is None, f"import cycle: {' -> '.join(c)}"


def test_no_file_imports_another_that_imports_it_back():
    """No cycle between files (a package's ``__init__`` re-exporting its modules is an
    edge from the package to them; a module importing its own package's ``__init__`` is
    one back)."""
    c = find_cycle(file_graph())
    assert c is None, f"import cycle between files: {' -> '.join(c)}"


def test_nothing_imports_a_generic_top_level_name():
    generic = {"plant", "controller", "bridge", "fmu_build", "experiments", "benchmarks",
               "ros2"}
    bad = [f"{f.relative_to(ROOT)}: {m}" for f in all_sources() for m in imported_modules(f)
           if m.split(".")[0] in generic]
    assert not bad, bad


@pytest.mark.parametrize("module", ["matplotlib", "msagv.experiments", "tqdm"])
def test_bridge_is_transport_only(module):
    users = [str(f.relative_to(ROOT)) for f in _sources("bridge")
             if any(m == module or m.startswith(module + ".") for m in imported_modules(f))]
    assert not users, f"bridge/ imports {module}: {users}"


def test_bridge_does_not_import_the_app():
    users = [str(f.relative_to(ROOT)) for f in _sources("bridge")
             if any(package_of(m) == "app" and m != "msagv" for m in imported_modules(f))]
    assert not users, users


def test_no_imports_by_string():
    """Modules are imported by name (visible to this test), never with importlib by string,
    except the solver table's ``module:Class`` targets (read above as imports) and the
    FMU's slave, which imports the plant the FMU bundles under a build-specific name, and
    the ROS 2 runtime, which finds a ROS message class (a third-party package) by its ROS
    type name (``nav_msgs/msg/Odometry``)."""
    pat = re.compile(r"importlib\.import_module|__import__\(")
    allowed = {"slave.py", "solvers.py", "runtime.py"}
    users = [str(f.relative_to(ROOT)) for f in all_sources()
             if pat.search(f.read_text()) and f.name not in allowed]
    assert not users, users


def test_the_checker_sees_lazy_relative_and_table_imports(tmp_path, monkeypatch):
    d = tmp_path / "msagv" / "bridge"
    d.mkdir(parents=True)
    f = d / "m.py"
    f.write_text("from . import x\nfrom .y import z\n\ndef g():\n    import msagv.experiments.runs\n"
                 "    from msagv.plant import a\n\nT = 'msagv.controller.mpc:MPC'\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    got = imported_modules(f)
    assert {"msagv.bridge", "msagv.bridge.y", "msagv.experiments.runs", "msagv.plant",
            "msagv.controller.mpc"} <= got
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_the_wheel_installs_one_top_level_package(tmp_path):
    """The built wheel holds ``msagv`` alone at its top level (plus its metadata), and a
    user's own ``plant`` and ``controller`` modules beside it import fine."""
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".venv", ".git", "__pycache__", "*.egg-info", "build", "out", "runs", ".pytest_cache",
        ".hypothesis", "*.fmu", "*.nbi", "*.nbc"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                        str(tmp_path), str(src)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    # a clean build: no deprecation walls from our pyproject.toml (the license as a table,
    # a data folder outside the packages)
    assert "BuildBackendWarning" not in r.stdout + r.stderr, (r.stdout + r.stderr)[-3000:]
    whl, = tmp_path.glob("msagv-*.whl")
    with zipfile.ZipFile(whl) as z:
        tops = {n.split("/")[0] for n in z.namelist()}
        names = set(z.namelist())
    tops = {t for t in tops if not t.endswith((".dist-info", ".data"))}
    assert tops == {"msagv"}, tops
    assert {"msagv/plant/tire.py", "msagv/plant/data/paper-2axle.toml",
            "msagv/controller/mirrors/rollout_ref.c", "msagv/cli/__init__.py"} <= names
    user = tmp_path / "user"
    user.mkdir()
    (user / "plant.py").write_text("WHO = 'the user plant'\n")
    (user / "controller.py").write_text("WHO = 'the user controller'\n")
    code = ("import plant, controller\n"
            "from msagv.plant import default_vehicle\n"
            "from msagv.controller.mpc import MPC\n"
            "import msagv.cli\n"
            "assert plant.WHO == 'the user plant' and controller.WHO == 'the user controller'\n"
            "assert default_vehicle().n_axles == 2\n"
            "print('ok')\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=user, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]


def test_the_error_list_does_not_load_the_fmu_exporter():
    """msagv.cli.errors names the FMU host's error; the host reads the FMU's configuration
    file name from fmu_build.variables, not from the exporter (fmu_build.slave), so
    pythonfmu is loaded only by the commands that build an FMU."""
    code = ("import sys, msagv.cli.errors, msagv.fmu_build.host\n"
            "print('pythonfmu' in sys.modules)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "False"


def test_the_slave_carries_the_fmu_configuration_names():
    """The slave runs inside the FMU without the package, so it carries the configuration
    file's name and format: they must be the variable table's."""
    from msagv.fmu_build import slave, variables

    assert (slave.CONFIG_FILE, slave.CONFIG_FORMAT) == (variables.CONFIG_FILE,
                                                        variables.CONFIG_FORMAT)


def test_the_import_path_is_the_file_path_without_an_install():
    """From the repository's root, with the installed package's finder taken away, every
    module of ours is the file its dotted name spells (what ``python -m pytest`` from a clean
    checkout and static tools see)."""
    code = ("import sys\n"
            "sys.meta_path = [m for m in sys.meta_path if 'editable' not in repr(m)]\n"
            "import msagv.plant.vehicle, msagv.controller.mpc, msagv.bridge.plant_node, msagv.cli\n"
            "for m in (msagv.plant.vehicle, msagv.controller.mpc, msagv.bridge.plant_node, msagv.cli):\n"
            "    print(m.__name__, m.__file__)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    for line in r.stdout.splitlines():
        name, path = line.split()
        assert Path(path).resolve() == _file_of(name).resolve(), line


def test_jedi_goes_to_the_definition_across_packages():
    """Go-to-definition, as an editor does it (jedi), from names imported across packages to
    the file and line that define them. (In a child process: jedi leaves threads and a
    subprocess behind, and an FMU loaded in-process later in the same worker must not meet
    them.)"""
    pytest.importorskip("jedi", reason="jedi is in the test extra")
    probes = [(1, "load_vehicle", "msagv/plant/vehicle.py"),
              (2, "MPC", "msagv/controller/mpc.py"),
              (3, "PlantConfig", "msagv/bridge/plant_node.py")]
    code = (
        "import json, sys, jedi\n"
        "root, probes = sys.argv[1], json.loads(sys.argv[2])\n"
        "src = ('from msagv.plant.vehicle import load_vehicle\\n'\n"
        "       'from msagv.controller.mpc import MPC\\n'\n"
        "       'from msagv.bridge.plant_node import PlantConfig\\n')\n"
        "script = jedi.Script(src, path=root + '/probe.py', project=jedi.Project(root))\n"
        "out = []\n"
        "for line, name, _ in probes:\n"
        "    col = src.splitlines()[line - 1].rindex(name)\n"
        "    d = script.goto(line, col, follow_imports=True)\n"
        "    out.append([str(d[0].module_path), d[0].line] if d else None)\n"
        "print(json.dumps(out))\n")
    r = subprocess.run([sys.executable, "-c", code, str(ROOT), json.dumps(probes)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    for (line, name, rel), got in zip(probes, json.loads(r.stdout)):
        assert got, f"jedi found no definition of {name}"
        path, lineno = got
        assert Path(path).resolve() == (ROOT / rel).resolve(), (name, path)
        text = (ROOT / rel).read_text().splitlines()[lineno - 1]
        assert f"class {name}" in text or f"def {name}" in text, (name, text)
