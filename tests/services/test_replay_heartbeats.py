"""Heartbeats (diffpos.heartbeat.v1, newly recorded) add no fusion step points: a replay in
recorded order (no decision record) of a recording with heartbeats publishes exactly what the
same recording without them does, every estimate's bytes (its step time too). Reference: the
replay of the copy without heartbeats."""

from __future__ import annotations

import msgspec
import pytest
from diffpos_services.recording.reader import McapScanner, side_records
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

HB_PERIOD_NS = 3_300_000  # between the 5 ms step points, off their grid


def _copy(src, dst, *, heartbeats: bool) -> int:
    """``src`` message for message into ``dst``, with (``heartbeats``) a fusion heartbeat
    every ``HB_PERIOD_NS`` of receive time between them. Returns the heartbeats written."""
    sink = McapSink(dst, library="test")
    for md in side_records(src).metadata:
        sink.add_metadata(md.name, dict(md.metadata))
    n, next_hb, site = 0, None, None
    for m in McapScanner(src).messages():
        site = site or m.topic.split("/")[1]
        next_hb = m.log_ns if next_hb is None else next_hb
        while heartbeats and next_hb <= m.log_ns:
            n += 1
            hb = M.Heartbeat(service="fusion", instance="abc", pid=1, seq=n, t_wall_ns=next_hb,
                             period_ns=HB_PERIOD_NS, progress=n, pending=0, last_epoch=None,
                             published=0)
            sink.write(Keys(site).heartbeat("fusion"), M.encode(hb), next_hb)
            next_hb += HB_PERIOD_NS
        sink.write(m.topic, m.data, m.log_ns, publish_ns=m.publish_ns, sequence=m.sequence)
    sink.close()
    return n


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    d = tmp_path_factory.mktemp("hb")
    write_synthetic_recording(d / "src.mcap", n_anchors=4, n_nodes=3, duration_s=3.0, seed=2)
    assert _copy(d / "src.mcap", d / "plain.mcap", heartbeats=False) == 0
    assert _copy(d / "src.mcap", d / "beats.mcap", heartbeats=True) > 500
    return d / "plain.mcap", d / "beats.mcap"


def test_heartbeats_add_no_step_points(pair):
    plain, beats = (replay(p, use_decisions=False) for p in pair)
    assert beats.report["messages"]["by_kind"].get("heartbeat", 0) > 500
    assert plain.report["decisions"] is None and beats.report["decisions"] is None
    assert len(plain.estimates) > 50
    a = [msgspec.json.encode(e) for e in plain.estimates]
    b = [msgspec.json.encode(e) for e in beats.estimates]
    assert a == b  # same fixes, published at the same step times, in the same order
