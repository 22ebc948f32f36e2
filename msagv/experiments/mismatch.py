"""The study's question for a vehicle whose tires the controller does not know:
``msagv experiment mismatch``.

A real vehicle's tire coefficients are never known to 10 %. This experiment asks the
study's question (:mod:`experiments.study`: does a wear term save wear at the same tracking
error?) on plants unlike the controller's vehicle file, in four columns of what the
controller knows:

* ``wrong``: the file's vehicle (the paper's), as a user who never measured the tires;
* ``identified``: the vehicle ``msagv calibrate`` identifies from one logged run of that
  plant (the excitation manoeuvre of ``msagv calibrate --maneuver``, driven by the default
  controller with the file's vehicle; :func:`identify_task`);
* ``adapted``: the file's vehicle with the online tire adaptation (``--adapt``) in every
  family whose model has tires (the ``mf``, ``dugoff`` and ``tct`` models; the kinematic
  family, with none, runs as in the other columns);
* ``true``: the plant's own vehicle file (the model right).

Every family of the study in each column, each with the offset-free disturbance on (the
same action for every family: the kinematic model's too, whose default is off). The paths
are random paths drawn for the file's vehicle (seeds 1..N at 15, 20 and 25 km/h in turn,
15 s each) and written as ``t,x,y,phi`` files, so every column drives the same path
whatever vehicle the controller believes in. The plants (:data:`PLANTS`): the Magic
Formula's stiffness factor B and peak friction mu together x0.7 to x1.3, each alone x0.8
and x1.2, combined slip, load transfer with actuator lags.

The ratio per scenario is the study's (:func:`experiments.study_analysis.compare`: each
side's front, the geometric mean at equal error; unmatched scenarios counted and entered at
their most-accurate ratio in a second column). Across scenarios the 95 % interval is a
percentile bootstrap that resamples *paths* as blocks (every plant and seed of a path goes
in or out together: the plants share the paths), each scenario's seeds averaged in logs
first. ``identified - true`` and ``adapted - true`` are the paired differences of the
geometric means over the same path blocks.

The wear floors are not computed here (a floor per plant and path would take longer than
the runs): the ratios need none.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from .checks import ScenarioError
from .runs import PERIOD, code_digest, dask_map, run_all
from .study import StudyScenario, check_noise, default_out, run_specs, with_noise
from .study_analysis import _f, _ratio_text, noise_text

# the plants unlike the file: factors on the Magic Formula's B and mu (both curves), or the
# plant's own options (vehicle file [plant])
PLANTS: dict[str, dict] = {
    "tires x0.7": {"B": 0.7, "mu": 0.7},
    "tires x0.8": {"B": 0.8, "mu": 0.8},
    "tires x0.9": {"B": 0.9, "mu": 0.9},
    "tires x1.1": {"B": 1.1, "mu": 1.1},
    "tires x1.2": {"B": 1.2, "mu": 1.2},
    "tires x1.3": {"B": 1.3, "mu": 1.3},
    "B x0.8": {"B": 0.8},
    "B x1.2": {"B": 1.2},
    "mu x0.8": {"mu": 0.8},
    "mu x1.2": {"mu": 1.2},
    "combined-slip": {"plant": {"combined_slip": 1.0}},
    "load-transfer+lags": {"plant": {"cg_height": 1.2, "wheel_lag": 0.05, "steer_lag": 0.05}},
}
MODELS = ("wrong", "identified", "adapted", "true")
COLUMN_SETTINGS = {"wrong": {"offset_free": True}, "identified": {"offset_free": True},
                   "adapted": {"offset_free": True, "adapt": True},
                   "true": {"offset_free": True}}
PATH_SPEEDS = (15.0, 20.0, 25.0)  # km/h, path p at PATH_SPEEDS[(p - 1) % 3]
DURATION = 15.0  # s of each path
PATHS = 10
SEEDS = (0, 1, 2)
QUICK = {"plants": ("tires x0.8", "tires x1.2"), "paths": 2, "seeds": 1}


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in name).strip("-")


def is_plant_file(name: str) -> bool:
    """A plant given as a vehicle file of its own (``--plants my_plant.toml``), not a name
    of :data:`PLANTS`."""
    return name.endswith(".toml")


def plant_vehicle(base, name: str):
    """The plant ``name`` of :data:`PLANTS` made from the vehicle ``base``."""
    from msagv.plant.vehicle import vehicle_from_dict

    spec = PLANTS[name]
    d = base.to_dict()
    for part in ("longitudinal", "lateral"):
        for k in ("B", "mu"):
            d["tire"][part][k] *= spec.get(k, 1.0)
    d["plant"].update({k: float(v) for k, v in spec.get("plant", {}).items()})
    d["name"] = f"{base.name} ({name})"
    return vehicle_from_dict(d)


def parse_plants(text: str | None) -> tuple[str, ...]:
    """``--plants``: names of :data:`PLANTS` or vehicle files of plants of your own
    (``*.toml``), comma-separated (``all``: every name of :data:`PLANTS`)."""
    if text is None or text.strip() == "all":
        return tuple(PLANTS)
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in PLANTS and not is_plant_file(n)]
    if bad or not names:
        raise ScenarioError(f"--plants: unknown plant '{bad[0] if bad else text}' (known: "
                            f"{', '.join(PLANTS)}, or all, or a plant's vehicle file *.toml)")
    if len(set(names)) != len(names):
        raise ScenarioError(f"--plants: a plant named twice in '{text}'")
    slugs = [_plant_slug(n) for n in names]
    if len(set(slugs)) != len(slugs):
        raise ScenarioError(f"--plants: two plant files of one name in '{text}' (their "
                            f"copies and results are kept by file name: rename one)")
    return names


def _plant_slug(name: str) -> str:
    """The name a plant's files take under ``OUT/`` (a plant file's: its file name)."""
    return _slug(Path(name).name if is_plant_file(name) else name)


def check_vehicles(plants, vehicle: str | None = None, trajectory: str | None = None):
    """The controller's vehicle, each plant file and the path load, and every plant has the
    vehicle's axles (a clear error before anything runs); returns the base vehicle."""
    from msagv.controller.reference import ReferenceError, from_csv
    from msagv.plant.vehicle import VehicleError, default_vehicle, load_vehicle

    try:
        base = load_vehicle(vehicle) if vehicle else default_vehicle()
    except (VehicleError, OSError) as e:
        raise ScenarioError(f"--vehicle: {e}") from None
    for name in plants:
        if not is_plant_file(name):
            continue
        try:
            own = load_vehicle(name)
        except (VehicleError, OSError) as e:
            raise ScenarioError(f"--plants: {e}") from None
        if own.n_axles != base.n_axles:
            raise ScenarioError(f"--plants: {name} has {own.n_axles} axles, the controller's "
                                f"vehicle {base.name} {base.n_axles}")
    if trajectory is not None:
        try:
            from_csv(trajectory)
        except (ReferenceError, OSError) as e:
            raise ScenarioError(f"--trajectory: {e}") from None
    return base


