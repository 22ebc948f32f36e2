"""Who drives the vehicle: one controller session owns it, and each controller is bound to
one plant session (docs/PROTOCOL.md, "Ownership").

Identity is the transport's (:class:`bridge.transport.Transport`: ``id``, a message's
``sender``, a reply's ``sender``); over Zenoh it is the session id (zid), which the
sender attaches to every ``cmd``, ``claim`` and ``state`` as ``source_info``, and a
reply's sender is Zenoh's ``replier_id``. The holder of a liveliness token is the last
chunk of its key (``alive/controller/{zid}``, ``alive/plant/{zid}``). On a plain bus these
are what the sender says (Zenoh's Python API can only attach the ids of its own session);
``--secure`` makes Zenoh check who may send what (:mod:`bridge.security`).

* The plant (:class:`Ownership`) grants the vehicle to the first controller that claims
  it (a ``get`` on ``msagv/{id}/claim``), applies commands only from that session
  (others are rejected as ``not_owner``, and a session that commands while another owns
  the vehicle is never granted it), counts only that session's token as the
  controller's presence, and hands the vehicle over only when its owner releases it or
  its token is lost.
* The controller binds to the one plant that answers its ``params`` (two different
  answers: it binds to neither), takes states only from that session (others:
  ``not_bound``), and commands only while the plant grants it the vehicle.
"""

from __future__ import annotations

import logging
import threading
import time

from . import messages as M

log = logging.getLogger("msagv.bridge")

CLAIM, RELEASE = "claim", "release"
CLAIM_REQUIRED = {"v": "int", "action": "str"}
GRANT_REQUIRED = {"v": "int", "granted": "bool"}
GRANT_OPTIONAL = {"owner": "str"}
MAX_CLAIM_BYTES = 1024
MAX_BANNED = 1024
GRANT_TOKEN_S = 3.0  # a grant whose owner never shows its token is void after this long
CLAIM_RETRY_S = 0.25  # the controller's claim period while not granted
CLAIM_REFRESH_S = 1.0  # ... and while granted (it learns of a lost grant within this)


# ---- messages ------------------------------------------------------------------------------
def encode_claim(action: str = CLAIM) -> bytes:
    return M.pack({"v": M.VERSION, "action": action})


def decode_claim(payload) -> str:
    m = M._fields(M.unpack(payload, MAX_CLAIM_BYTES), CLAIM_REQUIRED, {}, None)
    if m["action"] not in (CLAIM, RELEASE):
        raise M.MessageError(M.BAD_VALUE, f"action '{m['action']}' is not claim or release")
    return m["action"]


def encode_grant(granted: bool, owner: str | None) -> bytes:
    m = {"v": M.VERSION, "granted": bool(granted)}
    if owner is not None:
        m["owner"] = owner
    return M.pack(m)


def decode_grant(payload) -> dict:
    return M._fields(M.unpack(payload, MAX_CLAIM_BYTES), GRANT_REQUIRED, GRANT_OPTIONAL, None)


# ---- the plant's side ----------------------------------------------------------------------
class Ownership:
    """The plant's owner (one controller session at a time). Thread-safe; ``on_change(owner,
    why)`` is called (outside the lock) whenever the owner changes."""

    def __init__(self, on_change=None):
        self.owner: str | None = None
        self.owner_seen = False  # the owner's token has been seen since the grant
        self.granted_at = 0.0
        self.on_change = on_change
        self.grants = 0  # owners granted (a refresh by the owner is not counted)
        self.refused = 0  # claims refused (another session owns the vehicle)
        self.releases = 0
        self.losses = 0  # owners whose token was lost
        self.banned: set[str] = set()  # sessions that commanded while another owned it
        self._lock = threading.Lock()

    def claim(self, zid: str | None, action: str = CLAIM, now: float | None = None,
              token_present: bool = False) -> tuple[bool, str | None]:
        """Handle a claim or release from session ``zid`` (``token_present``: its token is
        visible now); returns (granted, owner after)."""
        now = time.monotonic() if now is None else now
        changed = None
        with self._lock:
            if zid is None:
                self.refused += 1
                return False, self.owner
            if action != RELEASE and zid in self.banned:
                self.refused += 1
                return False, self.owner
            if action == RELEASE:
                if zid == self.owner:
                    self.owner, self.releases = None, self.releases + 1
                    changed = (None, f"released by {zid}")
                granted, owner = False, self.owner
            elif self.owner == zid:
                self.owner_seen = self.owner_seen or token_present
                granted, owner = True, zid
            else:
                void = (self.owner is not None and not self.owner_seen
                        and now - self.granted_at > GRANT_TOKEN_S)
                if self.owner is None or void:
                    why = (f"granted to {zid}" if self.owner is None else
                           f"granted to {zid} (the grant to {self.owner} was void: no token "
                           f"within {GRANT_TOKEN_S:g} s)")
                    self.owner, self.owner_seen, self.granted_at = zid, token_present, now
                    self.grants += 1
                    changed = (zid, why)
                    granted, owner = True, zid
                else:
                    self.refused += 1
                    granted, owner = False, self.owner
        if changed is not None and self.on_change is not None:
            self.on_change(*changed)
        return granted, owner

    def token(self, zid: str, present: bool) -> None:
        """A controller token appeared or was lost (confirmed)."""
        changed = None
        with self._lock:
            if zid != self.owner:
                return
            if present:
                self.owner_seen = True
            else:
                self.owner, self.losses = None, self.losses + 1
                changed = (None, f"owner {zid} lost (its token is gone)")
        if changed is not None and self.on_change is not None:
            self.on_change(*changed)

    def violation(self, zid: str | None) -> None:
        """Session ``zid`` sent a command while another session owned the vehicle: it is
        never granted the vehicle by this plant (at most MAX_BANNED sessions are kept)."""
        with self._lock:
            if zid is not None and self.owner is not None and zid != self.owner \
                    and len(self.banned) < MAX_BANNED:
                if zid not in self.banned:
                    log.warning("session %s commanded vehicle owned by %s: it will not be "
                                "granted the vehicle", zid, self.owner)
                self.banned.add(zid)

    def accepts(self, zid: str | None) -> bool:
        with self._lock:
            return zid is not None and zid == self.owner

    def summary(self) -> dict:
        with self._lock:
            return {"owner": self.owner, "grants": self.grants, "refused": self.refused,
                    "releases": self.releases, "losses": self.losses,
                    "banned": len(self.banned)}


# ---- the controller's side -----------------------------------------------------------------
def claim(transport, keys, sn: int, action: str = CLAIM, timeout: float = 1.0
          ) -> list[tuple[str, dict | None]]:
    """Send a claim (or release) as ``transport``'s identity with the sequence number
    ``sn``; returns ``[(replier, grant or None if malformed)]`` for every plant that
    answered (error replies and replies without the replier's identity are left out)."""
    out = []
    for reply in transport.query(keys.claim, encode_claim(action), sn=sn, timeout=timeout):
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
    # ?wheel_wear=1: this controller understands the per-wheel wear fields of the state
    return [(r.sender, r.payload) for r in
            transport.query(f"{keys.params}?wheel_wear=1", timeout=timeout) if r.ok]
