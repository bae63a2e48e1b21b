"""Replay by the live fusion's decision record (issue 15 item 3), without Zenoh.

``write_late_recording`` plays a live fusion that receives a seeded tenth of the anchors'
epochs 0.5 s late (a loaded machine) while the recorder gets everything on time: the
recorder's order is not the fusion's. Replaying the recorder's order (as before) makes other
decisions; replaying by the recorded decisions gives the live fixes bit for bit. The same
recording pins the diagnostics v2 fields (late ranges per anchor, release reasons).
"""

from __future__ import annotations

import msgspec
import pytest
from diffpos_services.recording.reader import McapScanner
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_late_recording
from diffpos_services.wire import messages as M


@pytest.fixture(scope="module")
def late_rec(tmp_path_factory):
    path = tmp_path_factory.mktemp("decisions") / "late.mcap"
    write_late_recording(path, n_anchors=5, n_nodes=4, duration_s=6.0, late_fraction=0.15,
                         seed=5, outlier_probability=0.05)
    return path


def _bare(e):
    return M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))


def test_replay_by_decisions_is_bit_identical_to_live(late_rec):
    r = replay(late_rec)
    d = r.report["decisions"]
    assert d["chunks"] >= 6 and d["samples"] > 100
    assert d["chunks_missing"] == d["samples_missing"] == d["inputs_not_ingested"] == 0
    c = r.report["compare"]
    assert c["only_live"] == c["only_replayed"] == 0 and c["status_agree"] == 1.0
    assert c["identical_positions"] == c["with_positions"] > 0
    assert sorted(map(_bare, r.live_estimates)) == sorted(map(_bare, r.estimates))


def test_recorder_order_alone_does_not_reproduce_the_live_run(late_rec):
    """Without the record (the old way) the same file gives other fixes: the record is what
    makes replay live-equivalent here, not luck."""
    r = replay(late_rec, use_decisions=False)
    assert r.report["decisions"] is None
    assert sorted(map(_bare, r.live_estimates)) != sorted(map(_bare, r.estimates))


def test_diagnostics_say_why_fixes_were_lost(late_rec):
    dec = M.decoder(M.FusionDiagnostics)
    diags = [dec(m.data) for m in McapScanner(late_rec).messages()
             if m.topic.endswith("/fusion/diagnostics")]
    last = diags[-1]
    assert last.late_ranges > 0  # the late epochs were dropped ...
    assert sum(last.late_by_anchor.values()) == last.late_ranges  # ... and by whom
    assert last.deadline_ns is not None and last.max_lag_ns >= last.deadline_ns
    assert set(last.releases) == {"complete", "passed", "watermark", "wall_fallback", "flush"}
    assert sum(last.releases.values()) == last.solved  # every solved epoch has a reason
    assert all(d.decisions is not None for d in diags)
    assert [d.decisions.chunk for d in diags if d.decisions.ops] == list(
        range(sum(1 for d in diags if d.decisions.ops)))
