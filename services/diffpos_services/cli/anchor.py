"""One UAV anchor: flies its trajectory, ranges to nodes, publishes over Zenoh

The anchor ANCHOR_ID of the scenario flies its trajectory (hover, orbit, waypoints), runs
the outdoor-to-indoor channel emulator to every node (first arriving path, its SNR, range
noise at the ranging CRLB) and publishes, at --rate-hz, with congestion control BLOCK:

  diffpos/<site>/anchor/<id>/state          its own navigation estimate (GNSS/baro noise)
  diffpos/<site>/anchor/<id>/range/<node>   one range per node (null when not detected)
  diffpos/<site>/anchor/<id>/ranges         instead, one RangeBatch per epoch: by default when
                                            the anchor ranges more than 8 nodes (--range-batch,
                                            --no-range-batch force it)

and declares the liveliness token diffpos/<site>/alive/anchor/<id>. Every time on the wire
is the anchor's own clock (true time + --clock-offset-ms + jitter) in integer ns.

Time base: with --wait-start the anchor waits for the run control message of
`diffpos emulate` (emulated time, --speed); without it, it runs in real time with the
origin at the start of the current UTC hour (so independently started anchors agree).

examples:
  diffpos router &
  diffpos anchor --id uav1 --scenario scenarios/paper.toml
  diffpos anchor --id uav2 --scenario scenarios/paper.toml --clock-offset-ms 1.5
  diffpos anchor --id uav1 --channel ideal     upper-edge diffraction path only (benchmarks)
  diffpos anchor --id uav1 --channel raytrace --wait-start --raytrace-duration-s 20
                                               paths ray traced (Sionna RT) along the run's
                                               trajectories before it starts (cached; as
                                               diffpos emulate --channel raytrace)
  diffpos anchor --id uav1 --zenoh-config security/zenoh/anchor-uav1.json5
                                               TLS + its own user/password (security/README.md)

Stop with Ctrl-C or SIGTERM: the liveliness token is withdrawn and the session closed.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from diffpos_services.bus.session import add_zenoh_arguments, service_settings
from diffpos_services.cli.raytrace_options import add_raytrace_arguments
from diffpos_services.config import build_config
from diffpos_services.logs import add_logging_arguments, setup_logging
from diffpos_services.scenario_io import load_scenario_option
from diffpos_services.shutdown import Shutdown, run_main

if TYPE_CHECKING:
    from diffpos_services.anchor.service import AnchorConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--id", dest="anchor_id", required=True, help="anchor id in the scenario (e.g. uav1)"
    )
    parser.add_argument("--scenario", metavar="TOML", help="scenario file (default: the paper's)")
    parser.add_argument(
        "--site", default="demo", help="site name, the second key chunk (default demo)"
    )
    parser.add_argument(
        "--rate-hz", type=float, default=10.0, help="ranging rate [Hz] (default 10)"
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument(
        "--phase",
        type=float,
        default=None,
        help="measurement phase within the period, 0..1 (default: random from the seed)",
    )
    parser.add_argument("--clock-offset-ms", type=float, default=0.0, help="clock offset [ms] (default 0)")
    parser.add_argument(
        "--clock-jitter-us", type=float, default=20.0, help="clock jitter sigma [us] (default 20)"
    )
    parser.add_argument(
        "--gnss-sigma-h-m", type=float, default=0.02, help="GNSS horizontal position sigma [m] (default 0.02)"
    )
    parser.add_argument(
        "--gnss-sigma-v-m", type=float, default=0.03, help="GNSS vertical position sigma [m] (default 0.03)"
    )
    parser.add_argument(
        "--max-nodes", type=int, default=0, help="range to the first N nodes only (default 0 = all)"
    )
    parser.add_argument(
        "--channel",
        choices=["emulator", "ideal", "raytrace"],
        default="emulator",
        help="emulator: O2I multipath + first arrival (default); ideal: the "
        "D-NLS model's path with CRLB noise at --ideal-snr-db; raytrace: paths ray traced "
        "with Sionna RT (optional extra) before the run, the emulator's detection and noise "
        "(needs --wait-start)",
    )
    add_raytrace_arguments(parser)
    parser.add_argument(
        "--raytrace-duration-s", type=float, default=20.0, metavar="S",
        help="--channel raytrace: the run's length the paths are traced for [s] (default 20)")
    parser.add_argument(
        "--ideal-snr-db", type=float, default=20.0, help="SNR of --channel ideal [dB] (default 20)"
    )
    parser.add_argument(
        "--range-batch",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="publish one RangeBatch per epoch on .../anchor/<id>/ranges instead of one "
        "message per node (default: when the anchor ranges more than 8 nodes)",
    )
    parser.add_argument(
        "--wait-start",
        action="store_true",
        help="wait for the run control message of `diffpos emulate`",
    )
    add_zenoh_arguments(parser)
    add_logging_arguments(parser)


def config_from_args(args: argparse.Namespace) -> AnchorConfig:
    from diffpos_services.anchor.service import AnchorConfig  # the channel's kernels

    return build_config(
        AnchorConfig,
        dict(
            site=args.site,
            anchor_id=args.anchor_id,
            scenario=args.scenario,
            rate_hz=args.rate_hz,
            seed=args.seed,
            phase=args.phase,
            clock_offset_ns=round(args.clock_offset_ms * 1e6),
            clock_jitter_ns=round(args.clock_jitter_us * 1e3),
            gnss_sigma_h_m=args.gnss_sigma_h_m,
            gnss_sigma_v_m=args.gnss_sigma_v_m,
            max_nodes=args.max_nodes,
            channel=args.channel,
            raytrace_duration_s=args.raytrace_duration_s,
            raytrace_samples=(None if args.raytrace_samples is None
                              else round(args.raytrace_samples)),
            raytrace_depth=args.raytrace_depth,
            raytrace_step_s=args.raytrace_step_s,
            ideal_snr_db=args.ideal_snr_db,
            wait_start=args.wait_start,
            range_batch=args.range_batch,
        ),
    )


def run(args: argparse.Namespace) -> int:
    from diffpos_services.anchor.service import run_anchor  # the channel's kernels

    log = setup_logging(f"anchor.{args.anchor_id}", level=args.log_level, fmt=args.log_format)

    def body() -> int:
        cfg = config_from_args(args)
        zs = service_settings(args, log)
        scenario = load_scenario_option(cfg.scenario)
        traced = None
        if cfg.channel == "raytrace":  # from the cache (diffpos emulate traced it), or now
            from diffpos.emulation import emulation_nodes
            from diffpos_services.raytrace.live import anchor_links

            traced = anchor_links(
                scenario, cfg.anchor_id, emulation_nodes(scenario, max_nodes=cfg.max_nodes),
                duration_s=cfg.raytrace_duration_s, samples=cfg.raytrace_samples,
                depth=cfg.raytrace_depth, step_s=cfg.raytrace_step_s, log=log)
        stop = Shutdown(log)
        run_anchor(cfg, zs, stop.event, scenario=scenario, logger=log, traced=traced)
        return 0

    return run_main(body, log)
