"""Damaged and foreign recordings (issue 36, item 5): ``recover`` resyncs past a corrupt
chunk length (one corrupted length dropped the remaining 73 % of a file), every reader
reports the damage it passes over (replay passed over a CRC failure silently), and an MCAP
whose diffpos-looking channels are another tool's is refused in one line (it gave
``fixes: 0`` / an .rrd with exit 0).

References: the messages the test itself wrote (counts), the official ``mcap`` reader for
the recovered files, the MCAP record layout (spec) for where to corrupt.
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.recording.errors import ForeignRecordingError
from diffpos_services.recording.reader import JsonDecoderFactory, McapScanner
from diffpos_services.recording.repair import recover
from diffpos_services.recording.writer import McapSink
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys
from mcap.reader import make_reader
from mcap.writer import Writer

K = Keys("t1")
T0 = 1_700_000_000_000_000_000


def _write(path: Path, n_epochs: int = 60) -> int:
    """A recording of ``n_epochs`` x 3 anchor states in many small chunks; returns the count."""
    sink = McapSink(path, chunk_size=1500)
    sink.add_metadata("run", {"scenario": "damage"})
    n = 0
    for e in range(n_epochs):
        t = T0 + e * 100_000_000
        for i, a in enumerate(("a1", "a2", "a3")):
            msg = M.AnchorState(anchor_id=a, t_ns=t, seq=e, position_m=(float(i), -20.0, 10.0),
                                velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.1, 0.1, 0.2),
                                velocity_sigma_m_s=0.05, range_rate_hz=10.0, t_pub_wall_ns=t)
            sink.write(K.anchor_state(a), M.encode(msg), t + 1000)
            n += 1
    sink.close()
    return n


def _chunks(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of every chunk record, walking the records as the spec lays them out."""
    out, off = [], 8
    while off + 9 <= len(data):
        op, ln = struct.unpack_from("<BQ", data, off)
        if op == 0x06:
            out.append((off, ln))
        if op == 0x02:
            break
        off += 9 + ln
    return out


def _official_count(path: Path) -> int:
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[JsonDecoderFactory()])
        return sum(1 for _ in reader.iter_messages(log_time_order=False))


def _corrupt(tmp_path: Path, how: str) -> tuple[Path, int, int]:
    good = tmp_path / "good.mcap"
    n = _write(good)
    data = bytearray(good.read_bytes())
    chunks = _chunks(bytes(data))
    assert len(chunks) >= 20
    off, ln = chunks[len(chunks) // 4]  # a quarter in: 3/4 of the file follows
    if how == "longer":
        struct.pack_into("<Q", data, off + 1, ln + 3000)
    elif how == "shorter":
        struct.pack_into("<Q", data, off + 1, ln - 100)
    elif how == "past_end":
        struct.pack_into("<Q", data, off + 1, 2**40)
    elif how == "opcode":
        data[off] = 0x33
    elif how == "length_and_contents":  # the chunk is lost, nothing else
        struct.pack_into("<Q", data, off + 1, 2**40)
        data[off + 9 + 30] ^= 0xFF
    bad = tmp_path / f"{how}.mcap"
    bad.write_bytes(bytes(data))
    in_chunk = sum(1 for _ in McapScanner(good).iter_batches())  # batches = chunks
    return bad, n, in_chunk


@pytest.mark.parametrize("how", ["longer", "shorter", "past_end"])
def test_recover_reads_a_chunk_by_its_contents_when_its_length_field_is_corrupt(tmp_path, how):
    bad, n, _ = _corrupt(tmp_path, how)
    rep = recover(bad, tmp_path / "fixed.mcap")
    assert rep.messages == n  # every message: the chunk's own records length is right
    assert _official_count(tmp_path / "fixed.mcap") == n
    assert rep.damage.bad_records == 1 and not rep.damage.ok
    assert "length field" in rep.damage.notes[0]


@pytest.mark.parametrize("how", ["opcode", "length_and_contents"])
def test_recover_resyncs_past_an_unreadable_record(tmp_path, how):
    bad, n, _ = _corrupt(tmp_path, how)
    rep = recover(bad, tmp_path / "fixed.mcap")
    lost = n - rep.messages
    assert 0 < lost <= 10  # one chunk of 1500 bytes holds a few states; was 3/4 of the file
    assert _official_count(tmp_path / "fixed.mcap") == rep.messages
    assert rep.damage.skipped_bytes > 0
    assert "resynced at the next readable chunk" in " ".join(rep.damage.notes)


def test_recover_cli_says_what_it_skipped(tmp_path, capsys):
    bad, _, _ = _corrupt(tmp_path, "opcode")
    assert cli_main(["recover", str(bad), "--out", str(tmp_path / "o.mcap")]) == 0
    out = capsys.readouterr().out
    assert "was complete but damaged" in out and "resynced past" in out


def test_every_reader_logs_a_crc_failure_naming_file_and_byte(tmp_path, caplog):
    good = tmp_path / "good.mcap"
    n = _write(good)
    data = bytearray(good.read_bytes())
    off, _ = _chunks(bytes(data))[5]
    crc_at = off + 9 + 24  # record header, then start, end, uncompressed size: the CRC
    struct.pack_into("<I", data, crc_at, struct.unpack_from("<I", data, crc_at)[0] ^ 1)
    bad = tmp_path / "crc.mcap"
    bad.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="diffpos.recording"):
        got = sum(len(b) for b in McapScanner(bad).iter_batches())
    assert 0 < n - got <= 10
    warned = [r.getMessage() for r in caplog.records if r.name == "diffpos.recording"]
    assert warned == [f"{bad}: chunk at byte {off} skipped: chunk CRC mismatch"]


