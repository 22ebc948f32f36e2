"""Who drives the vehicle: one controller owns it, a lost owner latches it until an operator
re-arms it, and each controller is bound to one plant (docs/PROTOCOL.md, "Ownership").

Identity is the transport's (:class:`bridge.transport.Transport`: ``id``, a message's
``sender``, a query's ``sender``, a reply's ``sender``), never a message's: on Zenoh it
travels in the key (the session id on a plain bus; with ``--secure`` the certificate's
common name, which Zenoh's access control lets only that certificate use). The holder of a
liveliness token is the last chunk of its key (``alive/controller/{identity}``).

* The plant (:class:`Ownership`) grants the vehicle to the first controller that claims it
  (a query on ``msagv/{id}/claim``) while the vehicle is free, applies commands only from
  that identity (others are rejected as ``not_owner``, and an identity that commands while
  another owns the vehicle is never granted it), counts only its token as the controller's
  presence, and never tells anyone else who the owner is. Once the run has started, the
  loss of the owner (its token gone) or its release **latches** the vehicle: no claim is
  granted until an operator re-arms it (:meth:`Ownership.arm`, ``msagv arm``), naming the
  controller that may claim it next or nobody (then the first claim wins), or, with a
  configured :class:`RearmPolicy` ``same:N``, until the lost owner's own identity claims
  again N periods after the latch.
* The controller binds to the one plant that answers its ``params`` (two different
  answers: it binds to neither), takes states only from that plant (others: ``not_bound``),
  claims only from it, and commands only while it grants it the vehicle.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass

from msagv.plant.signals import CONTROL_PERIOD

from . import messages as M

log = logging.getLogger("msagv.bridge")

CLAIM, RELEASE = "claim", "release"
VERSION = 2  # the schema version of the claim, grant, arm and armed maps
CLAIM_REQUIRED = {"v": "int", "action": "str"}
# pk: the claimer's key; mac: the owner's proof of it (bridge.link_key)
CLAIM_OPTIONAL = {"wheel_wear": "bool", "pk": "bin", "mac": "bin"}
GRANT_REQUIRED = {"v": "int", "granted": "bool", "reason": "str"}
GRANT_OPTIONAL = {"pk": "bin"}  # the plant's key, in a grant to a claim that carried one
ARM_REQUIRED = {"v": "int"}
ARM_OPTIONAL = {"controller": "str"}
ARMED_REQUIRED = {"v": "int", "armed": "bool", "reason": "str"}
MAX_CLAIM_BYTES = 1024
MAX_IDENTITY = 64  # an identity: a Zenoh session id (32 hex digits) or a certificate's
# common name (at most 64 characters, X.509's upper bound)
_IDENTITY = re.compile(r"^[A-Za-z0-9_.\-]+$")
MAX_BANNED = 1024
GRANT_TOKEN_S = 3.0  # a grant whose owner never shows its token is void after this long
CLAIM_RETRY_S = 0.25  # the controller's claim period while not granted
CLAIM_REFRESH_S = 1.0  # ... and while granted (it learns of a lost grant within this)

# the grant's reasons (docs/PROTOCOL.md section 3.7)
GRANTED = "granted"  # the claimer owns the vehicle (a new grant, or a repeated claim)
RELEASED = "released"  # the answer to its owner's release
NOT_YOURS = "not_owner"  # a release by a controller that does not own the vehicle
OWNED = "owned"  # another controller owns the vehicle
LATCHED = "latched"  # the vehicle lost its owner: an operator must re-arm it
ARMED_FOR_ANOTHER = "armed_for_another"  # re-armed for another controller
BANNED = "banned"  # this identity commanded while another owned the vehicle
BAD_CLAIM = "bad_claim"  # the claim map was malformed (counted by its reason)
KEY_MISMATCH = "key_mismatch"  # a claim as the owner with a key that is not the grant's
GRANT_REASONS = (GRANTED, RELEASED, NOT_YOURS, OWNED, LATCHED, ARMED_FOR_ANOTHER, BANNED,
                 BAD_CLAIM, KEY_MISMATCH)
# the arm reply's reasons
ARMED, ARM_OWNED, BAD_ARM = "armed", "owned", "bad_arm"

# the vehicle's handover states
FREE, OWNED_STATE, LATCHED_STATE, ARMED_STATE = "free", "owned", "latched", "armed"


# ---- messages ------------------------------------------------------------------------------
def encode_claim(action: str = CLAIM, wheel_wear: bool | None = None,
                 pk: bytes | None = None, mac_key: bytes | None = None) -> bytes:
    """A claim map; ``mac_key``: the grant's command key, which the owner signs its
    claims and its release with (:mod:`bridge.link_key`)."""
    m = {"v": VERSION, "action": action}
    if wheel_wear is not None:
        m["wheel_wear"] = bool(wheel_wear)
    if pk is not None:
        m["pk"] = bytes(pk)
    return M._signed(m, mac_key)


def _versioned(payload, required: dict, optional: dict) -> dict:
    m = M.unpack(payload, MAX_CLAIM_BYTES)
    v = m.get("v")
    if isinstance(v, bool) or not isinstance(v, int) or v != VERSION:
        raise M.MessageError(M.VERSION_MISMATCH, f"schema version v = {v!r}, this side speaks "
                                                 f"{VERSION} for claims and grants")
    return M.fields(m, required, optional, None, version=VERSION)


def decode_claim(payload) -> dict:
    """A ``claim`` map: ``{"action": "claim" | "release", "wheel_wear": bool (optional)}``."""
    m = _versioned(payload, CLAIM_REQUIRED, CLAIM_OPTIONAL)
    if m["action"] not in (CLAIM, RELEASE):
        raise M.MessageError(M.BAD_VALUE, f"action '{m['action']}' is not claim or release")
    return m


def encode_grant(granted: bool, reason: str, pk: bytes | None = None) -> bytes:
    m = {"v": VERSION, "granted": bool(granted), "reason": reason}
    if pk is not None:
        m["pk"] = bytes(pk)
    return M.pack(m)


def decode_grant(payload) -> dict:
    return _versioned(payload, GRANT_REQUIRED, GRANT_OPTIONAL)


def encode_arm(controller: str | None = None) -> bytes:
    m = {"v": VERSION}
    if controller is not None:
        m["controller"] = controller
    return M.pack(m)


def identity_error(name) -> str | None:
    """Why ``name`` cannot be an identity (None: it can): one key chunk of
    ``A-Z a-z 0-9 _ . -``, 1 to MAX_IDENTITY characters, as a session id or a
    certificate's common name is."""
    if not isinstance(name, str):
        return f"{type(name).__name__} is not a name"
    if not name:
        return "an empty name"
    if len(name) > MAX_IDENTITY:
        return f"{len(name)} characters (an identity has at most {MAX_IDENTITY})"
    if not _IDENTITY.match(name):
        return (f"'{name}' is not one key chunk of A-Z a-z 0-9 _ . - (no wildcard, no "
                f"'/')")
    return None


