"""DEV ONLY certificates: a throw-away CA, the router's TLS identity, client certificates.

Two backends make the same files: the ``cryptography`` package (optional, not a dependency:
:mod:`.certs_cryptography`) and the ``openssl`` command (here). Keys are ECDSA P-256 in
PKCS#8 PEM, private keys written with mode 0600.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path

from diffpos_services.bus.security import certs_cryptography
from diffpos_services.bus.security.paths import (
    CA_NAME,
    ORGANISATION,
    cert_paths,
    subject_alt_names,
)
from diffpos_services.bus.security.profile import SecurityError, check_user

__all__ = ["make_dev_certs"]

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
        check_user(c, field_name="clients")
    paths = _make_with(_choose_backend(backend), out, hosts, clients, days)
    for name, p in paths.items():
        if "key" in name:
            os.chmod(p, 0o600)
    return paths


def _choose_backend(backend: str) -> str:
    if backend == "auto":
        return "cryptography" if certs_cryptography.AVAILABLE else "openssl"
    if backend not in ("cryptography", "openssl"):
        raise SecurityError(f"backend={backend!r}: use auto, cryptography or openssl")
    return backend


def _make_with(
    backend: str, out: Path, hosts: Sequence[str], clients: Sequence[str], days: int
) -> dict[str, Path]:
    if backend == "cryptography":
        if not certs_cryptography.AVAILABLE:
            raise SecurityError("backend='cryptography': the 'cryptography' package is not "
                                "installed (pip install cryptography), or use openssl")
        return certs_cryptography.certs_cryptography(out, hosts, clients, days)
    if shutil.which("openssl") is None:
        raise SecurityError(
            "neither the 'cryptography' package nor the 'openssl' command is available"
        )
    return _certs_openssl(out, hosts, clients, days)


# ----------------------------------------------------------------------------- openssl backend
_EC = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes")


def _openssl(*args: str) -> None:
    r = subprocess.run(["openssl", *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise SecurityError(f"openssl {args[0]} failed: {r.stderr.strip()}")


def _openssl_cnf(hosts: Sequence[str]) -> str:
    """The extension sections of the CA, the router (server) and client certificates."""
    san = ",".join(f"{k}:{v}" for k, v in subject_alt_names(hosts))
    return (
        "[req]\ndistinguished_name=dn\n[dn]\n"
        "[v3_ca]\nbasicConstraints=critical,CA:TRUE\nkeyUsage=critical,keyCertSign,cRLSign\n"
        "subjectKeyIdentifier=hash\n"
        "[v3_server]\nbasicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        f"extendedKeyUsage=serverAuth\nsubjectAltName={san}\n"
        "subjectKeyIdentifier=hash\nauthorityKeyIdentifier=keyid\n"
        "[v3_client]\nbasicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        "extendedKeyUsage=clientAuth\nsubjectKeyIdentifier=hash\nauthorityKeyIdentifier=keyid\n"
    )


def _openssl_ca(ca: Path, ca_key: Path, cnf: Path, days: int) -> None:
    _openssl("req", "-x509", *_EC, "-keyout", str(ca_key), "-out", str(ca),
             "-days", str(days), "-subj", f"/O={ORGANISATION}/CN={CA_NAME}",
             "-config", str(cnf), "-extensions", "v3_ca")


def _openssl_leaf(
    cn: str, cert: Path, key: Path, ext: str, *, ca: Path, ca_key: Path, cnf: Path, days: int
) -> None:
    """A key and a certificate for ``cn`` signed by the CA (``ext``: v3_server or v3_client)."""
    csr = cnf.parent / f"{cert.stem}.csr"
    _openssl("req", "-new", *_EC, "-keyout", str(key), "-out", str(csr),
             "-subj", f"/O={ORGANISATION}/CN={cn}", "-config", str(cnf))
    _openssl("x509", "-req", "-in", str(csr), "-CA", str(ca), "-CAkey", str(ca_key),
             "-set_serial", str(int.from_bytes(os.urandom(8), "big")), "-out", str(cert),
             "-days", str(days), "-extfile", str(cnf), "-extensions", ext)


def _certs_openssl(
    out: Path, hosts: Sequence[str], clients: Sequence[str], days: int
) -> dict[str, Path]:
    paths = cert_paths(out, clients)
    with tempfile.TemporaryDirectory() as tmp:
        cnf = Path(tmp) / "openssl.cnf"
        cnf.write_text(_openssl_cnf(hosts))
        ca = {"ca": paths["ca"], "ca_key": paths["ca_key"], "cnf": cnf, "days": days}
        _openssl_ca(paths["ca"], paths["ca_key"], cnf, days)
        _openssl_leaf(hosts[0], paths["router"], paths["router_key"], "v3_server", **ca)
        for c in clients:
            _openssl_leaf(c, paths[f"client:{c}"], paths[f"client_key:{c}"], "v3_client", **ca)
    return paths
