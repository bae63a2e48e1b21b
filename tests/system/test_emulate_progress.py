"""`diffpos emulate` judges progress, not only liveliness, and trusts nobody blindly on the
default bus (issue 36, items 1 and 4). Real processes, a real Zenoh router on loopback; every
wait is on a log line, a sample or a process exit."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading

import zenoh
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.emulate.supervise import MAX_RESTARTS, STALL_S
from diffpos_services.processes import free_tcp_port
from diffpos_services.recording.reader import McapScanner
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key
from test_emulate_faults import _pid_of, _start_emulate, children, wait_log


def _summary(tmp_path):
    return json.loads((tmp_path / "summary.json").read_text())


def test_sigstopped_fusion_and_recorder_are_hung_faults_killed_and_restarted(services, tmp_path):
    """SIGSTOP keeps the liveliness token alive (10 s lease); the missing progress is a fault
    within STALL_S + 2 s, the process is killed and restarted, the run exits 3."""
    out = tmp_path / "run.mcap"
    p, kids = _start_emulate(services, tmp_path, "--duration", "30", "--dashboard", "off",
                             "--record", str(out))
    stopped = []
    try:
        fusion = _pid_of(tmp_path, kids, "fusion")
        os.kill(fusion, signal.SIGSTOP)
        stopped.append(fusion)
        wait_log(services, "emulate", "service hung service=fusion")
        wait_log(services, "emulate", "service restarted service=fusion")
        recorder = _pid_of(tmp_path, children(p.pid), "recorder")
        os.kill(recorder, signal.SIGSTOP)
        stopped.append(recorder)
        wait_log(services, "emulate", "service restarted service=recorder")
        rc = p.wait(timeout=180)
    finally:
        for pid in stopped:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
    log = services.log("emulate")
    assert rc == 3, log[-3000:]
    faults = {f["service"]: f for f in _summary(tmp_path)["faults"]}
    assert set(faults) == {"fusion", "recorder"}, faults
    for f in faults.values():
        assert f["kind"] == "hung" and f["exit_code"] == -signal.SIGKILL
        assert STALL_S <= f["detected_after_s"] < STALL_S + 2.0, f
        assert f["restarted_s"] is not None
    assert "fusion: hung, found at" in log and "recorder: hung, found at" in log
    # the recorder's file was recovered after the kill, the new one has the rest
    assert "run-restart1.mcap" in faults["recorder"]["note"]
    assert _summary(tmp_path)["recordings"][1].endswith("run-restart1.mcap")


def test_fusion_killed_beyond_its_restarts_ends_the_run(services, tmp_path):
    """The 4th death of the fusion: not restarted, and the run ends at once with exit 3 and
    the reason (it used to go on without a fusion, silently)."""
    p, _ = _start_emulate(services, tmp_path, "--duration", "300", "--dashboard", "off",
                          "--record", str(tmp_path / "run.mcap"))
    for k in range(MAX_RESTARTS + 1):
        os.kill(_pid_of(tmp_path, children(p.pid), "fusion"), signal.SIGKILL)
        if k < MAX_RESTARTS:  # the next kill finds the new process (one log line each)
            wait_log(services, "emulate", f"service restarted service=fusion restart={k + 1}")
    rc = p.wait(timeout=120)
    log = services.log("emulate")
    assert rc == 3, log[-3000:]
    s = _summary(tmp_path)
    assert s["ended_early"].startswith("the run ended early: the fusion is gone"), s
    assert sum(f["service"] == "fusion" for f in s["faults"]) == MAX_RESTARTS + 1
    assert s["duration_s"] == 300 and "the run ended early" in log


def test_duplicate_anchor_publisher_is_reported_and_not_trusted(services, tmp_path):
    """A second process publishes under uav1's keys (copies of its messages, moved 5 m): the
    fusion stops using uav1 (no estimate uses it after the first copy), says why, and the
    summary lists the anchor as a fault (exit 3)."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys("demo")
    p = services.start("emulate", "emulate", "--no-progress", "--endpoint", endpoint,
                       "--speed", "0", "--duration", "3", "--dashboard", "off",
                       "--record", "off", "--log-dir", str(tmp_path / "logs"),
                       "--json", str(tmp_path / "summary.json"))
    stop = threading.Event()
    session = open_session(ZenohSettings(connect=(endpoint,)), stop)
    dec = M.estimate_decoder()
    first_fake: list[int] = []
    after: list = []
    lock = threading.Lock()
    with session:
        def fake(sample) -> None:
            if sample.attachment is None:  # our own copies come back: not copied again
                return
            doc = json.loads(sample.payload.to_bytes())
            if "position_m" in doc:
                doc["position_m"] = [v + 5.0 for v in doc["position_m"]]
            session.put(str(sample.key_expr), json.dumps(doc).encode(),
                        congestion_control=zenoh.CongestionControl.BLOCK)
            with lock:
                if not first_fake:
                    first_fake.append(1)

        def watch(sample) -> None:
            with lock:
                if first_fake:
                    after.append(dec(sample.payload.to_bytes()))

        subs = [session.declare_subscriber(f"{keys.root}/anchor/uav1/**", fake),
                session.declare_subscriber(keys.estimates(), watch)]
        rc = p.wait(timeout=240)
        for s in subs:
            s.undeclare()
    assert rc == 3, services.log("emulate")[-3000:]
    s = _summary(tmp_path)
    dup = [f for f in s["faults"] if f["kind"] == "duplicate publisher"]
    assert [f["service"] for f in dup] == ["anchor-uav1"], s["faults"]
    assert "duplicate publisher" in services.log("emulate")
    fusion_log = (tmp_path / "logs" / "fusion.log").read_text()
    assert "two publishers under one anchor key" in fusion_log
    # a few estimates solved before the first copy arrived may still use it; then none
    used = [e for e in after if "uav1" in e.used_anchors]
    assert len(after) > 50 and len(used) <= 2 * 6, (len(after), len(used))


