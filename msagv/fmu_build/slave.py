"""The msagv plant as an FMI 2.0 co-simulation slave (pythonfmu).

This file is copied into the FMU by :mod:`fmu_build.build` (under a name carrying a hash
of the code, so FMUs of different builds can share one Python process). It is a thin
:class:`pythonfmu.Fmi2Slave` that delegates to the bundled copy of the ``plant`` package
(``resources/msagv_plant_<hash>/``): no physics here.

Everything build-specific comes from ``resources/msagv_fmu.json``, written by the build:
the bundled package's name, the vehicle description and the variable table of
:func:`fmu_build.variables.fmu_variables` (names, roles, units, start values). The slave
imports only the standard library, pythonfmu and the bundled plant (numpy, numba).

Semantics:

* Parameters (vehicle values ``tunable``; initial state ``<state>_0`` and the integrator
  options ``fixed``) take effect at ``exitInitializationMode``, which builds the
  ``Plant``. A tunable vehicle value changed later takes effect at the next ``doStep``
  (a new ``Plant`` continues from the old one's state).
* Inputs are held over a step. Outputs follow the inputs at once (direct feedthrough:
  slips, forces and powers depend on the commands), as ``plant.Plant`` does.
* pythonfmu turns any Python exception into a fatal error that destroys the instance, so
  a rejected value (a negative or non-finite command, a fixed parameter set after
  initialization, a vehicle value the vehicle loader refuses) is logged at once and makes
  the next ``doStep`` fail (fmi2Discard/fmi2Error) with that message; the instance stays
  usable. Only a failing ``exitInitializationMode`` is fatal.
* numba: the plant's kernels are compiled with ``cache=True``, and numba keys its cache
  by the sources' directory and modification times, which are new in every fresh unpack
  of the FMU (fmpy unpacks into a new temporary directory each time). So the bundled
  package is imported from a copy kept under the user's cache directory
  (``$MSAGV_FMU_CACHE``, else ``$XDG_CACHE_HOME/msagv/fmu``, else ``~/.cache/msagv/fmu``),
  named by the build hash and made once: the first instantiation compiles (about 3 s),
  later ones, in any process and from any unpack, load the compiled kernels. Where that
  copy cannot be made, the package is imported from ``resources/``; if that cannot be
  written either (a read-only unpack directory) and ``NUMBA_CACHE_DIR`` is not set, the
  kernels cache into a fresh temporary directory, so the FMU still loads.
* A non-Python importer (the FMU's binary started Python: ``sys.orig_argv == []``):
  numba imports scipy when it is installed, and scipy's bundled libgfortran then aborts
  the importer at process exit ("free(): corrupted unsorted chunks") after pythonfmu has
  finalized the interpreter. The plant needs no BLAS, so in that case scipy is hidden from
  numba while the plant is imported and first compiled (numba then runs without BLAS),
  unless ``MSAGV_FMU_ALLOW_SCIPY=1``. In a Python host nothing is hidden; there the same
  libgfortran aborted the host at exit ("corrupted double-linked list", in its
  ``close_units``) in 30-50 % of fmpy runs that loaded the kernels from numba's cache
  (none when they were compiled, which imports all of ``scipy.linalg``; none in 50 runs
  whose host had imported ``scipy.linalg``). So in a Python host the slave imports
  ``scipy.linalg`` before the plant, when scipy is installed (none in 30 runs since;
  since then once in a CI run, none in 160 here: FMU.md, "numba inside the FMU").
"""

from __future__ import annotations

import atexit
import contextlib
import copy
import importlib
import json
import math
import os
import shutil
import sys
import tempfile
from pathlib import Path
from xml.etree.ElementTree import Element, SubElement

from pythonfmu import Fmi2Slave
from pythonfmu.default_experiment import DefaultExperiment
from pythonfmu.enums import Fmi2Causality, Fmi2Initial, Fmi2Status, Fmi2Variability
from pythonfmu.variables import Real, ScalarVariable

# the FMU's configuration file and format: fmu_build.variables.CONFIG_FILE/CONFIG_FORMAT (this
# script runs inside the FMU without the package, so it carries them; a test pins them)
CONFIG_FILE = "msagv_fmu.json"
CONFIG_FORMAT = 1
BUILD_ENV = "MSAGV_FMU_BUILDING"  # set by fmu_build.build to the bundled package's name


