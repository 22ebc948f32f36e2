"""``msagv plant``: the stepping plant (or a hosted FMU) as a Zenoh process.

:class:`PlantNode` is the process's logic; it talks to the bus only through a
:class:`bridge.transport.Transport` (Zenoh in the process, :mod:`bridge.loopback` in the
tests); :func:`serve` opens the Zenoh one unless given another.

Publishes ``msagv/{id}/state`` every control period, applies commands from
``msagv/{id}/cmd``, serves the vehicle description on the queryable ``msagv/{id}/params``
(read-only), grants the vehicle on ``msagv/{id}/claim``, takes an operator's re-arm on
``msagv/{id}/arm`` and declares the liveliness token ``msagv/{id}/alive/plant/{identity}``
(the transport adds every sender's identity to the keys: docs/PROTOCOL.md, "Keys"). Two
stepping modes (docs/PROTOCOL.md, "Modes"):

* ``--run-mode lockstep`` (default): publish state k, step when the command answering
  ``state_seq = k`` arrives. Deterministic and as fast as the controller answers; a run
  matches ``msagv run`` in-process. State k is published again every ``RESEND_S`` while
  unanswered (a state or command lost with a closed link would otherwise stall the run);
  no command within ``--timeout`` ends the run with an error (exit 3).
* ``--run-mode realtime``: step on the wall clock at 1/T with the newest valid command.
  :class:`bridge.loss.CommandWatch` decides every period: more than ``--stale-ms / T``
  consecutive periods without an answer (default 5), or the owner's liveliness token gone,
  put the plant in its safe behaviour (steering held, wheels ramped down at
  ``--safe-decel``) until the owner keeps up again for ``--resume-periods``. Missed
  periods (overruns) and late commands are counted.

One controller owns the vehicle (:class:`bridge.ownership.Ownership`): it claims it on
``msagv/{id}/claim``; commands from any other identity are rejected (``not_owner``, before
they are decoded, so a flood costs little) and only the owner's token
``alive/controller/{identity}`` counts as the controller's presence. Once the run has
started, losing the owner latches the vehicle until an operator re-arms it
(``msagv arm``) or the ``--rearm`` policy lets the same identity back.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from msagv.controller.metrics import percentiles
from msagv.plant.signals import BODY_FIELDS, WEAR_FIELDS, WHEEL_WEAR_FIELDS

from msagv.plant.signals import CONTROL_PERIOD
from . import messages as M
from .loss import SAFE, STALE_MS, CommandWatch
from .ownership import (BAD_ARM, BAD_CLAIM, CLAIM, LATCHED, Ownership, RearmPolicy,
                        decode_arm, decode_claim, encode_armed, encode_grant)
from .presence import TokenSet
from .process import EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, StopOnSignal, freeze_heap
from .recording import NullRecorder
from .session import Keys, SessionError, SessionOptions
from .transport import Query, Sample, Transport
from .zenoh_transport import ZenohTransport

log = logging.getLogger("msagv.plant")


WHEEL_WEAR_MODES = ("auto", "on", "off")
RESEND_S = 1.0  # lockstep: an unanswered state is published again after this long
STALL_S = 0.5  # a gap this long in the plant's own heartbeat: the plant itself was stopped
STALL_GRACE_S = 3.0  # after its own stall, the owner's token gets this long to come back
QUIET_MIN_S = 0.5  # the owner is lost only with its token missing and nothing from it for
# the staleness bound (--stale-ms), and at least this long (a loaded controller's solve)
OLD_CLIENT = ("msagv protocol 2 (docs/PROTOCOL.md): this query carried no identity, as a "
              "client of the first version asks; ask {key}/*/{{your identity}} instead")


class PlantRunError(RuntimeError):
    """The run cannot go on (no controller, a lockstep timeout, a failed step)."""


@dataclass
class PlantConfig:
    """How the plant process runs.

    run_mode : 'lockstep' or 'realtime'.
    period : control period T [s]; state k has t = k T exactly.
    steps : periods to run; the last state (seq = steps) carries ``end = true``.
    timeout_s : lockstep: the longest wait for a command answering the current state;
        realtime: for the first command (answering state 0). Exceeded: the run ends (exit 3).
    wait_s : how long to wait for the controller's liveliness token at start (0: forever).
    stale_ms : realtime: a command answering a state older than this [ms of vehicle time,
        which runs with the wall clock] is stale and the plant goes safe.
    safe_decel : realtime safe behaviour: wheel-speed ramp-down [m/s^2 at the rim].
    linger_s : after the end state, how long to keep the session open (the last messages
        are delivered, late commands still counted) before closing.
    resume_periods : realtime: consecutive periods in which the owner keeps up (its newest
        command answers the current or the previous state) before the safe behaviour ends.
    """

    run_mode: str = "lockstep"
    period: float = CONTROL_PERIOD
    steps: int = 100
    timeout_s: float = 10.0
    wait_s: float = 60.0
    stale_ms: float = STALE_MS
    safe_decel: float = 2.0
    linger_s: float = 0.2
    resume_periods: int = 3
    wheel_wear: str = "auto"  # per-wheel wear in the state: auto (when the owner's claim
    # asks for it, docs/PROTOCOL.md "Per-wheel wear") | on | off
    rearm: str = "manual"  # how a latched vehicle is driven again (RearmPolicy): manual |
    # same:N
    resend_s: float = RESEND_S  # lockstep: republish an unanswered state after this long

    def __post_init__(self):
        if self.run_mode not in M.RUN_MODES:
            raise ValueError(f"run mode: expected lockstep or realtime, got '{self.run_mode}'")
        if not (self.period > 0 and math.isfinite(self.period)):
            raise ValueError(f"--period must be > 0, got {self.period}")
        if self.steps < 1:
            raise ValueError("--duration must be at least one period")
        if not self.timeout_s > 0:
            raise ValueError(f"--timeout must be > 0, got {self.timeout_s}")
        if not self.wait_s >= 0:
            raise ValueError(f"--wait must be >= 0, got {self.wait_s}")
        if not self.stale_ms > 0:
            raise ValueError(f"--stale-ms must be > 0, got {self.stale_ms}")
        if not self.safe_decel > 0:
            raise ValueError(f"--safe-decel must be > 0, got {self.safe_decel}")
        if not 1 <= self.resume_periods <= 1000:
            raise ValueError(f"--resume-periods must be 1..1000, got {self.resume_periods}")
        if self.wheel_wear not in WHEEL_WEAR_MODES:
            raise ValueError(f"--wheel-wear: expected one of {', '.join(WHEEL_WEAR_MODES)}, "
                             f"got '{self.wheel_wear}'")
        RearmPolicy.parse(self.rearm)  # ValueError naming --rearm
        if not self.resend_s > 0:
            raise ValueError(f"resend_s must be > 0, got {self.resend_s}")

    @property
    def max_missed(self) -> int:
        """Consecutive periods without an answer the realtime plant tolerates (DCP's maximum
        consecutive missed PDUs): ``floor(stale_ms / T)``."""
        return int(math.floor(self.stale_ms / 1000.0 / self.period + 1e-9))


def percentiles_ms(values_s) -> dict:
    """Percentiles in ms of durations given in s (:func:`controller.metrics.percentiles`)."""
    return percentiles(values_s, scale=1000.0, count=True)


@dataclass
class _Cmd:
    state_seq: int
    seq: int
    omega_w: list
    omega_s: list
    rx_perf: float


@dataclass
class PlantStats:
    accepted: int = 0
    stale: int = 0  # valid but older than the newest accepted (out of order)
    duplicate: int = 0
    after_end: int = 0  # valid answers to the end state (never applied)
    late: int = 0  # realtime: accepted commands that arrived after their state's step
    cmd_seq_gaps: int = 0
    safe_events: int = 0
    safe_periods: int = 0
    resumes: int = 0
    missed_periods: int = 0
    clock_resyncs: int = 0
    controller_losses: int = 0
    watchdog_trips: int = 0  # the loop missed its deadline by more than stale_ms
    watchdog_periods: int = 0  # periods of safe behaviour run by the watchdog
    resent: int = 0  # states published again because their answer did not come
    old_clients: int = 0  # queries without an identity (clients of the first version)
    latency_s: list = field(default_factory=list)  # state published -> command received, - solve
    roundtrip_s: list = field(default_factory=list)  # state published -> command received
    lateness_s: list = field(default_factory=list)  # state publication - its nominal time
    pub_intervals_s: list = field(default_factory=list)


class PlantNode:
    """The plant process's logic: :meth:`open` it on a transport, :meth:`run`, :meth:`close`.
    Everything it does on the bus goes through that :class:`bridge.transport.Transport`."""

    def __init__(self, plant, keys: Keys, cfg: PlantConfig, recorder=None):
        self.plant = plant
        self.vehicle = plant.vehicle
        self.nw = self.vehicle.n_wheels
        self.keys = keys
        self.cfg = cfg
        self.transport: Transport | None = None  # open()
        self.recording = recorder is not None
        self.rec = recorder if recorder is not None else NullRecorder()
        self.rej = M.Rejections(f"plant {keys.id}", log)
        self.stats = PlantStats()
        self.seq = -1  # newest published state
        self._stepped = -1  # realtime: the newest step taken (its command chosen)
        self._pub_perf: OrderedDict[int, float] = OrderedDict()
        self._answered: set[int] = set()
        self._newest: _Cmd | None = None
        self._last_cmd_seq: int | None = None
        self._lock = threading.Lock()
        self._cmd_event = threading.Event()
        self._ctl_event = threading.Event()
        self.stop = threading.Event()
        self.controller_present = False
        self._ctl_generation = 0
        self.safe = False
        self.error: str | None = None
        self.final_state: dict | None = None
        self._params = M.encode_params(keys.id, self.vehicle.to_dict(), cfg.period, cfg.run_mode,
                                       self.nw)
        self._pub = None
        self._decls = []
        self._token = None
        self.ramp = cfg.safe_decel / self.vehicle.wheel_radius  # rad/s^2
        self.ownership = Ownership(on_change=self._on_owner_change,
                                   policy=RearmPolicy.parse(cfg.rearm), period=cfg.period,
                                   on_event=self._on_ownership_event)
        self.watch = CommandWatch(cfg.max_missed, cfg.resume_periods, cfg.period)
        self._tokens: TokenSet | None = None
        self._closed = threading.Event()
        self._plant_lock = threading.Lock()  # the plant's inputs and step (loop, watchdog)
        self._rt_due: float | None = None  # realtime: perf time the next period is due by
        self._wd_trip: str | None = None  # set by the watchdog, taken by the loop
        self._wd_active = False
        self._beat, self._last_stall = time.monotonic(), -1e9
        self._refused_logged = 0
        self._heard: tuple[str | None, float] = (None, 0.0)  # the owner's newest message
        # the per-wheel wear fields go out when on, or (auto) when the owner's claim asks
        # for them: a peer of the first protocol version rejects unknown fields
        self._wheel_wear_told = False  # the per-wheel wear last logged and recorded

    # ---- transport ---------------------------------------------------------------------
    def open(self, transport: Transport) -> None:
        """Declare on ``transport`` the publisher, subscribers, queryables, then the
        liveliness token (last: a controller that sees the token finds everything else
        declared)."""
        t, k = transport, self.keys
        self.transport = t
        self._pub = t.publisher(k.state)
        self._decls.append(t.subscribe(k.cmd, self._on_cmd_sample))
        self._decls.append(t.queryable(k.params, self._on_params_query))
        self._decls.append(t.queryable(k.claim, self._on_claim_query))
        self._decls.append(t.queryable(k.arm, self._on_arm_query))
        if self.recording:  # the references a controller sends, recorded
            self._decls.append(t.subscribe(k.reference, self._on_reference_sample))
        self._beat, self._last_stall = time.monotonic(), -1e9
        threading.Thread(target=self._heartbeat, daemon=True, name="plant heartbeat").start()
        self._tokens = TokenSet(t, k.alive_controller, self._on_token, quiet=self._quiet)
        self._tokens.focus(self.ownership.owner)
        self._decls.append(self._tokens)
        self._token = t.declare_token(k.plant_token(t.id))

    def close(self) -> None:
        """Undeclare everything :meth:`open` declared (the transport stays open)."""
        self._closed.set()
        for obj in [self._token] + self._decls + [self._pub]:
            if obj is not None:
                try:
                    obj.close()
                except Exception:
                    pass
        self._token, self._decls, self._pub = None, [], None

    def _old_client(self, query: Query) -> None:
        """A query without the querier's identity (a client of the first protocol version):
        an error reply that says why, and a log line (rate-limited)."""
        with self._lock:
            self.stats.old_clients += 1
            n = self.stats.old_clients
        if n <= 5 or n % 1000 == 0:
            log.warning("a query on %s without an identity (a client of the first protocol "
                        "version?): answered with an error (%d so far)", query.key, n)
        try:
            query.reply_err(OLD_CLIENT.format(key=query.key).encode())
        except Exception as e:  # a vanished querier: nothing to do
            log.debug("error reply failed: %s", e)

    def _on_params_query(self, query: Query) -> None:
        """Read-only: the params, to anyone who names itself (docs/PROTOCOL.md 3.4)."""
        if query.sender is None:
            return self._old_client(query)
        try:
            query.reply(self._params)
        except Exception as e:  # a vanished querier: nothing to do
            log.debug("params reply failed: %s", e)

    def _on_claim_query(self, query: Query) -> None:
        who = query.sender
        if who is None:
            return self._old_client(query)
        try:
            c = decode_claim(query.payload if query.payload is not None else b"")
        except M.MessageError as e:
            self.rej.add(e, self.keys.claim)
            grant = self.ownership.claim(None)
            grant.reason = BAD_CLAIM
        else:
            # the owner's wheel_wear is taken with the grant, under the ownership's lock: the
            # run may start the moment the grant is made, its first state must have it
            if who == self.ownership.owner:
                self._heard = (who, time.monotonic())
            grant = self.ownership.claim(
                who, c["action"], token_present=self._tokens is not None and self._tokens.present(who),
                wheel_wear=bool(c.get("wheel_wear", False)))
            if grant.granted:
                self._tell_wheel_wear()
            if c["action"] == CLAIM and not grant.granted:
                self._refused_logged += 1
                n = self._refused_logged
                if n <= 5 or n % 100 == 0:
                    hint = (f"; re-arm it with: msagv arm --id {self.keys.id} --controller {who}"
                            if grant.reason == LATCHED else "")
                    log.warning("claim of vehicle %s by %s refused: %s (%d refused)%s",
                                self.keys.id, who, grant.reason, n, hint)
        try:
            query.reply(encode_grant(grant.granted, grant.reason))
        except Exception as e:
            log.debug("claim reply failed: %s", e)

    def _on_arm_query(self, query: Query) -> None:
        """An operator's re-arm (``msagv arm``): docs/PROTOCOL.md section 3.8."""
        who = query.sender
        if who is None:
            return self._old_client(query)
        try:
            a = decode_arm(query.payload if query.payload is not None else b"")
        except M.MessageError as e:
            self.rej.add(e, self.keys.arm)
            armed, reason = False, BAD_ARM
        else:
            armed, reason = self.ownership.arm(who, a.get("controller"),
                                               t=max(self.seq, 0) * self.cfg.period)
            if armed:
                log.warning("vehicle %s re-armed by %s for %s", self.keys.id, who,
                            a.get("controller") or "the first controller that claims it")
            else:
                log.warning("re-arm of vehicle %s by %s refused: %s", self.keys.id, who, reason)
        try:
            query.reply(encode_armed(armed, reason))
        except Exception as e:
            log.debug("arm reply failed: %s", e)

    @property
    def wheel_wear(self) -> bool:
        """Whether the states carry the per-wheel wear: ``--wheel-wear on|off``, or (auto)
        as the owner's newest granted claim asks."""
        if self.cfg.wheel_wear != "auto":
            return self.cfg.wheel_wear == "on"
        return self.ownership.wheel_wear

    def _tell_wheel_wear(self) -> None:
        on = self.wheel_wear
        if on != self._wheel_wear_told:
            self._wheel_wear_told = on
            log.info("per-wheel wear in the state: %s (%s)", "on" if on else "off",
                     "asked by the owner's claim" if self.cfg.wheel_wear == "auto"
                     else "--wheel-wear")
            self.rec.event("wheel_wear", on=on)

    def _on_ownership_event(self, name: str, fields: dict) -> None:
        if name == "latched":
            log.warning("vehicle %s latched: %s; no claim is granted until an operator "
                        "re-arms it (msagv arm --id %s)%s", self.keys.id, fields["why"],
                        self.keys.id, "" if self.ownership.policy.same_after is None else
                        f" or the same identity claims it again after "
                        f"{self.ownership.policy.same_after} periods")
        self.rec.event(name, t=max(self.seq, 0) * self.cfg.period, **fields)

    def _quiet(self, who: str) -> bool:
        """Nothing (a command or a claim) from ``who`` for the staleness bound."""
        zid, at = self._heard
        bound = max(self.cfg.stale_ms / 1000.0, QUIET_MIN_S)
        return zid != who or time.monotonic() - at > bound

    def _on_owner_change(self, owner: str | None, why: str) -> None:
        log.info("vehicle %s: %s", self.keys.id, why)
        if self._tokens is not None:
            self._tokens.focus(owner)
        self.rec.event("owner", owner=owner, why=why)
        self._update_presence()

    def _on_token(self, zid: str, present: bool) -> None:
        if zid != self.ownership.owner:
            log.debug("controller token %s %s (not the owner: ignored)", zid,
                      "appeared" if present else "gone")
        elif not present and self._stalled_recently():
            # this process was stopped (SIGSTOP, a frozen machine): the owner closed the
            # link at its lease, and its token comes back with the reconnection; the owner
            # was not lost, this plant was away (as the controller's LossTimer judges)
            log.warning("owner %s's token lost right after this plant was stalled: waiting "
                        "%g s for it before the vehicle is latched", zid, STALL_GRACE_S)
            self._update_presence()  # not present meanwhile: safe in real time
            t = threading.Timer(STALL_GRACE_S, self._recheck_owner, args=(zid,))
            t.daemon = True
            t.start()
            return
        self.ownership.token(zid, present)
        self._update_presence()

    def _recheck_owner(self, zid: str) -> None:
        if self._tokens is not None and not self._tokens.present(zid):
            self.ownership.token(zid, False)
        self._update_presence()

    def _heartbeat(self) -> None:
        """Notice this process's own stalls (its threads stopped for over STALL_S)."""
        while not self._closed.wait(0.05):
            now = time.monotonic()
            if now - self._beat > STALL_S:
                self._last_stall = now
                log.warning("this plant was stalled for %.2f s (stopped, or the machine "
                            "froze)", now - self._beat)
            self._beat = now

    def _stalled_recently(self) -> bool:
        now = time.monotonic()
        return now - self._beat > STALL_S or now - self._last_stall < STALL_GRACE_S

    def _update_presence(self) -> None:
        owner = self.ownership.owner
        self._on_ctl_change(self._tokens is not None and self._tokens.present(owner))

    def _on_reference_sample(self, sample: Sample) -> None:
        self.rec.message("rx", self.keys.reference, sample.payload)

    def _on_ctl_change(self, present: bool) -> None:
        """The owner's presence (its token) changed."""
        with self._lock:
            was = self.controller_present
            self.controller_present = present
            if present and not was:
                self._ctl_generation += 1
        if present != was:
            if present:
                log.info("controller %s present", self.keys.id)
            elif self.final_state is not None:
                log.info("controller %s left after the end of the run", self.keys.id)
            else:
                self.stats.controller_losses += 1
                log.warning("controller %s gone (liveliness token lost)", self.keys.id)
            self.rec.event("controller_alive", present=present)
        self._ctl_event.set()

    def _on_cmd_sample(self, sample: Sample) -> None:
        sender = sample.sender
        if sender is None or sender != self.ownership.owner:
            # not the owner's: counted and dropped before anything else (a flood from
            # anyone else costs this, docs/PROTOCOL.md section 5)
            self.ownership.violation(sender)
            self.rej.add_reason(M.NOT_OWNER, self.keys.cmd, lambda: self._not_owner(sender))
            self.rec.message("rx", self.keys.cmd, sample.payload, time.time(),
                             why=M.NOT_OWNER)
            return
        self._heard = (sender, time.monotonic())
        self.handle_cmd(sample.payload, time.perf_counter(), time.time(), sender)

    # ---- commands ----------------------------------------------------------------------
    def handle_cmd(self, payload: bytes, rx_perf: float, rx_wall: float | None,
                   sender: str | None) -> dict | None:
        """Validate one command; the newest valid one is kept for the next step. Returns
        the decoded command, or None if rejected or ignored (stale, duplicate, or an answer
        to the end state: after_end). ``sender``: the sender's identity (None: the message
        carried none); a command not from the owner is rejected as ``not_owner`` before it
        is decoded (a flood from anyone else costs a comparison)."""
        key = self.keys.cmd
        try:
            if not self.ownership.accepts(sender):
                self.ownership.violation(sender)
                raise M.MessageError(M.NOT_OWNER, self._not_owner(sender))
            c = M.decode_cmd(payload, self.nw)
            with self._lock:
                newest_pub = self.seq
            j = c["state_seq"]
            if j > newest_pub:
                raise M.MessageError(M.UNKNOWN_STATE, f"state_seq {j} was never published "
                                                      f"(newest state is {newest_pub})")
            if abs(c["t"] - j * self.cfg.period) > 1e-6:
                raise M.MessageError(M.T_MISMATCH, f"t = {c['t']} but state {j} has t = "
                                                   f"{j * self.cfg.period}")
        except M.MessageError as e:
            self.rej.add(e, key)
            self.rec.message("rx", key, payload, rx_wall, why=e.reason)
            return None
        self.rec.message("rx", key, payload, rx_wall)
        if j >= self.cfg.steps:
            # the answer to the end state: the run is over, nothing will apply it
            with self._lock:
                self.stats.after_end += 1
            return None
        with self._lock:
            n = self._newest
            if n is not None and j < n.state_seq:
                self.stats.stale += 1
                self._answered.add(j)
                return None
            if n is not None and j == n.state_seq:
                self.stats.duplicate += 1
                return None
            if self._last_cmd_seq is not None and c["seq"] > self._last_cmd_seq + 1:
                self.stats.cmd_seq_gaps += c["seq"] - self._last_cmd_seq - 1
            self._last_cmd_seq = c["seq"]
            self._newest = _Cmd(j, c["seq"], c["omega_w"], c["omega_s"], rx_perf)
            self._answered.add(j)
            self.stats.accepted += 1
            if j <= self._stepped:
                self.stats.late += 1  # arrived after the plant took the step of its state
            tp = self._pub_perf.get(j)
        if tp is not None:
            rt = rx_perf - tp
            self.stats.roundtrip_s.append(rt)
            if "solve_ms" in c:
                self.stats.latency_s.append(rt - c["solve_ms"] / 1000.0)
        self._cmd_event.set()
        return c

    def _not_owner(self, sender: str | None) -> str:
        if sender is None:
            return (f"without the sender's identity: a client of the first protocol version "
                    f"publishes on {self.keys.cmd}, version 2 on {self.keys.cmd}/{{identity}} "
                    f"(docs/PROTOCOL.md)")
        return f"from {sender}, which does not own the vehicle"

    # ---- state -------------------------------------------------------------------------
    def publish_state(self, seq: int, end: bool = False) -> None:
        st = self.plant.state_message()
        st["t"] = seq * self.cfg.period  # t = seq T exactly (DESIGN.md: time never drifts)
        payload = M.encode_state(seq, st, safe=self.safe if self.cfg.run_mode == "realtime" else None,
                                 end=True if end else None, wheel_wear=self.wheel_wear)
        now = time.perf_counter()
        with self._lock:
            self.seq = seq
            self._pub_perf[seq] = now
            while len(self._pub_perf) > 4096:
                self._pub_perf.popitem(last=False)
        if seq == 0:
            self.ownership.start()  # from now on a lost owner latches the vehicle
        if end:
            self.ownership.end()  # from now on the owner's release is the normal end
        self._pub.put(payload, seq)
        self.rec.message("tx", self.keys.state, payload)
        if end:
            self.final_state = st

    def _apply(self, omega_w, omega_s) -> None:
        from msagv.plant.stepping import PlantError

        try:
            with self._plant_lock:
                self.plant.set_inputs(omega_w, omega_s)
                self.plant.do_step(self.plant.t, self.cfg.period)
        except PlantError as e:
            raise PlantRunError(f"step at t = {self.plant.t:.2f} s failed: {e}") from None

    # ---- waiting for the controller ----------------------------------------------------
    def _wait_controller(self) -> None:
        """Block until the controller's token is present and it subscribes to our state."""
        t0 = time.monotonic()
        waited_msg = False
        while not self.stop.is_set():
            if self.controller_present and self._pub.matching:
                return
            if not waited_msg and time.monotonic() - t0 > 1.0:
                log.info("waiting for a controller: its token on %s/* and its claim on "
                         "%s/%s/* (up to %s)", self.keys.alive_controller, self.keys.claim,
                         self.transport.id if self.transport is not None else "*",
                         f"{self.cfg.wait_s:g} s" if self.cfg.wait_s else "forever")
                waited_msg = True
            if self.cfg.wait_s and time.monotonic() - t0 > self.cfg.wait_s:
                raise PlantRunError(f"no controller for vehicle '{self.keys.id}' within "
                                    f"{self.cfg.wait_s:g} s (no liveliness token on "
                                    f"{self.keys.alive_controller}/*); start msagv controller "
                                    f"--id {self.keys.id} with matching --connect/--listen")
            self._ctl_event.wait(0.02)
            self._ctl_event.clear()

    def _wait_answer(self, k: int, timeout_s: float) -> _Cmd | None:
        """Wait for the command answering state k (lockstep: every k; realtime: k = 0). A
        controller that (re)appears meanwhile is sent state k again, and so is the owner
        every ``resend_s`` while it does not answer (a state, or its answer, lost with a
        link that was closed: a plant or controller stopped beyond the lease). None if
        stopped."""
        t0 = sent = time.monotonic()
        gen = self._ctl_generation
        while True:
            with self._lock:
                n = self._newest
            if n is not None and n.state_seq == k:
                return n
            if self.stop.is_set():
                return None
            if time.monotonic() - t0 > timeout_s:
                who = "present" if self.controller_present else "gone"
                raise PlantRunError(f"{self.cfg.run_mode}: no command answering state {k} (t = "
                                    f"{k * self.cfg.period:.2f} s) within {timeout_s:g} s "
                                    f"(controller token {who}); ending the run")
            if self._ctl_generation != gen and self.controller_present:
                gen = self._ctl_generation
                m0 = time.monotonic()
                while not self._pub.matching and time.monotonic() - m0 < 1.0:
                    time.sleep(0.005)
                log.info("controller (re)appeared: sending state %d again", k)
                self.publish_state(k)
                sent = time.monotonic()
            elif self.controller_present and time.monotonic() - sent >= self.cfg.resend_s:
                self.stats.resent += 1
                n = self.stats.resent
                if n <= 5 or n % 100 == 0:
                    log.info("no answer to state %d for %.1f s: sending it again (%d resent)",
                             k, time.monotonic() - sent, n)
                self.publish_state(k)
                sent = time.monotonic()
            self._cmd_event.wait(0.05)
            self._cmd_event.clear()

    # ---- runs --------------------------------------------------------------------------
    def run(self) -> dict:
        """Run to the end (or until :attr:`stop`); returns the summary. Raises
        PlantRunError on a timeout or a failed step."""
        try:
            self._wait_controller()
            if not self.stop.is_set():
                if self.cfg.run_mode == "lockstep":
                    self._run_lockstep()
                else:
                    self._run_realtime()
        except PlantRunError as e:
            self.error = str(e)
            raise
        finally:
            if self.final_state is None:
                st = self.plant.state_message()
                st["t"] = max(self.seq, 0) * self.cfg.period
                self.final_state = st
        return self.summary()

    def _run_lockstep(self) -> None:
        cfg = self.cfg
        self.publish_state(0)
        for k in range(cfg.steps):
            c = self._wait_answer(k, cfg.timeout_s)
            if c is None:
                return
            self._apply(c.omega_w, c.omega_s)
            self.publish_state(k + 1, end=k + 1 == cfg.steps)
            self.rec.maybe_flush()
        self._linger()

    def _run_realtime(self) -> None:
        cfg, T, st = self.cfg, self.cfg.period, self.stats
        self.publish_state(0)
        # the clock starts with the first command (the controller is warm by then); a
        # controller that (re)appears meanwhile is sent state 0 again, as in lockstep
        if self._wait_answer(0, cfg.timeout_s) is None:
            return
        w0 = time.perf_counter()
        last_pub = w0
        self._rt_due = w0 + 2 * T
        watchdog = threading.Thread(target=self._watchdog, daemon=True, name="plant watchdog")
        watchdog.start()
        for k in range(cfg.steps):
            target = w0 + (k + 1) * T
            now = time.perf_counter()
            if target - now > 0:
                time.sleep(target - now)
            elif now - target > 10 * T:  # stalled (e.g. the machine froze): re-anchor
                st.clock_resyncs += 1
                w0 += (now - target)
                target = now
            if self.stop.is_set():
                return
            with self._lock:
                n = self._newest
                present = self.controller_present
                self._stepped = k
            trip, self._wd_trip = self._wd_trip, None
            if trip is not None:
                d = self.watch.force_safe(trip)
            else:
                d = self.watch.step(k, n.state_seq if n is not None else None, present)
            if d.resumed:
                self.safe = False
                st.resumes += 1
                log.warning("resumed normal operation at t = %.2f s (the owner kept up for %d "
                            "periods; newest command answers state %d)", k * T,
                            cfg.resume_periods, n.state_seq)
                self.rec.event("safe", on=False, t=k * T)
            if d.use_command:
                u_w, u_s = n.omega_w, n.omega_s
            else:
                if d.entered_safe is not None:
                    self.safe = True
                    st.safe_events += 1
                    log.warning("SAFE at t = %.2f s: %s; holding steering, ramping the wheels "
                                "down at %g m/s^2", k * T, d.entered_safe, cfg.safe_decel)
                    self.rec.event("safe", on=True, t=k * T, why=d.entered_safe)
                st.safe_periods += 1
                held_w, _ = self.plant.inputs
                u_w = np.maximum(np.asarray(held_w) - self.ramp * T, 0.0)
                u_s = np.zeros(self.nw)
            self._apply(u_w, u_s)
            self.publish_state(k + 1, end=k + 1 == cfg.steps)
            done = time.perf_counter()
            st.lateness_s.append(done - target)
            st.pub_intervals_s.append(done - last_pub)
            last_pub = done
            if done - target > T:
                st.missed_periods += 1
            # the next period is due one period after its target (a loop that is behind, and
            # catches up or re-anchors its clock next, gets two periods from now)
            self._rt_due = max(w0 + (k + 3) * T, done + 2 * T)
            self._wd_active = False
            self.rec.maybe_flush()
        self._rt_due = None
        self._linger()

    def _watchdog(self) -> None:
        """Realtime: while the loop is more than ``stale_ms`` past a period's deadline, run
        the safe behaviour here (steering held, wheels ramped down at ``--safe-decel``),
        one period at a time. It touches the plant (under the plant's own lock) and the
        log, nothing of Zenoh: a loop stuck in the bus does not stop it."""
        T, bound = self.cfg.period, self.cfg.stale_ms / 1000.0
        st = self.stats
        while not (self.stop.wait(T) or self._closed.is_set()):
            due = self._rt_due
            if due is None:
                if self.final_state is not None:
                    return
                continue
            late = time.perf_counter() - due
            if late <= bound:
                continue
            if not self._wd_active:
                self._wd_active = True
                why = (f"the plant's own loop is {late * 1000:.0f} ms past its deadline "
                       f"(bound {self.cfg.stale_ms:g} ms): the watchdog runs the safe "
                       f"behaviour")
                self._wd_trip = why
                self.safe = True
                st.watchdog_trips += 1
                log.warning("SAFE (watchdog) at t = %.2f s: %s", max(self.seq, 0) * T, why)
            if self._plant_lock.acquire(timeout=T):
                try:
                    held_w, _ = self.plant.inputs
                    self.plant.set_inputs(np.maximum(np.asarray(held_w) - self.ramp * T, 0.0),
                                          np.zeros(self.nw))
                    st.watchdog_periods += 1
                except Exception as e:  # the plant refused: said once per trip, loop decides
                    log.error("watchdog: the safe behaviour failed: %s", e)
                finally:
                    self._plant_lock.release()

    def _linger(self) -> None:
        self.stop.wait(self.cfg.linger_s)

    # ---- results -----------------------------------------------------------------------
    def summary(self) -> dict:
        st, T = self.stats, self.cfg.period
        steps_done = max(self.seq, 0)
        with self._lock:
            answered = set(self._answered)
        lost = sum(1 for j in range(steps_done) if j not in answered)
        jit = [abs(d - T) for d in st.pub_intervals_s]
        fs = self.final_state or {}
        return {
            "role": "plant", "id": self.keys.id, "run_mode": self.cfg.run_mode,
            "period": T, "steps": steps_done, "t_end": steps_done * T,
            "completed": steps_done == self.cfg.steps and self.error is None,
            "error": self.error,
            "missed_periods": st.missed_periods, "clock_resyncs": st.clock_resyncs,
            "latency_ms": percentiles_ms(st.latency_s),
            "roundtrip_ms": percentiles_ms(st.roundtrip_s),
            "lateness_ms": percentiles_ms(st.lateness_s),
            "period_jitter_ms": percentiles_ms(jit),
            "commands": {"accepted": st.accepted, "stale": st.stale, "duplicate": st.duplicate,
                         "late": st.late, "lost": lost, "seq_gaps": st.cmd_seq_gaps,
                         "after_end": st.after_end},
            "safe": {"events": st.safe_events, "periods": st.safe_periods, "resumes": st.resumes,
                     "watchdog_trips": st.watchdog_trips,
                     "watchdog_periods": st.watchdog_periods},
            "controller_losses": st.controller_losses, "resent_states": st.resent,
            "old_clients": st.old_clients,
            "periods": (self.watch.summary() if self.cfg.run_mode == "realtime" else None),
            "ownership": self.ownership.summary(),
            "presence": self._tokens.summary() if self._tokens is not None else None,
            "rejected": self.rej.summary(),
            "final_state": {k: fs[k] for k in ("t",) + BODY_FIELDS + WEAR_FIELDS
                            + WHEEL_WEAR_FIELDS if k in fs},
        }


