"""Vehicle description: the TOML contract of DESIGN.md, loaded into a frozen, validated object.

Indices follow the paper: axle ``i = 1..n`` from the front, side ``j = 1`` left (y > 0),
``j = 2`` right. Every per-wheel array is ordered 11, 12, 21, 22, ..., n1, n2.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .model_params import SECTIONS, ModelParams, ParamValues

G_ACCEL = 9.81  # m/s^2, as in DESIGN.md (F_N = m g / (2n))


class VehicleError(ValueError):
    """A vehicle description is malformed. The message names the offending field."""


@dataclass(frozen=True)
class MagicFormula:
    """Coefficients of the Magic Formula f (paper, unnumbered, after eq. 12); D = mu * F_N."""

    B: float  # stiffness factor [1/unit of slip]
    C: float  # shape factor [-]
    mu: float  # peak friction coefficient [-], D = mu * F_N
    E: float  # curvature factor [-]


@dataclass(frozen=True)
class Limits:
    """Bounds of the paper's eq. (27)."""

    omega_s_min: float  # rad/s
    omega_s_max: float  # rad/s
    omega_w_max: float  # rad/s (omega_w_min is 0)
    delta_min: float  # rad
    delta_max: float  # rad


@dataclass(frozen=True)
class PlantOptions:
    """Plant-only realism the controller does not model (all off by default).

    cg_height : m. Height of the centre of gravity; > 0 turns on quasi-static load
        transfer (the paper's future work, its Assumption 2 dropped). 0 keeps
        F_N = m g / (2n) on every wheel.
    wheel_lag : s. Time constant of the wheel-speed tracker (first-order lag of the
        actual wheel speed behind omega_w). 0 = ideal tracking, as the paper assumes.
    steer_lag : s. Time constant of the steering-rate tracker. 0 = ideal.
    combined_slip : 0 or 1. 1: each tire's forces interact (a slip angle lowers the
        longitudinal force, a slip ratio the lateral force: Magic Formula combined-slip
        weighting functions, :func:`plant.tire.combined_slip_weights`); 0 (the paper's
        model): the longitudinal force depends on the slip ratio only, the lateral on the
        slip angle only.
    """

    cg_height: float = 0.0
    wheel_lag: float = 0.0
    steer_lag: float = 0.0
    combined_slip: float = 0.0


