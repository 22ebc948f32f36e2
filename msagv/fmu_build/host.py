"""Host an FMI 2.0 co-simulation FMU behind the interface of :class:`plant.Plant`.

:class:`FmuPlant` loads any co-simulation FMU with fmpy's ``FMU2Slave`` and offers what the
closed loop and the Zenoh bridge use of a ``Plant``: ``vehicle``, ``t``,
``set_inputs(omega_w, omega_s)``, ``do_step(t, h)``, ``outputs()``, ``state_message()``,
``reset(initial=None)``, plus ``close()``. So the controller runs unchanged against our
plant FMU or against another vendor's vehicle FMU.

Names. The host speaks our FMU's variable names (``docs/FMU.md``): inputs ``omega_w_ij``,
``omega_s_ij``; outputs ``x, y, phi, vx, vy, r, delta_ij, omega_w_act_ij, ..., W_tw``;
parameters ``mass, ...``, ``<state>_0``, ``rtol``. An FMU whose names differ is used
through a mapping (a dict, or a TOML file given to ``msagv fmu ... --map FILE``)::

    # our name = "the FMU's name"
    prefix = "agv_"           # optional: the FMU's name of every name not in [map]
    [map]
    x = "body.pos_x"
    omega_w_11 = "wheel_fl.speed_cmd"

Required: every input, and the outputs ``x y phi vx vy r delta_ij``. Everything else is
optional: a signal the FMU lacks is missing from ``outputs()``; ``state_message()`` then
reports the held (saturated) wheel-speed command for ``omega_w`` and leaves out the wear
fields; a parameter the FMU lacks cannot be set (asking to is an error).
"""

from __future__ import annotations

import json
import math
import shutil
import tomllib
import zipfile
from collections import deque
from ctypes import byref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from msagv.plant.interface import PlantError, check_inputs, check_step, saturate, state_message
from msagv.plant.signals import BODY_FIELDS, WEAR_FIELDS, signal_names, state_names
from msagv.plant.vehicle import Vehicle, vehicle_from_dict

from .variables import CONFIG_FILE, fmu_variables, set_path, vehicle_paths

REQUIRED_OUTPUTS = BODY_FIELDS  # plus delta_ij of every wheel


class FmuHostError(RuntimeError):
    """The FMU cannot be hosted as a plant (not FMI 2.0 co-simulation, a variable missing
    or of the wrong kind, a bad mapping, a failed initialization). The message says which."""


@dataclass(frozen=True)
class NameMap:
    """Our variable names -> the FMU's: ``table`` first, else ``prefix + name``."""

    table: dict[str, str] = field(default_factory=dict)
    prefix: str = ""
    source: str = "mapping"

    def their(self, our: str) -> str:
        return self.table.get(our, self.prefix + our)


def load_mapping(path: str | Path) -> NameMap:
    """Read a mapping file (TOML: optional ``prefix = "..."``, table ``[map]`` of
    ``our_name = "their_name"``). Raises :class:`FmuHostError` naming the problem."""
    p = Path(path)
    if not p.is_file():
        raise FmuHostError(f"mapping file not found: {p}")
    try:
        d = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise FmuHostError(f"{p}: not valid TOML: {e}") from None
    return mapping_from_dict(d, source=str(p))


def mapping_from_dict(d: Mapping[str, Any], source: str = "mapping") -> NameMap:
    unknown = sorted(set(d) - {"map", "prefix"})
    if unknown:
        raise FmuHostError(f"{source}: unknown key '{unknown[0]}' (expected 'prefix' and a "
                           f"[map] table)")
    prefix = d.get("prefix", "")
    if not isinstance(prefix, str):
        raise FmuHostError(f"{source}: prefix must be a string")
    table = d.get("map", {})
    if not isinstance(table, Mapping):
        raise FmuHostError(f"{source}: [map] must be a table of our_name = \"their_name\"")
    for k, v in table.items():
        if not isinstance(v, str) or not v:
            raise FmuHostError(f"{source}: map.{k}: expected the FMU's variable name as a "
                               f"non-empty string, got {v!r}")
    return NameMap(dict(table), prefix, source)


