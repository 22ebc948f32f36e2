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
import threading
import time
from dataclasses import dataclass

from . import messages as M
from .ownership import (BAD_ARM, BAD_CLAIM, CLAIM, LATCHED, Ownership, RearmPolicy,
                        decode_arm, decode_claim, encode_armed, encode_grant)
from .link_key import KeyPair, LinkKeyError, LinkKeys, derive
from .presence import TokenSet
from .process import EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, StopOnSignal, freeze_heap
from .run_core import (RESEND_S, Command, PlantRun, PlantRunError, PlantStats, RunConfig,
                       WallClock, percentiles_ms)
from .session import Keys, SessionError, SessionOptions
from .transport import Query, Sample, Transport, close_all
from .zenoh_transport import ZenohTransport

log = logging.getLogger("msagv.plant")


WHEEL_WEAR_MODES = ("auto", "on", "off")
STALL_S = 0.5  # a gap this long in the plant's own heartbeat: the plant itself was stopped
STALL_GRACE_S = 3.0  # after its own stall, the owner's token gets this long to come back
QUIET_MIN_S = 0.5  # the owner is lost only with its token missing and nothing from it for
# the staleness bound (--stale-ms), and at least this long (a loaded controller's solve)
OLD_CLIENT = ("msagv protocol 2 (docs/PROTOCOL.md): this query carried no identity, as a "
              "client of the first version asks; ask {key}/*/{{your identity}} instead")


__all__ = ["PlantConfig", "PlantNode", "PlantRunError", "percentiles_ms", "serve"]


@dataclass
class PlantConfig(RunConfig):
    """How the plant process runs: the run's settings (:class:`bridge.run_core.RunConfig`:
    run_mode, period, steps, timeout_s, wait_s, stale_ms, safe_decel, linger_s,
    resume_periods; the vehicle time runs with the wall clock) and the Zenoh plant's own."""

    wheel_wear: str = "auto"  # per-wheel wear in the state: auto (when the owner's claim
    # asks for it, docs/PROTOCOL.md "Per-wheel wear") | on | off
    rearm: str = "manual"  # how a latched vehicle is driven again (RearmPolicy): manual |
    # same:N
    resend_s: float = RESEND_S  # lockstep: republish an unanswered state after this long

    def __post_init__(self):
        super().__post_init__()
        if self.wheel_wear not in WHEEL_WEAR_MODES:
            raise ValueError(f"--wheel-wear: expected one of {', '.join(WHEEL_WEAR_MODES)}, "
                             f"got '{self.wheel_wear}'")
        RearmPolicy.parse(self.rearm)  # ValueError naming --rearm
        if not self.resend_s > 0:
            raise ValueError(f"resend_s must be > 0, got {self.resend_s}")


@dataclass
class _Cmd(Command):
    seq: int = 0
    rx_perf: float = 0.0


@dataclass
class ZenohPlantStats(PlantStats):
    controller_losses: int = 0
    old_clients: int = 0  # queries without an identity (clients of the first version)