@dataclass(frozen=True)
class TireWear:
    """A tire's wear calibration, the optional ``[tire.wear]`` table (docs/WEAR.md).

    Wear volume is taken proportional to the frictional work, ``V = k_a W`` (Archard's law;
    for rubber Schallamach's and Grosch's abradability), with ``k_a`` the abradability in
    mm^3/J: given as ``abradability``, or derived from a known life, ``reference_life_km``
    on a duty that costs ``reference_work_per_km`` J per km per tire (the ``W_tw`` per km
    ``msagv run`` reports for that duty), as ``k_a = V_usable / (life x work per km)``.

    tread_width : mm. The tread's width in contact with the road.
    usable_depth : mm. Tread depth from new to the replacement limit.
    abradability : mm^3/J. ``k_a``; or None with the two reference keys.
    reference_life_km : km. A known life of this tire on a reference duty.
    reference_work_per_km : J/km. Wear work per km of one tire on that duty.
    price : per tire, in any currency (the cost per km comes out in the same one).
    """

    tread_width: float
    usable_depth: float
    abradability: float | None = None
    reference_life_km: float | None = None
    reference_work_per_km: float | None = None
    price: float | None = None

    def usable_volume(self, wheel_radius: float) -> float:
        """mm^3 of tread that may wear away: the tread band ``pi D w d`` round a tire of
        outer diameter ``D = 2 r_w`` (a band thin against the radius)."""
        return math.pi * 2000.0 * wheel_radius * self.tread_width * self.usable_depth

    def k_a(self, wheel_radius: float) -> float:
        """The abradability [mm^3/J]: given, or ``V_usable / (reference_life_km x
        reference_work_per_km)``."""
        if self.abradability is not None:
            return self.abradability
        return self.usable_volume(wheel_radius) / (self.reference_life_km
                                                   * self.reference_work_per_km)

    def to_dict(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


@dataclass(frozen=True)
class Vehicle:
    """A multi-axle swerve-drive vehicle (any number of axles n >= 1).

    Units are SI; angles in radians. See ``docs/VEHICLE.md`` for the file format and the
    sources of the built-in tire coefficients.
    """

    name: str
    mass: float  # kg
    yaw_inertia: float  # kg m^2
    wheel_radius: float  # m
    axle_x: tuple[float, ...]  # m, front first
    half_track: float  # m
    steer_loss_kt: float  # m, k_t of eq. 15
    tire_longitudinal: MagicFormula
    tire_lateral: MagicFormula
    #: the prediction models' own parameters ([tire.<section>], plant.model_params), in
    #: the declarations' order
    model_params: tuple[ParamValues, ...]
    limits: Limits
    plant: PlantOptions = field(default_factory=PlantOptions)
    #: the tires' wear calibration ([tire.wear]); None: the wear is known in joules only
    tire_wear: TireWear | None = None

    def model_values(self, section: str) -> ParamValues:
        """The vehicle's values of the model parameters ``[tire.<section>]``."""
        for pv in self.model_params:
            if pv.spec.section == section:
                return pv
        raise KeyError(f"no model parameters '{section}' (known: "
                       f"{', '.join(pv.spec.section for pv in self.model_params)})")

    # ---- derived geometry -------------------------------------------------------------
    @property
    def n_axles(self) -> int:
        return len(self.axle_x)

    @property
    def n_wheels(self) -> int:
        return 2 * len(self.axle_x)

    @property
    def wheel_names(self) -> list[str]:
        """Wheel suffixes in array order: ['11', '12', '21', '22', ...]."""
        return [f"{i}{j}" for i in range(1, self.n_axles + 1) for j in (1, 2)]

    @property
    def wheel_x(self) -> np.ndarray:
        """x_wi of every wheel, shape (2n,)."""
        return np.repeat(np.asarray(self.axle_x, dtype=float), 2)

    @property
    def wheel_y(self) -> np.ndarray:
        """y_wj of every wheel, shape (2n,): +half_track left (j=1), -half_track right."""
        return np.tile(np.array([self.half_track, -self.half_track]), self.n_axles)

    @property
    def normal_load(self) -> float:
        """F_N = m g / (2n), per wheel (paper's Assumption 2)."""
        return self.mass * G_ACCEL / self.n_wheels

    # ---- conversions ------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The description as plain data, with the TOML file's key layout."""
        d = {
            "name": self.name,
            "mass": self.mass,
            "yaw_inertia": self.yaw_inertia,
            "wheel_radius": self.wheel_radius,
            "axle_x": list(self.axle_x),
            "half_track": self.half_track,
            "steer_loss_kt": self.steer_loss_kt,
            "tire": {
                "longitudinal": dataclasses.asdict(self.tire_longitudinal),
                "lateral": dataclasses.asdict(self.tire_lateral),
                **{pv.spec.section: pv.as_dict() for pv in self.model_params},
                **({"wear": self.tire_wear.to_dict()} if self.tire_wear is not None else {}),
            },
            "limits": dataclasses.asdict(self.limits),
            "plant": dataclasses.asdict(self.plant),
        }
        return d

    def replace(self, **changes: Any) -> "Vehicle":
        """A validated copy with some top-level fields changed (e.g. ``mass=16000.0``)."""
        d = self.to_dict()
        for k, v in changes.items():
            if k not in d:
                raise VehicleError(f"unknown key '{k}'")
            d[k] = list(v) if isinstance(v, tuple) else v
        return vehicle_from_dict(d)


# ---- loading and validation -------------------------------------------------------------
_TOP_KEYS = {
    "name", "mass", "yaw_inertia", "wheel_radius", "axle_x", "half_track", "steer_loss_kt",
    "tire", "limits",
}
_OPTIONAL_TOP = {"plant"}
_MF_KEYS = ("B", "C", "mu", "E")
_LIMIT_KEYS = ("omega_s_min", "omega_s_max", "omega_w_max", "delta_min", "delta_max")
_PLANT_KEYS = ("cg_height", "wheel_lag", "steer_lag", "combined_slip")
_WEAR_KEYS = ("tread_width", "usable_depth", "abradability", "reference_life_km",
              "reference_work_per_km", "price")


def _number(d: Mapping[str, Any], key: str, path: str, *, positive: bool = False,
            nonneg: bool = False) -> float:
    if key not in d:
        raise VehicleError(f"{path}{key}: missing")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise VehicleError(f"{path}{key}: expected a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise VehicleError(f"{path}{key}: must be finite, got {v}")
    if positive and v <= 0:
        raise VehicleError(f"{path}{key}: must be > 0, got {v}")
    if nonneg and v < 0:
        raise VehicleError(f"{path}{key}: must be >= 0, got {v}")
    return v


def _table(d: Mapping[str, Any], key: str, path: str, keys: tuple[str, ...]) -> dict:
    if key not in d:
        raise VehicleError(f"{path}{key}: missing table")
    t = d[key]
    if not isinstance(t, Mapping):
        raise VehicleError(f"{path}{key}: expected a table")
    unknown = sorted(set(t) - set(keys))
    if unknown:
        raise VehicleError(f"{path}{key}.{unknown[0]}: unknown key")
    return dict(t)


def vehicle_from_dict(d: Mapping[str, Any]) -> Vehicle:
    """Build and validate a :class:`Vehicle` from the TOML layout (a nested mapping)."""
    if not isinstance(d, Mapping):
        raise VehicleError("vehicle description must be a table")
    unknown = sorted(set(d) - _TOP_KEYS - _OPTIONAL_TOP)
    if unknown:
        raise VehicleError(f"{unknown[0]}: unknown key")
    for k in sorted(_TOP_KEYS):
        if k not in d:
            raise VehicleError(f"{k}: missing")
    name = d["name"]
    if not isinstance(name, str) or not name:
        raise VehicleError("name: expected a non-empty string")
    mass = _number(d, "mass", "", positive=True)
    yaw_inertia = _number(d, "yaw_inertia", "", positive=True)
    wheel_radius = _number(d, "wheel_radius", "", positive=True)
    half_track = _number(d, "half_track", "", positive=True)
    kt = _number(d, "steer_loss_kt", "", nonneg=True)

    ax = d["axle_x"]
    if not isinstance(ax, (list, tuple)) or len(ax) == 0:
        raise VehicleError("axle_x: expected a non-empty array of axle positions (n >= 1)")
    axle_x = []
    for k, v in enumerate(ax):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise VehicleError(f"axle_x[{k}]: expected a finite number, got {v!r}")
        axle_x.append(float(v))
    for k in range(1, len(axle_x)):
        if not axle_x[k] < axle_x[k - 1]:
            raise VehicleError(
                f"axle_x[{k}]: axles must be listed front first with strictly decreasing x "
                f"({axle_x[k - 1]} then {axle_x[k]})")

    tire = d["tire"]
    if not isinstance(tire, Mapping):
        raise VehicleError("tire: expected a table")
    unknown = sorted(set(tire) - {"longitudinal", "lateral", "wear", *SECTIONS})
    if unknown:
        raise VehicleError(f"tire.{unknown[0]}: unknown key")
    mfs = {}
    for part in ("longitudinal", "lateral"):
        t = _table(tire, part, "tire.", _MF_KEYS)
        p = f"tire.{part}."
        B = _number(t, "B", p, positive=True)
        C = _number(t, "C", p, positive=True)
        mu = _number(t, "mu", p, positive=True)
        E = _number(t, "E", p)
        if E > 1.0:
            raise VehicleError(f"{p}E: must be <= 1 (the Magic Formula loses monotonic "
                               f"rise for E > 1), got {E}")
        mfs[part] = MagicFormula(B=B, C=C, mu=mu, E=E)
    models = tuple(_model_params(tire, spec) for spec in SECTIONS.values())

    t = _table(d, "limits", "", _LIMIT_KEYS)
    lim = {k: _number(t, k, "limits.") for k in _LIMIT_KEYS}
    if lim["omega_s_min"] > lim["omega_s_max"]:
        raise VehicleError(f"limits.omega_s_min: greater than limits.omega_s_max "
                           f"({lim['omega_s_min']} > {lim['omega_s_max']})")
    if lim["delta_min"] > lim["delta_max"]:
        raise VehicleError(f"limits.delta_min: greater than limits.delta_max "
                           f"({lim['delta_min']} > {lim['delta_max']})")
    if lim["omega_w_max"] <= 0:
        raise VehicleError(f"limits.omega_w_max: must be > 0, got {lim['omega_w_max']}")
    if lim["omega_s_min"] > 0 or lim["omega_s_max"] < 0:
        raise VehicleError("limits.omega_s_min: the steering-rate range must contain 0 "
                           "(a wheel must be able to hold its angle)")
    if lim["delta_min"] > 0 or lim["delta_max"] < 0:
        raise VehicleError("limits.delta_min: the steering range must contain 0")
    if lim["delta_min"] < -math.pi or lim["delta_max"] > math.pi:
        raise VehicleError("limits.delta_max: steering limits must lie within [-pi, pi]")

    if "plant" in d:
        t = _table(d, "plant", "", _PLANT_KEYS)
        po = PlantOptions(**{k: _number(t, k, "plant.", nonneg=True) for k in t})
        if po.combined_slip not in (0.0, 1.0):
            raise VehicleError(f"plant.combined_slip: must be 0 (off) or 1 (on), got "
                               f"{po.combined_slip}")
    else:
        po = PlantOptions()

    wear = _tire_wear(tire, wheel_radius) if "wear" in tire else None
    return Vehicle(
        name=name, mass=mass, yaw_inertia=yaw_inertia, wheel_radius=wheel_radius,
        axle_x=tuple(axle_x), half_track=half_track, steer_loss_kt=kt,
        tire_longitudinal=mfs["longitudinal"], tire_lateral=mfs["lateral"],
        model_params=models, limits=Limits(**lim), plant=po, tire_wear=wear,
    )


def _model_params(tire: Mapping[str, Any], spec: ModelParams) -> ParamValues:
    """A model's ``[tire.<section>]`` table, checked against its declaration: required
    unless every parameter has a default; a key with a default may be left out."""
    sec = spec.section
    if sec not in tire and all(p.default is not None for p in spec.params):
        return ParamValues(spec, tuple(float(p.default) for p in spec.params))
    t = _table(tire, sec, "tire.", spec.names)
    return ParamValues(spec, tuple(
        float(p.default) if p.name not in t and p.default is not None
        else _number(t, p.name, f"tire.{sec}.", positive=p.positive) for p in spec.params))


def _tire_wear(tire: Mapping[str, Any], wheel_radius: float) -> TireWear:
    """The ``[tire.wear]`` table, checked: the tread's width and usable depth, then the
    abradability or a reference life with its duty's wear work per km (one or the other),
    and an optional price."""
    t = _table(tire, "wear", "tire.", _WEAR_KEYS)
    p = "tire.wear."
    width = _number(t, "tread_width", p, positive=True)
    depth = _number(t, "usable_depth", p, positive=True)
    if depth >= 1000.0 * wheel_radius:
        raise VehicleError(f"{p}usable_depth: {depth:g} mm is not less than the wheel radius "
                           f"({1000.0 * wheel_radius:g} mm); the depth is in mm")
    given = {k for k in ("abradability", "reference_life_km", "reference_work_per_km") if k in t}
    if "abradability" in given and len(given) > 1:
        raise VehicleError(f"{p}abradability: give the abradability or a reference life "
                           f"(reference_life_km with reference_work_per_km), not both")
    if "abradability" in given:
        kw = {"abradability": _number(t, "abradability", p, positive=True)}
    elif given:
        for k in ("reference_life_km", "reference_work_per_km"):
            if k not in t:
                raise VehicleError(f"{p}{k}: missing (a reference life needs "
                                   f"reference_life_km [km] and reference_work_per_km [J/km], "
                                   f"the wear work per km of one tire on that duty)")
        kw = {k: _number(t, k, p, positive=True)
              for k in ("reference_life_km", "reference_work_per_km")}
    else:
        raise VehicleError(f"{p}abradability: missing (give abradability [mm^3/J], or "
                           f"reference_life_km [km] with reference_work_per_km [J/km])")
    if "price" in t:
        kw["price"] = _number(t, "price", p, nonneg=True)
    return TireWear(tread_width=width, usable_depth=depth, **kw)


# ---- plausibility (warnings, not errors: an unusual vehicle may be meant) ---------------
# Ranges a wheeled vehicle's numbers fall in; outside them the likely cause is a unit slip
# (tonnes typed as kg, millimetres as metres, rpm as rad/s, degrees as radians).
PLAUSIBLE = {
    "load_per_wheel_kg": 20.0,  # below: tonnes typed as kg?
    "max_load_per_wheel_kg": 100000.0,  # above (100 t on one tire): grams typed as kg?
    "wheel_radius_m": (0.03, 3.0),
    "half_track_m": (0.1, 10.0),
    "axle_x_m": 60.0,  # |x| of an axle from the centre of mass
    "steer_loss_kt_m": 0.5,  # a lever arm within the contact patch (docs/VEHICLE.md 3.3)
    "top_speed_kmh": 150.0,  # omega_w_max x r_w
    "omega_s_rad_s": 10.0,  # 570 deg/s
    "gyration_ratio": 4.0,  # radius of gyration against a box of the vehicle's size
}


def _unit_slip(value: float, lo: float, hi: float, unit: str) -> str:
    """The unit slip that would bring ``value`` into [lo, hi], as a hint, or ''."""
    for factor, name in ((1000.0, "milli"), (100.0, "centi")):
        if lo <= value / factor <= hi:
            return (f": {name}{unit}s typed as {unit}s? ({value:g} {name[0]}{unit[0]} is "
                    f"{value / factor:g} {unit[0]})")
    return ""


def plausibility_warnings(v: Vehicle) -> list[str]:
    """One line for each number of ``v`` that no wheeled vehicle has, naming the likely unit
    slip: a load per wheel under 20 kg (tonnes typed as kg) or over 100 t, a wheel radius, half track or
    axle position in millimetres, a steering lever arm ``k_t`` in millimetres, a top speed
    ``omega_w_max x r_w`` over 150 km/h (rpm typed as rad/s), a steering rate over 10 rad/s
    (degrees typed as radians), wheels of neighbouring axles that overlap, a yaw inertia
    that does not fit the mass and the size (its radius of gyration more than 4 times off
    a box's of the vehicle's size), a tread width or usable depth of a fraction of a mm.
    The vehicle is used as given (these are warnings)."""
    P = PLAUSIBLE
    out = []
    per_wheel = v.mass / v.n_wheels
    if per_wheel < P["load_per_wheel_kg"]:
        out.append(f"mass: {v.mass:g} kg is {per_wheel:.3g} kg per wheel on {v.n_wheels} "
                   f"wheels: tonnes typed as kg? ({v.mass:g} t is {1000 * v.mass:g} kg)")
    elif per_wheel > P["max_load_per_wheel_kg"]:
        out.append(f"mass: {v.mass:g} kg is {per_wheel / 1000:.4g} t per wheel on "
                   f"{v.n_wheels} wheels, more than any tire carries: grams typed as kg? "
                   f"({v.mass:g} g is {v.mass / 1000:g} kg)")
    lo, hi = P["wheel_radius_m"]
    if not lo <= v.wheel_radius <= hi:
        out.append(f"wheel_radius: {v.wheel_radius:g} m is outside the {lo:g}-{hi:g} m of "
                   f"wheels" + _unit_slip(v.wheel_radius, lo, hi, "metre"))
    lo, hi = P["half_track_m"]
    if not lo <= v.half_track <= hi:
        out.append(f"half_track: {v.half_track:g} m (a track of {2 * v.half_track:g} m) is "
                   f"outside {lo:g}-{hi:g} m" + _unit_slip(v.half_track, lo, hi, "metre"))
    far = max(abs(x) for x in v.axle_x)
    if far > P["axle_x_m"]:
        out.append(f"axle_x: an axle {far:g} m from the centre of mass"
                   + _unit_slip(far, 0.0, P["axle_x_m"], "metre"))
    if v.steer_loss_kt > P["steer_loss_kt_m"]:
        out.append(f"steer_loss_kt: {v.steer_loss_kt:g} m is longer than a tire's contact "
                   f"patch (a lever arm of a few cm)"
                   + _unit_slip(v.steer_loss_kt, 0.0, P["steer_loss_kt_m"], "metre"))
    top = v.limits.omega_w_max * v.wheel_radius * 3.6
    if top > P["top_speed_kmh"] and lo <= v.wheel_radius <= hi:
        rpm = v.limits.omega_w_max * 2 * math.pi / 60
        out.append(f"limits.omega_w_max: {v.limits.omega_w_max:g} rad/s x r_w "
                   f"{v.wheel_radius:g} m is {top:.0f} km/h: rpm typed as rad/s? "
                   f"({v.limits.omega_w_max:g} rpm is {rpm:.3g} rad/s)")
    fast = max(abs(v.limits.omega_s_min), abs(v.limits.omega_s_max))
    if fast > P["omega_s_rad_s"]:
        out.append(f"limits.omega_s_max: steering at {fast:g} rad/s ({math.degrees(fast):.0f} "
                   f"deg/s): degrees per second typed as rad/s? ({fast:g} deg/s is "
                   f"{math.radians(fast):.3g} rad/s)")
    tw = v.tire_wear
    if tw is not None and tw.tread_width < 5.0:
        out.append(f"tire.wear.tread_width: {tw.tread_width:g} mm: metres typed as mm? "
                   f"({tw.tread_width:g} m is {1000 * tw.tread_width:g} mm)")
    if tw is not None and tw.usable_depth < 0.5:
        out.append(f"tire.wear.usable_depth: {tw.usable_depth:g} mm: centimetres or metres "
                   f"typed as mm? (a tread is a few mm to a few cm deep)")
    gaps = np.diff(-np.asarray(v.axle_x))
    if gaps.size and 2 * v.wheel_radius > gaps.min() and v.wheel_radius <= P["wheel_radius_m"][1]:
        i = int(np.argmin(gaps))
        out.append(f"wheel_radius: wheels {2 * v.wheel_radius:g} m across on axles {i + 1} and "
                   f"{i + 2}, {gaps[i]:g} m apart, overlap")
    length = (max(v.axle_x) - min(v.axle_x)) + 2 * v.wheel_radius
    width = 2 * v.half_track + 2 * 0.2  # the wheels' own width outside the track
    k_box = math.sqrt((length ** 2 + width ** 2) / 12.0)
    k = math.sqrt(v.yaw_inertia / v.mass)
    ratio = P["gyration_ratio"]
    # (after a mass or a size already named, a mismatch is its consequence: not repeated)
    if not out and not k_box / ratio <= k <= ratio * k_box:
        box = v.mass * (length ** 2 + width ** 2) / 12.0
        out.append(f"yaw_inertia: {v.yaw_inertia:g} kg m^2 with a mass of {v.mass:g} kg is a "
                   f"radius of gyration of {k:.3g} m on a vehicle about {length:.3g} m x "
                   f"{width:.3g} m (a box of that mass and size: {k_box:.2g} m, "
                   f"{box:.3g} kg m^2): check the mass and yaw_inertia units")
    return out


def load_vehicle(path: str | Path | None = None) -> Vehicle:
    """Load a vehicle TOML file; ``None`` gives the built-in paper vehicle.

    Raises :class:`VehicleError` naming the field for any malformed description, and
    ``FileNotFoundError`` when the file does not exist.
    """
    if path is None:
        text = resources.files(__package__).joinpath("data/paper-2axle.toml").read_text()
        where = "built-in paper-2axle"
    else:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"vehicle file not found: {p}")
        text = p.read_text()
        where = str(p)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise VehicleError(f"{where}: not valid TOML: {e}") from None
    try:
        return vehicle_from_dict(data)
    except VehicleError as e:
        raise VehicleError(f"{where}: {e}") from None


def default_vehicle() -> Vehicle:
    """The paper's 2-axle, 12 t vehicle (built in)."""
    return load_vehicle(None)


def n_axle_vehicle(n: int, spacing: float = 2.0, base: Vehicle | None = None,
                   mass_per_axle: float | None = None) -> Vehicle:
    """A vehicle like ``base`` with ``n`` axles evenly spaced about the centre of mass.

    ``mass_per_axle`` (kg) scales the mass and yaw inertia with n (default: the base
    vehicle's mass per axle), so each wheel carries the same load as on the base vehicle.
    Used for scaling studies and tests of other axle counts.
    """
    if n < 1:
        raise VehicleError("n_axles: must be >= 1")
    base = base or default_vehicle()
    mpa = mass_per_axle if mass_per_axle is not None else base.mass / base.n_axles
    xs = [spacing * ((n - 1) / 2.0 - k) for k in range(n)]
    mass = mpa * n
    length = max(spacing * (n - 1), 2.0) + 1.0
    width = 2 * base.half_track + 1.0
    inertia = mass * (length ** 2 + width ** 2) / 12.0
    d = base.to_dict()
    d.update(name=f"{n}-axle", mass=mass, yaw_inertia=inertia, axle_x=xs)
    return vehicle_from_dict(d)
