"""The one-command emulation: router, anchors, fusion (+ recorder, dashboard) as processes.

:class:`Emulation` starts every service as its own OS process (``python -m
diffpos_services.cli.main <service> ...``, each in its own session so a terminal Ctrl-C reaches
only the orchestrator), waits for readiness by liveliness tokens (never by sleeping), starts
the run by publishing the time base (``RunControl``), publishes ground truth on its own keys,
scores the estimates against the true trajectories, and shuts the services down in order
(anchors, fusion, extras, router last) with SIGTERM, escalating to SIGKILL only if a process
does not exit in time.

Extra services (recorder, dashboard) are hooks: :data:`EXTRA_SERVICES` maps a name to a
function building its command line; one is started only if its CLI module exists.

With ``security_profile`` (``diffpos emulate --security-profile FILE``) the bus is the
secured one of security/README.md: the profile is rendered into a private temporary folder
for a TLS endpoint on a free loopback port; the router loads its configuration (TLS
listener, password dictionary, access control), every child gets its own identity file
(``--zenoh-config <tmp>/<user>.json5``) and the orchestrator logs in as the emulator.
"""

from __future__ import annotations

import collections
import importlib.util
import json
import logging
import os
import queue
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from diffpos.emulation import TimeBase, emulation_nodes
from diffpos_services.bus.session import ZenohSettings, open_session, with_zenoh_config
from diffpos_services.fusion.config import FusionConfig, model_edge
from diffpos_services.kit import ConfigError, free_tcp_port, log_event, stop_process_groups
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

__all__ = ["EXTRA_SERVICES", "Emulation", "EmulationOptions", "Scorer", "free_tcp_port"]


@dataclass
class EmulationOptions:
    """What ``diffpos emulate`` runs (validated by :meth:`check`)."""

    scenario: str | None = None
    duration_s: float = 20.0
    speed: float = 1.0
    site: str = "demo"
    seed: int = 0
    endpoint: str | None = None
    channel: str = "emulator"
    max_nodes: int = 0
    rate_hz: float = 10.0
    clock_offset_max_ms: float = 2.0
    record: str | None = "auto"
    dashboard: list[str] = field(default_factory=lambda: ["auto"])
    log_dir: str | None = None
    progress: bool = True
    ready_timeout_s: float = 60.0
    log_level: str = "info"
    delta_m: float = 0.0
    edge: str = "auto"
    security_profile: str | None = None

    def check(self) -> None:
        if not self.duration_s > 0:
            raise ConfigError(f"--duration must be > 0 seconds, got {self.duration_s}")
        if not 0 <= self.speed <= 1000:
            raise ConfigError(f"--speed must be in [0, 1000] (0 = lockstep), got {self.speed}")
        if not self.rate_hz > 0:
            raise ConfigError(f"--rate-hz must be > 0, got {self.rate_hz}")
        if self.channel not in ("emulator", "ideal"):
            raise ConfigError(f"--channel must be emulator or ideal, got {self.channel!r}")
        if self.edge not in ("auto", "upper", "lower"):
            raise ConfigError(f"--edge must be auto, upper or lower, got {self.edge!r}")
        if self.security_profile is not None:
            if self.speed == 0:
                raise ConfigError(
                    "--security-profile with --speed 0: the access rules do not grant the "
                    "lockstep run clock (diffpos/<site>/run/clock); use --speed > 0")
            if self.endpoint is not None and not self.endpoint.startswith("tls/"):
                raise ConfigError(
                    f"--endpoint {self.endpoint}: with --security-profile use a tls/ endpoint "
                    "whose host is in the router certificate, e.g. tls/localhost:7447")


def _recorder_argv(o: EmulationOptions, endpoint: str, run_id: str) -> list[str] | None:
    if o.record in (None, "off", ""):
        return None
    argv = ["recorder", "--site", o.site, "--connect", endpoint, "--out", recording_path(o, run_id)]
    if o.scenario:
        argv += ["--scenario", o.scenario]
    return argv


