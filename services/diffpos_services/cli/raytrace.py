"""Ray-trace the scenario with Sionna RT (optional extra) for an independent check

Builds the scenario's building as a Sionna RT scene (thin concrete facade with the window
bands as holes, side/back walls, floor slabs, plasterboard partitions, ground), traces every
anchor x receiver link with line of sight, reflections, transmissions and first-order edge
diffraction, classifies each path into the paper's MPC groups 1..4 (Tx-Rx, Tx-R-Rx,
Tx-D[-T..]-Rx, the rest), and writes a dataset (.npz) with every path's length, gain,
angles, interaction chain and first interaction point.

The dataset replaces the channel emulator in the positioning study:

    diffpos reproduce --channel raytrace:out/raytrace-paper.npz

and the command prints how the emulator and the ray tracer agree on the same receivers: the
paper's P_e / P_fap table from both, the first-arrival group confusion matrix, and the
Fermat check (every ray-traced window-edge diffraction path vs the analytic length of
diffpos.geometry; they agree to micrometres).

Install the extra first (about 350 MB, plus Debian's LLVM 19 for Dr.Jit's CPU backend):

    pip install -e '.[raytrace]'
    apt-get install libllvm19      # DRJIT_LIBLLVM_PATH defaults to its libLLVM.so.19.1

Cost grows with samples x receivers: 6-18 s per 1000 links at 1e5 samples on 2 cores
(idle vs shared machine), so the paper's full grid (17,600 receivers x 4 anchors) takes
7-22 minutes. Sampling finds
almost every direct window-edge diffraction path at 1e5 samples, but diffraction paths that
then cross partitions (Tx-D-T-Rx) are found only partly; raise --samples to find more.

examples:
  diffpos raytrace paper --quick                      200 receivers, about half a minute
  diffpos raytrace scenarios/paper.toml --receivers 2000 --out out/rt2000.npz
  diffpos raytrace scenarios/paper.toml --samples 1000000 --receivers 500
  diffpos raytrace scenarios/paper.toml               every receiver of the grid (minutes)
  diffpos raytrace --compare tests/data/raytrace_small.npz    re-print the comparison
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from diffpos.scenario import Scenario, ScenarioError
from diffpos_services.scenario_io import load_scenario, resolve_scenario, scenario_or_default

if TYPE_CHECKING:
    from diffpos_services.raytrace.dataset import RaytraceDataset
    from diffpos_services.raytrace.tracing import RaytraceSettings

QUICK_RECEIVERS = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", nargs="?", help="scenario TOML file, or 'paper' for the "
                        "built-in paper geometry")
    parser.add_argument("--compare", type=Path, metavar="FILE",
                        help="do not trace: print the emulator comparison for an existing "
                        "dataset (needs no Sionna)")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--receivers", type=int, metavar="N",
                      help="trace N receivers evenly spread over the scenario's grid "
                      "(default: all)")
    size.add_argument("--quick", action="store_true",
                      help=f"{QUICK_RECEIVERS} receivers (a check in about half a minute)")
    parser.add_argument("--samples", type=float, default=1e5, metavar="S",
                        help="rays per transmitter (default 1e5; cost is linear in S)")
    parser.add_argument("--max-depth", type=int, default=3, metavar="D",
                        help="maximum interactions per path (default 3, covers Tx-D-T-T-Rx)")
    parser.add_argument("--seed", type=int, default=1, help="sampling seed (default 1)")
    parser.add_argument("--batch", type=int, default=2000, metavar="B",
                        help="receivers per solver call (default 2000)")
    parser.add_argument("--deterministic", action="store_true",
                        help="Sionna's deterministic candidate generator (reproducible, slower)")
    parser.add_argument("--out", type=Path, default=None, metavar="FILE",
                        help="dataset file (default out/raytrace-<scenario name>.npz)")
    parser.add_argument("--no-compare", action="store_true",
                        help="skip the comparison with the channel emulator")


def _load_scenario(spec: str) -> Scenario:
    """'paper' (the built-in geometry), a TOML file or a shipped scenario's name."""
    if spec == "paper":
        return scenario_or_default(None)
    path = resolve_scenario(spec)
    if not path.is_file():
        raise ValueError(f"scenario: no such file {spec!r} (give a TOML file or 'paper')")
    try:
        return load_scenario(path)
    except ScenarioError as exc:
        raise ValueError(f"{spec}: {exc}") from None


