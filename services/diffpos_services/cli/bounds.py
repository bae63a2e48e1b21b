"""PEB and z-axis bound over a grid of indoor nodes, heat maps per floor

Computes, for every node of a grid on every floor, the Cramer-Rao bounds of the paper's
diffraction positioning: the position error bound PEB = sqrt(tr J^-1) [m] and the z-axis
bound sqrt([J^-1]_zz) [m], where J is the Fisher information of the ranges to all anchors
under the window-edge diffraction path model (upper edge, paper eq. 6 and eq. 15).

How each link's ranging accuracy is obtained (a simple link budget):
  P_rx   = P_tx + Friis gain over the diffraction path length (OPL + IPL) at the carrier
           - a fixed diffraction loss (default 20 dB); or, with --diffraction utd, the power
           of the UTD-diffracted field of the upper window edge (x-polarised isotropic anchor,
           about 30-42 dB below free space at 28 GHz in the default geometry)
  SNR    = P_rx + processing gain (20 dB) - kTB   (kTB = -87.8 dBm at 400 MHz, 300 K)
  sigma  = c / sqrt(8 pi^2 B^2 SNR)               (ranging CRLB, SNR linear)

Default scenario (the paper's, where it is specified): anchors (-15,-20,1), (0,-15,0),
(0,-7,4), (15,-20,1) m (the paper prints (0,15,0) for anchor 2, which would be inside the
building; anchors fly outside, y < 0); 28 GHz carrier, 400 MHz bandwidth, 30 dBm transmit
power; building 40 m wide (window edges span x in [-20, 20]) and 20 m deep, 5 floors of 3 m
whose floor slabs are at z = 3, 6, 9, 12, 15 m; nodes at mid-floor height (z = 4.5, 7.5,
... 16.5 m), which is also the window centre (Assumption 1, Case-1), window height 1.5 m.

A node is "non-identifiable" when its FIM is singular or its condition number exceeds
1e12 (Theorem 2): the bounds are then infinite, shown grey in the maps and counted apart;
the statistics are over the identifiable nodes.

Outputs (in --out): bounds.csv (one row per node: floor, x, y, z, PEB, x/y/z bounds,
identifiable, per-anchor SNR and sigma) and floor<k>.png (PEB and z-bound heat maps,
top view, anchors marked).

examples:
  diffpos bounds                                  the paper's geometry, 0.5 m grid
  diffpos bounds --grid-step-m 2 --out /tmp/b     coarse and fast
  diffpos bounds --anchors "-10,-5,2;0,-8,1;10,-5,2" --tx-power-dbm 20
  diffpos bounds --diffraction utd                diffracted power from UTD, not a fixed loss
  diffpos bounds --anchors "0,-20,1;0,-15,0;0,-7,4"   the paper's x_a = 0 counter-example:
                                                  nodes at x = 0 are not identifiable
"""

from __future__ import annotations

import argparse
import csv
import math
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from diffpos.bounds import (
    DEFAULT_MAX_CONDITION,
    identifiability,
    path_jacobian,
    position_error_bound,
)
from diffpos.geometry import window_edge_path
from diffpos.linkbudget import (
    db_to_linear,
    free_space_path_gain_db,
    noise_floor_dbm,
    ranging_crlb_m,
    snr_db,
)
from diffpos_services.kit import ConfigError

PAPER_ANCHORS_M: tuple[tuple[float, float, float], ...] = (
    (-15.0, -20.0, 1.0),
    (0.0, -15.0, 0.0),
    (0.0, -7.0, 4.0),
    (15.0, -20.0, 1.0),
)


