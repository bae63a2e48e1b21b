"""scripts/bad_input_table.py run for real: the script as a process runs one case with the real
``diffpos`` and writes its row; ``--check`` against a fresh run passes and fails on a changed
exit code. The regeneration logic without processes is tests/services/test_bad_input_table.py.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from test_bad_input_table import SCRIPT, _script, _section

pytestmark = pytest.mark.system


def test_regenerating_rewrites_only_the_marked_table_from_real_runs(tmp_path):
    bit = _script()
    doc = tmp_path / "bad_input.md"
    prose_before, prose_after = "# Title\n\nprose | with a pipe\n\n", "\n\nmore prose\n"
    doc.write_text(f"{prose_before}{bit.BEGIN}\nstale hand-written row\n{bit.END}{prose_after}")
    proc = subprocess.run([sys.executable, str(SCRIPT), "--doc", str(doc), "--only", "facade"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    text = doc.read_text()
    assert text.startswith(prose_before + bit.BEGIN) and text.endswith(bit.END + prose_after)
    rows = _section(text, bit).strip().splitlines()
    assert rows[:2] == ["| item | tried | now | test |", "| --- | --- | --- | --- |"]
    assert len(rows) == 3 and "stale" not in text
    assert rows[2].startswith("| 15.11 | `solve`: anchor 2 on the facade (y = 0) | exit 0; "
                              "`invalid_input`: anchors_m[2] = [0, 0.0, 4] is on the facade")
    assert rows[2].endswith("test_anchor_not_outside_is_invalid_naming_the_anchor` |")
    # up to date now: --check agrees; a changed doc is reported, not rewritten
    check = [sys.executable, str(SCRIPT), "--doc", str(doc), "--only", "facade", "--check"]
    assert subprocess.run(check, capture_output=True, timeout=300, check=False).returncode == 0
    doc.write_text(text.replace("exit 0", "exit 9"))
    assert subprocess.run(check, capture_output=True, timeout=300, check=False).returncode == 1
    assert "exit 9" in doc.read_text()
