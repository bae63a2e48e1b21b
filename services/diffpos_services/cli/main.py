"""The ``diffpos`` command line.

Each subcommand lives in its own module ``diffpos_services.cli.<name>`` with a module
docstring (first line = one-line help), ``add_arguments(parser)`` and ``run(args) -> int``.
``diffpos --help`` imports no verb (:data:`COMMANDS` holds each verb's module and one-line
help; ``tests/services/test_cli_lazy.py`` checks them against the docstrings), and
``diffpos VERB --help`` imports that verb's module only: its ``add_arguments`` needs argparse
and constants, and the verb imports its service inside ``run`` (so no help ever imports, or
compiles, a numba kernel).

Errors are mapped to exit codes here and nowhere else: a :class:`~diffpos_services.errors.DiffposError`
prints one line ``diffpos <verb>: error: <message>`` and returns its ``exit_code``;
Ctrl-C returns 130.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import logging
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

from diffpos_services.errors import DiffposError

#: subcommand -> (module of ``diffpos_services.cli``, one-line help = the first line of the
#: module's docstring). The order is the order shown by ``--help``; a static table, so that
#: ``diffpos --help`` reads no verb module.
COMMANDS: dict[str, tuple[str, str]] = {
    "emulate": ("emulate", "Run the whole system on this machine: router, anchors, fusion, "
                           "recorder, dashboard"),
    "solve": ("solve", "Position fixes from JSON Lines problems on stdin (D-NLS, LLS, IPPA, M-NLS)"),
    "reproduce": ("reproduce", "Regenerate the paper's study: MPC table, first-arrival stats, "
                               "error CDFs"),
    "bounds": ("bounds", "PEB and z-axis bound over a grid of indoor nodes, heat maps per floor"),
    "power-ratio": ("power_ratio", "Upper/lower edge diffraction power ratio (Theorem 3): PNG + CSV"),
    "router": ("router", "Zenoh router in this Python process (no zenohd binary needed)"),
    "anchor": ("anchor", "One UAV anchor: flies its trajectory, ranges to nodes, publishes over "
                         "Zenoh"),
    "fusion": ("fusion", "Fusion service: aligns ranges in time, D-NLS with gating or mnls + "
                         "tracking, publishes estimates"),
    "recorder": ("recorder", "Record every message on the bus to MCAP (with liveliness events "
                             "and config)"),
    "replay": ("replay", "Re-run fusion offline from an MCAP recording; error report, CDF plot, "
                         "what-ifs"),
    "inspect": ("inspect", "Channels, schemas, counts, time span, anchors and nodes of an MCAP "
                           "recording"),
    "recover": ("recover", "Rewrite a truncated MCAP recording (e.g. after SIGKILL) into a valid one"),
    "dashboard": ("dashboard", "Live Rerun dashboard of a running system (viewer, web viewer or "
                               ".rrd)"),
    "to-rerun": ("to_rerun", "Convert an MCAP recording into a Rerun .rrd dashboard"),
    "raytrace": ("raytrace", "Ray-trace the scenario with Sionna RT (optional extra) for an "
                             "independent check"),
    "health": ("health", "Exit 0 if a liveliness token is alive on the bus (container health "
                         "checks)"),
    "security": ("security", "Bus security: DEV certificates, zenoh json5 files from a profile, "
                             "profile check"),
    "schemas": ("schemas", "Write the JSON Schemas of the bus messages into a folder (the "
                           "checked-in schemas/)"),
}

EPILOG = """\
examples:
  diffpos bounds                      PEB / z bound of the paper's geometry, heat maps per floor
  diffpos power-ratio --out out/      the paper's power-ratio figure and its data
  diffpos SUBCOMMAND --help           what a subcommand does and its options

Coordinates: the facade with the windows is the plane y = 0, the inside is y > 0, anchors
(UAVs) fly outside at y < 0, x runs along the window edges, z is up (0 at ground). SI units.
"""


def version() -> str:
    """The installed version of the ``diffpos`` distribution."""
    try:
        return importlib.metadata.version("diffpos")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - not installed
        return "unknown"


def _top_parser() -> argparse.ArgumentParser:
    width = max(len(name) for name in COMMANDS) + 2
    listing = "\n".join(f"  {name:<{width}}{help_}" for name, (_, help_) in COMMANDS.items())
    parser = argparse.ArgumentParser(
        prog="diffpos",
        description=(
            "Diffraction-aided positioning: find people inside buildings from UAV anchors "
            "outside, by modelling the first-arriving path as diffraction over the window edge "
            "on the person's own floor.\n\nsubcommands:\n" + listing
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    return parser


def _load(name: str):
    return importlib.import_module(f"diffpos_services.cli.{COMMANDS[name][0]}")


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


@contextmanager
def _root_logging_restored() -> Iterator[None]:
    """Give the root logger back its handlers and level when a verb returns: a service verb
    configures logging for its process (``logs.setup_logging``), and a caller running
    :func:`main` in-process (tests, scripts) must not inherit that level or a handler bound to
    a stream that is gone."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        yield
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``diffpos VERB [options]``; return the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "--version":
        print(f"diffpos {version()}")
        return 0
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
    try:
        with _stop_signals_interrupt(), _root_logging_restored():
            parser = build_parser(name)
            args = parser.parse_args(rest)
            return int(args._run(args) or 0)
    except DiffposError as exc:
        print(f"diffpos {name}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


@contextmanager
def _stop_signals_interrupt() -> Iterator[None]:
    """SIGTERM and SIGHUP act like Ctrl-C from the first moment of a verb: while its modules
    import (seconds) and until the verb installs its own handlers (``shutdown.Shutdown``), a
    stop by any of these signals exits 130, never 143 / 129 (docs/faults.md, signals). Only
    a handler still at the default is replaced, and the previous ones come back afterwards
    (``main`` runs in-process in tests)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(sig) == signal.SIG_DFL:
            previous[sig] = signal.signal(sig, _interrupt)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":
    sys.exit(main())
