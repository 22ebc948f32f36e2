"""Secure deployments with Zenoh's own security: mutual TLS and access control.

Nothing here is home-made cryptography. :func:`create_certs` writes, with the
``cryptography`` package, a certificate authority and one key and certificate per
identity; :func:`secure_config` turns a directory of them into the Zenoh settings of one
process:

* ``transport/link/tls``: every link is TLS, and both ends present a certificate signed by
  the deployment's CA (``enable_mtls``); a peer without one, or with one from another CA,
  cannot open a session with an ``msagv`` process;
* ``access_control``: default deny, and rules per identity, by the certificate's common
  name (Zenoh's ``cert_common_names`` subjects). A process's identity on the bus is its
  certificate's common name, and it travels in the keys (docs/PROTOCOL.md, "Keys"): the
  rules let each certificate send only under its own name and only for its vehicles. A
  plant of ``agv0`` may publish ``msagv/agv0/state/{its name}``, answer the
  ``params``/``claim``/``arm`` queries put to it and declare ``alive/plant/{its name}``; a
  controller of ``agv0`` may publish ``msagv/agv0/cmd/{its name}`` (and references), ask
  ``params`` and ``claim`` and declare ``alive/controller/{its name}``; an operator may
  ``arm`` a vehicle and ask ``params``; an observer may only read and ask ``params``; a
  router forwards everything to a process that reaches it as a client (it enforces the
  same rules on its own links), and may do nothing on a peer's direct links.

The directory (``msagv certs DIR``) holds ``ca.pem``, ``roles.json`` (identity -> common
name, role and vehicles) and ``NAME.pem``/``NAME.key`` per identity; ``ca.key`` is needed
only to add identities later (keep it off the vehicles). docs/SECURITY.md: the threat
model, the rules and how to deploy them across machines.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import re
from pathlib import Path

ROLES = ("plant", "controller", "router", "operator", "observer")
PER_VEHICLE = ("plant", "controller")  # roles issued once per vehicle: NAME = ROLE-VEHICLE
SHARED = ("router", "operator")  # roles issued once, for every vehicle of the directory
ANY = "*"  # an identity's vehicles: every vehicle
DEFAULT_VEHICLES = ("agv0",)
MANIFEST = "roles.json"
CA_CERT, CA_KEY = "ca.pem", "ca.key"
DEFAULT_SANS = ("localhost", "127.0.0.1", "::1")
_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class SecurityError(ValueError):
    """Bad security options or an incomplete certificate directory (one-line message)."""


# ---- the certificate directory -------------------------------------------------------------
def parse_extra(text: str) -> tuple[str, str, tuple[str, ...]]:
    """``NAME[:ROLE[:VEHICLE,...]]`` (``msagv certs --extra``) -> (name, role, vehicles); an
    extra identity is an observer of every vehicle unless a role and vehicles are given."""
    name, _, rest = text.partition(":")
    role, _, vids = rest.partition(":")
    role = role or "observer"
    if not _NAME_RE.match(name) or name in (CA_CERT[:-4], "roles"):
        raise SecurityError(f"--extra: '{name}' is not a valid identity name (1-64 characters "
                            f"of A-Z a-z 0-9 _ . -, not 'ca' or 'roles')")
    if role not in ROLES:
        raise SecurityError(f"--extra {text}: role must be one of {', '.join(ROLES)}")
    return name, role, check_vehicles(vids.split(",") if vids else [ANY], f"--extra {text}")


def check_vehicles(vids, what: str = "--vehicle") -> tuple[str, ...]:
    """Vehicle ids (each one key chunk, as ``--id``) or ``*`` (every vehicle)."""
    out = []
    for v in vids:
        if v != ANY and not _NAME_RE.match(v):
            raise SecurityError(f"{what}: '{v}' is not a vehicle id (1-64 characters of "
                                f"A-Z a-z 0-9 _ . -) or *")
        out.append(v)
    if not out:
        raise SecurityError(f"{what}: no vehicle")
    return tuple(dict.fromkeys(out))


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


def create_certs(directory, extras=(), sans: list[str] = (), days: int = 825,
                 force: bool = False, vehicles=DEFAULT_VEHICLES) -> dict:
    """Create (or complete) a certificate directory: a CA (reused if ``ca.pem`` and
    ``ca.key`` exist); per vehicle of ``vehicles`` a plant and a controller identity
    (``plant-ID``, ``controller-ID``, common names ``msagv-plant-ID``, ...), allowed that
    vehicle only; a ``router`` and an ``operator`` for every vehicle; and every
    ``(name, role[, vehicles])`` of ``extras`` (common name = name). Existing identity files
    are kept unless ``force``. Returns the manifest (also written to ``roles.json``)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if not 1 <= days <= 36500:
        raise SecurityError(f"--days must be 1..36500, got {days}")
    vehicles = check_vehicles(vehicles)
    if ANY in vehicles:
        raise SecurityError("--vehicle: plant and controller certificates are per vehicle; "
                            "name the vehicles (an --extra identity may have '*')")
    wanted = [(f"{role}-{v}", role, (v,)) for v in vehicles for role in PER_VEHICLE]
    wanted += [(r, r, (ANY,)) for r in SHARED]
    for e in extras:
        wanted.append((e[0], e[1], check_vehicles(e[2]) if len(e) > 2 else (ANY,)))
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

    manifest = read_manifest(d, missing_ok=True) if not force else {"version": 2, "identities": {}}
    manifest["version"] = 2
    generated = {n for n, _, _ in wanted[:len(wanted) - len(extras)]}
    for name, role, vids in wanted:
        cn = f"msagv-{name}" if name in generated else name
        cert_p, key_p = d / f"{name}.pem", d / f"{name}.key"
        known = manifest["identities"].get(name)
        if known is not None and known["role"] != role:
            raise SecurityError(f"identity '{name}' exists with role {known['role']}, not {role}")
        if cert_p.exists() and key_p.exists() and not force and known is not None:
            known["vehicles"] = list(vids)  # the rules follow the manifest (no new certificate)
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
        manifest["identities"][name] = {"cn": cn, "role": role, "vehicles": list(vids)}
    _write(d / MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode(), private=False)
    return manifest