def read_fmu_config(fmu_path: str | Path) -> dict | None:
    """The msagv build configuration inside an FMU (vehicle, variable table), or None
    for an FMU not built by ``msagv fmu build``."""
    try:
        with zipfile.ZipFile(fmu_path) as z:
            return json.loads(z.read(f"resources/{CONFIG_FILE}"))
    except KeyError:
        return None
    except zipfile.BadZipFile:
        raise FmuHostError(f"{fmu_path}: not an FMU (not a zip archive)") from None


@dataclass(frozen=True)
class FmuSnapshot:
    """A saved FMU state (:meth:`FmuPlant.get_state`), valid for the instance that took it."""

    owner: Any
    handle: Any
    t: float
    omega_w: np.ndarray
    omega_s: np.ndarray


class _LogRouter:
    """Every FMU message of this process's hosts to the log of the instance that sent it.

    fmpy formats an FMU's printf-style messages in a native proxy (``fmpy.logging``) that
    calls one logger for the whole process: the one last given to ``addLoggerProxy``. A host
    that gave it a logger of its own would get every other instance's messages, and once
    its logger is gone (the host collected) the next message from any instance would call
    freed memory. So the logger given to the proxy is this router's, made once and kept for
    the process; it sends a message to the log its ``componentEnvironment`` names, and one
    from an instance of somebody else's (fmpy's default callbacks have none) to fmpy's own
    printer, as fmpy would have. Code that gives the proxy another logger afterwards
    (``fmpy.simulate_fmu`` with a logger) is undone before each call of a host's instance
    (:class:`_Routed`)."""

    def __init__(self):
        self._logs: dict[int, deque] = {}
        self._next = 1
        self._logger = None  # the ctypes callback, made on first use, never freed
        self._arg = None
        self._add_proxy = None  # fmpy.logging.addLoggerProxy, found on first use (or none)

    def open(self, log: deque) -> int:
        env, self._next = self._next, self._next + 1
        self._logs[env] = log
        return env

    def close(self, env: int | None) -> None:
        self._logs.pop(env, None)

    def _route(self, env, instance, status, category, message) -> None:
        log = self._logs.get(env or 0)
        if log is None:
            from fmpy.fmi2 import printLogMessage

            printLogMessage(env, instance, status, category, message)
            return
        label = ["ok", "warning", "discard", "error", "fatal", "pending"][status] \
            if 0 <= status <= 5 else str(status)
        log.append(f"[{label}] {(message or b'').decode('utf-8', 'replace').strip()}")

    def attach(self, cb) -> None:
        """``cb``'s logger: the proxy, which calls this router."""
        from fmpy.fmi2 import fmi2CallbackFunctions, fmi2CallbackLoggerTYPE

        if self._logger is None:
            self._logger = fmi2CallbackLoggerTYPE(self._route)
            self._arg = fmi2CallbackFunctions()
            try:
                from fmpy.logging import addLoggerProxy

                self._add_proxy = addLoggerProxy
            except Exception:  # no proxy (fmpy without its native logging): cb.logger is ours
                pass
        cb.logger = self._logger
        self.claim(cb)

    def claim(self, cb=None) -> None:
        """Make the proxy call this router (again): before every call of a host's instance,
        so looked up once (:meth:`attach`), not here."""
        if self._add_proxy is None:
            return
        if cb is None:
            cb = self._arg
            cb.logger = self._logger  # (the proxy swapped it for itself last time)
        self._add_proxy(byref(cb))


_ROUTER = _LogRouter()


class _Routed:
    """An fmpy instance whose every call first has the proxy call the router."""

    def __init__(self, fmu):
        self._fmu = fmu

    def __getattr__(self, name):
        attr = getattr(self._fmu, name)
        if not callable(attr):
            return attr

        def call(*args, **kwargs):
            _ROUTER.claim()
            return attr(*args, **kwargs)
        return call


