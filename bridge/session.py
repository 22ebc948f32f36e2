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
  again within ~250 ms;
* a shortened transport lease (default 1 s instead of 10 s), so the loss of a process and
  of its liveliness token is noticed within about a second.

See docs/PROTOCOL.md for the key expressions and the messages.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field

DEFAULT_ID = "agv0"
DEFAULT_PORT = 7448  # the plant's default loopback endpoint (7447 is left to a router)
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
ROUTER_PORT = 7447  # zenoh's usual router port: ``msagv router``'s default
DEFAULT_LEASE_MS = 1000
_ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


class SessionError(ValueError):
    """Bad session options (the message names the option)."""


@dataclass(frozen=True)
class Keys:
    """The key expressions of one vehicle (docs/PROTOCOL.md, section "Keys")."""

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
    def alive_plant(self) -> str:
        return f"msagv/{self.id}/alive/plant"

    @property
    def alive_controller(self) -> str:
        return f"msagv/{self.id}/alive/controller"


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
    config_file : a zenoh JSON5 config file; applied first, the options above on top
        (only those given explicitly), and scouting is left as the file sets it.
    lease_ms : the transport lease [ms]; a dead peer (and its liveliness tokens) is
        noticed after at most this long.
    """

    id: str = DEFAULT_ID
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    mode: str = "peer"
    config_file: str | None = None
    lease_ms: int = DEFAULT_LEASE_MS


def make_config(opts: SessionOptions, role: str):
    """A :class:`zenoh.Config` for ``role`` in {'plant', 'controller', 'router', 'tool'}."""
    import zenoh

    if opts.mode not in ("peer", "client", "router"):
        raise SessionError(f"--mode: expected peer or client, got '{opts.mode}'")
    if not (100 <= opts.lease_ms <= 600_000):
        raise SessionError(f"--lease-ms: expected 100..600000, got {opts.lease_ms}")
    for ep in opts.connect + opts.listen:
        if "/" not in ep:
            raise SessionError(f"endpoint '{ep}': expected PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7448")
    connect, listen = list(opts.connect), list(opts.listen)
    from_file = opts.config_file is not None
    if from_file:
        try:
            conf = zenoh.Config.from_file(opts.config_file)
        except Exception as e:
            raise SessionError(f"--zenoh-config {opts.config_file}: {e}") from None
    else:
        conf = zenoh.Config()
        if not connect and not listen:
            if role == "plant":
                listen = [DEFAULT_ENDPOINT]
            elif role == "router":
                listen = [f"tcp/127.0.0.1:{ROUTER_PORT}"]
            else:
                connect = [DEFAULT_ENDPOINT]
    ins = conf.insert_json5
    ins("mode", json.dumps(opts.mode))
    if connect or not from_file:
        ins("connect/endpoints", json.dumps(connect))
    if listen or not from_file:
        # an empty list: a peer would otherwise listen on every interface
        ins("listen/endpoints", json.dumps(listen))
    if not from_file:
        ins("scouting/multicast/enabled", "false")
        ins("scouting/gossip/enabled", "false")
        ins("scouting/delay", "0")
    # DESIGN.md: the retry keys are accepted only as one object
    ins("connect/retry", "{period_init_ms: 50, period_max_ms: 250, period_increase_factor: 1.5}")
    if opts.mode != "client":
        ins("listen/retry", "{period_init_ms: 50, period_max_ms: 250, period_increase_factor: 1.5}")
    ins("transport/link/tx/lease", str(int(opts.lease_ms)))
    return conf


def open_session(opts: SessionOptions, role: str):
    """Open a session (``with open_session(...) as s:``); errors become SessionError."""
    import zenoh

    conf = make_config(opts, role)
    try:
        return zenoh.open(conf)
    except Exception as e:  # zenoh.ZError: e.g. the listen port is taken
        eps = ", ".join(opts.listen or opts.connect) or "the default endpoint"
        raise SessionError(f"cannot open the zenoh session ({role}, {eps}): {e}") from None