# ---- the inputs: paths and plants as files -----------------------------------------------------
def write_inputs(out: Path, plants, n_paths: int, vehicle: str | None = None,
                 trajectory: str | None = None, base=None
                 ) -> tuple[list[Path], dict[str, Path], Path]:
    """The path files, the plants' vehicle files and the manoeuvre under ``OUT/inputs/``
    (written once, deterministic: rewriting them gives the same bytes). ``vehicle``: the
    controller's vehicle file (default the paper's), which the factor plants, the random
    paths and the manoeuvre are made for; ``trajectory``: your own path instead of the
    random ones; a plant given as a file is copied as it is. ``base``: that vehicle, where
    the caller has loaded it (:func:`check_vehicles`)."""
    from msagv.experiments.calibrate import maneuver, maneuver_csv, vehicle_toml
    from msagv.experiments.scenario import Scenario
    from msagv.plant.vehicle import default_vehicle, load_vehicle

    d = out / "inputs"
    d.mkdir(parents=True, exist_ok=True)
    if base is None:
        base = load_vehicle(vehicle) if vehicle else default_vehicle()

    def put(p: Path, text: str | bytes) -> Path:
        data = text if isinstance(text, bytes) else text.encode()
        if not p.is_file() or p.read_bytes() != data:
            p.write_bytes(data)
        return p

    def random_path(p: int) -> Path:
        v = PATH_SPEEDS[(p - 1) % len(PATH_SPEEDS)]
        ref, _ = Scenario(case="random", speed=v, path_seed=p, duration=DURATION,
                          vehicle=vehicle).reference()
        lines = ["t,x,y,phi"] + [f"{t!r},{x!r},{y!r},{ph!r}" for t, x, y, ph in
                                 zip(ref.t.tolist(), ref.x.tolist(), ref.y.tolist(),
                                     ref.phi.tolist())]
        return put(d / f"random-{p}-{v:g}kmh.csv", "\n".join(lines) + "\n")

    paths = ([put(d / Path(trajectory).name, Path(trajectory).read_bytes())]
             if trajectory is not None else [random_path(p) for p in range(1, n_paths + 1)])
    files = {name: put(d / f"plant-{_plant_slug(name)}.toml",
                       Path(name).read_bytes() if is_plant_file(name) else
                       vehicle_toml(plant_vehicle(base, name),
                                    f"msagv experiment mismatch: the plant '{name}'"))
             for name in plants}
    man = put(d / "maneuver.csv", maneuver_csv(maneuver(base)))
    return paths, files, man


