"""The summary's notes (emulate/notes.py): when and why fixes were lost, every recording
file, foreign messages. References: counts by hand for made-up runs; real split recordings
written by the real sink."""

from __future__ import annotations

import msgspec
import numpy as np
from diffpos_services.bus.commands import foreign_path
from diffpos_services.emulate.notes import (
    EndToEnd,
    foreign_notes,
    fusion_notes,
    latency_notes,
    loss_notes,
    model_notes,
    recording_notes,
)
from diffpos_services.emulate.scoring import Scorer
from diffpos_services.recording.writer import McapSink, SplitPolicy, part_path
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

from diffpos.scenario import default_scenario
from diffpos.trajectory import Static

B = default_scenario().building
P = 100_000_000
T0 = 1_800_000_000_000_000_000
TRUTH = {"a": (1.0, 5.0, 5.5), "b": (-3.0, 8.0, 8.5), "c": (2.0, 6.0, 5.5)}


def _est(node, k, *, ok=True):
    return M.PositionEstimate(
        node_id=node, t_ns=T0 + k * P, epoch=T0 // P + k, seq=k,
        status="OK" if ok else "TOO_FEW_ANCHORS", position_m=TRUTH[node] if ok else None,
        covariance_m2=None, peb_m=None, z_bound_m=None, floor_index=None, used_anchors=[],
        residuals_m=[], excluded=[], message="", t_input_wall_ns=0, t_pub_wall_ns=0)


def test_loss_notes_say_how_many_how_and_when():
    """20 s at 10 Hz, three nodes: t = 8-12 s every node TOO_FEW_ANCHORS, t = 15-16 s no
    estimate at all, elsewhere one node-epoch in ten of node c missing (never >= 50 % of a
    second). Scored from 2 s: 180 epochs x 3 nodes."""
    sc = Scorer([(n, Static(p)) for n, p in TRUTH.items()], B, T0, period_ns=P,
                end_ns=T0 + 20 * 10**9)
    for k in range(200):
        for n in TRUTH:
            if 150 <= k < 160 or (n == "c" and k % 10 == 3):
                continue
            sc.add(_est(n, k, ok=not 80 <= k < 120))
    notes = loss_notes(sc)
    # without position: every node in [80, 120) except c's 4 missing epochs (83, ..., 113);
    # without estimate: [150, 160) x 3, and c's k % 10 == 3 in [20, 200) (18) except 153
    lost_fix, lost_none = 40 * 3 - 4, 10 * 3 + 18 - 1
    n = lost_fix + lost_none
    assert notes[0].startswith(f"fixes lost: {n} of 540 scored node-epochs ({100 * n / 540:.1f} %)")
    assert f"{lost_none} without an estimate, {lost_fix} with a status without position" in notes[0]
    assert f"TOO_FEW_ANCHORS {lost_fix}" in notes[0]
    assert notes[1] == ("fixes lost mostly at (run time): t = 8-12 s (100 % lost); "
                        "t = 15-16 s (100 % lost)")


def test_loss_notes_empty_when_nothing_lost_and_spread_when_scattered():
    sc = Scorer([(n, Static(p)) for n, p in TRUTH.items()], B, T0, period_ns=P,
                end_ns=T0 + 5 * 10**9)
    for k in range(50):
        for n in TRUTH:
            sc.add(_est(n, k))
    assert loss_notes(sc) == []
    sc.add(_est("a", 30, ok=False))  # the same node-epoch again, now without a position
    assert "spread over the run" in loss_notes(sc)[1]


def _diag(**kw):
    base = dict(t_wall_ns=0, watermark_ns=None, received={}, rejected={"late": 0,
                "unknown_anchor": 7}, gated=0, solved=0, published=0, fixes_by_status={},
                late_ranges=25, pending_epochs=0, live_anchors=["uav1"],
                anchors=[M.AnchorHealth("uav1", True, 1, 1, None, None),
                         M.AnchorHealth("uav2", False, 1, 1, None, 5_500_000_000)],
                latency=M.LatencyStats(count=0, p50_ms=None, p99_ms=None, max_ms=None))
    base.update(kw)
    return M.FusionDiagnostics(**base)


def test_fusion_notes_late_ranges_lost_anchors_rejections():
    notes = fusion_notes(_diag(), t0_wall_ns=1_000_000_000)
    assert notes == [
        "fusion: 25 ranges arrived after their epoch was solved and were not used",
        "fusion: anchor uav2 lost at t = 4.5 s and not back by the end (its liveliness token "
        "is gone)",
        "fusion rejected messages: unknown_anchor 7 (docs/bad_input.md)"]
    assert fusion_notes(_diag(late_ranges=0, rejected={}, anchors=[])) == []
    assert "never reported" in fusion_notes(None)[0]
    # epochs an overloaded fusion dropped unsolved are said apart from bad input
    over = fusion_notes(_diag(late_ranges=0, anchors=[],
                              rejected={"overloaded": 40, "unknown_anchor": 7}))
    assert over[0].startswith("fusion: overloaded: 40 node-epochs dropped unsolved")
    assert over[1] == "fusion rejected messages: unknown_anchor 7 (docs/bad_input.md)"
    # ... and so are those a fusion behind its input superseded by a node's newer epoch
    behind = fusion_notes(_diag(late_ranges=0, anchors=[],
                                rejected={"superseded": 12, "unknown_anchor": 7}))
    assert behind[0].startswith("fusion: behind its input: 12 node-epochs superseded")
    assert behind[1] == "fusion rejected messages: unknown_anchor 7 (docs/bad_input.md)"


