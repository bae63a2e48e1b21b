"""M-NLS on Sionna RT's channel vs the project's emulator, per building (issue 34's study).

    python benchmarks/study_raytrace.py                      # the default buildings below
    python benchmarks/study_raytrace.py --orders 2 4 --only paper heldout-1
    python benchmarks/study_raytrace.py --building NAME=SCENARIO.toml:DATASET.npz ...
    python benchmarks/study_raytrace.py --misses --orders 3 --only paper   # the misses, per link

For every building (a scenario and a dataset of ``diffpos raytrace SCEN --receivers 200
--samples 1000000 --max-depth 4``) and every M-NLS mechanism order K (``--orders``, default 2 3
4: ``diffpos reproduce --mnls-max-order K``), the study runs exactly what

    diffpos reproduce --scenario SCEN --channel raytrace:DATASET --methods mnls --mnls-max-order K

runs (:func:`diffpos.study.reproduce` with
:func:`diffpos_services.raytrace.evaluate.dataset_arrivals`, seed 0: the emulator's detector
and range noise on Sionna's paths), and the same study on the project's own O2I emulator for
the SAME receivers and anchors (the dataset's receivers as static nodes of the scenario:
:func:`diffpos.study.emulator_arrivals`; ``--emulator-order K``: the emulated channel with the
higher-order families M-NLS models at that K, ``radio.channel_max_order = K``, instead of the
scenario's 18 mechanisms; ``--emulator-order 3``: channel order 3 whatever K, the window edges
dielectric sheets). It prints, per channel, the right floor of M-NLS

- over the receivers with at least three detected anchors on that channel (``n>=3`` of them),
- over ALL receivers (a failed fix, or a receiver with fewer than three detections, is a miss:
  :func:`diffpos.study.floor_accuracy`),
- and the confidently wrong share (``conf.wrong``): receivers with at least three detected
  anchors whose M-NLS floor is wrong at a floor probability >= 0.95 (issue 34's honesty bar),
  from M-NLS's floor posterior on the same inputs (:func:`mnls_fixes`: the study's own call
  repeated, its positions checked equal to the study's).

The default buildings: the paper building (``paper``: the built-in scenario, partitions), its
open-plan variant (``openplan``: /work/rt/openplan.toml, no partitions) and three random
held-out buildings with partitions (``heldout-1..3``: ``python benchmarks/heldout.py
--write-scenarios /work/rt --count 3 --seed 3``, traced as above into
/work/rt/heldout-K.npz). Figures, command, date and machine: docs/raytrace_study.md.

``--misses`` (Sionna's channel only): per building and K, the receivers with at least three
detected anchors split by their links' traced first arrivals (the ray tracer's classifier,
:func:`diffpos_services.raytrace.mechanisms.classify_mechanisms` on
``mechanism_set(K, partitions=True)``): every link a family of M-NLS's set without the
partition families / some link a partition family (none else out) / some link out of every
family; right floor and confidently wrong of each group; then per missed receiver its floor
posterior and per link the traced chain beside the mechanism M-NLS chose on its answer.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from common import machine
from diffpos_services.raytrace.dataset import load_dataset
from diffpos_services.raytrace.evaluate import dataset_arrivals
from diffpos_services.scenario_io import scenario_or_default

from diffpos.estimators.mnls.rules import DEFAULT_SNR_RULE, SnrRule
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import NodeSpec, Scenario
from diffpos.study import ReproduceConfig, floor_accuracy, reproduce
from diffpos.trajectory import Static

RT = Path("/work/rt")
#: name -> (scenario file or None for the built-in paper scenario, dataset)
BUILDINGS: dict[str, tuple[str | None, Path]] = {
    "paper": (None, RT / "paper-200-1e6-d4.npz"),
    "openplan": (str(RT / "openplan.toml"), RT / "openplan-200-1e6-d4.npz"),
    **{f"heldout-{k}": (str(RT / f"heldout-{k}.toml"), RT / f"heldout-{k}.npz")
       for k in (1, 2, 3)},
}
MIN_ANCHORS = 3
#: A wrong floor published at this probability or more is "confidently wrong".
CONFIDENT_P = 0.95


def same_receivers(scenario: Scenario, nodes_m: np.ndarray) -> Scenario:
    """``scenario`` with ``nodes_m`` as its receivers (static nodes ``r000``, ...; no grid):
    what the emulator study needs to run on a dataset's receivers."""
    nodes = tuple(NodeSpec(f"r{i:03d}", Static(tuple(float(v) for v in p)))
                  for i, p in enumerate(np.asarray(nodes_m, dtype=float)))
    return dataclasses.replace(scenario, node_grid=None, nodes=nodes)


