"""Zenoh session configuration shared by every diffpos service.

Policy: explicit endpoints only, multicast scouting off (containers and CI hosts rarely route
multicast, and implicit discovery hides wiring mistakes). The embedded default topology is
one router (``diffpos router``, a Python process in router mode) listening on
``tcp/127.0.0.1:7447`` and every service connecting to it as a client.

Every service takes ``--zenoh-config FILE`` (env ``DIFFPOS_ZENOH_CONFIG``): a zenoh json5
file such as ``security/zenoh/fusion.json5`` (TLS + user/password, see security/README.md)
that replaces the embedded default; an explicit ``--connect``/``--listen`` still replaces
the file's endpoints. A service opens its bus with two lines::

    zs = service_settings(args, log)          # ConfigError on a bad file; logs the warning
    session = open_session(zs, stop, logger=log)
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import threading
from dataclasses import dataclass, field
from typing import Any, Literal

import zenoh

from diffpos_services.bus.security.configs import session_config
from diffpos_services.bus.security.profile import SecurityError
from diffpos_services.errors import ConfigError
from diffpos_services.logs import log_event

__all__ = [
    "DEFAULT_CONNECT",
    "DEFAULT_LISTEN",
    "ZENOH_CONFIG_ENV",
    "ZenohSettings",
    "add_zenoh_arguments",
    "check_endpoint",
    "open_session",
    "service_settings",
    "settings_from_args",
    "wait_matching",
    "with_zenoh_config",
]

#: Environment variable holding the default of ``--zenoh-config``.
ZENOH_CONFIG_ENV = "DIFFPOS_ZENOH_CONFIG"

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
    config : zenoh.Config or None
        The complete configuration to open instead of :meth:`to_config` (what
        ``--zenoh-config`` gave, see :func:`service_settings`); ``mode``, ``connect`` and
        ``listen`` then only describe it for logs.
    """

    mode: Mode = "client"
    connect: tuple[str, ...] = (DEFAULT_CONNECT,)
    listen: tuple[str, ...] = field(default_factory=tuple)
    connect_timeout_ms: int = -1
    config: Any = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.config is not None:
            return  # a configuration file is validated by zenoh (it may use per-mode tables)
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
        """A fresh ``zenoh.Config``: a copy of :attr:`config` if set."""
        if self.config is not None:
            return zenoh.Config.from_json5(str(self.config))
        return zenoh.Config.from_json5(json.dumps(self.to_json()))


