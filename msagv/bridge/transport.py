"""The transport seam: everything the plant and controller nodes do on the bus.

The nodes (:mod:`bridge.plant_node`, :mod:`bridge.controller_node`) and their helpers
(:mod:`bridge.presence`, :mod:`bridge.ownership`) see only :class:`Transport`, one endpoint
on a bus. Two implementations:

* :class:`bridge.zenoh_transport.ZenohTransport`: a Zenoh session (the processes, the
  protocol of docs/PROTOCOL.md);
* :class:`bridge.loopback.LoopbackTransport`: an endpoint of an in-memory
  :class:`bridge.loopback.LoopbackBus` (the tests: every ownership and binding check runs,
  and faults are injected without a network).

What an endpoint offers, and only that:

* ``id``: its identity, the string every message it sends carries as its sender. It comes
  from the transport, never from a message: on Zenoh it travels in the key (the last
  chunks, docs/PROTOCOL.md "Keys"); on a plain bus it is the session id, which anyone may
  copy; with ``--secure`` it is the common name of the endpoint's certificate, and Zenoh's
  access control lets a certificate send only under its own name. ``authenticated`` says
  which. A receiver compares identities, never parses them; an identity is one key chunk;
* :meth:`~Transport.publisher` / :meth:`Publisher.put`: publish on one key, each message
  with the sender's identity (and a sequence number for diagnostics: the state's ``seq``,
  the command's ``seq``); :attr:`Publisher.matching`: whether any subscriber matches the
  key now;
* :meth:`~Transport.subscribe`: a callback per :class:`Sample` (payload bytes, key, the
  sender's identity, or None when the message carried none: a client of the first
  protocol version);
* :meth:`~Transport.queryable` / :meth:`~Transport.query`: a query reaches every matching
  queryable (all of them, none consolidated, or only the one of ``to``) with the querier's
  identity (None: it carried none); the callback answers through :meth:`Query.reply` (or
  :meth:`Query.reply_err`); the querier gets every :class:`Reply` with the replier's
  identity;
* liveliness tokens: :meth:`~Transport.declare_token`, :meth:`~Transport.watch_tokens`
  (appearances and disappearances under a key expression, the tokens existing already
  reported first), :meth:`~Transport.tokens` (which exist now);
* :meth:`~Transport.close`.

Key expressions are Zenoh's: chunks separated by ``/``, ``*`` matches one chunk and
``**`` any number of chunks (docs/PROTOCOL.md, "Keys"). The keys the nodes name are the
protocol's base keys (``msagv/{id}/cmd``); where the sender's identity goes on the wire is
the implementation's business. Every declaration returns an object with ``close()``.
Callbacks may run on a thread of the transport (Zenoh's) or on the sender's (the
loopback's): a callback must not block for long, and a node must not hold a lock of its
own while it publishes, queries or declares.
"""

from __future__ import annotations

from typing import Callable, Mapping, NamedTuple, Protocol, runtime_checkable


class TransportError(ValueError):
    """A bad key expression or identity, or an endpoint used after it was closed (the
    message says which)."""


class Sample(NamedTuple):
    """A published message as a subscriber receives it (a named tuple: cheap to make at
    every message)."""

    key: str  # the base key subscribed to (without the sender's identity)
    payload: bytes
    sender: str | None  # the publisher's identity; None: the message carried none
    sn: int | None = None  # the sequence number the publisher attached (diagnostics only)


class Reply(NamedTuple):
    """One answer to :meth:`Transport.query`: ``ok`` False for an error reply."""

    sender: str | None  # the replier's identity (None: an error reply, which names nobody)
    payload: bytes
    ok: bool = True
    key: str | None = None  # the base key the replier answered on (ok replies)


class Query:
    """A query as a queryable's callback sees it: answer with :meth:`reply` (on the
    queryable's key) or :meth:`reply_err`, from within the callback."""

    __slots__ = ("key", "parameters", "payload", "sender", "_answer")

    def __init__(self, key: str, parameters: Mapping[str, str], payload: bytes | None,
                 sender: str | None, answer: Callable[[bool, bytes], None]):
        self.key = key  # the base key of the queryable
        self.parameters = parameters  # the selector's ``?name=value;...``
        self.payload = payload
        self.sender = sender  # the querier's identity (None: the query carried none)
        self._answer = answer

    def reply(self, payload: bytes) -> None:
        """Answer with ``payload`` (to a querier without identity: an error reply, as a
        reply must name the querier on Zenoh)."""
        self._answer(True, payload)

    def reply_err(self, payload: bytes) -> None:
        self._answer(False, payload)


class Declaration(Protocol):
    """A subscription, queryable, token or token watch; ``close()`` undeclares it."""

    def close(self) -> None: ...


class Publisher(Protocol):
    """A publisher on one key (:meth:`Transport.publisher`)."""

    key: str

    def put(self, payload: bytes, sn: int) -> None:
        """Publish ``payload`` with this endpoint's identity and the sequence number
        ``sn`` (taken modulo 2^32) attached."""

    @property
    def matching(self) -> bool:
        """True while at least one subscriber on the bus matches the key."""

    def close(self) -> None: ...


@runtime_checkable
class Transport(Protocol):
    """One endpoint on a bus (see the module)."""

    id: str
    authenticated: bool  # True: identities on this bus are certificates' (``--secure``)

    def publisher(self, key: str) -> Publisher:
        """A publisher on ``key`` (a key without wildcards)."""

    def subscribe(self, key: str, callback: Callable[[Sample], None]) -> Declaration:
        """``callback(sample)`` for every message published on a key matching ``key``."""

    def queryable(self, key: str, callback: Callable[[Query], None]) -> Declaration:
        """``callback(query)`` for every query whose key expression matches ``key``."""

    def query(self, selector: str, payload: bytes | None = None, *, to: str | None = None,
              sn: int = 0, timeout: float = 1.0) -> list[Reply]:
        """Ask every queryable matching ``selector`` (``KEY`` or ``KEY?name=value;...``),
        or only the one of the endpoint ``to``, with this endpoint's identity and ``sn``
        attached; returns their replies, waiting at most ``timeout`` seconds. Error
        replies may include the transport's own (Zenoh reports a timeout as one): take
        ``ok`` replies as the answers."""

    def declare_token(self, key: str) -> Declaration:
        """A liveliness token on ``key``: it exists until closed, or until the endpoint
        is gone (a lost endpoint's tokens disappear after the transport's lease)."""

    def watch_tokens(self, key: str, callback: Callable[[str, bool], None]) -> Declaration:
        """``callback(token key, present)`` for every token matching ``key`` that
        appears (True) or disappears (False); the tokens that exist already are reported
        first (history)."""

    def tokens(self, key: str, timeout: float = 0.3) -> list[str]:
        """The keys of the tokens matching ``key`` that exist now."""

    def close(self) -> None:
        """Undeclare everything and leave the bus (this endpoint's tokens disappear)."""


def close_all(declarations) -> None:
    """Close each of ``declarations`` (publishers, subscribers, queryables, tokens; None
    passed over), quietly: one that fails to close (its session already gone) stops
    none of the others."""
    for obj in declarations:
        if obj is not None:
            try:
                obj.close()
            except Exception:
                pass