def _pick_receivers(nodes: np.ndarray, n: int | None) -> np.ndarray:
    if n is None or n >= len(nodes):
        return np.arange(len(nodes))
    return np.unique(np.linspace(0, len(nodes) - 1, n).round().astype(int))


def _report(ds: RaytraceDataset, console: Console) -> None:
    """The emulator comparison of a dataset: MPC table, confusion matrix, Fermat check."""
    from diffpos_services.raytrace.evaluate import compare_with_emulator  # kernels

    cmp = compare_with_emulator(ds)
    t = Table(title=f"MPC groups over {cmp['links']} links (emulator | ray tracer) [%]")
    t.add_column("group")
    for c in ("P_e emu", "P_e RT", "P_fap emu", "P_fap RT"):
        t.add_column(c, justify="right")
    se, sr = cmp["stats_emulator"], cmp["stats_raytrace"]
    for g in ("MPC-1", "MPC-2", "MPC-3", "MPC-4"):
        t.add_row(g, f"{se[g]['P_e']:.1f}", f"{sr[g]['P_e']:.1f}", f"{se[g]['P_fap']:.1f}",
                  f"{sr[g]['P_fap']:.1f}")
    t.add_row("none", "", "", f"{se['none']['P_fap']:.1f}", f"{sr['none']['P_fap']:.1f}")
    console.print(t)
    conf = cmp["confusion"]
    c = Table(title="first-arrival group: rows emulator, columns ray tracer (0 = none)")
    c.add_column("")
    for g in range(5):
        c.add_column(str(g), justify="right")
    for g in range(5):
        c.add_row(str(g), *(str(v) for v in conf[g]))
    console.print(c)
    d = np.abs(cmp["path_diff_m"])
    console.print(f"first-arrival group agreement: {100 * cmp['class_agreement']:.1f} % of links")
    console.print(f"the ray tracer has the emulator's first-arrival path (same length to 1 mm) on "
                  f"{100 * cmp['found_emulator_fap']:.1f} % of links; group agreement there: "
                  f"{100 * cmp['class_agreement_found']:.1f} %")
    if d.size:
        console.print(f"both MPC-3 ({cmp['both_mpc3']} links): |RT - emulator| first-arrival "
                      f"length median {np.median(d) * 1e3:.3f} mm, "
                      f"{100 * np.mean(d < 1e-3):.1f} % within 1 mm, max {d.max():.3f} m")
    f = cmp["fermat"]
    console.print(f"Fermat check: {f['count']} ray-traced window-edge diffraction paths, "
                  f"max |traced - analytic| = {f['max_abs_m'] * 1e3:.4f} mm")
    if ds.path_vertices_m is not None:
        _report_mechanisms(ds, console)


def _report_mechanisms(ds: RaytraceDataset, console: Console) -> None:
    """First-arrival share per mechanism of diffpos.paths.model (emulator | ray tracer)."""
    from diffpos_services.raytrace.mechanism_mix import compare_mechanisms  # kernels
    from diffpos_services.raytrace.mechanisms import mechanism_length_check

    mix = compare_mechanisms(ds)
    t = Table(title=f"first-arrival mechanism over {mix['links']} links [%] (same mechanism on "
              f"{mix['agreement']:.1f} % of links)")
    for c, j in (("mechanism", "left"), ("emulator", "right"), ("ray tracer", "right")):
        t.add_column(c, justify=j)
    se, sr = mix["share_emulator"], mix["share_raytrace"]
    for k in sorted(set(se) | set(sr), key=lambda k: -(se.get(k, 0) + sr.get(k, 0)))[:16]:
        t.add_row(k, f"{se.get(k, 0.0):.1f}", f"{sr.get(k, 0.0):.1f}")
    console.print(t)
    console.print("where they differ [% of links]: " + ", ".join(
        f"{k} {v:.1f}" for k, v in mix["causes"].items()))
    worst = max((r["max_abs_m"] for r in mechanism_length_check(ds).values()),
                default=float("nan"))
    console.print(f"traced paths vs the model's closed-form length per mechanism: max "
                  f"|traced - model| = {worst * 1e6:.1f} um")


