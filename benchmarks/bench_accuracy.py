"""Accuracy of the whole system: lockstep ``diffpos emulate`` runs scored from their recordings.

Usage::

    python benchmarks/bench_accuracy.py            # every run, 20 s each
    python benchmarks/bench_accuracy.py --quick    # a short check (6 s, default + 2 variants)
    python benchmarks/bench_accuracy.py --only default large --duration 30 --json out.json
    python benchmarks/bench_accuracy.py --random 8 --random-seed 0 --keep /tmp/rand

Every run is the real system: ``diffpos emulate --speed 0 --record FILE`` (router, anchors,
fusion with its default method, recorder as processes; lockstep: emulated time advances as
fast as the fusion keeps up, so the machine's speed changes the latency, never the result).
The recording is then scored against the ground truth it holds with :func:`diffpos.metrics.
score` over EVERY node-epoch after the first 2 s (every truth sample of every node: a
node-epoch without an estimate, or whose estimate has no position, is a miss):
availability, floor accuracy over all node-epochs, 3D and |z| error p50/p90 over the fixes,
truth inside the reported 95 % ellipsoid, the fusion latency (estimate publish time minus
the newest input's publish time) p50/p99 of the recorded estimates, and the calibration of the
reported floor probabilities (:mod:`diffpos.floor_calibration`: ECE of the published floor's
probability, and "confidently wrong", a wrong floor published at p >= 0.95, as a share of all
node-epochs; ``--json`` has the reliability table; docs/floor_calibration.md).

Runs: ``default`` (the paper's building, 4 UAVs, 6 walking responders), ``large``
(scenarios/large.toml: 8 UAVs, 50 nodes), ``ideal`` (the default with ``--channel ideal``:
the paper's moving-edge diffraction path with CRLB noise, which the first-arrival model does
not contain) and variants written here as TOML (not in scenarios/, not tuned for):

- ``tall-floors``: 4 floors of 3.6 m from 2.5 m, 1.0 m sill, 1.2 m windows, 30 x 15 m;
- ``wide-windows``: 3.2 m floors, 0.4 m sill, 2.4 m windows (the band covers most of a floor);
- ``uavs-above-windows``: the default building with the UAVs at 6.5-13 m (at and above the
  windows of the lower floors);
- ``anchors-beyond-ends``: two UAVs beyond the facade ends (x = -27, +26 m) and three in front.

``--random N --random-seed S`` runs ``N`` seeded random held-out geometries ``rand-S-0`` ...
(``benchmarks/heldout.py``: buildings and UAV layouts varied one family at a time for half
the samples, both for the rest; its docstring lists the sampled ranges), alone unless
``--only`` names other runs too; their key parameters are printed below the table. Seeds 0
and 1 (40 each, 2026-11-28) and the diagnosis of their misses: docs/heldout_geo14.md
(``benchmarks/heldout_diag.py`` reads the recordings kept with ``--keep``).

The table (and ``--json``) names the command and the machine; docs/accuracy.md's table (and the
README's summary rows) is regenerated from it.

Measured 2026-11-27 08:27-08:50 UTC (``--only default``, ``--only tall-floors wide-windows
uavs-above-windows anchors-beyond-ends``, ``--only large``; 20 s, seed 0; 2-core VM shared with
four other jobs, load average 4-8), commit 94ee8c5 (fixed 0.2 m existence margin) -> the
tracker's margin of every hypothesis' own height uncertainty
(:func:`diffpos.tracking.model.existence_margin`):

===================  =============  ============  ============  ============
run                  floor %        3D p50 [m]    3D p90 [m]    cov95 %
===================  =============  ============  ============  ============
default              94.1 -> 97.1   0.12 -> 0.12  0.80 -> 0.41  80.6 -> 83.1
tall-floors          98.4 -> 99.2   0.12 -> 0.12  0.26 -> 0.24  86.7 -> 88.8
wide-windows         99.7 -> 99.7   0.11 -> 0.11  0.23 -> 0.23  86.9 -> 87.0
uavs-above-windows   99.7 -> 99.7   0.13 -> 0.13  0.21 -> 0.21  81.9 -> 81.9
anchors-beyond-ends  98.4 -> 98.4   0.12 -> 0.12  0.23 -> 0.23  83.7 -> 83.2
large                99.7 -> 100    0.08 -> 0.08  0.31 -> 0.31  87.1 -> 86.9
===================  =============  ============  ============  ============

(availability 100 % in every run; the table is of the scorer as it was then.) The time
reference of the scoring: a node-epoch's truth was the recorded sample at the epoch's start,
while the estimate is of the node at its own ``t_ns``, the mean time of the ranges it used
(every anchor measures at its own phase of the epoch, 5-95 % of the period): 58-76 ms later in
these runs (76.3 ms in the default run), 7-9 cm of a 1.2 m/s walk, as much as the tracker's
horizontal standard deviation on the level. ``emulate``'s summary already compared with the
truth at the estimate's time; this scorer and ``replay``'s node-epoch report now do too
(:func:`diffpos.metrics.truth_at`). Re-scored so, the same recordings give cov95 87.4 ->
90.3 % (default), 93.8 -> 95.5, 97.1 -> 97.3, 98.1 -> 98.0, 94.9 -> 94.4 and 91.5 -> 91.2 %
(large), 3D p50 0.09 m on default.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from common import SKIP_S, machine, score_recording
from heldout import family, random_scenarios, summary, to_toml

from diffpos.scenario import default_scenario

ROOT = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------------- scenarios
def _anchors(points: Iterable[Iterable[float]]) -> list[dict[str, Any]]:
    return [{"id": f"uav{i + 1}", "position_m": [float(x) for x in p]}
            for i, p in enumerate(points)]


def variants() -> dict[str, dict[str, Any]]:
    """The held-out geometries (scenario dicts; the nodes are the emulator's walking
    responders of each building)."""
    base = default_scenario().to_dict()
    base["nodes"] = {"grid": {}}

    def make(name: str, building: dict[str, Any] | None = None,
             anchors: list[dict[str, Any]] | None = None) -> dict[str, Any]:
        d = json.loads(json.dumps(base))
        d["name"], d["description"] = name, f"bench_accuracy variant {name}"
        if building is not None:
            d["building"].update(building)
            w = d["building"]["width_m"] / 2
            d["building"]["partitions"] = [
                {"axis": "x", "position_m": 0.0, "span_m": [0.0, d["building"]["depth_m"]],
                 "material": "plasterboard", "thickness_m": 0.025},
                {"axis": "y", "position_m": d["building"]["depth_m"] / 2, "span_m": [-w, w],
                 "material": "plasterboard", "thickness_m": 0.025}]
        if anchors is not None:
            d["anchors"] = anchors
        d["nodes"] = {"grid": {"y_max_m": min(22.0, d["building"]["depth_m"] - 1.0)}}
        return d

    return {
        "tall-floors": make("tall-floors", {
            "n_floors": 4, "floor_height_m": 3.6, "first_floor_z_m": 2.5, "sill_height_m": 1.0,
            "window_height_m": 1.2, "width_m": 30.0, "depth_m": 15.0},
            _anchors([[-12, -16, 1.5], [0, -11, 0.5], [11, -17, 2.0], [4, -24, 1.0]])),
        "wide-windows": make("wide-windows", {
            "floor_height_m": 3.2, "sill_height_m": 0.4, "window_height_m": 2.4,
            "first_floor_z_m": 3.5}),
        "uavs-above-windows": make("uavs-above-windows", anchors=_anchors(
            [[-14, -18, 6.5], [0, -13, 13.0], [13, -11, 9.0], [6, -22, 11.0]])),
        "anchors-beyond-ends": make("anchors-beyond-ends", anchors=_anchors(
            [[-27, -9, 2.0], [26, -12, 3.0], [0, -15, 1.0], [-6, -21, 2.5], [9, -17, 0.5]])),
    }


# ----------------------------------------------------------------------------- scoring
# ----------------------------------------------------------------------------- runs
def emulate_cmd(scenario: str | None, *, out: Path, duration_s: float, seed: int,
                channel: str = "emulator", methods: list[str] | None = None) -> list[str]:
    exe = Path(sys.executable).parent / "diffpos"
    cmd = [str(exe) if exe.exists() else "diffpos", "emulate"]
    if scenario is not None:
        cmd.append(scenario)
    method = ["--method", *methods] if methods else []
    return [*cmd, "--speed", "0", "--duration", f"{duration_s:g}", "--seed", str(seed),
            "--channel", channel, *method, "--dashboard", "off", "--no-progress",
            "--record", str(out)]


def runs(tmp: Path, names: list[str] | None,
         random: dict[str, dict[str, Any]] | None = None) -> dict[str, tuple[str | None, str]]:
    """name -> (scenario argument, channel); ``random``: extra scenario dicts by name (run
    whatever ``names`` says)."""
    out: dict[str, tuple[str | None, str]] = {
        "default": (None, "emulator"),
        "large": (str(ROOT / "scenarios" / "large.toml"), "emulator"),
        "ideal": (None, "ideal"),
    }
    random = random or {}
    names = None if names is None else [*names, *random]
    for name, d in (variants() | random).items():
        path = tmp / f"{name}.toml"
        path.write_text(to_toml(d), encoding="utf-8")
        out[name] = (str(path), "emulator")
    return {k: v for k, v in out.items() if names is None or k in names}


def _f(v: float | None, scale: float = 1.0, fmt: str = "6.2f") -> str:
    return "     -" if v is None else format(v * scale, fmt)


def _calib_cols(c: dict[str, Any] | None) -> str:
    """ECE and the confidently wrong share (of all node-epochs) of the floor probabilities;
    dashes when the estimates report none (estimate v1)."""
    if c is None:
        return f"{'-':>6s} {'-':>7s}"
    return f"{c['ece']:6.4f} {100 * c['confidently_wrong']:6.2f}%"


def table(results: dict[str, dict[str, Any]]) -> str:
    head = (f"{'run':20s} {'N':>3s} {'avail':>6s} {'floor':>6s} {'3D p50':>7s} {'3D p90':>7s} "
            f"{'z p50':>6s} {'z p90':>6s} {'cov95':>6s} {'lat p50':>8s} {'lat p99':>8s} "
            f"{'ECE':>6s} {'confwr':>7s}")
    lines = [head, "-" * len(head)]
    for name, r in results.items():
        if "error" in r:
            lines.append(f"{name:20s} failed: {r['error']}")
            continue
        lat = r["latency_ms"]
        lines.append(
            f"{name:20s} {r['nodes']:3d} {_f(r['availability'], 100, '5.1f')}% "
            f"{_f(r['floor'], 100, '5.1f')}% {_f(r['p50_3d'], 1, '7.2f')} "
            f"{_f(r['p90_3d'], 1, '7.2f')} {_f(r['p50_z'])} {_f(r['p90_z'])} "
            f"{_f(r['coverage95'], 100, '5.1f')}% {_f(lat['p50'], 1, '8.1f')} "
            f"{_f(lat['p99'], 1, '8.1f')} {_calib_cols(r.get('floor_calibration'))}"
            + (f"  ({r['recording_parts']} recording parts)"
               if r.get("recording_parts", 1) > 1 else ""))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, help="emulated seconds per run")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="*", help="run only these (default, large, ideal, "
                    + ", ".join(variants()) + ")")
    ap.add_argument("--quick", action="store_true",
                    help="6 s runs of default, tall-floors and anchors-beyond-ends")
    ap.add_argument("--random", type=int, default=0, metavar="N",
                    help="also N random held-out geometries rand-S-i (benchmarks/heldout.py); "
                    "alone unless --only names other runs")
    ap.add_argument("--random-seed", type=int, default=0, metavar="S",
                    help="seed of the random geometries (default 0)")
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    ap.add_argument("--keep", metavar="DIR", help="keep the recordings in DIR")
    ap.add_argument("--method", choices=["dnls", "mnls", "lls", "ippa"], default=None,
                    help="the fusion's estimator (default: diffpos emulate's default, mnls)")
    args = ap.parse_args(argv)
    duration = 6.0 if args.quick else args.duration
    only = args.only or (["default", "tall-floors", "anchors-beyond-ends"] if args.quick else None)
    rand = random_scenarios(args.random, args.random_seed) if args.random > 0 else {}
    if rand and only is None:
        only = []
    results: dict[str, dict[str, Any]] = {}
    commands: dict[str, str] = {}
    with tempfile.TemporaryDirectory(prefix="bench-accuracy-") as tmp_s:
        tmp = Path(args.keep) if args.keep else Path(tmp_s)
        tmp.mkdir(parents=True, exist_ok=True)
        for name, (scenario, channel) in runs(Path(tmp_s), only, rand).items():
            out = tmp / f"{name}.mcap"
            out.unlink(missing_ok=True)
            cmd = emulate_cmd(scenario, out=out, duration_s=duration, seed=args.seed,
                              channel=channel, methods=[args.method] if args.method else None)
            commands[name] = shlex.join(cmd)
            print(f"# {name}: {commands[name]}", file=sys.stderr, flush=True)
            t = time.perf_counter()
            p = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_s)
            if p.returncode != 0 or not out.exists():
                results[name] = {"error": f"exit {p.returncode}: {p.stderr.strip()[-300:]}"}
                continue
            results[name] = score_recording(out) | {"wall_s": time.perf_counter() - t}
    print(f"bench_accuracy: lockstep diffpos emulate --speed 0, {duration:g} s per run, seed "
          f"{args.seed}, every node-epoch after the first {SKIP_S:g} s (a missing position is a "
          f"miss); floor over all node-epochs; 3D/z in m over the fixes; cov95 = truth inside "
          f"the reported 95 % ellipsoid; latency in ms (estimate publish - newest input); ECE = "
          f"expected calibration error of the published floor's probability, confwr = wrong "
          f"floor published at p >= 0.95, % of all node-epochs (diffpos.floor_calibration)")
    print(f"command: python benchmarks/bench_accuracy.py {' '.join(argv or sys.argv[1:])}")
    print(f"machine: {machine()}")
    method = next((r["method"] for r in results.values() if "method" in r), "-")
    print(f"fusion: {method}\n")
    print(table(results))
    if rand:
        print("\nrandom geometries (family: building, uavs or both varied):")
        for i, (name, d) in enumerate(rand.items()):
            print(f"{name:12s} {family(i):8s} {summary(d)}")
    if args.json:
        Path(args.json).write_text(json.dumps({"duration_s": duration, "seed": args.seed,
                                               "machine": machine(), "commands": commands,
                                               "random": rand,
                                               "results": results}, indent=2))
    return 0 if all("error" not in r for r in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
