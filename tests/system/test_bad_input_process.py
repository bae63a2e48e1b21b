"""Bad input to real ``diffpos`` processes: the exit code and stderr a user sees.

Every case runs in the test process in tests/services/test_bad_input.py (``cli.main.main``);
here one solve over the whole nasty corpus and one config error go through the installed
entry point.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from test_bad_input import GOOD_LINE, NASTY, solve_rows

pytestmark = pytest.mark.system

EXE = Path(sys.executable).parent / "diffpos"


def test_solve_real_process_survives_the_corpus(tmp_path):
    rows = solve_rows()
    path = tmp_path / "nasty.jsonl"
    path.write_bytes(b"".join((NASTY / f).read_bytes() + GOOD_LINE for f, _ in rows))
    proc = subprocess.run([str(EXE), "solve", "--input", str(path), "--max-line-bytes", "65536",
                           "--strict"], capture_output=True, timeout=120, check=False)
    recs = [json.loads(x) for x in proc.stdout.splitlines()]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr.decode()
    assert [r["status"] == "invalid_input" for r in recs] == [True, False] * len(rows)


def test_service_cli_config_error_is_one_line_exit_2_from_a_real_process():
    """The first case of test_bad_input's test_service_cli_config_errors_are_one_line_naming_
    the_field, as a user sees it."""
    proc = subprocess.run([str(EXE), "fusion", "--deadline-s", "100"], capture_output=True,
                          text=True, timeout=60, check=False, stdin=subprocess.DEVNULL)
    assert proc.returncode == 2, proc.stderr
    assert "deadline_s" in proc.stderr and proc.stderr.count("\n") == 1, proc.stderr
    assert "Traceback" not in proc.stderr
