"""Recorder write rate and replay speed; prints a table.

Workload of the issue: 8 anchors x 50 nodes, 10 Hz ranging (4,000 ranges/s + 80 states/s +
500 truth/s), ~200-byte JSON messages, zstd chunks.

Rows
----
1. ``sink``: McapSink alone (what the recorder's drain thread does per message: read t_ns/seq
   from the JSON, add to the chunk, zstd), 200-byte range messages, flush every 200 ms.
2. ``bus``: the real recorder process behind a Python Zenoh router, one publisher process
   publishing as fast as it can with congestion control BLOCK; rate = messages / (time from
   the first publish to the recorder's flush status saying all of them are on disk), and
   the recorder's own received/written/gap counters (loss check).
3. ``scan``: reading a 10-minute recording of the workload back (McapScanner, messages/s).
4. ``floor``: what a replay costs before any fusion work: read every message of an S-second
   recording of the workload (with the live fusion's estimates, 500/s), track its sequence
   number and decode it with its schema. Two recordings: anchors publishing one message per
   range (the default) and one RangeBatch per epoch (``diffpos anchor --range-batch``).
5. ``replay``: ``diffpos replay`` on those recordings (fusion incl. D-NLS solves, report), as
   x real time, at each ``--step-ms``: 5 ms steps like the live service (reproduces its
   estimates) and 1000 ms (the epochs of each second solved as one batch: warm starts and
   motion compensation from up to 1 s old tracks, so fixes differ slightly from live: the
   agreement line says how much). Work is per epoch, so the rate holds for longer
   recordings (``--replay-seconds 600`` measures the issue's 10 minutes).

6. ``soak`` (``--soak-minutes M``, alone): the recorder's memory over a long run. M minutes
   of the workload (8 anchor states + 400 ranges + 50 truth per 100 ms, real payloads with
   running sequence numbers) go as fast as possible through the recorder's code path: the
   real :class:`McapSink` with the recorder's default split policy (``--no-split``: one
   file), ``write(key, payload, receive_ns)`` per message as the drain thread does and a
   ``flush()`` every 200 ms of simulated time as the flush thread does. RSS (VmRSS) is
   sampled at 0, 30, 60, 120 simulated minutes (and every ``--soak-every`` minutes);
   finished parts are deleted as they close (disk only, no effect on memory). docs/soak.md
   has the table.
7. ``live`` (``--live-minutes M``, alone): the recorder *process* over a long live run: a
   Python Zenoh router, the real recorder (``diffpos record``'s command line, its default
   split policy) and one publisher process publishing row 6's workload paced at real time
   (one 100-ms epoch per 100 ms, congestion control BLOCK). Every ``--soak-every`` minutes
   the recorder's VmRSS / VmHWM (from /proc) and its own counters are sampled; each part is
   read back with :class:`McapScanner` once the recorder has closed it (its messages
   counted: every part indexed and readable) and then deleted (disk only). At the end the
   messages in all parts must equal those published: ``lost`` is the difference.

Usage::

    python benchmarks/bench_recorder.py                     # all rows (several minutes)
    python benchmarks/bench_recorder.py --skip-bus --skip-scan --replay-seconds 30
    python benchmarks/bench_recorder.py --soak-minutes 120              # 2 h, split parts
    python benchmarks/bench_recorder.py --soak-minutes 30 --no-split    # one growing file
    python benchmarks/bench_recorder.py --live-minutes 120              # the process, 2 h
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from diffpos_services.cli.recorder import DEFAULT_SPLIT_MB, DEFAULT_SPLIT_S
from diffpos_services.fusion.core import FusionCore
from diffpos_services.processes import free_tcp_port
from diffpos_services.recorder import build_command
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.topics import SeqTracker, parse_topic
from diffpos_services.recording.writer import McapSink, SplitPolicy, part_path
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from diffpos_services.wire import messages as M

from diffpos.estimators.dnls import solver as est

# The publisher children (``python -c``) run with this folder as their working directory, so
# they import this module's payload helpers as a script run here would (no sys.path edit).
BENCH_DIR = Path(__file__).resolve().parent


def _payload_200(i: int) -> bytes:
    msg = M.RangeMeasurement(anchor_id="uav3", node_id=f"n{i % 50:02d}", t_ns=1_700_000_000_000_000_000 + i,
                             seq=i, range_m=27.123456789 + (i % 97) * 1e-3, sigma_m=0.0123456,
                             snr_db=18.25, t_pub_wall_ns=1_700_000_000_000_000_000 + i)
    return M.encode(msg)


def bench_sink(n: int, tmp: Path) -> dict:
    payloads = [_payload_200(i) for i in range(1000)]
    size = sum(map(len, payloads)) / len(payloads)
    keys = [f"diffpos/b/anchor/uav3/range/n{i:02d}" for i in range(50)]
    path = tmp / "sink.mcap"
    sink = McapSink(path)
    t0 = time.perf_counter()
    next_flush = t0 + 0.2
    now_ns = time.time_ns
    for i in range(n):
        sink.write(keys[i % 50], payloads[i % 1000], now_ns())
        if i % 1000 == 0 and time.perf_counter() >= next_flush:
            sink.flush()
            next_flush += 0.2
    sink.close()
    dt = time.perf_counter() - t0
    return {"row": "sink", "messages": n, "bytes_per_msg": round(size), "seconds": dt,
            "rate_msg_s": n / dt, "file_mb": path.stat().st_size / 1e6,
            "written": sink.stats.written}


_PUBLISHER = r"""
import sys, time, zenoh
from diffpos_services.bus.session import ZenohSettings, wait_matching
from bench_recorder import _payload_200
ep, n = sys.argv[1], int(sys.argv[2])
payloads = [_payload_200(i) for i in range(n)]
with zenoh.open(ZenohSettings(connect=(ep,)).to_config()) as s:
    pubs = [s.declare_publisher(f"diffpos/b/anchor/uav3/range/n{{i:02d}}",
                                congestion_control=zenoh.CongestionControl.BLOCK)
            for i in range(50)]
    for p in pubs:
        if not wait_matching(p, timeout_s=120.0):
            sys.exit(f"no recorder subscriber matched {{p.key_expr}} within 120 s")
    print("start", time.time_ns(), flush=True)
    for i in range(n):
        pubs[i % 50].put(payloads[i])
    print("sent", time.time_ns(), flush=True)
    sys.stdin.readline()   # keep the session open until the recorder has everything
