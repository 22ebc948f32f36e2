"""The grant's key (bridge.link_key, docs/PROTOCOL.md section 3.9): both ends derive the same
keys, the tag covers every field, and a claim in the owner's name without its key changes
nothing. The derivation is recomputed here from the page's words with cryptography's
primitives and the standard library, not with the module."""

from __future__ import annotations

import hashlib
import hmac

import msgpack
import pytest
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.hashes import SHA256
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

from msagv.bridge import messages as M
from msagv.bridge.link_key import KeyPair, LinkKeyError, LinkKeys, derive
from msagv.bridge.ownership import (GRANTED, KEY_MISMATCH, OWNED, RELEASE, Ownership,
                                    RearmPolicy,
                                    decode_claim, decode_grant, encode_claim, encode_grant)


def _pub(sk: X25519PrivateKey) -> bytes:
    return sk.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)


def test_both_ends_derive_the_keys_the_page_describes():
    plant, ctl = KeyPair(), KeyPair()
    a = derive(plant, ctl.public, "agv0", "p1", "c1")  # the plant's side
    b = derive(ctl, plant.public, "agv0", "p1", "c1")  # the controller's
    assert a.cmd == b.cmd and a.state == b.state and a.cmd != a.state
    # from the page: HKDF-SHA256, no salt, info "msagv v2 grant key" 0 vehicle 0 P 0 C, 64
    # bytes: the command key first; an outsider's own pair gives another secret
    sk = X25519PrivateKey.generate()
    outsider = KeyPair()
    c = derive(outsider, plant.public, "agv0", "p1", "c1")
    assert c.cmd != a.cmd
    shared = sk.exchange(X25519PublicKey.from_public_bytes(plant.public))
    okm = HKDF(algorithm=SHA256(), length=64, salt=None,
               info=b"msagv v2 grant key\x00agv0\x00p1\x00c1").derive(shared)
    d = derive(plant, _pub(sk), "agv0", "p1", "c1")
    assert (d.cmd, d.state) == (okm[:32], okm[32:])
    # the names are in the key: another vehicle, plant or controller gets other keys
    for names in (("agv1", "p1", "c1"), ("agv0", "p2", "c1"), ("agv0", "p1", "c2")):
        assert derive(plant, ctl.public, *names).cmd != a.cmd


def test_a_command_tag_covers_every_field_and_is_the_pages_hmac():
    keys = derive(KeyPair(), KeyPair().public, "agv0", "p", "c")
    payload = M.encode_cmd(3, 0.03, 3, [8.0, 8.0, 8.0, 8.0], [0.0, 0.1, 0.0, 0.0],
                           solve_ms=1.5, cost=2.0, mac_key=keys.cmd)
    c = M.decode_cmd(payload, 4)
    assert LinkKeys.valid(keys.cmd, c) and not LinkKeys.valid(keys.state, c)
    # the page's canonical form: the other fields in sorted key order, floats as float 64
    body = {k: c[k] for k in sorted(c) if k != "mac"}
    want = hmac.new(keys.cmd, msgpack.packb(body, use_single_float=False),
                    hashlib.sha256).digest()[:16]
    assert c["mac"] == want and len(want) == 16
    for field, value in (("omega_w", [9.0, 8.0, 8.0, 8.0]), ("state_seq", 4), ("seq", 4),
                         ("t", 0.04), ("omega_s", [0.0] * 4), ("cost", 2.5)):
        assert not LinkKeys.valid(keys.cmd, dict(c, **{field: value})), field
    assert not LinkKeys.valid(keys.cmd, {k: v for k, v in c.items() if k != "mac"})
    assert not LinkKeys.valid(keys.cmd, dict(c, mac="not bytes"))
    # the tag does not depend on the order of the fields on the wire
    reordered = msgpack.packb(dict(reversed(list(msgpack.unpackb(payload).items()))))
    assert LinkKeys.valid(keys.cmd, M.decode_cmd(reordered, 4))


