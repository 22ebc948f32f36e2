"""``msagv controller``: the MPC as a Zenoh process.

Gets the vehicle from the plant's ``msagv/{id}/params`` queryable (or ``--vehicle FILE``),
answers every ``state`` with a ``cmd`` naming the state it answers, takes new references on
``msagv/{id}/reference``, declares ``msagv/{id}/alive/controller`` once its MPC is warm, and
stops commanding while the plant's token ``msagv/{id}/alive/plant`` is gone (it never sends
a command for a state older than ``--max-age-ms``).

Determinism (lockstep): the MPC is warmed up (kernels compiled) and then reset, and it is
reset again at every state with ``seq = 0`` (a new plant run), exactly as
:func:`controller.loop.closed_loop` does, so a lockstep run over Zenoh gives the commands of
``msagv run`` in-process with the same options and seed.
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import threading
import time
from typing import Callable

import numpy as np

from . import messages as M
from .plant_node import percentiles_ms
from .presence import Presence
from .process import EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, freeze_heap
from .session import Keys, SessionError, SessionOptions, open_session

log = logging.getLogger("msagv.controller")

REALTIME_DEADLINE_MS = 7.0  # solve budget used against a realtime plant unless --deadline-ms


FALLBACK_LOSS_S = 2.0  # s without a state before a plant known only by its states is gone


class ControllerRunError(RuntimeError):
    """The controller cannot go on (no plant, the plant gone with --on-plant-loss exit)."""


@dataclasses.dataclass
class ControllerConfig:
    """How the controller process runs.

    max_age_ms : never send a command for a state received longer ago than this [ms]
        (None: no limit; the default against a realtime plant is its staleness bound).
    on_plant_loss : 'wait' for the plant to come back, or 'exit' (code 3).
    exit_at_end : exit (code 0) after a state with ``end = true``.
    """

    max_age_ms: float | None = None
    on_plant_loss: str = "wait"
    exit_at_end: bool = False


@dataclasses.dataclass
class ControllerStats:
    answered: int = 0
    skipped: int = 0  # states superseded by a newer one before they were solved
    duplicates: int = 0
    new_runs: int = 0
    dropped_stale: int = 0  # solved but too old to send
    ignored_no_plant: int = 0  # states while the plant's token was gone
    references: int = 0
    ends: int = 0
    solve_ms: list = dataclasses.field(default_factory=list)


class ControllerNode:
    """The controller process's logic. ``session`` None: a test feeds :meth:`handle_state`
    and reads :attr:`sent`."""

    def __init__(self, mpc, keys: Keys, cfg: ControllerConfig, session=None, recorder=None):
        self.mpc = mpc
        self.nw = mpc.vehicle.n_wheels
        self.keys = keys
        self.cfg = cfg
        self.session = session
        self.rec = recorder
        self.rej = M.Rejections(f"controller {keys.id}", log)
        self.stats = ControllerStats()
        self.stop = threading.Event()
        self._event = threading.Event()
        self._lock = threading.Lock()
        self._pending = None  # (state dict, rx_perf)
        self._held = None  # newest state received while the plant's token was not seen
        self._plant_presence = None  # the Presence of the plant's token (open())
        self._fallback = False  # present because its states arrive, its token never seen
        self._last_state_rx = 0.0  # time.monotonic() of the last valid state
        self._pending_ref = None  # decoded reference message
        self._last_seq: int | None = None
        self._cmd_seq = 0
        self.plant_present = session is None
        self.plant_seen = session is None
        self.sent: list[bytes] = []
        self.exit_reason: str | None = None
        self._pub = None
        self._decls: list = []
        self._token = None

    # ---- transport ---------------------------------------------------------------------
    def open(self) -> None:
        import zenoh

        s, k = self.session, self.keys
        self._plant_presence = Presence(s, k.alive_plant, self._on_plant_change)
        self._decls.append(self._plant_presence)
        self._pub = s.declare_publisher(k.cmd, express=True, priority=zenoh.Priority.REAL_TIME,
                                        congestion_control=zenoh.CongestionControl.BLOCK,
                                        encoding=zenoh.Encoding(M.CONTENT_TYPE))
        self._decls.append(s.declare_subscriber(
            k.state, lambda smp: self.handle_state(smp.payload.to_bytes(), time.perf_counter())))
        self._decls.append(s.declare_subscriber(
            k.reference, lambda smp: self.handle_reference(smp.payload.to_bytes())))
        # the token last: a plant that sees it finds our subscriber declared
        self._token = s.liveliness().declare_token(k.alive_controller)

    def close(self) -> None:
        for obj in [self._token] + self._decls + [self._pub]:
            if obj is not None:
                try:
                    obj.close() if isinstance(obj, Presence) else obj.undeclare()
                except Exception:
                    pass
        self._token, self._decls, self._pub = None, [], None

    def _on_plant_change(self, present: bool, via: str = "token") -> None:
        if via == "token":
            self._fallback = False
        self.plant_present = present
        if present:
            self.plant_seen = True
            log.info("plant %s present%s", self.keys.id,
                     "" if via == "token" else " (its states arrive; its liveliness token "
                                               "is not visible from here)")
            with self._lock:
                # a state that arrived just before the token was seen (the two travel on
                # different paths): answer it now; --max-age-ms still drops it if too old
                if self._held is not None and self._pending is None:
                    self._pending, self._held = self._held, None
        else:
            with self._lock:
                self._pending = None  # never answer a state of a plant that is gone
                self._held = None
            log.warning("plant %s gone (liveliness token lost): not commanding%s", self.keys.id,
                        "" if self.cfg.on_plant_loss == "exit" else "; waiting for it to return")
        if self.rec is not None:
            self.rec.event("plant_alive", present=present)
        self._event.set()

    def check_fallback_loss(self, now: float) -> None:
        """A plant known only by its states is gone after FALLBACK_LOSS_S without one."""
        if self._fallback and self.plant_present and now - self._last_state_rx > FALLBACK_LOSS_S:
            self._on_plant_change(False, via="states")

    # ---- incoming ----------------------------------------------------------------------
    def handle_state(self, payload: bytes, rx_perf: float) -> dict | None:
        """Validate a state; the newest valid one is solved next. Returns it, or None."""
        key = self.keys.state
        try:
            st = M.decode_state(payload, self.nw)
        except M.MessageError as e:
            self.rej.add(e, key)
            if self.rec is not None:
                self.rec.message("rx", key, payload, why=e.reason)
            return None
        if self.rec is not None:
            self.rec.message("rx", key, payload)
        self._last_state_rx = time.monotonic()
        pres = self._plant_presence
        if not self.plant_present and pres is not None and pres.generation == 0:
            # Zenoh did not deliver the plant's token to this session (seen in a mesh of
            # peers with gossip off: the token neither arrived nor answered a query),
            # but its states do: they are the evidence of presence, and their silence
            # (FALLBACK_LOSS_S) the evidence of loss, until the token shows up
            self._fallback = True
            self._on_plant_change(True, via="states")
        if not self.plant_present:
            self.stats.ignored_no_plant += 1
            with self._lock:
                self._held = (st, rx_perf)
            return None
        with self._lock:
            if self._pending is not None:
                self.stats.skipped += 1
            self._pending = (st, rx_perf)
        self._event.set()
        return st

    def handle_reference(self, payload: bytes) -> dict | None:
        key = self.keys.reference
        try:
            m = M.decode_reference(payload)
            from controller.reference import ReferenceError, from_samples

            try:  # checked here, so a bad one is rejected on arrival
                from_samples(m["t"], m["x"], m["y"], m["phi"])
            except ReferenceError as e:
                raise M.MessageError(M.BAD_VALUE, str(e)) from None
        except M.MessageError as e:
            self.rej.add(e, key)
            if self.rec is not None:
                self.rec.message("rx", key, payload, why=e.reason)
            return None
        if self.rec is not None:
            self.rec.message("rx", key, payload)
        with self._lock:
            self._pending_ref = m
        self._event.set()
        return m

    # ---- the loop ----------------------------------------------------------------------
    def run(self) -> dict:
        """Answer states until stopped (or the end, or the plant's loss, as configured)."""
        while not self.stop.is_set():
            self.check_fallback_loss(time.monotonic())
            if self.cfg.on_plant_loss == "exit" and self.plant_seen and not self.plant_present:
                self.exit_reason = "plant gone"
                raise ControllerRunError(
                    f"plant '{self.keys.id}' gone (its liveliness token {self.keys.alive_plant} "
                    f"disappeared); exiting (--on-plant-loss exit)")
            self._event.wait(0.05)
            self._event.clear()
            with self._lock:
                item, self._pending = self._pending, None
            if item is None:
                if self.rec is not None:
                    self.rec.maybe_flush()
                continue
            if self.step(*item) == "end" and self.cfg.exit_at_end:
                self.exit_reason = "end of run"
                break
            if self.rec is not None:
                self.rec.maybe_flush()
        if self.exit_reason is None:
            self.exit_reason = "stopped"
        return self.summary()

    def step(self, st: dict, rx_perf: float) -> str:
        """Solve for one state and send the command. Returns 'sent', 'end', 'duplicate',
        'stale' or 'no plant'."""
        seq = st["seq"]
        last = self._last_seq
        if last is not None and seq == last:
            self.stats.duplicates += 1
            return "duplicate"
        if last is None or seq == 0 or seq < last:
            # a new plant run (or the first state seen): forget the warm start and reseed,
            # as closed_loop does after its warm-up
            self.mpc.reset()
            self.stats.new_runs += 1
            if last is not None:
                log.info("new plant run (state seq %d after %d): MPC reset", seq, last)
            if self.rec is not None:
                self.rec.event("new_run", seq=seq)
        self._last_seq = seq
        if st.get("end"):
            self.stats.ends += 1
            log.info("end of the run at t = %.2f s (state %d)", st["t"], seq)
            return "end"
        with self._lock:
            ref_msg, self._pending_ref = self._pending_ref, None
        if ref_msg is not None:
            self._set_reference(ref_msg, st["t"])
        cmd = self.mpc.step(st)
        self.stats.solve_ms.append(cmd.solve_ms)
        if self.cfg.max_age_ms is not None and \
                (time.perf_counter() - rx_perf) * 1000.0 > self.cfg.max_age_ms:
            self.stats.dropped_stale += 1
            return "stale"
        if not self.plant_present:
            self.stats.ignored_no_plant += 1
            return "no plant"
        payload = M.encode_cmd(self._cmd_seq, st["t"], seq, cmd.omega_w, cmd.omega_s,
                               solve_ms=cmd.solve_ms, cost=cmd.cost)
        self._cmd_seq += 1
        if self._pub is not None:
            self._pub.put(payload)
        else:
            self.sent.append(payload)
        if self.rec is not None:
            self.rec.message("tx", self.keys.cmd, payload)
        self.stats.answered += 1
        return "sent"

    def _set_reference(self, m: dict, t_now: float) -> None:
        from controller.reference import from_samples

        t = np.asarray(m["t"], dtype=float)
        if m.get("relative"):
            t = t + t_now
        ref = from_samples(t, m["x"], m["y"], m["phi"], name=m.get("name", "bus-reference"))
        self.mpc.set_reference(ref)
        self.stats.references += 1
        log.info("new reference '%s' (%d samples, t %.2f..%.2f s) from t = %.2f s", ref.name,
                 len(t), t[0], t[-1], t_now)
        if self.rec is not None:
            self.rec.event("reference", t=t_now, name=ref.name)

    def summary(self) -> dict:
        s = self.stats
        return {"role": "controller", "id": self.keys.id, "answered": s.answered,
                "solve_ms": percentiles_ms(np.asarray(s.solve_ms) / 1000.0),
                "skipped": s.skipped, "duplicates": s.duplicates, "new_runs": s.new_runs,
                "dropped_stale": s.dropped_stale, "ignored_no_plant": s.ignored_no_plant,
                "references": s.references, "ends": s.ends, "rejected": self.rej.summary(),
                "exit_reason": self.exit_reason,
                "solver": getattr(self.mpc, "solver_name", "sa"),
                "settings": dataclasses.asdict(self.mpc.settings)}


# ---- the process ------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class PlantParams:
    """What a plant's ``params`` reply tells a controller (docs/PROTOCOL.md)."""

    vehicle: object  # plant.vehicle.Vehicle
    period: float
    run_mode: str


def realtime_defaults(run_mode: str | None, deadline_ms: float | None,
                      max_age_ms: float | None) -> tuple[float | None, float | None]:
    """The solve budget and the command age bound against a plant of ``run_mode``: against
    a realtime plant ``REALTIME_DEADLINE_MS`` and the plant's default staleness bound (50 ms)
    unless given; in lockstep only what is given."""
    if run_mode == "realtime":
        return (REALTIME_DEADLINE_MS if deadline_ms is None else deadline_ms,
                50.0 if max_age_ms is None else max_age_ms)
    return deadline_ms, max_age_ms


def fetch_params(session, keys: Keys, wait_s: float, stop: threading.Event) -> dict:
    """The plant's params (validated), retrying until ``wait_s`` (0: forever)."""
    t0 = time.monotonic()
    told = False
    last_err = None
    while not stop.is_set():
        try:
            # ?wheel_wear=1: this controller understands the per-wheel wear state fields
            for reply in session.get(f"{keys.params}?wheel_wear=1", timeout=1.0):
                if reply.ok is None:
                    last_err = f"error reply: {reply.err.payload.to_bytes()[:200]!r}"
                    continue
                try:
                    return M.decode_params(reply.ok.payload.to_bytes())
                except M.MessageError as e:
                    last_err = f"bad params reply: {e}"
                    log.warning("%s", last_err)
        except Exception as e:
            last_err = str(e)
        if wait_s and time.monotonic() - t0 > wait_s:
            raise ControllerRunError(
                f"no plant answered on {keys.params} within {wait_s:g} s"
                f"{' (' + last_err + ')' if last_err else ''}; start msagv plant --id {keys.id} "
                f"with matching --connect/--listen, or give --vehicle FILE")
        if not told:
            log.info("waiting for the plant's params on %s", keys.params)
            told = True
        stop.wait(0.1)
    raise ControllerRunError("stopped while waiting for the plant's params")


class SetupError(ValueError):
    """The controller cannot be built for this plant (e.g. its params name a vehicle the
    scenario cannot use); nothing ran (exit 2)."""


def serve(opts: SessionOptions, make_mpc: Callable[[PlantParams | None], object],
          cfg: ControllerConfig, *, fetch: bool = True, wait_s: float = 60.0,
          open_recorder: Callable[[object, PlantParams | None], object] | None = None,
          stop: threading.Event | None = None, on_signal_install: Callable[[], None] | None = None
          ) -> tuple[dict, int]:
    """Run the controller process: open the Zenoh session, fetch the plant's params (unless
    ``fetch`` is False: the caller's vehicle is used), build the MPC with
    ``make_mpc(params)``, warm it up, answer states until stopped, close everything.

    ``make_mpc`` raises :class:`SetupError` (or ValueError) for a scenario that cannot be
    built: exit 2. ``open_recorder(mpc, params)`` returns a Recorder or None (closed here,
    with the summary). ``cfg.max_age_ms`` None takes :func:`realtime_defaults`' bound for
    the plant's run mode. ``on_signal_install`` installs the caller's signal handlers once
    the session is open, and again after the warm-up (compiling cannot be interrupted from
    Python, so SIGTERM acts at once meanwhile). Returns ``(summary, exit code)``.
    """
    keys = Keys(opts.id)
    stop = stop or threading.Event()
    rec = None
    node = None
    rc = EXIT_OK
    summary: dict = {"role": "controller", "id": keys.id}
    try:
        with open_session(opts, "controller") as session:
            if on_signal_install is not None:
                on_signal_install()
            params = None
            if fetch:
                p = fetch_params(session, keys, wait_s, stop)
                from plant.vehicle import VehicleError, vehicle_from_dict

                try:
                    vehicle = vehicle_from_dict(p["vehicle"])
                except VehicleError as e:
                    raise ControllerRunError(f"the plant's params: vehicle: {e}") from None
                params = PlantParams(vehicle, p["period"], p["run_mode"])
                log.info("plant params: %s, %d wheels, T = %g s, %s", vehicle.name,
                         vehicle.n_wheels, params.period, params.run_mode)
            try:
                mpc = make_mpc(params)
            except ValueError as e:
                log.error("%s", e)
                return dict(summary, error=str(e)), EXIT_USAGE
            if cfg.max_age_ms is None:
                cfg = dataclasses.replace(cfg, max_age_ms=realtime_defaults(
                    params.run_mode if params else None, None, None)[1])
            t0 = time.perf_counter()
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            mpc.warmup()  # compiles, then resets the warm start and the RNG
            if on_signal_install is not None:
                on_signal_install()
            if stop.is_set():
                return summary, EXIT_OK
            s = mpc.settings
            log.info("MPC warm (%.2f s): %s %s, %s, seed %d", time.perf_counter() - t0,
                     s.method, s.model, getattr(mpc, "solver_name", "sa"), s.seed)
            if open_recorder is not None:
                rec = open_recorder(mpc, params)
            node = ControllerNode(mpc, keys, cfg, session=session, recorder=rec)
            node.stop = stop
            freeze_heap()
            node.open()
            log.info("controller ready on %s", keys.state)
            try:
                node.run()
            finally:
                node.close()
    except ControllerRunError as e:
        if not stop.is_set():
            log.error("%s", e)
            rc = EXIT_RUNTIME
    except SessionError as e:
        log.error("%s", e)
        rc = EXIT_USAGE
    except KeyboardInterrupt:
        pass
    finally:
        if node is not None:
            summary = node.summary()
        if rec is not None:  # the recorder's counters (errors, drops) in the summary too
            summary["recording"] = rec.close(summary)
    return summary, rc