"""


@contextlib.contextmanager
def _recorder_behind_router(site: str, out: Path, split_s: float | None = None):
    """A Python Zenoh router and the real recorder process writing ``out`` (its status lines
    on a queue, ``ready`` already seen), each in a process group of its own, killed on exit.
    Yields ``(endpoint, recorder Popen, status queue, start)``; ``start(argv, **popen)``
    starts another process that is killed with them."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = dict(os.environ, DIFFPOS_LOG_LEVEL="warning")
    procs = []

    def start(argv, **kw):
        p = subprocess.Popen(argv, start_new_session=True, env=env, text=True, **kw)
        procs.append(p)
        return p

    try:
        start([sys.executable, "-m", "diffpos_services.cli.main", "router", "--listen", ep],
              stderr=subprocess.DEVNULL)
        rec = start(build_command(site=site, out=out, connect=[ep], flush_interval_s=0.2,
                                  split_duration_s=split_s),
                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: [lines.put(json.loads(x)) for x in rec.stdout],
                         daemon=True).start()
        while lines.get(timeout=60)["event"] != "ready":
            pass
        yield ep, rec, lines, start
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def bench_bus(n: int, tmp: Path) -> dict:
    with _recorder_behind_router("b", tmp / "bus.mcap") as (ep, rec, lines, start):
        code = _PUBLISHER.format()
        pub = start([sys.executable, "-c", code, ep, str(n)], stdout=subprocess.PIPE,
                    stdin=subprocess.PIPE, cwd=BENCH_DIR)
        first = pub.stdout.readline()
        if not first.startswith("start"):  # it exited (no match within its bound): say so
            raise RuntimeError(f"publisher failed (exit {pub.wait(timeout=60)}); see above")
        t_start = int(first.split()[1])
        t_sent = int(pub.stdout.readline().split()[1])
        while True:
            ev = lines.get(timeout=120)
            if ev["event"] == "flush" and ev["flushed_written"] >= n:
                t_done = ev["t_wall_ns"]
                break
        pub.stdin.write("\n")
        pub.stdin.flush()
        pub.wait(timeout=60)
        rec.send_signal(signal.SIGTERM)
        while True:
            ev = lines.get(timeout=60)
            if ev["event"] == "closed":
                break
        rec.wait(timeout=60)
    dt = (t_done - t_start) / 1e9
    return {"row": "bus", "messages": n, "seconds": dt, "rate_msg_s": n / dt,
            "publish_rate_msg_s": n / ((t_sent - t_start) / 1e9), "received": ev["received"],
            "written": ev["written"], "gaps": ev["gaps"], "lost": n - ev["written"]}


