"""The orchestrator of ``diffpos emulate``: :class:`Emulation` (see the package docstring).

Steps of :meth:`Emulation.run`: start the router -> open the orchestrator's session ->
start the fusion, anchors and extra services -> wait for their liveliness tokens -> publish
the run control -> :class:`~diffpos_services.emulate.monitor.Monitor` the run -> summary;
the services are always stopped in order (anchors, fusion, extras, router).
"""

from __future__ import annotations

import collections
import importlib.util
import json
import logging
import os
import queue
import secrets
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import zenoh

from diffpos.emulation import TimeBase, emulation_nodes
from diffpos_services.bus.commands import foreign_path
from diffpos_services.bus.integrity import RUN_TOKEN_ENV, Verifier, new_run_token
from diffpos_services.bus.security.per_run import per_run_profile
from diffpos_services.bus.security.profile import SecurityError, anchor_user, load_profile
from diffpos_services.bus.security.render import render_profile
from diffpos_services.bus.session import ZenohSettings, open_session, with_zenoh_config
from diffpos_services.emulate.monitor import Monitor
from diffpos_services.emulate.notes import (
    EndToEnd,
    foreign_notes,
    fusion_notes,
    latency_notes,
    loss_notes,
    model_notes,
    recording_notes,
)
from diffpos_services.emulate.options import EXTRA_SERVICES, EmulationOptions, channel_argv
from diffpos_services.emulate.scoring import Scorer
from diffpos_services.emulate.supervise import (
    NotRestarted,
    Supervisor,
    disk_full,
    fusion_name,
    recover_in_place,
    service_role,
)
from diffpos_services.errors import ConfigError, DiffposError
from diffpos_services.fusion.config import (
    LIVE_MAX_BACKLOG_S,
    FusionConfig,
    channel_edge,
    model_edge,
    tracker_argv,
)
from diffpos_services.fusion.prepare import groups_for, prepare_kernels, progress_display
from diffpos_services.logs import log_event
from diffpos_services.processes import child_env, free_tcp_port, stop_process_groups
from diffpos_services.recording.summary import set_losses
from diffpos_services.recording.writer import recording_set, restart_path
from diffpos_services.scenario_io import load_scenario_option, resolve_scenario
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

__all__ = ["MAX_NODE_LIST_CHARS", "RUN_DIR_PREFIXES", "Emulation", "claim_run_dir", "fusion_node_list",
           "merged_diagnostics",
           "reap_run_dirs"]

#: Longest node allow-list emulate writes on the fusion's command line [characters]: Linux
#: refuses to start a process with one argument over 128 KiB (E2BIG), e.g. 20,000 ids of 6
#: characters or 2,000 of 64.
MAX_NODE_LIST_CHARS = 100_000


def merged_diagnostics(diags: list[M.FusionDiagnostics]) -> M.FusionDiagnostics:
    """What one fusion would report for the fusion shards' diagnostics ``diags`` (each
    shard's newest): counters summed, the lowest watermark (the run's progress is its
    slowest shard's), the latency of the shard with the highest p99, the newest shard's
    anchor health and release rule; no decision record."""
    newest = max(diags, key=lambda d: d.t_wall_ns)

    def total(name: str) -> Any:
        vals = [getattr(d, name) for d in diags]
        if isinstance(vals[0], dict):
            out: collections.Counter = collections.Counter()
            for v in vals:
                out.update(v)
            return dict(out)
        return sum(vals)

    wms = [d.watermark_ns for d in diags]
    return msgspec.structs.replace(
        newest, watermark_ns=None if None in wms else min(wms),
        **{k: total(k) for k in ("received", "rejected", "gated", "solved", "published",
                                 "fixes_by_status", "late_ranges", "pending_epochs",
                                 "late_by_anchor", "releases")},
        latency=max((d.latency for d in diags), key=lambda s: s.p99_ms or -1.0),
        decisions=None)


def fusion_node_list(nodes: list[tuple[str, Any]], scenario: Any, scenario_file: str | None
                     ) -> tuple[list[str], list[str] | None]:
    """``(argv, ids)``: the fusion's ``--nodes`` for the emulated ``nodes`` and the allow-list
    it parses from them: their ids; ``scenario`` (the fusion reads the same file) when the
    list would be too long (:data:`MAX_NODE_LIST_CHARS`) and is the scenario's own
    (:func:`~diffpos.emulation.emulation_nodes`); else none (any node: the fusion declares
    the estimate publishers as the nodes appear)."""
    ids = [nid for nid, _ in nodes]
    text = ",".join(ids)
    if len(text) <= MAX_NODE_LIST_CHARS:
        return ["--nodes", text], ids
    if scenario_file and ids == [nid for nid, _ in emulation_nodes(scenario)]:
        return ["--nodes", "scenario"], ids
    return [], None


