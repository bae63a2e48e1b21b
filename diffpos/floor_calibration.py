"""Can the published floor probability be trusted? Calibration of the per-floor probabilities.

The fusion publishes per node-epoch a floor index and the probability of every floor
(Estimate v2 ``floor_probabilities``); the dashboard shows the coordinator the probability of
the published floor. This module measures whether that number means what it says: of the
node-epochs published at ~0.97, are ~97 % on the right floor? Used by :func:`diffpos.metrics.
score` and :class:`diffpos.metrics.StreamingScore` (the one scorer of emulate, replay and the
benchmarks).

What is measured, and why this set (each is cheap: a few counters and sums per bin, so the
streaming version needs bounded memory and equals the batch one up to rounding):

* a **reliability table** over the reported probability ``p_pub`` of the *published* floor
  (the number the coordinator sees), in the bins of :data:`BIN_EDGES`: ``[0, 0.5)``,
  ``[0.5, 0.8)``, ``[0.8, 0.95)``, ``[0.95, 0.99)``, ``[0.99, 1]`` (with more than two floors
  the most probable one can be below 0.5); per bin the count, the mean ``p_pub`` and the
  fraction on the right floor. The upper bins are narrow on purpose: the tracker publishes
  most node-epochs above 0.95, and 0.96 vs 0.999 is the difference between "check the floor
  above" and "send the team there".
* the **expected calibration error** over those bins, ``sum_b n_b / n |mean p_b - right_b|``
  (the usual binned ECE of the top-label probability; ``n`` = node-epochs with
  probabilities). Its resolution is the bins': it cannot see a miscalibration inside a bin.
* the **log score** ``mean -ln max(p_true, P_FLOOR)`` with :data:`P_FLOOR` = 1e-6 (a wrong
  floor published at probability 1 would be infinite: the clip bounds one node-epoch's
  contribution to 13.8 nats; ``p_true`` is the reported probability of the TRUE floor, so it
  scores the whole vector, not only its top), and the **Brier score** ``mean sum_k (p_k -
  [k = true])^2`` over all floors (bounded in [0, 2], insensitive to the clip).
* the headline for a coordinator: **confidently wrong** = node-epochs whose published floor
  is wrong while ``p_pub >= CONFIDENT`` (0.95), as a share of ALL scored node-epochs (the
  denominator of the floor accuracy over all node-epochs: a node-epoch without a position
  counts in the denominator, never as confidently wrong), and the same count over the
  node-epochs with probabilities.

Which node-epochs are scored: every one counts in ``node_epochs``. A node-epoch with a
position and a published floor whose probability vector is finite, covers the published floor
(``0 <= floor < F``) and whose true floor is known (``0 <= true < F``) has probabilities and
enters the table and the scores. A vector with a NaN or infinite value, of length 0 (estimate
v1, or a method without floor probabilities), or not covering the published floor or the true
floor, is counted in ``without_probabilities`` and left out (it is neither right nor wrong
here; the floor accuracy scores its floor). Values outside [0, 1] (beyond 1e-9) are rejected
(``ValueError``): they are not probabilities. Without any node-epoch with probabilities the
calibration is absent (``None``): e.g. recordings of estimate v1.

Examples
--------
>>> import numpy as np
>>> p = np.array([[0.99, 0.01], [0.97, 0.03], [np.nan, np.nan]])
>>> c = floor_calibration([0, 0, -1], [0, 1, 0], p, has_position=[True, True, False])
>>> c["confidently_wrong"], c["confidently_wrong_count"], c["with_probabilities"]
(0.3333333333333333, 1, 2)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["BIN_EDGES", "CONFIDENT", "P_FLOOR", "FloorCalibration", "floor_calibration",
           "format_calibration", "probability_rows"]

#: bin edges of the reliability table over the published floor's probability (last bin closed)
BIN_EDGES: tuple[float, ...] = (0.0, 0.5, 0.8, 0.95, 0.99, 1.0)
#: a published floor at this probability or more is "confident"
CONFIDENT = 0.95
#: the log score clips the true floor's probability at this value (-ln 1e-6 = 13.8 nats)
P_FLOOR = 1e-6
_TOL = 1e-9


class FloorCalibration:
    """The calibration of a stream of node-epochs in bounded memory (counters and sums per
    bin): :meth:`add` batches, then :meth:`result`. :func:`floor_calibration` is one batch.

    Parameters
    ----------
    bin_edges : sequence of float
        Ascending edges from 0 to 1 (bins ``[e_i, e_i+1)``, the last closed).
    confident : float
        Threshold of "confidently wrong".
    p_floor : float
        Clip of the log score.
    """

    def __init__(self, *, bin_edges: tuple[float, ...] = BIN_EDGES,
                 confident: float = CONFIDENT, p_floor: float = P_FLOOR) -> None:
        e = np.asarray(bin_edges, float)
        if e.ndim != 1 or e.size < 2 or e[0] != 0.0 or e[-1] != 1.0 or np.any(np.diff(e) <= 0):
            raise ValueError(f"bin_edges {bin_edges} must ascend from 0 to 1")
        self.edges = e
        self.confident = float(confident)
        self.p_floor = float(p_floor)
        nb = e.size - 1
        self.count = np.zeros(nb, np.int64)
        self.right = np.zeros(nb, np.int64)
        self.sum_p = np.zeros(nb)
        self.node_epochs = 0
        self.without = 0
        self.confidently_wrong = 0
        self.log_score_sum = 0.0
        self.brier_sum = 0.0

    def add(self, estimate_floor: ArrayLike, truth_floor: ArrayLike,
            floor_probabilities: ArrayLike, *, has_position: ArrayLike | None = None) -> None:
        """A batch of N node-epochs.

        Parameters
        ----------
        estimate_floor, truth_floor : array_like of int, shape (N,)
            Published and true floor index (the published one is ignored without a position).
        floor_probabilities : array_like, shape (N, F) [-]
            Reported probability of every floor (NaN rows where there are none).
        has_position : array_like of bool, shape (N,), optional
            Default: every node-epoch has a position.
        """
        ef = np.asarray(estimate_floor, np.int64).reshape(-1)
        tf = np.asarray(truth_floor, np.int64).reshape(-1)
        n = ef.size
        p = np.asarray(floor_probabilities, float)
        p = p.reshape(n, p.shape[-1] if p.ndim == 2 else -1) if n else p.reshape(0, 0)
        has = (np.ones(n, bool) if has_position is None
               else np.asarray(has_position, bool).reshape(-1))
        if tf.size != n or has.size != n:
            raise ValueError(f"{n} estimate floors, {tf.size} true floors, {has.size} flags")
        fin = np.isfinite(p).all(axis=1) if p.shape[1] else np.zeros(n, bool)
        if np.any(fin & has & ((p < -_TOL) | (p > 1 + _TOL)).any(axis=1)):
            raise ValueError("floor probabilities outside [0, 1]")
        nf = p.shape[1]
        ok = has & fin & (ef >= 0) & (ef < nf) & (tf >= 0) & (tf < nf)
        self.node_epochs += n
        self.without += int((has & ~ok).sum())
        if not ok.any():
            return
        q, e, t = np.clip(p[ok], 0.0, 1.0), ef[ok], tf[ok]
        rows = np.arange(e.size)
        p_pub, p_true, right = q[rows, e], q[rows, t], e == t
        b = np.clip(np.searchsorted(self.edges, p_pub, side="right") - 1, 0, self.count.size - 1)
        nb = self.count.size
        self.count += np.bincount(b, minlength=nb)
        self.right += np.bincount(b, weights=right, minlength=nb).astype(np.int64)
        self.sum_p += np.bincount(b, weights=p_pub, minlength=nb)
        self.confidently_wrong += int((~right & (p_pub >= self.confident)).sum())
        self.log_score_sum += float(-np.log(np.maximum(p_true, self.p_floor)).sum())
        onehot = np.zeros_like(q)
        onehot[rows, t] = 1.0
        self.brier_sum += float(((q - onehot) ** 2).sum())

    def result(self) -> dict[str, Any] | None:
        """The calibration as a plain JSON-able dict, ``None`` without any node-epoch with
        probabilities (see the module docstring for every key's meaning)."""
        k = int(self.count.sum())
        if k == 0:
            return None
        table = []
        ece = 0.0
        for i in range(self.count.size):
            c = int(self.count[i])
            mean_p = float(self.sum_p[i] / c) if c else None
            frac = float(self.right[i] / c) if c else None
            if c:
                ece += c / k * abs(mean_p - frac)
            table.append({"bin": [float(self.edges[i]), float(self.edges[i + 1])],
                          "count": c, "mean_probability": mean_p, "fraction_right": frac})
        return {
            "node_epochs": self.node_epochs,
            "with_probabilities": k,
            "without_probabilities": self.without,
            "reliability": table,
            "ece": ece,
            "log_score": self.log_score_sum / k,
            "log_score_clip": self.p_floor,
            "brier": self.brier_sum / k,
            "confident": self.confident,
            "confidently_wrong_count": self.confidently_wrong,
            "confidently_wrong": self.confidently_wrong / self.node_epochs,
            "confidently_wrong_of_probabilities": self.confidently_wrong / k,
        }


def floor_calibration(estimate_floor: ArrayLike, truth_floor: ArrayLike,
                      floor_probabilities: ArrayLike, *, has_position: ArrayLike | None = None,
                      **kw: Any) -> dict[str, Any] | None:
    """The calibration of N node-epochs at once (:class:`FloorCalibration`'s arguments and
    result); ``None`` without a node-epoch with probabilities."""
    acc = FloorCalibration(**kw)
    acc.add(estimate_floor, truth_floor, floor_probabilities, has_position=has_position)
    return acc.result()


def probability_rows(vectors: Sequence[Sequence[float]]) -> np.ndarray | None:
    """The node-epochs' reported floor probabilities as one (N, F) array, F the longest
    vector: NaN rows where a vector is empty or shorter (estimate v1, no position); ``None``
    when none has any (what :func:`floor_calibration` and the scorer take)."""
    nf = max(map(len, vectors), default=0)
    if nf == 0:
        return None
    out = np.full((len(vectors), nf), np.nan)
    for i, v in enumerate(vectors):
        if len(v) == nf:
            out[i] = v
    return out


def format_calibration(c: dict[str, Any] | None) -> list[str]:
    """The calibration as text lines (the reliability table, then the scores); one line
    saying it is absent when ``c`` is None."""
    if c is None:
        return ["floor probabilities: none reported (estimate v1 or a method without them): "
                "calibration not measured"]
    out = [f"floor probability calibration over {c['with_probabilities']} node-epochs with "
           f"probabilities ({c['without_probabilities']} fixes without):",
           "  p(published floor)   count   mean p   right"]
    for r in c["reliability"]:
        lo, hi = r["bin"]
        close = "]" if hi == 1.0 else ")"
        mp = "-" if r["mean_probability"] is None else f"{r['mean_probability']:.4f}"
        fr = "-" if r["fraction_right"] is None else f"{100 * r['fraction_right']:.2f} %"
        out.append(f"  [{lo:.2f}, {hi:.2f}{close}   {r['count']:9d}   {mp:>6s}   {fr:>8s}")
    out.append(f"  ECE {c['ece']:.4f}; log score {c['log_score']:.4f} nats (p clipped at "
               f"{c['log_score_clip']:g}); Brier {c['brier']:.4f}")
    out.append(f"  confidently wrong (wrong floor at p >= {c['confident']:g}): "
               f"{c['confidently_wrong_count']} = {100 * c['confidently_wrong']:.2f} % of all "
               f"{c['node_epochs']} node-epochs")
    return out
