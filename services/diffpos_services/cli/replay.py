"""Re-run fusion offline from an MCAP recording; error report, CDF plot, what-ifs

Reads the recorded anchor states, ranges and anchor liveliness events and feeds them, in the
order and with the receive times the recorder saw, through the same fusion logic the live
service runs (FusionCore), then compares the fixes with the recorded ground truth. The result
depends only on the file and the settings: two replays give identical estimates, bit for bit.
The fusion settings of the live run are taken from the recording (metadata) when present;
options change them to answer "what if" questions on the same data.

The report (stdout, and report.json + cdf.png in --out, default out/replay/<name>/) has,
per node and overall: 3D, horizontal and z error percentiles (50/67/90/95/99 %, max) against
the truth interpolated at each fix time, floor accuracy, PEB percentiles and the share of
fixes within 2 PEB, fix status counts (units under every column, the names explained above the
table); the calibration of the reported floor probabilities over every node-epoch
(diffpos.floor_calibration: reliability table, ECE, log and Brier scores, confidently wrong = a
wrong floor published at p >= 0.95; absent for estimate v1); gating decisions per anchor (used;
"no track": measured while the node had no track yet, not an exclusion; excluded and why);
message counts and gaps in sequence numbers. --compare puts the recorded live estimates next to
the replayed ones (matched per node and epoch; differences named by their time into the
recording). A WARNING block (top, bottom and stderr) names every anchor or node the replayed
fixes lost (used by <= 10 % as many fixes as live), e.g. by a what-if limit. The kernels are
prepared first (compiled in parallel on a machine's first run, with a progress line; cached
after) and their time is reported apart from the replay's speed. --start/--end replay a time
window (seconds into the recording, as `diffpos inspect` counts them).

examples:
  diffpos replay recordings/sample.mcap                     # report + out files
  diffpos replay recordings/sample.mcap --compare           # live vs replayed
  diffpos replay recordings/sample.mcap --no-gating         # what if: no outlier gating
  diffpos replay recordings/sample.mcap --pfa 1e-4          # stricter false-alarm rate
  diffpos replay recordings/sample.mcap --method lls        # LoS least squares instead
  diffpos replay recordings/sample.mcap --set deadline_s=0.5 --set motion_compensation=false
  diffpos replay run.mcap --set tracker.nis_limit=12         # what if: one tracker setting
  diffpos replay run.mcap --write-mcap run.replayed.mcap    # replayed estimates on
                                                            #  diffpos/<site>/replay/node/<id>/estimate
  diffpos replay run.mcap --rrd run.replayed.rrd            # Rerun dashboard of the replay
  diffpos replay run.mcap --start 60 --end 90               # seconds 60-90 of the recording
  diffpos replay sharded.mcap --shards 1                    # what if: one fusion, not N shards
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from diffpos_services.config import load_json_option
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import tracker_help
from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.outputs import atomic_path, check_output

# (the kernels' preparation, the recording's reader, the progress bar and the report's
# formatting are imported where used: `diffpos replay --help` needs none of them)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.mcap", help="recording to replay")
    g = parser.add_argument_group("what if (fusion settings)")
    g.add_argument("--method", choices=["dnls", "mnls", "lls", "ippa"], default=None,
                   help="estimator (default: the recorded setting, else dnls): dnls (the "
                        "fusion's D-NLS), lls (LoS linear least "
                        "squares), ippa (iterative parallel projection)")
    g.add_argument("--no-gating", action="store_true", help="turn outlier gating (RAIM FDE) off")
    g.add_argument("--pfa", type=float, metavar="P",
                   help="gating false-alarm probability (e.g. 1e-4)")
    g.add_argument("--workers", type=int, metavar="N",
                   help="processes sharing the tracker's and the snapshot fixes' rows, this one "
                        "included (mnls + tracking; same estimates for any N; default: the "
                        "recorded setting, else 1; at most this machine's cores)")
    g.add_argument("--shards", type=int, metavar="N",
                   help="replay a run of fusion shards as N fusion processes, each live "
                        "shard's record (or the recorded order) on N cores keeping that "
                        "shard's responders; 1 = one fusion (default: as live, one core per "
                        "live shard, reproducing every live estimate)")
    g.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="any fusion setting, VALUE as JSON (repeatable), e.g. deadline_s=0.5; "
                        "a tracker setting as tracker.KEY=VALUE (changes only that one of the "
                        "recorded tracker settings), e.g. tracker.nis_limit=12. Tracker keys, "
                        "with default [unit]: " + tracker_help().replace("%", "%%"))
    g.add_argument("--config", metavar="FILE.json",
                   help="fusion settings from a JSON object (tracker settings as an object "
                        "under \"tracker\", merged into the recorded ones)")
    g.add_argument("--ignore-recorded-settings", action="store_true",
                   help="start from the defaults instead of the settings in the recording")
    g.add_argument("--step-ms", type=float, default=5.0, metavar="MS",
                   help="fusion step granularity in recorded receive time [ms] (default 5: like "
                        "the live service, reproduces its fixes; 0 = after every message; "
                        "larger = several epochs per solver batch, ~1.3x faster at 1000, but "
                        "warm starts and motion compensation then use older tracks and fixes "
                        "differ from live: see benchmarks/bench_recorder.py)")
    o = parser.add_argument_group("output")
    o.add_argument("--out", metavar="DIR",
                   help="directory for report.json and cdf.png (default out/replay/<FILE stem>/)")
    o.add_argument("--no-files", action="store_true", help="do not write report.json / cdf.png")
    o.add_argument("--json", action="store_true", help="print the JSON report to stdout")
    o.add_argument("--compare", action="store_true",
                   help="recorded live estimates vs replayed, side by side")
    o.add_argument("--write-mcap", metavar="OUT.mcap",
                   help="write a copy of the recording plus the replayed estimates")
    o.add_argument("--rrd", metavar="OUT.rrd",
                   help="write the Rerun dashboard of the replay (replayed estimates, recorded "
                   "anchors and truth; open with `rerun OUT.rrd`)")
    o.add_argument("--max-truth-gap", type=float, default=0.5, metavar="S",
                   help="only evaluate fixes within S seconds of a truth sample (default 0.5)")
    o.add_argument("--no-progress", action="store_true", help="no progress bar")
    w = parser.add_argument_group("time window")
    w.add_argument("--start", type=float, metavar="S",
                   help="replay from S seconds into the recording (after its first message; "
                        "as `diffpos inspect` counts); the anchors' liveliness before it too")
    w.add_argument("--end", type=float, metavar="S",
                   help="replay up to S seconds into the recording")


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if args.config:
        doc = load_json_option("--config", args.config)
        if not isinstance(doc, dict):
            raise ConfigError(f"--config {args.config}: must hold a JSON object of settings")
        out.update(doc)
    for item in args.set:
        field, sep, value = item.partition("=")
        if not sep or not field:
            raise ConfigError(f"--set {item!r}: expected FIELD=VALUE, e.g. deadline_s=0.5")
        try:
            parsed = json.loads(value)
        except ValueError:
            parsed = value
        name = field.strip()
        if name.startswith("tracker."):  # one tracker setting: merged into the recorded ones
            tracker = out.setdefault("tracker", {})
            if not isinstance(tracker, dict):
                raise ConfigError(f"--set {item!r}: tracker is not a JSON object of settings")
            tracker[name.removeprefix("tracker.")] = parsed
        elif name == "tracker" and isinstance(parsed, dict):
            out.setdefault("tracker", {}).update(parsed)
        else:
            out[name] = parsed
    if args.no_gating:
        out["gating"] = False
    if args.pfa is not None:
        out["false_alarm_probability"] = args.pfa
    if args.workers is not None:
        out["workers"] = args.workers
    return out


#: What the per-node table's columns mean (printed above it).
COLUMNS = (
    "fixes: estimates published; scored: fixes with a position and a truth sample within",
    "  --max-truth-gap; 3D, z: error percentiles of the scored fixes against the truth [m];",
    "  floor: scored fixes on the true floor [%]; PEB: position error bound, the fix's own",
    "  1-sigma 3D accuracy [m]; in 2 PEB: scored fixes with a 3D error <= 2 x PEB [%]",
)
#: What the exclusion reasons mean (printed under the gating table, those that occur).
REASONS = {
    "RAIM": "the fault test (RAIM) removed it from the fix",
    "NOT_DETECTED": "the anchor reported no range to the node",
    "NO_ANCHOR_STATE": "no usable anchor state (position) at the fix time",
    "NOT_USED": "not needed by the fix",
    "ANCHOR_LOST": "the anchor had left (liveliness)",
    "NOT_REPORTED": "the anchor's ranges did not arrive in time",
    "PREGATE_SHORTER_THAN_LOS": "range shorter than the line of sight: impossible",
}


def _fmt(v: float | None, nd: int = 2) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def _pct(share: float | None, nd: int = 1) -> str:
    """A share as a percentage number (the unit is in the header or follows as `` %``)."""
    return "-" if share is None else f"{100 * share:.{nd}f}"


def _at(rep: dict[str, Any], t_ns: int | None) -> str:
    """``12.3 s`` into the recording (receive time after its first message)."""
    if t_ns is None or rep.get("origin_ns") is None:
        return "?"
    return f"{(t_ns - rep['origin_ns']) / 1e9:.1f} s"


def dropped_lines(rep: dict[str, Any]) -> list[str]:
    """The loud warning when the replay's fixes lost an anchor or a node (empty: none)."""
    d = rep.get("dropped") or {}
    anchors, nodes = d.get("anchors") or {}, d.get("nodes") or {}
    if not anchors and not nodes:
        return []
    what_if = rep.get("what_if") or "none"
    out = ["!" * 78, f"WARNING: the replayed fixes lost {len(anchors)} anchor(s) and "
           f"{len(nodes)} node(s) the recording has (what-if: {what_if})"]
    for a, x in anchors.items():
        live = "" if x["live_used"] is None else f" (recorded live: {x['live_used']})"
        why = ", ".join(f"{r} {n}" for r, n in x["excluded"].items()) or "no exclusion listed"
        out.append(f"  anchor {a}: used by {x['replayed_used']} replayed fixes{live}; "
                   f"excluded: {why}")
    for n, x in nodes.items():
        live = "" if x["live_positioned"] is None else f" (recorded live: {x['live_positioned']})"
        out.append(f"  node {n}: {x['replayed_positioned']} of {x['replayed_fixes']} replayed "
                   f"fixes have a position{live}")
    rej = d.get("fusion_rejected") or {}
    if rej:
        out.append("  the fusion rejected input messages: "
                   + ", ".join(f"{r} {n}" for r, n in rej.items())
                   + " (a limit of the what-if? see the fusion settings)")
    out.append("!" * 78)
    return out


