"""Speed of the O2I channel emulator and of the full `diffpos reproduce` study.

Run:  /work/venv/bin/python benchmarks/bench_channel.py [--repeats 3] [--nodes N]

Prints a table of wall-clock times (median of the repeats) on the paper's scenario
(17,600 receivers x 4 anchors = 70,400 links, 18 MPC slots each):

- ``emulate_channel``: every MPC of every link (geometry, UTD fields, Fresnel reflections,
  partition losses, SNR);
- ``first_arrival``: the detector and the noisy ranges;
- the positioning study per estimator (LLS, IPPA, D-NLS Case-1, D-NLS Case-2) and the PEB;
- the total, i.e. what ``diffpos reproduce`` spends computing (without figures);
- ``pair_snr_db``: the per-slot SNR prediction of the estimators (M-NLS, tracker) on the same
  links, numpy reference (``diffpos.channel.emulator._pair_snr_db_numpy``, the emulator's own code) vs
  the compiled kernel (``diffpos.channel.snr_nb``), by this thread's CPU time per link
  (median of the repeats; the figure to compare on a shared machine), after a warm-up call;
  plus the kernel's first call in a fresh process (compile, or load numba's on-disk cache).
  ``--snr-only`` runs just this part, with one more row: what an anchor process computes
  per epoch (:func:`diffpos.emulation.first_arrivals`, one anchor to 50 nodes), the numpy
  emulator vs the compiled per-pair detector (:func:`diffpos.channel.emulator.pair_first_arrival`).

Measured 2026-11-27 05:40 UTC (``--snr-only``, 70,400 links, 3 repeats; shared 2-core x86_64
VM, Python 3.11.7, load average 8-10 from other jobs), thread CPU per link:

    call                              numpy us  kernel us  speed-up
    all links in one call                16.26      2.436      6.7x
    one node x 8 anchors per call      1561.77      2.679    583.0x

(an earlier run at load 4.4: 13.7 / 2.45 us and 1250 / 2.9 us). Re-run 06:26 UTC at load 0.8
with the anchor row: 15.35 / 2.04 us (7.5x), 1144.8 / 2.60 us (441x), anchor epoch of 50
nodes 10.62 / 0.292 ms (36x). numpy's per-call overhead
(~2,000 small array operations for the 18 slots) dominates one-node calls, which is what a
single live M-NLS fix or a tracker epoch makes. The kernel's first call in a fresh process:
6.9 s CPU with an empty numba cache (compile; 5.5 s at load 4), 0.25 s with the on-disk cache.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from diffpos.channel.emulator import _pair_snr_db_numpy, emulate_channel, first_arrival, pair_snr_db
from diffpos.scenario import default_scenario
from diffpos.study import DEFAULT_METHODS, FirstArrivalData, method_label, positioning_study

#: The extra anchors of benchmarks/bench_estimator_cost.py's 8-anchor layout [m].
EXTRA_ANCHORS_M = np.array([[-25.0, -12.0, 8.5], [10.0, -10.0, 14.0], [28.0, -18.0, 5.5],
                            [-30.0, -25.0, 19.0]])
_FIRST_CALL = """
import time
t = time.process_time()
from diffpos.channel.snr_nb import warm_channel
t1 = time.process_time()
warm_channel()
print(t1 - t, time.process_time() - t1)
"""


def snr_rows(sc, anchors: np.ndarray, nodes: np.ndarray, repeats: int) -> None:
    """pair_snr_db numpy vs kernel, CPU per link, and the kernel's first call."""
    b, r = sc.building, sc.radio
    per_node = np.ascontiguousarray(np.broadcast_to(anchors, (len(nodes), *anchors.shape)))
    eight = np.vstack([anchors, EXTRA_ANCHORS_M])[None]  # the 8-anchor layout of M-NLS' bench
    cases = {"all links in one call": (per_node, nodes),
             "one node x 8 anchors per call": (np.ascontiguousarray(eight), nodes[:1])}
    print(f"\npair_snr_db, CPU per link (thread time), median of {repeats}")
    print(f"{'call':<32} {'numpy us':>9} {'kernel us':>9} {'speed-up':>8}")
    for name, (anc, nod) in cases.items():
        n_calls = 1 if len(nod) > 1 else 200
        pair_snr_db(anc, nod, building=b, radio=r)  # warm-up (compile or cache load)
        times = {}
        for label, fn in (("numpy", _pair_snr_db_numpy), ("kernel", pair_snr_db)):
            ts = []
            for _ in range(repeats):
                t = time.thread_time()
                for _ in range(n_calls):
                    fn(anc, nod, building=b, radio=r)
                ts.append((time.thread_time() - t) / (n_calls * anc.shape[0] * anc.shape[1]))
            times[label] = float(np.median(ts))
        print(f"{name:<32} {1e6 * times['numpy']:9.2f} {1e6 * times['kernel']:9.3f} "
              f"{times['numpy'] / times['kernel']:7.1f}x")
    anchor_epoch_rows(sc, anchors, nodes, repeats)
    with tempfile.TemporaryDirectory() as empty:
        for label, env in (("empty numba cache (compile)", {"NUMBA_CACHE_DIR": empty}),
                           ("numba's on-disk cache", {})):
            out = subprocess.run([sys.executable, "-c", _FIRST_CALL], capture_output=True,
                                 text=True, check=True, env={**os.environ, **env}).stdout.split()
            print(f"kernel first call in a fresh process, {label}: import of diffpos "
                  f"{float(out[0]):.2f} s CPU, warm_channel {float(out[1]):.2f} s CPU")