def mnls_fixes(data: Any, scenario: Scenario, order: int, rule: SnrRule = DEFAULT_SNR_RULE
               ) -> Any:
    """M-NLS's fixes (:class:`~diffpos.estimators.mnls.result.MnlsResult`) on a study's first
    arrivals ``data``: the call :func:`diffpos.study.positioning_study` makes (same inputs and
    settings)."""
    mask = np.asarray(data.detected, dtype=bool)
    anchors = np.asarray(data.anchors_m, dtype=np.float64)
    a = np.broadcast_to(anchors, (mask.shape[0], *anchors.shape))
    radio = scenario.radio
    return mnls(a, np.where(mask, data.range_m, 0.0), np.where(mask, data.sigma_m, 1.0),
                mask=mask, building=scenario.building, snr_db=data.snr_db, radio=radio,
                max_order=order, bandwidth_hz=radio.bandwidth_hz,
                error_floor_m=radio.range_error_floor_m, snr_rule=rule)


def floor_shares(positions_m: np.ndarray, truth_m: np.ndarray, detected: np.ndarray,
                 building: Any, *, min_anchors: int = MIN_ANCHORS,
                 floor_probability: np.ndarray | None = None) -> dict[str, float | int]:
    """Right-floor shares of one study: ``n`` receivers, ``n_det`` of them with at least
    ``min_anchors`` detected anchors, ``floor_det`` the right floor over those, ``floor_all``
    over all (a failed fix is a miss); with ``floor_probability`` (N, F), ``conf_wrong``: the
    share of those ``n_det`` whose floor is wrong at probability >= :data:`CONFIDENT_P`."""
    ok = np.asarray(detected, dtype=bool).sum(axis=1) >= min_anchors
    pos, tru = np.asarray(positions_m, float), np.asarray(truth_m, float)
    out = {"n": len(tru), "n_det": int(ok.sum()),
           "floor_det": floor_accuracy(pos[ok], tru[ok], building) if ok.any() else float("nan"),
           "floor_all": floor_accuracy(pos, tru, building), "conf_wrong": float("nan")}
    if floor_probability is not None and ok.any():
        fp = np.nan_to_num(np.asarray(floor_probability, float)[ok])
        est = np.argmax(fp, axis=1)
        has = np.isfinite(pos[ok, 2])
        wrong = has & (est != building.floor_index(tru[ok, 2]))
        out["conf_wrong"] = float(np.mean(wrong & (fp[np.arange(len(est)), est] >= CONFIDENT_P)))
    return out


