"""The ``diffpos`` command line.

Each subcommand lives in its own module ``diffpos_services.cli.<name>`` with a module
docstring (first line = one-line help), ``add_arguments(parser)`` and ``run(args) -> int``.
Modules are imported only when their subcommand runs, so ``diffpos --help`` stays fast and a
numeric command never pays for importing Zenoh or Rerun.

Errors are mapped to exit codes here and nowhere else: a :class:`~diffpos_services.errors.DiffposError`
prints one line ``diffpos <verb>: error: <message>`` and returns its ``exit_code``;
Ctrl-C returns 130.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import importlib.metadata
import importlib.util
import logging
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from diffpos_services.errors import DiffposError

#: subcommand -> module of ``diffpos_services.cli``. The order is the order shown by ``--help``;
#: the one-line help is the first line of the module's docstring (read without importing it).
COMMANDS: dict[str, str] = {
    "emulate": "emulate",
    "solve": "solve",
    "reproduce": "reproduce",
    "bounds": "bounds",
    "power-ratio": "power_ratio",
    "router": "router",
    "anchor": "anchor",
    "fusion": "fusion",
    "recorder": "recorder",
    "replay": "replay",
    "inspect": "inspect",
    "recover": "recover",
    "dashboard": "dashboard",
    "to-rerun": "to_rerun",
    "raytrace": "raytrace",
    "health": "health",
    "security": "security",
    "schemas": "schemas",
}

EPILOG = """\
examples:
  diffpos bounds                      PEB / z bound of the paper's geometry, heat maps per floor
  diffpos power-ratio --out out/      the paper's power-ratio figure and its data
  diffpos SUBCOMMAND --help           what a subcommand does and its options

Coordinates: the facade with the windows is the plane y = 0, the inside is y > 0, anchors
(UAVs) fly outside at y < 0, x runs along the window edges, z is up (0 at ground). SI units.
"""


def summary(name: str) -> str:
    """The one-line help of subcommand ``name``: its module docstring's first line."""
    spec = importlib.util.find_spec(f"diffpos_services.cli.{COMMANDS[name]}")
    tree = ast.parse(Path(spec.origin).read_text(encoding="utf-8"))
    return (ast.get_docstring(tree) or "").strip().splitlines()[0]


def version() -> str:
    """The installed version of the ``diffpos`` distribution."""
    try:
        return importlib.metadata.version("diffpos")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - not installed
        return "unknown"


def _top_parser() -> argparse.ArgumentParser:
    width = max(len(name) for name in COMMANDS) + 2
    listing = "\n".join(f"  {name:<{width}}{summary(name)}" for name in COMMANDS)
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
    return importlib.import_module(f"diffpos_services.cli.{COMMANDS[name]}")


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
    parser = build_parser(name)
    args = parser.parse_args(rest)
    try:
        with _root_logging_restored():
            return int(args._run(args) or 0)
    except DiffposError as exc:
        print(f"diffpos {name}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
