"""Secure deployments with Zenoh's own security: mutual TLS and access control.

Nothing here is home-made cryptography. :func:`create_certs` writes, with the
``cryptography`` package, a certificate authority and one key and certificate per
identity; :func:`secure_config` turns a directory of them into the Zenoh settings of one
process:

* ``transport/link/tls``: every link is TLS, and both ends present a certificate signed by
  the deployment's CA (``enable_mtls``); a peer without one, or with one from another CA,
  cannot open a session with an ``msagv`` process;
* ``access_control``: default deny, and rules by the certificate's common name (Zenoh's
  ``cert_common_names`` subjects) that let only the plant's identity publish ``state``,
  declare the ``params``/``claim`` queryables and answer them and declare
  ``alive/plant/*``, only the controller's identity publish ``cmd``, query
  ``params``/``claim`` and declare ``alive/controller/*``, and a router's identity forward
  everything (it enforces the same rules on its own links). Any other identity of the CA
  (an *observer*) may only subscribe, read the tokens and get ``params``.

The directory (``msagv certs DIR``) holds ``ca.pem``, ``roles.json`` (identity -> common
name and role) and ``NAME.pem``/``NAME.key`` per identity; ``ca.key`` is needed only to
add identities later (keep it off the vehicles). docs/SECURITY.md: the threat model and how
to deploy it across machines.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import re
from pathlib import Path

ROLES = ("plant", "controller", "router", "observer")
DEFAULT_IDENTITIES = ("plant", "controller", "router")  # each is its own role
MANIFEST = "roles.json"
CA_CERT, CA_KEY = "ca.pem", "ca.key"
DEFAULT_SANS = ("localhost", "127.0.0.1", "::1")
_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class SecurityError(ValueError):
    """Bad security options or an incomplete certificate directory (one-line message)."""


# ---- the certificate directory -------------------------------------------------------------
def parse_extra(text: str) -> tuple[str, str]:
    """``NAME`` or ``NAME:ROLE`` (``msagv certs --extra``) -> (name, role); an extra
    identity is an observer unless a role is given."""
    name, _, role = text.partition(":")
    role = role or "observer"
    if not _NAME_RE.match(name) or name in (CA_CERT[:-4], "roles"):
        raise SecurityError(f"--extra: '{name}' is not a valid identity name (1-64 characters "
                            f"of A-Z a-z 0-9 _ . -, not 'ca' or 'roles')")
    if role not in ROLES:
        raise SecurityError(f"--extra {text}: role must be one of {', '.join(ROLES)}")
    return name, role


def _san(host: str):
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        if not re.match(r"^[A-Za-z0-9*][A-Za-z0-9.\-]*$", host):
            raise SecurityError(f"--san: '{host}' is neither an IP address nor a host name") \
                from None
        return x509.DNSName(host)


def _write(path: Path, data: bytes, private: bool) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if private else 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def create_certs(directory, extras: list[tuple[str, str]] = (), sans: list[str] = (),
                 days: int = 825, force: bool = False) -> dict:
    """Create (or complete) a certificate directory: a CA (reused if ``ca.pem`` and
    ``ca.key`` exist), and a key and certificate for ``plant``, ``controller``, ``router``
    and every ``(name, role)`` of ``extras``. Existing identity files are kept unless
    ``force``. Returns the manifest (also written to ``roles.json``)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if not 1 <= days <= 36500:
        raise SecurityError(f"--days must be 1..36500, got {days}")
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise SecurityError(f"{d} exists and is not a directory")
    d.mkdir(parents=True, exist_ok=True)
    san_list = [_san(h) for h in dict.fromkeys(list(DEFAULT_SANS) + list(sans))]
    now = datetime.datetime.now(datetime.timezone.utc)
    start = now - datetime.timedelta(minutes=5)
    pem = serialization.Encoding.PEM
    key_pem = lambda k: k.private_bytes(pem, serialization.PrivateFormat.PKCS8,  # noqa: E731
                                        serialization.NoEncryption())

    ca_cert_p, ca_key_p = d / CA_CERT, d / CA_KEY
    if ca_cert_p.exists() and ca_key_p.exists() and not force:
        ca_key = serialization.load_pem_private_key(ca_key_p.read_bytes(), None)
        ca = x509.load_pem_x509_certificate(ca_cert_p.read_bytes())
    elif ca_cert_p.exists() and not force:
        raise SecurityError(f"{ca_cert_p} exists without {CA_KEY}: cannot sign new identities "
                            f"(use --force to start a new CA)")
    else:
        ca_key = ec.generate_private_key(ec.SECP256R1())
        name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"msagv CA ({d.resolve().name})")])
        ca = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
              .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
              .not_valid_before(start).not_valid_after(now + datetime.timedelta(days=3650))
              .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
              .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True,
                                           crl_sign=True, content_commitment=False,
                                           key_encipherment=False, data_encipherment=False,
                                           key_agreement=False, encipher_only=False,
                                           decipher_only=False), critical=True)
              .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()),
                             critical=False)
              .sign(ca_key, hashes.SHA256()))
        _write(ca_key_p, key_pem(ca_key), private=True)
        _write(ca_cert_p, ca.public_bytes(pem), private=False)
        force = True  # a new CA: every identity must be signed again

    manifest = read_manifest(d, missing_ok=True) if not force else {"version": 1, "identities": {}}
    wanted = [(r, r) for r in DEFAULT_IDENTITIES] + list(extras)
    for name, role in wanted:
        cn = f"msagv-{name}" if name in DEFAULT_IDENTITIES else name
        cert_p, key_p = d / f"{name}.pem", d / f"{name}.key"
        known = manifest["identities"].get(name)
        if known is not None and known["role"] != role:
            raise SecurityError(f"identity '{name}' exists with role {known['role']}, not {role}")
        if cert_p.exists() and key_p.exists() and not force and known is not None:
            continue
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
                .issuer_name(ca.subject).public_key(key.public_key())
                .serial_number(x509.random_serial_number())
                .not_valid_before(start).not_valid_after(now + datetime.timedelta(days=days))
                .add_extension(x509.SubjectAlternativeName(san_list), critical=False)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]),
                               critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(
                    ca_key.public_key()), critical=False)
                .sign(ca_key, hashes.SHA256()))
        _write(key_p, key_pem(key), private=True)
        _write(cert_p, cert.public_bytes(pem), private=False)
        manifest["identities"][name] = {"cn": cn, "role": role}
    _write(d / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode(), private=False)
    return manifest