class PlantNode:
    """The Zenoh plant: the run (:class:`bridge.run_core.PlantRun`) on a transport.
    :meth:`open` it on a transport, :meth:`run`, :meth:`close`. Everything it does on the bus
    goes through that :class:`bridge.transport.Transport`; it is the run's
    :class:`bridge.run_core.PlantPort`: ownership, claims, liveliness, re-sends."""

    def __init__(self, plant, keys: Keys, cfg: PlantConfig, recorder=None, measure=None):
        self.plant = plant
        self.vehicle = plant.vehicle
        self.nw = self.vehicle.n_wheels
        self.keys = keys
        self.cfg = cfg
        self.transport: Transport | None = None  # open()
        self.recording = recorder is not None
        self.core = PlantRun(plant, cfg, self, clock=WallClock(), recorder=recorder, log=log,
                             stats=ZenohPlantStats(), measure=measure)
        self.rec = self.core.rec
        self.stats = self.core.stats
        self.watch = self.core.watch
        self._lock = self.core.lock  # seq, the newest command, the answered states
        self._plant_lock = self.core.plant_lock
        self.rej = M.Rejections(f"plant {keys.id}", log)
        # the states answered (for the summary's lost count): one bit per state of the run,
        # allocated once (a set of them grew by an int every period)
        self._answered = bytearray((cfg.steps + 8) // 8)
        self._newest: _Cmd | None = None
        self._last_cmd_seq: int | None = None
        self._wake = threading.Event()  # a command or the owner's presence changed
        self.controller_present = False
        self._ctl_generation = 0
        self._resend: tuple[int, float] = (0, 0.0)  # (generation, sent) of the awaited state
        self._params = M.encode_params(keys.id, self.vehicle.to_dict(), cfg.period, cfg.run_mode,
                                       self.nw)
        self._pub = None
        self._decls = []
        self._token = None
        self.ownership = Ownership(on_change=self._on_owner_change,
                                   policy=RearmPolicy.parse(cfg.rearm), period=cfg.period,
                                   on_event=self._on_ownership_event)
        self._keys = KeyPair()  # the grant's key exchange (bridge.link_key)
        self._derived = None  # (identity, pk, keys) of the last claim's key: derived once
        self._unkeyed_told: str | None = None  # the keyless owner last warned about
        self._tokens: TokenSet | None = None
        self._beat, self._last_stall = time.monotonic(), -1e9
        self._refused_logged = 0
        self._heard: tuple[str | None, float] = (None, 0.0)  # the owner's newest message
        # the per-wheel wear fields go out when on, or (auto) when the owner's claim asks
        # for them: a peer of the first protocol version rejects unknown fields
        self._wheel_wear_told = False  # the per-wheel wear last logged and recorded

    # the run's state, as the node's
    seq = property(lambda self: self.core.seq)
    safe = property(lambda self: self.core.safe)
    final_state = property(lambda self: self.core.final_state)

    @property
    def stop(self) -> threading.Event:
        return self.core.stop

    @stop.setter
    def stop(self, event: threading.Event) -> None:
        self.core.stop = event

    @property
    def _stepped(self) -> int:
        return self.core.stepped

    @_stepped.setter
    def _stepped(self, k: int) -> None:
        self.core.stepped = k

    @property
    def error(self) -> str | None:
        return self.core.error

    @error.setter
    def error(self, why: str | None) -> None:
        self.core.error = why


    # ---- transport ---------------------------------------------------------------------
    def open(self, transport: Transport) -> None:
        """Declare on ``transport`` the publisher, subscribers, queryables, then the
        liveliness token (last: a controller that sees the token finds everything else
        declared)."""
        t, k = transport, self.keys
        self.transport = t
        # with certificates an identity is proven: its restarted controller may bring a new key
        self.ownership.rekey = bool(getattr(t, "authenticated", False))
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
        self.core.close()
        close_all([self._token] + self._decls + [self._pub])
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
        pk = None
        try:
            c = decode_claim(query.payload if query.payload is not None else b"")
            pk, link = c.get("pk"), None
            if pk is not None:
                cached = self._derived
                if cached is not None and cached[:2] == (who, pk):
                    link = cached[2]
                else:
                    try:
                        link = derive(self._keys, pk, self.keys.id, self.transport.id, who)
                    except LinkKeyError as e:
                        raise M.MessageError(M.BAD_VALUE, f"pk: {e}") from None
                    self._derived = (who, pk, link)
        except M.MessageError as e:
            self.rej.add(e, self.keys.claim)
            grant = self.ownership.claim(None)
            grant.reason = BAD_CLAIM
            pk = None
        else:
            # the owner's wheel_wear (and key) is taken with the grant, under the ownership's
            # lock: the run may start the moment the grant is made, its first state must
            # have it
            owner, held = self.ownership.owner_link or (None, None)
            proven = owner == who and held is not None and LinkKeys.valid(held.cmd, c)
            grant = self.ownership.claim(
                who, c["action"], token_present=self._tokens is not None and self._tokens.present(who),
                wheel_wear=bool(c.get("wheel_wear", False)), pk=pk, link=link, proven=proven)
            if grant.granted:
                if owner == who and (held is None or proven):
                    # the owner's claim again, proven (or no key to prove it with): heard.
                    # (A new grant is heard in _on_owner_change; an unproven claim with the
                    # owner's pk, which any copier can send, is not.)
                    self._heard = (who, time.monotonic())
                self._tell_wheel_wear()
            if c["action"] == CLAIM and not grant.granted:
                self._refused_logged += 1
                n = self._refused_logged
                if n <= 5 or n % 100 == 0:
                    hint = (f"; re-arm it with: msagv arm --id {self.keys.id} --controller {who}"
                            if grant.reason == LATCHED else "")
                    log.warning("claim of vehicle %s by %s refused: %s (%d refused)%s",
                                self.keys.id, who, grant.reason, n, hint)
            if grant.granted and pk is None and self._unkeyed_told != who:
                self._unkeyed_told = who
                log.warning("controller %s claimed vehicle %s without a key (a client older "
                            "than the grant's key, docs/PROTOCOL.md): its commands are taken "
                            "without a mac, as any session that forges its source info could "
                            "send them", who, self.keys.id)
        try:
            query.reply(encode_grant(grant.granted, grant.reason,
                                     pk=self._keys.public if grant.granted and pk else None))
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
        if owner is not None:
            # a new owner is heard (its claim) before its token is queried: right after a
            # first grant the query through a router may still miss the token (issue 30,
            # item 4) while the owner, waiting for its first state, sends nothing yet (a CI
            # run latched a live owner that way)
            self._heard = (owner, time.monotonic())
        if self._tokens is not None:
            self._tokens.focus(owner)
        self.rec.event("owner", owner=owner, why=why)
        self._update_presence()

    def _on_token(self, zid: str, present: bool) -> None:
        if self.stop.is_set():
            # stopping (a signal): the owner is not judged by what the bus says meanwhile,
            # nor by this node's own close of its token watch (a loop that the bus held
            # past the stop runs on beside the close: serve's RUN_STOP_S)
            log.debug("controller token %s %s while stopping: ignored", zid,
                      "appeared" if present else "gone")
            return
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
        self.ownership.token(zid, present,
                             how="" if present or self._tokens is None else self._tokens.last_loss)
        self._update_presence()

    def _recheck_owner(self, zid: str) -> None:
        if self.stop.is_set():  # (as in _on_token)
            return
        if self._tokens is not None and not self._tokens.present(zid):
            self.ownership.token(zid, False, how="not back after this plant's own stall")
        self._update_presence()

    def _heartbeat(self) -> None:
        """Notice this process's own stalls (its threads stopped for over STALL_S)."""
        while not self.core.closed.wait(0.05):
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
        self._wake.set()

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
            owner, link = self.ownership.owner_link or (None, None)
            if link is not None:
                why = "not the owner's" if owner != sender else LinkKeys.fault(link.cmd, c)
                if why is not None:
                    raise M.MessageError(M.BAD_MAC, f"from {sender}: {why} (the owner's "
                                                    f"commands carry the grant's mac)")
            # the owner heard: its mac checked (a copied identity without the key is not)
            self._heard = (sender, time.monotonic())
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
                self._mark_answered(j)
                return None
            if n is not None and j == n.state_seq:
                self.stats.duplicate += 1
                return None
            if self._last_cmd_seq is not None and c["seq"] > self._last_cmd_seq + 1:
                self.stats.cmd_seq_gaps += c["seq"] - self._last_cmd_seq - 1
            self._last_cmd_seq = c["seq"]
            self._newest = _Cmd(j, c["omega_w"], c["omega_s"], seq=c["seq"], rx_perf=rx_perf)
            self._mark_answered(j)
            self.stats.accepted += 1
            if j <= self.core.stepped:
                self.stats.late += 1  # arrived after the plant took the step of its state
            self.core.answered(j, rx_perf, c.get("solve_ms"))
        self._wake.set()
        return c

    def _mark_answered(self, j: int) -> None:
        """(under the lock) State ``j`` was answered (a state the run has: 0 <= j < steps)."""
        if 0 <= j < self.cfg.steps:
            self._answered[j >> 3] |= 1 << (j & 7)

    def _lost(self, steps_done: int) -> int:
        """States 0 .. steps_done - 1 that no valid command answered."""
        with self._lock:
            bits = bytes(self._answered)
        full, rest = divmod(min(steps_done, 8 * len(bits)), 8)
        answered = sum(bin(b).count("1") for b in bits[:full])
        if rest:
            answered += bin(bits[full] & ((1 << rest) - 1)).count("1")
        return steps_done - answered

    def _not_owner(self, sender: str | None) -> str:
        if sender is None:
            return (f"without the sender's identity: a client of the first protocol version "
                    f"publishes on {self.keys.cmd}, version 2 on {self.keys.cmd}/{{identity}} "
                    f"(docs/PROTOCOL.md)")
        return f"from {sender}, which does not own the vehicle"

    # ---- the run's port (bridge.run_core.PlantPort) ------------------------------------
    def publish_state(self, seq: int, end: bool = False) -> None:
        self.core.publish_state(seq, end)

    def send_state(self, seq: int, st: dict, end: bool) -> None:
        link = (self.ownership.owner_link or (None, None))[1]
        payload = M.encode_state(seq, st, safe=self.safe if self.cfg.run_mode == "realtime" else None,
                                 end=True if end else None, wheel_wear=self.wheel_wear,
                                 mac_key=None if link is None else link.state)
        if seq == 0:
            self.ownership.start()  # from now on a lost owner latches the vehicle
        if end:
            self.ownership.end()  # from now on the owner's release is the normal end
        self._pub.put(payload, seq)
        self.rec.message("tx", self.keys.state, payload)

    def ready(self) -> bool:
        """The owner's token is present and it subscribes to our state."""
        return self.controller_present and self._pub.matching

    def answer(self, k: int) -> _Cmd | None:
        with self._lock:
            n = self._newest
        return n if n is not None and n.state_seq == k else None

    def newest(self) -> _Cmd | None:
        return self._newest

    def present(self) -> bool:
        return self.controller_present

    def idle(self, seconds: float, wake: bool = True) -> None:
        if not wake:  # commands are taken on the transport's threads meanwhile
            time.sleep(seconds)
            return
        self._wake.wait(seconds)
        self._wake.clear()

    def applied(self, k: int, omega_w, omega_s, commanded: bool) -> None:
        pass  # commands are recorded as they come (handle_cmd)

    def unanswered(self, k: int, first: bool) -> None:
        """A controller that (re)appears while state k is unanswered is sent it again, and
        so is the owner every ``resend_s`` (a state, or its answer, lost with a link that
        was closed: a plant or controller stopped beyond the lease)."""
        if first:
            self._resend = (self._ctl_generation, time.monotonic())
            return
        gen, sent = self._resend
        if self._ctl_generation != gen and self.controller_present:
            m0 = time.monotonic()
            while not self._pub.matching and time.monotonic() - m0 < 1.0:
                time.sleep(0.005)
            log.info("controller (re)appeared: sending state %d again", k)
            self.publish_state(k)
            self._resend = (self._ctl_generation, time.monotonic())
        elif self.controller_present and time.monotonic() - sent >= self.cfg.resend_s:
            self.stats.resent += 1
            n = self.stats.resent
            if n <= 5 or n % 100 == 0:
                log.info("no answer to state %d for %.1f s: sending it again (%d resent)",
                         k, time.monotonic() - sent, n)
            self.publish_state(k)
            self._resend = (gen, time.monotonic())

    def waiting(self) -> str:
        return (f"waiting for a controller: its token on {self.keys.alive_controller}/* and "
                f"its claim on {self.keys.claim}/"
                f"{self.transport.id if self.transport is not None else '*'}/* (up to "
                f"{f'{self.cfg.wait_s:g} s' if self.cfg.wait_s else 'forever'})")

    def no_controller(self) -> str:
        return (f"no controller for vehicle '{self.keys.id}' within {self.cfg.wait_s:g} s (no "
                f"liveliness token on {self.keys.alive_controller}/*); start msagv controller "
                f"--id {self.keys.id} with matching --connect/--listen")

    def no_answer(self, k: int, timeout_s: float) -> str:
        who = "present" if self.controller_present else "gone"
        return (f"{self.cfg.run_mode}: no command answering state {k} (t = "
                f"{k * self.cfg.period:.2f} s) within {timeout_s:g} s (controller token {who}); "
                f"ending the run")

    # ---- runs --------------------------------------------------------------------------
    def run(self) -> dict:
        """Run to the end (or until :attr:`stop`); returns the summary. Raises
        PlantRunError on a timeout or a failed step."""
        self.core.run()
        return self.summary()

    # ---- results -----------------------------------------------------------------------
    def summary(self) -> dict:
        st, r = self.stats, self.core.summary()
        steps_done = r["steps"]
        lost = self._lost(steps_done)
        return {
            "role": "plant", "id": self.keys.id,
            **{k: r[k] for k in ("run_mode", "period", "steps", "t_end", "completed", "error",
                                 "missed_periods", "clock_resyncs", "latency_ms",
                                 "roundtrip_ms", "lateness_ms", "period_jitter_ms")},
            "commands": {"accepted": st.accepted, "stale": st.stale, "duplicate": st.duplicate,
                         "late": st.late, "lost": lost, "seq_gaps": st.cmd_seq_gaps,
                         "after_end": st.after_end},
            "safe": r["safe"],
            "controller_losses": st.controller_losses, "resent_states": st.resent,
            "old_clients": st.old_clients,
            "periods": r["periods"],
            "ownership": self.ownership.summary(),
            "presence": self._tokens.summary() if self._tokens is not None else None,
            "rejected": self.rej.summary(),
            "final_state": r["final_state"],
        }



# ---- the process ------------------------------------------------------------------------
def serve(plant, cfg: PlantConfig, opts: SessionOptions, *, transport: Transport | None = None,
          recorder=None, signals: StopOnSignal | None = None,
          measure=None) -> tuple[dict, int]:
    """Run the plant process: open the Zenoh session, serve one run, close everything.

    ``plant``: any object with the plant interface (:class:`plant.interface.PlantInterface`),
    built by the caller; ``opts``: the vehicle id and the session options; ``transport``:
    an open transport to run on instead of the Zenoh session of ``opts`` (the caller
    closes it); ``recorder``: an open :class:`bridge.recording.Recorder` or None
    (closed here, with the summary); ``signals``: the installed SIGINT/SIGTERM handler
    whose event ends the run (the summary then names the signal); ``measure``: what the
    published states carry of the plant's (:class:`plant.sensors.MeasurementNoise`).
    Returns ``(summary, exit code)``: 0 done or stopped, 2 the session could not open,
    3 the run could not go on (:class:`PlantRunError`).
    """
    node = PlantNode(plant, Keys(opts.id), cfg, recorder=recorder, measure=measure)
    if signals is not None:
        node.stop = signals.event
    rc = EXIT_OK
    t = None
    left: list = []  # the loop, left behind (_run_within)
    try:
        t = transport if transport is not None else ZenohTransport.open(opts, "plant")
        plant.warmup()  # the integrator compiled before the real-time clock starts
        freeze_heap()
        node.open(t)
        log.info("%s plant ready: %s, %d steps of %g s", cfg.run_mode, plant.vehicle.name,
                 cfg.steps, cfg.period)
        try:
            _run_within(node, RUN_STOP_S, left)
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
        if left:  # the state it stood in, as the loop's own end would have kept it
            with node._plant_lock:
                node.core.final_state = dict(plant.state_message(),
                                             t=max(node.core.seq, 0) * cfg.period)
        # (a loop the bus held past the stop: its close is likely held too, and the second
        # goes on the same budget)
        closed = _close_within(node, t if transport is None else None,
                               None if not node.stop.is_set() else
                               CLOSE_LEFT_S if left else CLOSE_S)
        summary = node.summary()
        if not closed:
            summary["close_abandoned"] = True
        if left:
            summary["run_abandoned"] = True
        if signals is not None and signals.name is not None:
            summary["stopped_by"] = signals.name
            log.info("stopped by %s", signals.name)
        if recorder is not None:  # the recorder's counters (errors, drops) in the summary too
            summary["recording"] = recorder.close(summary)
    return summary, rc


CLOSE_S = 0.5  # a stopped plant waits this long for its declarations and session to close
RUN_STOP_S = 0.3  # ... and, before that, this long for its loop (it looks every period) to see the stop
CLOSE_LEFT_S = 0.2  # the close's time after a loop left behind (RUN_STOP_S spent already)


def _run_within(node: PlantNode, stop_s: float, left: list) -> None:
    """Run ``node`` on a thread of its own while this (the main) thread waits for it.

    Python runs a signal's handler on the main thread only, between two bytecodes: a loop
    on the main thread that the bus holds inside a call (a put waiting for Zenoh's tables
    while they take in the close of a peer that declared 10,000 tokens: 1.4 s, measured)
    would take SIGTERM only when the call returns. Waiting here in steps of 50 ms, the
    handler runs at once; once ``node.stop`` is set (or this thread is interrupted: a
    second signal, Ctrl-C) the loop has ``stop_s`` to see it (it looks every period). If
    it does not, it is left behind (``left`` gets True; a daemon thread, the process
    leaves without it, msagv.cli.nodes) and the summary is written without it. A failure
    of the run (:class:`PlantRunError`) is raised here."""
    failed: list[BaseException] = []
    done = threading.Event()

    def run() -> None:
        try:
            node.run()
        except BaseException as e:  # (raised again on the caller's thread)
            failed.append(e)
        finally:
            done.set()

    th = threading.Thread(target=run, daemon=True, name="plant run")
    th.start()
    try:
        while not done.wait(0.05) and not node.stop.is_set():
            pass
    finally:  # (also on a KeyboardInterrupt here: the loop is stopped, never left running)
        if not done.is_set():
            node.stop.set()
        if not done.wait(stop_s):
            left.append(True)
            log.warning("the loop did not see the stop within %g s (held in the bus, or "
                        "by the machine): leaving without it", stop_s)
    if failed:
        raise failed[0]


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
