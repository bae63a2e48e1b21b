"""Offline replay of a recording through the fusion logic, and the accuracy report.

The recorded anchor states, ranges and anchor liveliness events are fed, in file order (the
recorder's receive order) with their recorded receive times as the fusion's wall clock, into
the same network-free :class:`diffpos_services.fusion.core.FusionCore` the live service runs; the
fusion's time decisions (epoch deadlines) therefore see the times the recorder saw, and the
result depends only on the file and the settings (deterministic, bit for bit). The fusion is
stepped whenever the recorded receive time advanced by ``step_ns`` (the live service steps
after each drain of its queue) and flushed at the end like the live service at shutdown.

The report compares estimates with the recorded ground truth (``truth/node/<id>``,
interpolated linearly at each estimate's reference time ``t_ns``): 3D / horizontal / z error
percentiles per node and overall, floor accuracy, PEB, fix status counts, gating decisions
per anchor, message counts and sequence gaps; optionally recorded-live vs replayed
estimates side by side.
"""

from __future__ import annotations

import contextlib
import gc
import itertools
import json
import logging
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from diffpos_services.fusion.core import FusionConfig, FusionCore
from diffpos_services.kit import ConfigError, build_config
from diffpos_services.recording.mcap_io import (
    McapScanner,
    McapSink,
    RawMessage,
    RecordingError,
    SeqTracker,
    _natural,
    parse_topic,
    replay_estimate_topic,
)
from diffpos_services.wire import messages as M

__all__ = [
    "PERCENTILES",
    "ReplayResult",
    "compare_estimates",
    "derived_fusion_settings",
    "error_stats",
    "live_fusion_settings",
    "plot_cdf",
    "replay",
    "synthetic_run",
    "write_synthetic_recording",
]

#: percentiles reported for every error distribution
PERCENTILES = (50, 67, 90, 95, 99)
_GOOD = ("OK", "OK_UNVERIFIED")
_FUSION_INPUT_KINDS = ("anchor_state", "range", "range_batch")


# ----------------------------------------------------------------------------------------
# settings
# ----------------------------------------------------------------------------------------


def live_fusion_settings(scanner: McapScanner) -> tuple[dict[str, Any], str]:
    """The fusion settings the live run used, as far as the recording says.

    Looks for a metadata record ``fusion_config`` (key -> JSON value), then a ``fusion``
    entry in the ``run_config`` metadata / ``run_config.json`` attachment. Must be called
    after the scanner has been iterated (metadata is read on the way).

    Returns
    -------
    values : dict
        FusionConfig fields (possibly empty).
    source : str
        Where they came from (``"defaults"`` when the recording has none).
    """

    def decode(v: str) -> Any:
        try:
            return json.loads(v)
        except ValueError:
            return v

    for md in scanner.metadata:
        if md.name == "fusion_config":
            return {k: decode(v) for k, v in md.metadata.items()}, "metadata fusion_config"
    for md in scanner.metadata:
        if md.name == "run_config" and "fusion" in md.metadata:
            val = decode(md.metadata["fusion"])
            if isinstance(val, dict):
                return val, "metadata run_config.fusion"
    for att in scanner.attachments:
        if att.name == "run_config.json":
            try:
                doc = json.loads(att.data)
            except ValueError:
                continue
            if isinstance(doc, dict) and isinstance(doc.get("fusion"), dict):
                return doc["fusion"], "attachment run_config.json"
    return {}, "defaults"


def derived_fusion_settings(
    scanner: McapScanner, *, site: str, first_state: bytes | None
) -> tuple[dict[str, Any], str]:
    """Fusion settings as ``diffpos emulate`` would start the fusion, for recordings that do
    not store them: the fusion CLI's defaults, the geometry of the attached scenario (TOML
    attachment; else the built-in paper scenario) and an epoch period of one ranging period
    of the anchors (``range_rate_hz`` of the first anchor state).

    Returns
    -------
    values : dict
    source : str
    """
    import argparse
    import tomllib

    from diffpos.scenario import Scenario, ScenarioError, default_scenario
    from diffpos_services.cli import fusion as cmd_fusion

    scenario, what = None, "paper scenario (built in)"
    for att in scanner.attachments:
        if att.name.endswith(".toml"):
            try:
                scenario = Scenario.from_dict(tomllib.loads(att.data.decode("utf-8")))
                what = f"scenario {att.name} (attached)"
            except (UnicodeDecodeError, tomllib.TOMLDecodeError, ScenarioError):
                continue
            break
    if scenario is None:
        scenario = default_scenario()
    argv = ["--site", site]
    if first_state is not None:
        try:
            rate = M.decoder(M.AnchorState)(first_state).range_rate_hz
            argv += ["--epoch-period-s", repr(1.0 / rate)]
            what += f", epoch = 1/{rate:g} s from the anchors"
        except M.DecodeError:
            pass
    parser = argparse.ArgumentParser()
    cmd_fusion.add_arguments(parser)
    cfg = cmd_fusion.config_from_args(parser.parse_args(argv), scenario)
    return msgspec.to_builtins(cfg), f"derived: fusion CLI defaults, {what}"


