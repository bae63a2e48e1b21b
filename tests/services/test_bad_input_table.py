"""scripts/bad_input_table.py: the bad-input table of docs/bad_input.md comes from running the
cases, only the text between its markers changes, and the committed doc lists every case.

In this process with the runs stubbed; a real run of the script and of ``diffpos`` is
tests/system/test_bad_input_table_run.py."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "bad_input_table.py"
DOC = ROOT / "docs" / "bad_input.md"


def _script():
    if "bad_input_table" in sys.modules:
        return sys.modules["bad_input_table"]
    spec = importlib.util.spec_from_file_location("bad_input_table", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def _section(text: str, bit) -> str:
    return text.split(bit.BEGIN, 1)[1].split(bit.END, 1)[0]


def test_regenerating_rewrites_only_the_marked_table_and_check_never_writes(tmp_path,
                                                                          monkeypatch):
    """main() in this process with the runs stubbed: the prose around the markers is kept byte
    for byte, the rows are the selected cases, ``--check`` agrees with a fresh table and
    reports a changed doc without rewriting it. The same with real runs of ``diffpos``:
    tests/system/test_bad_input_table_run.py."""
    bit = _script()
    ran = []
    monkeypatch.setattr(bit, "run_case", lambda case, exe: ran.append(case) or "exit 0; stub")
    doc = tmp_path / "bad_input.md"
    prose_before, prose_after = "# Title\n\nprose | with a pipe\n\n", "\n\nmore prose\n"
    doc.write_text(f"{prose_before}{bit.BEGIN}\nstale hand-written row\n{bit.END}{prose_after}")
    assert bit.main(["--doc", str(doc), "--only", "facade"]) == 0
    text = doc.read_text()
    assert text.startswith(prose_before + bit.BEGIN) and text.endswith(bit.END + prose_after)
    rows = _section(text, bit).strip().splitlines()
    facade = [c for c in bit.CASES if "facade" in f"{c.item} {c.tried}"]
    assert ran == facade and len(facade) == 1
    assert rows == ["| item | tried | now | test |", "| --- | --- | --- | --- |",
                    f"| 15.11 | {facade[0].tried} | exit 0; stub | `{facade[0].test}` |"]
    check = ["--doc", str(doc), "--only", "facade", "--check"]
    assert bit.main(check) == 0
    doc.write_text(text.replace("exit 0", "exit 9"))
    assert bit.main(check) == 1
    assert "exit 9" in doc.read_text()


def test_markers_are_added_when_missing_and_cells_are_escaped():
    bit = _script()
    assert bit.splice("# Doc\n", "BODY") == f"# Doc\n\n{bit.BEGIN}\nBODY\n{bit.END}\n"
    case = bit.Case("x", "tried", ("solve",), "t.py::t")
    out = '{"line": 1, "status": "not_identifiable", "message": "a | b", "position_m": null}\n'
    assert bit.describe(case, 0, out, "") == "exit 0; `not_identifiable`, position_m null: a \\| b"
    other = bit.Case("x", "tried", ("replay",), "t.py::t")
    err = "noise\nTraceback (most recent call last):\nValueError: boom\n"
    assert bit.describe(other, 1, "", err) == "exit 1; ValueError: boom; **traceback**"
    assert bit._spans([1, 2, 3, 5, 7, 8]) == "1-3, 5, 7-8"


def test_committed_doc_has_a_row_for_every_case():
    """Adding a case without regenerating the doc fails here (cheap: nothing is run)."""
    bit = _script()
    section = _section(DOC.read_text(), bit)
    rows = [ln for ln in section.splitlines() if ln.startswith("| ") and "---" not in ln][1:]
    tried = [re.match(r"\| [^|]+ \| (.+?) \| exit ", row).group(1) for row in rows]
    assert tried == [c.tried for c in bit.CASES]
    assert all("**traceback**" not in row and "timed out" not in row for row in rows)
