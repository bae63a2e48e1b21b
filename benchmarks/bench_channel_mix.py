"""First-arrival mix per family: Sionna RT vs the emulator at each ``channel_max_order``.

Usage::

    python benchmarks/bench_channel_mix.py [DATASET.npz ...] [--orders 2 3 4]
        [--mnls] [--mnls-max-order 2]
    python benchmarks/bench_channel_mix.py --tracker [default scenarios/large.toml]
        [--orders 2 4] [--epochs 200]
    python benchmarks/bench_channel_mix.py --cost [--orders 2 3 4]
    python benchmarks/bench_channel_mix.py --live paper scenarios/large.toml --out DIR
        [--orders 2 3] [--duration 20]

For every ray-trace dataset (``diffpos raytrace SCEN --receivers 200 --samples 1e6
--max-depth 4``; default the paper building and its open-plan variant traced with the
diffraction-distance correction, /work/rt/fixed/), the
first arrival of every (receiver, anchor) link is classified into a family
(:func:`diffpos.paths.mechanisms.label_family`: direct; reflections only, by count; a window-edge
diffraction alone, then one or more slab reflections; a ground bounce before the diffraction;
a diffraction on a vertical window edge; any wall or partition reflection; other; none):

* Sionna: :func:`diffpos_services.raytrace.evaluate.dataset_first_arrival` (the emulator's
  detector on the traced paths) and the traced chain's label
  (:func:`diffpos_services.raytrace.mechanisms.classify_mechanisms`);
* the emulator on the SAME receivers and anchors with the dataset scenario's radio and
  ``channel_max_order`` = each of ``--orders`` (:func:`diffpos.channel.emulator.emulate_channel`
  + :func:`diffpos.channel.emulator.first_arrival`, noise-free: the family does not depend on
  the range noise), the first arrival's slot label.

Prints per building a table of shares [% of links] and, per order, the largest difference to
Sionna over the families (the goal: <= 5 points); then the same over the links with no
interior partition between the facade and the receiver (the straight anchor -> receiver line
crosses none inside): there Sionna's depth limit (every partition crossing is one of its
``--max-depth`` interactions) cannot hide a family of order <= 4, elsewhere it can (a link
behind two partitions has no traced D+RR path at depth 4, and often none at all). Sionna's
first arrival also depends on its samples per source: at 1e6 it misses short diffracted
paths that 4e6 samples find (docs/channel_mix.md, session 21), so compare against a trace
with enough samples before reading a gap as the emulator's.

``--mnls``: the consequence for positioning: M-NLS (``--mnls-max-order``) right floor over ALL
receivers (a failed fix is a miss) with :func:`diffpos.study.reproduce` on Sionna's first
arrivals (``diffpos reproduce --channel raytrace:FILE``) and on the emulator's at every order,
same receivers, anchors and noise seed.

``--tracker [SCENARIO ...]``: instead, the live tracker on the emulator's channel at every
order: ``benchmarks/bench_tracker_raytrace.py --emulator SCENARIO --epochs N`` (its scenarios,
epochs, configurations and scorer, imported from that script) with the scenario's radio set to
``channel_max_order`` = each order.

``--cost``: CPU per (anchor, node) pair of :func:`diffpos.channel.emulator.pair_first_arrival`
(what an emulated anchor runs per epoch) at every order, on 20,000 random pairs of the paper
scenario (the kernels warmed first; best of 3).

``--live SCENARIO ... --out DIR``: the whole live system on the emulator's channel at every
order: for each scenario (a file or a shipped name; ``paper`` is also what ``diffpos emulate``
runs without a scenario) and order, ``DIR/NAME-oN.toml`` (the scenario with ``[radio]
channel_max_order = N``, checked to load back equal) and ``diffpos emulate DIR/NAME-oN.toml
--speed 0 --duration S --record DIR/NAME-oN.mcap --dashboard off --no-progress`` (lockstep, seed
0), scored by ``common.score_recording`` over ALL node-epochs and after the first 2 s (right
floor, availability, a wrong floor published at p >= 0.95, 95 % ellipsoid), with the run's CPU
(user + sys of the emulate process and its services). Never writes over a file in DIR. The
figures: ``docs/channel_mix.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import os
import resource
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from diffpos_services.raytrace.dataset import load_dataset
from diffpos_services.raytrace.evaluate import dataset_first_arrival
from diffpos_services.raytrace.mechanisms import classify_mechanisms
from diffpos_services.scenario_io import load_scenario, resolve_scenario
from heldout import to_toml

from diffpos.channel.emulator import emulate_channel, first_arrival, pair_first_arrival
from diffpos.paths.mechanisms import FAMILIES, label_family
from diffpos.scenario import default_scenario
from diffpos.study import Arrivals, FirstArrivalData, ReproduceConfig, reproduce

DEFAULT = ["/work/rt/fixed/paper.npz", "/work/rt/fixed/openplan.npz"]


def shares(labels: np.ndarray) -> dict[str, float]:
    """Family -> % of the links whose first-arrival label is ``labels`` (any shape)."""
    fam = Counter(label_family(str(x)) for x in np.ravel(labels))
    n = max(int(np.size(labels)), 1)
    return {f: 100.0 * fam.get(f, 0) / n for f in FAMILIES}


def sionna_labels(ds) -> np.ndarray:
    """The traced first arrival's chain label per link (``"none"`` where undetected)."""
    fr = dataset_first_arrival(ds, radio=ds.scenario.radio)
    mech = classify_mechanisms(ds)
    lab = np.take_along_axis(mech.label, np.maximum(fr.slot, 0)[..., None], axis=-1)[..., 0]
    return np.where(fr.detected, lab, "none")


