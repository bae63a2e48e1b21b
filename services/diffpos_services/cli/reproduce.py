"""Regenerate the paper's study: MPC table, first-arrival stats, error CDFs

Reproduces the numerical study of Duggal et al. ("Diffraction-Aided Wireless Positioning",
Section V and the ray-tracing appendix) on a scenario (default: the paper's geometry, see
scenarios/paper.toml): 4 UAV anchors outside a 5-floor building and a receiver grid on every
floor (17,600 receivers).

What it does, in order:

1. Channels. For every receiver x anchor link the O2I emulator (diffpos.channel.emulator) lists the
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
   (node at the window mid-height), D-NLS Case-2 (model offset Delta = 1.5 m) and M-NLS
   (mnls: mechanism-aware NLS on the first-arrival path model, floor hypotheses from the
   scenario's building, the measured SNR with its radio), compared with the position error
   bound (PEB) and the z bound of the diffraction model.
5. Floor accuracy of every method: the share of ALL receivers whose estimate lies on the
   receiver's floor (a failed fix is a miss); for methods that report a covariance (M-NLS)
   the share of fixes whose 95 % ellipsoid holds the truth.

Outputs in --out (default out/reproduce): summary.json and summary.md (tables, with the
paper's numbers side by side, and the wall time of every method), cdf_3d_error.png,
cdf_z_error.png, first_arrival_boxplots.png and first_arrival.npz (the per-link
first-arrival data; feed it back with --channel arrivals:FILE to re-run only the
positioning).

The emulator is not the paper's commercial ray tracer: expect the same mechanisms and ordering,
not the same percentages (summary.md compares them).

Other channel sources (the hook for ray-traced data):
  --channel raytrace:FILE     a dataset written by 'diffpos raytrace' (Sionna RT)
  --channel arrivals:FILE     first-arrival arrays (.npz with anchors_m, nodes_m, range_m,
                              snr_db, detected [, sigma_m, mpc_class, aoa_deg])

examples:
  diffpos reproduce                              full study (M-NLS dominates the run time)
  diffpos reproduce --quick --out out/quick      1,500 random receivers, under a minute
  diffpos reproduce --seed 7 --methods dnls_case1 dnls_lower
  diffpos reproduce --scenario scenarios/paper.toml --delta-m 1.0
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from diffpos.scenario import Scenario, ScenarioError
from diffpos.study_methods import ALL_METHODS, DEFAULT_QUICK_NODES, REPRODUCE_METHODS
from diffpos_services.scenario_io import scenario_or_default


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
                        help=f"receivers kept by --quick (default {DEFAULT_QUICK_NODES})")
    parser.add_argument("--channel", default="emulator", metavar="SOURCE",
                        help="emulator (default), raytrace:FILE or arrivals:FILE.npz")
    parser.add_argument("--methods", nargs="+", choices=ALL_METHODS,
                        default=list(REPRODUCE_METHODS),
                        help="estimators to run (default: the paper's four and mnls, "
                             f"{' '.join(REPRODUCE_METHODS)}; dnls_lower models the lower "
                             "window edge; mnls uses the scenario's building and radio)")
    parser.add_argument("--delta-m", type=float, default=1.5,
                        help="D-NLS Case-2 model offset Delta [m] (default: 1.5, the paper's)")
    parser.add_argument("--mnls-max-order", type=int, default=2, choices=(2, 3, 4),
                        help="mnls's mechanism families: 2 = the 18 mechanisms of the emulator "
                             "(default); 3, 4 = also triple / quadruple bounces between the "
                             "slabs, edge diffraction then two or three bounces, a ground "
                             "bounce before the edge (what Sionna RT finds first indoors)")
    parser.add_argument("--mnls-measured-threshold", action="store_true",
                        help="mnls: the detector threshold is at least the measured first "
                             "arrival's SNR less fap_threshold_db (default: off; "
                             "diffpos.estimators.mnls.rules.SnrRule)")
    parser.add_argument("--mnls-first-arrival-prior", type=float, default=0.0, metavar="W",
                        help="mnls: the soft skip prior of the detector's earlier paths with "
                             "weight W in [0, 1) instead of the hard rule (default 0: off)")
    parser.add_argument("--mnls-keep-hard-rule", action="store_true",
                        help="mnls: with --mnls-first-arrival-prior, keep the hard rule too")
    parser.add_argument("--mnls-dielectric-edges", type=float, default=0.0, metavar="Q",
                        help="mnls: prior probability Q in [0, 1] that the window's sill and "
                             "lintel diffract as a dielectric sheet of the wall material (the "
                             "channel's edge at order >= 3): 1 predicts the SNR with it, "
                             "0 < Q < 1 mixes it with the radio's (default 0: the radio's)")
    parser.add_argument("--mnls-floor-box", action="store_true",
                        help="mnls: each floor's Laplace mass counts only its share inside "
                             "the floor's box (SnrRule.floor_box; default: the whole Gaussian)")
    parser.add_argument("--mnls-shadow-starts", type=float, default=0.0, metavar="D",
                        help="mnls: starts +-D m across a window edge's shadow boundary where a "
                             "floor's mode explains a link by the edge's diffraction and the "
                             "lit path does not exist there (SnrRule.shadow_starts; default 0: "
                             "none)")
    parser.add_argument("--mnls-path-region", action="store_true",
                        help="mnls: with --mnls-floor-box, each floor's Laplace mass counts "
                             "only its share where every used link's chosen mechanism exists "
                             "(SnrRule.path_region; default off)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def _channel_source(spec: str) -> tuple[str, Path | None]:
    """``--channel``: ``("emulator", None)`` or ``(kind, existing file)``."""
    if spec == "emulator":
        return "emulator", None
    kind, sep, path = spec.partition(":")
    if not sep or kind not in ("raytrace", "arrivals") or not path:
        raise ValueError(f"--channel: expected emulator, raytrace:FILE or arrivals:FILE, "
                         f"got {spec!r}")
    p = Path(path)
    if not p.exists():
        raise ValueError(f"--channel: no such file {p}")
    return kind, p


def _loader(kind: str, path: Path | None, scenario: Scenario):
    """How to read the first arrivals of a non-emulator source (None for the emulator)."""
    from diffpos.study import Arrivals, FirstArrivalData
    from diffpos_services.raytrace.evaluate import dataset_arrivals

    if kind == "arrivals":
        def load_arrivals(noise_rng: np.random.Generator) -> Arrivals:
            with np.load(path) as z:
                return Arrivals(FirstArrivalData.from_arrays(
                    dict(z), bandwidth_hz=scenario.radio.bandwidth_hz))
        return load_arrivals
    if kind == "raytrace":
        return lambda noise_rng: dataset_arrivals(path, scenario, rng=noise_rng)
    return None


def _scenario_problem(scenario: Scenario) -> str | None:
    if len(scenario.anchors) < 3:
        return (f"the scenario has {len(scenario.anchors)} anchor(s); at least 3 are needed "
                "for 3D fixes")
    if scenario.node_grid is None and not scenario.nodes:
        return "the scenario has no receivers ([nodes.grid] or [[nodes.list]])"
    return None


def _fail(message: str, code: int = 2) -> int:
    print(f"diffpos reproduce: {message}", file=sys.stderr)
    return code


def run(args: argparse.Namespace) -> int:
    # the study and its estimators (numba kernels), the plots (matplotlib): not for --help
    from diffpos.study import ReproduceConfig, build_summary, reproduce
    from diffpos_services.reports import study as report

    if args.quick_nodes < 10:
        return _fail("--quick-nodes must be >= 10")
    try:
        scenario = scenario_or_default(args.scenario)
    except ScenarioError as exc:
        return _fail(str(exc))
    problem = _scenario_problem(scenario)
    if problem:
        return _fail(problem)
    cfg = ReproduceConfig(seed=args.seed, quick=args.quick, quick_nodes=args.quick_nodes,
                          methods=tuple(args.methods), delta_m=args.delta_m,
                          mnls_max_order=args.mnls_max_order,
                          mnls_measured_threshold=args.mnls_measured_threshold,
                          mnls_first_arrival_prior=args.mnls_first_arrival_prior,
                          mnls_keep_hard_rule=args.mnls_keep_hard_rule,
                          mnls_dielectric_edges=args.mnls_dielectric_edges,
                          mnls_floor_box=args.mnls_floor_box,
                          mnls_shadow_starts=args.mnls_shadow_starts,
                          mnls_path_region=args.mnls_path_region)
    try:
        kind, path = _channel_source(args.channel)
        with report.ProgressBars(not args.no_progress) as prog:
            res = reproduce(scenario, cfg, kind=kind, path=path,
                            load=_loader(kind, path, scenario), progress=prog)
    except (ValueError, OSError) as exc:
        return _fail(str(exc))
    summary = build_summary(cfg, scenario, res)
    try:
        files = report.write_outputs(args.out, summary, res, args.delta_m)
    except OSError as exc:
        return _fail(f"cannot write to --out {args.out}: {exc}", 1)
    report.print_report(summary, files)
    return 0
