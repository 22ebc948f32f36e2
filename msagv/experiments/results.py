"""One JSON shape for a run's result, whichever command produced it.

``msagv run``, ``msagv fmu simulate``, ``msagv report``, ``msagv demo`` (``--json``) print
one document, and ``msagv experiment --json`` one per row under ``rows``::

    {"version":   "0.1.0",             # the msagv package
     "command":   "run",               # run | fmu simulate | report | demo | experiment
     "scenario":  {"case", "trajectory", "reference", "speed_kmh",
                   "vehicle": {"name", "axles", "mass_kg", "file"},
                   "method", "model", "solver", "seed",
                   "duration_s", "period_s", "after_end", "plant",
                   "plant_vehicle": null | {"name", "axles", "mass_kg", "file", "tire_scale",
                                            "options"},
                   "offset_free", "initial"},
     "metrics":   {"W_tw", "W_s", "W_alpha", "W_t", "e_x_cm", "e_y_cm", "e_phi_deg",
                   "e_bar", "Omega", "solve_ms": {"p50", "p99", "max"}, "steps"},
     "completed": true,                # false: cut short (Ctrl-C), the metrics so far
     "warnings":  ["one line each", ...],
     ...}                              # the command's own extras (recording, transport)

A field the producer cannot know is null (a plant's recording knows no MPC method).
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Iterable

DEFAULT_SPEED = {"curve": 15.0, "line": 10.0}  # km/h, controller.reference.make_case
CASE_NAMES = {"case1": "curve", "case2": "line"}


def package_version() -> str:
    """The installed msagv's version (``msagv.__version__``)."""
    try:
        return version("msagv")
    except PackageNotFoundError:  # a source tree that is not installed
        return "0+unknown"


def speed_value(speed) -> float | str | None:
    """km/h as a number, or the profile text ``'t:kmh,...'`` as given."""
    if speed is None:
        return None
    try:
        return float(speed)
    except (TypeError, ValueError):
        return str(speed)


def vehicle_info(vehicle, file: str | None = None) -> dict:
    return {"name": vehicle.name, "axles": vehicle.n_axles, "mass_kg": float(vehicle.mass),
            "file": None if file is None else str(file)}


def scenario_info(scenario, vehicle, reference, settings=None,
                  duration: float | None = None) -> dict:
    """The ``scenario`` block of a run built from an :class:`experiments.scenario.Scenario`
    (``settings``: its :class:`controller.models.MPCSettings`; None where the producer has
    no controller, a plant process: method, model and seed null). A plant process records
    it in its recording's header, so ``msagv report`` names what was run."""
    case = None if scenario.trajectory else CASE_NAMES.get(scenario.case, scenario.case or "curve")
    speed = speed_value(scenario.speed)
    if speed is None and case is not None:
        speed = DEFAULT_SPEED[case]
    vfile = scenario.vehicle if isinstance(scenario.vehicle, (str, Path)) else None
    return {"case": case, "trajectory": scenario.trajectory, "reference": reference.name,
            "speed_kmh": speed, "vehicle": vehicle_info(vehicle, vfile),
            "method": getattr(settings, "method", None), "model": getattr(settings, "model", None),
            "solver": scenario.solver if settings is not None else None,
            "seed": getattr(settings, "seed", None),
            "duration_s": None if duration is None else float(duration),
            "period_s": scenario.period,
            "after_end": scenario.after_end,
            "plant": f"fmu {Path(scenario.fmu).name}" if scenario.fmu else "native",
            "plant_vehicle": _plant_vehicle_info(scenario, vehicle),
            "offset_free": getattr(settings, "offset_free_on", None),
            "measurement_noise": _noise_info(scenario),
            "initial": "rest" if scenario.from_rest else "reference"}


def _noise_info(scenario) -> dict | None:
    """The controller's measurement noise (``measurement_noise``), or None without."""
    m = scenario.measurement() if hasattr(scenario, "measurement") else None
    return None if m is None else m.as_dict()


def _plant_vehicle_info(scenario, vehicle) -> dict | None:
    """The plant's own vehicle where it is not the controller's (``plant_vehicle``,
    ``plant_tire_scale``, ``plant_options``), else None."""
    pv = getattr(scenario, "plant_vehicle", None)
    if (pv is None and getattr(scenario, "plant_tire_scale", 1.0) == 1.0
            and not getattr(scenario, "plant_options", None)):
        return None
    info = vehicle_info(scenario.actual_vehicle(vehicle),
                        pv if isinstance(pv, (str, Path)) else None)
    info["tire_scale"] = float(scenario.plant_tire_scale)
    info["options"] = dict(scenario.plant_options)
    return info


def result(command: str, scenario: dict, metrics: dict, warnings: Iterable[str] = (),
           completed: bool = True, **extra: Any) -> dict:
    """The result document (see the module docstring)."""
    doc = {"version": package_version(), "command": command, "scenario": scenario,
           "metrics": metrics, "completed": bool(completed), "warnings": list(warnings)}
    doc.update(extra)
    return doc


def spec_info(spec: dict, duration: float | None = None) -> dict:
    """The ``scenario`` block of an experiment's run (a :class:`experiments.runs.RunSpec`
    as stored with its result)."""
    from .runs import PERIOD, RunSpec

    rs = RunSpec.from_dict(spec)
    sc = rs.scenario()
    vehicle = sc.resolve_vehicle()
    settings = sc.mpc_settings()
    ref_name = {"curve": "case1-curve", "line": "case2-line"}.get(rs.case, rs.case)
    return {"case": CASE_NAMES.get(rs.case, rs.case), "trajectory": None, "reference": ref_name,
            "speed_kmh": float(rs.speed_kmh),
            "vehicle": vehicle_info(vehicle, rs.vehicle),
            "method": settings.method, "model": settings.model, "solver": sc.solver,
            "seed": settings.seed,
            "duration_s": None if duration is None and rs.duration is None
            else float(duration if duration is not None else rs.duration),
            "period_s": PERIOD, "after_end": sc.after_end, "plant": "native",
            "initial": "reference", "label": rs.label, "group": rs.group}


