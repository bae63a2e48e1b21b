"""Plots of ``diffpos replay``: the error CDFs (``cdf.png``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

if TYPE_CHECKING:  # reports draw results; they do not depend on the services that make them
    from diffpos_services.replay.run import ReplayResult

__all__ = ["plot_cdf"]


def _denominator(node_epochs: dict | None, n_fixes: int) -> tuple[int, str]:
    """The CDF's denominator: every scored node-epoch (a miss is an infinite error, so the
    curve ends at the share of node-epochs with a fix), or the fixes without node-epochs."""
    n = int((node_epochs or {}).get("node_epochs") or 0)
    if n >= n_fixes and n > 0:
        return n, "node-epochs"
    return n_fixes, "fixes"


def plot_cdf(result: ReplayResult, path: str | Path, *, title: str | None = None) -> Path:
    """Empirical CDFs of the 3D and z errors (replayed, and recorded-live when present) over
    every node-epoch of the run: a node-epoch without a fix counts as an infinite error, so a
    curve ends at the share of node-epochs that got a fix (said on the plot, with n).

    Parameters
    ----------
    result : ReplayResult
    path : path
        PNG to write.
    title : str, optional
        Default: ``Error CDF - <recording file name>`` (cut to fit).
    """
    fig = Figure(figsize=(6.4, 4.4), dpi=120)  # no pyplot: no global backend or figure state
    ax = fig.subplots()
    method = result.report.get("method", "dnls").upper().replace("DNLS", "D-NLS")
    live_ne = (result.report.get("live") or {}).get("node_epochs")
    curves = [
        (result.errors.get("e3"), f"3D, replay ({method})", "C0", "-",
         result.report.get("node_epochs")),
        (result.errors.get("ez"), f"|z|, replay ({method})", "C1", "-",
         result.report.get("node_epochs")),
    ]
    if (result.report.get("live") or {}).get("fixes"):
        curves += [
            (result.live_errors.get("e3"), "3D, recorded live", "C0", "--", live_ne),
            (result.live_errors.get("ez"), "|z|, recorded live", "C1", "--", live_ne),
        ]
    xmax, unit = 0.0, "fixes"
    for arr, label, color, ls, ne in curves:
        if arr is None or arr.size == 0:
            continue
        x = np.sort(np.abs(arr))
        n, unit = _denominator(ne, x.size)
        y = np.arange(1, x.size + 1) / n
        ax.step(x, y, where="post", color=color, linestyle=ls,
                label=f"{label}: {x.size} fixes / {n} {unit}")
        xmax = max(xmax, float(np.percentile(x, 99)))
    ax.set_xlim(0, xmax * 1.05 if xmax > 0 else 1.0)
    ax.set_ylim(0, 1)
    ax.set_xlabel("error [m]")
    ax.set_ylabel(f"share of {unit}")
    ax.grid(True, alpha=0.3)
    name = Path(result.report["file"]).name
    name = name if len(name) <= 40 else name[:18] + "..." + name[-19:]
    ax.set_title(title or f"Error CDF - {name}", fontsize=10)
    if unit == "node-epochs":
        ax.text(0.01, 0.99, "over every node-epoch after the first 2 s; a node-epoch without "
                "a fix\ncounts as an infinite error (the curve ends at the availability)",
                transform=ax.transAxes, va="top", fontsize=7, color="0.3")
    if xmax > 0:
        ax.legend(loc="lower right", fontsize=7)
    else:
        ax.text(
            0.5, 0.5, "no fixes with ground truth to evaluate", ha="center", transform=ax.transAxes
        )
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    return out
