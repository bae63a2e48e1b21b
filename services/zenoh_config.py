"""Zenoh session configuration shared by every diffpos service.

Policy: explicit endpoints only, multicast scouting off (containers and CI hosts rarely route
multicast, and implicit discovery hides wiring mistakes). The embedded default topology is
one router (``diffpos router``, a Python process in router mode) listening on
``tcp/127.0.0.1:7447`` and every service connecting to it as a client.
"""

from __future__ import annotations

import argparse
import json
import re
from dataclasses import dataclass, field
from typing import Literal

__all__ = [
    "DEFAULT_CONNECT",
    "DEFAULT_LISTEN",
    "ZenohSettings",
    "add_zenoh_arguments",
    "check_endpoint",
    "settings_from_args",
]

DEFAULT_PORT = 7447
DEFAULT_CONNECT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
DEFAULT_LISTEN = f"tcp/127.0.0.1:{DEFAULT_PORT}"

Mode = Literal["router", "peer", "client"]
_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/(\[[0-9a-fA-F:]+\]|[^/:\s]+):(\d{1,5})$")


def check_endpoint(endpoint: str, *, field_name: str = "endpoint") -> str:
    """Validate a Zenoh locator such as ``tcp/127.0.0.1:7447``; raise ``ValueError`` naming it."""
    m = _ENDPOINT_RE.match(endpoint.strip())
    if not m or not 0 < int(m.group(3)) < 65536:
        raise ValueError(
            f"{field_name}={endpoint!r} is not a Zenoh endpoint: expected "
            "'<proto>/<host>:<port>', e.g. 'tcp/127.0.0.1:7447' or 'tcp/router:7447'"
        )
    return endpoint.strip()


@dataclass(frozen=True)
class ZenohSettings:
    """How a service joins the bus.

    Attributes
    ----------
    mode : {"router", "peer", "client"}
    connect : tuple of str
        Endpoints to connect to (routers).
    listen : tuple of str
        Endpoints to listen on (routers, or peers accepting connections).
    connect_timeout_ms : int [ms]
        How long ``zenoh.open`` waits for the connect endpoints; -1 = forever (services
        started before their router just wait), 0 = fail at once.
    """

    mode: Mode = "client"
    connect: tuple[str, ...] = (DEFAULT_CONNECT,)
    listen: tuple[str, ...] = field(default_factory=tuple)
    connect_timeout_ms: int = -1

    def __post_init__(self) -> None:
        if self.mode not in ("router", "peer", "client"):
            raise ValueError(f"mode={self.mode!r} must be one of router, peer, client")
        for e in self.connect:
            check_endpoint(e, field_name="connect")
        for e in self.listen:
            check_endpoint(e, field_name="listen")
        if self.mode == "client" and not self.connect:
            raise ValueError("connect: a client needs at least one router endpoint")
        if self.mode == "router" and not self.listen:
            raise ValueError("listen: a router needs at least one listen endpoint")

    def to_json(self) -> dict:
        """The Zenoh JSON configuration (a plain dict)."""
        cfg: dict = {
            "mode": self.mode,
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": self.mode != "client"}},
            "connect": {"endpoints": list(self.connect)},
            "listen": {"endpoints": list(self.listen)},
        }
        if self.connect:
            cfg["connect"]["timeout_ms"] = self.connect_timeout_ms
        return cfg

    def to_config(self):
        """A ``zenoh.Config`` (imports zenoh)."""
        import zenoh

        return zenoh.Config.from_json5(json.dumps(self.to_json()))


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, mode: Mode = "client") -> None:
    """Add ``--connect``/``--listen`` options (repeatable) to a service's parser."""
    g = parser.add_argument_group("zenoh")
    if mode == "router":
        g.add_argument(
            "--listen",
            action="append",
            metavar="ENDPOINT",
            help=f"endpoint to listen on (repeatable; default {DEFAULT_LISTEN})",
        )
    else:
        g.add_argument(
            "--connect",
            action="append",
            metavar="ENDPOINT",
            help=f"router endpoint to connect to (repeatable; default {DEFAULT_CONNECT})",
        )
        g.add_argument(
            "--connect-timeout-ms",
            type=int,
            default=-1,
            metavar="MS",
            help="how long to wait for the router at start, -1 = forever (default)",
        )
    g.set_defaults(_zenoh_mode=mode)


def settings_from_args(args: argparse.Namespace) -> ZenohSettings:
    """Validated :class:`ZenohSettings` from the options of :func:`add_zenoh_arguments`."""
    mode = getattr(args, "_zenoh_mode", "client")
    if mode == "router":
        return ZenohSettings(mode="router", connect=(), listen=tuple(args.listen or [DEFAULT_LISTEN]))
    return ZenohSettings(
        mode=mode,
        connect=tuple(args.connect or [DEFAULT_CONNECT]),
        connect_timeout_ms=int(args.connect_timeout_ms),
    )


def open_session(settings: ZenohSettings, stop=None, *, logger=None, attempt_ms: int = 1000):
    """Open a Zenoh session, retrying while the router is not up yet; ``None`` if ``stop``.

    ``zenoh.open`` blocks inside Rust where Python signal handlers cannot run, so instead of
    an unbounded wait (``connect_timeout_ms = -1``) this retries bounded attempts and checks
    ``stop`` (a ``threading.Event``) between them: SIGTERM during start-up is honoured.
    """
    import logging

    import zenoh

    if settings.mode == "router" or settings.connect_timeout_ms >= 0:
        return zenoh.open(settings.to_config())
    bounded = ZenohSettings(mode=settings.mode, connect=settings.connect, listen=settings.listen,
                            connect_timeout_ms=attempt_ms)
    attempt = 0
    while stop is None or not stop.is_set():
        try:
            return zenoh.open(bounded.to_config())
        except zenoh.ZError as exc:
            attempt += 1
            if (logger is not None and attempt in (1, 10)) or attempt % 60 == 0:
                (logger or logging.getLogger("diffpos")).info(
                    "waiting for the router", extra={"fields": {
                        "connect": list(settings.connect), "attempt": attempt,
                        "error": str(exc).split(" at ")[0]}})
    return None
