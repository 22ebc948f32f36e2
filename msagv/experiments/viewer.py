"""A live and replayable 3D view of a run with Rerun (the optional extra ``viewer``:
``pip install 'msagv[viewer]'``; its web viewer ships in the wheel and needs no internet).

What is logged (timeline ``sim_time``, the vehicle time of each state):

==========================  =========================================================
``world/reference``         the reference path (static line strip)
``world/path``              the driven path so far (line strip)
``vehicle/body``            the body: a box at the pose (x, y, phi), in :data:`BODY_COLOR`
``vehicle/wheel/ij``        each wheel at its position and steering angle ``phi + delta_ij``,
                            coloured by its wear power (green 0 -> red at the run's peak)
``errors/e_x_cm``, ``e_y_cm``, ``e_lat_cm``, ``e_phi_deg``   tracking errors (scalars)
``wear/power/ij``           each wheel's wear power [kW] (mean over the period:
                            the change of ``W_s_ij + W_alpha_ij + W_t_ij`` over T)
``wear/axle/i``             each axle's (its two wheels'), shown with the total
``wear/power/total``        the vehicle's [kW] (from ``W_s + W_alpha + W_t``)
==========================  =========================================================

Sources: :class:`RunView` takes states (the ``state`` message fields) from an in-process
loop (:meth:`RunView.on_step` for :func:`controller.loop.closed_loop`), from a running
plant process (:class:`ViewSink`, handed to :func:`bridge.plant_node.serve` in place of or
beside the recorder: it only queues, a thread logs) or from a recording
(:func:`view_recording`). Sinks: a web viewer served on loopback (``serve``) and/or an
``.rrd`` file (``save``), or a caller's :class:`rerun.RecordingStream` (tests use a memory
recording).
"""

from __future__ import annotations

import atexit
import logging
import math
import queue
import socket
import threading
import time
import urllib.parse
from pathlib import Path
from typing import Any

import numpy as np

from msagv.plant.signals import WEAR_FIELDS, WHEEL_WEAR_FIELDS

log = logging.getLogger("msagv.viewer")

BODY_COLOR = (125, 45, 200)  # the vehicle's body: purple, unlike the viewer's own UI
# colours (a test looks for it in a screenshot)
REFERENCE_COLOR = (90, 90, 90)
PATH_COLOR = (255, 150, 0)
COOL, HOT = np.array([60, 180, 75]), np.array([220, 30, 40])  # wheel colours: no wear -> peak
WEB_PORT, GRPC_PORT = 9090, 9876
PATH_EVERY = 10  # log the driven path every this many states (and at the end)


class ViewerError(ValueError):
    """The view cannot be made (rerun-sdk missing, a bad option); the message says why."""


def require_rerun():
    """The ``rerun`` module, or :class:`ViewerError` naming the extra to install."""
    try:
        import rerun
    except ImportError:
        raise ViewerError("the viewer needs rerun-sdk: pip install 'msagv[viewer]'") from None
    return rerun


LOOPBACK = "127.0.0.1"  # where a served view listens unless told otherwise


def shown_host(host: str) -> str:
    """The host to put in an address: ``host``, or this machine's name when ``host`` is
    every interface (0.0.0.0, ::)."""
    return socket.gethostname() if host in ("0.0.0.0", "::", "") else host


def web_url(web_port: int, grpc_uri: str, host: str = LOOPBACK) -> str:
    """The address of the served web viewer showing the recording at ``grpc_uri``."""
    h = shown_host(host)
    h = f"[{h}]" if ":" in h else h
    return f"http://{h}:{web_port}/?url={urllib.parse.quote(grpc_uri, safe='')}"


def _rerun_binary() -> Path:
    """The rerun command-line program the rerun-sdk wheel ships (package ``rerun_cli``)."""
    try:
        import rerun_cli
    except ImportError:
        raise ViewerError("the web viewer needs rerun-sdk's command-line program "
                          "(package rerun_cli): pip install 'msagv[viewer]'") from None
    base = Path(rerun_cli.__file__).parent
    for p in (base / "Rerun.app" / "Contents" / "MacOS" / "Rerun", base / "rerun",
              base / "rerun.exe"):
        if p.is_file():
            return p
    raise ViewerError(f"rerun-sdk's command-line program is missing from {base}")


