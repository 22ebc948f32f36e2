"""Foxglove WebSocket servers measured for the live view (docs/ROS2.md, "Both names of the
protocol"): foxglove-sdk's, foxglove-websocket 0.1.4's, and foxglove-sdk's behind msagv's
front (``experiments/foxglove.py``). Not a test: a measurement, run by hand, one server per
process (so the CPU time is that server's publishing process):

    pip install --no-deps --target /tmp/fgw foxglove-websocket==0.1.4   # for "fgw" only
    python tests/node/measure_servers.py sdk|fgw|front [--fgw-path /tmp/fgw]

With the npm client of tests/node (``npm ci`` there first) it prints: which protocol name
each offer gets at the handshake; how many of the run's messages (9 channels at 100 Hz of
1 KiB, one at 10 Hz of 4 KiB) one client receives paced at 100 Hz for 5 s, and the CPU time
per message; the same as fast as the server takes them; whether a client that stops reading
holds up a reading one. CPU times on a loaded machine are indicative only."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
TOPICS = ["/odom", "/tf", "/joint_states", "/wear", "/clock", "/plan", "/predicted_path",
          "/steering_controller/commands", "/wheel_controller/commands"]
PAY, MARK = os.urandom(1024), os.urandom(4096)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SDK:
    """foxglove-sdk's server, as it is (accepts foxglove.sdk.v1)."""
    offer = "foxglove.sdk.v1"

    def __init__(self):
        import foxglove

        self.ctx = foxglove.Context()
        self.ch = {t: foxglove.Channel(t, message_encoding="cdr", context=self.ctx,
                                       schema=foxglove.Schema(name="x", encoding="ros2msg",
                                                              data=b"int32 a"))
                   for t in TOPICS + ["/markers"]}
        class Listener(foxglove.websocket.ServerListener):  # every callback, doing nothing
            pass

        self.server = foxglove.start_server(host="127.0.0.1", port=0, context=self.ctx,
                                            server_listener=Listener())
        self.port = self.server.port

    def send(self, topic, payload, ts):
        self.ch[topic].log(payload, log_time=ts)

    def flush(self, timeout):
        return True

    def stop(self):
        self.server.stop()


class Front(SDK):
    """foxglove-sdk's server behind msagv's front (accepts both names)."""
    offer = "foxglove.websocket.v1"

    def __init__(self):
        super().__init__()
        sys.path.insert(0, str(HERE.parents[1]))
        from msagv.experiments.foxglove import _Front

        self.front = _Front("127.0.0.1", 0)
        self.front.start(self.port)
        self.port = self.front.port

    def stop(self):
        self.server.stop()
        self.front.close()


class FGW:
    """foxglove-websocket 0.1.4's server (accepts foxglove.websocket.v1), on its own loop."""
    offer = "foxglove.websocket.v1"

    def __init__(self):
        from foxglove_websocket.server import FoxgloveServer

        self.loop = asyncio.new_event_loop()
        self.port = _free_port()
        self.futs = []
        threading.Thread(target=self.loop.run_forever, daemon=True).start()

        async def start():
            self.server = FoxgloveServer("127.0.0.1", self.port, "measure")
            self.server.start()
            await self.server.wait_opened()
            self.ids = {t: await self.server.add_channel(
                {"topic": t, "encoding": "cdr", "schemaName": "x", "schema": "int32 a",
                 "schemaEncoding": "ros2msg"}) for t in TOPICS + ["/markers"]}

        asyncio.run_coroutine_threadsafe(start(), self.loop).result(10)

    def send(self, topic, payload, ts):
        self.futs.append(asyncio.run_coroutine_threadsafe(
            self.server.send_message(self.ids[topic], ts, payload), self.loop))

    def flush(self, timeout):
        """True when every send finished within ``timeout`` s (False: publishing blocked)."""
        end = time.monotonic() + timeout
        try:
            for f in self.futs:
                f.result(max(0.01, end - time.monotonic()))
            return True
        except Exception:  # noqa: BLE001 - a timeout: still pending
            return False
        finally:
            self.futs = []

    def stop(self):
        async def close():
            self.server.close()
            await self.server.wait_closed()

        asyncio.run_coroutine_threadsafe(close(), self.loop).result(10)


