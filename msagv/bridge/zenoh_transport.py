"""The transport over Eclipse Zenoh: one :class:`ZenohTransport` per Zenoh session.

It implements :class:`bridge.transport.Transport` with what docs/PROTOCOL.md prescribes on
the wire (protocol version 2):

* identity: on a plain bus the session id (``str(session.zid())``), with ``--secure`` the
  common name of the session's certificate. It travels in the key, never in the message:
  a publisher on ``K`` puts on ``K/{id}`` and a subscriber on ``K`` listens on ``K/*`` (the
  sender is the last chunk); a queryable on ``K`` answers on ``K/{id}/*`` and a query
  asks ``K/{to or *}/{id}`` (the querier is the last chunk, the replier the one before it
  in the reply's key). With ``--secure``, Zenoh's access control lets a certificate use
  only its own name there (:mod:`bridge.security`), so the identity is authenticated. On a
  plain bus the name in the key must be the session that Zenoh says sent the message (the
  ``source_info`` of a put or query, the ``replier_id`` of a reply), else the message has
  no identity. That refuses a key naming another session, but the source info itself is
  not authenticated: a session that received another's message can attach that session's
  id to its own put (``zenoh.SourceInfo`` is public; issue 30, item 2, docs/SECURITY.md);
* the first protocol version's keys (``K`` itself, no identity): a subscriber and a
  queryable listen there too and report the message with no sender (None), so a node can
  tell an old client why it is refused;
* publishers: ``express``, priority ``REAL_TIME``, congestion control ``BLOCK``, encoding
  ``application/msgpack``; each put and query carries ``source_info`` (this session and the
  caller's sequence number);
* queries: target ``ALL``, consolidation ``NONE``; replies with the msgpack encoding;
* liveliness: tokens, a liveliness subscriber with history, a liveliness get;
* replies (of a query and of a liveliness get) are taken by a callback that only appends
  to a list, at most :data:`MAX_REPLIES` of them (the rest counted in :attr:`dropped_replies`),
  never through Zenoh's default FIFO channel: a full channel (256 replies) made Zenoh's
  receive thread wait for the reader while holding the session, and a real-time plant
  whose token query matched 256 tokens stopped publishing (issue 30).

Callbacks run on Zenoh's threads. The session is opened by :func:`bridge.session.open_session`
(:meth:`ZenohTransport.open`), or an open one is wrapped (``owns=False``: a test's or a
benchmark's session, which it closes itself).
"""

from __future__ import annotations

import re
import threading
from typing import Callable

from . import messages as M
from .session import SessionOptions, open_session, secure_identity
from .transport import Query, Reply, Sample, TransportError

_SN_MASK = 0xFFFFFFFF  # Zenoh's source sequence number is a u32
MAX_REPLIES = 1024  # replies a query or a token query keeps (the rest are counted, dropped)
REPLY_GRACE_S = 1.0  # a query waits this long past its timeout for Zenoh's end of replies
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")  # an identity: one literal key chunk


def identity_chunk(chunk: str) -> str | None:
    """``chunk`` if it can be an identity (one literal key chunk: no wildcard), else None."""
    return chunk if _CHUNK.match(chunk) else None


def split_selector(selector: str) -> tuple[str, str]:
    """``KEY?PARAMS`` -> (KEY, '?PARAMS' or '')."""
    key, sep, params = selector.partition("?")
    return key, (sep + params if sep else "")


class _Declared:
    """Zenoh declarations (subscribers, queryables, a token) behind one ``close()``."""

    __slots__ = ("_objs",)

    def __init__(self, *objs):
        self._objs = objs

    def close(self) -> None:
        for o in self._objs:
            o.undeclare()


class ZenohPublisher:
    """A publisher of :class:`ZenohTransport` on ``key`` (it puts on ``key/{identity}``)."""

    def __init__(self, pub, key: str):
        import zenoh

        self._pub = pub
        self._source = zenoh.SourceInfo
        self.entity = pub.id  # the Zenoh entity id named by the source info of every put
        self.key = key

    def put(self, payload: bytes, sn: int) -> None:
        self._pub.put(payload, source_info=self._source(self.entity, int(sn) & _SN_MASK))

    @property
    def matching(self) -> bool:
        return self._pub.matching_status.matching

    def close(self) -> None:
        self._pub.undeclare()


