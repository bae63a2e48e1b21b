"""`diffpos solve` as a real process: a pipe with --strict (exit code and results as a user
sees them) and --batch 1 answering each line before the next one is written.

The verb's behaviour line by line is tested in the test process (tests/services/
test_solve_cli.py); these are the properties only a separate process shows.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_solve_cli import _problem

pytestmark = pytest.mark.system

EXE = Path(sys.executable).parent / "diffpos"


def test_real_process_pipe():
    lines = json.dumps(_problem([2.0, 5.0, 10.5], id=1)) + "\n" + "{}\n"
    proc = subprocess.run(
        [str(EXE), "solve", "--strict", "--batch", "1"],
        input=lines,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    recs = [json.loads(x) for x in proc.stdout.splitlines()]
    assert proc.returncode == 1
    assert recs[0]["status"] == "ok" and recs[0]["id"] == 1
    assert recs[1]["status"] == "invalid_input" and "anchors_m" in recs[1]["message"]
    assert "Traceback" not in proc.stderr


def test_batch_1_answers_each_line_before_the_next_arrives():
    proc = subprocess.Popen([str(EXE), "solve", "--batch", "1"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        for node in ([2.0, 5.0, 10.5], [-3.0, 7.0, 4.5]):
            proc.stdin.write(json.dumps(_problem(node)) + "\n")
            proc.stdin.flush()
            rec = json.loads(proc.stdout.readline())  # blocks until this line is answered
            assert np.allclose(rec["position_m"], node, atol=1e-6)
    finally:
        proc.stdin.close()
        assert proc.wait(timeout=60) == 0
        proc.stdout.close()