# ---- the identified column: one logged run of the plant, then msagv calibrate ----------------
def logged_run(plant_file: str, maneuver_csv: str, vehicle: str | None = None,
               noise: dict | None = None):
    """The excitation manoeuvre driven by the default controller that believes the file's
    vehicle (``vehicle``, default the paper's), on the plant of ``plant_file``: its states
    and commands as
    :class:`plant.identify.RunData` (what the plant's recording holds, in process). With
    ``noise`` (``Scenario.measurement_noise``) the body's states are the measured ones, as
    a real vehicle's log holds them and as the controller received them."""
    from msagv.controller.loop import closed_loop
    from msagv.experiments.scenario import Scenario
    from msagv.plant.identify import RunData

    sc = Scenario(trajectory=maneuver_csv, plant_vehicle=plant_file, after_end="stop",
                  vehicle=vehicle, settings={"threads": 1}, measurement_noise=noise)
    b = sc.build()
    rows = []
    seen = {}

    def measure(st):  # what the controller receives is what the log keeps
        seen["st"] = st if b.measure is None else b.measure(st)
        return seen["st"]

    def on_step(k, st, cmd):
        m = seen["st"]
        rows.append((st["t"], [m[f] for f in ("x", "y", "phi", "vx", "vy", "r")],
                     list(st["delta"]), list(st["omega_w"]), list(cmd.omega_w),
                     list(cmd.omega_s)))

    try:
        closed_loop(b.plant, b.controller, b.reference, b.duration, period=PERIOD,
                    on_step=on_step, progress=False, outputs=False, measure=measure)
    finally:
        b.close()
    cols = list(zip(*rows))
    return RunData(*(np.array(c, dtype=float) for c in cols))


def identify_task(name: str, plant_file: str, maneuver_csv: str, out_toml: str,
                  digest: str, vehicle: str | None = None, noise: dict | None = None) -> dict:
    """One plant's identified vehicle (a Dask task): the logged run (measured with
    ``noise``), ``calibrate`` on it, the vehicle file written to ``out_toml``; returns the
    estimates against the plant's truth."""
    from msagv.experiments.calibrate import vehicle_toml
    from msagv.plant.identify import calibrate, values_of
    from msagv.plant.vehicle import default_vehicle, load_vehicle

    t0 = time.perf_counter()
    base = load_vehicle(vehicle) if vehicle else default_vehicle()
    data = logged_run(plant_file, maneuver_csv, vehicle, noise)
    cal = calibrate(data, base, name=f"{base.name} (identified: {name})")
    Path(out_toml).write_text(vehicle_toml(
        cal.vehicle, f"msagv experiment mismatch: identified from a logged run of '{name}'"))
    truth = values_of(load_vehicle(plant_file))
    est = {p: {"value": e.value, "truth": truth.get(p), "base": e.base, "se": e.se,
               "identified": e.identified, "why": e.why} for p, e in cal.estimates.items()}
    return {"plant": name, "estimates": est, "seconds": cal.seconds, "code": digest,
            "vehicle": out_toml, "wall_s": time.perf_counter() - t0}


