"""scripts/faults_table.py run for real on one case (``diffpos emulate`` SIGHUPed): its row,
the prose kept byte for byte, ``--check`` passing on a fresh run and failing on a changed exit
code. The cheap checks of the script and the committed doc: tests/services/test_faults_table.py.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from test_faults_table import SCRIPT, _rows, _script

pytestmark = pytest.mark.system


def test_regenerating_one_case_rewrites_only_the_marked_table(tmp_path):
    """The SIGHUP case run for real into a scratch doc: prose kept byte for byte, one row
    describing what happened; ``--check`` against a fresh run passes (timings differ, words
    and exit codes do not) and fails on a changed exit code."""
    ft = _script()
    doc = tmp_path / "faults.md"
    before, after = "# Title\n\nprose | with a pipe\n\n", "\n\nmore prose\n"
    doc.write_text(f"{before}{ft.BEGIN}\nstale row\n{ft.END}{after}")
    cmd = [sys.executable, str(SCRIPT), "--doc", str(doc), "--only", "SIGHUP"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr
    text = doc.read_text()
    assert text.startswith(before + ft.BEGIN) and text.endswith(ft.END + after)
    rows = _rows(text, ft)
    assert len(rows) == 1 and "stale" not in text
    assert rows[0].startswith("| 15.7 | SIGHUP to `emulate`")
    assert "| exit 130; all 7 children gone " in rows[0], rows[0]
    assert "recording complete (footer and index)" in rows[0]
    check = subprocess.run([*cmd, "--check"], capture_output=True, timeout=600, check=False)
    assert check.returncode == 0, check.stderr
    doc.write_text(text.replace("exit 130", "exit 0"))
    check = subprocess.run([*cmd, "--check"], capture_output=True, timeout=600, check=False)
    assert check.returncode == 1
