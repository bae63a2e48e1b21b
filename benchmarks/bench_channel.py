"""Speed of the O2I channel emulator and of the full `diffpos reproduce` study.

Run:  /work/venv/bin/python benchmarks/bench_channel.py [--repeats 3] [--nodes N]

Prints a table of wall-clock times (median of the repeats) on the paper's scenario
(17,600 receivers x 4 anchors = 70,400 links, 18 MPC slots each):

- ``emulate_channel``: every MPC of every link (geometry, UTD fields, Fresnel reflections,
  partition losses, SNR);
- ``first_arrival``: the detector and the noisy ranges;
- the positioning study per estimator (LLS, IPPA, D-NLS Case-1, D-NLS Case-2) and the PEB;
- the total, i.e. what ``diffpos reproduce`` spends computing (without figures).

Targets (issue "O2I channel emulator and reproduction of the paper's study"): the channels of
the full study in seconds, the full study in under 60 s on 2 cores. The machine is shared, so
the numbers are noisy; threads are not pinned (numpy may use both cores).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from diffpos.channel import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.study import DEFAULT_METHODS, FirstArrivalData, method_label, positioning_study


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--nodes", type=int, default=None, help="subsample of receivers")
    args = ap.parse_args()
    sc = default_scenario()
    nodes = sc.node_positions_m()
    if args.nodes:
        nodes = nodes[:: max(len(nodes) // args.nodes, 1)][: args.nodes]
    anchors = sc.anchor_positions_m()
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


if __name__ == "__main__":
    main()
