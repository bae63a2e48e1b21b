"""Upper/lower edge diffraction power ratio (Theorem 3): PNG + CSV

A node inside the building receives two diffracted paths through its window: one over the
upper edge, one over the lower edge. With the anchor's antenna polarised along the edges (x),
the paper's Theorem 3 approximates their power ratio by a function of the anchor's elevation
angle theta alone,

    P_upper / P_lower ~ (1 + cos theta) / (1 - cos theta),

valid for nodes deep inside (window height w << node depth y_n). This command draws that curve
and, for comparison, the "exact" ratio of the full field model at real positions (UTD or
Keller coefficients, spherical-wave spreading) for several node depths.

How theta is swept: the anchor stays at (0, -ANCHOR_DISTANCE, ANCHOR_HEIGHT); the node's floor
is moved up or down so that the window centre is seen from the anchor at elevation theta
(window centre height z_c = z_a + |y_a| cot theta). theta = 90 deg puts the window at the
anchor's height; small theta is a floor far above the anchor. The node sits at the window
mid-height (or DELTA above it, Case-2) at depth y_n behind the wall.

Outputs in --out: power_ratio.csv (one row per depth and angle: depth_m, theta_deg,
window_center_z_m, node_z_m, ratio_approx, ratio_approx_db, ratio_exact, ratio_exact_db,
los_through_window) and power_ratio.png (ratio in dB vs theta). The table printed at the end
gives, per curve, the angle below which the ratio stays above --threshold-db (the paper: at
least 5 dB for theta < 60 deg; the closed form crosses 5 dB at 58.70 deg), the angle from
which the lower edge is the stronger one, and from which the node sees the anchor directly
through the window.

What to expect with the defaults (w = 1.5 m, |y_a| = 20 m): the exact curves lie below the
approximation and cross 5 dB at about 26, 39, 45 and 49 deg for y_n = 2, 5, 10, 20 m. The
approximation assumes psi = 3 pi/2 and the same theta for both edges; near theta = 90 deg the
node is close to the incident shadow boundary of both edges, where the small angular offsets
(about w/(2 y_n) at the node and w sin(theta)/|y_a| at the anchor) decide which edge is
stronger. Only for w << y_n and w << |y_a| do the exact curves converge to Theorem 3 (try
--depths-m 1000 --anchor-distance-m 1000).

examples:
  diffpos power-ratio --out out/
  diffpos power-ratio --depths-m 2 5 10 20 --window-height-m 1.5 --anchor-distance-m 20
  diffpos power-ratio --coefficients keller --spreading paper   # the paper's GTD forms
  diffpos power-ratio --e0 0 0 1 --out out/vpol                 # vertical polarisation
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from diffpos.channel.power_ratio import PowerRatioSweep


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out", type=Path, default=Path("out"), help="output directory (created) [default: out]"
    )
    parser.add_argument(
        "--depths-m",
        type=float,
        nargs="+",
        default=[2.0, 5.0, 10.0, 20.0],
        help="node depths y_n behind the wall, one exact curve each [m] (default: 2 5 10 20)",
    )
    parser.add_argument(
        "--window-height-m", type=float, default=1.5, help="window height w [m] (default: 1.5)"
    )
    parser.add_argument(
        "--anchor-distance-m",
        type=float,
        default=20.0,
        help="anchor distance |y_a| in front of the wall [m] (default: 20, as the paper's anchors 1 and 4)",
    )
    parser.add_argument(
        "--anchor-height-m", type=float, default=1.0, help="anchor height z_a [m] (default: 1)"
    )
    parser.add_argument(
        "--delta-m",
        type=float,
        default=0.0,
        help="Case-2 offset: node this far above the window centre [m] (default: 0)",
    )
    parser.add_argument(
        "--frequency-hz", type=float, default=28e9, help="carrier frequency [Hz] (default: 28e9)"
    )
    parser.add_argument(
        "--coefficients",
        choices=("utd", "keller"),
        default="utd",
        help="diffraction coefficients of the exact curves (default: utd, finite at shadow boundaries)",
    )
    parser.add_argument(
        "--spreading",
        choices=("spherical", "paper"),
        default="spherical",
        help="spreading factor: sqrt(s'/(s(s+s'))) or the paper's 1/sqrt(s) (default: spherical)",
    )
    parser.add_argument(
        "--e0",
        type=float,
        nargs=3,
        default=[1.0, 0.0, 0.0],
        metavar=("X", "Y", "Z"),
        help="transmit polarisation vector (default: 1 0 0, along the edges as in Theorem 3)",
    )
    parser.add_argument(
        "--theta-min-deg",
        type=float,
        default=2.0,
        help="smallest elevation angle [deg] (default: 2)",
    )
    parser.add_argument(
        "--theta-max-deg",
        type=float,
        default=90.0,
        help="largest elevation angle [deg] (default: 90)",
    )
    parser.add_argument(
        "--theta-step-deg", type=float, default=0.25, help="angle step [deg] (default: 0.25)"
    )
    parser.add_argument(
        "--threshold-db",
        type=float,
        default=5.0,
        help="ratio threshold to report [dB] (default: 5)",
    )


def _validate(args: argparse.Namespace) -> str | None:
    """The first option that is out of range, as a message naming it (None if all are fine)."""
    if not args.depths_m or any(not (d > 0 and math.isfinite(d)) for d in args.depths_m):
        return "--depths-m: every depth must be a positive number of metres (node inside, y > 0)"
    for name in ("window_height_m", "anchor_distance_m", "frequency_hz", "theta_step_deg"):
        v = getattr(args, name)
        if not (v > 0 and math.isfinite(v)):
            return f"--{name.replace('_', '-')}: must be positive, got {v}"
    if not 0.0 < args.theta_min_deg < args.theta_max_deg < 180.0:
        return (
            f"--theta-min-deg/--theta-max-deg: need 0 < min < max < 180 deg, got "
            f"{args.theta_min_deg} and {args.theta_max_deg}"
        )
    if not any(args.e0):
        return "--e0: the polarisation vector must not be zero"
    return None


def config_from_args(args: argparse.Namespace) -> PowerRatioSweep:
    """The sweep the options describe."""
    from diffpos.channel.power_ratio import PowerRatioSweep  # scipy: not for --help

    return PowerRatioSweep(
        depths_m=tuple(args.depths_m),
        window_height_m=args.window_height_m,
        anchor_distance_m=args.anchor_distance_m,
        anchor_height_m=args.anchor_height_m,
        delta_m=args.delta_m,
        frequency_hz=args.frequency_hz,
        coefficients=args.coefficients,
        spreading=args.spreading,
        e0=tuple(args.e0),
        theta_min_deg=args.theta_min_deg,
        theta_max_deg=args.theta_max_deg,
        theta_step_deg=args.theta_step_deg,
    )


def run(args: argparse.Namespace) -> int:
    # scipy and matplotlib (~1 s of imports): not for --help
    from diffpos.channel.power_ratio import compute_sweep
    from diffpos_services.reports import power_ratio as report

    problem = _validate(args)
    if problem:
        print(f"diffpos power-ratio: {problem}", file=sys.stderr)
        return 2
    cfg = config_from_args(args)
    try:
        sweep = compute_sweep(cfg)
    except ValueError as exc:
        print(f"diffpos power-ratio: {exc}", file=sys.stderr)
        return 2
    try:
        args.out.mkdir(parents=True, exist_ok=True)
        csv_path = args.out / report.CSV_NAME
        png_path = args.out / report.PNG_NAME
        report.write_csv(csv_path, sweep)
        report.write_png(png_path, sweep, cfg, args.threshold_db)
    except OSError as exc:
        print(f"diffpos power-ratio: cannot write to --out {args.out}: {exc}", file=sys.stderr)
        return 1
    report.print_report(sweep, args.threshold_db, csv_path, png_path)
    return 0
