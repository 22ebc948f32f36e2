"""The transport over Eclipse Zenoh: one :class:`ZenohTransport` per Zenoh session.

It implements :class:`bridge.transport.Transport` with what docs/PROTOCOL.md prescribes on
the wire:

* identity: the session id (``str(session.zid())``); a message's sender is the ``zid`` of
  the ``source_info`` it carries (``SourceInfo(entity id, sn)``), a reply's the Zenoh
  ``replier_id``;
* publishers: ``express``, priority ``REAL_TIME``, congestion control ``BLOCK``, encoding
  ``application/msgpack``; each put carries ``source_info`` with the caller's sequence
  number;
* queries: target ``ALL``, consolidation ``NONE``, with ``source_info`` naming the
  session (the entity of this endpoint's first publisher, e.g. the controller's ``cmd``
  publisher, else the session's own); replies with the msgpack encoding on the
  queryable's key;
* liveliness: tokens, a liveliness subscriber with history, a liveliness get.

Callbacks run on Zenoh's threads. The session is opened by :func:`bridge.session.open_session`
(:meth:`ZenohTransport.open`), or an open one is wrapped (``owns=False``: a test's or a
benchmark's session, which it closes itself).
"""

from __future__ import annotations

from typing import Callable

from . import messages as M
from .session import SessionOptions, open_session
from .transport import Query, Reply, Sample

_SN_MASK = 0xFFFFFFFF  # Zenoh's source sequence number is a u32


def _sender(sample_or_query) -> str | None:
    """The zid in a sample's (or query's) ``source_info``; None if it carries none."""
    si = getattr(sample_or_query, "source_info", None)
    if si is None or si.source_id is None:
        return None
    return str(si.source_id.zid)


class _Declared:
    """A Zenoh declaration (subscriber, queryable, token) behind ``close()``."""

    __slots__ = ("_obj",)

    def __init__(self, obj):
        self._obj = obj

    def close(self) -> None:
        self._obj.undeclare()


class ZenohPublisher:
    """A publisher of :class:`ZenohTransport` (the QoS of the module docstring)."""

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
    """:class:`bridge.transport.Transport` over the Zenoh ``session``; ``owns``: close the
    session in :meth:`close`. A context manager (``with ZenohTransport.open(...) as t:``)."""

    def __init__(self, session, *, owns: bool = True):
        self.session = session
        self.id = str(session.zid())
        self._owns = owns
        self._entity = None  # the entity id named by the source info of queries

    @classmethod
    def open(cls, opts: SessionOptions, role: str) -> "ZenohTransport":
        """Open a session for ``role`` with :func:`bridge.session.open_session` (its
        configuration: endpoints, scouting, lease, TLS; SessionError on failure)."""
        return cls(open_session(opts, role))

    def __enter__(self) -> "ZenohTransport":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- publish / subscribe ---------------------------------------------------------------
    def publisher(self, key: str) -> ZenohPublisher:
        import zenoh

        pub = self.session.declare_publisher(
            key, express=True, priority=zenoh.Priority.REAL_TIME,
            congestion_control=zenoh.CongestionControl.BLOCK,
            encoding=zenoh.Encoding(M.CONTENT_TYPE))
        p = ZenohPublisher(pub, key)
        if self._entity is None:
            self._entity = p.entity
        return p

    def subscribe(self, key: str, callback: Callable[[Sample], None]) -> _Declared:
        def on_sample(s) -> None:
            si = s.source_info
            if si is None:
                callback(Sample(str(s.key_expr), s.payload.to_bytes(), None, None))
            else:
                sid = si.source_id
                callback(Sample(str(s.key_expr), s.payload.to_bytes(),
                                None if sid is None else str(sid.zid), si.source_sn))

        return _Declared(self.session.declare_subscriber(key, on_sample))

    # ---- query / reply ---------------------------------------------------------------------
    def queryable(self, key: str, callback: Callable[[Query], None]) -> _Declared:
        def on_query(q) -> None:
            def answer(ok: bool, payload: bytes) -> None:
                if ok:
                    q.reply(key, payload, encoding=M.CONTENT_TYPE)
                else:
                    q.reply_err(payload)

            payload = q.payload.to_bytes() if q.payload is not None else None
            callback(Query(str(q.key_expr), dict(q.parameters), payload, _sender(q), answer))

        return _Declared(self.session.declare_queryable(key, on_query))

    def query(self, selector: str, payload: bytes | None = None, *, sn: int = 0,
              timeout: float = 1.0) -> list[Reply]:
        import zenoh

        entity = self._entity if self._entity is not None else self.session.id
        out = []
        for r in self.session.get(selector, payload=payload,
                                  source_info=zenoh.SourceInfo(entity, int(sn) & _SN_MASK),
                                  target=zenoh.QueryTarget.ALL,
                                  consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout):
            rid = None if r.replier_id is None else str(r.replier_id.zid)
            if r.ok is None and rid is None:
                continue  # Zenoh's own end of the query (a timeout), nobody's answer
            if r.ok is not None:
                out.append(Reply(rid, r.ok.payload.to_bytes(), True, str(r.ok.key_expr)))
            else:
                out.append(Reply(rid, r.err.payload.to_bytes(), False))
        return out

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
        return [str(r.ok.key_expr) for r in self.session.liveliness().get(key, timeout=timeout)
                if r.ok is not None]

    def close(self) -> None:
        if self._owns:
            self.session.close()