def identify_key(plant_file: Path, man: Path, digest: str, vehicle: str | None = None,
                 noise: dict | None = None) -> str:
    """The cache key of a plant's identified vehicle: its file, the manoeuvre, the code (the
    plant's and controller's ``digest``, the logged run's and the identification's here,
    ``experiments/calibrate.py``), the controller's vehicle file and the measurement
    noise."""
    import inspect

    h = hashlib.sha256(Path(plant_file).read_bytes() + Path(man).read_bytes() + digest.encode())
    h.update(Path(vehicle).read_bytes() if vehicle else b"")
    h.update((inspect.getsource(logged_run) + inspect.getsource(identify_task)).encode())
    h.update((Path(__file__).parent / "calibrate.py").read_bytes())
    if noise:
        h.update(json.dumps(noise, sort_keys=True).encode())
    return h.hexdigest()[:16]


def identify_plants(files: dict[str, Path], man: Path, out: Path, jobs=None, scheduler=None,
                    force: bool = False, progress: bool = True,
                    vehicle: str | None = None, noise: dict | None = None
                    ) -> dict[str, dict]:
    """Every plant's identified vehicle, cached under ``OUT/identified/`` (by the plant's
    file, the manoeuvre, the controller's vehicle file, the measurement noise and the
    code: the plant's and controller's (:func:`experiments.runs.code_digest`), the logged
    run's and the identification's here, and ``experiments/calibrate.py``)."""
    d = out / "identified"
    d.mkdir(parents=True, exist_ok=True)
    digest = code_digest()
    have, todo = {}, []
    for name, f in files.items():
        key = identify_key(f, man, digest, vehicle, noise)
        js, toml = d / f"{_plant_slug(name)}.json", d / f"{_plant_slug(name)}.toml"
        if not force and js.is_file() and toml.is_file():
            old = json.loads(js.read_text())
            if old.get("key") == key:
                have[name] = dict(old, vehicle=str(toml))  # where this output keeps it
                continue
        todo.append((name, str(f), str(man), str(toml), digest, vehicle, noise, key, js))
    bar = None
    if progress and todo:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), desc="identify the plants", unit="plant",
                   file=sys.stderr, dynamic_ncols=True)
    keys = {t[0]: (t[7], t[8]) for t in todo}

    def done(res):
        key, js = keys[res["plant"]]
        res["key"] = key
        js.write_text(json.dumps(res, indent=1))
        have[res["plant"]] = res
        if bar is not None:
            bar.update(1)

    try:
        args = [t[:7] for t in todo]
        if args and jobs == 1 and scheduler is None:
            for a in args:
                done(identify_task(*a))
        elif args:
            dask_map(identify_task, args, done, jobs=jobs, scheduler=scheduler)
    finally:
        if bar is not None:
            bar.close()
    return have


# ---- the design ----------------------------------------------------------------------------
def design(paths: list[Path], files: dict[str, Path], identified: dict[str, dict],
           seeds=SEEDS, vehicle: str | None = None,
           duration: float | None = DURATION, noise: dict | None = None
           ) -> list[StudyScenario]:
    """Every (path, plant, column, seed) as a study scenario; ``vehicle``: the
    controller's file in the wrong and adapted columns (default the paper's);
    ``duration``: of each run (None: the whole path); ``noise``: what the controller
    measures (``Scenario.measurement_noise``; its stream seeded by the annealer's seed, so
    the four columns of a path, plant and seed read the same noise)."""
    out = []
    for path in paths:
        for name, f in files.items():
            vehicles = {"wrong": vehicle, "identified": identified[name]["vehicle"],
                        "adapted": vehicle, "true": str(f)}
            for model in MODELS:
                for k in seeds:
                    out.append(StudyScenario(
                        "mismatch", "file", None, plant=name, seed=k, duration=duration,
                        vehicle=vehicles[model], trajectory=str(path),
                        plant_vehicle=str(f), model=model,
                        settings=dict(COLUMN_SETTINGS[model])))
    return with_noise(out, noise)


