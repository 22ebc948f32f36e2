"""An in-memory bus: several :class:`LoopbackTransport` endpoints in one process.

:class:`LoopbackBus` implements :class:`bridge.transport.Transport` for the tests: the
plant and controller nodes run on it unchanged, with every ownership and binding check,
and without a network. It delivers as Zenoh does from a node's point of view:

* key expressions match as Zenoh's do for the keys of the protocol (``*`` one chunk,
  ``**`` any number of chunks, on either side); a bad key expression is refused with a
  :class:`~bridge.transport.TransportError`, as Zenoh refuses it;
* a message reaches every matching subscriber, of every endpoint (the sender's own too),
  with the sender's identity; a query reaches every matching queryable (target ALL, no
  consolidation; or only the one of ``to``) and returns their replies with the repliers'
  identities; an error reply names nobody (as on Zenoh, where the identity is in an ok
  reply's key);
* a token exists from its declaration until it is closed, dropped (as zenoh-python
  undeclares a token it garbage-collects: keep the handle), its endpoint is closed, or it
  vanishes (:meth:`LoopbackBus.vanish`); watchers see it appear and disappear, and the
  tokens already there when they start watching (history). Subscriptions and queryables
  live until closed, whether their handle is kept or not, as on Zenoh.

**Threads.** Delivery is synchronous, on the caller's thread: when ``put`` returns, every
subscriber's callback has run (likewise a query's queryables, a token's watchers). A test
is thus deterministic: after ``plant.publish_state(0)`` the controller has the state. The
bus holds no lock while it runs a callback, so a callback may publish, query or declare
(the delivery nests) without a deadlock. One publisher's messages reach a subscriber in
order, as on Zenoh. An exception in a callback is logged and kept in
:attr:`LoopbackBus.errors` (Zenoh, too, does not hand it to the sender); the tests check
that list is empty.

**Identity.** ``LoopbackBus(authenticated=True)`` stands for a ``--secure`` bus (its
endpoints' ``authenticated`` is True); the bus itself never checks an identity.

**Faults.** :meth:`LoopbackBus.endpoint` takes any identity, also one another endpoint
has (a rogue that claims to be the owner); :meth:`LoopbackBus.inject` delivers a message
with any sender, or none (a client of the first protocol version);
:meth:`LoopbackBus.inject_query` asks the same way; :meth:`LoopbackBus.drop` loses the
next messages on a key; :meth:`LoopbackBus.vanish` removes a token as an expired lease
does, without its endpoint knowing.

Example (docs/ARCHITECTURE.md, "The transport seam")::

    bus = LoopbackBus()
    plant, ctl = bus.endpoint("p1"), bus.endpoint("c1")
    got = []
    ctl.subscribe("msagv/agv0/state", got.append)
    plant.publisher("msagv/agv0/state").put(b"hello", sn=0)
    assert got[0].payload == b"hello" and got[0].sender == "p1"
"""

from __future__ import annotations

import itertools
import logging
import threading
import uuid
from typing import Callable

from .transport import Query, Reply, Sample, TransportError

log = logging.getLogger("msagv.bridge")

_FORBIDDEN = set("?#$")


def key_chunks(key: str) -> tuple[str, ...]:
    """The chunks of a key expression, checked as Zenoh checks them (TransportError)."""
    if not isinstance(key, str) or not key:
        raise TransportError(f"key expression {key!r}: expected a non-empty string")
    chunks = tuple(key.split("/"))
    for c in chunks:
        if not c:
            raise TransportError(f"key expression '{key}': empty chunks are forbidden, as "
                                 f"are leading and trailing slashes")
        if _FORBIDDEN & set(c):
            raise TransportError(f"key expression '{key}': '?', '#' and '$' are not allowed "
                                 f"(parameters go after '?' in a query's selector only)")
        if "*" in c and c not in ("*", "**"):
            raise TransportError(f"key expression '{key}': '*' and '**' must be whole chunks")
    for a, b in zip(chunks, chunks[1:]):
        if a == b == "**":
            raise TransportError(f"key expression '{key}': '**/**' must be written '**'")
    return chunks


