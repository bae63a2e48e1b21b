"""Bad options of ``diffpos emulate`` / ``diffpos anchor`` (issue 15, item 12): one line naming
the option, exit 2, no traceback, nothing started."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from diffpos_services.emulate import EmulationOptions
from diffpos_services.kit import ConfigError, free_tcp_port


def _diffpos(*argv: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    env = dict(os.environ, DIFFPOS_LOG_FORMAT="text")
    env.pop("DIFFPOS_ZENOH_CONFIG", None)
    return subprocess.run([sys.executable, "-m", "diffpos_services.cli.main", *argv],
                          capture_output=True, text=True, timeout=timeout, env=env)


@pytest.mark.parametrize(("dashboard", "names"), [
    (["save"], "--dashboard save"),
    (["save", "a.rrd", "b.rrd"], "--dashboard save a.rrd b.rrd"),
    (["serve", "x.rrd"], "--dashboard serve x.rrd"),
    (["sve"], "--dashboard sve"),
])
def test_dashboard_option_checked_before_anything_starts(dashboard, names):
    with pytest.raises(ConfigError, match=names):
        EmulationOptions(dashboard=dashboard).check()


def test_dashboard_save_to_a_directory_refused(tmp_path):
    with pytest.raises(ConfigError, match="is a directory"):
        EmulationOptions(dashboard=["save", str(tmp_path)]).check()


def test_emulate_dashboard_save_without_path_is_one_line_exit_2():
    r = _diffpos("emulate", "--dashboard", "save", "--no-progress", timeout=30)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    err = [line for line in r.stderr.splitlines() if "error:" in line]
    assert err and "--dashboard save" in err[0] and "--rerun" not in err[0], r.stderr
    # validated before any process started (no router, no "starting" line)
    assert "starting" not in r.stderr and "waiting for the router" not in r.stderr


def test_emulate_bad_endpoint_is_one_line_exit_2():
    r = _diffpos("emulate", "--endpoint", "foo", "--no-progress", timeout=30)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert "diffpos emulate: error: --endpoint 'foo' is not a Zenoh endpoint" in r.stderr, r.stderr
    assert "starting" not in r.stderr


def test_anchor_unreachable_router_is_one_line_exit_2():
    port = free_tcp_port()  # nobody listens there
    r = _diffpos("anchor", "--id", "uav1", "--connect", f"tcp/127.0.0.1:{port}",
                 "--connect-timeout-ms", "500", timeout=60)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert "diffpos anchor: error: --connect" in r.stderr, r.stderr
    assert "--connect-timeout-ms 500" in r.stderr