def run_mismatch(out: str | Path | None = None, *, plants=None, n_paths: int | None = None,
                 seeds=None, quick: bool = False, levels_quick: bool | None = None,
                 jobs: int | None = None, scheduler: str | None = None, force: bool = False,
                 progress: bool = True, vehicle: str | None = None,
                 trajectory: str | None = None, noise: dict | None = None) -> dict:
    """Run (or resume) the experiment; returns its summary (``mismatch.json``).
    ``quick``: :data:`QUICK`'s plants, paths and seeds and the families' quick levels.
    ``vehicle``: the controller's vehicle file (default the paper's); ``trajectory``: one
    path of your own, driven whole, instead of ``n_paths`` random ones (one path: no
    interval, the bootstrap resamples paths); ``plants`` may name vehicle files;
    ``noise``: the controller measures the states with this noise (``{v, r, pos, phi}`` of
    ``Scenario.measurement_noise``), the identified column's logged run too."""
    if quick:
        plants = plants or QUICK["plants"]
        n_paths = n_paths or QUICK["paths"]
        seeds = seeds or tuple(range(QUICK["seeds"]))
    plants = tuple(plants or PLANTS)
    if trajectory is not None and n_paths is not None:
        raise ScenarioError("--paths does not apply with --trajectory (your path is the one "
                            "path)")
    n_paths = PATHS if n_paths is None else int(n_paths)
    seeds = tuple(SEEDS if seeds is None else seeds)
    base = check_vehicles(plants, vehicle, trajectory)
    if n_paths < 2 and trajectory is None:
        raise ScenarioError(f"--paths: at least 2 (the interval resamples paths), got {n_paths}")
    if not seeds or any(k < 0 for k in seeds):
        raise ScenarioError(f"--seeds: at least one annealer seed >= 0, got {seeds}")
    levels_quick = quick if levels_quick is None else levels_quick
    noise = check_noise(noise)
    out = Path(out) if out is not None else default_out("mismatch", quick, noise)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    vehicle = None if vehicle is None else str(Path(vehicle).resolve())
    paths, files, man = write_inputs(out, plants, n_paths, vehicle, trajectory, base)
    identified = identify_plants(files, man, out, jobs, scheduler, force, progress, vehicle,
                                 noise)
    duration = None if trajectory is not None else DURATION
    scenarios = design(paths, files, identified, seeds, vehicle, duration, noise)
    specs = run_specs(scenarios, quick=levels_quick)
    results, summ = run_all(specs, out, jobs=jobs, force=force, progress=progress,
                            desc="mismatch", scheduler=scheduler)
    summ["total_wall_s"] = time.perf_counter() - t0
    summ["scenarios"] = len(scenarios)
    design_doc = {"plants": list(plants), "paths": [p.name for p in paths],
                  "seeds": list(seeds), "levels": "quick" if levels_quick else "default",
                  "duration_s": duration, "speeds_kmh": list(PATH_SPEEDS)}
    if vehicle is not None:
        design_doc["vehicle"] = vehicle
    if noise is not None:
        design_doc["measurement_noise"] = noise
    if trajectory is not None:
        design_doc.update(trajectory=str(trajectory), speeds_kmh=None)
    return report(results, scenarios, identified, design_doc, out, summ)


# ---- the analysis --------------------------------------------------------------------------
def _block_ci(blocks: list[np.ndarray], stat) -> list[float | None]:
    """95 % percentile bootstrap of ``stat(concatenated blocks)`` resampling the blocks."""
    from scipy.stats import bootstrap

    from .study_analysis import BOOTSTRAP, _bootstrap_kw

    if len(blocks) < 2:
        return [None, None]
    idx = np.arange(len(blocks))
    vals = [stat(np.concatenate([blocks[j] for j in np.atleast_1d(i)])) for i in idx]
    full = stat(np.concatenate(blocks))
    if all(v == full for v in vals):
        return [float(full), float(full)]

    def s(i):
        return stat(np.concatenate([blocks[j] for j in i]))

    ci = bootstrap((idx,), s, vectorized=False, n_resamples=BOOTSTRAP, method="percentile",
                   **_bootstrap_kw()).confidence_interval
    return [float(ci.low), float(ci.high)]


