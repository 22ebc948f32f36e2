"""The transport seam (bridge/transport.py): one contract, run against both implementations
(the Zenoh sessions of the processes and the in-memory loopback bus of the tests), then the
loopback's own rules (Zenoh's key-expression matching, its faults, its threads)."""

from __future__ import annotations

import re
import threading
from pathlib import Path

import pytest

from msagv.bridge.loopback import LoopbackBus, intersects, key_chunks, parse_selector
from msagv.bridge.transport import Query, Transport, TransportError
from helpers import ep, free_port, wait_until

ROOT = Path(__file__).resolve().parents[1]


# ---- the contract, on both implementations ------------------------------------------------
@pytest.fixture(params=["loopback", "zenoh"])
def pair(request):
    """Two endpoints of one bus, ``(a, b)``: two loopback endpoints, or two Zenoh sessions
    on a free loopback port (``a`` listens, ``b`` connects; scouting off)."""
    if request.param == "loopback":
        bus = LoopbackBus()
        yield bus.endpoint("a"), bus.endpoint("b")
        assert not bus.errors
        return
    from msagv.bridge.session import SessionOptions
    from msagv.bridge.zenoh_transport import ZenohTransport

    port = free_port()
    a = ZenohTransport.open(SessionOptions(listen=[ep(port)]), "tool")
    try:
        b = ZenohTransport.open(SessionOptions(connect=[ep(port)]), "tool")
        try:
            yield a, b
        finally:
            b.close()
    finally:
        a.close()


def _connected(a, b) -> None:
    """Wait until a subscriber of ``b`` matches a publisher of ``a`` (Zenoh propagates
    declarations asynchronously; the loopback at once)."""
    probe = b.subscribe("probe/x", lambda s: None)
    pub = a.publisher("probe/x")
    wait_until(lambda: pub.matching, 10.0, "the two endpoints to connect")
    pub.close()
    probe.close()


def test_both_implementations_are_transports(pair):
    a, b = pair
    assert isinstance(a, Transport) and isinstance(b, Transport)
    assert a.id != b.id and a.id and b.id


def test_a_subscriber_gets_every_message_in_order_with_the_senders_identity(pair):
    a, b = pair
    got, other = [], []
    sub = b.subscribe("msagv/t0/*", got.append)
    b.subscribe("msagv/t1/state", other.append)
    pub = a.publisher("msagv/t0/state")
    wait_until(lambda: pub.matching, 10.0, "the subscriber")
    for i in range(50):
        pub.put(bytes([i]) * 3, 1000 + i)
    wait_until(lambda: len(got) == 50, 10.0, "50 messages")
    assert [s.payload for s in got] == [bytes([i]) * 3 for i in range(50)]
    assert [s.sn for s in got] == list(range(1000, 1050))
    assert {s.sender for s in got} == {a.id} and {s.key for s in got} == {"msagv/t0/state"}
    assert not other  # another vehicle's key
    sub.close()
    wait_until(lambda: not pub.matching, 10.0, "the subscriber to go")
    pub.put(b"late", 2)
    assert len(got) == 50


def test_a_query_reaches_the_queryable_with_the_queriers_identity(pair):
    a, b = pair
    seen: list[Query] = []

    def on_query(q: Query) -> None:
        seen.append(q)
        if q.payload == b"bad":
            q.reply_err(b"refused")
        else:
            q.reply(b"answer to " + (q.payload or b"nothing"))

    qbl = a.queryable("msagv/t0/params", on_query)
    _connected(a, b)
    wait_until(lambda: b.query("msagv/t0/params", timeout=1.0), 10.0, "the queryable")
    replies = b.query("msagv/t0/params?wheel_wear=1;x", b"claim", sn=7, timeout=2.0)
    # (Zenoh may add an error reply of its own, a timeout: the nodes read ok replies only)
    assert [(r.sender, r.payload, r.key) for r in replies if r.ok] == [
        (a.id, b"answer to claim", "msagv/t0/params")]
    q = seen[-1]
    assert (q.key, q.parameters, q.payload, q.sender) == (
        "msagv/t0/params", {"wheel_wear": "1", "x": ""}, b"claim", b.id)
    err = b.query("msagv/t0/params", b"bad", timeout=2.0)
    # an error reply names nobody (on Zenoh the replier's identity is in an ok reply's key)
    assert not [r for r in err if r.ok] and (None, b"refused", False) in [
        (r.sender, r.payload, r.ok) for r in err]
    assert b.query("msagv/t1/params", timeout=0.5) == []  # nobody answers another vehicle
    qbl.close()


