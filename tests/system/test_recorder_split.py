"""The recorder process splits a recording into complete parts (bounded memory), on a real
Zenoh bus (Python router, loopback, free port).

Synchronisation on readiness only: the recorder's "ready" status line, the publisher's
matching status, the "flush" status saying every message is on disk, the "closed" line.
"""

from __future__ import annotations

import os
import signal
import sys
from collections import Counter

import pytest
import zenoh
from diffpos_services.bus.session import ZenohSettings, wait_matching
from diffpos_services.cli.main import main as cli_main
from diffpos_services.recorder import build_command
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys
from mcap.reader import make_reader
from service_proc import ServiceProc

pytestmark = pytest.mark.slow
SITE = "sp"
K = Keys(SITE)
TIMEOUT_S = 60.0


def _Proc(argv: list[str]) -> ServiceProc:
    return ServiceProc(argv, timeout_s=TIMEOUT_S)


@pytest.fixture
def bus(endpoint):
    router = _Proc([sys.executable, "-m", "diffpos_services.cli.main", "router", "--listen",
                    endpoint])
    procs = [router]
    yield endpoint, procs
    for p in reversed(procs):
        p.kill()


def test_recorder_splits_into_complete_parts_holding_every_message(bus, tmp_path, capsys):
    ep, procs = bus
    out = tmp_path / "split.mcap"
    scenario = tmp_path / "scen.toml"
    scenario.write_text('name = "unit"\n')
    argv = build_command(site=SITE, out=out, connect=[ep], scenario=scenario,
                         flush_interval_s=0.02, split_size_mb=0.03, split_duration_s=0)
    rec = _Proc(argv)
    procs.append(rec)
    rec.wait_event(lambda e: e["event"] == "ready")
    sent: Counter = Counter()
    with zenoh.open(ZenohSettings(connect=(ep,)).to_config()) as s:
        block = zenoh.CongestionControl.BLOCK
        keys = {(a, n): K.anchor_range(a, n) for a in ("a1", "a2") for n in ("n1", "n2")}
        pubs = {k: s.declare_publisher(key, congestion_control=block) for k, key in keys.items()}
        for p in pubs.values():
            assert wait_matching(p, timeout_s=TIMEOUT_S)
        seq = Counter()
        # in rounds, each flushed before the next is sent: the parts then do not depend on how
        # many messages one flush happens to catch (one flush of everything made 2 parts)
        for first in range(0, 1500, 250):
            for e in range(first, first + 250):
                for (a, n), pub in pubs.items():
                    seq[a] += 1
                    t = 10**18 + e * 10**8
                    pub.put(M.encode(M.RangeMeasurement(
                        anchor_id=a, node_id=n, t_ns=t, seq=seq[a], range_m=20.0 + e * 1e-3,
                        sigma_m=0.2, snr_db=15.0, t_pub_wall_ns=t)))
                    sent[(keys[(a, n)], seq[a])] += 1
            total = sum(sent.values())
            rec.wait_event(lambda ev, n=total: ev["event"] == "flush"
                           and ev["flushed_written"] >= n)
    rec.p.send_signal(signal.SIGTERM)
    closed = rec.wait_event(lambda ev: ev["event"] == "closed")
    assert rec.p.wait(timeout=TIMEOUT_S) == 0
    assert closed["received"] == closed["written"] == total and closed["gaps"] == 0
    parts = closed["parts"]
    assert parts[0] == str(out) and len(parts) >= 3
    assert sorted(p.name for p in tmp_path.glob("split*.mcap")) == sorted(
        os.path.basename(p) for p in parts)
    got: Counter = Counter()
    for k, path in enumerate(parts):
        with open(path, "rb") as f:  # the official reader: complete and indexed
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None and summary.chunk_indexes, path
            for _, ch, m in reader.iter_messages():
                if "/range/" in ch.topic:
                    got[(ch.topic, m.sequence)] += 1
            meta = {m.name: m.metadata for m in reader.iter_metadata()}
            atts = {a.name: a.data for a in reader.iter_attachments()}
        assert meta["run"]["site"] == SITE and meta["part"]["index"] == str(k), path
        assert atts["scen.toml"] == b'name = "unit"\n', path
        assert cli_main(["inspect", path]) == 0  # each part stands alone
        capsys.readouterr()
    assert got == sent  # together the parts hold every message exactly once
