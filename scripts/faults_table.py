"""Regenerate the fault table of docs/faults.md by injecting every fault into a real run.

    .venv/bin/python scripts/faults_table.py            # rewrite the table in the doc
    .venv/bin/python scripts/faults_table.py --check    # exit 1 if the doc is out of date
    .venv/bin/python scripts/faults_table.py --only 15.7 --doc /tmp/x.md   # a subset

Every case starts the real ``diffpos emulate`` (the one next to this Python, else the one on
PATH) in a fresh temporary directory, on its own loopback port, waits for what the run logs
(``all services ready``, the ``progress`` lines with the run time) and injects the fault into
the real child process (found by its command line among emulate's children) or into emulate
itself; a Zenoh session of the script joins the run's router where a case needs to watch the
estimates or to play a foreign publisher. Its row says what happens now: the exit code, what
the summary (``--json``) reports and what the script observed. Nothing is synchronised by
sleeping: every wait is on a log line, an estimate or a process exit (pidfd).

The rows replace everything between ``<!-- generated: scripts/faults_table.py -->`` and
``<!-- /generated -->`` (added at the end of the doc if missing); the prose around them is
kept byte for byte. Measured figures (times, counts that depend on the machine's speed) vary
between runs: ``--check`` compares the rows with every number masked except exit codes, so
it fails when a case, its outcome in words or an exit code changes, not when a timing does.

Adding a case is a function ``run(ctx) -> str`` (the "now" cell) and one :class:`Case`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import queue
import re
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.summary import summarize
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "faults.md"
BEGIN = "<!-- generated: scripts/faults_table.py -->"
END = "<!-- /generated -->"
WAIT_S = 120.0  # upper bound of every wait [s]; a case returns as soon as it happens
PROFILE = ROOT / "security" / "profile.dev.toml"


@dataclass(frozen=True)
class Case:
    """One fault: what was tried, how to run it, and the tests that pin it."""

    item: str  # issue item ("15.7")
    tried: str  # markdown, one line
    run: Callable[[Ctx], str]  # the "now" cell
    test: str  # file::test that pins the behaviour (several: separated by " + ")


@dataclass
class Ctx:
    tmp: Path
    exe: str


# ----------------------------------------------------------------------------- processes
def diffpos_exe() -> str:
    here = Path(sys.executable).parent / "diffpos"
    return str(here) if here.exists() else (shutil.which("diffpos") or "diffpos")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                stat = Path(f"/proc/{entry}/stat").read_text()
                if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(entry))
    return out


def wait_gone(pids: list[int], timeout_s: float) -> tuple[list[int], float]:
    """Wait on pidfds until every pid exited: (pids still running, seconds waited)."""
    t0 = time.monotonic()
    fds = {}
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            fds[os.pidfd_open(pid)] = pid
    try:
        poller = select.poll()
        for fd in fds:
            poller.register(fd, select.POLLIN)
        left = set(fds)
        while left and time.monotonic() - t0 < timeout_s:
            for fd, _ in poller.poll(max(timeout_s - (time.monotonic() - t0), 0) * 1000):
                left.discard(fd)
                poller.unregister(fd)
        return sorted(fds[fd] for fd in left), time.monotonic() - t0
    finally:
        for fd in fds:
            os.close(fd)


class Emulate:
    """``diffpos emulate`` as a child: its JSON log lines (stderr) collected by a thread."""

    def __init__(self, ctx: Ctx, *argv: str, endpoint: str | None = None) -> None:
        self.ctx = ctx
        self.endpoint = endpoint or f"tcp/127.0.0.1:{free_port()}"
        self.summary_path = ctx.tmp / "summary.json"
        env = dict(os.environ, DIFFPOS_LOG_FORMAT="json")
        env.pop("DIFFPOS_ZENOH_CONFIG", None)
        ep = [] if "--security-profile" in argv else ["--endpoint", self.endpoint]
        self.p = subprocess.Popen(
            [ctx.exe, "emulate", *ep, "--json", str(self.summary_path), "--log-dir",
             str(ctx.tmp / "logs"), *argv], stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ctx.tmp, env=env,
            start_new_session=True)
        self.lines: queue.Queue = queue.Queue()
        self.log: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        self.t_run = 0.0
        self.stopped: list[int] = []  # children SIGSTOPped by the case (SIGCONT at the end)

    def stop_child(self, pid: int) -> float:
        """SIGSTOP a child (resumed by :meth:`kill` if the case does not); monotonic time."""
        os.kill(pid, signal.SIGSTOP)
        self.stopped.append(pid)
        return time.monotonic()

    def wait_msg(self, msg: str, service: str | None = None) -> float:
        """Block until emulate logs ``msg`` (for ``service``); its monotonic receive time."""
        self.wait(lambda r: r.get("msg") == msg and (service is None
                                                     or r.get("service") == service))
        return time.monotonic()

    def _read(self) -> None:
        for line in self.p.stderr:
            self.log.append(line)
            try:
                self.lines.put(json.loads(line))
            except ValueError:
                pass
        self.lines.put(None)

    def wait(self, pred: Callable[[dict], bool]) -> dict:
        """Block until a log record satisfies ``pred``."""
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            try:
                rec = self.lines.get(timeout=max(deadline - time.monotonic(), 0.01))
            except queue.Empty:
                break
            if rec is None:
                raise RuntimeError("emulate exited early: " + "".join(self.log[-5:]))
            # the status line's run time: "t 1.0/20 s" (older lines: "t=1.0/20")
            m = re.search(r"\bt[= ]\s*([\d.]+)/", str(rec.get("status", "")))
            if m:
                self.t_run = float(m.group(1))
            if pred(rec):
                return rec
        raise RuntimeError("emulate never logged what was waited for: " + "".join(self.log[-5:]))

    def ready(self) -> None:
        self.wait(lambda r: r.get("msg") == "all services ready")

    def at(self, t_s: float) -> None:
        """Block until the run time reaches ``t_s`` [s] (its progress lines)."""
        if self.t_run < t_s:
            self.wait(lambda r: self.t_run >= t_s)

    def child(self, service: str, arg: str | None = None) -> int:
        """pid of emulate's child running ``diffpos <service>`` (with ``arg`` in argv)."""
        for pid in children(self.p.pid):
            with contextlib.suppress(OSError, ValueError, IndexError):  # (exiting, or exec'ing)
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
                if (cmd[cmd.index("diffpos_services.cli.main") + 1] == service
                        and (arg is None or arg in cmd)):
                    return pid
        raise RuntimeError(f"no {service} {arg or ''} among emulate's children")

    def finish(self) -> tuple[int, dict]:
        rc = self.p.wait(timeout=WAIT_S)
        try:
            summary = json.loads(self.summary_path.read_text())
        except (OSError, ValueError):
            summary = {}
        return rc, summary

    def kill(self) -> None:
        for pid in self.stopped:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        if self.p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.p.pid, signal.SIGKILL)
            self.p.wait()