def bench_scan(minutes: float, tmp: Path) -> dict:
    path = tmp / "ten_minutes.mcap"
    t0 = time.perf_counter()
    counts = write_synthetic_recording(path, n_anchors=8, n_nodes=50, duration_s=60 * minutes,
                                       live=False, flush_every=0)
    t_gen = time.perf_counter() - t0
    t0 = time.perf_counter()
    n = 0
    sc = McapScanner(path)
    for batch in sc.iter_batches():
        n += len(batch)
    dt = time.perf_counter() - t0
    return {"row": "scan", "minutes": minutes, "messages": n, "seconds": dt, "rate_msg_s": n / dt,
            "x_real_time": 60 * minutes / dt, "file_mb": path.stat().st_size / 1e6,
            "generate_s": t_gen, "counts": counts}


def _recording(seconds: float, tmp: Path, *, range_batch: bool) -> Path:
    path = tmp / f"replay_{seconds:g}s_{'batch' if range_batch else 'single'}.mcap"
    if not path.exists():  # with the live fusion's estimates (what --compare checks against)
        write_synthetic_recording(path, n_anchors=8, n_nodes=50, duration_s=seconds,
                                  range_batch=range_batch)
    return path


def bench_read_floor(seconds: float, tmp: Path, *, range_batch: bool) -> dict:
    """What replay costs before any fusion work: read every message, track its sequence
    number, decode it with its schema (no fusion, no report)."""
    path = _recording(seconds, tmp, range_batch=range_batch)
    decoders = {"estimate": M.estimate_decoder(),  # v1 and v2
                "truth_node": M.decoder(M.GroundTruth),
                "range_batch": M.decoder(M.RangeBatch), "range": M.decoder(M.RangeMeasurement),
                "anchor_state": M.decoder(M.AnchorState)}
    best, n = float("inf"), 0
    for _ in range(2):
        t0 = time.perf_counter()
        kind_of: dict[int, str] = {}
        seq = SeqTracker()
        n = 0
        for batch in McapScanner(path).iter_batches():
            for m in batch:
                kind = kind_of.get(m.channel_id)
                if kind is None:
                    kind = kind_of[m.channel_id] = parse_topic(m.topic)[0]
                seq.add(m.topic, m.sequence)
                dec = decoders.get(kind)
                if dec is not None:
                    dec(m.data)
                n += 1
        best = min(best, time.perf_counter() - t0)
    return {"row": "floor", "recording_s": seconds, "range_batch": range_batch, "messages": n,
            "seconds": best, "x_real_time": seconds / best, "rate_msg_s": n / best}


