"""The plant's memory over a real-time run, and what liveliness tokens churned under
distinct names leave behind (issue 30, item 5).

``realtime``: ``msagv plant --run-mode realtime`` and ``msagv controller`` (Case 2, the
line, continued past its end) on a free loopback port, the plant's resident set (VmRSS of
``/proc/PID/status``) sampled every ``--every`` s for ``--minutes``; the slope [MB/min]
is a least-squares line through the samples taken once the run has started (the plant's
first state answered: the controller's token and the plant's RSS settle then), from
``--skip`` s after the first sample.

``churn``: a Zenoh session of this process listens on a free port (``--watch plant``: with
the plant's own token watch on ``msagv/agv0/alive/controller/*``, :class:`bridge.presence.
TokenSet`; ``none``: no subscriber at all, a bare session); a child process with stock
zenoh-python declares ``--names`` tokens under that prefix, 1,000 at a time, and undeclares
them (``--same``: the same 1,000 names every round). Prints this process's RSS before and
after and its Python heap's growth (tracemalloc): what the Python side keeps, and what
Zenoh itself keeps.

``sessions``: how many stock sessions a listening session links, with Zenoh's shared
memory on or off at either end (issue 30: with it on at both, 351 and no more). A bare
session of this process listens on a free port (``--listener-shm``); a child process opens
``--sessions`` stock peer sessions to it, one after another, as the flood of
``tests/test_processes.py -k session_flood`` does (``--sessions-shm``: ``default`` leaves
Zenoh's default, on). Prints how many the listener links, and its maps and open files. The
cause of the 351 is in Zenoh's source (``io/zenoh-transport/src/unicast/establishment/ext/
shm/segment.rs``): a listener's shared-memory metadata segment holds a fixed array of 2,810
counters, leased 8 to each peer that negotiates shared memory with QoS priorities on
(2,810 / 8 = 351); the next handshake fails with "No available SHM counters" (its debug
log: ``RUST_LOG=zenoh_transport=debug``) and the session is refused, whatever the memory
or file limits. A peer without shared memory takes no counter.

Run ``python -m msagv.benchmarks.memory_probe realtime [--minutes 10]``,
``python -m msagv.benchmarks.memory_probe churn [--names 5000] [--watch plant|none]
[--same]`` or ``python -m msagv.benchmarks.memory_probe sessions [--sessions 400]
[--listener-shm on|off] [--sessions-shm default|on|off]`` (Linux: reads ``/proc``).
"""

from __future__ import annotations

import argparse
import gc
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int | str = "self") -> float:
    """The resident set [MB] of process ``pid`` (``/proc/PID/status``'s VmRSS)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"no VmRSS for process {pid}")


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


def realtime(minutes: float, every: float, skip: float) -> dict:
    port = _free_port()
    ep = f"tcp/127.0.0.1:{port}"
    tmp = Path(tempfile.mkdtemp(prefix="msagv-memory-"))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "msagv"]
    plant = subprocess.Popen(cmd + ["plant", "--run-mode", "realtime", "--case", "line",
                                    "--duration", str(minutes * 60 + 600), "--wait", "600",
                                    "--listen", ep, "--json", "-q"],
                             env=env, stdout=(tmp / "plant.json").open("w"),
                             stderr=(tmp / "plant.err").open("w"))
    ctl = subprocess.Popen(cmd + ["controller", "--case", "line", "--connect", ep, "-q"],
                           env=env, stdout=subprocess.DEVNULL,
                           stderr=(tmp / "controller.err").open("w"))
    samples = []
    try:
        # the run has started when states come (the plant steps once the controller's
        # first answer came): 50 of them seen by a session of our own
        import zenoh

        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("connect/endpoints", f'["{ep}"]')
        c.insert_json5("scouting/multicast/enabled", "false")
        seen = []
        s = zenoh.open(c)
        try:
            sub = s.declare_subscriber("msagv/agv0/state/**", lambda _s: seen.append(1))
            t0 = time.monotonic()
            while len(seen) < 50:
                if plant.poll() is not None or time.monotonic() - t0 > 900:
                    raise RuntimeError(f"the run did not start: {(tmp / 'plant.err').read_text()}")
                time.sleep(0.2)
            sub.undeclare()
        finally:
            s.close()
        t0 = time.monotonic()
        while time.monotonic() - t0 < minutes * 60 and plant.poll() is None:
            samples.append((time.monotonic() - t0, rss_mb(plant.pid)))
            time.sleep(every)
    finally:
        _stop(ctl)
        _stop(plant)
    d = np.array([s for s in samples if s[0] >= skip])
    slope = float(np.polyfit(d[:, 0] / 60.0, d[:, 1], 1)[0]) if len(d) > 2 else float("nan")
    return {"minutes": minutes, "samples": len(d), "rss_first_mb": float(d[0, 1]),
            "rss_last_mb": float(d[-1, 1]), "rss_min_mb": float(d[:, 1].min()),
            "rss_max_mb": float(d[:, 1].max()), "slope_mb_per_min": slope,
            "load": os.getloadavg()[0], "logs": str(tmp)}


CHILD = """
import sys, time, uuid, zenoh
port, prefix, names, same = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] == "1"
c = zenoh.Config()
c.insert_json5("mode", '"peer"')
c.insert_json5("connect/endpoints", '["tcp/127.0.0.1:%s"]' % port)
c.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(c)
done = 0
while done < names:
    n = min(1000, names - done)
    keys = [prefix + "/" + ("n%d" % i if same else uuid.uuid4().hex) for i in range(n)]
    toks = [s.liveliness().declare_token(k) for k in keys]
    time.sleep(0.5)
    for t in toks:
        t.undeclare()
    time.sleep(0.5)
    done += n
