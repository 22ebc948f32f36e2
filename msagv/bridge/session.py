"""Zenoh session options shared by every bridge process, and the key expressions.

One helper turns ``--id/--connect/--listen/--mode/--zenoh-config/--lease-ms`` into a
:class:`zenoh.Config`, with the settings measured to work on these machines (DESIGN.md,
"The stack on these machines"):

* multicast and gossip scouting off, ``scouting/delay = 0``: no network traffic beyond the
  endpoints given, so ``make demo`` needs no network and no router;
* explicit endpoints, by default on loopback: the plant listens on
  ``tcp/127.0.0.1:7448`` and the controller connects to it (``listen/endpoints = []`` on
  the connecting side: a peer otherwise listens on every interface);
* a fast reconnect (``connect/retry`` set as one object), so a restarted process is found
  again within ~250 ms; a client's open waits up to 10 s for its router
  (``connect/timeout_ms``; Zenoh's default of 0 failed a client started a moment before
  its router);
* a shortened transport lease (default 1 s instead of 10 s), so the loss of a process and
  of its liveliness token is noticed within about a second;
* no shared memory (``transport/shared_memory/enabled = false``): with Zenoh's default the
  plant linked 351 sessions and no more (issue 30: a flood of sessions kept any later peer
  out; Zenoh leases each peer that negotiates shared memory 8 of a listener's 2,810
  counters, docs/PROTOCOL.md section 1); the protocol's messages are small and none is a
  shared-memory buffer;
* a maximum message size on the transport (:data:`MAX_MESSAGE_BYTES`, just above the
  largest message of the protocol, 1 MiB): Zenoh buffers at most that much of a larger
  message and drops it, so it never reaches, nor stalls, a process (Zenoh tells the
  application nothing of it: a message between the protocol's limit of its key and this
  one is counted by the receiver as ``too_large``);
* ``MSAGV_REQUIRE_SECURE`` in the environment (docs/SECURITY.md): no session without
  ``--secure``, so a deployment turns the plain bus off.

A ``--zenoh-config`` file is merged with these defaults: a key the file sets explicitly
wins, every other default stays (so a file that sets only TLS still listens on loopback
with scouting off). ``--secure DIR`` adds mutual TLS and access control
(:mod:`bridge.security`).

See docs/PROTOCOL.md for the key expressions and the messages.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field

DEFAULT_ID = "agv0"
DEFAULT_PORT = 7448  # the plant's default loopback endpoint (7447 is left to a router)
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
ROUTER_PORT = 7447  # zenoh's usual router port: ``msagv router``'s default
DEFAULT_LEASE_MS = 1000
MAX_MESSAGE_BYTES = 1024 * 1024 + 64 * 1024  # the largest message (a reference or params,
# 1 MiB, bridge.messages) + 64 KiB: Zenoh buffers no more of a larger one before dropping it
REQUIRE_SECURE_ENV = "MSAGV_REQUIRE_SECURE"  # set (not 0): every session needs --secure
RETRY = "{period_init_ms: 50, period_max_ms: 250, period_increase_factor: 1.5}"
CLIENT_CONNECT_TIMEOUT_MS = 10_000  # a client's open waits this long for its router (Zenoh's
# default is 0: a client started a moment before its router failed at once)
_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class SessionError(ValueError):
    """Bad session options (the message names the option)."""


@dataclass(frozen=True)
class Keys:
    """The base key expressions of one vehicle (docs/PROTOCOL.md, section "Keys"); the
    transport adds the sender's identity to them on the wire."""

    id: str = DEFAULT_ID

    def __post_init__(self):
        check_id(self.id)

    @property
    def state(self) -> str:
        return f"msagv/{self.id}/state"

    @property
    def cmd(self) -> str:
        return f"msagv/{self.id}/cmd"

    @property
    def params(self) -> str:
        return f"msagv/{self.id}/params"

    @property
    def reference(self) -> str:
        return f"msagv/{self.id}/reference"

    @property
    def claim(self) -> str:
        return f"msagv/{self.id}/claim"

    @property
    def arm(self) -> str:
        """The plant's queryable for an operator's re-arm (docs/PROTOCOL.md section 3.8)."""
        return f"msagv/{self.id}/arm"

    @property
    def alive_plant(self) -> str:
        """The prefix of the plant's token ``alive/plant/{zid}`` (:meth:`plant_token`)."""
        return f"msagv/{self.id}/alive/plant"

    @property
    def alive_controller(self) -> str:
        """The prefix of a controller's token ``alive/controller/{zid}``."""
        return f"msagv/{self.id}/alive/controller"

    def plant_token(self, zid: str = "*") -> str:
        """The liveliness token of the plant ``zid`` (an identity; ``*``: any plant's)."""
        return f"{self.alive_plant}/{zid}"

    def controller_token(self, zid: str = "*") -> str:
        """The liveliness token of the controller ``zid`` (an identity; ``*``: any)."""
        return f"{self.alive_controller}/{zid}"


