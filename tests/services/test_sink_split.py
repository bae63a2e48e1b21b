"""McapSink splits a long recording into complete parts (bounded writer memory, issue 15
"Must show"): every part is readable by the official mcap reader, carries the recording's
metadata and attachments, and together the parts hold every message exactly once."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.writer import McapSink, SplitPolicy, part_path
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from mcap.reader import make_reader

KEYS = [f"diffpos/sp/anchor/uav{a}/range/n{n:02d}" for a in range(3) for n in range(10)]


def _payload(i: int) -> bytes:
    return json.dumps({"t_ns": 10**18 + i, "seq": i // len(KEYS), "range_m": 20.0 + i * 1e-3,
                       "pad": "x" * 120}).encode()


def _official(path: Path) -> tuple[Counter, dict, dict, int]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        got = Counter((ch.topic, m.sequence) for _, ch, m in reader.iter_messages())
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        atts = {a.name: a.data for a in reader.iter_attachments()}
    assert summary is not None and summary.chunk_indexes  # complete and indexed
    return got, meta, atts, summary.statistics.message_count


@pytest.mark.parametrize("policy", [SplitPolicy(max_bytes=40_000),
                                    SplitPolicy(max_duration_s=2.0)], ids=["size", "duration"])
def test_split_parts_are_complete_and_hold_every_message(tmp_path, policy):
    out = tmp_path / "long.mcap"
    sink = McapSink(out, split=policy)
    sink.add_metadata("run", {"site": "sp", "scenario": "unit"})
    sink.add_attachment("scen.toml", b'name = "unit"\n', media_type="application/toml")
    n = 9000
    for i in range(n):  # 30 channels, 100 ms of receive time per round of 30 messages
        sink.write(KEYS[i % len(KEYS)], _payload(i), 10**18 + (i // len(KEYS)) * 100_000_000)
        if i % 300 == 299:
            sink.flush()
    sink.close(final_metadata={"stopped_by": "test"})
    parts = sink.parts
    assert parts[0] == out and len(parts) >= 3
    assert parts[1:] == [part_path(out, k) for k in range(1, len(parts))]
    assert parts[1].name == "long_0001.mcap"
    assert sorted(tmp_path.iterdir()) == sorted(parts)
    total: Counter = Counter()
    for k, p in enumerate(parts):
        got, meta, atts, count = _official(p)
        assert count == sum(got.values()) > 0
        assert meta["run"] == {"site": "sp", "scenario": "unit"}, p
        assert meta["part"]["index"] == str(k) and int(meta["part"]["messages"]) == count
        assert atts == {"scen.toml": b'name = "unit"\n'}, p
        assert ("recorder_stats" in meta) == (k == len(parts) - 1)
        total.update(got)
    want = Counter((KEYS[i % len(KEYS)], i // len(KEYS)) for i in range(n))
    assert total == want  # every message exactly once
    assert sink.stats.written == n and sink.stats.gaps == 0  # sequence tracking spans parts


def test_replay_and_inspect_accept_a_part(tmp_path, capsys):
    """A synthetic recording re-written through a splitting sink: a later part is a
    self-describing recording (settings from its own metadata, no default warning)."""
    src = tmp_path / "src.mcap"
    write_synthetic_recording(src, n_anchors=5, n_nodes=2, duration_s=3.0, seed=2,
                              flush_every=50)
    sc = McapScanner(src)
    msgs = list(sc.messages())
    out = tmp_path / "parts.mcap"
    sink = McapSink(out, split=SplitPolicy(max_duration_s=1.0))
    for md in sc.metadata:
        if md.name in ("run", "fusion_config"):
            sink.add_metadata(md.name, md.metadata)
    for i, m in enumerate(msgs):
        sink.write(m.topic, m.data, m.log_ns)
        if i % 50 == 49:
            sink.flush()
    sink.close()
    assert len(sink.parts) >= 2
    part = sink.parts[1]
    r = replay(part)
    assert r.report["settings_source"] == "metadata fusion_config"
    assert r.report["settings_warning"] is None and r.report["fixes"]["total"] > 0
    assert cli_main(["inspect", str(part)]) == 0
    assert "complete" in capsys.readouterr().out


def test_recorder_cli_refuses_to_overwrite_and_bad_split_options(tmp_path, capsys):
    old = tmp_path / "old.mcap"
    old.write_bytes(b"precious")
    rc = cli_main(["recorder", "--out", str(old), "--connect", "tcp/127.0.0.1:1",
                   "--connect-timeout-ms", "1"])
    assert rc == 2 and "already exists" in capsys.readouterr().err
    assert old.read_bytes() == b"precious"
    rc = cli_main(["recorder", "--out", str(tmp_path / "new.mcap"), "--split-size", "-1",
                   "--connect", "tcp/127.0.0.1:1", "--connect-timeout-ms", "1"])
    assert rc == 2 and "--split-size" in capsys.readouterr().err
    assert not (tmp_path / "new.mcap").exists()
