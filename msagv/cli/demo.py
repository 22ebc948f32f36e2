"""``msagv demo``: plant and controller as two processes over Zenoh.

Starts ``msagv plant --run-mode realtime`` and ``msagv controller`` on a free loopback port
(no network, no router), drives the paper's Case 1 curve at 15 km/h for 20 s of vehicle
time at 100 Hz in real time, evaluates the plant's recording with ``msagv report``'s code,
prints the metrics table and the transport figures, writes a PNG and stops both processes.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from msagv.bridge.messages import RUN_MODES
from msagv.bridge.process import free_port
from msagv.plant.signals import CONTROL_PERIOD


def msagv_cmd(*args: str) -> list[str]:
    """The command line running ``msagv ARGS`` with this Python."""
    return [sys.executable, "-m", "msagv", *args]


def stop_process(p: subprocess.Popen, grace: float = 2.0) -> int:
    """SIGTERM, then SIGKILL after ``grace`` seconds; returns the exit code."""
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(grace)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)
    return p.returncode


def _last_json(text: str) -> dict | None:
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                return None
    return None


def run_demo(duration: float = 20.0, speed: str = "15", run_mode: str = "realtime",
             deadline_ms: float | None = 7.0, seed: int = 0, workdir: str | Path | None = None,
             quiet: bool = True, extra_plant: list[str] | None = None,
             extra_controller: list[str] | None = None, timeout: float | None = None,
             secure: str | Path | None = None) -> dict:
    """Run plant + controller; returns ``{"metrics", "plant", "controller", "recording"}``.
    ``secure``: a certificate directory (``msagv certs``): mutual TLS and access control."""
    from msagv.experiments.recorded import evaluate

    work = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="msagv-demo-"))
    work.mkdir(parents=True, exist_ok=True)
    port = free_port()
    ep = f"{'tls' if secure else 'tcp'}/127.0.0.1:{port}"
    sec = ["--secure", str(secure)] if secure else []
    q = ["-q"] if quiet else []
    plant_rec, ctl_rec = work / "plant.rec", work / "controller.rec"
    plant_cmd = msagv_cmd("plant", "--run-mode", run_mode, "--case", "curve", "--speed", speed,
                          "--duration", f"{duration:g}", "--listen", ep, "--record", str(plant_rec),
                          "--json", *q, *sec, *(extra_plant or []))
    ctl_cmd = msagv_cmd("controller", "--case", "curve", "--speed", speed, "--seed", str(seed),
                        "--connect", ep, "--exit-at-end", "--record", str(ctl_rec), "--json", *q,
                        *sec, *(extra_controller or []))
    if deadline_ms is not None:
        ctl_cmd += ["--deadline-ms", f"{deadline_ms:g}"]
    timeout = timeout if timeout is not None else 120.0 + 3.0 * duration
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    procs: list[subprocess.Popen] = []
    try:
        plant = subprocess.Popen(plant_cmd, stdout=subprocess.PIPE, text=True, env=env)
        procs.append(plant)
        ctl = subprocess.Popen(ctl_cmd, stdout=subprocess.PIPE, text=True, env=env)
        procs.append(ctl)
        try:
            p_out, _ = plant.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"the plant did not finish within {timeout:g} s") from None
        try:
            c_out, _ = ctl.communicate(timeout=5.0)
        except subprocess.TimeoutExpired:
            stop_process(ctl)
            c_out, _ = ctl.communicate()
    finally:
        for p in procs:
            stop_process(p)
    p_sum, c_sum = _last_json(p_out or ""), _last_json(c_out or "")
    if plant.returncode != 0 or p_sum is None:
        raise RuntimeError(f"the plant failed (exit {plant.returncode}); see its messages above")
    metrics, info, log, ref = evaluate(plant_rec)
    return {"metrics": metrics, "info": info, "plant": p_sum, "controller": c_sum or {},
            "plant_rc": plant.returncode, "controller_rc": ctl.returncode, "workdir": str(work),
            "log": log, "reference": ref}


def _demo_scenario(a) -> dict:
    """The result's ``scenario`` block of the demo (Case 1 at ``--speed``, the built-in
    vehicle, the controller's default method and model)."""
    from msagv.controller.models import MPCSettings
    from msagv.experiments.results import speed_value, vehicle_info
    from msagv.plant.vehicle import default_vehicle

    d = MPCSettings()
    vehicle = vehicle_info(default_vehicle())  # the demo's plant serves the built-in one
    return {"case": "curve", "trajectory": None, "reference": "case1-curve",
            "speed_kmh": speed_value(a.speed), "vehicle": vehicle, "method": d.method,
            "model": d.model, "solver": a.solver, "seed": a.seed, "duration_s": a.duration,
            "period_s": CONTROL_PERIOD, "after_end": "continue", "plant": "native",
            "initial": "reference"}