def _recording(path, n, split=None):
    k = Keys("s")
    with McapSink(path, split=split) as sink:
        for i in range(n):
            sink.write(k.truth_node("n1"), b'{"t_ns": %d, "seq": %d}' % (i * 10**9, i), i * 10**9)
            sink.flush()


def test_recording_notes_list_every_part_and_the_foreign_file(tmp_path):
    one, split = tmp_path / "one.mcap", tmp_path / "split.mcap"
    _recording(one, 3)
    _recording(split, 6, SplitPolicy(max_bytes=None, max_duration_s=1.5))
    parts = [part_path(split, k) for k in range(5) if part_path(split, k).exists()]
    assert len(parts) >= 2
    _recording(foreign_path(one), 4)
    notes = recording_notes([one, split, tmp_path / "never.mcap"],
                            [foreign_path(r) for r in (one, split)])
    assert notes[0] == f"recording: {one}"
    assert notes[1] == (f"recording: {split} in {len(parts)} parts (split by duration/size): "
                        + ", ".join(map(str, parts)))
    assert notes[2] == f"recording {tmp_path / 'never.mcap'}: not written"
    assert notes[3].startswith("recorder: 4 foreign messages") and str(foreign_path(one)) in notes[3]
    assert len(notes) == 4


def test_foreign_notes():
    assert foreign_notes({}) == []
    note = foreign_notes({"diffpos/s/node/n1/estimate": 3, "diffpos/s/fusion/diagnostics": 1})
    assert note == ["foreign: 4 messages not from this run's fusion were ignored (not counted "
                    "or scored; another process publishes on this bus): "
                    "diffpos/s/node/n1/estimate 3, diffpos/s/fusion/diagnostics 1"]


def test_model_notes_only_when_the_fusion_does_not_model_the_channel():
    """The ideal channel (the paper's one-path model) with any method but D-NLS (the default
    first-arrival fusion, the LLS and IPPA baselines) gets a note naming the method that
    models it; the emulated channel, or D-NLS on the ideal one, none."""
    (note,) = model_notes("ideal", "mnls")
    assert "--method dnls" in note and "default fusion" in note
    for method in ("lls", "ippa"):  # baselines that do not model it either
        (note,) = model_notes("ideal", method)
        assert f"--method {method} does not model" in note
    for channel, method in (("emulator", "mnls"), ("ideal", "dnls"), ("emulator", "dnls"),
                            ("emulator", "lls")):
        assert model_notes(channel, method) == []


def test_end_to_end_latency_from_the_estimates_input_stamps():
    """rx - t_input_wall_ns per estimate (no input stamp: not counted; not JSON: ignored);
    percentiles against numpy's on the same values; the window drops older receipts."""
    e2e = EndToEnd()
    lat_ms = [3.0, 5.0, 7.0, 40.0, 9.0]
    for i, ms in enumerate(lat_ms):
        est = msgspec.structs.replace(_est("a", i), t_input_wall_ns=10**18 + i, t_pub_wall_ns=1)
        e2e.add(M.encode(est), 10**18 + i + round(ms * 1e6))
    e2e.add(M.encode(_est("a", 9)), 10**18 + 10**9)  # t_input_wall_ns 0: no input stamp
    e2e.add(b"not json", 10**18)
    s = e2e.stats_ms()
    assert s["count"] == 5 and s["max"] == 40.0
    assert abs(s["p50"] - 7.0) < 1e-9 and abs(s["p99"] - float(np.percentile(lat_ms, 99))) < 1e-9
    late = e2e.stats_ms(since_wall_ns=10**18 + 4 + 9_000_001)  # only the 40 ms one is newer
    assert late["count"] == 1 and late["max"] == 40.0
    assert latency_notes(s) == [
        "end-to-end latency (anchor publish -> estimate received by emulate, solve included): "
        f"p50 7.0 ms, p99 {s['p99']:.1f} ms, max 40.0 ms over 5 estimates"]
    assert latency_notes(EndToEnd().stats_ms()) == []
    # inputs published since a time (the scorer's skip): by rx - latency, not by rx
    settled = e2e.stats_ms(inputs_since_wall_ns=10**18 + 3)  # inputs 3 and 4: 40 and 9 ms
    assert settled["count"] == 2 and settled["max"] == 40.0 and settled["p50"] == 24.5
    assert latency_notes(s, settled, 2.0)[1] == (
        f"after the first 2 s: p50 24.5 ms, p99 {settled['p99']:.1f} ms, max 40.0 ms over "
        "2 estimates")
    assert len(latency_notes(s, EndToEnd().stats_ms(), 2.0)) == 1


def test_fusion_notes_say_why_ranges_were_late():
    """The diagnostics v2 fields (allowance, lags, release reasons) reach the summary's words."""
    notes = fusion_notes(_diag(late_by_anchor={"uav2": 20, "uav1": 5}, deadline_ns=150_000_000,
                               max_lag_ns=400_000_000, lag_by_anchor={"uav2": 380_000_000},
                               releases={"watermark": 90, "wall_fallback": 10}))
    assert notes[0] == ("fusion: 25 ranges arrived after their epoch was solved and were not "
                        "used (by anchor: uav2 20, uav1 5); lateness allowance in force 150 ms, "
                        "largest allowance 400 ms")
    assert notes[1] == "fusion: anchors lagging behind the others (largest recent lag): uav2 380 ms"
    assert notes[2].startswith("fusion: 10 of 100 epochs were released by the wall-clock fallback")
