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
fixes within 2 PEB, fix status counts; the calibration of the reported floor probabilities over
every node-epoch (diffpos.floor_calibration: reliability table, ECE, log and Brier scores,
confidently wrong = a wrong floor published at p >= 0.95; absent for estimate v1); gating decisions per anchor (used / excluded and why);
message counts and gaps in sequence numbers. --compare puts the recorded live estimates next to the replayed
ones (matched per node and epoch).

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
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from diffpos.floor_calibration import format_calibration
from diffpos_services.config import load_json_option
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import tracker_help
from diffpos_services.heap import keep_heap
from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.outputs import atomic_path, check_output


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


def _fmt(v: float | None, nd: int = 2) -> str:
    return "-" if v is None else f"{v:.{nd}f}"


def _changed(overrides: dict[str, Any]) -> str:
    """The what-ifs as ``FIELD=VALUE, ...`` (tracker settings as ``tracker.KEY=VALUE``)."""
    items: list[str] = []
    for k, v in overrides.items():
        items += ([f"{k}.{kk}={vv}" for kk, vv in v.items()] if isinstance(v, dict)
                  else [f"{k}={v}"])
    return ", ".join(items) or "none"


def _print_report(rep: dict[str, Any], *, compare: bool) -> None:
    p = print
    acc = rep["accuracy"]
    p(f"replay of {rep['file']}" + ("" if rep["complete"] else "  (TRUNCATED recording: "
                                     "replayed up to its last complete chunk)"))
    changed = _changed(rep["overrides"])
    p(f"  settings from {rep['settings_source']}; method {rep['method']}; changed: {changed}")
    if rep.get("settings_warning"):
        p(f"  WARNING: {rep['settings_warning']}")
    if rep.get("tracker_settings"):
        p(f"  tracker settings: {rep['tracker_settings']}")
    msgs = rep["messages"]
    kinds = ", ".join(f"{k} {n}" for k, n in msgs["by_kind"].items())
    p(f"  {msgs['total']} messages ({kinds}); gaps {msgs['gaps']}; "
      f"late ranges {msgs['late_ranges']}; rejected {sum(msgs['fusion_rejected'].values())}")
    if msgs["skipped_unknown"]:
        p(f"  skipped {msgs['skipped_unknown']} messages on channels that are not diffpos keys")
    t = rep["timing"]
    sp = f", {t['speedup_x']:.1f}x real time" if t.get("speedup_x") else ""
    p(f"  {rep['recording_s']:.1f} s of recording replayed in {t['wall_s']:.2f} s{sp}")
    fx = rep["fixes"]
    p(f"fixes: {fx['total']}  " + "  ".join(f"{k} {n}" for k, n in fx["by_status"].items()))
    hdr = (f"{'node':<10}{'fixes':>7}{'eval':>7}{'3D p50':>8}{'p67':>7}{'p90':>7}{'p95':>7}"
           f"{'max':>8}{'z p50':>7}{'z p90':>7}{'floor%':>8}{'PEB p50':>8}{'<=2PEB':>8}")
    p(hdr)

    def row(name: str, st: dict[str, Any]) -> str:
        e3, ez, pb = st["error_3d_m"], st["error_z_m"], st["peb_m"]
        fl = "-" if st["floor_accuracy"] is None else f"{100 * st['floor_accuracy']:.1f}"
        w2 = "-" if st["within_2peb"] is None else f"{100 * st['within_2peb']:.0f}%"
        return (f"{name:<10}{st['fixes']:>7}{st['evaluated']:>7}{_fmt(e3['p50']):>8}"
                f"{_fmt(e3['p67']):>7}{_fmt(e3['p90']):>7}{_fmt(e3['p95']):>7}{_fmt(e3['max']):>8}"
                f"{_fmt(ez['p50']):>7}{_fmt(ez['p90']):>7}{fl:>8}{_fmt(pb['p50']):>8}{w2:>8}")

    for node, st in acc["per_node"].items():
        p(row(node, st))
    p(row("ALL", acc["overall"]))
    if acc["overall"]["without_truth"]:
        p(f"  ({acc['overall']['without_truth']} fixes had no truth sample nearby: not evaluated)")
    ne = rep.get("node_epochs") or {}
    if ne:  # the replayed node-epochs (every truth sample after the first 2 s)
        for line in format_calibration(ne.get("floor_calibration")):
            p(line)
    p("gating per anchor (used / excluded by reason):")
    for a, g in rep["gating"].items():
        ex = ", ".join(f"{r} {n}" for r, n in g["excluded"].items()) or "-"
        p(f"  {a:<10} used {g['used']:>7}   excluded: {ex}")
    live = rep.get("live")
    if compare:
        if live is None:
            p("compare: the recording holds no live estimates (node/<id>/estimate)")
            return
        c = rep["compare"]
        lo, ro = live["accuracy"]["overall"], acc["overall"]
        p("recorded live vs replayed:")
        p(f"  {'':<22}{'live':>12}{'replayed':>12}")
        for label, lv, rv in (
            ("fixes", lo["fixes"], ro["fixes"]),
            ("evaluated", lo["evaluated"], ro["evaluated"]),
            ("3D error p50 [m]", lo["error_3d_m"]["p50"], ro["error_3d_m"]["p50"]),
            ("3D error p90 [m]", lo["error_3d_m"]["p90"], ro["error_3d_m"]["p90"]),
            ("3D error p95 [m]", lo["error_3d_m"]["p95"], ro["error_3d_m"]["p95"]),
            ("z error p50 [m]", lo["error_z_m"]["p50"], ro["error_z_m"]["p50"]),
            ("z error p90 [m]", lo["error_z_m"]["p90"], ro["error_z_m"]["p90"]),
            ("floor accuracy", lo["floor_accuracy"], ro["floor_accuracy"]),
            ("PEB p50 [m]", lo["peb_m"]["p50"], ro["peb_m"]["p50"]),
        ):
            fmt = (lambda v: str(v)) if isinstance(lv, int) else (lambda v: _fmt(v, 3))
            p(f"  {label:<22}{fmt(lv):>12}{fmt(rv):>12}")
        p(f"  matched {c['matched']} (node, epoch) pairs; only live {c['only_live']}, only "
          f"replayed {c['only_replayed']}; same status {_fmt(100 * (c['status_agree'] or 0), 1)}%")
        d = c["position_diff_m"]
        p50 = "-" if d["p50"] is None else f"{d['p50']:.3g}"
        pmax = "-" if d["max"] is None else f"{d['max']:.3g}"
        p(f"  position difference over {c['with_positions']} pairs: identical "
          f"{c['identical_positions']}, p50 {p50} m, max {pmax} m")
        for ex in c["examples"]:
            if ex["diff_m"] > 0:
                p(f"    {ex['node']} epoch {ex['epoch']}: {ex['diff_m']:.3g} m "
                  f"({ex['live_status']} / {ex['replayed_status']})")


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


