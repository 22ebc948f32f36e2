"""Presence of the other side, from its liveliness token.

A liveliness subscriber reports a token's appearance (PUT) and disappearance (DELETE; for
a killed process after the transport lease). A process restarted quickly declares a new
token under the same key before the old one has expired, so a DELETE is checked with a
liveliness query before the peer is declared gone.
"""

from __future__ import annotations

import logging
import threading
from typing import Callable

log = logging.getLogger("msagv.bridge")


class Presence:
    """``present`` is True while a liveliness token matching ``key`` exists.

    ``on_change(present)`` is called (from a zenoh or helper thread) on every change;
    ``generation`` counts appearances, ``losses`` disappearances.
    """

    def __init__(self, session, key: str, on_change: Callable[[bool], None] | None = None):
        self.session = session
        self.key = key
        self.on_change = on_change
        self.present = False
        self.generation = 0
        self.losses = 0
        self.changed = threading.Event()
        self._epoch = 0
        self._lock = threading.Lock()
        self._closed = False
        self._sub = session.liveliness().declare_subscriber(key, self._on_sample, history=True)

    def _on_sample(self, sample) -> None:
        import zenoh

        with self._lock:
            self._epoch += 1
            epoch = self._epoch
        if sample.kind == zenoh.SampleKind.PUT:
            self._set(True, epoch)
        else:
            threading.Thread(target=self._verify, args=(epoch,), daemon=True).start()

    def _verify(self, epoch: int) -> None:
        alive = False
        try:
            for reply in self.session.liveliness().get(self.key, timeout=0.3):
                if reply.ok is not None:
                    alive = True
        except Exception:  # the session is closing
            alive = False
        self._set(alive, epoch)

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
        try:
            self._sub.undeclare()
        except Exception:
            pass