class ZenohTransport:
    """:class:`bridge.transport.Transport` over the Zenoh ``session``; ``identity``: the
    endpoint's name on the bus (None: the session id); ``authenticated``: the identity is
    the certificate's common name, which the bus's access control checks (``--secure``);
    ``owns``: close the session in :meth:`close`. A context manager (``with
    ZenohTransport.open(...) as t:``)."""

    def __init__(self, session, *, identity: str | None = None, authenticated: bool = False,
                 owns: bool = True):
        self.session = session
        self.authenticated = authenticated
        self.id = identity if identity is not None else str(session.zid())
        # a plain bus: a key's identity must be the session Zenoh names as the sender
        self._confirm = not authenticated
        if identity_chunk(self.id) is None:
            raise TransportError(f"identity '{self.id}' is not one key chunk")
        self._owns = owns
        self._entity = None  # the entity id named by the source info of queries
        self.dropped_replies = 0  # replies beyond MAX_REPLIES (a query matched too many)

    def _gather(self, get, timeout: float, convert) -> list:
        """Call ``get(handler)`` with a callback handler, keep ``convert(reply)`` (None:
        skipped) of at most MAX_REPLIES replies, and wait for the end of the replies (or
        ``timeout`` + REPLY_GRACE_S). Zenoh's threads never wait on the caller."""
        import zenoh

        out: list = []
        done = threading.Event()

        def on_reply(r) -> None:
            if len(out) >= MAX_REPLIES:
                self.dropped_replies += 1
                return
            try:
                item = convert(r)
            except Exception:  # a malformed reply is no reply
                return
            if item is not None:
                out.append(item)

        get(zenoh.handlers.Callback(on_reply, done.set))
        done.wait(timeout + REPLY_GRACE_S)
        return out[:]

    @classmethod
    def open(cls, opts: SessionOptions, role: str) -> "ZenohTransport":
        """Open a session for ``role`` with :func:`bridge.session.open_session` (its
        configuration: endpoints, scouting, lease, TLS; SessionError on failure); with
        ``--secure`` the identity is the certificate's common name."""
        identity = secure_identity(opts, role)
        return cls(open_session(opts, role), identity=identity,
                   authenticated=identity is not None)

    def __enter__(self) -> "ZenohTransport":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- publish / subscribe ---------------------------------------------------------------
    def publisher(self, key: str) -> ZenohPublisher:
        import zenoh

        pub = self.session.declare_publisher(
            f"{key}/{self.id}", express=True, priority=zenoh.Priority.REAL_TIME,
            congestion_control=zenoh.CongestionControl.BLOCK,
            encoding=zenoh.Encoding(M.CONTENT_TYPE))
        p = ZenohPublisher(pub, key)
        if self._entity is None:
            self._entity = p.entity
        return p

    def subscribe(self, key: str, callback: Callable[[Sample], None]) -> _Declared:
        confirm = self._confirm

        def signed(s) -> None:
            base, _, sender = str(s.key_expr).rpartition("/")
            si = s.source_info
            if confirm and (si is None or str(si.source_id.zid) != sender):
                sender = ""  # no proof that the session in the key sent it
            callback(Sample(base, s.payload.to_bytes(), identity_chunk(sender),
                            None if si is None else si.source_sn))

        def unsigned(s) -> None:  # the first protocol version's key: no identity
            callback(Sample(str(s.key_expr), s.payload.to_bytes(), None, None))

        return _Declared(self.session.declare_subscriber(f"{key}/*", signed),
                         self.session.declare_subscriber(key, unsigned))

    # ---- query / reply ---------------------------------------------------------------------
    def queryable(self, key: str, callback: Callable[[Query], None]) -> _Declared:
        mine = f"{key}/{self.id}/"

        def handle(q, querier: str | None) -> None:
            def answer(ok: bool, payload: bytes) -> None:
                if ok and querier is not None:
                    q.reply(mine + querier, payload, encoding=M.CONTENT_TYPE)
                else:
                    q.reply_err(payload)

            payload = q.payload.to_bytes() if q.payload is not None else None
            callback(Query(key, dict(q.parameters), payload, querier, answer))

        confirm = self._confirm

        def signed(q) -> None:
            k = str(q.key_expr)
            who = k.rsplit("/", 1)[1] if k.count("/") == key.count("/") + 2 else ""
            if confirm:
                si = q.source_info
                if si is None or str(si.source_id.zid) != who:
                    who = ""
            handle(q, identity_chunk(who))

        return _Declared(self.session.declare_queryable(mine + "*", signed),
                         self.session.declare_queryable(key, lambda q: handle(q, None)))

    def query(self, selector: str, payload: bytes | None = None, *, to: str | None = None,
              sn: int = 0, timeout: float = 1.0) -> list[Reply]:
        import zenoh

        key, params = split_selector(selector)
        if to is not None and identity_chunk(to) is None:
            raise TransportError(f"query to '{to}': not an identity")
        entity = self._entity if self._entity is not None else self.session.id
        depth = key.count("/") + 2
        confirm = self._confirm

        def convert(r) -> Reply | None:
            if r.ok is not None:
                k = str(r.ok.key_expr).split("/")
                who = k[-2] if len(k) == depth + 1 else ""
                if confirm and (r.replier_id is None or str(r.replier_id.zid) != who):
                    who = ""
                return Reply(identity_chunk(who), r.ok.payload.to_bytes(), True, key)
            if r.replier_id is not None:  # (none: Zenoh's own end of the query, a timeout)
                return Reply(None, r.err.payload.to_bytes(), False)
            return None

        return self._gather(
            lambda handler: self.session.get(
                f"{key}/{to or '*'}/{self.id}{params}", handler, payload=payload,
                source_info=zenoh.SourceInfo(entity, int(sn) & _SN_MASK),
                target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                timeout=timeout),
            timeout, convert)

    # ---- liveliness ------------------------------------------------------------------------
    def declare_token(self, key: str) -> _Declared:
        return _Declared(self.session.liveliness().declare_token(key))

    def watch_tokens(self, key: str, callback: Callable[[str, bool], None]) -> _Declared:
        import zenoh

        put = zenoh.SampleKind.PUT

        def on_sample(s) -> None:
            callback(str(s.key_expr), s.kind == put)

        return _Declared(self.session.liveliness().declare_subscriber(key, on_sample,
                                                                      history=True))

    def tokens(self, key: str, timeout: float = 0.3) -> list[str]:
        return self._gather(
            lambda handler: self.session.liveliness().get(key, handler, timeout=timeout),
            timeout, lambda r: str(r.ok.key_expr) if r.ok is not None else None)

    def close(self) -> None:
        if self._owns:
            self.session.close()
