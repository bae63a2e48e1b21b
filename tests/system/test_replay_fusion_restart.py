"""Replay of a real run whose fusion was killed and restarted (issue 36 item 1).

``diffpos emulate`` (router, anchors, fusion, recorder as processes on loopback) records a
run; the fusion is SIGKILLed once after all services are ready and emulate restarts it (a new
process: another ``instance`` in its diagnostics, a decision record from chunk 0). Replay of
the one recording reproduces every estimate of both fusion processes bit for bit except those
the killed one published after its last diagnostics (their record died with it), which the
report counts with that reason. Before: the second process's record was dropped as repeated
chunks and its estimates came from the first core (the issue's hostile trial: 0 of 552 matched).
Readiness by log lines and process exit; nothing is slept for.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path

import msgspec
import pytest
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.processes import free_tcp_port
from diffpos_services.replay.run import replay
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

pytestmark = pytest.mark.slow


def _wait_log(services, name: str, text: str, timeout_s: float = 120.0) -> None:
    tick = threading.Event()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if text in services.log(name):
            return
        if services.procs[name].poll() is not None:
            raise AssertionError(f"{name} exited before {text!r}:\n{services.log(name)[-3000:]}")
        tick.wait(0.05)
    raise AssertionError(f"no {text!r} in {name}'s log:\n{services.log(name)[-3000:]}")


def _fusion_pid(parent: int) -> int:
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        with contextlib.suppress(OSError):
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmd = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
            if int(stat.rsplit(")", 1)[1].split()[1]) == parent and \
                    b"diffpos_services.cli.main" in cmd and \
                    cmd[cmd.index(b"diffpos_services.cli.main") + 1] == b"fusion":
                return int(entry)
    raise AssertionError(f"no fusion child of {parent}")


def _bare(e):
    return M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))


def test_replay_of_a_run_with_a_killed_fusion_reproduces_both_processes(services, tmp_path):
    out = tmp_path / "run.mcap"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    p = services.start("emulate", "emulate", "--no-progress", "--log-dir", str(tmp_path / "logs"),
                       "--endpoint", endpoint, "--duration", "20", "--dashboard", "off",
                       "--record", str(out))
    _wait_log(services, "emulate", "all services ready")
    # kill the fusion once it has solved and published its record for a while (3 diagnostics
    # with fixes solved): the first process' estimates and record are in the recording
    stop, solving = threading.Event(), threading.Event()
    seen: list[str] = []
    dec = M.decoder(M.FusionDiagnostics)

    def on_diag(sample) -> None:
        d = dec(sample.payload.to_bytes())
        if d.solved > 0:
            seen.append(d.instance)
            if len(seen) >= 3:
                solving.set()

    with open_session(ZenohSettings(connect=(endpoint,)), stop) as session:
        sub = session.declare_subscriber(Keys("demo").fusion_diagnostics(), on_diag)
        assert solving.wait(120), services.log("emulate")[-3000:]
        sub.undeclare()
    os.kill(_fusion_pid(p.pid), signal.SIGKILL)
    _wait_log(services, "emulate", "service restarted service=fusion")
    assert p.wait(timeout=180) == 3, services.log("emulate")[-3000:]  # a fault: exit 3
    r = replay(out)
    inst = r.report["fusion_instances"]["instances"]
    assert [i["replayed_by"] for i in inst] == ["decisions", "decisions"], inst
    assert inst[0]["instance"] == seen[0] != inst[1]["instance"]
    d = r.report["decisions"]
    assert d["restarts"] == 1 and d["chunks_repeated"] == 0, d
    c = r.report["compare"]
    assert c["only_replayed"] == 0 and c["status_agree"] == 1.0, c
    assert c["identical_positions"] == c["with_positions"] > 0, c
    assert c["only_live"] == c["live_not_reproducible"], c
    # every replayed estimate is a live one, bit for bit (t_pub_wall_ns aside)
    live = {_bare(e) for e in r.live_estimates}
    assert all(b in live for b in map(_bare, r.estimates))
    assert len(r.estimates) == len(r.live_estimates) - c["live_not_reproducible"]
