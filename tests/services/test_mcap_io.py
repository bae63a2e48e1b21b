"""MCAP layer without Zenoh: sink -> file -> official mcap reader, damage, recover, inspect.

References are independent of the code under test: the official ``mcap`` reader
(``make_reader``) for what a valid file contains, ``jsonschema`` for message validity, and the
list of what the test itself wrote for counts, order and sequence gaps.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.reader import JsonDecoderFactory, McapScanner
from diffpos_services.recording.repair import recover
from diffpos_services.recording.schemas import SchemaRegistry
from diffpos_services.recording.summary import summarize
from diffpos_services.recording.writer import McapSink
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys
from mcap.reader import make_reader
from mcap.writer import Writer

SITE = "t1"
K = Keys(SITE)


def _sample_stream(n_epochs: int = 30, *, anchors=("a1", "a2", "a3"), nodes=("n1", "n2"),
                   seed: int = 0) -> list[tuple[str, bytes, int]]:
    """(key, payload, receive_ns) of a small but complete run, built with the real structs.

    Sequence numbers as the services number them: one counter per anchor over its state and
    all its ranges, one counter over all estimates (the fusion's).
    """
    rng = np.random.default_rng(seed)
    out: list[tuple[str, bytes, int]] = []
    seq: dict[str, int] = {}
    t0 = 1_700_000_000_000_000_000

    def put(key: str, msg, rx: int) -> None:
        out.append((key, M.encode(msg), rx))

    def nxt(key: str) -> int:
        seq[key] = seq.get(key, -1) + 1
        return seq[key]

    for e in range(n_epochs):
        t = t0 + e * 100_000_000
        for a in anchors:
            key = K.anchor_state(a)
            put(key, M.AnchorState(anchor_id=a, t_ns=t, seq=nxt(a),
                                   position_m=(float(rng.normal()), -20.0, 10.0),
                                   velocity_m_s=(1.0, 0.0, 0.0),
                                   position_sigma_m=(0.1, 0.1, 0.2), velocity_sigma_m_s=0.05,
                                   range_rate_hz=10.0, t_pub_wall_ns=t + 1000), t + 2000)
            for n in nodes:
                key = K.anchor_range(a, n)
                r = None if rng.random() < 0.1 else float(30 + rng.normal())
                put(key, M.RangeMeasurement(anchor_id=a, node_id=n, t_ns=t + 5, seq=nxt(a),
                                            range_m=r, sigma_m=0.3, snr_db=12.5,
                                            t_pub_wall_ns=t + 3000), t + 4000)
        for n in nodes:
            key = K.truth_node(n)
            put(key, M.GroundTruth(entity="node", id=n, t_ns=t, position_m=(1.0, 2.0, 3.0),
                                   velocity_m_s=(0.0, 0.0, 0.0), floor_index=0), t + 5000)
            key = K.node_estimate(n)
            put(key, M.PositionEstimate(
                node_id=n, t_ns=t + 5, epoch=e, seq=nxt("estimates"), status="OK",
                position_m=(1.1, 2.0, 3.0), covariance_m2=((1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0)),
                peb_m=0.5, z_bound_m=0.3, floor_index=0, used_anchors=list(anchors),
                residuals_m=[0.1] * len(anchors), excluded=[], message="",
                t_input_wall_ns=t + 3000, t_pub_wall_ns=t + 9000), t + 9500)
    return out


def _read_official(path: Path):
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[JsonDecoderFactory()])
        summary = reader.get_summary()
        msgs = [(ch.topic, sch, m, obj) for sch, ch, m, obj in reader.iter_decoded_messages(
            log_time_order=False)]
        metadata = {md.name: dict(md.metadata) for md in reader.iter_metadata()}
        attachments = {a.name: a.data for a in reader.iter_attachments()}
    return summary, msgs, metadata, attachments


def test_round_trip_every_message_valid_and_stamped(tmp_path):
    stream = _sample_stream()
    path = tmp_path / "rt.mcap"
    with McapSink(path) as sink:
        sink.add_metadata("run", {"scenario": "unit", "n": 3})
        sink.add_attachment("scenario.toml", b"[x]\ny = 1\n", media_type="application/toml")
        for i, (key, payload, rx) in enumerate(stream):
            sink.write(key, payload, rx)
            if i % 50 == 49:
                sink.flush()
        sink.write_liveliness(SITE, K.alive_anchor("a1"), True, stream[0][2])
        sink.write_liveliness(SITE, K.alive_anchor("a1"), False, stream[-1][2])
    assert sink.stats.received == sink.stats.written == len(stream)
    assert sink.stats.gaps == 0 and sink.stats.out_of_order == 0

    summary, msgs, metadata, attachments = _read_official(path)
    assert summary.statistics.message_count == len(stream) + 2
    # one channel per key expression (+ the liveliness channel)
    assert {ch.topic for ch in summary.channels.values()} == {k for k, _, _ in stream} | {
        f"{K.root}/recorder/liveliness"}
    for ch in summary.channels.values():
        assert ch.message_encoding == "json"
        assert summary.schemas[ch.schema_id].encoding == "jsonschema"
    # file order == write order; every field as written; every message valid
    data_msgs = [x for x in msgs if not x[0].endswith("/recorder/liveliness")]
    assert len(data_msgs) == len(stream)
    validators = {}
    for (key, payload, rx), (topic, sch, m, obj) in zip(stream, data_msgs, strict=True):
        assert topic == key and m.data == payload and m.log_time == rx
        doc = json.loads(payload)
        assert m.publish_time == doc.get("t_ns", rx)
        assert m.sequence == doc.get("seq", 0)
        v = validators.setdefault(sch.id, jsonschema.Draft202012Validator(json.loads(sch.data)))
        v.validate(obj)
    live = [obj for topic, _, _, obj in msgs if topic.endswith("/recorder/liveliness")]
    assert [(e["role"], e["id"], e["alive"]) for e in live] == [("anchor", "a1", True),
                                                                ("anchor", "a1", False)]
    assert json.loads(metadata["run"]["n"]) == 3
    assert json.loads(metadata["recorder_stats"]["stats"])["written"] == len(stream)
    assert attachments["scenario.toml"] == b"[x]\ny = 1\n"


def test_scanner_matches_official_reader(tmp_path):
    stream = _sample_stream(n_epochs=20)
    path = tmp_path / "s.mcap"
    with McapSink(path, chunk_size=4096) as sink:  # many chunks
        for key, payload, rx in stream:
            sink.write(key, payload, rx)
    _, msgs, _, _ = _read_official(path)
    sc = McapScanner(path)
    mine = [(m.topic, m.log_ns, m.publish_ns, m.sequence, m.data) for m in sc.messages()]
    ref = [(t, m.log_time, m.publish_time, m.sequence, m.data) for t, _, m, _ in msgs]
    assert mine == ref
    assert sc.complete and sc.damage.ok
    assert sc.statistics.message_count == len(stream)


def test_sequence_gaps_are_counted(tmp_path):
    stream = _sample_stream(n_epochs=40)
    rng = np.random.default_rng(3)
    drop = set(rng.choice(len(stream), size=25, replace=False).tolist())
    kept = [x for i, x in enumerate(stream) if i not in drop]
    # reference: per publisher (anchor key / the fusion), the holes between consecutive kept
    # sequence numbers
    last: dict[str, int] = {}
    expected = 0
    for key, payload, _ in kept:
        s = json.loads(payload).get("seq")
        if s is None:
            continue
        stream = "estimates" if key.endswith("/estimate") else key.split("/")[3]  # anchor id
        if stream in last:
            expected += s - last[stream] - 1
        last[stream] = s
    sink = McapSink(io.BytesIO())
    for key, payload, rx in kept:
        sink.write(key, payload, rx)
    assert expected > 0
    assert sink.stats.gaps == expected
    assert sink.stats.out_of_order == 0
    assert sum(b - a + 1 for _, a, b in sink.stats.gap_list) == expected
    # the file-level summary finds the same holes
    path = tmp_path / "gaps.mcap"
    with McapSink(path) as s2:
        for key, payload, rx in kept:
            s2.write(key, payload, rx)
    summ = summarize(path)
    assert sum(summ.gaps.values()) == expected and not summ.out_of_order


def test_undecodable_and_unknown_keys_are_still_recorded(tmp_path):
    path = tmp_path / "u.mcap"
    with McapSink(path) as sink:
        sink.write("diffpos/t1/something/else", b'{"t_ns": 5, "seq": 1}', 10)
        sink.write(K.anchor_state("a1"), b"\x00not json", 11)
        sink.write(K.anchor_state("a1"), b'{"t_ns": "late", "seq": -3}', 12)
    assert sink.stats.written == 3
    assert sink.stats.unknown_schema == 1
    assert sink.stats.undecodable == 2
    _, msgs, _, _ = _read_official_raw(path)
    assert [(t, m.log_time, m.publish_time) for t, m in msgs] == [
        ("diffpos/t1/something/else", 10, 5),
        (K.anchor_state("a1"), 11, 11),  # no measurement time: publish_time = receive time
        (K.anchor_state("a1"), 12, 12),
    ]


def _read_official_raw(path: Path):
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        msgs = [(ch.topic, m) for _, ch, m in reader.iter_messages(log_time_order=False)]
    return summary, msgs, None, None


def test_recover_every_cut_point_keeps_exactly_the_flushed_prefix(tmp_path):
    """Truncate a recording at many offsets: the recovered file is valid and holds a prefix of
    the written messages, at least everything flushed before the cut."""
    stream = _sample_stream(n_epochs=12)
    buf = io.BytesIO()
    sink = McapSink(buf)
    sink.add_metadata("run", {"scenario": "cut"})
    boundaries = [(buf.tell(), 0)]  # (file size after flush, messages flushed)
    for i, (key, payload, rx) in enumerate(stream):
        sink.write(key, payload, rx)
        if i % 17 == 16:
            sink.flush()
            boundaries.append((buf.tell(), i + 1))
    sink.flush()
    boundaries.append((buf.tell(), len(stream)))
    data = buf.getvalue()  # no footer yet: what a SIGKILL leaves behind
    cuts = sorted({*np.linspace(0, len(data), 40).astype(int).tolist(),
                   *(b for b, _ in boundaries), *(b - 1 for b, _ in boundaries if b > 0)})
    for cut in cuts:
        if cut < 8:
            continue  # not even the magic: refused (tested below)
        src = tmp_path / "cut.mcap"
        src.write_bytes(data[:cut])
        dst = tmp_path / "cut.recovered.mcap"
        rep = recover(src, dst)
        _, msgs, _, _ = _read_official_raw(dst)  # the official reader opens it
        got = [(t, m.log_time, m.data) for t, m in msgs]
        want = [(k, rx, p) for k, p, rx in stream]
        assert got == want[:len(got)], f"cut {cut}: not a prefix"
        floor = max((n for b, n in boundaries if b <= cut), default=0)
        assert len(got) >= floor, f"cut {cut}: lost flushed messages"
        assert rep.messages == len(got)
        assert rep.damage.truncated or cut == len(data)


def test_recover_keeps_metadata_attachments_and_skips_corrupt_chunk(tmp_path):
    stream = _sample_stream(n_epochs=10)
    buf = io.BytesIO()
    sink = McapSink(buf, chunk_size=2048)
    sink.add_metadata("run", {"scenario": "corrupt"})
    sink.add_attachment("cfg.json", b"{}", media_type="application/json")
    for key, payload, rx in stream:
        sink.write(key, payload, rx)
    sink.close()
    data = bytearray(buf.getvalue())
    good = tmp_path / "good.mcap"
    good.write_bytes(bytes(data))
    sc = McapScanner(good)
    n_total = sum(1 for _ in sc.messages())
    # flip bytes inside the compressed data of one chunk in the middle
    mid = len(data) // 2
    data[mid:mid + 16] = bytes(b ^ 0xFF for b in data[mid:mid + 16])
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    sc = McapScanner(bad)
    n_bad = sum(1 for _ in sc.messages())
    assert sc.damage.bad_chunks + sc.damage.bad_records >= 1
    assert 0 < n_bad < n_total
    rep = recover(bad, tmp_path / "fixed.mcap")
    _summary, msgs, metadata, attachments = _read_official(tmp_path / "fixed.mcap")
    assert len(msgs) == rep.messages == n_bad
    assert "run" in metadata and attachments["cfg.json"] == b"{}"


def test_foreign_and_broken_inputs_give_clear_errors(tmp_path, capsys):
    # not MCAP at all
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello, not an mcap file\n")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        McapScanner(junk)
    assert cli_main(["inspect", str(junk)]) == 1  # foreign input: exit 1, as a foreign MCAP
    err = capsys.readouterr().err
    assert "not an MCAP file" in err and "Traceback" not in err
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    for verb in (["to-rerun", str(empty), "-o", str(tmp_path / "e.rrd")],
                 ["replay", str(empty), "--no-files"], ["inspect", str(empty)]):
        assert cli_main(verb) == 1, verb
        assert "is empty (0 bytes)" in capsys.readouterr().err
    assert not (tmp_path / "e.rrd").exists()
    assert cli_main(["recover", str(tmp_path / "missing.mcap")]) == 2
    assert "does not exist" in capsys.readouterr().err
    # a foreign MCAP: protobuf channel with an unknown topic, no diffpos keys at all
    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("foo.Bar", "protobuf", b"\x00\x01")
        cid = w.register_channel("/camera/image", "protobuf", sid)
        for i in range(5):
            w.add_message(cid, log_time=i, data=b"\x08\x01", publish_time=i)
        w.finish()
    s = summarize(foreign)
    assert s.messages == 5 and [c.kind for c in s.channels] == ["unknown"]
    assert s.anchors == [] and s.nodes == []
    assert cli_main(["inspect", str(foreign), "--validate"]) == 0
    out = capsys.readouterr().out
    assert "unknown" in out and "0 checked" in out


def test_schema_registry_maps_every_bus_key():
    reg = SchemaRegistry()
    expect = {
        K.anchor_state("a"): "diffpos.anchor_state.v1",
        K.anchor_range("a", "n"): "diffpos.range.v1",
        K.node_estimate("n"): "diffpos.estimate.v2",  # the newest version of the key's schema
        K.fusion_diagnostics(): "diffpos.fusion_diagnostics.v2",
        K.truth_node("n"): "diffpos.truth.v1",
        K.truth_anchor("a"): "diffpos.truth.v1",
        K.run_control(): "diffpos.run_control.v1",
    }
    for key, name in expect.items():
        entry = reg.for_key(key)
        assert entry is not None and entry.name == name, key
        # the registered document is the checked-in schema file
        assert json.loads(entry.data) == json.loads(
            (Path(__file__).resolve().parents[2] / "schemas" / entry.source).read_text())
    assert reg.for_key("diffpos/t1/not/a/key") is None


def test_inspect_reports_counts_anchors_nodes(tmp_path, capsys):
    stream = _sample_stream(n_epochs=5)
    path = tmp_path / "i.mcap"
    with McapSink(path) as sink:
        for key, payload, rx in stream:
            sink.write(key, payload, rx)
    assert cli_main(["inspect", str(path), "--json", "--validate"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["messages"] == len(stream) and d["complete"] is True
    assert d["anchors"] == ["a1", "a2", "a3"] and d["nodes"] == ["n1", "n2"]
    assert d["validation"]["checked"] == len(stream) and d["validation"]["invalid"] == 0
    by_kind = {}
    for c in d["channels"]:
        by_kind[c["kind"]] = by_kind.get(c["kind"], 0) + c["count"]
    assert by_kind == {"anchor_state": 15, "range": 30, "truth_node": 10, "estimate": 10}


def test_schema_registry_without_schema_files_generates_the_same_documents(monkeypatch):
    import diffpos_services.recording.schemas as mi

    from_files = SchemaRegistry()
    monkeypatch.setattr(mi, "default_schema_dir", lambda: Path("/nonexistent/schemas"))
    generated = SchemaRegistry()
    assert {e.source for e in generated.by_stem.values()} == {"generated", "builtin"}
    for stem, entry in generated.by_stem.items():
        assert from_files.by_stem[stem].data == entry.data, stem


def test_wrong_schema_payloads_are_counted_not_fatal(tmp_path, capsys):
    path = tmp_path / "w.mcap"
    good = _sample_stream(n_epochs=2)
    with McapSink(path) as sink:
        for key, payload, rx in good:
            sink.write(key, payload, rx)
        # valid JSON, wrong shape for the range schema (missing fields, wrong type)
        sink.write(K.anchor_range("a1", "n1"), b'{"schema": "diffpos.range.v1", "range_m": "far"}', 5)
    assert cli_main(["inspect", str(path), "--validate"]) == 1
    out = capsys.readouterr()
    assert "1 invalid" in out.out and "Traceback" not in out.err
    assert f"{K.anchor_range('a1', 'n1')} seq 0" in out.out  # names the message


def test_channel_schema_is_the_version_the_messages_carry(tmp_path):
    """Estimates exist as v1 (dnls/lls/ippa) and v2 (mnls): each channel is registered with the
    schema version its messages are tagged with, so Foxglove decodes them with the right one
    (the newest version only for untagged payloads)."""
    reg = SchemaRegistry()
    assert reg.for_key(K.node_estimate("n")).name == "diffpos.estimate.v2"
    path = tmp_path / "versions.mcap"
    with McapSink(path) as sink:
        sink.write(K.node_estimate("n1"), b'{"schema":"diffpos.estimate.v1","t_ns":1,"seq":1}', 1)
        sink.write(K.node_estimate("n2"), b'{"schema":"diffpos.estimate.v2","t_ns":1,"seq":1}', 1)
        sink.write(K.node_estimate("n3"), b'{"t_ns":1,"seq":1}', 1)
        sink.write(K.node_estimate("n4"), b'{"schema":"evil.v1","t_ns":1,"seq":1}', 1)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    names = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
    assert names == {K.node_estimate("n1"): "diffpos.estimate.v1",
                     K.node_estimate("n2"): "diffpos.estimate.v2",
                     K.node_estimate("n3"): "diffpos.estimate.v2",
                     K.node_estimate("n4"): "diffpos.estimate.v2"}