def anchor_epoch_rows(sc, anchors: np.ndarray, nodes: np.ndarray, repeats: int,
                      n_nodes: int = 50, n_epochs: int = 40) -> None:
    """What an anchor process computes per epoch: :func:`diffpos.emulation.first_arrivals`
    of one anchor to ``n_nodes`` nodes, numpy emulator (``kernel=False``) vs the compiled
    per-pair detector, thread CPU per anchor epoch (median of ``repeats``)."""
    from diffpos.emulation import first_arrivals

    nod = nodes[:: max(len(nodes) // n_nodes, 1)][:n_nodes][None]
    times = {}
    for kernel in (False, True):
        first_arrivals(anchors[:1], nod, sc, rng=np.random.default_rng(0), kernel=kernel)
        ts = []
        for _ in range(repeats):
            t = time.thread_time()
            for k in range(n_epochs):
                first_arrivals(anchors[k % len(anchors)][None], nod, sc,
                               rng=np.random.default_rng(k), kernel=kernel)
            ts.append((time.thread_time() - t) / n_epochs)
        times[kernel] = float(np.median(ts))
    print(f"{'anchor epoch, 1 x ' + str(nod.shape[1]) + ' nodes (ms)':<32} "
          f"{1e3 * times[False]:9.2f} {1e3 * times[True]:9.3f} "
          f"{times[False] / times[True]:7.1f}x")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--nodes", type=int, default=None, help="subsample of receivers")
    ap.add_argument("--snr-only", action="store_true", help="only the pair_snr_db rows")
    args = ap.parse_args()
    sc = default_scenario()
    nodes = sc.node_positions_m()
    if args.nodes:
        nodes = nodes[:: max(len(nodes) // args.nodes, 1)][: args.nodes]
    anchors = sc.anchor_positions_m()
    if args.snr_only:
        snr_rows(sc, anchors, nodes, args.repeats)
        return
    rows: dict[str, list[float]] = {}

    def timed(name, fn):
        t = time.perf_counter()
        out = fn()
        rows.setdefault(name, []).append(time.perf_counter() - t)
        return out

    for rep in range(args.repeats):
        t_all = time.perf_counter()
        ch = timed("emulate_channel", lambda: emulate_channel(
            anchors, nodes, building=sc.building, radio=sc.radio))
        fa = timed("first_arrival", lambda ch=ch, rep=rep: first_arrival(
            ch, radio=sc.radio, rng=np.random.default_rng(rep)))
        data = FirstArrivalData.from_channel(fa, anchors, nodes)
        marks: dict[str, float] = {}
        last = [time.perf_counter()]

        def prog(m, done, n, marks=marks, last=last):
            if done == n:
                now = time.perf_counter()
                marks[m] = now - last[0]
                last[0] = now

        positioning_study(data, window_height_m=sc.building.window_height_m,
                          edge_x_m=sc.building.edge_x_m, methods=DEFAULT_METHODS,
                          progress=prog)
        for m, dt in marks.items():
            rows.setdefault(f"study: {method_label(m) if m != 'peb' else 'PEB + z bound'}",
                            []).append(dt)
        rows.setdefault("total (channels + study)", []).append(time.perf_counter() - t_all)

    n_links = len(nodes) * len(anchors)
    print(f"scenario 'paper': {len(nodes)} receivers x {len(anchors)} anchors = {n_links} "
          f"links, {ch.valid.shape[-1]} MPC slots; median of {args.repeats} repeats")
    print(f"{'stage':<34} {'time [s]':>9} {'us/link':>9}")
    for name, ts in rows.items():
        med = float(np.median(ts))
        print(f"{name:<34} {med:9.3f} {1e6 * med / n_links:9.2f}")
    snr_rows(sc, anchors, nodes, args.repeats)


if __name__ == "__main__":
    main()
