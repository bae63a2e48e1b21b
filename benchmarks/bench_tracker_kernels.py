"""CPU of the tracker's hot compiled kernels on the inputs of a real replay, with a digest of
their outputs: a before/after comparison of kernel code that must stay bit-identical.

Usage::

    python benchmarks/bench_tracker_kernels.py capture RECORDING INPUTS.pkl [--skip 100]
        [--calls 300]
    python benchmarks/bench_tracker_kernels.py time INPUTS.pkl [--reps 5]
    python benchmarks/bench_tracker_kernels.py update-capture RECORDING UPDATES.pkl
        [--calls 400]
    python benchmarks/bench_tracker_kernels.py update-time UPDATES.pkl [--reps 3]

``capture`` replays the recording in this process (:func:`diffpos_services.replay.run
.replay`, M-NLS + tracker, all epochs solved, no recorded decisions) and keeps the inputs
(copies; the outputs' shapes only) of ``--calls`` calls of each kernel after the first
``--skip``: ``tracking_nb.all_paths_kernel`` (the tracker's path model, ~3 calls per update),
``channel_nb.channel_snr_masked_kernel`` (the tracker's SNR prediction: the hypotheses' slots
and the relax holes), ``channel_nb.channel_snr_kernel`` (every slot: the M-NLS snapshots) and
``grid_nb.grid_cost_kernel`` (the grid search of a track's initialisation; its calls from
the first on, as many as come before the others have theirs).
``time`` runs each kernel over the kept calls ``--reps`` times (``time.process_time``, the
best pass; the first call before, so compile or cache load is not counted) and prints the
CPU, ns per output element and a sha256 of every output byte (NaN patterns included; for
``grid`` of what its caller uses: the ``keep`` cheapest cells per node and floor, in order, and
their totals, since which other cells it abandons (+inf) depends on its pruning).

To compare two trees, capture once (the inputs are the same in both while the estimates are)
and run ``time`` alternately with each tree on ``PYTHONPATH`` (numba's cache of the tree is
used; delete ``diffpos/_kernels/__pycache__`` after editing a kernel's callees, see
DEVELOPING.md). Equal digests: the kernels' outputs are bit-identical on these inputs.

Measured 2026-11-27 16:25-16:27 UTC (2-core x86_64 VM shared with another job, load 2.8-4.7),
300 calls of each kernel from ``/tmp/s8/soak/soak16x200.mcap`` (16 anchors x 200 nodes, calls
101-400), best of 5 passes, main 73c3e34 (before) and the cost10 branch (after) alternating::

    kernel   CPU s before     CPU s after      ns/element before -> after   output sha256
    paths    1.117 / 1.102    1.105 / 1.092    23.7 / 23.4 -> 23.4 / 23.2  b6fd9fd156132501 (all)
    masked   1.343 / 1.300    1.228 / 1.221    35.2 / 34.0 -> 32.1 / 32.0  72eff9bf032401bf (all)
    full     0.777 / 0.767    0.703 / 0.721    121.1 / 119.6 -> 109.6 / 112.5  a2f8834c6ec1511c

(``masked``: the tracker's SNR prediction, -6 to -9 %; ``full``: every slot, the M-NLS
snapshots' SNR, -6 to -9 %; ``paths``: within the noise.) Equal digests: bit-identical outputs.

The grid search visiting its cells by a lower bound (``grid_cost_kernel``), 2026-11-28
00:00 UTC (same VM, load 6.7-8.2: other jobs), main 7f546cd (before) and after alternating,
best of 5, one call each (every node's initialisation of the replay)::

    capture                          CPU s before     CPU s after      ranked output sha256
    soak16x200.mcap (200 nodes x 16) 0.446 / 0.442    0.185 / 0.184    f590bd5e8c5d5e72 (both)
    large (50 nodes x 8 anchors)     0.066 / 0.065    0.024 / 0.024    05074f345cb61916 (both)

``update-capture`` keeps the tracker's whole measurement updates instead
(:func:`diffpos.tracking.model.measurement_update` as :mod:`diffpos.tracking.tracker` calls
it: the first ``--calls`` of the replay, every hypothesis pair of a tracker call in one
batch), with their outputs and the SNR cache after each. ``update-time`` runs the updates of
the tree on ``PYTHONPATH`` over them: the count of outputs (x, P, log-evidence, the selection,
residuals, the SNR cache) that differ from the captured ones in any bit, a sha256 of them, and
the CPU (best of ``--reps`` passes; ``time.process_time``) split into its kernels (timers
around them, looked up by name in ``diffpos.tracking.model``, ``diffpos.tracking.links`` and
``diffpos.channel.emulator``; a tree without one shows none) and the rest (Python, numpy).
Capture with the before tree, then time both trees alternately: 0 differing outputs and
equal digests = bit-identical updates.

Measured 2026-12-06 (issue 37: the compiled SNR term and set-up of the measurement update),
see docs/performance.md, "The measurement update compiled".
"""