def recording_path(o: EmulationOptions, run_id: str) -> str | None:
    """Where the recorder writes: ``--record PATH``, or for ``auto``
    ``recordings/<scenario>-<UTC run id>.mcap`` (``None`` when recording is off)."""
    if o.record in (None, "off", ""):
        return None
    if o.record != "auto":
        return o.record
    scenario = Path(o.scenario).stem if o.scenario else "paper-default"
    return str(Path("recordings") / f"{scenario}-{run_id}.mcap")


def _dashboard_argv(o: EmulationOptions, endpoint: str, run_id: str) -> list[str] | None:
    if not o.dashboard or o.dashboard[0] == "off":
        return None
    argv = ["dashboard", "--site", o.site, "--connect", endpoint, "--rerun", *o.dashboard]
    # without a scenario file the run uses the built-in default: draw that building
    argv += ["--scenario", o.scenario or "default"]
    return argv


def dashboard_hint(o: EmulationOptions) -> str | None:
    """How to open the dashboard that ``diffpos emulate`` starts (``None`` when it is off)."""
    if not o.dashboard or o.dashboard[0] == "off":
        return None
    from diffpos_services.dashboard.service import RerunTarget, describe_target

    mode = o.dashboard[0]
    path = o.dashboard[1] if mode == "save" and len(o.dashboard) > 1 else None
    return describe_target(RerunTarget(mode=mode, path=path))


#: name -> (CLI module that must exist, argv builder, liveliness key to wait for or None).
#: Add a service here to have ``diffpos emulate`` start (and stop) it with the others; with
#: a readiness key the run starts only once that token is alive (nothing is missed).
EXTRA_SERVICES: dict[
    str,
    tuple[str, Callable[[EmulationOptions, str, str], list[str] | None],
          Callable[[Keys], str] | None],
] = {
    "recorder": ("diffpos_services.cli.recorder", _recorder_argv, Keys.alive_recorder),
    "dashboard": ("diffpos_services.cli.dashboard", _dashboard_argv, None),
}


# ----------------------------------------------------------------------------- scoring
class Scorer:
    """Errors of the estimates against the true node trajectories (emulation only)."""

    def __init__(self, nodes: list[tuple[str, Any]], building, t0_ns: int) -> None:
        self.traj = dict(nodes)
        self.building = building
        self.t0_ns = t0_ns
        self.count = 0
        self.status: collections.Counter[str] = collections.Counter()
        self.err3d: list[float] = []
        self.errz: list[float] = []
        self.floor_ok: list[bool] = []
        self.peb: list[float] = []
        self.epochs: dict[str, set[int]] = collections.defaultdict(set)

    def add(self, est: M.PositionEstimate) -> float | None:
        self.count += 1
        self.status[est.status] += 1
        self.epochs[est.node_id].add(est.epoch)
        tr = self.traj.get(est.node_id)
        if tr is None or est.position_m is None:
            return None
        truth = np.asarray(tr.position_m((est.t_ns - self.t0_ns) * 1e-9), float)
        d = np.asarray(est.position_m) - truth
        e = float(np.linalg.norm(d))
        self.err3d.append(e)
        self.errz.append(abs(float(d[2])))
        if est.peb_m is not None:
            self.peb.append(est.peb_m)
        true_floor = int(self.building.floor_index(truth[2]))
        self.floor_ok.append(est.floor_index == true_floor)
        return e

    def summary(self) -> dict[str, Any]:
        def pct(v: list[float]) -> dict[str, float | None]:
            a = np.asarray(v)
            return {f"p{q}": (float(np.percentile(a, q)) if a.size else None) for q in (50, 67, 90, 95)}

        return {
            "estimates": self.count,
            "with_position": len(self.err3d),
            "status": dict(self.status),
            "error_3d_m": pct(self.err3d),
            "error_z_m": pct(self.errz),
            "peb_m": pct(self.peb),
            "floor_accuracy": (float(np.mean(self.floor_ok)) if self.floor_ok else None),
        }