def _header(rep: dict[str, Any], p: Any) -> None:
    p(f"replay of {rep['file']}" + ("" if rep["complete"] else "  (TRUNCATED recording: "
                                     "replayed up to its last complete chunk)"))
    p(f"  settings from {rep['settings_source']}; method {rep['method']}")
    p(f"  WHAT-IF, settings changed: {rep['what_if']}" if rep.get("what_if")
      else "  what-if: none (the recorded settings)")
    win = rep.get("window")
    if win:
        lo = "its start" if win["start_s"] is None else f"{win['start_s']:g} s"
        hi = "its end" if win["end_s"] is None else f"{win['end_s']:g} s"
        p(f"  time window: {lo} to {hi} into the recording (decision record not used)")
    if rep.get("settings_warning"):
        p(f"  WARNING: {rep['settings_warning']}")
    shards_note = (rep.get("shards") or {}).get("note")
    if shards_note:
        p(f"  fusion shards: {shards_note}")
    if rep.get("tracker_settings"):
        p(f"  tracker settings: {rep['tracker_settings']}")
    msgs = rep["messages"]
    kinds = ", ".join(f"{k} {n}" for k, n in msgs["by_kind"].items())
    p(f"  {msgs['total']} messages ({kinds}); gaps {msgs['gaps']}; "
      f"late ranges {msgs['late_ranges']}; rejected {sum(msgs['fusion_rejected'].values())}")
    if msgs["skipped_unknown"]:
        p(f"  skipped {msgs['skipped_unknown']} messages on channels that are not diffpos keys")
    _timing_line(rep, p)


