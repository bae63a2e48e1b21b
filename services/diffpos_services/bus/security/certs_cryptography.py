"""The ``cryptography`` backend of :func:`.certs.make_dev_certs` (optional package).

``cryptography`` is not a dependency of diffpos: without it :data:`AVAILABLE` is False and
:func:`.certs.make_dev_certs` uses the ``openssl`` command.
"""

from __future__ import annotations

import datetime
import ipaddress
from collections.abc import Sequence
from pathlib import Path

from diffpos_services.bus.security.paths import (
    CA_NAME,
    ORGANISATION,
    cert_paths,
    subject_alt_names,
)

try:  # optional extra
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
except ImportError:  # pragma: no cover - depends on the environment
    AVAILABLE = False
else:
    AVAILABLE = True

__all__ = ["AVAILABLE", "certs_cryptography"]


def _name(cn: str):
    return x509.Name([
        x509.NameAttribute(NameOID.ORGANIZATION_NAME, ORGANISATION),
        x509.NameAttribute(NameOID.COMMON_NAME, cn),
    ])


def _write(key, cert, cert_path: Path, key_path: Path) -> None:
    key_path.write_bytes(key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption()))
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _builder(subject: str, issuer, public_key, days: int):
    now = datetime.datetime.now(datetime.UTC)
    return (
        x509.CertificateBuilder()
        .subject_name(_name(subject))
        .issuer_name(issuer)
        .public_key(public_key)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
    )


def _ca(days: int, cert_path: Path, key_path: Path):
    """A self-signed CA (key usage: certificate and CRL signing); returns its key."""
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        _builder(CA_NAME, _name(CA_NAME), key.public_key(), days)
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(False, False, False, False, False, True, True, False, False),
            critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                       critical=False)
        .sign(key, hashes.SHA256())
    )
    _write(key, cert, cert_path, key_path)
    return key


def _leaf(ca_key, cn: str, eku, san: list | None, days: int, cert_path: Path,
          key_path: Path) -> None:
    """A key and a certificate for ``cn`` (digital signature, extended usage ``eku``)."""
    key = ec.generate_private_key(ec.SECP256R1())
    b = (
        _builder(cn, _name(CA_NAME), key.public_key(), days)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(True, False, False, False, False, False, False, False, False),
            critical=True)
        .add_extension(x509.ExtendedKeyUsage([eku]), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                       critical=False)
    )
    if san:
        b = b.add_extension(x509.SubjectAlternativeName(san), critical=False)
    _write(key, b.sign(ca_key, hashes.SHA256()), cert_path, key_path)


def certs_cryptography(
    out: Path, hosts: Sequence[str], clients: Sequence[str], days: int
) -> dict[str, Path]:
    """The files of :func:`.certs.make_dev_certs` made with the ``cryptography`` package."""
    paths = cert_paths(out, clients)
    ca_key = _ca(days, paths["ca"], paths["ca_key"])
    san = [
        x509.IPAddress(ipaddress.ip_address(v)) if k == "IP" else x509.DNSName(v)
        for k, v in subject_alt_names(hosts)
    ]
    _leaf(ca_key, hosts[0], ExtendedKeyUsageOID.SERVER_AUTH, san, days, paths["router"],
          paths["router_key"])
    for c in clients:
        _leaf(ca_key, c, ExtendedKeyUsageOID.CLIENT_AUTH, None, days, paths[f"client:{c}"],
              paths[f"client_key:{c}"])
    return paths