@dataclass(frozen=True)
class BoundsConfig:
    """Everything ``diffpos bounds`` needs; one place to swap in a scenario file later.

    Attributes
    ----------
    anchors_m : tuple of (x, y, z) [m]
        Anchor positions, outside the building (``y < 0``).
    frequency_hz : float [Hz]
        Carrier (for the Friis gain).
    bandwidth_hz : float [Hz]
        Signal bandwidth (noise floor and ranging CRLB).
    tx_power_dbm : float [dBm]
    diffraction_loss_db : float [dB]
        Fixed extra loss of the diffracted path relative to free space (``diffraction="fixed"``).
    diffraction : {"fixed", "utd"}
        How the diffracted power is obtained: Friis over the path length minus
        ``diffraction_loss_db``, or the UTD field of the upper window edge for x-polarised
        isotropic anchors (:func:`diffpos.gtd.window_edge_fields`).
    processing_gain_db : float [dB]
    temperature_k : float [K]
    window_height_m : float [m]
        ``w``; the upper edge is ``w/2`` above the node (Case-1).
    delta_m : float [m]
        Case-2 offset of the model (0 = Assumption 1).
    width_m, depth_m : float [m]
        Building extent: ``x`` in ``[-width/2, width/2]`` (also the window-edge extent),
        ``y`` in ``[0, depth]``.
    n_floors : int
    floor_height_m : float [m]
    first_floor_z_m : float [m]
        Height of the lowest floor slab; floor ``k`` (1-based) has its slab at
        ``first_floor_z_m + (k - 1) floor_height_m`` and its nodes half a floor above it.
    grid_step_m : float [m]
        Node grid spacing: ``x = k * step`` (symmetric about and including ``x = 0``) and
        ``y = y_min_m + k * step``, at least half a step inside the walls.
    y_min_m : float [m]
        Distance of the first grid row behind the facade.
    """

    anchors_m: tuple[tuple[float, float, float], ...] = PAPER_ANCHORS_M
    frequency_hz: float = 28e9
    bandwidth_hz: float = 400e6
    tx_power_dbm: float = 30.0
    diffraction_loss_db: float = 20.0
    processing_gain_db: float = 20.0
    temperature_k: float = 300.0
    window_height_m: float = 1.5
    delta_m: float = 0.0
    width_m: float = 40.0
    depth_m: float = 20.0
    n_floors: int = 5
    floor_height_m: float = 3.0
    first_floor_z_m: float = 3.0
    grid_step_m: float = 0.5
    y_min_m: float = 0.5
    model: str = "diffraction"
    diffraction: str = "fixed"
    max_condition: float = DEFAULT_MAX_CONDITION

    def node_height_m(self, floor: int) -> float:
        """Mid-floor node height of floor ``floor`` (1-based) [m]."""
        return self.first_floor_z_m + (floor - 0.5) * self.floor_height_m

    def grid_xy_m(self) -> tuple[np.ndarray, np.ndarray]:
        """Grid coordinates ``(x, y)`` of the nodes of one floor [m]."""
        step = self.grid_step_m
        k = np.floor((0.5 * self.width_m - 0.5 * step) / step + 1e-9)
        x = np.arange(-k, k + 1) * step
        n_y = np.floor((self.depth_m - 0.5 * step - self.y_min_m) / step + 1e-9)
        y = self.y_min_m + np.arange(n_y + 1) * step
        return x, y


def _check_range(name: str, value: float, lo: float, hi: float, *, lo_open=True) -> None:
    ok = (value > lo if lo_open else value >= lo) and value <= hi and math.isfinite(value)
    if not ok:
        bracket = "(" if lo_open else "["
        raise ConfigError(f"{name}: {value:g} is out of range; allowed {bracket}{lo:g}, {hi:g}]")


def validate(cfg: BoundsConfig) -> BoundsConfig:
    """Check a configuration; raise :class:`ConfigError` naming the option."""
    if len(cfg.anchors_m) < 3:
        raise ConfigError(
            f"--anchors: {len(cfg.anchors_m)} anchor(s) given; 3D positioning needs at least 3 "
            "(paper, Corollary 3)"
        )
    for i, a in enumerate(cfg.anchors_m, start=1):
        if len(a) != 3 or not all(math.isfinite(v) for v in a):
            raise ConfigError(f"--anchors: anchor {i} must be three finite numbers x,y,z [m]")
        if a[1] >= 0.0:
            raise ConfigError(
                f"--anchors: anchor {i} ({a[0]:g},{a[1]:g},{a[2]:g}) has y = {a[1]:g} >= 0, which "
                "is inside the building; anchors fly outside, in front of the facade (y < 0)"
            )
    _check_range("--grid-step-m", cfg.grid_step_m, 0.05, min(cfg.width_m, cfg.depth_m) / 2)
    _check_range("--window-height-m", cfg.window_height_m, 0.0, cfg.floor_height_m)
    _check_range("--bandwidth-hz", cfg.bandwidth_hz, 1e3, 1e11)
    _check_range("--frequency-hz", cfg.frequency_hz, 1e6, 1e12)
    _check_range("--tx-power-dbm", cfg.tx_power_dbm, -60.0, 80.0, lo_open=False)
    _check_range("--diffraction-loss-db", cfg.diffraction_loss_db, 0.0, 100.0, lo_open=False)
    _check_range("--floors", cfg.n_floors, 0, 200)
    if cfg.diffraction not in ("fixed", "utd"):
        raise ConfigError(f"--diffraction: {cfg.diffraction!r}; allowed 'fixed' or 'utd'")
    if cfg.model not in ("diffraction", "los"):
        raise ConfigError(f"--model: {cfg.model!r}; allowed 'diffraction' or 'los'")
    n_nodes = cfg.n_floors * np.prod([len(v) for v in cfg.grid_xy_m()])
    if n_nodes > 5_000_000:
        raise ConfigError(f"--grid-step-m: {cfg.grid_step_m:g} m gives {n_nodes} nodes; max 5e6")
    return cfg