def check_id(vid: str) -> str:
    """A vehicle id is one key-expression chunk: 1-64 of ``A-Z a-z 0-9 _ . -``."""
    if not isinstance(vid, str) or not _ID_RE.match(vid):
        raise SessionError(f"--id: '{vid}' is not a valid vehicle id (1-64 characters of "
                           f"A-Z a-z 0-9 _ . -; no '/', '*', '$', '?', '#')")
    return vid


@dataclass
class SessionOptions:
    """What :func:`make_config` needs (the parsed command-line options, or set by a test).

    connect, listen : endpoints such as ``tcp/127.0.0.1:7448``. If both are empty the
        role's default applies: a ``plant`` listens on :data:`DEFAULT_ENDPOINT`, a
        ``controller`` (or any other client role) connects to it, a ``router`` listens on
        ``tcp/127.0.0.1:7447``.
    mode : ``peer`` (default) or ``client`` (needs a router to connect to); ``router``
        only for ``msagv router``.
    config_file : a zenoh JSON5 config file, merged with the defaults: what it sets
        explicitly wins over the defaults (loopback endpoints, scouting off, the message
        size limit); the options above that are given win over the file.
    lease_ms : the transport lease [ms]; a dead peer (and its liveliness tokens) is
        noticed after at most this long.
    secure_dir : a certificate directory (``msagv certs``): mutual TLS and access control
        with the identity ``identity`` (default: ``ROLE-ID``, else ``ROLE``,
        :func:`bridge.security.identity_for`); every endpoint must be ``tls/...``.
    """

    id: str = DEFAULT_ID
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    mode: str = "peer"
    config_file: str | None = None
    lease_ms: int = DEFAULT_LEASE_MS
    secure_dir: str | None = None
    identity: str | None = None


def _file_keys(path: str) -> dict:
    """The keys a JSON5 config file sets explicitly (nested dicts), for the merge."""
    import json5

    try:
        with open(path) as f:
            d = json5.load(f)
    except OSError as e:
        raise SessionError(f"--zenoh-config {path}: {e.strerror or e}") from None
    except ValueError as e:
        raise SessionError(f"--zenoh-config {path}: not JSON5 ({e})") from None
    if not isinstance(d, dict):
        raise SessionError(f"--zenoh-config {path}: expected a JSON5 object")
    return d


def _has(d: dict, path: str) -> bool:
    for part in path.split("/"):
        if not isinstance(d, dict) or part not in d:
            return False
        d = d[part]
    return True


