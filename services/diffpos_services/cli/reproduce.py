"""Regenerate the paper's study: MPC table, first-arrival stats, error CDFs

Reproduces the numerical study of Duggal et al. ("Diffraction-Aided Wireless Positioning",
Section V and the ray-tracing appendix) on a scenario (default: the paper's geometry, see
scenarios/paper.toml): 4 UAV anchors outside a 5-floor building and a receiver grid on every
floor (17,600 receivers).

What it does, in order:

1. Channels. For every receiver x anchor link the O2I emulator (diffpos.channel) lists the
   multipath components: MPC-1 direct (through the window, or through concrete), MPC-2 single
   reflections (ground, floor, ceiling, walls), MPC-3 diffraction over the upper/lower window
   edge of the receiver's floor (UTD, plus drywall partitions crossed), MPC-4 higher order
   (diffraction + reflection, double reflections).
2. First arrival. The paper's detector: the earliest MPC whose SNR (power + 20 dB processing
   gain - kTB) is above P_max - 15 dB; the measured range is c x its delay plus Gaussian noise
   with the ranging CRLB c / sqrt(8 pi^2 B^2 SNR).
3. Statistics. P_e (an MPC group exists) and P_fap (the first arrival belongs to it) per group,
   the paper's Table; the first arrival's AoA and SNR distributions (box plots).
4. Positioning. Every receiver is located from its 4 ranges by LLS, IPPA, D-NLS Case-1
   (node at the window mid-height) and D-NLS Case-2 (model offset Delta = 1.5 m), compared
   with the position error bound (PEB) and the z bound of the diffraction model.

Outputs in --out (default out/reproduce): summary.json and summary.md (tables, with the
paper's numbers side by side), cdf_3d_error.png, cdf_z_error.png, first_arrival_boxplots.png
and first_arrival.npz (the per-link first-arrival data; feed it back with
--channel arrivals:FILE to re-run only the positioning).

The emulator is not the paper's commercial ray tracer: expect the same mechanisms and ordering,
not the same percentages (summary.md compares them).

Other channel sources (the hook for ray-traced data):
  --channel raytrace:FILE     a dataset written by 'diffpos raytrace' (Sionna RT)
  --channel arrivals:FILE     first-arrival arrays (.npz with anchors_m, nodes_m, range_m,
                              snr_db, detected [, sigma_m, mpc_class, aoa_deg])

examples:
  diffpos reproduce                              full study, about a minute on 2 cores
  diffpos reproduce --quick --out out/quick      1,500 random receivers, a few seconds
  diffpos reproduce --seed 7 --methods dnls_case1 dnls_lower
  diffpos reproduce --scenario scenarios/paper.toml --delta-m 1.0
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from diffpos.channel import (
    Channel,
    emulate_channel,
    first_arrival,
    mpc_statistics,
)
from diffpos.scenario import Scenario, ScenarioError
from diffpos.study import (
    METHOD_LABELS,
    FirstArrivalData,
    PositioningStudy,
    empirical_cdf,
    first_arrival_statistics,
    floor_starts_m,
    method_label,
    positioning_study,
)

#: The paper's Table "MPC through the windows" [%].
PAPER_TABLE: dict[str, dict[str, float]] = {
    "MPC-1": {"P_e": 3.47, "P_fap": 3.47},
    "MPC-2": {"P_e": 9.03, "P_fap": 1.60},
    "MPC-3": {"P_e": 91.52, "P_fap": 84.79},
    "MPC-4": {"P_e": 100.0, "P_fap": 10.12},
}
ALL_METHODS = [k for k in METHOD_LABELS if k != "peb"]
DEFAULT_QUICK_NODES = 1500
COLORS = {"lls": "tab:red", "ippa": "tab:orange", "dnls_case1": "tab:blue",
          "dnls_case2": "tab:green", "dnls_lower": "tab:purple"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", metavar="FILE",
                        help="scenario TOML file or shipped name (default: the paper's, "
                             "scenarios/paper.toml)")
    parser.add_argument("--out", type=Path, default=Path("out/reproduce"),
                        help="output directory, created (default: out/reproduce)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the range noise and the --quick subsample (default: 0)")
    parser.add_argument("--quick", action="store_true",
                        help=f"a random subsample of --quick-nodes receivers "
                             f"(default {DEFAULT_QUICK_NODES})")
    parser.add_argument("--quick-nodes", type=int, default=DEFAULT_QUICK_NODES, metavar="N",
                        help="receivers kept by --quick")
    parser.add_argument("--channel", default="emulator", metavar="SOURCE",
                        help="emulator (default), raytrace:FILE or arrivals:FILE.npz")
    parser.add_argument("--methods", nargs="+", choices=ALL_METHODS,
                        default=["lls", "ippa", "dnls_case1", "dnls_case2"],
                        help="estimators to run (default: the paper's four; dnls_lower models "
                             "the lower window edge)")
    parser.add_argument("--delta-m", type=float, default=1.5,
                        help="D-NLS Case-2 model offset Delta [m] (default: 1.5, the paper's)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


# --------------------------------------------------------------------------------------------
# computation
# --------------------------------------------------------------------------------------------


def _load_scenario(name: str | None) -> Scenario:
    from diffpos_services.scenario_io import scenario_or_default

    return scenario_or_default(name)


def _channel_source(args: argparse.Namespace) -> tuple[str, Path | None]:
    src = args.channel
    if src == "emulator":
        return "emulator", None
    kind, sep, path = src.partition(":")
    if not sep or kind not in ("raytrace", "arrivals") or not path:
        raise ValueError(f"--channel: expected emulator, raytrace:FILE or arrivals:FILE, "
                         f"got {src!r}")
    p = Path(path)
    if not p.exists():
        raise ValueError(f"--channel: no such file {p}")
    return kind, p


class _Progress:
    """Rich progress bars (or nothing), one task per stage."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.tasks: dict[str, Any] = {}
        self.bar = None
        if enabled:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )

            self.bar = Progress(TextColumn("{task.description:<28}"), BarColumn(),
                                MofNCompleteColumn(), TimeElapsedColumn(),
                                console=Console(stderr=True))

    def __enter__(self):
        if self.bar is not None:
            self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)

    def add(self, key: str, label: str, total: int) -> None:
        if self.bar is not None:
            self.tasks[key] = self.bar.add_task(label, total=total)

    def update(self, key: str, done: int) -> None:
        if self.bar is not None and key in self.tasks:
            self.bar.update(self.tasks[key], completed=done)