from __future__ import annotations

import argparse
import hashlib
import os
import pickle
import platform
import sys
import time

import numpy as np

_N_OUT = {"paths": 5, "masked": 1, "full": 1, "grid": 1}  # trailing output arguments
_SKIPPED = {"grid"}  # kernels kept from their first call (a replay initialises early)


class _Enough(Exception):
    """Every kernel has its calls: stop the replay."""


def capture(recording: str, out: str, skip: int, n_calls: int) -> dict[str, int]:
    from diffpos_services.replay.run import replay

    import diffpos.channel.snr_nb as cn
    import diffpos.tracking.initialisation as ti
    import diffpos.tracking.links as tp

    cn.warm_channel()  # before the kernels are wrapped (it compiles them by name)
    kept: dict[str, list] = {k: [] for k in _N_OUT}
    seen = dict.fromkeys(_N_OUT, 0)
    orig = {"paths": tp.all_paths_kernel, "masked": cn.channel_snr_masked_kernel,
            "full": cn.channel_snr_kernel, "grid": ti.grid_cost_kernel}

    def wrap(key):
        f = orig[key]

        def g(*args):
            seen[key] += 1
            if seen[key] > (0 if key in _SKIPPED else skip) and len(kept[key]) < n_calls:
                ins, outs = args[:-_N_OUT[key]], args[-_N_OUT[key]:]
                kept[key].append((tuple(np.array(a) if isinstance(a, np.ndarray) else a
                                        for a in ins), [(o.shape, o.dtype) for o in outs]))
            if all(len(v) >= n_calls for k, v in kept.items() if k not in _SKIPPED):
                raise _Enough
            return f(*args)
        return g

    tp.all_paths_kernel = wrap("paths")
    cn.channel_snr_masked_kernel = wrap("masked")
    cn.channel_snr_kernel = wrap("full")
    ti.grid_cost_kernel = wrap("grid")
    try:
        replay(recording, use_decisions=False, method="mnls", out_mcap=None,
               keep_estimates=False)
    except _Enough:
        pass
    finally:
        tp.all_paths_kernel = orig["paths"]
        cn.channel_snr_masked_kernel = orig["masked"]
        cn.channel_snr_kernel = orig["full"]
        ti.grid_cost_kernel = orig["grid"]
    with open(out, "wb") as fh:
        pickle.dump(kept, fh)
    return {k: len(v) for k, v in kept.items()}


