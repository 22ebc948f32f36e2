"""A key shared by the plant and the controller it granted the vehicle to, that binds the
owner's commands and the plant's states to that grant (docs/PROTOCOL.md, "The grant's key";
issue 30, item 2).

On a plain bus an identity is a Zenoh session id that the message's ``source_info`` names,
and ``zenoh.SourceInfo`` is public: a session that has seen the owner's commands (a client
on the plant's port, any client of a router) can put its own with the owner's id and be
taken for the owner. Its commands are not what this module lets through:

* each side makes an X25519 key pair for its lifetime (:class:`KeyPair`); the controller's
  claim carries its public key ``pk``; the plant binds the grant to that key and answers
  the grant with its own public key. ``pk`` is public: the owner proves it holds the key
  with a ``mac`` on its later claims and its release (a release without it, or a claim
  with another key, is refused: ``key_mismatch``);
* both derive, with HKDF-SHA256 over the X25519 shared secret and the names of the
  vehicle, the plant and the controller, one key for commands and one for states
  (:func:`derive`): nobody who saw the two public keys on the bus can derive them;
* the owner's commands and the plant's states carry ``mac``: the first
  :data:`MAC_BYTES` bytes of HMAC-SHA256 over :func:`canonical` (the message's other
  fields); a command or a state whose ``mac`` is missing or wrong is rejected as
  ``bad_mac``. A replayed message is the stale or duplicate one it was.

What it does not do: a claim without ``pk`` (a peer written before this) is granted and its
commands go without a ``mac``, as before, and the plant says so once; references, arms and
the params are not covered (with ``--secure`` the certificates cover all of them).
"""

from __future__ import annotations

import hashlib
import hmac
from dataclasses import dataclass
from typing import Any, Mapping

import msgpack
from cryptography.hazmat.primitives.asymmetric.x25519 import (X25519PrivateKey,
                                                              X25519PublicKey)
from cryptography.hazmat.primitives.hashes import SHA256
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

PK_BYTES = 32  # an X25519 public key
MAC_BYTES = 16  # the tag a message carries (HMAC-SHA256, truncated: 128 bits)
_INFO = b"msagv v2 grant key"


class LinkKeyError(ValueError):
    """A peer's public key that is not one (its length, or a low-order point)."""


class KeyPair:
    """An X25519 key pair (one per node, for its lifetime)."""

    def __init__(self):
        self._sk = X25519PrivateKey.generate()
        self.public = self._sk.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)

    def shared(self, peer: bytes) -> bytes:
        if not isinstance(peer, (bytes, bytearray)) or len(peer) != PK_BYTES:
            raise LinkKeyError(f"a public key has {PK_BYTES} bytes, got "
                            f"{len(peer) if isinstance(peer, (bytes, bytearray)) else type(peer).__name__}")
        try:
            return self._sk.exchange(X25519PublicKey.from_public_bytes(bytes(peer)))
        except ValueError as e:  # the all-zero shared secret of a low-order point
            raise LinkKeyError(f"not a usable public key: {e}") from None


def canonical(m: Mapping[str, Any]) -> bytes:
    """The bytes a ``mac`` covers: the message's fields but ``mac``, as a msgpack map in
    code-point key order, floats as float64: both sides compute them from the fields as the
    receiver validates them (a float field is a Python float there), whatever order the
    message had on the wire. A sender signs those values: an int or a float 32 in a float
    field is signed as its float 64 (docs/PROTOCOL.md 3.9)."""
    return msgpack.packb({k: m[k] for k in sorted(m) if k != "mac"}, use_bin_type=True,
                         use_single_float=False)


@dataclass(frozen=True)
class LinkKeys:
    """The two keys of one grant: ``cmd`` (the owner's commands), ``state`` (the plant's
    states); ``peer_pk``: the other side's public key they were derived with."""

    cmd: bytes
    state: bytes
    peer_pk: bytes

    @staticmethod
    def tag(key: bytes, m: Mapping[str, Any]) -> bytes:
        return hmac.new(key, canonical(m), hashlib.sha256).digest()[:MAC_BYTES]

    @staticmethod
    def valid(key: bytes, m: Mapping[str, Any]) -> bool:
        mac = m.get("mac")
        return (isinstance(mac, (bytes, bytearray))
                and hmac.compare_digest(bytes(mac), LinkKeys.tag(key, m)))

    @staticmethod
    def fault(key: bytes, m: Mapping[str, Any]) -> str | None:
        """None if ``m`` carries a valid tag under ``key``, else what is wrong with it (for
        a ``bad_mac`` rejection)."""
        if LinkKeys.valid(key, m):
            return None
        return "no mac" if "mac" not in m else "a wrong mac"


def derive(pair: KeyPair, peer_pk: bytes, vehicle: str, plant: str, controller: str
           ) -> LinkKeys:
    """The grant's keys, as both sides derive them: HKDF-SHA256 over the X25519 shared
    secret, its ``info`` naming the vehicle, the plant and the controller (a key is good for
    that pair on that vehicle only). Raises :class:`LinkKeyError` for a bad ``peer_pk``."""
    info = b"\x00".join((_INFO, vehicle.encode(), plant.encode(), controller.encode()))
    okm = HKDF(algorithm=SHA256(), length=64, salt=None, info=info).derive(
        pair.shared(peer_pk))
    return LinkKeys(okm[:32], okm[32:], bytes(peer_pk))
