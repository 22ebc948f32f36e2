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
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any, Mapping

from msagv.bridge import messages as M
from msagv.bridge import ros_msgs as R

log = logging.getLogger("msagv.foxglove")

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765  # Foxglove's default
PLAN_EVERY = 200  # the plan again every this many states (2 s at 100 Hz)


class FoxgloveError(ValueError):
    """The view cannot be served (foxglove-sdk missing, the port taken); says why."""


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
                             float(header.get("period") or 0.01), header.get("reference"))
        self._subscribed = threading.Event()
        view = self

        class Listener:
            def on_subscribe(self, client, channel):
                view._subscribed.set()

        try:
            self.server = fg.start_server(name=name, host=host, port=port, context=self.ctx,
                                          server_listener=Listener())
        except Exception as e:  # the port taken, an address not on this machine
            raise FoxgloveError(f"--foxglove: cannot serve on {host}:{port} ({e})") from None
        self.host = host
        self.port = self.server.port
        self.dropped = 0
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

    def event(self, name: str, **fields) -> None:
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
        try:
            self._q.put(None, timeout=2.0)
        except queue.Full:
            pass
        self._t.join(5.0)
        self.server.stop()
        return {"address": self.address, "sent": self._ch.sent, "dropped": self.dropped}
