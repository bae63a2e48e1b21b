"""Rewrite a truncated MCAP recording (e.g. after SIGKILL) into a valid one

A recording whose writer died (SIGKILL, power cut, full disk) has no footer and no index,
and the mcap reader refuses it. This command scans the file record by record and copies
every complete chunk (the recorder flushes one every 0.2 s by default), loose message,
metadata and attachment into a new, indexed MCAP file; an incomplete last record is dropped,
chunks that fail their CRC are skipped and counted, and after a corrupt record length the
copy resyncs at the next readable chunk (only the bytes in between are lost). A "recovery" metadata record notes
what happened. The input is never modified.

examples:
  diffpos recover recordings/demo-20260101T120000Z.mcap      # -> ...Z.recovered.mcap
  diffpos recover broken.mcap --out fixed.mcap
  diffpos recover broken.mcap --json                          # machine-readable report
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.outputs import check_output
from diffpos_services.recording.repair import recover


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.mcap", help="recording to recover")
    parser.add_argument("--out", metavar="OUT.mcap",
                        help="output file (default FILE.recovered.mcap next to the input)")
    parser.add_argument("--compression", default="zstd", choices=["zstd", "lz4", "none"],
                        help="chunk compression of the recovered file (default zstd)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def run(args: argparse.Namespace) -> int:
    src = Path(args.file)
    out = Path(args.out) if args.out else src.with_name(src.stem + ".recovered.mcap")
    check_output(out, option="--out", inputs=[src])  # ConfigError, exit 2, before any work
    try:
        rep = recover(src, out, compression=args.compression)
    except RecordingError as exc:
        print(f"diffpos recover: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"diffpos recover: {exc.filename or out}: {exc.strerror}", file=sys.stderr)
        return 2
    d = rep.damage
    report = {
        "input": str(src), "output": str(out), "messages": rep.messages,
        "channels": rep.channels, "metadata": rep.metadata, "attachments": rep.attachments,
        "input_was_complete": rep.was_complete, "truncated": d.truncated,
        "bad_chunks": d.bad_chunks, "bad_records": d.bad_records,
        "unread_bytes": d.unread_bytes, "skipped_bytes": d.skipped_bytes, "notes": d.notes,
    }
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        state = ("was already complete" if rep.was_complete and d.ok else
                 "was complete but damaged" if rep.was_complete else "was truncated")
        print(f"{src} {state}: wrote {out}")
        print(f"  {rep.messages} messages on {rep.channels} channels, "
              f"{rep.metadata} metadata, {rep.attachments} attachments")
        if d.unread_bytes:
            print(f"  dropped the incomplete last {d.unread_bytes} bytes")
        if d.bad_chunks or d.bad_records:
            print(f"  skipped {d.bad_chunks} corrupt chunks, {d.bad_records} bad records")
        if d.skipped_bytes:
            print(f"  resynced past {d.skipped_bytes} corrupt bytes")
        for note in d.notes[:10]:
            print(f"  note: {note}")
    return 0
