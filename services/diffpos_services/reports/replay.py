"""Plots of ``diffpos replay``: the error CDFs (``cdf.png``)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

if TYPE_CHECKING:  # reports draw results; they do not depend on the services that make them
    from diffpos_services.replay.run import ReplayResult

__all__ = ["CUT_FACTOR", "cdf_figure", "plot_cdf", "x_limit"]


def _denominator(node_epochs: dict | None, n_fixes: int) -> tuple[int, str]:
    """The CDF's denominator: every scored node-epoch (a miss is an infinite error, so the
    curve ends at the share of node-epochs with a fix), or the fixes without node-epochs."""
    n = int((node_epochs or {}).get("node_epochs") or 0)
    if n >= n_fixes and n > 0:
        return n, "node-epochs"
    return n_fixes, "fixes"


#: The x axis ends at the worst error unless that is more than this many times the 99th
#: percentile (one far outlier would squeeze the curves): then it ends at the percentile and
#: the plot says where it cut and what the worst error is.
CUT_FACTOR = 3.0


def x_limit(arrays: list[np.ndarray], worst: float | None = None) -> tuple[float, float, int]:
    """``(x_max, worst, beyond)``: the axis end, the worst error and the errors beyond the
    axis end (0: the axis shows every error) over the non-empty ``arrays`` [m]; ``worst``: the
    exact worst error when the arrays are a summary's (bucket centres, within 0.5 %)."""
    vals = [np.abs(a) for a in arrays if a is not None and a.size]
    if not vals:
        return 1.0, 0.0, 0
    allv = np.concatenate(vals)
    worst = max(float(allv.max()), worst or 0.0)
    p99 = float(np.percentile(allv, 99))
    if worst <= CUT_FACTOR * p99 or p99 <= 0:
        return (worst * 1.05 if worst > 0 else 1.0), worst, 0
    x_max = p99 * 1.2
    return x_max, worst, int((allv > x_max).sum())


def _worst(rep: dict) -> float | None:
    """The exact worst 3D and z error of the report's streams (``None``: none)."""
    vals = [v for acc in (rep.get("accuracy"), (rep.get("live") or {}).get("accuracy")) if acc
            for k in ("error_3d_m", "error_z_m")
            if (v := (acc.get("overall", {}).get(k) or {}).get("max")) is not None]
    return max(vals) if vals else None


def _fixes(accuracy: dict | None) -> tuple[int, int]:
    """``(scored, without a position)`` fixes of a stream's overall accuracy."""
    o = (accuracy or {}).get("overall") or {}
    return int(o.get("evaluated") or 0), int(o.get("without_position") or 0)


def _curves(result: ReplayResult) -> list[tuple]:
    """``(errors, label, colour, line style, node-epochs, (scored, without a position))`` of
    every curve: 3D and |z|, replayed and (when recorded) live."""
    rep = result.report
    method = rep.get("method", "dnls").upper().replace("DNLS", "D-NLS")
    live = rep.get("live") or {}
    mine = (rep.get("node_epochs"), _fixes(rep.get("accuracy")))
    curves = [(result.errors.get("e3"), f"3D, replay ({method})", "C0", "-", *mine),
              (result.errors.get("ez"), f"|z|, replay ({method})", "C1", "-", *mine)]
    if live.get("fixes"):
        theirs = (live.get("node_epochs"), _fixes(live.get("accuracy")))
        curves += [(result.live_errors.get("e3"), "3D, recorded live", "C0", "--", *theirs),
                   (result.live_errors.get("ez"), "|z|, recorded live", "C1", "--", *theirs)]
    return curves


def _title(rep: dict, title: str | None) -> str:
    if title:
        return title
    name = Path(rep["file"]).name
    name = name if len(name) <= 40 else name[:18] + "..." + name[-19:]
    what_if = rep.get("what_if") or "none (the recorded settings)"
    what_if = what_if if len(what_if) <= 70 else what_if[:67] + "..."
    win = rep.get("window")
    span = "" if not win else (f"; {0 if win['start_s'] is None else win['start_s']:g}-"
                               f"{'end' if win['end_s'] is None else format(win['end_s'], 'g')} s")
    d = rep.get("dropped") or {}
    lost = [f"anchor {a}" for a in d.get("anchors") or {}] + [f"node {n}" for n in
                                                              d.get("nodes") or {}]
    lost_s = "" if not lost else ("; LOST " + ", ".join(lost[:4])
                                  + (f" +{len(lost) - 4}" if len(lost) > 4 else ""))
    return f"Error CDF - {name}{span}\nwhat-if: {what_if}{lost_s}"


def cdf_figure(result: ReplayResult, *, title: str | None = None) -> Figure:
    """Empirical CDFs of the 3D and z errors (replayed, and recorded-live when present) over
    every fix, a fix without a position (no track yet, lost, failed) counting as an infinite
    error, or over every node-epoch when there are more of those (a node-epoch without a fix
    counts likewise): a curve ends at the share that had a position (said on the plot, with
    n). The title names the recording, the time window and the what-if (``title``: instead);
    the x axis shows the worst error, or says where it cut it (:func:`x_limit`)."""
    fig = Figure(figsize=(6.4, 4.4), dpi=120)  # no pyplot: no global backend or figure state
    ax = fig.subplots()
    drawn, unit = [], "fixes"
    for arr, label, color, ls, ne, (scored, no_pos) in _curves(result):
        if arr is None or arr.size == 0:
            continue
        x = np.sort(np.abs(arr))
        n, unit = _denominator(ne, max(scored, x.size) + no_pos)
        ax.step(x, np.arange(1, x.size + 1) / n, where="post", color=color, linestyle=ls,
                label=f"{label}: {x.size} with a position / {n} {unit}")
        drawn.append(x)
    x_max, worst, beyond = x_limit(drawn, _worst(result.report))
    ax.set_xlim(0, x_max)
    ax.set_ylim(0, 1)
    ax.set_xlabel("error [m]" + (f"  (axis cut at {x_max:.2f} m: worst error {worst:.2f} m, "
                                 f"{beyond} errors beyond)" if beyond else
                                 f"  (worst error {worst:.2f} m)" if drawn else ""))
    ax.set_ylabel(f"share of {unit}")
    ax.grid(True, alpha=0.3)
    ax.set_title(_title(result.report, title), fontsize=9)
    note = ("over every node-epoch after the first 2 s; a node-epoch without a fix"
            if unit == "node-epochs" else "over every fix; a fix without a position")
    ax.text(0.98, 0.3, f"{note}\ncounts as an infinite error (the curve ends at the share "
            "with a position)", transform=ax.transAxes, ha="right", va="bottom", fontsize=7,
            color="0.3")
    if drawn:
        ax.legend(loc="lower right", fontsize=7)
    else:
        ax.text(0.5, 0.5, "no fixes with ground truth to evaluate", ha="center",
                transform=ax.transAxes)
    fig.tight_layout()
    return fig


def plot_cdf(result: ReplayResult, path: str | Path, *, title: str | None = None) -> Path:
    """Write :func:`cdf_figure` of ``result`` to the PNG ``path``."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    cdf_figure(result, title=title).savefig(out)
    return out