def pooled_blocked(items: list[dict], key: str = "ratio", fill: str | None = None) -> dict:
    """The geometric mean of ``key`` over the scenarios of ``items`` (a scenario's seeds
    averaged in logs first) with its 95 % interval resampling paths as blocks."""
    units: dict[str, list[float]] = {}
    block_of: dict[str, str] = {}
    missing = 0
    for d in items:
        v = d.get(key)
        if (v is None or not v > 0) and fill is not None:
            v = d.get(fill)
        if v is None or not v > 0:
            missing += 1
            continue
        units.setdefault(d["unit"], []).append(math.log(v))
        block_of[d["unit"]] = d["path"]
    by_block: dict[str, list[float]] = {}
    for u, logs in units.items():
        by_block.setdefault(block_of[u], []).append(float(np.mean(logs)))
    res = {"n": len(units), "paths": len(by_block), "missing": missing, "gmean": None,
           "ci95": [None, None], "below_1": None}
    if not units:
        return res
    blocks = [np.array(v) for v in by_block.values()]
    allv = np.concatenate(blocks)
    lo, hi = _block_ci(blocks, np.mean)
    res.update(gmean=float(np.exp(allv.mean())), below_1=int(np.sum(allv < 0)),
               ci95=[None if lo is None else float(np.exp(lo)),
                     None if hi is None else float(np.exp(hi))])
    return res


def paired_difference(items: list[dict], model: str, key: str = "ratio",
                      fill: str | None = None) -> dict:
    """``gmean(model) - gmean(true)`` over the (path, plant, seed) both have, with its 95 %
    interval resampling paths as blocks (the pairs stay together)."""
    val = {}
    for d in items:
        v = d.get(key)
        if (v is None or not v > 0) and fill is not None:
            v = d.get(fill)
        if v is not None and v > 0:
            val[(d["path"], d["plant"], d["seed"], d["model"])] = math.log(v)
    by_block: dict[str, list[tuple[float, float]]] = {}
    for (path, plant, seed, m), v in val.items():
        t = val.get((path, plant, seed, "true"))
        if m == model and t is not None:
            by_block.setdefault(path, []).append((v, t))
    res = {"pairs": sum(len(v) for v in by_block.values()), "paths": len(by_block),
           "difference": None, "ci95": [None, None]}
    if not by_block:
        return res
    blocks = [np.array(v) for v in by_block.values()]

    def stat(a):
        a = a.reshape(-1, 2)
        return float(np.exp(a[:, 0].mean()) - np.exp(a[:, 1].mean()))

    flat = [b.ravel() for b in blocks]
    res["difference"] = stat(np.concatenate(flat))
    res["ci95"] = _block_ci(flat, stat)
    return res


def summarise(comparisons: list[dict], plants) -> dict:
    """Per column: pooled over every plant and path, and per plant; the paired differences
    against the true model."""
    out = {"by_model": {}, "by_plant": {}, "against_true": {}}
    for m in MODELS:
        items = [d for d in comparisons if d["model"] == m]
        out["by_model"][m] = {
            "scenarios": len({d["unit"] for d in items}), "instances": len(items),
            "equal_error": pooled_blocked(items),
            "with_unmatched": pooled_blocked(items, fill="most_accurate"),
            "unmatched": sum(d["reason"] is not None for d in items),
            "e_ntwo_cm": _mean([d["e_ntwo_cm"] for d in items])}
        out["by_plant"][m] = {}
        for p in plants:
            its = [d for d in items if d["plant"] == p]
            out["by_plant"][m][p] = {
                "equal_error": pooled_blocked(its),
                "with_unmatched": pooled_blocked(its, fill="most_accurate"),
                "unmatched": sum(d["reason"] is not None for d in its),
                "instances": len(its), "e_ntwo_cm": _mean([d["e_ntwo_cm"] for d in its])}
    for m in MODELS[:-1]:
        out["against_true"][m] = {
            "equal_error": paired_difference(comparisons, m),
            "with_unmatched": paired_difference(comparisons, m, fill="most_accurate")}
    return out