def partial_run(res: dict) -> tuple[float, float] | None:
    """``(ran, whole)`` [s] of a stored experiment run that covered only part of its
    reference (``--duration`` shorter than the path), None for a whole run: such a row is
    not comparable with the paper's, which are for the whole path."""
    spec = res.get("spec") or {}
    if spec.get("duration") is None:
        return None
    from .runs import RunSpec

    whole = float(RunSpec.from_dict(spec).scenario().reference()[0].duration)
    ran = float(res.get("duration") or spec["duration"])
    return (ran, whole) if ran < whole - 1e-6 else None


def stamp(summary: dict, results: list[dict]) -> dict:
    """An experiment's summary with the fields every result document has: the package
    version, the command and the warnings (failed runs, and each run's own warnings, once
    each)."""
    warnings = []
    for r in results:
        where = f"{r['spec']['label']} {r['spec']['group']}"
        if r["status"] != "ok":
            warnings.append(f"{where}: the run failed: {r.get('error')}")
        warnings += [f"{where}: {w}" for w in r.get("warnings", [])]
    head = {"version": package_version(), "command": "experiment",
            "warnings": list(dict.fromkeys(warnings))}
    return dict(head, **summary)


def floor_errors(metrics: dict) -> tuple[float | None, float | None]:
    """A run's largest distance from the reference's position [cm] and heading error [deg]
    (``e_pos_max_cm``, ``e_phi_max_deg``): what the wear floor holds a motion to. Metrics
    that predate the distance give the largest lateral error (``e_lat_max_cm``, never more
    than the distance); None where they say nothing."""
    e_pos = metrics.get("e_pos_max_cm")
    if e_pos is None:
        e_pos = metrics.get("e_lat_max_cm")
    return e_pos, metrics.get("e_phi_max_deg")


def within_floor_bounds(metrics: dict) -> bool:
    """Whether a run kept within what its wear floor bounds (``FLOOR_TOL_M`` of the
    reference's position, ``FLOOR_TOL_PHI_DEG`` of its heading) by :func:`floor_errors`;
    a figure the metrics lack counts as within (flagged, never excused)."""
    from msagv.controller.floors import FLOOR_TOL_M, FLOOR_TOL_PHI_DEG

    e_pos, e_phi = floor_errors(metrics)
    return not ((e_pos is not None and e_pos > 100.0 * FLOOR_TOL_M)
                or (e_phi is not None and e_phi > FLOOR_TOL_PHI_DEG))


def split_below_floor(below: list[dict], metrics: dict) -> tuple[list[dict], list[dict]]:
    """:func:`controller.floors.broken_floor`'s entries of a run with ``metrics``, split by
    where the run went: ``(broken, off_path)``. The floor is the least wear of any motion
    whose centre stays within ``FLOOR_TOL_M`` of the reference's position and whose heading
    stays within ``FLOOR_TOL_PHI_DEG`` of the reference's; a run that kept to both
    (``e_pos_max_cm``, ``e_phi_max_deg``) and wears less breaks the floor; one that left
    either is below it without breaking it (its entries carry ``off_path_cm`` and
    ``off_heading_deg``, its largest errors). A run whose metrics predate those two is
    judged by its largest lateral error (``e_lat_max_cm``, never more than its distance):
    off the path if that is beyond the tolerance, otherwise counted as within (flagged,
    never excused): :func:`within_floor_bounds`."""
    if within_floor_bounds(metrics):
        return list(below), []
    e_pos, e_phi = floor_errors(metrics)
    return [], [dict(b, off_path_cm=e_pos, off_heading_deg=e_phi) for b in below]


def off_path_floor_note(entries: list[dict], what: str = "the run") -> str:
    """A one-line note for :func:`split_below_floor`'s (non-empty) ``off_path`` entries."""
    from msagv.controller.floors import BROKEN_RATIO, FLOOR_TOL_M, FLOOR_TOL_PHI_DEG

    parts = ", ".join(f"{p['part']} {p['W']:.4g} J = {p['ratio']:.3f} x its floor "
                      f"{p['floor']:.4g} J" for p in entries)
    tol = f"{100.0 * FLOOR_TOL_M:g} cm and {FLOOR_TOL_PHI_DEG:g} deg"
    return (f"below the floor off the path: {what} wears less than {BROKEN_RATIO} x the wear "
            f"floor of any motion within {tol} of the path ({parts}) while straying "
            f"{strayed(entries)} from it: the floor bounds only motions within {tol}, so "
            f"this does not break it (docs/WEAR.md, Wear floors)")


def strayed(entries: list[dict]) -> str:
    """How far :func:`split_below_floor`'s off-path entries strayed: 'up to X cm' (the
    largest distance from the reference's position) and 'Y deg in heading'."""
    e = [p["off_path_cm"] for p in entries if p.get("off_path_cm") is not None]
    h = [p["off_heading_deg"] for p in entries if p.get("off_heading_deg") is not None]
    return " and ".join(([f"up to {max(e):.3g} cm"] if e else [])
                        + ([f"up to {max(h):.3g} deg in heading"] if h else []))