def handshake(port, offer):
    from websockets.sync.client import connect

    try:
        with connect(f"ws://127.0.0.1:{port}", subprotocols=offer, open_timeout=5) as ws:
            return ws.subprotocol
    except Exception as e:  # noqa: BLE001 - the refusal is the result
        return f"refused ({type(e).__name__})"


def publish(srv, rounds, paced):
    t0, c0, n = time.monotonic(), time.process_time(), 0
    for k in range(rounds):
        if paced and (w := t0 + k * 0.01 - time.monotonic()) > 0:
            time.sleep(w)
        ts = time.time_ns()
        for t in TOPICS:
            srv.send(t, PAY, ts)
            n += 1
        if k % 10 == 0:
            srv.send("/markers", MARK, ts)
            n += 1
    return n, time.process_time() - c0


class Client:
    """The npm client of tests/node in a subprocess."""

    def __init__(self, srv, seconds):
        self.out = Path(tempfile.mkstemp(suffix=".json")[1])
        self.p = subprocess.Popen(
            ["node", str(HERE / "foxglove_client.mjs"), "--url", f"ws://127.0.0.1:{srv.port}",
             "--out", str(self.out), "--seconds", str(seconds), "--subprotocol", srv.offer])
        time.sleep(3)  # connected and subscribed (a measurement: not a test's wait)

    def received(self):
        self.p.wait(60)
        n = len(json.loads(self.out.read_text())["messages"])
        self.out.unlink()
        return n


def stalled_client(port, offer):
    """A client that subscribes to every channel, then never reads."""
    s = socket.create_connection(("127.0.0.1", port))
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
               f"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {offer}\r\n\r\n").encode())
    time.sleep(1)
    head = s.recv(65536)
    ids = [int(x) for x in re.findall(rb'"id":(\d+)', head[head.find(b'"advertise"'):])]
    body = json.dumps({"op": "subscribe", "subscriptions": [
        {"id": i + 1, "channelId": c} for i, c in enumerate(ids)]}).encode()
    frame = bytes([0x81, 0x80 | 126]) + len(body).to_bytes(2, "big") + b"\0\0\0\0" + body
    s.sendall(frame)  # masked with a zero key: the payload as it is
    return s, len(ids)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("server", choices=["sdk", "fgw", "front"])
    ap.add_argument("--fgw-path", default="/tmp/fgw")
    a = ap.parse_args()
    sys.path.insert(0, a.fgw_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        srv = {"sdk": SDK, "fgw": FGW, "front": Front}[a.server]()
    print("warnings on start:", len({str(w.message) for w in caught}))
    print("handshake, offered -> chosen:", {
        ",".join(o): handshake(srv.port, o) for o in (
            ["foxglove.websocket.v1"], ["foxglove.sdk.v1"],
            ["foxglove.sdk.v1", "foxglove.websocket.v1"])})
    c = Client(srv, 12)
    n, cpu = publish(srv, 500, paced=True)
    srv.flush(30)
    print(f"paced 100 Hz, 5 s: sent {n}, received {c.received()}, CPU {cpu / n * 1e6:.1f} us/msg")
    c = Client(srv, 25)
    n, cpu = publish(srv, 3000, paced=False)
    srv.flush(60)
    print(f"burst: sent {n}, received {c.received()}, CPU {cpu / n * 1e6:.1f} us/msg to hand over")
    s, subscribed = stalled_client(srv.port, srv.offer)
    c = Client(srv, 15)
    n, _ = publish(srv, 500, paced=True)
    done = srv.flush(10)
    print(f"a stalled client ({subscribed} channels) beside: sent {n}, the reading client "
          f"received {c.received()}, publishing finished within 10 s: {done}")
    s.close()
    srv.stop()


if __name__ == "__main__":
    main()