def emulator_labels(ds, order: int) -> np.ndarray:
    """The emulator's first-arrival label per link at ``channel_max_order`` = ``order``."""
    radio = dataclasses.replace(ds.scenario.radio, channel_max_order=order)
    ch = emulate_channel(ds.anchors_m, ds.nodes_m, building=ds.scenario.building, radio=radio)
    fa = first_arrival(ch, radio=radio)
    names = np.array([*ch.mechanism, "none"], dtype=object)
    return names[np.where(fa.detected, fa.slot, len(ch.mechanism))]


def open_links(ds) -> np.ndarray:
    """(N, M) bool: the straight anchor -> receiver line crosses no partition inside."""
    b = ds.scenario.building
    a = np.asarray(ds.anchors_m)[None]
    n = np.asarray(ds.nodes_m)[:, None]
    d = n - a
    entry = a + (-a[..., 1] / d[..., 1])[..., None] * d
    clear = np.ones(d.shape[:2], dtype=bool)
    for p in b.partitions:
        ax = 0 if p.axis == "x" else 1
        u, v = entry[..., ax] - p.position_m, n[..., ax] - p.position_m
        with np.errstate(invalid="ignore", divide="ignore"):
            t = u / (u - v)
            o = entry[..., 1 - ax] + t * (n[..., 1 - ax] - entry[..., 1 - ax])
        clear &= ~((u * v < 0) & (o > p.span_m[0]) & (o < p.span_m[1]))
    return clear


def building_mix(ds, orders: list[int], keep: np.ndarray | None = None
                 ) -> dict[str, dict[str, float]]:
    """Column name -> family shares for one dataset (over the links ``keep``, default all)."""
    sel = (lambda x: x) if keep is None else (lambda x: x[keep])
    cols = {"Sionna": shares(sel(sionna_labels(ds)))}
    for o in orders:
        cols[f"emu {o}"] = shares(sel(emulator_labels(ds, o)))
    return cols


def mnls_right_floor(path: str, ds, orders: list[int], mnls_order: int, seed: int = 0
                     ) -> dict[str, float]:
    """M-NLS right floor over all receivers [%]: Sionna, then the emulator at every order."""
    cfg = ReproduceConfig(seed=seed, methods=("mnls",), mnls_max_order=mnls_order)
    out = {}

    def right(sc, load) -> float:
        res = reproduce(sc, cfg, kind="bench", load=load)
        return 100.0 * float(res.study.summary()["mnls"]["floor_accuracy"])

    from diffpos_services.raytrace.evaluate import dataset_arrivals
    sc = ds.scenario
    out["Sionna"] = right(sc, lambda rng: dataset_arrivals(path, sc, rng=rng))
    for o in orders:
        radio = dataclasses.replace(sc.radio, channel_max_order=o)

        def load(rng, radio=radio) -> Arrivals:
            ch = emulate_channel(ds.anchors_m, ds.nodes_m, building=sc.building, radio=radio)
            fa = first_arrival(ch, radio=radio, rng=rng)
            return Arrivals(data=FirstArrivalData.from_channel(fa, ds.anchors_m, ds.nodes_m))

        out[f"emu {o}"] = right(dataclasses.replace(sc, radio=radio), load)
    return out


