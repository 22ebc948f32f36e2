"""A live view of a run in Foxglove: foxglove-sdk's WebSocket server serving the run's ROS 2
channels (the optional extra ``foxglove``: ``pip install 'msagv[foxglove]'``).

The channels are those of a recording's ROS 2 bag (:mod:`bridge.ros_msgs`, docs/ROS2.md):
``/odom``, ``/tf``, ``/joint_states``, ``/wear``, ``/markers`` (the body and each wheel at
its steering angle, coloured by its wear power), ``/plan`` (the reference, again every
``PLAN_EVERY`` states for a viewer that joins late), ``/clock``, the two command topics and,
from an in-process run, ``/predicted_path``; CDR with ``ros2msg`` schemas, so Foxglove
decodes them as it decodes a ROS 2 bag. Open Foxglove, "Open connection", Foxglove
WebSocket, the printed address.

:class:`FoxgloveView` has the recorder's interface (``message``, ``event``,
``maybe_flush``, ``close``), so a plant process hands it every state it publishes as it
hands them to its recorder (beside it: :class:`experiments.viewer.Tee`); an in-process loop
calls :meth:`FoxgloveView.on_step`. It only queues (bounded, drops counted): a thread encodes
and sends, so a control loop never waits for the view. The server binds to 127.0.0.1 unless
told otherwise.

Both names of the protocol are accepted: ``foxglove.sdk.v1`` (today's Foxglove app) and
``foxglove.websocket.v1`` (the npm ``@foxglove/ws-protocol`` client, Lichtblick, older Foxglove
Studio). The two are the same protocol under two names (Foxglove's stance; the npm client
decodes foxglove-sdk's messages unchanged), but foxglove-sdk's server refuses the older name
at the handshake (HTTP 400). So the address printed is a small front (:class:`_Front`): it
reads a client's upgrade request, offers foxglove-sdk ``foxglove.sdk.v1`` in place of
``foxglove.websocket.v1`` when the client offers only the older name, names it back in the
answer, and from then on relays bytes unchanged both ways to foxglove-sdk's server on a
loopback port of its own. A client that stops reading stalls only its own relay: foxglove-sdk
then drops that client's oldest messages, as it does for a direct client.
"""

from __future__ import annotations

import asyncio
import logging
import queue
import socket
import threading
import time
from typing import Any, Mapping

from msagv.bridge import messages as M
from msagv.bridge import ros_msgs as R
from msagv.plant.signals import CONTROL_PERIOD

log = logging.getLogger("msagv.foxglove")

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765  # Foxglove's default
PLAN_EVERY = 200  # the plan again every this many states (2 s at 100 Hz)
SDK_PROTOCOLS = ("foxglove.sdk.v1", "foxglove.sdk.v1.1")  # what foxglove-sdk's server accepts
WS_PROTOCOL = "foxglove.websocket.v1"  # the same protocol's older name
MAX_HEAD = 16384  # an HTTP upgrade request or answer longer than this is dropped


class FoxgloveError(ValueError):
    """The view cannot be served (foxglove-sdk missing, the port taken); says why."""


DRAIN_S = 0.5  # s: what the server gets to send its queued messages before it stops

def require_foxglove():
    try:
        import foxglove
    except ImportError:
        raise FoxgloveError("--foxglove needs foxglove-sdk: pip install 'msagv[foxglove]'") \
            from None
    return foxglove


class _Channels(R.RunChannels):
    def __init__(self, fg, ctx, vehicle, period: float, reference):
        super().__init__(vehicle, period, reference, plan_every=PLAN_EVERY)
        self.fg, self.ctx = fg, ctx
        self.channels: dict[str, Any] = {}
        for topic, typ in R.TYPES.items():
            self.channels[topic] = fg.Channel(
                "/" + topic, message_encoding="cdr", context=ctx,
                schema=fg.Schema(name=typ, encoding="ros2msg", data=R.msgdef(typ).encode()))
        self.sent = 0

    def write(self, topic: str, msg, ts: float) -> None:
        self.channels[topic].log(R.encode(msg, R.TYPES[topic]), log_time=int(ts * 1e9))
        self.sent += 1