def study(scenario: Scenario, dataset: Path, order: int, seed: int = 0, *,
          emulator_order: int | None = None, rule: SnrRule = DEFAULT_SNR_RULE
          ) -> dict[str, dict[str, float | int]]:
    """``{"raytrace": shares, "emulator": shares}`` of M-NLS at mechanism order ``order``;
    ``emulator_order``: the emulated channel's ``radio.channel_max_order`` (None: the
    scenario's, 2 by default: the 18 mechanisms only)."""
    cfg = ReproduceConfig(seed=seed, methods=("mnls",), mnls_max_order=order,
                          mnls_measured_threshold=rule.measured_threshold,
                          mnls_first_arrival_prior=rule.first_arrival_prior,
                          mnls_keep_hard_rule=rule.keep_hard_rule,
                          mnls_dielectric_edges=rule.dielectric_edges,
                          mnls_floor_box=rule.floor_box,
                          mnls_shadow_starts=rule.shadow_starts,
                          mnls_path_region=rule.path_region)
    out = {}
    rt = reproduce(scenario, cfg, kind="raytrace", path=dataset,
                   load=lambda rng: dataset_arrivals(dataset, scenario, rng=rng))
    em_scenario = same_receivers(scenario, rt.data.nodes_m)
    if emulator_order is not None:
        em_scenario = dataclasses.replace(em_scenario, radio=dataclasses.replace(
            scenario.radio, channel_max_order=int(emulator_order)))
    em = reproduce(em_scenario, cfg)
    for name, res in (("raytrace", rt), ("emulator", em)):
        fix = mnls_fixes(res.data, scenario, order, rule)
        if not np.array_equal(fix.position_m, res.study.positions_m["mnls"], equal_nan=True):
            raise RuntimeError(f"{name}: mnls_fixes's positions differ from the study's "
                               "(its M-NLS call no longer matches positioning_study's)")
        out[name] = floor_shares(res.study.positions_m["mnls"], res.data.nodes_m,
                                 res.data.detected, scenario.building,
                                 floor_probability=fix.floor_probability)
    return out


def misses(scenario: Scenario, dataset: Path, order: int, seed: int = 0, *,
           per_link: bool = True) -> str:
    """The ``--misses`` report (module docstring) of M-NLS at ``order`` on Sionna's channel."""
    from diffpos_services.raytrace.mechanisms import classify_mechanisms

    from diffpos.paths.mechanisms import mechanism_set
    from diffpos.study import study_rngs

    ds = load_dataset(dataset, scenario=scenario)
    data = dataset_arrivals(dataset, scenario, rng=study_rngs(seed)[1]).data
    fa_slot = dataset_first_arrival_slot(dataset, scenario, seed)  # the same draw
    plain, full = mechanism_set(order), mechanism_set(order, partitions=True)
    cl = classify_mechanisms(ds, full)
    code = np.take_along_axis(cl.code, fa_slot[..., None], -1)[..., 0]
    label = np.take_along_axis(cl.label, fa_slot[..., None], -1)[..., 0]
    det = np.asarray(data.detected, dtype=bool)
    part = det & (code >= len(plain))
    out = det & ((code < 0) | (code >= len(full)))
    res = mnls_fixes(data, scenario, order)
    pos, prob = res.position_m, res.floor_probability
    b = scenario.building
    truth = b.floor_index(np.asarray(data.nodes_m)[:, 2])
    est = np.argmax(np.nan_to_num(prob), axis=1)
    right = np.isfinite(pos[:, 2]) & (est == truth)
    conf = np.nan_to_num(prob)[np.arange(len(est)), est] >= CONFIDENT_P
    ok3 = det.sum(axis=1) >= MIN_ANCHORS
    groups = {"every link in the K families": ok3 & ~part.any(1) & ~out.any(1),
              "a partition family (no other out)": ok3 & part.any(1) & ~out.any(1),
              "a link out of every family": ok3 & out.any(1)}
    lines = [f"K = {order}: {ok3.sum()} receivers with >= {MIN_ANCHORS} anchors, right "
             f"{np.sum(right & ok3)}, confidently wrong {np.sum(~right & conf & ok3)}"]
    for name, g in groups.items():
        lines.append(f"  {name}: {g.sum()} receivers, right {np.sum(right & g)}, "
                     f"confidently wrong {np.sum(~right & conf & g)}")
    if not per_link:
        return "\n".join(lines)
    mech = mechanism_set(order, partitions=bool(b.partitions))
    for i in np.flatnonzero(ok3 & ~right):
        lines.append(f"  receiver {i}: floor {truth[i]}, M-NLS {est[i]}, p = "
                     f"{np.array2string(np.nan_to_num(prob[i]), precision=2)}")
        for j in np.flatnonzero(det[i]):
            s = res.mechanism[i, j]
            kind = "in" if not (part[i, j] or out[i, j]) else ("partition" if part[i, j] else "OUT")
            lines.append(f"    link {j}: traced {label[i, j]:<44s} {kind:9s} M-NLS "
                         f"{mech.labels[s] if s >= 0 else '-':<40s} "
                         f"{'excluded' if res.excluded[i, j] else ''}")
    return "\n".join(lines)


