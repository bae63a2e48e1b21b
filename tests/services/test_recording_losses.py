"""Every loss counted (issue 36, item 3): messages missing by sequence number across a
recording's split parts and restart files (a recorder restart lost seq 687-756 of every
anchor and each part said ``gaps: 0``); no recorder restart onto a full disk; a failed
in-place recovery is said.

References: the sequence numbers the test itself left out.
"""

from __future__ import annotations

import errno
import logging
from pathlib import Path

import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.emulate import supervise
from diffpos_services.emulate.supervise import (
    NotRestarted,
    Supervisor,
    disk_full,
    recover_in_place,
)
from diffpos_services.recording.summary import set_losses, summarize
from diffpos_services.recording.writer import McapSink, SplitPolicy, recording_set, restart_path
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

K = Keys("t1")
T0 = 1_700_000_000_000_000_000
ANCHORS = ("a1", "a2", "a3")


def _write(path: Path, seqs, split: SplitPolicy | None = None) -> None:
    sink = McapSink(path, split=split, chunk_size=4096)
    for s in seqs:
        t = T0 + s * 100_000_000
        for a in ANCHORS:
            msg = M.AnchorState(anchor_id=a, t_ns=t, seq=s, position_m=(0.0, -20.0, 10.0),
                                velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.1, 0.1, 0.2),
                                velocity_sigma_m_s=0.05, range_rate_hz=10.0, t_pub_wall_ns=t)
            sink.write(K.anchor_state(a), M.encode(msg), t + 1000)
        sink.flush()
    sink.close()


def test_hole_between_a_recording_and_its_restart_is_counted(tmp_path, capsys):
    first = tmp_path / "run.mcap"
    _write(first, range(0, 687), split=SplitPolicy(max_duration_s=20.0))
    _write(restart_path(first, 1), range(757, 900))
    files = recording_set(first)
    assert len(files) >= 5 and files[-1] == tmp_path / "run-restart1.mcap"
    assert all(summarize(f).gaps == {} for f in files)  # each file alone: no gap
    got = set_losses(first)
    assert got.missing == 70 * len(ANCHORS)
    assert got.by_stream == {f"diffpos/t1/anchor/{a}/**": 70 for a in ANCHORS}
    assert sorted(got.holes) == sorted((f"diffpos/t1/anchor/{a}/**", 687, 756) for a in ANCHORS)
    assert "210 messages missing by sequence number across its" in got.line()
    assert cli_main(["inspect", str(first)]) == 0
    out = capsys.readouterr().out
    assert f"across the recording's {len(files)} files (split parts, restarts): 210 missing" in out


def test_recording_without_loss_says_zero(tmp_path):
    first = tmp_path / "run.mcap"
    _write(first, range(50))
    _write(restart_path(first, 1), range(50, 60))
    got = set_losses(first)
    assert got.missing == 0 and len(got.files) == 2


def test_disk_full_is_named_and_the_recorder_not_restarted(tmp_path, monkeypatch):
    class _Usage:
        free = 1000

    monkeypatch.setattr(supervise.shutil, "disk_usage", lambda d: _Usage())
    assert disk_full(tmp_path / "run.mcap") == (
        f"disk full: 1000 bytes free on {tmp_path} (No space left on device)")

    class _Dead:
        def poll(self):
            return 1

    def restart(name, n):
        raise NotRestarted(disk_full(tmp_path / "run.mcap"))

    sup = Supervisor(lambda: [("recorder", _Dead())], restart, logging.getLogger("t"))
    sup.check()
    (fault,) = sup.faults
    assert fault.restarted_s is None and sup.restarts == {}
    assert fault.note.startswith("not restarted: disk full: 1000 bytes free")


def test_failed_in_place_recovery_is_said(tmp_path, monkeypatch):
    first = tmp_path / "run.mcap"
    _write(first, range(20))
    data = first.read_bytes()
    first.write_bytes(data[: len(data) * 2 // 3])  # killed: no footer

    def no_room(src, dst, **kw):
        Path(dst).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(supervise, "recover", no_room)
    note = recover_in_place(first)
    assert note.startswith(f"{first}: RECOVERY FAILED (disk full): No space left on device; "
                           "kept as it is, truncated")
    assert first.read_bytes() == data[: len(data) * 2 // 3]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]  # no partial left


@pytest.mark.parametrize("free", [MIN := supervise.MIN_FREE_BYTES, MIN * 10])
def test_enough_room_is_not_full(tmp_path, monkeypatch, free):
    monkeypatch.setattr(supervise.shutil, "disk_usage", lambda d: type("U", (), {"free": free}))
    assert disk_full(tmp_path / "x.mcap") is None
