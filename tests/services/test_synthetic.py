"""replay.synthetic: both synthetic runs are seeded, and keyed() gives their bus keys."""

from __future__ import annotations

import msgspec
from diffpos_services.recording.topics import parse_topic
from diffpos_services.replay.synthetic import display_run, keyed, synthetic_run
from diffpos_services.wire import messages as M


def test_display_run_is_seeded_and_keyed_like_the_bus():
    b, msgs = display_run(n_anchors=3, n_nodes=2, duration_s=2.0, seed=4)
    _, again = display_run(n_anchors=3, n_nodes=2, duration_s=2.0, seed=4)
    assert [msgspec.json.encode(x) for x in msgs] == [msgspec.json.encode(x) for x in again]
    assert b["n_floors"] == 4
    kinds = {"AnchorState": "anchor_state", "GroundTruth": "truth_node",
             "PositionEstimate": "estimate", "FusionDiagnostics": "diagnostics"}
    items = keyed(msgs, site="s1", latency_ns=5)
    for (rx, key, payload), x in zip(items, msgs, strict=True):
        assert parse_topic(key)[0] == kinds[type(x).__name__]
        assert rx == (getattr(x, "t_ns", None) or x.watermark_ns) + 5
        assert payload == M.encode(x)


def test_synthetic_run_items_are_keyed_like_keyed_would():
    run = synthetic_run(n_anchors=2, n_nodes=2, duration_s=0.3, seed=1)
    dec = {"anchor_state": M.AnchorState, "range": M.RangeMeasurement, "truth_node": M.GroundTruth}
    for items in run.epochs:
        for _rx, key, payload in items:
            msg = M.decoder(dec[parse_topic(key)[0]])(payload)
            assert keyed([msg], site="synth", latency_ns=0)[0][1:] == (key, payload)


def test_recording_only_topics_round_trip_through_keys():
    from diffpos_services.wire.keys import Keys, parse_key, parse_recording_topic

    k = Keys("s1")
    assert parse_recording_topic(k.recorder_liveliness()).kind == "liveliness"
    pk = parse_recording_topic(k.replay_estimate("n7"))
    assert (pk.kind, pk.site, pk.node_id) == ("replay_estimate", "s1", "n7")
    assert parse_key(k.replay_estimate("n7")) is None  # never a bus key
    assert parse_topic(k.anchor_range("a1", "n2")) == ("range", {"site": "s1", "anchor": "a1",
                                                                 "node": "n2"})
    try:
        k.of(object())
    except ValueError as exc:
        assert "object" in str(exc)
    else:  # pragma: no cover
        raise AssertionError("Keys.of accepted a non-message")