def _timing_line(rep: dict[str, Any], p: Any) -> None:
    """The replay's speed, the kernels' time before it and the processes that ran it."""
    t = rep["timing"]
    sp = f": {t['speedup_x']:.1f}x real time" if t.get("speedup_x") else ""
    kern = t.get("kernels_s")
    # compiled: a worker spent CPU seconds on it (a cache load takes about one, whatever the
    # wall seconds on a busy machine)
    compiled = max(t.get("kernel_worker_cpu_s") or [0.0]) > 5.0
    before = ("" if kern is None else f"; before that the solver kernels took {kern:.1f} s "
              f"({'compiled: first run on this machine, cached after' if compiled else 'loaded from the cache'})")
    load = t.get("kernel_load_s")
    loads = "" if load is None else f"; kernel loads in this process {load:.2f} s"
    n = t.get("processes", 1)
    procs = f"; {n} processes (--workers)" if n > 1 else "; 1 process"
    p(f"  {rep['recording_s']:.1f} s of recording replayed in {t['wall_s']:.2f} s{sp} "
      f"(fusion warm-up {t.get('warm_up_s', 0.0):.1f} s{before}{loads}{procs})")


def _accuracy_table(rep: dict[str, Any], p: Any) -> None:
    acc = rep["accuracy"]
    fx = rep["fixes"]
    no_pos = acc["overall"].get("without_position", 0)
    p(f"fixes: {fx['total']} published (" + ", ".join(f"{k} {n}" for k, n in
                                                     fx["by_status"].items())
      + f"); {no_pos} without a position")
    for line in COLUMNS:
        p(f"  {line}")
    p(f"{'node':<10}{'fixes':>7}{'scored':>7}{'3D p50':>8}{'p67':>7}{'p90':>7}{'p95':>7}"
      f"{'max':>8}{'z p50':>7}{'z p90':>7}{'floor':>7}{'PEB p50':>8}{'in 2 PEB':>9}")
    p(f"{'':<10}{'[n]':>7}{'[n]':>7}{'[m]':>8}{'[m]':>7}{'[m]':>7}{'[m]':>7}"
      f"{'[m]':>8}{'[m]':>7}{'[m]':>7}{'[%]':>7}{'[m]':>8}{'[%]':>9}")

    def row(name: str, st: dict[str, Any]) -> str:
        e3, ez, pb = st["error_3d_m"], st["error_z_m"], st["peb_m"]
        return (f"{name:<10}{st['fixes']:>7}{st['evaluated']:>7}{_fmt(e3['p50']):>8}"
                f"{_fmt(e3['p67']):>7}{_fmt(e3['p90']):>7}{_fmt(e3['p95']):>7}{_fmt(e3['max']):>8}"
                f"{_fmt(ez['p50']):>7}{_fmt(ez['p90']):>7}{_pct(st['floor_accuracy']):>7}"
                f"{_fmt(pb['p50']):>8}{_pct(st['within_2peb']):>9}")

    for node, st in acc["per_node"].items():
        p(row(node, st))
    p(row("ALL", acc["overall"]))
    if acc["overall"]["without_truth"]:
        p(f"  ({acc['overall']['without_truth']} fixes had no truth sample nearby: not scored)")