def add_zenoh_arguments(parser: argparse.ArgumentParser, *, mode: Mode = "client") -> None:
    """Add ``--zenoh-config`` and ``--connect``/``--listen`` (repeatable) to a service's parser.

    ``--connect``/``--listen`` default to ``None`` (an explicit value is distinguishable:
    it replaces the endpoints of a ``--zenoh-config`` file); :func:`settings_from_args`
    fills in the defaults.
    """
    g = parser.add_argument_group("zenoh")
    g.add_argument(
        "--zenoh-config",
        metavar="FILE",
        default=os.environ.get(ZENOH_CONFIG_ENV) or None,
        help="zenoh json5 configuration, e.g. security/zenoh/<role>.json5 (TLS + user/password "
        "+ access control, see security/README.md); replaces the plain default, an explicit "
        f"--connect/--listen still replaces its endpoints (env {ZENOH_CONFIG_ENV})",
    )
    if mode == "router":
        g.add_argument(
            "--listen",
            action="append",
            default=None,
            metavar="ENDPOINT",
            help=f"endpoint to listen on (repeatable; default {DEFAULT_LISTEN})",
        )
    else:
        g.add_argument(
            "--connect",
            action="append",
            default=None,
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


def service_settings(args: argparse.Namespace, logger: logging.Logger | None = None) -> ZenohSettings:
    """The bus settings of a service, with its ``--zenoh-config`` applied; logs the warning.

    One call for every service (router, anchor, fusion, recorder, dashboard)::

        zs = service_settings(args, log)
        session = open_session(zs, stop, logger=log)

    :func:`settings_from_args` validates the options, then
    :func:`diffpos_services.bus.security.session_config` builds the ``zenoh.Config`` (the
    file, or the plain default; an explicit ``--connect``/``--listen`` replaces the
    endpoints). Its transport warning is logged once here: at ERROR if it starts with
    ``"NOT loopback"``, else WARNING.

    Raises
    ------
    diffpos_services.errors.ConfigError
        Bad endpoint, or the file is missing / rejected by zenoh / names a missing
        certificate (the message names the file).
    """
    try:
        settings = settings_from_args(args)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    router = settings.mode == "router"
    return with_zenoh_config(
        settings,
        getattr(args, "zenoh_config", None),
        connect=None if router else (getattr(args, "connect", None) or None),
        listen=(getattr(args, "listen", None) or None) if router else None,
        logger=logger,
    )


def with_zenoh_config(
    settings: ZenohSettings,
    config_file: str | None = None,
    *,
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    logger: logging.Logger | None = None,
) -> ZenohSettings:
    """``settings`` carrying the ``zenoh.Config`` of ``config_file`` (or of ``settings``).

    The core of :func:`service_settings`, for processes without an argparse namespace
    (``diffpos emulate``'s own session, tests): builds the configuration with
    :func:`diffpos_services.bus.security.session_config` and logs its transport warning
    once (ERROR if ``"NOT loopback"``, else WARNING). Raises ``ConfigError``.
    """
    try:
        cfg, warning = session_config(config_file, fallback=settings.to_json(), connect=connect,
                                      listen=listen)
    except SecurityError as exc:
        raise ConfigError(
            f"{exc} (fix the file, or drop --zenoh-config / {ZENOH_CONFIG_ENV})") from None
    if warning:
        log = logger or logging.getLogger("diffpos")
        level = logging.ERROR if warning.startswith("NOT loopback") else logging.WARNING
        log_event(log, level, warning, **({"zenoh_config": str(config_file)} if config_file else {}))
    mode = json.loads(cfg.get_json("mode")) or "peer"

    def eps(section: str) -> tuple[str, ...]:
        v = json.loads(cfg.get_json(f"{section}/endpoints")) or []
        if isinstance(v, dict):
            v = v.get(mode) or []
        return tuple(str(e) for e in v)

    timeout = json.loads(cfg.get_json("connect/timeout_ms"))
    if isinstance(timeout, dict):
        timeout = timeout.get(mode)
    return ZenohSettings(mode=mode, connect=eps("connect"), listen=eps("listen"),
                         connect_timeout_ms=-1 if timeout is None else int(timeout), config=cfg)

_LOG_INIT = []


def _init_zenoh_log() -> None:
    """Route zenoh's own log (ERROR and up, or ``RUST_LOG``) to stderr, once per process:
    a refused login is only visible there (``Received a close message ... OpenSyn``)."""
    if not _LOG_INIT:
        _LOG_INIT.append(True)
        try:
            zenoh.init_log_from_env_or("error")
        except Exception:  # pragma: no cover - already initialised by the host process
            pass


def _has_login(cfg) -> bool:
    try:
        auth = json.loads(cfg.get_json("transport/auth/usrpwd")) or {}
    except Exception:  # pragma: no cover
        return False
    return bool(auth.get("user"))


def _open_error(mode: str, endpoints: list, timeout: Any, cfg: Any, exc: Exception) -> str:
    """One line for a session that did not open (no traceback): what to check."""
    why = str(exc).split(" at ")[0]
    if mode == "router":
        listen = json.loads(cfg.get_json("listen/endpoints")) or []
        return f"--listen {' '.join(map(str, listen))}: cannot listen there ({why})"
    return (f"--connect {' '.join(map(str, endpoints))}: no router answered within "
            f"--connect-timeout-ms {timeout} ({why}); is the router running at that endpoint?")


def open_session(settings, stop=None, *, logger=None, attempt_ms: int = 1000):
    """Open a Zenoh session, retrying while the router is not up yet; ``None`` if ``stop``.

    Parameters
    ----------
    settings : ZenohSettings or zenoh.Config
        What to open (a ``ZenohSettings`` from :func:`service_settings` carries the
        ``zenoh.Config`` of ``--zenoh-config``).
    stop : threading.Event, optional
    attempt_ms : int [ms]
        Length of one bounded attempt when the configuration waits forever.

    ``zenoh.open`` blocks inside Rust where Python signal handlers cannot run, so instead of
    an unbounded wait (``connect/timeout_ms = -1``) this retries bounded attempts of
    ``attempt_ms`` and checks ``stop`` (a ``threading.Event``) between them: SIGTERM during
    start-up is honoured. A refused login looks the same as a router that is down (zenoh
    says ``Timeout``), so with a user/password the "waiting for the router" message says so.
    """
    _init_zenoh_log()
    if isinstance(settings, ZenohSettings):
        cfg = settings.to_config()
        endpoints = list(settings.connect)
    else:
        cfg = zenoh.Config.from_json5(str(settings))
        endpoints = json.loads(cfg.get_json("connect/endpoints")) or []
    mode = json.loads(cfg.get_json("mode")) or "peer"
    timeout = json.loads(cfg.get_json("connect/timeout_ms"))
    if isinstance(timeout, dict):
        timeout = timeout.get(mode)
    if mode == "router" or (timeout is not None and int(timeout) >= 0) or not endpoints:
        try:
            return zenoh.open(cfg)
        except zenoh.ZError as exc:
            raise ConfigError(_open_error(mode, endpoints, timeout, cfg, exc)) from None
    cfg.insert_json5("connect/timeout_ms", json.dumps(int(attempt_ms)))
    msg = "waiting for the router"
    if _has_login(cfg):
        msg += " or the login is refused: check user/password"
    attempt = 0
    while stop is None or not stop.is_set():
        try:
            return zenoh.open(cfg)
        except zenoh.ZError as exc:
            attempt += 1
            if (logger is not None and attempt == 10) or attempt % 60 == 0:
                # not on the first attempt: a router still starting is normal, not news
                (logger or logging.getLogger("diffpos")).info(
                    msg, extra={"fields": {
                        "connect": endpoints, "attempt": attempt,
                        "error": str(exc).split(" at ")[0]}})
    return None


def wait_matching(publisher: Any, *, timeout_s: float) -> bool:
    """Block until ``publisher`` has a matching subscriber (readiness, no polling).

    Zenoh reports matching through a listener; the current status is checked after the
    listener is declared, so a match that happened before is not missed. Returns False after
    ``timeout_s`` [s] without a match.
    """
    matched = threading.Event()
    listener = publisher.declare_matching_listener(
        lambda status: matched.set() if status.matching else None
    )
    try:
        if publisher.matching_status.matching:
            matched.set()
        return matched.wait(timeout_s)
    finally:
        listener.undeclare()
