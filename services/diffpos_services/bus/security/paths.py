"""Names and file layout of the DEV certificates (shared by both backends of :mod:`.certs`)."""

from __future__ import annotations

import ipaddress
from collections.abc import Sequence
from pathlib import Path

__all__ = ["CA_NAME", "ORGANISATION", "cert_paths", "subject_alt_names"]

#: Subject organisation of every certificate made here.
ORGANISATION = "diffpos DEV ONLY"
#: Common name of the dev CA.
CA_NAME = "diffpos dev CA (DEV ONLY)"


def cert_paths(out: Path, clients: Sequence[str] = ()) -> dict[str, Path]:
    """Where :func:`.certs.make_dev_certs` writes each file under ``out`` (the returned dict)."""
    paths = {
        "ca": out / "ca.pem",
        "ca_key": out / "ca.key",
        "router": out / "router.pem",
        "router_key": out / "router.key",
    }
    for c in clients:
        paths[f"client:{c}"] = out / "clients" / f"{c}.pem"
        paths[f"client_key:{c}"] = out / "clients" / f"{c}.key"
    return paths


def subject_alt_names(hosts: Sequence[str]) -> list[tuple[str, str]]:
    """``("IP", host)`` for an IP address, else ``("DNS", host)``."""
    out = []
    for h in hosts:
        try:
            ipaddress.ip_address(h)
            out.append(("IP", h))
        except ValueError:
            out.append(("DNS", h))
    return out
