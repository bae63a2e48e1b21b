"""The ray-traced channel's options, shared by ``diffpos anchor`` and ``diffpos emulate``.

Not a verb: argparse only (a verb's ``--help`` must not import the tracer).
"""

from __future__ import annotations

import argparse


def add_raytrace_arguments(parser: argparse.ArgumentParser) -> None:
    """``--raytrace-samples``, ``--raytrace-depth``, ``--raytrace-step-s`` (also of ``diffpos
    emulate``; defaults in :mod:`diffpos_services.raytrace.live`, stated in the help and
    checked by tests/services/test_raytrace_live.py)."""
    parser.add_argument(
        "--raytrace-samples", type=float, default=None, metavar="N",
        help="--channel raytrace: rays shot per source (anchor) per traced time (default "
        "3e5; one trace of 6 nodes at depth 4 takes about 1.5 s here, linear in N)")
    parser.add_argument(
        "--raytrace-depth", type=int, default=None, metavar="D",
        help="--channel raytrace: maximum interactions per path (default 4; each partition "
        "crossing counts, so depth 3 hides third-order paths behind a partition)")
    parser.add_argument(
        "--raytrace-step-s", type=float, default=None, metavar="S",
        help="--channel raytrace: traced every S seconds of the run [s] (default 0.5); "
        "epochs in between interpolate each path whose interaction chain is unchanged")