def run(args: argparse.Namespace) -> int:
    from diffpos_services.replay.run import replay  # the fusion core: its kernels, not for --help

    src = Path(args.file)
    out_dir = check_outputs(args)
    keep_heap()  # as the live fusion's process (diffpos_services.heap)
    try:
        overrides = _overrides(args)
        progress = None
        bar = None
        if not args.no_progress and sys.stderr.isatty():
            bar = Progress(TextColumn("replay"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                           TimeRemainingColumn(), transient=True)
            task = bar.add_task("replay", total=max(src.stat().st_size, 1))

            def progress(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            bar.start()
        try:
            result = replay(src, overrides=overrides, method=args.method, step_ms=args.step_ms,
                            use_recorded_settings=not args.ignore_recorded_settings,
                            out_mcap=args.write_mcap, max_truth_gap_s=args.max_truth_gap,
                            progress=progress,
                            # the estimate lists only for the .rrd (bounded memory otherwise)
                            keep_estimates=bool(args.rrd))
        finally:
            if bar is not None:
                bar.stop()
    except (RecordingError, ConfigError) as exc:
        print(f"diffpos replay: {exc}", file=sys.stderr)
        return exc.exit_code  # 1: not a diffpos recording; 2: broken input or options
    except OSError as exc:
        print(f"diffpos replay: {exc.filename or src}: {exc.strerror}", file=sys.stderr)
        return 2
    rep = result.report
    if rep.get("settings_warning"):
        print(f"diffpos replay: WARNING: {rep['settings_warning']}", file=sys.stderr)
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
