"""Bad options of ``diffpos emulate`` / ``diffpos anchor`` as real processes (exit code and
stderr as a user sees them; the anchor tries a router nobody listens on), and the dashboard's
liveliness token that ``diffpos emulate`` waits for, on a real Zenoh router (loopback).

The option checks in the test process: tests/services/test_emulate_options.py.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading

import pytest
import zenoh
from diffpos_services.emulate.options import EXTRA_SERVICES
from diffpos_services.processes import free_tcp_port
from diffpos_services.wire.keys import Keys

pytestmark = pytest.mark.system


def _diffpos(*argv: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    env = dict(os.environ, DIFFPOS_LOG_FORMAT="text")
    env.pop("DIFFPOS_ZENOH_CONFIG", None)
    return subprocess.run([sys.executable, "-m", "diffpos_services.cli.main", *argv],
                          capture_output=True, text=True, timeout=timeout, env=env)


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


def test_emulate_waits_for_the_dashboards_token_which_the_service_declares():
    """The dashboard declares its liveliness token once subscribed (real Zenoh, loopback) and
    ``diffpos emulate`` waits for it before the run starts (a short run's .rrd misses
    nothing; tests/system/test_emulate_faults.py::test_short_run_rrd_holds_every_estimate)."""
    import rerun as rr  # the Rerun stack: optional extra, heavy
    from diffpos_services.dashboard.service import DashboardService

    keys = Keys("demo")
    assert EXTRA_SERVICES["dashboard"][2](keys) == keys.alive_dashboard()
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"

    def cfg(**kv):
        c = zenoh.Config()
        c.insert_json5("scouting/multicast/enabled", "false")
        for k, v in kv.items():
            c.insert_json5(k.replace("__", "/"), json.dumps(v))
        return c

    seen = threading.Event()
    with zenoh.open(cfg(mode="router", listen__endpoints=[ep])) as router, \
            zenoh.open(cfg(mode="client", connect__endpoints=[ep])) as watcher:
        sub = watcher.liveliness().declare_subscriber(
            keys.alive_dashboard(),
            lambda s: seen.set() if s.kind == zenoh.SampleKind.PUT else None, history=True)
        svc = DashboardService(router, rr.RecordingStream("test-token"), site="demo")
        svc.start()
        try:
            assert seen.wait(10.0), "no dashboard liveliness token"
        finally:
            svc.close()
            sub.undeclare()
