"""``msagv controller``: the MPC as a Zenoh process.

Gets the vehicle from the plant's ``msagv/{id}/params`` queryable (or ``--vehicle FILE``)
and binds to the plant that answered, by its identity (:mod:`bridge.ownership`; on a plain
bus it warns that it cannot tell the real plant from a liar, with ``--secure`` the
plant's certificate proves it): states from any other identity are rejected
(``not_bound``), before they are decoded. Once its MPC is warm it declares
``msagv/{id}/alive/controller/{identity}``, claims the vehicle from that plant on
``msagv/{id}/claim`` (asking for the per-wheel wear), and while the plant grants it,
answers every ``state`` with a ``cmd`` naming the state it answers (never for a state older
than ``--max-age-ms``; a state sent again gets the same command again). It takes new
references on ``msagv/{id}/reference`` where their sender is known (``--bus-references``:
by default only with ``--secure``). It stops commanding while the plant's token
``msagv/{id}/alive/plant/{identity}`` is gone, and decides the plant is lost only after
:class:`bridge.loss.LossTimer`'s confirmation time of its own running time.

:class:`ControllerNode` is the process's logic; it talks to the bus only through a
:class:`bridge.transport.Transport` (Zenoh in the process, :mod:`bridge.loopback` in the
tests); :func:`serve` opens the Zenoh one unless given another.

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
from contextlib import nullcontext
from typing import Callable

import numpy as np

from . import messages as M
from .controller_run import AnswerCounts, ControllerRun
from .loss import LOST, STALE_MS, LossTimer
from .link_key import KeyPair, LinkKeyError, LinkKeys, derive
from .ownership import (BAD_CLAIM, CLAIM_REFRESH_S, CLAIM_RETRY_S, LATCHED, RELEASE, claim,
                        params_replies)
from .plant_node import percentiles_ms
from .presence import Presence
from .process import EXIT_OK, EXIT_RUNTIME, EXIT_USAGE, freeze_heap
from .recording import NullRecorder
from .session import Keys, SessionError, SessionOptions
from .transport import Sample, Transport, close_all
from .zenoh_transport import ZenohTransport

log = logging.getLogger("msagv.controller")

REALTIME_DEADLINE_MS = 7.0  # solve budget used against a realtime plant unless --deadline-ms


FALLBACK_LOSS_S = 2.0  # s without a state before a plant known only by its states is gone
LOSS_CONFIRM_S = 2.0  # s of running time without the plant before it is lost


ON_PLANT_LOSS = ("wait", "exit")  # --on-plant-loss
BUS_REFERENCES = ("auto", "on", "off")  # --bus-references


class ControllerRunError(RuntimeError):
    """The controller cannot go on (no plant, the plant gone with --on-plant-loss exit)."""


@dataclasses.dataclass
class ControllerConfig:
    """How the controller process runs.

    max_age_ms : never send a command for a state received longer ago than this [ms]
        (None: no limit; the default against a realtime plant is its staleness bound).
    on_plant_loss : 'wait' for the plant to come back, or 'exit' (code 3).
    exit_at_end : exit (code 0) after a state with ``end = true``.
    bus_references : take references from the bus: 'auto' only on an authenticated bus
        (``--secure``: the access control lets only the controller's own and the operator's
        certificates put them), 'on' from anyone, 'off' never. Refused ones are counted
        as ``references_off``. On a plain bus any session, or a client that copied a
        sender's source info, could give the vehicle a path.
    """

    max_age_ms: float | None = None
    on_plant_loss: str = "wait"
    exit_at_end: bool = False
    bus_references: str = "auto"

    def __post_init__(self):
        for name, allowed in (("on_plant_loss", ON_PLANT_LOSS),
                              ("bus_references", BUS_REFERENCES)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name}: expected one of {', '.join(allowed)}, got "
                                 f"'{getattr(self, name)}'")

    def takes_references(self, authenticated: bool) -> bool:
        """Whether references from a bus (``authenticated``: ``--secure``) are taken."""
        return self.bus_references == "on" or (self.bus_references == "auto"
                                               and authenticated)


@dataclasses.dataclass
class ControllerStats(AnswerCounts):
    """:class:`bridge.controller_run.AnswerCounts` (answered, new runs, stale, solve times)
    and the Zenoh node's own counts."""

    skipped: int = 0  # states superseded by a newer one before they were solved
    duplicates: int = 0
    ignored_no_plant: int = 0  # states while the plant's token was gone
    not_granted: int = 0  # solved but not sent: the plant did not grant us the vehicle
    resent: int = 0  # commands sent again: their state came again (a lockstep re-send)
    references: int = 0
    ends: int = 0
    replayed: int = 0  # signed states older than the newest one of the same grant


