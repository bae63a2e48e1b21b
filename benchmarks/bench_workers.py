"""What a split tracker update costs and saves (services/diffpos_services/fusion/workers.py).

    python benchmarks/bench_workers.py [--rows 8,16,32,64,128,256] [--repeat 20]

Static nodes in the default scenario's building, 8 anchors, the emulated channel; each node's
track is run for 8 epochs (TRACKING), then the next epoch's :func:`diffpos.tracking.tracker.update` is
timed on ``rows`` nodes (ms per call): locally in one call (CPU and wall), and through a 2-way :class:`RowPool` (one worker
process; the calling process computes the first share). Per call: wall, the caller's CPU, the
worker's CPU (its /proc stat), the bytes pickled both ways, and the caller's CPU spent outside
its own share (slicing, pickling, pipe, concatenation: the calling thread's CPU). The worker's
CPU comes from /proc in clock ticks (10 ms) over ``repeat`` calls. The estimates of both paths
are compared bit for bit. Prints a table.
"""

from __future__ import annotations

import argparse
import os
import pickle
import time

import numpy as np
from common import cpu_s
from diffpos_services.fusion import rows as R
from diffpos_services.fusion import workers as W

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state, update

SC = default_scenario()
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0],
                    [-25.0, -12.0, 3.0], [25.0, -12.0, 3.0], [-8.0, -10.0, 2.0],
                    [8.0, -25.0, 0.5]])


def _batch(n: int, seed: int = 0):
    """Tracker state of ``n`` static nodes after 8 epochs and the 9th epoch's inputs."""
    rng = np.random.default_rng(seed)
    b = SC.building
    nodes = np.column_stack([rng.uniform(-8, 8, n), rng.uniform(1.5, 9, n),
                             b.first_floor_z_m + rng.integers(0, b.n_floors, n)
                             * b.floor_height_m + 1.2])
    a = np.broadcast_to(ANCHORS, (n, *ANCHORS.shape))
    state = init_state(n, b)
    for k in range(9):
        fa = first_arrival(emulate_channel(ANCHORS, nodes, building=b, radio=SC.radio),
                           radio=SC.radio, rng=rng)
        args = (a, fa.range_m, fa.sigma_m, fa.detected, np.full(n, round(k * 1e8), np.int64),
                fa.snr_db)
        if k < 8:
            state, _ = update(state, *args[:5], b, TrackerConfig(), snr_db=args[5],
                              radio=SC.radio)
    return state, args


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", default="8,16,32,64,128,256")
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args(argv)
    cfg, b = TrackerConfig(), SC.building
    W.MIN_PARALLEL_COST = 0.0  # every call split
    print(f"bench_workers: {os.cpu_count()} cores, load avg {os.getloadavg()}")
    print(f"{'rows':>5} {'local CPU':>9} {'local wall':>10} {'split wall':>10} {'caller CPU':>10} "
          f"{'worker CPU':>10} {'overhead':>9} {'KB out/in':>11}  same")
    with W.RowPool(2, (b, SC.radio, b.window_height_m, b.first_floor_z_m)) as pool:
        pool.wait_ready()
        wpid = pool.pids[0]
        for n in (int(v) for v in args.rows.split(",")):
            state, (a, r, s, m, t, snr) = _batch(n)
            rows = (R.slim_state(state, cfg), a, r, s, m, t, snr)

            def local(rows=rows):
                return R.run_update(b, *rows, cfg, SC.radio)

            ref = local()
            w0, c0 = time.perf_counter(), time.process_time()
            for _ in range(args.repeat):
                local()
            t_local = (time.process_time() - c0) / args.repeat
            w_local = (time.perf_counter() - w0) / args.repeat
            pool.map_rows("update", rows, np.ones(n), shared=(cfg, SC.radio))  # first calls
            pool.calls.clear()
            w0, k0 = time.perf_counter(), cpu_s(wpid)
            for _ in range(args.repeat):
                got = pool.map_rows("update", rows, np.ones(n), local=None,
                                    shared=(cfg, SC.radio))
            wall = (time.perf_counter() - w0) / args.repeat
            caller = pool.calls["caller_cpu_s"] / args.repeat  # the caller's thread CPU
            worker = (cpu_s(wpid) - k0) / args.repeat
            own = pool.calls["own_cpu_s"] / args.repeat  # the caller's thread CPU in its share
            sl = R.share_bounds(np.ones(n), 2)
            kb_out = len(pickle.dumps(R.take_rows(rows, sl[-1]), protocol=5)) / 1024
            kb_in = len(pickle.dumps(R.take_rows(ref, sl[-1]), protocol=5)) / 1024
            same = all(getattr(got[1], f).tobytes() == getattr(ref[1], f).tobytes()
                       for f in ref[1].__dataclass_fields__)
            print(f"{n:>5} {t_local * 1e3:>9.2f} {w_local * 1e3:>10.2f} {wall * 1e3:>10.2f} "
                  f"{caller * 1e3:>10.2f} "
                  f"{worker * 1e3:>10.2f} {(caller - own) * 1e3:>9.2f} "
                  f"{kb_out:>5.0f}/{kb_in:<5.0f}  {same}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
