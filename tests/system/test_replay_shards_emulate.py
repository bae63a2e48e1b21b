"""A live run of two fusion shards, recorded and replayed (issue 37 item 4): real processes
(``diffpos emulate --fusion-shards 2``: a router, the anchors, ``diffpos fusion --shard 0/2``
and ``1/2``, the recorder), a real MCAP read back. Each shard says in its diagnostics which it
is and the run records each shard's settings; the replay runs one core per shard by that
shard's decision record and reproduces every live estimate bit for bit (its sequence number
too). On the same recorded stream (the recorder's order, unbudgeted steps) one fusion and two
shards publish the same estimates, for every live node-epoch.
"""

from __future__ import annotations

import json
import zlib

import msgspec
from diffpos_services.recording.reader import McapScanner, side_records
from diffpos_services.replay.run import replay
from diffpos_services.wire import messages as M


def _bare(e, *, seq: bool = True) -> bytes:
    return M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0, **({} if seq else {"seq": 0})))


def test_a_live_two_shard_run_replays_bit_for_bit_and_equals_one_fusion(services, tmp_path):
    mcap = tmp_path / "run.mcap"
    p = services.start("emulate", "emulate", "--duration", "4", "--speed", "0",
                       "--record", str(mcap), "--dashboard", "off", "--no-progress",
                       "--fusion-shards", "2")
    assert p.wait(timeout=600) == 0, services.log("emulate")[-3000:]

    run_config = next(m.metadata for m in side_records(mcap).metadata if m.name == "run_config")
    by_shard = json.loads(run_config["fusion_by_shard"])
    assert [(c["shard"], c["shards"]) for c in by_shard] == [(0, 2), (1, 2)]
    dec = M.decoder(M.FusionDiagnostics)
    diags = [dec(m.data) for m in McapScanner(mcap).messages()
             if m.topic.endswith("/fusion/diagnostics")]
    assert {(d.shard, d.shards) for d in diags} == {(0, 2), (1, 2)}
    assert len({d.instance for d in diags}) == 2

    r = replay(mcap)
    sh = r.report["shards"]
    assert (sh["live"], sh["replayed"], sh["by_record"]) == (2, 2, [0, 1])
    assert sh["settings"] == "recorded per shard"
    d = r.report["decisions"]
    assert d["samples_missing"] == d["chunks_missing"] == d["restarts"] == 0
    live = r.live_estimates
    assert {zlib.crc32(e.node_id.encode()) % 2 for e in live} == {0, 1}  # both published
    assert len(live) >= 6 * 20
    assert sorted(map(_bare, live)) == sorted(map(_bare, r.estimates))  # bit for bit

    one = replay(mcap, use_decisions=False, shards=1)
    two = replay(mcap, use_decisions=False)
    assert one.report["shards"]["cores"] == [["0/1"], ["0/1"]]
    a = {(e.node_id, e.epoch): _bare(e, seq=False) for e in one.estimates}
    b = {(e.node_id, e.epoch): _bare(e, seq=False) for e in two.estimates}
    assert a.keys() == b.keys() == {(e.node_id, e.epoch) for e in live}
    assert a == b
