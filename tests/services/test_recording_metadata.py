"""Run metadata is found anywhere in a file and kept in every file diffpos writes; replay says
loudly when it falls back to default settings (issue 15 item 4). ``inspect --validate``
checks messages against diffpos' own schemas, not the file's embedded ones (item 13).

Files with metadata after the chunks are written by the official ``mcap`` writer (as the
standard writer and ``replay --write-mcap`` place it), with and without the summary's
metadata index.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.recording.reader import McapScanner, side_records
from diffpos_services.recording.schemas import SchemaRegistry
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from diffpos_services.wire import messages as M
from mcap.reader import make_reader
from mcap.writer import IndexType, Writer

SCENARIO = b'name = "attached"\n'


@pytest.fixture(scope="module")
def rec(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("meta") / "run.mcap"
    write_synthetic_recording(path, n_anchors=5, n_nodes=2, duration_s=1.5, seed=5,
                              outlier_probability=0.1, flush_every=100)
    return path


def _rewrite_with_late_metadata(src: Path, dst: Path, *, metadata: dict[str, dict[str, str]],
                                index_types: IndexType = IndexType.ALL) -> Path:
    """Every message of ``src`` through the official writer; the metadata and a scenario
    attachment only AFTER all chunks."""
    sc = McapScanner(src)
    msgs = list(sc.messages())
    with open(dst, "wb") as f:
        w = Writer(f, index_types=index_types, chunk_size=4096)
        w.start()
        sids, cids = {}, {}
        for m in msgs:
            if m.channel_id not in cids:
                ch = sc.channels[m.channel_id]
                sch = sc.schemas.get(ch.schema_id)
                if sch is not None and sch.id not in sids:
                    sids[sch.id] = w.register_schema(sch.name, sch.encoding, sch.data)
                cids[m.channel_id] = w.register_channel(
                    ch.topic, ch.message_encoding, sids.get(ch.schema_id, 0), ch.metadata)
            w.add_message(cids[m.channel_id], log_time=m.log_ns, data=m.data,
                          publish_time=m.publish_ns, sequence=m.sequence)
        for name, md in metadata.items():
            w.add_metadata(name, md)
        w.add_attachment(1, 1, "scenario.toml", "application/toml", SCENARIO)
        w.finish()
    return dst


def _recorded_metadata(path: Path) -> dict[str, dict[str, str]]:
    sc = McapScanner(path)
    list(sc.messages())
    return {m.name: dict(m.metadata) for m in sc.metadata}


@pytest.mark.parametrize("index", ["summary", "scan"])
def test_metadata_after_the_chunks_is_used(rec, tmp_path, index):
    meta = _recorded_metadata(rec)
    fc = meta["fusion_config"]
    fc["method"] = json.dumps("lls")  # distinctive: not what defaults would give
    late = _rewrite_with_late_metadata(
        rec, tmp_path / "late.mcap", metadata={"run": meta["run"], "fusion_config": fc},
        index_types=IndexType.ALL if index == "summary" else IndexType.CHUNK)
    side = side_records(late)
    assert side.source == ("summary index" if index == "summary" else "scan")
    assert {m.name for m in side.metadata} == {"run", "fusion_config"}
    assert [a.name for a in side.attachments] == ["scenario.toml"]
    r = replay(late)
    assert r.report["settings_source"] == "metadata fusion_config"
    assert r.report["method"] == "lls" and r.report["settings_warning"] is None
    ref = replay(rec, method="lls")
    assert [M.encode(e) for e in r.estimates] == [M.encode(e) for e in ref.estimates]


def test_defaults_are_announced_loudly(rec, tmp_path, capsys):
    bare = _rewrite_with_late_metadata(rec, tmp_path / "bare.mcap", metadata={})
    rc = cli_main(["replay", str(bare), "--no-files", "--no-progress"])
    cap = capsys.readouterr()
    assert rc == 0
    assert "WARNING" in cap.err and "DEFAULT settings" in cap.err
    assert "WARNING" in cap.out  # and in the printed report
    r = replay(bare)
    assert "DEFAULT settings" in r.report["settings_warning"]
    assert replay(rec).report["settings_warning"] is None


def test_every_written_file_keeps_metadata_and_scenario(rec, tmp_path):
    """replay --write-mcap output (whose own metadata lands after the chunks) replays with the
    recorded settings, not defaults; recover keeps metadata and the attachment too."""
    late = _rewrite_with_late_metadata(rec, tmp_path / "late.mcap",
                                       metadata=_recorded_metadata(rec))
    out = tmp_path / "replayed.mcap"
    first = replay(late, out_mcap=out)
    again = replay(out)
    assert again.report["settings_source"] == "metadata fusion_config"
    assert again.report["settings_warning"] is None
    assert [M.encode(e) for e in again.estimates] == [M.encode(e) for e in first.estimates]
    rec_out = tmp_path / "recovered.mcap"
    assert cli_main(["recover", str(out), "--out", str(rec_out)]) == 0
    for path in (out, rec_out):
        with open(path, "rb") as f:  # the official reader sees them
            reader = make_reader(f)
            names = {m.name for m in reader.iter_metadata()}
            atts = {a.name: a.data for a in reader.iter_attachments()}
        assert {"run", "fusion_config"} <= names, path
        assert atts.get("scenario.toml") == SCENARIO, path


def _crafted(path: Path, payloads: list[bytes], *, schema: bytes) -> Path:
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("diffpos.range.v1", "jsonschema", schema)
        cid = w.register_channel("diffpos/demo/anchor/uav1/range/n01", "json", sid)
        for i, p in enumerate(payloads):
            w.add_message(cid, log_time=i, data=p, publish_time=i, sequence=i)
        w.finish()
    return path


def test_inspect_validate_uses_our_schemas_not_the_embedded_one(rec, tmp_path, capsys):
    good = next(m.data for m in McapScanner(rec).messages() if "/range/" in m.topic)
    doc = json.loads(good)
    bad_type = json.dumps({**doc, "range_m": "far"}).encode()
    bad_tag = json.dumps({**doc, "schema": "evil.v9"}).encode()
    crafted = _crafted(tmp_path / "c.mcap", [good, bad_type, bad_tag], schema=b'{"type":"object"}')
    rc = cli_main(["inspect", str(crafted), "--validate", "--json"])
    v = json.loads(capsys.readouterr().out)["validation"]
    assert rc == 1
    assert v["checked"] == 3 and v["invalid"] == 2
    assert any("range_m" in e or "far" in e for e in v["examples"])
    assert any("evil.v9" in e for e in v["examples"])
    assert v["schema_mismatch"] and v["schema_mismatch"][0]["ours"] == "diffpos.range.v1"
    # the same good message with our schema embedded: valid, no mismatch, exit 0
    ours = SchemaRegistry().by_stem["range"].data
    ok = _crafted(tmp_path / "ok.mcap", [good], schema=ours)
    assert cli_main(["inspect", str(ok), "--validate", "--json"]) == 0
    v = json.loads(capsys.readouterr().out)["validation"]
    assert v["invalid"] == 0 and v["schema_mismatch"] == []
