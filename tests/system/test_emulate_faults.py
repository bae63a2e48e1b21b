"""`diffpos emulate` under faults (issue 15, items 6, 7, 9 and the dashboard's readiness):
children die with it, a dead fusion/recorder is restarted and reported, only the run's own
fusion is counted, a short run's .rrd holds every estimate. Real processes, real Zenoh."""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import threading
import time
from pathlib import Path

import zenoh
from conftest import thread_states
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.processes import free_tcp_port
from diffpos_services.recording.reader import McapScanner
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key


def complete(path: Path) -> bool:
    """The MCAP file has its footer (read through)."""
    scanner = McapScanner(path)
    for _ in scanner.iter_batches():
        pass
    return scanner.complete


def wait_log(services, name: str, text: str, timeout_s: float = 90.0) -> str:
    """Block until ``text`` appears in ``name``'s log (readiness by a log line)."""
    tick = threading.Event()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        log = services.log(name)
        if text in log:
            return log
        if services.procs[name].poll() is not None:
            raise AssertionError(f"{name} exited before {text!r}:\n{log[-3000:]}")
        tick.wait(0.05)
    raise AssertionError(f"no {text!r} in {name}'s log after {timeout_s} s:\n"
                         f"{services.log(name)[-3000:]}")


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                stat = Path(f"/proc/{entry}/stat").read_text()
                if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(entry))
    return out


def wait_gone(pids: list[int], timeout_s: float) -> list[int]:
    """Wait (pidfds, no sleeps) until every pid has exited; the pids still running after
    ``timeout_s`` [s]."""
    fds = {}
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            fds[os.pidfd_open(pid)] = pid
    deadline = time.monotonic() + timeout_s
    try:
        poller = select.poll()
        for fd in fds:
            poller.register(fd, select.POLLIN)
        left = set(fds)
        while left and time.monotonic() < deadline:
            for fd, _ in poller.poll(max(deadline - time.monotonic(), 0) * 1000):
                left.discard(fd)
                poller.unregister(fd)
        return sorted(fds[fd] for fd in left)
    finally:
        for fd in fds:
            os.close(fd)


def _start_emulate(services, tmp_path, *extra: str):
    p = services.start("emulate", "emulate", "--no-progress", "--log-dir", str(tmp_path / "logs"),
                       "--json", str(tmp_path / "summary.json"), *extra)
    wait_log(services, "emulate", "all services ready")
    kids = children(p.pid)
    # router, fusion, 4 anchors, recorder
    assert len(kids) >= 7, kids
    return p, kids


def test_sighup_stops_every_child(services, tmp_path):
    """Closing the terminal (SIGHUP to emulate): the run ends, no child is left running."""
    p, kids = _start_emulate(services, tmp_path, "--duration", "120", "--dashboard", "off",
                             "--record", str(tmp_path / "run.mcap"))
    os.kill(p.pid, signal.SIGHUP)
    assert p.wait(timeout=60) == 130, services.log("emulate")[-3000:]
    assert wait_gone(kids, 1.0) == []
    # the recording was closed properly (complete: footer and index)
    assert complete(tmp_path / "run.mcap")


def test_sigkill_of_emulate_stops_every_child(services, tmp_path):
    """emulate SIGKILLed: its children get the parent-death signal and stop."""
    p, kids = _start_emulate(services, tmp_path, "--duration", "120", "--dashboard", "off",
                             "--record", str(tmp_path / "run.mcap"))
    cmds = {pid: _cmdline(pid) for pid in kids}
    os.kill(p.pid, signal.SIGKILL)
    p.wait(timeout=10)
    left = wait_gone(kids, 30.0)
    assert left == [], ([cmds[pid] for pid in left], [thread_states(pid) for pid in left],
                        _log_tails(tmp_path / "logs"))


def _cmdline(pid: int) -> str:
    with contextlib.suppress(OSError):
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    return "?"


def _log_tails(log_dir: Path, n_chars: int = 600) -> dict[str, str]:
    """The end of every child's log (what a survivor was doing when its parent died)."""
    return {f.name: f.read_text(errors="replace")[-n_chars:] for f in sorted(log_dir.glob("*"))
            if f.is_file()}


def _pid_of(tmp_path: Path, kids: list[int], service: str) -> int:
    for pid in kids:
        with contextlib.suppress(OSError):
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            if b"diffpos_services.cli.main" in cmd and cmd[cmd.index(b"diffpos_services.cli.main") + 1] == service.encode():
                return pid
    raise AssertionError(f"no {service} among {kids}")