def time_kernels(inputs: str, reps: int) -> list[tuple]:
    import diffpos.channel.snr_nb as cn
    import diffpos.tracking.initialisation_nb as gn
    import diffpos.tracking.model_nb as tn

    with open(inputs, "rb") as fh:
        kept = pickle.load(fh)
    cn.warm_channel()
    fn = {"paths": tn.all_paths_kernel, "masked": cn.channel_snr_masked_kernel,
          "full": cn.channel_snr_kernel, "grid": gn.grid_cost_kernel}
    rows = []
    for key, calls in kept.items():
        if not calls:
            continue
        outs = [[np.empty(s, d) for s, d in o] for _, o in calls]
        fn[key](*calls[0][0], *outs[0])
        best = np.inf
        for _ in range(reps):
            t0 = time.process_time()
            for (ins, _), out in zip(calls, outs, strict=True):
                fn[key](*ins, *out)
            best = min(best, time.process_time() - t0)
        h = hashlib.sha256()
        for (ins, _), out in zip(calls, outs, strict=True):
            for o in (_ranked(out[0], ins[11]) if key == "grid" else out):
                h.update(np.ascontiguousarray(o).tobytes())
        n_items = sum(o[0].size for o in outs)
        rows.append((key, len(calls), best, 1e9 * best / n_items, h.hexdigest()[:16]))
    return rows


def _ranked(total: np.ndarray, keep: int) -> tuple[np.ndarray, np.ndarray]:
    """What ``grid_starts`` uses of a ``grid_cost_kernel`` output: the ``keep`` cheapest cells
    per (node, floor) in stable order and their totals."""
    order = np.argsort(total, axis=2, kind="stable")[..., :max(int(keep), 1)]
    return order, np.take_along_axis(total, order, 2)


def capture_updates(recording: str, out: str, n_calls: int) -> int:
    """Keep the first ``n_calls`` measurement updates of the tracker in a replay (inputs,
    outputs, the SNR cache after)."""
    import copy

    from diffpos_services.replay.run import replay

    import diffpos.tracking.tracker as tracker

    kept: list = []
    orig = tracker.measurement_update

    def mu(*a, **k):
        if len(kept) >= n_calls:
            return orig(*a, **k)
        ins = copy.deepcopy((a, k))
        res = orig(*a, **k)
        sc = k.get("snr_cache")
        after = None if sc is None else (sc.node.copy(), sc.anchor.copy(), sc.pred.copy())
        kept.append((ins, copy.deepcopy(res), after))
        return res

    tracker.measurement_update = mu
    try:
        replay(recording, use_decisions=False, method="mnls", out_mcap=None,
               keep_estimates=False)
    finally:
        tracker.measurement_update = orig
    with open(out, "wb") as fh:
        pickle.dump(kept, fh)
    return len(kept)


def _update_outputs(res, cache) -> list:
    x, p, ev, sel, r = res
    out = [x, p, ev, sel.slot, sel.log_weight, sel.nis, sel.extra_var, r]
    return out + ([] if cache is None else list(cache))


_UPDATE_KERNELS = {
    "diffpos.channel.emulator": ["eval_snr_masked_kernel"],
    "diffpos.tracking.links": ["all_paths_kernel"],
    "diffpos.tracking.model": ["iekf_kernel", "select_pack_kernel", "select_best_kernel",
                               "select_mix_kernel", "snr_plan_kernel", "snr_score_kernel",
                               "snr_hole_kernel", "update_fixed_kernel", "clamp_kernel",
                               "cache_plan_kernel", "cache_store_kernel",
                               "prior_info_kernel"],
}


