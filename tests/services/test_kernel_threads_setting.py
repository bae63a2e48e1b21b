"""The fusion's ``kernel_threads`` setting (diffpos._kernels.pool): its CLI option and default,
its validation, and replay applying it (the replayed estimates are the same bytes for 1 and 2
threads; the kernels' own 1-vs-2 equality is tests/core/test_kernel_threads.py)."""

from __future__ import annotations

import argparse

import pytest
from diffpos_services.cli import fusion as cmd_fusion
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import DEFAULT_KERNEL_THREADS, FusionConfig
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from diffpos_services.wire import messages as M

from diffpos._kernels import pool
from diffpos.scenario import default_scenario


def _config(*argv: str) -> FusionConfig:
    p = argparse.ArgumentParser()
    cmd_fusion.add_arguments(p)
    return cmd_fusion.config_from_args(p.parse_args(list(argv)), default_scenario())


def test_cli_kernel_threads_default_and_value():
    """Default: 1 (live on a shared 2-core machine a second thread was worse); ``--kernel-threads
    N`` sets it; the option is in ``diffpos fusion --help``; 0 is rejected naming the field."""
    assert DEFAULT_KERNEL_THREADS == 1
    assert _config().kernel_threads == DEFAULT_KERNEL_THREADS
    assert FusionConfig().kernel_threads == DEFAULT_KERNEL_THREADS
    assert _config("--kernel-threads", "1").kernel_threads == 1
    assert _config("--kernel-threads", "3").kernel_threads == 3
    p = argparse.ArgumentParser()
    cmd_fusion.add_arguments(p)
    assert "--kernel-threads" in p.format_help()
    with pytest.raises(ConfigError, match="kernel_threads"):
        _config("--kernel-threads", "0")


def test_replay_applies_kernel_threads(tmp_path):
    """replay sets the process's kernel pool from the setting; mnls + tracker estimates are
    the same bytes with 1 and 2 threads."""
    path = tmp_path / "syn.mcap"
    write_synthetic_recording(path, n_anchors=6, n_nodes=4, duration_s=1.5, seed=3)
    try:
        out = {}
        for n in (2, 1):
            r = replay(path, method="mnls", overrides={"kernel_threads": n},
                       use_decisions=False)
            assert pool.threads() == n
            out[n] = [M.encode(e) for e in r.estimates]
        assert len(out[1]) == 4 * 15 and out[1] == out[2]
    finally:
        pool.set_threads(1)
        pool.shutdown()
