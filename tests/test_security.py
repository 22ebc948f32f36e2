"""Secure deployments and safe configuration (issue 13, items 2 and 3): certificates,
mutual TLS and access control with Zenoh's own security, the config-file merge and the
transport's message size limit. Processes use loopback TLS endpoints on free ports and are
always stopped (the ``procs`` fixture); assertions are on counts and behaviour."""

from __future__ import annotations

import json
import stat
import subprocess
import threading
import time

import pytest

from msagv.bridge import messages as M
from msagv.bridge.security import SecurityError, acl_config, create_certs, parse_extra, read_manifest
from msagv.bridge.session import (MAX_MESSAGE_BYTES, Keys, SessionError, SessionOptions,
                            make_config, open_session)
from helpers import free_port, msagv, wait_until

T = 0.01


def tls(port: int) -> str:
    return f"tls/127.0.0.1:{port}"


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    """A CA; plant and controller identities for agv0 and agv1, a router and an operator;
    an observer of every vehicle and a second controller identity for agv0."""
    d = tmp_path_factory.mktemp("certs")
    create_certs(d, [parse_extra("monitor"), parse_extra("spare:controller:agv0")],
                 vehicles=("agv0", "agv1"))
    return d


# ---- certificates ------------------------------------------------------------------------------
def test_certs_have_one_identity_per_role_and_vehicle_and_private_keys_only_for_the_owner(certs):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    m = read_manifest(certs)
    assert m["identities"] == {
        "plant-agv0": {"cn": "msagv-plant-agv0", "role": "plant", "vehicles": ["agv0"]},
        "controller-agv0": {"cn": "msagv-controller-agv0", "role": "controller",
                            "vehicles": ["agv0"]},
        "plant-agv1": {"cn": "msagv-plant-agv1", "role": "plant", "vehicles": ["agv1"]},
        "controller-agv1": {"cn": "msagv-controller-agv1", "role": "controller",
                            "vehicles": ["agv1"]},
        "router": {"cn": "msagv-router", "role": "router", "vehicles": ["*"]},
        "operator": {"cn": "msagv-operator", "role": "operator", "vehicles": ["*"]},
        "monitor": {"cn": "monitor", "role": "observer", "vehicles": ["*"]},
        "spare": {"cn": "spare", "role": "controller", "vehicles": ["agv0"]}}
    ca = x509.load_pem_x509_certificate((certs / "ca.pem").read_bytes())
    for name, v in m["identities"].items():
        c = x509.load_pem_x509_certificate((certs / f"{name}.pem").read_bytes())
        assert c.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == v["cn"]
        assert c.issuer == ca.subject
        c.verify_directly_issued_by(ca)
        assert stat.S_IMODE((certs / f"{name}.key").stat().st_mode) == 0o600
    assert stat.S_IMODE((certs / "ca.key").stat().st_mode) == 0o600


def test_certs_complete_a_directory_with_the_same_ca(tmp_path):
    create_certs(tmp_path)
    ca = (tmp_path / "ca.pem").read_bytes()
    plant = (tmp_path / "plant-agv0.pem").read_bytes()
    create_certs(tmp_path, [("dash", "observer")], vehicles=("agv0", "agv7"))
    assert (tmp_path / "ca.pem").read_bytes() == ca
    assert (tmp_path / "plant-agv0.pem").read_bytes() == plant  # kept
    ids = read_manifest(tmp_path)["identities"]
    assert "dash" in ids and ids["plant-agv7"]["vehicles"] == ["agv7"]
    with pytest.raises(SecurityError, match="role observer, not plant"):
        create_certs(tmp_path, [("dash", "plant")])
    with pytest.raises(SecurityError, match="per vehicle"):
        create_certs(tmp_path, vehicles=("*",))


def test_a_directory_of_the_first_version_serves_every_vehicle(tmp_path):
    """roles.json without vehicles (msagv certs before per-vehicle certificates): read as
    every vehicle, so such a deployment keeps working (and keeps its limit: SECURITY.md)."""
    create_certs(tmp_path)
    m = json.loads((tmp_path / "roles.json").read_text())
    for v in m["identities"].values():
        del v["vehicles"]
    (tmp_path / "roles.json").write_text(json.dumps(m))
    assert {v["vehicles"][0] for v in read_manifest(tmp_path)["identities"].values()} == {"*"}


