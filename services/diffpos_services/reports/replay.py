"""Plots of ``diffpos replay``: the error CDFs (``cdf.png``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

if TYPE_CHECKING:  # reports draw results; they do not depend on the services that make them
    from diffpos_services.recording.replay import ReplayResult

__all__ = ["plot_cdf"]


def plot_cdf(result: ReplayResult, path: str | Path, *, title: str | None = None) -> Path:
    """Empirical CDFs of the 3D and z errors (replayed, and recorded-live when present).

    Parameters
    ----------
    result : ReplayResult
    path : path
        PNG to write.
    title : str, optional
        Default: ``Positioning error CDF - <recording file name>``.
    """
    fig = Figure(figsize=(6.4, 4.2), dpi=120)  # no pyplot: no global backend or figure state
    ax = fig.subplots()
    method = result.report.get("method", "dnls").upper().replace("DNLS", "D-NLS")
    curves = [
        (result.errors.get("e3"), f"3D error, replay ({method})", "C0", "-"),
        (result.errors.get("ez"), f"z error, replay ({method})", "C1", "-"),
    ]
    if result.live_estimates:
        curves += [
            (result.live_errors.get("e3"), "3D error, recorded live", "C0", "--"),
            (result.live_errors.get("ez"), "z error, recorded live", "C1", "--"),
        ]
    xmax = 0.0
    for arr, label, color, ls in curves:
        if arr is None or arr.size == 0:
            continue
        x = np.sort(arr)
        y = np.arange(1, x.size + 1) / x.size
        ax.step(x, y, where="post", label=f"{label} (n={x.size})", color=color, linestyle=ls)
        xmax = max(xmax, float(np.percentile(x, 99)))
    ax.set_xlim(0, xmax * 1.05 if xmax > 0 else 1.0)
    ax.set_ylim(0, 1)
    ax.set_xlabel("error [m]")
    ax.set_ylabel("CDF")
    ax.grid(True, alpha=0.3)
    ax.set_title(title or f"Positioning error CDF - {Path(result.report['file']).name}")
    if xmax > 0:
        ax.legend(loc="lower right", fontsize=8)
    else:
        ax.text(
            0.5, 0.5, "no fixes with ground truth to evaluate", ha="center", transform=ax.transAxes
        )
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    return out