def decode_arm(payload) -> dict:
    """An ``arm`` map; a ``controller`` it names must be an identity (:func:`identity_error`):
    an arm for "", "*" or a 900-character name would hold the vehicle for nobody."""
    m = _versioned(payload, ARM_REQUIRED, ARM_OPTIONAL)
    if "controller" in m:
        why = identity_error(m["controller"])
        if why is not None:
            raise M.MessageError(M.BAD_VALUE, f"arm: controller: {why}")
    return m


def encode_armed(armed: bool, reason: str) -> bytes:
    return M.pack({"v": VERSION, "armed": bool(armed), "reason": reason})


def decode_armed(payload) -> dict:
    return _versioned(payload, ARMED_REQUIRED, {})


# ---- the plant's side ----------------------------------------------------------------------
@dataclass(frozen=True)
class RearmPolicy:
    """How a latched vehicle may be driven again (``msagv plant --rearm``).

    ``manual`` (the default, strict): only an operator's arm (``msagv arm``).
    ``same:N``: besides, the identity that lost the vehicle may claim it again once N
    periods (N T of time, all of them safe in real time) have passed since the latch; any
    other identity still needs an arm.
    """

    same_after: int | None = None  # None: manual

    @classmethod
    def parse(cls, text: str) -> "RearmPolicy":
        if text == "manual":
            return cls()
        kind, _, n = text.partition(":")
        if kind == "same" and n.isdigit() and 1 <= int(n) <= 10 ** 6:
            return cls(int(n))
        raise ValueError(f"--rearm: expected manual or same:N (N periods, 1..1000000), "
                         f"got '{text}'")

    def __str__(self) -> str:
        return "manual" if self.same_after is None else f"same:{self.same_after}"