class Watch:
    """A Zenoh session of the script on the run's router: every estimate of the run's
    fusion (samples stamped by another session) with its receive wall time."""

    def __init__(self, endpoint: str, site: str = "demo") -> None:
        self.zenoh, self.keys = zenoh, Keys(site)
        self.stop = threading.Event()
        self.session = open_session(ZenohSettings(connect=(endpoint,)), self.stop)
        self.dec = M.estimate_decoder()
        self.estimates: list[tuple[int, object]] = []
        self.prefix = ""
        self.lock = threading.Lock()
        self.subs = [self.session.declare_subscriber(self.keys.estimates(), self._on_est)]

    def _on_est(self, sample) -> None:
        if sample.timestamp is None:  # our own publication delivered locally
            return
        self.prefix = self.prefix or str(sample.timestamp.get_id())
        est = self.dec(sample.payload.to_bytes())
        with self.lock:
            self.estimates.append((time.time_ns(), est))

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.session.close()


# ----------------------------------------------------------------------------- describing
def _faults(summary: dict) -> str:
    out = []
    for f in summary.get("faults", []):
        again = (f", restarted at {f['restarted_s']:.1f} s" if f.get("restarted_s") is not None
                 else ", not restarted")
        out.append(f"fault reported: {f['service']} died at {f['died_s']:.1f} s "
                   f"(exit code {f['exit_code']}){again}")
    return "; ".join(out)