def test_dead_fusion_and_recorder_are_restarted_and_reported(services, tmp_path):
    out = tmp_path / "run.mcap"
    p, kids = _start_emulate(services, tmp_path, "--duration", "25", "--dashboard", "off",
                             "--record", str(out))
    os.kill(_pid_of(tmp_path, kids, "fusion"), signal.SIGKILL)
    wait_log(services, "emulate", "service restarted service=fusion")
    os.kill(_pid_of(tmp_path, kids, "recorder"), signal.SIGKILL)
    log = wait_log(services, "emulate", "service restarted service=recorder")
    rc = p.wait(timeout=120)
    log = services.log("emulate")
    assert rc == 3, log[-3000:]  # the run lost data
    summary = json.loads((tmp_path / "summary.json").read_text())
    faults = {f["service"]: f for f in summary["faults"]}
    assert set(faults) == {"fusion", "recorder"}, summary["faults"]
    for f in faults.values():
        assert f["exit_code"] == -signal.SIGKILL
        assert f["restarted_s"] is not None and f["restarted_s"] >= f["died_s"]
    assert "faults: 2" in log and "fusion: died at" in log and "recorder: died at" in log
    # the dead recorder's file is recovered in place (complete), the new one holds what the
    # restarted fusion published
    new = tmp_path / "run-restart1.mcap"
    assert summary["recordings"] == [str(out), str(new)]
    assert complete(out)
    est = 0
    for batch in McapScanner(new).iter_batches():
        est += sum(1 for m in batch if (pk := parse_key(m.topic)) and pk.kind == "estimate")
    assert est > 0, "the restarted fusion's estimates were recorded in the new file"
    # the summary's notes name every file written, and say fixes were lost exactly when some
    # scored node-epoch has no position (the tracker of the default fusion may bridge the
    # restart inside the first, unscored seconds: then there is nothing to report)
    notes = summary["notes"]
    assert f"recording: {out}" in notes and f"recording: {new}" in notes, notes
    lost = any(n.startswith("fixes lost: ") for n in notes)
    assert lost == (summary["availability"] < 1.0), (summary["availability"], notes)


def test_foreign_estimates_and_anchor_not_used_but_reported(services, tmp_path):
    """Another process on the emulate bus (a real zenoh session) republishes every estimate it
    sees and poses as a fake anchor ``uav9`` (copies of uav1's messages): the summary counts
    each of the fusion's estimates once, reports the copies as foreign, no fix uses ``uav9``,
    and the dashboard draws no copy."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys("demo")
    p = services.start("emulate", "emulate", "--no-progress", "--endpoint", endpoint,
                       "--speed", "0", "--duration", "2", "--dashboard", "save",
                       str(tmp_path / "run.rrd"), "--record", "off",
                       "--json", str(tmp_path / "summary.json"))
    stop = threading.Event()
    session = open_session(ZenohSettings(connect=(endpoint,)), stop)
    copies, used = [], set()
    dec = M.estimate_decoder()
    block = zenoh.CongestionControl.BLOCK
    with session:
        def copy(sample) -> None:
            # a foreign publisher: same key, same bytes (BLOCK: every copy arrives); our own
            # copies come back unstamped (local delivery): not copied again
            if sample.timestamp is not None:
                data = sample.payload.to_bytes()
                used.update(dec(data).used_anchors)
                session.put(str(sample.key_expr), data, congestion_control=block)
                copies.append(str(sample.key_expr))

        def fake_anchor(sample) -> None:
            key = str(sample.key_expr)
            if "/anchor/uav1/" in key:
                doc = json.loads(sample.payload.to_bytes())
                doc["anchor_id"] = "uav9"
                session.put(key.replace("/anchor/uav1/", "/anchor/uav9/"),
                            json.dumps(doc).encode(), congestion_control=block)

        token = session.liveliness().declare_token(keys.alive_anchor("uav9"))
        subs = [session.declare_subscriber(keys.estimates(), copy),
                session.declare_subscriber(f"{keys.root}/anchor/uav1/**", fake_anchor)]
        rc = p.wait(timeout=180)
        for sub in subs:
            sub.undeclare()
        token.undeclare()
    assert rc == 0, services.log("emulate")[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["foreign"]["count"] >= 1
    assert all(parse_key(k).kind == "estimate" for k in summary["foreign"]["keys"])
    assert summary["foreign"]["count"] <= len(copies)
    assert summary["estimates"] == 6 * 20, summary["foreign"]  # 6 nodes x 20 epochs, once
    assert "foreign:" in services.log("emulate")
    assert any(n.startswith(f"foreign: {summary['foreign']['count']} messages")
               for n in summary["notes"]), summary["notes"]
    assert used and "uav9" not in used, used
    # the dashboard draws only the run's fusion: one row per estimate, no copies
    assert estimate_rows(tmp_path / "run.rrd") == 6 * 20


def test_short_run_rrd_holds_every_estimate(services, tmp_path):
    """Lockstep run with --dashboard save: emulate waits for the dashboard's liveliness token,
    so the .rrd has a row for every estimate of the run."""
    rrd = tmp_path / "run.rrd"
    p = services.start("emulate", "emulate", "--no-progress", "--speed", "0", "--duration", "2",
                       "--dashboard", "save", str(rrd), "--record", "off",
                       "--json", str(tmp_path / "summary.json"))
    assert p.wait(timeout=180) == 0, services.log("emulate")[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert estimate_rows(rrd) == 6 * 20 == summary["estimates"]


def estimate_rows(rrd: Path) -> int:
    """Rows of the estimate entities in a saved .rrd."""
    import rerun.chunk as rc  # the Rerun stack: optional extra, heavy

    rows = 0
    for chunk in rc.RrdReader(str(rrd)).stream():
        if chunk.entity_path.endswith("/estimate") and chunk.entity_path.startswith("/world/nodes/"):
            rows += chunk.num_rows
    return rows
