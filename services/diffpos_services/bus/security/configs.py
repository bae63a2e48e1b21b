"""Zenoh configurations: the router's and each client's (from a profile), and the one a
service opens (from its ``--zenoh-config`` file or the plain default) with its warning.

The router file has a TLS listener, the ``transport/auth/usrpwd`` dictionary and the
access control of :mod:`.acl`; a client file has TLS trust in the CA (the client checks
the router's name), its own user/password and the router endpoint.
"""

from __future__ import annotations

import ipaddress
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import zenoh

from diffpos_services.bus.security.acl import acl_config
from diffpos_services.bus.security.credentials import read_credentials
from diffpos_services.bus.security.profile import (
    ENDPOINT_RE,
    SecurityError,
    SecurityProfile,
    check_encrypted,
)

__all__ = [
    "PLAIN_TRANSPORT_WARNING",
    "client_config",
    "insecure_transport_warning",
    "router_config",
    "session_config",
    "to_zenoh",
]

#: What a service logs (level WARNING, once at start) when its session has no TLS and no
#: authentication; ``{endpoints}`` is filled in by :func:`insecure_transport_warning`.
PLAIN_TRANSPORT_WARNING = (
    "zenoh transport is UNAUTHENTICATED and UNENCRYPTED ({endpoints}): any process that can "
    "reach this endpoint can publish anchor ranges or estimates and read everything; "
    "acceptable only for a single-user loopback demo. Use --zenoh-config "
    "security/zenoh/<role>.json5 (TLS + user/password + access control, see security/README.md)"
)


def router_config(
    profile: SecurityProfile,
    *,
    listen: Sequence[str] | None = None,
    base_dir: str | Path | None = None,
) -> dict:
    """Zenoh configuration (plain dict) of the router for ``profile``.

    Parameters
    ----------
    profile : SecurityProfile
    listen : sequence of str, optional
        Override the profile's listen endpoints (tests use a free loopback port).
    base_dir : str or Path, optional
        Where the profile's folder is seen by the router (e.g. ``/security`` in a
        container); default: its real location on this machine.
    """
    listen = tuple(listen) if listen is not None else profile.listen
    check_encrypted(listen, field_name="listen")
    tls: dict[str, Any] = {
        "root_ca_certificate": profile.path(profile.ca_certificate, base_dir=base_dir),
        "listen_certificate": profile.path(profile.router_certificate, base_dir=base_dir),
        "listen_private_key": profile.path(profile.router_private_key, base_dir=base_dir),
    }
    if profile.mtls:
        tls["enable_mtls"] = True
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {"protocols": ["tls", "quic"], "tls": tls},
            "auth": {
                "usrpwd": {
                    "dictionary_file": profile.path(profile.dictionary_file, base_dir=base_dir)
                }
            },
        },
        "access_control": acl_config(profile),
        "adminspace": {"enabled": False},
    }


def client_config(
    profile: SecurityProfile,
    user: str,
    *,
    password: str | None = None,
    connect: Sequence[str] | None = None,
    connect_timeout_ms: int = -1,
    base_dir: str | Path | None = None,
) -> dict:
    """Zenoh configuration (plain dict) of a client session authenticating as ``user``.

    Parameters
    ----------
    profile : SecurityProfile
    user : str
        One of the profile's identities (``anchor-<id>``, the fusion user, ...).
    password : str, optional
        Default: looked up in the profile's dictionary file (fine for dev; in production
        each host holds only its own client file).
    connect : sequence of str, optional
        Override the profile's router endpoints.
    connect_timeout_ms : int [ms]
        ``connect/timeout_ms``; -1 waits for the router forever (a refused login then also
        waits forever: give a finite value to fail fast).
    base_dir : str or Path, optional
        As in :func:`router_config`.
    """
    if connect is not None:
        check_encrypted(connect, field_name="connect")
    ids = profile.identities()
    if user not in ids:
        raise SecurityError(
            f"user={user!r} is not an identity of the profile; known: {sorted(ids)}"
        )
    if password is None:
        creds = read_credentials(profile.path(profile.dictionary_file))
        if user not in creds:
            raise SecurityError(f"user={user!r} has no entry in {profile.dictionary_file}")
        password = creds[user]
    tls: dict[str, Any] = {
        "root_ca_certificate": profile.path(profile.ca_certificate, base_dir=base_dir),
        "verify_name_on_connect": True,
    }
    if profile.mtls:
        tls["enable_mtls"] = True  # the client side needs it too, or it sends no certificate
        tls["connect_certificate"] = profile.path(
            f"{profile.client_cert_dir}/{user}.pem", base_dir=base_dir
        )
        tls["connect_private_key"] = profile.path(
            f"{profile.client_cert_dir}/{user}.key", base_dir=base_dir
        )
    link: dict[str, Any] = {"protocols": ["tls", "quic"], "tls": tls}
    if profile.lease_ms is not None:
        link["tx"] = {"lease": int(profile.lease_ms)}
    return {
        "mode": "client",
        "connect": {
            "endpoints": list(connect if connect is not None else profile.connect),
            "timeout_ms": int(connect_timeout_ms),
        },
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": link,
            "auth": {"usrpwd": {"user": user, "password": password}},
        },
    }


