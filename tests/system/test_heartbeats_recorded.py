"""The services' heartbeats are in the recording, and the dashboard has one too (issue 36
leftovers).

A real ``diffpos emulate`` run (router, fusion, four anchors, recorder and a dashboard saving
an .rrd, as processes on loopback) is recorded; the MCAP read back holds each service's
heartbeats (fusion, dashboard, every anchor; not the recorder's own) with rising progress, ``diffpos
inspect``'s summary lists them, and replay gives the same estimates with them as without
them (a copy with the heartbeat channels left out), also after a truncated copy was
recovered. A SIGSTOPped dashboard is found hung by emulate's supervisor like any service.
Every wait is on a log line or a process exit; nothing is slept for.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import msgspec
from diffpos_services.emulate.supervise import STALL_S
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.repair import recover
from diffpos_services.recording.summary import summarize
from diffpos_services.replay.run import replay
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key
from mcap.writer import Writer
from test_emulate_faults import _pid_of, _start_emulate, wait_log

SITE = "demo"


def _heartbeats(path: Path) -> dict[str, list[tuple[int, M.Heartbeat]]]:
    """Topic -> (receive time, heartbeat) of every recorded heartbeat, in file order."""
    dec = M.decoder(M.Heartbeat)
    sc = McapScanner(path)
    out: dict[str, list] = defaultdict(list)
    for m in sc.messages():
        pk = parse_key(m.topic)
        if pk is not None and pk.kind == "heartbeat":
            assert sc.schema_of(m.channel_id).name == "diffpos.heartbeat.v1", m.topic
            out[m.topic].append((m.log_ns, dec(m.data)))
    return out


def _without_heartbeats(src: Path, dst: Path) -> int:
    """Copy ``src`` to ``dst`` leaving out the heartbeat channels (a recording made before
    they were recorded); returns the messages left out."""
    sc = McapScanner(src)
    left_out = 0
    with open(dst, "wb") as f:
        w = Writer(f)
        w.start(profile=sc.header_profile, library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for m in sc.messages():
            pk = parse_key(m.topic)
            if pk is not None and pk.kind == "heartbeat":
                left_out += 1
                continue
            if m.channel_id not in channels:
                ch = sc.channels[m.channel_id]
                sch = sc.schemas.get(ch.schema_id)
                if sch is not None and ch.schema_id not in schemas:
                    schemas[ch.schema_id] = w.register_schema(sch.name, sch.encoding, sch.data)
                channels[m.channel_id] = w.register_channel(
                    ch.topic, ch.message_encoding, schemas.get(ch.schema_id, 0), ch.metadata)
            w.add_message(channels[m.channel_id], log_time=m.log_ns, data=m.data,
                          publish_time=m.publish_ns, sequence=m.sequence)
        for md in sc.metadata:
            w.add_metadata(md.name, md.metadata)
        for a in sc.attachments:
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        w.finish()
    return left_out


def _bare(e) -> bytes:
    return M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))


def test_a_recorded_run_holds_every_services_heartbeats_and_replay_ignores_them(
        services, tmp_path):
    out = tmp_path / "run.mcap"
    p = services.start("emulate", "emulate", "--no-progress", "--log-dir", str(tmp_path / "logs"),
                       "--json", str(tmp_path / "summary.json"), "--duration", "4",
                       "--dashboard", "save", str(tmp_path / "run.rrd"), "--record", str(out))
    assert p.wait(timeout=600) == 0, services.log("emulate")[-3000:]

    beats = _heartbeats(out)
    keys = Keys(SITE)
    s = summarize(out)
    anchors = s.anchors
    assert len(anchors) == 4, anchors
    # every service's but the recorder's own (its stall shows as a silence of every channel)
    want = {keys.heartbeat(s) for s in ("fusion", "dashboard")}
    want |= {keys.heartbeat("anchor", a) for a in anchors}
    assert set(beats) == want, sorted(beats)
    for topic, got in beats.items():
        pk = parse_key(topic)
        assert len(got) >= 3, (topic, len(got))  # 0.5 s apart over a run of >= 4 s
        hbs = [hb for _, hb in got]
        assert {hb.service for hb in hbs} == {pk.service}
        assert {hb.anchor_id for hb in hbs} == {pk.anchor_id}
        assert len({(hb.instance, hb.pid) for hb in hbs}) == 1, topic  # nothing restarted
        assert [hb.seq for hb in hbs] == list(range(hbs[0].seq, hbs[0].seq + len(hbs))), topic
        progress = [hb.progress for hb in hbs]
        assert progress == sorted(progress) and progress[-1] > progress[0], (topic, progress)

    # the summary (diffpos inspect) lists them, per process start
    assert {b["who"] for b in s.heartbeats} == {"fusion", "dashboard"} | {
        f"anchor {a}" for a in anchors}
    for b in s.heartbeats:
        assert b["regressions"] == 0 and b["last_progress"] > b["first_progress"], b
        assert b["longest_silence_s"] < STALL_S, b  # nothing stalled in this run
    printed = subprocess.run([sys.executable, "-m", "diffpos_services.cli.main", "inspect",
                              str(out)], capture_output=True, text=True, timeout=120, check=True)
    lines = printed.stdout.split("heartbeats:", 1)[1].splitlines()[1:1 + len(s.heartbeats)]
    assert sorted(ln.split(" pid ")[0].strip() for ln in lines) == sorted(
        b["who"] for b in s.heartbeats), printed.stdout

    # replay reads past them: the same estimates with and without them, all the live ones
    bare = tmp_path / "no-heartbeats.mcap"
    assert _without_heartbeats(out, bare) == sum(map(len, beats.values()))
    with_hb, without = replay(out), replay(bare)
    assert [_bare(e) for e in with_hb.estimates] == [_bare(e) for e in without.estimates]
    c = with_hb.report["compare"]
    assert c["identical_positions"] == c["with_positions"] > 0, c
    assert c["only_live"] == c["only_replayed"] == 0, c

    # recover of a truncated copy keeps the heartbeats before the cut; replay still runs
    cut = tmp_path / "cut.mcap"
    data = out.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    fixed = tmp_path / "recovered.mcap"
    rep = recover(cut, fixed)
    assert rep.messages > 0 and not rep.was_complete
    kept = _heartbeats(fixed)
    assert kept and all(len(v) <= len(beats[t]) for t, v in kept.items())
    r = replay(fixed)
    assert len(r.estimates) > 0


def test_a_stopped_dashboard_is_a_hung_fault_killed_not_restarted(services, tmp_path):
    """The dashboard publishes heartbeats like the other services, so a SIGSTOPped one (its
    liveliness token lives on for the 10 s lease) is found hung within STALL_S + 2 s: killed
    like every hung service but the anchors, not restarted (a viewer), exit 3."""
    p, kids = _start_emulate(services, tmp_path, "--duration", "30", "--record", "off",
                             "--dashboard", "save", str(tmp_path / "run.rrd"))
    dash = _pid_of(tmp_path, kids, "dashboard")
    os.kill(dash, signal.SIGSTOP)
    try:
        wait_log(services, "emulate", "service hung service=dashboard")
        rc = p.wait(timeout=180)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(dash, signal.SIGCONT)
    log = services.log("emulate")
    assert rc == 3, log[-3000:]
    faults = json.loads((tmp_path / "summary.json").read_text())["faults"]
    assert [f["service"] for f in faults] == ["dashboard"], faults
    f = faults[0]
    assert f["kind"] == "hung" and f["exit_code"] == -signal.SIGKILL, f
    assert STALL_S <= f["detected_after_s"] < STALL_S + 2.0, f
    assert f["restarted_s"] is None and "not restarted" in f["note"], f
