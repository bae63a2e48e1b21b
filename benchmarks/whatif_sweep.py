"""Replay kept ``bench_accuracy --keep`` recordings with a :mod:`whatif_skip_term` mode and
score them: the table of docs/heldout_geo14.md's skip14 note.

Usage::

    python benchmarks/whatif_sweep.py OUT_DIR MODE DIR...   # e.g. off, soft, 0.15

Every ``rand-S-i.mcap`` of every ``DIR`` is replayed in its own process
(``whatif_skip_term.py MODE REC --json --write-mcap OUT_DIR/MODE_NAME.mcap``); the replay
report's ``node_epochs`` block (:func:`diffpos.metrics.score`, every node-epoch after 2 s:
the scorer of ``bench_accuracy.py``) gives availability, floor %, 3D p90 and cov95 per run,
and :class:`heldout_diag.Run` on the written replay the pooled level / stairs split. The
reports are kept as ``OUT_DIR/MODE_NAME.json`` and reused by name when the sweep is run
again (to resume): after a change to the code, use a fresh ``OUT_DIR``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import heldout_diag as hd
from diffpos_services.recording.topics import parse_topic

HERE = Path(__file__).resolve().parent
THRESHOLDS = "avail >= 90, floor >= 80, cov95 85-99, 3D p90 <= 1.5 m"


def _replayed_topic(topic: str):
    """:func:`parse_topic` with the replayed estimates read as the estimates."""
    k = parse_topic(topic)
    if k[0] == "estimate":
        return ("live_estimate", *k[1:])
    if k[0] == "replay_estimate":
        return ("estimate", *k[1:])
    return k


def replay(out: Path, mode: str, rec: Path) -> tuple[dict, Path]:
    """One replay: its report's ``node_epochs`` and the written recording."""
    js, mc = out / f"{mode}_{rec.stem}.json", out / f"{mode}_{rec.stem}.mcap"
    if not js.exists():
        r = subprocess.run([sys.executable, str(HERE / "whatif_skip_term.py"), mode, str(rec),
                            "--json", "--write-mcap", str(mc)], capture_output=True, text=True,
                           check=True)
        js.write_text(r.stdout[r.stdout.index("{"):])
    return json.loads(js.read_text())["node_epochs"], mc


def main(argv: list[str]) -> int:
    if len(argv) < 3:
        print(__doc__)
        return 2
    out, mode = Path(argv[0]), argv[1]
    out.mkdir(parents=True, exist_ok=True)
    recs = sorted((p for d in argv[2:] for p in Path(d).glob("rand-*.mcap")),
                  key=lambda p: tuple(int(v) for v in p.stem.split("-")[1:]))
    hd.parse_topic = _replayed_topic
    pooled = {"level": [0, 0, 0, 0], "stairs": [0, 0, 0, 0]}  # n, right floor, fixes, inside
    passed = 0
    print(f"| run | {mode}: avail % / floor % / 3D p90 m / cov95 % |\n|---|---|")
    for rec in recs:
        ne, mc = replay(out, mode, rec)
        ok = (ne["availability"] >= 0.9 and ne["floor_accuracy_all"] >= 0.8
              and 0.85 <= ne["ellipsoid_coverage"] <= 0.99 and ne["error_3d_m"]["p90"] <= 1.5)
        passed += ok
        print(f"| {rec.stem} | {100 * ne['availability']:.1f} / "
              f"{100 * ne['floor_accuracy_all']:.1f} / {ne['error_3d_m']['p90']:.2f} / "
              f"{100 * ne['ellipsoid_coverage']:.1f} |", flush=True)
        for x in hd.Run(mc, hd.scenario_of(rec.stem)).rows:
            t = pooled[x[8]]
            t[0] += 1
            t[1] += int(x[2] is not None and x[3] == x[2])
            t[2] += int(x[3] is not None)
            t[3] += int(x[3] is not None and x[5])
    print(f"{passed} of {len(recs)} pass ({THRESHOLDS})")
    for k, (n, right, fixes, inside) in pooled.items():
        print(f"{k}: {n} node-epochs, floor {100 * right / max(n, 1):.2f} %, cov95 "
              f"{100 * inside / max(fixes, 1):.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