class ControllerNode:
    """The controller process's logic: :meth:`open` it on a transport, :meth:`run`,
    :meth:`close`. Everything it does on the bus goes through that
    :class:`bridge.transport.Transport`. ``plant_zid``: the identity of the plant whose
    params it was built for (None: it binds to the one plant that answers its claim)."""

    def __init__(self, mpc, keys: Keys, cfg: ControllerConfig, recorder=None,
                 plant_zid: str | None = None, rebind: Callable[[], str] | None = None):
        self.mpc = mpc
        self.nw = mpc.vehicle.n_wheels
        self.keys = keys
        self.cfg = cfg
        self.transport: Transport | None = None  # open()
        self.recording = recorder is not None
        self.rec = recorder if recorder is not None else NullRecorder()
        self.rej = M.Rejections(f"controller {keys.id}", log)
        self.stats = ControllerStats()
        self.run_core = ControllerRun(lambda: [self.mpc], lambda: self.cfg.max_age_ms,
                                      counts=self.stats, recorder=recorder)
        self.stop = threading.Event()
        self._event = threading.Event()
        self._lock = threading.Lock()
        self._pending = None  # (state dict, rx_perf)
        self._held = None  # newest state received while the plant's token was not seen
        self._plant_presence = None  # the Presence of the plant's token (open())
        self._fallback = False  # present because its states arrive, its token never seen
        self._last_state_rx = 0.0  # time.monotonic() of the last valid state
        self._pending_ref = None  # decoded reference message
        self._again = None  # (state, command): a held state, solved, to answer later
        self._last_seq: int | None = None
        self._sent: tuple[int, bytes] | None = None  # (state seq, payload) of the last command
        self._solved = None  # (state seq, command) of the last solve
        self.plant_present = False
        self.plant_seen = False
        self.exit_reason: str | None = None
        self._pub = None
        self._decls: list = []
        self._token = None
        # ownership: the plant session we are bound to, and whether it grants us the vehicle
        self.plant_zid = plant_zid
        self._rebind = rebind  # fetches the params again; returns the new plant's zid
        self.granted = False
        self.grant_reason: str | None = None  # the plant's newest answer to our claim
        self._claim_wake = threading.Event()
        self._closing = threading.Event()
        self._claimer: threading.Thread | None = None
        self.loss = LossTimer(LOSS_CONFIRM_S)
        # the grant's key (bridge.link_key): our key pair, and the keys derived with the
        # bound plant's key (None: not granted yet, or a plant that sends no key)
        self._keys = KeyPair()
        self._link: LinkKeys | None = None
        self._send_pk = True  # False: the plant refused the field (older than the key)
        self._link_top = -1  # the newest state seq taken under the current key

    # ---- transport ---------------------------------------------------------------------
    def open(self, transport: Transport) -> None:
        """Declare on ``transport`` the cmd publisher, the state and reference subscribers,
        the token, and start claiming the vehicle."""
        t, k = transport, self.keys
        self.transport = t
        log.info("controller identity %s (%s)", t.id, "its certificate's common name"
                 if t.authenticated else "the session id: self-declared on a plain bus")
        if self.plant_zid is not None:
            self._watch_plant(self.plant_zid)
        self._pub = t.publisher(k.cmd)
        self._decls.append(t.subscribe(k.state, self._on_state_sample))
        if not self._takes_references() and self.cfg.bus_references == "auto":
            log.info("references from the bus are not taken (a plain bus: anyone could send "
                     "one); --bus-references on takes them, --secure authenticates them")
        self._decls.append(t.subscribe(k.reference,
                                       lambda smp: self.handle_reference(smp.payload)))
        # the token, then the claim: a plant that grants us the vehicle finds our token and
        # our state subscriber declared
        self._token = t.declare_token(k.controller_token(t.id))
        self._claimer = threading.Thread(target=self._claim_loop, daemon=True,
                                         name=f"claim {k.id}")
        self._claimer.start()

    def _watch_plant(self, zid: str) -> None:
        """Bind to the plant session ``zid``: its token is the plant's presence."""
        self.plant_zid = zid
        self._plant_presence = Presence(self.transport, self.keys.plant_token(zid),
                                        self._on_plant_token)
        self._decls.append(self._plant_presence)
        log.info("bound to plant session %s", zid)

    def _unbind(self) -> None:
        pres = self._plant_presence
        if pres is not None:
            pres.close()
            if pres in self._decls:
                self._decls.remove(pres)
        self._plant_presence = None
        self.plant_zid = None
        self.granted, self.grant_reason = False, None
        self._link = None
        self.plant_present, self.plant_seen, self._fallback = False, False, False
        with self._lock:
            self._pending = self._held = None
        self.loss.reset()

    # ---- ownership ---------------------------------------------------------------------
    def _claim_loop(self) -> None:
        """Claim the vehicle from the bound plant (every CLAIM_RETRY_S until granted, then
        every CLAIM_REFRESH_S, so a lost grant is noticed); with ``--vehicle`` (no params),
        the one plant that answers the claim is the one we bind to."""
        n = 0
        while not self._closing.is_set():
            bound = self.plant_zid
            if bound is None and self._rebind is not None:
                # between two plants (the next one's params not fetched yet): a claim now
                # would make the next plant grant us the vehicle and publish its first
                # state before we are bound to it, a state we would reject (not_bound)
                self._claim_wake.wait(CLAIM_RETRY_S)
                self._claim_wake.clear()
                continue
            try:
                link = self._link
                replies = claim(self.transport, self.keys, n, to=bound, wheel_wear=True,
                                pk=self._keys.public if self._send_pk else None,
                                mac_key=None if link is None else link.cmd)
            except Exception as e:  # the transport is closing
                log.debug("claim failed: %s", e)
                replies = []
            n += 1
            if bound is None and self._rebind is None:
                plants = sorted({z for z, g in replies if g is not None})
                if len(plants) == 1:
                    self._watch_plant(plants[0])
                    bound = plants[0]
                elif len(plants) > 1:
                    log.warning("%d plants answer the claim for vehicle %s (%s): binding to "
                                "none", len(plants), self.keys.id, ", ".join(plants))
            for z, g in replies:
                if bound is not None and z == bound and g is not None:
                    self._last_state_rx = time.monotonic()  # the plant answered: alive
                    if not self.plant_present and self._plant_presence is not None:
                        self._fallback = True
                        self._on_plant_change(True, via="claims")
                    if g["reason"] == BAD_CLAIM and self._send_pk:
                        # a plant older than the grant's key refuses the field: claim
                        # without it (its commands then go without a mac)
                        self._send_pk = False
                        log.warning("plant %s refuses the claim's key (a plant older than "
                                    "docs/PROTOCOL.md 3.9): claiming without it", z)
                        self._claim_wake.set()
                        continue
                    if g["granted"] and not self._take_key(z, g.get("pk")):
                        continue
                    self._set_granted(g["granted"], g["reason"])
            wait = CLAIM_REFRESH_S if self.granted else CLAIM_RETRY_S
            self._claim_wake.wait(wait)
            self._claim_wake.clear()

    def _take_key(self, plant: str, pk: bytes | None) -> bool:
        """The grant's key, derived with the plant's key of its grant (a plant that sends
        none: commands without a mac, states taken without one). False: the plant's key is
        not usable (the grant is not taken)."""
        link = self._link
        if pk is None:
            if link is not None:
                log.warning("plant %s granted the vehicle without its key: commands go "
                            "without a mac", plant)
            self._link = None
        elif link is None or link.peer_pk != pk:
            try:
                self._link = derive(self._keys, pk, self.keys.id, plant, self.transport.id)
                self._link_top = -1
            except LinkKeyError as e:
                log.warning("plant %s's key is not usable (%s): not commanding", plant, e)
                self._link = None
                self._set_granted(False, "bad key")
                return False
        return True

    def _mac_error(self, st: dict) -> M.MessageError | None:
        """None if the state carries the grant's mac (or no key is agreed yet), else its
        ``bad_mac`` rejection."""
        link = self._link
        why = None if link is None else LinkKeys.fault(link.state, st)
        if why is None:
            return None
        return M.MessageError(M.BAD_MAC, f"state {st.get('seq')} from {self.plant_zid}: "
                                         f"{why} (the plant's states carry the grant's mac)")

    def _set_granted(self, granted: bool, reason: str) -> None:
        was, self.granted = self.granted, granted
        told, self.grant_reason = self.grant_reason, reason
        if granted and not was:
            log.info("vehicle %s granted by plant %s", self.keys.id, self.plant_zid)
            with self._lock:  # a state that arrived before the grant's reply
                if self._held is not None and self._pending is None and self.plant_present:
                    self._pending, self._held = self._held, None
            self._event.set()
        if not granted:
            self._link = None  # the plant signs its states for its new owner, or nobody
        if was and not granted:
            log.warning("plant %s no longer grants vehicle %s to this controller (%s): "
                        "not commanding", self.plant_zid, self.keys.id, reason)
        if not granted and reason != told:
            if reason == LATCHED:
                log.warning("vehicle %s is latched (it lost its controller): an operator "
                            "re-arms it for this controller with: msagv arm --id %s "
                            "--controller %s", self.keys.id, self.keys.id, self.transport.id)
            else:
                log.info("vehicle %s not granted: %s; claiming again every %g s", self.keys.id,
                         reason, CLAIM_RETRY_S)
        if granted != was or reason != told:
            self.rec.event("granted", granted=granted, reason=reason)

    def close(self) -> None:
        self._closing.set()
        self._claim_wake.set()
        if self.granted:
            try:  # hand the vehicle back at once (the plant also notices our token going)
                link = self._link
                claim(self.transport, self.keys, 0, RELEASE, timeout=0.3,
                      pk=self._keys.public if self._send_pk else None,
                      mac_key=None if link is None else link.cmd)
            except Exception:
                pass
            self.granted = False
        close_all([self._token] + self._decls + [self._pub])
        self._token, self._decls, self._pub = None, [], None

    def _on_plant_token(self, present: bool) -> None:
        """The bound plant's token appeared or was lost. A loss reported while the plant
        still shows signs of life (a state or a claim answer within FALLBACK_LOSS_S) is not
        believed: zenoh once in a while reported a live plant's token gone under CPU load
        (the link up, the token then unanswered by queries); the plant's silence decides."""
        if not present and time.monotonic() - self._last_state_rx < FALLBACK_LOSS_S:
            if not self._fallback:
                log.info("plant %s: token reported gone, but the plant answered %.2f s ago: "
                         "its silence decides (%g s)", self.keys.id,
                         time.monotonic() - self._last_state_rx, FALLBACK_LOSS_S)
            self._fallback = True
            return
        self._on_plant_change(present)

    def _on_plant_change(self, present: bool, via: str = "token") -> None:
        if via == "token":
            self._fallback = False
        self.plant_present = present
        if present:
            self._claim_wake.set()  # (re)appeared: claim at once (a lost grant is renewed)
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
        self.rec.event("plant_alive", present=present)
        self._event.set()

    def check_fallback_loss(self, now: float) -> None:
        """A plant known only by its states is gone after FALLBACK_LOSS_S without one."""
        if self._fallback and self.plant_present and now - self._last_state_rx > FALLBACK_LOSS_S:
            self._on_plant_change(False, via="states")

    # ---- incoming ----------------------------------------------------------------------
    def _on_state_sample(self, sample: Sample) -> None:
        sender = sample.sender
        if sender is None or sender != self.plant_zid:  # counted and dropped first
            self.rej.add_reason(M.NOT_BOUND, self.keys.state, lambda: self._not_bound(sender))
            self.rec.message("rx", self.keys.state, sample.payload, why=M.NOT_BOUND)
            return
        self.handle_state(sample.payload, time.perf_counter(), sender)

    def _not_bound(self, sender: str | None) -> str:
        who = sender or "a sender without identity (protocol version 1)"
        return f"from {who}; bound to plant {self.plant_zid or '(none yet)'}"

    def handle_state(self, payload: bytes, rx_perf: float, sender: str | None) -> dict | None:
        """Validate a state; the newest valid one is solved next. Returns it, or None.
        ``sender``: the sender's identity (None: the message carried none); a state not
        from the bound plant is rejected as ``not_bound``."""
        key = self.keys.state
        try:
            if sender is None or sender != self.plant_zid:
                raise M.MessageError(M.NOT_BOUND, self._not_bound(sender))
            st = M.decode_state(payload, self.nw)
            bad = self._mac_error(st)
            if bad is not None:
                raise bad
        except M.MessageError as e:
            self.rej.add(e, key)
            self.rec.message("rx", key, payload, why=e.reason)
            return None
        if self._link is not None:
            # a signed state older than one taken under the same key is a replay (a plant
            # starts a new run under a new key): never a new run of the MPC
            if st["seq"] < self._link_top:
                self.stats.replayed += 1
                self.rec.message("rx", key, payload, why="replayed")
                return None
            self._link_top = st["seq"]
        self.rec.message("rx", key, payload)
        self._last_state_rx = time.monotonic()
        pres = self._plant_presence
        if not self.plant_present and pres is not None:
            # Zenoh did not deliver the plant's token to this session (seen in a mesh of
            # peers with gossip off: the token neither arrived nor answered a query), or
            # reported it gone while the plant (bound, by its session id) still sends its
            # states (seen under CPU load: a DELETE while the link stayed up): the states
            # are the evidence of presence, and their silence (FALLBACK_LOSS_S) the
            # evidence of loss, until the token shows up again
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

    def _takes_references(self) -> bool:
        """Whether this node takes references from its bus (:attr:`ControllerConfig.
        bus_references`; not before :meth:`open`)."""
        t = self.transport
        return self.cfg.takes_references(t is not None and t.authenticated)

    def handle_reference(self, payload: bytes) -> dict | None:
        key = self.keys.reference
        try:
            if not self._takes_references():
                raise M.MessageError(M.REFERENCES_OFF, "this controller takes no reference "
                                     "from the bus (--bus-references; a plain bus: anyone "
                                     "could send one)")
            m = M.decode_reference(payload)
            from msagv.controller.reference import ReferenceError, from_samples

            try:  # checked here, so a bad one is rejected on arrival
                from_samples(m["t"], m["x"], m["y"], m["phi"])
            except ReferenceError as e:
                raise M.MessageError(M.BAD_VALUE, str(e)) from None
        except M.MessageError as e:
            self.rej.add(e, key)
            self.rec.message("rx", key, payload, why=e.reason)
            return None
        self.rec.message("rx", key, payload)
        with self._lock:
            self._pending_ref = m
        self._event.set()
        return m

    # ---- the loop ----------------------------------------------------------------------
    def run(self) -> dict:
        """Answer states until stopped (or the end, or the plant's loss, as configured)."""
        while not self.stop.is_set():
            now = time.monotonic()
            self.check_fallback_loss(now)
            if self.plant_seen and self.loss.update(now, self.plant_present) == LOST:
                self._plant_lost()
            self._event.wait(0.05)
            self._event.clear()
            with self._lock:
                item, self._pending = self._pending, None
            if item is None:
                self.rec.maybe_flush()
                continue
            if self.step(*item) == "end" and self.cfg.exit_at_end:
                self.exit_reason = "end of run"
                break
            self.rec.maybe_flush()
        if self.exit_reason is None:
            self.exit_reason = "stopped"
        return self.summary()

    def _plant_lost(self) -> None:
        """The bound plant is confirmed lost: exit, or wait for a plant and bind to it."""
        zid = self.plant_zid
        if self.cfg.on_plant_loss == "exit":
            self.exit_reason = "plant gone"
            raise ControllerRunError(
                f"plant '{self.keys.id}' gone (its liveliness token {self.keys.plant_token(zid)} "
                f"disappeared and no state came for {self.loss.confirm_s:g} s); exiting "
                f"(--on-plant-loss exit)")
        log.warning("plant %s (session %s) lost: waiting for a plant to bind to", self.keys.id, zid)
        self.rec.event("plant_lost", zid=zid)
        self._unbind()
        if self._rebind is not None:
            new = self._rebind()  # blocks until a plant answers (or stop)
            if new is not None and not self.stop.is_set():
                self._watch_plant(new)
        self._claim_wake.set()

    def step(self, st: dict, rx_perf: float) -> str:
        """Solve for one state and send the command. Returns 'sent', 'resent' (the same
        command again for a state sent again), 'end', 'duplicate', 'stale', 'no plant' or
        'not granted'."""
        bad = self._mac_error(st)
        if bad is not None:
            # a state taken before the grant's key came, without its mac
            self.rej.add(bad, self.keys.state)
            return "bad_mac"
        seq = st["seq"]
        last = self._last_seq
        held = self._again
        again = held is not None and st is held[0]  # a held state, solved before, answered now
        if again:
            self._again = None
        # a state solved before is answered with the command computed then: a second solve
        # would start from the first one's warm start (no longer the in-process run's)
        reuse = held[1] if again else None
        if last is not None and seq == last and not again:
            sent = self._sent
            if st.get("end") or sent is not None and sent[0] == seq:
                if st.get("end") or not (self.granted and self.plant_present):
                    self.stats.duplicates += 1
                    return "duplicate"
                # the plant sent this state again: our answer was lost (a lockstep plant
                # re-sends an unanswered state); the same command again, not a new solve
                self._pub.put(sent[1], self.run_core.cmd_seq - 1)
                self.stats.resent += 1
                self.rec.message("tx", self.keys.cmd, sent[1])
                return "resent"
            # never answered (dropped while the plant was away, or not granted): answer it
            solved = self._solved
            if solved is not None and solved[0] == seq:
                reuse = solved[1]
        if reuse is None and (last is None or seq == 0 or seq < last):
            # a new plant run (or the first state seen): forget the warm start and reseed,
            # as closed_loop does after its warm-up
            if last is not None:
                log.info("new plant run (state seq %d after %d): MPC reset", seq, last)
            self.run_core.new_run(seq=seq)
        self._last_seq = seq
        if st.get("end"):
            self.stats.ends += 1
            log.info("end of the run at t = %.2f s (state %d)", st["t"], seq)
            return "end"
        with self._lock:
            ref_msg, self._pending_ref = self._pending_ref, None
        if ref_msg is not None:
            self._set_reference(ref_msg, st["t"])
        if reuse is not None:
            cmd = reuse
        else:
            cmd = self.run_core.solve(self.mpc, st)
            self._solved = (seq, cmd)
        if self.run_core.too_old(rx_perf):
            return "stale"
        if not self.plant_present:
            self.stats.ignored_no_plant += 1
            if self.stats.ignored_no_plant <= 3:
                log.warning("state %d solved but not answered: the plant is not present", seq)
            self._hold(st, rx_perf, cmd)  # answered if the plant shows up again
            return "no plant"
        if not self.granted:
            self.stats.not_granted += 1
            if self.stats.not_granted <= 3:
                # nobody owns it yet: our claim's answer is on its way (the plant publishes
                # its first state as it grants); another owner: we are not driving
                log.info("state %d solved but not answered: the plant does not grant us the "
                         "vehicle (%s)", seq, self.grant_reason or "no answer to our claim yet")
            # answered once the grant comes: the plant publishes its first state as soon
            # as it grants, which can arrive before the grant's reply
            self._hold(st, rx_perf, cmd)
            return "not granted"
        link = self._link
        payload = self.run_core.encode(st, seq, cmd, None if link is None else link.cmd)
        self._pub.put(payload, self.run_core.cmd_seq)
        self._sent = (seq, payload)
        # recorded: the command, and the horizon as the ROS 2 channel predicted_path
        self.run_core.sent(self.mpc, st, self.keys.cmd, payload)
        return "sent"

    def _hold(self, st: dict, rx_perf: float, cmd) -> None:
        """Keep a solved but unanswered state, with its command, to answer later (unless a
        newer one came); ``--max-age-ms`` still drops it if it is too old by then."""
        with self._lock:
            if self._held is None and self._pending is None:
                self._again = (st, cmd)
                if self.granted and self.plant_present:
                    # the grant (or the plant) came while this state was being solved
                    self._pending = (st, rx_perf)
                    self._event.set()
                else:
                    self._held = (st, rx_perf)

    def _set_reference(self, m: dict, t_now: float) -> None:
        from msagv.controller.reference import from_samples

        t = np.asarray(m["t"], dtype=float)
        if m.get("relative"):
            t = t + t_now
        ref = from_samples(t, m["x"], m["y"], m["phi"], name=m.get("name", "bus-reference"))
        self.mpc.set_reference(ref)
        self.stats.references += 1
        log.info("new reference '%s' (%d samples, t %.2f..%.2f s) from t = %.2f s", ref.name,
                 len(t), t[0], t[-1], t_now)
        self.rec.event("reference", t=t_now, name=ref.name)

    def summary(self) -> dict:
        s = self.stats
        return {"role": "controller", "id": self.keys.id, "answered": s.answered,
                "solve_ms": percentiles_ms(np.asarray(s.solve_ms) / 1000.0),
                "skipped": s.skipped, "duplicates": s.duplicates, "new_runs": s.new_runs,
                "replayed": s.replayed,
                "dropped_stale": s.dropped_stale, "ignored_no_plant": s.ignored_no_plant,
                "not_granted": s.not_granted, "resent": s.resent, "plant_zid": self.plant_zid,
                "grant": self.grant_reason,
                "loss": {"state": self.loss.state, "suspicions": self.loss.suspicions,
                         "stalls": self.loss.stalls},
                "references": s.references, "ends": s.ends, "rejected": self.rej.summary(),
                "exit_reason": self.exit_reason,
                "solver": self.mpc.name,
                "budget": self.mpc.budget(),
                # the offset-free disturbance and the adapted tires at the end (None: off)
                "disturbance": mpc_estimate(self.mpc, "disturbance"),
                "adapted_tires": mpc_estimate(self.mpc, "adapted_tires"),
                "settings": dataclasses.asdict(self.mpc.settings)}


