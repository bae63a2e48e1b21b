"""CPU per node-epoch of the whole fusion core, as it runs live, per method (issue 13's "usable
live: <= 2 ms per node-epoch on average with 8 anchors").

Usage::

    python benchmarks/bench_fusion_cost.py [--scenario large] [--duration 10] [--seed 0]
    python benchmarks/bench_fusion_cost.py --recording REC --parts [--startup-s 1]
    python benchmarks/bench_fusion_cost.py --recording REC --compare CHECKOUT [--repeat 2]
    python benchmarks/bench_fusion_cost.py --recording REC --steps [--startup-s 2.5]

``--steps`` (session 26, the live ``large``'s p99): a replay of REC by its recorded decisions
(the live run's solve steps, bit for bit) with the CPU of each step and of its parts
(:data:`STEP_PARTS`: the tracker's update, its hypothesis updates, floor re-seeds and track
initialisations, the M-NLS check fixes) and their rows: the distribution over the steps after
``--startup-s`` of wall time and the slowest steps (docs/performance.md "Session 26").

``--compare CHECKOUT`` (session 22): the same measurement (``--recording``: an M-NLS replay with
the recorded decisions after a warm-up replay; ``--schedule``: the live loop) by CHECKOUT's code
(its tree and ``services`` on ``PYTHONPATH``) and this tree's, alternating in fresh processes
for ``--repeat`` rounds, CPU per node-epoch side by side with the load and the ratio of the
best of each (docs/soak.md, session 22: on this shared VM the rounds scatter by +-15 %).

``--parts`` (issue 37, session 21): one M-NLS replay of REC (every epoch solved, no recorded
decisions, after a warm-up replay of its first 16 s) with timers around the mnls snapshot fix,
the tracker bank's update and the update's parts (:data:`PARTS`), the start-up (the first
``--startup-s`` of measurement time: the track initialisations and every node's first
snapshot) apart from the rest: where the CPU per node-epoch goes (docs/soak.md).

Records a lockstep run of the real system (``diffpos emulate SCENARIO --speed 0 --record``,
realistic emulated channel, the fusion's default method), then replays the recording in this
process with each method (:func:`diffpos_services.replay.run.replay`: the same fusion
core as the live service, fed the recorded ranges in the recorded order) and divides the
replay's CPU time (``time.process_time``, imports and the first-call costs excluded: one warm-up
replay of the first seconds precedes the timed ones) by the node-epochs it solved. The figure
covers everything the live fusion does per node-epoch: ingest, alignment, the M-NLS snapshots
(every 1 s per node, every 10 s for a confident track, every epoch for a node the tracker
does not place), the
tracker's update, estimate building and the report. Side by side in one run: ``mnls`` (the
default: M-NLS + tracker) and ``dnls``.

Measured 2026-11-27 07:02 UTC (2-core x86_64 VM, Python 3.11.7, load average 0.8-2.1)::

    scenario              method  node-epochs  CPU s  ms/node-epoch  right floor (all)
    large (8 x 50), 10 s  mnls           5000   9.31          1.862  99.8 %   (<= 2 ms: met)
                          dnls           5000   1.99          0.398  44.6 %
    paper (4 x 6), 20 s   mnls           1200   1.77          1.476  94.1 %
                          dnls           1200   0.43          0.359  25.4 %

(``python benchmarks/bench_fusion_cost.py`` and ``... --scenario paper --duration 20``.) Before
this round's compiled SNR prediction, M-NLS LM steps and tracker kernels, the same large
replay took 3.4 ms per node-epoch (``diffpos replay``: 17.2 s for 5,000, same machine, load 2).
The snapshot fix alone costs more (3.1-3.8 ms with 8 anchors, benchmarks/
bench_estimator_cost.py): live it runs for a fraction of the node-epochs only.

The livefuse branch (bounded heavy work per step, steps sized by a fitted fixed + per-epoch
cost), 2026-11-27 09:05 UTC, load 4-5.3, a 20 s lockstep ``large`` recording made by each
code and replayed by it twice (``replay(path)`` CPU, the live steps re-issued): before 1.33 /
1.39 ms per node-epoch (859 solve steps), after 1.01 / 1.16 ms (326 steps); replay identical
to live in both (9,751 / 9,751 positions after).

``--schedule REC`` (issue 16, live latency on a shared machine): the live service loop
(:class:`~diffpos_services.fusion.service.ServiceLoop`, the real code: bounded ingest, step
sizing, publishing) fed the fusion inputs of a **real-time** recording at their recorded
receive times, on a virtual wall clock that advances by the CPU time the loop uses
(``time.process_time_ns``) and jumps over idle waits. It measures the latency the loop would
have on one core of its own, whatever else loads the machine (other processes' load changes
the wall figures of ``diffpos emulate``, not these), and prints end-to-end latency (input
publish -> estimate handed to the bus) overall and over the first 2 s (start-up), the steps'
sizes and the CPU per node-epoch (the estimates are encoded as the publisher does; the bus
itself is not simulated). Run with another checkout's ``services`` on ``PYTHONPATH``
it measures that code on the same input (before vs after).

Measured 2026-11-27 08:56-09:00 UTC (2-core VM shared with other jobs, load average 3.3-6.0;
the virtual clock makes the latency independent of that load, but CPU time itself varies by
~+-25 % between runs on this machine, so each row was run twice, interleaved). Input: a
real-time ``diffpos emulate scenarios/large.toml --duration 20 --record`` (8 x 50, 10,000
node-epochs); before = the fusion of commit 94ee8c5 (``services`` of that commit on
``PYTHONPATH``), after = this branch::

    python benchmarks/bench_fusion_cost.py --schedule rt.mcap
                         before (94ee8c5)         after
    CPU per node-epoch   1.14 / 1.47 ms           0.99 / 1.02 ms
    end-to-end p50       35.7 / 47.9 ms           44.5 / 45.2 ms
    end-to-end p99       1,196 / 1,349 ms         80.1 / 79.0 ms      (target <= 50 ms: missed)
    first 2 s, p99       1,273 / 1,398 ms         151 / 126 ms
    after 2 s, p99       475 / 793 ms             67.1 / 70.8 ms
    solve steps          641 / 797                399 / 399

Before, the first epoch of 50 new tracks was solved in one step (50 initialisations and 50
snapshot fixes, ~0.5 s) and every step after it took 8-20 epochs (sized by the mean cost per
epoch, which charged each epoch the tracker's per-call cost); after, a step does at most
``heavy_budget`` initialisations/snapshots (fusion/tracked.py) and steps are sized by a fitted
fixed + per-epoch cost (``StepCost``), larger while the fusion is behind. What remains above
50 ms is the tracker's own CPU: a release of 50 node-epochs costs ~50 ms.

Issue 16, latency branch, 2026-11-27 09:56 UTC (same machine, load average 2.7-3.7), the same
real-time input (a ``diffpos emulate scenarios/large.toml --duration 20 --record`` of 09:36),
before = main at b016ce2 (``services`` of /work/main on ``PYTHONPATH``), after = this branch,
interleaved::

    python benchmarks/bench_fusion_cost.py --schedule rt.mcap
                         before (b016ce2)         after
    CPU per node-epoch   0.57 / 0.61 ms           0.63 / 0.63 ms
    end-to-end p50       21.1 / 21.2 ms           21.4 / 21.4 ms
    end-to-end p99       70.4 / 86.2 ms           45.3 / 47.5 ms      (target <= 50 ms: met)
    first 2 s, p99       126 / 138 ms             70 / 78 ms
    after 2 s, p99       37.8 / 40.4 ms           35.9 / 34.1 ms
    estimates > 50 ms    425 / 484 of 10,000      86 / 88
    UNINITIALISED        268 / 268                273 / 278

Where the p99 came from (per-step trace of the loop on this input): the first ~1.5 s, where
each 100 ms epoch's steps carried 4-5 track initialisations (~6 ms each) and the snapshots
of the unconfirmed tracks (~3.5 ms each) in front of every other estimate of the step, plus
one full garbage collection of the warmed-up heap (~70 ms inside one step). After: a
budgeted step solves its initialisations after its other epochs and the service publishes
those first (``FusionCore.step(emit=...)``); snapshots have a credit of their own (one per
50 epochs solved, fusion/tracked.py ``SNAPSHOT_WORK_EPOCHS``); the service freezes the heap
after its warm-up (``service.freeze_heap``). The live figure is not met: ``diffpos emulate
scenarios/large.toml --duration 20 --dashboard off --record off``, interleaved, load 2.2-2.8:
before p50 30.8 / 37.0 ms, p99 81.2 / 102.7 ms; after p50 30.2 / 36.7 ms, p99 72.2 / 86.9 ms
(what is left is not the start-up: the summary's "fusion latency", anchor publish -> fusion
publish over the fusion's last 4,096 estimates, is p99 55 / 61 ms before and 64 / 58 ms
after; on 2 cores the loop shares the CPU with 8 anchor processes, the router and emulate,
which the virtual clock leaves out, and the delivery to emulate adds the rest).

The same on bench_soak's 16 x 200 input (``bench_soak.py --load 16x200 --method mnls
--log-dir D``, first 10 s; ``--fusion-args "--site soak16x200 --scenario D/soak16x200.toml
--method mnls"``): before 3.29-3.68 ms CPU per node-epoch (steps of 8-9 epochs), 7,117-7,281
of 20,000 node-epochs published; after 1.66-1.99 ms (steps of 43-49), 8,854-9,845. Keeping
up needs <= 0.5 ms per node-epoch on a whole core: not met (the tracker's update).

``--recording REC --threads 1,2`` (the threads branch): M-NLS replays of REC (every epoch
solved, no recorded decisions) with ``kernel_threads`` 1 and 2, alternating, CPU and wall per
node-epoch, the "free-core wall" (the process CPU with each split kernel call counted at its
busiest thread's CPU: the wall time with a free core per thread, ``diffpos._kernels.pool
.stats``) and a digest of the replayed estimates' bytes. 2026-11-27 11:27-11:36 UTC, 2-core
VM shared with four other jobs (load average 4.9-7.2: there was no free core, so the wall
column mostly measures the other jobs)::

    python benchmarks/bench_fusion_cost.py --recording /tmp/s8/soak/soak16x200.mcap --threads 1,2
    threads  CPU ms/ne       wall ms/ne      free-core wall ms/ne   digest (60,000 estimates)
    1        0.873 / 0.897   2.241 / 1.554   0.873 / 0.897          500966d8ef81 (all four)
    2        0.916 / 0.835   2.226 / 1.239   0.692 / 0.630
    2 vs 1:  CPU x0.99, wall x0.91, free-core wall x0.75 (kernels: 59 % of the CPU)

    ... --recording /tmp/s8/large.mcap --threads 1,2          (8 x 50, 10,000 estimates)
    1        0.757 / 0.736   4.583 / 2.413   0.757 / 0.736          531888983ccb (all four)
    2        0.739 / 0.763   2.798 / 1.943   0.655 / 0.675
    2 vs 1:  CPU x1.01, wall x0.68, free-core wall x0.89 (kernels: 40 % of the CPU)

Live, before (main at 5e10a2d, one thread) vs after (the threads branch, ``kernel_threads``
2, its default then; the default is 1 since, ``FusionConfig.kernel_threads``), alternating, 11:10-11:19 UTC (load 5.5-11) and 11:40-11:48 UTC (load 3.2-4.5)::

    python benchmarks/bench_soak.py --load 16x200 --duration 60 --method mnls
    published of 120,000     before 14,714 / 20,235 / 33,789 / 36,804
                             after   9,313 / 27,206 / 33,237 / 37,154
    fusion latency p99       before 18.5 / 9.6 / 5.3 / 4.9 s;  after 23.3 / 15.8 / 6.1 / 5.9 s
    diffpos emulate scenarios/large.toml --duration 20 --dashboard off --record off
    end-to-end p50 / p99     before 63.5/532, 684.9/2229, 37.8/169.1, 41.6/239.5 ms
                             after  128.5/2084, 120.2/562.3, 50.9/549.0, 56.4/238.1 ms
    fusion latency p50 / p99 (last two rounds) before 29.0/72.8, 36.4/73.6 ms;
                             after 41.1/83.2, 56.7/82.2 ms

Not met, and not helped on this machine: live, the second core is taken (16 anchors, router
and recorder, or 8 anchors and emulate, plus the other jobs), so the soak publishes as many
estimates as before and the fusion's latency is 5-20 ms worse at p50 (a helper thread that
waits for a core holds its chunk, and every hand-off of the GIL to a thread without a core
waits for the scheduler). ``diffpos fusion --kernel-threads 1`` restores the one-thread
behaviour; the split pays where a core is free (free-core wall above). After these runs the
pool got its back-off rule (``diffpos._kernels.pool.BACKOFF_WAIT_SHARE``); two more rounds,
11:48-11:51 UTC, load 1.6-2.9: fusion latency p50/p99 before 30.0/67.6, 29.5/60.3 ms, after
27.2/54.2, 36.3/86.6 ms; end-to-end p99 before 194.0/217.7 ms, after 484.0/231.4 ms (no
clear difference either way). The replays once the machine had a free core::

    ... --recording /tmp/s8/soak/soak16x200.mcap --threads 1,2    11:53-11:57 UTC, load 1.1-1.3
    threads  CPU ms/ne       wall ms/ne      free-core wall ms/ne   digest
    1        0.877 / 0.815   0.878 / 0.815   0.877 / 0.815          500966d8ef81 (all four)
    2        0.867 / 0.852   0.615 / 0.604   0.616 / 0.606
    2 vs 1:  CPU x1.016, wall x0.720, free-core wall x0.722 (kernels: 60-63 % of the CPU)
    ... --recording /tmp/s8/large.mcap (11:52 UTC, load 1.8-1.9): CPU x1.00, wall x0.935,
    free-core wall x0.886, estimates bit-identical.

(the measured wall with a free core equals the free-core projection of the loaded runs:
x0.72 vs x0.75 on the soak).

Live once the other jobs had stopped (11:57-12:05 UTC, load 0.2-2.9: the run's own
processes), alternating, the back-off rule in: ``bench_soak.py --load 16x200 --duration 60
--method mnls`` published before 56,757 / 61,363, after 53,911 / 39,410 of 120,000 (fusion
latency p99 2.9 / 3.6 s vs 4.4 / 4.8 s); ``diffpos emulate scenarios/large.toml --duration 20
--dashboard off --record off`` end-to-end p50/p99 before 30.2/77.3, 28.8/59.3 ms, after
41.6/77.3, 33.4/64.2 ms (fusion latency p50 23.8, 22.5 vs 38.3, 29.7 ms). Live, the run's
own anchors, router and recorder (or emulate) use the second core: 2 kernel threads are
worse there; ``--kernel-threads 1`` is the better setting for these runs on 2 cores.

The shed branch (issues 14/16: the live overload policy, ``fusion.overload``),
2026-11-27 13:31-13:53 UTC, load average 1.4-2.8 (the virtual clock charges this process'
CPU only); the soak input, the first 15 s (``--schedule /tmp/s8/soak/soak16x200.mcap
--seconds 15 --fusion-args "--site soak16x200 --method mnls --scenario .../soak16x200.toml"``,
30,000 node-epochs; ``--cpu-scale 2``: the fusion has half a core). Age: the mean over the
nodes of the time-averaged age of a node's newest published input (what a coordinator sees;
"this branch" and the trial variants coalesce as soon as a step is behind: they predate
``FusionConfig.supersede_after_s``, i.e. ``--fusion-args "... --supersede-after-s 0"`` today;
the default 0.5 s is not in this table)::

    policy when behind                  CPU  estimates       e2e p50 ms    age mean / worst ms
    max_backlog_s drop (main, 1ab98ea)  x1   25,727-29,042   2,053-2,121   1,905-1,991 / 2,131
    this branch (newest 1, round-robin) x1   25,483          93            155 / 168
    keep the newest 1 (*)               x1   21,920-24,493   100-101       167-189 / 189-212
    keep the newest 2 (*)               x1   22,944-25,598   167-197       236-279 / 268-308
    keep the newest 4 (*)               x1   22,010          391           459 / 480
    max_backlog_s drop (main)           x1.5 16,477          2,136         -
    keep the newest 1 / 2 (*)           x1.5 10,824 / 10,451 116 / 213     272 / 379
    max_backlog_s drop (main)           x2   12,294-12,732   2,146-2,147   4,110-4,300 / 7,443
    this branch                         x2   5,339           110           411 / 421
    keep the newest 1 / 2 / 4 (*)       x2   5,812 / 5,941 / 6,037  110 / 210 / 417
                                                                           381 / 488 / 711

(*: trial variants, not kept: the constant ``core.BEHIND_KEEP_EPOCHS`` 1, 2 or 4 with the
nodes queued by the place of their oldest ready epoch instead of least recently served
first; ranges: repeated runs.) Where it falls behind (a per-step trace of the loop on this input, main): the
start-up. The first ~3 s cost 1.1-1.5 ms CPU per node-epoch (200 track initialisations, ~25
per step, and INITIALISING nodes update every hypothesis) against the input's 0.5 ms per
node-epoch budget on one core, so the backlog reaches the 2 s limit by t = 3.5 s; after that
a step of 150-190 epochs costs 0.38-0.52 ms per node-epoch, about the input rate, so the 2 s
debt is never paid back (latency p50 2.1 s for the rest of the run; steps of 165 epochs, p90
180). How the tracker's update cost grows with the gap since a node's previous update (steps
after 4 s of a run of the first implementation, least squares over the steps' mean gap):
``0.31 + 0.26 ms x gap [epochs]`` (gap 1: 0.55, 1.8: 0.81, 2.1: 0.86, 2.8: 0.97 ms): the
dormant hypotheses' refreshes (diffpos/tracking/dormant.py, one per hypothesis per second of
measurement time) and the snapshots are per time, not per update, so skipping a node's
epochs saves only the 0.31 ms part. That is why the new policy publishes fewer estimates
than the old one when the fusion has much less CPU than it needs (x2: about half): the old
one solves whole epochs at a gap of 1 and drops the rest in blocks (uneven: live 0.4-8 node
updates per second, gaps up to 57 s), the new one updates every node about equally often at
longer gaps. Its pictures are 10-13 times fresher either way (age above).
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import importlib
import os
import platform
import queue
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import msgspec
import numpy as np
from common import tree_env
from diffpos_services.fusion.core import FusionCore
from diffpos_services.heap import keep_heap
from diffpos_services.replay.run import replay
from diffpos_services.wire import messages as M

from diffpos._kernels import pool as kernel_pool

TARGET_MS = 2.0


def record(scenario: str, duration_s: float, seed: int, out: Path) -> None:
    """A lockstep run of the whole system, recorded."""
    exe = Path(sys.executable).with_name("diffpos")
    cmd = [str(exe), "emulate", scenario, "--speed", "0", "--duration", str(duration_s),
           "--seed", str(seed), "--dashboard", "off", "--no-progress", "--record", str(out)]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def thread_costs(path: Path, threads: list[int], repeat: int) -> list[dict]:
    """CPU and wall seconds of an M-NLS replay of ``path`` (every epoch solved, no recorded
    decisions) with each kernel thread count, ``repeat`` rounds alternating the counts, and
    a digest of the replayed estimates (their wire bytes: equal digests = bit-identical)."""
    rows = []
    for _ in range(repeat):
        for n in threads:
            kernel_pool.reset_stats()
            w, t = time.perf_counter(), time.process_time()
            r = replay(path, method="mnls", overrides={"kernel_threads": n},
                       use_decisions=False, keep_estimates=True)
            cpu, wall = time.process_time() - t, time.perf_counter() - w
            st = kernel_pool.stats()
            # with a free core per thread: the process CPU with each kernel call's chunks
            # replaced by its busiest thread's share (diffpos._kernels.pool.stats)
            free = cpu - st["chunk_cpu_s"] + st["critical_cpu_s"]
            h = hashlib.sha256()
            for e in r.estimates:
                h.update(M.encode(e))
            rows.append({"threads": n, "cpu_s": cpu, "wall_s": wall, "free_s": free,
                         "kernel_share": st["chunk_cpu_s"] / cpu, "estimates": len(r.estimates),
                         "digest": h.hexdigest()[:12], "load": os.getloadavg()[0]})
            del r
    return rows


#: ``--parts``: the functions timed (module, attribute, label); a label's leading spaces mark a
#: part of the tracker's update (the kernels inside a track initialisation count there too)
PARTS = (
    ("diffpos.estimators.mnls.solver", "mnls", "mnls snapshot fixes"),
    ("diffpos.tracking.tracker", "snapshot_init", "  track initialisations (grid snapshot)"),
    ("diffpos.tracking.tracker", "snapshot", "  floor re-seeds, deficit tests (floor snapshot)"),
    ("diffpos.tracking.model", "pair_snr_db", "  SNR prediction (channel.snr_nb kernel)"),
    ("diffpos.tracking.model", "all_paths", "  paths kernel"),
    ("diffpos.tracking.model", "select", "  mechanism selection"),
    ("diffpos.tracking.model", "iekf", "  IEKF"),
    ("diffpos.tracking.tracker", "match_links", "  learned links: match_links"),
    ("diffpos.tracking.tracker", "learned_weights", "  learned links: learned_weights"),
    ("diffpos.tracking.tracker", "learn", "  learned links: learn"),
    ("diffpos.tracking.tracker", "_mix", "  IMM mixing"),
)


def parts(path: Path, startup_s: float = 1.0, warm_s: float = 16.0) -> tuple[float, dict, dict]:
    """CPU of an M-NLS replay of ``path`` (every epoch solved, no recorded decisions) split
    into the start-up (the first ``startup_s`` of measurement time) and the rest, by part
    (timers around the functions of :data:`PARTS`, the tracker bank's update; process CPU).
    Returns (replay CPU, node-epochs per phase, {(late, label): CPU s})."""
    from diffpos_services.fusion import tracked

    cpu_by: dict = collections.defaultdict(float)
    phase, t0, n_by = [False], [None], collections.Counter()
    saved = []

    def timed(fn, label):
        def run(*a, **k):
            t = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                cpu_by[(phase[0], label)] += time.process_time() - t
        return run

    def update(bank, ids, anchors, ranges, sigmas, mask, t_ns, *a, **k):
        if t0[0] is None:
            t0[0] = int(t_ns.min())
        phase[0] = int(t_ns.min()) - t0[0] >= round(startup_s * 1e9)
        n_by[phase[0]] += len(ids)
        return timed(bank_update, "tracker update (all)")(bank, ids, anchors, ranges, sigmas,
                                                           mask, t_ns, *a, **k)

    bank_update = tracked.TrackBank.update
    for mod, name, label in PARTS:
        m = importlib.import_module(mod)
        saved.append((m, name, getattr(m, name)))
        setattr(m, name, timed(getattr(m, name), label))
    saved.append((tracked.TrackBank, "update", bank_update))
    tracked.TrackBank.update = update
    try:
        replay(path, method="mnls", use_decisions=False, keep_estimates=False,
               end_s=warm_s)  # warm-up: imports, kernels, first calls
        cpu_by.clear()
        n_by.clear()
        t0[0] = None
        t = time.process_time()
        replay(path, method="mnls", use_decisions=False, keep_estimates=False)
        cpu = time.process_time() - t
    finally:
        for obj, name, fn in saved:
            setattr(obj, name, fn)
    return cpu, dict(n_by), dict(cpu_by)


def _print_parts(path: Path, cpu: float, n_by: dict, cpu_by: dict, startup_s: float) -> None:
    n = sum(n_by.values())
    print(f"bench_fusion_cost --parts: recording {path}; machine {platform.machine()} "
          f"{os.cpu_count()} cores, Python {platform.python_version()}, load avg "
          f"{os.getloadavg()[0]:.1f}")
    print(f"  M-NLS replay, every epoch solved: CPU {cpu:.2f} s, {n} node-epochs, "
          f"{1e3 * cpu / max(n, 1):.3f} ms per node-epoch")
    for late in (False, True):
        k = n_by.get(late, 0)
        print(f"  {'after' if late else 'the first'} {startup_s:g} s of measurement time: "
              f"{k} node-epochs")
        print(f"    {'part':<44} {'CPU s':>7} {'ms/node-epoch':>14}")
        for (ph, label), v in sorted(cpu_by.items(), key=lambda x: -x[1]):
            if ph == late:
                print(f"    {label:<44} {v:>7.2f} {1e3 * v / max(k, 1):>14.3f}")
    rest = cpu - sum(v for (_, label), v in cpu_by.items() if not label.startswith(" "))
    print(f"  the rest (ingest, alignment, step assembly, estimates, report; both phases): "
          f"{rest:.2f} s, {1e3 * rest / max(n, 1):.3f} ms per node-epoch")


#: ``--steps``: the work timed and counted per solve step (module, attribute, label, the rows
#: of a call from its arguments): what makes a step slow
STEP_PARTS = (
    ("diffpos_services.fusion.tracked", "update", "tracker update (all)",
     lambda a: a[0].status.shape[0]),
    ("diffpos.tracking.tracker", "_update_pairs", "  hypothesis updates", lambda a: a[3].size),
    ("diffpos.tracking.tracker", "snapshot", "  floor re-seeds (snapshot)", lambda a: len(a[1])),
    ("diffpos.tracking.tracker", "snapshot_init", "  track initialisations",
     lambda a: a[0].rho.shape[0]),
    ("diffpos.estimators.mnls.solver", "mnls", "M-NLS check fixes", lambda a: len(a[0])),
)


def steps(path: Path, warm_s: float = 16.0) -> list[dict]:
    """Per solve step of a replay of ``path`` with its recorded decisions (the live run's
    steps, bit for bit): its epochs, process CPU [s] and, per :data:`STEP_PARTS` label, the
    CPU and the rows of its calls; after a warm-up replay of the first ``warm_s``."""
    rows: list[dict] = []
    cur: dict = collections.defaultdict(float)
    saved = []

    def timed(fn, label, count):
        def run(*a, **k):
            t = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                cur[label] += time.process_time() - t
                cur["#" + label] += count(a)
        return run

    def step(core, now_wall_ns, **k):
        cur.clear()
        n0, t = core.solved, time.process_time()
        out = core_step(core, now_wall_ns, **k)
        if core.solved > n0:
            rows.append({"t_ns": now_wall_ns, "epochs": core.solved - n0,
                         "cpu": time.process_time() - t, **cur})
        return out

    core_step = FusionCore.step
    for mod, name, label, count in STEP_PARTS:
        m = importlib.import_module(mod)
        saved.append((m, name, getattr(m, name)))
        setattr(m, name, timed(getattr(m, name), label, count))
    saved.append((FusionCore, "step", core_step))
    FusionCore.step = step
    try:
        replay(path, keep_estimates=False, end_s=warm_s)  # imports, kernels, first calls
        rows.clear()
        replay(path, keep_estimates=False)
    finally:
        for obj, name, fn in saved:
            setattr(obj, name, fn)
    return rows


def _print_steps(path: Path, rows: list[dict], startup_s: float) -> None:
    t0 = min(r["t_ns"] for r in rows)
    late = [r for r in rows if r["t_ns"] - t0 >= startup_s * 1e9]
    cpu = 1e3 * np.array([r["cpu"] for r in late])
    print(f"bench_fusion_cost --steps: recording {path} (its recorded steps); machine "
          f"{platform.machine()} {os.cpu_count()} cores, load avg {os.getloadavg()[0]:.1f}")
    print(f"  {len(late)} of {len(rows)} steps after the first {startup_s:g} s, "
          f"{sum(r['epochs'] for r in late)} epochs; CPU per step [ms] p50 "
          f"{np.percentile(cpu, 50):.1f} p90 {np.percentile(cpu, 90):.1f} p99 "
          f"{np.percentile(cpu, 99):.1f} max {cpu.max():.1f} mean {cpu.mean():.1f}")
    print(f"    {'part':<30} {'ms/step':>8} {'p90':>6} {'max':>6} {'share':>6} "
          f"{'rows/step':>9} {'max':>5} {'ms/row':>7}")
    for _, _, label, _ in STEP_PARTS:
        v = 1e3 * np.array([r.get(label, 0.0) for r in late])
        n = np.array([r.get("#" + label, 0) for r in late])
        print(f"    {label:<30} {v.mean():>8.2f} {np.percentile(v, 90):>6.2f} {v.max():>6.2f} "
              f"{100 * v.sum() / cpu.sum():>5.1f}% {n.mean():>9.2f} {n.max():>5} "
              f"{v.sum() / max(n.sum(), 1):>7.2f}")
    print("  the slowest steps (CPU ms, epochs, then each part's ms / rows):")
    for i in np.argsort(-cpu)[:6]:
        r = late[i]
        parts_ = ", ".join(f"{label.strip()} {1e3 * r.get(label, 0.0):.1f}/"
                           f"{r.get('#' + label, 0):.0f}" for _, _, label, _ in STEP_PARTS)
        print(f"    {cpu[i]:6.1f} {r['epochs']:4d}  {parts_}")


def _print_threads(path: Path, rows: list[dict]) -> None:
    print(f"bench_fusion_cost --threads: recording {path}; machine {platform.machine()} "
          f"{os.cpu_count()} cores, Python {platform.python_version()}")
    print("  (free-core wall: the process CPU with each split kernel call counted at its busiest "
          "thread's CPU, the wall time with a free core per thread; kernels: their share of "
          "the CPU)")
    print(f"{'threads':>7} {'node-epochs':>11} {'CPU s':>7} {'wall s':>7} {'CPU ms/ne':>9} "
          f"{'wall ms/ne':>10} {'free-core wall ms/ne':>20} {'kernels':>7} {'load1':>5}  digest")
    for r in rows:
        n = max(r["estimates"], 1)
        print(f"{r['threads']:>7} {r['estimates']:>11} {r['cpu_s']:>7.2f} {r['wall_s']:>7.2f} "
              f"{1e3 * r['cpu_s'] / n:>9.3f} {1e3 * r['wall_s'] / n:>10.3f} "
              f"{1e3 * r['free_s'] / n:>20.3f} {100 * r['kernel_share']:>6.0f}% "
              f"{r['load']:>5.1f}  {r['digest']}")
    by = collections.defaultdict(list)
    for r in rows:
        by[r["threads"]].append(r)
    base = by[min(by)]
    for k in sorted(by):
        cpu = sum(r["cpu_s"] for r in by[k]) / sum(r["cpu_s"] for r in base)
        wall = sum(r["wall_s"] for r in by[k]) / sum(r["wall_s"] for r in base)
        free = sum(r["free_s"] for r in by[k]) / sum(r["free_s"] for r in base)
        print(f"  {k} threads vs {min(by)}: CPU x{cpu:.3f}, wall x{wall:.3f}, free-core wall "
              f"x{free:.3f}")
    print("  estimates bit-identical across thread counts:",
          len({r["digest"] for r in rows}) == 1)


def cost(path: Path, method: str) -> tuple[float, int, dict]:
    """CPU seconds of one replay and the node-epochs it solved."""
    t = time.process_time()
    r = replay(path, method=method, keep_estimates=False)
    cpu = time.process_time() - t
    return cpu, int(r.report["fixes"]["total"]), r.report


def _cost_in(tree: Path | None, argv: list[str]) -> dict:
    """One ``--cost-json`` run of this script under ``tree``'s code (a fresh process)."""
    out = subprocess.run([sys.executable, __file__, *argv, "--cost-json"], env=tree_env(tree),
                         check=True, capture_output=True, text=True).stdout
    return msgspec.json.decode(out.strip().splitlines()[-1])


def compare(other: Path, argv: list[str], rounds: int) -> list[tuple[str, dict]]:
    """``rounds`` x (other checkout, this one), alternating, each a fresh process: CPU per
    node-epoch of the same measurement (``argv``: ``--recording R`` or ``--schedule R ...``)."""
    here = Path(__file__).resolve().parents[1]
    rows = []
    for _ in range(rounds):
        for name, tree in (("before", other), ("after", here)):
            rows.append((name, _cost_in(tree, argv)))
    return rows


def _print_compare(other: Path, argv: list[str], rows: list[tuple[str, dict]]) -> None:
    print(f"bench_fusion_cost --compare {other} {' '.join(argv)}: machine {platform.machine()} "
          f"{os.cpu_count()} cores, Python {platform.python_version()}, load avg "
          f"{os.getloadavg()[0]:.1f} at the end")
    print(f"{'round':>5} {'code':<7} {'node-epochs':>11} {'CPU s':>7} {'ms/node-epoch':>14} "
          f"{'load':>5}")
    per = collections.defaultdict(list)
    for i, (name, r) in enumerate(rows):
        ms = 1e3 * r["cpu_s"] / max(r["n"], 1)
        per[name].append(ms)
        print(f"{i // 2 + 1:>5} {name:<7} {r['n']:>11} {r['cpu_s']:>7.2f} {ms:>14.3f} "
              f"{r['load']:>5.1f}")
    b, a = min(per["before"]), min(per["after"])
    print(f"best of each: before {b:.3f}, after {a:.3f} ms per node-epoch: after / before "
          f"{a / b:.3f}")


class _VirtualClock:
    """Wall clock of the schedule: the first input's receive time, then + the CPU time this
    process used (times ``cpu_scale``: 2 = a core half as fast, or half a core), + the idle
    time skipped while waiting for the next input."""

    def __init__(self, t0_ns: int, cpu_scale: float = 1.0) -> None:
        self.base = t0_ns
        self.cpu0 = time.process_time_ns()
        self.scale = float(cpu_scale)

    def time_ns(self) -> int:
        return self.base + round(self.scale * (time.process_time_ns() - self.cpu0))

    monotonic_ns = time_ns

    def skip_to(self, t_ns: int) -> None:
        self.base += max(t_ns - self.time_ns(), 0)


class _ScheduledQueue:
    """The loop's input queue: each item becomes available at its recorded receive time."""

    def __init__(self, items: list, clock: _VirtualClock) -> None:
        self.items = collections.deque(items)  # (rx_ns, queue item), by rx
        self.clock = clock

    def get_nowait(self):
        if self.items and self.items[0][0] <= self.clock.time_ns():
            return self.items.popleft()[1]
        raise queue.Empty

    def get(self, timeout: float | None = None):
        if not self.items:
            raise queue.Empty
        nxt, now = self.items[0][0], self.clock.time_ns()
        if nxt > now and timeout is not None and nxt > now + timeout * 1e9:
            self.clock.skip_to(now + round(timeout * 1e9))
            raise queue.Empty
        self.clock.skip_to(nxt)
        return self.items.popleft()[1]

    def qsize(self) -> int:
        now = self.clock.time_ns()
        return sum(1 for rx, _ in self.items if rx <= now)


def _fusion_config(path: Path, fusion_argv: list[str] | None):
    """The recorded live fusion settings, or those of ``diffpos fusion FUSION_ARGV`` (a
    recording without settings, e.g. bench_soak's recorder)."""
    from diffpos_services.fusion.config import FusionConfig
    from diffpos_services.recording.reader import side_records
    from diffpos_services.recording.summary import live_fusion_settings

    if fusion_argv is not None:
        from diffpos_services.cli import fusion as cli
        from diffpos_services.scenario_io import load_scenario_option

        ap = argparse.ArgumentParser()
        cli.add_arguments(ap)
        args = ap.parse_args(fusion_argv)
        return cli.config_from_args(args, load_scenario_option(args.scenario))
    settings, _ = live_fusion_settings(side_records(path))
    known = set(FusionConfig.__struct_fields__)
    return msgspec.convert({k: v for k, v in settings.items() if k in known}, FusionConfig)


def schedule(path: Path, startup_s: float = 2.0, *, seconds: float | None = None,
             fusion_argv: list[str] | None = None, cpu_scale: float = 1.0) -> dict:
    """The live loop on the recorded real-time input, on a virtual clock (module docstring):
    the first ``seconds`` of input (None: all), the recorded fusion settings or those of
    ``fusion_argv``; ``cpu_scale`` > 1 charges each CPU second that many wall seconds (a
    fusion with only 1 / cpu_scale of a core: the overload of a loaded machine, reproducibly)."""
    import logging

    from diffpos_services.fusion import service
    from diffpos_services.fusion.core import FusionCore
    from diffpos_services.recording.reader import McapScanner
    from diffpos_services.recording.topics import parse_topic
    from diffpos_services.replay.synthetic import FUSION_INPUT_KINDS

    cfg = _fusion_config(path, fusion_argv)
    items, anchors = [], set()
    for m in McapScanner(path).messages():
        kind, fields = parse_topic(m.topic)
        if kind in FUSION_INPUT_KINDS:
            anchors.add(fields["anchor"])
            items.append((m.log_ns, (service._DATA, m.topic, m.data, m.log_ns)))
    items.sort(key=lambda x: x[0])
    t0 = items[0][0]
    if seconds is not None:
        items = [x for x in items if x[0] < t0 + round(seconds * 1e9)]
    keys = service.Keys(cfg.site)
    items[:0] = [(t0 - 1, (service._ALIVE, keys.alive_anchor(a), True, t0 - 1))
                 for a in sorted(anchors)]
    log = logging.getLogger("bench.schedule")
    log.addHandler(logging.NullHandler())
    log.propagate = False
    # the virtual clock is one core of its own (process CPU): one kernel thread, whatever
    # the recorded kernel_threads (on 2 threads it would charge both threads' CPU)
    kernel_pool.set_threads(1)
    core = FusionCore(cfg, logger=log, record_decisions=False)
    core.warm_up()
    if hasattr(service, "freeze_heap"):  # as run_fusion does after its warm-up
        service.freeze_heap()
    clock = _VirtualClock(t0 - 1, cpu_scale)
    inbox = type("Inbox", (), {})()
    inbox.q, inbox.release = _ScheduledQueue(items, clock), lambda size: None
    lat: list[tuple[int, int]] = []  # (input publish, estimate publish) [ns]
    by_node: dict[str, list[tuple[int, int]]] = collections.defaultdict(list)

    def put(e) -> None:  # what the service's publisher does before the bus: encode
        M.encode(e)
        if e.t_input_wall_ns > 0:
            lat.append((e.t_input_wall_ns, e.t_pub_wall_ns))
            by_node[e.node_id].append((e.t_input_wall_ns, e.t_pub_wall_ns))

    real_time = service.time
    service.time = clock  # the loop's clock (time_ns, monotonic_ns) is the virtual one
    try:
        loop = service.ServiceLoop(core, inbox, put, lambda d: None, log)
        sizes = []
        cpu = time.process_time()
        while inbox.q.items or core.backlog:
            turn = loop.turn()
            if turn.published:
                sizes.append(turn.published)
        cpu = time.process_time() - cpu
    finally:
        service.time = real_time
    if not lat:
        raise SystemExit(
            f"bench_fusion_cost --schedule {path}: the fusion published no estimate from the "
            f"recording's input with site {cfg.site!r} (a recording without fusion settings, "
            "e.g. bench_soak's: give them, e.g. --fusion-args '--site soak16x200 --method mnls "
            "--scenario DIR/soak16x200.toml')")
    a = np.array(lat, np.int64)
    e2e_ms = (a[:, 1] - a[:, 0]) * 1e-6
    start = a[:, 0] < t0 + round(startup_s * 1e9)

    def pct(v):
        return [round(float(np.percentile(v, q)), 1) for q in (50, 99)] + [
            round(float(v.max()), 1)] if v.size else [None] * 3

    return {"estimates": int(a.shape[0]), "cpu_s": cpu, "ms_per_node_epoch":
            1e3 * cpu / max(a.shape[0], 1), "e2e_ms_p50_p99_max": pct(e2e_ms),
            "startup_e2e_ms_p50_p99_max": pct(e2e_ms[start]),
            "after_startup_e2e_ms_p50_p99_max": pct(e2e_ms[~start]),
            "over_50ms": int((e2e_ms > 50).sum()), "steps": len(sizes),
            "epochs_per_step_p50_p90_max": [int(np.percentile(sizes, 50)),
                                            int(np.percentile(sizes, 90)), int(max(sizes))],
            "superseded": int(core.rejected.get("superseded", 0)),
            "overloaded": int(core.rejected.get("overloaded", 0)),
            "uninitialised": int(core.by_status.get("UNINITIALISED", 0)),
            "age_of_information_ms_mean_worst": age_of_information(by_node, items[-1][0])}


def age_of_information(by_node: dict[str, list[tuple[int, int]]], t_end_ns: int) -> list:
    """How old each node's picture is on average (the age of information): from a node's
    first published estimate to ``t_end_ns``, the time average of (now - input publish time
    of the node's newest published estimate), per node [ms]; returns the mean over the nodes
    and the worst node's. Counts both latency and the gaps between a node's updates: a
    fusion 2 s behind has an age >= 2 s however many estimates it publishes."""
    ages = []
    for rows in by_node.values():
        rows = sorted((r for r in rows if r[1] <= t_end_ns), key=lambda r: r[1])
        if not rows or rows[0][1] >= t_end_ns:
            continue
        area, newest = 0.0, rows[0][0]
        for (t_in, p0), (_, p1) in zip(rows, [*rows[1:], (0, t_end_ns)], strict=True):
            newest = max(newest, t_in)
            area += (p1 - p0) * ((p0 - newest) + 0.5 * (p1 - p0))
        ages.append(area / (t_end_ns - rows[0][1]) * 1e-6)
    return [round(float(np.mean(ages)), 1), round(float(np.max(ages)), 1)] if ages else [None] * 2


def main(argv: list[str] | None = None) -> int:
    keep_heap()  # the allocator settings of the live fusion process (diffpos_services.heap)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="large", help="scenario name or file (default large)")
    ap.add_argument("--duration", type=float, default=10.0, help="emulated seconds (default 10)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--recording", type=Path, help="replay this recording instead of making one")
    ap.add_argument("--schedule", type=Path, metavar="REC",
                    help="the live loop on this real-time recording's input, virtual clock")
    ap.add_argument("--seconds", type=float, help="--schedule: only the first S s of input")
    ap.add_argument("--cpu-scale", type=float, default=1.0, metavar="X",
                    help="--schedule: charge each CPU second X wall seconds (default 1; 2: the "
                    "fusion has half a core)")
    ap.add_argument("--fusion-args", metavar="ARGS",
                    help="--schedule: the settings of 'diffpos fusion ARGS' (one string) "
                    "instead of the recorded ones")
    ap.add_argument("--threads", metavar="N,N,...",
                    help="with --recording: M-NLS replays (all epochs, no recorded decisions) "
                    "with these kernel_threads, CPU and wall per node-epoch, alternating")
    ap.add_argument("--repeat", type=int, default=2, help="--threads: rounds (default 2)")
    ap.add_argument("--parts", action="store_true",
                    help="with --recording: an M-NLS replay's CPU per node-epoch by part, the "
                    "start-up (first --startup-s) apart from the rest")
    ap.add_argument("--startup-s", type=float, default=1.0, metavar="S",
                    help="--parts: the start-up's length [s of measurement time] (default 1); "
                    "--steps: of wall time (the steps before it are left out)")
    ap.add_argument("--steps", action="store_true",
                    help="with --recording: CPU per solve step of a replay by the recorded "
                    "decisions, by part (re-seeds, initialisations, M-NLS check fixes)")
    ap.add_argument("--compare", type=Path, metavar="CHECKOUT",
                    help="with --recording (an M-NLS replay, the recorded decisions) or "
                    "--schedule: the same measurement by CHECKOUT's code and this one's, "
                    "alternating in fresh processes (--repeat rounds), ratio side by side")
    ap.add_argument("--cost-json", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.compare is not None:
        sub = list(argv if argv is not None else sys.argv[1:])
        i = sub.index("--compare")
        sub = sub[:i] + sub[i + 2:]
        _print_compare(args.compare, sub, compare(args.compare, sub, args.repeat))
        return 0
    if args.cost_json:  # one measurement for --compare, as JSON on the last line
        if args.schedule is not None:
            r = schedule(args.schedule, seconds=args.seconds, cpu_scale=args.cpu_scale,
                         fusion_argv=None if args.fusion_args is None
                         else args.fusion_args.split())
            out = {"n": r["estimates"], **{k: v for k, v in r.items()
                                           if isinstance(v, (int, float))}}
        else:
            cost(args.recording, "mnls")  # warm-up: imports, kernels, first calls
            cpu, n, _ = cost(args.recording, "mnls")
            out = {"cpu_s": cpu, "n": n}
        out["load"] = os.getloadavg()[0]
        print(msgspec.json.encode(out).decode())
        return 0
    if args.parts and args.recording is not None:
        _print_parts(args.recording, *parts(args.recording, args.startup_s), args.startup_s)
        return 0
    if args.steps and args.recording is not None:
        _print_steps(args.recording, steps(args.recording), args.startup_s)
        return 0
    if args.threads is not None and args.recording is not None:
        counts = [int(v) for v in args.threads.split(",")]
        _print_threads(args.recording, thread_costs(args.recording, counts, args.repeat))
        return 0
    if args.schedule is not None:
        r = schedule(args.schedule, seconds=args.seconds, cpu_scale=args.cpu_scale,
                     fusion_argv=None if args.fusion_args is None else args.fusion_args.split())
        print(f"bench_fusion_cost --schedule {args.schedule}: machine {platform.machine()} "
              f"{os.cpu_count()} cores, load avg {os.getloadavg()[0]:.1f} (virtual clock: CPU "
              f"time of this process x {args.cpu_scale:g})")
        for k, v in r.items():
            print(f"  {k:<34} {v if not isinstance(v, float) else round(v, 3)}")
        return 0
    with tempfile.TemporaryDirectory(prefix="bench-fusion-cost-") as tmp:
        rec = args.recording or Path(tmp) / "run.mcap"
        if args.recording is None:
            record(args.scenario, args.duration, args.seed, rec)
        cost(rec, "mnls")  # warm-up: imports, kernels, first calls
        rows = []
        for method in ("mnls", "dnls"):
            cpu, n, rep = cost(rec, method)
            rows.append((method, cpu, n, rep))
    what = (f"recording {args.recording}" if args.recording is not None else
            f"{args.scenario}, {args.duration:g} s lockstep recording, seed {args.seed}")
    print(f"bench_fusion_cost: {what}; machine {platform.machine()} {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load avg {os.getloadavg()[0]:.1f}")
    print(f"{'method':<8} {'node-epochs':>11} {'CPU s':>7} {'ms/node-epoch':>14} "
          f"{'floor':>6}  (floor: all node-epochs after 2 s)  target <= {TARGET_MS} ms (8 anchors)")
    for method, cpu, n, rep in rows:
        per = 1e3 * cpu / max(n, 1)
        floor = (rep.get("node_epochs") or {}).get("floor_accuracy_all")
        fl = f"{100 * floor:5.1f}%" if isinstance(floor, float) else "   -"
        ok = ("met" if per <= TARGET_MS else "NOT met") if method == "mnls" else ""
        print(f"{method:<8} {n:>11} {cpu:>7.2f} {per:>14.3f} {fl:>6}  {ok}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
