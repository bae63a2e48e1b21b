"""Speed of the Rerun dashboard: live logging rate and offline MCAP -> .rrd conversion.

Run:  /work/venv/bin/python benchmarks/bench_dashboard.py [--minutes 10] [--anchors 8]
          [--nodes 50] [--rate 10] [--live-seconds 60] [--no-ranges] [--zenoh-seconds 0]

Targets (issue "Rerun dashboards"): keep up live with 8 anchors x 50 nodes at 10 Hz, and
convert a 10-minute recording in under 30 s.

- ``live``: the dashboard's per-batch work (decode nothing, just ``Dashboard.add`` of
  0.2 s batches, as the live service does) for ``--live-seconds`` of data, logging into an
  .rrd sink; reported as CPU seconds per second of data (must stay well below 1).
- ``zenoh`` (optional, ``--zenoh-seconds S``): a publisher replays S seconds of the run over
  Zenoh in real time into the live service (its own process is this one), reporting
  dropped messages and the lag from estimate publish to drawn.
- ``offline``: a synthetic recording (anchor states, node truth, estimates, fusion
  diagnostics and, unless ``--no-ranges``, every range message) is written to MCAP
  with the recorder's sink, then ``mcap_to_rrd`` converts it; the conversion is timed.

The machine is shared; numbers are noisy. The recording is generated, not timed.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import rerun as rr
import zenoh
from diffpos_services.bus.session import ZenohSettings, wait_matching
from diffpos_services.dashboard.blueprint import default_blueprint
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.common import APP_ID
from diffpos_services.dashboard.convert import mcap_to_rrd
from diffpos_services.dashboard.service import DashboardService, RerunTarget, open_rerun
from diffpos_services.dashboard.stream import Dashboard
from diffpos_services.processes import free_tcp_port
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.synthetic import display_run
from diffpos_services.wire import messages as m
from diffpos_services.wire.keys import Keys


def synthetic_run(**kw):
    """The dashboard's synthetic run (``replay.synthetic.display_run``), its building as
    the outline the dashboard draws."""
    building, msgs = display_run(**kw)
    return BuildingOutline.from_object(building), msgs


def _batches(msgs, period_ns):
    key = {
        "AnchorState": "anchor_states",
        "GroundTruth": "truth",
        "PositionEstimate": "estimates",
        "FusionDiagnostics": "diagnostics",
    }
    batch: dict[str, list] = {v: [] for v in key.values()}
    t_batch = None
    for x in msgs:
        t = getattr(x, "t_ns", None) or x.watermark_ns
        if t_batch is None:
            t_batch = t
        if t - t_batch >= period_ns:
            yield batch
            batch = {v: [] for v in key.values()}
            t_batch = t
        batch[key[type(x).__name__]].append(x)
    yield batch


def bench_live(args, tmp: Path) -> dict:
    building, msgs = synthetic_run(
        n_anchors=args.anchors,
        n_nodes=args.nodes,
        duration_s=args.live_seconds,
        rate_hz=args.rate,
        seed=1,
    )
    batches = list(_batches(msgs, int(args.batch_s * 1e9)))
    rec = rr.RecordingStream(APP_ID, recording_id="bench-live")
    rec.save(str(tmp / "live.rrd"), default_blueprint=default_blueprint())
    dash = Dashboard(rec, building=building)
    worst = 0.0
    c0 = time.process_time()
    w0 = time.perf_counter()
    for b in batches:
        t = time.perf_counter()
        dash.add(**b)
        worst = max(worst, time.perf_counter() - t)
    rec.flush()
    wall = time.perf_counter() - w0
    cpu = time.process_time() - c0
    rec.disconnect()
    return {
        "messages": len(msgs),
        "data_s": args.live_seconds,
        "wall_s": wall,
        "cpu_s": cpu,
        "cpu_per_data_s": cpu / args.live_seconds,
        "worst_batch_ms": worst * 1e3,
        "batches": len(batches),
    }


def _wait_matched(pubs, *, timeout_s: float) -> None:
    """Block until every Zenoh publisher in ``pubs`` has a matching subscriber (no sleeps)."""
    for pub in pubs:
        if not wait_matching(pub, timeout_s=timeout_s):
            raise RuntimeError(f"no subscriber matched {pub.key_expr} within {timeout_s} s")


def bench_zenoh(args, tmp: Path) -> dict:
    building, msgs = synthetic_run(
        n_anchors=args.anchors,
        n_nodes=args.nodes,
        duration_s=args.zenoh_seconds,
        rate_hz=args.rate,
        seed=2,
    )
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    pub_s = zenoh.open(ZenohSettings(mode="peer", connect=(), listen=(ep,)).to_config())
    sub_s = zenoh.open(ZenohSettings(mode="peer", connect=(ep,)).to_config())
    rec, _ = open_rerun(RerunTarget(mode="save", path=str(tmp / "zenoh.rrd")))
    svc = DashboardService(sub_s, rec, site="bench", building=building)
    stop = threading.Event()
    th = threading.Thread(target=svc.run, args=(stop,), kwargs={"report_every_s": 1e9})
    th.start()
    keys = [Keys("bench").of(x) for x in msgs]
    # BLOCK: the benchmark counts what arrives; Zenoh's default (DROP) loses under load
    block = zenoh.CongestionControl.BLOCK
    pubs = {k: pub_s.declare_publisher(k, congestion_control=block) for k in set(keys)}
    _wait_matched(pubs.values(), timeout_s=30.0)  # run() has declared its subscribers

    t_of = [getattr(x, "t_ns", None) or x.watermark_ns for x in msgs]
    t0_data, t0_wall = t_of[0], time.perf_counter()
    lags = []
    for k, x, t in zip(keys, msgs, t_of, strict=True):
        due = (t - t0_data) / 1e9
        now = time.perf_counter() - t0_wall
        if due > now:
            time.sleep(due - now)
            lags.append(svc.stats.lag_ms)
        if isinstance(x, m.PositionEstimate):  # publish stamp = now, for the lag
            x = msgspec.structs.replace(x, t_pub_wall_ns=time.time_ns())
        pubs[k].put(m.encode(x))
    if not svc.wait_received(len(msgs), timeout_s=60.0):  # all arrived; then stop (close draws)
        print(f"warning: only {svc.stats.received} of {len(msgs)} messages arrived in 60 s",
              file=sys.stderr)
    stop.set()
    th.join()
    rec.disconnect()
    sub_s.close()
    pub_s.close()
    st = svc.stats
    return {
        "messages": len(msgs),
        "received": st.received,
        "drawn": st.drawn,
        "dropped": st.dropped,
        "log_cpu_s": st.log_time_s,
        "lag_ms_median": float(np.median(lags)) if lags else float("nan"),
        "lag_ms_max": float(np.max(lags)) if lags else float("nan"),
    }


def write_recording(args, path: Path) -> int:
    """The synthetic run (plus every range message unless --no-ranges) as an MCAP file."""
    t = time.perf_counter()
    _, msgs = synthetic_run(
        n_anchors=args.anchors,
        n_nodes=args.nodes,
        duration_s=args.minutes * 60.0,
        rate_hz=args.rate,
        seed=3,
    )
    print(f"  generated {len(msgs)} messages in {time.perf_counter() - t:.1f} s", flush=True)
    n = 0
    anchors = [f"uav{i + 1}" for i in range(args.anchors)]
    nodes = [f"n{i:02d}" for i in range(args.nodes)]
    keys = Keys("demo")
    range_keys = [[keys.anchor_range(a, nn) for nn in nodes] for a in anchors]
    rng = np.random.default_rng(0)
    with McapSink(path) as sink:
        for x in msgs:
            t_ns = getattr(x, "t_ns", None) or x.watermark_ns
            sink.write(Keys("demo").of(x), m.encode(x), t_ns + 2_000_000)
            n += 1
            if not args.no_ranges and isinstance(x, m.AnchorState):
                j = anchors.index(x.anchor_id)
                r = rng.uniform(5, 60, len(nodes))
                for k in range(len(nodes)):
                    payload = (
                        b'{"schema":"diffpos.range.v1","anchor_id":"%s","node_id":"%s","t_ns":%d,'
                        b'"seq":%d,"range_m":%.4f,"sigma_m":0.1,"snr_db":20.0,"t_pub_wall_ns":%d}'
                        % (
                            x.anchor_id.encode(),
                            nodes[k].encode(),
                            x.t_ns,
                            x.seq,
                            r[k],
                            x.t_pub_wall_ns,
                        )
                    )
                    sink.write(range_keys[j][k], payload, x.t_ns + 1_000_000)
                    n += 1
    return n


def bench_offline(args, tmp: Path) -> dict:
    mcap = tmp / "bench.mcap"
    t = time.perf_counter()
    n = write_recording(args, mcap)
    print(
        f"  wrote {n} messages ({mcap.stat().st_size / 1e6:.0f} MB) in {time.perf_counter() - t:.1f} s",
        flush=True,
    )
    out = tmp / "bench.rrd"
    t = time.perf_counter()
    counts = mcap_to_rrd(mcap, out)
    dt = time.perf_counter() - t
    return {
        "mcap_messages": n,
        "mcap_MB": mcap.stat().st_size / 1e6,
        "estimates": counts["estimate"],
        "convert_s": dt,
        "rrd_MB": out.stat().st_size / 1e6,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="offline recording length")
    ap.add_argument("--anchors", type=int, default=8)
    ap.add_argument("--nodes", type=int, default=50)
    ap.add_argument("--rate", type=float, default=10.0, help="fix rate [Hz]")
    ap.add_argument("--live-seconds", type=float, default=60.0)
    ap.add_argument("--batch-s", type=float, default=0.5, help="live drain period [s]")
    ap.add_argument("--zenoh-seconds", type=float, default=0.0, help="0 = skip the Zenoh run")
    ap.add_argument("--no-ranges", action="store_true", help="recording without range messages")
    ap.add_argument("--skip-offline", action="store_true")
    args = ap.parse_args()
    print(f"dashboard benchmark: {args.anchors} anchors x {args.nodes} nodes at {args.rate:g} Hz")
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        live = bench_live(args, tmp)
        print(
            f"live   : {live['data_s']:.0f} s of data ({live['messages']} msgs, {live['batches']} batches of {args.batch_s:g} s): "
            f"CPU {live['cpu_s']:.2f} s = {live['cpu_per_data_s']:.3f} s per data second, "
            f"worst batch {live['worst_batch_ms']:.0f} ms",
            flush=True,
        )
        if args.zenoh_seconds > 0:
            z = bench_zenoh(args, tmp)
            print(
                f"zenoh  : {z['messages']} msgs in real time: received {z['received']}, drawn {z['drawn']}, "
                f"dropped {z['dropped']}, logging CPU {z['log_cpu_s']:.2f} s, estimate publish -> drawn "
                f"median {z['lag_ms_median']:.0f} ms, max {z['lag_ms_max']:.0f} ms",
                flush=True,
            )
        if not args.skip_offline:
            off = bench_offline(args, tmp)
            print(
                f"offline: {args.minutes:g} min recording, {off['mcap_messages']} msgs "
                f"({off['mcap_MB']:.0f} MB MCAP, {off['estimates']} estimates) -> "
                f"{off['rrd_MB']:.0f} MB .rrd in {off['convert_s']:.1f} s (target < 30 s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
