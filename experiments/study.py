"""The study: does a wear term in the MPC cut tire wear, and at what cost in tracking?

``msagv experiment study`` answers the paper's question on many scenarios, against the
strongest wear-blind references, at matched accuracy, with confidence intervals:

* **Families**, each swept over its own lever (:data:`FAMILIES`): the paper's TWO
  (quadratic wear term ``P^T L P``, lever: a factor on L), TWO-energy (a linear wear-energy
  term ``E . P``, lever: E), the paper's NTWO (no wear term), NTWO-wheel (NTWO with a
  ridge on the wheel-speed offsets only, lever: R_ow: wheels near pure rolling), FF (the
  feed-forward policy alone, no optimisation), and the paper's baselines Kinematic (every
  wheel about one centre), DH (Dugoff tires derived from the plant's) and TCT. Every
  optimising family gets the same annealer, budget, horizon and tracking weights.
* **The decision parametrisation as a factor** (on a subset): NTWO and TWO-energy with the
  paper's own decision vector (the raw commands U of eq. 27) and four times the annealing
  budget, against our feed-forward offsets.
* **Scenarios** (:func:`design`): the paper's Case 1 curve and Case 2 line, a lane change,
  a tight turn and seeded random paths (:mod:`controller.paths`), 5-35 km/h, 8-20 t, 2 and
  4 axles, several annealer seeds; and robustness with the plant unlike the controller's
  model: combined-slip tires, tire coefficients +-20 %, load transfer with actuator lags.
* **Wear floors** (:mod:`controller.floors`): each scenario's wear that exact tracking
  cannot avoid, so runs are also compared on the wear above it.

Runs are cached and resumable (:mod:`experiments.runs`), spread by Dask over a local
cluster or the one at ``--scheduler``. The analysis is :mod:`experiments.study_report`.
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from .runs import PERIOD, RunSpec, code_digest, dask_map, run_all

# family -> (lever name, levels, settings at a level, solver, wear-aware?)
# levels are chosen to span each family's front from "as accurate as NTWO" to "cuts
# corners" (docs/RESULTS.md, "The study")
_DEFAULT_L = (0.02, 0.01, 0.02)
_DEFAULT_R = (0.05, 20.0, 0.005, 2.0)
_DEFAULT_Q = (200.0, 200.0, 1000.0)
FAMILIES = {
    "FF": ("none", (None,), lambda x: {"method": "ntwo"}, "ff", False),
    "NTWO": ("none", (None,), lambda x: {"method": "ntwo"}, "sa", False),
    "NTWO-wheel": ("R_ow", (0.05, 0.2, 1.0),
                   lambda x: {"method": "ntwo", "R": [_DEFAULT_R[0], _DEFAULT_R[1], x,
                                                      _DEFAULT_R[3]]}, "sa", False),
    # the same wear-blind controller with an accuracy lever, as the wear-aware families
    # have one: the tracking weights Q scaled down (towards the feed-forward, which the
    # ridge and smoothing pull to), so the blind front may also trade accuracy for wear
    "NTWO-wheel-Q": ("Q x", (0.3, 0.1, 0.03),
                     lambda x: {"method": "ntwo", "Q": [x * v for v in _DEFAULT_Q],
                                "R": [_DEFAULT_R[0], _DEFAULT_R[1], 0.05, _DEFAULT_R[3]]},
                     "sa", False),
    "Kinematic": ("none", (None,), lambda x: {"model": "kinematic", "method": "ntwo",
                                              "policy": "twist"}, "sa", False),
    "DH": ("none", (None,), lambda x: {"model": "dugoff", "method": "ntwo"}, "sa", False),
    "TCT": ("none", (None,), lambda x: {"model": "tct", "method": "ntwo"}, "sa", False),
    "TWO": ("L x", (0.05, 0.25, 1.0, 4.0),
            lambda x: {"method": "two", "L": [x * v for v in _DEFAULT_L]}, "sa", True),
    "TWO-energy": ("E", (0.003, 0.01, 0.03, 0.1),
                   lambda x: {"method": "two-energy", "E": [x, x, x]}, "sa", True),
}
# the decision-parametrisation factor: the paper's raw U with 4x the annealing budget
# (4 x the default 40 iterations)
RAW_FAMILIES = {
    "NTWO-raw": ("none", (None,), lambda x: {"method": "ntwo", "policy": "raw",
                                             "iterations": 160, "R": [0.05, 0.2, 0.0, 0.0]},
                 "sa", False),
    "TWO-energy-raw": ("E", (0.03, 0.1),
                       lambda x: {"method": "two-energy", "E": [x, x, x], "policy": "raw",
                                  "iterations": 160, "R": [0.05, 0.2, 0.0, 0.0]}, "sa", True),
}
WEAR_AWARE = {f for f, v in {**FAMILIES, **RAW_FAMILIES}.items() if v[4]}
QUICK_LEVELS = {"NTWO-wheel": (0.2,), "NTWO-wheel-Q": (0.1,), "TWO": (0.25,), "TWO-energy": (0.01, 0.1),
                "TWO-energy-raw": (0.1,)}

# robustness: the plant unlike the controller's model (the controller keeps the nominal)
PLANTS = {
    "nominal": {},
    "combined-slip": {"plant_options": {"combined_slip": 1.0}},
    "tires+20%": {"plant_tire_scale": 1.2},
    "tires-20%": {"plant_tire_scale": 0.8},
    "load-transfer+lags": {"plant_options": {"cg_height": 1.2, "wheel_lag": 0.05,
                                             "steer_lag": 0.05}},
}


@dataclass
class StudyScenario:
    """One scenario instance: a path at a speed, a vehicle and load, a plant, a seed."""

    cls: str  # the class the summary groups by (case1, case2, lane, turn, random, user, ...)
    case: str  # Scenario.case: curve, line, lane, turn, random, or 'file' (a trajectory)
    speed: float | None  # km/h (None for a trajectory file)
    mass_kg: float | None = None
    axles: int | None = None
    path_seed: int = 0
    plant: str = "nominal"
    seed: int = 0  # the annealer's
    duration: float | None = None
    vehicle: str | None = None
    trajectory: str | None = None
    raw: bool = False  # also run the raw-decision families here
    extra: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        if self.case == "random":
            first = (f"random-{self.path_seed}" if self.cls == "random"
                     else f"{self.cls} random-{self.path_seed}")
        elif self.cls in ("case1", "case2", "lane", "turn", "user"):  # the class is the path
            first = self.cls
        else:  # a class over several paths (load, 4-axle, robust): name the path too
            first = f"{self.cls} {self.case}"
        parts = [first]
        if self.speed is not None:
            parts.append(f"{self.speed:g} km/h")
        if self.mass_kg is not None:
            parts.append(f"{self.mass_kg / 1000:g} t")
        if self.axles:
            parts.append(f"{self.axles} axles")
        if self.plant != "nominal":
            parts.append(self.plant)
        parts.append(f"seed {self.seed}")
        return ", ".join(parts)

    @property
    def path_key(self) -> str:
        """What determines the reference, the plant's vehicle and the window (the floors)."""
        d = {k: getattr(self, k) for k in ("case", "speed", "mass_kg", "axles", "path_seed",
                                           "plant", "duration", "vehicle", "trajectory")}
        if self.trajectory:
            d["trajectory_sha"] = hashlib.sha256(Path(self.trajectory).read_bytes()).hexdigest()
        if self.vehicle:
            d["vehicle_sha"] = hashlib.sha256(Path(self.vehicle).read_bytes()).hexdigest()
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]

    def extra_fields(self) -> dict:
        ex = dict(PLANTS[self.plant])
        if self.axles:
            ex["axles"] = self.axles
        if self.case == "random":
            ex["path_seed"] = self.path_seed
        if self.trajectory:
            ex["trajectory"] = self.trajectory
        ex.update(self.extra)
        return ex

    def scenario(self, settings=None, solver="sa"):
        """The :class:`experiments.scenario.Scenario` of this instance."""
        from .scenario import Scenario

        ex = self.extra_fields()
        traj = ex.pop("trajectory", None)
        return Scenario(vehicle=self.vehicle, mass_kg=self.mass_kg,
                        case=None if traj else self.case, trajectory=traj,
                        speed=None if traj else self.speed, duration=self.duration,
                        settings=dict(settings or {}), solver=solver, period=PERIOD, **ex)


