"""What ``diffpos emulate`` runs: its options and the command lines of the extra services."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from diffpos_services.bus.commands import recorder_args
from diffpos_services.bus.session import check_endpoint
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import EDGES, MAX_SHARDS, MAX_WORKERS, METHODS, tracker_value
from diffpos_services.wire.keys import Keys

__all__ = ["CHANNELS", "EXTRA_SERVICES", "EmulationOptions", "channel_argv", "dashboard_argv",
           "recorder_argv", "recording_path"]


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
    method: str | None = None
    fusion_workers: int = 1
    fusion_shards: int = 1
    """Fusion processes sharing the responders (``--fusion-shards``; ``diffpos fusion --shard
    K/N`` each): together they publish what one fusion publishes."""
    security_profile: str | None = None
    tracker: dict[str, Any] = field(default_factory=dict)
    """The fusion's tracker settings (``--tracker KEY=VALUE``; FusionConfig.tracker)."""
    #: ``--channel raytrace``: trace settings (``None``: the defaults of
    #: :mod:`diffpos_services.raytrace.live`)
    raytrace_samples: float | None = None
    raytrace_depth: int | None = None
    raytrace_step_s: float | None = None

    def check(self) -> None:
        if not self.duration_s > 0:
            raise ConfigError(f"--duration must be > 0 seconds, got {self.duration_s}")
        if not 0 <= self.speed <= 1000:
            raise ConfigError(f"--speed must be in [0, 1000] (0 = lockstep), got {self.speed}")
        if not self.rate_hz > 0:
            raise ConfigError(f"--rate-hz must be > 0, got {self.rate_hz}")
        if self.channel not in CHANNELS:
            raise ConfigError(f"--channel must be emulator, ideal or raytrace, got "
                              f"{self.channel!r}")
        self._check_raytrace()
        if self.method is not None and self.method not in METHODS:
            raise ConfigError(f"--method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if not 1 <= self.fusion_workers <= MAX_WORKERS:
            raise ConfigError(f"--fusion-workers must be in [1, {MAX_WORKERS}], got "
                              f"{self.fusion_workers}")
        if not 1 <= self.fusion_shards <= MAX_SHARDS:
            raise ConfigError(f"--fusion-shards must be in [1, {MAX_SHARDS}], got "
                              f"{self.fusion_shards}")
        for key, value in self.tracker.items():
            self.tracker[key] = tracker_value(key, value, where=f"--tracker {key}={value}")
        if self.edge not in EDGES:
            raise ConfigError(f"--edge must be auto, upper or lower, got {self.edge!r}")
        if self.endpoint is not None:
            try:
                check_endpoint(self.endpoint, field_name="--endpoint")
            except ValueError as exc:
                raise ConfigError(str(exc).replace("--endpoint=", "--endpoint ")) from None
        self._check_dashboard()
        self._check_record()
        if self.security_profile is not None:
            if self.endpoint is not None and not self.endpoint.startswith("tls/"):
                raise ConfigError(
                    f"--endpoint {self.endpoint}: with --security-profile use a tls/ endpoint "
                    "whose host is in the router certificate, e.g. tls/localhost:7447")


    def _check_raytrace(self) -> None:
        """The ``--raytrace-*`` options only with ``--channel raytrace`` (their ranges:
        ``diffpos_services.raytrace.live.live_settings``, checked by ``diffpos emulate``)."""
        given = [f"--{n.replace('_', '-')}" for n in ("raytrace_samples", "raytrace_depth",
                                                      "raytrace_step_s")
                 if getattr(self, n) is not None]
        if given and self.channel != "raytrace":
            raise ConfigError(f"{', '.join(given)}: only with --channel raytrace")

    def _check_dashboard(self) -> None:
        """``--dashboard``: one mode; ``save`` with exactly one writable .rrd path."""
        d = self.dashboard
        if not d:
            return
        mode, rest = d[0], d[1:]
        if mode not in DASHBOARD_MODES:
            raise ConfigError(f"--dashboard {' '.join(d)}: use auto, spawn, serve, save "
                              "FILE.rrd or off")
        if mode == "save":
            if len(rest) != 1:
                raise ConfigError(f"--dashboard {' '.join(d)}: save needs one path, e.g. "
                                  "--dashboard save out/run.rrd")
            _check_writable("--dashboard save", rest[0])
        elif rest:
            raise ConfigError(f"--dashboard {' '.join(d)}: only save takes a path")

    def _check_record(self) -> None:
        if self.record not in (None, "off", "", "auto"):
            _check_writable("--record", self.record)


#: what ``--channel`` accepts
CHANNELS = ("emulator", "ideal", "raytrace")


def channel_argv(o: EmulationOptions) -> list[str]:
    """An anchor's ``--channel`` (with ``raytrace``: the run's length and trace settings, so
    it finds the links :func:`diffpos_services.raytrace.live.prepare_for_run` cached)."""
    argv = ["--channel", o.channel]
    if o.channel == "raytrace":
        argv += ["--raytrace-duration-s", repr(float(o.duration_s))]
        for name in ("raytrace_samples", "raytrace_depth", "raytrace_step_s"):
            if getattr(o, name) is not None:
                argv += [f"--{name.replace('_', '-')}", repr(getattr(o, name))]
    return argv


#: what ``--dashboard`` accepts
DASHBOARD_MODES = ("auto", "spawn", "serve", "save", "off")


def _check_writable(option: str, path: str) -> None:
    """``path`` can be created: not a directory, its folder exists (or can be made)."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{option} {path}: is a directory; give a file name")
    parent = p.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK):
        raise ConfigError(f"{option} {path}: cannot write there ({parent} is not a writable "
                          "folder)")


def recorder_argv(o: EmulationOptions, endpoint: str, run_id: str) -> list[str] | None:
    """``diffpos recorder`` arguments of the run (``None`` when recording is off), from
    :func:`diffpos_services.bus.commands.recorder_args` (the one recorder command line)."""
    if o.record in (None, "off", ""):
        return None
    return recorder_args(site=o.site, connect=[endpoint], out=recording_path(o, run_id),
                         scenario=o.scenario or None)


def recording_path(o: EmulationOptions, run_id: str) -> str | None:
    """Where the recorder writes: ``--record PATH``, or for ``auto``
    ``recordings/<scenario>-<UTC run id>.mcap`` (``None`` when recording is off)."""
    if o.record in (None, "off", ""):
        return None
    if o.record != "auto":
        return o.record
    scenario = Path(o.scenario).stem if o.scenario else "paper-default"
    return str(Path("recordings") / f"{scenario}-{run_id}.mcap")


def dashboard_argv(o: EmulationOptions, endpoint: str, run_id: str) -> list[str] | None:
    """``diffpos dashboard`` arguments of the run (``None`` when the dashboard is off)."""
    if not o.dashboard or o.dashboard[0] == "off":
        return None
    argv = ["dashboard", "--site", o.site, "--connect", endpoint, "--rerun", *o.dashboard]
    # without a scenario file the run uses the built-in default: draw that building
    argv += ["--scenario", o.scenario or "default"]
    return argv


#: name -> (CLI module that must exist, argv builder, liveliness key to wait for or None).
#: Add a service here to have ``diffpos emulate`` start (and stop) it with the others; with
#: a readiness key the run starts only once that token is alive (nothing is missed).
EXTRA_SERVICES: dict[
    str,
    tuple[str, Callable[[EmulationOptions, str, str], list[str] | None],
          Callable[[Keys], str] | None],
] = {
    "recorder": ("diffpos_services.cli.recorder", recorder_argv, Keys.alive_recorder),
    "dashboard": ("diffpos_services.cli.dashboard", dashboard_argv, Keys.alive_dashboard),
}