def _parser() -> argparse.ArgumentParser:
    from msagv.controller import solvers

    from .args import add_common_args
    from .foxglove_cli import add_foxglove_args

    ap = argparse.ArgumentParser(prog="msagv demo", description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, metavar="S",
                    help="vehicle time [s] (default 20)")
    ap.add_argument("--speed", default="15", metavar="KMH", help="Case 1 speed (default 15)")
    ap.add_argument("--run-mode", choices=list(RUN_MODES), default="realtime",
                    help="the plant's stepping (default realtime: on the wall clock)")
    ap.add_argument("--deadline-ms", type=float, default=7.0,
                    help="the controller's solve budget per period (default 7)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--solver", choices=list(solvers.SOLVERS), default=solvers.DEFAULT_SOLVER,
                    help=f"the controller's solver (default {solvers.DEFAULT_SOLVER}; ipopt: "
                         "the reference, too slow for 100 Hz here: use it with --run-mode "
                         "lockstep; msagv controller --help lists them)")
    ap.add_argument("--plot", metavar="FILE", default="msagv-demo.png",
                    help="figure to write (default msagv-demo.png)")
    ap.add_argument("-o", "--out", metavar="DIR", help="keep the recordings in DIR")
    ap.add_argument("--keep", metavar="DIR", help=argparse.SUPPRESS)  # deprecated: --out
    ap.add_argument("--json", action="store_true",
                    help="print the result as JSON (the shape of msagv run --json, plus "
                         "'transport': missed periods, latency, rejected messages, ...)")
    ap.add_argument("--json-out", metavar="FILE", help="also write the JSON result to FILE")
    ap.add_argument("--rt-priority", type=int, default=0, metavar="N",
                    help="run both processes under SCHED_FIFO priority N (needs CAP_SYS_NICE; "
                         "default 0: normal priority)")
    ap.add_argument("--secure", action="store_true",
                    help="mutual TLS and access control (certificates made for the run by "
                         "msagv certs; docs/SECURITY.md)")
    add_foxglove_args(ap)  # served by the plant process, which prints the address
    add_common_args(ap)  # -v also shows the processes' logs
    return ap


def main(argv: list[str]) -> int:
    from .args import PLOT_SUFFIXES, check_distinct, check_output, fail, warn
    from .foxglove_cli import check_foxglove_args

    prog = "msagv demo"
    a = _parser().parse_args(argv)
    if a.keep:
        warn(prog, ["--keep is deprecated, use --out DIR"])
        a.out = a.out or a.keep
    if not a.duration > 0:
        print("msagv demo: --duration must be > 0", file=sys.stderr)
        return 2
    try:
        check_output(a.plot, "--plot", suffixes=PLOT_SUFFIXES)
        check_output(a.out, "--out", directory=True)
        check_output(a.json_out, "--json-out")
        check_distinct(("--plot", a.plot), ("--json-out", a.json_out))
        from msagv.experiments.scenario import Scenario

        # what the plant process will check, before either process starts
        warn(prog, Scenario(case="curve", speed=a.speed, duration=a.duration,
                            solver=a.solver).preflight())
        check_foxglove_args(a, prog)
    except ValueError as e:
        return fail(prog, e, a)
    t0 = time.monotonic()
    with (tempfile.TemporaryDirectory(prefix="msagv-demo-") if a.out is None
          else contextlib.nullcontext(a.out)) as work:
        if not (a.json or a.quiet):
            print(f"msagv demo: plant and controller over Zenoh (loopback), Case 1 at "
                  f"{a.speed} km/h, {a.duration:g} s, {a.run_mode}...", file=sys.stderr, flush=True)
        try:
            r = _run_processes(a, Path(work))
        except (RuntimeError, ValueError) as e:
            return fail(prog, e, a, 1)
        except KeyboardInterrupt:
            _interrupted(Path(work), a)
            return 130
        scenario = _demo_scenario(a)
        if a.plot:
            from msagv.experiments.plots import plot_run, run_title

            plot_run(r["log"], r["reference"], a.plot,
                     title=run_title(scenario, f"two processes over Zenoh ({a.run_mode})"))
    _report(a, prog, r, scenario, t0)
    return 0