# ---- the process ------------------------------------------------------------------------
def serve(plant, cfg: PlantConfig, opts: SessionOptions, *, transport: Transport | None = None,
          recorder=None, signals: StopOnSignal | None = None) -> tuple[dict, int]:
    """Run the plant process: open the Zenoh session, serve one run, close everything.

    ``plant``: any object with the plant interface (:class:`plant.interface.PlantInterface`),
    built by the caller; ``opts``: the vehicle id and the session options; ``transport``:
    an open transport to run on instead of the Zenoh session of ``opts`` (the caller
    closes it); ``recorder``: an open :class:`bridge.recording.Recorder` or None
    (closed here, with the summary); ``signals``: the installed SIGINT/SIGTERM handler
    whose event ends the run (the summary then names the signal).
    Returns ``(summary, exit code)``: 0 done or stopped, 2 the session could not open,
    3 the run could not go on (:class:`PlantRunError`).
    """
    node = PlantNode(plant, Keys(opts.id), cfg, recorder=recorder)
    if signals is not None:
        node.stop = signals.event
    rc = EXIT_OK
    t = None
    try:
        t = transport if transport is not None else ZenohTransport.open(opts, "plant")
        plant.warmup()  # the integrator compiled before the real-time clock starts
        freeze_heap()
        node.open(t)
        log.info("%s plant ready: %s, %d steps of %g s", cfg.run_mode, plant.vehicle.name,
                 cfg.steps, cfg.period)
        try:
            node.run()
        except PlantRunError as e:
            log.error("%s", e)
            rc = EXIT_RUNTIME
    except SessionError as e:
        log.error("%s", e)
        node.error = str(e)
        rc = EXIT_USAGE
    except KeyboardInterrupt:
        node.error = "interrupted"
    finally:
        closed = _close_within(node, t if transport is None else None,
                               CLOSE_S if node.stop.is_set() else None)
        summary = node.summary()
        if not closed:
            summary["close_abandoned"] = True
        if signals is not None and signals.name is not None:
            summary["stopped_by"] = signals.name
            log.info("stopped by %s", signals.name)
        if recorder is not None:  # the recorder's counters (errors, drops) in the summary too
            summary["recording"] = recorder.close(summary)
    return summary, rc


CLOSE_S = 0.5  # a stopped plant waits this long for its declarations and session to close


def _close_within(node: PlantNode, transport, timeout: float | None) -> bool:
    """Close ``node`` (its declarations) and ``transport`` (None: the caller's), within
    ``timeout`` s (None: however long it takes). A run stopped by a signal must end within
    a second, with its summary, even if the bus holds a close: then the closing is left to
    a daemon thread (False; the process leaves without waiting for it, msagv.cli.nodes)."""

    def close() -> None:
        try:
            node.close()
        finally:
            if transport is not None:
                transport.close()

    if timeout is None:
        close()
        return True
    th = threading.Thread(target=close, daemon=True, name="plant close")
    th.start()
    th.join(timeout)
    if th.is_alive():
        log.warning("closing the Zenoh session took over %g s: leaving without it", timeout)
        return False
    return True
