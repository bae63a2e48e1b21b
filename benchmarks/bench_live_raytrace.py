"""The live system on Sionna RT's channel: lockstep ``diffpos emulate --channel raytrace`` runs
scored from their recordings over ALL node-epochs, beside the emulator channel (issue 34).

    python benchmarks/bench_live_raytrace.py                    # paper, large, heldout-1..3
    python benchmarks/bench_live_raytrace.py --only paper large --keep DIR

Every run is the real system (router, anchors, fusion with its default method and tracker,
recorder as processes):

    diffpos emulate SCEN --channel raytrace --speed 0 --duration 20 --seed 0 \\
        --record OUT.mcap --dashboard off --no-progress

``--channel raytrace`` first traces every anchor's paths to the run's responders along their
trajectories with Sionna RT (the emulate defaults: 3e5 rays per source, depth 4, every 0.5 s;
``--raytrace-samples``/``--raytrace-depth``/``--raytrace-step-s`` pass through), cached on disk
(``$DIFFPOS_RAYTRACE_CACHE``, default ``~/.cache/diffpos/raytrace-live``) by scenario, seed-free
trajectories and settings, so a re-run on other code only pays the run. The same scenario is
then run with ``--channel emulator``.

Scored with the one scorer of a recording (``common.score_recording``: the recorded truth of
every node and fusion epoch against the recorded estimate, :func:`diffpos.metrics.score`); a
node-epoch without a usable position is a miss. Columns: right floor and availability over ALL
node-epochs from t = 0 (``skip_s = 0``), and, over every node-epoch after the first 2 s (as
emulate's summary and bench_accuracy.py), right floor, availability, 95 % ellipsoid coverage
of the fixes, confidently
wrong (wrong floor published at p >= 0.95, share of all node-epochs:
:mod:`diffpos.floor_calibration`), 3D and |z| error p50 / p90 of the fixes, and for the
ray-traced runs the prepare time (the trace or cache look-up, from the run configuration the
recording keeps: ``emulate.raytrace.prepare_s``; ``cold`` when anchors were traced now) and the
whole command's wall time.

Buildings: the paper's (emulate's default: six responders walking and taking the stairs),
``scenarios/large.toml`` (8 UAVs, 50 nodes) and the three random held-out buildings of
``python benchmarks/heldout.py --write-scenarios /work/rt --count 3 --seed 3``
(/work/rt/heldout-K.toml; the emulator's six walking responders). Figures:
docs/raytrace_study.md.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from common import SKIP_S, machine, score_recording
from diffpos_services.recording.reader import side_records

ROOT = Path(__file__).resolve().parents[1]
#: name -> scenario argument of diffpos emulate (None: the built-in paper scenario)
SCENARIOS: dict[str, str | None] = {
    "paper": None,
    "large": str(ROOT / "scenarios" / "large.toml"),
    **{f"heldout-{k}": f"/work/rt/heldout-{k}.toml" for k in (1, 2, 3)},
}
CHANNELS = ("raytrace", "emulator")


def emulate_cmd(scenario: str | None, *, channel: str, out: Path, duration_s: float, seed: int,
                raytrace_opts: list[str]) -> list[str]:
    """The ``diffpos emulate`` command of one run (lockstep, recorded, no dashboard)."""
    cmd = [sys.executable, "-m", "diffpos_services.cli.main", "emulate"]
    if scenario is not None:
        cmd.append(scenario)
    rt = raytrace_opts if channel == "raytrace" else []
    return [*cmd, "--channel", channel, *rt, "--speed", "0", "--duration", f"{duration_s:g}",
            "--seed", str(seed), "--dashboard", "off", "--no-progress", "--record", str(out)]


def raytrace_record(path: Path) -> dict[str, Any] | None:
    """``emulate.raytrace`` of the run configuration a recording keeps (prepare time, settings,
    which anchors were traced now), or None."""
    for att in side_records(path).attachments:
        if att.name == "run_config.json":
            doc = json.loads(att.data)
            return (doc.get("emulate") or {}).get("raytrace")
    return None


def run_one(scenario: str | None, channel: str, out: Path, args: argparse.Namespace,
            raytrace_opts: list[str]) -> dict[str, Any]:
    cmd = emulate_cmd(scenario, channel=channel, out=out, duration_s=args.duration,
                      seed=args.seed, raytrace_opts=raytrace_opts)
    print(f"# {shlex.join(cmd)}", file=sys.stderr, flush=True)
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode != 0 or not out.exists():
        return {"error": f"exit {p.returncode}: {p.stderr.strip()[-400:]}", "wall_s": wall,
                "command": shlex.join(cmd)}
    r = score_recording(out, skip_s=SKIP_S)
    r["from_start"] = score_recording(out, skip_s=0.0)
    r |= {"wall_s": wall, "command": shlex.join(cmd)}
    if channel == "raytrace":
        rec = raytrace_record(out) or {}
        r["prepare_s"], r["traced_now"] = rec.get("prepare_s"), rec.get("traced_now", [])
        r["raytrace"] = rec.get("settings")
    return r


def _f(v: float | None, scale: float = 1.0, fmt: str = "6.2f") -> str:
    return f"{'-':>{len(format(0.0, fmt))}s}" if v is None else format(v * scale, fmt)


def table(results: dict[tuple[str, str], dict[str, Any]]) -> str:
    head = (f"{'building':10s} {'channel':8s} {'N':>3s} {'epochs':>6s} {'floor0':>6s} "
            f"{'avail0':>6s} {'floor':>6s} {'avail':>6s} {'cov95':>6s} {'confwr':>6s} {'3D p50':>6s} "
            f"{'3D p90':>6s} {'z p50':>6s} {'z p90':>6s} {'prep s':>7s} {'wall s':>7s}")
    lines = [head, "-" * len(head)]
    for (name, channel), r in results.items():
        if "error" in r:
            lines.append(f"{name:10s} {channel:8s} failed ({r['wall_s']:.0f} s): {r['error']}")
            continue
        c, a = r.get("floor_calibration") or {}, r["from_start"]
        prep = "" if r.get("prepare_s") is None else (
            f"{r['prepare_s']:6.0f}{'c' if r.get('traced_now') else ' '}")
        lines.append(
            f"{name:10s} {channel:8s} {r['nodes']:3d} {r['node_epochs']:6d} "
            f"{_f(a['floor'], 100, '5.1f')}% {_f(a['availability'], 100, '5.1f')}% "
            f"{_f(r['floor'], 100, '5.1f')}% {_f(r['availability'], 100, '5.1f')}% "
            f"{_f(r['coverage95'], 100, '5.1f')}% "
            f"{_f(c.get('confidently_wrong'), 100, '5.2f')}% {_f(r['p50_3d'])} "
            f"{_f(r['p90_3d'])} {_f(r['p50_z'])} {_f(r['p90_z'])} {prep:>7s} "
            f"{r['wall_s']:7.0f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=list(SCENARIOS), help="only these buildings")
    ap.add_argument("--channels", nargs="+", choices=CHANNELS, default=list(CHANNELS))
    ap.add_argument("--duration", type=float, default=20.0, help="emulated seconds (default 20)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--raytrace-samples", help="passed to diffpos emulate (default: its own)")
    ap.add_argument("--raytrace-depth", help="passed to diffpos emulate (default: its own)")
    ap.add_argument("--raytrace-step-s", help="passed to diffpos emulate (default: its own)")
    ap.add_argument("--keep", metavar="DIR", help="keep the recordings in DIR")
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args(argv)
    rt_opts = [x for k in ("samples", "depth", "step_s")
               if (v := getattr(args, f"raytrace_{k}")) is not None
               for x in (f"--raytrace-{k.replace('_', '-')}", str(v))]
    names = args.only or list(SCENARIOS)
    missing = [SCENARIOS[n] for n in names if SCENARIOS[n] and not Path(SCENARIOS[n]).is_file()]
    if missing:
        sys.exit(f"missing scenario(s) {missing}: write them with python benchmarks/heldout.py "
                 "--write-scenarios /work/rt --count 3 --seed 3, or leave them out with --only")
    results: dict[tuple[str, str], dict[str, Any]] = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-live-rt-") as tmp_s:
        out_dir = Path(args.keep) if args.keep else Path(tmp_s)
        out_dir.mkdir(parents=True, exist_ok=True)
        for name in names:
            for channel in args.channels:
                out = out_dir / f"{name}-{channel}.mcap"
                if out.exists():
                    sys.exit(f"{out} exists: remove it or choose another --keep DIR")
                results[(name, channel)] = run_one(SCENARIOS[name], channel, out, args, rt_opts)
                print(table({(name, channel): results[(name, channel)]}).splitlines()[-1],
                      file=sys.stderr, flush=True)
    print(f"bench_live_raytrace: lockstep diffpos emulate --speed 0, {args.duration:g} s, seed "
          f"{args.seed}; every node-epoch counts (a missing position is a miss): floor0 / avail0 "
          f"= right floor / availability over ALL node-epochs from t = 0, the other columns "
          f"over every node-epoch after the first {SKIP_S:g} s (emulate's summary, "
          f"bench_accuracy.py; epochs = their number): cov95 = truth inside the reported 95 % "
          f"ellipsoid (fixes), confwr = wrong floor published at p >= 0.95 (% of the "
          f"node-epochs), 3D / z errors [m] of the fixes; prep s = ray-trace "
          f"preparation (c: traced now, else from the cache), wall s = the whole command")
    print(f"command: python benchmarks/bench_live_raytrace.py {' '.join(argv or sys.argv[1:])}")
    print(f"date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC; machine: {machine()}; total wall "
          f"{time.perf_counter() - t0:.0f} s\n")
    print(table(results))
    if args.json:
        Path(args.json).write_text(json.dumps(
            {"machine": machine(), "duration_s": args.duration, "seed": args.seed,
             "results": {f"{n}/{c}": r for (n, c), r in results.items()}}, indent=2,
            default=str))
    return 0 if all("error" not in r for r in results.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
