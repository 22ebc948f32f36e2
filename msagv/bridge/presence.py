"""Presence of the other side, from its liveliness token (through a
:class:`bridge.transport.Transport`: ``watch_tokens`` and ``tokens``).

A liveliness subscriber reports a token's appearance (PUT) and disappearance (DELETE; for
a killed process after the transport lease); its callback only records the event, one
helper thread per watch does every query (a flood of tokens starts no thread). A process restarted quickly declares a new
token under the same key before the old one has expired, so a DELETE is checked with a
liveliness query before the peer is declared gone. Another node of the bus can still hold
a dead peer's token for up to its lease after the DELETE and answer that query, so the
check is repeated for ``VERIFY_S``: the peer is declared gone at the first query nobody
answers, and kept only if it answers throughout (a restarted peer does).

Events alone were not enough: about one run in three of a process test, a controller's
liveliness subscriber (declared with history, on a bus with several paths) never received
the plant's PUT, so it never commanded, nor noticed the plant's loss. A helper thread
therefore also queries every ``POLL_S`` and reconciles: a token found while absent is a
PUT, a token missing while present is a DELETE (re-checked as above).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

log = logging.getLogger("msagv.bridge")

VERIFY_S = 2.5  # s, how long a DELETE is re-checked (more than twice the 1 s lease)
VERIFY_EVERY_S = 0.25
POLL_S = 0.5  # s, reconciliation query period



def _close_watch(w) -> None:
    """Stop a token watch (:class:`Presence`, :class:`TokenSet`): closed under its lock, its
    helper thread woken to end, its subscriber undeclared (a closing transport may refuse)."""
    with w._lock:
        w._closed = True
    w._stop.set()
    w._wake.set()
    try:
        w._sub.close()
    except Exception:
        pass

class Presence:
    """``present`` is True while a liveliness token matching ``key`` exists.

    ``on_change(present)`` is called (from the transport's or a helper thread) on every
    change; ``generation`` counts appearances, ``losses`` disappearances.
    """

    def __init__(self, transport, key: str, on_change: Callable[[bool], None] | None = None):
        self.transport = transport
        self.key = key
        self.on_change = on_change
        self.present = False
        self.generation = 0
        self.losses = 0
        self.changed = threading.Event()
        self._epoch = 0
        self._lock = threading.Lock()
        self._closed = False
        self._verifying = 0
        self._pending: int | None = None  # a DELETE's epoch, for the helper to verify
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._sub = transport.watch_tokens(key, self._on_token)
        self._poller = threading.Thread(target=self._poll, daemon=True,
                                        name=f"presence {key}")
        self._poller.start()

    def _on_token(self, key: str, present: bool) -> None:
        with self._lock:
            self._epoch += 1
            epoch = self._epoch
        log.debug("presence %s: %s %s (epoch %d)", self.key, "PUT" if present else "DELETE",
                  key, epoch)
        if present:
            self._set(True, epoch)
        else:  # verified by the helper thread (a flood of DELETEs starts no thread)
            with self._lock:
                self._pending = epoch
            self._wake.set()

    def _query(self) -> bool:
        try:
            return bool(self.transport.tokens(self.key, timeout=0.3))
        except Exception:  # the transport is closing
            return False

    def _poll(self) -> None:
        while True:
            self._wake.wait(POLL_S)
            self._wake.clear()
            if self._stop.is_set():
                return
            with self._lock:
                pending, self._pending = self._pending, None
            if pending is not None:
                self._verify(pending)
                continue
            alive = self._query()
            with self._lock:
                if self._closed:
                    return
                if alive == self.present or self._verifying:
                    continue
                self._epoch += 1
                epoch = self._epoch
            if alive:
                log.debug("presence %s: found by query (no PUT seen)", self.key)
                self._set(True, epoch)
            else:
                log.debug("presence %s: missing from query (no DELETE seen)", self.key)
                self._verify(epoch)

    def _verify(self, epoch: int) -> None:
        with self._lock:
            self._verifying += 1
        try:
            self._verify_loop(epoch)
        finally:
            with self._lock:
                self._verifying -= 1

    def _verify_loop(self, epoch: int) -> None:
        end = time.monotonic() + VERIFY_S
        while True:
            if not self._query():
                log.debug("presence %s: verified gone (epoch %d)", self.key, epoch)
                self._set(False, epoch)
                return
            with self._lock:
                if epoch != self._epoch or self._closed:  # a newer event decides
                    return
            if time.monotonic() >= end:
                self._set(True, epoch)
                return
            time.sleep(VERIFY_EVERY_S)

    def _set(self, present: bool, epoch: int) -> None:
        with self._lock:
            if epoch != self._epoch or self._closed:  # a newer event decides
                return
            was = self.present
            self.present = present
            if present and not was:
                self.generation += 1
            elif was and not present:
                self.losses += 1
        if present != was:
            self.changed.set()
            if self.on_change is not None:
                self.on_change(present)

    def close(self) -> None:
        _close_watch(self)


MAX_TOKENS = 64  # controller tokens a plant tracks per vehicle (the owner's always among them)


class TokenSet:
    """The endpoints holding a token under ``prefix/*``: the last chunk of a token's key is
    the holder's identity (``msagv/{id}/alive/controller/{zid}``), so a node can tell its
    peer's token from anyone else's (docs/PROTOCOL.md, "Ownership").

    Built for a bus that anyone may flood with tokens (issue 30): the token watch's
    callback does a set operation and nothing else (no thread, no query); at most ``bound``
    holders are kept (the ``focus``, the one identity whose presence matters, always is;
    the others beyond the bound are counted in ``untracked`` and logged); and one helper
    thread queries only the focus's own token (``prefix/{focus}``: one reply), every
    ``POLL_S`` and at once when the focus changes or its DELETE arrives.

    The focus is lost when its DELETE is confirmed by a query that does not find the
    token, or when a query nobody answers (no DELETE seen) finds it missing *and*
    ``quiet(focus)`` says it has sent nothing for the staleness bound: through a router,
    Zenoh's token query now and then misses a live token (issue 30, item 4), and one
    missing answer must not end a live owner; but a DELETE is the session gone, and what
    still arrives under its identity afterwards (a client copying it) must not keep it. A focus whose token answers throughout
    ``VERIFY_S`` after a DELETE (a restarted peer) is kept. ``on_change(zid, present)`` is
    called for the focus only, from the transport's or the helper thread.
    """

    def __init__(self, transport, prefix: str,
                 on_change: Callable[[str, bool], None] | None = None,
                 bound: int = MAX_TOKENS, quiet: Callable[[str], bool] | None = None):
        if bound < 1:
            raise ValueError(f"bound must be >= 1, got {bound}")
        self.transport = transport
        self.prefix = prefix
        self.on_change = on_change
        self.bound = bound
        self.quiet = quiet if quiet is not None else (lambda zid: True)
        self._present: set[str] = set()
        self._focus: str | None = None
        self._suspect_since: float | None = None  # the focus's token missing since
        self._deleted = False  # ... and the suspicion began with its DELETE
        self._lock = threading.Lock()
        self._closed = False
        self._stop = threading.Event()
        self._wake = threading.Event()
        self.untracked = 0  # PUTs of holders not kept (the set was full)
        self.tracked_max = 0
        self.suspicions = 0  # the focus's token found missing
        self.kept = 0  # ... while the focus still sent: not taken for lost
        self.last_loss = ""  # why the focus was last taken for lost (for the caller's log)
        self._sub = transport.watch_tokens(f"{prefix}/*", self._on_token)
        self._poller = threading.Thread(target=self._poll, daemon=True,
                                        name=f"tokens {prefix}")
        self._poller.start()

    def present(self, zid: str | None) -> bool:
        with self._lock:
            return zid is not None and zid in self._present

    def holders(self) -> set[str]:
        with self._lock:
            return set(self._present)

    def focus(self, zid: str | None) -> None:
        """The identity whose presence matters (the owner; None: nobody): always tracked,
        and queried at once."""
        with self._lock:
            if zid == self._focus:
                return
            self._focus, self._suspect_since, self._deleted = zid, None, False
        self._wake.set()

    def _zid(self, key) -> str | None:
        key = str(key)
        if not key.startswith(self.prefix + "/"):
            return None
        z = key[len(self.prefix) + 1:]
        return z if z and "/" not in z else None

    def _add(self, zid: str) -> bool:
        """(locked) Keep ``zid``; False if the set is full (counted)."""
        if zid in self._present:
            return True
        if len(self._present) >= self.bound:
            if zid != self._focus:
                self.untracked += 1
                n = self.untracked
                if n == 1 or n % 1000 == 0:
                    log.warning("more than %d tokens under %s: %d not tracked (only the "
                                "owner's counts)", self.bound, self.prefix, n)
                return False
            self._present.discard(next(z for z in self._present if z != zid))
        self._present.add(zid)
        self.tracked_max = max(self.tracked_max, len(self._present))
        return True

    def _on_token(self, key: str, present: bool) -> None:
        zid = self._zid(key)
        if zid is None:
            return
        changed = None
        with self._lock:
            if self._closed:
                return
            focus = zid == self._focus
            if present:
                if focus:
                    self._suspect_since = None
                    self._deleted = False
                was = zid in self._present
                if self._add(zid) and focus and not was:
                    changed = True
            elif focus:
                if zid in self._present and self._suspect_since is None:
                    self._suspect_since = time.monotonic()
                    self.suspicions += 1
                self._deleted = True
                self._wake.set()  # the helper thread decides
            else:
                self._present.discard(zid)
        log.debug("tokens %s: %s %s", self.prefix, "PUT" if present else "DELETE", zid)
        if changed is not None and self.on_change is not None:
            self.on_change(zid, changed)

    def _query(self, zid: str) -> bool | None:
        """Whether a token query finds ``prefix/{zid}`` (None: the transport closed)."""
        try:
            keys = self.transport.tokens(f"{self.prefix}/{zid}", timeout=0.3)
        except Exception:
            return None
        return any(self._zid(k) == zid for k in keys)

    def _poll(self) -> None:
        while True:
            with self._lock:
                suspect = self._suspect_since is not None
            self._wake.wait(VERIFY_EVERY_S if suspect else POLL_S)
            self._wake.clear()
            if self._stop.is_set():
                return
            with self._lock:
                zid = self._focus
            if zid is None:
                continue
            found = self._query(zid)
            if found is None:
                return
            self._decide(zid, found)

    def _decide(self, zid: str, found: bool) -> None:
        now = time.monotonic()
        changed = None
        with self._lock:
            if self._closed or zid != self._focus:
                return
            had = zid in self._present
            since = self._suspect_since
            if found:
                if since is None or now - since >= VERIFY_S:
                    # present, or answered throughout VERIFY_S after a DELETE: kept
                    self._suspect_since = None
                    self._deleted = False
                    if not had:
                        self._add(zid)
                        changed = True
                        log.debug("tokens %s: %s found by query (no PUT seen)", self.prefix,
                                  zid)
            elif had:
                if since is None:
                    self._suspect_since = since = now
                    self.suspicions += 1
                    log.debug("tokens %s: %s missing from query (no DELETE seen)",
                              self.prefix, zid)
            deleted = self._deleted
        if found or not had:
            if changed is not None and self.on_change is not None:
                self.on_change(zid, True)
            return
        # a DELETE that the query confirms is the token gone (a killed or closed session):
        # lost whatever still arrives under that identity (on the plain bus a client can
        # copy it); a token only missing from a query (a router's mis-answer) is lost only
        # if its holder has also gone quiet
        if not deleted and not self.quiet(zid):  # (outside the lock: the caller's state)
            with self._lock:
                self.kept += 1
                n = self.kept
            if n == 1 or n % 100 == 0:
                log.info("%s's token is missing from the query but it still sends: kept "
                         "(%d times)", zid, n)
            return
        with self._lock:
            if self._closed or zid != self._focus or self._suspect_since is None:
                return
            self._present.discard(zid)
            self.last_loss = ("its DELETE confirmed by a query" if deleted else
                              f"missing from the token query for {now - since:.2f} s, and "
                              "nothing received from it")
            self._suspect_since = None
            self._deleted = False
        log.debug("tokens %s: %s gone (%s)", self.prefix, zid, self.last_loss)
        if self.on_change is not None:
            self.on_change(zid, False)

    def summary(self) -> dict:
        with self._lock:
            return {"bound": self.bound, "tracked": len(self._present),
                    "tracked_max": self.tracked_max, "untracked": self.untracked,
                    "suspicions": self.suspicions, "kept_while_sending": self.kept}

    def close(self) -> None:
        _close_watch(self)