def compute(args: argparse.Namespace, scenario: Scenario) -> dict[str, Any]:
    """Run the whole study; returns everything the writers need."""
    ss = np.random.SeedSequence(args.seed)
    sub_rng, noise_rng = (np.random.default_rng(s) for s in ss.spawn(2))
    kind, path = _channel_source(args)
    timing: dict[str, float] = {}
    channel: Channel | None = None
    table: dict[str, dict[str, float]] | None = None
    t_all = time.perf_counter()
    with _Progress(not args.no_progress) as prog:
        t0 = time.perf_counter()
        if kind == "arrivals":
            with np.load(path) as z:
                data = FirstArrivalData.from_arrays(dict(z),
                                                    bandwidth_hz=scenario.radio.bandwidth_hz)
        elif kind == "raytrace":
            from diffpos_services import raytrace

            ds = raytrace.load_dataset(path, scenario=scenario)
            channel = raytrace.dataset_channel(ds, scenario.radio)
            fa = raytrace.dataset_first_arrival(ds, radio=scenario.radio, rng=noise_rng)
            table = mpc_statistics(channel, fa, path_class=ds.path_class)
            data = FirstArrivalData.from_channel(fa, ds.anchors_m, ds.nodes_m)
        else:
            nodes = scenario.node_positions_m()
            if args.quick and args.quick_nodes < len(nodes):
                keep = np.sort(sub_rng.choice(len(nodes), args.quick_nodes, replace=False))
                nodes = nodes[keep]
            anchors = scenario.anchor_positions_m()
            prog.add("channel", "channels + first arrival", 1)
            channel = emulate_channel(anchors, nodes, building=scenario.building,
                                      radio=scenario.radio)
            fa = first_arrival(channel, radio=scenario.radio, rng=noise_rng)
            table = mpc_statistics(channel, fa)
            data = FirstArrivalData.from_channel(fa, anchors, nodes)
            prog.update("channel", 1)
        if kind != "emulator" and args.quick and args.quick_nodes < data.n_nodes:
            keep = np.sort(sub_rng.choice(data.n_nodes, args.quick_nodes, replace=False))
            data = data.subset(keep)
        timing["channel_s"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        for m in args.methods:
            prog.add(m, method_label(m, args.delta_m), data.n_nodes)
        prog.add("peb", "PEB / z bound", data.n_nodes)
        study = positioning_study(
            data, window_height_m=scenario.building.window_height_m,
            edge_x_m=scenario.building.edge_x_m, delta_case2_m=args.delta_m,
            methods=tuple(args.methods), progress=lambda m, d, n: prog.update(m, d),
            z_starts_m=floor_starts_m(scenario.building),
            start_y_m=0.5 * scenario.building.depth_m,
        )
        timing["positioning_s"] = time.perf_counter() - t0
    timing["total_s"] = time.perf_counter() - t_all
    by_mech = None
    if kind == "emulator":
        pairs = max(fa.slot.size, 1)
        by_mech = {lab: 100.0 * float(np.sum(fa.slot == k)) / pairs
                   for k, lab in enumerate(channel.mechanism)}
        by_mech = {k: v for k, v in by_mech.items() if v > 0}
    return {"kind": kind, "path": path, "channel": channel, "table": table, "data": data,
            "study": study, "timing": timing, "fap_stats": first_arrival_statistics(data),
            "fap_by_mechanism": by_mech}


# --------------------------------------------------------------------------------------------
# outputs
# --------------------------------------------------------------------------------------------


def _clean(x: Any) -> Any:
    """JSON-safe copy: inf/NaN -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def build_summary(args: argparse.Namespace, scenario: Scenario, res: dict[str, Any]
                  ) -> dict[str, Any]:
    data: FirstArrivalData = res["data"]
    study: PositioningStudy = res["study"]
    return {
        "scenario": scenario.name,
        "channel_source": res["kind"] + ("" if res["path"] is None else f":{res['path']}"),
        "seed": args.seed,
        "quick": bool(args.quick),
        "n_receivers": data.n_nodes,
        "n_anchors": int(np.shape(data.anchors_m)[0]),
        "anchors_m": np.asarray(data.anchors_m).tolist(),
        "delta_case2_m": args.delta_m,
        "window_height_m": scenario.building.window_height_m,
        "mpc_table_pct": res["table"],
        "first_arrival_mechanism_pct": res["fap_by_mechanism"],
        "paper_mpc_table_pct": PAPER_TABLE,
        "first_arrival": res["fap_stats"],
        "positioning_m": study.summary(),
        "timing_s": res["timing"],
    }


def _fmt(v: Any, nd: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "inf"
    return f"{v:.{nd}f}"


def write_markdown(path: Path, s: dict[str, Any]) -> None:
    lines = [
        f"# diffpos reproduce: scenario `{s['scenario']}`",
        "",
        f"{s['n_receivers']} receivers x {s['n_anchors']} anchors, channel source "
        f"`{s['channel_source']}`, seed {s['seed']}{' (quick subsample)' if s['quick'] else ''}"
        f". Run time {s['timing_s']['total_s']:.1f} s (channels {s['timing_s']['channel_s']:.1f}"
        f" s, positioning {s['timing_s']['positioning_s']:.1f} s).",
        "",
    ]
    if s["mpc_table_pct"] is not None:
        lines += ["## MPC groups (the paper's Table)", "",
                  "| group | P_e [%] | P_e paper [%] | P_fap [%] | P_fap paper [%] |",
                  "| --- | ---: | ---: | ---: | ---: |"]
        for g in ("MPC-1", "MPC-2", "MPC-3", "MPC-4"):
            t, p = s["mpc_table_pct"][g], PAPER_TABLE[g]
            lines.append(f"| {g} | {t['P_e']:.2f} | {p['P_e']:.2f} | {t['P_fap']:.2f} | "
                         f"{p['P_fap']:.2f} |")
        lines.append(f"| none detected | | | {s['mpc_table_pct']['none']['P_fap']:.2f} | |")
        lines.append("")
    if s.get("first_arrival_mechanism_pct"):
        lines += ["First-arriving path by mechanism (emulator slots) [% of links]:", "",
                  "| mechanism | P_fap [%] |", "| --- | ---: |"]
        for lab, v in sorted(s["first_arrival_mechanism_pct"].items(), key=lambda kv: -kv[1]):
            lines.append(f"| `{lab}` | {v:.2f} |")
        lines.append("")
    fa = s["first_arrival"]
    lines += ["## First-arriving path", ""]
    if fa["aoa_deg"]:
        a = fa["aoa_deg"]
        lines.append(f"- AoA (zenith, 90 = horizontal): median {a['median']:.1f} deg, quartiles "
                     f"{a['q1']:.1f}-{a['q3']:.1f}, 5-95% {a['p5']:.1f}-{a['p95']:.1f}; "
                     f"{fa['aoa_within_tolerance_pct']:.1f}% within "
                     f"{fa['aoa_tolerance_deg']:g} deg of 90 (paper: always).")
    if fa["snr_db"]:
        sn = fa["snr_db"]
        lines.append(f"- SNR: median {sn['median']:.1f} dB, quartiles {sn['q1']:.1f} to "
                     f"{sn['q3']:.1f} dB; {fa['snr_above_floor_pct']:.1f}% above "
                     f"{fa['snr_floor_db']:g} dB (paper: typically).")
    lines.append(f"- Links with a detected first arrival: {fa['detected_pct']:.2f}%.")
    lines += ["", "## Positioning error [m]", "",
              "| method | 3D median | 3D 80% | 3D 95% | z median | z 80% | z 95% | solved |",
              "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for v in s["positioning_m"].values():
        solved = v.get("solved_fraction")
        lines.append(
            f"| {v['label']} | {_fmt(v['3d']['median'])} | {_fmt(v['3d']['p80'])} | "
            f"{_fmt(v['3d']['p95'])} | {_fmt(v['z']['median'])} | {_fmt(v['z']['p80'])} | "
            f"{_fmt(v['z']['p95'])} | {'' if solved is None else f'{100 * solved:.1f}%'} |")
    if abs(s["delta_case2_m"] - s["window_height_m"]) < 1e-12:
        lines += ["", f"Note: with Delta = w = {s['window_height_m']:g} m the Case-2 model's "
                  "upper edge sits exactly where the lower edge of the Case-1 model is, so "
                  "D-NLS Case-2 is also the lower-edge diffraction model."]
    lines += ["", "Failed fixes count as infinite errors. The emulator is a simplified "
              "physical model, not the paper's commercial ray tracer; compare mechanisms and "
              "orderings, not exact percentages.", ""]
    path.write_text("\n".join(lines))


def write_figures(out: Path, res: dict[str, Any], delta_m: float) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    study: PositioningStudy = res["study"]
    data: FirstArrivalData = res["data"]
    paths = []
    for kind, errs, bound, blabel, fname in (
        ("3D", study.error_3d_m, study.peb_m, "PEB", "cdf_3d_error.png"),
        ("z-axis", study.error_z_m, study.z_bound_m, "z bound", "cdf_z_error.png"),
    ):
        fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
        for m in study.methods:
            x, f = empirical_cdf(errs[m])
            ax.step(x, f, where="post", color=COLORS.get(m), label=method_label(m, delta_m))
        x, f = empirical_cdf(bound)
        ax.step(x, f, where="post", color="black", ls="--", label=blabel)
        ax.set_xscale("log")
        ax.set_xlim(1e-3, 100)
        ax.set_ylim(0, 1)
        ax.set_xlabel(f"{kind} position error [m]")
        ax.set_ylabel("CDF")
        ax.set_title(f"{kind} positioning, {data.n_nodes} receivers")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
        fig.tight_layout()
        p = out / fname
        fig.savefig(p)
        plt.close(fig)
        paths.append(p)
    det = np.asarray(data.detected)
    m = det.shape[1]
    fig, axes = plt.subplots(1, 2, figsize=(8.8, 4.0), dpi=120)
    labels = [f"anchor {j + 1}" for j in range(m)] + ["all"]
    for ax, arr, ylabel in ((axes[0], data.aoa_deg, "first-arrival AoA (zenith) [deg]"),
                            (axes[1], data.snr_db, "first-arrival SNR [dB]")):
        cols = [np.asarray(arr)[det[:, j], j] for j in range(m)]
        cols.append(np.asarray(arr)[det])
        cols = [c[np.isfinite(c)] for c in cols]
        ax.boxplot(cols, whis=(5, 95), showfliers=False)
        ax.set_xticks(range(1, m + 2), labels, rotation=30, fontsize=8)
        ax.set_ylabel(ylabel)
        ax.grid(True, axis="y", alpha=0.3)
    axes[0].axhspan(84, 96, color="tab:green", alpha=0.12, label="90 +- 6 deg")
    axes[0].legend(fontsize=8)
    axes[1].axhline(5.0, color="tab:red", lw=0.8, ls="--", label="5 dB")
    axes[1].legend(fontsize=8)
    fig.suptitle("First-arriving path (whiskers 5-95 %)")
    fig.tight_layout()
    p = out / "first_arrival_boxplots.png"
    fig.savefig(p)
    plt.close(fig)
    paths.append(p)
    return paths


def _print_report(summary: dict[str, Any], files: list[Path]) -> None:
    from rich.console import Console
    from rich.table import Table

    con = Console()
    if summary["mpc_table_pct"] is not None:
        t = Table(title="MPC groups [%] (emulator vs paper)")
        for c in ("group", "P_e", "paper", "P_fap", "paper "):
            t.add_column(c, justify="right")
        for g in ("MPC-1", "MPC-2", "MPC-3", "MPC-4"):
            v, p = summary["mpc_table_pct"][g], PAPER_TABLE[g]
            t.add_row(g, f"{v['P_e']:.2f}", f"{p['P_e']:.2f}", f"{v['P_fap']:.2f}",
                      f"{p['P_fap']:.2f}")
        con.print(t)
    t = Table(title=f"Position error \\[m], {summary['n_receivers']} receivers")
    for c in ("method", "3D med", "3D 80%", "3D 95%", "z med", "z 80%", "z 95%"):
        t.add_column(c, justify="right")
    for v in summary["positioning_m"].values():
        t.add_row(v["label"], *(_fmt(v[a][k]) for a in ("3d", "z")
                                for k in ("median", "p80", "p95")))
    con.print(t)
    con.print(f"run time {summary['timing_s']['total_s']:.1f} s; wrote "
              + ", ".join(str(f) for f in files), highlight=False, soft_wrap=True)


def run(args: argparse.Namespace) -> int:
    if args.quick_nodes < 10:
        print("diffpos reproduce: --quick-nodes must be >= 10", file=sys.stderr)
        return 2
    try:
        scenario = _load_scenario(args.scenario)
    except ScenarioError as exc:
        print(f"diffpos reproduce: {exc}", file=sys.stderr)
        return 2
    if len(scenario.anchors) < 3:
        print(f"diffpos reproduce: the scenario has {len(scenario.anchors)} anchor(s); at "
              "least 3 are needed for 3D fixes", file=sys.stderr)
        return 2
    if scenario.node_grid is None and not scenario.nodes:
        print("diffpos reproduce: the scenario has no receivers ([nodes.grid] or "
              "[[nodes.list]])", file=sys.stderr)
        return 2
    try:
        res = compute(args, scenario)
    except (ValueError, OSError) as exc:
        print(f"diffpos reproduce: {exc}", file=sys.stderr)
        return 2
    summary = build_summary(args, scenario, res)
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        files = []
        p = args.out / "summary.json"
        p.write_text(json.dumps(_clean(summary), indent=2) + "\n")
        files.append(p)
        p = args.out / "summary.md"
        write_markdown(p, summary)
        files.append(p)
        p = args.out / "first_arrival.npz"
        np.savez_compressed(p, **res["data"].to_arrays())
        files.append(p)
        files += write_figures(args.out, res, args.delta_m)
    except OSError as exc:
        print(f"diffpos reproduce: cannot write to --out {args.out}: {exc}", file=sys.stderr)
        return 1
    _print_report(summary, files)
    return 0