def parse_anchors(text: str) -> tuple[tuple[float, float, float], ...]:
    """``"x,y,z;x,y,z;..."`` [m] -> tuple of triples; :class:`ConfigError` names the bad one."""
    anchors = []
    for i, part in enumerate(p for p in text.split(";") if p.strip()):
        fields = part.split(",")
        try:
            xyz = tuple(float(f) for f in fields)
        except ValueError:
            xyz = ()
        if len(xyz) != 3:
            raise ConfigError(
                f"--anchors: anchor {i + 1} is {part.strip()!r}; expected three numbers 'x,y,z' in "
                "metres, anchors separated by ';' (e.g. \"-15,-20,1;0,-15,0;15,-20,1\")"
            )
        anchors.append(xyz)
    return tuple(anchors)


@dataclass(frozen=True)
class FloorResult:
    """Bounds of one floor's grid (arrays of shape (ny, nx) unless noted)."""

    floor: int
    z_m: float
    x_m: np.ndarray  # (nx,)
    y_m: np.ndarray  # (ny,)
    peb_m: np.ndarray
    z_bound_m: np.ndarray
    axis_bounds_m: np.ndarray  # (ny, nx, 3)
    identifiable: np.ndarray
    snr_db: np.ndarray  # (ny, nx, M)
    sigma_m: np.ndarray  # (ny, nx, M)


def path_gain_db(
    cfg: BoundsConfig, anchors: np.ndarray, nodes: np.ndarray, length_m: np.ndarray
) -> np.ndarray:
    """Gain of the upper-edge diffracted path [dB], shape of ``length_m`` (nodes x anchors).

    ``fixed``: Friis over the unfolded length minus ``diffraction_loss_db``. ``utd``: an
    isotropic x-polarised source with field 1 V/m at 1 m has Friis gain
    ``(lambda / 4 pi)^2 |E|^2`` at a point where its field is ``E``; ``E`` is the UTD field of the
    upper edge (Theorem 3: it dominates for x polarisation).
    """
    if cfg.diffraction == "fixed":
        return free_space_path_gain_db(length_m, cfg.frequency_hz) - cfg.diffraction_loss_db
    from diffpos.constants import SPEED_OF_LIGHT_M_S
    from diffpos.gtd import window_edge_fields

    half = 0.5 * cfg.width_m
    e_up, _ = window_edge_fields(
        anchors,
        nodes[..., None, :],
        window_height_m=cfg.window_height_m,
        delta_m=cfg.delta_m,
        e0=(1.0, 0.0, 0.0),
        frequency_hz=cfg.frequency_hz,
        edge_x_m=(-half, half),
        coefficients="utd",
    )
    lam = SPEED_OF_LIGHT_M_S / cfg.frequency_hz
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(lam / (4.0 * np.pi)) + 20.0 * np.log10(np.linalg.norm(e_up, axis=-1))


def compute(cfg: BoundsConfig) -> list[FloorResult]:
    """Bounds for every floor of the grid (vectorised over the nodes of a floor)."""
    anchors = np.asarray(cfg.anchors_m, dtype=np.float64)
    x, y = cfg.grid_xy_m()
    xx, yy = np.meshgrid(x, y)  # the same grid on every floor
    half = 0.5 * cfg.width_m
    out = []
    for k in range(1, cfg.n_floors + 1):
        z = cfg.node_height_m(k)
        nodes = np.stack([xx, yy, np.full_like(xx, z)], axis=-1)  # (ny, nx, 3)
        path = window_edge_path(
            anchors,
            nodes[..., None, :],
            window_height_m=cfg.window_height_m,
            delta_m=cfg.delta_m,
            edge_x_m=(-half, half),
        )
        p_rx = cfg.tx_power_dbm + path_gain_db(cfg, anchors, nodes, path.length_m)
        snr = snr_db(
            p_rx,
            bandwidth_hz=cfg.bandwidth_hz,
            processing_gain_db=cfg.processing_gain_db,
            temperature_k=cfg.temperature_k,
        )
        sigma = ranging_crlb_m(db_to_linear(snr), cfg.bandwidth_hz)
        b = position_error_bound(
            anchors,
            nodes,
            sigma,
            cfg.window_height_m,
            cfg.delta_m,
            model=cfg.model,
            edge_x_m=(-half, half),
            max_condition=cfg.max_condition,
        )
        out.append(
            FloorResult(
                floor=k,
                z_m=z,
                x_m=x,
                y_m=y,
                peb_m=b.peb_m,
                z_bound_m=b.z_bound_m,
                axis_bounds_m=b.axis_bounds_m,
                identifiable=b.identifiable,
                snr_db=snr,
                sigma_m=sigma,
            )
        )
    return out


