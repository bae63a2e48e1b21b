"""The estimates' sequence streams of a replay follow the shard count the run configuration
records (``SeqTracker(estimate_shards=N)``) instead of inferring it from the sequence numbers
(issue 37). References: the sequence numbers and shard owners the test itself wrote."""

from __future__ import annotations

import msgspec
import pytest
from diffpos_services.fusion.config import shard_of
from diffpos_services.recording.reader import side_records
from diffpos_services.recording.topics import SeqTracker
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.run import recorded_shards, replay
from diffpos_services.replay.synthetic import synthetic_run, write_late_recording
from diffpos_services.wire.keys import Keys

K = Keys("t1")


def _owned(shard: int, shards: int, count: int) -> list[str]:
    out, i = [], 0
    while len(out) < count:
        if shard_of(f"n{i}", shards) == shard:
            out.append(f"n{i}")
        i += 1
    return out


def test_a_hole_of_the_only_publishing_shard_is_named_by_its_recorded_shard():
    """Only shard 1 of 2 publishes (its nodes' estimates, one counter) and loses seq 5: the
    numbers alone cannot tell one fusion from shard 1/2 (a tie, inferred as one fusion); the
    recorded count names the stream that lost it."""
    nodes = _owned(1, 2, 3)
    msgs = [(K.node_estimate(nodes[s % 3]), s) for s in range(1, 40) if s != 5]
    inferred, recorded = SeqTracker(), SeqTracker(estimate_shards=2)
    for topic, s in msgs:
        inferred.add(topic, s)
        recorded.add(topic, s)
    assert inferred.gaps == {"diffpos/t1/node/*/estimate": 1}
    assert recorded.gaps == {"diffpos/t1/node/*/estimate shard 1/2": 1}
    assert recorded.gap_list == [("diffpos/t1/node/*/estimate shard 1/2", 5, 5)]


@pytest.mark.parametrize("shards", [1, 3, 11])  # 11: beyond the inferred candidates (8)
def test_interleaved_recorded_shards_count_one_hole_from_the_first_estimate(shards):
    owned = [_owned(k, shards, 2) for k in range(shards)]
    seq = [0] * shards
    t = SeqTracker(estimate_shards=shards)
    found = 0
    for _ in range(3):  # few estimates: nothing to infer from yet
        for k in range(shards):
            for node in owned[k]:
                seq[k] += 1
                if (k, seq[k]) != (shards - 1, 2):
                    found += t.add(K.node_estimate(node), seq[k])
    name = "diffpos/t1/node/*/estimate" + ("" if shards == 1 else f" shard {shards - 1}/{shards}")
    assert found == t.total_gaps == 1 and t.gaps == {name: 1} and t.total_out_of_order == 0


def test_estimate_shards_must_be_positive():
    with pytest.raises(ValueError, match="estimate_shards"):
        SeqTracker(estimate_shards=0)


def test_recorded_shards_as_before(tmp_path):
    """The run configuration's count (2) and each shard's settings; a recording without a run
    configuration: one fusion, no per-shard settings."""
    two = tmp_path / "two.mcap"
    write_late_recording(two, n_anchors=4, n_nodes=6, duration_s=1.0, seed=3, shards=2)
    n, per = recorded_shards(side_records(two))
    assert n == 2 and [d["shard"] for d in per] == [0, 1]
    bare = tmp_path / "bare.mcap"
    sink = McapSink(bare, library="test")
    sink.add_metadata("fusion_config", msgspec.to_builtins(synthetic_run(seed=1).config))
    sink.close()
    assert recorded_shards(side_records(bare)) == (1, None)


def test_a_sharded_replay_reports_no_gap(tmp_path):
    """A two-shard recording replayed: the live estimates' streams per recorded shard have no
    gap and nothing out of order."""
    path = tmp_path / "sharded.mcap"
    write_late_recording(path, n_anchors=4, n_nodes=6, duration_s=2.0, seed=3, shards=2)
    msgs = replay(path, keep_estimates=False).report["messages"]
    assert msgs["gaps"] == 0 and msgs["out_of_order"] == 0, msgs["gaps_by_stream"]
