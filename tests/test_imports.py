"""The layout of the house: which package may import which (README, docs/ARCHITECTURE.md).

Read from the source with ``ast`` (every ``import`` and ``from ... import``, also those
inside functions), so the rule holds for lazily imported modules too:

    plant <- controller <- (bridge, fmu_build) <- experiments <- benchmarks <- msagv

An arrow points from a package to those that may import it; nothing imports upwards and
there are no cycles. bridge/ is transport only: no matplotlib, no experiments, no app.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("plant", "controller", "bridge", "fmu_build", "experiments", "benchmarks", "msagv")
ALLOWED = {
    "plant": set(),
    "controller": {"plant"},
    "bridge": {"plant", "controller"},
    "fmu_build": {"plant"},
    "experiments": {"plant", "controller", "bridge", "fmu_build"},
    "benchmarks": {"plant", "controller", "bridge", "fmu_build", "experiments"},
    "msagv": {"plant", "controller", "bridge", "fmu_build", "experiments", "benchmarks"},
}


def _imports(path: Path, package: str) -> set[str]:
    """Top-level modules imported anywhere in ``path`` (relative imports resolved)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: inside the same top-level package
                out.add(package)
            elif node.module:
                out.add(node.module.split(".")[0])
    return out


def _sources(package: str):
    return sorted((ROOT / package).rglob("*.py"))


def import_graph() -> dict[str, set[str]]:
    graph = {p: set() for p in PACKAGES}
    for pkg in PACKAGES:
        for f in _sources(pkg):
            graph[pkg] |= (_imports(f, pkg) & set(PACKAGES)) - {pkg}
    return graph


def test_every_package_imports_only_what_lies_below_it():
    graph = import_graph()
    bad = {p: sorted(graph[p] - ALLOWED[p]) for p in PACKAGES if graph[p] - ALLOWED[p]}
    assert not bad, f"upward or sideways imports: {bad}"


def test_the_import_graph_has_no_cycle():
    graph = import_graph()
    seen, stack = set(), []

    def visit(p):
        if p in stack:
            raise AssertionError(f"import cycle: {' -> '.join(stack[stack.index(p):] + [p])}")
        if p in seen:
            return
        stack.append(p)
        for q in graph[p]:
            visit(q)
        stack.pop()
        seen.add(p)

    for p in PACKAGES:
        visit(p)


@pytest.mark.parametrize("module", ["matplotlib", "experiments", "msagv", "tqdm"])
def test_bridge_is_transport_only(module):
    users = [str(f.relative_to(ROOT)) for f in _sources("bridge")
             if module in _imports(f, "bridge")]
    assert not users, f"bridge/ imports {module}: {users}"


def test_no_imports_by_string():
    """Modules are imported by name (visible to this test), never with importlib by string."""
    pat = re.compile(r"importlib\.import_module|__import__\(")
    users = [str(f.relative_to(ROOT)) for pkg in PACKAGES for f in _sources(pkg)
             if pat.search(f.read_text()) and not f.name == "slave.py"]
    # fmu_build/slave.py imports the plant the FMU bundles under a build-specific name: the
    # one place where the module's name is only known at run time
    assert not users, users


def test_the_checker_sees_lazy_and_relative_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("from . import x\n\ndef g():\n    import experiments.runs\n    from plant import a\n")
    assert _imports(f, "bridge") == {"bridge", "experiments", "plant"}
