"""The named controller configurations of the experiments and their levers: one table.

A *family* is a controller configuration with a name (``NTWO``, ``TWO``, ``TWO-energy``,
...): its base MPC settings (:class:`controller.models.MPCSettings` fields), its solver
(an entry of :data:`controller.solvers.SOLVERS`) and, where it has one, a *lever*: one
settings field that a level sets (a factor on the default ``L``, the weights ``E``, the
wheel-speed ridge ``R_ow``, ...). Everything that runs a named controller reads
:data:`FAMILIES`:

* the paper's case tables (``msagv experiment case1|case2|case3``) take every family with
  a ``case_level`` at that level, the paper's five (``paper``) first in the paper's order,
  then the references; ``--methods`` offers their names;
* the study (:mod:`experiments.study`) sweeps every family with ``study`` set over its
  ``levels`` (``quick_levels`` with ``--quick``); ``raw`` families only where the design
  asks for the decision-parametrisation factor;
* ``pareto`` and ``ridge`` sweep the levers of ``NTWO-smooth``, ``NTWO-ridge`` and
  ``TWO`` at their own levels.

"method" is the wear term of the cost only (``MPCSettings.method``: ``two``,
``two-energy``, ``ntwo``, :data:`controller.models.METHODS`); a family names a whole
configuration, and its base settings name its method explicitly, so a change of the
product's default method changes no family. Levers that scale a default read it from
``MPCSettings()``: nothing here copies a default.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Mapping

from msagv.controller.models import MPCSettings
from msagv.controller.solvers import DEFAULT_SOLVER, SOLVERS

DEFAULTS = MPCSettings()
# (R_ow [1/(rad/s)^2], R_od [1/rad^2]) at a ridge level of 1 (the shipped default is x0.1):
# the pareto and ridge experiments' scale of the command ridge
RIDGE_BASE = (0.05, 20.0)


@dataclass(frozen=True)
class Lever:
    """One :class:`MPCSettings` field that a family's level sets.

    field : the settings field.
    label : how tables name it (``'L x'``, ``'E'``, ``'R_ow'``; a run is labelled
        ``'<family> <label>=<level>'``).
    scale : True: the level multiplies ``base`` (a factor); False: the level is the value.
    components : for a tuple field, the entries the level sets (None: all of them).
    base : the values a factor multiplies, one per entry set (None: the default's).
    unit : the level's unit (for docs and axes; '' for a factor).
    """

    field: str
    label: str
    scale: bool = False
    components: tuple[int, ...] | None = None
    base: tuple[float, ...] | None = None
    unit: str = ""

    def __post_init__(self):
        if self.field not in MPCSettings.field_names():
            raise ValueError(f"lever: unknown MPCSettings field '{self.field}'")
        default = getattr(DEFAULTS, self.field)
        if isinstance(default, tuple):
            idx = self.indices(len(default))
            if any(not 0 <= i < len(default) for i in idx):
                raise ValueError(f"lever {self.field}: components {self.components} outside "
                                 f"its {len(default)} entries")
            if self.base is not None and len(self.base) != len(idx):
                raise ValueError(f"lever {self.field}: base needs {len(idx)} values")
        elif self.components is not None:
            raise ValueError(f"lever {self.field}: a scalar field has no components")

    def indices(self, n: int) -> tuple[int, ...]:
        return tuple(range(n)) if self.components is None else tuple(self.components)

    def apply(self, settings: Mapping[str, Any], level: float) -> dict:
        """``settings`` (MPCSettings fields) with this lever at ``level``: a new dict."""
        default = getattr(DEFAULTS, self.field)
        out = dict(settings)
        if isinstance(default, tuple):
            vals = [float(v) for v in settings.get(self.field, default)]
            idx = self.indices(len(vals))
            base = self.base if self.base is not None else tuple(default[i] for i in idx)
            for i, b in zip(idx, base):
                vals[i] = level * b if self.scale else float(level)
            out[self.field] = vals
        else:
            b = self.base[0] if self.base is not None else default
            out[self.field] = level * b if self.scale else float(level)
        return out


@dataclass(frozen=True)
class Family:
    """A named controller configuration (see the module docstring).

    name : the row's and the run's name.
    summary : one line: what it is.
    settings : its base :class:`MPCSettings` fields (``method`` always named).
    solver : an entry of :data:`controller.solvers.SOLVERS`.
    lever, levels : the lever and the levels the study sweeps (``(None,)``: no lever).
    quick_levels : the levels of ``--quick`` (None: ``levels``).
    case_row : a row of the case tables (the paper's five always are).
    case_level : the level of that row (None: the base settings).
    wear_aware : its cost has a wear term (the study's wear-aware side).
    paper : one of the paper's five methods (Section 4.2), whose targets the case tables
        judge.
    study : swept by the study; raw : only on the scenarios of the decision-parametrisation
        factor (the paper's raw U).
    classes : the study's classes it is swept in (None: every class); a family whose levers
        answer one class's question (Case 2's recovery levers) stays out of the others, so
        their numbers do not move.
    not_in : classes it is not swept in: its lever does nothing there (the corner-cutting
        smoothing on Case 2's straight line).
    style : (matplotlib colour, marker) in every figure.
    """

    name: str
    summary: str
    settings: Mapping[str, Any]
    solver: str = DEFAULT_SOLVER
    lever: Lever | None = None
    levels: tuple = (None,)
    quick_levels: tuple | None = None
    case_row: bool = False
    case_level: float | None = None
    wear_aware: bool = False
    paper: bool = False
    study: bool = True
    raw: bool = False
    classes: tuple[str, ...] | None = None
    not_in: tuple[str, ...] = ()
    style: tuple[str, str] = ("k", "o")

    def __post_init__(self):
        object.__setattr__(self, "settings", MappingProxyType(dict(self.settings)))
        object.__setattr__(self, "case_row", self.case_row or self.paper)
        if self.solver not in SOLVERS:
            raise ValueError(f"family {self.name}: solver '{self.solver}' is not one of "
                             f"{', '.join(SOLVERS)}")
        if "method" not in self.settings:
            raise ValueError(f"family {self.name}: its settings must name the method")
        if (self.lever is None) != (tuple(self.levels) == (None,)):
            raise ValueError(f"family {self.name}: levels need a lever and a lever levels")
        for lv in tuple(self.levels) + tuple(self.quick_levels or ()):
            MPCSettings(**_tuples(self.settings_at(lv)))  # a bad value fails at import

    def in_class(self, cls: str | None) -> bool:
        """Whether the study sweeps this family in the class ``cls`` (None: any class)."""
        if cls is None:
            return self.classes is None
        return (self.classes is None or cls in self.classes) and cls not in self.not_in

    def settings_at(self, level: float | None = None) -> dict:
        """The MPCSettings fields of this family at ``level`` (None: its base)."""
        s = {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.settings.items()}
        return s if level is None or self.lever is None else self.lever.apply(s, level)

    def label(self, level: float | None = None) -> str:
        """A run's name: the family's, with the lever's value (``TWO-energy E=0.01``)."""
        return self.name if level is None else f"{self.name} {self.lever.label}={level:g}"

    def study_levels(self, quick: bool = False) -> tuple:
        return tuple(self.quick_levels if quick and self.quick_levels else self.levels)

    def extra(self) -> dict:
        """The further :class:`experiments.scenario.Scenario` fields (its solver)."""
        return {} if self.solver == DEFAULT_SOLVER else {"solver": self.solver}

    @property
    def lever_label(self) -> str:
        return self.lever.label if self.lever is not None else "none"


def _tuples(d: Mapping) -> dict:
    return {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()}


def _with(field_: str, i: int, value: float) -> list[float]:
    """The default of a tuple field with entry ``i`` set to ``value``."""
    v = [float(x) for x in getattr(DEFAULTS, field_)]
    v[i] = value
    return v


R_OW = 2  # the index of R_ow in MPCSettings.R = (R_dw, R_dd, R_ow, R_od)
WHEEL_RIDGE = 0.05  # R_ow of the references NTWO-wheel (10x the default) and its variants
_WHEEL = {"model": "mf", "method": "ntwo", "R": _with("R", R_OW, WHEEL_RIDGE)}
# the paper's raw decision vector U: 4x the annealing budget; the commands' own smoothing
# (R_dw, R_dd) and no ridge (the commands are not offsets from anything)
_RAW = {"policy": "raw", "iterations": 4 * DEFAULTS.iterations, "R": [0.05, 0.2, 0.0, 0.0]}

_TABLE = (
    # ---- the paper's five (Section 4.2), in its tables' order -----------------------------
    # the paper's Kinematic "considers only geometric relationships": every wheel steered
    # about one instantaneous centre, the decision is the body twist
    Family("Kinematic", "the paper's kinematic method: every wheel about one centre",
           {"model": "kinematic", "method": "ntwo", "policy": "twist"}, paper=True,
           style=("C7", "v")),
    Family("DH", "the paper's DH: Dugoff tires, stiffnesses the plant's at its load",
           {"model": "dugoff", "method": "ntwo"}, paper=True, style=("C2", "D")),
    Family("TCT", "the paper's TCT: lateral and yaw dynamics only",
           {"model": "tct", "method": "ntwo"}, paper=True, style=("C4", "P")),
    Family("NTWO", "the paper's wear-blind MPC (no wear term)",
           {"model": "mf", "method": "ntwo"}, paper=True, style=("C0", "o")),
    Family("TWO", "the paper's MPC with its quadratic wear term P^T L P",
           {"model": "mf", "method": "two"}, lever=Lever("L", "L x", scale=True),
           levels=(0.05, 0.25, 1.0, 4.0), quick_levels=(0.25,), case_level=1.0,
           wear_aware=True, paper=True, style=("C3", "^")),
    # ---- the references every case table carries ------------------------------------------
    Family("FF", "the feed-forward policy alone, no optimisation",
           {"model": "mf", "method": "ntwo"}, solver="ff", case_row=True, style=("0.4", "x")),
    # NTWO with 10x the default ridge on the wheel-speed offsets only: the wheels near pure
    # rolling, the steering as free as NTWO's
    Family("NTWO-wheel", "NTWO with a ridge on the wheel-speed offsets only (wheels near "
           "pure rolling)", _WHEEL, lever=Lever("R", "R_ow", components=(R_OW,)),
           levels=(WHEEL_RIDGE, 0.2, 1.0), quick_levels=(0.2,), case_row=True, case_level=WHEEL_RIDGE,
           style=("C9", "s")),
    Family("TWO-energy", "a linear wear-energy term E . P (its sum over the horizon is the "
           "predicted wear work)", {"model": "mf", "method": "two-energy"},
           lever=Lever("E", "E", unit="1/kW"), levels=(0.003, 0.01, 0.03, 0.1, 0.3),
           quick_levels=(0.01, 0.1), case_row=True, case_level=DEFAULTS.E[0], wear_aware=True,
           style=("C1", "*")),
    # ---- the study's further wear-blind levers: the blind side may trade accuracy for
    # wear as the wear-aware families do ---------------------------------------------------
    Family("NTWO-wheel-Q", "NTWO-wheel with its tracking weights Q lowered", _WHEEL,
           lever=Lever("Q", "Q x", scale=True), levels=(0.3, 0.1, 0.03), quick_levels=(0.1,),
           style=("C6", "d")),
    Family("NTWO-wheel-cut", "NTWO-wheel tracking its reference smoothed along the path: "
           "cuts each corner by about sigma^2 kappa / 2", _WHEEL,
           lever=Lever("ref_smoothing", "sigma", unit="m"), levels=(0.35, 0.5, 0.7, 1.0, 1.4),
           quick_levels=(0.5, 1.0), not_in=("case2",), style=("navy", "h")),
    # ---- Case 2's wear-blind recovery levers (issue 29 item 2): how hard the blind side
    # turns back to the line. The feed-forward's pose feedback (controller.rollout.
    # policy_head): its yaw-rate limit r_fb_max, its position gain K_pos and the limit of its
    # velocity correction v_fb_max (the speed at which it closes a lateral gap); and NTWO's
    # heading weight Q_phi. Case 2 only: elsewhere the recovery is not the question, and the
    # other classes' numbers stay as they were ---------------------------------------------
    Family("FF-yaw", "the feed-forward alone with its yaw-rate limit r_fb_max set",
           {"model": "mf", "method": "ntwo"}, solver="ff",
           lever=Lever("r_fb_max", "r_fb_max", unit="rad/s"),
           levels=(0.15, 0.2, 0.25, 0.35, 0.45, 0.6, 0.8, 1.0), quick_levels=(0.45,),
           classes=("case2",), style=("0.25", "1")),
    Family("FF-pos", "the feed-forward alone with its position gain K_pos set",
           {"model": "mf", "method": "ntwo"}, solver="ff",
           lever=Lever("K_pos", "K_pos", unit="1/s"), levels=(0.5, 0.7, 1.5, 2.0, 3.0),
           quick_levels=(1.5,), classes=("case2",), style=("0.25", "2")),
    Family("FF-speed", "the feed-forward alone with the limit v_fb_max of its velocity "
           "correction set", {"model": "mf", "method": "ntwo"}, solver="ff",
           lever=Lever("v_fb_max", "v_fb_max", unit="m/s"), levels=(0.5, 0.75, 1.0, 2.0, 3.0),
           quick_levels=(1.0,), classes=("case2",), style=("0.25", "3")),
    Family("NTWO-heading", "NTWO with its heading weight Q_phi scaled",
           {"model": "mf", "method": "ntwo"},
           lever=Lever("Q", "Q_phi x", scale=True, components=(2,)),
           levels=(0.1, 0.3, 3.0, 10.0), quick_levels=(0.3,), classes=("case2",),
           style=("C0", "4")),
    # ---- the decision-parametrisation factor: the paper's raw U, 4x the annealing budget -
    Family("NTWO-raw", "NTWO on the paper's raw decision vector U (4x the annealing budget)",
           dict(_RAW, model="mf", method="ntwo"), raw=True, style=("C8", "<")),
    Family("TWO-energy-raw", "TWO-energy on the paper's raw decision vector U (4x the "
           "annealing budget)", dict(_RAW, model="mf", method="two-energy"),
           lever=Lever("E", "E", unit="1/kW"), levels=(0.03, 0.1), quick_levels=(0.1,),
           wear_aware=True, raw=True, style=("C5", ">")),
    # ---- pareto's and ridge's levers on NTWO ---------------------------------------------
    Family("NTWO-smooth", "NTWO with its smoothing of the offsets (R_dw, R_dd) scaled",
           {"model": "mf", "method": "ntwo"},
           lever=Lever("R", "R_dw,R_dd x", scale=True, components=(0, 1)),
           levels=(0.0, 1.0, 4.0, 16.0, 64.0, 256.0), study=False, style=("C0", "o")),
    Family("NTWO-ridge", "NTWO with its ridge on the offsets (R_ow, R_od) scaled (x0.1 is "
           "the default)", {"model": "mf", "method": "ntwo"},
           lever=Lever("R", "R_ow,R_od x", scale=True, components=(2, 3), base=RIDGE_BASE),
           levels=(0.0, 0.1, 0.3, 1.0, 4.0, 16.0), study=False, style=("C8", "p")),
)
FAMILIES: dict[str, Family] = {f.name: f for f in _TABLE}


def case_rows() -> list[Family]:
    """The rows of the case tables: the paper's five in its order, then the references."""
    return [f for f in FAMILIES.values() if f.case_row]


def paper_methods() -> list[str]:
    """The names of the paper's five methods, in its tables' order."""
    return [f.name for f in FAMILIES.values() if f.paper]


def study_families(raw: bool = False, cls: str | None = None) -> list[Family]:
    """The families the study sweeps in a scenario of the class ``cls`` (``raw``: with the
    raw-U factor; ``cls`` None: the families of every class)."""
    return [f for f in FAMILIES.values()
            if f.study and (raw or not f.raw) and f.in_class(cls)]


def wear_aware() -> set[str]:
    return {f.name for f in FAMILIES.values() if f.wear_aware}


def methods_help() -> str:
    """``--methods``: the case tables' rows, each with its one line."""
    return "; ".join(f"{f.name}: {f.summary}" for f in case_rows())
