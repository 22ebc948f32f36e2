"""Helpers shared by the test modules (fixtures are in conftest.py): the command line as a
subprocess, loopback endpoints, a set of processes a test starts and always stops, a 3-axle
vehicle unlike the built-in one, and editing TOML texts line by line.

``tests/`` is not a package: pytest puts it on ``sys.path``, so modules import this as
``import helpers`` (as they import ``reference_model``)."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def msagv(*args) -> list[str]:
    """The command line running ``msagv ARGS`` with this Python (no installed script needed)."""
    return [sys.executable, "-m", "msagv", *[str(a) for a in args]]


def run_msagv(*args, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    """``msagv ARGS`` to completion, output captured as text."""
    return subprocess.run(msagv(*args), capture_output=True, text=True, timeout=timeout, **kw)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now (the standard library only, so the
    protocol test's client stays free of the project's code)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def ep(port: int) -> str:
    """The loopback TCP endpoint of ``port``."""
    return f"tcp/127.0.0.1:{port}"


def default_sigint() -> None:
    """In the child, before exec: SIGINT back to its default disposition."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def stop(p: subprocess.Popen, grace: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``grace`` seconds (by the process's own id)."""
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(grace)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(5)


class Procs:
    """Processes of one test: output to files, SIGTERM then SIGKILL at the end."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.p: dict[str, subprocess.Popen] = {}

    def start(self, name: str, args: list[str]) -> subprocess.Popen:
        env = dict(os.environ, PYTHONUNBUFFERED="1",
                   PYTHONFAULTHANDLER="1")  # an abort prints every thread's stack
        out = (self.tmp / f"{name}.out").open("w")
        err = (self.tmp / f"{name}.err").open("w")
        # SIGINT as a terminal's foreground job has it (a suite started in the background of
        # a non-interactive shell would hand it down ignored, and Python keeps it so)
        self.p[name] = subprocess.Popen(args, stdout=out, stderr=err, env=env, cwd=self.tmp,
                                        preexec_fn=default_sigint)
        out.close()
        err.close()
        return self.p[name]

    def wait(self, name: str, timeout: float) -> int:
        try:
            return self.p[name].wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{name} still running after {timeout} s; stderr:\n"
                                 f"{self.err(name)[-3000:]}") from None

    def out(self, name: str) -> str:
        return (self.tmp / f"{name}.out").read_text()

    def err(self, name: str) -> str:
        return (self.tmp / f"{name}.err").read_text()

    def json(self, name: str) -> dict:
        lines = [ln for ln in self.out(name).splitlines() if ln.startswith("{")]
        assert lines, f"{name} printed no JSON; stderr:\n{self.err(name)[-3000:]}"
        return json.loads(lines[-1])

    def stop_all(self) -> None:
        for p in self.p.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 5
        for p in self.p.values():
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)


# ---- vehicles as TOML text -----------------------------------------------------------------
BUILTIN_TOML = (ROOT / "plant" / "data" / "paper-2axle.toml").read_text()

# A 3-axle vehicle unlike the built-in one: axles not centred on the CG, other tires.
THREE_AXLE_TOML = """\
name = "test-3axle"
mass = 18500.0            # kg
yaw_inertia = 150000.0    # kg m^2
wheel_radius = 0.45       # m
axle_x = [4.0, 0.5, -3.0] # m, front first
half_track = 1.1          # m
steer_loss_kt = 0.025     # m

[tire.longitudinal]
B = 10.0
C = 1.6
mu = 0.85
E = 0.1

[tire.lateral]
B = 8.0
C = 1.35
mu = 0.85
E = -0.3

[tire.dugoff]
C_s = 360000.0
C_alpha = 240000.0
mu = 0.85

