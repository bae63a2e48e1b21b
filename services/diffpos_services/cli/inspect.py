"""Channels, schemas, counts, time span, anchors and nodes of an MCAP recording

Like `mcap info`, in diffpos terms: which anchors and nodes the recording holds, how many
messages of each kind, the time span, gaps in the publishers' sequence numbers (in this file,
and across every file of the recording when it has split parts or restart files: a hole
between two files is counted there), the liveliness
events (anchors joining and leaving), the services' heartbeats (per process: how far its
progress went, its longest silence and stall, and when), the run metadata and attachments. Works on truncated
recordings too (it says so and suggests `diffpos recover`). With --validate every message is
checked against diffpos' own JSON Schema (schemas/) named by its "schema" tag, not against
the schema embedded in the file, and channels whose embedded schema differs from ours are
listed (needs the jsonschema package).

examples:
  diffpos inspect recordings/sample.mcap
  diffpos inspect recordings/sample.mcap --channels       # one line per channel
  diffpos inspect recordings/sample.mcap --validate       # schema-check every message
  diffpos inspect recordings/sample.mcap --json > info.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter

from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.summary import set_losses, summarize, validate_file
from diffpos_services.recording.writer import recording_set


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.mcap", help="recording to inspect")
    parser.add_argument("--channels", action="store_true", help="list every channel")
    parser.add_argument("--validate", action="store_true",
                        help="validate every message against diffpos' own JSON Schemas (schemas/)")
    parser.add_argument("--json", action="store_true", help="print everything as JSON")


def _utc(ns: int) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ns / 1e9)) + f".{(ns // 1_000_000) % 1000:03d}Z"


def _print_validation(validation: dict) -> None:
    print(f"validation: {validation['checked']} checked, {validation['invalid']} invalid, "
          f"{validation['no_schema']} without schema, {validation['not_json']} not JSON")
    print("            against diffpos' own schemas (schemas/), by each message's schema tag")
    for ex in validation["examples"]:
        print(f"  {ex}")
    for mm in validation["schema_mismatch"]:
        print(f"  embedded schema differs from ours: {mm['embedded']} vs {mm['ours']} on "
              f"{mm['channels']} channels (e.g. {mm['example']})")


def _print_across(across) -> None:
    if across is not None:
        detail = ", ".join(f"{k}: {n}" for k, n in across.by_stream.items())
        print(f"           across the recording's {len(across.files)} files (split parts, "
              f"restarts): {across.missing} missing" + (f" ({detail[:300]})" if detail else ""))


def _print_heartbeats(beats: list[dict], t0: int) -> None:
    """Per process start: its heartbeats, progress, longest silence and stall (and when)."""
    if not beats:
        return
    print("heartbeats: per process start (silence: no heartbeat; stall: no progress with work "
          "pending)")

    def at(ns: int) -> str:
        return f"{(ns - t0) / 1e9:+.1f} s"

    for b in beats[:40]:
        stall = (f"stall {b['longest_stall_s']:.1f} s from {at(b['stall_from_ns'])}"
                 if b["longest_stall_s"] > 0 else "no stall")
        back = f", {b['regressions']} times backwards" if b["regressions"] else ""
        print(f"  {b['who']:<12} pid {b['pid']:<7} {b['beats']:>5} beats "
              f"{at(b['first_ns'])} .. {at(b['last_ns'])}, progress {b['first_progress']} -> "
              f"{b['last_progress']}{back}; longest silence {b['longest_silence_s']:.1f} s from "
              f"{at(b['silence_from_ns'] or b['first_ns'])}; {stall}")
    if len(beats) > 40:
        print(f"  ... {len(beats) - 40} more")


def run(args: argparse.Namespace) -> int:
    try:
        s = summarize(args.file)
    except RecordingError as exc:
        print(f"diffpos inspect: {exc}", file=sys.stderr)
        return exc.exit_code  # 1 for a file that is not ours, 2 for a broken one
    except OSError as exc:
        print(f"diffpos inspect: {args.file}: {exc.strerror}", file=sys.stderr)
        return 2
    across = set_losses(args.file) if len(recording_set(args.file)) > 1 else None
    validation = None
    if args.validate:
        try:
            validation = validate_file(args.file)
        except ImportError:
            print("diffpos inspect: --validate needs the jsonschema package", file=sys.stderr)
            return 2
    if args.json:
        d = s.as_dict()
        if validation is not None:
            d["validation"] = validation
        if across is not None:
            d["set_losses"] = across.__dict__
        print(json.dumps(d, indent=2, default=str))
        return 0 if s.damage.ok and not (validation and validation["invalid"]) else 1

    print(f"file:      {s.path} ({s.size_bytes / 1e6:.2f} MB)")
    if s.complete:
        print("status:    complete (footer and index present)")
    else:
        print(f"status:    TRUNCATED - {'; '.join(s.damage.notes[:2])}")
        print(f"           run: diffpos recover {s.path}")
    if s.damage.bad_chunks or s.damage.bad_records or s.damage.messages_without_channel:
        print(f"damage:    {s.damage.bad_chunks} corrupt chunks, {s.damage.bad_records} bad "
              f"records, {s.damage.messages_without_channel} messages without channel (skipped)")
    if s.messages:
        print(f"span:      {_utc(s.start_ns)} .. {_utc(s.end_ns)} ({s.duration_s:.3f} s)")
    print(f"messages:  {s.messages} on {len(s.channels)} channels")
    kinds: Counter[str] = Counter()
    kind_ch: Counter[str] = Counter()
    gaps = sum(s.gaps.values())
    for c in s.channels:
        kinds[c.kind] += c.count
        kind_ch[c.kind] += 1
    for kind, n in sorted(kinds.items(), key=lambda kv: -kv[1]):
        rate = f", {n / s.duration_s:.1f}/s" if s.duration_s > 0 else ""
        print(f"  {kind:<16} {n:>9} messages on {kind_ch[kind]:>4} channels{rate}")
    detail = ", ".join(f"{k}: {n}" for k, n in s.gaps.items())
    print(f"gaps:      {gaps} messages missing by sequence number"
          + (f" ({detail[:300]})" if gaps else ""))
    _print_across(across)
    if s.out_of_order:
        print(f"repeats:   {sum(s.out_of_order.values())} sequence numbers went backwards "
              "(publisher restarted?)")
    print(f"schemas:   {', '.join(f'{n} ({e})' for n, e in sorted(s.schemas.items())) or '-'}")
    print(f"anchors:   {len(s.anchors)}: {' '.join(s.anchors)}")
    nodes = " ".join(s.nodes[:40]) + (" ..." if len(s.nodes) > 40 else "")
    print(f"nodes:     {len(s.nodes)}: {nodes}")
    if s.liveliness:
        print("liveliness:")
        t0 = s.start_ns or s.liveliness[0].get("t_ns", 0)
        for ev in s.liveliness[:30]:
            what = "joined" if ev.get("alive") else "left"
            dt = (ev.get("t_ns", t0) - t0) / 1e9
            print(f"  {dt:+9.3f} s  {ev.get('role', '?'):<9} {ev.get('id', '') or '-':<10} {what}")
        if len(s.liveliness) > 30:
            print(f"  ... {len(s.liveliness) - 30} more")
    _print_heartbeats(s.heartbeats, s.start_ns)
    for name, md in s.metadata.items():
        keys = ", ".join(f"{k}={v if len(v) < 40 else v[:37] + '...'}" for k, v in list(md.items())[:8])
        print(f"metadata:  {name}: {keys}")
    for name, media, size in s.attachments:
        print(f"attachment: {name} ({media}, {size} bytes)")
    if args.channels:
        print("channels:")
        for c in s.channels:
            print(f"  {c.topic:<48} {c.schema:<32} {c.count:>8}")
    if validation is not None:
        _print_validation(validation)
    bad = (not s.damage.ok) or (validation is not None and validation["invalid"] > 0)
    return 1 if bad else 0
