"""End-to-end latency of the distributed runtime: anchor publish -> estimate publish.

Starts a router, M anchor processes (``--channel ideal``: the D-NLS model's path with CRLB
noise, so the numbers measure the runtime and the solver, not the channel emulator) and the
fusion, on loopback, in real time at 10 Hz, for a generated scenario of M hovering UAVs and N
static nodes spread over the floors; subscribes to the estimates and diagnostics and prints:

- latency fusion: estimate ``t_pub_wall_ns`` - newest input range ``t_pub_wall_ns``
  (anchor publish -> estimate publish, the issue's definition), p50 / p99 / max;
- latency e2e: the same to the estimate's arrival at this subscriber;
- loss: estimates expected (N x epochs) vs received, ranges received by the fusion vs sent;
- fusion memory: RSS at 25 % of the run and at the end (bounded = no growth trend);
- CPU seconds per second of run of the router, the fusion and all anchors together (the
  machine's 2 cores are shared: compare these, not wall times), and the worst epochs.

    python benchmarks/bench_latency.py                      # both loads of the issue
    python benchmarks/bench_latency.py --load 4x10 --duration 20
    python benchmarks/bench_latency.py --load 16x200 --json out.json

Targets (issue): p50 < 5 ms, p99 < 20 ms at 4 x 10 x 10 Hz; no loss and bounded memory at
16 x 200 x 10 Hz. The machine's load matters: run it alone.
"""

from __future__ import annotations

import argparse
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
from diffpos_services.processes import free_tcp_port, stop_process_groups
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key


def cpu_by_role(procs: list[subprocess.Popen]) -> dict[str, float]:
    """CPU seconds so far of the router, the fusion and all anchors together."""
    out: dict[str, float] = {}
    for p in procs:
        role = p.args[p.args.index("diffpos_services.cli.main") + 1]
        out[role] = out.get(role, 0.0) + (cpu_s(p.pid) or 0.0)
    return out


