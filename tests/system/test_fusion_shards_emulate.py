"""``diffpos emulate --fusion-shards 2`` with real processes (issue 37, item 4): two fusion
processes (``diffpos fusion --shard 0/2`` and ``1/2``) together publish one estimate of every
node-epoch, each started, awaited and counted as the run's own; the recording says the run
was sharded and holds the whole run's fusion settings, and a replay of the whole run (one
fusion) gives an estimate of every live node-epoch. The bit-for-bit equality of the shards'
union with one fusion: tests/services/test_fusion_shards.py.
"""

from __future__ import annotations

import collections
import json

import pytest
from diffpos_services.recording.reader import side_records
from diffpos_services.replay.run import replay

pytestmark = pytest.mark.slow


def test_emulate_with_two_fusion_shards_publishes_every_node_epoch_once(services, tmp_path):
    mcap = tmp_path / "run.mcap"
    p = services.start("emulate", "emulate", "--duration", "3", "--speed", "0",
                       "--record", str(mcap), "--dashboard", "off", "--no-progress",
                       "--fusion-shards", "2")
    assert p.wait(timeout=600) == 0, services.log("emulate")[-3000:]
    md = {m.name: m.metadata for m in side_records(mcap).metadata}
    emu = json.loads(md["run_config"]["emulate"])
    fusion = json.loads(md["run_config"]["fusion"])
    assert emu["fusion_shards"] == 2
    assert (fusion["shard"], fusion["shards"]) == (0, 1)  # the whole run's settings

    r = replay(mcap, keep_estimates=True)
    c = r.report["compare"]
    assert c["live"] == c["matched"] == c["replayed"] > 0, c  # no node-epoch missing or twice
    assert c["only_live"] == c["only_replayed"] == 0
    live = collections.Counter((e.node_id, e.epoch) for e in r.live_estimates)
    assert set(live.values()) == {1}  # no node-epoch published by both shards
    per_node = collections.Counter(node for node, _ in live)
    assert len(per_node) >= 2 and len(set(per_node.values())) == 1, per_node