def read_manifest(directory, missing_ok: bool = False) -> dict:
    p = Path(directory) / MANIFEST
    if not p.exists():
        if missing_ok:
            return {"version": 2, "identities": {}}
        raise SecurityError(f"--secure {directory}: no {MANIFEST} (create the directory with "
                            f"msagv certs {directory})")
    try:
        m = json.loads(p.read_text())
        ids = m["identities"]
        for name, v in ids.items():
            if v["role"] not in ROLES or not isinstance(v["cn"], str) \
                    or not _NAME_RE.match(v["cn"].removeprefix("msagv-")):
                raise ValueError(name)
            # a directory of the first version (no vehicles): every vehicle
            v["vehicles"] = list(check_vehicles(v.get("vehicles", [ANY]), name))
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise SecurityError(f"--secure {directory}: {MANIFEST} is malformed ({e})") from None
    return m


def identity_for(directory, role: str, vid: str, name: str | None = None) -> str:
    """The identity (a name of ``roles.json``) a process of ``role`` for vehicle ``vid``
    uses: ``name`` if given, else ``ROLE-VID``, else ``ROLE`` (a router, an operator, or a
    directory of the first version). SecurityError if there is none, or if it may not
    serve ``vid``."""
    if not Path(directory).is_dir():
        raise SecurityError(f"--secure {directory}: not a directory (create it with "
                            f"msagv certs {directory})")
    m = read_manifest(directory)
    ids = m["identities"]
    if name is None:
        name = next((n for n in (f"{role}-{vid}", role) if n in ids), None)
        if name is None:
            raise SecurityError(f"--secure {directory}: no identity for a {role} of vehicle "
                                f"'{vid}' in {MANIFEST} (add one with msagv certs {directory} "
                                f"--vehicle {vid})")
    elif name not in ids:
        raise SecurityError(f"--secure {directory}: no identity '{name}' in {MANIFEST} "
                            f"(add it with msagv certs {directory} --extra {name}:ROLE)")
    vids = ids[name]["vehicles"]
    if ANY not in vids and vid not in vids and role != "router":
        raise SecurityError(f"--secure {directory}: identity '{name}' serves vehicle(s) "
                            f"{', '.join(vids)}, not '{vid}'")
    return name


# ---- the Zenoh settings --------------------------------------------------------------------
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]


