"""Transport: state-to-command round trip over Zenoh between two processes, without a solve.

This process plays the plant: it listens on a free loopback port and publishes a ``state``
message (docs/PROTOCOL.md, 2-axle vehicle, ~230 bytes) every 10 ms, timed on the wall clock
as the realtime plant does. A child process (``python -m msagv.benchmarks.transport_bench
--echo``) plays a controller without a solve: it validates each state with the bridge's
own decoder and answers with a ``cmd`` (encoded by the bridge, ``solve_ms`` 0). The
round trip is measured here from just before ``put`` to the command's arrival in the
subscriber callback, so it holds both directions, both validations and the Python
callbacks: exactly the "latency excluding solve time" of the plant process.

Run ``python benchmarks/transport_bench.py [--seconds 5]``; it prints the result of
:func:`bench_transport` as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import threading
import time

import numpy as np

from msagv.plant.signals import CONTROL_PERIOD

T = CONTROL_PERIOD
N_WHEELS = 4


def _state(seq: int) -> dict:
    return {"t": seq * T, "x": 1.0 + seq * 0.04, "y": 0.5, "phi": 0.1, "vx": 4.1, "vy": 0.3,
            "r": 0.02, "delta": [0.01, 0.012, -0.01, -0.012], "omega_w": [8.3, 8.4, 8.3, 8.4],
            "W_s": 10.0, "W_alpha": 20.0, "W_t": 30.0}


def _echo(endpoint: str, vid: str) -> int:
    """The child: answer every valid state with a zero-solve command."""
    import zenoh

    from msagv.bridge import messages as M
    from msagv.bridge.session import Keys, SessionOptions, open_session

    k = Keys(vid)
    stop = threading.Event()
    import signal

    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with open_session(SessionOptions(id=vid, connect=[endpoint]), "controller") as s:
        pub = s.declare_publisher(k.cmd, express=True, priority=zenoh.Priority.REAL_TIME,
                                  congestion_control=zenoh.CongestionControl.BLOCK)
        seq = [0]
        zeros = [0.0] * N_WHEELS

        def on_state(sample):
            try:
                st = M.decode_state(sample.payload.to_bytes(), N_WHEELS)
            except M.MessageError:
                return
            pub.put(M.encode_cmd(seq[0], st["t"], st["seq"], st["omega_w"], zeros, solve_ms=0.0))
            seq[0] += 1

        sub = s.declare_subscriber(k.state, on_state)
        tok = s.liveliness().declare_token(k.controller_token(str(s.info.zid())))
        while not stop.wait(0.1):
            pass
        tok.undeclare()
        sub.undeclare()
    return 0


def bench_transport(seconds: float = 5.0, period: float = T) -> dict:
    """Round trip state -> command at 1/period over Zenoh between two processes.

    Returns ``{"p50_ms", "p99_ms", "max_ms", "lost", "sent", "received", "rate_hz",
    "seconds", "payload_bytes", "cmd_bytes", "python", "machine"}``. ``lost``: states
    without a command 0.5 s after the last one was sent.
    """
    import zenoh

    from msagv.bridge import messages as M
    from msagv.bridge.process import free_port
    from msagv.bridge.presence import Presence
    from msagv.bridge.session import Keys, SessionOptions, open_session
    from msagv.bridge.zenoh_transport import ZenohTransport

    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    vid = f"bench{os.getpid()}"
    k = Keys(vid)
    n = int(round(seconds / period))
    sent: dict[int, float] = {}
    rtt: dict[int, float] = {}
    lock = threading.Lock()
    cmd_bytes = [0]
    with open_session(SessionOptions(id=vid, listen=[ep]), "plant") as s:
        child = subprocess.Popen([sys.executable, "-m", "msagv.benchmarks.transport_bench", "--echo",
                                  "--endpoint", ep, "--id", vid])
        try:
            def on_cmd(sample):
                now = time.perf_counter()
                b = sample.payload.to_bytes()
                try:
                    c = M.decode_cmd(b, N_WHEELS)
                except M.MessageError:
                    return
                with lock:
                    t0 = sent.get(c["state_seq"])
                    if t0 is not None and c["state_seq"] not in rtt:
                        rtt[c["state_seq"]] = now - t0
                cmd_bytes[0] = len(b)

            sub = s.declare_subscriber(k.cmd, on_cmd)
            pub = s.declare_publisher(k.state, express=True, priority=zenoh.Priority.REAL_TIME,
                                      congestion_control=zenoh.CongestionControl.BLOCK)
            ctl = Presence(ZenohTransport(s, owns=False), k.controller_token())
            t_wait = time.monotonic()
            while not (ctl.present and pub.matching_status.matching):
                if time.monotonic() - t_wait > 60 or child.poll() is not None:
                    raise RuntimeError("transport bench: the echo process did not come up")
                time.sleep(0.01)
            payload_len = len(M.encode_state(0, _state(0)))
            for seq in range(50):  # warm-up (connection, caches), not timed
                pub.put(M.encode_state(10 ** 6 + seq, _state(seq)))
                time.sleep(0.002)
            time.sleep(0.2)
            w0 = time.perf_counter()
            for seq in range(n):
                target = w0 + seq * period
                d = target - time.perf_counter()
                if d > 0:
                    time.sleep(d)
                payload = M.encode_state(seq, _state(seq))
                with lock:
                    sent[seq] = time.perf_counter()
                pub.put(payload)
            time.sleep(0.5)
            ctl.close()
            sub.undeclare()
            pub.undeclare()
        finally:
            child.terminate()
            try:
                child.wait(5)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
    with lock:
        r = np.array([rtt[q] for q in range(n) if q in rtt]) * 1000.0
    return {
        "p50_ms": float(np.percentile(r, 50)) if r.size else None,
        "p99_ms": float(np.percentile(r, 99)) if r.size else None,
        "max_ms": float(r.max()) if r.size else None,
        "lost": int(n - r.size), "sent": n, "received": int(r.size), "rate_hz": 1.0 / period,
        "seconds": seconds, "payload_bytes": payload_len, "cmd_bytes": cmd_bytes[0],
        "python": platform.python_version(), "machine": f"{platform.machine()}, "
                                                      f"{os.cpu_count()} cpus",
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--echo", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--id", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.echo:
        return _echo(a.endpoint, a.id)
    print(json.dumps(bench_transport(a.seconds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
