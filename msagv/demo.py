"""``msagv demo``: plant and controller as two processes over Zenoh.

Starts ``msagv plant --run-mode realtime`` and ``msagv controller`` on a free loopback port
(no network, no router), drives the paper's Case 1 curve at 15 km/h for 20 s of vehicle
time at 100 Hz in real time, evaluates the plant's recording with ``msagv report``'s code,
prints the metrics table and the transport figures, writes a PNG and stops both processes.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bridge.process import free_port


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
             extra_controller: list[str] | None = None, timeout: float | None = None) -> dict:
    """Run plant + controller; returns ``{"metrics", "plant", "controller", "recording"}``."""
    from experiments.recorded import evaluate

    work = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="msagv-demo-"))
    work.mkdir(parents=True, exist_ok=True)
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    q = ["-q"] if quiet else []
    plant_rec, ctl_rec = work / "plant.rec", work / "controller.rec"
    plant_cmd = msagv_cmd("plant", "--run-mode", run_mode, "--case", "curve", "--speed", speed,
                          "--duration", f"{duration:g}", "--listen", ep, "--record", str(plant_rec),
                          "--json", *q, *(extra_plant or []))
    ctl_cmd = msagv_cmd("controller", "--case", "curve", "--speed", speed, "--seed", str(seed),
                        "--connect", ep, "--exit-at-end", "--record", str(ctl_rec), "--json", *q,
                        *(extra_controller or []))
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


def main(argv: list[str]) -> int:
    from controller.metrics import format_table
    from experiments.plots import plot_run

    ap = argparse.ArgumentParser(prog="msagv demo", description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, metavar="S",
                    help="vehicle time [s] (default 20)")
    ap.add_argument("--speed", default="15", metavar="KMH", help="Case 1 speed (default 15)")
    ap.add_argument("--run-mode", choices=["realtime", "lockstep"], default="realtime")
    ap.add_argument("--deadline-ms", type=float, default=7.0,
                    help="the controller's solve budget per period (default 7)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--solver", choices=["sa", "ipopt"], default="sa",
                    help="the controller's solver (ipopt: the reference, too slow for 100 Hz "
                         "here; use it with --run-mode lockstep)")
    ap.add_argument("--plot", metavar="FILE", default="msagv-demo.png",
                    help="PNG to write (default msagv-demo.png)")
    ap.add_argument("--keep", metavar="DIR", help="keep the recordings in DIR")
    ap.add_argument("--json", action="store_true",
                    help="print the metrics (keys as msagv run --json) plus missed_periods, "
                         "latency_ms and rejected")
    ap.add_argument("--rt-priority", type=int, default=0, metavar="N",
                    help="run both processes under SCHED_FIFO priority N (needs CAP_SYS_NICE; "
                         "default 0: normal priority)")
    ap.add_argument("-v", "--verbose", action="store_true", help="show the processes' logs")
    a = ap.parse_args(argv)
    if not a.duration > 0:
        print("msagv demo: --duration must be > 0", file=sys.stderr)
        return 2
    tmp = None
    work = a.keep
    if work is None:
        tmp = tempfile.TemporaryDirectory(prefix="msagv-demo-")
        work = tmp.name
    t0 = time.monotonic()
    try:
        if not a.json:
            print(f"msagv demo: plant and controller over Zenoh (loopback), Case 1 at "
                  f"{a.speed} km/h, {a.duration:g} s, {a.run_mode}...", file=sys.stderr, flush=True)
        try:
            rt = ["--rt-priority", str(a.rt_priority)] if a.rt_priority else []
            r = run_demo(a.duration, a.speed, a.run_mode, a.deadline_ms, a.seed, work,
                         quiet=not a.verbose, extra_plant=rt,
                         extra_controller=rt + ["--solver", a.solver])
        except (RuntimeError, ValueError) as e:
            print(f"msagv demo: {e}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            print("msagv demo: interrupted", file=sys.stderr)
            return 130
        if a.plot:
            plot_run(r["log"], r["reference"], a.plot,
                     title=f"{r['reference'].name} over Zenoh ({a.run_mode}, {a.speed} km/h)")
    finally:
        if tmp is not None:
            tmp.cleanup()
    m, ps, cs = r["metrics"], r["plant"], r["controller"]
    rejected = ps["rejected"]["total"] + cs.get("rejected", {}).get("total", 0)
    lat = {k: ps["latency_ms"][k] for k in ("p50", "p99", "max")}
    if a.json:
        out = dict(m)
        out.update(missed_periods=ps["missed_periods"], latency_ms=lat, rejected=rejected,
                   period_jitter_ms={k: ps["period_jitter_ms"][k] for k in ("p50", "p99", "max")},
                   lost_commands=ps["commands"]["lost"], late_commands=ps["commands"]["late"],
                   safe_events=ps["safe"]["events"], run_mode=a.run_mode)
        print(json.dumps(out))
        return 0
    print(format_table(m, f"{r['reference'].name}, TWO (mf), two processes over Zenoh, "
                          f"{a.run_mode}"))
    c = ps["commands"]
    print(f"  commands   {c['accepted']} accepted, {c['late']} late, {c['lost']} lost; "
          f"rejected messages {rejected}")
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
    if a.keep:
        print(f"  recordings {Path(a.keep) / 'plant.rec'}, {Path(a.keep) / 'controller.rec'}")
    print(f"  wall time  {time.monotonic() - t0:.1f} s")
    return 0