def _hung_faults(summary: dict) -> str:
    out = []
    for f in summary.get("faults", []):
        if f.get("kind") == "hung":
            out.append(f"fault reported: {f['service']} hung ({f['detected_after_s']:.1f} s "
                       "without progress)" + ("; restarted" if f.get("restarted_s") is not None
                                              else "; " + f["note"].split("; ")[-1]))
        elif f.get("kind") == "duplicate publisher":
            out.append(f"fault reported: {f['service']} duplicate publisher")
        else:
            out.append(f"fault reported: {f['service']} died (exit code {f['exit_code']})"
                       + (", restarted" if f.get("restarted_s") is not None
                          else ", not restarted"))
    return "; ".join(out) or "no fault reported"


def _lost(summary: dict) -> str:
    """Estimates and messages lost, as the summary counts them."""
    n, miss = summary.get("node_epochs"), summary.get("node_epochs_without_estimate")
    out = [] if n is None else [f"{miss} of {n} scored node-epochs without an estimate"]
    rl = summary.get("recording_losses")
    if rl is not None:
        out.append(f"recording: {rl['missing']} messages missing by sequence number across "
                   f"{len(rl['files'])} file(s)")
    return "; ".join(out)


def _detected(t_inject: float, t_seen: float | None, what: str = "detected") -> str:
    return (f"{what} {t_seen - t_inject:.1f} s after the fault" if t_seen is not None
            else "**not detected**")


def _avail(summary: dict) -> str:
    a = summary.get("availability")
    n = summary.get("node_epochs")
    return "no summary" if a is None else f"availability {100 * a:.1f} % of {n} node-epochs"


def _cell(*parts: str) -> str:
    return "; ".join(p for p in parts if p).replace("|", "\\|")


# ----------------------------------------------------------------------------- cases
def hung_anchor(ctx: Ctx) -> str:
    """SIGSTOP uav2 for 12 s (its 10 s liveliness lease expires), then SIGCONT."""
    emu = Emulate(ctx, "--channel", "ideal", "--duration", "24", "--dashboard", "off",
                  "--record", "off")
    watch = None
    try:
        emu.ready()
        watch = Watch(emu.endpoint)
        emu.at(3.0)
        pid = emu.child("anchor", "uav2")
        os.kill(pid, signal.SIGSTOP)
        t_stop = time.time_ns()
        emu.at(15.0)
        os.kill(pid, signal.SIGCONT)
        t_cont = time.time_ns()
        rc, summary = emu.finish()
    finally:
        emu.kill()
        if watch is not None:
            watch.close()
    hang = [e for rx, e in watch.estimates if t_stop < rx <= t_cont]
    after = [(rx, e) for rx, e in watch.estimates if rx > t_cont]
    back = [rx for rx, e in after if "uav2" in e.used_anchors]
    with_pos = sum(e.position_m is not None for e in hang)
    used_back = (f"uav2 used again {(back[0] - t_cont) * 1e-9:.1f} s after SIGCONT, then in "
                 f"{100 * len(back) / max(len(after), 1):.0f} % of the fixes"
                 if back else "**uav2 never used again**")
    few = sum(e.status == "TOO_FEW_ANCHORS" for _, e in after)
    return _cell(f"exit {rc}", _hung_faults(summary), f"during the hang {len(hang)} estimates, "
                 f"{100 * with_pos / max(len(hang), 1):.0f} % with a position (3 anchors)",
                 used_back, f"{few} TOO_FEW_ANCHORS after it", _avail(summary))


def killed(service: str) -> Callable[[Ctx], str]:
    def run(ctx: Ctx) -> str:
        out = ctx.tmp / "run.mcap"
        emu = Emulate(ctx, "--channel", "ideal", "--duration", "10", "--dashboard", "off",
                      "--record", str(out))
        watch = None
        try:
            emu.ready()
            watch = Watch(emu.endpoint)
            emu.at(3.0)
            os.kill(emu.child(service), signal.SIGKILL)
            t_kill, t0 = time.time_ns(), time.monotonic()
            seen = emu.wait_msg("service died", service)
            rc, summary = emu.finish()
        finally:
            emu.kill()
            if watch is not None:
                watch.close()
        resumed = ""
        if service == "fusion":
            after = [rx for rx, _ in watch.estimates if rx > t_kill]
            resumed = (f"estimates again {(after[0] - t_kill) * 1e-9:.1f} s after the kill "
                       "(the restarted fusion resumes from the bus)" if after
                       else "**no estimate after the kill**")
        files = [Path(r).name for r in summary.get("recordings", [])]
        rec = ""
        if service == "recorder":
            rec = (f"recordings {files}; " + " ".join(summary.get("recording_notes", []))
                   .replace(str(ctx.tmp) + "/", ""))
        return _cell(f"exit {rc}", _detected(t0, seen), _faults(summary), resumed, rec,
                     _lost(summary), _avail(summary))
    return run


