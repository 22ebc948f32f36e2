"""Presence of the other side, from its liveliness token (through a
:class:`bridge.transport.Transport`: ``watch_tokens`` and ``tokens``).

A liveliness subscriber reports a token's appearance (PUT) and disappearance (DELETE; for
a killed process after the transport lease). A process restarted quickly declares a new
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
        self._stop = threading.Event()
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
        else:
            threading.Thread(target=self._verify, args=(epoch,), daemon=True).start()

    def _query(self) -> bool:
        try:
            return bool(self.transport.tokens(self.key, timeout=0.3))
        except Exception:  # the transport is closing
            return False

    def _poll(self) -> None:
        while not self._stop.wait(POLL_S):
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
        with self._lock:
            self._closed = True
        self._stop.set()
        try:
            self._sub.close()
        except Exception:
            pass


class TokenSet:
    """The endpoints holding a token under ``prefix/*``: the last chunk of a token's key is
    the holder's identity (``msagv/{id}/alive/controller/{zid}``), so a node can tell its
    peer's token from anyone else's (docs/PROTOCOL.md, "Ownership").

    One token watch on ``prefix/*`` (with history) and a reconciling query every
    ``POLL_S``, as :class:`Presence`; a DELETE (or a token missing from the query) is
    confirmed by querying that token for up to ``VERIFY_S``. ``on_change(zid, present)`` is
    called from the transport's or a helper thread.
    """

    def __init__(self, transport, prefix: str,
                 on_change: Callable[[str, bool], None] | None = None):
        self.transport = transport
        self.prefix = prefix
        self.on_change = on_change
        self._present: set[str] = set()
        self._epoch: dict[str, int] = {}
        self._verifying: dict[str, int] = {}  # zid -> verifications running
        self._lock = threading.Lock()
        self._closed = False
        self._stop = threading.Event()
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

    def _zid(self, key) -> str | None:
        key = str(key)
        if not key.startswith(self.prefix + "/"):
            return None
        z = key[len(self.prefix) + 1:]
        return z if z and "/" not in z else None

    def _bump(self, zid: str) -> int:
        with self._lock:
            e = self._epoch.get(zid, 0) + 1
            self._epoch[zid] = e
            return e

    def _on_token(self, key: str, present: bool) -> None:
        zid = self._zid(key)
        if zid is None:
            return
        epoch = self._bump(zid)
        if present:
            self._set(zid, True, epoch)
        else:
            threading.Thread(target=self._verify, args=(zid, epoch), daemon=True).start()

    def _query(self, key: str) -> set[str] | None:
        """The holders found by a token query on ``key`` (None: the transport closed)."""
        try:
            keys = self.transport.tokens(key, timeout=0.3)
        except Exception:
            return None
        return {z for z in map(self._zid, keys) if z is not None}

    def _poll(self) -> None:
        while not self._stop.wait(POLL_S):
            found = self._query(f"{self.prefix}/*")
            if found is None:
                return
            with self._lock:
                if self._closed:
                    return
                new = found - self._present
                gone = self._present - found - set(self._verifying)
            for zid in new:
                log.debug("tokens %s: %s found by query (no PUT seen)", self.prefix, zid)
                self._set(zid, True, self._bump(zid))
            for zid in gone:
                log.debug("tokens %s: %s missing from query (no DELETE seen)", self.prefix, zid)
                self._verify(zid, self._bump(zid))

    def _verify(self, zid: str, epoch: int) -> None:
        with self._lock:
            self._verifying[zid] = self._verifying.get(zid, 0) + 1
        try:
            end = time.monotonic() + VERIFY_S
            while True:
                found = self._query(f"{self.prefix}/{zid}")
                if not found:
                    self._set(zid, False, epoch)
                    return
                with self._lock:
                    if self._epoch.get(zid) != epoch or self._closed:
                        return
                if time.monotonic() >= end:
                    self._set(zid, True, epoch)
                    return
                time.sleep(VERIFY_EVERY_S)
        finally:
            with self._lock:
                n = self._verifying.pop(zid) - 1
                if n:
                    self._verifying[zid] = n

    def _set(self, zid: str, present: bool, epoch: int) -> None:
        with self._lock:
            if self._epoch.get(zid) != epoch or self._closed:
                return
            was = zid in self._present
            if present:
                self._present.add(zid)
            else:
                self._present.discard(zid)
        if present != was and self.on_change is not None:
            self.on_change(zid, present)

    def close(self) -> None:
        with self._lock:
            self._closed = True
        self._stop.set()
        try:
            self._sub.close()
        except Exception:
            pass