@dataclass
class Grant:
    """The plant's answer to a claim."""

    granted: bool
    reason: str


class Ownership:
    """The plant's owner and handover state (see the module). Thread-safe; ``on_change(owner,
    why)`` is called (outside the lock) whenever the owner changes, ``on_event(name,
    fields)`` on a latch and an arm (for the recording)."""

    def __init__(self, on_change=None, policy: RearmPolicy = RearmPolicy(),
                 period: float = CONTROL_PERIOD,
                 on_event=None, rekey: bool = False):
        self.owner: str | None = None
        # the key the owner's grant is bound to (bridge.link_key; None: its claim had none);
        # rekey: a claim as the owner may bring another key (identities are authenticated:
        # --secure; a restarted controller with the same certificate), else it is refused
        self.owner_pk: bytes | None = None
        self.lost_pk: bytes | None = None  # latched: the key of the lost owner's grant
        self.owner_link = None  # (owner, what the caller derived from pk), set with the grant
        self.rekey = rekey
        self.key_mismatches = 0
        self.state = FREE
        self.armed_for: str | None = None  # armed: the identity that may claim (None: any)
        self.lost: str | None = None  # latched: the identity that lost the vehicle
        self.latched_at = 0.0
        self.why: str | None = None  # latched: why
        self.started = False  # the run has started: a loss now latches the vehicle
        self.ended = False  # the end state is out: a release is the normal end, no latch
        self.owner_seen = False  # the owner's token has been seen since the grant
        self.wheel_wear = False  # the owner's newest granted claim asks for per-wheel wear
        self.granted_at = 0.0
        self._before_grant = (FREE, None)  # (state, armed_for) a void grant returns to
        self.policy = policy
        self.period = period
        self.on_change = on_change
        self.on_event = on_event
        self.grants = 0  # owners granted (a refresh by the owner is not counted)
        self.refused = 0  # claims refused
        self.releases = 0
        self.losses = 0  # owners whose token was lost
        self.latches = 0
        self.arms: list[dict] = []  # every accepted arm: {t, by, controller}
        self.banned: set[str] = set()  # identities that commanded while another owned it
        self._lock = threading.Lock()

    def start(self) -> None:
        """The run has started (state 0 published): from now on a lost owner latches."""
        with self._lock:
            self.started = True

    def end(self) -> None:
        """The run's end state is published: the owner's release from now on is the normal
        end of the run (the vehicle grants nothing more, but it is not a latch)."""
        with self._lock:
            self.ended = True

    def _end_ownership(self, why: str, now: float, released: bool = False) -> tuple:
        """(locked) The owner is gone: latched once the run has started, else free; a
        release after the end of the run ends it normally (no claim granted, no latch)."""
        prev, self.owner = self.owner, None
        self.lost_pk = self.owner_pk
        self.owner_pk, self.owner_link = None, None
        if self.ended and released:
            self.state, self.lost, self.why, self.armed_for = LATCHED_STATE, None, why, None
            self.latched_at = now
            return (None, f"the run ended normally and controller {prev} released the "
                          f"vehicle", ("released", {"why": why, "previous": prev}))
        if self.started:
            self.state, self.lost, self.latched_at, self.why = LATCHED_STATE, prev, now, why
            self.armed_for = None
            self.latches += 1
            return (None, f"{why}: vehicle latched until an operator re-arms it"
                          f"{'' if self.policy.same_after is None else f' or {prev} claims it again after {self.policy.same_after} periods'}",
                    ("latched", {"why": why, "previous": prev}))
        self.state, self.armed_for = FREE, None
        return None, f"{why} (before the run started: free)", None

    def _notify(self, changed) -> None:
        if changed is None:
            return
        owner, why, event = changed
        if event is not None and self.on_event is not None:
            self.on_event(*event)
        if self.on_change is not None:
            self.on_change(owner, why)

    def claim(self, who: str | None, action: str = CLAIM, now: float | None = None,
              token_present: bool = False, wheel_wear: bool | None = None,
              pk: bytes | None = None, link=None, proven: bool = False) -> Grant:
        """Handle a claim or release from identity ``who`` (``token_present``: its token is
        visible now; ``wheel_wear``: what the claim asks, taken with the grant; ``pk``: the
        claimer's key, that a new grant is bound to and a repeated claim must bring again
        (:attr:`owner_pk`); ``link``: what the caller derived from it, kept as
        :attr:`owner_link` ``(owner, link)`` with the grant, atomically; ``proven``: the
        claim carries a valid ``mac`` under the owner's command key: the owner's release
        needs it, and its claim to change anything)."""
        now = time.monotonic() if now is None else now
        changed = None
        with self._lock:
            if who is None:
                self.refused += 1
                return Grant(False, BAD_CLAIM)
            keyed = who == self.owner and self.owner_pk is not None and not self.rekey
            if who == self.owner and pk != self.owner_pk and not self.rekey or (
                    keyed and action == RELEASE and not proven):
                # the owner's identity with another key (or none), or its release without
                # the proof of its key: on a plain bus, a copied source info (the key
                # itself is public); never the owner's own controller
                self.key_mismatches += 1
                self.refused += 1
                return Grant(False, KEY_MISMATCH)
            if keyed and not proven:
                # the owner's key without its proof: the owner's claim before its grant's
                # reply reached it (it cannot sign yet), or a copy: told it is granted (the
                # plant's key is public), nothing changes
                return Grant(True, GRANTED)
            if action == RELEASE:
                if who != self.owner:
                    return Grant(False, NOT_YOURS)
                self.releases += 1
                changed = self._end_ownership(f"released by {who}", now, released=True)
                grant = Grant(False, RELEASED)
            elif self.owner == who:
                self.owner_seen = self.owner_seen or token_present
                if self.rekey:
                    self.owner_link = (who, link)
                    self.owner_pk = pk
                grant = Grant(True, GRANTED)
            else:
                if (self.owner is not None and not self.owner_seen
                        and now - self.granted_at > GRANT_TOKEN_S):
                    # the grant is void (its owner never showed its token): undo it
                    log.info("the grant to %s is void: no token within %g s", self.owner,
                             GRANT_TOKEN_S)
                    self.owner_link = None
                    self.owner = None
                    self.state, self.armed_for = self._before_grant
                grant = self._grant_or_refuse(who, now, token_present, pk, link)
                if grant.granted:
                    changed = (who, f"granted to {who}", None)
            if grant.granted and wheel_wear is not None:
                self.wheel_wear = wheel_wear
            if not grant.granted and action != RELEASE:
                self.refused += 1
        self._notify(changed)
        return grant

    def _grant_or_refuse(self, who: str, now: float, token_present: bool,
                         pk: bytes | None = None, link=None) -> Grant:
        """(locked) A claim by ``who``, who does not own the vehicle (the grant binds
        ``pk`` and ``link``: set before the owner, so that a reader without the lock that
        sees the new owner sees its key)."""
        if self.state == OWNED_STATE:
            return Grant(False, OWNED)
        if self.state == LATCHED_STATE:
            n = self.policy.same_after
            # (same:N: the lost owner's identity with the lost grant's key: a copied source
            # info alone does not make the same controller)
            if not (n is not None and who == self.lost and pk == self.lost_pk
                    and now - self.latched_at >= n * self.period - 1e-9):
                return Grant(False, LATCHED)
        elif self.state == ARMED_STATE and self.armed_for not in (None, who):
            return Grant(False, ARMED_FOR_ANOTHER)
        if who in self.banned and not (self.state == ARMED_STATE and self.armed_for == who):
            return Grant(False, BANNED)
        self._before_grant = (self.state, self.armed_for)
        self.owner_pk, self.owner_link = pk, (who, link)
        self.owner, self.state, self.armed_for = who, OWNED_STATE, None
        self.owner_seen, self.granted_at = token_present, now
        self.grants += 1
        return Grant(True, GRANTED)

    def token(self, who: str, present: bool, now: float | None = None, how: str = ""
              ) -> None:
        """A controller token appeared or was lost (confirmed; ``how``: by what, for the
        log)."""
        now = time.monotonic() if now is None else now
        changed = None
        with self._lock:
            if who != self.owner:
                return
            if present:
                self.owner_seen = True
            else:
                self.losses += 1
                changed = self._end_ownership(
                    f"owner {who} lost (its token is gone{': ' + how if how else ''})", now)
        self._notify(changed)

    def arm(self, by: str | None, controller: str | None = None, t: float | None = None
            ) -> tuple[bool, str]:
        """An operator's re-arm (``by``: its identity): the vehicle, latched or free, may be
        claimed by ``controller`` (None: by the first controller that claims it). Refused
        while a controller owns it."""
        with self._lock:
            if self.owner is not None:
                return False, ARM_OWNED
            self.state, self.armed_for, self.lost, self.why = ARMED_STATE, controller, None, None
            if controller is not None:
                self.banned.discard(controller)  # a deliberate act overrides the ban
            entry = {"t": t, "by": by, "controller": controller}
            self.arms.append(entry)
        if self.on_event is not None:
            self.on_event("armed", {"by": by, "controller": controller})
        return True, ARMED

    def violation(self, who: str | None) -> None:
        """Identity ``who`` sent a command while another owned the vehicle: it is never
        granted the vehicle by this plant (at most MAX_BANNED identities are kept)."""
        if who is None or who in self.banned or self.owner is None:
            return  # (reads without the lock: a flood of one sender costs no lock)
        with self._lock:
            if who is not None and self.owner is not None and who != self.owner \
                    and len(self.banned) < MAX_BANNED:
                if who not in self.banned:
                    log.warning("%s commanded the vehicle owned by %s: it will not be granted "
                                "the vehicle", who, self.owner)
                self.banned.add(who)

    def accepts(self, who: str | None) -> bool:
        return who is not None and who == self.owner  # (one read: atomic under the GIL)

    def summary(self) -> dict:
        with self._lock:
            return {"state": self.state, "owner": self.owner, "armed_for": self.armed_for,
                    "grants": self.grants, "refused": self.refused, "releases": self.releases,
                    "losses": self.losses, "latches": self.latches, "arms": list(self.arms),
                    "banned": len(self.banned), "rearm": str(self.policy),
                    "key_mismatches": self.key_mismatches}


