"""Replay of a run of fusion shards (issue 37 item 4), without Zenoh.

``write_late_recording(shards=2)`` plays two live fusions (``diffpos fusion --shard 0/2`` and
``1/2``), each on its own machine (its own seeded late epochs, so each ingests and steps in
its own order), publishing their diagnostics (with their decision records) on the one
diagnostics key and their responders' estimates; the recorder gets everything on time and
the run configuration as ``diffpos emulate --fusion-shards 2`` records it. Replay runs one core
per live shard by that shard's record: every live estimate bit for bit (its ``seq`` too).
One fusion and two shards fed the same recorded stream publish the same estimates. A
sharded recording made before the diagnostics said which shard sent them still replays, and
says in one line that the live estimates cannot be reproduced.
"""

from __future__ import annotations

import json
import zlib

import msgspec
import pytest
from diffpos_services.recording.reader import McapScanner, side_records
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_late_recording
from diffpos_services.wire import messages as M


@pytest.fixture(scope="module")
def sharded(tmp_path_factory):
    path = tmp_path_factory.mktemp("shards") / "sharded.mcap"
    write_late_recording(path, n_anchors=5, n_nodes=6, duration_s=5.0, late_fraction=0.15,
                         seed=5, outlier_probability=0.05, shards=2)
    return path


def _bare(e, *, seq: bool = True) -> bytes:
    """The estimate's bytes but its publish time (and, unless ``seq``, its per-publisher
    sequence number)."""
    return M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0, **({} if seq else {"seq": 0})))


def _diagnostics(path):
    dec = M.decoder(M.FusionDiagnostics)
    return [dec(m.data) for m in McapScanner(path).messages()
            if m.topic.endswith("/fusion/diagnostics")]


def test_each_shard_replays_by_its_own_record_bit_for_bit(sharded):
    diags = _diagnostics(sharded)
    assert {(d.shard, d.shards) for d in diags} == {(0, 2), (1, 2)}
    assert len({d.instance for d in diags}) == 2  # two processes on one key
    r = replay(sharded)
    sh = r.report["shards"]
    assert (sh["live"], sh["replayed"], sh["by_record"], sh["note"]) == (2, 2, [0, 1], None)
    assert sh["settings"] == "recorded per shard" and sh["cores"] == [["0/2"], ["1/2"]]
    d = r.report["decisions"]
    assert d["samples"] > 100 and d["restarts"] == 0
    assert d["chunks_missing"] == d["samples_missing"] == d["inputs_not_ingested"] == 0
    live = r.live_estimates
    # both shards published, each only its responders (CRC-32 of the id, computed here)
    owners = {zlib.crc32(e.node_id.encode()) % 2 for e in live}
    assert owners == {0, 1}
    assert r.report["fusion_instances"]["estimates"] == 0  # nothing unreproducible
    assert len(live) > 200 and sorted(map(_bare, live)) == sorted(map(_bare, r.estimates))


def test_the_recorder_order_does_not_reproduce_the_live_shards(sharded):
    """Each shard ingested in its own order: without the records the replay differs (the
    record, per shard, is what makes the replay live-equivalent, not luck)."""
    r = replay(sharded, use_decisions=False)
    assert sorted(map(_bare, r.live_estimates)) != sorted(map(_bare, r.estimates))


def test_one_fusion_and_two_shards_on_the_same_stream_publish_the_same(sharded):
    one = replay(sharded, use_decisions=False, shards=1)
    two = replay(sharded, use_decisions=False)
    assert one.report["shards"]["cores"] == [["0/1"], ["0/1"]]
    assert two.report["shards"]["cores"] == [["0/2"], ["1/2"]]
    a = sorted(_bare(e, seq=False) for e in one.estimates)
    b = sorted(_bare(e, seq=False) for e in two.estimates)
    assert len(a) == len(one.live_estimates) and a == b


def _strip_shards(src, dst) -> int:
    """``src`` as recorded before the diagnostics carried shard/shards (those fields dropped;
    everything else as is). Returns the diagnostics rewritten."""
    side = side_records(src)
    sink = McapSink(dst, library="test")
    for md in side.metadata:
        sink.add_metadata(md.name, {k: v for k, v in md.metadata.items()
                                    if k != "fusion_by_shard"})
    n = 0
    for m in McapScanner(src).messages():
        data = m.data
        if m.topic.endswith("/fusion/diagnostics"):
            doc = json.loads(data)
            doc.pop("shard"), doc.pop("shards")
            data, n = json.dumps(doc).encode(), n + 1
        sink.write(m.topic, data, m.log_ns, publish_ns=m.publish_ns, sequence=m.sequence)
    sink.close()
    return n


def test_an_older_sharded_recording_replays_and_says_what_it_cannot_reproduce(
        sharded, tmp_path, caplog):
    old = tmp_path / "old.mcap"
    assert _strip_shards(sharded, old) > 4
    assert {(d.shard, d.shards) for d in _diagnostics(old)} == {(0, 1)}  # read as 0 of 1
    with caplog.at_level("WARNING", logger="diffpos.replay"):
        r = replay(old)
    sh = r.report["shards"]
    assert (sh["live"], sh["recorded"], sh["by_record"]) == (1, 2, [])
    assert [rec.getMessage() for rec in caplog.records] == [sh["note"]]
    assert "cannot be reproduced" in sh["note"]
    assert r.report["decisions"] is None  # no record replayed (two records interleave)
    c = r.report["compare"]
    assert c["live"] == c["replayed"] == c["matched"] > 200  # every node-epoch, once
    assert r.report["fusion_instances"]["estimates"] == c["live"]  # each one said so
    assert r.report["fusion_instances"]["instances"] == []  # no fresh core per instance


def test_diagnostics_without_shard_fields_decode_as_one_fusion():
    d = _diagnostics_example()
    raw = json.loads(M.encode(d))
    raw.pop("shard"), raw.pop("shards")
    back = M.decoder(M.FusionDiagnostics)(json.dumps(raw).encode())
    assert (back.shard, back.shards) == (0, 1)
    with pytest.raises(M.DecodeError, match="shards"):
        M.decoder(M.FusionDiagnostics)(json.dumps({**raw, "shards": 0}).encode())


def _diagnostics_example() -> M.FusionDiagnostics:
    return M.FusionDiagnostics(
        t_wall_ns=1, watermark_ns=None, received={}, rejected={}, gated=0, solved=0,
        published=0, fixes_by_status={}, late_ranges=0, pending_epochs=0, live_anchors=[],
        anchors=[], latency=M.LatencyStats(0, None, None, None), shard=1, shards=2)