@pytest.mark.parametrize("args,msg", [
    (["--extra", "a/b"], "not a valid identity name"),
    (["--extra", "x:pilot"], "role must be one of"),
    (["--extra", "x:observer:a/b"], "is not a vehicle id"),
    (["--vehicle", "a b"], "is not a vehicle id"),
    (["--san", "bad host"], "neither an IP address nor a host name"),
    (["--days", "0"], "--days must be 1..36500"),
])
def test_msagv_certs_bad_input_one_line_and_nothing_written(tmp_path, args, msg):
    r = subprocess.run(msagv("certs", tmp_path / "d", *args), capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and msg in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "d" / "roles.json").exists()


def _may(acl, cn: str, message: str, key: str, flow: str = "ingress") -> bool:
    """Whether ``acl`` lets the certificate ``cn`` send ``message`` on ``key`` (Zenoh's rule:
    a rule applies when its key expression includes the message's, zenoh.KeyExpr)."""
    import zenoh

    rules = {r["id"]: r for r in acl["rules"]}
    subj = {x["id"] for x in acl["subjects"] if cn in x["cert_common_names"]}
    k = zenoh.KeyExpr(key)
    return any(message in rules[r]["messages"] and rules[r]["flows"] == [flow]
               and any(zenoh.KeyExpr(e).includes(k) for e in rules[r]["key_exprs"])
               for p in acl["policies"] if subj & set(p["subjects"]) for r in p["rules"])


def test_acl_lets_each_certificate_send_only_under_its_own_name_for_its_vehicle(certs):
    acl = acl_config(read_manifest(certs))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    may = lambda cn, m, k: _may(acl, cn, m, k)  # noqa: E731
    C0, C1, P0 = "msagv-controller-agv0", "msagv-controller-agv1", "msagv-plant-agv0"
    # a controller: its vehicle's cmd under its own name, claims and params of its vehicle
    assert may(C0, "put", f"msagv/agv0/cmd/{C0}")
    assert not may(C0, "put", f"msagv/agv0/cmd/{C1}")  # another's name
    assert not may(C0, "put", "msagv/agv0/cmd/spare") and not may(C0, "put", "msagv/agv0/cmd/*")
    assert not may(C1, "put", f"msagv/agv0/cmd/{C1}")  # another vehicle
    assert not may(C0, "put", f"msagv/agv0/state/{C0}")
    assert may(C0, "query", f"msagv/agv0/claim/*/{C0}") and may(C0, "query", f"msagv/agv0/claim/{P0}/{C0}")
    assert not may(C0, "query", f"msagv/agv0/claim/*/{C1}") and not may(C0, "query", "msagv/agv0/claim/**")
    assert not may(C1, "query", f"msagv/agv0/claim/*/{C1}")
    assert not may(C0, "query", f"msagv/agv0/arm/*/{C0}")  # only an operator arms
    assert not may(C0, "reply", f"msagv/agv0/params/{C0}/x")
    assert may(C0, "liveliness_token", f"msagv/agv0/alive/controller/{C0}")
    assert not may(C0, "liveliness_token", f"msagv/agv0/alive/controller/{C1}")
    assert not may(C0, "liveliness_token", f"msagv/agv0/alive/plant/{C0}")
    assert may("spare", "put", "msagv/agv0/cmd/spare") and not may("spare", "put", f"msagv/agv0/cmd/{C0}")
    # a plant: its states, its answers, its token; nothing of another vehicle
    assert may(P0, "put", f"msagv/agv0/state/{P0}") and not may(P0, "put", f"msagv/agv0/cmd/{P0}")
    assert may(P0, "reply", f"msagv/agv0/claim/{P0}/{C0}") and may(P0, "declare_queryable",
                                                                     f"msagv/agv0/arm/{P0}/*")
    assert not may(P0, "reply", f"msagv/agv0/claim/msagv-plant-agv1/{C0}")
    assert not may(P0, "put", "msagv/agv1/state/msagv-plant-agv0")
    # an operator arms any vehicle; an observer only reads and asks params
    assert may("msagv-operator", "query", "msagv/agv1/arm/*/msagv-operator")
    assert not may("msagv-operator", "put", "msagv/agv1/cmd/msagv-operator")
    assert may("monitor", "query", "msagv/agv0/params/*/monitor")
    assert may("monitor", "declare_subscriber", "msagv/agv0/state/*")
    assert not any(may("monitor", m, k) for m in ("put", "reply", "liveliness_token")
                   for k in (f"msagv/agv0/cmd/monitor", "msagv/agv0/state/monitor",
                             "msagv/agv0/params/monitor/x", "msagv/agv0/alive/controller/monitor"))
    assert not may("monitor", "query", "msagv/agv0/claim/*/monitor")
    # a client of version 1 (bare keys) reaches the plant, to be told why it is refused
    assert may(C0, "put", "msagv/agv0/cmd") and may(C0, "query", "msagv/agv0/claim")
    # what the plant sends a controller of another vehicle: nothing of agv0
    assert not _may(acl, C1, "put", f"msagv/agv0/state/{P0}", flow="egress")
    assert _may(acl, C0, "put", f"msagv/agv0/state/{P0}", flow="egress")


