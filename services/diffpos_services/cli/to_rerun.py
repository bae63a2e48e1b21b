"""Convert an MCAP recording into a Rerun .rrd dashboard

Reads a diffpos recording (from `diffpos recorder` or `diffpos emulate`; truncated files
work too) and writes the same dashboard as the live `diffpos dashboard`, in bulk
(send_columns), with the default blueprint embedded: open the result with `rerun OUT.rrd`
(or drag it into the web viewer at https://rerun.io/viewer, version 0.41).

Shown: the building (from --scenario, else the scenario file attached to the recording, else
the building of the run configuration `diffpos emulate` attaches),
anchors with trails, true and estimated node positions with 95% ellipsoids and diffraction
paths (excluded anchors in red), 3D/z error and PEB per node, residuals per anchor, gating
counts, the floor table and the event log (liveliness, exclusions, unidentifiable fixes).
Rows use measurement time (timeline "meas_time"), so they line up with a live recording.
Range messages are not decoded (they are not drawn), which keeps the conversion fast.

examples:
  diffpos to-rerun recordings/demo.mcap                      -> recordings/demo.rrd
  diffpos to-rerun run.mcap -o out/run.rrd --scenario scenarios/paper.toml
  diffpos to-rerun run.mcap --replayed                       estimates written by diffpos replay
  diffpos to-rerun run.mcap --start 10 --end 40              only that slice of measurement time
  rerun out/run.rrd                                          look at it
  rerun rrd verify out/run.rrd                               check the file
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from diffpos_services.errors import ConfigError
from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.outputs import atomic_path, check_output


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mcap", metavar="FILE.mcap", help="diffpos MCAP recording")
    parser.add_argument(
        "-o", "--out", metavar="OUT.rrd", help="output (default: FILE.rrd next to the input)"
    )
    parser.add_argument(
        "--scenario",
        metavar="FILE",
        help="scenario TOML, shipped name or 'default' for the building (default: the one attached)",
    )
    parser.add_argument(
        "--replayed",
        action="store_true",
        help="draw the replayed estimates (replay/node/<id>/estimate) instead of the live ones",
    )
    parser.add_argument("--recording-id", help="Rerun recording id (default: the MCAP file stem)")
    parser.add_argument(
        "--path-period",
        type=float,
        default=0.5,
        metavar="S",
        help="draw each node's diffraction paths at most every S seconds (default 0.5)",
    )
    parser.add_argument(
        "--start",
        type=float,
        default=None,
        metavar="S",
        help="keep messages from S seconds after the first anchor state (measurement time)",
    )
    parser.add_argument(
        "--end",
        type=float,
        default=None,
        metavar="S",
        help="keep messages up to S seconds after the first anchor state",
    )
    parser.add_argument("--json", action="store_true", help="print the counts as JSON")


def run(args: argparse.Namespace) -> int:
    src = Path(args.mcap)
    if not src.is_file():
        print(
            f"error: {src}: no such file (give an MCAP recording, e.g. recordings/*.mcap)",
            file=sys.stderr,
        )
        return 2
    out = Path(args.out) if args.out else src.with_suffix(".rrd")
    if out.suffix != ".rrd":
        print(f"error: --out {out}: the output must end in .rrd", file=sys.stderr)
        return 2
    if args.start is not None and args.end is not None and args.end <= args.start:
        print(f"error: --end {args.end} must be after --start {args.start}", file=sys.stderr)
        return 2
    if args.path_period <= 0:
        print("error: --path-period must be > 0", file=sys.stderr)
        return 2
    check_output(out, option="--out", inputs=[src])  # ConfigError, exit 2, before any work
    # deferred: the converter imports rerun and the MCAP reader (~1 s), which `--help` and the
    # argument checks above must not pay for
    from diffpos_services.dashboard.convert import mcap_to_rrd
    from diffpos_services.dashboard.scenario import building_for_option

    try:
        building = building_for_option(args.scenario)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        with atomic_path(out) as tmp:  # renamed to OUT.rrd only once complete
            counts = mcap_to_rrd(
                src,
                tmp,
                building=building,
                use_replayed=args.replayed,
                recording_id=args.recording_id or src.stem,
                path_period_s=args.path_period,
                window_s=(args.start, args.end),
            )
    except RecordingError as exc:
        print(f"error: {src}: {exc}", file=sys.stderr)
        return exc.exit_code
    counts["seconds"] = round(time.perf_counter() - t0, 3)
    counts["out"] = str(out)
    if args.json:
        print(json.dumps(counts))
        return 0
    print(
        f"wrote {out}: {counts['estimate']} estimates, {counts['anchor_state']} anchor states, "
        f"{counts['truth']} truth, {counts['diagnostics']} diagnostics, "
        f"{counts['liveliness']} liveliness events in {counts['seconds']} s"
    )
    if not counts["building"]:
        print(
            "note: no building in the recording (neither a scenario TOML nor a run configuration "
            "attached): give --scenario FILE.toml, a shipped name or 'default' (emulate's "
            "built-in); without it paths are straight lines and there is no wireframe"
        )
    if not counts["estimate"]:
        print(
            "note: no estimates in the recording" + ("" if args.replayed else " (try --replayed)")
        )
    if counts["damage"]:
        print("note: recording damaged, drew what was readable: " + "; ".join(counts["damage"][:3]))
    print(f"open it with: rerun {out}")
    return 0
