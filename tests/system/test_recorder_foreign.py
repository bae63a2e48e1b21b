"""Foreign publishers on a recorded run (issue 15 item 9): the recorder, given the run
configuration ``diffpos emulate`` writes (the run's fusion id prefix and its anchors), keeps
the run's own messages in the recording and every foreign one, unchanged, in
``<stem>.foreign.mcap``, and says so in the recording's metadata.

Real router and recorder processes on loopback; the test's publishers are real Zenoh
sessions: "the fusion" with a zenoh id carrying the run's prefix (timestamping on, as
emulate starts it), an intruder with its own id. Synchronised on the recorder's status lines.
"""

from __future__ import annotations

import json
import secrets
import signal
import sys
from collections import Counter

import pytest
import zenoh
from diffpos_services.bus.commands import foreign_path
from diffpos_services.bus.session import ZenohSettings, wait_matching
from diffpos_services.recorder import build_command
from diffpos_services.recording.reader import JsonDecoderFactory
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys
from mcap.reader import make_reader
from service_proc import ServiceProc

SITE = "fx"
K = Keys(SITE)
TIMEOUT_S = 30.0
PREFIX = f"{secrets.randbits(60) | (1 << 60):x}"


def _session(ep: str, zid: str | None) -> zenoh.Session:
    cfg = ZenohSettings(connect=(ep,)).to_config()
    if zid is not None:
        cfg.insert_json5("id", json.dumps(zid))
    cfg.insert_json5("timestamping/enabled", "true")
    return zenoh.open(cfg)


def _estimate(n: str, e: int, msg: str) -> bytes:
    return M.encode(M.PositionEstimate(
        node_id=n, t_ns=1_000_000_000 + e * 100_000_000, epoch=e, seq=e + 1,
        status="NOT_IDENTIFIABLE", position_m=None, covariance_m2=None, peb_m=None,
        z_bound_m=None, floor_index=None, used_anchors=[], residuals_m=[], excluded=[],
        message=msg, t_input_wall_ns=1, t_pub_wall_ns=2))


def _state(a: str, e: int) -> bytes:
    return M.encode(M.AnchorState(
        anchor_id=a, t_ns=1_000_000_000 + e * 100_000_000, seq=e + 1, position_m=(0.0, -10.0, 2.0),
        velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.1, 0.1, 0.1), velocity_sigma_m_s=0.0,
        range_rate_hz=10.0, t_pub_wall_ns=1))


def _read(path) -> tuple[Counter, dict]:
    topics: Counter[str] = Counter()
    texts = []
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[JsonDecoderFactory()])
        for _, ch, _, obj in reader.iter_decoded_messages():
            if not ch.topic.endswith("/recorder/liveliness"):
                topics[ch.topic] += 1
                texts.append(obj.get("message"))
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    return topics, {"meta": meta, "messages": texts}


@pytest.mark.slow
def test_foreign_estimates_and_anchors_kept_apart_and_counted(endpoint, tmp_path):
    ep = endpoint
    router = ServiceProc([sys.executable, "-m", "diffpos_services.cli.main", "router",
                          "--listen", ep], timeout_s=TIMEOUT_S)
    procs = [router]
    try:
        out = tmp_path / "run.mcap"
        run_cfg = tmp_path / "run_config.json"
        run_cfg.write_text(json.dumps({"fusion": {"site": SITE, "anchors": ["uav1", "uav2"]},
                                       "emulate": {"fusion_id_prefix": PREFIX}}))
        rec = ServiceProc(build_command(site=SITE, out=out, connect=[ep], run_config=run_cfg,
                                        flush_interval_s=0.05), timeout_s=TIMEOUT_S)
        procs.append(rec)
        rec.wait_event(lambda e: e["event"] == "ready")
        own_zid = PREFIX + f"{secrets.randbits(64):016x}"
        bc = zenoh.CongestionControl.BLOCK
        sent = Counter()
        with _session(ep, own_zid) as own, _session(ep, None) as intruder:
            pubs = {
                "own_est": own.declare_publisher(K.node_estimate("n1"), congestion_control=bc),
                "fake_est": intruder.declare_publisher(K.node_estimate("n1"), congestion_control=bc),
                "uav1": intruder.declare_publisher(K.anchor_state("uav1"), congestion_control=bc),
                "uav9": intruder.declare_publisher(K.anchor_state("uav9"), congestion_control=bc),
            }
            for p in pubs.values():
                assert wait_matching(p, timeout_s=TIMEOUT_S)
            for e in range(40):
                pubs["own_est"].put(_estimate("n1", e, "own"))
                pubs["uav1"].put(_state("uav1", e))
                if e % 2 == 0:
                    pubs["fake_est"].put(_estimate("n1", e, "fake"))
                    pubs["uav9"].put(_state("uav9", e))
            sent.update(own=80, foreign=40)
            rec.wait_event(lambda e: e["event"] == "flush" and e["flushed_written"] >= 80
                           and e.get("foreign", 0) >= 40)
        rec.p.send_signal(signal.SIGTERM)
        rec.wait_event(lambda e: e["event"] == "closed")
        assert rec.p.wait(timeout=TIMEOUT_S) == 0
    finally:
        for p in reversed(procs):
            p.kill()
    topics, got = _read(out)
    # the recording: the run's fusion's estimates and the run's anchor, nothing else
    assert topics == Counter({K.node_estimate("n1"): 40, K.anchor_state("uav1"): 40})
    assert set(got["messages"]) == {"own", None}
    info = got["meta"]["foreign"]
    assert int(info["count"]) == 40 and info["file"] == foreign_path(out).name
    assert json.loads(info["keys"]) == {K.node_estimate("n1"): 20, K.anchor_state("uav9"): 20}
    # the foreign messages, unchanged, next to it
    ftopics, fgot = _read(foreign_path(out))
    assert ftopics == Counter({K.node_estimate("n1"): 20, K.anchor_state("uav9"): 20})
    assert set(fgot["messages"]) == {"fake", None}
    assert "foreign" in fgot["meta"]