def dataset_first_arrival_slot(dataset: Path, scenario: Scenario, seed: int) -> np.ndarray:
    """The traced path index of every link's detected first arrival (the study's draw)."""
    from diffpos_services.raytrace.evaluate import dataset_first_arrival

    from diffpos.study import study_rngs

    ds = load_dataset(dataset, scenario=scenario)
    fa = dataset_first_arrival(ds, radio=scenario.radio, rng=study_rngs(seed)[1])
    return np.maximum(fa.slot, 0)


def _pct(v: float) -> str:
    return "   -  " if v != v else f"{100 * v:5.1f}%"


def table(rows: list[tuple[str, int, dict[str, dict[str, float | int]]]]) -> str:
    head = (f"{'building':10s} {'K':>2s} | {'RT n>=3':>8s} {'RT floor>=3':>12s} "
            f"{'RT floor all':>13s} {'RT conf.wrong':>13s} | {'emu n>=3':>8s} "
            f"{'emu floor>=3':>13s} {'emu floor all':>14s} {'emu conf.wrong':>14s}")
    lines = [head, "-" * len(head)]
    for name, k, r in rows:
        a, e = r["raytrace"], r["emulator"]
        lines.append(f"{name:10s} {k:2d} | {a['n_det']:4d}/{a['n']:<3d} {_pct(a['floor_det']):>12s} "
                     f"{_pct(a['floor_all']):>13s} {_pct(a['conf_wrong']):>13s} | "
                     f"{e['n_det']:4d}/{e['n']:<3d} {_pct(e['floor_det']):>13s} "
                     f"{_pct(e['floor_all']):>14s} {_pct(e['conf_wrong']):>14s}")
    return "\n".join(lines)