def signal_emulate(sig: signal.Signals) -> Callable[[Ctx], str]:
    def run(ctx: Ctx) -> str:
        out = ctx.tmp / "run.mcap"
        emu = Emulate(ctx, "--duration", "120", "--dashboard", "off", "--record", str(out))
        try:
            emu.ready()
            emu.at(1.0)
            kids = children(emu.p.pid)
            os.kill(emu.p.pid, sig)
            rc = emu.p.wait(timeout=WAIT_S)
            left, waited = wait_gone(kids, 60.0)
        finally:
            emu.kill()
        sc = McapScanner(out)
        for _ in sc.iter_batches():
            pass
        gone = (f"all {len(kids)} children gone {waited:.1f} s after emulate exited"
                if not left else f"**{len(left)} of {len(kids)} children still running**")
        return _cell(f"exit {rc}", gone, "recording complete (footer and index)" if sc.complete
                     else "recording truncated (recover with `diffpos recover`)")
    return run


def secured(ctx: Ctx) -> str:
    out = ctx.tmp / "run.mcap"
    emu = Emulate(ctx, "--security-profile", str(PROFILE), "--speed", "0", "--duration", "3",
                  "--dashboard", "off", "--record", str(out))
    try:
        rc, summary = emu.finish()
    finally:
        emu.kill()
    kinds: dict[str, int] = {}
    if out.exists():
        for c in summarize(out).channels:
            kinds[c.kind] = kinds.get(c.kind, 0) + c.count
    return _cell(f"exit {rc}", "secured bus" if summary.get("secured") else "**not secured**",
                 f"{summary.get('estimates')} estimates scored "
                 f"({summary.get('nodes')} nodes x {summary.get('expected_epochs_per_node')} "
                 "epochs)", f"recording: {kinds.get('estimate', 0)} estimates, "
                 f"{kinds.get('range', 0)} ranges, {kinds.get('truth_node', 0)} truth")


def foreign(ctx: Ctx) -> str:
    """A foreign process on the run's bus republishes every estimate with a moved position
    and poses as anchor uav9 (copies of uav1's messages)."""
    out = ctx.tmp / "run.mcap"
    emu = Emulate(ctx, "--channel", "ideal", "--speed", "0", "--duration", "3", "--dashboard",
                  "off", "--record", str(out))
    watch = None
    try:
        emu.ready()
        watch = Watch(emu.endpoint)
        z, s, keys = watch.zenoh, watch.session, watch.keys
        block = z.CongestionControl.BLOCK
        n_fake = [0, 0]

        def fake_estimate(sample) -> None:
            if sample.timestamp is not None:
                doc = json.loads(sample.payload.to_bytes())
                if doc.get("position_m"):
                    doc["position_m"] = [v + 5.0 for v in doc["position_m"]]
                s.put(str(sample.key_expr), json.dumps(doc).encode(), congestion_control=block)
                n_fake[0] += 1

        def fake_anchor(sample) -> None:
            key = str(sample.key_expr)
            doc = json.loads(sample.payload.to_bytes())
            doc["anchor_id"] = "uav9"
            s.put(key.replace("/anchor/uav1/", "/anchor/uav9/"), json.dumps(doc).encode(),
                  congestion_control=block)
            n_fake[1] += 1

        token = s.liveliness().declare_token(keys.alive_anchor("uav9"))
        watch.subs += [s.declare_subscriber(keys.estimates(), fake_estimate),
                       s.declare_subscriber(f"{keys.root}/anchor/uav1/**", fake_anchor)]
        rc, summary = emu.finish()
        token.undeclare()
    finally:
        emu.kill()
        if watch is not None:
            watch.close()
    used9 = sum("uav9" in e.used_anchors for _, e in watch.estimates)
    used9_text = "no fix used uav9" if not used9 else f"**{used9} fixes used uav9**"
    fusion = summary.get("fusion", {})
    rejected = (fusion.get("rejected") or {}).get("unknown_anchor", 0)
    rec_note = next((n for n in summary.get("notes", []) if n.startswith("recorder:")), "")
    rec_note = rec_note.replace(str(ctx.tmp) + "/", "")
    return _cell(
        f"exit {rc}", f"{n_fake[0]} fake estimates and {n_fake[1]} fake uav9 messages sent",
        f"summary: {summary.get('foreign', {}).get('count')} foreign messages reported, "
        f"{summary.get('estimates')} estimates scored "
        f"({summary.get('nodes')} nodes x {summary.get('expected_epochs_per_node')} epochs)",
        f"fusion: {rejected} uav9 messages rejected (unknown_anchor), {used9_text}",
        rec_note)


