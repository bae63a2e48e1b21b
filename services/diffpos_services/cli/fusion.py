"""Fusion service: aligns ranges in time, D-NLS with gating or mnls + tracking, publishes estimates

Subscribes with one subscriber to diffpos/<site>/anchor/** (states, ranges and range
batches of every anchor, each anchor's in publish order; never the truth keys) and watches
the anchors' liveliness tokens.
Ranges are grouped per node into epochs of --epoch-period-s; an epoch is solved as soon as
every live anchor has reported for it (or moved past it), or --deadline-s after its first
range. Each range is paired with its anchor's self-reported position interpolated at the
range's own time. The default method is mnls: it fits the first-arrival path model of the
scenario's building (which mechanism arrived first on each link: window, reflections, edge
diffraction) and runs a per-responder tracker (an IMM over the floors: every floor hypothesis
stays alive until the data decides; a responder without ranges coasts). On 2 cores it keeps up
in real time with the paper's 4 UAVs and 6 responders; with 8 UAVs x 50 responders it does not
yet (use lockstep, diffpos emulate --speed 0, or --method dnls). --method dnls is the paper's
D-NLS on the window-edge diffraction path with RAIM gating (estimate v1, ~0.1 ms per fix).
With mnls it publishes

  diffpos/<site>/node/<node>/estimate   estimate v2: filtered position, covariance (95 %
                                        ellipsoid), floor and per-floor probabilities, track
                                        status, the snapshot fix, per anchor the mechanism and
                                        residual, used and excluded anchors
  diffpos/<site>/fusion/diagnostics     counters (received, rejected by reason, gated,
                                        solved), live/lost anchors, latency p50/p99

An unidentifiable or degraded geometry is published as a status with a null position,
never as a wrong fix. Anchors' clocks are assumed to agree within --clock-tolerance-ms.

examples:
  diffpos fusion --scenario scenarios/paper.toml
  diffpos fusion --window-height-m 1.5 --epoch-period-s 0.2 --connect tcp/router:7447
  diffpos fusion --zenoh-config security/zenoh/fusion.json5   TLS + user/password + ACL
  diffpos fusion --scenario scenarios/paper.toml --anchors scenario --nodes scenario
                                        accept only the scenario's anchors and nodes
  diffpos fusion --anchors uav1,uav2,uav3,uav4 --method lls   allow-list; LoS baseline solver
  diffpos fusion --scenario scenarios/large.toml --no-tracking    mnls snapshot fixes only
  diffpos fusion --tracker nis_limit=12 --tracker dormant=false    tracker settings

Stop with Ctrl-C or SIGTERM: pending epochs are solved and published before the session closes.
"""

from __future__ import annotations

import argparse
import logging

