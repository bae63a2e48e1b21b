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

The scenario is the paper's (scenarios/paper.toml, the one reproduce and emulate use):
anchors (-15,-20,1), (0,-15,0), (0,-7,4), (15,-20,1) m (the paper prints (0,15,0) for
anchor 2, which would be inside the building; anchors fly outside, y < 0); 28 GHz carrier,
400 MHz bandwidth, 30 dBm transmit power; building 40 m wide (window edges span x in
[-20, 20]) and 22.5 m deep, 5 floors of 3 m whose floors are at z = 4, 7, 10, 13, 16 m;
nodes at the window's mid-height (z = 5.5, 8.5, ... 17.5 m), which is also mid-floor
(Assumption 1, Case-1), window height 1.5 m.

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
import dataclasses
import math
import re
from pathlib import Path

import numpy as np
from rich.console import Console

from diffpos import bound_maps
from diffpos.bound_maps import BoundMapSettings
from diffpos.scenario import AnchorSpec, Scenario, default_scenario
from diffpos.trajectory import Static
from diffpos_services.errors import ConfigError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d, b, radio = BoundMapSettings(), default_scenario().building, default_scenario().radio
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
        default=b.window_height_m,
        help="window height w [m] (default %(default)s)",
    )
    parser.add_argument(
        "--bandwidth-hz",
        type=float,
        default=radio.bandwidth_hz,
        help="signal bandwidth [Hz] (default %(default)g)",
    )
    parser.add_argument(
        "--frequency-hz",
        type=float,
        default=radio.frequency_hz,
        help="carrier frequency [Hz] (default %(default)g)",
    )
    parser.add_argument(
        "--tx-power-dbm",
        type=float,
        default=radio.tx_power_dbm,
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
        "--floors", type=int, default=b.n_floors, help="number of floors (default %(default)s)"
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


def _check_range(name: str, value: float, lo: float, hi: float, *, lo_open=True) -> None:
    ok = (value > lo if lo_open else value >= lo) and value <= hi and math.isfinite(value)
    if not ok:
        bracket = "(" if lo_open else "["
        raise ConfigError(f"{name}: {value:g} is out of range; allowed {bracket}{lo:g}, {hi:g}]")


def _check_anchors(anchors: list[np.ndarray]) -> None:
    if len(anchors) < 3:
        raise ConfigError(
            f"--anchors: {len(anchors)} anchor(s) given; 3D positioning needs at least 3 "
            "(paper, Corollary 3)"
        )
    for i, a in enumerate(anchors, start=1):
        if len(a) != 3 or not all(math.isfinite(v) for v in a):
            raise ConfigError(f"--anchors: anchor {i} must be three finite numbers x,y,z [m]")
        if a[1] >= 0.0:
            raise ConfigError(
                f"--anchors: anchor {i} ({a[0]:g},{a[1]:g},{a[2]:g}) has y = {a[1]:g} >= 0, which "
                "is inside the building; anchors fly outside, in front of the facade (y < 0)"
            )


def validate(scenario: Scenario, settings: BoundMapSettings) -> None:
    """Check a bound map's inputs; raise :class:`ConfigError` naming the option."""
    b, radio = scenario.building, scenario.radio
    _check_anchors([a.position_m for a in scenario.anchors])
    _check_range("--grid-step-m", settings.grid_step_m, 0.05, min(b.width_m, b.depth_m) / 2)
    _check_range("--window-height-m", b.window_height_m, 0.0, b.floor_height_m)
    _check_range("--bandwidth-hz", radio.bandwidth_hz, 1e3, 1e11)
    _check_range("--frequency-hz", radio.frequency_hz, 1e6, 1e12)
    _check_range("--tx-power-dbm", radio.tx_power_dbm, -60.0, 80.0, lo_open=False)
    _check_range("--diffraction-loss-db", settings.diffraction_loss_db, 0.0, 100.0, lo_open=False)
    _check_range("--floors", b.n_floors, 0, 200)
    if settings.diffraction not in ("fixed", "utd"):
        raise ConfigError(f"--diffraction: {settings.diffraction!r}; allowed 'fixed' or 'utd'")
    if settings.model not in ("diffraction", "los"):
        raise ConfigError(f"--model: {settings.model!r}; allowed 'diffraction' or 'los'")
    n_nodes = b.n_floors * np.prod([len(v) for v in bound_maps.grid_xy_m(b, settings)])
    if n_nodes > 5_000_000:
        raise ConfigError(
            f"--grid-step-m: {settings.grid_step_m:g} m gives {n_nodes} nodes; max 5e6"
        )


def config_from_args(args: argparse.Namespace) -> tuple[Scenario, BoundMapSettings]:
    """The paper's scenario with the options applied, and the map settings (validated)."""
    scenario = default_scenario()
    if args.anchors is not None:
        anchors = tuple(
            AnchorSpec(id=f"a{j}", trajectory=Static(xyz))
            for j, xyz in enumerate(parse_anchors(args.anchors), start=1)
        )
        scenario = dataclasses.replace(scenario, anchors=anchors)
    scenario = dataclasses.replace(
        scenario,
        building=dataclasses.replace(
            scenario.building, window_height_m=args.window_height_m, n_floors=args.floors
        ),
        radio=dataclasses.replace(
            scenario.radio,
            bandwidth_hz=args.bandwidth_hz,
            frequency_hz=args.frequency_hz,
            tx_power_dbm=args.tx_power_dbm,
        ),
    )
    settings = BoundMapSettings(
        grid_step_m=args.grid_step_m,
        diffraction_loss_db=args.diffraction_loss_db,
        diffraction=args.diffraction,
        model=args.model,
    )
    validate(scenario, settings)
    return scenario, settings


def _write(out: Path, results, scenario: Scenario, settings, *, plots: bool) -> list[Path]:
    from diffpos_services.reports import bounds as report  # matplotlib: not for --help

    csv_path = out / "bounds.csv"
    report.write_csv(csv_path, results, len(scenario.anchors))
    written = [csv_path]
    if plots:
        for r in results:
            png = out / f"floor{r.floor}.png"
            report.plot_floor(png, r, scenario, settings)
            written.append(png)
    return written


def run(args: argparse.Namespace) -> int:
    """Options -> bound maps -> tables, CSV and heat maps; a bad option or an unwritable
    --out is a :class:`ConfigError` (exit 2, printed by :func:`diffpos_services.cli.main.main`)."""
    from diffpos_services.reports import bounds as report  # matplotlib: not for --help

    scenario, settings = config_from_args(args)
    out: Path = args.out
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out: cannot create {out}: {exc}") from None
    results = bound_maps.compute(scenario, settings)
    console = Console()
    explanations = bound_maps.explain_non_identifiable(scenario, settings, results)
    report.print_summary(console, scenario, settings, results, explanations)
    try:
        written = _write(out, results, scenario, settings, plots=not args.no_plots)
    except OSError as exc:
        raise ConfigError(f"--out: cannot write to {out}: {exc}") from None
    console.print("wrote " + ", ".join(str(p) for p in written), highlight=False, soft_wrap=True)
    return 0