def check_port_free(host: str, port: int, what: str) -> None:
    """:class:`ViewerError` when ``port`` on ``host`` is taken (another view, another
    program): said at once, not as a server thread's error after the work."""
    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(fam, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, int(port)))
        except OSError as e:
            raise ViewerError(f"port {port} on {host} ({what}) is in use ({e.strerror}): "
                              f"another view? choose another --view-port") from None


class WebViewer:
    """Rerun's web viewer (HTML and wasm) served over HTTP on ``host:port`` by the rerun
    program of the rerun-sdk wheel, opening the recording at ``grpc_uri``; stopped by
    :meth:`close` (by its process id).

    Why a process of its own: rerun-sdk's ``serve_web_viewer`` listens on every interface
    (0.0.0.0) with no way to choose; ``rerun --serve-web --bind HOST`` listens where it is
    told. Its output (a first-run notice about Rerun's usage statistics, its log) goes to
    a file, read when it fails to start."""

    def __init__(self, host: str, port: int, grpc_uri: str, timeout: float = 30.0):
        import subprocess
        import tempfile

        self.host, self.port = host, int(port)
        self._out = tempfile.TemporaryFile(mode="w+")
        args = [str(_rerun_binary()), "--serve-web", "--bind", host,
                "--web-viewer-port", str(self.port), grpc_uri]
        try:
            self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=self._out,
                                         stderr=subprocess.STDOUT)
        except OSError as e:
            raise ViewerError(f"the web viewer could not start: {e}") from None
        atexit.register(self.close)
        probe = "127.0.0.1" if host in ("0.0.0.0", "") else ("::1" if host == "::" else host)
        t_end = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                self._out.seek(0)
                lines = [ln.strip() for ln in self._out.read().splitlines() if ln.strip()]
                why = lines[-1] if lines else f"exit code {self.proc.returncode}"
                self.close()
                raise ViewerError(f"the web viewer could not listen on {host}:{port}: {why}")
            try:
                with socket.create_connection((probe, self.port), timeout=0.5):
                    break
            except OSError:
                pass
            if time.monotonic() > t_end:
                self.close()
                raise ViewerError(f"the web viewer did not listen on {host}:{port} within "
                                  f"{timeout:g} s")
            time.sleep(0.1)

    def close(self) -> None:
        p = getattr(self, "proc", None)
        if p is not None and p.poll() is None:
            p.terminate()
            try:
                p.wait(5)
            except Exception:  # noqa: BLE001 - still there: kill it
                p.kill()
                p.wait(5)
        atexit.unregister(self.close)
        self._out.close()


def wheel_colour(p_kw: float, scale_kw: float) -> list[int]:
    """Green at no wear power, red at ``scale_kw`` and above (linear in between)."""
    a = 0.0 if not scale_kw > 0 else min(max(p_kw / scale_kw, 0.0), 1.0)
    return [int(round(v)) for v in (1 - a) * COOL + a * HOT]