def _fusion_fields() -> set[str]:
    return set(FusionConfig.__struct_fields__)


# ----------------------------------------------------------------------------------------
# statistics
# ----------------------------------------------------------------------------------------


def _pct(values: np.ndarray) -> dict[str, float | None]:
    if values.size == 0:
        return {f"p{p}": None for p in PERCENTILES} | {"max": None, "mean": None}
    q = np.percentile(values, PERCENTILES)
    out: dict[str, float | None] = {f"p{p}": float(v) for p, v in zip(PERCENTILES, q, strict=True)}
    out["max"] = float(values.max())
    out["mean"] = float(values.mean())
    return out


def error_stats(
    err_3d_m: np.ndarray,
    err_z_m: np.ndarray,
    err_h_m: np.ndarray,
    floor_ok: np.ndarray,
    peb_m: np.ndarray,
    *,
    fixes: int,
) -> dict[str, Any]:
    """Summary of one error distribution.

    Parameters
    ----------
    err_3d_m, err_z_m, err_h_m : ndarray, shape (K,) [m]
        3D, vertical (absolute) and horizontal errors of the fixes with a position and truth.
    floor_ok : ndarray of bool, shape (K,)
        Estimated floor index equals the true one.
    peb_m : ndarray, shape (K,) [m]
        PEB reported with each fix (NaN when absent).
    fixes : int
        All fixes of the group (with or without a position), for availability.

    Returns
    -------
    dict
        ``fixes``, ``evaluated``, ``availability`` (evaluated / fixes), ``error_3d_m``,
        ``error_z_m``, ``error_h_m`` (percentiles, max, mean), ``rmse_3d_m``,
        ``floor_accuracy``, ``peb_m`` (percentiles of the reported PEB) and
        ``within_2peb`` (fraction of fixes with error <= 2 PEB).
    """
    k = int(err_3d_m.size)
    finite_peb = np.isfinite(peb_m)
    return {
        "fixes": int(fixes),
        "evaluated": k,
        "availability": (k / fixes) if fixes else None,
        "error_3d_m": _pct(err_3d_m),
        "error_z_m": _pct(err_z_m),
        "error_h_m": _pct(err_h_m),
        "rmse_3d_m": float(np.sqrt(np.mean(err_3d_m**2))) if k else None,
        "floor_accuracy": float(np.mean(floor_ok)) if k else None,
        "peb_m": _pct(peb_m[finite_peb]),
        "within_2peb": float(np.mean(err_3d_m[finite_peb] <= 2 * peb_m[finite_peb]))
        if finite_peb.any()
        else None,
    }


@dataclass
class _Truth:
    t_ns: list[int] = field(default_factory=list)
    pos: list[tuple[float, float, float]] = field(default_factory=list)
    floor: list[int] = field(default_factory=list)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(self.t_ns, np.int64)
        order = np.argsort(t, kind="stable")
        return (
            t[order],
            np.asarray(self.pos, float).reshape(-1, 3)[order],
            np.asarray(self.floor, np.int64)[order],
        )