def stopped(service: str, arg: str | None = None, *, resume_s: float | None = None,
            duration: str = "20", name: str | None = None,
            dashboard: tuple[str, ...] = ("off",)) -> Callable[[Ctx], str]:
    """SIGSTOP ``diffpos <service>`` at t = 3 s (its token lives on: 10 s lease); with
    ``resume_s`` SIGCONT it that much later."""
    def run(ctx: Ctx) -> str:
        out = ctx.tmp / "run.mcap"
        emu = Emulate(ctx, "--channel", "ideal", "--duration", duration, "--dashboard",
                      *dashboard, "--record", str(out))
        seen = None
        try:
            emu.ready()
            emu.at(3.0)
            t_stop = emu.stop_child(emu.child(service, arg))
            if resume_s is not None:
                emu.at(3.0 + resume_s)
                for pid in emu.stopped:
                    os.kill(pid, signal.SIGCONT)
            else:
                seen = emu.wait_msg("service hung", name or service)
            rc, summary = emu.finish()
        finally:
            emu.kill()
        det = _detected(t_stop, seen, "hang detected") if resume_s is None else ""
        return _cell(f"exit {rc}", det, _hung_faults(summary), _lost(summary), _avail(summary))
    return run


def stopped2(ctx: Ctx) -> str:
    """SIGSTOP two of the four anchors at t = 3 s, never resumed."""
    emu = Emulate(ctx, "--channel", "ideal", "--duration", "20", "--dashboard", "off",
                  "--record", "off")
    try:
        emu.ready()
        emu.at(3.0)
        t_stop = emu.stop_child(emu.child("anchor", "uav1"))
        emu.stop_child(emu.child("anchor", "uav2"))
        seen = emu.wait_msg("service hung")
        rc, summary = emu.finish()
    finally:
        emu.kill()
    return _cell(f"exit {rc}", _detected(t_stop, seen, "first hang detected"),
                 _hung_faults(summary), _lost(summary), _avail(summary))


def killed_again(ctx: Ctx) -> str:
    """The fusion SIGKILLed once more than it is restarted."""
    emu = Emulate(ctx, "--channel", "ideal", "--duration", "300", "--dashboard", "off",
                  "--record", "off")
    try:
        emu.ready()
        for k in range(4):
            os.kill(emu.child("fusion"), signal.SIGKILL)
            t_kill = emu.wait_msg("service died", "fusion")
            if k < 3:
                emu.wait(lambda r, k=k: r.get("msg") == "service restarted"
                         and r.get("restart") == k + 1)
        t_end = None
        rc, summary = emu.finish()
        t_end = time.monotonic()
    finally:
        emu.kill()
    return _cell(f"exit {rc}", f"run ended {t_end - t_kill:.1f} s after the 4th kill "
                 f"(of 300 s): {summary.get('ended_early', '**not ended**')}",
                 f"{sum(f['service'] == 'fusion' for f in summary.get('faults', []))} fusion "
                 "faults reported")


def killed_other(service: str, arg: str | None = None) -> Callable[[Ctx], str]:
    """SIGKILL a service emulate does not restart (an anchor, the router) at t = 3 s."""
    def run(ctx: Ctx) -> str:
        emu = Emulate(ctx, "--channel", "ideal", "--duration", "10", "--dashboard", "off",
                      "--record", str(ctx.tmp / "run.mcap"))
        try:
            emu.ready()
            emu.at(3.0)
            name = f"anchor-{arg}" if service == "anchor" else service
            os.kill(emu.child(service, arg), signal.SIGKILL)
            t_kill = time.monotonic()
            seen = emu.wait_msg("service died", name)
            rc, summary = emu.finish()
        finally:
            emu.kill()
        return _cell(f"exit {rc}", _detected(t_kill, seen), _hung_faults(summary),
                     _lost(summary), _avail(summary))
    return run