# ----------------------------------------------------------------------------- processes
@dataclass
class _Proc:
    name: str
    popen: subprocess.Popen
    log_path: Path | None
    argv: list[str]


#: prefixes of a run's folders in the temporary directory: ``diffpos-run-*`` (the recorder's
#: run configuration), ``diffpos-zenoh-*`` (the secured run's secrets, the bus configuration)
RUN_DIR_PREFIXES = ("diffpos-run-", "diffpos-zenoh-")
_OWNER_FILE = "owner.json"


def _start_ticks(pid: int) -> int | None:
    """A process's start time [clock ticks since boot] (``/proc/<pid>/stat`` field 22), or
    None when no such process exists: with the pid it names one process, never a reused pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat[stat.rindex(")") + 2:].split()[19])


def claim_run_dir(path: Path) -> None:
    """Write the owner (this process's pid and start time) into a run folder."""
    (path / _OWNER_FILE).write_text(json.dumps({"pid": os.getpid(),
                                                "start_ticks": _start_ticks(os.getpid())}))


def reap_run_dirs(tmp: str | os.PathLike[str] | None = None) -> list[Path]:
    """Remove the run folders (:data:`RUN_DIR_PREFIXES`, ours by uid) whose owner is gone:
    a SIGKILLed ``emulate`` cannot clean up after itself, so the next run does. A folder
    without an owner file, another user's, or one whose owner lives is left alone.

    Returns
    -------
    list of Path
        The folders removed.
    """
    out = []
    root = Path(tmp or tempfile.gettempdir())
    for d in (d for prefix in RUN_DIR_PREFIXES for d in root.glob(prefix + "*")):
        try:
            if not d.is_dir() or d.is_symlink() or d.stat().st_uid != os.getuid():
                continue
            owner = json.loads((d / _OWNER_FILE).read_text())
            pid, ticks = int(owner["pid"]), owner.get("start_ticks")
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if _start_ticks(pid) is not None and _start_ticks(pid) == ticks:
            continue  # its run is still going
        shutil.rmtree(d, ignore_errors=True)
        out.append(d)
    return out


class Emulation:
    """Orchestrates one emulated run (see module docstring).

    Parameters
    ----------
    options : EmulationOptions
    logger : logging.Logger
    stop : threading.Event
        Set by SIGINT/SIGTERM: the run ends early but still shuts down in order and summarises.
    """

    def __init__(self, options: EmulationOptions, logger: logging.Logger,
                 stop: threading.Event, *, dashboard_hint: str | None = None) -> None:
        options.check()
        if options.scenario is not None:
            # a shipped name ("paper") becomes its file, which every service can read
            options.scenario = str(resolve_scenario(options.scenario))
        self.o = options
        self.log = logger
        self.stop = stop
        self.dashboard_hint = dashboard_hint
        self.scenario = load_scenario_option(options.scenario)
        self.keys = Keys(options.site)
        self.nodes = emulation_nodes(self.scenario, max_nodes=options.max_nodes)
        if not self.nodes:
            raise ConfigError("the scenario has no nodes to emulate")
        self.anchor_ids = [a.id for a in self.scenario.anchors]
        # the fusion's path model (fusion.config: the one edge rule)
        edge = channel_edge(options.edge, options.channel)
        # only the scenario's anchors: a foreign publisher's anchor is never used in a fix;
        # only the emulated nodes, whose estimate publishers the fusion declares before the
        # run starts (else 8 per loop turn as the nodes appear; ~1 ms each)
        self.fusion_args = ["--epoch-period-s", str(1.0 / options.rate_hz),
                            "--delta-m", str(options.delta_m), "--edge", edge,
                            "--anchors", ",".join(self.anchor_ids)]
        nodes_argv, self.fusion_nodes = fusion_node_list(self.nodes, self.scenario,
                                                         options.scenario)
        self.fusion_args += nodes_argv
        if options.scenario:
            self.fusion_args += ["--scenario", options.scenario]
        if options.method is not None:
            self.fusion_args += ["--method", options.method]
        if options.speed == 0:  # lockstep: the input waits for the fusion, never behind
            self.fusion_args += ["--max-backlog-s", "0", "--unbounded-steps"]
        if options.fusion_workers != 1:
            self.fusion_args += ["--workers", str(options.fusion_workers)]
        self.fusion_args += tracker_argv(options.tracker)  # --tracker KEY=VALUE, each
        self.fusion_config, self.edge, self.edge_reason = self._fusion_config(edge)
        self.profile = None
        if options.security_profile is not None:
            self.profile = self._load_profile(options.security_profile)
            port = free_tcp_port()
            self.endpoint = options.endpoint or f"tls/localhost:{port}"
            # the router listens on the loopback address of the host it is dialled by
            host, _, port_s = self.endpoint[len("tls/"):].rpartition(":")
            self.listen = f"tls/{'127.0.0.1' if host == 'localhost' else host}:{port_s}"
        else:
            self.endpoint = options.endpoint or f"tcp/127.0.0.1:{free_tcp_port()}"
            self.listen = self.endpoint
        self.zenoh_files: dict[str, str] = {}
        self.run_id = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + uuid.uuid4().hex[:6]
        self.procs: list[_Proc] = []
        self.log_dir = Path(options.log_dir) if options.log_dir else None
        self.alive: set[str] = set()
        self.alive_event = threading.Condition()
        self.q: queue.Queue = queue.Queue()
        self._diag: M.FusionDiagnostics | None = None
        # with fusion shards: each shard's newest diagnostics (by shard: a restarted shard's
        # new zenoh id replaces the old one's), merged by the property ``diag``
        self._zid_shard: dict[str, int] = {}
        self._shard_diags: dict[int, M.FusionDiagnostics] = {}
        self._dec_diag = M.decoder(M.FusionDiagnostics)
        # estimates count only from the fusion this run started: its zenoh ids (one per
        # start), seen in the timestamps its session puts on every sample
        self.fusion_ids: set[str] = set()
        # every fusion start's id begins with the run's prefix (the dashboard checks that)
        self.fusion_id_prefix = f"{secrets.randbits(60) | (1 << 60):x}"
        self.foreign: collections.Counter[str] = collections.Counter()
        # the run's secret token: handed to the services in their environment; the fusion
        # signs what it publishes with it, and "ours" is its MAC bound to the full zenoh id
        self.run_token = new_run_token()
        self.verifier = Verifier(bytes.fromhex(self.run_token))
        self.dec_heartbeat = M.decoder(M.Heartbeat)
        self.tmp: tempfile.TemporaryDirectory | None = None
        self.supervisor = Supervisor(lambda: [(p.name, p.popen) for p in self.procs],
                                     self._restart, logger)
        self.recordings: list[str] = []
        self.recording_notes: list[str] = []
        self.t0_wall_ns: int | None = None  # wall clock of the run's start [ns]
        # anchor publish -> estimate received here, per estimate (the live status may show
        # e2e.stats_ms(since) of the last seconds)
        self.e2e = EndToEnd()
        # --channel raytrace: what was traced before the run (diffpos emulate sets it:
        # diffpos_services.raytrace.live.prepare_for_run), kept in the run configuration
        self.raytrace: dict[str, Any] | None = None

    # -------------------------------------------------------------- security
    def _load_profile(self, path: str):
        try:
            profile = load_profile(path)
        except (SecurityError, OSError) as exc:
            raise ConfigError(f"--security-profile {path}: {exc}") from None
        # only its identities are used: the run gets fresh secrets (_render_security)
        ids = profile.identities()
        missing = [a for a in self.anchor_ids if anchor_user(a) not in ids]
        if missing:
            raise ConfigError(
                f"--security-profile {path}: anchors {missing} of the scenario have no identity "
                "(add them to 'anchors' in the profile and a password line for anchor-<id>)")
        for role in ("fusion", "emulator"):
            if role not in profile.users:
                raise ConfigError(f"--security-profile {path}: users.{role} is missing")
        if profile.site not in ("*", self.o.site):
            raise ConfigError(
                f"--security-profile {path}: it covers site {profile.site!r}, not --site {self.o.site}")
        return profile

    def _render_security(self, out_dir: str) -> None:
        """Fresh passwords and certificates for this run in the private folder ``out_dir``
        (never the profile's committed dev secrets), the profile rendered from them for this
        run's endpoint; remember each identity's file."""
        host = self.endpoint[len("tls/"):].rpartition(":")[0].strip("[]")
        try:
            run_profile = per_run_profile(self.profile, out_dir,
                                          hosts=[host, "localhost", "127.0.0.1"])
            written = render_profile(run_profile, Path(out_dir) / "zenoh",
                                     connect=[self.endpoint], listen=[self.listen])
        except SecurityError as exc:
            raise ConfigError(f"--security-profile {self.o.security_profile}: {exc}") from None
        self.zenoh_files = {p.stem: str(p) for p in written}
        log_event(self.log, logging.INFO, "secured bus: fresh passwords and certificates for "
                  "this run (removed at the end)", dir=out_dir)

    def _zargs(self, role: str, anchor_id: str | None = None) -> list[str] | None:
        """``--connect`` (plain) or ``--zenoh-config <file>`` of ``role``; ``None`` if the
        profile has no identity for it."""
        if self.profile is None:
            return ["--connect", self.endpoint]
        if role == "router":
            return ["--zenoh-config", self.zenoh_files["router"]]
        user = f"anchor-{anchor_id}" if role == "anchor" else self.profile.users.get(role)
        if user is None or user not in self.zenoh_files:
            return None
        return ["--zenoh-config", self.zenoh_files[user]]

    @property
    def diag(self) -> M.FusionDiagnostics | None:
        """The fusion's newest diagnostics (the monitor sets them); with fusion shards, every
        shard's newest merged (:func:`merged_diagnostics`; ``None`` until each reported)."""
        if self.o.fusion_shards == 1:
            return self._diag
        diags = list(self._shard_diags.values())
        return merged_diagnostics(diags) if len(diags) == self.o.fusion_shards else None

    @diag.setter
    def diag(self, value: M.FusionDiagnostics | None) -> None:
        self._diag = value

    def _fusion_zargs(self, shard: int = 0) -> list[str]:
        """``--zenoh-config <file>`` of a fusion start: its bus settings (plain, or its
        identity file of the secured bus) with a fresh zenoh id and timestamping on, so every
        sample it publishes carries that id (:meth:`_on_data` counts only those)."""
        base = self._zargs("fusion")
        if base is None:
            raise ConfigError("the security profile has no identity for the fusion")
        if base[0] == "--zenoh-config":
            cfg = zenoh.Config.from_file(base[1])
        else:
            cfg = ZenohSettings(connect=(self.endpoint,)).to_config()
        zid = f"{self.fusion_id_prefix}{secrets.randbits(64):016x}"  # 16 bytes
        cfg.insert_json5("id", json.dumps(zid))
        cfg.insert_json5("timestamping/enabled", "true")
        path = Path(self.tmp.name) / f"fusion-{len(self.fusion_ids)}.json5"
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(str(cfg))
        self.fusion_ids.add(zid)
        self._zid_shard[zid] = shard
        return ["--zenoh-config", str(path)]

    def _restart(self, name: str, n: int) -> str:
        """Start service ``name`` again (the supervisor's ``n``-th restart of it); what was
        done, for the faults report."""
        old = next(p for p in reversed(self.procs) if p.name == name)
        argv = list(old.argv)
        note = ""
        if service_role(name) == "fusion":
            i = argv.index("--zenoh-config")
            k = argv.index("--shard") if "--shard" in argv else None
            argv[i:i + 2] = self._fusion_zargs(0 if k is None else
                                               int(argv[k + 1].partition("/")[0]))
            note = "resumed from the bus (epochs while it was down have no estimate)"
        elif name == "recorder":
            i = argv.index("--out")
            dead = argv[i + 1]
            full = disk_full(dead)
            if full is not None:  # no restart onto a full disk: it would write 0-byte files
                note = f"{full}; {recover_in_place(dead)}"
                self.recording_notes.append(f"recorder: {note}")
                raise NotRestarted(note)
            new = restart_path(self.recordings[0], n)
            argv[i + 1] = str(new)
            self.recordings.append(str(new))
        self._spawn(name, argv)
        if name == "recorder":
            note = f"new file {new}; {recover_in_place(dead)}"
            self.recording_notes.append(note)
        return note

    # -------------------------------------------------------------- process helpers
    def _spawn(self, name: str, argv: list[str]) -> _Proc:
        cmd = [sys.executable, "-m", "diffpos_services.cli.main", *argv, "--log-level", self.o.log_level]
        log_path = None
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            log_path = self.log_dir / f"{name}.log"
            # a restarted service appends to the log of the one that died
            err = open(log_path, "ab" if any(p.name == name for p in self.procs) else "wb")
        else:
            err = subprocess.DEVNULL
        # the child stops when emulate dies, even by SIGKILL (kit.die_with_parent)
        env = child_env(dict(os.environ, DIFFPOS_LOG_FORMAT="json"))
        # each child gets its bus explicitly (--connect or its own --zenoh-config): an
        # inherited default file would replace the run's router configuration
        env.pop("DIFFPOS_ZENOH_CONFIG", None)
        if name != "router":  # never on a command line (ps shows those to every user)
            env[RUN_TOKEN_ENV] = self.run_token
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                             start_new_session=True, env=env)
        if err is not subprocess.DEVNULL:
            err.close()
        proc = _Proc(name, p, log_path, list(argv))
        self.procs.append(proc)
        log_event(self.log, logging.DEBUG, "started", service=name, pid=p.pid, argv=" ".join(argv))
        return proc

    def _stop_procs(self, names: Callable[[str], bool], timeout_s: float = 8.0) -> None:
        group = {p.popen: p.name for p in self.procs if names(p.name) and p.popen.poll() is None}
        stop_process_groups(
            list(group), timeout_s=timeout_s,
            on_kill=lambda pp: log_event(self.log, logging.WARNING,
                                         "did not stop on SIGTERM, killing", service=group[pp]))

    def _fusion_config(self, edge: str) -> tuple[FusionConfig, str, str]:
        """The fusion's config exactly as ``diffpos fusion`` builds it from ``fusion_args``."""
        cfg = FusionConfig.from_scenario(self.scenario, edge=edge, site=self.o.site,
                                         anchors=list(self.anchor_ids),
                                         nodes=self.fusion_nodes,
                                         delta_m=self.o.delta_m,
                                         epoch_period_s=1.0 / self.o.rate_hz,
                                         max_backlog_s=(None if self.o.speed == 0
                                                        else LIVE_MAX_BACKLOG_S),
                                         bounded_steps=self.o.speed != 0,
                                         workers=self.o.fusion_workers,
                                         tracker=dict(self.o.tracker),
                                         **({} if self.o.method is None
                                            else {"method": self.o.method}))
        edge, why = model_edge(edge, self.scenario)
        return cfg, edge, why

    def _write_run_config(self) -> str:
        """A JSON run configuration for the recorder (``{"fusion": ..., "emulate": ...}``), in
        this run's folder ``diffpos-run-*`` (with its owner, for :func:`reap_run_dirs`)."""
        self._run_dir = tempfile.TemporaryDirectory(prefix=RUN_DIR_PREFIXES[0])
        claim_run_dir(Path(self._run_dir.name))
        path = Path(self._run_dir.name) / "run_config.json"
        doc = {"fusion": msgspec.to_builtins(self.fusion_config),
               "emulate": {"run_id": self.run_id, "channel": self.o.channel, "seed": self.o.seed,
                           "edge": self.edge, "edge_reason": self.edge_reason,
                           "raytrace": self.raytrace,
                           # the recorder keeps other publishers' estimates apart (recorder.py)
                           "fusion_id_prefix": self.fusion_id_prefix,
                           # "fusion" is the whole run's: one fusion publishes what the
                           # shards (diffpos fusion --shard K/N) published together
                           "fusion_shards": self.o.fusion_shards}}
        n = self.o.fusion_shards
        if n > 1:  # what each shard ran (diffpos fusion --shard K/N): replay runs each
            doc["fusion_by_shard"] = [msgspec.to_builtins(msgspec.structs.replace(
                self.fusion_config, shard=k, shards=n)) for k in range(n)]
        path.write_text(json.dumps(doc, indent=2), encoding="utf-8")
        return str(path)

    def shutdown(self) -> None:
        """Stop in dependency order: anchors, fusion, extras, router (no restarts from now
        on; the supervisor's thread ends after the children it started)."""
        self.supervisor.stopping()
        self._stop_procs(lambda n: n.startswith("anchor-"))
        self._stop_procs(lambda n: service_role(n) == "fusion")
        self._stop_procs(lambda n: n in EXTRA_SERVICES)
        self._stop_procs(lambda n: True)
        self.supervisor.close()
        if getattr(self, "_run_dir", None) is not None:
            self._run_dir.cleanup()

    def _check_children(self) -> None:
        for p in self.procs:
            rc = p.popen.poll()
            if rc is not None:
                hint = f" (log: {p.log_path})" if p.log_path else " (rerun with --log-dir DIR)"
                raise ConfigError(f"service {p.name} exited early with code {rc}{hint}")

    # -------------------------------------------------------------- run
    def _on_alive(self, sample) -> None:
        key = str(sample.key_expr)
        with self.alive_event:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(key)
            else:
                self.alive.discard(key)
            self.alive_event.notify_all()
        self.q.put(("alive", key, sample.kind == zenoh.SampleKind.PUT))

    def _on_heartbeat(self, sample) -> None:
        """A service's heartbeat (signed with the run token) to the supervisor."""
        if not self.verifier.ours(sample, stamped=False):
            self.foreign[str(sample.key_expr)] += 1
            return
        try:
            hb = self.dec_heartbeat(sample.payload.to_bytes())
        except M.DecodeError:
            return
        self.supervisor.on_heartbeat(hb.pid, hb.progress, hb.pending)
        if self.o.fusion_shards > 1:
            with self.alive_event:  # (readiness waits for every shard's first heartbeat)
                self.alive_event.notify_all()

    def _on_data(self, sample) -> None:
        key = str(sample.key_expr)
        ts = sample.timestamp
        # the run's own: stamped with the full id of a fusion this run started, and signed
        # with the run's token (a copy, or a session posing under that id, is not)
        if ts is None or str(ts.get_id()) not in self.fusion_ids \
                or not self.verifier.ours(sample):
            # not from the fusion this run started: reported, never counted or scored
            self.foreign[key] += 1
            return
        # (kind, key, payload, receive wall time [ns]: the end-to-end latency of an estimate
        # is this minus its t_input_wall_ns)
        payload, rx = sample.payload.to_bytes(), time.time_ns()
        pk = parse_key(key)
        if pk is not None and pk.kind == "estimate":
            self.e2e.add(payload, rx)
        elif pk is not None and pk.kind == "diagnostics" and self.o.fusion_shards > 1:
            try:  # (about once a second per shard)
                self._shard_diags[self._zid_shard[str(ts.get_id())]] = self._dec_diag(payload)
            except M.DecodeError:
                pass  # (the monitor reports it)
        self.q.put(("data", key, payload, rx))

    def _wait_ready(self, need: set[str]) -> None:
        deadline = time.monotonic() + self.o.ready_timeout_s
        with self.alive_event:
            while not (need <= self.alive and self._fusions_heard()):
                if self.stop.is_set():
                    return
                self._check_children()
                if time.monotonic() > deadline:
                    missing = sorted(need - self.alive) or [
                        f"{p.name} (no heartbeat)" for p in self.procs
                        if service_role(p.name) == "fusion"
                        and not self.supervisor.heard([p.popen.pid])]
                    raise ConfigError(f"services not ready after {self.o.ready_timeout_s:.0f} s: {missing}")
                self.alive_event.wait(0.2)

    def _fusions_heard(self) -> bool:
        """Every fusion process sent a heartbeat: the supervisor judges a process from its
        first heartbeat on, so a fusion that stops before it would never be found hung; and
        fusion shards share the one ``alive/fusion`` token key, whose first token says nothing
        of the others."""
        return self.supervisor.heard([p.popen.pid for p in self.procs
                                      if service_role(p.name) == "fusion"])

    def _prepare_kernels(self) -> None:
        """Compile the numba kernels this run needs (or load them from numba's on-disk cache)
        before any service starts, in parallel worker processes (:mod:`diffpos_services.fusion.
        prepare`: the groups of the fusion's method, and the SNR kernels of the emulated
        channel), so the fusion and the anchors load them in about a second instead of each
        compiling them (over a minute of CPU on a fresh machine, which would also run past the
        services' readiness timeout). A moving status line with an estimate says so when it
        takes long (the first run on a machine), and the log records how long it took."""
        cfg = self.fusion_config
        groups = groups_for(cfg.method, tracking=cfg.tracking,
                            channel=self.o.channel == "emulator")
        took = prepare_kernels(groups, progress=progress_display(say_done=False), stop=self.stop)
        if took.wall_s > 5.0:
            log_event(self.log, logging.INFO, "compiled the solver kernels (cached for later runs)",
                      seconds=round(took.wall_s, 1), groups=groups,
                      worker_cpu_s=list(took.worker_cpu_s))

    def run(self) -> dict[str, Any]:
        """Run the emulation; returns the summary dictionary (empty if stopped before the
        run started)."""
        # private (0700): the run's secrets and the fusion's bus configuration
        reaped = reap_run_dirs()  # a SIGKILLed run's folders (secrets among them)
        if reaped:
            log_event(self.log, logging.INFO, "removed the folders of killed runs",
                      folders=[p.name for p in reaped])
        self.tmp = tmp = tempfile.TemporaryDirectory(prefix=RUN_DIR_PREFIXES[1])
        claim_run_dir(Path(tmp.name))
        try:
            self._prepare_kernels()
            session = open_session(self._start_router(tmp if self.profile else None), self.stop,
                                   logger=self.log)
            if session is None:
                return {}
            with session:
                live = session.liveliness().declare_subscriber(self.keys.alive_all(),
                                                               self._on_alive, history=True)
                subs = [session.declare_subscriber(k, self._on_data)
                        for k in (self.keys.estimates(), self.keys.fusion_diagnostics())]
                subs.append(session.declare_subscriber(self.keys.heartbeats(),
                                                       self._on_heartbeat))
                need = self._start_services()
                t_ready = time.monotonic()
                self._wait_ready(need)
                if self.stop.is_set():
                    return {}
                self._announce_ready(t_ready)
                tb = self._start_run(session)
                self.supervisor.start(t0=time.monotonic())
                monitor = Monitor(self, session, tb)
                monitor.run()
                self.supervisor.stopping()
                for s in subs:
                    s.undeclare()
                live.undeclare()
                summary = self._summary(monitor.scorer, monitor.lost_events)
        finally:
            self.shutdown()
            tmp.cleanup()
        return self._with_recording_losses(summary)

    def _with_recording_losses(self, summary: dict[str, Any]) -> dict[str, Any]:
        """The messages missing by sequence number across every file the recorder(s) wrote
        (read once the recorder has finished its file): ``recording_losses`` and a note."""
        if not self.recordings or not recording_set(self.recordings[0]):
            return summary
        try:
            losses = set_losses(self.recordings[0])
        except DiffposError as exc:
            summary["notes"].append(f"recording: losses not counted ({exc})")
            return summary
        summary["recording_losses"] = {"missing": losses.missing, "by_stream": losses.by_stream,
                                       "files": losses.files,
                                       "holes": [list(h) for h in losses.holes[:50]]}
        summary["notes"].append(losses.line())
        return summary

    def _start_router(self, tmp: tempfile.TemporaryDirectory | None) -> ZenohSettings:
        """Start the router (secured: render the profile into ``tmp`` first); the
        orchestrator's own bus settings."""
        if tmp is not None:
            self._render_security(tmp.name)
            self._spawn("router", ["router", *self._zargs("router")])
            return with_zenoh_config(ZenohSettings(connect=(self.endpoint,)),
                                     self.zenoh_files[self.profile.users["emulator"]],
                                     logger=self.log)
        self._spawn("router", ["router", "--listen", self.listen])
        return with_zenoh_config(ZenohSettings(connect=(self.endpoint,)), logger=self.log)

    def _start_services(self) -> set[str]:
        """Start the fusion, the anchors and the extra services; the liveliness keys to
        wait for."""
        o = self.o
        rng = np.random.default_rng(o.seed)
        offsets = rng.uniform(-o.clock_offset_max_ms, o.clock_offset_max_ms, len(self.anchor_ids))
        scen = ["--scenario", o.scenario] if o.scenario else []
        n = o.fusion_shards
        for k in range(n):  # each shard owns the responders whose id's CRC-32 mod n is k
            shard = ["--shard", f"{k}/{n}"] if n > 1 else []
            self._spawn(fusion_name(k, n), ["fusion", "--site", o.site, *self._fusion_zargs(k),
                                            *self.fusion_args, *shard])
        for aid, off in zip(self.anchor_ids, offsets, strict=True):
            self._spawn(f"anchor-{aid}", [
                "anchor", "--id", aid, "--site", o.site, *self._zargs("anchor", aid),
                "--seed", str(o.seed), "--rate-hz", str(o.rate_hz), "--wait-start",
                "--clock-offset-ms", f"{off:.4f}", *channel_argv(o),
                "--max-nodes", str(o.max_nodes), *scen])
        need = {self.keys.alive_anchor(a) for a in self.anchor_ids} | {self.keys.alive_fusion()}
        for name, (module, build, ready_key) in EXTRA_SERVICES.items():
            argv = self._extra_argv(name, build)
            if argv is not None and importlib.util.find_spec(module) is not None:
                self._spawn(name, argv)
                if ready_key is not None:
                    need.add(ready_key(self.keys))
        return need

    def _extra_argv(self, name: str, build: Callable[..., list[str] | None]) -> list[str] | None:
        """The command line of extra service ``name`` (None: not started)."""
        argv = build(self.o, self.endpoint, self.run_id)
        if argv is not None and self.profile is not None:
            # the same command with this role's identity file instead of --connect
            z = self._zargs(name)
            if z is None:
                log_event(self.log, logging.WARNING, "not started: the security "
                          "profile has no identity for it", service=name)
                argv = None
            else:
                i = argv.index("--connect")
                argv = argv[:i] + z + argv[i + 2:]
        if argv is not None and name == "dashboard":
            argv = [*argv, "--estimates-from", self.fusion_id_prefix]
        if argv is not None and name == "recorder":
            # the fusion settings travel with the recording: replay reproduces live
            argv = [*argv, "--run-config", self._write_run_config()]
            self.recordings = [argv[argv.index("--out") + 1]]
        return argv

    def _announce_ready(self, t_ready: float) -> None:
        log_event(self.log, logging.INFO, "all services ready",
                  anchors=len(self.anchor_ids), nodes=len(self.nodes),
                  ready_s=round(time.monotonic() - t_ready, 2), endpoint=self.endpoint)
        hint = self.dashboard_hint if "dashboard" in {p.name for p in self.procs} else None
        if hint:
            log_event(self.log, logging.DEBUG, "dashboard", how=hint)  # the line below says it
            print(f"dashboard: {hint}", file=sys.stderr, flush=True)

    def _start_run(self, session: Any) -> TimeBase:
        """Publish the run control: the run starts 0.3 s from now, on the fusion's epoch grid
        (epoch k = [kT, (k+1)T))."""
        o = self.o
        period = round(1e9 / o.rate_hz)
        wall_t0 = -(-(time.time_ns() + 300_000_000) // period) * period
        rc = M.RunControl(run_id=self.run_id, t0_ns=wall_t0, wall_t0_ns=wall_t0,
                          speed=o.speed or 1.0, duration_ns=round(o.duration_s * 1e9),
                          seed=o.seed, lockstep=o.speed == 0)
        session.put(self.keys.run_control(), M.encode(rc),
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK)
        self.t0_wall_ns = wall_t0
        return TimeBase.from_control(rc)

    def _integrity_faults(self) -> list[dict[str, Any]]:
        """Anchors under whose key two processes published (the fusion's diagnostics):
        a fault each (the fusion did not use the anchor meanwhile)."""
        d = self.diag
        dup = getattr(d, "duplicate_publishers", None) or {}
        return [{"service": f"anchor-{a}", "died_s": None, "exit_code": None,
                 "restarted_s": None, "kind": "duplicate publisher", "detected_after_s": None,
                 "note": (f"two processes published under its key ({n} time(s)); the fusion "
                          "did not use it while both did"
                          + (" (still contested at the end)" if a in d.contested_anchors
                             else ""))}
                for a, n in sorted(dup.items())]

    def _summary(self, scorer: Scorer, lost: list[str]) -> dict[str, Any]:
        """The run's summary: the scorer's statistics, the run and the fusion's counters."""
        o = self.o
        out = scorer.summary()
        expected_epochs = int(o.duration_s * o.rate_hz)
        # one snapshot of the foreign counter for the summary and its note (the bus callback
        # may still count copies of the last estimates while the summary is written)
        foreign = dict(self.foreign)
        out.update(
            run_id=self.run_id, endpoint=self.endpoint, anchors=len(self.anchor_ids),
            secured=self.profile is not None,
            nodes=len(self.nodes), duration_s=o.duration_s, speed=o.speed, channel=o.channel,
            expected_epochs_per_node=expected_epochs,
            epochs_per_node_min=min((len(v) for v in scorer.epochs.values()), default=0),
            lost=lost,
            model=f"{self.edge} window edge, Delta {o.delta_m:g} m ({self.edge_reason})",
            recording=self.recordings[0] if self.recordings else None,
            recordings=list(self.recordings), recording_notes=list(self.recording_notes),
            faults=[f.as_dict() for f in self.supervisor.faults] + self._integrity_faults(),
            foreign={"count": sum(foreign.values()), "keys": foreign},
        )
        if self.supervisor.fatal is not None:
            out["ended_early"] = self.supervisor.fatal
        out["latency_e2e_ms"] = self.e2e.stats_ms()
        # the same estimates without the scorer's first skip_s (in wall time: not lockstep)
        skip_ns = round(scorer.k_skip * scorer.period_ns)
        out["latency_e2e_settled_ms"] = (
            None if self.t0_wall_ns is None or not o.speed else self.e2e.stats_ms(
                inputs_since_wall_ns=self.t0_wall_ns + round(skip_ns / o.speed)))
        # when and why fixes were lost, every file written, foreign messages: plain lines
        out["notes"] = [*model_notes(self.o.channel, self.fusion_config.method),
                        *loss_notes(scorer), *fusion_notes(self.diag, self.t0_wall_ns),
                        *recording_notes(self.recordings,
                                         [foreign_path(r) for r in self.recordings]),
                        *foreign_notes(foreign),
                        *([self.supervisor.fatal] if self.supervisor.fatal else []),
                        *latency_notes(out["latency_e2e_ms"], out["latency_e2e_settled_ms"],
                                       skip_ns * 1e-9)]
        if self.diag is not None:
            d = self.diag
            out["fusion"] = {"received": d.received, "rejected": d.rejected, "gated": d.gated,
                             "solved": d.solved, "late_ranges": d.late_ranges,
                             "latency_ms": {"p50": d.latency.p50_ms, "p99": d.latency.p99_ms}}
        return out