def bench_replay(seconds: float, tmp: Path, *, range_batch: bool, step_ms: float) -> dict:
    """Replay speed (best of two runs after a warm-up), agreement with the recorded live
    fusion, and where the time goes: ``solver_s`` (inside D-NLS, the estimator in
    diffpos.estimators) and ``ingest_s`` (FusionCore.on_sample: checks, decoding, alignment);
    the rest is the fusion's batch assembly and estimate building, reading the file and the
    report."""
    path = _recording(seconds, tmp, range_batch=range_batch)
    replay(path, step_ms=step_ms)  # imports and first-call costs are not part of the rate
    dt = float("inf")
    for _ in range(2):
        t0 = time.perf_counter()
        r = replay(path, step_ms=step_ms)
        dt = min(dt, time.perf_counter() - t0)
    # third run, instrumented (the wrappers cost a little, so it is not the rate)
    spent = {"solver": 0.0, "ingest": 0.0}
    dnls, on_sample = est.dnls, FusionCore.on_sample

    def timed(fn, what):
        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[what] += time.perf_counter() - t
        return wrapper

    est.dnls, FusionCore.on_sample = timed(dnls, "solver"), timed(on_sample, "ingest")
    try:
        t1 = time.perf_counter()
        replay(path, step_ms=step_ms)
        dt_i = time.perf_counter() - t1
    finally:
        est.dnls, FusionCore.on_sample = dnls, on_sample
    c = r.report["compare"]
    return {"row": "replay", "recording_s": seconds, "range_batch": range_batch,
            "step_ms": step_ms, "seconds": dt, "x_real_time": seconds / dt,
            "fixes": len(r.estimates), "fixes_per_s": len(r.estimates) / dt,
            "p50_3d_m": r.report["accuracy"]["overall"]["error_3d_m"]["p50"],
            "status_agree": c["status_agree"],
            "identical": c["identical_positions"] / max(c["with_positions"], 1),
            "max_diff_m": c["position_diff_m"]["max"],
            "solver_s": spent["solver"], "ingest_s": spent["ingest"], "instrumented_s": dt_i,
            "solver_share": spent["solver"] / dt_i, "ingest_share": spent["ingest"] / dt_i}


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _soak_epoch(e: int, t: int, seqs: dict[str, int]) -> list[tuple[str, bytes]]:
    """One 100-ms epoch of the workload: 8 anchor states, 8 x 50 ranges, 50 truth."""
    out = []
    for a in range(8):
        aid = f"uav{a}"
        seqs[aid] += 1
        out.append((f"diffpos/soak/anchor/{aid}/state", M.encode(M.AnchorState(
            anchor_id=aid, t_ns=t, seq=seqs[aid], position_m=(a * 3.0, -15.0, 10.0),
            velocity_m_s=(0.1, 0.0, 0.0), position_sigma_m=(0.1, 0.1, 0.2),
            velocity_sigma_m_s=0.05, range_rate_hz=10.0, t_pub_wall_ns=t))))
        for n in range(50):
            seqs[aid] += 1
            out.append((f"diffpos/soak/anchor/{aid}/range/n{n:02d}", M.encode(M.RangeMeasurement(
                anchor_id=aid, node_id=f"n{n:02d}", t_ns=t, seq=seqs[aid],
                range_m=20.0 + ((e * 7 + n * 13 + a) % 1000) * 1e-2, sigma_m=0.2, snr_db=15.0,
                t_pub_wall_ns=t))))
    for n in range(50):
        out.append((f"diffpos/soak/truth/node/n{n:02d}", M.encode(M.GroundTruth(
            entity="node", id=f"n{n:02d}", t_ns=t, position_m=(n * 0.5, 5.0, 4.0),
            velocity_m_s=(0.0, 0.0, 0.0), floor_index=1))))
    return out


def bench_soak(minutes: float, tmp: Path, *, split: bool, every_min: float) -> dict:
    """RSS of the recorder's sink over ``minutes`` of simulated workload (see row 6)."""
    policy = SplitPolicy(max_bytes=round(DEFAULT_SPLIT_MB * 1e6),
                         max_duration_s=DEFAULT_SPLIT_S) if split else None
    sink = McapSink(tmp / "soak.mcap", split=policy)
    sink.add_metadata("run", {"site": "soak", "scenario": "bench"})
    seqs = {f"uav{a}": 0 for a in range(8)}
    t0_ns = 1_700_000_000_000_000_000
    epochs = round(minutes * 600)
    marks = sorted({0.0, 30.0, 60.0, 120.0, minutes} | {
        k * every_min for k in range(1, int(minutes / every_min) + 1)})
    marks = [m for m in marks if m <= minutes]
    samples = []
    deleted = 0
    wall0 = time.perf_counter()
    for e in range(epochs + 1):
        sim_min = e / 600
        if marks and sim_min >= marks[0]:
            marks.pop(0)
            samples.append({"sim_min": round(sim_min, 2), "rss_mb": round(_rss_mb(), 1),
                            "messages": sink.stats.written, "parts": len(sink.parts),
                            "wall_s": round(time.perf_counter() - wall0, 1)})
            print(json.dumps(samples[-1]), file=sys.stderr, flush=True)
        if e == epochs:
            break
        t = t0_ns + e * 100_000_000
        for key, payload in _soak_epoch(e, t, seqs):
            sink.write(key, payload, t + 2_000_000)
        if e % 2 == 1:
            sink.flush()  # the recorder's flush thread: every 200 ms
            for old in sink.parts[deleted:-1]:  # finished parts: disk only
                old.unlink()
                deleted += 1
    sink.close()
    return {"row": "soak", "minutes": minutes, "split": split, "samples": samples,
            "messages": sink.stats.written, "parts": len(sink.parts),
            "wall_s": time.perf_counter() - wall0,
            "policy": None if policy is None else
            {"max_bytes": policy.max_bytes, "max_duration_s": policy.max_duration_s}}


