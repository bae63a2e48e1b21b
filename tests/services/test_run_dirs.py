"""The folders of a SIGKILLed ``emulate`` (``/tmp/diffpos-run-*``, ``/tmp/diffpos-zenoh-*`` with
a secured run's secrets) are removed by the next run (issue 36, item 6: they were left
behind)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from diffpos_services.emulate.orchestrator import RUN_DIR_PREFIXES, claim_run_dir, reap_run_dirs


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_only_folders_of_gone_owners_are_removed(tmp_path):
    live = tmp_path / "diffpos-run-live"
    live.mkdir()
    claim_run_dir(live)  # this process: alive
    dead = tmp_path / "diffpos-zenoh-dead"
    dead.mkdir()
    (dead / "secret.txt").write_text("x")
    (dead / "owner.json").write_text(json.dumps({"pid": _dead_pid(), "start_ticks": 1}))
    reused = tmp_path / "diffpos-run-reused"  # our pid, another start time: a reused pid
    reused.mkdir()
    mine = json.loads((live / "owner.json").read_text())
    (reused / "owner.json").write_text(json.dumps({"pid": os.getpid(),
                                                   "start_ticks": mine["start_ticks"] - 1}))
    unowned = tmp_path / "diffpos-run-old"  # no owner file (an older version): left alone
    unowned.mkdir()
    other = tmp_path / "something-else"
    other.mkdir()
    (other / "owner.json").write_text(json.dumps({"pid": _dead_pid(), "start_ticks": 1}))
    got = sorted(p.name for p in reap_run_dirs(tmp_path))
    assert got == ["diffpos-run-reused", "diffpos-zenoh-dead"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "diffpos-run-live", "diffpos-run-old", "something-else"]
    assert RUN_DIR_PREFIXES == ("diffpos-run-", "diffpos-zenoh-")