def duplicate_anchor(ctx: Ctx) -> str:
    """A second process publishes under uav1's keys: copies of its messages moved 5 m."""
    emu = Emulate(ctx, "--channel", "ideal", "--speed", "0", "--duration", "3", "--dashboard",
                  "off", "--record", "off")
    watch = None
    try:
        emu.ready()
        watch = Watch(emu.endpoint)
        s, keys, sent = watch.session, watch.keys, [0, None]

        def fake(sample) -> None:
            if sample.attachment is None:  # our own copies come back
                return
            doc = json.loads(sample.payload.to_bytes())
            if "position_m" in doc:
                doc["position_m"] = [v + 5.0 for v in doc["position_m"]]
            s.put(str(sample.key_expr), json.dumps(doc).encode(),
                  congestion_control=watch.zenoh.CongestionControl.BLOCK)
            sent[0] += 1
            sent[1] = sent[1] or time.time_ns()

        watch.subs.append(s.declare_subscriber(f"{keys.root}/anchor/uav1/**", fake))
        rc, summary = emu.finish()
    finally:
        emu.kill()
        if watch is not None:
            watch.close()
    after = [e for rx, e in watch.estimates if sent[1] and rx > sent[1]]
    used = sum("uav1" in e.used_anchors for e in after)
    return _cell(f"exit {rc}", f"{sent[0]} copies sent under uav1's keys",
                 _hung_faults(summary), f"after the first copy {used} of {len(after)} "
                 "estimates used uav1", _avail(summary))


def forged_estimates(ctx: Ctx) -> str:
    """A forger reads the fusion's zenoh id prefix from an estimate, opens a session whose
    id has that prefix and publishes stamped estimates moved by 5 m."""
    out = ctx.tmp / "run.mcap"
    emu = Emulate(ctx, "--channel", "ideal", "--speed", "0", "--duration", "3", "--dashboard",
                  "off", "--record", str(out))
    watch = forger = None
    sent = [0]
    try:
        emu.ready()
        watch = Watch(emu.endpoint)
        while not watch.estimates:
            emu.wait(lambda r: True)  # a log line (progress) or more: then look again
        zid = watch.prefix
        cfg = ZenohSettings(connect=(emu.endpoint,)).to_config()
        cfg.insert_json5("id", json.dumps(zid[:16] + "0123456789abcdef"))
        cfg.insert_json5("timestamping/enabled", "true")
        forger = zenoh.open(cfg)

        def forge(sample) -> None:
            ts = sample.timestamp
            if ts is not None and not str(ts.get_id()).endswith("0123456789abcdef"):
                doc = json.loads(sample.payload.to_bytes())
                if doc.get("position_m"):
                    doc["position_m"] = [v + 5.0 for v in doc["position_m"]]
                doc["seq"] += 1_000_000
                forger.put(str(sample.key_expr), json.dumps(doc).encode(),
                           congestion_control=zenoh.CongestionControl.BLOCK)
                sent[0] += 1

        sub = forger.declare_subscriber(watch.keys.estimates(), forge)
        rc, summary = emu.finish()
        sub.undeclare()
    finally:
        emu.kill()
        if forger is not None:
            forger.close()
        if watch is not None:
            watch.close()
    recorded = forged = 0
    if out.exists():
        for batch in McapScanner(out).iter_batches():
            for m in batch:
                if m.topic.endswith("/estimate") and "/replay/" not in m.topic:
                    recorded += 1
                    forged += json.loads(m.data)["seq"] >= 1_000_000
    return _cell(f"exit {rc}", f"{sent[0]} forged estimates sent under an id with the "
                 "fusion's prefix", f"summary: {summary.get('foreign', {}).get('count')} "
                 f"foreign, {summary.get('estimates')} estimates scored",
                 f"recording: {recorded} estimates, {forged} forged")