def test_a_state_carries_the_tag_and_a_mac_field_is_checked_as_binary():
    keys = derive(KeyPair(), KeyPair().public, "agv0", "p", "c")
    st = {"t": 0.5, "x": 1.0, "y": 2.0, "phi": 0.1, "vx": 4.0, "vy": 0.0, "r": 0.0,
          "delta": [0.0] * 4, "omega_w": [10.0] * 4, "W_s": 1.0, "W_alpha": 2.0, "W_t": 3.0}
    m = M.decode_state(M.encode_state(50, st, safe=False, mac_key=keys.state), 4)
    assert LinkKeys.valid(keys.state, m) and not LinkKeys.valid(keys.cmd, m)
    assert not LinkKeys.valid(keys.state, dict(m, safe=True))
    plain = msgpack.unpackb(M.encode_state(50, st))
    for bad, reason in ((dict(plain, mac=1.0), M.BAD_TYPE), (dict(plain, mac=b"\0" * 65),
                                                              M.BAD_LENGTH)):
        with pytest.raises(M.MessageError) as e:
            M.decode_state(msgpack.packb(bad, use_bin_type=True), 4)
        assert e.value.reason == reason


def test_a_public_key_that_is_not_one_is_refused():
    pair = KeyPair()
    for bad in (b"", b"\x01" * 31, b"\x00" * 32, "x" * 32):
        with pytest.raises(LinkKeyError):
            derive(pair, bad, "agv0", "p", "c")


def test_a_claim_in_the_owners_name_without_its_key_changes_nothing():
    """The key ``pk`` is public (every claim carries it): the owner's release needs the
    proof (a ``mac`` under the command key), a claim with another key is refused, and the
    owner's key without the proof is told ``granted`` and changes nothing."""
    o = Ownership()
    k1, k2 = KeyPair().public, KeyPair().public
    assert o.claim("c1", pk=k1, link="L1", wheel_wear=True).granted
    assert o.owner_link == ("c1", "L1") and o.wheel_wear
    assert o.claim("c1", pk=k1, proven=True).reason == GRANTED  # the owner's refresh
    for pk in (k2, None):  # a copier of c1's source info with another key, or none
        assert o.claim("c1", pk=pk).reason == KEY_MISMATCH
        assert o.claim("c1", RELEASE, pk=pk).reason == KEY_MISMATCH
    # the copied key itself: a release refused, a claim told granted that changes nothing
    assert o.claim("c1", RELEASE, pk=k1).reason == KEY_MISMATCH
    assert o.claim("c1", pk=k1, wheel_wear=False).reason == GRANTED and o.wheel_wear
    assert o.owner == "c1" and o.owner_link == ("c1", "L1") and o.state == "owned"
    assert o.summary()["key_mismatches"] == 5 and o.claim("c2", pk=k2).reason == OWNED
    # the owner's own release (proven) frees it and forgets the key
    assert o.claim("c1", RELEASE, pk=k1, proven=True).reason == "released"
    assert o.owner is None and o.owner_link is None and o.owner_pk is None
    # identities proven by certificates (--secure): the owner's new key replaces the old
    s = Ownership(rekey=True)
    assert s.claim("cert", pk=k1, link="A").granted
    assert s.claim("cert", pk=k2, link="B").granted and s.owner_link == ("cert", "B")


def test_same_n_regrants_the_lost_owner_only_with_its_keys_grant():
    """``--rearm same:N``: the lost owner's identity with the lost grant's key (which only
    that controller can use: a copier of it gets a vehicle it cannot command)."""
    o = Ownership(policy=RearmPolicy.parse("same:5"), period=0.01)
    k1, k2 = KeyPair().public, KeyPair().public
    assert o.claim("c1", pk=k1, link="L1", now=0.0).granted
    o.start()
    o.token("c1", True, now=0.0)
    o.token("c1", False, now=1.0)
    assert o.state == "latched" and o.lost_pk == k1
    assert o.claim("c1", pk=k2, now=2.0).reason == "latched"  # another key: refused
    assert o.claim("c1", pk=k1, link="L1b", now=2.0).granted
    assert o.owner_link == ("c1", "L1b")


def test_claim_and_grant_carry_the_keys():
    pk = KeyPair().public
    assert decode_claim(encode_claim(pk=pk))["pk"] == pk
    assert "pk" not in decode_claim(encode_claim())
    assert decode_grant(encode_grant(True, GRANTED, pk=pk))["pk"] == pk
