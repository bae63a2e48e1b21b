"""Replay of a recording that spans a fusion restart (issue 36 item 1), without Zenoh.

``write_late_recording(restart_at_s=...)`` plays a live fusion that is killed at 3.5 s (its
inbox, pending epochs and the decision record since its last diagnostics are lost) and a new
fusion process (fresh core, another ``instance``, a record from chunk 0) that starts 1.2 s
later; the recorder records throughout. Replay starts a fresh core where ``instance`` changes
and follows the new record: every estimate it produces is the live one bit for bit, and the
live estimates it cannot produce (the dead instance's after its last diagnostics; an instance
whose record does not begin in the file) are counted with the reason.
"""

from __future__ import annotations

import msgspec
import pytest
from diffpos_services.recording.reader import McapScanner, side_records
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_late_recording
from diffpos_services.wire import messages as M

TAIL = ("published after the instance's last diagnostics (killed: the record of their calls "
        "died with it)")


@pytest.fixture(scope="module")
def restart_rec(tmp_path_factory):
    path = tmp_path_factory.mktemp("restart") / "restart.mcap"
    write_late_recording(path, n_anchors=5, n_nodes=4, duration_s=8.0, late_fraction=0.15,
                         seed=5, outlier_probability=0.05, restart_at_s=3.5,
                         restart_gap_s=1.2)
    return path


def _bare(e):
    return M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))


def _diagnostics(path):
    dec = M.decoder(M.FusionDiagnostics)
    return [(m.log_ns, dec(m.data)) for m in McapScanner(path).messages()
            if m.topic.endswith("/fusion/diagnostics")]


def test_replay_across_a_fusion_restart_reproduces_both_instances(restart_rec):
    diags = _diagnostics(restart_rec)
    assert diags[0][1].instance != diags[-1][1].instance  # the file spans a restart
    r = replay(restart_rec)
    d = r.report["decisions"]
    assert d["restarts"] == 1 and d["chunks_repeated"] == 0 and d["samples_missing"] == 0, d
    c = r.report["compare"]
    # every replayed estimate is the live one (before: the second instance's record was
    # dropped as 'repeated' chunks and its estimates came from the old core)
    assert c["only_replayed"] == 0 and c["status_agree"] == 1.0, c
    assert c["identical_positions"] == c["with_positions"] > 0, c
    # what is not reproduced is exactly what the dead instance published after its last
    # diagnostics, and the report says so
    dead_last = max(t for t, dg in diags if dg.instance == diags[0][1].instance)
    new_start = r.report["fusion_instances"]["instances"][1]["start_ns"]
    tail = [e for e in r.live_estimates if dead_last < e.t_pub_wall_ns + 50_000 < new_start]
    assert len(tail) > 0
    assert c["only_live"] == c["live_not_reproducible"] == len(tail), c
    assert c["live_not_reproducible_by_reason"] == {TAIL: len(tail)}
    tail_keys = {_bare(e) for e in tail}
    live = sorted(b for b in map(_bare, r.live_estimates) if b not in tail_keys)
    assert live == sorted(map(_bare, r.estimates))


def test_instance_whose_record_does_not_begin_in_the_file_is_counted(restart_rec, tmp_path):
    """The same run, but the recorder missed the new instance's first diagnostics (chunk 0):
    that instance is replayed in recorded order on a fresh core, and its live estimates are
    counted as not reproducible, with the reason."""
    diags = _diagnostics(restart_rec)
    first_new = next(t for t, d in diags if d.instance != diags[0][1].instance)
    cut = tmp_path / "cut.mcap"
    sink = McapSink(cut, library="test")
    for md in side_records(restart_rec).metadata:
        sink.add_metadata(md.name, md.metadata)
    for m in McapScanner(restart_rec).messages():
        if not (m.log_ns == first_new and m.topic.endswith("/fusion/diagnostics")):
            sink.write(m.topic, m.data, m.log_ns, publish_ns=m.publish_ns, sequence=m.sequence)
    sink.close()
    r = replay(cut)
    inst = r.report["fusion_instances"]["instances"]
    assert [i["replayed_by"] for i in inst] == ["decisions", "recorded order"], inst
    assert "begins at chunk 1, not 0" in inst[1]["reason"]
    second = sum(1 for e in r.live_estimates if e.t_pub_wall_ns + 50_000 >= inst[1]["start_ns"])
    c = r.report["compare"]
    assert c["live_not_reproducible_by_reason"][inst[1]["reason"]] == second > 0, c
    assert r.report["decisions"]["restarts"] == 1
    # the recorded-order instance is stepped as the file goes (each step's estimates published
    # at that step's receive time), not only by the drain at the recording's end
    times = {e.t_pub_wall_ns for e in r.estimates if e.t_pub_wall_ns >= inst[1]["start_ns"]}
    assert len(times) > 10, sorted(times)