CASES: list[Case] = [
    Case("15.2", "anchor `uav2` hung: SIGSTOP for 12 s (its 10 s lease expires), then SIGCONT "
         "(`--channel ideal --duration 24`)", hung_anchor,
         "tests/services/test_fusion_timing.py::test_stalled_anchor_never_stops_the_others_and"
         "_is_used_again + tests/system/test_faults.py::test_anchor_killed_and_hung_fusion_"
         "continues_and_takes_it_back"),
    Case("15.6", "fusion SIGKILLed at t = 3 s (`--duration 10 --record run.mcap`)",
         killed("fusion"),
         "tests/system/test_emulate_faults.py::test_dead_fusion_and_recorder_are_restarted_and"
         "_reported"),
    Case("15.6", "recorder SIGKILLed at t = 3 s (`--duration 10 --record run.mcap`)",
         killed("recorder"),
         "tests/system/test_emulate_faults.py::test_dead_fusion_and_recorder_are_restarted_and"
         "_reported"),
    Case("15.7", "SIGHUP to `emulate` (terminal closed) at t = 1 s of a 120 s run",
         signal_emulate(signal.SIGHUP),
         "tests/system/test_emulate_faults.py::test_sighup_stops_every_child"),
    Case("15.7", "SIGKILL of `emulate` at t = 1 s of a 120 s run",
         signal_emulate(signal.SIGKILL),
         "tests/system/test_emulate_faults.py::test_sigkill_of_emulate_stops_every_child"),
    Case("15.8", "secured run: `--security-profile security/profile.dev.toml --speed 0 "
         "--duration 3 --record run.mcap`", secured,
         "tests/system/test_security_emulate.py::test_secured_lockstep_emulate_records_and"
         "_reads_back"),
    Case("15.9", "foreign process on the run's bus: republishes every estimate moved by 5 m "
         "and poses as anchor `uav9` (copies of uav1)", foreign,
         "tests/system/test_emulate_faults.py::test_foreign_estimates_and_anchor_not_used_but"
         "_reported + tests/system/test_recorder_foreign.py::test_foreign_estimates_and_anchors"
         "_kept_apart_and_counted"),
    Case("36.1", "fusion hung: SIGSTOP at t = 3 s, never resumed (its token lives 10 s; "
         "`--duration 20 --record run.mcap`)", stopped("fusion"),
         "tests/system/test_emulate_progress.py::test_sigstopped_fusion_and_recorder_are_hung_faults_killed_and_restarted + "
         "tests/services/test_progress_integrity.py::test_silent_fusion_is_hung_killed_and_restarted"),
    Case("36.1", "recorder hung: SIGSTOP at t = 3 s, never resumed", stopped("recorder"),
         "tests/system/test_emulate_progress.py::test_sigstopped_fusion_and_recorder_are_hung_faults_killed_and_restarted"),
    Case("36.1", "anchor `uav2` hung: SIGSTOP at t = 3 s, never resumed",
         stopped("anchor", "uav2", name="anchor-uav2"),
         "tests/services/test_progress_integrity.py::test_hung_anchor_reported_left_running_and_resumes"),
    Case("36.1", "dashboard hung: SIGSTOP at t = 3 s, never resumed (`--dashboard save "
         "run.rrd`)", stopped("dashboard", dashboard=("save", "run.rrd")),
         "tests/system/test_heartbeats_recorded.py::test_a_stopped_dashboard_is_a_hung_fault_"
         "killed_not_restarted + tests/services/test_heartbeats_recorded_units.py::"
         "test_dashboard_heartbeat_counts_what_the_drain_loop_takes"),
    Case("36.1", "two of four anchors hung (`uav1`, `uav2`: SIGSTOP at t = 3 s)",
         stopped2, "tests/services/test_progress_integrity.py::test_hung_anchor_reported_left_running_and_resumes"),
    Case("36.1", "fusion stalled 2 s (SIGSTOP, SIGCONT 2 s later: shorter than the 5 s "
         "stall limit)", stopped("fusion", resume_s=2.0),
         "tests/services/test_progress_integrity.py::test_stuck_with_work_pending_is_hung_but_idle_is_not"),
    Case("36.1", "recorder stalled 2 s (SIGSTOP, SIGCONT 2 s later)",
         stopped("recorder", resume_s=2.0),
         "tests/services/test_progress_integrity.py::test_stuck_with_work_pending_is_hung_but_idle_is_not"),
    Case("36.1", "fusion SIGKILLed 4 times (restarted at most 3 times; `--duration 300`)",
         killed_again, "tests/system/test_emulate_progress.py::test_fusion_killed_beyond_its_restarts_ends_the_run + "
         "tests/services/test_progress_integrity.py::test_fusion_that_cannot_be_restarted_ends_the_run"),
    Case("36.1", "anchor `uav2` SIGKILLed at t = 3 s (anchors are not restarted)",
         killed_other("anchor", "uav2"),
         "tests/system/test_faults.py::test_anchor_killed_and_hung_fusion_continues_and_takes_"
         "it_back"),
    Case("36.1", "router SIGKILLed at t = 3 s (the bus of every service)",
         killed_other("router"),
         "tests/system/test_faults.py::test_router_killed_and_restarted_clients_reconnect_nothing_"
         "lost_after"),
    Case("36.4", "second publisher under anchor `uav1`'s keys: copies of its messages moved "
         "5 m (`--speed 0 --duration 3`)", duplicate_anchor,
         "tests/system/test_emulate_progress.py::test_duplicate_anchor_publisher_is_reported_and_not_trusted + "
         "tests/services/test_progress_integrity.py::test_guard_two_nonces_contested_until_one_remains"),
    Case("36.4", "forged estimates (moved 5 m) from a session whose zenoh id has the run's "
         "fusion id prefix, timestamped (`--speed 0 --duration 3 --record run.mcap`)",
         forged_estimates,
         "tests/system/test_emulate_progress.py::test_forged_estimates_under_the_fusion_id_prefix_are_not_ours + "
         "tests/services/test_progress_integrity.py::test_recorder_needs_the_mac_not_the_prefix"),
    Case("36.6", "SIGINT to `emulate` (Ctrl-C) at t = 1 s of a 120 s run",
         signal_emulate(signal.SIGINT),
         "tests/system/test_emulate_faults.py::test_sighup_stops_every_child"),
    Case("36.6", "SIGTERM to `emulate` at t = 1 s of a 120 s run",
         signal_emulate(signal.SIGTERM),
         "tests/system/test_emulate_faults.py::test_sighup_stops_every_child"),
]


