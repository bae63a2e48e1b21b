"""Zenoh transport security for the diffpos bus: TLS, user/password and access control.

A *security profile* (a small TOML file, see ``security/profile.dev.toml``) names the
certificate files, the credentials dictionary, the site(s) it protects and the anchors that
exist. From it this module renders

- the router's Zenoh configuration (:func:`router_config`): a TLS listener, a
  ``transport/auth/usrpwd`` dictionary and an ``access_control`` block whose rules say that
  only anchor ``<id>`` (user ``anchor-<id>``) may put ``diffpos/<site>/anchor/<id>/state``
  and ``.../anchor/<id>/range/*``, only the fusion user may put estimates and diagnostics,
  only the emulator may put truth and the run-control gate, and recorder/dashboard only read;
- one client configuration per identity (:func:`client_config`): TLS trust in the dev CA
  (the client checks the router's name), its own user/password and the router endpoint.

The rules follow the key expressions of :mod:`diffpos_services.wire.keys`; the access control is
enforced by the router (every service is a client of it), default ``deny``.

Zenoh facts this relies on (measured with eclipse-zenoh 1.10.2, see ``security/README.md``):

- a client without credentials, or with a wrong password, is refused when the session is
  established (``zenoh.open`` raises after ``connect/timeout_ms``); it never gets to put;
- an ACL ``declare_subscriber`` *egress* rule must let publishers learn of subscribers
  (clients drop puts nobody subscribes to), and declarations are matched by *inclusion*:
  a recorder's ``diffpos/**`` subscription reaches a publisher only through a rule whose key
  expression includes ``diffpos/**``. That rule reveals subscriptions, never data;
- the dictionary file has one ``user:password`` per line, nothing else (no comments, no
  blank lines: zenoh rejects the file).

Command line (also used to regenerate the committed files)::

    python -m diffpos_services.bus.security certs  OUT_DIR [--host NAME ...] [--client USER ...]
    python -m diffpos_services.bus.security render PROFILE OUT_DIR [--base-dir /security]
        [--connect tls/localhost:7447 --listen tls/127.0.0.1:7447]
    python -m diffpos_services.bus.security check  PROFILE
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = [
    "PLAIN_TRANSPORT_WARNING",
    "ROLES",
    "SecurityError",
    "SecurityProfile",
    "acl_config",
    "anchor_user",
    "client_config",
    "insecure_transport_warning",
    "load_profile",
    "make_dev_certs",
    "read_credentials",
    "render_profile",
    "router_config",
    "session_config",
    "write_credentials",
]

#: Roles an identity can have on the bus.
ROLES = ("anchor", "fusion", "recorder", "dashboard", "emulator")

#: What a service logs (level WARNING, once at start) when its session has no TLS and no
#: authentication; ``{endpoints}`` is filled in by :func:`insecure_transport_warning`.
PLAIN_TRANSPORT_WARNING = (
    "zenoh transport is UNAUTHENTICATED and UNENCRYPTED ({endpoints}): any process that can "
    "reach this endpoint can publish anchor ranges or estimates and read everything; "
    "acceptable only for a single-user loopback demo. Use --zenoh-config "
    "security/zenoh/<role>.json5 (TLS + user/password + access control, see security/README.md)"
)

_ID_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_\-]{0,63}$")
_USER_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$")
_ENDPOINT_RE = re.compile(
    r"^(tcp|udp|tls|quic|ws|unixsock-stream)/(\[[0-9a-fA-F:]+\]|[^/:\s]+):(\d{1,5})$"
)


class SecurityError(ValueError):
    """Invalid security profile, credentials file or role; the message names the field."""


# ----------------------------------------------------------------------------- profile
@dataclass(frozen=True)
class SecurityProfile:
    """Validated security profile (what ``security/profile.dev.toml`` holds).

    Attributes
    ----------
    root : Path
        Directory the relative paths below are resolved against (the profile's folder).
    site : str
        Site the access rules cover, one key chunk, or ``"*"`` for every site.
    anchors : tuple of str
        Anchor ids allowed to publish; anchor ``a`` authenticates as user ``anchor-a``.
    users : dict
        Role -> user name for the single-instance roles (fusion, recorder, dashboard,
        emulator). A role left out has no identity and therefore no access.
    ca_certificate, router_certificate, router_private_key : str
        PEM files relative to ``root`` (the CA clients trust; the router's TLS identity).
    dictionary_file : str
        ``user:password`` lines, relative to ``root`` (read by the router only).
    listen : tuple of str
        Router listen endpoints (``tls/...``).
    connect : tuple of str
        Endpoints clients connect to (``tls/<router host>:<port>``).
    mtls : bool
        Also require client certificates (``enable_mtls``); client ``<user>`` then loads
        ``client_cert_dir/<user>.pem`` and ``<user>.key``.
    client_cert_dir : str
        Folder of the client certificates, relative to ``root`` (only with ``mtls``).
    lease_ms : int or None [ms]
        Link lease every client announces (``transport/link/tx/lease``): the router drops a
        client that stays silent this long, so a hung service (or a link gone quiet) is
        reported lost after it. ``None``: zenoh's default, 10000 ms (docs/faults.md).
    """

    root: Path
    site: str = "*"
    anchors: tuple[str, ...] = ()
    users: Mapping[str, str] = field(default_factory=dict)
    ca_certificate: str = "certs/ca.pem"
    router_certificate: str = "certs/router.pem"
    router_private_key: str = "certs/router.key"
    dictionary_file: str = "credentials.dev.txt"
    listen: tuple[str, ...] = ("tls/0.0.0.0:7447",)
    connect: tuple[str, ...] = ("tls/router:7447",)
    mtls: bool = False
    client_cert_dir: str = "certs/clients"
    lease_ms: int | None = None

    def __post_init__(self) -> None:
        if self.lease_ms is not None and (
            isinstance(self.lease_ms, bool)
            or not isinstance(self.lease_ms, int)
            or not 100 <= self.lease_ms <= 3_600_000
        ):
            raise SecurityError(
                f"lease_ms={self.lease_ms!r}: give the client link lease in milliseconds, "
                "an integer from 100 to 3600000 (zenoh's default is 10000)"
            )
        if self.site != "*" and not _ID_RE.match(self.site):
            raise SecurityError(
                f"site={self.site!r}: use one key chunk (letters, digits, '_', '-') or '*'"
            )
        seen: set[str] = set()
        for a in self.anchors:
            if not isinstance(a, str) or not _ID_RE.match(a):
                raise SecurityError(
                    f"anchors: {a!r} is not a valid anchor id (letters, digits, '_', '-')"
                )
            if a in seen:
                raise SecurityError(f"anchors: {a!r} is listed twice")
            seen.add(a)
        for role, user in self.users.items():
            if role not in ROLES or role == "anchor":
                raise SecurityError(
                    f"users.{role}: unknown role; use one of {', '.join(r for r in ROLES if r != 'anchor')} "
                    "(anchors get their users from the 'anchors' list)"
                )
            _check_user(user, field_name=f"users.{role}")
        names = [anchor_user(a) for a in self.anchors] + list(self.users.values())
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise SecurityError(
                f"users: the user name(s) {sorted(dup)} are used by more than one identity"
            )
        for name in ("listen", "connect"):
            _check_encrypted(getattr(self, name), field_name=name)

    # -- identities ----------------------------------------------------------------------
    def identities(self) -> dict[str, tuple[str, str | None]]:
        """User name -> (role, anchor id or ``None``), for every identity of the profile."""
        out: dict[str, tuple[str, str | None]] = {
            anchor_user(a): ("anchor", a) for a in self.anchors
        }
        for role, user in self.users.items():
            out[user] = (role, None)
        return out

    def path(self, relative: str, *, base_dir: str | Path | None = None) -> str:
        """Absolute path of a profile file, under ``base_dir`` if given (e.g. a container mount)."""
        p = Path(relative)
        if p.is_absolute():
            return str(p)
        return str(Path(base_dir) / p) if base_dir is not None else str((self.root / p).resolve())


def anchor_user(anchor_id: str) -> str:
    """User name of anchor ``anchor_id`` (``anchor-<id>``)."""
    return f"anchor-{anchor_id}"


def _check_encrypted(endpoints: Sequence[str], *, field_name: str) -> None:
    """Raise :class:`SecurityError` unless every endpoint is a ``tls/``/``quic/`` locator."""
    if not endpoints:
        raise SecurityError(f"{field_name}: give at least one endpoint")
    for e in endpoints:
        m = _ENDPOINT_RE.match(str(e))
        if not m:
            raise SecurityError(f"{field_name}: {e!r} is not a Zenoh endpoint such as 'tls/router:7447'")
        if m.group(1) not in ("tls", "quic"):
            raise SecurityError(
                f"{field_name}: {e!r} is not encrypted; a security profile only uses "
                "'tls/' (or 'quic/') endpoints"
            )


def _check_user(user: Any, *, field_name: str) -> str:
    if not isinstance(user, str) or not _USER_RE.match(user):
        raise SecurityError(
            f"{field_name}={user!r} is not a valid user name: 1-64 characters from letters, digits, "
            "'_', '.', '-' (no ':' or spaces)"
        )
    return user


def load_profile(path: str | Path) -> SecurityProfile:
    """Read and validate a security profile TOML file.

    Raises
    ------
    SecurityError
        Naming the file and the bad field (unknown keys are errors too: a typo must not
        silently weaken the configuration).
    """
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SecurityError(f"security profile {path}: file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise SecurityError(f"security profile {path}: not valid TOML ({exc})") from None
    return profile_from_dict(raw, root=path.parent, source=str(path))


def profile_from_dict(
    raw: Mapping[str, Any], *, root: str | Path, source: str = "profile"
) -> SecurityProfile:
    """Validate a profile given as a plain dict (``root``: base of relative paths)."""
    allowed = {
        "site",
        "anchors",
        "users",
        "ca_certificate",
        "router_certificate",
        "router_private_key",
        "dictionary_file",
        "listen",
        "connect",
        "mtls",
        "client_cert_dir",
        "lease_ms",
    }
    unknown = sorted(set(raw) - allowed)
    if unknown:
        raise SecurityError(f"{source}: unknown field(s) {unknown}; allowed: {sorted(allowed)}")
    kw: dict[str, Any] = {}
    for k, v in raw.items():
        if k in ("anchors", "listen", "connect"):
            if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
                raise SecurityError(f"{source}: {k} must be a list of strings")
            kw[k] = tuple(v)
        elif k == "users":
            if not isinstance(v, dict):
                raise SecurityError(f'{source}: users must be a table role = "user name"')
            kw[k] = dict(v)
        elif k == "mtls":
            if not isinstance(v, bool):
                raise SecurityError(f"{source}: mtls must be true or false")
            kw[k] = v
        elif k == "lease_ms":
            kw[k] = v  # checked by SecurityProfile
        else:
            if not isinstance(v, str):
                raise SecurityError(f"{source}: {k} must be a string")
            kw[k] = v
    try:
        return SecurityProfile(root=Path(root), **kw)
    except SecurityError as exc:
        raise SecurityError(f"{source}: {exc}") from None


# ----------------------------------------------------------------------------- credentials
def read_credentials(path: str | Path) -> dict[str, str]:
    """Parse a zenoh user/password dictionary (``user:password`` per line) into a dict.

    The password is everything after the first ``:``. Raises :class:`SecurityError` naming
    the line for anything zenoh would reject (blank lines, comments, duplicates).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SecurityError(f"dictionary_file {path}: file not found") from None
    out: dict[str, str] = {}
    for i, line in enumerate(text.splitlines(), start=1):
        user, sep, pw = line.partition(":")
        if not sep or not pw:
            raise SecurityError(
                f"dictionary_file {path}, line {i}: expected 'user:password' (zenoh accepts no "
                "comments or blank lines in this file)"
            )
        _check_user(user, field_name=f"dictionary_file {path}, line {i}: user")
        if pw != pw.strip():
            raise SecurityError(
                f"dictionary_file {path}, line {i}: password has leading/trailing spaces"
            )
        if user in out:
            raise SecurityError(f"dictionary_file {path}, line {i}: user {user!r} appears twice")
        out[user] = pw
    return out


def write_credentials(path: str | Path, credentials: Mapping[str, str]) -> Path:
    """Write a dictionary file zenoh accepts (mode 0600); return its path."""
    path = Path(path)
    lines = []
    for user, pw in credentials.items():
        _check_user(user, field_name="user")
        if not pw or "\n" in pw or pw != pw.strip():
            raise SecurityError(
                f"password of {user!r}: must be non-empty, one line, no surrounding spaces"
            )
        lines.append(f"{user}:{pw}\n")
    path.write_text("".join(lines), encoding="utf-8")
    os.chmod(path, 0o600)
    return path


# ----------------------------------------------------------------------------- ACL
def _rule(
    rule_id: str, messages: Sequence[str], flows: Sequence[str], key_exprs: Iterable[str]
) -> dict:
    return {
        "id": rule_id,
        "messages": list(messages),
        "flows": list(flows),
        "permission": "allow",
        "key_exprs": list(key_exprs),
    }


def acl_config(profile: SecurityProfile) -> dict:
    """The router's ``access_control`` block (default deny) for ``profile``.

    Rules, with ``S = diffpos/<site>``:

    ========================== ============================================ =====================
    rule                        what                                         subjects
    ========================== ============================================ =====================
    ``learn-subscribers``       declare_subscriber egress on ``diffpos/**``  everybody
    ``anchor-<id>``             put ingress ``S/anchor/<id>/state``,         that anchor only
                                ``S/anchor/<id>/range/*``; liveliness token
                                ``S/alive/anchor/<id>`` (declare, and query
                                it: the container health check)
    ``run-control-read``        subscribe ``S/run/control``                  anchors
    ``fusion-publish``          put ingress estimates, diagnostics;          fusion
                                liveliness token ``S/alive/fusion``
    ``fusion-read``             subscribe ``S/anchor/*/state``,              fusion
                                ``S/anchor/*/range/*`` (never truth)
    ``emulator-publish``        put ingress ``S/truth/**``, ``S/run/control`` emulator
    ``read-all``                subscribe ``S/**``                           recorder, dashboard,
                                                                             emulator
    ``watch-alive``             liveliness subscriber/query on               fusion, recorder,
                                ``S/alive/**``                               dashboard, emulator
    ========================== ============================================ =====================

    "subscribe" = ``declare_subscriber`` ingress + ``put`` egress on the key expressions.
    With ``profile.mtls`` every subject also lists ``cert_common_names`` equal to its user
    names (zenoh requires one of each, so a password alone no longer suffices).
    """
    from diffpos_services.wire.keys import PREFIX

    s = f"{PREFIX}/{profile.site}"
    read = ("declare_subscriber", "put")
    watch = ("declare_liveliness_subscriber", "liveliness_query", "liveliness_token")
    rules: list[dict] = [
        _rule("learn-subscribers", ["declare_subscriber"], ["egress"], [f"{PREFIX}/**"]),
        _rule("run-control-read", read[:1], ["ingress"], [f"{s}/run/control"]),
        _rule("run-control-deliver", read[1:], ["egress"], [f"{s}/run/control"]),
        _rule(
            "fusion-publish",
            ["put"],
            ["ingress"],
            [f"{s}/node/*/estimate", f"{s}/fusion/diagnostics"],
        ),
        _rule("fusion-alive", ["liveliness_token"], ["ingress"], [f"{s}/alive/fusion"]),
        _rule(
            "fusion-read-subscribe",
            read[:1],
            ["ingress"],
            [f"{s}/anchor/**"],  # states, ranges and range batches, in publish order
        ),
        _rule(
            "fusion-read-deliver",
            read[1:],
            ["egress"],
            [f"{s}/anchor/**"],  # states, ranges and range batches, in publish order
        ),
        _rule("emulator-publish", ["put"], ["ingress"], [f"{s}/truth/**", f"{s}/run/control"]),
        _rule("read-all-subscribe", read[:1], ["ingress"], [f"{s}/**"]),
        _rule("read-all-deliver", read[1:], ["egress"], [f"{s}/**"]),
        _rule("watch-alive-ask", watch[:2], ["ingress"], [f"{s}/alive/**"]),
        _rule("watch-alive-deliver", watch[2:], ["egress"], [f"{s}/alive/**"]),
    ]
    subjects: list[dict] = []
    policies: list[dict] = []
    ids = profile.identities()
    everybody = sorted(ids)
    subjects.append({"id": "everybody", "usernames": everybody})
    policies.append({"id": "everybody", "rules": ["learn-subscribers"], "subjects": ["everybody"]})

    for a in profile.anchors:
        rid = f"anchor-{a}"
        rules.append(
            _rule(
                f"{rid}-publish",
                ["put"],
                ["ingress"],
                [f"{s}/anchor/{a}/state", f"{s}/anchor/{a}/range/*"],
            )
        )
        rules.append(
            _rule(f"{rid}-alive", ["liveliness_token"], ["ingress"], [f"{s}/alive/anchor/{a}"])
        )
        # the container health check: a liveliness query for its own token only
        rules.append(
            _rule(f"{rid}-health-ask", ["liveliness_query"], ["ingress"], [f"{s}/alive/anchor/{a}"])
        )
        rules.append(
            _rule(
                f"{rid}-health-answer",
                ["liveliness_token"],
                ["egress"],
                [f"{s}/alive/anchor/{a}"],
            )
        )
        subjects.append({"id": rid, "usernames": [anchor_user(a)]})
        policies.append(
            {
                "id": rid,
                "rules": [f"{rid}-publish", f"{rid}-alive", f"{rid}-health-ask", f"{rid}-health-answer"],
                "subjects": [rid],
            }
        )
    if profile.anchors:
        subjects.append({"id": "anchors", "usernames": [anchor_user(a) for a in profile.anchors]})
        policies.append(
            {
                "id": "anchors",
                "rules": ["run-control-read", "run-control-deliver"],
                "subjects": ["anchors"],
            }
        )

    by_role: dict[str, list[str]] = {}
    for user, (role, _) in ids.items():
        if role != "anchor":
            by_role.setdefault(role, []).append(user)
    role_rules = {
        "fusion": [
            "fusion-publish",
            "fusion-alive",
            "fusion-read-subscribe",
            "fusion-read-deliver",
            "watch-alive-ask",
            "watch-alive-deliver",
        ],
        "recorder": [
            "read-all-subscribe",
            "read-all-deliver",
            "watch-alive-ask",
            "watch-alive-deliver",
        ],
        "dashboard": [
            "read-all-subscribe",
            "read-all-deliver",
            "watch-alive-ask",
            "watch-alive-deliver",
        ],
        "emulator": [
            "emulator-publish",
            "read-all-subscribe",
            "read-all-deliver",
            "watch-alive-ask",
            "watch-alive-deliver",
        ],
    }
    for role in ROLES[1:]:
        if role in by_role:
            subjects.append({"id": role, "usernames": sorted(by_role[role])})
            policies.append({"id": role, "rules": role_rules[role], "subjects": [role]})
    if profile.mtls:  # with client certificates, a subject needs the user name AND its certificate
        for subj in subjects:
            subj["cert_common_names"] = list(subj["usernames"])
    used = {r for p in policies for r in p["rules"]}
    rules = [r for r in rules if r["id"] in used]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# ----------------------------------------------------------------------------- configs
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
    _check_encrypted(listen, field_name="listen")
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
        _check_encrypted(connect, field_name="connect")
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
    """A ``zenoh.Config`` from a configuration dict (imports zenoh)."""
    import zenoh

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
    import zenoh

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
    m = _ENDPOINT_RE.match(str(endpoint))
    if not m:
        return False
    host = m.group(2).strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# ----------------------------------------------------------------------------- rendering
def _json5_text(config: Mapping[str, Any], header: str) -> str:
    body = json.dumps(config, indent=2)
    return "".join(f"// {line}\n" for line in header.splitlines()) + body + "\n"


def render_profile(
    profile: SecurityProfile,
    out_dir: str | Path,
    *,
    base_dir: str | Path | None = None,
    connect_timeout_ms: int = -1,
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
) -> list[Path]:
    """Write ``router.json5`` and one ``<user>.json5`` per identity into ``out_dir``.

    ``connect``/``listen`` replace the profile's endpoints (e.g. ``tls/localhost:7447`` to run
    the services on this machine). Returns the written paths. The files are ordinary zenoh
    configurations: the router file
    works with ``zenohd -c`` and with ``zenoh.Config.from_file``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    where = f"paths under {base_dir}" if base_dir is not None else "absolute paths of this machine"
    written = []
    header = (
        "GENERATED by `python -m diffpos_services.bus.security render` from the security profile;\n"
        f"edit the profile and re-render, not this file ({where}).\n"
    )
    p = out / "router.json5"
    p.write_text(
        _json5_text(
            router_config(profile, listen=listen, base_dir=base_dir), header + "Role: router."
        ),
        encoding="utf-8",
    )
    written.append(p)
    for user, (role, anchor_id) in sorted(profile.identities().items()):
        cfg = client_config(
            profile, user, connect=connect, connect_timeout_ms=connect_timeout_ms, base_dir=base_dir
        )
        what = f"Role: {role}" + (f" (anchor {anchor_id})" if anchor_id else "") + f", user {user}."
        p = out / f"{user}.json5"
        p.write_text(
            _json5_text(cfg, header + what + "\nContains a password: DEV ONLY."), encoding="utf-8"
        )
        os.chmod(p, 0o600)
        written.append(p)
    return written


def check_profile(profile: SecurityProfile) -> list[str]:
    """Problems of a profile's files (missing certificate, user without password, ...)."""
    problems = []
    for name in ("ca_certificate", "router_certificate", "router_private_key", "dictionary_file"):
        p = Path(profile.path(getattr(profile, name)))
        if not p.is_file():
            problems.append(
                f"{name}: {p} does not exist (run security/make_dev_certs.py for dev files)"
            )
    try:
        creds = read_credentials(profile.path(profile.dictionary_file))
    except SecurityError as exc:
        problems.append(str(exc))
    else:
        for user in profile.identities():
            if user not in creds:
                problems.append(f"user {user!r} has no password in {profile.dictionary_file}")
    if profile.mtls:
        for user in profile.identities():
            for ext in ("pem", "key"):
                p = Path(profile.path(f"{profile.client_cert_dir}/{user}.{ext}"))
                if not p.is_file():
                    problems.append(f"mtls: {p} does not exist")
    return problems


# ----------------------------------------------------------------------------- certificates
def make_dev_certs(
    out_dir: str | Path,
    *,
    hosts: Sequence[str] = ("localhost", "router", "127.0.0.1"),
    clients: Sequence[str] = (),
    days: int = 825,
    backend: str = "auto",
) -> dict[str, Path]:
    """Create a DEV ONLY certificate authority, a router certificate and client certificates.

    Parameters
    ----------
    out_dir : str or Path
        Output folder: ``ca.pem``, ``ca.key``, ``router.pem``, ``router.key`` and
        ``clients/<name>.pem|key`` for each client.
    hosts : sequence of str
        DNS names / IP addresses of the router (subjectAltName); clients check the name they
        connect to (``tls/<host>:port``) against this list.
    clients : sequence of str
        Common names of client certificates (only needed with ``mtls = true``); the ACL can
        match them with ``cert_common_names``.
    days : int [day]
        Validity.
    backend : {"auto", "cryptography", "openssl"}
        ``auto``: the ``cryptography`` package if importable, else the ``openssl`` CLI.

    Returns
    -------
    dict
        Name (``"ca"``, ``"ca_key"``, ``"router"``, ``"router_key"``, ``"client:<name>"``,
        ``"client_key:<name>"``) -> path.

    Keys are ECDSA P-256 in PKCS#8 PEM, private keys written with mode 0600.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if clients:
        (out / "clients").mkdir(exist_ok=True)
    if not hosts:
        raise SecurityError(
            "hosts: the router certificate needs at least one DNS name or IP address"
        )
    for c in clients:
        _check_user(c, field_name="clients")
    if backend == "auto":
        try:
            import cryptography  # noqa: F401

            backend = "cryptography"
        except ImportError:
            backend = "openssl"
    if backend == "cryptography":
        paths = _certs_cryptography(out, hosts, clients, days)
    elif backend == "openssl":
        if shutil.which("openssl") is None:
            raise SecurityError(
                "neither the 'cryptography' package nor the 'openssl' command is available"
            )
        paths = _certs_openssl(out, hosts, clients, days)
    else:
        raise SecurityError(f"backend={backend!r}: use auto, cryptography or openssl")
    for name, p in paths.items():
        if "key" in name:
            os.chmod(p, 0o600)
    return paths


def _san(hosts: Sequence[str]) -> list[tuple[str, str]]:
    out = []
    for h in hosts:
        try:
            ipaddress.ip_address(h)
            out.append(("IP", h))
        except ValueError:
            out.append(("DNS", h))
    return out


def _certs_openssl(
    out: Path, hosts: Sequence[str], clients: Sequence[str], days: int
) -> dict[str, Path]:
    def run(*args: str) -> None:
        r = subprocess.run(["openssl", *args], capture_output=True, text=True)
        if r.returncode != 0:
            raise SecurityError(f"openssl {args[0]} failed: {r.stderr.strip()}")

    san = ",".join(f"{k}:{v}" for k, v in _san(hosts))
    cnf = (
        "[req]\ndistinguished_name=dn\n[dn]\n"
        "[v3_ca]\nbasicConstraints=critical,CA:TRUE\nkeyUsage=critical,keyCertSign,cRLSign\n"
        "subjectKeyIdentifier=hash\n"
        "[v3_server]\nbasicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        f"extendedKeyUsage=serverAuth\nsubjectAltName={san}\n"
        "subjectKeyIdentifier=hash\nauthorityKeyIdentifier=keyid\n"
        "[v3_client]\nbasicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        "extendedKeyUsage=clientAuth\nsubjectKeyIdentifier=hash\nauthorityKeyIdentifier=keyid\n"
    )
    paths: dict[str, Path] = {
        "ca": out / "ca.pem",
        "ca_key": out / "ca.key",
        "router": out / "router.pem",
        "router_key": out / "router.key",
    }
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "openssl.cnf"
        cfg.write_text(cnf)
        ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes")
        run(
            "req",
            "-x509",
            *ec,
            "-keyout",
            str(paths["ca_key"]),
            "-out",
            str(paths["ca"]),
            "-days",
            str(days),
            "-subj",
            "/O=diffpos DEV ONLY/CN=diffpos dev CA (DEV ONLY)",
            "-config",
            str(cfg),
            "-extensions",
            "v3_ca",
        )

        def leaf(cn: str, cert: Path, key: Path, ext: str) -> None:
            csr = Path(tmp) / f"{cert.stem}.csr"
            run(
                "req",
                "-new",
                *ec,
                "-keyout",
                str(key),
                "-out",
                str(csr),
                "-subj",
                f"/O=diffpos DEV ONLY/CN={cn}",
                "-config",
                str(cfg),
            )
            run(
                "x509",
                "-req",
                "-in",
                str(csr),
                "-CA",
                str(paths["ca"]),
                "-CAkey",
                str(paths["ca_key"]),
                "-set_serial",
                str(int.from_bytes(os.urandom(8), "big")),
                "-out",
                str(cert),
                "-days",
                str(days),
                "-extfile",
                str(cfg),
                "-extensions",
                ext,
            )

        leaf(hosts[0], paths["router"], paths["router_key"], "v3_server")
        for c in clients:
            paths[f"client:{c}"] = out / "clients" / f"{c}.pem"
            paths[f"client_key:{c}"] = out / "clients" / f"{c}.key"
            leaf(c, paths[f"client:{c}"], paths[f"client_key:{c}"], "v3_client")
    return paths


def _certs_cryptography(
    out: Path, hosts: Sequence[str], clients: Sequence[str], days: int
) -> dict[str, Path]:
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.UTC)

    def name(cn: str) -> x509.Name:
        return x509.Name(
            [
                x509.NameAttribute(NameOID.ORGANIZATION_NAME, "diffpos DEV ONLY"),
                x509.NameAttribute(NameOID.COMMON_NAME, cn),
            ]
        )

    def write(key, cert, cert_path: Path, key_path: Path) -> None:
        key_path.write_bytes(
            key.private_bytes(
                serialization.Encoding.PEM,
                serialization.PrivateFormat.PKCS8,
                serialization.NoEncryption(),
            )
        )
        cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = name("diffpos dev CA (DEV ONLY)")
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False),
            critical=True,
        )
        .add_extension(
            x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    paths: dict[str, Path] = {
        "ca": out / "ca.pem",
        "ca_key": out / "ca.key",
        "router": out / "router.pem",
        "router_key": out / "router.key",
    }
    write(ca_key, ca, paths["ca"], paths["ca_key"])

    def leaf(cn: str, eku, san: list | None, cert_path: Path, key_path: Path) -> None:
        key = ec.generate_private_key(ec.SECP256R1())
        b = (
            x509.CertificateBuilder()
            .subject_name(name(cn))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.KeyUsage(True, False, False, False, False, False, False, False, False),
                critical=True,
            )
            .add_extension(x509.ExtendedKeyUsage([eku]), critical=False)
            .add_extension(
                x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                critical=False,
            )
        )
        if san:
            b = b.add_extension(x509.SubjectAlternativeName(san), critical=False)
        write(key, b.sign(ca_key, hashes.SHA256()), cert_path, key_path)

    san = [
        x509.IPAddress(ipaddress.ip_address(v)) if k == "IP" else x509.DNSName(v)
        for k, v in _san(hosts)
    ]
    leaf(hosts[0], ExtendedKeyUsageOID.SERVER_AUTH, san, paths["router"], paths["router_key"])
    for c in clients:
        paths[f"client:{c}"] = out / "clients" / f"{c}.pem"
        paths[f"client_key:{c}"] = out / "clients" / f"{c}.key"
        leaf(
            c, ExtendedKeyUsageOID.CLIENT_AUTH, None, paths[f"client:{c}"], paths[f"client_key:{c}"]
        )
    return paths


# ----------------------------------------------------------------------------- CLI
def main(argv: Sequence[str] | None = None) -> int:
    """``python -m diffpos_services.bus.security {certs,render,check} ...``."""
    ap = argparse.ArgumentParser(
        prog="python -m diffpos_services.bus.security", description=__doc__.splitlines()[0]
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser(
        "certs", help="create a DEV ONLY CA, router certificate and client certificates"
    )
    c.add_argument("out_dir")
    c.add_argument(
        "--host",
        action="append",
        help="router DNS name/IP (repeatable; default localhost, router, 127.0.0.1)",
    )
    c.add_argument(
        "--client", action="append", default=[], help="client certificate common name (repeatable)"
    )
    c.add_argument("--days", type=int, default=825)
    c.add_argument("--backend", choices=["auto", "cryptography", "openssl"], default="auto")
    r = sub.add_parser("render", help="write router.json5 and <user>.json5 from a profile")
    r.add_argument("profile")
    r.add_argument("out_dir")
    r.add_argument(
        "--base-dir", help="where the profile folder is mounted for the services (e.g. /security)"
    )
    r.add_argument(
        "--connect", action="append", help="client endpoint (repeatable; default: the profile's)"
    )
    r.add_argument(
        "--listen", action="append", help="router endpoint (repeatable; default: the profile's)"
    )
    k = sub.add_parser("check", help="validate a profile and the files it names")
    k.add_argument("profile")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "certs":
            paths = make_dev_certs(
                args.out_dir,
                hosts=args.host or ("localhost", "router", "127.0.0.1"),
                clients=args.client,
                days=args.days,
                backend=args.backend,
            )
            for n, p in paths.items():
                print(f"{n:24s} {p}")
        elif args.cmd == "render":
            for p in render_profile(
                load_profile(args.profile),
                args.out_dir,
                base_dir=args.base_dir,
                connect=args.connect,
                listen=args.listen,
            ):
                print(p)
        else:
            problems = check_profile(load_profile(args.profile))
            for p in problems:
                print("problem:", p)
            if problems:
                return 1
            print("ok")
    except SecurityError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