def intersects(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    """Whether two key expressions (as chunks) have a key in common (Zenoh's rule for
    delivery: a subscriber on ``a/*`` receives a put on ``a/b``, a liveliness get on
    ``a/**`` finds the token ``a/b/c``)."""
    if not a:
        return all(c == "**" for c in b)
    if not b:
        return all(c == "**" for c in a)
    if a[0] == "**":
        return intersects(a[1:], b) or intersects(a, b[1:])
    if b[0] == "**":
        return intersects(a, b[1:]) or intersects(a[1:], b)
    return (a[0] == b[0] or a[0] == "*" or b[0] == "*") and intersects(a[1:], b[1:])


def parse_selector(selector: str) -> tuple[str, dict[str, str]]:
    """``KEY?name=value;name2`` -> (KEY, {name: value, name2: ""}) (Zenoh separates
    parameters with ``;``)."""
    key, _, params = selector.partition("?")
    out: dict[str, str] = {}
    for p in params.split(";") if params else ():
        name, _, value = p.partition("=")
        if name:
            out.setdefault(name, value)
    return key, out


class _Entry:
    """One declaration on the bus: a subscriber, queryable, token or token watch."""

    __slots__ = ("bus", "table", "owner", "key", "chunks", "callback", "id")

    def __init__(self, bus: "LoopbackBus", table: str, owner: "LoopbackTransport", key: str,
                 callback=None):
        self.bus, self.table, self.owner = bus, table, owner
        self.key, self.chunks = key, key_chunks(key)
        self.callback = callback
        self.id = next(bus._ids)

    def close(self) -> None:
        self.bus._remove(self)


class _Token:
    """The handle of a token: closed when closed, or when nobody holds it any longer
    (zenoh-python undeclares a token it garbage-collects; subscribers and queryables it
    keeps, as the bus does)."""

    __slots__ = ("_entry", "__weakref__")

    def __init__(self, entry: _Entry):
        self._entry = entry

    @property
    def key(self) -> str:
        return self._entry.key

    def close(self) -> None:
        self._entry.close()

    def __del__(self):
        try:
            self._entry.close()
        except Exception:  # the interpreter is shutting down
            pass


class LoopbackPublisher:
    """A publisher of :class:`LoopbackTransport`."""

    def __init__(self, endpoint: "LoopbackTransport", key: str):
        chunks = key_chunks(key)
        if "*" in chunks or "**" in chunks:
            raise TransportError(f"publisher on '{key}': a publisher's key has no wildcards")
        self._endpoint = endpoint
        self._chunks = chunks
        self.key = key
        self._closed = False

    def put(self, payload: bytes, sn: int) -> None:
        if self._closed:
            raise TransportError(f"publisher on '{self.key}' of {self._endpoint.id}: closed")
        self._endpoint._check_open()
        self._endpoint.bus._publish(self.key, self._chunks, bytes(payload),
                                    self._endpoint.id, int(sn) & 0xFFFFFFFF)

    @property
    def matching(self) -> bool:
        return not self._closed and self._endpoint.bus._matching(self._chunks)

    def close(self) -> None:
        self._closed = True


class LoopbackTransport:
    """One endpoint of a :class:`LoopbackBus` with the identity ``id`` (made by
    :meth:`LoopbackBus.endpoint`). Implements :class:`bridge.transport.Transport`."""

    def __init__(self, bus: "LoopbackBus", id: str):
        self.bus = bus
        self.id = id
        self.authenticated = bus.authenticated
        self.closed = False
        self._publishers: list[LoopbackPublisher] = []

    def __repr__(self) -> str:
        return f"LoopbackTransport({self.id!r}{', closed' if self.closed else ''})"

    def _check_open(self) -> None:
        if self.closed:
            raise TransportError(f"loopback endpoint {self.id} is closed")

    def publisher(self, key: str) -> LoopbackPublisher:
        self._check_open()
        p = LoopbackPublisher(self, key)
        self._publishers.append(p)
        return p

    def subscribe(self, key: str, callback: Callable[[Sample], None]) -> _Entry:
        self._check_open()
        return self.bus._add(_Entry(self.bus, "subs", self, key, callback))

    def queryable(self, key: str, callback: Callable[[Query], None]) -> _Entry:
        self._check_open()
        return self.bus._add(_Entry(self.bus, "queryables", self, key, callback))

    def query(self, selector: str, payload: bytes | None = None, *, to: str | None = None,
              sn: int = 0, timeout: float = 1.0) -> list[Reply]:
        self._check_open()
        return self.bus._query(selector, None if payload is None else bytes(payload), self.id,
                               to)

    def declare_token(self, key: str) -> _Token:
        self._check_open()
        return _Token(self.bus._declare_token(_Entry(self.bus, "tokens", self, key)))

    def watch_tokens(self, key: str, callback: Callable[[str, bool], None]) -> _Entry:
        self._check_open()
        return self.bus._watch(_Entry(self.bus, "watchers", self, key, callback))

    def tokens(self, key: str, timeout: float = 0.3) -> list[str]:
        self._check_open()
        return self.bus.tokens(key)

    def close(self) -> None:
        """Leave the bus: every declaration of this endpoint goes (its tokens disappear
        for the watchers, as at a clean exit); further calls raise TransportError."""
        if self.closed:
            return
        self.closed = True
        for p in self._publishers:
            p.close()
        self.bus._remove_owner(self)


class LoopbackBus:
    """The in-memory bus (see the module). Thread-safe."""

    def __init__(self, authenticated: bool = False):
        self.authenticated = authenticated
        self._lock = threading.Lock()
        self._ids = itertools.count(1)
        self._tables: dict[str, list[_Entry]] = {"subs": [], "queryables": [], "tokens": [],
                                                 "watchers": []}
        self._drops: list[list] = []  # [chunks, remaining]
        self.delivered = 0  # samples handed to a subscriber
        self.dropped = 0  # samples lost by drop()
        self.errors: list[BaseException] = []  # exceptions raised by callbacks

    # ---- endpoints and faults ------------------------------------------------------------
    def endpoint(self, id: str | None = None) -> LoopbackTransport:
        """A new endpoint with the identity ``id`` (default: a fresh 32-hex-digit id, as a
        Zenoh session's). Any identity is accepted, also one in use (a rogue)."""
        if id is None:
            id = uuid.uuid4().hex
        if not isinstance(id, str) or not id or "/" in id or "*" in id or _FORBIDDEN & set(id):
            raise TransportError(f"endpoint identity {id!r}: expected one key chunk (no '/', "
                                 f"'*', '?', '#', '$')")
        return LoopbackTransport(self, id)

    def inject(self, key: str, payload: bytes, sender: str | None = None,
               sn: int | None = None) -> int:
        """Deliver ``payload`` on ``key`` as if sent by ``sender`` (None: a message without
        the sender's identity); returns the number of subscribers reached."""
        chunks = key_chunks(key)
        return self._publish(key, chunks, bytes(payload), sender, sn)

    def inject_query(self, selector: str, payload: bytes | None = None,
                     sender: str | None = None) -> list[Reply]:
        """Ask the queryables matching ``selector`` as ``sender`` (None: a query without the
        querier's identity); returns their replies."""
        return self._query(selector, None if payload is None else bytes(payload), sender)

    def drop(self, key: str, count: int = 1) -> None:
        """Lose the next ``count`` messages published on keys matching ``key``."""
        if count < 1:
            raise TransportError(f"drop: count must be >= 1, got {count}")
        chunks = key_chunks(key)
        with self._lock:
            self._drops.append([chunks, int(count)])

    def vanish(self, key: str, notify: bool = True) -> int:
        """Remove the tokens matching ``key`` without their endpoints knowing (an expired
        lease); the watchers see them disappear (a DELETE), or with ``notify=False`` do not
        (a token a router's query misses: issue 30, item 4). Returns how many vanished."""
        chunks = key_chunks(key)
        with self._lock:
            gone = [e for e in self._tables["tokens"] if intersects(e.chunks, chunks)]
        for e in gone:
            self._remove(e, notify)
        return len(gone)

    def tokens(self, key: str) -> list[str]:
        """The keys of the tokens matching ``key`` (every endpoint's)."""
        chunks = key_chunks(key)
        with self._lock:
            return [e.key for e in self._tables["tokens"] if intersects(e.chunks, chunks)]

    # ---- delivery -----------------------------------------------------------------------
    def _call(self, fn, *args) -> None:
        try:
            fn(*args)
        except Exception as e:  # a receiver's bug never reaches the sender, as on Zenoh
            log.exception("loopback bus: a callback raised")
            self.errors.append(e)

    def _publish(self, key: str, chunks, payload: bytes, sender: str | None,
                 sn: int | None) -> int:
        with self._lock:
            for d in self._drops:
                if d[1] > 0 and intersects(d[0], chunks):
                    d[1] -= 1
                    self.dropped += 1
                    self._drops = [x for x in self._drops if x[1] > 0]
                    return 0
            subs = [e for e in self._tables["subs"] if intersects(e.chunks, chunks)]
            self.delivered += len(subs)
        sample = Sample(key, payload, sender, sn)
        for e in subs:
            self._call(e.callback, sample)
        return len(subs)

    def _matching(self, chunks) -> bool:
        with self._lock:
            return any(intersects(e.chunks, chunks) for e in self._tables["subs"])

    def _query(self, selector: str, payload: bytes | None, sender: str | None,
               to: str | None = None) -> list[Reply]:
        key, params = parse_selector(selector)
        chunks = key_chunks(key)
        with self._lock:
            qbls = [e for e in self._tables["queryables"] if intersects(e.chunks, chunks)
                    and (to is None or e.owner.id == to)]
        replies: list[Reply] = []
        for e in qbls:
            def answer(ok: bool, data: bytes, e=e) -> None:
                ok = ok and sender is not None  # (a reply names its querier, as on Zenoh)
                replies.append(Reply(e.owner.id if ok else None, bytes(data), ok,
                                     e.key if ok else None))

            self._call(e.callback, Query(key, dict(params), payload, sender, answer))
        return replies

    # ---- declarations -------------------------------------------------------------------
    def _add(self, e: _Entry) -> _Entry:
        with self._lock:
            self._tables[e.table].append(e)
        return e

    def _declare_token(self, e: _Entry) -> _Entry:
        with self._lock:
            self._tables["tokens"].append(e)
            watchers = [w for w in self._tables["watchers"] if intersects(w.chunks, e.chunks)]
        for w in watchers:
            self._call(w.callback, e.key, True)
        return e

    def _watch(self, w: _Entry) -> _Entry:
        with self._lock:
            self._tables["watchers"].append(w)
            history = [e.key for e in self._tables["tokens"] if intersects(w.chunks, e.chunks)]
        for key in history:
            self._call(w.callback, key, True)
        return w

    def _remove(self, e: _Entry, notify: bool = True) -> None:
        with self._lock:
            table = self._tables[e.table]
            if e not in table:
                return  # closed already (or vanished)
            table.remove(e)
            watchers = ([w for w in self._tables["watchers"] if intersects(w.chunks, e.chunks)]
                        if e.table == "tokens" and notify else [])
        for w in watchers:
            self._call(w.callback, e.key, False)

    def _remove_owner(self, owner: LoopbackTransport) -> None:
        with self._lock:  # its watchers first: a leaving endpoint hears nothing of itself
            mine = [e for t in ("watchers", "subs", "queryables", "tokens")
                    for e in self._tables[t] if e.owner is owner]
        for e in mine:
            self._remove(e)
