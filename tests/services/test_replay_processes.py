"""The replay's report says how many processes ran the fusion (``timing.processes``): the
configured ``workers`` capped at the machine's cores when a pool ran, else 1; the CLI's timing
line prints it."""

from __future__ import annotations

import os

import pytest
from diffpos_services.cli import replay as cmd_replay
from diffpos_services.fusion import workers as W
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("processes") / "syn.mcap"
    write_synthetic_recording(path, n_anchors=6, n_nodes=4, duration_s=1.0, seed=5)
    return path


class _Pool:
    """A stand-in worker pool: every call computed locally (as with one process)."""

    building = None

    def __init__(self, n, model, logger=None) -> None:
        pass

    def wait_ready(self, timeout_s=300.0) -> int:
        return 0

    def close(self, timeout_s=5.0) -> None:
        pass


def test_one_process_without_workers(recording):
    r = replay(recording, method="mnls", use_decisions=False)
    assert r.report["timing"]["processes"] == 1
    r = replay(recording, method="dnls", use_decisions=False, overrides={"workers": 4})
    assert r.report["timing"]["processes"] == 1  # (no tracker: no pool)


def test_workers_capped_at_the_cores(recording, monkeypatch):
    monkeypatch.setattr(W, "RowPool", _Pool)
    monkeypatch.setattr(os, "cpu_count", lambda: 3)
    r = replay(recording, method="mnls", use_decisions=False, overrides={"workers": 64})
    assert r.report["timing"]["processes"] == 3
    r = replay(recording, method="mnls", use_decisions=False, overrides={"workers": 2})
    assert r.report["timing"]["processes"] == 2


@pytest.mark.parametrize("n, text", [(1, "; 1 process)"), (2, "; 2 processes (--workers))")])
def test_the_timing_line_names_the_processes(n, text):
    lines: list[str] = []
    rep = {"recording_s": 10.0, "timing": {"wall_s": 1.0, "speedup_x": 10.0, "warm_up_s": 0.1,
                                           "processes": n}}
    cmd_replay._timing_line(rep, lines.append)
    assert lines[-1].endswith(text), lines