def explain_non_identifiable(cfg: BoundsConfig, results: list[FloorResult]) -> list[str]:
    """Why nodes are not identifiable: one line per floor that has any (the first node)."""
    lines = []
    anchors = np.asarray(cfg.anchors_m)
    half = 0.5 * cfg.width_m
    for r in results:
        bad = np.argwhere(~r.identifiable)
        if bad.size == 0:
            continue
        iy, ix = bad[0]
        node = np.array([r.x_m[ix], r.y_m[iy], r.z_m])
        jac = path_jacobian(
            anchors,
            node,
            model=cfg.model,
            window_height_m=cfg.window_height_m,
            delta_m=cfg.delta_m,
            edge_x_m=(-half, half),
        )
        verdict = identifiability(jac, r.sigma_m[iy, ix], max_condition=cfg.max_condition)
        lines.append(
            f"floor {r.floor}: {len(bad)} node(s) not identifiable, e.g. at "
            f"({node[0]:g}, {node[1]:g}, {node[2]:g}) m: {verdict.message[0]}"
        )
    return lines


def _stats(values: np.ndarray, ok: np.ndarray) -> list[float]:
    v = values[ok]
    if v.size == 0:
        return [math.inf] * 4
    return [float(np.median(v)), *np.percentile(v, [80, 95]).tolist(), float(v.max())]


def _fmt(v: float, scale: float) -> str:
    return f"{v * scale:.3g}" if math.isfinite(v) else "inf"


def write_csv(path: Path, results: list[FloorResult], n_anchors: int) -> None:
    header = ["floor", "x_m", "y_m", "z_m", "peb_m", "x_bound_m", "y_bound_m", "z_bound_m"]
    header += ["identifiable"]
    header += [f"snr_db_a{j + 1}" for j in range(n_anchors)]
    header += [f"sigma_m_a{j + 1}" for j in range(n_anchors)]
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
            fmt = ["{:d}", "{:.3f}", "{:.3f}", "{:.3f}"] + ["{:.6g}"] * 4 + ["{:d}"]
            fmt += ["{:.2f}"] * n_anchors + ["{:.6g}"] * n_anchors
            for row in zip(*cols, strict=True):
                w.writerow(
                    [f.format(int(v) if f == "{:d}" else v) for f, v in zip(fmt, row, strict=True)]
                )