class FoxgloveView:
    """The live view of one process (see the module docstring). ``header``: the run's
    header (``vehicle`` as a dict, ``period``, ``reference`` message); ``host``/``port``:
    where the WebSocket server listens (port 0: any free one)."""

    def __init__(self, header: Mapping, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                 name: str = "msagv", queue_items: int = 2000):
        fg = require_foxglove()
        from msagv.plant.vehicle import vehicle_from_dict

        self.ctx = fg.Context()
        self._ch = _Channels(fg, self.ctx, vehicle_from_dict(header["vehicle"]),
                             float(header.get("period") or CONTROL_PERIOD), header.get("reference"))
        self._subscribed = threading.Event()
        view = self

        class Listener(fg.websocket.ServerListener):  # every callback (a disconnect unsubscribes)
            def on_subscribe(self, client, channel):
                view._subscribed.set()

        # the public port first (its errors are the user's: the port taken, an address not
        # on this machine), then foxglove-sdk's server behind it on a free loopback port
        try:
            self._front = _Front(host, port)
        except OSError as e:
            raise FoxgloveError(f"--foxglove: cannot serve on {host}:{port} ({e})") from None
        try:
            self.server = fg.start_server(name=name, host="127.0.0.1", port=0, context=self.ctx,
                                          server_listener=Listener())
        except Exception as e:  # noqa: BLE001 - no loopback port left
            self._front.close(0.0)
            raise FoxgloveError(f"--foxglove: cannot start the server ({e})") from None
        self._front.start(self.server.port)
        self.host = host
        self.port = self._front.port
        self.dropped = 0
        self._closed = False
        self._q: queue.Queue = queue.Queue(maxsize=queue_items)
        self._t = threading.Thread(target=self._run, name="msagv-foxglove", daemon=True)
        self._t.start()

    @property
    def address(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def wait_for_client(self, timeout: float) -> bool:
        """Wait until a client subscribes to a channel (True), or ``timeout`` s."""
        return self._subscribed.wait(timeout)

    # ---- the recorder's interface ----------------------------------------------------------
    def message(self, direction: str, key: str, payload, ts: float | None = None,
                why: str | None = None) -> None:
        if why is not None or not key.endswith(("/state", "/cmd", "/reference")):
            return
        self._put(("msg", key, bytes(payload), time.time() if ts is None else ts))

    def predicted_path(self, t0: float, dt: float, poses) -> None:
        self._put(("pred", float(t0), float(dt), [list(map(float, p)) for p in poses],
                   time.time()))

    def event(self, name: str, /, **fields) -> None:
        pass

    def maybe_flush(self) -> None:
        pass

    def on_step(self, k: int, st: dict, cmd) -> None:
        """:func:`controller.loop.closed_loop`'s ``on_step``: state k and its command."""
        now = time.time()
        self.message("tx", "run/state", M.encode_state(k, st), now)
        self.message("rx", "run/cmd", M.encode_cmd(k, st["t"], k, cmd.omega_w, cmd.omega_s,
                                                   solve_ms=cmd.solve_ms), now)

    def _put(self, item) -> None:
        try:
            self._q.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            try:
                if item[0] == "msg":
                    self._ch.record(item[1], item[2], item[3])
                else:
                    self._ch.predicted(*item[1:])
            except Exception as e:  # noqa: BLE001 - the view never stops the run
                log.debug("foxglove view: %s", e)

    def close(self, summary: dict | None = None) -> dict:
        """Send what is queued, close every client's connection and the server (again: a
        no-op); the view's address and counts."""
        if not self._closed:
            self._closed = True
            try:
                self._q.put(None, timeout=2.0)
            except queue.Full:
                pass
            self._t.join(5.0)
            # the server sends from its own queues and has no flush: stopping it right after
            # the last record lost that record to a client now and then (seen in a clean
            # clone's make test: 249 of 250 states, the last one missing)
            if self._subscribed.is_set():  # (no client ever subscribed: nothing queued)
                time.sleep(DRAIN_S)
            self.server.stop()  # closes its connections: each relay ends when its backend does
            self._front.close()
        return {"address": self.address, "sent": self._ch.sent, "dropped": self.dropped}


def _protocols(head: bytes, name: bytes) -> tuple[list[bytes], list[str]]:
    """The lines of an HTTP head and the comma-separated values of its ``name`` headers."""
    lines = head.split(b"\r\n")
    values: list[str] = []
    for line in lines[1:]:
        key, sep, value = line.partition(b":")
        if sep and key.strip().lower() == name:
            values += [v.strip() for v in value.decode("latin-1").split(",") if v.strip()]
    return lines, values


def _replace_header(lines: list[bytes], name: bytes, value: str) -> bytes:
    """The head of ``lines`` with every ``name`` header replaced by one ``name: value``."""
    out, done = [lines[0]], False
    for line in lines[1:]:
        key, sep, _ = line.partition(b":")
        if sep and key.strip().lower() == name:
            if not done:
                out.append(key.strip() + b": " + value.encode("latin-1"))
                done = True
            continue
        out.append(line)
    return b"\r\n".join(out)


def offer_sdk_name(request: bytes) -> tuple[bytes, bool]:
    """An upgrade request as foxglove-sdk takes it: when the client offers the older name
    (``foxglove.websocket.v1``) and no name foxglove-sdk knows, the request offering
    ``foxglove.sdk.v1`` instead and True (the answer is to be renamed back); else the
    request unchanged and False."""
    lines, offered = _protocols(request, b"sec-websocket-protocol")
    if WS_PROTOCOL not in offered or any(p in SDK_PROTOCOLS for p in offered):
        return request, False
    return _replace_header(lines, b"sec-websocket-protocol", SDK_PROTOCOLS[0]), True


def answer_old_name(answer: bytes) -> bytes:
    """foxglove-sdk's answer to a renamed request, naming the protocol the client offered."""
    lines, chosen = _protocols(answer, b"sec-websocket-protocol")
    if chosen != [SDK_PROTOCOLS[0]]:
        return answer  # a refusal (no protocol chosen): passed on as it is
    return _replace_header(lines, b"sec-websocket-protocol", WS_PROTOCOL)


class _Front:
    """The view's public address: accepts both names of the protocol and relays each
    connection to foxglove-sdk's server (see the module docstring). The listening socket is
    bound at construction (an ``OSError`` when it cannot be); :meth:`start` serves it from a
    thread with its own event loop."""

    def __init__(self, host: str, port: int):
        family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                    flags=socket.AI_PASSIVE)[0][0]
        self.sock = socket.create_server((host, port), family=family)
        self.port = self.sock.getsockname()[1]
        self.loop = asyncio.new_event_loop()
        self._tasks: set[asyncio.Task] = set()
        self._t: threading.Thread | None = None

    def start(self, backend_port: int) -> None:
        self.backend = backend_port
        started = threading.Event()
        self._t = threading.Thread(target=self._serve, args=(started,), daemon=True,
                                   name="msagv-foxglove-front")
        self._t.start()
        started.wait(10.0)

    def _serve(self, started: threading.Event) -> None:
        asyncio.set_event_loop(self.loop)
        self.server = self.loop.run_until_complete(
            asyncio.start_server(self._connection, sock=self.sock, limit=MAX_HEAD))
        started.set()
        self.loop.run_forever()
        self.loop.close()

    async def _connection(self, cr: asyncio.StreamReader, cw: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        self._tasks.add(task)
        bw = None
        try:
            request = await asyncio.wait_for(cr.readuntil(b"\r\n\r\n"), 30.0)
            request, renamed = offer_sdk_name(request)
            br, bw = await asyncio.open_connection("127.0.0.1", self.backend, limit=MAX_HEAD)
            bw.write(request)
            answer = await asyncio.wait_for(br.readuntil(b"\r\n\r\n"), 30.0)
            cw.write(answer_old_name(answer) if renamed else answer)
            await cw.drain()
            relays = [asyncio.ensure_future(_relay(cr, bw)), asyncio.ensure_future(_relay(br, cw))]
            _, pending = await asyncio.wait(relays, return_when=asyncio.FIRST_COMPLETED)
            for p in pending:  # one side closed: the other is closed below
                p.cancel()
            await asyncio.gather(*pending, return_exceptions=True)
        except (OSError, EOFError, asyncio.LimitOverrunError, asyncio.TimeoutError,
                asyncio.CancelledError) as e:  # a client gone, a head too long or never sent
            log.debug("foxglove front: %s", e)
        finally:
            for w in (cw, bw):
                if w is not None:
                    w.close()
            self._tasks.discard(task)

    def close(self, grace: float = 2.0) -> None:
        """Stop listening; connections still open after ``grace`` s are cut (again: a no-op)."""
        if self._t is None or not self._t.is_alive():
            self.sock.close()
            return
        fut = asyncio.run_coroutine_threadsafe(self._shutdown(grace), self.loop)
        try:
            fut.result(grace + 5.0)
        except Exception as e:  # noqa: BLE001 - closing never fails the run
            log.debug("foxglove front: %s", e)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._t.join(5.0)

    async def _shutdown(self, grace: float) -> None:
        self.server.close()
        if self._tasks:
            await asyncio.wait(list(self._tasks), timeout=grace)
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.wait(list(self._tasks), timeout=1.0)


async def _relay(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
    """Bytes from ``r`` to ``w`` until ``r`` ends, waiting for ``w`` to take them (a reader
    that stalls stalls this relay, not the others)."""
    try:
        while True:
            data = await r.read(65536)
            if not data:
                return
            w.write(data)
            await w.drain()
    except OSError:  # a peer reset its connection: this relay ends, its connection closes
        return
