"""The paper's metrics from a recording (``msagv report``, ``msagv demo``).

A recording of either process (``--record``) holds every state and command with its time.
The report rebuilds the per-step log of :class:`controller.loop.RunLog` from it (state k,
the reference at t_k, the command answering state k) and computes the metrics with the same
function as ``msagv run`` (:func:`controller.metrics.compute_metrics`), so a run over Zenoh
is evaluated exactly like an in-process one: in lockstep the numbers are identical.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msagv.bridge.recording import RecordedRun, read_recording, split_runs


class ReportError(ValueError):
    """The recording holds no usable run (the message says why)."""


@dataclass
class _Cmd:
    omega_w: list
    omega_s: list
    solve_ms: float
    cost: float


def reference_from_message(m: dict, t_offset: float = 0.0):
    from msagv.controller.reference import from_samples

    t = np.asarray(m["t"], dtype=float) + t_offset
    return from_samples(t, m["x"], m["y"], m["phi"], name=m.get("name", "trajectory"))


def log_from_run(run: RecordedRun, reference):
    """``(RunLog, solve_ms, references)``: rows for every state before the end (or before
    the last recorded state if the run was cut short); W at the end from the last state."""
    from msagv.controller.loop import RunLog

    seqs = sorted(run.states)
    last = run.end_seq if run.end_seq is not None else seqs[-1]
    rows = [k for k in seqs if k < last]
    if not rows:
        raise ReportError("the run has fewer than two states")
    refs = {k: m for k, m in run.references}
    log = RunLog()
    solve = []
    prev = None
    ref = reference
    used = [reference]
    for k in rows:
        st = run.states[k]
        if k in refs:
            m = refs[k]
            ref = reference_from_message(m, st["t"] if m.get("relative") else 0.0)
            used.append(ref)
        c = run.cmds.get(k)
        if c is not None:
            prev = _Cmd(c["omega_w"], c["omega_s"], c.get("solve_ms", float("nan")),
                        c.get("cost", float("nan")))
            if "solve_ms" in c:
                solve.append(c["solve_ms"])
        row_cmd = prev if prev is not None else _Cmd([float("nan")] * len(st["delta"]),
                                                     [float("nan")] * len(st["delta"]),
                                                     float("nan"), float("nan"))
        if c is None:
            row_cmd = _Cmd(row_cmd.omega_w, row_cmd.omega_s, float("nan"), float("nan"))
        log.append(st, ref.sample(st["t"]), row_cmd)
    fin = run.states[last]
    log.W_final = (fin.get("W_s", 0.0), fin.get("W_alpha", 0.0), fin.get("W_t", 0.0))
    log.final_state = fin
    return log, solve, used


def load_run(path: str | Path, run_index: int = -1):
    """``(header, records, summary, runs, run)`` of a recording, ``run`` the one at
    ``run_index`` (default the last); a recording without states or without that run is a
    :class:`ReportError`."""
    header, records, summary = read_recording(path)
    runs = split_runs(header, records)
    if not runs:
        raise ReportError(f"{path}: no states recorded")
    try:
        return header, records, summary, runs, runs[run_index]
    except IndexError:
        raise ReportError(f"{path}: --run {run_index}: the recording has {len(runs)} run(s)") from None


def evaluate(path: str | Path, run_index: int = -1):
    """``(metrics, info, log, reference)`` of one run of a recording (default the last)."""
    from msagv.controller.metrics import compute_metrics, percentiles

    header, records, summary, runs, run = load_run(path, run_index)
    reference = reference_from_message(header["reference"])
    log, solve, refs = log_from_run(run, reference)
    m = compute_metrics(np.asarray(log.pose), np.asarray(log.ref), log.W[0], log.W_final, solve,
                        distance_m=log.distance())
    rows = len(log.t)
    answered = sum(1 for k in run.states if k in run.cmds and k < (run.end_seq or 1 << 62))
    # state -> command time as recorded (record times of one process; without the solve)
    lat = [run.cmd_ts[k] - run.state_ts[k] - run.cmds[k].get("solve_ms", 0.0) / 1000.0
           for k in run.cmds if k in run.state_ts]
    rejected = sum(1 for r in records if "why" in r and "key" in r)  # not events' why
    info = {"recording": str(path), "role": header.get("role"), "id": header.get("id"),
            "run_mode": header.get("run_mode"), "runs": len(runs),
            "run": run_index if run_index >= 0 else len(runs) + run_index,
            "steps": rows, "answered": answered, "unanswered": rows - min(answered, rows),
            "ended": run.end_seq is not None, "references": len(refs) - 1,
            "latency_ms": percentiles(lat, scale=1000.0),
            "rejected": rejected, "summary": summary}
    return m, info, log, refs[-1]