def make_config(opts: SessionOptions, role: str):
    """A :class:`zenoh.Config` for ``role`` in {'plant', 'controller', 'router', 'tool'}.

    Precedence: the command-line options that are given, then what the ``--zenoh-config``
    file sets explicitly, then the project's defaults (loopback endpoints of the role,
    multicast and gossip scouting off, the message size limit), then Zenoh's defaults.
    ``mode``, the retry keys and the lease always come from the options; ``--secure``
    always sets TLS and access control."""
    import zenoh

    if opts.mode not in ("peer", "client", "router"):
        raise SessionError(f"--mode: expected peer or client, got '{opts.mode}'")
    if not (100 <= opts.lease_ms <= 600_000):
        raise SessionError(f"--lease-ms: expected 100..600000, got {opts.lease_ms}")
    for ep in opts.connect + opts.listen:
        if "/" not in ep:
            raise SessionError(f"endpoint '{ep}': expected PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7448")
    secure = None
    if opts.secure_dir is None and os.environ.get(REQUIRE_SECURE_ENV, "") not in ("", "0"):
        raise SessionError(f"{REQUIRE_SECURE_ENV} is set: this deployment runs only with "
                           f"--secure DIR (mutual TLS and access control, docs/SECURITY.md)")
    if opts.secure_dir is not None:
        from .security import SecurityError, identity_for, secure_config

        try:
            ident = identity_for(opts.secure_dir, role, opts.id, opts.identity)
            # a router's certificate forwards only to its clients (and other routers); a
            # peer's links refuse it (issue 30, item 3: least privilege)
            secure = secure_config(opts.secure_dir, ident,
                                   routed=opts.mode == "client" or role == "router")
        except SecurityError as e:
            raise SessionError(str(e)) from None
        bad = [ep for ep in opts.connect + opts.listen if not ep.startswith("tls/")]
        if bad:
            raise SessionError(f"--secure: endpoint '{bad[0]}' is not TLS; use tls/ADDRESS, "
                               f"e.g. tls/127.0.0.1:{DEFAULT_PORT}")
    proto = "tls" if secure else "tcp"
    connect, listen = list(opts.connect), list(opts.listen)
    explicit: dict = {}
    if opts.config_file is not None:
        explicit = _file_keys(opts.config_file)
        try:
            conf = zenoh.Config.from_file(opts.config_file)
        except Exception as e:
            raise SessionError(f"--zenoh-config {opts.config_file}: {e}") from None
    else:
        conf = zenoh.Config()
    file_eps = _has(explicit, "connect/endpoints") or _has(explicit, "listen/endpoints")
    if not connect and not listen and not file_eps:
        if role == "plant":
            listen = [f"{proto}/127.0.0.1:{DEFAULT_PORT}"]
        elif role == "router":
            listen = [f"{proto}/127.0.0.1:{ROUTER_PORT}"]
        else:
            connect = [f"{proto}/127.0.0.1:{DEFAULT_PORT}"]
    ins = conf.insert_json5

    def default(key: str, value: str) -> None:
        if not _has(explicit, key):
            ins(key, value)

    ins("mode", json.dumps(opts.mode))
    if connect or listen:  # given (or the role's default): both lists are ours
        ins("connect/endpoints", json.dumps(connect))
        # an empty list: a peer would otherwise listen on every interface
        ins("listen/endpoints", json.dumps(listen))
    else:  # the file names endpoints; whichever list it leaves out stays empty
        default("connect/endpoints", "[]")
        default("listen/endpoints", "[]")
    default("scouting/multicast/enabled", "false")
    default("scouting/gossip/enabled", "false")
    default("scouting/delay", "0")
    default("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
    # no shared memory (the protocol's messages are small; none is a shared-memory buffer):
    # with Zenoh's default (on) the plant linked 351 sessions and no more, so a flood of
    # stock sessions kept every later peer, a restarted controller too, off it
    default("transport/shared_memory/enabled", "false")
    # DESIGN.md: the retry keys are accepted only as one object
    ins("connect/retry", RETRY)
    if opts.mode != "client":
        ins("listen/retry", RETRY)
    else:
        default("connect/timeout_ms", str(CLIENT_CONNECT_TIMEOUT_MS))
    ins("transport/link/tx/lease", str(int(opts.lease_ms)))
    if secure is not None:
        if _has(explicit, "access_control") or _has(explicit, "transport/link/tls"):
            raise SessionError("--secure and a --zenoh-config that sets access_control or "
                               "transport/link/tls: use one of the two")
        for key, value in secure.items():
            ins(key, json.dumps(value))
    return conf


def secure_identity(opts: SessionOptions, role: str) -> str | None:
    """The common name of the certificate a ``--secure`` process of ``role`` presents: its
    identity on the bus (None without ``--secure``: the session id is)."""
    if opts.secure_dir is None:
        return None
    from .security import SecurityError, common_name, identity_for

    try:
        return common_name(opts.secure_dir,
                           identity_for(opts.secure_dir, role, opts.id, opts.identity))
    except SecurityError as e:
        raise SessionError(str(e)) from None


def open_session(opts: SessionOptions, role: str):
    """Open a session (``with open_session(...) as s:``); errors become SessionError."""
    import zenoh

    conf = make_config(opts, role)
    try:
        return zenoh.open(conf)
    except Exception as e:  # zenoh.ZError: e.g. the listen port is taken
        eps = ", ".join(opts.listen or opts.connect) or "the default endpoint"
        raise SessionError(f"cannot open the zenoh session ({role}, {eps}): {e}") from None