s.close()
"""


def churn(names: int, watch: str, same: bool) -> dict:
    from msagv.bridge.presence import TokenSet
    from msagv.bridge.session import SessionOptions
    from msagv.bridge.zenoh_transport import ZenohTransport

    port = _free_port()
    prefix = "msagv/agv0/alive/controller"
    t = ZenohTransport.open(SessionOptions(listen=[f"tcp/127.0.0.1:{port}"]), "plant")
    ts = None
    try:
        if watch == "plant":
            ts = TokenSet(t, prefix)
            ts.focus("owner")
        tracemalloc.start()
        time.sleep(2.0)
        gc.collect()
        r0, h0 = rss_mb(), tracemalloc.get_traced_memory()[0]
        subprocess.run([sys.executable, "-c", CHILD, str(port), prefix, str(names),
                        "1" if same else "0"], timeout=600, check=True)
        time.sleep(3.0)
        gc.collect()
        r1, h1 = rss_mb(), tracemalloc.get_traced_memory()[0]
        out = {"names": names, "same": same, "watch": watch, "rss_before_mb": r0,
               "rss_after_mb": r1, "rss_growth_mb": r1 - r0,
               "python_heap_growth_mb": (h1 - h0) / 1e6}
        if ts is not None:
            out["presence"] = ts.summary()
        return out
    finally:
        tracemalloc.stop()
        if ts is not None:
            ts.close()
        t.close()


SESSIONS_CHILD = r"""
import json, sys, time
import zenoh

port, n, shm = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
sessions = []
for i in range(n):
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    if shm != "default":
        c.insert_json5("transport/shared_memory/enabled", "true" if shm == "on" else "false")
    sessions.append(zenoh.open(c))
print(len(sessions), flush=True)
sys.stdin.read()  # held open until the parent has counted
"""


def sessions(n: int, listener_shm: str, sessions_shm: str) -> dict:
    import json

    import zenoh

    port = _free_port()
    c = zenoh.Config()
    c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/shared_memory/enabled",
                   "true" if listener_shm == "on" else "false")
    z = zenoh.open(c)
    child = subprocess.Popen([sys.executable, "-c", SESSIONS_CHILD, str(port), str(n),
                              sessions_shm], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             text=True)
    try:
        t0 = time.monotonic()
        opened = int(child.stdout.readline() or 0)
        open_s = time.monotonic() - t0
        time.sleep(2.0)  # links that were coming up
        maps = sum(1 for _ in open("/proc/self/maps"))
        return {"sessions": n, "listener_shm": listener_shm, "sessions_shm": sessions_shm,
                "opened": opened, "open_s": open_s, "linked": len(list(z.info.peers_zid())),
                "listener_maps": maps, "listener_fds": len(os.listdir("/proc/self/fd"))}
    finally:
        child.stdin.close()
        _stop(child)
        z.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m msagv.benchmarks.memory_probe",
                                 description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    r = sub.add_parser("realtime")
    r.add_argument("--minutes", type=float, default=10.0)
    r.add_argument("--every", type=float, default=5.0)
    r.add_argument("--skip", type=float, default=30.0)
    c = sub.add_parser("churn")
    c.add_argument("--names", type=int, default=5000)
    c.add_argument("--watch", choices=["plant", "none"], default="plant")
    c.add_argument("--same", action="store_true")
    s = sub.add_parser("sessions")
    s.add_argument("--sessions", type=int, default=400)
    s.add_argument("--listener-shm", choices=["on", "off"], default="on")
    s.add_argument("--sessions-shm", choices=["default", "on", "off"], default="default")
    a = ap.parse_args(argv)
    if a.what == "realtime":
        res = realtime(a.minutes, a.every, a.skip)
    elif a.what == "churn":
        res = churn(a.names, a.watch, a.same)
    else:
        res = sessions(a.sessions, a.listener_shm, a.sessions_shm)
    for k, v in res.items():
        print(f"{k}: {v:.2f}" if isinstance(v, float) else f"{k}: {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