def _mean(v):
    v = [x for x in v if x is not None]
    return float(np.mean(v)) if v else None


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _diff_text(s: dict) -> str:
    if s.get("difference") is None:
        return "n/a"
    lo, hi = s["ci95"]
    ci = "" if lo is None else f" [{lo:+.3f}, {hi:+.3f}]"
    return f"{s['difference']:+.3f}{ci} ({_count(s['pairs'], 'pair')})"


ID_PARAMS = ("lateral.K", "lateral.mu", "longitudinal.K", "longitudinal.mu", "wheel_lag",
             "steer_lag")


def markdown(summary: dict, identified: dict, design_doc: dict, runs: dict,
             sentence: str) -> str:
    plants = design_doc["plants"]
    L = ["# Tires the controller does not know: the study's question on plants unlike the "
         "vehicle file", "",
         f"`msagv experiment mismatch`: {runs['runs']} runs ({runs['failed']} failed) on "
         + (f"the path {design_doc['paths'][0]} (whole) " if design_doc.get("trajectory") else
            f"{len(design_doc['paths'])} random paths ({DURATION:g} s at "
            f"{', '.join(f'{v:g}' for v in PATH_SPEEDS)} km/h in turn) ")
         + (f"of the vehicle {Path(design_doc['vehicle']).name} " if design_doc.get("vehicle")
            else "")
         + f"x {_count(len(plants), 'plant')} x "
         f"4 columns x {_count(len(design_doc['seeds']), 'annealer seed')}, the families' "
         f"{design_doc['levels']} levels, every family with the offset-free disturbance"
         + (f", the states measured with noise ({noise_text(design_doc['measurement_noise'])})"
            ", the identified column's logged run too"
            if design_doc.get("measurement_noise") else "") + ".", "",
         f"**{sentence}**", "",
         "Wear-aware / wear-blind tire wear at equal lateral RMS error (the study's rule), "
         "geometric mean over paths and plants, 95 % percentile bootstrap resampling paths as "
         "blocks; *u*: scenarios whose fronts share no error (left out here, entered at their "
         "most-accurate ratio in the second table).", "",
         "| plant | model wrong | identified (one logged run) | adapted online | model true |",
         "|---|---|---|---|---|"]
    for p in plants:
        cells = []
        for m in MODELS:
            s = summary["by_plant"][m][p]
            cells.append(f"{_ratio_text(s['equal_error'])} (u {s['unmatched']})")
        L.append(f"| {p} | " + " | ".join(cells) + " |")
    cells = [f"**{_ratio_text(summary['by_model'][m]['equal_error'])}** "
             f"(u {summary['by_model'][m]['unmatched']})" for m in MODELS]
    L.append("| all | " + " | ".join(cells) + " |")
    L += ["", "With the unmatched scenarios at their most-accurate ratio:", "",
          "| plant | model wrong | identified | adapted | model true |", "|---|---|---|---|---|"]
    for p in plants:
        L.append(f"| {p} | " + " | ".join(
            _ratio_text(summary["by_plant"][m][p]["with_unmatched"]) for m in MODELS) + " |")
    L.append("| all | " + " | ".join(
        f"**{_ratio_text(summary['by_model'][m]['with_unmatched'])}**" for m in MODELS) + " |")
    L += ["", "Each column against the true model (the paired difference of the geometric "
          "means over the same paths, plants and seeds; 95 % interval resampling paths):", "",
          "| column | at equal error | with the unmatched |", "|---|---|---|"]
    for m in MODELS[:-1]:
        a = summary["against_true"][m]
        L.append(f"| {m} - true | {_diff_text(a['equal_error'])} | "
                 f"{_diff_text(a['with_unmatched'])} |")
    L += ["", "NTWO's lateral RMS error [cm] (mean over paths): the offset-free disturbance "
          "against each column's model:", "",
          "| plant | model wrong | identified | adapted | model true |", "|---|---|---|---|---|"]
    for p in plants:
        L.append(f"| {p} | " + " | ".join(_f(summary["by_plant"][m][p]["e_ntwo_cm"], 2)
                                          for m in MODELS) + " |")
    L += ["", "The identified vehicles (`msagv calibrate`'s estimator on one logged run of the "
          "excitation manoeuvre per plant): value / truth, or why a parameter was not "
          "identified (then the file's value is kept):", "",
          "| plant | " + " | ".join(ID_PARAMS) + " |", "|---|" + "---|" * len(ID_PARAMS)]
    for p in plants:
        est = identified.get(p, {}).get("estimates", {})
        cells = []
        for k in ID_PARAMS:
            e = est.get(k)
            if e is None:
                cells.append("")
            elif not e["identified"]:
                cells.append("not identified")
            elif e["truth"]:
                cells.append(f"{e['value'] / e['truth']:.3f}")
            else:
                cells.append(f"{e['value']:.3g} (truth {e['truth']:.3g})")
        L.append(f"| {p} | " + " | ".join(cells) + " |")
    return "\n".join(L) + "\n"