def plot_floor(path: Path, r: FloorResult, cfg: BoundsConfig) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    anchors = np.asarray(cfg.anchors_m)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2), constrained_layout=True)
    step = cfg.grid_step_m
    extent = (r.x_m[0] - step / 2, r.x_m[-1] + step / 2, r.y_m[0] - step / 2, r.y_m[-1] + step / 2)
    for ax, data, title in (
        (axes[0], r.peb_m, "PEB"),
        (axes[1], r.z_bound_m, "z-axis bound"),
    ):
        finite = np.where(np.isfinite(data), data, np.nan)
        cmap = plt.get_cmap("viridis").with_extremes(bad="0.6")
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
        f"{cfg.model} model, B = {cfg.bandwidth_hz / 1e6:g} MHz, P_tx = {cfg.tx_power_dbm:g} dBm, "
        f"f = {cfg.frequency_hz / 1e9:g} GHz, w = {cfg.window_height_m:g} m"
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = BoundsConfig()
    # Let "--anchors -15,-20,1;..." through: argparse would take a value starting with "-" for
    # an option unless it looks like a negative number. (--anchors=... always works.)
    if hasattr(parser, "_negative_number_matcher"):
        parser._negative_number_matcher = re.compile(r"^-\d+$|^-\d*\.\d+$|^-[\d.,;eE+\s-]+$")
    parser.add_argument(
        "--anchors",
        default=None,
        metavar="X,Y,Z;...",
        help="anchor positions [m], ';'-separated (default: the paper's four anchors)",
    )
    parser.add_argument(
        "--grid-step-m",
        type=float,
        default=d.grid_step_m,
        help="node grid spacing [m] (default %(default)s)",
    )
    parser.add_argument(
        "--window-height-m",
        type=float,
        default=d.window_height_m,
        help="window height w [m] (default %(default)s)",
    )
    parser.add_argument(
        "--bandwidth-hz",
        type=float,
        default=d.bandwidth_hz,
        help="signal bandwidth [Hz] (default %(default)g)",
    )
    parser.add_argument(
        "--frequency-hz",
        type=float,
        default=d.frequency_hz,
        help="carrier frequency [Hz] (default %(default)g)",
    )
    parser.add_argument(
        "--tx-power-dbm",
        type=float,
        default=d.tx_power_dbm,
        help="transmit power [dBm] (default %(default)s)",
    )
    parser.add_argument(
        "--diffraction-loss-db",
        type=float,
        default=d.diffraction_loss_db,
        help="fixed diffraction loss on top of free space [dB] (default %(default)s)",
    )
    parser.add_argument(
        "--diffraction",
        choices=("fixed", "utd"),
        default=d.diffraction,
        help="diffracted power: free space minus --diffraction-loss-db ('fixed', default) or "
        "the UTD field of the upper window edge for x-polarised anchors ('utd')",
    )
    parser.add_argument(
        "--floors", type=int, default=d.n_floors, help="number of floors (default %(default)s)"
    )
    parser.add_argument(
        "--model",
        choices=("diffraction", "los"),
        default=d.model,
        help="path model of the FIM (default %(default)s; 'los' for comparison)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("out/bounds"),
        help="output directory (default %(default)s)",
    )
    parser.add_argument("--no-plots", action="store_true", help="write the CSV only")


def config_from_args(args: argparse.Namespace) -> BoundsConfig:
    cfg = BoundsConfig()
    if args.anchors is not None:
        cfg = replace(cfg, anchors_m=parse_anchors(args.anchors))
    cfg = replace(
        cfg,
        grid_step_m=args.grid_step_m,
        window_height_m=args.window_height_m,
        bandwidth_hz=args.bandwidth_hz,
        frequency_hz=args.frequency_hz,
        tx_power_dbm=args.tx_power_dbm,
        diffraction_loss_db=args.diffraction_loss_db,
        diffraction=args.diffraction,
        n_floors=args.floors,
        model=args.model,
    )
    return validate(cfg)


def run(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    err = Console(stderr=True)
    try:
        cfg = config_from_args(args)
    except ConfigError as exc:
        err.print(f"[bold red]diffpos bounds: error:[/] {exc}", highlight=False)
        return 2
    out: Path = args.out
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        err.print(
            f"[bold red]diffpos bounds: error:[/] --out: cannot create {out}: {exc}",
            highlight=False,
        )
        return 2

    results = compute(cfg)
    console = Console()
    n0 = float(noise_floor_dbm(cfg.bandwidth_hz, temperature_k=cfg.temperature_k))
    all_snr = np.concatenate([r.snr_db.ravel() for r in results])
    console.print(
        f"{len(cfg.anchors_m)} anchors, {cfg.model} model, kTB = {n0:.1f} dBm, link SNR "
        f"{all_snr.min():.1f} .. {all_snr.max():.1f} dB (incl. {cfg.processing_gain_db:g} dB "
        "processing gain, "
        + (
            f"{cfg.diffraction_loss_db:g} dB diffraction loss)"
            if cfg.diffraction == "fixed"
            else "UTD upper-edge diffraction, x polarisation)"
        ),
        highlight=False,
    )
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
    console.print(t_peb)
    console.print(t_z)
    for line in explain_non_identifiable(cfg, results):
        console.print(line, highlight=False)

    csv_path = out / "bounds.csv"
    try:
        write_csv(csv_path, results, len(cfg.anchors_m))
        written = [csv_path]
        if not args.no_plots:
            for r in results:
                png = out / f"floor{r.floor}.png"
                plot_floor(png, r, cfg)
                written.append(png)
    except OSError as exc:
        err.print(
            f"[bold red]diffpos bounds: error:[/] --out: cannot write to {out}: {exc}",
            highlight=False,
        )
        return 2
    console.print("wrote " + ", ".join(str(p) for p in written), highlight=False, soft_wrap=True)
    return 0


if __name__ == "__main__":  # pragma: no cover
    from diffpos_services.cli.main import main

    sys.exit(main(["bounds", *sys.argv[1:]]))