def acl_config(manifest: dict, routed: bool = True) -> dict:
    """Zenoh's ``access_control`` section for the identities of ``manifest``.

    ``routed``: this process reaches the others through a router (a client, or the router
    itself), so a router's certificate forwards everything on its link. Otherwise (a
    peer: the plant listening, the controller connecting to it) a router's certificate
    may do nothing at all here: on a direct link it is not forwarding for anyone, and it
    would otherwise be a master key, able to command as any controller, hold the owner's
    token and arm the vehicle (issue 30, item 3).

    Every process applies the rules on its own links, by the common name of the remote
    end's certificate: ``ingress`` is what that identity may send to us, ``egress`` what we
    may send to it (everything of its vehicles: reading is not restricted among a
    vehicle's identities). Each identity may send only under its own name (the last key
    chunks, docs/PROTOCOL.md "Keys") and only for its vehicles; a key of the first
    protocol version (no name) is let through to the plant, which answers it with the
    reason it refuses it. Default deny: an identity absent from the manifest may do
    nothing."""
    rules, policies, subjects = [], [], []

    def rule(rid, messages, keys, flow="ingress"):
        rules.append({"id": rid, "messages": messages, "flows": [flow], "permission": "allow",
                      "key_exprs": keys})
        return rid

    for i, (name, v) in enumerate(sorted(manifest["identities"].items())):
        cn, role, vids = v["cn"], v["role"], v["vehicles"]
        base = [f"msagv/{vid}" for vid in vids]
        mine = []
        if role == "router":
            if not routed:
                continue  # no rule: default deny, both ways
            mine.append(rule(f"{i}_forwards", ALL_MESSAGES, ["msagv/**"]))
        else:
            mine.append(rule(f"{i}_reads", ["declare_subscriber", "declare_liveliness_subscriber",
                                            "liveliness_query"], [f"{b}/**" for b in base]))
            asks = {"plant": (), "controller": ("params", "claim"), "operator": ("params", "arm"),
                    "observer": ("params",)}[role]
            if asks:
                mine.append(rule(f"{i}_asks", ["query"],
                                 [f"{b}/{q}/*/{cn}" for b in base for q in asks]
                                 + [f"{b}/{q}" for b in base for q in asks if q != "arm"]))
            if role == "plant":
                mine.append(rule(f"{i}_sends", ["put"], [f"{b}/state/{cn}" for b in base]))
                mine.append(rule(f"{i}_answers", ["declare_queryable", "reply"],
                                 [f"{b}/{q}/{cn}/*" for b in base for q in ("params", "claim", "arm")]
                                 + [f"{b}/{q}" for b in base for q in ("params", "claim")]))
                mine.append(rule(f"{i}_token", ["liveliness_token"],
                                 [f"{b}/alive/plant/{cn}" for b in base]))
            elif role == "controller":
                mine.append(rule(f"{i}_sends", ["put"],
                                 [f"{b}/{k}/{cn}" for b in base for k in ("cmd", "reference")]
                                 + [f"{b}/cmd" for b in base]))
                mine.append(rule(f"{i}_token", ["liveliness_token"],
                                 [f"{b}/alive/controller/{cn}" for b in base]))
            elif role == "operator":
                mine.append(rule(f"{i}_sends", ["put"], [f"{b}/reference/{cn}" for b in base]))
        mine.append(rule(f"{i}_egress", ALL_MESSAGES,
                         ["msagv/**"] if role == "router" else [f"{b}/**" for b in base],
                         flow="egress"))
        subjects.append({"id": f"s{i}", "cert_common_names": [cn]})
        policies.append({"id": f"p{i}_{name}", "rules": mine, "subjects": [f"s{i}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def common_name(directory, identity: str) -> str:
    """The common name of ``identity``'s certificate: its name on the bus."""
    return read_manifest(directory)["identities"][identity]["cn"]


def secure_config(directory, identity: str, routed: bool = True) -> dict:
    """``{zenoh config key: value}`` for a process with ``identity`` (a name of the
    directory's ``roles.json``: ``plant``, ``controller``, ``router`` or an extra);
    ``routed``: it reaches the others through a router (:func:`acl_config`).
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
    return {"transport/link/tls": tls, "access_control": acl_config(manifest, routed)}