def design(quick: bool = False, vehicle: str | None = None,
           trajectory: str | None = None) -> list[StudyScenario]:
    """The scenario instances of the default (or ``quick``) design, plus a user scenario
    when ``vehicle`` or ``trajectory`` is given (docs/RESULTS.md lists the design)."""
    S = StudyScenario
    out: list[StudyScenario] = []
    if quick:
        out += [S("case1", "curve", 35.0, duration=10.0, raw=True),
                S("case2", "line", 10.0, duration=8.0),
                S("lane", "lane", 15.0, duration=10.0),
                S("random", "random", 20.0, path_seed=1, duration=8.0),
                S("random", "random", 20.0, path_seed=2, duration=8.0)]
    else:
        # the paper's Case 1 at its four speeds (5 km/h: the first 30 s of 108 s), Case 2
        for v in (5.0, 15.0, 25.0, 35.0):
            for seed in (range(5) if v in (15.0, 35.0) else (0,)):
                out.append(S("case1", "curve", v, seed=seed, duration=30.0 if v == 5 else None,
                             raw=seed == 0 and v in (15.0, 35.0)))
        out.append(S("case2", "line", 10.0))
        out += [S("lane", "lane", v) for v in (15.0, 30.0)]
        out += [S("turn", "turn", v) for v in (10.0, 20.0)]
        out += [S("random", "random", v, path_seed=k, duration=15.0)
                for k in range(1, 6) for v in (10.0, 25.0)]
        # loads (Case 3's question on other paths too)
        for m in (8000.0, 20000.0):
            out.append(S("load", "curve", 25.0, mass_kg=m))
            out += [S("load", "random", 20.0, mass_kg=m, path_seed=k, duration=15.0)
                    for k in (1, 2)]
        # a 4-axle vehicle (same load per wheel)
        out += [S("4-axle", "curve", v, axles=4) for v in (15.0, 35.0)]
        out.append(S("4-axle", "lane", 15.0, axles=4))
        out += [S("4-axle", "random", 20.0, axles=4, path_seed=k, duration=15.0)
                for k in range(1, 6)]
        # the plant unlike the model
        for plant in PLANTS:
            if plant == "nominal":
                continue
            out += [S("robust", "curve", 25.0, plant=plant),
                    S("robust", "random", 20.0, plant=plant, path_seed=1, duration=15.0),
                    S("robust", "lane", 15.0, plant=plant)]
    if vehicle or trajectory:
        seeds = (0, 1, 2)
        if trajectory:
            out += [S("user", "file", None, vehicle=vehicle, trajectory=trajectory, seed=s,
                      duration=10.0 if quick else None) for s in seeds]
        else:
            out += [S("user", "random", 20.0, vehicle=vehicle, path_seed=1, seed=s,
                      duration=8.0 if quick else 15.0) for s in seeds]
    return out