def _compare_only(args: argparse.Namespace, console: Console, err: Callable[[str], None]) -> int:
    """--compare FILE: the emulator comparison of an existing dataset (no Sionna needed)."""
    from diffpos_services.raytrace.dataset import load_dataset

    try:
        ds = load_dataset(args.compare)
    except ValueError as exc:
        err(str(exc))
        return 2
    console.print(f"{args.compare}: {len(ds.nodes_m)} receivers x {len(ds.anchors_m)} "
                  f"anchors, scenario {ds.metadata['scenario']['name']!r}, "
                  f"{ds.metadata['settings']['samples_per_src']:.0e} samples")
    _report(ds, console)
    return 0


def _settings(args: argparse.Namespace) -> tuple[Scenario, RaytraceSettings]:
    """The scenario and the solver settings of the options (ValueError names the option)."""
    from diffpos_services.raytrace.tracing import RaytraceSettings

    scenario = _load_scenario(args.scenario)
    settings = RaytraceSettings(max_depth=args.max_depth,
                                samples_per_src=int(args.samples), seed=args.seed,
                                batch_size=args.batch, deterministic=args.deterministic)
    if args.receivers is not None and args.receivers < 1:
        raise ValueError(f"--receivers: must be >= 1, got {args.receivers}")
    return scenario, settings


def _trace_with_progress(scenario: Scenario, nodes: np.ndarray, settings: RaytraceSettings,
                         console: Console) -> RaytraceDataset:
    from diffpos_services.raytrace.tracing import trace

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("links"), TimeElapsedColumn(), TimeRemainingColumn(),
                  console=console, transient=False) as bar:
        task = bar.add_task("tracing", total=len(nodes) * len(scenario.anchors))

        def progress(done: int, total: int, label: str) -> None:
            bar.update(task, completed=done, description=f"tracing {label}")

        return trace(scenario, nodes, settings=settings, progress=progress)


def run(args: argparse.Namespace) -> int:
    from diffpos_services.raytrace.backend import RaytraceUnavailable, check_sionna
    from diffpos_services.raytrace.dataset import save_dataset

    console = Console(stderr=True)
    err = lambda msg: console.print(f"diffpos raytrace: {msg}", style="red",  # noqa: E731
                                    markup=False, highlight=False, soft_wrap=True)
    if args.compare is not None:
        return _compare_only(args, console, err)
    if args.scenario is None:
        err("give a SCENARIO to trace (a TOML file or 'paper'), or --compare FILE")
        return 2
    try:
        scenario, settings = _settings(args)
    except ValueError as exc:
        err(str(exc))
        return 2
    try:
        versions = check_sionna()
    except RaytraceUnavailable as exc:
        err(str(exc))
        return exc.exit_code
    nodes = scenario.node_positions_m()
    if len(nodes) == 0:
        err("scenario: no receivers (add a [nodes.grid] table or [[nodes.list]] entries)")
        return 2
    n_req = QUICK_RECEIVERS if args.quick else args.receivers
    nodes = nodes[_pick_receivers(nodes, n_req)]
    out = args.out or Path("out") / f"raytrace-{scenario.name}.npz"
    console.print(f"Sionna RT {versions['sionna-rt']} ({versions['variant']}, LLVM "
                  f"{versions['libllvm'] or 'default'}): {len(nodes)} receivers x "
                  f"{len(scenario.anchors)} anchors, {settings.samples_per_src:.0e} samples, "
                  f"max depth {settings.max_depth}")
    t0 = time.perf_counter()
    try:
        ds = _trace_with_progress(scenario, nodes, settings, console)
    except ValueError as exc:
        err(str(exc))
        return 2
    path = save_dataset(out, ds)
    console.print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB, "
                  f"{ds.path_valid.shape[-1]} paths max per link) in "
                  f"{time.perf_counter() - t0:.1f} s; "
                  f"{ds.metadata['s_per_1000_links']:.2f} s per 1000 links")
    if not args.no_compare:
        _report(ds, console)
    console.print(f"use it: diffpos reproduce --channel raytrace:{path}")
    return 0