def _evaluate(
    estimates: list[M.PositionEstimate], truth: dict[str, _Truth], *, max_truth_gap_ns: int
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Errors per node and overall; also returns the raw overall error arrays (for plots)."""
    by_node: dict[str, list[M.PositionEstimate]] = defaultdict(list)
    for e in estimates:
        by_node[e.node_id].append(e)
    per_node: dict[str, Any] = {}
    all_parts: dict[str, list[np.ndarray]] = defaultdict(list)
    no_truth = 0
    for node in sorted(by_node, key=_natural):
        ests = by_node[node]
        with_pos = [e for e in ests if e.position_m is not None and e.status in _GOOD]
        tr = truth.get(node)
        if tr is None or not tr.t_ns or not with_pos:
            no_truth += len(with_pos) if tr is None or not tr.t_ns else 0
            per_node[node] = error_stats(
                np.empty(0),
                np.empty(0),
                np.empty(0),
                np.empty(0, bool),
                np.empty(0),
                fixes=len(ests),
            )
            continue
        tt, tp, tf = tr.arrays()
        te = np.array([e.t_ns for e in with_pos], np.int64)
        pe = np.array([e.position_m for e in with_pos], float)
        peb = np.array([np.nan if e.peb_m is None else e.peb_m for e in with_pos], float)
        fe = np.array([-999 if e.floor_index is None else e.floor_index for e in with_pos])
        # nearest truth sample: refuse to evaluate far beyond the truth track
        n = tt.size
        j = np.searchsorted(tt, te)
        left, right = np.clip(j - 1, 0, n - 1), np.clip(j, 0, n - 1)
        dl, dr = np.abs(te - tt[left]), np.abs(te - tt[right])
        closer = np.where(dl <= dr, left, right)
        inside = np.minimum(dl, dr) <= max_truth_gap_ns
        no_truth += int((~inside).sum())
        te, pe, peb, fe, closer = te[inside], pe[inside], peb[inside], fe[inside], closer[inside]
        tq = (te - tt[0]).astype(float)
        tgrid = (tt - tt[0]).astype(float)
        truth_pos = np.stack([np.interp(tq, tgrid, tp[:, k]) for k in range(3)], axis=-1)
        truth_floor = tf[closer]
        d = pe - truth_pos
        e3 = np.linalg.norm(d, axis=-1)
        ez = np.abs(d[:, 2])
        eh = np.linalg.norm(d[:, :2], axis=-1)
        fok = fe == truth_floor
        per_node[node] = error_stats(e3, ez, eh, fok, peb, fixes=len(ests))
        for name, arr in (("e3", e3), ("ez", ez), ("eh", eh), ("fok", fok), ("peb", peb)):
            all_parts[name].append(arr)
    cat = {k: np.concatenate(v) if v else np.empty(0) for k, v in all_parts.items()}
    for k in ("e3", "ez", "eh", "peb"):
        cat.setdefault(k, np.empty(0))
    cat.setdefault("fok", np.empty(0, bool))
    overall = error_stats(
        cat["e3"], cat["ez"], cat["eh"], cat["fok"].astype(bool), cat["peb"], fixes=len(estimates)
    )
    overall["without_truth"] = no_truth
    return {"overall": overall, "per_node": per_node}, cat


def _gating(estimates: list[M.PositionEstimate]) -> dict[str, Any]:
    used: Counter[str] = Counter()
    excluded: dict[str, Counter[str]] = defaultdict(Counter)
    for e in estimates:
        used.update(e.used_anchors)
        for x in e.excluded:
            excluded[x.anchor_id][x.reason] += 1
    anchors = sorted(set(used) | set(excluded), key=_natural)
    return {
        a: {"used": used.get(a, 0), "excluded": dict(sorted(excluded[a].items()))} for a in anchors
    }


def compare_estimates(
    live: list[M.PositionEstimate], replayed: list[M.PositionEstimate]
) -> dict[str, Any]:
    """Recorded-live vs replayed estimates, matched on (node, epoch).

    Returns
    -------
    dict
        ``live``, ``replayed``, ``matched``, ``only_live``, ``only_replayed`` counts,
        ``status_agree`` (fraction of matches with the same status), ``position_diff_m``
        (percentiles/max over matches where both have a position), ``identical_positions``
        (matches whose positions are bit-identical), ``peb_diff_m`` (max abs) and
        ``examples`` (first 5 largest position differences).
    """
    lmap = {(e.node_id, e.epoch): e for e in live}
    rmap = {(e.node_id, e.epoch): e for e in replayed}
    lkeys, rkeys = lmap.keys(), rmap.keys()
    both = sorted(lkeys & rkeys, key=lambda k: (_natural(k[0]), k[1]))
    pairs = [(lmap[k], rmap[k]) for k in both]
    status_same = sum(a.status == b.status for a, b in pairs)
    # pairs where both have a position, as arrays (one vectorised difference, not per pair)
    sel = [i for i, (a, b) in enumerate(pairs)
           if a.position_m is not None and b.position_m is not None]
    keys_d = [both[i] for i in sel]
    pa_m = np.array([pairs[i][0].position_m for i in sel], dtype=np.float64).reshape(-1, 3)
    pb_m = np.array([pairs[i][1].position_m for i in sel], dtype=np.float64).reshape(-1, 3)
    arr = np.sqrt(np.sum((pa_m - pb_m) ** 2, axis=1))
    diffs = arr.tolist()
    identical = int(np.all(pa_m == pb_m, axis=1).sum())
    peb_d = [abs(a.peb_m - b.peb_m) for a, b in (pairs[i] for i in sel)
             if a.peb_m is not None and b.peb_m is not None]
    order = np.argsort(-arr, kind="stable")[:5] if arr.size else []
    return {
        "live": len(live),
        "replayed": len(replayed),
        "matched": len(both),
        "only_live": len(lkeys - rkeys),
        "only_replayed": len(rkeys - lkeys),
        "status_agree": (status_same / len(both)) if both else None,
        "with_positions": int(arr.size),
        "identical_positions": identical,
        "position_diff_m": _pct(arr),
        "peb_diff_m": float(max(peb_d)) if peb_d else None,
        "examples": [
            {
                "node": keys_d[i][0],
                "epoch": keys_d[i][1],
                "diff_m": diffs[i],
                "live_status": lmap[keys_d[i]].status,
                "replayed_status": rmap[keys_d[i]].status,
            }
            for i in order
        ],
    }


# ----------------------------------------------------------------------------------------
# replay
# ----------------------------------------------------------------------------------------


@dataclass
class ReplayResult:
    """Everything a replay produced.

    Attributes
    ----------
    estimates : list of PositionEstimate
        Replayed fixes in the order produced (``t_pub_wall_ns`` = the recorded receive time
        of the message after which the fix was computed, so the list is reproducible).
    live_estimates : list of PositionEstimate
        The estimates recorded from the live fusion.
    report : dict
        JSON-able report (see ``diffpos replay --help``); ``report["timing"]`` is the only
        part that changes between identical runs.
    errors : dict of ndarray
        Overall replayed error arrays (``e3``, ``ez``, ``eh`` [m]) for plots;
        ``live_errors`` the same for the live estimates.
    """

    estimates: list[M.PositionEstimate]
    live_estimates: list[M.PositionEstimate]
    report: dict[str, Any]
    errors: dict[str, np.ndarray]
    live_errors: dict[str, np.ndarray]


@contextlib.contextmanager
def _fewer_gc_passes() -> Iterator[None]:
    """Run the cyclic garbage collector less often for the duration (restored after).

    A replay keeps every replayed and recorded estimate until the report (300,000 each for
    10 minutes of 8 x 50 nodes at 10 Hz); they hold no reference cycles, but with the default
    thresholds the collector traverses them again and again (measured: 17 % of a 2-minute
    replay). Cycles are still collected, just in larger batches.
    """
    old = gc.get_threshold()
    gc.set_threshold(max(old[0], 100_000), max(old[1], 50), max(old[2], 1000))
    try:
        yield
    finally:
        gc.set_threshold(*old)


@_fewer_gc_passes()  # a contextmanager is also a decorator (fresh per call)
def replay(
    path: str | Path,
    *,
    overrides: dict[str, Any] | None = None,
    method: str | None = None,
    step_ms: float = 5.0,
    use_recorded_settings: bool = True,
    out_mcap: str | Path | None = None,
    copy_input: bool = True,
    max_truth_gap_s: float = 0.5,
    progress: Callable[[int, int], None] | None = None,
    logger: logging.Logger | None = None,
) -> ReplayResult:
    """Re-run the fusion on a recording.

    Parameters
    ----------
    path : path
        MCAP recording (complete or truncated: a truncated one is replayed up to its last
        complete chunk, and the report says so).
    overrides : dict, optional
        FusionConfig fields to change (e.g. ``{"gating": False}``,
        ``{"false_alarm_probability": 1e-4}``); applied on top of the recorded settings.
    method : {"dnls", "lls", "ippa"}, optional
        Estimator (``FusionConfig.method``; default: the recorded setting, else D-NLS).
        Overrides a ``method`` in ``overrides``.
    step_ms : float [ms]
        Fusion step granularity in recorded receive time (0 = after every message).
    use_recorded_settings : bool
        Start from the fusion settings stored in the recording (else the defaults).
    out_mcap : path, optional
        Write a new MCAP: (a copy of the input if ``copy_input``) plus the replayed estimates
        on ``diffpos/<site>/replay/node/<id>/estimate``.
    max_truth_gap_s : float [s]
        Estimates farther than this from any truth sample are not evaluated.
    progress : callable, optional
        ``progress(bytes_read, bytes_total)`` after each chunk.
    logger : logging.Logger, optional
        Logger handed to the fusion (default: a quiet one).

    Raises
    ------
    RecordingError
        Not MCAP, missing, or no fusion input (anchor states / ranges) in it.
    ConfigError
        Invalid settings (names the field).
    """
    t_wall0 = time.perf_counter()
    scanner = McapScanner(path)
    if logger is None:
        logger = _quiet_logger()
    step_ns = max(0, round(step_ms * 1e6))

    # settings need the metadata (our recorder writes it before the first chunk) and, when
    # the recording has none, the site and the anchors' ranging rate: read ahead until the
    # first anchor state (at most 64 chunks), then decide.
    batches = scanner.iter_batches()
    ahead: list[list[RawMessage]] = []
    first_state = None
    for batch in batches:
        ahead.append(batch)
        first_state = next((m for m in batch if parse_topic(m.topic)[0] == "anchor_state"), None)
        if first_state is not None or len(ahead) >= 64:
            break
    sites: Counter[str] = Counter()
    for ch in scanner.channels.values():
        kind, fields = parse_topic(ch.topic)
        if kind in _FUSION_INPUT_KINDS:
            sites[fields["site"]] += 1
    recorded, source = live_fusion_settings(scanner)
    if not recorded and use_recorded_settings and sites:
        recorded, source = derived_fusion_settings(
            scanner, site=sites.most_common(1)[0][0],
            first_state=None if first_state is None else first_state.data)
    base: dict[str, Any] = dict(recorded) if use_recorded_settings else {}
    if not use_recorded_settings:
        source = "defaults (--ignore-recorded-settings)"
    unknown_fields = sorted(set(base) - _fusion_fields())
    for f in unknown_fields:
        base.pop(f)
    bad = sorted(set(overrides or {}) - _fusion_fields())
    if bad:
        raise ConfigError(
            f"{', '.join(bad)}: not a fusion setting; known settings: "
            f"{', '.join(sorted(_fusion_fields()))}"
        )
    base.update(overrides or {})
    if method is not None:
        if method not in ("dnls", "lls", "ippa"):
            raise ConfigError(f"--method {method!r}: choose dnls, lls or ippa")
        base["method"] = method
    if "site" not in base and sites:
        base["site"] = sites.most_common(1)[0][0]
    config = build_config(FusionConfig, base)
    site = config.site

    core = FusionCore(config, logger=logger)
    dec_est = M.decoder(M.PositionEstimate)
    dec_truth = M.decoder(M.GroundTruth)
    truth: dict[str, _Truth] = defaultdict(_Truth)
    live: list[M.PositionEstimate] = []
    out: list[M.PositionEstimate] = []
    counts: Counter[str] = Counter()
    bad_payloads: Counter[str] = Counter()
    kind_of: dict[int, str] = {}
    seq = SeqTracker()
    t_first = t_last = None
    sink = None
    if out_mcap is not None:
        sink = McapSink(out_mcap, library="diffpos-replay")
        sink.add_metadata(
            "replay",
            {
                "source": str(path),
                "method": config.method,
                "step_ms": step_ms,
                "settings": msgspec.to_builtins(config),
                "settings_source": source,
            },
        )

    def emit(ests: list[M.PositionEstimate], now_ns: int) -> None:
        for e in ests:
            e = msgspec.structs.replace(e, t_pub_wall_ns=now_ns)
            out.append(e)
            if sink is not None:
                sink.write(replay_estimate_topic(site, e.node_id), M.encode(e), now_ns)

    next_step = None
    for batch in itertools.chain(ahead, batches):
        for m in batch:
            kind = kind_of.get(m.channel_id)
            if kind is None:
                kind = kind_of[m.channel_id] = parse_topic(m.topic)[0]
            counts[kind] += 1
            seq.add(m.topic, m.sequence)
            now = m.log_ns
            if t_first is None:
                t_first = now
            t_last = now
            if sink is not None and copy_input:
                sink.write(m.topic, m.data, now, publish_ns=m.publish_ns, sequence=m.sequence)
            if kind in _FUSION_INPUT_KINDS:
                core.on_sample(m.topic, m.data, now)
            elif kind == "liveliness":
                try:
                    ev = json.loads(m.data)
                    if ev.get("role") == "anchor" and ev.get("id"):
                        core.on_liveliness(str(ev["id"]), bool(ev["alive"]), now)
                except (ValueError, KeyError, TypeError, AttributeError):
                    bad_payloads[kind] += 1
            elif kind == "truth_node":
                try:
                    g = dec_truth(m.data)
                except M.DecodeError:
                    bad_payloads[kind] += 1
                else:
                    tr = truth[g.id]
                    tr.t_ns.append(g.t_ns)
                    tr.pos.append(g.position_m)
                    tr.floor.append(-999 if g.floor_index is None else g.floor_index)
            elif kind == "estimate":
                try:
                    live.append(dec_est(m.data))
                except M.DecodeError:
                    bad_payloads[kind] += 1
            if next_step is None or now >= next_step:
                emit(core.step(now), now)
                next_step = now + step_ns
        if progress is not None:
            progress(scanner.offset, scanner.size_bytes)
    if counts["anchor_state"] + counts["range"] + counts["range_batch"] == 0:
        if sink is not None:
            sink.close()
        raise RecordingError(
            f"{path} has no anchor states or ranges under diffpos/<site>/anchor/...: "
            "nothing to replay (is it a diffpos recording? see diffpos inspect)"
        )
    end = (t_last or 0) + 10**12  # far past every deadline: what is pending is solved
    emit(core.step(end), t_last or 0)
    emit(core.flush(t_last or 0), t_last or 0)  # like the live service at shutdown
    if sink is not None:
        sink.close(final_metadata={"replayed_estimates": len(out)})

    gap_s = round(max_truth_gap_s * 1e9)
    accuracy, errs = _evaluate(out, truth, max_truth_gap_ns=gap_s)
    live_accuracy, live_errs = (
        _evaluate(live, truth, max_truth_gap_ns=gap_s) if live else (None, {})
    )
    duration_s = ((t_last or 0) - (t_first or 0)) / 1e9
    wall = time.perf_counter() - t_wall0
    report: dict[str, Any] = {
        "file": str(path),
        "complete": scanner.complete,
        "damage": {**scanner.damage.__dict__, "ok": scanner.damage.ok},
        "settings": msgspec.to_builtins(config),
        "settings_source": source,
        "ignored_recorded_fields": unknown_fields,
        "overrides": dict(overrides or {}),
        "method": config.method,
        "step_ms": step_ms,
        "recording_s": duration_s,
        "messages": {
            "by_kind": dict(sorted(counts.items())),
            "total": sum(counts.values()),
            "skipped_unknown": counts.get("unknown", 0),
            "undecodable": dict(bad_payloads),
            "gaps": seq.total_gaps,
            "gaps_by_stream": dict(sorted(seq.gaps.items())[:200]),
            "out_of_order": seq.total_out_of_order,
            "fusion_received": dict(core.received),
            "fusion_rejected": dict(core.rejected),
            "late_ranges": core.book.late,
        },
        "fixes": {
            "total": len(out),
            "by_status": dict(sorted(Counter(e.status for e in out).items())),
        },
        "nodes": sorted({e.node_id for e in out} | set(truth), key=_natural),
        "anchors": sorted(core.anchors, key=_natural),
        "accuracy": accuracy,
        "gating": _gating(out),
        "live": None
        if live_accuracy is None
        else {
            "fixes": len(live),
            "by_status": dict(sorted(Counter(e.status for e in live).items())),
            "accuracy": live_accuracy,
            "gating": _gating(live),
        },
        "compare": compare_estimates(live, out) if live else None,
        "timing": {
            "wall_s": wall,
            "speedup_x": (duration_s / wall) if wall > 0 and duration_s > 0 else None,
        },
    }
    return ReplayResult(
        estimates=out, live_estimates=live, report=report, errors=errs, live_errors=live_errs
    )


# ----------------------------------------------------------------------------------------
# plot
# ----------------------------------------------------------------------------------------


def plot_cdf(result: ReplayResult, path: str | Path, *, title: str | None = None) -> Path:
    """Empirical CDFs of the 3D and z errors (replayed, and recorded-live when present).

    Parameters
    ----------
    result : ReplayResult
    path : path
        PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    method = result.report.get("method", "dnls").upper().replace("DNLS", "D-NLS")
    curves = [
        (result.errors.get("e3"), f"3D error, replay ({method})", "C0", "-"),
        (result.errors.get("ez"), f"z error, replay ({method})", "C1", "-"),
    ]
    if result.live_estimates:
        curves += [
            (result.live_errors.get("e3"), "3D error, recorded live", "C0", "--"),
            (result.live_errors.get("ez"), "z error, recorded live", "C1", "--"),
        ]
    xmax = 0.0
    for arr, label, color, ls in curves:
        if arr is None or arr.size == 0:
            continue
        x = np.sort(arr)
        y = np.arange(1, x.size + 1) / x.size
        ax.step(x, y, where="post", label=f"{label} (n={x.size})", color=color, linestyle=ls)
        xmax = max(xmax, float(np.percentile(x, 99)))
    ax.set_xlim(0, xmax * 1.05 if xmax > 0 else 1.0)
    ax.set_ylim(0, 1)
    ax.set_xlabel("error [m]")
    ax.set_ylabel("CDF")
    ax.grid(True, alpha=0.3)
    ax.set_title(title or f"Positioning error CDF - {Path(result.report['file']).name}")
    if xmax > 0:
        ax.legend(loc="lower right", fontsize=8)
    else:
        ax.text(
            0.5, 0.5, "no fixes with ground truth to evaluate", ha="center", transform=ax.transAxes
        )
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


# ----------------------------------------------------------------------------------------
# synthetic recordings (tests and benchmarks without Zenoh)
# ----------------------------------------------------------------------------------------

#: geometry of :func:`write_synthetic_recording` (the paper-like building of the scenario model)
SYNTHETIC_FUSION = {
    "window_height_m": 1.5,
    "edge_x_m": [-20.0, 20.0],
    "first_floor_z_m": 4.0,
    "floor_height_m": 3.0,
    "n_floors": 5,
    "epoch_period_s": 0.1,
    "deadline_s": 0.3,
}


@dataclass(frozen=True)
class SyntheticRun:
    """An emulated run without Zenoh (see :func:`synthetic_run`).

    Attributes
    ----------
    config : FusionConfig
        Fusion settings matching the geometry.
    anchor_ids, node_ids : list of str
    t0_ns : int [ns]
        Start of the run (emulated time).
    epochs : iterator of list of (rx_ns, key, payload)
        Per epoch, every message in receive order: anchor states, ranges and node truth.
    """

    config: FusionConfig
    anchor_ids: list[str]
    node_ids: list[str]
    t0_ns: int
    epochs: Iterator[list[tuple[int, str, bytes]]]


def synthetic_run(
    *,
    n_anchors: int = 5,
    n_nodes: int = 4,
    duration_s: float = 5.0,
    rate_hz: float = 10.0,
    sigma_m: float = 0.1,
    outlier_probability: float = 0.0,
    seed: int = 0,
    site: str = "synth",
    t0_ns: int = 100_000_000_000_000_000,
    range_batch: bool = False,
) -> SyntheticRun:
    """Messages of an emulated run, generated without Zenoh.

    Anchors hover outside the facade (``y < 0``), nodes walk slowly on their floor inside
    (straight lines, reflected at the walls of a 39 m x 21.5 m floor);
    ranges are the diffraction path lengths over the window edge (the fusion's own model)
    plus Gaussian noise and, with ``outlier_probability``, positive NLoS-like biases of
    2-10 m. Each epoch an anchor reports its state and a range to every node at its own phase
    (one sequence counter per anchor, like the anchor service); receive times add 0.2-1.2 ms
    of latency. The default ``t0_ns`` (1e17 ns, 1973) keeps FusionCore's int64 sum of an
    epoch's range times from overflowing (present-day Unix times overflow with 5+ anchors:
    reported upstream).

    Parameters
    ----------
    n_anchors, n_nodes : int
    duration_s : float [s]
    rate_hz : float [Hz]
        Ranging rate of every anchor (= fusion epoch rate).
    sigma_m : float [m]
        Ranging noise one-sigma.
    outlier_probability : float
    seed : int
    site : str
    t0_ns : int [ns]
    range_batch : bool
        Anchors publish one :class:`RangeBatch` per epoch on ``anchor/<id>/ranges`` (like
        ``diffpos anchor --range-batch``) instead of one message per node.
    """
    from diffpos.geometry import window_edge_path
    from diffpos_services.wire.keys import Keys

    rng = np.random.default_rng(seed)
    keys = Keys(site)
    config = build_config(
        FusionConfig, dict(SYNTHETIC_FUSION, site=site, epoch_period_s=1.0 / rate_hz)
    )
    period_ns = round(1e9 / rate_hz)
    ang = np.linspace(0, np.pi, n_anchors)
    anchors = np.stack(
        [
            -18 + 36 * np.arange(n_anchors) / max(n_anchors - 1, 1),
            -8 - 10 * np.sin(ang),
            1.0 + 3.0 * (np.arange(n_anchors) % 2),
        ],
        axis=-1,
    )
    anchor_ids = [f"uav{i + 1}" for i in range(n_anchors)]
    floors = rng.integers(0, 5, n_nodes)
    start = np.stack(
        [rng.uniform(-15, 15, n_nodes), rng.uniform(2, 15, n_nodes), 4.0 + 3.0 * floors + 1.5],
        axis=-1,
    )
    vel = np.concatenate([rng.normal(0, 0.5, (n_nodes, 2)), np.zeros((n_nodes, 1))], axis=-1)
    node_ids = [f"n{i + 1:02d}" for i in range(n_nodes)]
    phases = (0.05 + 0.9 * np.arange(n_anchors) / n_anchors) * period_ns
    enc = M.encode
    n_epochs = round(duration_s * rate_hz)

    lo, hi = np.array([-19.5, 0.5]), np.array([19.5, 22.0])  # x, y extent of the walk [m]

    def node_state(t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities: straight walks reflected at the walls of the floor, so
        long runs keep the nodes spread over the floor (not piled up in the corners)."""
        raw = start + vel * ((t_ns - t0_ns) * 1e-9)
        span = hi - lo
        q = np.mod(raw[:, :2] - lo, 2.0 * span)
        back = q > span
        p, v = raw.copy(), vel.copy()
        p[:, :2] = lo + np.where(back, 2.0 * span - q, q)
        v[:, :2] = np.where(back, -vel[:, :2], vel[:, :2])
        return p, v

    def epochs() -> Iterator[list[tuple[int, str, bytes]]]:
        seqs: Counter[str] = Counter()
        for e in range(n_epochs):
            items: list[tuple[int, str, bytes]] = []
            te = t0_ns + e * period_ns
            for j, a in enumerate(anchor_ids):
                t = te + int(phases[j])
                r = window_edge_path(
                    anchors[j], node_state(t)[0], window_height_m=1.5, edge_x_m=(-20.0, 20.0)
                ).length_m
                r = r + rng.normal(0, sigma_m, n_nodes)
                if outlier_probability > 0:
                    out = rng.random(n_nodes) < outlier_probability
                    r = r + out * rng.uniform(2, 10, n_nodes)
                rx = t + int(rng.integers(200_000, 1_200_000))
                items.append(
                    (
                        rx,
                        keys.anchor_state(a),
                        enc(
                            M.AnchorState(
                                anchor_id=a,
                                t_ns=t,
                                seq=seqs[a],
                                position_m=M.vec3(anchors[j]),
                                velocity_m_s=(0.0, 0.0, 0.0),
                                position_sigma_m=(0.05, 0.05, 0.05),
                                velocity_sigma_m_s=0.02,
                                range_rate_hz=rate_hz,
                                t_pub_wall_ns=t,
                            )
                        ),
                    )
                )
                seqs[a] += 1
                if range_batch:
                    batch = M.RangeBatch(anchor_id=a, t_ns=t, seq=seqs[a], node_ids=node_ids,
                                         range_m=r.tolist(), sigma_m=[sigma_m] * n_nodes,
                                         snr_db=[20.0] * n_nodes, t_pub_wall_ns=t)
                    items.append((rx + 1000, keys.anchor_range_batch(a), enc(batch)))
                    seqs[a] += 1
                else:
                    for i, n in enumerate(node_ids):
                        rm = M.RangeMeasurement(anchor_id=a, node_id=n, t_ns=t, seq=seqs[a],
                                                range_m=float(r[i]), sigma_m=sigma_m,
                                                snr_db=20.0, t_pub_wall_ns=t)
                        items.append((rx + 1000 * (i + 1), keys.anchor_range(a, n), enc(rm)))
                        seqs[a] += 1
            tt = te + period_ns // 2
            pos_t, vel_t = node_state(tt)
            for i, n in enumerate(node_ids):
                items.append(
                    (
                        tt + 300_000,
                        keys.truth_node(n),
                        enc(
                            M.GroundTruth(
                                entity="node",
                                id=n,
                                t_ns=tt,
                                position_m=M.vec3(pos_t[i]),
                                velocity_m_s=M.vec3(vel_t[i]),
                                floor_index=int(floors[i]),
                            )
                        ),
                    )
                )
            items.sort(key=lambda x: x[0])
            yield items

    return SyntheticRun(config, anchor_ids, node_ids, t0_ns, epochs())


def write_synthetic_recording(
    path: str | Path,
    *,
    live: bool = True,
    live_step_ms: float = 5.0,
    flush_every: int = 0,
    **run_kw: Any,
) -> dict[str, int]:
    """Write a recording of a :func:`synthetic_run` like the recorder would.

    With ``live`` a FusionCore run over the same stream (stepped every ``live_step_ms`` of
    receive time) plays the live fusion and its estimates are recorded on
    ``node/<id>/estimate``. The fusion settings are stored as metadata ``fusion_config``
    (what ``diffpos replay`` starts from).

    Parameters
    ----------
    path : path
        Output MCAP.
    live : bool
    live_step_ms : float [ms]
    flush_every : int
        Close a chunk every this many messages (0: only by size).
    **run_kw
        Passed to :func:`synthetic_run`.

    Returns
    -------
    counts : dict
        Messages written per kind.
    """
    run = synthetic_run(**run_kw)
    site = run.config.site
    from diffpos_services.wire.keys import Keys

    keys = Keys(site)
    sink = McapSink(path, library="diffpos-synthetic")
    sink.add_metadata("run", {"scenario": "synthetic", "site": site, **run_kw})
    sink.add_metadata("fusion_config", msgspec.to_builtins(run.config))
    core = FusionCore(run.config, logger=_quiet_logger()) if live else None
    counts: Counter[str] = Counter()
    for a in run.anchor_ids:
        sink.write_liveliness(site, keys.alive_anchor(a), True, run.t0_ns - 10_000_000)
        if core is not None:
            core.on_liveliness(a, True, run.t0_ns - 10_000_000)
    next_step = None
    step_ns = round(live_step_ms * 1e6)
    written = 0
    for items in run.epochs:
        for rx, k, payload in items:
            sink.write(k, payload, rx)
            kind = parse_topic(k)[0]
            counts[kind] += 1
            written += 1
            if flush_every and written % flush_every == 0:
                sink.flush()
            if core is None or kind not in _FUSION_INPUT_KINDS:
                continue
            core.on_sample(k, payload, rx)
            if next_step is None or rx >= next_step:
                for est in core.step(rx):
                    est = msgspec.structs.replace(est, t_pub_wall_ns=rx)
                    sink.write(keys.node_estimate(est.node_id), M.encode(est), rx + 50_000)
                    counts["estimate"] += 1
                next_step = rx + step_ns
    sink.close()
    return dict(counts)


def _quiet_logger() -> logging.Logger:
    lg = logging.getLogger("diffpos.replay.quiet")
    lg.setLevel(logging.ERROR)
    return lg
