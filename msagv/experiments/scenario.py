"""One description of a closed-loop run, and the one place that assembles it.

A :class:`Scenario` names everything that determines a run: the vehicle (a TOML file, or
the built-in paper vehicle, with an optional mass), the reference (the paper's Case 1
curve or Case 2 line at a speed, or a ``t,x,y,phi`` CSV), the initial state (on the
reference unless ``from_rest``, plus overrides), the controller (MPC settings and solver),
the plant (the built-in stepping plant, or an FMU with its name mapping and parameters),
the duration and the control period. It is built from command-line options
(:mod:`msagv.cli.args`), from an experiment's run spec (:mod:`experiments.runs`) or from a
TOML file (:meth:`Scenario.from_file`), and :meth:`Scenario.build` turns it into the plant,
the controller and the reference that every caller (``msagv run``, ``msagv plant``,
``msagv controller``, the experiments, the benchmarks) then connects its own way.

Errors name the problem and come as the model's own exceptions (``VehicleError``,
``ReferenceError``, ``PlantError``, ``ControllerError``, ``FmuHostError``, all
``ValueError`` or ``RuntimeError`` subclasses) or :class:`ScenarioError`.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

from msagv.plant.signals import CONTROL_PERIOD

from .checks import ScenarioError, initial_checks, reference_checks

CASES = ("curve", "line", "lane", "turn", "random")  # paper Cases 1, 2; the study's paths
AFTER_END = ("continue", "stop")  # past the reference's end: go on straight, or end the run
PERIOD = CONTROL_PERIOD  # s, the paper's control period T (plant.signals)
# top-level keys of a scenario file that are MPC settings (the rest go under [settings])
SETTING_KEYS = ("method", "model", "seed")


@dataclass
class Built:
    """What :meth:`Scenario.build` returns: connect ``plant`` and ``controller`` your way."""

    plant: Any  # plant.Plant or fmu_build.host.FmuPlant (plant.interface.PlantInterface)
    controller: Any  # controller.interface.Controller (controller.mpc.MPC)
    reference: Any  # controller.reference.Reference
    vehicle: Any  # plant.vehicle.Vehicle
    initial: dict  # the plant's initial state by signal name
    duration: float  # s of vehicle time to run
    warnings: list = field(default_factory=list)  # one line each (experiments.checks)
    measure: Any = None  # plant.sensors.MeasurementNoise: what the controller measures

    def close(self) -> None:
        """Free what the plant holds (an FMU instance); a no-op for the native plant."""
        self.plant.close()


@dataclass
class Scenario:
    """A closed-loop run, described (see the module docstring).

    vehicle : path of a vehicle TOML, a :class:`plant.vehicle.Vehicle`, or None (the
        built-in paper vehicle; for an FMU plant: the vehicle inside the FMU).
    mass_kg : override of the vehicle's mass [kg] (for an FMU: its ``mass`` parameter).
    case : 'curve' (paper Case 1) or 'line' (Case 2), unless ``trajectory`` is given.
    trajectory : a ``t,x,y,phi`` CSV to track instead of a case.
    speed : the case's speed in km/h, or a profile ``'t:kmh,t:kmh,...'`` (None: the case's
        default, 15 km/h on the curve, 10 on the line). Not with a trajectory.
    initial : initial-state overrides by signal name (``vx``, ``phi``, ``delta_11``, ...),
        plus ``u``: the forward speed in the body frame [m/s] (sets ``vx, vy`` along the
        final heading, no sideways slip, and steers the wheels for pure rolling unless
        ``delta_ij`` are given). With a vehicle whose wheels lag (``wheel_lag`` > 0) the
        wheels start at the rolling speed of the initial state unless ``omega_w_ij`` are
        given.
    from_rest : start at rest at the origin (plus ``initial``) instead of on the reference.
    duration : vehicle time [s] (None: the reference's nominal duration).
    after_end : past the reference's end the reference goes on straight at its last
        heading and speed; 'continue' runs the whole ``duration`` (with a warning if it
        passes the end), 'stop' ends the run at the end.
    settings : :class:`controller.models.MPCSettings` fields that differ from the defaults.
    solver : a horizon solver of :data:`controller.solvers.SOLVERS`: 'sa' (simulated
        annealing), 'ipopt', 'acados' (SQP-RTI), 'ff' (the feed-forward alone), ...
    fmu, fmu_map, fmu_params : an FMI 2.0 co-simulation FMU as the plant, its name mapping
        file and its parameters by our names.
    period : control period T [s].
    axles : a vehicle like the scenario's with this many axles, evenly spaced about the
        centre of mass, each carrying the same load (:func:`plant.vehicle.n_axle_vehicle`).
    path_seed : the seed of ``case = 'random'`` (:func:`controller.paths.random_path`);
        ``'lane'`` and ``'turn'`` are :func:`controller.paths.lane_change` and
        :func:`~controller.paths.tight_turn`, feasible for the vehicle at ``speed``.
    plant_options : the plant's own realism, on top of the vehicle file's ``[plant]``
        (``cg_height``, ``wheel_lag``, ``steer_lag``, ``combined_slip``); the controller
        does not model them.
    plant_tire_scale : the plant's Magic Formula stiffness factors B and peak friction mu
        (both curves) times this factor; the controller keeps the nominal tires (a model
        error of the prediction, as a real tire would make).
    plant_vehicle : the plant's own vehicle (a file path or a :class:`plant.vehicle.Vehicle`):
        its tires, mass, inertia, lags and geometry, while the controller keeps ``vehicle``
        (its belief). ``plant_options`` and ``plant_tire_scale`` apply on top of it. It must
        have as many wheels as the controller's vehicle.
    measurement_noise : the noise of the controller's measurements, as a real vehicle's
        odometry has (:class:`plant.sensors.MeasurementNoise`: standard deviations ``v``
        [m/s] of the body's velocity along and across it, ``r`` [rad/s], ``pos`` [m] of x
        and y, ``phi`` [rad], and ``seed``); the plant and the metrics keep the true state.
        Default none.
    """

    vehicle: Any = None
    mass_kg: float | None = None
    case: str | None = None
    trajectory: str | None = None
    speed: str | float | None = None
    initial: dict = field(default_factory=dict)
    from_rest: bool = False
    duration: float | None = None
    after_end: str = "continue"
    settings: dict = field(default_factory=dict)
    solver: str = "sa"  # controller.solvers.DEFAULT_SOLVER (not imported here: see its test)
    fmu: str | None = None
    fmu_map: str | None = None
    fmu_params: dict = field(default_factory=dict)
    period: float = PERIOD
    axles: int | None = None
    path_seed: int = 0
    plant_options: dict = field(default_factory=dict)
    plant_tire_scale: float = 1.0
    plant_vehicle: Any = None
    measurement_noise: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.trajectory is not None and self.case is not None:
            raise ScenarioError("give a case or a trajectory, not both")
        if self.trajectory is not None and self.speed is not None:
            raise ScenarioError("speed applies to a case; a trajectory CSV carries its own "
                                "timing")
        if self.case is not None and self.case not in CASES + ("case1", "case2"):
            raise ScenarioError(f"case: expected one of {', '.join(CASES)}, got '{self.case}'")
        from msagv.controller.solvers import SOLVERS

        if self.solver not in SOLVERS:
            raise ScenarioError(f"solver: expected one of {', '.join(SOLVERS)}, got "
                                f"'{self.solver}'")
        if self.duration is not None and not (math.isfinite(self.duration) and self.duration > 0):
            raise ScenarioError(f"duration: must be > 0, got {self.duration}")
        if self.after_end not in AFTER_END:
            raise ScenarioError(f"after_end: expected one of {', '.join(AFTER_END)}, got "
                                f"'{self.after_end}'")
        if not (math.isfinite(self.period) and self.period > 0):
            raise ScenarioError(f"period: must be > 0, got {self.period}")
        if self.duration is not None and self.duration < self.period * (1 - 1e-9):
            raise ScenarioError(f"duration: {self.duration:g} s is shorter than one control "
                                f"period ({self.period:g} s)")
        if self.mass_kg is not None and not (math.isfinite(self.mass_kg) and self.mass_kg > 0):
            raise ScenarioError(f"mass: must be > 0 kg, got {self.mass_kg}")
        if self.axles is not None and not (isinstance(self.axles, int) and self.axles >= 1):
            raise ScenarioError(f"axles: must be an integer >= 1, got {self.axles!r}")
        if not (math.isfinite(self.plant_tire_scale) and self.plant_tire_scale > 0):
            raise ScenarioError(f"plant_tire_scale: must be > 0, got {self.plant_tire_scale}")
        if self.fmu is not None and (self.plant_options or self.plant_tire_scale != 1.0
                                     or self.plant_vehicle is not None):
            raise ScenarioError("plant_vehicle, plant_options and plant_tire_scale apply to the "
                                "built-in plant, not to an FMU (set the FMU's parameters "
                                "instead)")
        try:
            self.measurement()
        except ValueError as e:
            raise ScenarioError(str(e)) from None
        if self.fmu_map is not None and self.fmu is None:
            raise ScenarioError("--map applies to --fmu: a name mapping needs an FMU plant")

    # ---- the parts -----------------------------------------------------------------------
    def measurement(self):
        """What the controller measures: a fresh :class:`plant.sensors.MeasurementNoise`
        of ``measurement_noise`` (its stream from its seed), or None without noise."""
        from msagv.plant.sensors import MeasurementNoise

        return MeasurementNoise.from_mapping(self.measurement_noise or None)

    def resolve_vehicle(self, given=None):
        """The vehicle: ``given`` (e.g. the one a plant serves as its params, or the FMU's),
        else the scenario's, with ``mass_kg`` applied."""
        from msagv.plant.vehicle import Vehicle, load_vehicle

        if given is not None:
            v = given
        elif isinstance(self.vehicle, Vehicle):
            v = self.vehicle
        else:
            v = load_vehicle(self.vehicle)
        if self.axles is not None and given is None and v.n_axles != self.axles:
            from msagv.plant.vehicle import n_axle_vehicle

            v = n_axle_vehicle(self.axles, base=v)
        if self.mass_kg is not None and v.mass != self.mass_kg:
            v = v.replace(mass=float(self.mass_kg))
        return v

    def reference(self):
        """``(reference, initial_state_fn)``: ``initial_state_fn(vehicle)`` starts on it."""
        from msagv.controller.reference import from_csv, make_case

        if self.trajectory is not None:
            ref = from_csv(self.trajectory).with_after_end("continue")
            return ref, ref.initial_state
        if self.case in ("lane", "turn", "random"):
            from msagv.controller import paths

            v, speed = self.resolve_vehicle(), float(self.speed if self.speed is not None else 15)
            ref = (paths.lane_change(v, speed) if self.case == "lane" else
                   paths.tight_turn(v, speed) if self.case == "turn" else
                   paths.random_path(v, speed, self.path_seed))
            ref.after_end = "continue"
            return ref, ref.initial_state
        ref, start = make_case(self.case or "curve", self.speed)
        # both after_end choices continue the reference, so the horizon near the end
        # never sees a vehicle told to stand still
        ref.after_end = "continue"
        return ref, start

    def initial_state(self, vehicle, start_fn) -> dict[str, float]:
        """The plant's initial state: on the reference (``start_fn(vehicle)``), or at rest
        with ``from_rest``; then the ``initial`` overrides."""
        from msagv.controller.reference import rolling_wheels

        st = {} if self.from_rest else dict(start_fn(vehicle))
        given = {k: float(v) for k, v in self.initial.items()}
        u = given.pop("u", None)
        if u is not None and ({"vx", "vy"} & set(given)):
            raise ScenarioError("initial: u (forward speed in the body frame) sets vx and vy; "
                                "give u or vx/vy, not both")
        st.update(given)
        if u is not None:
            phi, r = st.get("phi", 0.0), st.get("r", 0.0)
            st["vx"], st["vy"] = u * math.cos(phi), u * math.sin(phi)
            delta = rolling_wheels(vehicle, phi, st["vx"], st["vy"], r)[0]
            st.update({k: v for k, v in delta.items() if k not in given})
        if vehicle.plant.wheel_lag > 0:
            omega = rolling_wheels(vehicle, st.get("phi", 0.0), st.get("vx", 0.0),
                                   st.get("vy", 0.0), st.get("r", 0.0))[1]
            st.update({k: v for k, v in omega.items() if k not in given})
        return st

    def mpc_settings(self, **override):
        """The :class:`controller.models.MPCSettings` of this scenario (plus ``override``)."""
        from msagv.controller.models import MPCSettings

        known = set(MPCSettings.field_names())
        kw = {}
        for k, v in dict(self.settings, **override).items():
            if k not in known:
                raise ScenarioError(f"settings: unknown setting '{k}' (known: "
                                    f"{', '.join(sorted(known))})")
            kw[k] = tuple(v) if isinstance(v, list) else v
        return MPCSettings(**kw)

    def make_controller(self, vehicle, reference, period: float | None = None, *,
                        options=None, **override):
        """The controller: :class:`controller.mpc.MPC` with the scenario's solver (an
        entry of :data:`controller.solvers.SOLVERS`) and its ``options``; ``override``:
        settings fields on top of the scenario's."""
        from msagv.controller.mpc import MPC

        T = self.period if period is None else period
        return MPC(vehicle, self.mpc_settings(**override), reference, period=T,
                   solver=self.solver, options=options)

    def check_solver(self) -> None:
        """Fail early (before any plant or network) if the solver cannot serve the settings
        (IPOPT without CasADi, or with a baseline's prediction model)."""
        from msagv.controller.solvers import check_supported

        check_supported(self.solver, self.mpc_settings())

    def make_plant(self):
        """``(plant, vehicle, reference, initial)``: the plant at its initial state."""
        ref, start = self.reference()
        if self.fmu is not None:
            from msagv.fmu_build.host import FmuPlant

            given = None
            if self.vehicle is not None:
                given = self.resolve_vehicle()
            params = dict(self.fmu_params)
            if self.mass_kg is not None:
                params.setdefault("mass", float(self.mass_kg))
            plant = FmuPlant(self.fmu, given, mapping=self.fmu_map, parameters=params)
            try:
                vehicle = plant.vehicle
                initial = self.initial_state(vehicle, start)
                plant.reset(initial)
            except BaseException:
                plant.close()
                raise
            return plant, vehicle, ref, initial
        from msagv.plant.stepping import Plant

        vehicle = self.resolve_vehicle()
        actual = self.actual_vehicle(vehicle)
        initial = self.initial_state(actual, start)
        return Plant(actual, initial=initial), vehicle, ref, initial

    def actual_vehicle(self, vehicle):
        """The vehicle the plant simulates: ``plant_vehicle`` (default ``vehicle``) with
        ``plant_options`` and ``plant_tire_scale`` applied (the controller's is ``vehicle``
        itself)."""
        from msagv.plant.vehicle import Vehicle, VehicleError, load_vehicle, vehicle_from_dict

        if self.plant_vehicle is not None:
            try:
                own = (self.plant_vehicle if isinstance(self.plant_vehicle, Vehicle)
                       else load_vehicle(self.plant_vehicle))
            except VehicleError as e:
                raise ScenarioError(f"plant_vehicle: {e}") from None
            if own.n_wheels != vehicle.n_wheels:
                raise ScenarioError(
                    f"plant_vehicle: {own.n_axles} axles, but the controller's vehicle has "
                    f"{vehicle.n_axles}: the plant must have as many wheels as the commands")
            vehicle = own
        if not self.plant_options and self.plant_tire_scale == 1.0:
            return vehicle
        d = vehicle.to_dict()
        unknown = sorted(set(self.plant_options) - set(d["plant"]))
        if unknown:
            raise ScenarioError(f"plant_options: unknown option '{unknown[0]}' (known: "
                                f"{', '.join(d['plant'])})")
        d["plant"].update({k: float(v) for k, v in self.plant_options.items()})
        for part in ("longitudinal", "lateral"):
            d["tire"][part]["B"] *= self.plant_tire_scale
            d["tire"][part]["mu"] *= self.plant_tire_scale
        return vehicle_from_dict(d)

    def run_duration(self, reference) -> float:
        """Vehicle time to run: ``duration`` (default the reference's), ended at the
        reference's end with ``after_end = "stop"``."""
        d = float(self.duration) if self.duration is not None else float(reference.duration)
        if self.after_end == "stop":
            d = min(d, reference.end_time)
        return d

    def check(self, vehicle, reference, initial: dict | None = None) -> list[str]:
        """Warnings about running this scenario (:mod:`experiments.checks`) from
        ``initial`` (the plant's initial state); raises :class:`ScenarioError` for a
        request no vehicle can meet."""
        from msagv.plant.vehicle import plausibility_warnings

        d = float(self.duration) if self.duration is not None else float(reference.duration)
        where = "" if self.vehicle is None else f"{vehicle.name}: "
        return ([where + w for w in plausibility_warnings(vehicle)]
                + reference_checks(vehicle, reference, d, self.after_end)
                + initial_checks(vehicle, initial or {}))

    def preflight(self) -> list[str]:
        """The checks of :meth:`build` without building a plant or a controller (cheap:
        for many runs before any of them starts): raises for a request no vehicle can
        meet, returns the warnings."""
        self.check_solver()
        vehicle = self.resolve_vehicle() if self.fmu is None else None
        if vehicle is None:  # an FMU's vehicle is known once it is loaded
            return []
        ref, _ = self.reference()
        return self.check(vehicle, ref)

    def build(self) -> Built:
        """Plant, controller and reference, ready to connect (close ``Built`` when done)."""
        self.check_solver()
        plant, vehicle, ref, initial = self.make_plant()
        try:
            warnings = self.check(vehicle, ref, initial)
            ctl = self.make_controller(vehicle, ref)
        except BaseException:
            plant.close()
            raise
        return Built(plant, ctl, ref, vehicle, initial, self.run_duration(ref), warnings,
                     measure=self.measurement())

    # ---- as data -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Plain data (the vehicle as its file path or its description)."""
        from msagv.plant.vehicle import Vehicle

        d = {f.name: getattr(self, f.name) for f in fields(self)}
        if isinstance(self.vehicle, Vehicle):
            d["vehicle"] = self.vehicle.to_dict()
        if isinstance(self.plant_vehicle, Vehicle):
            d["plant_vehicle"] = self.plant_vehicle.to_dict()
        d["settings"] = {k: (list(v) if isinstance(v, tuple) else v)
                         for k, v in self.settings.items()}
        if not d["measurement_noise"]:  # (none: the files of runs without it stay as they were)
            del d["measurement_noise"]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], base: str | Path | None = None) -> "Scenario":
        """A scenario from plain data (a TOML file's tables; see docs/SCENARIOS.md).
        Relative file paths are taken relative to ``base`` (the scenario file's folder);
        ``method``, ``model`` and ``seed`` may be given at the top level as well as under
        ``settings``. Every key is checked here (type, range, files exist), so a bad
        file fails naming its key before anything is built. Unknown keys are refused."""
        from msagv.plant.vehicle import VehicleError, vehicle_from_dict

        d = {k: v for k, v in d.items() if v is not None}  # None: not given (to_dict)
        known = {f.name for f in fields(cls)} | set(SETTING_KEYS)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ScenarioError(f"{unknown[0]}: unknown key (known: {', '.join(sorted(known))})")
        kw = {k: v for k, v in d.items() if k not in SETTING_KEYS}
        for k in ("initial", "settings", "fmu_params", "measurement_noise"):
            if k in kw and not isinstance(kw[k], Mapping):
                raise ScenarioError(f"{k}: expected a table, got {kw[k]!r}")
            if k in kw:
                kw[k] = dict(kw[k])
        settings = dict(kw.get("settings", {}))
        for k in SETTING_KEYS:
            if k in d:
                if k in settings:
                    raise ScenarioError(f"{k}: given at the top level and under [settings]")
                settings[k] = d[k]
        kw["settings"] = settings
        for k in ("case", "solver", "after_end"):
            if k in kw and not isinstance(kw[k], str):
                raise ScenarioError(f"{k}: expected a string, got {kw[k]!r}")
        for k in ("trajectory", "fmu", "fmu_map"):
            if kw.get(k) is not None:
                if not isinstance(kw[k], str):
                    raise ScenarioError(f"{k}: expected a file path, got {kw[k]!r}")
                kw[k] = _resolve(kw[k], base)
                if not Path(kw[k]).is_file():
                    raise ScenarioError(f"{k}: no such file {kw[k]}")
        for k, what in (("duration", "seconds"), ("mass_kg", "kilograms"), ("period", "seconds")):
            if k in kw and not _is_number(kw[k]):
                raise ScenarioError(f"{k}: expected a number of {what}, got {kw[k]!r}")
            if k in kw:
                kw[k] = float(kw[k])
        if "from_rest" in kw and not isinstance(kw["from_rest"], bool):
            raise ScenarioError(f"from_rest: expected true or false, got {kw['from_rest']!r}")
        for k in ("initial", "fmu_params"):
            for name, v in kw.get(k, {}).items():
                if not _is_number(v):
                    raise ScenarioError(f"{k}.{name}: expected a number, got {v!r}")
        if "speed" in kw:
            sp = kw["speed"]
            if not (_is_number(sp) or isinstance(sp, str)):
                raise ScenarioError(f"speed: expected km/h or a profile 't:kmh,...', got {sp!r}")
            from msagv.controller.reference import ReferenceError, SpeedProfile

            try:
                SpeedProfile.parse(sp)
            except ReferenceError as e:
                raise ScenarioError(f"speed: {e}") from None
        for key in ("vehicle", "plant_vehicle"):
            v = kw.get(key)
            if isinstance(v, Mapping):
                try:
                    kw[key] = vehicle_from_dict(v)
                except VehicleError as e:
                    raise ScenarioError(f"{key}.{e}") from None
            elif v is not None:
                if not isinstance(v, str):
                    raise ScenarioError(f"{key}: expected a file path or a table, got {v!r}")
                kw[key] = _resolve(v, base)
                if not Path(kw[key]).is_file():
                    raise ScenarioError(f"{key}: no such file {kw[key]}")
        sc = cls(**kw)
        try:
            sc.mpc_settings()  # a bad setting is named now
        except (TypeError, ValueError) as e:
            msg = str(e)
            raise ScenarioError(msg if msg.startswith("settings") else f"settings: {msg}") from None
        if isinstance(sc.vehicle, str):
            try:
                sc.resolve_vehicle()
            except VehicleError as e:
                raise ScenarioError(f"vehicle: {e}") from None
        if sc.plant_vehicle is not None:
            sc.actual_vehicle(sc.resolve_vehicle())  # loads it, checks its wheels
        return sc

    @classmethod
    def from_file(cls, path: str | Path) -> "Scenario":
        """Read a scenario TOML file (keys as the fields; see docs/SCENARIOS.md). Errors
        are one line naming the file and the key."""
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"scenario file not found: {p}")
        try:
            data = tomllib.loads(p.read_text())
        except tomllib.TOMLDecodeError as e:
            raise ScenarioError(f"{p}: not valid TOML: {e}") from None
        except UnicodeDecodeError:
            raise ScenarioError(f"{p}: not a text file") from None
        try:
            return cls.from_dict(data, base=p.parent)
        except (ScenarioError, TypeError) as e:
            raise ScenarioError(f"{p}: {e}") from None


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


def _resolve(path, base) -> str:
    p = Path(str(path))
    if base is not None and not p.is_absolute():
        p = Path(base) / p
    return str(p)