def _gating_table(rep: dict[str, Any], p: Any) -> None:
    p("gating per anchor [fixes]: used = fixes that used the anchor; no track = fixes of a")
    p("  node without a track yet (UNINITIALISED) or any more (LOST): measured, not an")
    p("  exclusion; excluded = left out of a fix, by reason")
    p(f"  {'anchor':<10}{'used':>8}{'no track':>10}   excluded")
    seen: set[str] = set()
    for a, g in rep["gating"].items():
        seen |= set(g["excluded"])
        ex = ", ".join(f"{r} {n}" for r, n in g["excluded"].items()) or "-"
        p(f"  {a:<10}{g['used']:>8}{g.get('no_track', 0):>10}   {ex}")
    for r in sorted(seen):
        p(f"    {r}: {REASONS.get(r, 'see docs/wire.md')}")


def _compare_table(rep: dict[str, Any], p: Any) -> None:
    live, acc = rep.get("live"), rep["accuracy"]
    if live is None:
        p("compare: the recording holds no live estimates (node/<id>/estimate)")
        return
    c = rep["compare"]
    lo, ro = live["accuracy"]["overall"], acc["overall"]
    p("recorded live vs replayed:")
    p(f"  {'':<26}{'live':>12}{'replayed':>12}")
    rows: list[tuple[str, Any, Any, Any]] = [
        ("fixes [n]", lo["fixes"], ro["fixes"], str),
        ("scored [n]", lo["evaluated"], ro["evaluated"], str),
        ("without a position [n]", lo.get("without_position"), ro.get("without_position"), str),
    ]
    for label, key, q in (("3D error", "error_3d_m", "p50"), ("3D error", "error_3d_m", "p90"),
                          ("3D error", "error_3d_m", "p95"), ("3D error", "error_3d_m", "max"),
                          ("z error", "error_z_m", "p50"), ("z error", "error_z_m", "p90"),
                          ("PEB", "peb_m", "p50")):
        rows.append((f"{label} {q} [m]", lo[key][q], ro[key][q], lambda v: _fmt(v, 3)))
    rows.append(("on the true floor [%]", lo["floor_accuracy"], ro["floor_accuracy"], _pct))
    for label, lv, rv, fmt in rows:
        p(f"  {label:<26}{fmt(lv):>12}{fmt(rv):>12}")
    p(f"  matched {c['matched']} (node, epoch) pairs; only live {c['only_live']}, only "
      f"replayed {c['only_replayed']}; same status {_pct(c['status_agree'] or 0)} %")
    d = c["position_diff_m"]
    p50 = "-" if d["p50"] is None else f"{d['p50']:.3g}"
    pmax = "-" if d["max"] is None else f"{d['max']:.3g}"
    p(f"  position difference over {c['with_positions']} pairs: identical "
      f"{c['identical_positions']}, p50 {p50} m, max {pmax} m")
    if c.get("live_not_reproducible"):  # a fusion restart the record cannot follow
        p(f"  not reproducible: {c['live_not_reproducible']} live estimates: " + "; ".join(
            f"{n} {why}" for why, n in c["live_not_reproducible_by_reason"].items()))
    if any(ex["diff_m"] > 0 for ex in c["examples"]):
        p("  largest differences (time = received, s into the recording):")
    for ex in c["examples"]:
        if ex["diff_m"] > 0:
            p(f"    {ex['node']} at {_at(rep, ex.get('received_ns'))}: {ex['diff_m']:.3g} m "
              f"(status live {ex['live_status']} / replayed {ex['replayed_status']})")


