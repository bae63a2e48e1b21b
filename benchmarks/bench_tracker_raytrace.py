"""The per-responder tracker on a channel we did not write: Sionna RT first arrivals.

Usage::

    python benchmarks/bench_tracker_raytrace.py [DATASET.npz] [--epochs 60] [--seed 0]
        [--nodes N] [--set KEY=VALUE ...] [--before KEY=VALUE ...]

The receivers of a ray-trace dataset (``diffpos raytrace SCEN --receivers 200 --samples 1e6
--max-depth 4``; default ``/work/rt/paper-200-1e6-d4.npz``: the paper building, 200 receivers,
4 hovering anchors) are static responders tracked over ``--epochs`` lockstep epochs at 10 Hz
(:func:`diffpos.tracking.tracker.update`). Every epoch draws fresh first arrivals from the
traced paths (:func:`diffpos_services.raytrace.evaluate.dataset_first_arrival`: the emulator's
detector and noise on Sionna's paths, so range noise, detection and SNR are those of the live
channel, the paths are not the path model's), and the anchors are reported with the GNSS error
of ``benchmarks/bench_tracking.py`` (per-anchor bias + white noise, 2 cm / 3 cm). Two tracker
configurations run on the SAME epochs: ``before`` (the new evidence settings off:
:data:`EVIDENCE_OFF`, i.e. the tracker as it was, or ``--before KEY=VALUE`` overrides) and
``after`` (the defaults, plus ``--set`` overrides).

Scored by the one scorer (:func:`diffpos.metrics.score` with the floor calibration of
:mod:`diffpos.floor_calibration`) over ALL node-epochs (a node-epoch without a position is a
miss): right floor, availability, confidently wrong (a wrong floor published at p >= 0.95, of
all node-epochs), 95 % ellipsoid coverage, 3D / |z| error percentiles; and the same over the
last ``--tail`` epochs (the tracker's steady state); also the share of receivers whose
floor is right at the last epoch, and the tracker's CPU per node-epoch.

The figures and the command lines that produced them: ``docs/tracking_evidence.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
import tomllib
from pathlib import Path

import numpy as np
from diffpos_services.raytrace.dataset import load_dataset
from diffpos_services.raytrace.evaluate import dataset_first_arrival

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.emulation import responders
from diffpos.metrics import score
from diffpos.scenario import NodeSpec, Scenario, default_scenario
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state, update

DEFAULT_DATASET = "/work/rt/paper-200-1e6-d4.npz"
#: The new evidence settings switched off: the tracker as it was before them (issue 34,
#: items 3 and 5); filled from TrackerConfig's fields that exist.
EVIDENCE_OFF = {"link_learn": False, "snr_cost_cap_nats": 0.0, "floor_model_doubt": False,
                "max_order": 2}


def _parse_sets(items: list[str]) -> dict:
    out = {}
    fields = {f.name: f for f in dataclasses.fields(TrackerConfig)}
    for item in items:
        key, _, val = item.partition("=")
        if key not in fields:
            raise SystemExit(f"--set {item}: no TrackerConfig field {key!r}")
        cur = getattr(TrackerConfig(), key)
        if isinstance(cur, bool):
            out[key] = val.lower() in ("1", "true", "on", "yes")
        else:
            out[key] = type(cur)(val)
    return out


def configs(after: dict, before: dict) -> dict[str, TrackerConfig]:
    """``before`` (:data:`EVIDENCE_OFF` and the overrides) and ``after`` (defaults and the
    overrides) configurations."""
    names = {f.name for f in dataclasses.fields(TrackerConfig)}
    off = {k: v for k, v in EVIDENCE_OFF.items() if k in names}
    return {"before": TrackerConfig(**(off | before)), "after": TrackerConfig(**after)}


def epochs(ds, *, n_epochs: int, seed: int, rate_hz: float = 10.0):
    """Yield ``(t_ns, reported anchors (M, 3), FirstArrival)`` per epoch."""
    rng = np.random.default_rng(seed)
    radio = ds.scenario.radio
    anchors = np.asarray(ds.anchors_m, float)
    m = anchors.shape[0]
    sig = np.array([0.02, 0.02, 0.03])
    bias = rng.standard_normal((m, 3)) * sig * np.sqrt(0.5)
    period = round(1e9 / rate_hz)
    for k in range(n_epochs):
        fa = dataset_first_arrival(ds, radio=radio, rng=rng)
        rep = anchors + bias + rng.standard_normal((m, 3)) * sig * np.sqrt(0.5)
        yield k * period, rep, fa


def emulator_epochs(sc, *, n_epochs: int, seed: int, rate_hz: float = 10.0):
    """Yield ``(t_ns, reported anchors (M, 3), FirstArrival, truth (N, 3))`` per epoch of the
    emulator's channel (``benchmarks/bench_tracking.py``'s lockstep emulation)."""
    rng = np.random.default_rng(seed)
    m = len(sc.anchors)
    sig = np.array([0.02, 0.02, 0.03])
    bias = rng.standard_normal((m, 3)) * sig * np.sqrt(0.5)
    period = round(1e9 / rate_hz)
    for k in range(n_epochs):
        t_s = k * period * 1e-9
        anchors, nodes = sc.anchor_positions_m(t_s), sc.node_positions_m(t_s)
        ch = emulate_channel(anchors, nodes, building=sc.building, radio=sc.radio)
        fa = first_arrival(ch, radio=sc.radio, rng=rng)
        rep = anchors + bias + rng.standard_normal((m, 3)) * sig * np.sqrt(0.5)
        yield k * period, rep, fa, nodes


def emulator_scenario(name: str):
    """``default`` (the paper's building, 4 UAVs, the six walkers of ``diffpos emulate``) or
    a scenario file (e.g. scenarios/large.toml)."""
    if name == "default":
        sc = default_scenario()
        return dataclasses.replace(sc, node_grid=None, nodes=tuple(
            NodeSpec(i, tr) for i, tr in responders(sc.building, count=6, seed=0)))
    return Scenario.from_dict(tomllib.loads(Path(name).read_text()))


def run_emulator(sc, cfgs: dict[str, TrackerConfig], *, n_epochs: int, seed: int,
                 skip: int = 20) -> dict:
    """Track an emulated scenario with every configuration; the one scorer's summary per label
    over every node-epoch after ``skip`` epochs, and the CPU per node-epoch."""
    b = sc.building
    n = len(sc.nodes)
    states = {k: init_state(n, b) for k in cfgs}
    outs = {k: [] for k in cfgs}
    cpu = {k: 0.0 for k in cfgs}
    truth, tfl = [], []
    for t_ns, rep, fa, nodes in emulator_epochs(sc, n_epochs=n_epochs, seed=seed):
        a = np.broadcast_to(rep, (n, *rep.shape))
        for k, cfg in cfgs.items():
            t0 = time.process_time()
            states[k], out = update(states[k], a, fa.range_m, fa.sigma_m, fa.detected, t_ns, b,
                                    cfg, snr_db=fa.snr_db, radio=sc.radio)
            if t_ns > 0:
                cpu[k] += time.process_time() - t0
            outs[k].append(out)
        truth.append(nodes)
        tfl.append(b.floor_index(nodes[:, 2]))
    res = {}
    for k in cfgs:
        o = outs[k][skip:]
        tr, tf = np.concatenate(truth[skip:]), np.concatenate(tfl[skip:])
        s = score(np.concatenate([x.position_m for x in o]), tr,
                  estimate_floor=np.concatenate([x.floor_index for x in o]), truth_floor=tf,
                  covariance_m2=np.concatenate([x.covariance_m2 for x in o]),
                  floor_probabilities=np.concatenate([x.floor_probabilities for x in o]))
        cal = s.floor_calibration or {}
        res[k] = {"node_epochs": s.node_epochs, "availability": s.availability,
                  "floor": s.floor_accuracy_all, "conf_wrong": cal.get("confidently_wrong"),
                  "cov95": s.ellipsoid_coverage, "p50_3d": s.error_3d_m["p50"],
                  "p90_3d": s.error_3d_m["p90"], "p90_z": s.error_z_m["p90"],
                  "log_score": cal.get("log_score"), "ece": cal.get("ece"),
                  "ms_per_node_epoch": 1e3 * cpu[k] / (n * max(n_epochs - 1, 1))}
    return res


def run(ds, cfgs: dict[str, TrackerConfig], *, n_epochs: int, seed: int) -> dict:
    """Track the dataset's receivers with every configuration; per label the stacked
    outputs (epochs x nodes) and the CPU per node-epoch."""
    sc = ds.scenario
    b, radio = sc.building, sc.radio
    n = ds.nodes_m.shape[0]
    states = {k: init_state(n, b) for k in cfgs}
    outs = {k: [] for k in cfgs}
    cpu = {k: 0.0 for k in cfgs}
    for t_ns, rep, fa in epochs(ds, n_epochs=n_epochs, seed=seed):
        a = np.broadcast_to(rep, (n, *rep.shape))
        for k, cfg in cfgs.items():
            t0 = time.process_time()
            states[k], out = update(states[k], a, fa.range_m, fa.sigma_m, fa.detected, t_ns, b,
                                    cfg, snr_db=fa.snr_db, radio=radio)
            if t_ns > 0:  # the snapshot initialisation of epoch 0 excluded
                cpu[k] += time.process_time() - t0
            outs[k].append(out)
    return {k: {"outs": outs[k], "ms_per_node_epoch": 1e3 * cpu[k] / (n * max(n_epochs - 1, 1))}
            for k in cfgs}


def summarise(outs, truth: np.ndarray, truth_floor: np.ndarray, first: int = 0) -> dict:
    """The one scorer over the epochs ``first:`` of ``outs`` (every node-epoch)."""
    o = outs[first:]
    k, n = len(o), truth.shape[0]
    pos = np.concatenate([x.position_m for x in o])
    cov = np.concatenate([x.covariance_m2 for x in o])
    fl = np.concatenate([x.floor_index for x in o])
    prob = np.concatenate([x.floor_probabilities for x in o])
    tr = np.broadcast_to(truth, (k, n, 3)).reshape(-1, 3)
    tf = np.broadcast_to(truth_floor, (k, n)).reshape(-1)
    s = score(pos, tr, estimate_floor=fl, truth_floor=tf, covariance_m2=cov,
              floor_probabilities=prob)
    cal = s.floor_calibration or {}
    return {"node_epochs": s.node_epochs, "availability": s.availability,
            "floor": s.floor_accuracy_all, "conf_wrong": cal.get("confidently_wrong"),
            "cov95": s.ellipsoid_coverage, "p50_3d": s.error_3d_m["p50"] if s.fixes else None,
            "p90_3d": s.error_3d_m["p90"] if s.fixes else None,
            "p90_z": s.error_z_m["p90"] if s.fixes else None,
            "log_score": cal.get("log_score"), "ece": cal.get("ece")}


def _fmt(v, pct: bool) -> str:
    if v is None:
        return "-"
    return f"{100 * v:.2f} %" if pct else f"{v:.3f}"


ROWS = (("right floor (all node-epochs)", "floor", True), ("availability", "availability", True),
        ("confidently wrong (p>=0.95)", "conf_wrong", True), ("95 % ellipsoid", "cov95", True),
        ("3D p50 [m]", "p50_3d", False), ("3D p90 [m]", "p90_3d", False),
        ("|z| p90 [m]", "p90_z", False), ("floor log score [nats]", "log_score", False),
        ("floor ECE", "ece", False))


def print_table(title: str, res: dict[str, dict]) -> None:
    labels = list(res)
    print(f"\n{title}")
    print(f"{'':32}" + "".join(f"{lab:>14}" for lab in labels))
    for name, key, pct in ROWS:
        print(f"{name:32}" + "".join(f"{_fmt(res[lab][key], pct):>14}" for lab in labels))
    print(f"{'node-epochs':32}" + "".join(f"{res[lab]['node_epochs']:>14}" for lab in labels))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", nargs="?", default=DEFAULT_DATASET)
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--tail", type=int, default=20, help="epochs of the steady-state table")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--nodes", type=int, default=0, help="only the first N receivers (0: all)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="TrackerConfig overrides of 'after'")
    ap.add_argument("--before", nargs="*", default=[], metavar="KEY=VALUE",
                    help="TrackerConfig overrides of 'before'")
    ap.add_argument("--emulator", nargs="*", default=None, metavar="SCENARIO",
                    help="instead: the emulator's channel on these scenarios ('default' or a "
                         "TOML file), --epochs epochs each (scored after 2 s)")
    args = ap.parse_args(argv)
    cfgs = configs(_parse_sets(args.set), _parse_sets(args.before))
    if args.emulator is not None:
        for name in args.emulator or ["default", "scenarios/large.toml"]:
            sc = emulator_scenario(name)
            res = run_emulator(sc, cfgs, n_epochs=args.epochs, seed=args.seed)
            print_table(f"emulator: {name} ({len(sc.nodes)} nodes x {len(sc.anchors)} anchors, "
                        f"{args.epochs} epochs, seed {args.seed}; load "
                        f"{os.getloadavg()[0]:.1f})", res)
            print("tracker CPU ms per node-epoch: " + ", ".join(
                f"{k} {v['ms_per_node_epoch']:.3f}" for k, v in res.items()))
        return 0
    ds = load_dataset(Path(args.dataset))
    if args.nodes:
        ds = ds.subset(np.arange(min(args.nodes, ds.nodes_m.shape[0])))
    sc = ds.scenario
    truth = np.asarray(ds.nodes_m, float)
    tf = sc.building.floor_index(truth[:, 2])
    print(f"{args.dataset}: {truth.shape[0]} receivers x {ds.anchors_m.shape[0]} anchors, "
          f"{args.epochs} epochs at 10 Hz, seed {args.seed}; load {os.getloadavg()[0]:.1f}")
    t0 = time.perf_counter()
    res = run(ds, cfgs, n_epochs=args.epochs, seed=args.seed)
    full = {k: summarise(v["outs"], truth, tf) for k, v in res.items()}
    tail = {k: summarise(v["outs"], truth, tf, first=max(args.epochs - args.tail, 0))
            for k, v in res.items()}
    print_table(f"all {args.epochs} epochs", full)
    print_table(f"last {args.tail} epochs", tail)
    for k, v in res.items():
        last = v["outs"][-1]
        print(f"{k}: receivers on the right floor at the last epoch "
              f"{100 * np.mean(last.floor_index == tf):.1f} %; tracker CPU "
              f"{v['ms_per_node_epoch']:.3f} ms per node-epoch")
    print(f"wall {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
