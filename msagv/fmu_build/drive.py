"""Step the plant FMU with fmpy, with libcosim, or the native plant, over the same inputs.

Used by the FMU tests and benchmarks to compare the three. Every runner follows one
protocol, so their results compare row by row: for step k, set the inputs ``U[k]``,
advance by ``h``, read every output. Row 0 of the result holds the outputs after
initialization (``nan`` where an engine cannot read them before its first step); row
k + 1 those after step k. Columns follow ``plant.signal_names`` (our signal names).

Run as ``python -m msagv.fmu_build.drive JOB.json OUT.npz`` to simulate in a fresh process
(FMUs in one process share ``sys.modules``). This module imports ``plant`` only for the
native runner, so a job can check that an FMU does not touch the project's ``plant``.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path
from typing import Mapping

import numpy as np

from msagv.plant.signals import CONTROL_PERIOD

from .variables import CONFIG_FILE


def varied_inputs(n_wheels: int, n_steps: int, h: float = CONTROL_PERIOD, seed: int = 0) -> np.ndarray:
    """Deterministic, varied commands, shape (n_steps, 2 * n_wheels): wheel speeds then
    steering rates, in the wheel order 11, 12, 21, ...

    Wheel speeds ramp up to about 5 rad/s with per-wheel sines and random steps every
    0.5 s (wheels disagree, so tires slip); from t = 12 s to 12.5 s they exceed 25 rad/s
    (the paper vehicle's omega_w_max: saturation). Steering rates are sines plus random
    steps in [-1, 1] rad/s (beyond the paper vehicle's +/-0.8: saturation), drifting far
    enough to reach the steering stops now and then.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps) * h
    seg = (t / 0.5).astype(int)
    n_seg = int(seg.max()) + 1 if n_steps else 1
    jump_w = rng.uniform(-1.0, 1.0, (n_seg, n_wheels))
    jump_s = rng.uniform(-1.0, 1.0, (n_seg, n_wheels))
    ph = rng.uniform(0, 2 * np.pi, (2, n_wheels))
    ramp = np.minimum(t / 2.0, 1.0)[:, None]
    w = ramp * (5.0 + 1.5 * np.sin(0.7 * t[:, None] + ph[0])) + 0.7 * jump_w[seg]
    w = np.maximum(w, 0.0)
    burst = (t >= 12.0) & (t < 12.5)
    w[burst] = 30.0
    s = 0.6 * np.sin(0.5 * t[:, None] + ph[1]) + 0.5 * jump_s[seg]
    return np.hstack([w, s])


def fmu_config(fmu_path: str | Path) -> dict:
    import zipfile

    with zipfile.ZipFile(fmu_path) as z:
        return json.loads(z.read(f"resources/{CONFIG_FILE}"))


def _signal_columns(cfg: dict) -> tuple[list[str], list[str]]:
    """(our signal names, the FMU's output names) in output order."""
    outs = [v for v in cfg["variables"] if v["role"] == "output"]
    return [v["key"] for v in outs], [v["name"] for v in outs]


def _names_to_fmu(cfg: dict, values: Mapping[str, float] | None) -> dict[str, float]:
    """Parameter values by our name -> by the FMU's name (the build's prefix applied)."""
    by_key = {v["key"]: v["name"] for v in cfg["variables"] if v["role"] not in ("input", "output")}
    by_key.update({f"{v['key']}_0": v["name"] for v in cfg["variables"] if v["role"] == "initial"})
    out = {}
    for k, x in (values or {}).items():
        if k not in by_key:
            raise KeyError(f"no parameter '{k}' in the FMU")
        out[by_key[k]] = float(x)
    return out


def run_native(vehicle, U: np.ndarray, h: float | np.ndarray = CONTROL_PERIOD,
               parameters: Mapping[str, float] | None = None) -> tuple[list[str], np.ndarray]:
    """The native ``plant.Plant`` under the runners' protocol. ``parameters`` by our
    names: initial values ``<state>_0``, ``rtol``/``atol``/``v_eps``, vehicle values.
    ``h`` may be an array of per-step sizes (see :func:`libcosim_step_sizes`)."""
    from msagv.plant.signals import state_names
    from msagv.plant.stepping import Plant

    from .variables import set_path, vehicle_paths

    params = dict(parameters or {})
    initial = {s: params.pop(f"{s}_0") for s in state_names(vehicle) if f"{s}_0" in params}
    opts = {k: params.pop(k) for k in ("rtol", "atol", "v_eps") if k in params}
    if params:
        from msagv.plant.vehicle import vehicle_from_dict

        paths = {n: p for n, p, _, _ in vehicle_paths(vehicle)}
        vd = vehicle.to_dict()
        for k, x in params.items():
            set_path(vd, paths[k], x)
        vehicle = vehicle_from_dict(vd)
    p = Plant(vehicle, initial=initial, **opts)
    nw = vehicle.n_wheels
    S = np.empty((len(U) + 1, len(p.signal_names)))
    S[0] = p.output_vector()
    hs = np.broadcast_to(np.asarray(h, dtype=float), (len(U),))
    for k in range(len(U)):
        p.set_inputs(U[k, :nw], U[k, nw:])
        p.do_step(p.t, float(hs[k]))
        S[k + 1] = p.output_vector()
    return p.signal_names, S


def run_fmpy(fmu_path: str | Path, U: np.ndarray, h: float = CONTROL_PERIOD,
             parameters: Mapping[str, float] | None = None,
             timing: list | None = None) -> tuple[list[str], np.ndarray]:
    """Our FMU stepped by fmpy's ``FMU2Slave`` (setReal inputs, doStep, getReal outputs).

    ``parameters`` by our names (as :func:`run_native`). If ``timing`` is a list, the wall
    time of each step's set/doStep/get is appended to it (seconds).
    """
    from fmpy import extract, read_model_description
    from fmpy.fmi2 import FMU2Slave

    cfg = fmu_config(fmu_path)
    md = read_model_description(str(fmu_path))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    keys, out_names = _signal_columns(cfg)
    in_vr = [vr[v["name"]] for v in cfg["variables"] if v["role"] == "input"]
    out_vr = [vr[n] for n in out_names]
    pars = _names_to_fmu(cfg, parameters)
    d = extract(str(fmu_path))
    fmu = FMU2Slave(guid=md.guid, unzipDirectory=d, modelIdentifier=md.coSimulation.modelIdentifier,
                    instanceName="plant")
    try:
        fmu.instantiate(loggingOn=True)
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
        if pars:
            fmu.setReal([vr[n] for n in pars], list(pars.values()))
        fmu.exitInitializationMode()
        S = np.empty((len(U) + 1, len(out_vr)))
        S[0] = fmu.getReal(out_vr)
        t = 0.0
        clock = time.perf_counter
        for k in range(len(U)):
            t0 = clock()
            fmu.setReal(in_vr, U[k].tolist())
            fmu.doStep(currentCommunicationPoint=t, communicationStepSize=h)
            S[k + 1] = fmu.getReal(out_vr)
            if timing is not None:
                timing.append(clock() - t0)
            t += h
        fmu.terminate()
    finally:
        fmu.freeInstance()
        shutil.rmtree(d, ignore_errors=True)
    return keys, S


def run_libcosim(fmu_path: str | Path, U: np.ndarray, h: float = CONTROL_PERIOD,
                 parameters: Mapping[str, float] | None = None) -> tuple[list[str], np.ndarray]:
    """Our FMU simulated by libcosim (Open Simulation Platform) through libcosimpy:
    inputs by an override manipulator, outputs by a last-value observer, one
    ``execution.step()`` per row. Row 0 is ``nan`` (libcosim initializes in its first step)."""
    from fmpy import read_model_description
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimManipulator import CosimManipulator
    from libcosimpy.CosimObserver import CosimObserver
    from libcosimpy.CosimSlave import CosimLocalSlave

    cfg = fmu_config(fmu_path)
    md = read_model_description(str(fmu_path))
    vr = {v.name: v.valueReference for v in md.modelVariables}
    keys, out_names = _signal_columns(cfg)
    in_vr = [vr[v["name"]] for v in cfg["variables"] if v["role"] == "input"]
    out_vr = [vr[n] for n in out_names]
    pars = _names_to_fmu(cfg, parameters)
    log_output_level(CosimLogLevel.WARNING)
    step_ns = int(round(h * 1e9))
    ex = CosimExecution.from_step_size(step_ns)
    slave = CosimLocalSlave(fmu_path=str(Path(fmu_path).resolve()), instance_name="plant")
    idx = ex.add_local_slave(slave)
    if idx < 0:
        raise RuntimeError("libcosim could not load the FMU")
    obs = CosimObserver.create_last_value()
    ex.add_observer(obs)
    man = CosimManipulator.create_override()
    ex.add_manipulator(man)
    for n, x in pars.items():
        if not ex.real_initial_value(idx, vr[n], x):
            raise RuntimeError(f"libcosim refused the initial value of {n}")
    S = np.full((len(U) + 1, len(out_vr)), np.nan)
    for k in range(len(U)):
        if not man.slave_real_values(idx, in_vr, U[k].tolist()):
            raise RuntimeError(f"libcosim refused the inputs of step {k}")
        if not ex.step(1):
            raise RuntimeError(f"libcosim step {k} failed")
        S[k + 1] = obs.last_real_values(idx, out_vr)
    return keys, S


def libcosim_step_sizes(n_steps: int, h: float) -> np.ndarray:
    """The step sizes libcosim hands an FMU: it counts time in integer nanoseconds and
    passes ``t_(k+1) - t_k`` with ``t = ns / 1e9``, which differ from ``h`` in the last
    bits. The native plant stepped with these matches libcosim exactly."""
    ns = int(round(h * 1e9))
    k = np.arange(n_steps + 1)
    t = np.array([(i * ns) / 1e9 for i in k])
    return np.diff(t)


def main(argv: list[str] | None = None) -> int:
    """``python -m msagv.fmu_build.drive JOB.json OUT.npz``.

    JOB: ``{"runs": [{"engine": "fmpy" | "libcosim", "fmu": path, "seconds": 2.0,
    "h": 0.01, "seed": 0, "parameters": {...}}, ...]}``, inputs from
    :func:`varied_inputs`. Runs share the process, so the plant compiles once. OUT holds,
    for run i, ``names_i``, ``S_i``, ``U_i``, and ``plant_imported`` (whether the
    project's ``plant`` got imported: it must not be, each FMU brings its own copy).
    """
    argv = sys.argv[1:] if argv is None else argv
    job = json.loads(Path(argv[0]).read_text())
    out = {}
    for i, r in enumerate(job["runs"]):
        cfg = fmu_config(r["fmu"])
        h = float(r.get("h", CONTROL_PERIOD))
        n = int(round(float(r.get("seconds", 2.0)) / h))
        U = varied_inputs(2 * cfg["n_axles"], n, h, int(r.get("seed", 0)))
        run = {"fmpy": run_fmpy, "libcosim": run_libcosim}[r["engine"]]
        names, S = run(r["fmu"], U, h, r.get("parameters"))
        out.update({f"names_{i}": np.array(names), f"S_{i}": S, f"U_{i}": U})
    np.savez(argv[1], plant_imported=np.array("plant" in sys.modules), **out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