# ---- the controller's side -----------------------------------------------------------------
def claim(transport, keys, sn: int, action: str = CLAIM, timeout: float = 1.0,
          to: str | None = None, wheel_wear: bool | None = None, pk: bytes | None = None,
          mac_key: bytes | None = None) -> list[tuple[str, dict | None]]:
    """Send a claim (or release) as ``transport``'s identity to the plant ``to`` (None:
    every plant), with the claimer's key ``pk`` and, once granted, signed with the grant's
    command key ``mac_key`` (:mod:`bridge.link_key`); returns
    ``[(replier, grant or None if malformed)]`` for every plant that answered (error
    replies, which name nobody, are left out)."""
    out = []
    for reply in transport.query(keys.claim, encode_claim(action, wheel_wear, pk, mac_key), to=to,
                                 sn=sn, timeout=timeout):
        if not reply.ok or reply.sender is None:
            continue
        try:
            g = decode_grant(reply.payload)
        except M.MessageError:
            g = None
        out.append((reply.sender, g))
    return out


def params_replies(transport, keys, timeout: float = 1.0) -> list[tuple[str | None, bytes]]:
    """Every ok answer to a query on ``params``: ``[(replier, payload)]``."""
    return [(r.sender, r.payload) for r in transport.query(keys.params, timeout=timeout)
            if r.ok]


def arm(transport, keys, controller: str | None = None, timeout: float = 2.0,
        to: str | None = None) -> list[tuple[str, dict | None]]:
    """An operator's re-arm of the vehicle (``msagv arm``): ``[(plant, armed reply or None
    if malformed)]`` of every plant that answered."""
    out = []
    for reply in transport.query(keys.arm, encode_arm(controller), to=to, timeout=timeout):
        if not reply.ok or reply.sender is None:
            continue
        try:
            out.append((reply.sender, decode_armed(reply.payload)))
        except M.MessageError:
            out.append((reply.sender, None))
    return out
