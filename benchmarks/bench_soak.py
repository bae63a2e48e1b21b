"""Load and soak: M anchors x N nodes x 10 Hz through the real runtime, for minutes.

Starts a router, the MCAP recorder, the fusion and M anchor processes (``--channel ideal``,
``--range-batch``: one RangeBatch per anchor epoch) on loopback with congestion control
BLOCK everywhere, runs in real time for ``--duration`` seconds and reports

- loss (must be 0 with BLOCK): ranges received by the fusion vs sent, estimates received by
  this subscriber vs expected (every node, every epoch), recorder received vs written and its
  sequence gaps;
- how an overloaded fusion served the nodes: estimates per node per second (min / median /
  max over the nodes), the gaps between a node's consecutive estimates, and the node-epochs
  it did not solve (``superseded``: a newer epoch of the node was solved instead;
  ``overloaded``: more than ``max_backlog_s`` behind; FusionConfig.max_backlog_s);
- how long the responders, all switched on at the run's start, waited for their first
  estimate with a position (p50 / p90 / max over the nodes): what a fusion that admits new
  tracks only with headroom (FusionConfig.admit_lag_s) trades for losing nothing;
- fusion latency (estimate publish - newest input publish) p50/p99/max overall and per
  minute; ranges that arrived after their epoch was solved (``late``, not a transport loss);
- RSS of every process (router, recorder, fusion, each anchor, this subscriber) after the
  warm-up and at the end, growth, and the slope of a line fitted to the samples [MB/min];
- the recorder file size.

The scenario, RSS probe and ports come from ``bench_latency.py`` (same machinery, longer run,
more processes watched)::

    python benchmarks/bench_soak.py --load 16x200 --duration 600 --json soak.json
    python benchmarks/bench_soak.py --load 16x50 --duration 60          # the CI size
    python benchmarks/bench_soak.py --load 16x200 --duration 60 --shards 2   # 2 fusion shards

With ``--shards N`` it runs N fusion processes (``diffpos fusion --shard K/N``) and prints each
one's CPU per node-epoch (after the start-up and over the run; docs/soak.md, "Fusion shards").

``tests/system/test_soak.py`` runs :func:`run_soak` for 60 s and asserts zero loss and bounded RSS.

The live overload policy (shed branch, issues 14/16; FusionConfig.max_backlog_s), 2026-11-27,
2-core VM shared with other jobs, ``python benchmarks/bench_soak.py --load 16x200 --duration 60
--warmup 10 --method mnls``, before = main at 1ab98ea (its ``services`` on PYTHONPATH), after =
this branch, run back to back (13:53-13:56 UTC, load average 1.4-4.1; "after" is the shed
branch before ``FusionConfig.supersede_after_s`` existed, i.e. coalescing as soon as a step
is behind, today's ``--supersede-after-s 0``; with the default 0.5 s not measured here)::

                                          before (1ab98ea)         after
    estimates of 120,000                  59,832                   55,190
    fusion latency p50 / p99 / max        2,122 / 2,803 / 2,894 ms 130 / 199 / 241 ms
    estimates per node per second         0.78 / 3.53 / 8.53       4.52 / 4.62 / 4.70
      (min / median / max over nodes)
    gap between a node's estimates        1 / 10 / 130 epochs      2 / 4 / 5 epochs
      (p50 / p99 / max)
    age of a node's picture mean / worst  2,719 / 6,739 ms         247 / 249 ms
    not solved: overloaded / superseded   60,168 / -               0 / 64,810
    ranges delivered, recorded            1,920,000 of 1,920,000, recorder received =
                                          written, no sequence holes (both)

Earlier rounds with a first version (each node's newest two epochs kept, places by queue
position), interleaved with main: load 0.9-3.0: main 45,820 estimates, p50 2,143 ms, 0.45-8.12
estimates per node per second, longest gap 354 epochs; that version 60,084, 222 ms, 4.37-5.70,
8 epochs. Load 4-7.7 (other jobs): main 47,256 / 31,538 estimates, that version 29,360 /
25,635 (p50 2,143 vs 224-229 ms; 0.43-8.2 vs 1.97-2.67 per node per second): with much less
CPU than it needs the new policy publishes fewer estimates (the tracker's update costs more
after a longer gap: bench_fusion_cost.py, where ``--schedule --cpu-scale 2`` shows the same
reproducibly: 12,732 vs 5,339 of 30,000, age 4.1 s vs 0.41 s).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from common import PERIOD_NS, cpu_s, rss_mb, scenario_toml
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.fusion.config import shard_of
from diffpos_services.processes import free_tcp_port, stop_process_groups
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

__all__ = ["AgeOfInformation", "LatencyHistogram", "run_soak"]


class LatencyHistogram:
    """Log-spaced histogram of latencies [ms] (1 % bins from 1 us to 1000 s): bounded memory
    for millions of samples, percentiles to about 1 %."""

    def __init__(self) -> None:
        self.edges = np.geomspace(1e-3, 1e6, 2085)
        self.counts = np.zeros(self.edges.size + 1, np.int64)
        self.max_ms = 0.0

    def add(self, values_ms) -> None:
        v = np.asarray(values_ms, float)
        if v.size:
            self.counts += np.bincount(np.searchsorted(self.edges, v), minlength=self.counts.size)
            self.max_ms = max(self.max_ms, float(v.max()))

    @property
    def count(self) -> int:
        return int(self.counts.sum())

    def percentile(self, q: float) -> float | None:
        n = self.count
        if n == 0:
            return None
        k = int(np.searchsorted(np.cumsum(self.counts), q / 100.0 * n))
        return float(self.edges[min(k, self.edges.size - 1)])


class AgeOfInformation:
    """How old each node's picture is on average: from a node's first estimate to the end of
    the run, the time average of (now - input publish time of the node's newest estimate)
    [ms]. Counts latency and the gaps between a node's updates together (a fusion 2 s behind
    has an age >= 2 s however many estimates it publishes); O(1) per estimate."""

    def __init__(self) -> None:
        self.state: dict[str, list[float]] = {}  # node -> [first pub, last pub, newest input, area]

    def add(self, node_id: str, t_input_ns: int, t_pub_ns: int) -> None:
        st = self.state.get(node_id)
        if st is None:
            self.state[node_id] = [t_pub_ns, t_pub_ns, t_input_ns, 0.0]
            return
        dt = t_pub_ns - st[1]
        if dt > 0:
            st[3] += dt * ((st[1] - st[2]) + 0.5 * dt)
            st[1] = t_pub_ns
        st[2] = max(st[2], t_input_ns)

    def summary(self, t_end_ns: int) -> list | None:
        """``[mean over the nodes, worst node]`` [ms] up to ``t_end_ns``."""
        ages = []
        for first, last, newest, area in self.state.values():
            if t_end_ns > first:
                dt = max(t_end_ns - last, 0)
                ages.append((area + dt * ((last - newest) + 0.5 * dt)) / (t_end_ns - first) * 1e-6)
        return [round(float(np.mean(ages)), 1), round(float(np.max(ages)), 1)] if ages else None


def _slope_mb_per_min(samples: list[tuple[float, float]]) -> float | None:
    if len(samples) < 3:
        return None
    t = np.array([s[0] for s in samples]) / 60.0
    r = np.array([s[1] for s in samples])
    return float(np.polyfit(t - t[0], r, 1)[0])


def run_soak(
    n_anchors: int,
    n_nodes: int,
    duration_s: float,
    log_dir: Path,
    *,
    recorder: bool = True,
    warmup_s: float = 10.0,
    rss_period_s: float = 2.0,
    ready_timeout_s: float = 180.0,
    site: str | None = None,
    max_backlog_s: float | None = None,
    method: str = "dnls",
    kernel_threads: int | None = None,
    workers: int | None = None,
    shards: int = 1,
) -> dict:
    """Run the load and return the measurements (see the module docstring).

    Parameters
    ----------
    n_anchors, n_nodes : int
        Anchor processes and static nodes (every anchor ranges to every node at 10 Hz).
    duration_s : float [s]
        Emulated = wall run length (speed 1).
    log_dir : Path
        Service logs, the scenario and the recording go here.
    warmup_s : float [s]
        RSS "start" is the first sample after this much of the run.
    max_backlog_s : float [s], optional
        The fusion's ``--max-backlog-s`` (None: the live default, the overload policy on;
        0: never drop epochs, a fusion that falls behind only lags).
    method : str
        The fusion's ``--method``. Default ``dnls``: this soak measures the transport, the
        recorder and the fusion's ingest at a load (16 x 200 x 10 Hz) where the default
        ``mnls`` + tracker does not keep up on 2 cores yet (docs/performance.md, live). Measured
        2026-11-27 (``--load 16x200 --duration 120 --method mnls``, machine shared, load
        4.8-7.8): 15,145 / 240,000 estimates before the bounded, batched steps of the
        livefuse branch, 24,013 after; every range delivered, the rest dropped as
        ``overloaded`` (the tracker needs ~1.7-2 ms CPU per node-epoch with 16 anchors:
        3-4 cores for 2,000 node-epochs per second).
    kernel_threads : int, optional
        The fusion's ``--kernel-threads`` (None: its default).
    workers : int, optional
        The fusion's ``--workers`` (None: its default, 1). Its worker processes (children of
        the fusion, found once it is ready) are sampled as ``fworker<i>`` (CPU role
        ``fusion-workers``; multiprocessing's resource tracker, also a child, included).
    shards : int
        Fusion processes sharing the responders (``diffpos fusion --shard K/N``, named
        ``fusion-K``; 1: one ``fusion``). The run waits for each one's heartbeat, ends when
        every shard's diagnostics say it is done, and reports each one's CPU per node-epoch
        (``cpu_per_node_epoch``: its CPU seconds over its estimates received here, after the
        start-up and over the whole run).
    """
    site = site or f"soak{n_anchors}x{n_nodes}"
    keys = Keys(site)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    log_dir.mkdir(parents=True, exist_ok=True)
    scen = log_dir / f"{site}.toml"
    scen.write_text(scenario_toml(n_anchors, n_nodes))
    mcap = log_dir / f"{site}.mcap"
    procs: dict[str, subprocess.Popen] = {}
    env = dict(os.environ, DIFFPOS_LOG_FORMAT="text")

    def start(name: str, *argv: str) -> subprocess.Popen:
        with open(log_dir / f"{site}-{name}.log", "wb") as log:
            p = subprocess.Popen([sys.executable, "-m", "diffpos_services.cli.main", *argv],
                                 stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 start_new_session=True, env=env)
        procs[name] = p
        return p

    q: queue.Queue = queue.Queue()
    alive: set[str] = set()
    cv = threading.Condition()

    def on_alive(s) -> None:
        import zenoh

        with cv:
            (alive.add if s.kind == zenoh.SampleKind.PUT else alive.discard)(str(s.key_expr))
            cv.notify_all()

    def on_data(s) -> None:
        q.put((str(s.key_expr), s.payload.to_bytes(), time.time_ns()))

    beating: set[int] = set()  # pids of the fusion processes that sent a heartbeat
    dec_hb = M.decoder(M.Heartbeat)

    def on_heartbeat(s) -> None:
        with contextlib.suppress(M.DecodeError), cv:
            beating.add(dec_hb(s.payload.to_bytes()).pid)
            cv.notify_all()

    fusions = ["fusion"] if shards == 1 else [f"fusion-{k}" for k in range(shards)]
    by_shard = np.zeros(shards, np.int64)  # estimates received per shard (the node's owner)
    owner: dict[str, int] = {}
    shard_counts: dict[float, list[int]] = {}  # by_shard at each CPU sample time

    node_ids = [f"n{i + 1:03d}" for i in range(n_nodes)]
    node_index = {n: i for i, n in enumerate(node_ids)}
    n_epochs = round(duration_s * 10)
    seen = np.zeros((n_nodes, n_epochs), np.uint8)
    first_fix = np.full(n_nodes, n_epochs, np.int64)  # each node's first epoch with a position
    hist = LatencyHistogram()
    per_minute: list[LatencyHistogram] = []
    settled = LatencyHistogram()  # latencies after the first STARTUP_S (whole sample chunks)
    statuses: dict[str, int] = {}
    rss: dict[str, list[tuple[float, float]]] = {}
    cpu: dict[str, list[tuple[float, float]]] = {}
    out_of_run = 0
    aoi = AgeOfInformation()
    diags: dict[int, M.FusionDiagnostics] = {}
    result: dict = {"anchors": n_anchors, "nodes": n_nodes, "rate_hz": 10, "method": method,
                    "duration_s": duration_s, "range_batch": True, "recorder": recorder}
    t0 = 0
    try:
        start("router", "router", "--listen", endpoint)
        session = open_session(ZenohSettings(connect=(endpoint,)), threading.Event())
        with session:
            import zenoh

            subs = [session.liveliness().declare_subscriber(keys.alive_all(), on_alive,
                                                            history=True),
                    session.declare_subscriber(keys.estimates(), on_data),
                    session.declare_subscriber(keys.fusion_diagnostics(), on_data),
                    session.declare_subscriber(keys.heartbeat("fusion"), on_heartbeat)]
            need = {keys.alive_fusion()} | {keys.alive_anchor(f"uav{j + 1}")
                                            for j in range(n_anchors)}
            if recorder:
                start("recorder", "recorder", "--site", site, "--out", str(mcap), "--connect",
                      endpoint, "--scenario", str(scen), "--status")
                need.add(keys.alive_recorder())
            for k, name in enumerate(fusions):
                start(name, "fusion", "--site", site, "--connect", endpoint,
                      "--scenario", str(scen), "--diagnostics-period-s", "1.0", "--method",
                      method,
                      *([] if max_backlog_s is None else ["--max-backlog-s", str(max_backlog_s)]),
                      *([] if kernel_threads is None else ["--kernel-threads",
                                                           str(kernel_threads)]),
                      *([] if workers is None else ["--workers", str(workers)]),
                      *([] if shards == 1 else ["--shard", f"{k}/{shards}"]))
            for j in range(n_anchors):
                start(f"uav{j + 1}", "anchor", "--id", f"uav{j + 1}", "--site", site,
                      "--connect", endpoint, "--scenario", str(scen), "--wait-start",
                      "--channel", "ideal", "--seed", str(j), "--clock-offset-ms", "0.5",
                      "--range-batch")
            deadline = time.monotonic() + ready_timeout_s
            with cv:
                # every fusion process's heartbeat: the shards share one liveliness key
                while not (need <= alive and {procs[f].pid for f in fusions} <= beating):
                    dead = [n for n, p in procs.items() if p.poll() is not None]
                    if time.monotonic() > deadline or dead:
                        raise RuntimeError(f"not ready: missing {sorted(need - alive)}, "
                                           f"exited {dead} (logs in {log_dir})")
                    cv.wait(0.2)
            pids = {name: p.pid for name, p in procs.items()}
            pids["bench"] = os.getpid()
            for f in fusions:
                for i, pid in enumerate(_children(procs[f].pid)):
                    pids[f"fworker{f[len('fusion'):]}{i + 1}"] = pid
            t0 = -(-(time.time_ns() + 1_000_000_000) // PERIOD_NS) * PERIOD_NS
            rc = M.RunControl(run_id=site, t0_ns=t0, wall_t0_ns=t0, speed=1.0,
                              duration_ns=round(duration_s * 1e9), seed=0)
            session.put(keys.run_control(), M.encode(rc),
                        congestion_control=zenoh.CongestionControl.BLOCK)
            end_ns = t0 + rc.duration_ns
            e0 = t0 // PERIOD_NS
            dec_e, dec_d = M.estimate_decoder(), M.decoder(M.FusionDiagnostics)  # estimate v1 and v2
            lat_chunk: list[float] = []
            next_rss = time.monotonic()
            hard_end = time.monotonic() + duration_s + 60
            received_est = 0
            while time.monotonic() < hard_end:
                now = time.monotonic()
                if now >= next_rss:
                    t_rel = (time.time_ns() - t0) * 1e-9
                    for name, pid in pids.items():
                        v, c = rss_mb(pid), cpu_s(pid)
                        if v is not None:
                            rss.setdefault(name, []).append((t_rel, v))
                        if c is not None:
                            cpu.setdefault(name, []).append((t_rel, c))
                    shard_counts[t_rel] = by_shard.tolist()
                    next_rss += rss_period_s
                    hist.add(lat_chunk)
                    minute = max(int(t_rel // 60), 0)
                    while len(per_minute) <= minute:
                        per_minute.append(LatencyHistogram())
                    per_minute[minute].add(lat_chunk)
                    if t_rel - rss_period_s >= STARTUP_S:  # the chunk began after the start-up
                        settled.add(lat_chunk)
                    lat_chunk = []
                    for name, p in procs.items():
                        if p.poll() is not None:
                            raise RuntimeError(f"{name} exited ({p.returncode}) during the "
                                               f"run (logs in {log_dir})")
                try:
                    key, val, _t_rx = q.get(timeout=0.2)
                except queue.Empty:
                    continue
                pk = parse_key(key)
                if pk.kind == "estimate":
                    e = dec_e(val)
                    received_est += 1
                    k = e.epoch - e0
                    i = node_index.get(e.node_id)
                    if i is None or not 0 <= k < n_epochs:
                        out_of_run += 1
                    else:
                        seen[i, k] = min(int(seen[i, k]) + 1, 255)
                        if e.position_m is not None:
                            first_fix[i] = min(first_fix[i], k)
                    statuses[e.status] = statuses.get(e.status, 0) + 1
                    k_own = owner.get(e.node_id)
                    if k_own is None:
                        k_own = owner[e.node_id] = shard_of(e.node_id, shards)
                    by_shard[k_own] += 1
                    if e.t_input_wall_ns > 0:
                        lat_chunk.append((e.t_pub_wall_ns - e.t_input_wall_ns) * 1e-6)
                        aoi.add(e.node_id, e.t_input_wall_ns, e.t_pub_wall_ns)
                else:
                    diag = dec_d(val)
                    diags[diag.shard] = diag
                    if len(diags) == shards and all(
                            d.watermark_ns is not None and d.watermark_ns >= end_ns - PERIOD_NS
                            and d.pending_epochs == 0 for d in diags.values()) \
                            and received_est >= sum(d.published for d in diags.values()):
                        break
            hist.add(lat_chunk)
            for s in subs:
                s.undeclare()
    finally:
        codes = _stop_all(procs)
    result["exit_codes"] = codes
    # ---- loss
    expected = n_nodes * n_epochs
    result.update(
        estimates_expected=expected,
        estimates_received=int(np.count_nonzero(seen)),
        estimates_missing=int(np.count_nonzero(seen == 0)),
        estimates_duplicated=int(np.count_nonzero(seen > 1)),
        estimates_outside_run=out_of_run,
        missing_by_epoch=_missing_summary(seen),
        statuses=statuses,
        per_node=_per_node_summary(seen, duration_s),
        first_position_s=_first_position_summary(first_fix, n_epochs),
    )
    result["per_node"]["age_of_information_ms_mean_worst"] = aoi.summary(t0 + round(
        duration_s * 1e9)) if t0 else None
    if diags:
        result["fusion"] = _fusion_summary(diags, n_anchors * n_nodes * n_epochs)
    result["shards"] = shards
    result["cpu_per_node_epoch"] = _cpu_per_node_epoch(cpu, shard_counts, fusions)
    # ---- latency
    result["latency_fusion_ms"] = {"p50": hist.percentile(50), "p99": hist.percentile(99),
                                   "max": hist.max_ms, "count": hist.count}
    result["latency_after_startup_ms"] = {"p50": settled.percentile(50),
                                          "p99": settled.percentile(99),
                                          "max": settled.max_ms, "count": settled.count}
    result["latency_per_minute_ms"] = [
        {"minute": k, "p50": h.percentile(50), "p99": h.percentile(99), "max": h.max_ms}
        for k, h in enumerate(per_minute) if h.count
    ]
    # ---- memory
    mem = {}
    for name, samples in rss.items():
        after = [s for s in samples if s[0] >= warmup_s] or samples
        mem[name] = {"start_mb": after[0][1], "end_mb": samples[-1][1],
                     "max_mb": max(v for _, v in samples),
                     "growth_mb": samples[-1][1] - after[0][1],
                     "slope_mb_per_min": _slope_mb_per_min(after),
                     "samples": [[round(t, 1), round(v, 1)] for t, v in samples]}
    result["rss"] = mem
    result["cpu_cores"] = _cpu_cores(cpu)
    # ---- recorder
    if recorder:
        result["recorder"] = _recorder_summary(log_dir / f"{site}-recorder.log")
        result["recorder"]["file_mb"] = mcap.stat().st_size / 2**20 if mcap.exists() else None
        if mcap.exists():
            result["recording"] = count_recording(mcap, n_anchors=n_anchors)
    return result


def count_recording(path: Path, *, n_anchors: int) -> dict:
    """Messages per kind in the recording and holes in each anchor's sequence numbers
    (an anchor numbers its states and range batches with one counter from 1: the recording
    is complete iff every anchor's numbers are exactly 1..max)."""
    from mcap.reader import make_reader

    counts: dict[str, int] = {}
    seqs: dict[str, list[int]] = {}
    dec = msgspec_seq()
    with open(path, "rb") as f:
        for _schema, channel, message in make_reader(f).iter_messages():
            pk = parse_key(channel.topic)
            kind = pk.kind if pk is not None else "other"
            counts[kind] = counts.get(kind, 0) + 1
            if kind in ("anchor_state", "range_batch"):
                seqs.setdefault(pk.anchor_id, []).append(dec(message.data).seq)
    holes = {}
    for aid, v in seqs.items():
        a = np.sort(np.asarray(v, np.int64))
        want = np.arange(1, a[-1] + 1)
        missing = np.setdiff1d(want, a).size
        dup = a.size - np.unique(a).size
        if missing or dup:
            holes[aid] = {"missing": int(missing), "duplicated": int(dup)}
    return {"messages_by_kind": counts, "anchors_recorded": len(seqs),
            "anchors_expected": n_anchors, "anchor_seq_holes": holes}


def msgspec_seq():
    """A decoder of just the ``seq`` field of any message."""
    import msgspec

    class _Seq(msgspec.Struct):
        seq: int

    d = msgspec.json.Decoder(_Seq)
    return d.decode


STARTUP_S = 5.0  # every node appears at once: its track initialisations are a burst of work


def _missing_summary(seen: np.ndarray, rate_hz: float = 10.0) -> dict:
    """Where estimates are missing: per epoch index (first/last few) and count, in the first
    :data:`STARTUP_S` seconds and after, the last epoch with one [s] (None: none missing)."""
    miss = (seen == 0).sum(axis=0)
    idx = np.flatnonzero(miss)
    k0 = round(STARTUP_S * rate_hz)
    return {"epochs_with_missing": int(idx.size), "first": [[int(k), int(miss[k])] for k in idx[:5]],
            "last": [[int(k), int(miss[k])] for k in idx[-5:]], "missing_startup":
            int(miss[:k0].sum()), "missing_after_startup": int(miss[k0:].sum()),
            "last_missing_s": float(idx[-1] / rate_hz) if idx.size else None}


def _per_node_summary(seen: np.ndarray, duration_s: float) -> dict:
    """How evenly the nodes were served: estimates per node per second (min / median / max
    over the nodes) and the gaps between a node's consecutive estimates [epochs] (median and
    max over all nodes' gaps; the longest gap of the worst node), over the run's epochs."""
    got = seen > 0
    rate = got.sum(axis=1) / max(duration_s, 1e-9)
    gaps = []
    for row in got:
        k = np.flatnonzero(row)
        if k.size > 1:
            gaps.append(np.diff(k))
    g = np.concatenate(gaps) if gaps else np.zeros(0, np.int64)
    return {"rate_hz_min_p50_max": [round(float(v), 2) for v in
                                    (rate.min(), np.median(rate), rate.max())] if rate.size
            else None,
            "gap_epochs_p50_p99_max": [int(np.percentile(g, 50)), int(np.percentile(g, 99)),
                                       int(g.max())] if g.size else None,
            "nodes_without_estimate": int((~got.any(axis=1)).sum())}


def _first_position_summary(first_fix: np.ndarray, n_epochs: int) -> dict:
    """How long the responders, all switched on at the run's start, waited for their first
    estimate with a position [s] (p50 / p90 / max over the nodes, from the run's first epoch)
    and how many never got one."""
    placed = first_fix < n_epochs
    t = first_fix[placed] * (PERIOD_NS * 1e-9)
    return {"p50_p90_max": [round(float(np.percentile(t, q)), 1) for q in (50, 90)]
            + [round(float(t.max()), 1)] if t.size else None,
            "never": int((~placed).sum())}


def _fusion_summary(diags: dict[int, M.FusionDiagnostics], ranges_sent: int) -> dict:
    """The fusion's counters (each shard's last diagnostics: every shard receives every
    range and state, so those are each shard's minimum; rejections, published and solved
    are summed) and each shard's own."""
    ds = [diags[k] for k in sorted(diags)]
    rejected: dict[str, int] = {}
    for d in ds:
        for k, v in d.rejected.items():
            rejected[k] = rejected.get(k, 0) + v
    out = {"ranges_received": min(d.received.get("range", 0) for d in ds),
           "ranges_sent": ranges_sent,
           "states_received": min(d.received.get("anchor_state", 0) for d in ds),
           "rejected": rejected, "late_ranges": sum(d.late_ranges for d in ds),
           "published": sum(d.published for d in ds), "solved": sum(d.solved for d in ds)}
    if len(ds) > 1:
        out["by_shard"] = [{"shard": f"{d.shard}/{d.shards}", "published": d.published,
                            "solved": d.solved, "rejected": d.rejected,
                            "ranges_received": d.received.get("range", 0)} for d in ds]
    return out


def _cpu_per_node_epoch(cpu: dict[str, list[tuple[float, float]]],
                        counts: dict[float, list[int]], fusions: list[str]) -> list:
    """Each fusion process's CPU per node-epoch [ms]: its CPU seconds over the estimates of
    its responders received here, after the first :data:`STARTUP_S` (from the first sample
    at or after it to the last) and over the whole run (from the run's start)."""
    out = []
    for k, name in enumerate(fusions):
        samples = [(t, c, counts[t][k]) for t, c in cpu.get(name, []) if t >= 0.0 and t in counts]
        row: dict = {"process": name}
        for label, lo in (("after_startup", STARTUP_S), ("run", 0.0)):
            run = [s for s in samples if s[0] >= lo]
            if len(run) >= 2 and run[-1][2] > run[0][2]:
                cpu_s_, n = run[-1][1] - run[0][1], run[-1][2] - run[0][2]
                row[label] = {"cpu_s": round(cpu_s_, 2), "node_epochs": int(n),
                              "ms_per_node_epoch": round(1e3 * cpu_s_ / n, 3),
                              "cores": round(cpu_s_ / (run[-1][0] - run[0][0]), 3)}
        out.append(row)
    return out


def _children(pid: int) -> list[int]:
    """Child process ids of ``pid`` (Linux /proc; empty if unknown)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return sorted(out)


def _cpu_cores(cpu: dict[str, list[tuple[float, float]]]) -> dict[str, float]:
    """Mean CPU use of every role over the run (cores: CPU seconds per wall second between
    the first sample at or after the run's start and the last one; the anchors summed)."""
    out: dict[str, float] = {}
    for name, samples in cpu.items():
        run = [s for s in samples if s[0] >= 0.0]
        if len(run) < 2 or run[-1][0] <= run[0][0]:
            continue
        role = ("anchors" if name.startswith("uav") else
                "fusion-workers" if name.startswith("fworker") else name)
        out[role] = out.get(role, 0.0) + (run[-1][1] - run[0][1]) / (run[-1][0] - run[0][0])
    return {k: round(v, 3) for k, v in out.items()}


def _recorder_summary(log_path: Path) -> dict:
    """The recorder's final JSON status line ("closed": received, written, gaps...)."""
    out: dict = {}
    if log_path.exists():
        for line in log_path.read_text(errors="replace").splitlines():
            if line.startswith("{"):
                with contextlib.suppress(ValueError):
                    ev = json.loads(line)
                    if ev.get("event") == "closed":
                        out = {k: ev.get(k) for k in ("received", "written", "gaps",
                                                      "out_of_order", "unknown_schema")}
    return out


def _stop_all(procs: dict[str, subprocess.Popen]) -> dict[str, int]:
    """SIGTERM anchors first, then fusion, recorder and router last; SIGKILL stragglers."""
    order = [n for n in procs if n.startswith("uav")] + [
        n for n in procs if n.startswith("fusion")] + [
        n for n in ("recorder", "router") if n in procs]
    return {name: stop_process_groups([procs[name]], timeout_s=30)[0] for name in order}


def format_report(r: dict) -> str:
    """Human-readable summary of :func:`run_soak`'s result."""
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    fu, lat, rec = r.get("fusion", {}), r["latency_fusion_ms"], r.get("recorder", {})
    lines = [
        f"load {r['anchors']} anchors x {r['nodes']} nodes x 10 Hz, {r['duration_s']:.0f} s "
        f"(range batches, recorder {'on' if r['recorder'] else 'off'}, fusion "
        f"{r.get('method', '?')}, {r.get('shards', 1)} fusion process(es))",
        f"ranges rx/sent {fu.get('ranges_received')}/{fu.get('ranges_sent')}, late "
        f"{fu.get('late_ranges')}, rejected {fu.get('rejected')}",
        f"estimates {r['estimates_received']}/{r['estimates_expected']} (missing "
        f"{r['estimates_missing']}, duplicated {r['estimates_duplicated']}), statuses "
        f"{r['statuses']}",
        f"fusion latency p50 {fmt(lat['p50'])} ms, p99 {fmt(lat['p99'])} ms, "
        f"max {fmt(lat['max'])} ms; after the first {STARTUP_S:.0f} s p50 "
        f"{fmt(r['latency_after_startup_ms']['p50'])} ms, p99 "
        f"{fmt(r['latency_after_startup_ms']['p99'])} ms",
    ]
    fp = r.get("first_position_s") or {}
    if fp:
        lines.append(f"time to each node's first position [s] p50/p90/max {fp['p50_p90_max']}, "
                     f"nodes never placed {fp['never']}")
    mb = r["missing_by_epoch"]
    lines.append(f"missing estimates: {mb['missing_startup']} in the first {STARTUP_S:.0f} s "
                 f"(every node starts at once), {mb['missing_after_startup']} after; the last "
                 f"epoch with one at t = {mb['last_missing_s']} s")
    pn = r.get("per_node") or {}
    if pn:
        lines.append(f"per node: estimates/s min/median/max {pn.get('rate_hz_min_p50_max')}, "
                     f"gap between a node's estimates [epochs] p50/p99/max "
                     f"{pn.get('gap_epochs_p50_p99_max')}, nodes without any "
                     f"{pn.get('nodes_without_estimate')}")
        lines.append(f"age of each node's picture (time average of now - input time of its "
                     f"newest estimate) [ms] mean/worst node "
                     f"{pn.get('age_of_information_ms_mean_worst')}")
    rej = fu.get("rejected") or {}
    lines.append(f"node-epochs not solved by an overloaded fusion: superseded "
                 f"{rej.get('superseded', 0)} (a newer epoch of the node was solved instead), "
                 f"overloaded {rej.get('overloaded', 0)} (more than max_backlog_s behind)")
    for m in r["latency_per_minute_ms"]:
        lines.append(f"  minute {m['minute']}: p50 {fmt(m['p50'])} p99 {fmt(m['p99'])} "
                     f"max {fmt(m['max'])} ms")
    if rec:
        lines.append(f"recorder received/written {rec.get('received')}/{rec.get('written')}, "
                     f"file {fmt(rec.get('file_mb'))} MB")
    if "recording" in r:
        rg = r["recording"]
        lines.append(f"recording: {rg['messages_by_kind']}, anchor sequence holes "
                     f"{rg['anchor_seq_holes'] or 'none'}")
    for row in r.get("cpu_per_node_epoch") or []:
        parts = [f"{label} {v['ms_per_node_epoch']:.3f} ms ({v['cpu_s']:.1f} CPU s / "
                 f"{v['node_epochs']:,} node-epochs, {v['cores']:.2f} cores)"
                 for label, v in row.items() if label != "process"]
        lines.append(f"CPU per node-epoch of {row['process']}: " + "; ".join(parts))
    if r.get("cpu_cores"):
        lines.append("CPU over the run [cores]: " + ", ".join(
            f"{k} {v:.2f}" for k, v in r["cpu_cores"].items())
            + f" (total {sum(r['cpu_cores'].values()):.2f} of {os.cpu_count()})")
    lines.append(f"{'process':>10} {'RSS start':>10} {'end':>8} {'max':>8} {'growth':>8} "
                 f"{'MB/min':>8}")
    for name, m in r["rss"].items():
        lines.append(f"{name:>10} {m['start_mb']:>10.1f} {m['end_mb']:>8.1f} {m['max_mb']:>8.1f}"
                     f" {m['growth_mb']:>8.1f} {fmt(m['slope_mb_per_min']):>8}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--load", default="16x200", metavar="MxN", help="anchors x nodes (16x200)")
    ap.add_argument("--duration", type=float, default=600.0, metavar="S",
                    help="run length [s] (default 600)")
    ap.add_argument("--warmup", type=float, default=30.0, metavar="S",
                    help="RSS 'start' sample after this long [s] (default 30)")
    ap.add_argument("--no-recorder", action="store_true", help="run without the recorder")
    ap.add_argument("--max-backlog-s", type=float, metavar="S",
                    help="the fusion's --max-backlog-s (default: the live fusion's; 0: a "
                    "fusion that falls behind never drops epochs, it only lags)")
    ap.add_argument("--method", default="dnls", choices=["dnls", "mnls", "lls", "ippa"],
                    help="the fusion's estimator (default dnls: the default mnls + tracker "
                    "does not keep up with 16 x 200 on 2 cores yet)")
    ap.add_argument("--kernel-threads", type=int, metavar="N",
                    help="the fusion's --kernel-threads (default: the fusion's, 1)")
    ap.add_argument("--workers", type=int, metavar="N",
                    help="the fusion's --workers (default: the fusion's, 1)")
    ap.add_argument("--shards", type=int, default=1, metavar="N",
                    help="fusion processes sharing the responders (diffpos fusion --shard "
                    "K/N; default 1)")
    ap.add_argument("--json", metavar="FILE", help="write the result as JSON")
    ap.add_argument("--log-dir", metavar="DIR", help="keep logs and the recording here")
    args = ap.parse_args(argv)
    m, n = (int(v) for v in args.load.lower().split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        log_dir = Path(args.log_dir or tmp)
        load_before = os.getloadavg()
        r = run_soak(m, n, args.duration, log_dir, recorder=not args.no_recorder,
                     warmup_s=args.warmup, rss_period_s=5.0, max_backlog_s=args.max_backlog_s,
                     method=args.method, kernel_threads=args.kernel_threads,
                     workers=args.workers, shards=args.shards)
        r["loadavg_before"] = load_before
        r["loadavg_after"] = os.getloadavg()
        r["cpus"] = os.cpu_count()
    print(format_report(r))
    print(f"load average before/after: {r['loadavg_before']} / {r['loadavg_after']} "
          f"on {r['cpus']} CPUs")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
