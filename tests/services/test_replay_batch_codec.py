"""The replay's batch decoding and encoding (issue 37 item 2: no Python call per message where
a batch does): the recorded truth and live estimates decoded a batch at a time
(``report_stream.decode_lines``, ``Recorded.flush``), the written replay estimates encoded a
batch at a time (``wire.messages.encode_many``).

References: the per-message decoder / encoder on the real recording ``recordings/sample.mcap``
(every payload), and ``Recorded.take_one`` (one message at a time, as before) on the same
messages plus hostile ones (a payload that is two JSON lines, a pretty-printed one, another
message's schema, a node that differs from the topic's, malformed JSON)."""

from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np
import pytest
from diffpos_services.recording.reader import McapScanner, RawMessage
from diffpos_services.recording.topics import parse_topic
from diffpos_services.replay.report_stream import (
    Recorded,
    SlimEstimate,
    SlimTruth,
    decode_lines,
)
from diffpos_services.replay.run import replay
from diffpos_services.wire import messages as M

SAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "sample.mcap"


@pytest.fixture(scope="module")
def recorded() -> list[tuple[str, RawMessage, str | None]]:
    """Every truth sample and live estimate of the sample recording, in file order."""
    out = []
    for batch in McapScanner(SAMPLE).iter_batches():
        for m in batch:
            kind, fields = parse_topic(m.topic)
            if kind in ("truth_node", "estimate"):
                out.append((kind, m, fields.get("node")))
    assert sum(k == "estimate" for k, _, _ in out) > 500
    assert sum(k == "truth_node" for k, _, _ in out) > 500
    return out


@pytest.mark.parametrize(("kind", "struct"), [("estimate", SlimEstimate),
                                              ("truth_node", SlimTruth)])
def test_decode_lines_is_the_per_message_decode_on_a_real_recording(recorded, kind, struct):
    payloads = [m.data for k, m, _ in recorded if k == kind]
    dec = msgspec.json.Decoder(struct)
    got = decode_lines(dec, payloads)
    assert got is not None
    assert got == [dec.decode(p) for p in payloads]
    for k in (1, 7, 64):  # any batch size
        assert decode_lines(dec, payloads[:k]) == [dec.decode(p) for p in payloads[:k]]


def test_decode_lines_gives_up_where_lines_are_not_the_payloads(recorded):
    dec = msgspec.json.Decoder(SlimEstimate)
    good = [m.data for k, m, _ in recorded if k == "estimate"][:3]
    two = good[0] + b"\n" + good[1]  # two messages in one payload: not two lines
    pretty = msgspec.json.format(good[2], indent=2)  # valid alone, but several lines
    assert dec.decode(pretty) == dec.decode(good[2])
    for bad in ([two, good[2]], [good[0], pretty], [good[0], b""], [good[0], b"{"],
                [b"[1]", good[1]]):
        assert decode_lines(dec, bad) is None


def _hostile(recorded) -> list[tuple[str, RawMessage, str | None]]:
    """The recording's messages with hostile ones in between."""
    est = next(m for k, m, _ in recorded if k == "estimate")
    node = next(n for k, _, n in recorded if k == "estimate")
    truth = next(m for k, m, _ in recorded if k == "truth_node")
    tnode = next(n for k, _, n in recorded if k == "truth_node")
    odd = [
        ("estimate", msgspec.structs.replace(est, data=est.data + b"\n" + est.data), node),
        ("estimate", msgspec.structs.replace(est, data=msgspec.json.format(est.data, indent=1)), node),
        ("estimate", msgspec.structs.replace(est, data=truth.data), node),  # another schema
        ("estimate", est, "n_other"),  # the node differs from the topic's
        ("truth_node", msgspec.structs.replace(truth, data=b"{nope"), tnode),
        ("truth_node", msgspec.structs.replace(truth, data=est.data), tnode),
        ("truth_node", truth, "n_other"),
        ("truth_node", msgspec.structs.replace(truth, data=msgspec.json.format(truth.data, indent=1)), tnode),
    ]
    out = list(recorded)
    for i, o in enumerate(odd):
        out.insert(37 * (i + 1), o)
    return out


def _state(r: Recorded) -> dict:
    r.advance(r.t_last or 0, final=True)
    live = r.live
    acc, _ = live.accuracy()
    return {
        "bad": dict(r.bad_payloads),
        "truth": {n: [c.tolist() for c in r.truth.columns(n)] for n in sorted(r.truth.t)},
        "period": r.truth.period, "samples": r.truth.samples,
        "total": live.total, "status": dict(live.by_status), "used": dict(live.used),
        "excluded": {a: dict(c) for a, c in live.excluded.items()},
        "no_track": dict(live.no_track), "positioned": dict(live.positioned),
        "accuracy": acc, "node_epochs": live.node_epochs(), "compare": r.compare.result(),
    }


def test_a_batch_takes_what_one_message_at_a_time_takes(recorded):
    msgs = _hostile(recorded)
    kw = dict(max_truth_gap_ns=500_000_000, keep_estimates=False, window_ns=30_000_000_000)
    by_batch, by_one = Recorded(("range_batch",), **kw), Recorded(("range_batch",), **kw)
    for i, (kind, m, node) in enumerate(msgs):
        by_batch.take(kind, m, node)
        by_one.take_one(kind, m.data, node, m.log_ns)
        by_batch.t_last = by_one.t_last = m.log_ns
        if i % 500 == 499:  # a flush now and then, as the feed does after each chunk
            by_batch.flush()
    assert not by_one._pending
    a, b = _state(by_batch), _state(by_one)
    assert a["bad"] == {"estimate": 3, "truth_node": 3}  # the pretty ones are good
    assert a == b


def test_encode_many_is_encode_of_each(recorded):
    dec = M.estimate_decoder()
    msgs = [dec(m.data) for k, m, _ in recorded if k == "estimate"]
    msgs.append(msgspec.structs.replace(msgs[0], message="two\nlines \u00e9 \"quoted\""))
    assert M.encode_many(msgs) == [M.encode(e) for e in msgs]
    assert M.encode_many(msgs[:1]) == [M.encode(msgs[0])]
    assert M.encode_many([]) == []


def test_a_written_replay_holds_its_estimates_encoded_one_by_one(tmp_path):
    out = tmp_path / "replayed.mcap"
    res = replay(SAMPLE, out_mcap=out, keep_estimates=True, copy_input=False)
    written = [m.data for b in McapScanner(out).iter_batches() for m in b
               if "/replay/" in m.topic]
    assert len(written) == len(res.estimates) > 500
    assert written == [M.encode(e) for e in res.estimates]
    assert np.isfinite([e.t_ns for e in res.estimates]).all()
