"""scripts/faults_table.py: the fault table of docs/faults.md comes from injecting each fault
into real runs, only the text between its markers changes, ``--check`` ignores measured
numbers but not outcomes or exit codes, and the committed doc lists every case with tests
that exist. Nothing is run here; one real case (the script and ``diffpos emulate`` as
processes) is tests/system/test_faults_table_run.py."""

from __future__ import annotations

import ast
import importlib.util
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "faults_table.py"
DOC = ROOT / "docs" / "faults.md"


def _script():
    if "faults_table" in sys.modules:
        return sys.modules["faults_table"]
    spec = importlib.util.spec_from_file_location("faults_table", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def _rows(text: str, ft) -> list[str]:
    section = text.split(ft.BEGIN, 1)[1].split(ft.END, 1)[0]
    return [ln for ln in section.splitlines() if ln.startswith("| ") and "---" not in ln][1:]


def test_committed_doc_has_a_row_for_every_case_naming_existing_tests():
    """Adding a case without regenerating the doc fails here (cheap: nothing is run)."""
    ft = _script()
    rows = _rows(DOC.read_text(), ft)
    assert [re.match(r"\| [^|]+ \| (.+?) \| exit ", r).group(1) for r in rows] == [
        c.tried for c in ft.CASES]
    assert all("**" not in r for r in rows), [r for r in rows if "**" in r]
    for case in ft.CASES:
        for test in case.test.split(" + "):
            path, name = test.split("::")
            tree = ast.parse((ROOT / path).read_text())
            assert name in {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}, test


def test_masking_keeps_exit_codes_and_words():
    ft = _script()
    a = "exit 3; fault reported: fusion died at 3.8 s (exit code -9); uav2 used in 100 % | 15.6"
    b = "exit 3; fault reported: fusion died at 4.1 s (exit code -9); uav2 used in 97 % | 15.6"
    assert ft.masked(a) == ft.masked(b)
    assert ft.masked("exit -9; x") != ft.masked("exit 0; x")
    assert ft.masked("no fix used uav9") != ft.masked("**2 fixes used uav9**")
    assert ft.splice("# Doc\n", "BODY") == f"# Doc\n\n{ft.BEGIN}\nBODY\n{ft.END}\n"
