"""No command writes over its input; every output is checked before any work and written
atomically; bad outputs give one clear line and exit code 2 (issue 15 items 1 and 12, and
the to-rerun / inspect parts of item 13).

Real MCAP files (our writer, and the official ``mcap`` writer for foreign files), real CLI
runs through ``diffpos_services.cli.main`` (the one place that maps errors to exit codes).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.recording.reader import McapScanner
from diffpos_services.replay.synthetic import write_synthetic_recording
from mcap.writer import Writer


@pytest.fixture(scope="module")
def rec(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("noover") / "run.mcap"
    write_synthetic_recording(path, n_anchors=5, n_nodes=2, duration_s=1.0, seed=3,
                              flush_every=100)
    return path


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _copy(rec: Path, tmp_path: Path, name: str = "in.mcap") -> Path:
    dst = tmp_path / name
    dst.write_bytes(rec.read_bytes())
    return dst


def _leftovers(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if ".partial" in p.name)


def _foreign(path: Path) -> Path:
    """A valid MCAP from the official writer with no diffpos channel."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel("/imu", "cdr", 0)
        for i in range(5):
            w.add_message(cid, log_time=i, data=b"\x00\x01", publish_time=i)
        w.finish()
    return path


@pytest.mark.parametrize("alias", ["same", "dot", "symlink", "hardlink"])
def test_replay_write_mcap_onto_its_input_is_refused(rec, tmp_path, capsys, alias):
    src = _copy(rec, tmp_path)
    before = _digest(src)
    n_before = sum(1 for _ in McapScanner(src).messages())
    target = {"same": src, "dot": tmp_path / "." / "in.mcap"}.get(alias)
    if alias == "symlink":
        target = tmp_path / "link.mcap"
        target.symlink_to(src)
    elif alias == "hardlink":
        target = tmp_path / "hard.mcap"
        os.link(src, target)
    rc = cli_main(["replay", str(src), "--no-files", "--no-progress", "--write-mcap", str(target)])
    err = capsys.readouterr().err
    assert rc == 2
    assert "--write-mcap" in err and "input" in err and "Traceback" not in err
    assert _digest(src) == before
    assert sum(1 for _ in McapScanner(src).messages()) == n_before
    assert _leftovers(tmp_path) == []


def test_recover_and_to_rerun_onto_their_input_are_refused(rec, tmp_path, capsys):
    src = _copy(rec, tmp_path)
    before = _digest(src)
    assert cli_main(["recover", str(src), "--out", str(src)]) == 2
    assert "input" in capsys.readouterr().err
    # to-rerun wants an .rrd name: a hard link of the input with that name is still the input
    alias = tmp_path / "in.rrd"
    os.link(src, alias)
    assert cli_main(["to-rerun", str(src), "-o", str(alias)]) == 2
    assert "input" in capsys.readouterr().err
    assert _digest(src) == before
    assert _leftovers(tmp_path) == []


def test_replay_bad_outputs_fail_before_any_work(rec, tmp_path, capsys):
    src = _copy(rec, tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = {
        "--out at an existing file": ["--out", str(afile)],
        "--out under a file": ["--out", str(afile / "sub")],
        "--rrd at a directory": ["--no-files", "--rrd", str(tmp_path)],
        "--rrd under a file": ["--no-files", "--rrd", str(afile / "x.rrd")],
        "--write-mcap at a directory": ["--no-files", "--write-mcap", str(tmp_path)],
        "--write-mcap under a file": ["--no-files", "--write-mcap", str(afile / "x.mcap")],
    }
    for what, opts in cases.items():
        rc = cli_main(["replay", str(src), "--no-progress", *opts])
        cap = capsys.readouterr()
        assert rc == 2, what
        assert "diffpos replay: error:" in cap.err and "Traceback" not in cap.err, what
        assert cap.out == "", what  # refused before the replay ran (no report printed)
    assert afile.read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "in.mcap"]


def test_to_rerun_unwritable_output_and_foreign_input(rec, tmp_path, capsys):
    src = _copy(rec, tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert cli_main(["to-rerun", str(src), "-o", str(afile / "out.rrd")]) == 2
    err = capsys.readouterr().err
    assert "not a directory" in err and "Traceback" not in err
    assert cli_main(["to-rerun", str(src), "-o", str(tmp_path)]) == 2  # a directory
    capsys.readouterr()
    # a valid MCAP with no diffpos channel: exit 1, a clear line, and NO .rrd written
    foreign = _foreign(tmp_path / "foreign.mcap")
    rc = cli_main(["to-rerun", str(foreign), "-o", str(tmp_path / "foreign.rrd")])
    err = capsys.readouterr().err
    assert rc == 1
    assert "no diffpos channels" in err and "/imu" in err
    assert not (tmp_path / "foreign.rrd").exists()
    assert _leftovers(tmp_path) == []


def test_failed_replay_leaves_no_output_file(tmp_path, capsys):
    """The output is renamed into place only when complete: a replay that fails half-way (no
    fusion input) leaves neither the final name nor a temporary file."""
    foreign = _foreign(tmp_path / "foreign.mcap")
    out = tmp_path / "replayed.mcap"
    assert cli_main(["replay", str(foreign), "--no-files", "--write-mcap", str(out)]) == 2
    assert "nothing to replay" in capsys.readouterr().err
    assert not out.exists() and _leftovers(tmp_path) == []


def test_outputs_are_written_atomically_and_complete(rec, tmp_path, capsys):
    """Good outputs appear under their final names, complete, with no temporary files left."""
    src = _copy(rec, tmp_path)
    out = tmp_path / "rep"
    rc = cli_main(["replay", str(src), "--no-progress", "--out", str(out),
                   "--write-mcap", str(tmp_path / "r.mcap"), "--json"])
    assert rc == 0
    rep = json.loads(capsys.readouterr().out)
    assert json.loads((out / "report.json").read_text())["fixes"] == rep["fixes"]
    sc = McapScanner(tmp_path / "r.mcap")
    list(sc.messages())
    assert sc.complete
    assert cli_main(["recover", str(src), "--out", str(tmp_path / "rec.mcap")]) == 0
    assert _leftovers(tmp_path) == [] and _leftovers(out) == []