def time_updates(inputs: str, reps: int) -> tuple[int, int, str, float, int, dict]:
    """Run the kept updates: (updates, differing outputs, sha256, best CPU [s],
    hypotheses, CPU per kernel of the best pass)."""
    import copy
    import importlib
    from collections import Counter

    import diffpos.tracking.model as tm

    with open(inputs, "rb") as fh:
        kept = pickle.load(fh)
    acc: Counter = Counter()
    for mod_name, names in _UPDATE_KERNELS.items():
        mod = importlib.import_module(mod_name)
        for name in names:
            if hasattr(mod, name):
                setattr(mod, name, _timed(getattr(mod, name), name, acc))
    h = hashlib.sha256()
    bad = 0
    for (a, k), ref, after in kept:  # the check (and the first call's compile or cache load)
        a2, k2 = copy.deepcopy((a, k))
        res = tm.measurement_update(*a2, **k2)
        sc = k2.get("snr_cache")
        got = _update_outputs(res, None if sc is None else (sc.node, sc.anchor, sc.pred))
        for g, r in zip(got, _update_outputs(ref, after), strict=True):
            bad += g.shape != r.shape or g.dtype != r.dtype or g.tobytes() != r.tobytes()
            h.update(np.ascontiguousarray(g).tobytes())
    best, best_acc = np.inf, {}
    for _ in range(reps):
        batch = [copy.deepcopy((a, k)) for (a, k), _, _ in kept]
        acc.clear()
        t0 = time.process_time()
        for a2, k2 in batch:
            tm.measurement_update(*a2, **k2)
        cpu = time.process_time() - t0
        if cpu < best:
            best, best_acc = cpu, dict(acc)
    n_hyp = sum(a[0].shape[0] * a[0].shape[1] for (a, _), _, _ in kept)
    return len(kept), bad, h.hexdigest()[:16], best, n_hyp, best_acc


def _timed(f, name: str, acc) -> object:
    def g(*a, **k):
        t0 = time.process_time()
        try:
            return f(*a, **k)
        finally:
            acc[name] += time.process_time() - t0
    return g


def _print_updates(inputs: str, reps: int) -> None:
    n, bad, dig, cpu, n_hyp, per = time_updates(inputs, reps)
    print(f"{n} measurement updates, {n_hyp:,} hypotheses: {bad} outputs differ from the "
          f"captured ones; sha256 {dig}")
    print(f"CPU (best of {reps}) {cpu:.3f} s, {1e6 * cpu / max(n_hyp, 1):.1f} us per hypothesis")
    for name, v in sorted(per.items(), key=lambda kv: -kv[1]):
        print(f"  {name:<24} {v:7.3f} s  {100 * v / cpu:5.1f} %")
    rest = cpu - sum(per.values())
    print(f"  {'rest (Python, numpy)':<24} {rest:7.3f} s  {100 * rest / cpu:5.1f} %")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture")
    c.add_argument("recording")
    c.add_argument("inputs")
    c.add_argument("--skip", type=int, default=100, help="calls of each kernel skipped first")
    c.add_argument("--calls", type=int, default=300, help="calls of each kernel kept")
    t = sub.add_parser("time")
    t.add_argument("inputs")
    t.add_argument("--reps", type=int, default=5)
    uc = sub.add_parser("update-capture")
    uc.add_argument("recording")
    uc.add_argument("updates")
    uc.add_argument("--calls", type=int, default=400, help="updates kept (the first ones)")
    ut = sub.add_parser("update-time")
    ut.add_argument("updates")
    ut.add_argument("--reps", type=int, default=3)
    args = ap.parse_args()
    if args.cmd == "capture":
        print(capture(args.recording, args.inputs, args.skip, args.calls))
        return 0
    if args.cmd == "update-capture":
        print(f"{capture_updates(args.recording, args.updates, args.calls)} updates kept")
        return 0
    import diffpos

    if args.cmd == "update-time":
        print(f"bench_tracker_kernels: {os.path.dirname(diffpos.__file__)}; machine "
              f"{platform.machine()} {os.cpu_count()} cores, load avg {os.getloadavg()[0]:.1f}")
        _print_updates(args.updates, args.reps)
        return 0

    print(f"bench_tracker_kernels: {os.path.dirname(diffpos.__file__)}; machine "
          f"{platform.machine()} {os.cpu_count()} cores, load avg {os.getloadavg()[0]:.1f}")
    print(f"{'kernel':<8} {'calls':>5} {'CPU s (best)':>12} {'ns/element':>10}  output sha256")
    for key, n, cpu, per, dig in time_kernels(args.inputs, args.reps):
        print(f"{key:<8} {n:>5} {cpu:>12.3f} {per:>10.1f}  {dig}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