def test_tokens_are_watched_with_history_and_queried(pair):
    a, b = pair
    first = a.declare_token("msagv/t0/alive/plant/" + a.id)
    _connected(a, b)
    events: list[tuple[str, bool]] = []
    watch = b.watch_tokens("msagv/t0/alive/*/*", lambda k, p: events.append((k, p)))
    wait_until(lambda: events, 10.0, "the existing token (history)")
    assert events == [("msagv/t0/alive/plant/" + a.id, True)]
    second = a.declare_token("msagv/t0/alive/controller/x")
    wait_until(lambda: len(events) == 2, 10.0, "the new token")
    assert events[1] == ("msagv/t0/alive/controller/x", True)
    assert sorted(b.tokens("msagv/t0/alive/**", timeout=1.0)) == sorted(
        ["msagv/t0/alive/plant/" + a.id, "msagv/t0/alive/controller/x"])
    first.close()
    wait_until(lambda: len(events) == 3, 10.0, "the token's disappearance")
    assert events[2] == ("msagv/t0/alive/plant/" + a.id, False)
    assert b.tokens("msagv/t0/alive/plant/*", timeout=1.0) == []
    watch.close()
    second.close()


def test_a_closed_endpoints_tokens_disappear(pair):
    a, b = pair
    token = a.declare_token("msagv/t0/alive/plant/" + a.id)  # kept: a dropped token goes
    _connected(a, b)
    events: list[tuple[str, bool]] = []
    b.watch_tokens("msagv/t0/alive/plant/*", lambda k, p: events.append((k, p)))
    wait_until(lambda: events, 10.0, "the token")
    a.close()
    wait_until(lambda: len(events) == 2, 10.0, "the token to go with its endpoint")
    assert events[1] == ("msagv/t0/alive/plant/" + a.id, False)
    del token


# ---- the loopback: Zenoh's key expressions ---------------------------------------------------
@pytest.mark.parametrize("a, b, want", [
    ("msagv/agv0/state", "msagv/agv0/state", True),
    ("msagv/agv0/state", "msagv/agv1/state", False),
    ("msagv/agv0/alive/controller/*", "msagv/agv0/alive/controller/c1", True),
    ("msagv/agv0/alive/controller/*", "msagv/agv0/alive/controller", False),  # * is one chunk
    ("msagv/agv0/alive/controller/*", "msagv/agv0/alive/controller/c1/x", False),
    ("msagv/**", "msagv", True),  # ** is zero or more chunks
    ("msagv/**", "msagv/agv0/alive/plant/p1", True),
    ("msagv/**/plant/*", "msagv/agv0/alive/plant/p1", True),
    ("msagv/**/plant/*", "msagv/agv0/alive/controller/p1", False),
    ("msagv/*/state", "msagv/**", True),  # wildcards on both sides
    ("msagv/*/state", "*/agv0/*", True),
    ("a/*/c", "a/b/*/c", False),
    ("**", "anything/at/all", True),
])
def test_key_expressions_intersect_as_zenohs_do(a, b, want):
    assert intersects(key_chunks(a), key_chunks(b)) is want
    assert intersects(key_chunks(b), key_chunks(a)) is want  # symmetric