def _print_report(rep: dict[str, Any], *, compare: bool) -> None:
    from diffpos.floor_calibration import format_calibration

    p = print
    _header(rep, p)
    warn = dropped_lines(rep)
    for line in warn:
        p(line)
    _accuracy_table(rep, p)
    ne = rep.get("node_epochs") or {}
    if ne:  # the replayed node-epochs (every truth sample after the first 2 s)
        for line in format_calibration(ne.get("floor_calibration")):
            p(line)
    _gating_table(rep, p)
    if compare:
        _compare_table(rep, p)
    for line in warn:  # again at the end, where the eye lands
        p(line)


def check_outputs(args: argparse.Namespace) -> Path | None:
    """Every output option, checked before any work (ConfigError, exit 2): none may be the
    input, a directory where a file goes (or a file where the --out directory goes), or
    unwritable. Returns the report directory (``None`` with --no-files)."""
    src = Path(args.file)
    if args.write_mcap:
        check_output(args.write_mcap, option="--write-mcap", inputs=[src])
    if args.rrd:
        check_output(args.rrd, option="--rrd", inputs=[src])
    if args.no_files:
        return None
    out_dir = Path(args.out) if args.out else Path("out") / "replay" / src.stem
    check_output(out_dir, option="--out", directory=True)
    for name in ("report.json", "cdf.png"):
        check_output(out_dir / name, option="--out", inputs=[src])
    outs = [Path(p) for p in (args.write_mcap, args.rrd) if p]
    for a, b in ((a, b) for i, a in enumerate(outs) for b in outs[i + 1:]):
        if a.resolve() == b.resolve():
            raise ConfigError(f"--write-mcap and --rrd both name {a}: give two files")
    return out_dir


def _write_report_files(result: Any, out_dir: Path) -> list[str]:
    out_dir.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_dir / "report.json") as tmp:
        tmp.write_text(json.dumps(result.report, indent=2) + "\n", encoding="utf-8")
    from diffpos_services.reports.replay import plot_cdf  # matplotlib: only when plotting

    with atomic_path(out_dir / "cdf.png") as tmp:
        plot_cdf(result, tmp)
    return [str(out_dir / "report.json"), str(out_dir / "cdf.png")]


