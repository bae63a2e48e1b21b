"""``diffpos bounds`` outputs: the per-floor tables (rich), bounds.csv and the heat maps."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from rich.console import Console
from rich.table import Table

from diffpos.bound_maps import BoundMapSettings, FloorResult
from diffpos.channel.linkbudget import noise_floor_dbm
from diffpos.scenario import Scenario

__all__ = ["plot_floor", "print_summary", "write_csv"]


def _stats(values: np.ndarray, ok: np.ndarray) -> list[float]:
    v = values[ok]
    if v.size == 0:
        return [math.inf] * 4
    return [float(np.median(v)), *np.percentile(v, [80, 95]).tolist(), float(v.max())]


def _fmt(v: float, scale: float) -> str:
    return f"{v * scale:.3g}" if math.isfinite(v) else "inf"


def _link_line(scenario: Scenario, settings: BoundMapSettings, results: list[FloorResult]) -> str:
    radio = scenario.radio
    n0 = float(noise_floor_dbm(radio.bandwidth_hz, temperature_k=radio.noise_temperature_k))
    all_snr = np.concatenate([r.snr_db.ravel() for r in results])
    return (
        f"{len(scenario.anchors)} anchors, {settings.model} model, kTB = {n0:.1f} dBm, link SNR "
        f"{all_snr.min():.1f} .. {all_snr.max():.1f} dB (incl. {radio.processing_gain_db:g} dB "
        "processing gain, "
        + (
            f"{settings.diffraction_loss_db:g} dB diffraction loss)"
            if settings.diffraction == "fixed"
            else "UTD upper-edge diffraction, x polarisation)"
        )
    )


def _tables(results: list[FloorResult]) -> tuple[Table, Table]:
    stats = [
        (r, _stats(r.peb_m, r.identifiable), _stats(r.z_bound_m, r.identifiable)) for r in results
    ]
    finite = [v for _, p, z in stats for v in (*p, *z) if math.isfinite(v)]
    unit, scale = ("cm", 100.0) if finite and max(finite) < 1.0 else ("m", 1.0)
    t_peb = Table(title=f"Position error bound per floor in {unit} (identifiable nodes)")
    t_z = Table(title=f"z-axis bound per floor in {unit} (identifiable nodes)")
    for col in ("floor", "z_n (m)", "nodes", "non-ident."):
        t_peb.add_column(col, justify="right")
    t_z.add_column("floor", justify="right")
    for q in ("median", "80 %", "95 %", "max"):
        t_peb.add_column(q, justify="right")
        t_z.add_column(q, justify="right")
    for r, p, z in stats:
        bad = 1.0 - r.identifiable.mean()
        t_peb.add_row(
            str(r.floor),
            f"{r.z_m:g}",
            str(r.identifiable.size),
            f"{100 * bad:.1f} %" if bad else "0",
            *(_fmt(v, scale) for v in p),
        )
        t_z.add_row(str(r.floor), *(_fmt(v, scale) for v in z))
    return t_peb, t_z


def print_summary(
    console: Console,
    scenario: Scenario,
    settings: BoundMapSettings,
    results: list[FloorResult],
    explanations: list[str],
) -> None:
    """The link-budget line, the PEB and z-bound tables per floor and the explanations."""
    console.print(_link_line(scenario, settings, results), highlight=False)
    for table in _tables(results):
        console.print(table)
    for line in explanations:
        console.print(line, highlight=False)


def write_csv(path: Path, results: list[FloorResult], n_anchors: int) -> None:
    """bounds.csv: one row per node (floor, position, bounds, identifiable, SNR and sigma)."""
    header = ["floor", "x_m", "y_m", "z_m", "peb_m", "x_bound_m", "y_bound_m", "z_bound_m"]
    header += ["identifiable"]
    header += [f"snr_db_a{j + 1}" for j in range(n_anchors)]
    header += [f"sigma_m_a{j + 1}" for j in range(n_anchors)]
    fmt = ["{:d}", "{:.3f}", "{:.3f}", "{:.3f}"] + ["{:.6g}"] * 4 + ["{:d}"]
    fmt += ["{:.2f}"] * n_anchors + ["{:.6g}"] * n_anchors
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r in results:
            xx, yy = np.meshgrid(r.x_m, r.y_m)
            n = xx.size
            cols = [
                np.full(n, r.floor),
                xx.ravel(),
                yy.ravel(),
                np.full(n, r.z_m),
                r.peb_m.ravel(),
                *r.axis_bounds_m.reshape(n, 3).T,
                r.identifiable.ravel().astype(int),
                *r.snr_db.reshape(n, -1).T,
                *r.sigma_m.reshape(n, -1).T,
            ]
            for row in zip(*cols, strict=True):
                w.writerow(
                    [f.format(int(v) if f == "{:d}" else v) for f, v in zip(fmt, row, strict=True)]
                )


def plot_floor(
    path: Path, r: FloorResult, scenario: Scenario, settings: BoundMapSettings
) -> None:
    """floor<k>.png: PEB and z-bound heat maps of one floor, top view, anchors marked."""
    anchors = scenario.anchor_positions_m()
    radio, w = scenario.radio, scenario.building.window_height_m
    fig = Figure(figsize=(13, 5.2), constrained_layout=True)
    axes = fig.subplots(1, 2)
    step = settings.grid_step_m
    extent = (r.x_m[0] - step / 2, r.x_m[-1] + step / 2, r.y_m[0] - step / 2, r.y_m[-1] + step / 2)
    for ax, data, title in (
        (axes[0], r.peb_m, "PEB"),
        (axes[1], r.z_bound_m, "z-axis bound"),
    ):
        finite = np.where(np.isfinite(data), data, np.nan)
        cmap = colormaps["viridis"].with_extremes(bad="0.6")
        vals = finite[np.isfinite(finite)]
        norm = LogNorm(vmin=vals.min(), vmax=vals.max()) if vals.size and vals.min() > 0 else None
        im = ax.imshow(finite, origin="lower", extent=extent, cmap=cmap, norm=norm, aspect="equal")
        fig.colorbar(im, ax=ax, label=f"{title} [m]", shrink=0.85)
        ax.plot(anchors[:, 0], anchors[:, 1], "r^", ms=9, label="anchors (UAV)")
        for j, a in enumerate(anchors, start=1):
            ax.annotate(
                f"A{j} z={a[2]:g}", a[:2], textcoords="offset points", xytext=(4, 4), fontsize=8
            )
        ax.axhline(0.0, color="k", lw=1.5)
        ax.set_xlabel("x [m] (along the window edges)")
        ax.set_ylabel("y [m] (into the building)")
        ax.set_ylim(min(anchors[:, 1].min() - 2, -1), extent[3] + 0.5)
        n_bad = int(np.count_nonzero(~r.identifiable))
        ax.set_title(
            f"{title}, floor {r.floor} (nodes at z = {r.z_m:g} m)"
            + (f"; {n_bad} non-identifiable (grey)" if n_bad else "")
        )
        ax.legend(loc="lower center", fontsize=8)
    fig.suptitle(
        f"{settings.model} model, B = {radio.bandwidth_hz / 1e6:g} MHz, "
        f"P_tx = {radio.tx_power_dbm:g} dBm, f = {radio.frequency_hz / 1e9:g} GHz, w = {w:g} m"
    )
    fig.savefig(path, dpi=110)
