"""``diffpos reproduce`` outputs: summary.json/md, first_arrival.npz, the CDF and box-plot
figures, the terminal tables and the progress bars."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from diffpos.study import PAPER_TABLE, Reproduction, empirical_cdf, method_label

__all__ = ["ProgressBars", "print_report", "write_figures", "write_markdown", "write_outputs"]

COLORS = {"lls": "tab:red", "ippa": "tab:orange", "dnls_case1": "tab:blue",
          "dnls_case2": "tab:green", "dnls_lower": "tab:purple", "mnls": "tab:brown"}


class ProgressBars:
    """Rich progress bars (or nothing), one task per stage."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.tasks: dict[str, Any] = {}
        self.bar = None
        if enabled:
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


def _fmt(v: Any, nd: int = 2) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "inf"
    return f"{v:.{nd}f}"


def _pct(v: Any) -> str:
    """A share [-] as a percentage; blank where the method has none (the PEB row)."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return f"{100 * v:.1f}%"


def _positioning_lines(s: dict[str, Any]) -> list[str]:
    """summary.md's positioning table, the floor-accuracy definition and the method times."""
    lines = ["## Positioning error [m]", "",
             "| method | 3D median | 3D 80% | 3D 95% | z median | z 80% | z 95% | solved "
             "| right floor | 95% ellipsoid holds truth |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for v in s["positioning_m"].values():
        lines.append(
            f"| {v['label']} | {_fmt(v['3d']['median'])} | {_fmt(v['3d']['p80'])} | "
            f"{_fmt(v['3d']['p95'])} | {_fmt(v['z']['median'])} | {_fmt(v['z']['p80'])} | "
            f"{_fmt(v['z']['p95'])} | {_pct(v.get('solved_fraction'))} | "
            f"{_pct(v.get('floor_accuracy'))} | {_pct(v.get('ellipsoid95_coverage'))} |")
    lines += ["", "*right floor*: share of ALL receivers whose estimate lies on the receiver's "
              "floor (a failed fix is a miss). *95% ellipsoid*: share of the fixes whose "
              "reported covariance's 95 % ellipsoid holds the truth (methods reporting a "
              "covariance)."]
    method_s = s["timing_s"].get("method_s") or {}
    cpu_s = s["timing_s"].get("method_cpu_s") or {}
    n = max(int(s["n_receivers"]), 1)
    times = [f"{s['positioning_m'][m]['label']} {t:.1f} s wall, "
             f"{cpu_s.get(m, math.nan):.1f} s CPU ({1e3 * cpu_s.get(m, math.nan) / n:.2f} ms "
             "CPU per fix)"
             for m, t in method_s.items() if m in s["positioning_m"] and m != "peb"]
    if times:
        lines += ["", "Time per method: " + "; ".join(times) + "."]
    return lines


def write_markdown(path: Path, s: dict[str, Any]) -> None:
    """summary.md: the tables, with the paper's numbers side by side."""
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
    lines += ["", *_positioning_lines(s)]
    if abs(s["delta_case2_m"] - s["window_height_m"]) < 1e-12:
        lines += ["", f"Note: with Delta = w = {s['window_height_m']:g} m the Case-2 model's "
                  "upper edge sits exactly where the lower edge of the Case-1 model is, so "
                  "D-NLS Case-2 is also the lower-edge diffraction model."]
    lines += ["", "Failed fixes count as infinite errors. The emulator is a simplified "
              "physical model, not the paper's commercial ray tracer; compare mechanisms and "
              "orderings, not exact percentages.", ""]
    path.write_text("\n".join(lines))


def write_figures(out: Path, res: Reproduction, delta_m: float) -> list[Path]:
    """cdf_3d_error.png, cdf_z_error.png and first_arrival_boxplots.png; their paths.

    The CDF legends give each method's floor accuracy (share of all receivers on the right
    floor)."""
    study, data = res.study, res.data
    paths = []
    for kind, errs, bound, blabel, fname in (
        ("3D", study.error_3d_m, study.peb_m, "PEB", "cdf_3d_error.png"),
        ("z-axis", study.error_z_m, study.z_bound_m, "z bound", "cdf_z_error.png"),
    ):
        fig = Figure(figsize=(6.4, 4.4), dpi=120)
        ax = fig.subplots()
        floor = study.extra.get("floor_accuracy", {})
        for m in study.methods:
            x, f = empirical_cdf(errs[m])
            label = method_label(m, delta_m)
            if m in floor:
                label += f", {_pct(floor[m])} right floor"
            ax.step(x, f, where="post", color=COLORS.get(m), label=label)
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
        paths.append(p)
    det = np.asarray(data.detected)
    m = det.shape[1]
    fig = Figure(figsize=(8.8, 4.0), dpi=120)
    axes = fig.subplots(1, 2)
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
    paths.append(p)
    return paths


def write_outputs(out: Path, summary: dict[str, Any], res: Reproduction, delta_m: float
                  ) -> list[Path]:
    """Every output file in ``out`` (created); their paths, in the order they are written."""
    out.mkdir(parents=True, exist_ok=True)
    files = []
    p = out / "summary.json"
    p.write_text(json.dumps(_clean(summary), indent=2) + "\n")
    files.append(p)
    p = out / "summary.md"
    write_markdown(p, summary)
    files.append(p)
    p = out / "first_arrival.npz"
    np.savez_compressed(p, **res.data.to_arrays())
    files.append(p)
    files += write_figures(out, res, delta_m)
    return files


def print_report(summary: dict[str, Any], files: list[Path]) -> None:
    """The MPC table and the positioning errors on the terminal, and the files written."""
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
    for c in ("method", "3D\nmed", "3D\np80", "3D\np95", "z\nmed", "z\np80", "z\np95",
              "right\nfloor", "ell.\n95%"):
        t.add_column(c, justify="left" if c == "method" else "right", no_wrap=True)
    for key, v in summary["positioning_m"].items():
        # the method key (what --methods takes) keeps the table within 80 columns
        t.add_row(key, *(_fmt(v[a][k]) for a in ("3d", "z") for k in ("median", "p80", "p95")),
                  _pct(v.get("floor_accuracy")), _pct(v.get("ellipsoid95_coverage")))
    con.print(t)
    con.print("right floor: share of all receivers on the right floor (a failed fix is a "
              "miss); ell. 95%: share of fixes whose 95 % ellipsoid holds the truth; method "
              "keys as --methods takes them", highlight=False)
    con.print(f"run time {summary['timing_s']['total_s']:.1f} s; wrote "
              + ", ".join(str(f) for f in files), highlight=False, soft_wrap=True)