def the_sentence(summary: dict) -> str:
    """What a user with unknown tires can expect, in one sentence, from the numbers."""
    bm = summary["by_model"]

    def t(m):
        s = bm[m]["with_unmatched"]
        return _ratio_text(s)

    def u(m):
        return f"{bm[m]['unmatched']} of {bm[m]['instances']}"

    return (f"With tires it does not know, the wear-aware controller wears "
            f"{t('wrong')}x the best wear-blind controller's wear at equal error ({u('wrong')} "
            f"scenarios unmatched, entered at their most-accurate ratio); with the tires "
            f"identified from one logged run {t('identified')}x ({u('identified')}), adapted "
            f"online {t('adapted')}x ({u('adapted')}), and with the true tires {t('true')}x "
            f"({u('true')})")


def plot(summary: dict, plants, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(plants) + 2.5), 4.2))
    cols = {"wrong": "C3", "identified": "C0", "adapted": "C2", "true": "k"}
    rows = list(plants) + ["all"]
    w = 0.8 / len(MODELS)
    for j, m in enumerate(MODELS):
        for i, p in enumerate(rows):
            s = (summary["by_model"][m] if p == "all" else summary["by_plant"][m][p]
                 )["with_unmatched"]
            if s["gmean"] is None:
                continue
            x = i + (j - 1.5) * w
            lo, hi = s["ci95"]
            yerr = None if lo is None else [[s["gmean"] - lo], [hi - s["gmean"]]]
            ax.errorbar([x], [s["gmean"]], yerr=yerr, fmt="o", color=cols[m], ms=4,
                        capsize=2, label=m if i == 0 else None)
    ax.axhline(1.0, color="0.5", lw=0.8, ls="--")
    ax.set_xticks(range(len(rows)))
    ax.set_xticklabels(rows, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("wear-aware / wear-blind wear\nat equal error")
    ax.set_title("Plants unlike the vehicle file: what the controller knows", fontsize=10)
    ax.legend(fontsize=8, ncol=4, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(results: list[dict], scenarios, identified: dict, design_doc: dict, out: Path,
           runs: dict) -> dict:
    """Write ``mismatch.md``, ``mismatch.json``, ``mismatch.png``; return the JSON document."""
    from .results import stamp
    from .study_analysis import _json_default, _row, compare

    meta = {sc.name: sc for sc in scenarios}
    rows = [_row(r, {}) for r in results]
    for r, res in zip(rows, results):
        r["model"] = res["spec"]["tags"].get("model")
    comparisons = compare(rows)
    for d in comparisons:
        sc = meta[d["scenario"]]
        d.update(model=sc.model, path=Path(sc.trajectory).name)
    summary = summarise(comparisons, design_doc["plants"])
    sentence = the_sentence(summary)
    (out / "mismatch.md").write_text(markdown(summary, identified, design_doc, runs, sentence))
    figures = []
    if any(r["status"] == "ok" for r in rows):
        plot(summary, design_doc["plants"], out / "mismatch.png")
        figures.append("mismatch.png")
    doc = {"experiment": "mismatch", "design": design_doc, "sentence": sentence,
           "summary": summary, "identified": identified, "rows": rows,
           "comparisons": [{k: v for k, v in d.items() if k not in ("aware_front",
                                                                    "blind_front")}
                           for d in comparisons],
           "runs": runs, "figures": figures, "out": str(out)}
    doc = stamp(doc, results)
    text = json.dumps(doc, indent=1, default=_json_default)
    (out / "mismatch.json").write_text(text)
    return json.loads(text)
