"""Exit 0 if a liveliness token is alive on the bus (container health checks)

Opens a short Zenoh session (a plain client of --connect, or the identity of a
--zenoh-config file on a secured bus), asks for the liveliness token KEY and prints
"healthy" (exit 0) or "unhealthy" (exit 1). A bad --zenoh-config file exits 2.

examples:
  diffpos health --connect tcp/router:7447 --liveliness KEY
  diffpos health --zenoh-config /security/zenoh/fusion.json5 --liveliness KEY
  (KEY: the service's liveliness token, as named in diffpos_services.wire.keys)
"""

from __future__ import annotations

import argparse

from diffpos_services.bus.health import health_check


def add_arguments(parser: argparse.ArgumentParser) -> None:
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--connect", action="append", metavar="ENDPOINT",
                       help="plain router endpoint (repeatable), e.g. tcp/router:7447")
    where.add_argument("--zenoh-config", metavar="FILE",
                       help="zenoh json5 file of the service's identity (secured bus), e.g. "
                       "/security/zenoh/fusion.json5")
    parser.add_argument("--liveliness", required=True, metavar="KEY",
                        help="liveliness key expression the service declares (required)")
    parser.add_argument("--timeout", type=float, default=3.0, metavar="S",
                        help="give up after S seconds [s] (default 3)")


def run(args: argparse.Namespace) -> int:
    ok = health_check(args.connect, args.liveliness, timeout_s=args.timeout,
                      zenoh_config=args.zenoh_config)
    print("healthy" if ok else "unhealthy")
    return 0 if ok else 1