@pytest.mark.parametrize("bad, why", [
    ("", "non-empty"), ("a//b", "empty chunks"), ("a/", "empty chunks"), ("/a", "empty chunks"),
    ("a/b?x=1", r"'\?'"), ("a/#", r"'\?', '#'"), ("a/$*", r"'\$'"), ("a/*b", "whole chunks"),
    ("a/**/**", r"'\*\*/\*\*'"), (None, "non-empty string"),
])
def test_a_bad_key_expression_is_refused_and_declares_nothing(bad, why):
    bus = LoopbackBus()
    e = bus.endpoint("e")
    for declare in (lambda: e.subscribe(bad, print), lambda: e.queryable(bad, print),
                    lambda: e.declare_token(bad), lambda: e.watch_tokens(bad, print),
                    lambda: e.publisher(bad), lambda: e.tokens(bad)):
        with pytest.raises(TransportError, match=why):
            declare()
    assert all(not t for t in bus._tables.values())


def test_selectors_and_publisher_keys():
    assert parse_selector("msagv/a/params?wheel_wear=1;v;x=a=b") == (
        "msagv/a/params", {"wheel_wear": "1", "v": "", "x": "a=b"})
    assert parse_selector("msagv/a/params") == ("msagv/a/params", {})
    e = LoopbackBus().endpoint("e")
    with pytest.raises(TransportError, match="no wildcards"):
        e.publisher("msagv/*/state")
    for bad in ("", "a/b", "a*", "x?", 7):
        with pytest.raises(TransportError, match="identity"):
            LoopbackBus().endpoint(bad)


# ---- the loopback: faults ------------------------------------------------------------------
def test_a_rogue_may_take_any_identity_and_inject_may_send_none():
    bus = LoopbackBus()
    plant, rogue = bus.endpoint("p1"), bus.endpoint("p1")  # the same identity: a spoof
    got = []
    bus.endpoint("c1").subscribe("msagv/t0/state", got.append)
    plant.publisher("msagv/t0/state").put(b"1", 1)
    rogue.publisher("msagv/t0/state").put(b"2", 2)
    assert bus.inject("msagv/t0/state", b"3") == 1
    assert bus.inject("msagv/t0/state", b"4", sender="c9", sn=4) == 1
    assert [(s.payload, s.sender, s.sn) for s in got] == [
        (b"1", "p1", 1), (b"2", "p1", 2), (b"3", None, None), (b"4", "c9", 4)]
    assert len(bus.endpoint().id) == 32  # a fresh identity looks like a Zenoh session id


def test_drop_loses_the_next_messages_on_a_key_only():
    bus = LoopbackBus()
    got = []
    bus.endpoint("c").subscribe("msagv/t0/**", got.append)
    pub = bus.endpoint("p").publisher("msagv/t0/state")
    ref = bus.endpoint("r").publisher("msagv/t0/reference")
    bus.drop("msagv/t0/state", count=2)
    for i in range(4):
        pub.put(bytes([i]), i)
        ref.put(bytes([10 + i]), i)
    assert [s.payload for s in got] == [b"\x0a", b"\x0b", b"\x02", b"\x0c", b"\x03", b"\x0d"]
    assert bus.dropped == 2 and bus.delivered == 6
    with pytest.raises(TransportError, match="count"):
        bus.drop("msagv/t0/state", count=0)


def test_vanish_removes_a_token_without_its_endpoint():
    bus = LoopbackBus()
    holder, watcher = bus.endpoint("c1"), bus.endpoint("p1")
    tok = holder.declare_token("msagv/t0/alive/controller/c1")
    events = []
    watcher.watch_tokens("msagv/t0/alive/controller/*", lambda k, p: events.append((k, p)))
    assert bus.vanish("msagv/t0/alive/controller/*") == 1
    assert events == [("msagv/t0/alive/controller/c1", True),
                      ("msagv/t0/alive/controller/c1", False)]
    assert watcher.tokens("msagv/t0/alive/**") == []
    tok.close()  # the holder closes it later: nothing more happens
    assert len(events) == 2 and bus.vanish("msagv/t0/alive/**") == 0