class _Real(Real):
    """A pythonfmu Real with a unit, whose start value is written exactly (``repr``).

    pythonfmu's own Real writes 16 significant digits, which does not round-trip every
    double; an importer that sets parameters from their start values would then run a
    slightly different vehicle.
    """

    def __init__(self, name: str, unit: str | None = None, **kwargs):
        super().__init__(name, **kwargs)
        self.unit = unit

    def to_xml(self) -> Element:
        parent = ScalarVariable.to_xml(self)
        attrib = {}
        if self.start is not None:
            attrib["start"] = repr(float(self.start))
        if self.unit:
            attrib["unit"] = self.unit
        SubElement(parent, "Real", attrib)
        return parent


def _cache_writable(pkg_dir: Path) -> bool:
    """Whether numba can cache next to the bundled sources (the test numba itself does)."""
    try:
        cache = pkg_dir / "__pycache__"
        cache.mkdir(exist_ok=True)
        tempfile.TemporaryFile(dir=cache).close()
        return True
    except OSError:
        return False


def _package_digest(pkg: Path) -> str:
    """SHA-256 over the package's files (paths and contents; ``__pycache__`` excluded)."""
    import hashlib

    h = hashlib.sha256()
    for f in sorted(p for p in pkg.rglob("*") if p.is_file() and "__pycache__" not in p.parts):
        h.update(f.relative_to(pkg).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def _stable_copy(name: str, resources: Path) -> Path | None:
    """The directory holding a kept copy of the bundled package ``name`` (made from
    ``resources/name`` if missing or different), or None where none can be made."""
    base = os.environ.get("MSAGV_FMU_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
        "msagv", "fmu")
    root = Path(base) / name
    try:
        src = resources / name
        want = _package_digest(src)
        if (root / name).is_dir() and _package_digest(root / name) == want \
                and _cache_writable(root / name):
            os.utime(root)  # in use: kept by the pruning below
            return root
        root.parent.mkdir(parents=True, exist_ok=True)
        _prune(root.parent)
        tmp = Path(tempfile.mkdtemp(prefix=f".{name}-", dir=root.parent))
        shutil.copytree(src, tmp / name, ignore=shutil.ignore_patterns("__pycache__"))
        if root.exists():  # a damaged or different copy: set it aside, atomically
            shutil.rmtree(root.rename(root.with_name(f".{name}-old-{os.getpid()}")), True)
        try:
            tmp.rename(root)
        except OSError:  # another process made it meanwhile
            shutil.rmtree(tmp, True)
        ok = (root / name).is_dir() and _package_digest(root / name) == want
        return root if ok and _cache_writable(root / name) else None
    except OSError:
        return None


KEEP_DAYS = 30  # copies of other builds unused this long are removed


def _prune(cache: Path) -> None:
    """Remove the copies of builds not instantiated for KEEP_DAYS (each use touches its
    directory), and leftovers of interrupted copies."""
    import time

    old = time.time() - KEEP_DAYS * 86400
    for d in cache.iterdir():
        try:
            if d.name.startswith(("msagv_plant_", ".msagv_plant_")) and d.stat().st_mtime < old:
                shutil.rmtree(d, True)
        except OSError:
            pass


def _import_plant(name: str, resources: Path):
    """Import the bundled plant package, with a usable numba cache location."""
    if name in sys.modules:
        return sys.modules[name]
    root = _stable_copy(name, resources)
    if root is not None:
        sys.path.insert(0, str(root))
        try:
            return importlib.import_module(name)
        finally:
            sys.path.remove(str(root))
    if _cache_writable(resources / name):
        return importlib.import_module(name)
    from numba.core import config as numba_config

    if numba_config.CACHE_DIR:  # the user chose a cache directory: numba uses it
        return importlib.import_module(name)
    # The locator of a cached function is chosen when it is decorated (at import), so
    # redirecting the cache only during this import leaves the host's own numba
    # functions alone.
    tmp = tempfile.mkdtemp(prefix="msagv-fmu-numba-")
    atexit.register(shutil.rmtree, tmp, True)
    old = numba_config.CACHE_DIR
    numba_config.CACHE_DIR = tmp
    try:
        return importlib.import_module(name)
    finally:
        numba_config.CACHE_DIR = old


def _embedded() -> bool:
    """Whether Python was started by the FMU's binary (a non-Python importer)."""
    return getattr(sys, "orig_argv", None) == []


@contextlib.contextmanager
def _scipy_hidden_if_embedded():
    """Hide scipy from numba in an interpreter the FMU started (see the module doc)."""
    hide = (_embedded() and "numba" not in sys.modules and "scipy" not in sys.modules
            and os.environ.get("MSAGV_FMU_ALLOW_SCIPY") != "1")
    if hide:
        sys.modules["scipy"] = None  # import scipy -> ImportError: numba goes without it
    elif not _embedded():
        try:  # all of scipy.linalg, before numba loads cached kernels (see the module doc)
            importlib.import_module("scipy.linalg")
        except ImportError:
            pass
    try:
        yield
    finally:
        if hide and sys.modules.get("scipy", 0) is None:
            del sys.modules["scipy"]


class MsagvPlant(Fmi2Slave):
    """The stepping plant (``plant.Plant``) behind the FMI 2.0 co-simulation interface."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        res = Path(self.resources)
        cfg = json.loads((res / CONFIG_FILE).read_text())
        if cfg.get("format") != CONFIG_FORMAT:
            raise RuntimeError(f"{CONFIG_FILE}: unsupported format {cfg.get('format')!r}")
        self._cfg = cfg
        # pythonfmu instantiates the slave once while building, to write the model
        # description: import the bundled plant then (a missing module fails the build),
        # but take the outputs' start values from the table (the native plant's) instead
        # of compiling the kernels
        building = os.environ.get(BUILD_ENV) == cfg["plant_package"]
        with _scipy_hidden_if_embedded():
            self._pk = _import_plant(cfg["plant_package"], res)
            vehicle = self._pk.vehicle_from_dict(cfg["vehicle"])
            if not building:
                # compile every kernel now, not in the first doStep (numba picks BLAS here)
                warm = self._pk.Plant(vehicle)
                warm.do_step(0.0, 1e-3)
        self.author = "msagv"
        self.version = cfg.get("version")
        self.description = cfg["description"]
        self.default_experiment = DefaultExperiment(start_time=0.0, stop_time=10.0,
                                                    step_size=cfg["step_size"])
        self._table = cfg["variables"]
        self._par: dict[str, float] = {}
        self._par_role: dict[str, dict] = {}
        self._u_names: list[str] = []
        self._u: list[float] = []
        self._u_is_wheel: list[bool] = []
        self._out_keys: list[str] = []
        self._out_start: list[float] = []
        self._bad_inputs: dict[int, str] = {}
        self._pending: list[str] = []
        self._inputs_dirty = True
        self._vehicle_dirty = False
        self._initialized = False
        self._start_time = 0.0
        for v in self._table:
            self._register(v)
        if building:
            self._plant = None
            self._y = list(self._out_start)
            self._inputs_dirty = False
            return
        self._plant = self._make_plant()
        self._out_index = [self._plant.signal_names.index(k) for k in self._out_keys]
        self._y = [0.0] * len(self._out_keys)
        self._apply_inputs()

    # ---- registration --------------------------------------------------------------
    def _register(self, v: dict) -> None:
        name, role = v["name"], v["role"]
        initial = Fmi2Initial[v["initial"]] if v["initial"] else None
        kw = dict(causality=Fmi2Causality[v["causality"]],
                  variability=Fmi2Variability[v["variability"]], initial=initial,
                  description=v["description"], unit=v["unit"])
        if role == "input":
            i = len(self._u)
            self._u.append(float(v["start"]))
            self._u_names.append(name)
            self._u_is_wheel.append(v["key"].startswith("omega_w_"))
            var = _Real(name, start=v["start"], getter=lambda i=i: self._u[i],
                        setter=lambda x, i=i: self._set_input(i, x), **kw)
        elif role == "output":
            j = len(self._out_keys)
            self._out_keys.append(v["key"])
            self._out_start.append(float(v["start"]))
            var = _Real(name, getter=lambda j=j: self._output(j),
                        setter=lambda x, n=name: self._reject(f"{n} is an output; not set"),
                        **kw)
        else:
            self._par[name] = float(v["start"])
            self._par_role[name] = v
            var = _Real(name, start=v["start"], getter=lambda n=name: self._par[n],
                        setter=lambda x, n=name: self._set_param(n, x), **kw)
        self.register_variable(var, nested=False)

    def to_xml(self, model_options=None) -> Element:
        root = super().to_xml(model_options or {})
        used = sorted({v["unit"] for v in self._table if v["unit"]})
        units = Element("UnitDefinitions")
        for u in used:
            unit = SubElement(units, "Unit", {"name": u})
            SubElement(unit, "BaseUnit", {k: str(e) for k, e in self._cfg["units"][u].items()})
        pos = [i for i, child in enumerate(root) if child.tag == "CoSimulation"][0] + 1
        root.insert(pos, units)
        return root

    # ---- values in ------------------------------------------------------------------
    def _reject(self, msg: str) -> None:
        self.log(msg, Fmi2Status.error)
        self._pending.append(msg)

    def _set_input(self, i: int, x: float) -> None:
        x = float(x)
        self._u[i] = x
        self._inputs_dirty = True
        if not math.isfinite(x):
            self._bad_inputs[i] = f"input {self._u_names[i]} must be finite, got {x}"
        elif self._u_is_wheel[i] and x < 0:
            self._bad_inputs[i] = f"input {self._u_names[i]} must be >= 0, got {x}"
        else:
            self._bad_inputs.pop(i, None)
            return
        self.log(self._bad_inputs[i], Fmi2Status.error)

    def _set_param(self, name: str, x: float) -> None:
        x = float(x)
        role = self._par_role[name]
        if not math.isfinite(x):
            return self._reject(f"parameter {name} must be finite, got {x}; not set")
        if self._initialized and role["variability"] != "tunable":
            return self._reject(f"parameter {name} is fixed: it can only be set before "
                                f"exitInitializationMode; not set")
        self._par[name] = x
        if role["role"] == "vehicle":
            self._vehicle_dirty = True

    # ---- the plant -------------------------------------------------------------------
    def _make_plant(self):
        vd = copy.deepcopy(self._cfg["vehicle"])
        initial, opts = {}, {}
        for name, v in self._par_role.items():
            if v["role"] == "vehicle":
                node = vd
                for p in v["path"][:-1]:
                    node = node[p]
                node[v["path"][-1]] = self._par[name]
            elif v["role"] == "initial":
                initial[v["key"]] = self._par[name]
            else:
                opts[v["key"]] = self._par[name]
        vehicle = self._pk.vehicle_from_dict(vd)
        return self._pk.Plant(vehicle, initial=initial, **opts)

    def _apply_inputs(self) -> None:
        if self._bad_inputs:
            return  # keep the outputs of the last accepted commands
        nw = len(self._u) // 2
        self._plant.set_inputs(self._u[:nw], self._u[nw:])
        self._refresh()
        self._inputs_dirty = False

    def _refresh(self) -> None:
        y = self._plant.output_vector().tolist()
        self._y = [y[k] for k in self._out_index]

    def _output(self, j: int) -> float:
        if self._inputs_dirty:
            self._apply_inputs()
        return self._y[j]

    # ---- FMI ------------------------------------------------------------------------
    def setup_experiment(self, start_time: float, stop_time=None, tolerance=None):
        self._start_time = float(start_time)

    def exit_initialization_mode(self):
        try:
            self._plant = self._make_plant()
        except Exception as e:  # the vehicle loader's or plant's message names the field
            self.log(f"exitInitializationMode: parameters rejected: {e}", Fmi2Status.error)
            raise
        self._vehicle_dirty = False
        self._initialized = True
        self._inputs_dirty = True
        self._apply_inputs()

    # ---- FMU state (canGetAndSetFMUstate: fmi2GetFMUstate / fmi2SetFMUstate) ------------
    def _get_fmu_state(self):
        """The whole instance state, held as Python objects by pythonfmu's wrapper: the
        plant (with a snapshot of its integrator state), inputs, parameters, flags."""
        return {"plant": self._plant,
                "snapshot": None if self._plant is None else self._plant.get_state(),
                "u": list(self._u), "par": dict(self._par), "bad": dict(self._bad_inputs),
                "pending": list(self._pending), "y": list(self._y),
                "flags": (self._inputs_dirty, self._vehicle_dirty, self._initialized,
                          self._start_time)}

    def _set_fmu_state(self, state) -> None:
        self._plant = state["plant"]
        if self._plant is not None:
            self._plant.set_state(state["snapshot"])
        self._u = list(state["u"])
        self._par = dict(state["par"])
        self._bad_inputs = dict(state["bad"])
        self._pending = list(state["pending"])
        self._y = list(state["y"])
        (self._inputs_dirty, self._vehicle_dirty, self._initialized,
         self._start_time) = state["flags"]

    def do_step(self, current_time: float, step_size: float) -> bool:
        try:
            if self._pending:
                msg = "; ".join(self._pending)
                self._pending.clear()
                raise ValueError(msg)
            if self._bad_inputs:
                raise ValueError("; ".join(self._bad_inputs.values()))
            if self._vehicle_dirty:
                new = self._make_plant()  # raises (plant unchanged) for a bad value
                new.set_state(self._plant.get_state())
                self._plant = new
                self._vehicle_dirty = False
                self._inputs_dirty = True
            if self._inputs_dirty:
                self._apply_inputs()
            self._plant.do_step(current_time - self._start_time, step_size)
            self._refresh()
            return True
        except Exception as e:
            self.log(f"doStep at t = {current_time}: {e}", Fmi2Status.error)
            return False