def test_acl_of_every_certificate_msagv_certs_makes(certs):
    """Issue 30, item 3: every identity of the directory against every name and vehicle:
    what it may send is exactly its role's, under its own name, for its vehicles; the
    router's certificate forwards only where the process reaches it as a client, and may
    do nothing on a peer's links (there it would be a master key)."""
    m = read_manifest(certs)
    ids = m["identities"]
    names = sorted(v["cn"] for v in ids.values()) + ["x"]
    for routed in (True, False):
        acl = acl_config(m, routed=routed)
        for ident, v in ids.items():
            cn, role, vids = v["cn"], v["role"], v["vehicles"]
            for vid in ("agv0", "agv1"):
                mine = "*" in vids or vid in vids
                for n in names:
                    own = n == cn and mine
                    want = {
                        ("put", f"msagv/{vid}/state/{n}"): role == "plant" and own,
                        ("put", f"msagv/{vid}/cmd/{n}"): role == "controller" and own,
                        ("liveliness_token", f"msagv/{vid}/alive/controller/{n}"):
                            role == "controller" and own,
                        ("liveliness_token", f"msagv/{vid}/alive/plant/{n}"): role == "plant" and own,
                        ("query", f"msagv/{vid}/claim/*/{n}"): role == "controller" and own,
                        ("query", f"msagv/{vid}/arm/*/{n}"): role == "operator" and own,
                        ("reply", f"msagv/{vid}/claim/{n}/x"): role == "plant" and own,
                        ("reply", f"msagv/{vid}/arm/{n}/x"): role == "plant" and own,
                    }
                    for (msg, key), allowed in want.items():
                        if role == "router":
                            allowed = routed
                        got = _may(acl, cn, msg, key)
                        assert got == allowed, (ident, routed, msg, key, got)
                # reading: every identity of the vehicle, the router only where it routes
                reads = _may(acl, cn, "declare_subscriber", f"msagv/{vid}/state/*")
                assert reads == (routed if role == "router" else mine), (ident, routed, vid)
                egress = _may(acl, cn, "put", f"msagv/{vid}/state/x", flow="egress")
                assert egress == (routed if role == "router" else mine), (ident, routed, vid)


