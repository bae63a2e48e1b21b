"""Run the whole system on this machine: router, anchors, fusion, recorder, dashboard

Starts every service of a deployment as its own process on this machine, wired over a
Zenoh router on a free loopback port:

  router                  a Python Zenoh router (no zenohd needed)
  anchor x M              one per UAV of the scenario, each with its own clock offset
  fusion                  first-arrival model + tracker (mnls), publishes estimates
  recorder                MCAP file of everything on the bus (--record)
  dashboard               live Rerun view (--dashboard)

It waits until every anchor and the fusion have declared their liveliness tokens, starts
the run by publishing the time base (emulated time runs --speed times faster than the wall
clock), publishes the nodes' ground truth on diffpos/<site>/truth/... (the fusion never
subscribes to it), shows a live status line (fixes/s, median error against the truth,
gated measurements), and at the end prints a summary: 3D and z error percentiles, floor
accuracy, fix status counts, gating and fusion latency.

Default scenario: the paper's building and four UAVs with six responders walking and
taking the stairs between floors. Scenarios with explicit nodes (e.g. scenarios/large.toml:
8 UAVs, 50 nodes) are emulated as they are.

examples:
  diffpos emulate                                  the paper's geometry, 20 s, real time
  diffpos emulate scenarios/large.toml --duration 30 --speed 2
  diffpos emulate --channel ideal --speed 5        model-matched ranges, 5x real time
  diffpos emulate --channel raytrace --speed 0     paths ray traced with Sionna RT (optional
                                                   extra) along the run's trajectories first:
                                                   about 5 minutes for the paper's 20 s, then
                                                   cached (docs/raytrace.md)
  diffpos emulate --speed 0 --duration 60          lockstep: as fast as the fusion keeps up
  diffpos emulate --dashboard serve --record run.mcap
  diffpos emulate --log-dir logs/ --json out.json  per-service logs and the summary as JSON
  diffpos emulate --tracker nis_limit=12           a tracker setting of the fusion
  diffpos emulate --security-profile security/profile.dev.toml
                                                   the secured bus: TLS + a user/password per
                                                   service + access control (security/README.md)

Ctrl-C (or SIGTERM, or closing the terminal) ends the run early; services are stopped in
order (anchors, fusion, recorder, dashboard, router) and the summary is still printed. The
services also stop if emulate itself is killed (parent-death signal).

Faults: a fusion or recorder that dies is started again (the recorder with a new file, the
dead one's file recovered in place); every service that died is listed under "faults" in the
summary, and the exit code is then 3 (the run lost data). Estimates not published by the
fusion this run started (another process on the bus) are never counted: they are reported
under "foreign".

exit codes: 0 ok, 2 bad option, 3 a service died (data lost), 130 interrupted
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import TYPE_CHECKING

from diffpos_services.cli.raytrace_options import add_raytrace_arguments
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import (
    DEFAULT_METHOD,
    METHODS,
    parse_tracker_items,
    tracker_help,
)
from diffpos_services.logs import add_logging_arguments, log_event, setup_logging
from diffpos_services.shutdown import Shutdown, run_main

if TYPE_CHECKING:
    from diffpos_services.emulate.options import EmulationOptions


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", nargs="?", metavar="SCENARIO.toml",
                        help="scenario file or shipped name (paper, large); default: the paper's "
                        "geometry with moving responders")
    parser.add_argument("--duration", type=float, default=20.0, metavar="S",
                        help="emulated run length [s] (default 20)")
    parser.add_argument("--speed", type=float, default=1.0, metavar="X",
                        help="emulated seconds per wall second (default 1 = real time); 0 = "
                        "lockstep: as fast as the fusion keeps up")
    parser.add_argument("--site", default="demo", help="site name on the bus (default demo)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--rate-hz", type=float, default=10.0, help="anchor ranging rate [Hz] (default 10)")
    parser.add_argument("--channel", choices=["emulator", "ideal", "raytrace"],
                        default="emulator",
                        help="emulator: O2I multipath + first arrival (default); ideal: the "
                        "D-NLS model's diffraction path with CRLB noise; raytrace: every "
                        "anchor-node path ray traced with Sionna RT (pip install -e "
                        "'.[raytrace]') along the run's trajectories before it starts, cached, "
                        "then the emulator's detection and noise")
    add_raytrace_arguments(parser)
    parser.add_argument("--delta-m", type=float, default=0.0, metavar="M",
                        help="the fusion's model offset Delta [m] (default 0: Case-1)")
    parser.add_argument("--edge", choices=["auto", "upper", "lower"], default="auto",
                        help="window edge the fusion models: upper (the paper's D-NLS), lower, "
                        "or auto (default): lower when every anchor flies below the lowest "
                        "window, because that diffracted path is then the shorter one and "
                        "arrives first on the emulated channel; upper otherwise and for "
                        "--channel ideal")
    parser.add_argument("--method", choices=METHODS, default=None,
                        help=f"the fusion's estimator (default {DEFAULT_METHOD}, as diffpos "
                        "fusion): mnls = the first-arrival model of every mechanism + a tracker "
                        "per responder (keeps up in real time on the paper's geometry; for large "
                        "scenarios on 2 cores use lockstep, --speed 0); dnls = the paper's window-edge D-NLS "
                        "with gating; lls, ippa = the baselines")
    parser.add_argument("--fusion-workers", type=int, default=1, metavar="N",
                        help="the fusion's worker processes (diffpos fusion --workers; default "
                        "1: none). N > 1 splits the tracker's rows over N processes, the "
                        "same estimates bit for bit; pays only where a core is free")
    parser.add_argument("--fusion-shards", type=int, default=1, metavar="N",
                        help="fusion processes sharing the responders (diffpos fusion --shard "
                        "K/N, K = 0 .. N-1; default 1): together they publish what one fusion "
                        "publishes, each solving the responders whose id's CRC-32 modulo N is K")
    parser.add_argument("--tracker", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting of the fusion's per-responder tracker (diffpos fusion "
                        "--tracker; repeatable; recorded with the fusion settings; meaning of "
                        "each: diffpos.tracking.state.TrackerConfig). Keys, with default [unit]: "
                        + tracker_help().replace("%", "%%"))
    parser.add_argument("--max-nodes", type=int, default=0, help="emulate only the first N nodes (default 0 = all)")
    parser.add_argument("--endpoint", metavar="ENDPOINT",
                        help="router endpoint (default tcp/127.0.0.1:<free port>; with "
                        "--security-profile tls/localhost:<free port>)")
    parser.add_argument("--security-profile", metavar="PROFILE.toml",
                        help="run on the secured bus of this security profile (e.g. "
                        "security/profile.dev.toml): TLS, one user/password per service, access "
                        "control; rendered into a private temporary folder (not with --speed 0)")
    parser.add_argument("--record", default="auto", metavar="FILE.mcap",
                        help="MCAP recording: auto (default: recordings/<name>-<UTC>.mcap), a path, or off")
    parser.add_argument("--dashboard", nargs="+", default=["auto"], metavar="MODE",
                        help="dashboard: auto | spawn | serve | save FILE.rrd | off (default auto)")
    parser.add_argument("--log-dir", metavar="DIR", help="write each service's log to DIR/<service>.log")
    parser.add_argument("--json", metavar="FILE", help="also write the summary as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no live status line")
    parser.add_argument("--ready-timeout", type=float, default=60.0, metavar="S",
                        help="give up if the services are not ready after S seconds (default 60)")
    add_logging_arguments(parser)


def run(args: argparse.Namespace) -> int:
    # the services it starts and scores (zenoh, the channel's kernels): not for --help
    from diffpos_services.emulate.options import EmulationOptions
    from diffpos_services.emulate.orchestrator import Emulation
    from diffpos_services.emulate.scoring import format_summary
    from diffpos_services.emulate.supervise import format_faults
    from diffpos_services.raytrace.live import live_settings, prepare_for_run

    fmt = args.log_format if args.log_format != "json" or not _tty() else "text"
    log = setup_logging("emulate", level=args.log_level, fmt=fmt)

    def body() -> int:
        opts = EmulationOptions(
            scenario=args.scenario, duration_s=args.duration, speed=args.speed, site=args.site,
            seed=args.seed, endpoint=args.endpoint, channel=args.channel,
            max_nodes=args.max_nodes, rate_hz=args.rate_hz, record=args.record,
            dashboard=list(args.dashboard), log_dir=args.log_dir,
            progress=not args.no_progress, ready_timeout_s=args.ready_timeout,
            log_level=args.log_level,
            delta_m=args.delta_m, edge=args.edge, method=args.method,
            fusion_workers=args.fusion_workers, fusion_shards=args.fusion_shards,
            security_profile=args.security_profile,
            tracker=parse_tracker_items(args.tracker),
            raytrace_samples=args.raytrace_samples, raytrace_depth=args.raytrace_depth,
            raytrace_step_s=args.raytrace_step_s,
        )
        opts.check()  # every option before anything starts (the dashboard hint needs them)
        if opts.channel == "raytrace":
            live_settings(opts.raytrace_samples, opts.raytrace_depth, opts.raytrace_step_s)
        stop = Shutdown(log)
        emu = Emulation(opts, log, stop.event, dashboard_hint=dashboard_hint(opts))
        if opts.channel == "raytrace":  # trace the run's paths (or load them) first
            emu.raytrace = prepare_for_run(emu.scenario, emu.nodes, opts, log, stop.event)
            if emu.raytrace is None:
                return 130
        log_event(log, logging.INFO, "starting", scenario=args.scenario or "paper (default)",
                  anchors=len(emu.anchor_ids), nodes=len(emu.nodes), endpoint=emu.endpoint)
        summary = emu.run()
        if not summary:
            if stop.is_set():
                return 130
            raise ConfigError("the run produced no summary")
        print(format_summary(summary))
        faults = format_faults(summary.get("faults", []))
        if faults:  # foreign messages and recording files are among the summary's notes
            print(faults)
        if args.json:
            with open(args.json, "w", encoding="utf-8") as f:
                json.dump(summary, f, indent=2)
        if stop.is_set():
            return 130
        return EXIT_DATA_LOST if summary.get("faults") else 0

    return run_main(body, log)


#: exit code of a run in which a service died (data lost, see the summary's faults)
EXIT_DATA_LOST = 3


def _tty() -> bool:
    return sys.stderr.isatty()


def dashboard_hint(o: EmulationOptions) -> str | None:
    """How to open the dashboard that ``diffpos emulate`` starts (``None`` when it is off)."""
    if not o.dashboard or o.dashboard[0] == "off":
        return None
    # the dashboard service imports rerun (heavy): only when a dashboard is started, and
    # never for --help
    from diffpos_services.dashboard.service import RerunTarget, describe_target

    mode = o.dashboard[0]
    path = o.dashboard[1] if mode == "save" and len(o.dashboard) > 1 else None
    return describe_target(RerunTarget(mode=mode, path=path))