_LIVE_PUBLISHER = r"""
import sys, time, zenoh
from diffpos_services.bus.session import ZenohSettings, wait_matching
from bench_recorder import _soak_epoch
ep, epochs = sys.argv[1], int(sys.argv[2])
seqs = {{f"uav{{a}}": 0 for a in range(8)}}
with zenoh.open(ZenohSettings(connect=(ep,)).to_config()) as s:
    pubs = {{key: s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
             for key, _ in _soak_epoch(0, 0, dict(seqs))}}
    for p in pubs.values():
        if not wait_matching(p, timeout_s=120.0):
            sys.exit(f"no recorder subscriber matched {{p.key_expr}} within 120 s")
    t0, wall0, n, late = time.monotonic_ns(), time.time_ns(), 0, 0
    print("start", wall0, flush=True)
    for e in range(epochs):
        wait_ns = t0 + e * 100_000_000 - time.monotonic_ns()
        if wait_ns > 0:
            time.sleep(wait_ns / 1e9)   # pacing at real time
        elif wait_ns < -100_000_000:
            late += 1                   # more than one epoch behind the schedule
        for key, payload in _soak_epoch(e, wall0 + e * 100_000_000, seqs):
            pubs[key].put(payload)
            n += 1
    print("sent", time.time_ns(), n, late, flush=True)
    sys.stdin.readline()   # keep the session open until the recorder has everything
"""


def _proc_mem_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of process ``pid`` [MB]."""
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line[:5]] = int(line.split()[1]) / 1024
    return out.get("VmRSS", float("nan")), out.get("VmHWM", float("nan"))


_LIVE_TOPICS = ("diffpos/soak/anchor/", "diffpos/soak/truth/")


def _read_parts(out: Path, done: int, upto: int) -> int:
    """Published messages (anchor and truth topics; not the liveliness the recorder also
    keeps) in parts ``done`` .. ``upto - 1`` of the recording ``out``, each read back whole
    with the scanner (indexed and readable) and deleted after reading."""
    n = 0
    for k in range(done, upto):
        path = part_path(out, k)
        for batch in McapScanner(path).iter_batches():
            n += sum(m.topic.startswith(_LIVE_TOPICS) for m in batch)
        path.unlink()
    return n


def bench_live(minutes: float, tmp: Path, *, every_min: float,
               split_s: float | None = None) -> dict:
    """The recorder process's memory over ``minutes`` of live workload (see row 7)."""
    samples, last = [], {}
    out = tmp / "live.mcap"
    with _recorder_behind_router("soak", out, split_s) as (ep, rec, lines, start):
        code = _LIVE_PUBLISHER.format()
        pub = start([sys.executable, "-c", code, ep, str(round(minutes * 600))],
                    stdout=subprocess.PIPE, stdin=subprocess.PIPE, cwd=BENCH_DIR)
        first = pub.stdout.readline()
        if not first.startswith("start"):
            raise RuntimeError(f"publisher failed (exit {pub.wait(timeout=60)}); see above")
        sent: queue.Queue = queue.Queue()
        threading.Thread(target=lambda: sent.put(pub.stdout.readline()), daemon=True).start()
        wall0, read, done = time.monotonic(), 0, 0
        while True:
            try:
                line = sent.get(timeout=max(0.0, wall0 + 60 * every_min * (len(samples) + 1)
                                            - time.monotonic()))
            except queue.Empty:
                line = None
            while not lines.empty():
                last = lines.get()
            parts_now = len(list(tmp.glob("live*.mcap")))
            closed = done + max(parts_now - 1, 0)  # every part but the newest is closed
            read += _read_parts(out, done, closed)
            done = closed
            rss, hwm = _proc_mem_mb(rec.pid)
            samples.append({"wall_min": round((time.monotonic() - wall0) / 60, 2),
                            "rss_mb": round(rss, 1), "hwm_mb": round(hwm, 1),
                            "written": last.get("flushed_written", 0),
                            "parts": closed + 1, "gaps": last.get("gaps", 0)})
            print(json.dumps(samples[-1]), file=sys.stderr, flush=True)
            if line is not None:
                break
        if not line.startswith("sent"):  # EOF: the publisher died before it finished
            raise RuntimeError(f"the publisher exited ({pub.wait(timeout=60)}) before it had "
                               f"published every epoch; see its error above")
        _, _t_sent, n_sent, late = line.split()
        pub.stdin.write("\n")
        pub.stdin.flush()
        pub.wait(timeout=60)
        rec.send_signal(signal.SIGTERM)
        while (ev := lines.get(timeout=120))["event"] != "closed":
            pass
        rec.wait(timeout=120)
        left = len(list(tmp.glob("live*.mcap")))
        read += _read_parts(out, done, done + left)
        done += left
    return {"row": "live", "minutes": minutes, "samples": samples, "sent": int(n_sent),
            "late_epochs": int(late), "received": ev["received"], "written": ev["written"],
            "gaps": ev["gaps"], "read_back": read, "lost": int(n_sent) - read,
            "parts": done}


