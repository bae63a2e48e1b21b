"""Per-run secrets: fresh passwords and certificates for one ``diffpos emulate`` run.

The committed dev set (``security/credentials.dev.txt``, ``security/certs/``) is public: anyone
who has the repository can log in with it. ``diffpos emulate --security-profile`` therefore
never uses those secrets; :func:`per_run_profile` keeps what the profile *says* (site,
anchors, users, mTLS, lease) and replaces what it *holds*: a random password per identity, a
throw-away CA and router certificate (client certificates too with ``mtls``), all written
into a private folder (mode 0700) that the caller removes at the end of the run. The CA's
private key is deleted as soon as the certificates are issued: nothing can be signed with
it during the run.
"""

from __future__ import annotations

import dataclasses
import secrets
from collections.abc import Sequence
from pathlib import Path

from diffpos_services.bus.security.certs import make_dev_certs
from diffpos_services.bus.security.credentials import write_credentials
from diffpos_services.bus.security.profile import SecurityError, SecurityProfile

__all__ = ["PER_RUN_DICTIONARY", "per_run_profile"]

#: File name of the per-run password dictionary inside the private folder.
PER_RUN_DICTIONARY = "credentials.txt"

#: Validity of the per-run certificates [days] (a run is minutes to hours long).
_DAYS = 2


def per_run_profile(
    profile: SecurityProfile, out_dir: str | Path, *, hosts: Sequence[str],
    backend: str = "auto",
) -> SecurityProfile:
    """Fresh secrets for ``profile`` in the private folder ``out_dir``; the profile using them.

    Parameters
    ----------
    profile : SecurityProfile
        The profile whose identities, site, anchors, mTLS and lease are kept.
    out_dir : str or Path
        An existing folder only this user may enter (mode 0700, e.g. a
        ``tempfile.TemporaryDirectory``); the caller removes it after the run.
    hosts : sequence of str
        Names the router certificate is valid for (the host the clients dial).
    backend : str
        Certificate backend (:func:`~.certs.make_dev_certs`).

    Returns
    -------
    SecurityProfile
        ``profile`` with ``root = out_dir`` and its certificate, key and dictionary files
        replaced by the fresh ones (``certs/``, :data:`PER_RUN_DICTIONARY`).

    Raises
    ------
    SecurityError
        ``out_dir`` is missing or other users may access it; certificate generation failed.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise SecurityError(f"per-run secrets: folder {out} does not exist")
    mode = out.stat().st_mode & 0o777
    if mode & 0o077:
        raise SecurityError(f"per-run secrets: folder {out} has mode {mode:o}; it must be "
                            "private to this user (0700)")
    users = sorted(profile.identities())
    write_credentials(out / PER_RUN_DICTIONARY,
                      {u: secrets.token_urlsafe(24) for u in users})
    clients = users if profile.mtls else ()
    paths = make_dev_certs(out / "certs", hosts=list(dict.fromkeys(hosts)), clients=clients,
                           days=_DAYS, backend=backend)
    paths["ca_key"].unlink()  # issued: nobody signs anything with it during the run
    return dataclasses.replace(
        profile, root=out, ca_certificate="certs/ca.pem", router_certificate="certs/router.pem",
        router_private_key="certs/router.key", dictionary_file=PER_RUN_DICTIONARY,
        client_cert_dir="certs/clients")
