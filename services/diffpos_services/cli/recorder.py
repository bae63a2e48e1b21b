"""Record every message on the bus to MCAP (with liveliness events and config)

Subscribes to everything under diffpos/<site>/ and writes each message to an MCAP file:
one channel per key expression, the message's JSON Schema from schemas/ (schema encoding
jsonschema, message encoding json: Foxglove opens it), log_time = when the recorder received
it, publish_time = the message's own measurement time t_ns, the publisher's sequence number
kept, zstd-compressed chunks. Anchors joining and leaving (liveliness tokens) go to the
channel diffpos/<site>/recorder/liveliness; the run settings are MCAP metadata ("run") and the
scenario file an attachment, so a recording explains itself (see `diffpos inspect`).

Nothing received is lost: Zenoh hands samples to a bounded queue drained by a thread of the
recorder (when it is full, publishers using congestion control BLOCK wait). Every
--flush-interval seconds the current chunk is written out, so if the recorder is killed
(SIGKILL, power cut) at most that last interval is missing; `diffpos recover FILE` turns the
footer-less file into a valid one. SIGINT/SIGTERM end recording cleanly (footer + index +
final counters as metadata "recorder_stats"). Received vs written counts and gaps in sequence
numbers are logged at the end.

Long recordings are split (like rosbag2) so the recorder's memory stays bounded: the MCAP
writer keeps an index entry per chunk and channel until the file is finished (+~10 MB per
minute at 8 anchors x 50 nodes x 10 Hz), so a new file is started every --split-duration
seconds or --split-size MB. Part 0 is --out itself, part k is <stem>_000k.mcap next to it;
every part is a complete, indexed MCAP with the run metadata and the scenario attachment
(replay, inspect and to-rerun accept any part). See docs/soak.md for the measurement.
An existing --out (or part) is never overwritten.

examples:
  diffpos router &                                        # the bus, tcp/127.0.0.1:7447
  diffpos recorder --site demo                            # -> recordings/demo-<UTC>.mcap
  diffpos recorder --site demo --out run1.mcap --scenario scenarios/paper.toml
  diffpos recorder --site demo --duration 60 --status     # stop after 60 s; JSON status lines
  diffpos recorder --site demo --split-duration 60        # a new file every minute
  diffpos inspect run1.mcap                               # what is in it
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from diffpos_services.bus.session import add_zenoh_arguments, service_settings
from diffpos_services.config import load_json_option
from diffpos_services.errors import ConfigError
from diffpos_services.logs import add_logging_arguments, log_event, setup_logging
from diffpos_services.recorder import (
    RecorderOptions,
    default_output_path,
    record,
    run_metadata,
    status_printer,
)
from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.writer import McapSink, SplitPolicy, part_path
from diffpos_services.shutdown import Shutdown, run_main

#: default part length [s] and size [MB]: ~50 MB of writer index at the issue's load
DEFAULT_SPLIT_S = 300.0
DEFAULT_SPLIT_MB = 1024.0


def split_policy(args: argparse.Namespace) -> SplitPolicy:
    """--split-duration / --split-size as a :class:`SplitPolicy` (0 = that limit off)."""
    for opt, v in (("--split-duration", args.split_duration), ("--split-size", args.split_size)):
        if not v >= 0:
            raise ConfigError(f"{opt} {v}: must be >= 0 (0 = no limit)")
    return SplitPolicy(
        max_bytes=round(args.split_size * 1e6) if args.split_size > 0 else None,
        max_duration_s=args.split_duration if args.split_duration > 0 else None,
    )


def _refuse_existing(out: Path) -> None:
    """A recording is never written over an existing file (or an existing later part)."""
    for path in (out, part_path(out, 1)):
        if path.exists():
            raise ConfigError(f"--out {out}: {path} already exists; recordings are never "
                              "overwritten: give a new name (or move the old file)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--site", default="demo", help="site to record, diffpos/<site>/** (default demo)")
    parser.add_argument("--out", metavar="FILE.mcap",
                        help="output file (default recordings/<scenario or site>-<UTC time>.mcap)")
    parser.add_argument("--dir", default="recordings", metavar="DIR",
                        help="directory for the default file name (default recordings)")
    parser.add_argument("--scenario", metavar="FILE",
                        help="scenario file to attach (its stem names the default output)")
    parser.add_argument("--run-config", metavar="FILE.json",
                        help="run configuration (JSON) to attach and to copy into the 'run' metadata")
    parser.add_argument("--name", help="scenario/run name for the default file name and metadata")
    parser.add_argument("--flush-interval", type=float, default=0.2, metavar="S",
                        help="write the current chunk every S seconds: the most a SIGKILL can lose (default 0.2)")
    parser.add_argument("--compression", default="zstd", choices=["zstd", "lz4", "none"],
                        help="chunk compression (default zstd)")
    parser.add_argument("--queue", type=int, default=65536, metavar="N",
                        help="samples buffered between Zenoh and the writer (default 65536)")
    parser.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    parser.add_argument("--split-duration", type=float, default=DEFAULT_SPLIT_S, metavar="S",
                        help="start a new file (part) after S seconds of recording, bounding "
                             f"memory (default {DEFAULT_SPLIT_S:g}; 0 = never)")
    parser.add_argument("--split-size", type=float, default=DEFAULT_SPLIT_MB, metavar="MB",
                        help=f"start a new file once the current one holds MB megabytes "
                             f"(default {DEFAULT_SPLIT_MB:g}; 0 = never)")
    parser.add_argument("--status", action="store_true",
                        help="print JSON status lines to stdout (ready, flush, closed)")
    add_zenoh_arguments(parser)
    add_logging_arguments(parser)


def run(args: argparse.Namespace) -> int:
    logger = setup_logging("recorder", level=args.log_level, fmt=args.log_format)
    return run_main(lambda: _run(args, logger), logger)


def _run(args: argparse.Namespace, logger: logging.Logger) -> int:
    try:
        settings = service_settings(args, logger)
        options = RecorderOptions(site=args.site, flush_interval_s=args.flush_interval,
                                  queue_size=args.queue, duration_s=args.duration)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    scenario_bytes = run_config = None
    if args.scenario:
        try:
            scenario_bytes = Path(args.scenario).read_bytes()
        except OSError as exc:
            raise ConfigError(f"--scenario {args.scenario}: cannot read it ({exc.strerror})") from None
    if args.run_config:
        run_config = load_json_option("--run-config", args.run_config)
    name = args.name or (Path(args.scenario).stem if args.scenario else args.site)
    out = Path(args.out) if args.out else default_output_path(name, directory=args.dir)
    split = split_policy(args)
    _refuse_existing(out)
    shutdown = Shutdown(logger)
    try:
        sink = McapSink(out, compression=args.compression, split=split)
    except (OSError, RecordingError) as exc:
        raise ConfigError(f"--out {out}: cannot create it ({exc})") from None
    meta = run_metadata(settings, options, scenario=name)
    sink.add_metadata("run", meta)
    if scenario_bytes is not None:
        media = "application/toml" if args.scenario.endswith(".toml") else "text/plain"
        sink.add_attachment(Path(args.scenario).name, scenario_bytes, media_type=media)
    if run_config is not None:
        sink.add_metadata("run_config", dict(run_config)
                          if isinstance(run_config, dict) else {"value": run_config})
        sink.add_attachment("run_config.json", json.dumps(run_config, indent=2).encode(),
                            media_type="application/json")
    emit = status_printer() if args.status else None

    def on_status(event: str, fields: dict) -> None:
        if event in ("ready", "stopped"):
            log_event(logger, logging.INFO, f"recorder {event}", **fields)
        if emit is not None:
            emit(event, fields)

    log_event(logger, logging.INFO, "recording", path=str(out), site=args.site)
    try:
        stats = record(settings, sink, options, stop=shutdown.event, on_status=on_status)
    finally:
        final = sink.close(final_metadata={"stopped_by": shutdown.signal_name or "duration"})
    summary = final.as_dict()
    lost = final.received - final.written
    log_event(logger, logging.WARNING if (lost or final.gaps) else logging.INFO,
              "recording closed", path=str(out), **{k: summary[k] for k in
              ("received", "written", "gaps", "out_of_order", "unknown_schema", "channels")})
    if final.gaps:
        for key, first, last in final.gap_list[:20]:
            log_event(logger, logging.WARNING, "sequence gap", key=key, first_missing=first,
                      last_missing=last)
    if len(sink.parts) > 1:
        log_event(logger, logging.INFO, "recording split", parts=len(sink.parts),
                  last=str(sink.parts[-1]))
    if emit is not None:
        emit("closed", {"path": str(out), "parts": [str(p) for p in sink.parts], **summary})
    return 0 if stats.written == stats.received else 1
