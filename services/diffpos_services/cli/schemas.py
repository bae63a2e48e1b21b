"""Write the JSON Schemas of the bus messages into a folder (the checked-in schemas/)

One file per message type, versioned in its name (e.g. estimate.v1.json),
generated from the msgspec structs of diffpos_services.wire.messages; prints the written
paths. A golden test fails when schemas/ differs from what this writes.

example:
  diffpos schemas --write schemas/
"""

from __future__ import annotations

import argparse

from diffpos_services.wire.messages import write_schemas


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--write", metavar="DIR", required=True,
                        help="folder to write the schema files into (created if missing)")


def run(args: argparse.Namespace) -> int:
    for path in write_schemas(args.write):
        print(path)
    return 0
