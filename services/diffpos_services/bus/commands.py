"""Command lines of the services that join the bus, built in one place.

:func:`recorder_args` is the ``diffpos recorder`` command line: ``diffpos emulate`` starts
its recorder with it (:func:`diffpos_services.emulate.options.recorder_argv`) and tests and
benchmarks start theirs with it (:func:`diffpos_services.recorder.build_command`);
:func:`foreign_path` is where a recorder keeps the foreign messages of a recording. They live in
the shared bus layer because services do not import each other (DEVELOPING.md).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

__all__ = ["foreign_path", "recorder_args"]


def recorder_args(
    *,
    site: str,
    out: str | os.PathLike[str],
    connect: Sequence[str] = (),
    scenario: str | os.PathLike[str] | None = None,
    run_config: str | os.PathLike[str] | None = None,
    flush_interval_s: float | None = None,
    split_duration_s: float | None = None,
    split_size_mb: float | None = None,
    status: bool = False,
) -> list[str]:
    """``recorder ...``: the verb and its options (``None`` options: the recorder's default).

    Parameters
    ----------
    site : str
    out : path
        MCAP file to write (part 0 of a split recording).
    connect : sequence of str
        Router endpoints (``--connect`` each; none: the caller adds ``--zenoh-config``).
    scenario : path, optional
        Scenario TOML, attached to the recording.
    run_config : path, optional
        JSON run configuration, attached to the recording.
    flush_interval_s : float, optional [s]
        ``--flush-interval``.
    split_duration_s, split_size_mb : float, optional [s], [MB]
        ``--split-duration`` / ``--split-size`` (0 = off).
    status : bool
        ``--status``: JSON status lines on stdout.
    """
    argv = ["recorder", "--site", site]
    for ep in connect:
        argv += ["--connect", ep]
    argv += ["--out", str(out)]
    if scenario is not None:
        argv += ["--scenario", str(scenario)]
    if run_config is not None:
        argv += ["--run-config", str(run_config)]
    for opt, v in (("--flush-interval", flush_interval_s),
                   ("--split-duration", split_duration_s), ("--split-size", split_size_mb)):
        if v is not None:
            argv += [opt, repr(float(v))]
    if status:
        argv.append("--status")
    return argv


def foreign_path(out: str | os.PathLike[str]) -> Path:
    """Where the recorder keeps the foreign messages of recording ``out`` (messages on the
    run's keys that are not the run's own, see :mod:`diffpos_services.recorder`):
    ``<stem>.foreign.mcap`` next to it."""
    p = Path(out)
    return p.with_name(f"{p.stem}.foreign{p.suffix or '.mcap'}")