def run_load(n_anchors: int, n_nodes: int, duration_s: float, log_dir: Path, *, batch: bool = False,
             profile: str | None = None) -> dict:
    site = f"bench{n_anchors}x{n_nodes}"
    keys = Keys(site)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    scen = log_dir / f"{site}.toml"
    scen.write_text(scenario_toml(n_anchors, n_nodes))
    procs: list[subprocess.Popen] = []

    def start(name: str, *argv: str) -> subprocess.Popen:
        prof = ["-m", "cProfile", "-o", profile] if profile and name == "fusion" else []
        with open(log_dir / f"{site}-{name}.log", "wb") as log:
            p = subprocess.Popen([sys.executable, *prof, "-m", "diffpos_services.cli.main", *argv],
                                 stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 start_new_session=True, env=dict(os.environ, DIFFPOS_LOG_FORMAT="text"))
        procs.append(p)
        return p

    q: queue.Queue = queue.Queue()
    alive: set[str] = set()
    cv = threading.Condition()

    def on_alive(s):
        import zenoh

        with cv:
            (alive.add if s.kind == zenoh.SampleKind.PUT else alive.discard)(str(s.key_expr))
            cv.notify_all()

    def on_data(s):
        q.put((str(s.key_expr), s.payload.to_bytes(), time.time_ns()))

    result: dict = {"anchors": n_anchors, "nodes": n_nodes, "rate_hz": 10, "duration_s": duration_s,
                    "range_batch": batch}
    try:
        start("router", "router", "--listen", endpoint)
        session = open_session(ZenohSettings(connect=(endpoint,)), threading.Event())
        with session:
            subs = [session.liveliness().declare_subscriber(keys.alive_all(), on_alive, history=True),
                    session.declare_subscriber(keys.estimates(), on_data),
                    session.declare_subscriber(keys.fusion_diagnostics(), on_data)]
            fusion = start("fusion", "fusion", "--site", site, "--connect", endpoint,
                           "--scenario", str(scen), "--diagnostics-period-s", "0.5")
            for j in range(n_anchors):
                start(f"uav{j + 1}", "anchor", "--id", f"uav{j + 1}", "--site", site,
                      "--connect", endpoint, "--scenario", str(scen), "--wait-start",
                      "--channel", "ideal", "--seed", str(j), "--clock-offset-ms", "0.5",
                      "--range-batch" if batch else "--no-range-batch")
            need = {keys.alive_anchor(f"uav{j + 1}") for j in range(n_anchors)} | {keys.alive_fusion()}
            deadline = time.monotonic() + 120
            with cv:
                while not need <= alive:
                    if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
                        raise RuntimeError(f"not ready: {sorted(need - alive)} (logs in {log_dir})")
                    cv.wait(0.2)
            cpu0 = cpu_by_role(procs)
            t0 = -(-(time.time_ns() + 500_000_000) // PERIOD_NS) * PERIOD_NS
            rc = M.RunControl(run_id=site, t0_ns=t0, wall_t0_ns=t0, speed=1.0,
                              duration_ns=round(duration_s * 1e9), seed=0)
            import zenoh

            session.put(keys.run_control(), M.encode(rc), congestion_control=zenoh.CongestionControl.BLOCK)
            end_ns = t0 + rc.duration_ns
            dec_e, dec_d = M.estimate_decoder(), M.decoder(M.FusionDiagnostics)  # estimate v1 and v2
            lat_pub, lat_rx, seen, lat_ep = [], [], set(), {}
            statuses: dict[str, int] = {}
            diag = None
            rss = []
            next_rss = time.monotonic()
            hard_end = time.monotonic() + duration_s + 30
            while time.monotonic() < hard_end:
                if time.monotonic() >= next_rss:
                    rss.append((time.time_ns(), rss_mb(fusion.pid)))
                    next_rss += 0.5
                try:
                    key, val, t_rx = q.get(timeout=0.2)
                except queue.Empty:
                    continue
                pk = parse_key(key)
                if pk.kind == "estimate":
                    e = dec_e(val)
                    seen.add((e.node_id, e.epoch))
                    statuses[e.status] = statuses.get(e.status, 0) + 1
                    if e.t_input_wall_ns > 0:
                        lat_pub.append((e.t_pub_wall_ns - e.t_input_wall_ns) * 1e-6)
                        lat_rx.append((t_rx - e.t_input_wall_ns) * 1e-6)
                        lat_ep[e.epoch] = max(lat_ep.get(e.epoch, 0.0), lat_pub[-1])
                else:
                    diag = dec_d(val)
                    if diag.watermark_ns is not None and diag.watermark_ns >= end_ns - PERIOD_NS \
                            and diag.pending_epochs == 0:
                        break
            cpu1 = cpu_by_role(procs)
            result["cpu_s_per_s"] = {k: round((cpu1[k] - cpu0.get(k, 0.0)) / duration_s, 3)
                                     for k in cpu1}
            for s in subs:
                s.undeclare()
    finally:
        for p in reversed(procs):  # anchors first, router last
            stop_process_groups([p], timeout_s=15)
    n_epochs = round(duration_s * 10)
    e0 = t0 // PERIOD_NS
    want = {(f"n{i + 1:03d}", e0 + k) for i in range(n_nodes) for k in range(n_epochs)}

    def pct(v, q):
        return float(np.percentile(v, q)) if v else None

    rs = [r for _, r in rss if r is not None]
    q1 = rs[len(rs) // 4] if rs else None
    result.update(
        estimates_expected=len(want), estimates_received=len(seen & want),
        missing=len(want - seen), statuses=statuses,
        latency_fusion_ms={"p50": pct(lat_pub, 50), "p99": pct(lat_pub, 99), "max": max(lat_pub, default=None)},
        latency_e2e_ms={"p50": pct(lat_rx, 50), "p99": pct(lat_rx, 99), "max": max(lat_rx, default=None)},
        worst_epochs_ms=sorted(((round(v, 1), int(k - e0)) for k, v in lat_ep.items()),
                               reverse=True)[:5],
        fusion_rss_mb={"at_25pct": q1, "end": rs[-1] if rs else None, "max": max(rs, default=None)},
    )
    if diag is not None:
        result["fusion"] = {"ranges_received": diag.received.get("range", 0),
                            "ranges_sent": n_anchors * n_nodes * n_epochs,
                            "rejected": diag.rejected, "late_ranges": diag.late_ranges}
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--load", action="append", metavar="MxN",
                    help="anchors x nodes (repeatable; default 4x10 and 16x200)")
    ap.add_argument("--duration", type=float, default=10.0, metavar="S", help="seconds per load")
    ap.add_argument("--json", metavar="FILE", help="write the results as JSON")
    ap.add_argument("--range-batch", choices=["auto", "on", "off"], default="auto",
                    help="anchors publish one RangeBatch per epoch (auto: when nodes > 50)")
    ap.add_argument("--log-dir", metavar="DIR", help="keep the services' logs here")
    ap.add_argument("--profile-fusion", metavar="FILE",
                    help="run the fusion under cProfile, stats to FILE (last load; slows it)")
    args = ap.parse_args(argv)
    loads = args.load or ["4x10", "16x200"]
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        log_dir = Path(args.log_dir or tmp)
        log_dir.mkdir(parents=True, exist_ok=True)
        for spec in loads:
            m, n = (int(v) for v in spec.lower().split("x"))
            batch = args.range_batch == "on" or (args.range_batch == "auto" and n > 50)
            r = run_load(m, n, args.duration, log_dir, batch=batch, profile=args.profile_fusion)
            out.append(r)
    hdr = f"{'load':>10} {'fixes':>12} {'fusion p50/p99 ms':>20} {'e2e p50/p99 ms':>18} {'ranges rx/sent':>16} {'RSS MB 25%/end':>16}"
    print(hdr)
    for r in out:
        lf, le, mem, fu = r["latency_fusion_ms"], r["latency_e2e_ms"], r["fusion_rss_mb"], r.get("fusion", {})
        fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
        print(f"{r['anchors']:>4}x{r['nodes']:<3}@10Hz{'b' if r['range_batch'] else ' '} {r['estimates_received']:>5}/{r['estimates_expected']:<6}"
              f" {fmt(lf['p50']):>9}/{fmt(lf['p99']):<9} {fmt(le['p50']):>8}/{fmt(le['p99']):<9}"
              f" {fu.get('ranges_received', '-'):>7}/{fu.get('ranges_sent', '-'):<8}"
              f" {fmt(mem['at_25pct']):>7}/{fmt(mem['end']):<7}")
        print(f"{'':>10} CPU s per s of run: " + ", ".join(
            f"{k} {v:.2f}" for k, v in r.get("cpu_s_per_s", {}).items())
            + f"; worst epochs [ms, epoch]: {r['worst_epochs_ms'][:3]}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
