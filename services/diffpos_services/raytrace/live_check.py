"""What tracing on a coarser grid costs: interpolated vs traced at every epoch (Sionna RT).

Traces every anchor's paths to the emulated nodes on a fine grid (``--fine-step-s``, the
reference: every epoch traced), keeps every n-th grid time as a coarse grid, interpolates
(:func:`diffpos.channel.traced.paths_at`) at the fine times between them and compares:

- per path (same key in both): the interpolated length minus the traced one;
- per link (noise-free first arrival, the emulator's detector): same first-arriving path
  (key), detection disagreements, and the first-arrival length difference.

With ``--seed2`` it also traces the fine grid with another sampling seed: what tracing every
epoch itself varies by (Sionna samples rays, so two traces of one geometry differ).

    python -m diffpos_services.raytrace.live_check [SCENARIO] --span-s 4 --steps 0.5 1
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from typing import Any

import numpy as np

from diffpos.channel.traced import TracedArrivals, TracedLinks, paths_at, traced_first_arrivals
from diffpos.emulation import emulation_nodes
from diffpos.scenario import Radio
from diffpos_services.raytrace.live import LiveTraceSettings, grid_times, trace_links
from diffpos_services.scenario_io import load_scenario_option


def subgrid(links: TracedLinks, idx: np.ndarray) -> TracedLinks:
    """The traced epochs ``idx`` of ``links`` only."""
    return TracedLinks(**{f.name: getattr(links, f.name)[idx]
                          for f in dataclasses.fields(TracedLinks)})


def arrivals(links: TracedLinks, at: TracedLinks, radio: Radio) -> TracedArrivals:
    """Noise-free first arrivals of ``links`` at the epochs (times, positions) of ``at``."""
    return traced_first_arrivals(links, at.t_s, at.anchor_m, at.nodes_m, radio=radio, rng=None)


def compare_arrivals(ref: TracedArrivals, test: TracedArrivals, mask: np.ndarray) -> dict:
    """First-arrival agreement on the links of ``mask`` ((B, N) bool)."""
    both = ref.detected & test.detected & mask
    same = both & (ref.key == test.key)
    diff = np.abs(test.true_path_m - ref.true_path_m)
    pct = lambda a, q: float(np.percentile(a, q)) if a.size else float("nan")  # noqa: E731
    return {"links": int(mask.sum()),
            "detection_differs": int(((ref.detected != test.detected) & mask).sum()),
            "same_path": int(same.sum()), "other_path": int((both & ~same).sum()),
            "same_path_abs_m": {"p50": pct(diff[same], 50), "p99": pct(diff[same], 99),
                                "max": pct(diff[same], 100)},
            "all_abs_m": {"p50": pct(diff[both], 50), "p95": pct(diff[both], 95),
                          "max": pct(diff[both], 100)},
            "rmse_m": float(np.sqrt(np.mean(diff[both] ** 2))) if both.any() else float("nan")}


def path_errors(fine: TracedLinks, coarse: TracedLinks, mask_t: np.ndarray) -> np.ndarray:
    """|interpolated - traced| length of every path with the same key at the fine times
    ``mask_t`` [m]."""
    sel = np.flatnonzero(mask_t)
    p = paths_at(coarse, fine.t_s[sel], fine.anchor_m[sel], fine.nodes_m[sel])
    out = []
    for b, e in enumerate(sel):
        for i in range(fine.nodes_m.shape[1]):
            ref = dict(zip(fine.key[e, i][fine.valid[e, i]], fine.length_m[e, i][fine.valid[e, i]],
                           strict=True))
            got = p.key[b, i][p.valid[b, i]], p.length_m[b, i][p.valid[b, i]]
            out += [abs(ln - ref[k]) for k, ln in zip(*got, strict=True) if k in ref]
    return np.asarray(out)


def _table(rows: list[tuple[str, dict, np.ndarray | None]]) -> str:
    head = ("| compared | links | detection differs | same first path | other first path | "
            "same path: |d| p50 / p99 / max [mm] | all detected: |d| p50 / p95 / max [m] | "
            "RMSE [m] | path length |d| p99 / max [mm] |")
    lines = [head, "| " + " | ".join(["---"] + ["---:"] * 8) + " |"]
    for name, c, perr in rows:
        s, a = c["same_path_abs_m"], c["all_abs_m"]
        pe = ("-" if perr is None or not perr.size else
              f"{1e3 * np.percentile(perr, 99):.3f} / {1e3 * perr.max():.3f}")
        lines.append(
            f"| {name} | {c['links']} | {c['detection_differs']} "
            f"({100 * c['detection_differs'] / max(c['links'], 1):.1f} %) | "
            f"{c['same_path']} ({100 * c['same_path'] / max(c['links'], 1):.1f} %) | "
            f"{c['other_path']} | {1e3 * s['p50']:.3f} / {1e3 * s['p99']:.3f} / "
            f"{1e3 * s['max']:.3f} | {a['p50']:.3f} / {a['p95']:.3f} / {a['max']:.3f} | "
            f"{c['rmse_m']:.3f} | {pe} |")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> dict[str, Any]:
    scenario = load_scenario_option(args.scenario)
    nodes = emulation_nodes(scenario)
    times = grid_times(args.span_s, args.fine_step_s)
    ids = [a.id for a in scenario.anchors]
    st = LiveTraceSettings(samples=int(args.samples), depth=args.depth, step_s=args.fine_step_s)

    def bar(done: int, total: int, aid: str) -> None:
        print(f"\r  traced {done}/{total} ({aid}) {time.perf_counter() - t0:.0f} s",
              end="", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    fine = trace_links(scenario, nodes, times, ids, st, progress=bar)
    t_fine = time.perf_counter() - t0
    print(f"\nfine grid: {len(times)} times x {len(ids)} anchors in {t_fine:.0f} s "
          f"({t_fine / (len(times) * len(ids)):.2f} s per trace)", file=sys.stderr)
    rows: list[tuple[str, dict, np.ndarray | None]] = []
    radio = scenario.radio
    for step in args.steps:
        n = round(step / args.fine_step_s)
        idx = np.arange(0, len(times), n)
        if idx[-1] != len(times) - 1:
            idx = idx[idx <= len(times) - 1 - (len(times) - 1) % n]
        span = slice(0, idx[-1] + 1)
        off = np.ones(len(times), bool)
        off[idx] = False
        off[span.stop:] = False
        refs, tests, perrs = [], [], []
        for aid in ids:
            f = fine[aid]
            c = subgrid(f, idx)
            fs = subgrid(f, np.arange(span.stop))
            refs.append(arrivals(f, fs, radio))
            tests.append(arrivals(c, fs, radio))
            perrs.append(path_errors(f, c, off[:span.stop]))
        mask = np.concatenate([np.repeat(off[:span.stop, None], len(nodes), 1)] * len(ids))
        cat = lambda xs: TracedArrivals(**{k.name: np.concatenate(  # noqa: E731
            [getattr(x, k.name) for x in xs]) for k in dataclasses.fields(TracedArrivals)})
        rows.append((f"step {step:g} s vs every {args.fine_step_s:g} s (times between)",
                     compare_arrivals(cat(refs), cat(tests), mask), np.concatenate(perrs)))
    if args.seed2 is not None:
        st2 = dataclasses.replace(st, seed=args.seed2)
        t0 = time.perf_counter()
        fine2 = trace_links(scenario, nodes, times, ids, st2, progress=bar)
        print(file=sys.stderr)
        ra = [arrivals(fine[a], fine[a], radio) for a in ids]
        rb = [arrivals(fine2[a], fine[a], radio) for a in ids]
        cat = lambda xs: TracedArrivals(**{k.name: np.concatenate(  # noqa: E731
            [getattr(x, k.name) for x in xs]) for k in dataclasses.fields(TracedArrivals)})
        a_, b_ = cat(ra), cat(rb)
        rows.append((f"seed {args.seed2} vs seed {st.seed}, every {args.fine_step_s:g} s",
                     compare_arrivals(a_, b_, np.ones(a_.detected.shape, bool)), None))
    print(f"{scenario.name}: {len(ids)} anchors x {len(nodes)} nodes, {args.span_s:g} s, "
          f"{st.samples:.0e} samples, depth {st.depth}")
    print(_table(rows))
    return {"rows": rows}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m diffpos_services.raytrace.live_check",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("scenario", nargs="?", help="scenario file or shipped name (default: the "
                   "paper's geometry with moving responders, as diffpos emulate)")
    p.add_argument("--span-s", type=float, default=4.0, help="traced span [s] (default 4)")
    p.add_argument("--fine-step-s", type=float, default=0.1,
                   help="the reference grid step [s] (default 0.1: every epoch at 10 Hz)")
    p.add_argument("--steps", type=float, nargs="+", default=[0.5, 1.0],
                   help="coarse grid steps to check [s], multiples of the fine step")
    p.add_argument("--samples", type=float, default=3e5, help="rays per source (default 3e5)")
    p.add_argument("--depth", type=int, default=4, help="max interactions (default 4)")
    p.add_argument("--seed2", type=int, default=None,
                   help="also trace the fine grid with this sampling seed (the baseline)")
    run(p.parse_args(argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
