"""Live Rerun dashboard of a running system (viewer, web viewer or .rrd)

Subscribes to diffpos/<site>/ over Zenoh (anchor states, estimates, node truth, fusion
diagnostics, liveliness; never the high-rate ranges) and streams a Rerun dashboard: the
building in 3D with anchors and their trails, true and estimated node positions with 95%
uncertainty ellipsoids and the diffraction path anchor -> window edge -> node of every used
anchor (excluded anchors in red), time series of 3D error, z error and PEB per node, range
residuals per anchor, gating counts, a floor table (estimated vs true) and an event log.
Rows are stamped with measurement time (timeline "meas_time"), so the live view and an
offline conversion of the same run (`diffpos to-rerun`) line up.

It is its own process and keeps a ring buffer: a slow viewer makes the dashboard drop its
oldest undrawn messages (counted in the status lines), it never slows the fusion.

Where the dashboard goes (--rerun):
  auto         spawn a native viewer if a display is available, else serve (default)
  spawn        native Rerun viewer window (needs DISPLAY / WAYLAND_DISPLAY)
  serve        gRPC server + web viewer over HTTP; prints the URL to open in a browser
  save PATH    write an .rrd file (open later with `rerun PATH`)
  off          consume and count only

examples:
  diffpos dashboard --site demo                          viewer or web viewer, whichever works
  diffpos dashboard --rerun serve --web-port 9090        then open the printed http:// URL
  diffpos dashboard --rerun save out/live.rrd --scenario scenarios/paper.toml
  diffpos dashboard --demo --rerun save demo.rrd         synthetic run, no bus needed

`diffpos emulate` starts this service by default. Stop with Ctrl-C or SIGTERM: the last
messages are drawn and the .rrd is closed properly.
"""

from __future__ import annotations

import argparse
import logging
import threading