# ---- session configuration ------------------------------------------------------------------
def test_secure_config_needs_tls_endpoints_and_a_complete_directory(certs, tmp_path):
    c = make_config(SessionOptions(secure_dir=str(certs)), "plant")
    assert json.loads(c.get_json("listen/endpoints")) == ["tls/127.0.0.1:7448"]
    assert json.loads(c.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(c.get_json("access_control/enabled")) is True
    c = make_config(SessionOptions(secure_dir=str(certs)), "controller")
    assert json.loads(c.get_json("connect/endpoints")) == ["tls/127.0.0.1:7448"]
    with pytest.raises(SessionError, match="is not TLS"):
        make_config(SessionOptions(secure_dir=str(certs), connect=["tcp/127.0.0.1:1"]),
                    "controller")
    with pytest.raises(SessionError, match="not a directory"):
        make_config(SessionOptions(secure_dir=str(tmp_path / "nope")), "plant")
    with pytest.raises(SessionError, match="no identity for a tool of vehicle 'agv0'"):
        make_config(SessionOptions(secure_dir=str(certs)), "tool")
    # a process uses ROLE-ID: the plant of agv1 gets agv1's certificate
    from msagv.bridge.session import secure_identity

    assert secure_identity(SessionOptions(id="agv1", secure_dir=str(certs)), "plant") == \
        "msagv-plant-agv1"
    assert secure_identity(SessionOptions(secure_dir=str(certs)), "operator") == "msagv-operator"
    with pytest.raises(SessionError, match="no identity for a plant of vehicle 'agv2'"):
        make_config(SessionOptions(id="agv2", secure_dir=str(certs)), "plant")
    with pytest.raises(SessionError, match="serves vehicle.s. agv0, not 'agv1'"):
        make_config(SessionOptions(id="agv1", secure_dir=str(certs), identity="spare"),
                    "controller")


def test_a_config_file_is_merged_with_the_safe_defaults(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text("{ // only a lease\n transport: { link: { tx: { keep_alive: 4 } } }, }\n")
    c = make_config(SessionOptions(config_file=str(f)), "plant")
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7448"]
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False
    assert json.loads(c.get_json("scouting/gossip/enabled")) is False
    assert json.loads(c.get_json("transport/link/rx/max_message_size")) == MAX_MESSAGE_BYTES
    # what the file sets explicitly wins; the command line wins over the file
    f.write_text("{ scouting: { multicast: { enabled: true } }, "
                 "listen: { endpoints: ['tcp/127.0.0.1:9999'] }, "
                 "transport: { link: { rx: { max_message_size: 1000000 } } } }")
    c = make_config(SessionOptions(config_file=str(f)), "plant")
    assert json.loads(c.get_json("scouting/multicast/enabled")) is True
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:9999"]
    assert json.loads(c.get_json("connect/endpoints")) == []
    assert json.loads(c.get_json("transport/link/rx/max_message_size")) == 1000000
    c = make_config(SessionOptions(config_file=str(f), listen=["tcp/127.0.0.1:8888"]), "plant")
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:8888"]
    f.write_text("{ mode: ")
    with pytest.raises(SessionError, match="not JSON5"):
        make_config(SessionOptions(config_file=str(f)), "plant")


def test_a_config_file_may_set_the_session_id(tmp_path):
    """docs/PROTOCOL.md section 1 (issue 27, item 3): the file's ``id`` is kept (on a plain
    bus it is then the process's identity); one Zenoh refuses (a leading zero) is a
    SessionError naming the file (exit 2)."""
    f = tmp_path / "z.json5"
    f.write_text('{ id: "abc123" }')
    c = make_config(SessionOptions(config_file=str(f)), "plant")
    assert json.loads(c.get_json("id")) == "abc123"
    f.write_text('{ id: "0abc123" }')
    with pytest.raises(SessionError, match="--zenoh-config .*0abc123"):
        make_config(SessionOptions(config_file=str(f)), "plant")


# ---- processes ----------------------------------------------------------------------------
OWNER = "msagv-controller-agv0"  # the controller's certificate: its name on the bus


def _listening(port: int) -> bool:
    """Something accepts TCP connections on loopback ``port``."""
    import socket

    with socket.socket() as so:
        so.settimeout(0.5)
        return so.connect_ex(("127.0.0.1", port)) == 0


class Peer:
    """A session that is not an msagv process: TLS with ``identity``'s certificate (None:
    no certificate), no access-control rules of its own, the Zenoh session id ``zid``
    (None: its own). It answers every state it sees with a command under its own name and
    under the owner's, claims the vehicle as itself and in the owner's name, declares its
    own token and the owner's, and asks ``params`` (``wheel_wear`` could be set that way
    in version 1)."""

    def __init__(self, certs, identity: str | None, port: int, zid: str | None = None):
        import zenoh

        conf = zenoh.Config()
        for k, v in (("mode", '"peer"'), ("connect/endpoints", json.dumps([tls(port)])),
                     ("listen/endpoints", "[]"), ("scouting/multicast/enabled", "false"),
                     ("scouting/gossip/enabled", "false")):
            conf.insert_json5(k, v)
        if zid is not None:
            conf.insert_json5("id", json.dumps(zid))
        t = {"root_ca_certificate": str(certs / "ca.pem"), "enable_mtls": True}
        if identity is not None:
            key, pem = str(certs / f"{identity}.key"), str(certs / f"{identity}.pem")
            t.update(connect_private_key=key, connect_certificate=pem,
                     listen_private_key=key, listen_certificate=pem)
        conf.insert_json5("transport/link/tls", json.dumps(t))
        self.keys = Keys("agv0")
        self.name = read_manifest(certs)["identities"][identity]["cn"] if identity else "nobody"
        self.session = zenoh.open(conf)
        self.pubs = [self.session.declare_publisher(f"{self.keys.cmd}/{n}")
                     for n in (self.name, OWNER)]
        self.states = 0
        self.wheel_wear_states = 0
        self.sent = 0
        self.granted = 0
        self.answers = 0  # ok replies to its params queries
        self._sub = self.session.declare_subscriber(f"{self.keys.state}/*", self._on_state)
        self.tokens = [self.session.liveliness().declare_token(self.keys.controller_token(n))
                       for n in (self.name, OWNER)]
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._claim, daemon=True)
        self._t.start()

    def _on_state(self, s):
        try:
            st = M.decode_state(s.payload.to_bytes(), 4)
        except M.MessageError:
            return
        self.states += 1
        self.wheel_wear_states += "W_s_ij" in st
        if not st.get("end"):
            c = M.encode_cmd(10 ** 9 + self.sent, st["t"], st["seq"], [20.0] * 4, [0.8] * 4)
            for pub in self.pubs:
                pub.put(c)
                self.sent += 1

    def _claim(self):
        from msagv.bridge.ownership import encode_claim

        while not self._stop.wait(0.1):
            for name in (self.name, OWNER):
                try:
                    for r in self.session.get(f"{self.keys.claim}/*/{name}", timeout=0.3,
                                              payload=encode_claim("claim", False)):
                        if r.ok is not None and M.unpack(r.ok.payload.to_bytes(), 1024)["granted"]:
                            self.granted += 1
                except Exception:
                    pass
            self.answers += self.params()

    def params(self) -> int:
        return sum(1 for r in self.session.get(f"{self.keys.params}/*/{self.name}", timeout=0.5)
                   if r.ok)

    def close(self):
        self._stop.set()
        self._t.join(2)
        for x in self.tokens + [self._sub] + self.pubs:
            x.undeclare()
        self.session.close()


@pytest.mark.timeout(300)
def test_secure_run_refuses_peers_without_a_certificate_or_of_the_wrong_role(procs, certs):
    """Issue 22, item 2: with --secure, a peer without a certificate gets no link; one with
    the CA's observer certificate, the plant's, or another vehicle's controller's answers
    every state under its own name and the owner's, claims as itself and as the owner and
    declares the owner's token: none of it reaches the plant (the access control drops it),
    the controller's 300 commands are the only ones, and the observer's params queries
    (answered) change nothing it receives. (A second controller certificate of this
    vehicle may claim it: the first claim wins; under the owner's name it may not send,
    test_acl_lets_each_certificate_send_only_under_its_own_name_for_its_vehicle.)"""
    P = free_port()
    procs.start("plant", msagv("plant", "--secure", certs, "--run-mode", "lockstep",
                               "--duration", 3, "--listen", tls(P), "--json", "-q"))
    peers = {}
    try:
        # the peers connect once the plant listens (on a loaded machine its start takes
        # seconds; a peer that dialled before it never linked and saw no state)
        wait_until(lambda: _listening(P), 120, "the plant's listener")
        for name, ident in (("nocert", None), ("observer", "monitor"),
                            ("plant_cert", "plant-agv0"), ("other_vehicle", "controller-agv1"),
                            ("router_cert", "router")):
            peers[name] = Peer(certs, ident, P)
        time.sleep(1.0)
        # issue 30, item 3: the router's certificate on a direct link arms nothing (it
        # forwards only for its clients): its arm reaches no plant, no reply comes back
        from msagv.bridge.ownership import encode_arm

        rs = peers["router_cert"].session
        armed = [r for r in rs.get(f"msagv/agv0/arm/*/msagv-router", payload=encode_arm(OWNER),
                                   timeout=2.0) if r.ok is not None]
        assert armed == []
        procs.start("ctl", msagv("controller", "--secure", certs, "--connect", tls(P),
                                 "--exit-at-end", "--json", "-q"))
        assert procs.wait("plant", 240) == 0, procs.err("plant")
        assert procs.wait("ctl", 30) == 0, procs.err("ctl")
        s, c = procs.json("plant"), procs.json("ctl")
        assert s["completed"] and s["steps"] == 300 and c["answered"] == 300
        assert c["plant_zid"] == "msagv-plant-agv0"  # bound to the plant's certificate
        cm = s["commands"]
        assert cm["accepted"] == 300 and cm["duplicate"] == 0 and cm["stale"] == 0
        # nothing of the refused peers reached the plant: no command, no claim, no token
        assert s["rejected"]["total"] == 0, s["rejected"]
        o = s["ownership"]
        assert o["grants"] == 1 and o["refused"] == 0 and o["banned"] == 0, o
        assert s["old_clients"] == 0
        nc = peers["nocert"]
        assert nc.states == 0 and nc.params() == 0 and not list(nc.session.info.peers_zid())
        assert all(p.granted == 0 for p in peers.values())
        # the observer may read and ask params: it saw the states, its queries were
        # answered, and the per-wheel wear the controller asked for went out throughout
        ob = peers["observer"]
        assert ob.states > 0 and ob.sent > 0 and ob.answers > 0
        assert ob.wheel_wear_states == 301  # taken with the grant: from state 0 on
        # another vehicle's controller gets nothing of agv0 (the plant's egress rules), nor
        # does the router's certificate on a peer's direct link
        assert peers["other_vehicle"].states == 0 and peers["router_cert"].states == 0
        print(f"\nsecure run: {cm['accepted']} commands accepted; "
              + ", ".join(f"{n} sent {p.sent}" for n, p in peers.items())
              + f"; none reached the plant; observer's params answered {ob.answers} times")
    finally:
        for p in peers.values():
            p.close()


@pytest.mark.timeout(300)
def test_secure_plant_and_controller_through_a_secure_router(procs, certs):
    """Through ``msagv router --secure``. The plant and the controller are started with
    the router, not after it: a client's session open waits for its router (it used to
    exit 2 when it came first, a flaky failure on a loaded machine)."""
    R = free_port()
    procs.start("router", msagv("router", "--secure", certs, "--listen", tls(R)))
    procs.start("plant", msagv("plant", "--secure", certs, "--mode", "client", "--connect",
                               tls(R), "--duration", 0.5, "--json", "-q"))
    procs.start("ctl", msagv("controller", "--secure", certs, "--mode", "client", "--connect",
                             tls(R), "--exit-at-end", "--json", "-q"))
    assert procs.wait("plant", 240) == 0, procs.err("plant")
    assert procs.wait("ctl", 30) == 0, procs.err("ctl")
    s = procs.json("plant")
    assert s["completed"] and s["commands"]["accepted"] == 50 and s["rejected"]["total"] == 0


@pytest.mark.timeout(120)
@pytest.mark.parametrize("args,msg", [
    (["plant", "--secure", "missing-dir"], "not a directory"),
    (["controller", "--secure", "CERTS", "--connect", "tcp/127.0.0.1:7448"], "is not TLS"),
    (["router", "--secure", "CERTS", "--listen", "tcp/127.0.0.1:7447"], "is not TLS"),
])
def test_secure_bad_options_exit_2_with_one_line(args, msg, certs, tmp_path):
    args = [str(certs) if a == "CERTS" else a for a in args]
    r = subprocess.run(msagv(*args), capture_output=True, text=True, timeout=100, cwd=tmp_path)
    assert r.returncode == 2 and msg in r.stderr, r.stderr


@pytest.mark.timeout(300)
def test_secure_demo_short(tmp_path):
    r = subprocess.run(msagv("demo", "--secure", "--json", "--duration", 2, "--plot",
                             tmp_path / "d.png"),
                       capture_output=True, text=True, timeout=250, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    tr = json.loads(r.stdout)["transport"]
    assert tr["secure"] is True and tr["rejected"] == 0 and tr["accepted_commands"] >= 100
    print(f"\nsecure demo 2 s: {tr}")


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_secure_demo_20s_100hz(tmp_path):
    """The secure demo at full length: 100 Hz with 0 missed periods (needs a machine that
    is not saturated by other work; the figures are printed either way)."""
    r = subprocess.run(msagv("demo", "--secure", "--json", "--plot", tmp_path / "d.png"),
                       capture_output=True, text=True, timeout=500, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    tr = json.loads(r.stdout)["transport"]
    print(f"\nsecure demo 20 s: {tr}")
    assert tr["secure"] is True and tr["rejected"] == 0
    assert tr["missed_periods"] == 0


# ---- the transport's message size limit ----------------------------------------------------
@pytest.mark.timeout(300)
def test_a_50_mb_message_is_dropped_before_it_reaches_the_realtime_plant_or_controller(procs):
    """Issue 22, item 4: Zenoh's limit (1 MiB + 64 KiB) drops a 50 MB command and a 50 MB
    state before they are buffered beyond it: neither reaches a process; a 200 KB command
    (over the protocol's 64 KiB, under Zenoh's limit) reaches the plant and is counted
    (from this tool: not_owner, the sender is checked first). Periods and safe events are
    printed (timing on a loaded machine is not asserted; the slow flood test is)."""
    from msagv.bridge.zenoh_transport import ZenohTransport

    P = free_port()
    procs.start("plant", msagv("plant", "--run-mode", "realtime", "--duration", 6, "--listen",
                               f"tcp/127.0.0.1:{P}", "--json", "-q"))
    procs.start("ctl", msagv("controller", "--connect", f"tcp/127.0.0.1:{P}", "--exit-at-end",
                             "--json", "-q"))
    with ZenohTransport.open(SessionOptions(connect=[f"tcp/127.0.0.1:{P}"]), "tool") as t:
        keys = Keys("agv0")
        states = []
        sub = t.subscribe(keys.state, lambda x: states.append(1))
        t0 = time.monotonic()
        while len(states) < 150:  # 1.5 s into the real-time run
            assert time.monotonic() - t0 < 180, procs.err("plant")
            time.sleep(0.02)
        cmd, state = t.publisher(keys.cmd), t.publisher(keys.state)
        cmd.put(M.pack({"v": 1}), 0)  # a small malformed command: it arrives
        cmd.put(b"\x80" + b"\x00" * (200 << 10), 1)  # 200 KB: it arrives
        time.sleep(0.2)
        big = b"\x00" * (50 * 1024 * 1024)
        assert len(big) > MAX_MESSAGE_BYTES
        cmd.put(big, 2)
        state.put(big, 3)
        assert procs.wait("plant", 120) == 0, procs.err("plant")
        assert procs.wait("ctl", 60) == 0, procs.err("ctl")
        sub.close()
    st, c = procs.json("plant"), procs.json("ctl")
    assert st["completed"] and st["steps"] == 600
    # the small ones reached the plant and were rejected; the 50 MB ones reached nobody
    assert st["rejected"]["total"] == 2 and st["rejected"]["by_reason"] == {M.NOT_OWNER: 2}
    assert c["rejected"]["total"] == 0
    print(f"\n50 MB on cmd and state: missed periods {st['missed_periods']}, lateness "
          f"{st['lateness_ms']}, safe {st['safe']}")
