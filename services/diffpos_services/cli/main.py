"""The ``diffpos`` command line.

Each subcommand lives in its own module ``diffpos_services.cli.<name>`` with a module
docstring (first line = one-line help), ``add_arguments(parser)`` and ``run(args) -> int``.
Modules are imported only when their subcommand runs, so ``diffpos --help`` stays fast and a
numeric command never pays for importing Zenoh or Rerun.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

#: subcommand -> (module, one-line help). The order is the order shown by ``--help``.
COMMANDS: dict[str, tuple[str, str]] = {
    "emulate": ("emulate", "Run the whole system on this machine: router, anchors, fusion, recorder, dashboard"),
    "solve": ("solve", "Position fixes from JSON Lines problems on stdin (D-NLS, LLS, IPPA)"),
    "reproduce": ("reproduce", "Regenerate the paper's study: MPC table, first-arrival stats, error CDFs"),
    "bounds": ("bounds", "PEB and z-axis bound over a grid of indoor nodes, heat maps per floor"),
    "power-ratio": ("power_ratio", "Upper/lower edge diffraction power ratio (Theorem 3): PNG + CSV"),
    "router": ("router", "Zenoh router in this Python process (no zenohd binary needed)"),
    "anchor": ("anchor", "One UAV anchor: flies its trajectory, ranges to nodes, publishes over Zenoh"),
    "fusion": ("fusion", "Fusion service: aligns ranges in time, D-NLS with outlier gating, publishes fixes"),
    "recorder": ("recorder", "Record every message on the bus to MCAP (with liveliness events and config)"),
    "replay": ("replay", "Re-run fusion offline from an MCAP recording; error report, CDF plot, what-ifs"),
    "inspect": ("inspect", "Channels, schemas, counts, time span, anchors and nodes of an MCAP recording"),
    "recover": ("recover", "Rewrite a truncated MCAP recording (e.g. after SIGKILL) into a valid one"),
    "dashboard": ("dashboard", "Live Rerun dashboard of a running system (viewer, web viewer or .rrd)"),
    "to-rerun": ("to_rerun", "Convert an MCAP recording into a Rerun .rrd dashboard"),
    "raytrace": ("raytrace", "Ray-trace the scenario with Sionna RT (optional extra) for an independent check"),
}

EPILOG = """\
examples:
  diffpos bounds                      PEB / z bound of the paper's geometry, heat maps per floor
  diffpos power-ratio --out out/      the paper's power-ratio figure and its data
  diffpos SUBCOMMAND --help           what a subcommand does and its options

Coordinates: the facade with the windows is the plane y = 0, the inside is y > 0, anchors
(UAVs) fly outside at y < 0, x runs along the window edges, z is up (0 at ground). SI units.
"""


def _top_parser() -> argparse.ArgumentParser:
    width = max(len(name) for name in COMMANDS) + 2
    listing = "\n".join(f"  {name:<{width}}{text}" for name, (_, text) in COMMANDS.items())
    return argparse.ArgumentParser(
        prog="diffpos",
        description=(
            "Diffraction-aided positioning: find people inside buildings from UAV anchors "
            "outside, by modelling the first-arriving path as diffraction over the window edge "
            "on the person's own floor.\n\nsubcommands:\n" + listing
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


def _load(name: str):
    module_name, _ = COMMANDS[name]
    return importlib.import_module(f"diffpos_services.cli.{module_name}")


def build_parser(name: str) -> argparse.ArgumentParser:
    """The argument parser of one subcommand (imports its module)."""
    module = _load(name)
    doc = (module.__doc__ or "").strip()
    parser = argparse.ArgumentParser(
        prog=f"diffpos {name}",
        description=doc,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    module.add_arguments(parser)
    parser.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = _top_parser()
    if not argv or argv[0] in ("-h", "--help"):
        top.print_help()
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        top.print_usage(sys.stderr)
        close = [c for c in COMMANDS if c.startswith(name[:2])]
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        print(f"diffpos: unknown subcommand {name!r}{hint}; see 'diffpos --help'", file=sys.stderr)
        return 2
    parser = build_parser(name)
    args = parser.parse_args(rest)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