class FmuPlant:
    """An FMU stepped by fmpy, with the interface of :class:`plant.Plant`.

    Parameters
    ----------
    fmu_path : an FMI 2.0 co-simulation FMU.
    vehicle : the vehicle the FMU simulates. Default: for an FMU built by
        ``msagv fmu build``, the vehicle inside it (with ``parameters`` applied); other
        FMUs need it given (the controller needs the geometry and limits).
    mapping : a :class:`NameMap`, a dict in the file's layout, or a path to a mapping file.
    parameters : values of FMU parameters by our name (``mass``, ``tire_lateral_mu``,
        ``rtol``, ...), set before initialization.
    initial : initial state by signal name (``x, y, phi, vx, vy, r, delta_ij``), set as the
        parameters ``<state>_0``; others keep the FMU's start values.
    instance_name : the FMI instance name.
    unpack_dir : where to unpack the FMU (default: a temporary directory, removed by
        :meth:`close`). A fixed directory lets numba reuse its compiled kernels across runs.
    """

    def __init__(self, fmu_path: str | Path, vehicle: Vehicle | None = None, *,
                 mapping: NameMap | Mapping | str | Path | None = None,
                 parameters: Mapping[str, float] | None = None,
                 initial: Mapping[str, float] | None = None,
                 instance_name: str = "plant", unpack_dir: str | Path | None = None):
        from fmpy import read_model_description

        self.path = Path(fmu_path)
        if not self.path.is_file():
            raise FmuHostError(f"FMU not found: {self.path}")
        try:
            md = read_model_description(str(self.path))
        except Exception as e:
            raise FmuHostError(f"{self.path}: cannot read modelDescription.xml: {e}") from None
        if md.fmiVersion != "2.0" or md.coSimulation is None:
            raise FmuHostError(f"{self.path}: not an FMI 2.0 co-simulation FMU "
                               f"(fmiVersion {md.fmiVersion})")
        self.model_description = md
        self.names = self._as_map(mapping)
        self._config = read_fmu_config(self.path)
        self._params = {k: float(v) for k, v in (parameters or {}).items()}
        self.vehicle = self._resolve_vehicle(vehicle)
        self._table = {v.name: v for v in fmu_variables(self.vehicle, output_start=False)}
        self._resolve_variables(md)
        self._check_parameters(self._params)
        self._initial: dict[str, float] = {}
        if initial:
            self._initial = self._check_initial(initial)
        self._log: deque[str] = deque(maxlen=50)
        self._own_dir = unpack_dir is None
        self._unzip = self._unpack(unpack_dir)
        self._fmu = None
        self._env: int | None = None  # this instance's key in _ROUTER
        self.t = 0.0
        try:
            self._instantiate(instance_name)
            self._initialize()
        except BaseException:
            self.close()
            raise

    # ---- set-up ----------------------------------------------------------------------
    @staticmethod
    def _as_map(mapping) -> NameMap:
        if mapping is None:
            return NameMap(source="no mapping")
        if isinstance(mapping, NameMap):
            return mapping
        if isinstance(mapping, (str, Path)):
            return load_mapping(mapping)
        return mapping_from_dict(mapping)

    def _resolve_vehicle(self, vehicle: Vehicle | None) -> Vehicle:
        """The FMU's vehicle (ours: from its resources) with ``parameters`` applied."""
        cfg = self._config
        if vehicle is None:
            if cfg is None:
                raise FmuHostError(
                    f"{self.path.name} was not built by msagv fmu build (no resources/"
                    f"{CONFIG_FILE}): pass the vehicle it simulates (vehicle=..., --vehicle FILE)")
            vehicle = vehicle_from_dict(cfg["vehicle"])
        elif cfg is not None and cfg.get("n_axles") != vehicle.n_axles:
            raise FmuHostError(f"{self.path.name} simulates {cfg.get('n_axles')} axles, the "
                               f"vehicle given has {vehicle.n_axles}")
        paths = {name: path for name, path, _, _ in vehicle_paths(vehicle)}
        over = {k: v for k, v in self._params.items() if k in paths}
        if not over:
            return vehicle
        vd = vehicle.to_dict()
        for k, val in over.items():
            set_path(vd, paths[k], val)
        return vehicle_from_dict(vd)  # VehicleError names a bad value before the FMU sees it

    def _find(self, our: str, byname: dict, required: bool, what: str):
        their = self.names.their(our)
        v = byname.get(their)
        if v is None:
            if our in self.names.table:
                raise FmuHostError(
                    f"{self.names.source}: {our} -> '{their}': {self.path.name} has no "
                    f"variable '{their}'")
            if required:
                raise FmuHostError(
                    f"{self.path.name} has no variable '{their}' ({what}, required); map it "
                    f"in a mapping file: [map] {our} = \"<the FMU's name>\"")
            return None
        if v.type != "Real":
            raise FmuHostError(f"{self.path.name}: variable '{their}' (our {our}) is "
                               f"{v.type}, expected Real")
        return v

    def _resolve_variables(self, md) -> None:
        byname = {v.name: v for v in md.modelVariables}
        unknown = sorted(set(self.names.table) - set(self._table))
        if unknown:
            raise FmuHostError(
                f"{self.names.source}: '{unknown[0]}' is not one of our variable names "
                f"(see docs/FMU.md; e.g. x, omega_w_11, omega_w_act_11, mass, x_0)")
        nw = self.vehicle.n_wheels
        required_out = set(REQUIRED_OUTPUTS) | {f"delta_{w}" for w in self.vehicle.wheel_names}
        self._in_vr: list[int] = []
        self._out_vr: list[int] = []
        self._out_sig: list[str] = []
        self._par_vr: dict[str, int] = {}
        for name, v in self._table.items():
            if v.role == "input":
                mv = self._find(name, byname, True, v.description)
                if mv.causality != "input":
                    raise FmuHostError(f"{self.path.name}: '{mv.name}' (our input {name}) has "
                                       f"causality {mv.causality}, expected input")
                self._in_vr.append(mv.valueReference)
            elif v.role == "output":
                mv = self._find(name, byname, v.key in required_out, v.description)
                if mv is None:
                    continue
                if mv.causality not in ("output", "local"):
                    raise FmuHostError(f"{self.path.name}: '{mv.name}' (our output {name}) "
                                       f"has causality {mv.causality}, expected output")
                self._out_vr.append(mv.valueReference)
                self._out_sig.append(v.key)
            else:
                mv = self._find(name, byname, False, v.description)
                if mv is not None and mv.causality == "parameter":
                    self._par_vr[name] = mv.valueReference
        assert len(self._in_vr) == 2 * nw
        self._has = set(self._out_sig)
        self._out_index = {s: i for i, s in enumerate(self._out_sig)}

    def _check_parameters(self, params: Mapping[str, float]) -> None:
        for k, v in params.items():
            if k not in self._table or self._table[k].role in ("input", "output"):
                raise FmuHostError(f"parameters: '{k}' is not one of our parameter names "
                                   f"(see docs/FMU.md)")
            if k not in self._par_vr:
                raise FmuHostError(f"parameters: {self.path.name} has no parameter "
                                   f"'{self.names.their(k)}' (our {k})")
            if not math.isfinite(v):
                raise FmuHostError(f"parameters: {k} must be finite, got {v}")

    def _check_initial(self, initial: Mapping[str, float]) -> dict[str, float]:
        allowed = state_names(self.vehicle)
        out = {}
        for k, v in initial.items():
            if k not in allowed:
                raise PlantError(f"initial: unknown signal '{k}' (settable: {', '.join(allowed)})")
            v = float(v)
            if not math.isfinite(v):
                raise PlantError(f"initial: {k} must be finite, got {v}")
            if f"{k}_0" not in self._par_vr:
                raise FmuHostError(f"initial: {self.path.name} has no parameter "
                                   f"'{self.names.their(k + '_0')}' for the initial {k}")
            out[k] = v
        lim = self.vehicle.limits
        for w in self.vehicle.wheel_names:
            d = out.get(f"delta_{w}", 0.0)
            if not lim.delta_min <= d <= lim.delta_max:
                raise PlantError(f"initial: delta_{w} = {d} outside the steering limits "
                                 f"[{lim.delta_min}, {lim.delta_max}]")
            if out.get(f"omega_w_{w}", 0.0) < 0:
                raise PlantError(f"initial: omega_w_{w} must be >= 0")
        return out

    def _unpack(self, unpack_dir) -> Path:
        from fmpy import extract

        if unpack_dir is not None:
            d = Path(unpack_dir)
            try:  # the same FMU already unpacked there: reuse (keeps numba's cache valid)
                from fmpy import read_model_description

                if read_model_description(str(d)).guid == self.model_description.guid:
                    return d
            except Exception:
                pass
            d.mkdir(parents=True, exist_ok=True)
            return Path(extract(str(self.path), str(d)))
        return Path(extract(str(self.path)))

    def _instantiate(self, instance_name: str) -> None:
        from fmpy.fmi2 import (FMU2Slave, fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFunctions,
                               fmi2CallbackFreeMemoryTYPE)
        from fmpy import calloc, free

        # the FMU hands componentEnvironment back with every message: this instance's key
        # in the process-wide router (see _LogRouter)
        self._env = _ROUTER.open(self._log)
        cb = fmi2CallbackFunctions()
        cb.componentEnvironment = self._env
        cb.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
        cb.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
        _ROUTER.attach(cb)
        self._callbacks = cb  # the FMU keeps a pointer to it (pythonfmu does) until freed
        md = self.model_description
        fmu = FMU2Slave(guid=md.guid, unzipDirectory=str(self._unzip),
                        modelIdentifier=md.coSimulation.modelIdentifier,
                        instanceName=instance_name)
        try:
            fmu.instantiate(loggingOn=True, callbacks=cb)
        except Exception as e:
            self._cleanup_dir()
            _ROUTER.close(self._env)
            raise FmuHostError(f"{self.path.name}: instantiation failed: {e}{self._log_tail()}") from None
        self._fmu = _Routed(fmu)

    def _initialize(self) -> None:
        fmu = self._fmu
        values = dict(self._params)
        values.update({f"{k}_0": v for k, v in self._initial.items()})
        try:
            fmu.setupExperiment(startTime=0.0)
            fmu.enterInitializationMode()
            if values:
                fmu.setReal([self._par_vr[k] for k in values], list(values.values()))
            fmu.exitInitializationMode()
        except Exception as e:
            raise FmuHostError(f"{self.path.name}: initialization failed: {e}{self._log_tail()}") from None
        self.t = 0.0
        lim = self.vehicle.limits
        self._u_w = np.minimum(np.array([self._initial.get(f"omega_w_{w}", 0.0)
                                         for w in self.vehicle.wheel_names]), lim.omega_w_max)
        self._u_s = np.zeros(self.vehicle.n_wheels)
        self._y: list[float] | None = None

    def _log_tail(self, n: int = 8) -> str:
        if not self._log:
            return ""
        return "\nFMU log:\n  " + "\n  ".join(list(self._log)[-n:])

    # ---- the Plant interface -----------------------------------------------------------
    def set_inputs(self, omega_w, omega_s) -> None:
        """Set the held commands (shape (2n,) each); same checks as ``Plant.set_inputs``."""
        w, s = check_inputs(self.vehicle, omega_w, omega_s)
        try:
            self._fmu.setReal(self._in_vr, w.tolist() + s.tolist())
        except Exception as e:
            raise PlantError(f"inputs: the FMU refused them: {e}{self._log_tail()}") from None
        self._u_w, self._u_s = saturate(self.vehicle, w, s)
        self._y = None

    @property
    def inputs(self) -> tuple[np.ndarray, np.ndarray]:
        return self._u_w.copy(), self._u_s.copy()

    def do_step(self, t: float, h: float) -> None:
        """Advance from ``t`` (must equal :attr:`t`) by ``h`` > 0 seconds."""
        check_step(self.t, t, h)
        try:
            self._fmu.doStep(currentCommunicationPoint=self.t, communicationStepSize=h)
        except Exception as e:
            raise PlantError(f"do_step: the FMU failed at t = {self.t}: {e}{self._log_tail()}") from None
        self.t = self.t + h
        self._y = None

    def _values(self) -> list[float]:
        if self._y is None:
            self._y = self._fmu.getReal(self._out_vr)
        return self._y

    @property
    def signal_names(self) -> list[str]:
        """Our names of the signals this FMU provides, in ``plant.signal_names`` order."""
        return [s for s in signal_names(self.vehicle) if s in self._has]

    def outputs(self) -> dict[str, float]:
        """Every signal the FMU provides, by our signal name (``omega_w_ij`` is the actual
        wheel speed, as in ``Plant.outputs``)."""
        y = self._values()
        return {s: y[self._out_index[s]] for s in self.signal_names}

    def get(self, name: str) -> float:
        if name not in self._out_index:
            raise PlantError(f"unknown signal '{name}'")
        return self._values()[self._out_index[name]]

    def state_message(self) -> dict:
        """DESIGN.md's ``state`` fields (without ``v``/``seq``), like ``Plant.state_message``."""
        y, ix = self._values(), self._out_index
        w = self.vehicle.wheel_names
        omega_w = ([y[ix[f"omega_w_{k}"]] for k in w] if all(f"omega_w_{k}" in ix for k in w)
                   else self._u_w)
        wear = None
        if all(k in ix for k in WEAR_FIELDS):
            wear = [y[ix[k]] for k in WEAR_FIELDS]
        per_wheel = [[f"{q}_{k}" for k in w] for q in WEAR_FIELDS]
        wheel_wear = None  # each wheel's wear work, when the FMU has every such output
        if all(n in ix for row in per_wheel for n in row):
            wheel_wear = [[y[ix[n]] for n in row] for row in per_wheel]
        return state_message(self.t, [y[ix[k]] for k in REQUIRED_OUTPUTS],
                             [y[ix[f"delta_{k}"]] for k in w], omega_w, wear, wheel_wear)

    def get_state(self) -> "FmuSnapshot":
        """A snapshot of the FMU's whole state (fmi2GetFMUstate) with the host's time and
        held inputs; :class:`PlantError` if the FMU cannot save its state."""
        if not getattr(self.model_description.coSimulation, "canGetAndSetFMUstate", False):
            raise PlantError(f"get_state: {self.path.name} cannot save its state "
                             f"(canGetAndSetFMUstate is false)")
        try:
            handle = self._fmu.getFMUState()
        except Exception as e:
            raise PlantError(f"get_state: the FMU failed: {e}{self._log_tail()}") from None
        return FmuSnapshot(self, handle, self.t, self._u_w.copy(), self._u_s.copy())

    def set_state(self, snap: "FmuSnapshot") -> None:
        """Restore a snapshot of this instance (fmi2SetFMUstate)."""
        if not isinstance(snap, FmuSnapshot) or snap.owner is not self:
            raise PlantError("set_state: snapshot does not belong to this FMU instance")
        try:
            self._fmu.setFMUState(snap.handle)
        except Exception as e:
            raise PlantError(f"set_state: the FMU failed: {e}{self._log_tail()}") from None
        self.t = snap.t
        self._u_w, self._u_s = snap.omega_w.copy(), snap.omega_s.copy()
        self._y = None

    def reset(self, initial: Mapping[str, float] | None = None) -> None:
        """Back to t = 0 at the initial state (the constructor's, or ``initial``)."""
        if initial is not None:
            self._initial = self._check_initial(initial)
        try:
            self._fmu.reset()
        except Exception as e:
            raise FmuHostError(f"{self.path.name}: reset failed: {e}{self._log_tail()}") from None
        self._initialize()

    @property
    def log(self) -> list[str]:
        """The FMU's most recent log messages."""
        return list(self._log)

    def warmup(self) -> None:
        """Nothing to prepare: the FMU is instantiated and initialised by the constructor
        (:class:`plant.interface.PlantInterface`)."""

    def close(self) -> None:
        """Terminate and free the FMU instance and remove its unpack directory."""
        fmu, self._fmu = self._fmu, None
        if fmu is not None:
            try:
                fmu.terminate()
            except Exception:
                pass
            try:
                fmu.freeInstance()
            except Exception:
                pass
            _ROUTER.close(self._env)
        self._cleanup_dir()

    def _cleanup_dir(self) -> None:
        if self._own_dir and self._unzip is not None:
            shutil.rmtree(self._unzip, ignore_errors=True)
            self._unzip = None

    def __enter__(self) -> "FmuPlant":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
