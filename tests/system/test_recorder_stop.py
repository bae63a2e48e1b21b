"""The recorder's stop is bounded and lossless when SIGTERM is delivered to one of its other
threads (a Zenoh or a Python helper thread) instead of the main one.

The kernel hands a process-directed signal to any thread that does not block it; Python runs
its handler only when the main thread next runs bytecode. The recorder's main thread used to
wait on ``Shutdown.event`` without a timeout, so such a SIGTERM was never acted on: the
recorder sat after "ready" until killed (tests/system/test_faults.py's fusion restart test,
seen in CI under load). ``kill(2)`` on a thread id of the process delivers the signal to that
thread when it can take it, which makes the case deterministic here.
"""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest
import zenoh
from diffpos_services.bus.session import ZenohSettings, wait_matching
from diffpos_services.recorder import build_command
from diffpos_services.recording.reader import McapScanner
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys
from service_proc import ServiceProc

pytestmark = pytest.mark.system
SITE = "stop"
K = Keys(SITE)
TIMEOUT_S = 30.0
#: SIGTERM's bit in /proc/<pid>/task/<tid>/status SigBlk (bit signo - 1)
_SIGTERM_BIT = 1 << (signal.SIGTERM - 1)


def _other_thread(pid: int) -> int:
    """A thread of ``pid`` other than the main one, asleep and not blocking SIGTERM."""
    for tid in sorted(int(t) for t in os.listdir(f"/proc/{pid}/task")):
        if tid == pid:
            continue
        status = dict(line.split(":\t", 1) for line in
                      Path(f"/proc/{pid}/task/{tid}/status").read_text().splitlines()
                      if ":\t" in line)
        if status["State"].startswith("S") and not int(status["SigBlk"], 16) & _SIGTERM_BIT:
            return tid
    raise AssertionError(f"no sleeping thread of {pid} takes SIGTERM")


def test_sigterm_to_another_thread_stops_the_recorder_and_keeps_every_message(endpoint,
                                                                               tmp_path):
    router = ServiceProc([sys.executable, "-m", "diffpos_services.cli.main", "router",
                          "--listen", endpoint], timeout_s=TIMEOUT_S)
    procs = [router]
    try:
        out = tmp_path / "stop.mcap"
        rec = ServiceProc(build_command(site=SITE, out=out, connect=[endpoint],
                                        flush_interval_s=0.05), timeout_s=TIMEOUT_S)
        procs.append(rec)
        rec.wait_event(lambda e: e["event"] == "ready")
        n = 500
        with zenoh.open(ZenohSettings(connect=(endpoint,)).to_config()) as s:
            pub = s.declare_publisher(K.anchor_range("a1", "n1"),
                                      congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_matching(pub, timeout_s=TIMEOUT_S)
            for i in range(n):
                pub.put(M.encode(M.RangeMeasurement(
                    anchor_id="a1", node_id="n1", t_ns=1_000 + i, seq=i, range_m=20.0,
                    sigma_m=0.2, snr_db=15.0, t_pub_wall_ns=1_000 + i)))
            rec.wait_event(lambda e: e["event"] == "flush" and e["flushed_written"] >= n)
        tid = _other_thread(rec.p.pid)
        os.kill(tid, signal.SIGTERM)  # a thread id: delivered to that thread
        closed = rec.wait_event(lambda e: e["event"] == "closed")  # fails after TIMEOUT_S
        assert rec.p.wait(timeout=TIMEOUT_S) == 0
        assert closed["received"] == closed["written"] == n
        scanner = McapScanner(out)
        seqs = [m.sequence for batch in scanner.iter_batches() for m in batch
                if m.topic == K.anchor_range("a1", "n1")]
        assert scanner.complete  # footer and index written
        assert seqs == list(range(n))
    finally:
        for p in reversed(procs):
            p.kill()
