"""The zenoh user/password dictionary: one ``user:password`` per line, nothing else.

Zenoh refuses to start a router whose dictionary has a comment or a blank line, so
:func:`read_credentials` reports those (and duplicates) naming the line.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from diffpos_services.bus.security.profile import SecurityError, check_user

__all__ = ["read_credentials", "write_credentials"]


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
        check_user(user, field_name=f"dictionary_file {path}, line {i}: user")
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
        check_user(user, field_name="user")
        if not pw or "\n" in pw or pw != pw.strip():
            raise SecurityError(
                f"password of {user!r}: must be non-empty, one line, no surrounding spaces"
            )
        lines.append(f"{user}:{pw}\n")
    path.write_text("".join(lines), encoding="utf-8")
    os.chmod(path, 0o600)
    return path