def test_a_dropped_token_goes_as_on_zenoh():
    bus = LoopbackBus()
    e = bus.endpoint("e")
    e.declare_token("a/dropped")  # the handle is not kept: undeclared at once
    kept = e.declare_token("a/kept")
    e.subscribe("a/sub", print)  # a subscription lives on without its handle
    assert bus.tokens("a/*") == ["a/kept"] and bus._matching(key_chunks("a/sub"))
    del kept
    assert bus.tokens("a/*") == []


def test_a_closed_endpoint_refuses_everything():
    bus = LoopbackBus()
    e = bus.endpoint("e")
    pub = e.publisher("a/b")
    e.close()
    e.close()  # twice: nothing more
    for call in (lambda: pub.put(b"x", 0), lambda: e.subscribe("a/b", print),
                 lambda: e.query("a/b"), lambda: e.declare_token("a/b"), lambda: e.tokens("a/b"),
                 lambda: e.publisher("a/c")):
        with pytest.raises(TransportError, match="closed"):
            call()
    assert not pub.matching


# ---- the loopback: threads -------------------------------------------------------------------
def test_delivery_is_synchronous_and_a_callback_may_publish_and_query():
    """A ping-pong of 60 messages between two endpoints, each answer published from
    within the callback (and a query made from one): every delivery nests on the sender's
    thread, no lock is held across a callback, nothing deadlocks."""
    bus = LoopbackBus()
    a, b = bus.endpoint("a"), bus.endpoint("b")
    to_b, to_a = a.publisher("x/b"), b.publisher("x/a")
    b.queryable("x/q", lambda q: q.reply(b"ok"))
    log: list[tuple[str, int]] = []
    threads = set()

    def on_b(s):
        n = s.sn
        log.append(("b", n))
        threads.add(threading.get_ident())
        if n < 60:
            assert [r.payload for r in b.query("x/q")] == [b"ok"]
            to_a.put(b"", n + 1)

    def on_a(s):
        log.append(("a", s.sn))
        threads.add(threading.get_ident())
        to_b.put(b"", s.sn + 1)

    b.subscribe("x/b", on_b)
    a.subscribe("x/a", on_a)
    done = threading.Event()
    t = threading.Thread(target=lambda: (to_b.put(b"", 0), done.set()), daemon=True)
    t.start()
    assert done.wait(10), "the ping-pong deadlocked"
    assert log == [("b" if n % 2 == 0 else "a", n) for n in range(61)]
    assert threads == {t.ident}  # all of it ran on the first sender's thread
    assert not bus.errors


def test_a_callbacks_exception_stays_on_the_bus():
    bus = LoopbackBus()
    got = []
    bus.endpoint("c").subscribe("a/b", lambda s: 1 / 0)
    bus.endpoint("d").subscribe("a/b", got.append)
    bus.endpoint("p").publisher("a/b").put(b"x", 0)  # the sender sees nothing
    assert len(got) == 1 and len(bus.errors) == 1
    assert isinstance(bus.errors[0], ZeroDivisionError)


def test_every_queryable_answers_a_query():
    bus = LoopbackBus()
    for name in ("p1", "p2"):
        bus.endpoint(name).queryable("msagv/t0/params", lambda q, n=name: q.reply(n.encode()))
    bus.endpoint("x").queryable("msagv/t1/params", lambda q: q.reply(b"x"))
    replies = bus.endpoint("c").query("msagv/*/params")
    assert sorted((r.sender, r.payload) for r in replies) == [
        ("p1", b"p1"), ("p2", b"p2"), ("x", b"x")]


# ---- the worked example of docs/ARCHITECTURE.md ----------------------------------------------
def test_the_architecture_docs_worked_example_runs():
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    m = re.search(r"<!-- example: transport[^>]*-->\s*```python\n(.*?)```", text, re.S)
    assert m, "docs/ARCHITECTURE.md has no example 'transport'"
    code = m.group(1)
    ns: dict = {}
    exec(compile(code, "ARCHITECTURE.md", "exec"), ns)
    assert ns["summary"]["completed"] and ns["summary"]["rejected"]["by_reason"] == {
        "not_owner": 1}
