"""The plain-language notes of an emulated run's summary (``summary["notes"]``, a list of str).

What a user needs to trust the numbers above them (issue 15 items 5, 6 and 9): when and why
fixes were lost (node-epochs without a position, the stretches of the run where most were
lost, the fusion's own account: late ranges per anchor, the lateness allowance in force,
lost anchors, rejections), every file the recorder wrote (split parts, restarts, the file of
foreign messages) and the messages of other publishers. One function per source; the
renderer (``emulate/scoring.py``) wraps them to the terminal.
"""

from __future__ import annotations

import collections
import os
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.summary import summarize
from diffpos_services.recording.writer import existing_parts
from diffpos_services.wire import messages as M

__all__ = ["foreign_notes", "fusion_notes", "loss_notes", "model_notes", "recording_notes"]

#: a stretch of the run counts as "fixes lost" when at least this share of its node-epochs
#: has no position (per-second bins, adjacent ones merged)
LOSS_SHARE = 0.5
#: at most this many stretches are listed
MAX_STRETCHES = 5


def _top(counts: Mapping[str, int], n: int = 6) -> str:
    items = sorted(((k, v) for k, v in counts.items() if v), key=lambda kv: (-kv[1], kv[0]))
    more = f", ... ({len(items) - n} more)" if len(items) > n else ""
    return ", ".join(f"{k} {v}" for k, v in items[:n]) + more


def _stretches(lost_by_s: Mapping[int, tuple[int, int]]) -> list[tuple[int, int, int, int]]:
    """Merged runs of seconds where the lost share >= LOSS_SHARE: (first s, last s, lost,
    total)."""
    out: list[list[int]] = []
    for s in sorted(lost_by_s):
        lost, total = lost_by_s[s]
        if total and lost >= LOSS_SHARE * total:
            if out and out[-1][1] == s - 1:
                out[-1][1], out[-1][2], out[-1][3] = s, out[-1][2] + lost, out[-1][3] + total
            else:
                out.append([s, s, lost, total])
    return [tuple(x) for x in out]  # type: ignore[misc]