class RunView:
    """One Rerun recording of a run (see the module docstring).

    ``vehicle``: a :class:`plant.vehicle.Vehicle`; ``reference``: a
    :class:`controller.reference.Reference` (None: no reference path or errors).
    ``save``: an ``.rrd`` file to write; ``serve``: serve the web viewer (``web_port``) and
    the data (``grpc_port``), both on ``host`` (default loopback: this machine only;
    :class:`WebViewer`); ``stream``: log into this
    :class:`rerun.RecordingStream` instead (no sinks are set). ``power_scale_kw``: the wear
    power shown as the hottest wheel colour (None: the running peak, at least 0.05 kW).
    """

    def __init__(self, vehicle, reference=None, *, save: str | Path | None = None,
                 serve: bool = False, web_port: int = WEB_PORT, grpc_port: int = GRPC_PORT,
                 host: str = LOOPBACK, stream=None, name: str = "msagv",
                 power_scale_kw: float | None = None):
        rr = require_rerun()
        self.rr = rr
        if stream is None and not save and not serve:
            raise ViewerError("a view needs somewhere to go: serve it, save it, or both")
        if save is not None and Path(save).suffix != ".rrd":
            raise ViewerError(f"{save}: a saved view is an .rrd file")
        self.vehicle = vehicle
        self.reference = reference
        self.url: str | None = None
        self.host = host
        self.listening: list[str] = []  # host:port of each socket the view serves
        self.web: WebViewer | None = None
        if stream is None:
            stream = rr.RecordingStream("msagv", recording_id=None)
            sinks = []
            if save is not None:
                sinks.append(rr.FileSink(str(save)))
            if serve:
                check_port_free(host, web_port, "the viewer")
                check_port_free(host, grpc_port, "the data")
                server = rr.GrpcServerSink(bind_ip=host, port=int(grpc_port))
                sinks.append(server)
                h = shown_host(host)
                uri = f"rerun+http://{f'[{h}]' if ':' in h else h}:{int(grpc_port)}/proxy"
                self.web = WebViewer(host, int(web_port), uri)
                self.url = web_url(int(web_port), uri, host)
                self.listening = [f"{host}:{int(web_port)} (viewer)",
                                  f"{host}:{int(grpc_port)} (data)"]
            stream.set_sinks(*sinks, default_blueprint=self._blueprint())
            stream.send_recording_name(name)
        else:
            stream.send_blueprint(self._blueprint())
        self.rec = stream
        self._prev: dict | None = None
        self._path: list = []
        self._n = 0
        self._scale_fixed = power_scale_kw
        self._peak = 0.05
        nw = vehicle.n_wheels
        self._wheels = list(vehicle.wheel_names)
        self._wx, self._wy = np.asarray(vehicle.wheel_x, float), np.asarray(vehicle.wheel_y, float)
        r_w = vehicle.wheel_radius
        self._wheel_half = [r_w, 0.18, r_w]
        span = float(self._wx.max() - self._wx.min()) if nw else 0.0
        self._body_half = [0.5 * span + r_w + 0.4, max(float(np.abs(self._wy).max()) - 0.35, 0.3),
                           0.25]
        self._body_z = 2 * r_w + 0.3
        self._log_static()

    # ---- layout --------------------------------------------------------------------------
    def _blueprint(self, at: tuple[float, float] | None = None):
        """The layout: the 3D scene (its camera behind and above the vehicle's start
        ``at``, following the body), the errors and the wear powers over time."""
        rrb = self.rr.blueprint
        # the curves start near 0 at the left (a run starts on its reference, wear power from
        # 0): the top left corner is where a legend covers least
        legend = rrb.PlotLegend(corner=rrb.Corner2D.LeftTop, visible=True)
        eye = None
        if at is not None:
            x0, y0 = at
            eye = rrb.EyeControls3D(position=[x0 - 16.0, y0 - 16.0, 18.0],
                                    look_target=[x0, y0, 0.0], eye_up=[0.0, 0.0, 1.0],
                                    tracking_entity="/vehicle/body")
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="/", name="vehicle", contents=["/world/**", "/vehicle/**"],
                                  eye_controls=eye),
                rrb.Vertical(
                    rrb.TimeSeriesView(origin="/errors", name="tracking errors",
                                       plot_legend=legend),
                    # per axle and the total: readable at 8 axles (16 wheels' lines are
                    # not); each wheel's series stays logged under /wear/power/ij
                    rrb.TimeSeriesView(origin="/wear", name="wear power [kW]",
                                       contents=["/wear/axle/**", "/wear/power/total"],
                                       plot_legend=legend)),
                column_shares=[3, 2]),
            collapse_panels=True)

    def _log_static(self) -> None:
        rr = self.rr
        if self.reference is not None:
            ref = self.reference
            t = np.linspace(ref.t[0], ref.t[-1], min(4000, max(10, len(ref.t) * 4)))
            s = ref.sample(t)
            pts = np.column_stack([s[:, 0], s[:, 1], np.zeros(len(t))])
            self.rec.log("world/reference", rr.LineStrips3D([pts], colors=[REFERENCE_COLOR],
                                                            radii=0.04), static=True)

    # ---- states --------------------------------------------------------------------------
    def log_state(self, st: dict) -> None:
        """Log one state (the ``state`` message's fields: t, x, y, phi, delta, and the
        optional wear work)."""
        rr, rec = self.rr, self.rec
        t = float(st["t"])
        x, y, phi = float(st["x"]), float(st["y"]), float(st["phi"])
        if self._n == 0:  # the camera starts at the vehicle and follows it
            rec.send_blueprint(self._blueprint((x, y)))
        rec.set_time("sim_time", duration=t)
        c, s = math.cos(phi), math.sin(phi)
        rec.log("vehicle/body", rr.Boxes3D(
            centers=[[x, y, self._body_z]], half_sizes=[self._body_half],
            rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=phi)],
            colors=[BODY_COLOR], fill_mode="solid"))
        p_wheel = self._wheel_power(st)
        scale = self._scale_fixed if self._scale_fixed else self._peak
        delta = st.get("delta") or [0.0] * len(self._wheels)
        for k, name in enumerate(self._wheels):
            cx = x + c * self._wx[k] - s * self._wy[k]
            cy = y + s * self._wx[k] + c * self._wy[k]
            colour = [150, 150, 150] if p_wheel is None else wheel_colour(p_wheel[k], scale)
            rec.log(f"vehicle/wheel/{name}", rr.Boxes3D(
                centers=[[cx, cy, self._wheel_half[2]]], half_sizes=[self._wheel_half],
                rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1],
                                                           radians=phi + float(delta[k]))],
                colors=[colour], fill_mode="solid"))
            if p_wheel is not None:
                rec.log(f"wear/power/{name}", rr.Scalars(p_wheel[k]))
        if p_wheel is not None:
            for i in range(len(self._wheels) // 2):
                rec.log(f"wear/axle/{i + 1}", rr.Scalars(p_wheel[2 * i] + p_wheel[2 * i + 1]))
        p_total = self._total_power(st)
        if p_total is not None:
            rec.log("wear/power/total", rr.Scalars(p_total))
        if self.reference is not None:
            from msagv.controller.metrics import wrap_angle

            r = self.reference.sample(t)
            ex, ey = x - r[0], y - r[1]
            rc, rs = math.cos(r[2]), math.sin(r[2])
            rec.log("errors/e_x_cm", rr.Scalars(100.0 * ex))
            rec.log("errors/e_y_cm", rr.Scalars(100.0 * ey))
            rec.log("errors/e_lat_cm", rr.Scalars(100.0 * (-ex * rs + ey * rc)))
            rec.log("errors/e_phi_deg", rr.Scalars(math.degrees(float(wrap_angle(phi - r[2])))))
        self._path.append([x, y, 0.02])
        self._n += 1
        if self._n % PATH_EVERY == 1 or PATH_EVERY == 1:
            self._log_path()
        self._prev = st

    def _log_path(self) -> None:
        if len(self._path) >= 2:
            self.rec.log("world/path", self.rr.LineStrips3D([self._path], colors=[PATH_COLOR],
                                                            radii=0.06))

    def _wheel_power(self, st: dict) -> list[float] | None:
        prev = self._prev
        if prev is None or not all(k in st and k in prev for k in WHEEL_WEAR_FIELDS):
            return None
        dt = float(st["t"]) - float(prev["t"])
        if not dt > 0:
            return None
        now = np.sum([st[k] for k in WHEEL_WEAR_FIELDS], axis=0)
        before = np.sum([prev[k] for k in WHEEL_WEAR_FIELDS], axis=0)
        p = ((now - before) / dt / 1000.0).tolist()
        self._peak = max(self._peak, max(p))
        return p

    def _total_power(self, st: dict) -> float | None:
        prev = self._prev
        keys = WEAR_FIELDS
        if prev is None or not all(k in st and k in prev for k in keys):
            return None
        dt = float(st["t"]) - float(prev["t"])
        if not dt > 0:
            return None
        return sum(float(st[k]) - float(prev[k]) for k in keys) / dt / 1000.0

    def on_step(self, k: int, st: dict, cmd) -> None:
        """:func:`controller.loop.closed_loop`'s ``on_step`` hook."""
        self.log_state(st)

    def finish(self, final_state: dict | None = None) -> None:
        """Log the final state (if given) and the whole driven path; flush the sinks."""
        if final_state is not None and (self._prev is None or final_state["t"] > self._prev["t"]):
            self.log_state(final_state)
        self._log_path()
        try:
            self.rec.flush()
        except TypeError:  # older signature
            self.rec.flush(blocking=True)

    def close(self) -> None:
        """Finish and end the recording's sinks (a served viewer stops)."""
        self.finish()
        try:
            self.rec.disconnect()
        except Exception:  # already gone
            pass
        if self.web is not None:
            self.web.close()


# ---- a running plant: a sink beside the recorder ------------------------------------------
class ViewSink:
    """A plant process's live view, with the recorder's interface (``message``, ``event``,
    ``maybe_flush``, ``close``): :func:`bridge.plant_node.serve` hands it every state it
    publishes. It only queues (bounded; drops are counted): a thread decodes and logs, so
    the real-time loop never waits for the viewer. ``plant``: the plant itself, whose
    per-wheel wear work is read when the published state leaves it out."""

    def __init__(self, view: RunView, plant=None, queue_items: int = 2000):
        self.view = view
        self.plant = plant
        self.dropped = 0
        self._q: queue.Queue = queue.Queue(maxsize=queue_items)
        self._t = threading.Thread(target=self._run, name="msagv-viewer", daemon=True)
        self._t.start()

    def message(self, direction: str, key: str, payload, ts=None, why=None) -> None:
        if why is not None or direction != "tx" or not key.endswith("/state"):
            return
        extra = None
        if self.plant is not None:
            try:
                st = self.plant.state_message()
                extra = {k: st[k] for k in WHEEL_WEAR_FIELDS if k in st}
            except Exception:
                extra = None
        try:
            self._q.put_nowait((bytes(payload), extra))
        except queue.Full:
            self.dropped += 1

    def event(self, name: str, /, **fields) -> None:
        pass

    def maybe_flush(self) -> None:
        pass

    def _run(self) -> None:
        from msagv.bridge import messages as M

        nw = self.view.vehicle.n_wheels
        while True:
            item = self._q.get()
            if item is None:
                return
            payload, extra = item
            try:
                st = M.decode_state(payload, nw)
            except M.MessageError:
                continue
            if st["seq"] == 0 and self.view._prev is not None:  # a new run
                self.view._prev = None
            if extra:
                for k, v in extra.items():
                    st.setdefault(k, v)
            try:
                self.view.log_state(st)
            except Exception as e:  # never the plant's problem
                log.warning("viewer: %s", e)

    def close(self, summary: dict | None = None) -> dict:
        self._q.put(None)
        self._t.join(10.0)
        self.view.close()  # the .rrd gets its footer; a served view ends with the plant
        return {"dropped": self.dropped}


class Tee:
    """The recorder and the view as one recorder for :func:`bridge.plant_node.serve`;
    ``close`` returns the recorder's counters."""

    def __init__(self, recorder, view_sink):
        self.parts = [p for p in (recorder, view_sink) if p is not None]
        self.recorder = recorder

    def message(self, *a, **kw) -> None:
        for p in self.parts:
            p.message(*a, **kw)

    def event(self, *a, **kw) -> None:
        for p in self.parts:
            p.event(*a, **kw)

    def maybe_flush(self) -> None:
        for p in self.parts:
            p.maybe_flush()

    def close(self, summary: dict | None = None) -> Any:
        out = None
        for p in self.parts:
            r = p.close(summary)
            if p is self.recorder:
                out = r
        return out


# ---- a recording ---------------------------------------------------------------------------
def view_recording(path: str | Path, view_kwargs: dict, run_index: int = -1) -> tuple[RunView, int]:
    """Log one run of a recording (:mod:`bridge.recording`, MCAP or the first format) into a
    new :class:`RunView` (``view_kwargs``: its keyword arguments: save, serve, ports,
    stream). Returns the view and the number of states logged. The wheel colours use the
    run's peak wear power."""
    from msagv.plant.vehicle import vehicle_from_dict

    from .recorded import load_run, reference_from_message

    header, _, _, _, run = load_run(path, run_index)
    vehicle = vehicle_from_dict(header["vehicle"])
    reference = reference_from_message(header["reference"])
    seqs = sorted(run.states)
    states = [run.states[k] for k in seqs]
    scale = _peak_power(states)
    kw = dict(view_kwargs)
    kw.setdefault("name", Path(path).name)
    view = RunView(vehicle, reference, power_scale_kw=scale, **kw)
    try:
        for st in states:
            view.log_state(st)
        view.finish()
    except RuntimeError as e:  # rerun's sinks (a server that could not start, a full disk)
        view.close()
        raise ViewerError(f"the view failed: {e}") from None
    return view, len(states)


def _peak_power(states: list[dict]) -> float | None:
    """The hottest wheel colour's wear power [kW] for a run: the 95th percentile of the
    per-wheel powers over its periods (a start-up spike does not wash the colours out);
    None without per-wheel wear work."""
    powers = []
    for a, b in zip(states, states[1:]):
        if not all(k in a and k in b for k in WHEEL_WEAR_FIELDS):
            return None
        dt = b["t"] - a["t"]
        if dt > 0:
            powers.extend((np.sum([b[k] for k in WHEEL_WEAR_FIELDS], axis=0)
                           - np.sum([a[k] for k in WHEEL_WEAR_FIELDS], axis=0)) / dt / 1000.0)
    return max(float(np.percentile(powers, 95)), 0.05) if powers else None