def test_forged_estimates_under_the_fusion_id_prefix_are_not_ours(services, tmp_path):
    """Issue 36: a forger that reads the fusion's zenoh id prefix from an estimate and
    publishes stamped estimates under an id with that prefix was recorded as the run's own
    (716 of them). Now "ours" needs the MAC under the run's secret token: every forged
    estimate is foreign, none is in the recording or counted."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    keys = Keys("demo")
    out = tmp_path / "run.mcap"
    p = services.start("emulate", "emulate", "--no-progress", "--endpoint", endpoint,
                       "--speed", "0", "--duration", "3", "--dashboard", "off",
                       "--record", str(out), "--json", str(tmp_path / "summary.json"))
    stop = threading.Event()
    watcher = open_session(ZenohSettings(connect=(endpoint,)), stop)
    got_prefix = threading.Event()
    prefix: list[str] = []

    def learn(sample) -> None:
        if sample.timestamp is not None and not prefix:
            prefix.append(str(sample.timestamp.get_id())[:16])
            got_prefix.set()

    sub = watcher.declare_subscriber(keys.estimates(), learn)
    assert got_prefix.wait(120), services.log("emulate")[-3000:]
    sub.undeclare()
    cfg = ZenohSettings(connect=(endpoint,)).to_config()
    cfg.insert_json5("id", json.dumps(prefix[0] + "0123456789abcdef"))
    cfg.insert_json5("timestamping/enabled", "true")
    forger = zenoh.open(cfg)
    sent = [0]

    def forge(sample) -> None:
        ts = sample.timestamp
        if ts is not None and str(ts.get_id()).startswith(prefix[0]) \
                and not str(ts.get_id()).endswith("0123456789abcdef"):
            doc = json.loads(sample.payload.to_bytes())
            if doc.get("position_m"):
                doc["position_m"] = [v + 5.0 for v in doc["position_m"]]
            doc["seq"] = doc["seq"] + 1_000_000
            forger.put(str(sample.key_expr), json.dumps(doc).encode(),
                       congestion_control=zenoh.CongestionControl.BLOCK)
            sent[0] += 1

    sub = forger.declare_subscriber(keys.estimates(), forge)
    rc = p.wait(timeout=240)
    sub.undeclare()
    forger.close()
    watcher.close()
    assert rc == 0, services.log("emulate")[-3000:]
    s = _summary(tmp_path)
    assert sent[0] > 10
    assert s["estimates"] == 6 * 30, s["foreign"]
    assert s["foreign"]["count"] >= 1
    recorded = 0
    for batch in McapScanner(out).iter_batches():
        for m in batch:
            if (pk := parse_key(m.topic)) is not None and pk.kind == "estimate":
                recorded += 1
                assert json.loads(m.data)["seq"] < 1_000_000, "a forged estimate was recorded"
    assert recorded == s["estimates"]