from diffpos_services.bus.session import add_zenoh_arguments, open_session, service_settings
from diffpos_services.errors import ConfigError
from diffpos_services.logs import add_logging_arguments, log_event, setup_logging
from diffpos_services.shutdown import Shutdown, run_main


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--site", default="demo", help="site to show, diffpos/<site>/** (default demo)"
    )
    parser.add_argument(
        "--rerun",
        nargs="+",
        default=["auto"],
        metavar="MODE",
        help="auto | spawn | serve | save PATH | off (default auto)",
    )
    parser.add_argument(
        "--scenario",
        metavar="FILE",
        help="scenario TOML, shipped name (paper, large) or 'default' (emulate's built-in): draws its building",
    )
    parser.add_argument(
        "--grpc-port", type=int, default=9876, help="serve: gRPC port (default 9876, 0 = free)"
    )
    parser.add_argument(
        "--web-port", type=int, default=9090, help="serve: web viewer port (default 9090, 0 = free)"
    )
    parser.add_argument("--host", default="127.0.0.1", help="serve: host name printed in the URL (default 127.0.0.1)")
    parser.add_argument(
        "--memory-limit", default="1GiB", help="viewer/server memory budget (default 1GiB)"
    )
    parser.add_argument(
        "--ring-size",
        type=int,
        default=200_000,
        help="ring buffer capacity [messages] (default 200000)",
    )
    parser.add_argument(
        "--drain-period",
        type=float,
        default=0.5,
        metavar="S",
        help="seconds between draws (default 0.5)",
    )
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    parser.add_argument(
        "--report-every",
        type=float,
        default=10.0,
        metavar="S",
        help="seconds between 'dashboard running' status log lines with the received / drawn "
        "/ dropped counts (default 10)",
    )
    parser.add_argument(
        "--demo",
        action="store_true",
        help="no bus: draw a synthetic run (8 anchors x 20 nodes, 60 s) and exit",
    )
    parser.add_argument("--recording-id", default=None, help="Rerun recording id (default random)")
    parser.add_argument(
        "--estimates-from",
        metavar="ZID_PREFIX",
        default=None,
        help="draw only estimates/diagnostics published by a zenoh session whose id starts "
        "with this (with timestamping on; diffpos emulate passes its fusion's); others are "
        "counted as foreign",
    )
    add_zenoh_arguments(parser, mode="client")
    add_logging_arguments(parser)


def _target(args: argparse.Namespace):
    # deferred here and below: the dashboard service imports rerun (~0.6 s), which
    # `diffpos dashboard --help` must not pay for
    from diffpos_services.dashboard.service import RerunTarget

    mode, *rest = args.rerun
    if len(rest) > 1 or (rest and mode != "save"):
        raise ConfigError(f"--rerun {' '.join(args.rerun)}: use spawn, serve, save PATH or off")
    try:
        return RerunTarget(
            mode=mode,
            path=rest[0] if rest else None,
            grpc_port=args.grpc_port,
            web_port=args.web_port,
            bind=args.host,
            memory_limit=args.memory_limit,
        )
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def run(args: argparse.Namespace) -> int:
    log = setup_logging("dashboard", level=args.log_level, fmt=args.log_format)

    def body() -> int:
        # deferred: the scenario's stairs come from its trajectories (diffpos.emulation, whose
        # channel kernels `--help` must not load)
        from diffpos_services.dashboard.scenario import building_for_option

        target = _target(args)
        building = building_for_option(args.scenario)
        if args.ring_size < 1 or args.drain_period <= 0 or args.report_every <= 0:
            raise ConfigError("--ring-size must be >= 1, --drain-period and --report-every > 0")
        from diffpos_services.dashboard.service import DashboardService, open_rerun

        try:
            rec, how = open_rerun(target, recording_id=args.recording_id)
        except RuntimeError as exc:
            raise ConfigError(str(exc)) from None
        print(how, flush=True)
        log_event(log, logging.INFO, "dashboard output", how=how, mode=target.mode)
        if args.demo:
            return _demo(rec, building, target)
        try:
            settings = service_settings(args, log)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        stop = Shutdown(log)
        if args.duration is not None:
            threading.Timer(args.duration, stop.set).start()
        session = open_session(settings, stop, logger=log)
        if session is None:  # stopped while waiting for the router
            return 0
        with session:
            svc = DashboardService(
                session,
                rec,
                site=args.site,
                building=building,
                ring_size=args.ring_size,
                drain_period_s=args.drain_period,
                logger=log,
                estimates_from=args.estimates_from,
            )
            log_event(log, logging.INFO, "dashboard subscribed", site=args.site)
            svc.run(stop.event, report_every_s=args.report_every)
        if rec.is_enabled():
            rec.disconnect()
        return 0

    return run_main(body, log)


def _demo(rec, building, target) -> int:
    from diffpos_services.dashboard.building import BuildingOutline
    from diffpos_services.dashboard.stream import Dashboard  # deferred: imports rerun
    from diffpos_services.replay.synthetic import display_run  # the fusion core's kernels

    b, msgs = display_run(n_anchors=8, n_nodes=20, duration_s=60.0, seed=1)
    dash = Dashboard(rec, building=building or BuildingOutline.from_object(b))
    kinds = {"AnchorState": [], "GroundTruth": [], "PositionEstimate": [], "FusionDiagnostics": []}
    for msg in msgs:
        kinds[type(msg).__name__].append(msg)
    dash.add(
        anchor_states=kinds["AnchorState"],
        truth=kinds["GroundTruth"],
        estimates=kinds["PositionEstimate"],
        diagnostics=kinds["FusionDiagnostics"],
    )
    if not rec.is_enabled():
        return 0
    rec.flush()
    if target.mode == "serve" or (target.mode == "auto" and not _display()):
        print("demo data sent; keep this process running to view it, Ctrl-C to stop", flush=True)
        Shutdown().wait()
    rec.disconnect()
    return 0


def _display() -> bool:
    from diffpos_services.dashboard.service import display_available

    return display_available()
