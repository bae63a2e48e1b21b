"""The security profile: which identities (roles, users) exist and which files they use.

A profile is a small TOML file (``security/profile.dev.toml``); :func:`load_profile` reads
and validates it into a :class:`SecurityProfile`. Validation is strict: an unknown key, a
plain ``tcp/`` endpoint or a user name zenoh would reject is a :class:`SecurityError`
naming the field (a typo must not silently weaken the configuration).
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from diffpos_services.errors import DiffposError

__all__ = [
    "ROLES",
    "SecurityError",
    "SecurityProfile",
    "anchor_user",
    "load_profile",
    "profile_from_dict",
]

#: Roles an identity can have on the bus.
ROLES = ("anchor", "fusion", "recorder", "dashboard", "emulator")

_ID_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_\-]{0,63}$")
_USER_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]{0,63}$")
ENDPOINT_RE = re.compile(
    r"^(tcp|udp|tls|quic|ws|unixsock-stream)/(\[[0-9a-fA-F:]+\]|[^/:\s]+):(\d{1,5})$"
)


class SecurityError(DiffposError, ValueError):
    """Invalid security profile, credentials file or role; the message names the field.

    ``diffpos security`` exits 2 with it (a ``ValueError`` too, for callers that catch those).
    """

    exit_code = 2


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
            check_user(user, field_name=f"users.{role}")
        names = [anchor_user(a) for a in self.anchors] + list(self.users.values())
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise SecurityError(
                f"users: the user name(s) {sorted(dup)} are used by more than one identity"
            )
        for name in ("listen", "connect"):
            check_encrypted(getattr(self, name), field_name=name)

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


def check_encrypted(endpoints: Sequence[str], *, field_name: str) -> None:
    """Raise :class:`SecurityError` unless every endpoint is a ``tls/``/``quic/`` locator."""
    if not endpoints:
        raise SecurityError(f"{field_name}: give at least one endpoint")
    for e in endpoints:
        m = ENDPOINT_RE.match(str(e))
        if not m:
            raise SecurityError(f"{field_name}: {e!r} is not a Zenoh endpoint such as 'tls/router:7447'")
        if m.group(1) not in ("tls", "quic"):
            raise SecurityError(
                f"{field_name}: {e!r} is not encrypted; a security profile only uses "
                "'tls/' (or 'quic/') endpoints"
            )


def check_user(user: Any, *, field_name: str) -> str:
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

