"""Runs of the experiments: one closed-loop run per configuration, cached on disk under a
hash of that configuration, executed in parallel by Dask (a local cluster of one process
per core, or the cluster of ``--scheduler ADDRESS``), as FMPy's parameter-variation
example spreads FMU runs.

A run is ``Plant(vehicle, initial) + MPC(vehicle, settings, reference) + closed_loop`` at
T = 0.01 s, with the annealer's fixed iteration budget and seed, so it is deterministic: the
same configuration gives the same numbers, and a finished run never needs redoing.

On disk, under ``OUT/runs/``: ``<key>.json`` (the configuration, the metrics of eq. 28-33,
wall and CPU time, status) and ``<key>.csv`` (the per-step log of
:meth:`controller.loop.RunLog.to_csv`). The JSON is written last and atomically, so its
presence means the run finished; an interrupted experiment resumes where it stopped.

The key hashes everything that determines the result: the case, speed, mass and duration,
the vehicle description, *all* MPC settings (resolved against the current defaults, so a
change of a default weight reruns the affected runs) and a digest of the source of
``controller/`` and ``plant/`` (so a code change does too).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from msagv.plant.signals import CONTROL_PERIOD

_log = logging.getLogger("msagv.experiment")
SCHEMA = 1  # bump when the meaning of a stored result changes
PERIOD = CONTROL_PERIOD  # s, the paper's control period T (plant.signals)

@dataclass
class RunSpec:
    """One closed-loop run of an experiment.

    label : the row's method name (``TWO``, or ``TWO L x0.5`` on a Pareto front).
    group : the row group (``35 km/h``, ``12 t``).
    case : ``curve`` (Case 1) or ``line`` (Case 2).
    speed_kmh : reference speed [km/h].
    mass_kg : gross vehicle weight [kg]; None keeps the vehicle file's.
    settings : MPCSettings fields that differ from the defaults.
    duration : vehicle time [s]; None runs the whole reference.
    vehicle : vehicle TOML path; None is the built-in paper vehicle.
    tags : free data carried into the result (Pareto family and scale).
    extra : further :class:`experiments.scenario.Scenario` fields (``solver``, ``axles``,
        ``path_seed``, ``plant_options``, ``plant_tire_scale``); ``case`` may then also be
        ``lane``, ``turn`` or ``random``.
    """

    label: str
    group: str
    case: str
    speed_kmh: float
    mass_kg: float | None = None
    settings: dict = field(default_factory=dict)
    duration: float | None = None
    vehicle: str | None = None
    tags: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "RunSpec":
        return cls(**d)

    def scenario(self):
        """The run as a :class:`experiments.scenario.Scenario` (one core per run: the runs
        themselves are parallel, so the rollouts stay serial unless the spec says)."""
        from .scenario import Scenario

        settings = dict(self.settings)
        settings.setdefault("threads", 1)
        if self.case == "file":  # a trajectory CSV (extra["trajectory"]) carries its timing
            return Scenario(vehicle=self.vehicle, mass_kg=self.mass_kg,
                            duration=self.duration, settings=settings, period=PERIOD,
                            **self.extra)
        return Scenario(vehicle=self.vehicle, mass_kg=self.mass_kg, case=self.case,
                        speed=self.speed_kmh, duration=self.duration, settings=settings,
                        period=PERIOD, **self.extra)

    def estimated_steps(self) -> int:
        """Control periods this run will take (for scheduling the longest first)."""
        if self.duration is not None:
            return int(self.duration / PERIOD)
        if self.case == "line" or self.case in ("lane", "turn", "random"):
            return int(20.0 / PERIOD)
        return int(150.0 / (max(self.speed_kmh, 0.1) / 3.6) / PERIOD)


def code_digest() -> str:
    """SHA-256 over the source that determines a run: plant/, controller/ (with their
    data) and the scenario assembly."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    files = sorted(list((root / "controller").glob("*.py")) + list((root / "plant").glob("*.py"))
                   + list((root / "plant" / "data").glob("*.toml"))
                   + [root / "experiments" / "scenario.py"])
    for p in files:
        h.update(p.relative_to(root).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def build_vehicle(spec: RunSpec):
    return spec.scenario().resolve_vehicle()


def build_settings(spec: RunSpec):
    return spec.scenario().mpc_settings()


def config_of(spec: RunSpec, digest: str | None = None) -> dict:
    """Everything that determines the run's result (the content of its key)."""
    s = build_settings(spec)
    cfg = {
        "schema": SCHEMA,
        "case": spec.case,
        "speed_kmh": float(spec.speed_kmh),
        "duration": None if spec.duration is None else float(spec.duration),
        "period": PERIOD,
        "vehicle": build_vehicle(spec).to_dict(),
        # files by their content, not their paths: an edited file reruns its runs, a moved
        # one does not
        "extra": {k: v for k, v in spec.extra.items() if k not in ("trajectory", "plant_vehicle")},
        "trajectory_sha": (hashlib.sha256(Path(spec.extra["trajectory"]).read_bytes()).hexdigest()
                           if spec.extra.get("trajectory") else None),
        "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(s).items()},
        "code": digest or code_digest(),
    }
    if spec.extra.get("plant_vehicle"):  # the plant's own vehicle file, by its content
        sc = spec.scenario()
        cfg["plant_vehicle"] = sc.actual_vehicle(sc.resolve_vehicle()).to_dict()
    return cfg


def run_key(spec: RunSpec, digest: str | None = None) -> str:
    blob = json.dumps(config_of(spec, digest), sort_keys=True, default=repr)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def execute(spec_d: dict, key: str) -> dict:
    """Run one configuration (on a worker): the result with its per-step log as CSV text
    (``log_csv``), stored by :func:`store` where the experiment runs. Errors of the
    simulation itself (a diverging plant, refused commands) make a failed run: they are
    as deterministic as a result."""
    import tempfile

    from msagv.controller.loop import closed_loop

    _worker_init()
    spec = RunSpec.from_dict(spec_d)
    t0, c0 = time.perf_counter(), time.process_time()
    res = {"key": key, "spec": spec.to_dict(), "status": "ok", "error": None, "metrics": None}
    try:
        scenario = spec.scenario()
        scenario.duration = None  # the reference's own length, then clipped to the spec's
        built = scenario.build()
        plant, mpc, ref = built.plant, built.controller, built.reference
        duration = ref.duration if spec.duration is None else min(spec.duration, ref.duration)
        # the state, commands and references only: the plant's outputs would triple the
        # stored logs (msagv run --log has them)
        log = closed_loop(plant, mpc, ref, duration, period=PERIOD, progress=False,
                          outputs=False, measure=built.measure)
        with tempfile.TemporaryDirectory() as td:
            log.to_csv(Path(td) / "log.csv")
            res["log_csv"] = (Path(td) / "log.csv").read_text()
        m = log.metrics()
        res["metrics"] = m
        # the controller's solve-time warnings too: they reach the user through the result
        # (once, counted), not through a worker's stderr
        res["warnings"] = list(built.warnings) + list(mpc.budget()["warnings"])
        res["duration"] = duration
        res["log"] = f"runs/{key}.csv"
    except Exception as e:  # noqa: BLE001 - stored and reported, never hidden
        res["status"] = "failed"
        res["error"] = f"{type(e).__name__}: {e}"
    res["wall_s"] = time.perf_counter() - t0
    res["cpu_s"] = time.process_time() - c0
    res["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
    res["config"] = config_of(spec)
    return res


def store(res: dict, out_dir: str | Path) -> dict:
    """Write a result under ``OUT/runs/``: the log CSV, then the JSON (last and atomically:
    its presence means the run finished). Returns the result without its log text."""
    runs = Path(out_dir) / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    res = dict(res)
    text = res.pop("log_csv", None)
    if text is not None:
        _atomic_write(runs / f"{res['key']}.csv", text)
    _atomic_write(runs / f"{res['key']}.json", json.dumps(res, indent=1, sort_keys=True))
    return res


def _worker_init() -> None:
    # each worker is one single-threaded run; the parallelism is across runs
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(k, "1")
    try:
        import numba

        numba.set_num_threads(1)
    except Exception:  # noqa: BLE001 - numba missing or already configured
        pass
    if "distributed" in sys.modules:  # a Dask worker's warnings travel in the result
        from distributed import get_worker  # (execute), not on its stderr

        try:
            get_worker()
        except ValueError:  # not in a worker
            return
        logging.getLogger("msagv").setLevel(logging.ERROR)


def load_result(out_dir: Path, key: str) -> dict | None:
    p = Path(out_dir) / "runs" / f"{key}.json"
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return None  # a damaged result is redone


def run_all(specs: list[RunSpec], out_dir: str | Path, jobs: int | None = None,
            force: bool = False, progress: bool = True, desc: str = "runs",
            scheduler: str | None = None) -> tuple[list[dict], dict]:
    """Run every spec not already finished under ``out_dir`` (all of them with ``force``).

    Returns the results in the order of ``specs`` and a summary
    ``{"runs", "reused", "executed", "failed", "wall_s"}``. The runs go to Dask, longest
    first (:func:`dask_map`); ``jobs = 1`` without a scheduler runs them in this process.
    Results are stored here as they finish (an interrupted experiment resumes); progress
    is a bar over finished runs on stderr.
    """
    out_dir = Path(out_dir)
    (out_dir / "runs").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    digest = code_digest()
    keys = [run_key(s, digest) for s in specs]
    results: dict[str, dict] = {}
    todo: dict[str, RunSpec] = {}
    for s, k in zip(specs, keys):
        if k in results or k in todo:
            continue
        old = None if force else load_result(out_dir, k)
        if old is not None:
            results[k] = old
        else:
            todo[k] = s
    reused = len(results)
    order = sorted(todo, key=lambda k: -todo[k].estimated_steps())
    # a run no vehicle can drive is refused before any run starts: the solver of every run,
    # the vehicle and path of each distinct scenario once (the runs of a study share a few
    # dozen paths; building a random path for each of 1000 runs took 20 min)
    checked: set[str] = set()
    for k in order:
        sc = todo[k].scenario()
        sc.check_solver()
        where = json.dumps({f: v for f, v in sc.to_dict().items()
                            if f not in ("settings", "solver")}, sort_keys=True, default=str)
        if where not in checked:
            checked.add(where)
            sc.preflight()
    jobs = max(1, int(jobs or os.cpu_count() or 1))
    bar = None
    if progress and order:
        from tqdm import tqdm

        bar = tqdm(total=len(order), desc=desc, unit="run", file=sys.stderr, dynamic_ncols=True)

    def done(res):
        res = store(res, out_dir)
        results[res["key"]] = res
        _log.info("%s %s: %s (%.1f s)", res["spec"]["label"], res["spec"]["group"],
                  res["status"] if res["status"] != "ok" else
                  f"W_tw {res['metrics']['W_tw']:.4g} J, e_bar {res['metrics']['e_bar']:.3g}",
                  res["wall_s"])
        if bar is not None:
            bar.set_postfix_str(f"{res['spec']['label']} {res['spec']['group']}", refresh=False)
            bar.update(1)

    if order and jobs == 1 and scheduler is None:
        for k in order:
            done(execute(todo[k].to_dict(), k))
    elif order:
        dask_map(execute, [(todo[k].to_dict(), k) for k in order], done, jobs=jobs,
                 scheduler=scheduler)
    if bar is not None:
        bar.close()
    # a stored run is found by its content; its names (label, group, tags) are this call's,
    # so a renamed scenario or two specs with the same content report under their own names
    out = [dict(results[k], spec=s.to_dict()) for s, k in zip(specs, keys)]
    failed = sum(1 for k in set(keys) if results[k]["status"] != "ok")
    summary = {"runs": len(set(keys)), "reused": reused, "executed": len(order),
               "failed": failed, "wall_s": time.perf_counter() - t0}
    return out, summary


def finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def dask_map(fn, arg_tuples: list[tuple], on_result, *, jobs: int | None = None,
             scheduler: str | None = None) -> None:
    """``fn(*args)`` for every tuple on Dask, ``on_result(value)`` for each as it finishes
    (in this process). ``scheduler``: the address of a running cluster
    (``dask scheduler`` + ``dask worker`` on other machines, with this package installed);
    else a local cluster of ``jobs`` worker processes (default: the machine's cores), one
    thread each (numba threads 1), without a dashboard. Ctrl-C cancels what is queued and
    closes the cluster; finished results are already stored."""
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise RuntimeError("parallel runs need Dask (pip install 'msagv[study]'); or run "
                           "them one by one with --jobs 1") from None
    cluster = None
    if scheduler:
        client = Client(scheduler, timeout="20s")
    else:
        n = max(1, int(jobs or os.cpu_count() or 1))
        cluster = LocalCluster(n_workers=min(n, len(arg_tuples)), threads_per_worker=1,
                               processes=True, dashboard_address=None,
                               silence_logs=logging.ERROR)
        client = Client(cluster)
    try:
        futures = [client.submit(fn, *args, pure=False) for args in arg_tuples]
        try:
            for f in as_completed(futures):
                on_result(f.result())
        except BaseException:
            client.cancel(futures)
            raise
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