def _foreign(path: Path, encoding: str, schema: tuple[str, str] | None, ours: bool = False):
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(schema[0], schema[1], b"{}") if schema else 0
        cid = w.register_channel(K.anchor_state("uav1"), encoding, sid)
        for i in range(5):
            w.add_message(cid, log_time=T0 + i, data=b'{"x": 1}', publish_time=T0 + i)
        if ours:
            sid = w.register_schema("diffpos.run_control.v1", "jsonschema", b"{}")
            cid = w.register_channel(K.run_control(), "json", sid)
            w.add_message(cid, log_time=T0, data=b'{"schema": "x"}', publish_time=T0)
        w.finish()


@pytest.mark.parametrize(("encoding", "schema", "why"), [
    ("protobuf", ("foo.Bar", "protobuf"), "message encoding 'protobuf'"),
    ("json", None, "no JSON Schema"),
    ("json", ("other.State", "jsonschema"), "schema 'other.State'"),
])
def test_foreign_mcap_with_diffpos_looking_topics_is_refused(tmp_path, capsys, encoding,
                                                            schema, why):
    f = tmp_path / "foreign.mcap"
    _foreign(f, encoding, schema)
    with pytest.raises(ForeignRecordingError, match=why):
        list(McapScanner(f).iter_batches())
    rrd = tmp_path / "x.rrd"
    for verb in (["to-rerun", str(f), "-o", str(rrd)], ["inspect", str(f)]):
        assert cli_main(verb) == 1, verb
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "is not a diffpos recording" in err[0], err
    assert not rrd.exists()


def test_look_alike_channel_in_a_diffpos_file_is_skipped_and_counted(tmp_path, caplog):
    f = tmp_path / "mixed.mcap"
    _foreign(f, "cdr", None, ours=True)
    sc = McapScanner(f)
    with caplog.at_level(logging.WARNING, logger="diffpos.recording"):
        got = [m.topic for b in sc.iter_batches() for m in b]
    assert got == [K.run_control()]
    assert sc.damage.foreign_messages == 5 and not sc.damage.ok
    assert "5 messages on 1 channels that are not diffpos channels" in caplog.text


def test_recover_copies_a_foreign_file_as_it_is(tmp_path):
    f = tmp_path / "foreign.mcap"
    _foreign(f, "protobuf", ("foo.Bar", "protobuf"))
    assert recover(f, tmp_path / "copy.mcap").messages == 5
