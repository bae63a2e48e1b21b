"""Estimate sequence numbers of several fusion shards (``diffpos emulate --fusion-shards
N``): each shard numbers its own estimates on the one ``node/*/estimate`` key, so the tracker
counts per shard (the node's owner, :func:`shard_of`) and reports nothing missing when
nothing was lost, while a real hole is still counted. References: the sequence numbers the
test itself wrote or left out."""

from __future__ import annotations

import pytest
from diffpos_services.fusion.config import shard_of
from diffpos_services.recording.summary import set_losses
from diffpos_services.recording.topics import LOCK_AFTER, SeqTracker
from diffpos_services.replay.synthetic import write_late_recording
from diffpos_services.wire.keys import Keys

K = Keys("t1")


def _nodes(shards: int, per_shard: int = 3) -> list[list[str]]:
    """``per_shard`` node ids owned by each of ``shards`` shards."""
    out: list[list[str]] = [[] for _ in range(shards)]
    i = 0
    while min(map(len, out)) < per_shard:
        n = f"n{i}"
        if len(out[shard_of(n, shards)]) < per_shard:
            out[shard_of(n, shards)].append(n)
        i += 1
    return out


def _interleaved(shards: int, epochs: int = 20, drop: tuple[int, int] | None = None):
    """(topic, seq) of ``shards`` fusions, each publishing its nodes' estimates per epoch
    with its own counter, epochs interleaved shard by shard; ``drop``: (shard, seq) lost."""
    owned = _nodes(shards)
    seq = [0] * shards
    out = []
    for _ in range(epochs):
        for k in range(shards):
            for node in owned[k]:
                seq[k] += 1
                if drop != (k, seq[k]):
                    out.append((K.node_estimate(node), seq[k]))
    return out


@pytest.mark.parametrize("shards", [1, 2, 3])
@pytest.mark.parametrize("epochs", [20, 400])  # 400: past LOCK_AFTER estimates
def test_interleaved_shards_without_loss_miss_nothing(shards, epochs):
    t = SeqTracker()
    for topic, s in _interleaved(shards, epochs):
        assert t.add(topic, s) == 0
    assert (t.total_gaps, t.gaps, t.total_out_of_order, t.out_of_order) == (0, {}, 0, {})


@pytest.mark.parametrize("shards", [1, 2, 3])
@pytest.mark.parametrize(("epochs", "lost"), [(20, 17), (400, 1100)])  # 1100: after the lock
def test_one_dropped_estimate_is_one_missing(shards, epochs, lost):
    assert epochs * 3 * shards > LOCK_AFTER or epochs == 20
    t = SeqTracker()
    found = sum(t.add(topic, s) for topic, s in _interleaved(shards, epochs,
                                                               drop=(shards - 1, lost)))
    assert found == t.total_gaps == 1 and t.total_out_of_order == 0
    name = "diffpos/t1/node/*/estimate" + ("" if shards == 1 else f" shard {shards - 1}/{shards}")
    assert t.gaps == {name: 1} and t.gap_list == [(name, lost, lost)]


def test_anchor_streams_unchanged_beside_estimates():
    t = SeqTracker()
    for s in (1, 2, 5):
        t.add(K.anchor_state("a1"), s)
    for topic, s in _interleaved(2):
        t.add(topic, s)
    assert t.gaps == {"diffpos/t1/anchor/a1/**": 2} and t.total_gaps == 2


def test_a_sharded_recording_loses_nothing(tmp_path):
    """The emulate summary's count (:func:`set_losses`) on a two-shard recording."""
    path = tmp_path / "sharded.mcap"
    write_late_recording(path, n_anchors=4, n_nodes=6, duration_s=2.0, seed=3, shards=2)
    losses = set_losses(path)
    assert losses.missing == 0 and losses.by_stream == {}, losses.by_stream
    assert losses.restarted_streams == {}  # (the two counters, merged, also went backwards)