from diffpos_services.bus.session import add_zenoh_arguments, service_settings
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import (
    DEFAULT_ADMIT_LAG_S,
    DEFAULT_DNLS_EXCLUSION_STARTS,
    DEFAULT_KERNEL_THREADS,
    DEFAULT_METHOD,
    DEFAULT_SUPERSEDE_AFTER_S,
    DEFAULT_WORKERS,
    EDGES,
    LIVE_MAX_BACKLOG_S,
    METHODS,
    FusionConfig,
    model_edge,
    parse_shard,
    parse_tracker_items,
    tracker_help,
)
from diffpos_services.logs import add_logging_arguments, log_event, setup_logging
from diffpos_services.scenario_io import load_scenario_option
from diffpos_services.shutdown import Shutdown, run_main


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scenario", metavar="TOML", help="scenario file: building geometry (default: the paper's)"
    )
    parser.add_argument("--site", default="demo", help="site name (default demo)")
    parser.add_argument("--window-height-m", type=float, help="override the window height w [m]")
    parser.add_argument(
        "--delta-m", type=float, default=0.0, help="Case-2 offset Delta [m] (default 0)"
    )
    parser.add_argument(
        "--edge", choices=list(EDGES), default="upper",
        help="window edge of the path model: upper (the paper's D-NLS, default), lower, or auto: "
        "lower when every anchor of the scenario flies below the lowest window (that diffracted "
        "path is then the shorter one and usually arrives first), else upper",
    )
    parser.add_argument(
        "--epoch-period-s", type=float, default=0.1, help="epoch length [s] (default 0.1)"
    )
    parser.add_argument("--deadline-s", type=float, default=0.3, help="solve an epoch this "
                        "long (wall time) after its first range [s] (default 0.3)")
    parser.add_argument(
        "--clock-tolerance-ms",
        type=float,
        default=5.0,
        help="assumed bound on anchor clock offsets [ms] (default 5)",
    )
    parser.add_argument(
        "--method",
        choices=list(METHODS),
        default=DEFAULT_METHOD,
        help="estimator: mnls (default: mechanism-aware NLS on the first-arrival path model "
        "of the scenario's building, floor probabilities, with the tracker unless "
        "--no-tracking), dnls (the paper's diffraction-aware D-NLS with gating), lls (line-of-sight linear least squares, the paper's baseline), ippa "
        "(iterative parallel projection)",
    )
    parser.add_argument(
        "--no-tracking", action="store_true",
        help="mnls: publish the snapshot fix of every epoch instead of the tracked estimate",
    )
    parser.add_argument(
        "--anchors",
        metavar="ID,ID,...",
        help="accept only these anchors (default: any valid id; 'scenario' = the scenario's "
        "anchors); data and liveliness of other anchors are rejected as unknown_anchor",
    )
    parser.add_argument(
        "--nodes",
        metavar="ID,ID,...",
        help="accept only ranges to these nodes (default: any valid id; 'scenario' = the nodes "
        "the scenario is emulated with); others are rejected as unknown_node",
    )
    add_tracker_argument(parser)
    parser.add_argument("--no-gating", action="store_true", help="disable outlier gating")
    parser.add_argument(
        "--dnls-exclusion-starts", choices=["grid", "local"],
        default=DEFAULT_DNLS_EXCLUSION_STARTS,
        help="dnls with gating: starts of a cold fix's exclusion candidates (the fix's anchors "
        "left out one at a time): local = the candidate's own LLS position and the current "
        f"solution only (default: {DEFAULT_DNLS_EXCLUSION_STARTS}; ~0.4x the cold fixes' "
        "kernel CPU), grid = the fix's whole multi-start (height grid every 3 m + LLS, "
        "screened; before 2026-12-07); warm fixes unaffected; recorded in the fusion settings "
        "(replay: --set dnls_exclusion_starts=grid)",
    )
    parser.add_argument(
        "--no-motion-compensation",
        action="store_true",
        help="only inflate sigmas for node motion within an epoch",
    )
    _add_overload_arguments(parser)
    parser.add_argument(
        "--diagnostics-period-s",
        type=float,
        default=1.0,
        help="diagnostics publish period [s] (default 1)",
    )
    _add_cpu_arguments(parser)
    add_zenoh_arguments(parser)
    add_logging_arguments(parser)



def add_tracker_argument(parser: argparse.ArgumentParser) -> None:
    """``--tracker KEY=VALUE`` (repeatable): a setting of the per-responder tracker
    (FusionConfig.tracker); also ``diffpos emulate``'s."""
    parser.add_argument(
        "--tracker", action="append", default=[], metavar="KEY=VALUE",
        help="mnls + tracking: set one of the per-responder tracker's settings (repeatable; "
        "recorded with the fusion settings, so a replay runs the same tracker; meaning of "
        "each: diffpos.tracking.state.TrackerConfig). Keys, with default [unit]: "
        + tracker_help().replace("%", "%%"),
    )


def _add_overload_arguments(parser: argparse.ArgumentParser) -> None:
    """The overload policy's options (FusionConfig.max_backlog_s, supersede_after_s,
    admit_lag_s)."""
    parser.add_argument(
        "--max-backlog-s",
        type=float,
        default=LIVE_MAX_BACKLOG_S,
        metavar="S",
        help="when the fusion is slower than its input, solve each node's newest ready "
        "epoch only once the backlog spans more than --supersede-after-s (its older ones "
        "counted as rejected 'superseded', nodes served round-robin) and drop ready epochs "
        "more than S seconds older than the newest ('overloaded'); 0: neither, a slow "
        "fusion only lags "
        f"(default {LIVE_MAX_BACKLOG_S:g})",
    )
    parser.add_argument(
        "--supersede-after-s",
        type=float,
        default=DEFAULT_SUPERSEDE_AFTER_S,
        metavar="S",
        help="with --max-backlog-s: solve only each node's newest ready epoch once the ready "
        "epochs span more than S seconds of measurement time (a shorter backlog is worked off "
        "without loss; 0: as soon as a step cannot take them all) "
        f"(default {DEFAULT_SUPERSEDE_AFTER_S:g})",
    )
    parser.add_argument(
        "--unbounded-steps", action="store_true",
        help="solve every ready epoch with every track start and snapshot due in each step "
        "(no work bound per step): the estimates then depend on the ranges only, not on "
        "timing or CPU load; for an input that waits for the fusion (lockstep emulate uses "
        "it); recorded in the fusion settings (default: bounded steps)",
    )
    parser.add_argument(
        "--admit-lag-s",
        type=float,
        default=DEFAULT_ADMIT_LAG_S,
        metavar="S",
        help="a solve step that leaves ready epochs spanning more than S seconds (the fusion "
        "is behind) starts only the minimum of new tracks; the other new responders are "
        "published on time without a position until there is headroom to place them "
        f"(default {DEFAULT_ADMIT_LAG_S:g})",
    )