[limits]
omega_s_min = -0.7
omega_s_max = 0.7
omega_w_max = 30.0
delta_min = -1.4
delta_max = 1.4
"""


def edit_toml(text: str, table: str, key: str, value: str | None) -> str:
    """Replace the value of ``key`` in ``[table]`` ('' = top level); None deletes the line."""
    out, current, hits = [], "", 0
    for line in text.splitlines():
        m = re.match(r"^\s*\[([^\]]+)\]", line)
        if m:
            current = m.group(1).strip()
        elif current == table and re.match(rf"^\s*{re.escape(key)}\s*=", line):
            hits += 1
            if value is None:
                continue
            line = f"{key} = {value}"
        out.append(line)
    assert hits == 1, f"{table}.{key} not found exactly once"
    return "\n".join(out) + "\n"


def add_toml(text: str, table: str, line: str) -> str:
    """Insert ``line`` into ``[table]`` ('' = top level, before the first table)."""
    lines = text.splitlines()
    if table == "":
        i = next(k for k, s in enumerate(lines) if s.startswith("["))
    else:
        i = lines.index(next(s for s in lines if re.match(rf"^\[{re.escape(table)}\]", s))) + 1
    lines.insert(i, line)
    return "\n".join(lines) + "\n"


def drop_toml_table(text: str, table: str) -> str:
    out, skipping = [], False
    for line in text.splitlines():
        m = re.match(r"^\s*\[([^\]]+)\]", line)
        if m:
            skipping = m.group(1).strip() == table
        if not skipping:
            out.append(line)
    return "\n".join(out) + "\n"


def assert_commands_within_bounds(mpc, vehicle) -> None:
    """Six random states (one with two wheels at their steering stops) through
    ``mpc.step``: every command inside eq. (27)'s bounds, the next steering angle inside
    the stops, the solution inside its box, a finite cost. ``vehicle``: 2 axles."""
    import math

    import numpy as np

    lim = vehicle.limits
    rng = np.random.default_rng(5)
    for i in range(6):
        v = rng.uniform(0.0, 12.0)
        delta = rng.uniform(lim.delta_min, lim.delta_max, vehicle.n_wheels)
        if i == 0:
            delta[:] = [lim.delta_max - 1e-4, lim.delta_min + 1e-4, 0.0, 0.5]
        st = {"t": rng.uniform(0.0, 5.0), "x": rng.uniform(0, 40), "y": rng.normal(0, 2),
              "phi": rng.normal(0.0, 0.5), "vx": v, "vy": 0.1 * v, "r": rng.normal(0, 0.3),
              "delta": delta.tolist()}
        cmd = mpc.step(st)
        assert np.all(cmd.omega_w >= 0) and np.all(cmd.omega_w <= lim.omega_w_max)
        assert np.all(cmd.omega_s >= lim.omega_s_min) and np.all(cmd.omega_s <= lim.omega_s_max)
        nxt = delta + 0.01 * cmd.omega_s
        assert np.all(nxt >= lim.delta_min - 1e-12) and np.all(nxt <= lim.delta_max + 1e-12)
        assert np.all(mpc.z >= mpc.horizon.lower) and np.all(mpc.z <= mpc.horizon.upper)
        assert math.isfinite(cmd.cost)


# ---- the bridge's nodes over the loopback bus ------------------------------------------------
def wait_until(pred, timeout: float, what: str) -> None:
    """Poll ``pred()`` until true; AssertionError naming ``what`` after ``timeout`` s (for
    what a node's helper threads do: the claim loop, a token's confirmation)."""
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.002)


class Running:
    """``with Running(node):`` runs ``node.run()`` in a thread, stopped and joined at exit."""

    def __init__(self, node):
        import threading

        self.node = node
        self.result: dict | None = None
        self.thread = threading.Thread(target=self._run, daemon=True, name="node under test")

    def _run(self) -> None:
        self.result = self.node.run()

    def __enter__(self) -> "Running":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.node.stop.set()
        self.thread.join(10)
        assert not self.thread.is_alive(), "the node's loop did not stop"


class LoopbackPlant:
    """A plant's endpoint on a :class:`bridge.loopback.LoopbackBus`, for the controller's
    tests: it answers claims with a real :class:`bridge.ownership.Ownership` (only while
    ``granting``), declares its token ``alive/plant/{id}`` (``token``), publishes states as
    the plant does (its identity and ``sn = seq``) and keeps the commands it receives."""

    def __init__(self, bus, vid: str = "t0", id: str = "p1", token: bool = True,
                 granting: bool = True):
        from msagv.bridge.ownership import Ownership
        from msagv.bridge.session import Keys

        self.keys = Keys(vid)
        self.t = bus.endpoint(id)
        self.ownership = Ownership()
        self.granting = granting
        self.claims = 0  # claims answered
        self.claims_seen: list[dict] = []  # the claim maps received
        self.cmds: list = []  # the samples received on cmd
        self.t.subscribe(self.keys.cmd, self.cmds.append)
        self._claims = self.t.queryable(self.keys.claim, self._on_claim)
        self.token = self.t.declare_token(self.keys.plant_token(id)) if token else None
        self.pub = self.t.publisher(self.keys.state)

    def _on_claim(self, q) -> None:
        from msagv.bridge.ownership import decode_claim, encode_grant

        if self.granting:
            g = self.ownership.claim(q.sender, decode_claim(q.payload)["action"])
            granted, reason = g.granted, g.reason
        else:
            granted, reason = False, "owned"
        self.claims += 1
        self.claims_seen.append(decode_claim(q.payload))
        q.reply(encode_grant(granted, reason))

    def publish(self, seq: int, payload: bytes) -> None:
        self.pub.put(payload, seq)

    def exchange(self, seq: int, payload: bytes, timeout: float = 10.0) -> dict:
        """Publish state ``seq`` and wait for the command answering it (lockstep)."""
        from msagv.bridge import messages as M

        n = len(self.cmds)
        self.publish(seq, payload)
        wait_until(lambda: any(M.decode_cmd(s.payload, 4)["state_seq"] == seq
                               for s in self.cmds[n:]), timeout, f"the answer to state {seq}")
        return next(M.decode_cmd(s.payload, 4) for s in self.cmds[n:]
                    if M.decode_cmd(s.payload, 4)["state_seq"] == seq)

    def stop_answering_claims(self) -> None:
        """Close the claim queryable right after a claim was answered (the controller's
        next claim is CLAIM_REFRESH_S away, so none is in flight)."""
        n = self.claims
        wait_until(lambda: self.claims > n, 5.0, "a claim")
        time.sleep(0.02)
        self._claims.close()

    def leave(self) -> None:
        """The plant's endpoint leaves the bus (its token disappears, its queryable goes)."""
        self.t.close()


def ros_domain_id() -> int:
    """A random ROS 2 domain id in this test worker's own slice of 1..100: two xdist workers
    never draw the same one (two tests of two workers on one domain saw each other's
    plants and controllers: a clean clone's run failed that way once)."""
    import random

    w = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(w[2:]) if w.startswith("gw") and w[2:].isdigit() else 0
    count = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1))
    size = max(1, 100 // count)
    return 1 + (index % count) * size + random.randrange(size)