def _levels(fam: str, levels, quick: bool):
    return QUICK_LEVELS.get(fam, levels) if quick else levels


def run_specs(scenarios: list[StudyScenario], quick: bool = False) -> list[RunSpec]:
    """Every run of the study: each family at each lever level in each scenario."""
    specs = []
    for sc in scenarios:
        fams = dict(FAMILIES)
        if sc.raw:
            fams.update(RAW_FAMILIES)
        for fam, (lever, levels, make, solver, aware) in fams.items():
            for x in _levels(fam, levels, quick):
                st = dict(make(x), seed=sc.seed)
                label = fam if x is None else f"{fam} {lever}={x:g}"
                extra = sc.extra_fields()
                if solver != "sa":
                    extra["solver"] = solver
                traj = extra.pop("trajectory", None)
                if traj:
                    extra["trajectory"] = traj
                specs.append(RunSpec(label, sc.name, "file" if traj else sc.case,
                                     0.0 if sc.speed is None else float(sc.speed), sc.mass_kg,
                                     st, sc.duration, sc.vehicle,
                                     {"family": fam, "lever": lever, "level": x,
                                      "aware": aware, "scenario": sc.name, "class": sc.cls,
                                      "plant": sc.plant, "path_key": sc.path_key,
                                      "seed": sc.seed}, extra))
    return specs