def _buildings(specs: list[str] | None, only: list[str] | None) -> dict[str, tuple[str | None, Path]]:
    out = dict(BUILDINGS)
    for spec in specs or []:
        name, sep, rest = spec.partition("=")
        scen, sep2, ds = rest.rpartition(":")
        if not sep or not sep2:
            sys.exit(f"--building {spec!r}: expected NAME=SCENARIO.toml:DATASET.npz")
        out[name] = (None if scen == "paper" else scen, Path(ds))
    if only:
        unknown = [n for n in only if n not in out]
        if unknown:
            sys.exit(f"--only: unknown building(s) {unknown}; known: {list(out)}")
        out = {n: out[n] for n in only}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--orders", type=int, nargs="+", default=[2, 3, 4], choices=(2, 3, 4),
                    help="M-NLS mechanism orders (diffpos reproduce --mnls-max-order)")
    ap.add_argument("--only", nargs="+", help=f"only these buildings ({', '.join(BUILDINGS)})")
    ap.add_argument("--building", action="append", metavar="NAME=SCENARIO.toml:DATASET.npz",
                    help="another building (SCENARIO 'paper' = the built-in one); repeatable")
    ap.add_argument("--emulator-order", default="scenario",
                    choices=("scenario", "K", "2", "3", "4"),
                    help="the emulated channel's mechanism order: the scenario's (default: 2, "
                         "the 18 mechanisms), K, the same higher-order families M-NLS "
                         "models at that K (radio.channel_max_order = K), or 2, 3, 4 whatever K")
    ap.add_argument("--seed", type=int, default=0, help="range-noise seed (default 0)")
    ap.add_argument("--mnls-measured-threshold", action="store_true",
                    help="diffpos reproduce --mnls-measured-threshold (SnrRule)")
    ap.add_argument("--mnls-first-arrival-prior", type=float, default=0.0, metavar="W",
                    help="diffpos reproduce --mnls-first-arrival-prior (SnrRule; default 0)")
    ap.add_argument("--mnls-keep-hard-rule", action="store_true",
                    help="diffpos reproduce --mnls-keep-hard-rule (SnrRule)")
    ap.add_argument("--mnls-dielectric-edges", type=float, default=0.0, metavar="Q",
                    help="diffpos reproduce --mnls-dielectric-edges (SnrRule; default 0)")
    ap.add_argument("--mnls-floor-box", action="store_true",
                    help="diffpos reproduce --mnls-floor-box (SnrRule.floor_box; default off)")
    ap.add_argument("--mnls-shadow-starts", type=float, default=0.0, metavar="D",
                    help="diffpos reproduce --mnls-shadow-starts (SnrRule.shadow_starts; "
                         "default 0: off)")
    ap.add_argument("--mnls-path-region", action="store_true",
                    help="diffpos reproduce --mnls-path-region (SnrRule.path_region; needs "
                         "--mnls-floor-box; default off)")
    ap.add_argument("--misses", action="store_true",
                    help="the misses on Sionna's channel per traced first-arrival family")
    ap.add_argument("--summary", action="store_true",
                    help="with --misses: the groups only, not every missed receiver's links")
    args = ap.parse_args(argv)
    buildings = _buildings(args.building, args.only)
    missing = [str(ds) for _, ds in buildings.values() if not ds.is_file()]
    if missing:
        sys.exit(f"missing dataset(s): {', '.join(missing)} (trace them with diffpos raytrace; "
                 "or leave them out with --only)")
    if args.misses:
        for name, (scen, ds) in buildings.items():
            for k in args.orders:
                print(f"# {name}, {ds}")
                print(misses(scenario_or_default(scen), ds, k, seed=args.seed,
                             per_link=not args.summary), flush=True)
        return 0
    rows, t0 = [], time.perf_counter()
    for name, (scen, ds) in buildings.items():
        scenario = scenario_or_default(scen)
        st = load_dataset(ds, scenario=scenario).metadata.get("settings", {})
        print(f"# {name}: {scenario.name}, {ds}: {st.get('samples_per_src', 0):g} samples, "
              f"depth {st.get('max_depth')}", file=sys.stderr, flush=True)
        for k in args.orders:
            eo = (k if args.emulator_order == "K" else None if args.emulator_order == "scenario"
                  else int(args.emulator_order))
            rows.append((name, k, study(scenario, ds, k, seed=args.seed, emulator_order=eo,
                                        rule=SnrRule(
                    args.mnls_measured_threshold, args.mnls_first_arrival_prior,
                    args.mnls_keep_hard_rule, args.mnls_dielectric_edges,
                    args.mnls_floor_box, args.mnls_shadow_starts, args.mnls_path_region))))
            print(table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    print(f"study_raytrace: M-NLS right floor on Sionna RT's channel (RT) and the emulator's (emu) "
          f"for the same receivers and anchors, seed {args.seed}; K = --mnls-max-order; n>=3 = "
          f"receivers with >= {MIN_ANCHORS} detected anchors on that channel / all; floor>=3 over "
          f"those, floor all over ALL receivers (a failed fix is a miss); conf.wrong = wrong floor at "
          f"p >= {CONFIDENT_P} over the n>=3 receivers; emulator channel order: "
          f"{'the scenario radio.channel_max_order' if args.emulator_order == 'scenario' else args.emulator_order}")
    print(f"command: python benchmarks/study_raytrace.py {' '.join(argv or sys.argv[1:])}")
    print(f"date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC; machine: {machine()}; "
          f"wall {time.perf_counter() - t0:.0f} s\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