# ----------------------------------------------------------------------------- processes
@dataclass
class _Proc:
    name: str
    popen: subprocess.Popen
    log_path: Path | None


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
                 stop: threading.Event) -> None:
        from diffpos_services.anchor.service import load_scenario_file

        options.check()
        if options.scenario is not None:
            # a shipped name ("paper") becomes its file, which every service can read
            try:
                from diffpos_services.scenario_io import resolve_scenario

                options.scenario = str(resolve_scenario(options.scenario))
            except ImportError:  # pragma: no cover
                pass
        self.o = options
        self.log = logger
        self.stop = stop
        self.scenario = load_scenario_file(options.scenario)
        self.keys = Keys(options.site)
        self.nodes = emulation_nodes(self.scenario, max_nodes=options.max_nodes)
        if not self.nodes:
            raise ConfigError("the scenario has no nodes to emulate")
        self.anchor_ids = [a.id for a in self.scenario.anchors]
        # The fusion's path model: --edge auto is decided by the fusion from the scenario
        # (lower edge when every UAV flies below the windows); the ideal channel generates the
        # upper-edge path, so it gets the upper edge.
        edge = "upper" if options.edge == "auto" and options.channel == "ideal" else options.edge
        self.fusion_args = ["--epoch-period-s", str(1.0 / options.rate_hz),
                            "--delta-m", str(options.delta_m), "--edge", edge]
        if options.scenario:
            self.fusion_args += ["--scenario", options.scenario]
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
        self.diag: M.FusionDiagnostics | None = None

    # -------------------------------------------------------------- security
    def _load_profile(self, path: str):
        from diffpos_services.bus.security import (
            SecurityError,
            anchor_user,
            check_profile,
            load_profile,
        )

        try:
            profile = load_profile(path)
        except (SecurityError, OSError) as exc:
            raise ConfigError(f"--security-profile {path}: {exc}") from None
        problems = check_profile(profile)
        if problems:
            raise ConfigError(f"--security-profile {path}: {problems[0]}")
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
        """Render the profile for this run's endpoint; remember each identity's file."""
        from diffpos_services.bus.security import SecurityError, render_profile

        try:
            written = render_profile(self.profile, out_dir, connect=[self.endpoint],
                                     listen=[self.listen])
        except SecurityError as exc:
            raise ConfigError(f"--security-profile {self.o.security_profile}: {exc}") from None
        self.zenoh_files = {p.stem: str(p) for p in written}

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

    # -------------------------------------------------------------- process helpers
    def _spawn(self, name: str, argv: list[str]) -> _Proc:
        cmd = [sys.executable, "-m", "diffpos_services.cli.main", *argv, "--log-level", self.o.log_level]
        log_path = None
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            log_path = self.log_dir / f"{name}.log"
            err = open(log_path, "wb")
        else:
            err = subprocess.DEVNULL
        env = dict(os.environ, DIFFPOS_LOG_FORMAT="json")
        # each child gets its bus explicitly (--connect or its own --zenoh-config): an
        # inherited default file would replace the run's router configuration
        env.pop("DIFFPOS_ZENOH_CONFIG", None)
        p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err,
                             start_new_session=True, env=env)
        if err is not subprocess.DEVNULL:
            err.close()
        proc = _Proc(name, p, log_path)
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
                                         delta_m=self.o.delta_m,
                                         epoch_period_s=1.0 / self.o.rate_hz)
        edge, why = model_edge(edge, self.scenario)
        return cfg, edge, why

    def _write_run_config(self) -> str:
        """A JSON run configuration for the recorder (``{"fusion": ..., "emulate": ...}``)."""
        import msgspec

        self._run_dir = tempfile.TemporaryDirectory(prefix="diffpos-run-")
        path = Path(self._run_dir.name) / "run_config.json"
        doc = {"fusion": msgspec.to_builtins(self.fusion_config),
               "emulate": {"run_id": self.run_id, "channel": self.o.channel, "seed": self.o.seed,
                           "edge": self.edge, "edge_reason": self.edge_reason}}
        path.write_text(json.dumps(doc, indent=2), encoding="utf-8")
        return str(path)

    def shutdown(self) -> None:
        """Stop in dependency order: anchors, fusion, extras, router."""
        self._stop_procs(lambda n: n.startswith("anchor-"))
        self._stop_procs(lambda n: n == "fusion")
        self._stop_procs(lambda n: n in EXTRA_SERVICES)
        self._stop_procs(lambda n: True)
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
        import zenoh

        key = str(sample.key_expr)
        with self.alive_event:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(key)
            else:
                self.alive.discard(key)
            self.alive_event.notify_all()
        self.q.put(("alive", key, sample.kind == zenoh.SampleKind.PUT))

    def _on_data(self, sample) -> None:
        self.q.put(("data", str(sample.key_expr), sample.payload.to_bytes()))

    def _wait_ready(self, need: set[str]) -> None:
        deadline = time.monotonic() + self.o.ready_timeout_s
        with self.alive_event:
            while not need <= self.alive:
                if self.stop.is_set():
                    return
                self._check_children()
                if time.monotonic() > deadline:
                    missing = sorted(need - self.alive)
                    raise ConfigError(f"services not ready after {self.o.ready_timeout_s:.0f} s: {missing}")
                self.alive_event.wait(0.2)

    def run(self) -> dict[str, Any]:
        """Run the emulation; returns the summary dictionary."""
        import zenoh

        o = self.o
        rng = np.random.default_rng(o.seed)
        offsets = rng.uniform(-o.clock_offset_max_ms, o.clock_offset_max_ms, len(self.anchor_ids))
        scen = ["--scenario", o.scenario] if o.scenario else []
        summary: dict[str, Any] = {}
        tmp = tempfile.TemporaryDirectory(prefix="diffpos-zenoh-") if self.profile else None
        try:
            if tmp is not None:
                self._render_security(tmp.name)
                self._spawn("router", ["router", *self._zargs("router")])
                zs = with_zenoh_config(ZenohSettings(connect=(self.endpoint,)),
                                       self.zenoh_files[self.profile.users["emulator"]],
                                       logger=self.log)
            else:
                self._spawn("router", ["router", "--listen", self.listen])
                zs = with_zenoh_config(ZenohSettings(connect=(self.endpoint,)), logger=self.log)
            session = open_session(zs, self.stop, logger=self.log)
            if session is None:
                return summary
            with session:
                live = session.liveliness().declare_subscriber(self.keys.alive_all(), self._on_alive,
                                                               history=True)
                subs = [session.declare_subscriber(k, self._on_data)
                        for k in (self.keys.estimates(), self.keys.fusion_diagnostics())]
                self._spawn("fusion", ["fusion", "--site", o.site, *self._zargs("fusion"),
                                       *self.fusion_args])
                for aid, off in zip(self.anchor_ids, offsets, strict=True):
                    self._spawn(f"anchor-{aid}", [
                        "anchor", "--id", aid, "--site", o.site, *self._zargs("anchor", aid),
                        "--seed", str(o.seed), "--rate-hz", str(o.rate_hz), "--wait-start",
                        "--clock-offset-ms", f"{off:.4f}", "--channel", o.channel,
                        "--max-nodes", str(o.max_nodes), *scen])
                need = {self.keys.alive_anchor(a) for a in self.anchor_ids} | {self.keys.alive_fusion()}
                for name, (module, build, ready_key) in EXTRA_SERVICES.items():
                    argv = build(o, self.endpoint, self.run_id)
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
                    if argv is not None and name == "recorder":
                        # the fusion settings travel with the recording: replay reproduces live
                        argv = [*argv, "--run-config", self._write_run_config()]
                    if argv is not None and importlib.util.find_spec(module) is not None:
                        self._spawn(name, argv)
                        if ready_key is not None:
                            need.add(ready_key(self.keys))
                t_ready = time.monotonic()
                self._wait_ready(need)
                if self.stop.is_set():
                    return summary
                log_event(self.log, logging.INFO, "all services ready",
                          anchors=len(self.anchor_ids), nodes=len(self.nodes),
                          ready_s=round(time.monotonic() - t_ready, 2), endpoint=self.endpoint)
                hint = dashboard_hint(o) if "dashboard" in {p.name for p in self.procs} else None
                if hint:
                    log_event(self.log, logging.INFO, "dashboard", how=hint)
                    print(f"dashboard: {hint}", file=sys.stderr, flush=True)
                # start 0.3 s from now, on the fusion's epoch grid (epoch k = [kT, (k+1)T))
                period = round(1e9 / o.rate_hz)
                wall_t0 = -(-(time.time_ns() + 300_000_000) // period) * period
                rc = M.RunControl(run_id=self.run_id, t0_ns=wall_t0, wall_t0_ns=wall_t0,
                                  speed=o.speed or 1.0, duration_ns=round(o.duration_s * 1e9),
                                  seed=o.seed, lockstep=o.speed == 0)
                session.put(self.keys.run_control(), M.encode(rc),
                            encoding=zenoh.Encoding.APPLICATION_JSON,
                            congestion_control=zenoh.CongestionControl.BLOCK)
                tb = TimeBase.from_control(rc)
                summary = self._monitor(session, tb)
                for s in subs:
                    s.undeclare()
                live.undeclare()
        finally:
            self.shutdown()
            if tmp is not None:
                tmp.cleanup()
        return summary

    # -------------------------------------------------------------- monitoring
    def _publish_truth(self, session, pubs: dict, tb: TimeBase, k: int) -> None:
        t_ns = tb.t0_ns + round(k * 1e9 / self.o.rate_hz)
        t_s = (t_ns - tb.t0_ns) * 1e-9
        for nid, tr in self.nodes:
            p = np.asarray(tr.position_m(t_s), float)
            msg = M.GroundTruth(entity="node", id=nid, t_ns=t_ns, position_m=M.vec3(p),
                                velocity_m_s=M.vec3(tr.velocity_m_s(t_s)),
                                floor_index=int(self.scenario.building.floor_index(p[2])))
            pubs[("node", nid)].put(M.encode(msg))
        for a in self.scenario.anchors:
            msg = M.GroundTruth(entity="anchor", id=a.id, t_ns=t_ns,
                                position_m=M.vec3(a.trajectory.position_m(t_s)),
                                velocity_m_s=M.vec3(a.trajectory.velocity_m_s(t_s)), floor_index=None)
            pubs[("anchor", a.id)].put(M.encode(msg))

    def _monitor(self, session, tb: TimeBase) -> dict[str, Any]:
        import zenoh

        o = self.o
        enc, bc = zenoh.Encoding.APPLICATION_JSON, zenoh.CongestionControl.BLOCK
        pubs = {("node", nid): session.declare_publisher(self.keys.truth_node(nid), encoding=enc,
                                                         congestion_control=bc)
                for nid, _ in self.nodes}
        pubs.update({("anchor", a.id): session.declare_publisher(
            self.keys.truth_anchor(a.id), encoding=enc, congestion_control=bc)
            for a in self.scenario.anchors})
        scorer = Scorer(self.nodes, self.scenario.building, tb.t0_ns)
        dec_est, dec_diag = M.decoder(M.PositionEstimate), M.decoder(M.FusionDiagnostics)
        end_ns = tb.t0_ns + round(o.duration_s * 1e9)
        period_ns = round(1e9 / o.rate_hz)
        k_truth = 0
        # lockstep (speed 0): release emulated time epoch by epoch, LOOKAHEAD epochs ahead of
        # the oldest epoch whose estimates are not all in yet
        lockstep = o.speed == 0
        lookahead = 2
        e0 = tb.t0_ns // period_ns
        per_epoch: collections.Counter[int] = collections.Counter()
        next_needed = 0
        clock_k = -1
        clock_wall = time.monotonic()
        clock_pub = session.declare_publisher(self.keys.run_clock(), encoding=enc,
                                              congestion_control=bc) if lockstep else None

        def release(k: int) -> None:
            nonlocal clock_k, clock_wall
            clock_k = k
            clock_wall = time.monotonic()
            clock_pub.put(M.encode(M.RunClock(run_id=self.run_id,
                                              t_ns=tb.t0_ns + (k + 1) * period_ns - 1)))

        def emu_now(wall_ns: int | None = None) -> int:
            if lockstep:
                return tb.t0_ns + (clock_k + 1) * period_ns
            return tb.now_ns(wall_ns)

        if lockstep:
            release(lookahead - 1)
        last_est_wall = time.monotonic()
        recent: collections.deque[tuple[float, float | None]] = collections.deque()
        next_status = time.monotonic()
        finish_wall: float | None = None
        lost_events = []
        tty = sys.stderr.isatty()
        while True:
            now_wall = time.time_ns()
            # truth, paced on the time base
            while tb.t0_ns + k_truth * period_ns <= min(emu_now(now_wall), end_ns - 1):
                self._publish_truth(session, pubs, tb, k_truth)
                k_truth += 1
            if self.stop.is_set():
                break
            if lockstep:
                while per_epoch[next_needed] >= len(self.nodes):
                    next_needed += 1
                if next_needed + lookahead - 1 > clock_k:
                    release(next_needed + lookahead - 1)
                elif time.monotonic() - clock_wall > 2.0:
                    # no progress (an estimate lost?): move on rather than deadlock
                    next_needed += 1
                    release(next_needed + lookahead - 1)
            if finish_wall is None and emu_now(now_wall) >= end_ns:
                finish_wall = time.monotonic()
            if finish_wall is not None:
                wm = self.diag.watermark_ns if self.diag else None
                # wait for the last epochs: the fusion's watermark past the end with nothing
                # pending; or, if the machine cannot keep up, until estimates stop coming
                # (no estimate for 3 s after the end of the run)
                if (wm is not None and wm >= end_ns - period_ns and self.diag.pending_epochs == 0) \
                        or time.monotonic() - max(finish_wall, last_est_wall) > 3.0:
                    break
            try:
                item = self.q.get(timeout=0.05)
            except queue.Empty:
                item = None
            while item is not None:
                if item[0] == "data":
                    pk = parse_key(item[1])
                    try:
                        if pk is not None and pk.kind == "estimate":
                            est = dec_est(item[2])
                            last_est_wall = time.monotonic()
                            per_epoch[est.epoch - e0] += 1
                            recent.append((last_est_wall, scorer.add(est)))
                            if not o.progress and len(recent) > 10_000:
                                recent.popleft()
                        elif pk is not None and pk.kind == "diagnostics":
                            self.diag = dec_diag(item[2])
                    except M.DecodeError as exc:
                        log_event(self.log, logging.WARNING, "bad message", key=item[1], error=str(exc)[:200])
                elif item[0] == "alive" and not item[2] and finish_wall is None:
                    # (anchors leave on their own at the end of the run: not a loss)
                    lost_events.append(item[1])
                    log_event(self.log, logging.WARNING, "service lost", key=item[1])
                try:
                    item = self.q.get_nowait()
                except queue.Empty:
                    item = None
            if o.progress and time.monotonic() >= next_status:
                next_status = time.monotonic() + 0.5
                t_now = time.monotonic()
                while recent and recent[0][0] < t_now - 2.0:
                    recent.popleft()
                errs = [e for _, e in recent if e is not None]
                rate = len(recent) / 2.0
                med = f"{np.median(errs):.2f} m" if errs else "-"
                gated = self.diag.gated if self.diag else 0
                el = max(min(emu_now(), end_ns) - tb.t0_ns, 0) * 1e-9
                line = (f"t={el:5.1f}/{o.duration_s:.0f} s  fixes/s={rate:6.1f}  median err={med:>8}  "
                        f"gated={gated}  fixes={scorer.count}")
                if tty:
                    print("\r" + line, end="", file=sys.stderr, flush=True)
                else:
                    log_event(self.log, logging.INFO, "progress", status=line)
        if tty and o.progress:
            print(file=sys.stderr)
        for p in pubs.values():
            p.undeclare()
        if clock_pub is not None:
            clock_pub.undeclare()
        out = scorer.summary()
        expected_epochs = int(o.duration_s * o.rate_hz)
        out.update(
            run_id=self.run_id, endpoint=self.endpoint, anchors=len(self.anchor_ids),
            secured=self.profile is not None,
            nodes=len(self.nodes), duration_s=o.duration_s, speed=o.speed, channel=o.channel,
            expected_epochs_per_node=expected_epochs,
            epochs_per_node_min=min((len(v) for v in scorer.epochs.values()), default=0),
            lost=lost_events,
            model=f"{self.edge} window edge, Delta {o.delta_m:g} m ({self.edge_reason})",
            recording=recording_path(o, self.run_id)
            if "recorder" in {p.name for p in self.procs} else None,
        )
        if self.diag is not None:
            d = self.diag
            out["fusion"] = {"received": d.received, "rejected": d.rejected, "gated": d.gated,
                             "solved": d.solved, "late_ranges": d.late_ranges,
                             "latency_ms": {"p50": d.latency.p50_ms, "p99": d.latency.p99_ms}}
        return out


def format_summary(s: dict[str, Any]) -> str:
    """The summary as a plain-text table."""
    def f(v: float | None, unit: str = " m") -> str:
        return "-" if v is None else f"{v:.3f}{unit}"

    rows = [
        ("run", f"{s.get('run_id', '-')}  ({s.get('anchors')} anchors x {s.get('nodes')} nodes, "
                f"{s.get('duration_s')} s at x{s.get('speed')}, channel {s.get('channel')})"),
        ("model", s.get("model", "-")),
        ("estimates", f"{s.get('estimates', 0)} ({s.get('with_position', 0)} with a position)"),
        ("status", ", ".join(f"{k} {v}" for k, v in sorted(s.get("status", {}).items())) or "-"),
    ]
    for name, key in (("3D error", "error_3d_m"), ("z error", "error_z_m"), ("PEB", "peb_m")):
        p = s.get(key, {})
        rows.append((name, "  ".join(f"p{q} {f(p.get(f'p{q}'))}" for q in (50, 67, 90, 95))))
    fa = s.get("floor_accuracy")
    rows.append(("floor accuracy", "-" if fa is None else f"{100 * fa:.1f} %"))
    fu = s.get("fusion")
    if fu:
        lat = fu["latency_ms"]
        rows.append(("gating", f"{fu['gated']} measurements excluded; rejected {fu['rejected'] or 0}; "
                               f"late ranges {fu['late_ranges']}"))
        rows.append(("fusion latency", f"p50 {f(lat['p50'], ' ms')}  p99 {f(lat['p99'], ' ms')}"))
    if s.get("lost"):
        rows.append(("lost", ", ".join(s["lost"])))
    if s.get("recording"):
        rows.append(("recording", f"{s['recording']}  (diffpos replay / inspect / to-rerun FILE)"))
    w = max(len(r[0]) for r in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)
