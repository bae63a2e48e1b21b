"""Fixes against the recorded truth, gating decisions, live vs replayed (replay's report).

The math of the error summaries is :mod:`diffpos.metrics` (the one scorer); this module
matches recorded messages to it: truth tracks per node, fixes per node, (node, epoch) pairs.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from diffpos.metrics import error_stats, percentiles, score, truth_at
from diffpos_services.recording.topics import natural_key
from diffpos_services.replay.report_stream import NO_TRACK_STATUSES
from diffpos_services.wire import messages as M

__all__ = ["TruthTracks", "compare_estimates", "evaluate", "gating_counts",
           "node_epoch_accuracy"]


@dataclass
class TruthTracks:
    """Recorded ground truth of one node (appended in file order; sorted by :meth:`arrays`)."""

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


def evaluate(
    estimates: list[M.PositionEstimate], truth: dict[str, TruthTracks], *, max_truth_gap_ns: int,
    floor_of: Callable[[np.ndarray], Any] | None = None,
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Errors per node and overall against the truth; also returns the raw overall error
    arrays (``e3``, ``ez``, ``eh``, ``fok``, ``peb``; for plots).

    A fix is evaluated when it has a good status and a position and the node has a truth
    sample within ``max_truth_gap_ns`` (truth interpolated linearly at the fix time; its floor
    ``floor_of`` of that height, the building's ``floor_index``, or without one the floor of
    the nearest sample: :func:`diffpos.metrics.truth_at`). Availability counts every published
    fix of the node.
    """
    by_node: dict[str, list[M.PositionEstimate]] = defaultdict(list)
    for e in estimates:
        by_node[e.node_id].append(e)
    per_node: dict[str, Any] = {}
    all_parts: dict[str, list[np.ndarray]] = defaultdict(list)
    no_truth = 0
    for node in sorted(by_node, key=natural_key):
        ests = by_node[node]
        with_pos = [e for e in ests if e.position_m is not None and e.status in M.GOOD_STATUSES]
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
        inside = np.minimum(dl, dr) <= max_truth_gap_ns
        no_truth += int((~inside).sum())
        te, pe, peb, fe = te[inside], pe[inside], peb[inside], fe[inside]
        truth_pos, truth_floor = truth_at(te, tt, tp, tf, floor_of=floor_of)
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


def gating_counts(estimates: list[M.PositionEstimate]) -> dict[str, Any]:
    """Per anchor: fixes that used it, fixes that measured it while the node had no track
    (``no_track``: the "RAIM" of a fix in :data:`NO_TRACK_STATUSES
    <diffpos_services.replay.report_stream.NO_TRACK_STATUSES>`, not an exclusion), and
    exclusions by reason (as :meth:`FixStream.gating
    <diffpos_services.replay.report_stream.FixStream.gating>`)."""
    used: Counter[str] = Counter()
    no_track: Counter[str] = Counter()
    excluded: dict[str, Counter[str]] = defaultdict(Counter)
    for e in estimates:
        used.update(e.used_anchors)
        for x in e.excluded:
            if x.reason == "RAIM" and e.status in NO_TRACK_STATUSES:
                no_track[x.anchor_id] += 1
            else:
                excluded[x.anchor_id][x.reason] += 1
    anchors = sorted(set(used) | set(excluded) | set(no_track), key=natural_key)
    return {
        a: {"used": used.get(a, 0), "no_track": no_track.get(a, 0),
            "excluded": dict(sorted(excluded[a].items()))} for a in anchors
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
    both = sorted(lkeys & rkeys, key=lambda k: (natural_key(k[0]), k[1]))
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
        "position_diff_m": percentiles(arr),
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


def node_epoch_accuracy(estimates: list[Any], truth: dict[str, TruthTracks], *,
                        skip_s: float = 2.0,
                        floor_of: Callable[[np.ndarray], Any] | None = None) -> dict[str, Any]:
    """Every node-epoch after the first ``skip_s`` of the truth: :func:`diffpos.metrics.score`.

    The node-epochs are the recorded truth samples of every node (one per node and epoch of
    an emulated run) from ``skip_s`` after the first one; a node-epoch's estimate is the fix of
    that node whose ``t_ns`` falls in the same epoch (the truth sample spacing), if it has a
    usable position (``GOOD_STATUSES``), else it is a miss (availability and floor accuracy
    over all node-epochs count it); a fix is compared with the truth at its own ``t_ns``
    (:func:`diffpos.metrics.truth_at`: the floor ``floor_of`` of the true height then, the
    building's ``floor_index``; without one the nearest sample's). v1 and v2 estimates alike.

    Returns
    -------
    dict
        :meth:`diffpos.metrics.Score.as_dict` plus ``skip_s``; ``{}`` without truth.
    """
    tracks = {n: tr.arrays() for n, tr in truth.items() if tr.t_ns}
    if not tracks:
        return {}
    t_all = np.unique(np.concatenate([t for t, _, _ in tracks.values()]))
    period = int(np.min(np.diff(t_all))) if t_all.size > 1 else 0
    if period <= 0:
        return {}
    start = int(t_all[0]) + round(skip_s * 1e9)
    fixes: dict[tuple[str, int], Any] = {}
    for e in estimates:
        if e.position_m is not None and e.status in M.GOOD_STATUSES:
            fixes[(e.node_id, e.t_ns // period)] = e
    est, tru, e_floor, t_floor, cov = [], [], [], [], []
    for node in sorted(tracks, key=natural_key):
        tt, tp, tf = tracks[node]
        for t, p, f in zip(tt.tolist(), tp, tf.tolist(), strict=True):
            if t < start:
                continue
            e = fixes.get((node, t // period))
            est.append(e.position_m if e is not None else (np.nan,) * 3)
            cov.append(e.covariance_m2 if e is not None and e.covariance_m2 is not None
                       else np.full((3, 3), np.nan))
            e_floor.append(-1 if e is None or e.floor_index is None else e.floor_index)
            if e is not None:  # the truth at the estimate's own time
                (p,), (f,) = truth_at([e.t_ns], tt, tp, tf, floor_of=floor_of)
            tru.append(p)
            t_floor.append(f)
    if not est:
        return {}
    s = score(np.array(est, float), np.array(tru, float), estimate_floor=e_floor,
              truth_floor=t_floor, covariance_m2=np.array(cov, float))
    return s.as_dict() | {"skip_s": skip_s}