def _alone(run, as_json: bool, show) -> int:
    """A row run alone in a temporary directory: its result as JSON or ``show(result)``."""
    with tempfile.TemporaryDirectory() as d:
        r = run(Path(d))
    if as_json:
        print(json.dumps(r))
        return 0
    return show(r)


def _print_live(r: dict) -> int:
    print(f"live: the recorder process, {r['minutes']:g} min of 8 x 50 x 10 Hz at real time"
          f" ({r['late_epochs']} epochs published > 100 ms late); sent {r['sent']:,}, "
          f"recorder received {r['received']:,} / wrote {r['written']:,}, gaps "
          f"{r['gaps']}, read back from {r['parts']} parts {r['read_back']:,}: lost "
          f"{r['lost']}")
    print(f"{'wall min':>9}{'written':>14}{'parts':>7}{'RSS MB':>9}{'HWM MB':>9}")
    for smp in r["samples"]:
        print(f"{smp['wall_min']:>9g}{smp['written']:>14,}{smp['parts']:>7}"
              f"{smp['rss_mb']:>9.1f}{smp['hwm_mb']:>9.1f}")
    return 0 if r["lost"] == 0 else 1


def _print_soak(r: dict) -> int:
    print(f"soak: {r['minutes']:g} simulated minutes, {r['messages']:,} messages, "
          f"{'split ' + json.dumps(r['policy']) if r['split'] else 'one file'}, "
          f"{r['parts']} parts, {r['wall_s']:.0f} s wall")
    print(f"{'simulated min':>14}{'messages':>14}{'parts':>7}{'RSS MB':>9}")
    for smp in r["samples"]:
        print(f"{smp['sim_min']:>14g}{smp['messages']:>14,}{smp['parts']:>7}"
              f"{smp['rss_mb']:>9.1f}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--messages", type=int, default=200_000, help="messages for sink/bus rows")
    ap.add_argument("--scan-minutes", type=float, default=10.0)
    ap.add_argument("--replay-seconds", type=float, default=30.0)
    ap.add_argument("--skip-bus", action="store_true")
    ap.add_argument("--skip-scan", action="store_true")
    ap.add_argument("--skip-replay", action="store_true")
    ap.add_argument("--step-ms", type=float, nargs="+", default=[5.0, 1000.0],
                    help="replay step granularities to measure (5 ms: as the live service, "
                         "reproduces its estimates; 1000 ms: epochs solved in 1-s batches)")
    ap.add_argument("--json", action="store_true", help="print rows as JSON lines")
    ap.add_argument("--soak-minutes", type=float, metavar="M",
                    help="only the soak row: M simulated minutes through the recorder's sink")
    ap.add_argument("--soak-every", type=float, default=10.0, metavar="M",
                    help="soak: also sample RSS every M simulated minutes; live: every M wall-clock "
                         "minutes (default 10)")
    ap.add_argument("--no-split", action="store_true", help="soak: one file, no split policy")
    ap.add_argument("--live-minutes", type=float, metavar="M",
                    help="only the live row: the recorder process for M wall-clock minutes of "
                         "the workload at real time (RSS sampled every --soak-every minutes)")
    ap.add_argument("--split-duration", type=float, metavar="S",
                    help=f"live: the recorder's --split-duration [s] (default its own, "
                         f"{DEFAULT_SPLIT_S:g})")
    args = ap.parse_args(argv)
    rows = []
    if args.live_minutes:
        return _alone(lambda tmp: bench_live(args.live_minutes, tmp, every_min=args.soak_every,
                                             split_s=args.split_duration),
                      args.json, _print_live)
    if args.soak_minutes:
        return _alone(lambda tmp: bench_soak(args.soak_minutes, tmp, split=not args.no_split,
                                             every_min=args.soak_every),
                      args.json, _print_soak)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows.append(bench_sink(args.messages, tmp))
        if not args.skip_bus:
            rows.append(bench_bus(args.messages, tmp))
        if not args.skip_scan:
            rows.append(bench_scan(args.scan_minutes, tmp))
        if not args.skip_replay:
            for batch in (False, True):
                rows.append(bench_read_floor(args.replay_seconds, tmp, range_batch=batch))
                for step in args.step_ms:
                    rows.append(bench_replay(args.replay_seconds, tmp, range_batch=batch,
                                             step_ms=step))
    if args.json:
        for r in rows:
            print(json.dumps(r))
        return 0
    print(f"{'row':<8}{'what':<58}{'result':>22}")
    for r in rows:
        if r["row"] == "sink":
            what = f"McapSink, {r['messages']} x {r['bytes_per_msg']} B, zstd"
            print(f"{'sink':<8}{what:<58}{r['rate_msg_s']:>14,.0f} msg/s")
        elif r["row"] == "bus":
            what = (f"recorder via router, {r['messages']} msgs BLOCK, lost {r['lost']}, "
                    f"gaps {r['gaps']}")
            print(f"{'bus':<8}{what:<58}{r['rate_msg_s']:>14,.0f} msg/s")
        elif r["row"] == "scan":
            what = f"read {r['minutes']:g} min 8x50@10Hz ({r['messages']:,} msgs, {r['file_mb']:.0f} MB)"
            print(f"{'scan':<8}{what:<58}{r['rate_msg_s']:>14,.0f} msg/s  ({r['x_real_time']:,.0f}x real time)")
        elif r["row"] == "floor":
            what = (f"read+decode {r['recording_s']:g} s of 8x50@10Hz, "
                    f"{'RangeBatch' if r['range_batch'] else 'one msg/range'} ({r['messages']:,} msgs)")
            print(f"{'floor':<8}{what:<58}{r['x_real_time']:>14.1f}x real time "
                  f"({r['rate_msg_s']:,.0f} msg/s, no fusion)")
        elif r["row"] == "replay":
            what = (f"replay {r['recording_s']:g} s, {'RangeBatch' if r['range_batch'] else 'one msg/range'}"
                    f", --step-ms {r['step_ms']:g} ({r['fixes']} fixes)")
            print(f"{'replay':<8}{what:<58}{r['x_real_time']:>14.1f}x real time ({r['fixes_per_s']:.0f} fixes/s)")
            print(f"{'':<8}{'  vs live: same status / identical position / max diff':<58}"
                  f"{100 * r['status_agree']:>13.2f}% / {100 * r['identical']:.1f}% / {r['max_diff_m']:.2g} m")
            print(f"{'':<8}{'  time in D-NLS / in ingestion (on_sample)':<58}"
                  f"{100 * r['solver_share']:>13.0f}% / {100 * r['ingest_share']:.0f}%")
    return 0


if __name__ == "__main__":
    sys.exit(main())
