#!/usr/bin/env python3
"""Create the DEV ONLY certificates (and optionally new dev passwords) of the diffpos bus.

Writes, next to this script unless told otherwise:

- ``certs/ca.pem``, ``certs/ca.key``: a throw-away certificate authority;
- ``certs/router.pem``, ``certs/router.key``: the router's TLS identity, valid for the
  names given with ``--host`` (default: localhost, router, 127.0.0.1; clients check the name
  they connect to, e.g. ``tls/router:7447`` in docker-compose);
- ``certs/clients/<user>.pem|key`` for ``--client USER`` (only needed with ``mtls = true``);
- with ``--new-passwords``: a fresh ``credentials.dev.txt`` for every identity of the
  profile, then ``zenoh/*.json5`` re-rendered from ``profile.dev.toml``.

Uses the ``cryptography`` package when it is importable, else the ``openssl`` command.
Everything written here is for development only: the keys and passwords are committed, and
only the docker-compose example uses them (``diffpos emulate --security-profile`` makes fresh
ones for every run, see security/README.md).

examples:
  python security/make_dev_certs.py                         regenerate the dev CA + router cert
  python security/make_dev_certs.py --host router --host my-laptop.local
  python security/make_dev_certs.py --new-passwords         rotate every dev password
  python security/make_dev_certs.py --out /tmp/certs --days 2
"""

from __future__ import annotations

import argparse
import secrets
import sys
from pathlib import Path

from diffpos_services.bus.security.certs import make_dev_certs
from diffpos_services.bus.security.credentials import write_credentials
from diffpos_services.bus.security.profile import SecurityError, load_profile
from diffpos_services.bus.security.render import render_profile

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog="\n".join(__doc__.splitlines()[2:]),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=HERE / "certs", help="output folder (default security/certs)")
    ap.add_argument("--host", action="append", help="router DNS name or IP (repeatable)")
    ap.add_argument("--client", action="append", default=[], help="client certificate for USER (repeatable)")
    ap.add_argument("--days", type=int, default=825, help="validity [days] (default 825)")
    ap.add_argument("--backend", choices=["auto", "cryptography", "openssl"], default="auto")
    ap.add_argument("--new-passwords", action="store_true",
                    help="write new random passwords to credentials.dev.txt and re-render zenoh/*.json5")
    ap.add_argument("--profile", type=Path, default=HERE / "profile.dev.toml")
    args = ap.parse_args(argv)
    try:
        hosts = args.host or ["localhost", "router", "127.0.0.1"]
        paths = make_dev_certs(args.out, hosts=hosts, clients=args.client, days=args.days, backend=args.backend)
        for name, p in paths.items():
            print(f"wrote {name:22s} {p}")
        if args.new_passwords:
            profile = load_profile(args.profile)
            creds = {u: f"dev-{secrets.token_urlsafe(12)}" for u in profile.identities()}
            p = write_credentials(profile.path(profile.dictionary_file), creds)
            print(f"wrote {len(creds)} passwords to {p}")
            for p in render_profile(profile, args.profile.parent / "zenoh", base_dir="/security"):
                print(f"rendered {p}")
    except SecurityError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print("DEV ONLY: never deploy these keys or passwords.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
