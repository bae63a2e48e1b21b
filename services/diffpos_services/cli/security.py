"""Bus security: DEV certificates, zenoh json5 files from a profile, profile check

A security profile (security/profile.dev.toml) names the anchors, users, certificates and
password dictionary of a secured bus (TLS + user/password + access control, see
security/README.md). Three actions:

  certs   a DEV ONLY certificate authority, router certificate and client certificates
  render  router.json5 and one <user>.json5 per identity from a profile
  check   validate a profile and the files it names (exit 1 if something is missing)

examples:
  diffpos security render security/profile.dev.toml security/zenoh --base-dir /security
  diffpos security check security/profile.dev.toml
  diffpos security certs /tmp/certs --host router --client fusion
"""

from __future__ import annotations

import argparse

from diffpos_services.bus.security.certs import make_dev_certs
from diffpos_services.bus.security.profile import load_profile
from diffpos_services.bus.security.render import check_profile, render_profile

DEFAULT_HOSTS = ("localhost", "router", "127.0.0.1")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True)
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
    c.set_defaults(_action=_certs)
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
    r.set_defaults(_action=_render)
    k = sub.add_parser("check", help="validate a profile and the files it names")
    k.add_argument("profile")
    k.set_defaults(_action=_check)


def run(args: argparse.Namespace) -> int:
    return args._action(args)


def _certs(args: argparse.Namespace) -> int:
    paths = make_dev_certs(args.out_dir, hosts=args.host or DEFAULT_HOSTS, clients=args.client,
                           days=args.days, backend=args.backend)
    for n, p in paths.items():
        print(f"{n:24s} {p}")
    return 0


def _render(args: argparse.Namespace) -> int:
    for p in render_profile(load_profile(args.profile), args.out_dir, base_dir=args.base_dir,
                            connect=args.connect, listen=args.listen):
        print(p)
    return 0


def _check(args: argparse.Namespace) -> int:
    problems = check_profile(load_profile(args.profile))
    for p in problems:
        print("problem:", p)
    if problems:
        return 1
    print("ok")
    return 0