def _run_processes(a, work: Path) -> dict:
    """The two processes of the demo (:func:`run_demo`) with the options' extras."""
    rt = ["--rt-priority", str(a.rt_priority)] if a.rt_priority else []
    certs = None
    if a.secure:
        from msagv.bridge.security import create_certs

        certs = work / "certs"
        create_certs(certs)
    # --foxglove: served by the plant process, which prints the address
    fox = (["--foxglove", "--foxglove-port", str(a.foxglove_port), "--foxglove-host",
            a.foxglove_host] if a.foxglove else [])
    return run_demo(a.duration, a.speed, a.run_mode, a.deadline_ms, a.seed, work,
                    quiet=not a.verbose, extra_plant=rt + fox,
                    extra_controller=rt + ["--solver", a.solver], secure=certs)


def _transport(a, ps: dict, cs: dict) -> dict:
    """The result's ``transport`` block, from the plant's and the controller's summaries."""
    rejected = ps["rejected"]["total"] + cs.get("rejected", {}).get("total", 0)
    return {"run_mode": a.run_mode, "secure": a.secure,
            "missed_periods": ps["missed_periods"],
            "latency_ms": {k: ps["latency_ms"][k] for k in ("p50", "p99", "max")},
            "rejected": rejected,
            "period_jitter_ms": {k: ps["period_jitter_ms"][k] for k in ("p50", "p99", "max")},
            "accepted_commands": ps["commands"]["accepted"],
            "lost_commands": ps["commands"]["lost"], "late_commands": ps["commands"]["late"],
            "safe_events": ps["safe"]["events"]}


def _report(a, prog: str, r: dict, scenario: dict, t0: float) -> None:
    """The result: warnings, the JSON document or the table and the transport's figures."""
    from msagv.controller.metrics import format_table
    from msagv.experiments.results import result

    from .args import note, warn

    m, ps = r["metrics"], r["plant"]
    transport = _transport(a, ps, r["controller"])
    warnings = []
    if a.run_mode == "realtime" and ps["missed_periods"]:
        warnings.append(f"{ps['missed_periods']} control periods were missed (a loaded "
                        f"machine, or solves over the budget): the plant held the last command")
    warn(prog, warnings)
    doc = result("demo", scenario, m, warnings, completed=bool(ps.get("completed", True)),
                 transport=transport)
    if a.json_out:
        Path(a.json_out).write_text(json.dumps(doc, indent=1) + "\n")
    if a.json:
        print(json.dumps(doc))
        return
    how = f"{scenario['method'].upper()} ({scenario['model']}" + (
        f", {a.solver})" if a.solver != "sa" else ")")
    print(format_table(m, f"{r['reference'].name}, {how}, two processes over Zenoh, "
                          f"{a.run_mode}{', mutual TLS + access control' if a.secure else ''}"))
    c, lat = ps["commands"], transport["latency_ms"]
    print(f"  commands   {c['accepted']} accepted, {c['late']} late, {c['lost']} lost; "
          f"rejected messages {transport['rejected']}")
    if lat["p50"] is not None:
        print(f"  latency    p50 {lat['p50']:.3f}  p99 {lat['p99']:.3f}  max {lat['max']:.3f} ms "
              f"(state published -> command received, without the solve)")
    if a.run_mode == "realtime":
        j = ps["period_jitter_ms"]
        print(f"  periods    missed {ps['missed_periods']}; jitter p50 {(j['p50'] or 0):.3f}  "
              f"p99 {(j['p99'] or 0):.3f}  max {(j['max'] or 0):.3f} ms; safe events "
              f"{ps['safe']['events']}")
    if a.plot:
        print(f"  plot       {Path(a.plot)}")
    if a.out:
        print(f"  recordings {Path(a.out) / 'plant.rec'}, {Path(a.out) / 'controller.rec'}")
    note(a, f"  wall time  {time.monotonic() - t0:.1f} s")


def _interrupted(work: Path, a) -> None:
    """Ctrl-C: both processes got it too and closed their recordings; report the metrics
    of the part that ran, from the plant's recording, if there is one."""
    from msagv.controller.metrics import format_table
    from msagv.experiments.recorded import evaluate

    try:
        m, info, _, ref = evaluate(work / "plant.rec")
    except Exception:  # noqa: BLE001 - nothing usable was recorded yet
        print("msagv demo: interrupted before the run produced a result", file=sys.stderr)
        return
    print(format_table(m, f"{ref.name} (interrupted after {info['steps']} steps)"))
    print("msagv demo: interrupted", file=sys.stderr)