def kernel_groups(args: argparse.Namespace, overrides: dict[str, Any]) -> list[str]:
    """The kernel groups (:func:`~diffpos_services.fusion.prepare.groups_for`) of the method
    the replay will run, read cheaply before the fusion is imported (which compiles): --method,
    else a ``method`` what-if, else the recorded one (``dnls`` when none is recorded or with
    --ignore-recorded-settings, as :func:`~diffpos_services.replay.run.replay_settings`)."""
    from diffpos_services.fusion.prepare import GROUP_METHODS, groups_for
    from diffpos_services.recording.reader import side_records
    from diffpos_services.recording.summary import live_fusion_settings

    recorded: dict[str, Any] = {}
    if not args.ignore_recorded_settings:
        try:
            recorded, _ = live_fusion_settings(side_records(args.file))
        except (RecordingError, OSError):
            recorded = {}  # the replay itself says what is wrong with the file
    settings = {**recorded, **overrides}
    method = args.method or settings.get("method") or "dnls"
    if method not in GROUP_METHODS:
        method = "mnls"  # an unknown method fails later, in the settings; prepare the most
    return groups_for(method, tracking=bool(settings.get("tracking", True)))


def _progress_bar(src: Path) -> tuple[Any, Any]:
    """A transient progress bar over the recording's bytes (a terminal only) and its update
    function; ``(None, None)`` without a terminal."""
    if not sys.stderr.isatty():
        return None, None
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(TextColumn("replay"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                   TimeRemainingColumn(), transient=True)
    task = bar.add_task("replay", total=max(src.stat().st_size, 1))

    def progress(done: int, total: int) -> None:
        bar.update(task, completed=done, total=total)

    return bar, progress


def run(args: argparse.Namespace) -> int:
    from diffpos_services.fusion.prepare import KernelError, prepare_kernels, progress_display
    from diffpos_services.heap import keep_heap

    src = Path(args.file)
    out_dir = check_outputs(args)
    keep_heap()  # as the live fusion's process (diffpos_services.heap)
    try:
        overrides = _overrides(args)
        # the kernels first (compiled in parallel on a fresh machine, with a moving progress
        # line; loaded from numba's cache after), then the fusion's import loads them: both
        # before the replay, so its speed does not count them
        t0 = time.perf_counter()
        # (skip_cached: no worker processes when numba's cache holds them already; the
        # import below loads them, ~2 s of CPU less than workers that load them too)
        prepared = prepare_kernels(kernel_groups(args, overrides),
                                   progress=None if args.no_progress else progress_display(),
                                   skip_cached=True)
        from diffpos_services.replay.run import replay  # the fusion core: not for --help

        kernels_s = time.perf_counter() - t0

        bar, progress = (None, None) if args.no_progress else _progress_bar(src)
        if bar is not None:
            bar.start()
        try:
            result = replay(src, overrides=overrides, method=args.method, step_ms=args.step_ms,
                            use_recorded_settings=not args.ignore_recorded_settings,
                            out_mcap=args.write_mcap, max_truth_gap_s=args.max_truth_gap,
                            progress=progress, start_s=args.start, end_s=args.end,
                            shards=args.shards,
                            # the estimate lists only for the .rrd (bounded memory otherwise)
                            keep_estimates=bool(args.rrd))
        finally:
            if bar is not None:
                bar.stop()
    except (RecordingError, ConfigError, KernelError) as exc:
        print(f"diffpos replay: {exc}", file=sys.stderr)
        return exc.exit_code  # 1: not a diffpos recording; 2: broken input or options
    except OSError as exc:
        print(f"diffpos replay: {exc.filename or src}: {exc.strerror}", file=sys.stderr)
        return 2
    rep = result.report
    rep["timing"]["kernels_s"] = kernels_s  # the workers' compile (or cache load) + imports
    rep["timing"]["kernel_worker_cpu_s"] = list(prepared.worker_cpu_s)
    if rep.get("settings_warning"):
        print(f"diffpos replay: WARNING: {rep['settings_warning']}", file=sys.stderr)
    for line in dropped_lines(rep):  # also where a script's log keeps it
        print(f"diffpos replay: {line}", file=sys.stderr)
    if args.rrd:
        # rerun is a heavy import that `diffpos replay --help` and plain replays must not pay
        from diffpos_services.dashboard.convert import mcap_to_rrd

        with atomic_path(args.rrd) as tmp:
            mcap_to_rrd(src, tmp, estimates=result.estimates,
                        recording_id=f"{src.stem}-replay")
    rep_files = [] if out_dir is None else _write_report_files(result, out_dir)
    if args.json:
        print(json.dumps(rep, indent=2))
    else:
        _print_report(rep, compare=args.compare)
        for f in rep_files:
            print(f"wrote {f}")
        if args.write_mcap:
            print(f"wrote {args.write_mcap}")
        if args.rrd:
            print(f"wrote {args.rrd}")
    return 0