def table(name: str, cols: dict[str, dict[str, float]], links: int) -> str:
    head = f"{name} ({links} links)"
    keys = list(cols)
    lines = [f"{head:<34}" + "".join(f"{k:>10}" for k in keys)]
    for f in FAMILIES:
        if all(cols[k][f] == 0 for k in keys):
            continue
        lines.append(f"  {f:<32}" + "".join(f"{cols[k][f]:>10.2f}" for k in keys))
    ref = cols["Sionna"]
    worst = []
    for k in keys[1:]:
        d = {f: cols[k][f] - ref[f] for f in FAMILIES}
        f = max(d, key=lambda x: abs(d[x]))
        worst.append(f"{k}: {d[f]:+.2f} ({f})")
    lines.append("  max |emulator - Sionna| [points]: " + "; ".join(worst))
    return "\n".join(lines)


def tracker_on_orders(names: list[str], orders: list[int], epochs: int, seed: int) -> None:
    """``bench_tracker_raytrace.py --emulator NAME`` at every channel order (module docstring)."""
    spec = importlib.util.spec_from_file_location(
        "bench_tracker_raytrace", Path(__file__).with_name("bench_tracker_raytrace.py"))
    btr = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(btr)
    cfgs = btr.configs({}, {})
    for name in names:
        base = btr.emulator_scenario(name)
        for o in orders:
            sc = dataclasses.replace(base, radio=dataclasses.replace(base.radio,
                                                                      channel_max_order=o))
            res = btr.run_emulator(sc, cfgs, n_epochs=epochs, seed=seed)
            btr.print_table(f"emulator: {name}, channel_max_order {o} ({len(sc.nodes)} nodes x "
                            f"{len(sc.anchors)} anchors, {epochs} epochs, seed {seed}; load "
                            f"{os.getloadavg()[0]:.1f})", res)


def pair_cost_us(orders: list[int], n: int = 20_000) -> dict[int, float]:
    """CPU microseconds per pair of :func:`pair_first_arrival` at every order (``--cost``)."""
    import time

    sc = default_scenario()
    b = sc.building
    rng = np.random.default_rng(0)
    k = rng.integers(0, b.n_floors, n)
    nodes = np.stack([rng.uniform(-19.5, 19.5, n), rng.uniform(0.2, 22.3, n),
                      b.floor_z_m(k) + rng.uniform(0.1, 2.9, n)], axis=-1)
    anchors = sc.anchor_positions_m()[rng.integers(0, len(sc.anchors), n)]
    out = {}
    for o in orders:
        radio = dataclasses.replace(sc.radio, channel_max_order=o)
        pair_first_arrival(anchors[:10], nodes[:10], building=b, radio=radio)  # warm
        best = np.inf
        for _ in range(3):
            t0 = time.process_time()
            pair_first_arrival(anchors, nodes, building=b, radio=radio)
            best = min(best, time.process_time() - t0)
        out[o] = 1e6 * best / n
    return out


def order_copy(scenario: str, order: int, out_dir: Path) -> Path:
    """``out_dir/NAME-oORDER.toml``: ``scenario`` with ``channel_max_order = order`` (a new
    file, checked to load back as the same scenario)."""
    src = resolve_scenario(scenario)
    sc = load_scenario(src)
    want = dataclasses.replace(sc, radio=dataclasses.replace(sc.radio, channel_max_order=order))
    path = out_dir / f"{Path(src).stem}-o{order}.toml"
    if path.exists():
        raise FileExistsError(f"{path} exists: remove it or choose another --out")
    path.write_text(f"# {src} with channel_max_order = {order} (bench_channel_mix.py --live)\n\n"
                    + to_toml(want.to_dict()))
    back = load_scenario(path)
    if (back.building, back.radio, back.anchors, back.nodes, back.node_grid) != (
            want.building, want.radio, want.anchors, want.nodes, want.node_grid):
        raise RuntimeError(f"{path} does not load back as {src} at order {order}")
    return path


def live_score(rec: Path, skip_s: float) -> dict[str, float]:
    """Right floor, availability, confidently wrong, 95 % ellipsoid [%] of a recording."""
    from common import score_recording

    s = score_recording(rec, skip_s=skip_s)
    return {"node-epochs": s["node_epochs"], "right floor": 100 * s["floor"],
            "availability": 100 * s["availability"],
            "conf. wrong": 100 * (s["floor_calibration"] or {}).get("confidently_wrong", 0.0),
            "95% ellipsoid": 100 * s["coverage95"]}


