"""Package the plant as an FMI 2.0 co-simulation FMU with pythonfmu.

:func:`build_fmu` stages, in a temporary directory,

* ``msagv_slave_<hash>.py`` -- a copy of :mod:`fmu_build.slave` (the Fmi2Slave),
* ``msagv_plant_<hash>/`` -- a copy of the ``plant`` package's sources and data (no
  ``__pycache__``, no numba cache files),
* ``msagv_fmu.json`` -- the vehicle description, the variable table and the units,

and runs ``python -m pythonfmu build -f msagv_slave_<hash>.py -d OUTDIR <the two others>``
in a subprocess (pythonfmu imports and instantiates the slave to write the model
description, which imports the bundled plant and leaves modules and ``sys.path`` entries
behind: a subprocess keeps them out of the caller). While building, the slave takes the
outputs' start values from the variable table (computed here by the native plant)
instead of compiling the kernels. The finished ``.fmu`` is moved to the requested path.

``<hash>`` is a digest of the slave and plant sources: the plant is bundled under its own
name so an FMU never picks up a ``plant`` package the host happens to have imported (or a
different build's), and two FMUs built from the same code share one copy in
``sys.modules``, which is safe because each instance reads its vehicle from its own
resources. The plant must therefore import itself only relatively; the build checks it.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from msagv import plant as plant_pkg
from msagv.plant.signals import CONTROL_PERIOD
from msagv.plant.vehicle import Vehicle, default_vehicle

from . import slave as slave_mod
from .variables import CONFIG_FILE, CONFIG_FORMAT, UNITS, VariableTableError, fmu_variables

MODEL_NAME = "MsagvPlant"
# The modelDescription grows by 26 variables per axle (13 per wheel) and the plant's cost
# per step linearly with the axle count; the plant itself takes any n >= 1. Beyond this the
# FMU would still work but no multi-axle AGV we know of comes near it (the longest
# self-propelled modular transporter units have about 24 axle lines), so a larger count is
# almost certainly a mistake in the vehicle file.
MAX_AXLES = 24
BUILD_TIMEOUT_S = 300.0

_ABS_IMPORT = re.compile(r"^\s*(from\s+(msagv\.)?plant(\.|\s)|import\s+(msagv\.)?plant(\.|\s|,|$)"
                         r"|from\s+msagv(\.|\s)|import\s+msagv(\.|\s|,|$))", re.M)
# XML 1.0 cannot carry these characters at all (not even escaped).
_XML_BAD = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ufffe\uffff]")


class FmuBuildError(ValueError):
    """The FMU cannot be built; the message says why (and names the offending field)."""


def _plant_files() -> list[Path]:
    root = Path(plant_pkg.__file__).parent
    files = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if p.is_file() and "__pycache__" not in rel.parts and p.suffix in (".py", ".toml"):
            files.append(p)
    return files


def code_hash() -> str:
    """Digest of the slave and the plant sources (10 hex digits)."""
    h = hashlib.sha256()
    root = Path(plant_pkg.__file__).parent
    for p in _plant_files():
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes() + b"\0")
    h.update(Path(slave_mod.__file__).read_bytes())
    return h.hexdigest()[:10]


def check_expressible(vehicle: Vehicle, prefix: str = "") -> None:
    """Raise :class:`FmuBuildError` if ``vehicle`` (with ``prefix``) cannot be an FMU.

    What the loader accepts but an FMU cannot carry: more than :data:`MAX_AXLES` axles,
    a name with characters XML 1.0 cannot represent, variable names that are not valid
    FMI structured names (a bad prefix), a plant signal without a unit/description.
    """
    if vehicle.n_axles > MAX_AXLES:
        raise FmuBuildError(
            f"axle_x: {vehicle.n_axles} axles is more than the FMU build's maximum of "
            f"{MAX_AXLES} (see fmu_build.build.MAX_AXLES for why)")
    if _XML_BAD.search(vehicle.name):
        raise FmuBuildError(f"name: {vehicle.name!r} contains control characters that an "
                            f"FMU's modelDescription.xml (XML 1.0) cannot represent")
    for v in vehicle.to_dict().values():  # defensive: the loader rejects these already
        if isinstance(v, float) and not math.isfinite(v):
            raise FmuBuildError("vehicle values must be finite")
    try:
        fmu_variables(vehicle, prefix, output_start=False)
    except VariableTableError as e:
        raise FmuBuildError(f"prefix {prefix!r}: {e}" if prefix else str(e)) from None


def _check_relative_imports(files: list[Path]) -> None:
    root = Path(plant_pkg.__file__).parent
    for p in files:
        if p.suffix == ".py" and _ABS_IMPORT.search(p.read_text()):
            raise FmuBuildError(
                f"plant/{p.relative_to(root)} imports 'msagv.plant' (or msagv) by absolute name; the "
                f"FMU bundles the package under another name, so plant must import itself relatively "
                f"(from . import ...)")


def _stage(src: Path, vehicle: Vehicle, prefix: str, initial: dict | None, h: str) -> tuple[Path, list[Path]]:
    pkg_name = f"msagv_plant_{h}"
    root = Path(plant_pkg.__file__).parent
    files = _plant_files()
    _check_relative_imports(files)
    pkg = src / pkg_name
    for p in files:
        dst = pkg / p.relative_to(root)
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(p, dst)
    table = fmu_variables(vehicle, prefix, initial=initial)
    cfg = {
        "format": CONFIG_FORMAT,
        "plant_package": pkg_name,
        "version": _version(),
        "description": (f"msagv plant: {vehicle.n_axles}-axle swerve-drive AGV "
                        f"'{vehicle.name}' with tire wear (FMI 2.0 co-simulation, pythonfmu)"),
        "prefix": prefix,
        "n_axles": vehicle.n_axles,
        "vehicle": vehicle.to_dict(),
        "units": UNITS,
        "step_size": CONTROL_PERIOD,  # the default experiment's communication step
        "variables": [v.to_json() for v in table],
    }
    cfg_path = src / CONFIG_FILE
    cfg_path.write_text(json.dumps(cfg, indent=1))
    script = src / f"msagv_slave_{h}.py"
    shutil.copyfile(slave_mod.__file__, script)
    return script, [pkg, cfg_path]


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("msagv")
    except Exception:
        return "0"


def build_fmu(out: str | Path, vehicle: Vehicle | None = None, *, prefix: str = "",
              initial: dict[str, float] | None = None,
              timeout: float = BUILD_TIMEOUT_S) -> Path:
    """Build the plant FMU for ``vehicle`` (default: the built-in paper vehicle) at ``out``.

    Parameters
    ----------
    out : path of the ``.fmu`` to write (its directory is created; an existing file is
        replaced only once the build has succeeded).
    prefix : put in front of every variable name (e.g. ``"agv0."`` or ``"agv_"``).
    initial : start values of the initial-state parameters, e.g. ``{"vx": 2.0}``.

    Returns the path written. Raises :class:`FmuBuildError` for a vehicle or prefix the
    FMU cannot express, or when pythonfmu fails (its output is quoted).
    """
    vehicle = vehicle or default_vehicle()
    out = Path(out)
    if out.suffix != ".fmu":
        raise FmuBuildError(f"output {out}: the file name must end in .fmu")
    check_expressible(vehicle, prefix)
    try:
        fmu_variables(vehicle, prefix, initial=initial, output_start=False)
    except VariableTableError as e:
        raise FmuBuildError(str(e)) from None
    h = code_hash()
    with tempfile.TemporaryDirectory(prefix="msagv-fmu-build-") as td:
        td = Path(td)
        src, dest = td / "src", td / "out"
        src.mkdir()
        try:
            script, project = _stage(src, vehicle, prefix, initial, h)
        except Exception as e:  # e.g. a PlantError for an initial state outside the limits
            if isinstance(e, FmuBuildError):
                raise
            raise FmuBuildError(f"initial: {e}") from None
        cmd = [sys.executable, "-m", "pythonfmu", "build", "-f", str(script), "-d", str(dest),
               "--handle-state", *[str(p) for p in project]]
        env = dict(os.environ, **{slave_mod.BUILD_ENV: f"msagv_plant_{h}"})
        try:
            r = subprocess.run(cmd, cwd=td, env=env, capture_output=True, text=True,
                               timeout=timeout)
        except subprocess.TimeoutExpired:
            raise FmuBuildError(f"pythonfmu build did not finish within {timeout:g} s") from None
        built = dest / f"{MODEL_NAME}.fmu"
        if r.returncode != 0 or not built.is_file():
            raise FmuBuildError(f"pythonfmu build failed (exit {r.returncode}):\n"
                                f"{r.stdout[-2000:]}{r.stderr[-4000:]}")
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(built), str(out))
    return out
