"""``msagv report``: the paper's metrics and plots from a recording.

A recording of either process (``--record``) holds every state and command with its time.
The report rebuilds the per-step log of :class:`controller.loop.RunLog` from it (state k,
the reference at t_k, the command answering state k) and computes the metrics with the same
function as ``msagv run`` (:func:`controller.metrics.compute_metrics`), so a run over Zenoh
is evaluated exactly like an in-process one: in lockstep the numbers are identical.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import messages as M
from .recording import RecordingError, read_recording


class ReportError(ValueError):
    """The recording holds no usable run (the message says why)."""


@dataclass
class RecordedRun:
    """One plant run (seq from 0) as seen in a recording."""

    states: dict = field(default_factory=dict)  # seq -> decoded state
    cmds: dict = field(default_factory=dict)  # state_seq -> first decoded command answering it
    cmd_ts: dict = field(default_factory=dict)  # state_seq -> its record time
    state_ts: dict = field(default_factory=dict)  # seq -> record time
    references: list = field(default_factory=list)  # (first seq it applies to, message)
    end_seq: int | None = None


@dataclass
class _Cmd:
    omega_w: list
    omega_s: list
    solve_ms: float
    cost: float


def split_runs(header: dict, records: list[dict]) -> list[RecordedRun]:
    """Valid states and commands of each run (a run starts at seq 0 or when seq decreases).
    Records carrying a rejection reason (``why``) are skipped, as the process skipped them."""
    nw = len(header["vehicle"]["axle_x"]) * 2
    runs: list[RecordedRun] = []
    cur: RecordedRun | None = None
    last = None
    pending_refs: list = []
    for r in records:
        key = r.get("key")
        if key is None or "why" in r:
            continue
        if key.endswith("/state"):
            try:
                st = M.decode_state(r["p"], nw)
            except M.MessageError:
                continue
            seq = st["seq"]
            if cur is None or seq == 0 and cur.states or (last is not None and seq < last):
                cur = RecordedRun()
                runs.append(cur)
            last = seq
            if seq in cur.states:  # a state sent again (lockstep, controller restarted)
                continue
            cur.states[seq] = st
            cur.state_ts[seq] = r["ts"]
            for m in pending_refs:
                cur.references.append((seq, m))
            pending_refs = []
            if st.get("end"):
                cur.end_seq = seq
        elif key.endswith("/cmd"):
            try:
                c = M.decode_cmd(r["p"], nw)
            except M.MessageError:
                continue
            if cur is not None and c["state_seq"] in cur.states and c["state_seq"] not in cur.cmds:
                cur.cmds[c["state_seq"]] = c
                cur.cmd_ts[c["state_seq"]] = r["ts"]
        elif key.endswith("/reference"):
            try:
                pending_refs.append(M.decode_reference(r["p"]))
            except M.MessageError:
                continue
    return [r for r in runs if r.states]


def reference_from_message(m: dict, t_offset: float = 0.0):
    from controller.reference import from_samples

    t = np.asarray(m["t"], dtype=float) + t_offset
    return from_samples(t, m["x"], m["y"], m["phi"], name=m.get("name", "trajectory"))


def log_from_run(run: RecordedRun, reference):
    """``(RunLog, solve_ms, references)``: rows for every state before the end (or before
    the last recorded state if the run was cut short); W at the end from the last state."""
    from controller.loop import RunLog

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


def evaluate(path: str | Path, run_index: int = -1):
    """``(metrics, info, log, reference)`` of one run of a recording (default the last)."""
    from controller.metrics import compute_metrics, percentiles

    header, records, summary = read_recording(path)
    runs = split_runs(header, records)
    if not runs:
        raise ReportError(f"{path}: no states recorded")
    try:
        run = runs[run_index]
    except IndexError:
        raise ReportError(f"{path}: --run {run_index}: the recording has {len(runs)} run(s)") from None
    reference = reference_from_message(header["reference"])
    log, solve, refs = log_from_run(run, reference)
    m = compute_metrics(np.asarray(log.pose), np.asarray(log.ref), log.W[0], log.W_final, solve)
    rows = len(log.t)
    answered = sum(1 for k in run.states if k in run.cmds and k < (run.end_seq or 1 << 62))
    # state -> command time as recorded (record times of one process; without the solve)
    lat = [run.cmd_ts[k] - run.state_ts[k] - run.cmds[k].get("solve_ms", 0.0) / 1000.0
           for k in run.cmds if k in run.state_ts]
    rejected = sum(1 for r in records if "why" in r)
    info = {"recording": str(path), "role": header.get("role"), "id": header.get("id"),
            "run_mode": header.get("run_mode"), "runs": len(runs),
            "run": run_index if run_index >= 0 else len(runs) + run_index,
            "steps": rows, "answered": answered, "unanswered": rows - min(answered, rows),
            "ended": run.end_seq is not None, "references": len(refs) - 1,
            "latency_ms": {k: (v if v == v else None) for k, v in
                           percentiles(np.asarray(lat) * 1000.0).items()},
            "rejected": rejected, "summary": summary}
    return m, info, log, refs[-1]


def main(argv: list[str]) -> int:
    from controller.metrics import format_table

    from .run_cmd import plot_run

    ap = argparse.ArgumentParser(prog="msagv report",
                                 description="The paper's metrics and plots from a recording "
                                             "(msagv plant/controller --record FILE).")
    ap.add_argument("recording", metavar="FILE")
    ap.add_argument("--run", type=int, default=-1,
                    help="which plant run of the recording, 0 = first (default: the last)")
    ap.add_argument("--json", action="store_true",
                    help="print the metrics (keys as msagv run --json) plus 'recording' info")
    ap.add_argument("--plot", metavar="FILE", help="write a PNG (path, errors, wear power)")
    ap.add_argument("--log", metavar="FILE", help="write the per-step log as CSV")
    a = ap.parse_args(argv)
    try:
        m, info, log, ref = evaluate(a.recording, a.run)
    except (RecordingError, ReportError, KeyError, TypeError) as e:
        print(f"msagv report: {e}", file=sys.stderr)
        return 2
    if a.log:
        log.to_csv(a.log)
    if a.plot:
        plot_run(log, ref, a.plot, title=f"{ref.name} over Zenoh ({info['run_mode']}, "
                                         f"{info['role']} recording)")
    if a.json:
        print(json.dumps(dict(m, recording=info)))
    else:
        print(format_table(m, f"{ref.name}: {info['recording']} ({info['role']}, "
                              f"{info['run_mode']}, run {info['run']} of {info['runs']})"))
        lat = info["latency_ms"]
        print(f"  answered   {info['answered']} of {info['steps']} states; rejected messages "
              f"{info['rejected']}")
        if lat["p50"] is not None:
            print(f"  latency    p50 {lat['p50']:.3f}  p99 {lat['p99']:.3f}  max {lat['max']:.3f} ms "
                  f"(state -> command, without the solve; as recorded)")
        if a.plot:
            print(f"  plot       {Path(a.plot)}")
    return 0