def live_runs(scenarios: list[str], orders: list[int], out_dir: Path, duration: float) -> None:
    """``--live`` (module docstring): one lockstep run per scenario and order, scored."""
    out_dir.mkdir(parents=True, exist_ok=True)
    print(f"{'run':<16}{'load':>6}{'CPU s':>8}{'scored':>8}{'epochs':>8}{'right %':>9}"
          f"{'avail %':>9}{'cw %':>7}{'ell95 %':>9}")
    for scen in scenarios:
        for o in orders:
            toml = order_copy(scen, o, out_dir)
            rec = toml.with_suffix(".mcap")
            if rec.exists():
                raise FileExistsError(f"{rec} exists: remove it or choose another --out")
            load = os.getloadavg()[0]
            ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cmd = [sys.executable, "-m", "diffpos_services.cli.main", "emulate", str(toml),
                   "--speed", "0", "--duration", str(duration), "--record", str(rec),
                   "--dashboard", "off", "--no-progress"]
            with open(toml.with_suffix(".out"), "w") as log:
                rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode
            ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            if rc != 0:
                raise RuntimeError(f"{' '.join(cmd)} exited {rc}: see {toml.with_suffix('.out')}")
            cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
            for skip, what in ((0.0, "all"), (2.0, "after 2 s")):
                r = live_score(rec, skip)
                print(f"{toml.stem:<16}{load:>6.1f}{cpu:>8.1f}{what:>10}{r['node-epochs']:>8}"
                      f"{r['right floor']:>9.2f}{r['availability']:>9.2f}{r['conf. wrong']:>7.2f}"
                      f"{r['95% ellipsoid']:>9.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("datasets", nargs="*", default=DEFAULT)
    ap.add_argument("--orders", type=int, nargs="+", default=[2, 3, 4])
    ap.add_argument("--mnls", action="store_true", help="also M-NLS's right floor")
    ap.add_argument("--mnls-max-order", type=int, default=2, choices=(2, 3, 4))
    ap.add_argument("--tracker", nargs="*", default=None, metavar="SCENARIO",
                    help="instead: the tracker on the emulator at every order ('default' or a "
                         "TOML file; default: default scenarios/large.toml)")
    ap.add_argument("--epochs", type=int, default=200, help="--tracker's epochs")
    ap.add_argument("--seed", type=int, default=0, help="--tracker's seed")
    ap.add_argument("--cost", action="store_true", help="instead: pair_first_arrival's CPU")
    ap.add_argument("--live", nargs="+", default=None, metavar="SCENARIO",
                    help="instead: diffpos emulate (lockstep) at every order, scored")
    ap.add_argument("--out", type=Path, help="--live's directory (scenario copies, recordings)")
    ap.add_argument("--duration", type=float, default=20.0, help="--live's run length [s]")
    args = ap.parse_args()
    if args.live is not None:
        if args.out is None:
            ap.error("--live needs --out DIR (the scenario copies and recordings go there)")
        live_runs(args.live, args.orders, args.out, args.duration)
        return
    if args.cost:
        for o, us in pair_cost_us(args.orders).items():
            print(f"channel_max_order {o}: pair_first_arrival {us:.2f} us CPU per pair "
                  f"(load {os.getloadavg()[0]:.1f})")
        return
    if args.tracker is not None:
        tracker_on_orders(args.tracker or ["default", "scenarios/large.toml"], args.orders,
                          args.epochs, args.seed)
        return
    for path in args.datasets:
        ds = load_dataset(path)
        name = Path(path).name
        print(table(name, building_mix(ds, args.orders), ds.nodes_m.shape[0]
                    * ds.anchors_m.shape[0]))
        keep = open_links(ds)
        if not keep.all():
            print(table(f"{name}, no partition on the way", building_mix(ds, args.orders, keep),
                        int(keep.sum())))
        if args.mnls:
            rf = mnls_right_floor(path, ds, args.orders, args.mnls_max_order)
            print(f"  M-NLS (max order {args.mnls_max_order}) right floor, all "
                  f"{ds.nodes_m.shape[0]} receivers [%]: "
                  + "  ".join(f"{k} {v:.1f}" for k, v in rf.items()))
        print()


if __name__ == "__main__":
    main()