def to_zenoh(config: Mapping[str, Any]):
    """A ``zenoh.Config`` from a configuration dict."""
    return zenoh.Config.from_json5(json.dumps(config))


def session_config(
    config_file: str | Path | None,
    *,
    fallback: Mapping[str, Any] | None = None,
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
):
    """The ``zenoh.Config`` a service opens, and the warning it must log (or ``None``).

    Parameters
    ----------
    config_file : str or Path or None
        A zenoh json5 file (e.g. ``security/zenoh/fusion.json5``, the ``--zenoh-config``
        option). ``None``: use ``fallback``.
    fallback : mapping, optional
        The plain configuration dict used without a file (``ZenohSettings.to_json()``).
    connect, listen : sequence of str, optional
        Endpoints given explicitly on the command line; they replace the file's.

    Returns
    -------
    config : zenoh.Config
    warning : str or None
        :func:`insecure_transport_warning` of the effective configuration: log it once at
        start, at ERROR level if it starts with ``"NOT loopback"``, else WARNING.

    Raises
    ------
    SecurityError
        The file is missing or zenoh rejects it (the message names the file), or neither a
        file nor a fallback is given.
    """
    if config_file is None:
        if fallback is None:
            raise SecurityError(
                "no zenoh configuration: give a config file or the fallback settings"
            )
        effective = dict(fallback)
        if connect:
            effective["connect"] = {**(effective.get("connect") or {}), "endpoints": list(connect)}
        if listen:
            effective["listen"] = {**(effective.get("listen") or {}), "endpoints": list(listen)}
        return zenoh.Config.from_json5(json.dumps(effective)), insecure_transport_warning(effective)
    path = Path(config_file)
    if not path.is_file():
        raise SecurityError(f"--zenoh-config {path}: file not found")
    try:
        cfg = zenoh.Config.from_file(str(path))
        if connect:
            cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
        if listen:
            cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    except zenoh.ZError as exc:
        raise SecurityError(f"--zenoh-config {path}: zenoh rejects it: {exc}") from None
    effective = {
        "mode": json.loads(cfg.get_json("mode")) or "peer",
        "connect": json.loads(cfg.get_json("connect")),
        "listen": json.loads(cfg.get_json("listen")),
        "transport": {
            "auth": {"usrpwd": json.loads(cfg.get_json("transport/auth/usrpwd"))},
            "link": {"tls": json.loads(cfg.get_json("transport/link/tls"))},
        },
    }
    for name in (
        "root_ca_certificate",
        "listen_certificate",
        "listen_private_key",
        "connect_certificate",
        "connect_private_key",
    ):
        f = effective["transport"]["link"]["tls"].get(name)
        if f and not Path(f).is_file():
            raise SecurityError(
                f"--zenoh-config {path}: transport/link/tls/{name} = {f!r} does not exist"
            )
    return cfg, insecure_transport_warning(effective)


def insecure_transport_warning(config: Mapping[str, Any]) -> str | None:
    """The warning a service must log for ``config`` (a Zenoh config dict), or ``None``.

    ``None`` when every endpoint is ``tls/``/``quic/`` and user/password (or mTLS) is set.
    Otherwise :data:`PLAIN_TRANSPORT_WARNING` with the endpoints; a plain endpoint that is
    not loopback gets ``"NOT loopback: "`` prepended (log it at ERROR level).
    """
    mode = config.get("mode") or "peer"
    eps = _endpoints(config.get("connect"), mode)
    if mode != "client":  # clients never listen
        eps += _endpoints(config.get("listen"), mode)
    transport = config.get("transport") or {}
    auth = (transport.get("auth") or {}).get("usrpwd") or {}
    tls = (transport.get("link") or {}).get("tls") or {}
    has_auth = bool(
        auth.get("user")
        or auth.get("dictionary_file")
        or tls.get("enable_mtls")
        or tls.get("connect_certificate")
    )
    plain = [e for e in eps if not str(e).startswith(("tls/", "quic/"))]
    if not plain and has_auth:
        return None
    msg = PLAIN_TRANSPORT_WARNING.format(endpoints=", ".join(map(str, eps)) or "no endpoints")
    if any(not _is_loopback(e) for e in plain):
        msg = "NOT loopback: " + msg
    return msg


def _endpoints(section: Mapping[str, Any] | None, mode: str) -> list[str]:
    """Endpoints of a ``connect``/``listen`` section (a list, or a per-mode table)."""
    eps = (section or {}).get("endpoints") or []
    if isinstance(eps, Mapping):
        eps = eps.get(mode) or []
    return [str(e) for e in eps]


def _is_loopback(endpoint: str) -> bool:
    m = ENDPOINT_RE.match(str(endpoint))
    if not m:
        return False
    host = m.group(2).strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