def loss_notes(scorer: Any) -> list[str]:
    """When fixes were lost: scored node-epochs without a position (no estimate, or a status
    without one), and the stretches of the run (run time [s]) where most were lost.

    ``scorer`` is the run's :class:`~diffpos_services.emulate.scoring.Scorer`.
    """
    a = scorer.arrays()
    missing = a["missing"]
    no_pos = ~(a["estimate"] == a["estimate"]).all(axis=1)  # NaN rows
    n, n_lost = len(missing), int(no_pos.sum())
    if n == 0 or n_lost == 0:
        return []
    n_missing = int(missing.sum())
    bad = {k: v for k, v in scorer.status.items() if k not in M.GOOD_STATUSES}
    why = f"{n_missing} without an estimate, {n_lost - n_missing} with a status without position"
    if bad:
        why += f" (estimates so: {_top(bad)})"
    notes = [f"fixes lost: {n_lost} of {n} scored node-epochs ({100 * n_lost / n:.1f} %) have no "
             f"position: {why}"]
    per_s = round(1e9 / scorer.period_ns)
    n_nodes = len(scorer.traj)
    by_s: dict[int, list[int]] = collections.defaultdict(lambda: [0, 0])
    for i, lost in enumerate(no_pos.tolist()):
        k = scorer.k_skip + i % (n // n_nodes)  # the grid is node-major
        b = by_s[k // max(per_s, 1)]
        b[0] += lost
        b[1] += 1
    st = _stretches({s: (v[0], v[1]) for s, v in by_s.items()})
    if st:
        shown = "; ".join(f"t = {a0}-{b0 + 1} s ({100 * lost / tot:.0f} % lost)"
                          for a0, b0, lost, tot in st[:MAX_STRETCHES])
        more = f"; ... ({len(st) - MAX_STRETCHES} more)" if len(st) > MAX_STRETCHES else ""
        notes.append(f"fixes lost mostly at (run time): {shown}{more}")
    else:
        notes.append(f"fixes lost spread over the run (no second with >= "
                     f"{100 * LOSS_SHARE:.0f} % of its node-epochs lost)")
    return notes


def fusion_notes(diag: M.FusionDiagnostics | None, t0_wall_ns: int | None = None) -> list[str]:
    """Why, in the fusion's words (its last diagnostics): late ranges (per anchor, with the
    lateness allowance and the largest anchor lag when the diagnostics carry them), anchors
    it lost, messages it rejected. ``t0_wall_ns`` [ns]: the run's start (times of losses)."""
    if diag is None:
        return ["fusion: no diagnostics received (the fusion never reported; see the faults)"]
    notes = []
    if diag.late_ranges:
        line = (f"fusion: {diag.late_ranges} ranges arrived after their epoch was solved and "
                "were not used")
        by_anchor = getattr(diag, "late_by_anchor", None)
        if by_anchor:
            line += f" (by anchor: {_top(by_anchor)})"
        extra = [f"{label} {v * 1e-6:.0f} ms" for label, name in (
            ("lateness allowance in force", "deadline_ns"),
            ("largest allowance", "max_lag_ns"))
            if isinstance(v := getattr(diag, name, None), int | float)]
        if extra:
            line += "; " + ", ".join(extra)
        notes.append(line)
    lags = {k: v for k, v in (getattr(diag, "lag_by_anchor", None) or {}).items() if v}
    if diag.late_ranges and lags:
        worst = sorted(lags.items(), key=lambda kv: -kv[1])[:4]
        notes.append("fusion: anchors lagging behind the others (largest recent lag): "
                     + ", ".join(f"{k} {v * 1e-6:.0f} ms" for k, v in worst))
    releases = {k: v for k, v in (getattr(diag, "releases", None) or {}).items() if v}
    if releases.get("wall_fallback"):
        notes.append(f"fusion: {releases['wall_fallback']} of {sum(releases.values())} epochs "
                     "were released by the wall-clock fallback (an anchor's ranges never came "
                     f"in time); releases by reason: {_top(releases)}")
    for a in diag.anchors:
        if not a.alive:
            when = ""
            if a.lost_wall_ns is not None and t0_wall_ns is not None:
                when = f" at t = {(a.lost_wall_ns - t0_wall_ns) * 1e-9:.1f} s"
            notes.append(f"fusion: anchor {a.anchor_id} lost{when} and not back by the end "
                         "(its liveliness token is gone)")
    rejected = {k: v for k, v in diag.rejected.items() if v}
    if rejected.get("overloaded"):
        notes.append(f"fusion: overloaded: {rejected.pop('overloaded')} node-epochs dropped "
                     "unsolved (the fusion was slower than its input and kept only the last "
                     "max_backlog_s of ready epochs; diffpos fusion --max-backlog-s)")
    if rejected.get("superseded"):
        notes.append(f"fusion: behind its input: {rejected.pop('superseded')} node-epochs "
                     "superseded by the same node's newer epoch (dropped unsolved: each node "
                     "was updated with its newest ranges, round-robin; docs/bad_input.md)")
    if rejected:
        notes.append(f"fusion rejected messages: {_top(rejected, 8)} (docs/bad_input.md)")
    return notes


def recording_notes(recordings: Iterable[str | os.PathLike[str]],
                    foreign_files: Iterable[str | os.PathLike[str]] = ()) -> list[str]:
    """Every file the recorder wrote: each recording (one per recorder start) with its split
    parts, and the files of foreign messages kept apart (with their message count)."""
    notes = []
    for rec in recordings:
        first = Path(rec)
        parts = existing_parts(first)
        if not parts:
            notes.append(f"recording {first}: not written")
        elif len(parts) == 1:
            notes.append(f"recording: {first}")
        else:
            notes.append(f"recording: {first} in {len(parts)} parts (split by duration/size): "
                         + ", ".join(str(p) for p in parts))
    for f in foreign_files:
        p = Path(f)
        if not p.exists():
            continue
        try:
            n = f"{summarize(p).messages} "
        except RecordingError:
            n = ""
        notes.append(f"recorder: {n}foreign messages (not from this run's fusion, or from an "
                     f"anchor outside the scenario) kept apart in {p}, not in the recording")
    return notes


def model_notes(channel: str, method: str) -> list[str]:
    """A channel the fusion's method does not model: ``--channel ideal`` is the paper's
    one-path model (diffraction over an edge that moves with the node, CRLB noise), which the
    first-arrival model of ``mnls`` (the default) does not contain, nor the baselines ``lls``
    (line of sight) and ``ippa``; ``dnls`` is its own."""
    if channel != "ideal" or method == "dnls":
        return []
    what = ("the default fusion (mnls: the building's first-arrival mechanisms)"
            if method == "mnls" else f"--method {method}")
    return [f"model: --channel ideal is the paper's one-path channel, which {what} does not "
            "model; --method dnls is that channel's own model (README, What to expect)"]


def foreign_notes(foreign: Mapping[str, int]) -> list[str]:
    """Messages on the run's estimate/diagnostics keys from other publishers, which emulate
    ignored (not counted, not scored)."""
    n = sum(foreign.values())
    if not n:
        return []
    return [f"foreign: {n} messages not from this run's fusion were ignored (not counted or "
            f"scored; another process publishes on this bus): {_top(foreign, 8)}"]


class _InputStamp(msgspec.Struct):
    t_input_wall_ns: int = 0


class EndToEnd:
    """End-to-end latency of the run's estimates: anchor publish (the estimate's newest input,
    ``t_input_wall_ns``) -> the estimate received by ``emulate`` [ns], the figure a user of
    the positions sees (the fusion's own latency stops at its publish).

    :meth:`add` is cheap (one small decode) and thread-safe: Zenoh's callback calls it.
    Keeps the last ``keep`` values.
    """

    def __init__(self, keep: int = 100_000) -> None:
        self._dec = msgspec.json.Decoder(_InputStamp)
        self._lat: collections.deque[tuple[int, int]] = collections.deque(maxlen=keep)
        self._lock = threading.Lock()

    def add(self, payload: bytes, rx_wall_ns: int) -> None:
        """One estimate (its JSON) received at ``rx_wall_ns`` [ns]."""
        try:
            t_in = self._dec.decode(payload).t_input_wall_ns
        except msgspec.DecodeError:
            return
        if t_in > 0:
            with self._lock:
                self._lat.append((rx_wall_ns, rx_wall_ns - t_in))

    def stats_ms(self, since_wall_ns: int | None = None,
                 inputs_since_wall_ns: int | None = None) -> dict[str, float | int | None]:
        """``count``, ``p50``, ``p99``, ``max`` [ms] (of the estimates received since
        ``since_wall_ns`` and whose newest input was published since
        ``inputs_since_wall_ns``; all kept ones by default)."""
        lo_rx = -(2**63) if since_wall_ns is None else since_wall_ns
        lo_in = -(2**63) if inputs_since_wall_ns is None else inputs_since_wall_ns
        with self._lock:
            lat = [d for rx, d in self._lat if rx >= lo_rx and rx - d >= lo_in]
        if not lat:
            return {"count": 0, "p50": None, "p99": None, "max": None}
        a = np.asarray(lat, np.float64) * 1e-6
        return {"count": int(a.size), "p50": float(np.percentile(a, 50)),
                "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def latency_notes(stats: Mapping[str, Any], settled: Mapping[str, Any] | None = None,
                  skip_s: float = 0.0) -> list[str]:
    """The end-to-end latency line of the summary (nothing without estimates), and with
    ``settled`` the same over the estimates whose inputs came after the first ``skip_s``
    (the part of the run the accuracy is scored on)."""
    if not stats.get("count"):
        return []
    out = [f"end-to-end latency (anchor publish -> estimate received by emulate, solve "
           f"included): p50 {stats['p50']:.1f} ms, p99 {stats['p99']:.1f} ms, max "
           f"{stats['max']:.1f} ms over {stats['count']} estimates"]
    if settled and settled.get("count"):
        out.append(f"after the first {skip_s:g} s: p50 {settled['p50']:.1f} ms, p99 "
                   f"{settled['p99']:.1f} ms, max {settled['max']:.1f} ms over "
                   f"{settled['count']} estimates")
    return out