# ---- the floors, once per path ------------------------------------------------------------------
def floor_task(sc_dict: dict, digest: str) -> dict:
    """The wear floors of one scenario's reference (a Dask task): ``{key, floors}``."""
    from msagv.controller.floors import wear_floors

    t0 = time.perf_counter()
    sc = StudyScenario(**sc_dict)
    scen = sc.scenario()
    vehicle = scen.plant_vehicle(scen.resolve_vehicle())
    ref, _ = scen.reference()
    dur = scen.run_duration(ref)
    f = wear_floors(ref, vehicle, float(ref.t[0]), float(ref.t[0]) + dur, dt=0.05)
    return {"key": sc.path_key, "floors": f.as_dict(), "duration": dur, "code": digest,
            "wall_s": time.perf_counter() - t0}


def compute_floors(scenarios: list[StudyScenario], out: Path, jobs=None, scheduler=None,
                   force: bool = False, progress: bool = True) -> dict[str, dict]:
    """The floors of every distinct path (cached under ``OUT/floors/``); ``progress``: a bar
    over the paths on stderr (the default design's floors take ~10 minutes on 2 cores)."""
    from dataclasses import asdict

    d = out / "floors"
    d.mkdir(parents=True, exist_ok=True)
    digest = code_digest()
    have, todo = {}, {}
    for sc in scenarios:
        k = sc.path_key
        p = d / f"{k}.json"
        if not force and p.is_file():
            old = json.loads(p.read_text())
            if old.get("code") == digest:
                have[k] = old
                continue
        todo.setdefault(k, asdict(sc))

    bar = None
    if progress and todo:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), desc="wear floors", unit="path", file=sys.stderr,
                   dynamic_ncols=True)

    def done(res):
        (d / f"{res['key']}.json").write_text(json.dumps(res, indent=1))
        have[res["key"]] = res
        if bar is not None:
            bar.update(1)

    try:
        if todo and (jobs == 1 and scheduler is None):
            for sc_d in todo.values():
                done(floor_task(sc_d, digest))
        elif todo:
            dask_map(floor_task, [(v, digest) for v in todo.values()], done, jobs=jobs,
                     scheduler=scheduler)
    finally:
        if bar is not None:
            bar.close()
    return have


def run_study(out: str | Path | None = None, *, quick: bool = False, jobs: int | None = None,
              scheduler: str | None = None, force: bool = False, progress: bool = True,
              vehicle: str | None = None, trajectory: str | None = None) -> dict:
    """Run (or resume) the study and write its report; returns the summary."""
    from .study_report import report_study

    for p, what in ((vehicle, "--vehicle"), (trajectory, "--trajectory")):
        if p is not None and not Path(p).is_file():
            raise FileNotFoundError(f"{what}: {p}: no such file")
    out = Path(out) if out is not None else Path("runs") / ("study-quick" if quick else "study")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scenarios = design(quick, vehicle, trajectory)
    for sc in scenarios:  # a bad user file fails now, in one line, before any run
        sc.scenario().reference()
    floors = compute_floors(scenarios, out, jobs, scheduler, force, progress)
    specs = run_specs(scenarios, quick)
    results, summ = run_all(specs, out, jobs=jobs, force=force, progress=progress,
                            desc="study", scheduler=scheduler)
    summ["total_wall_s"] = time.perf_counter() - t0
    summ["design"] = "quick" if quick else "default"
    summ["scenarios"] = len(scenarios)
    return report_study(results, floors, scenarios, out, summ)