def read_manifest(directory, missing_ok: bool = False) -> dict:
    p = Path(directory) / MANIFEST
    if not p.exists():
        if missing_ok:
            return {"version": 1, "identities": {}}
        raise SecurityError(f"--secure {directory}: no {MANIFEST} (create the directory with "
                            f"msagv certs {directory})")
    try:
        m = json.loads(p.read_text())
        ids = m["identities"]
        for name, v in ids.items():
            if v["role"] not in ROLES or not isinstance(v["cn"], str):
                raise ValueError(name)
    except (ValueError, KeyError, TypeError) as e:
        raise SecurityError(f"--secure {directory}: {MANIFEST} is malformed ({e})") from None
    return m


# ---- the Zenoh settings --------------------------------------------------------------------
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]


def acl_config(manifest: dict) -> dict:
    """Zenoh's ``access_control`` section for the identities of ``manifest``.

    Every process applies the rules on its own links, by the common name of the remote
    end's certificate: ``ingress`` is what that identity may send to us, ``egress`` what we
    may send to it (everything in ``msagv/**``: reading is not restricted among the CA's
    identities). Default deny: an identity absent from the manifest may do nothing."""
    rules = []

    def rule(rid, messages, flow, keys):
        rules.append({"id": rid, "messages": messages, "flows": [flow], "permission": "allow",
                      "key_exprs": keys})

    rule("plant_sends", ["put"], "ingress", ["msagv/*/state"])
    rule("plant_answers", ["declare_queryable", "reply"], "ingress",
         ["msagv/*/params", "msagv/*/claim"])
    rule("plant_token", ["liveliness_token"], "ingress", ["msagv/*/alive/plant/*"])
    rule("controller_sends", ["put"], "ingress", ["msagv/*/cmd", "msagv/*/reference"])
    rule("controller_asks", ["query"], "ingress", ["msagv/*/params", "msagv/*/claim"])
    rule("controller_token", ["liveliness_token"], "ingress", ["msagv/*/alive/controller/*"])
    rule("reads", ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
         "ingress", ["msagv/**"])
    rule("observer_asks", ["query"], "ingress", ["msagv/*/params"])
    rule("forwards", ALL_MESSAGES, "ingress", ["msagv/**"])
    rule("to_anyone", ALL_MESSAGES, "egress", ["msagv/**"])
    policy_rules = {
        "plant": ["plant_sends", "plant_answers", "plant_token", "reads", "to_anyone"],
        "controller": ["controller_sends", "controller_asks", "controller_token", "reads",
                       "to_anyone"],
        "router": ["forwards", "to_anyone"],
        "observer": ["reads", "observer_asks", "to_anyone"],
    }
    by_role: dict[str, list[str]] = {}
    for v in manifest["identities"].values():
        by_role.setdefault(v["role"], []).append(v["cn"])
    subjects = [{"id": role, "cert_common_names": sorted(cns)} for role, cns in by_role.items()]
    policies = [{"id": f"{role}_policy", "rules": policy_rules[role], "subjects": [role]}
                for role in by_role]
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def secure_config(directory, identity: str) -> dict:
    """``{zenoh config key: value}`` for a process with ``identity`` (a name of the
    directory's ``roles.json``: ``plant``, ``controller``, ``router`` or an extra).
    SecurityError names a missing file or identity."""
    d = Path(directory)
    if not d.is_dir():
        raise SecurityError(f"--secure {directory}: not a directory (create it with "
                            f"msagv certs {directory})")
    manifest = read_manifest(d)
    if identity not in manifest["identities"]:
        raise SecurityError(f"--secure {directory}: no identity '{identity}' in {MANIFEST} "
                            f"(add it with msagv certs {directory} --extra {identity}:ROLE)")
    for f in (CA_CERT, f"{identity}.pem", f"{identity}.key"):
        if not (d / f).is_file():
            raise SecurityError(f"--secure {directory}: {f} is missing")
    key, cert = str((d / f"{identity}.key").resolve()), str((d / f"{identity}.pem").resolve())
    tls = {"root_ca_certificate": str((d / CA_CERT).resolve()), "enable_mtls": True,
           "listen_private_key": key, "listen_certificate": cert,
           "connect_private_key": key, "connect_certificate": cert,
           "verify_name_on_connect": True}
    return {"transport/link/tls": tls, "access_control": acl_config(manifest)}