# ----------------------------------------------------------------------------- the doc
def run_case(case: Case, exe: str) -> str:
    with tempfile.TemporaryDirectory(prefix="faults-") as tmp:
        try:
            return case.run(Ctx(Path(tmp), exe))
        except Exception as exc:  # the row says so; the table is still written
            return f"**failed**: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}"


def table(cases: Sequence[Case], exe: str, *, progress: bool = False) -> str:
    rows = ["| item | tried | now | test |", "| --- | --- | --- | --- |"]
    for k, case in enumerate(cases, start=1):
        if progress:
            print(f"[{k}/{len(cases)}] {case.item}: {case.tried}", file=sys.stderr)
        tests = " + ".join(f"`{t}`" for t in case.test.split(" + "))
        rows.append(f"| {case.item} | {case.tried} | {run_case(case, exe)} | {tests} |")
    return "\n".join(rows)


def splice(doc: str, body: str) -> str:
    """``doc`` with the text between the markers replaced by ``body`` (markers appended at the
    end if missing)."""
    if BEGIN not in doc or END not in doc:
        doc = doc.rstrip("\n") + f"\n\n{BEGIN}\n{END}\n"
    head, rest = doc.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{body}\n{END}{tail}"


def masked(text: str) -> str:
    """``text`` with every number masked except exit codes (what ``--check`` compares)."""
    return re.sub(r"(?<![\w.])(?<!exit )-?\d+(?:\.\d+)?(?![\w.])", "#", text)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--doc", type=Path, default=DOC, help="the markdown file to update")
    parser.add_argument("--check", action="store_true",
                        help="do not write; exit 1 if the doc's table is out of date (numbers "
                             "other than exit codes masked)")
    parser.add_argument("--only", metavar="TEXT",
                        help="only the cases whose item or description contains TEXT")
    args = parser.parse_args(argv)
    cases = [c for c in CASES if not args.only or args.only in f"{c.item} {c.tried}"]
    doc = args.doc.read_text(encoding="utf-8")
    new = splice(doc, table(cases, diffpos_exe(), progress=True))
    if args.check:
        if masked(new) != masked(doc):
            print(f"{args.doc} is out of date: run scripts/faults_table.py", file=sys.stderr)
            return 1
        return 0
    if new != doc:
        tmp = args.doc.with_name(args.doc.name + ".tmp")
        tmp.write_text(new, encoding="utf-8")
        tmp.replace(args.doc)
    print(f"{args.doc}: {len(cases)} cases", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