def _add_cpu_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--kernel-threads", type=int, default=DEFAULT_KERNEL_THREADS, metavar="N",
        help="threads for the compiled kernels' rows (tracker SNR and paths, M-NLS steps; "
        "estimates identical for any N; 2 pays only where a core is free, e.g. a replay on an "
        f"idle machine) (default: {DEFAULT_KERNEL_THREADS})",
    )
    parser.add_argument(
        "--workers", type=int, default=DEFAULT_WORKERS, metavar="N",
        help="processes sharing the per-node work of mnls + tracking (tracker update, snapshot "
        "fixes), this one included: N - 1 worker processes are started and warmed up before "
        "the fusion is ready; estimates identical for any N; 2 pays only where a core is free "
        f"(default: {DEFAULT_WORKERS})",
    )
    parser.add_argument(
        "--shard", metavar="K/N", default=None,
        help="own a share of the responders: those whose id's CRC-32 modulo N is K (0 <= K < N). "
        "N fusions started with 0/N .. N-1/N, on one or many machines, together publish what "
        "one fusion publishes (each ingests every anchor, solves only its responders); "
        "recorded in the fusion settings (default: all responders)",
    )


def config_from_args(args: argparse.Namespace, scenario=None) -> FusionConfig:
    """The :class:`FusionConfig` of the command line (geometry and edge rule: ``from_scenario``)."""
    values = dict(
        site=args.site,
        method=args.method,
        tracking=not args.no_tracking,
        delta_m=args.delta_m,
        epoch_period_s=args.epoch_period_s,
        deadline_s=args.deadline_s,
        clock_tolerance_s=args.clock_tolerance_ms * 1e-3,
        gating=not args.no_gating,
        dnls_exclusion_starts=args.dnls_exclusion_starts,
        motion_compensation=not args.no_motion_compensation,
        diagnostics_period_s=args.diagnostics_period_s,
        # FusionConfig.max_backlog_s: None never drops; --max-backlog-s 0 means the same
        max_backlog_s=args.max_backlog_s or None,
        supersede_after_s=args.supersede_after_s,
        admit_lag_s=args.admit_lag_s,
        bounded_steps=not args.unbounded_steps,
        kernel_threads=args.kernel_threads,
        workers=args.workers,
        tracker=parse_tracker_items(args.tracker),
    )
    if getattr(args, "shard", None) is not None:
        values["shard"], values["shards"] = parse_shard(args.shard)
    if args.window_height_m is not None:
        values["window_height_m"] = args.window_height_m
    for name in ("anchors", "nodes"):
        ids = allow_list(getattr(args, name, None), name, scenario)
        if ids is not None:
            values[name] = ids
    return FusionConfig.from_scenario(scenario, edge=args.edge, **values)


def allow_list(text: str | None, name: str, scenario=None) -> list[str] | None:
    """Parse ``--anchors`` / ``--nodes``: ``None`` (accept any), ``"scenario"`` or ``ID,ID,...``.

    ``"scenario"`` means the scenario's anchors, or for nodes the nodes the scenario is
    emulated with (:func:`diffpos.emulation.emulation_nodes`: its explicit nodes, or the
    generated responders ``r01``... of a scenario with only a study grid). Ids are checked
    by :class:`FusionConfig` (the error names ``anchors[i]`` / ``nodes[i]``).

    Raises
    ------
    ConfigError
        An empty list, or ``scenario`` without a scenario.
    """
    if text is None:
        return None
    if text.strip() == "scenario":
        if scenario is None:
            raise ConfigError(f"--{name} scenario: no scenario given (use --scenario TOML)")
        if name == "anchors":
            return [a.id for a in scenario.anchors]
        from diffpos.emulation import emulation_nodes  # the channel's kernels: not for --help

        return [nid for nid, _ in emulation_nodes(scenario)]
    ids = [v.strip() for v in text.split(",") if v.strip()]
    if not ids:
        raise ConfigError(f"--{name} {text!r}: give a comma-separated list of ids, e.g. "
                          f"--{name} {'uav1,uav2' if name == 'anchors' else 'n01,n02'}, "
                          "or 'scenario'")
    return ids


def run(args: argparse.Namespace) -> int:
    from diffpos_services.fusion.service import run_fusion  # kernels: not for --help

    log = setup_logging("fusion", level=args.log_level, fmt=args.log_format)

    def body() -> int:
        scenario = load_scenario_option(args.scenario)
        cfg = config_from_args(args, scenario)
        edge, why = model_edge(args.edge, scenario)
        log_event(log, logging.INFO, "path model", edge=edge, delta_m=cfg.delta_m, why=why)
        zs = service_settings(args, log)
        stop = Shutdown(log)
        run_fusion(cfg, zs, stop.event, logger=log)
        return 0

    return run_main(body, log)