def mpc_estimate(mpc, name: str):
    """A controller's estimate by name (``MPC.disturbance``, ``MPC.adapted_tires``); None
    where the controller has none."""
    fn = getattr(mpc, name, None)
    return fn() if fn is not None else None


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
    a realtime plant ``REALTIME_DEADLINE_MS`` and the plant's default staleness bound
    (:data:`bridge.loss.STALE_MS`) unless given; in lockstep only what is given."""
    if run_mode == "realtime":
        return (REALTIME_DEADLINE_MS if deadline_ms is None else deadline_ms,
                STALE_MS if max_age_ms is None else max_age_ms)
    return deadline_ms, max_age_ms


CONFIRM_S = 0.3  # s: a lone plant's answer is confirmed by a second query this much later


def fetch_params(transport: Transport, keys: Keys, wait_s: float, stop: threading.Event
                 ) -> tuple[dict, str]:
    """The plant's params (validated) and the identity of the plant that answered,
    retrying until ``wait_s`` (0: forever). Answers from two or more identities are refused
    (a second plant, or a rogue, on the same vehicle id): nothing is bound, and the query
    is repeated. Error replies (which name nobody) do not count as answers. On a plain bus
    the answer is taken on trust (logged, and said in ``--help``); with ``--secure`` only a plant
    certificate of this vehicle can answer (the access control). A single answer binds only
    when the next query, :data:`CONFIRM_S` later, is answered by the same plant alone: a
    session connecting to several endpoints may ask before its second link is up, and must
    not bind to one plant of two."""
    t0 = time.monotonic()
    told = False
    last_err = None
    single = None  # the plant that alone answered the last query
    while not stop.is_set():
        try:
            good: dict[str, dict] = {}
            for zid, payload in params_replies(transport, keys, timeout=1.0):
                try:
                    m = M.decode_params(payload)
                except M.MessageError as e:
                    last_err = f"bad params reply from {zid}: {e}"
                    log.warning("%s", last_err)
                    continue
                if zid is None:
                    last_err = "a params reply without the replier's id"
                    continue
                good.setdefault(zid, m)
            if len(good) == 1 and single != next(iter(good)):
                single = next(iter(good))  # asked again before binding
                stop.wait(CONFIRM_S)
                continue
            if len(good) == 1:
                (zid, m), = good.items()
                if transport.authenticated:
                    log.info("params from plant %s (its certificate's common name, checked by "
                             "the bus's access control)", zid)
                else:
                    # what the plain bus promises is said once, in --help (--secure) and
                    # docs/SECURITY.md, not as a warning on every run that went right
                    log.info("params from plant %s (plain bus: taken on trust, see --secure)",
                             zid)
                return m, zid
            single = None
            if len(good) > 1:
                last_err = (f"{len(good)} plant sessions answer {keys.params}/*/{transport.id} "
                            f"({', '.join(sorted(good))}): binding to none")
                log.warning("%s", last_err)
        except Exception as e:
            last_err = str(e)
        if wait_s and time.monotonic() - t0 > wait_s:
            raise ControllerRunError(
                f"no plant answered on {keys.params}/*/{transport.id} within {wait_s:g} s"
                f"{' (' + last_err + ')' if last_err else ''}; start msagv plant --id {keys.id} "
                f"with matching --connect/--listen, or give --vehicle FILE")
        if not told:
            log.info("waiting for the plant's params on %s/*/%s", keys.params, transport.id)
            told = True
        stop.wait(0.1)
    raise ControllerRunError("stopped while waiting for the plant's params")


class SetupError(ValueError):
    """The controller cannot be built for this plant (e.g. its params name a vehicle the
    scenario cannot use); nothing ran (exit 2)."""


def _plant_params(transport: Transport, keys: Keys, wait_s: float, stop: threading.Event
                  ) -> tuple[PlantParams, dict, str]:
    """The params of the one plant that answers (:func:`fetch_params`), with its vehicle
    built: ``(params, the raw params message, the plant's identity)``."""
    from msagv.plant.vehicle import VehicleError, vehicle_from_dict

    p, plant_zid = fetch_params(transport, keys, wait_s, stop)
    try:
        vehicle = vehicle_from_dict(p["vehicle"])
    except VehicleError as e:
        raise ControllerRunError(f"the plant's params: vehicle: {e}") from None
    params = PlantParams(vehicle, p["period"], p["run_mode"])
    log.info("plant params: %s, %d wheels, T = %g s, %s", vehicle.name, vehicle.n_wheels,
             params.period, params.run_mode)
    return params, p, plant_zid


def _warm_up(mpc, on_signal_install: Callable[[], None] | None) -> float:
    """Compile the MPC (then reset its warm start and RNG); returns the seconds it took.
    SIGTERM acts at once meanwhile (compiling cannot be interrupted from Python); the
    caller's handlers come back after."""
    t0 = time.perf_counter()
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    mpc.warmup()
    if on_signal_install is not None:
        on_signal_install()
    return time.perf_counter() - t0


def _rebinder(transport: Transport, keys: Keys, p: dict, stop: threading.Event
              ) -> Callable[[], str | None]:
    """What the node calls after the loss of its plant: the identity of the plant that
    answers the params next (None: stopped), or exit 3 if its params differ from ``p``."""

    def rebind() -> str | None:
        try:
            q, zid = fetch_params(transport, keys, 0.0, stop)
        except ControllerRunError:
            return None  # stopped
        if q != p:
            raise ControllerRunError(
                f"the plant now answering {keys.params}/{zid}/{transport.id} has other params "
                f"than the one this controller was built for; restart the controller")
        return zid

    return rebind


def serve(opts: SessionOptions, make_mpc: Callable[[PlantParams | None], object],
          cfg: ControllerConfig, *, fetch: bool = True, wait_s: float = 60.0,
          open_recorder: Callable[[object, PlantParams | None], object] | None = None,
          stop: threading.Event | None = None, on_signal_install: Callable[[], None] | None = None,
          transport: Transport | None = None) -> tuple[dict, int]:
    """Run the controller process: open the Zenoh session, fetch the plant's params (unless
    ``fetch`` is False: the caller's vehicle is used), build the MPC with
    ``make_mpc(params)``, warm it up, answer states until stopped, close everything.

    ``make_mpc`` raises :class:`SetupError` (or ValueError) for a scenario that cannot be
    built: exit 2. ``open_recorder(mpc, params)`` returns a Recorder or None (closed here,
    with the summary). ``cfg.max_age_ms`` None takes :func:`realtime_defaults`' bound for
    the plant's run mode. ``on_signal_install`` installs the caller's signal handlers once
    the session is open, and again after the warm-up (compiling cannot be interrupted from
    Python, so SIGTERM acts at once meanwhile). ``transport``: an open transport to run on
    instead of the Zenoh session of ``opts`` (the caller closes it). Returns
    ``(summary, exit code)``.
    """
    keys = Keys(opts.id)
    stop = stop or threading.Event()
    rec = None
    node = None
    rc = EXIT_OK
    summary: dict = {"role": "controller", "id": keys.id}
    try:
        with (nullcontext(transport) if transport is not None
              else ZenohTransport.open(opts, "controller")) as t:
            if on_signal_install is not None:
                on_signal_install()
            params = p = plant_zid = None
            if fetch:
                params, p, plant_zid = _plant_params(t, keys, wait_s, stop)
            try:
                mpc = make_mpc(params)
            except ValueError as e:
                log.error("%s", e)
                return dict(summary, error=str(e)), EXIT_USAGE
            if cfg.max_age_ms is None:
                cfg = dataclasses.replace(cfg, max_age_ms=realtime_defaults(
                    params.run_mode if params else None, None, None)[1])
            warm_s = _warm_up(mpc, on_signal_install)
            if stop.is_set():
                return summary, EXIT_OK
            s = mpc.settings
            log.info("MPC warm (%.2f s): %s %s, %s, seed %d", warm_s, s.method, s.model,
                     mpc.name, s.seed)
            if open_recorder is not None:
                rec = open_recorder(mpc, params)
            node = ControllerNode(mpc, keys, cfg, recorder=rec, plant_zid=plant_zid,
                                  rebind=_rebinder(t, keys, p, stop) if fetch else None)
            node.stop = stop
            freeze_heap()
            node.open(t)
            log.info("controller ready: states on %s/*, commands on %s/%s", keys.state,
                     keys.cmd, t.id)
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
