"""The v2 estimates (``diffpos.estimate.v2``, method mnls, with or without the tracker) of a
batch solved by :func:`~diffpos_services.fusion.tracked.solve_mnls`.

Moved out of :mod:`diffpos_services.fusion.tracked`. A batch's estimates are kept as columns
(:class:`~diffpos_services.fusion.estimates.ColumnBatch`): the
:class:`~diffpos_services.wire.messages.PositionEstimateV2` structs (with their links,
snapshot fixes and lists) are made only when something reads them as messages; a replay's
report reads the columns.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np

from diffpos.alignment import PendingEpoch
from diffpos.paths.mechanisms import MECHANISMS
from diffpos_services.fusion.estimates import ColumnBatch, EstimateRows, finite_or_none_all
from diffpos_services.fusion.step import Batch, exclusion_groups
from diffpos_services.fusion.tracked import _FIX_NAMES, Solved
from diffpos_services.wire import messages as M

__all__ = ["estimates_v2", "v2_builder"]


def _probs(row: list[float], finite: bool) -> list[float]:
    """Floor probabilities for the wire (empty when unknown; clipped into [0, 1])."""
    if not row or not finite:
        return []
    return [min(max(p, 0.0), 1.0) for p in row]


def _finite_rows(a: np.ndarray) -> list[bool]:
    """Whether every value of each row of ``a`` (B, ...) is finite (no NaN rows: non-empty)."""
    return np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1).tolist()


def _snapshot_msg(s: Solved, i: int, pos_l, cov_l, prob_l, fin) -> M.SnapshotFix | None:
    if not s.tracking or not s.snap_rows[i]:
        return None
    st = _FIX_NAMES[int(s.snap.status[i])]
    pos_ok, cov_ok, prob_ok = fin
    ok = st in M.GOOD_STATUSES and pos_ok[i]
    return M.SnapshotFix(
        method="mnls", status=st, position_m=tuple(pos_l[i]) if ok else None,
        covariance_m2=tuple(map(tuple, cov_l[i])) if ok and cov_ok[i] else None,
        floor_index=int(s.snap_floor[i]) if ok and s.snap_floor[i] >= 0 else None,
        floor_probabilities=_probs(prob_l[i], prob_ok[i]))


_MECH_OR_NONE = np.array([*MECHANISMS, None], dtype=object)  # index -1: no mechanism


def _links(use: np.ndarray, mech: np.ndarray, resid: np.ndarray, names: list[str]
           ) -> tuple[list[M.AnchorLink], list[int]]:
    """The :class:`AnchorLink` of every used (row, anchor) of a batch, row by row in anchor
    order, and each row's start in that list (``offs[i]:offs[i + 1]``): built by columns
    (mechanism labels and wire residuals, NaN -> None, for the whole batch at once)."""
    ii, jj = np.nonzero(use)
    offs = np.concatenate([[0], np.cumsum(np.count_nonzero(use, axis=1))]).tolist()
    ids = np.array(names, dtype=object)[jj] if names else np.zeros(0, object)
    links = list(map(M.AnchorLink, ids.tolist(), _MECH_OR_NONE[mech[ii, jj]].tolist(),
                     finite_or_none_all(resid[ii, jj])))
    return links, offs


def estimates_v2(epochs: list[PendingEpoch], batch: Batch, s: Solved, lost: set[str], *,
                 seq0: int, now: int, method: str,
                 rows: np.ndarray | None = None) -> ColumnBatch:
    """One :class:`PositionEstimateV2` per row (only ``rows``, in their order, if given) of a
    batch solved by :func:`solve_mnls`, numbered ``seq0 + 1 ...``: :func:`v2_builder`."""
    return v2_builder(epochs, batch, s, lost)(rows, seq0=seq0, now=now, method=method)


def _snapshot_columns(s: Solved) -> tuple | None:
    """The snapshot fixes' columns as lists (at the time of the call), None without tracking."""
    if not s.tracking:
        return None
    return (s.snap.pos.tolist(), s.snap.cov.tolist(), s.snap_prob.tolist(),
            tuple(_finite_rows(a) for a in (s.snap.pos, s.snap.cov, s.snap_prob)))


def v2_builder(epochs: list[PendingEpoch], batch: Batch, s: Solved, lost: set[str]
               ) -> Callable[..., ColumnBatch]:
    """``build(rows, *, seq0, now, method)``: the :func:`estimates_v2` of ``rows`` (None:
    all) as a :class:`ColumnBatch`. The batch's columns are made once here (finiteness tests
    per batch on the arrays; the per-row work is list indexing), the snapshot columns when
    ``build`` is called, so one builder serves both parts of
    :func:`~diffpos_services.fusion.tracked.in_publish_order` (the second after the fixes)."""
    res = s.res
    group_l, shared = exclusion_groups(batch, res, lost)
    pos_l = res.pos.tolist()
    pos_ok, cov_ok, prob_ok = (_finite_rows(a) for a in (res.pos, res.cov, s.floor_prob))
    peb_l = finite_or_none_all(res.peb)
    # the wire's floor probabilities (_probs) of every row, clipped by columns
    prob_l = np.clip(s.floor_prob, 0.0, 1.0).tolist() if s.floor_prob.shape[1] else None
    best_l = np.argmax(np.where(np.isnan(s.floor_prob), -np.inf,
                                np.clip(s.floor_prob, 0.0, 1.0)), axis=1).tolist()
    t_ref_l = batch.t_ref.tolist()
    in_wall_l = np.where(batch.reported, batch.pub_wall, 0).max(axis=1).tolist()
    good = M.GOOD_STATUSES

    def build(rows: np.ndarray | None, *, seq0: int, now: int, method: str) -> ColumnBatch:
        idx = list(range(len(epochs))) if rows is None else rows.tolist()
        has = [s.status[i] in good and pos_ok[i] for i in idx]
        probs = [prob_l[i] if h and prob_ok[i] and prob_l is not None else []
                 for i, h in zip(idx, has, strict=True)]
        r = EstimateRows(
            node_id=[epochs[i].node_id for i in idx], epoch=[epochs[i].epoch for i in idx],
            t_ns=[t_ref_l[i] for i in idx], status=[s.status[i] for i in idx], ok=has,
            has_pos=has, has_cov=[cov_ok[i] for i in idx], pos=[pos_l[i] for i in idx],
            cov=res.cov[idx], peb=[peb_l[i] for i in idx],
            floor=[best_l[i] if p else None for i, p in zip(idx, probs, strict=True)],
            group=[group_l[i] for i in idx], shared=shared,
            in_wall=[in_wall_l[i] for i in idx], probs=probs)
        make = functools.partial(_structs, r, idx, batch, s, _snapshot_columns(s),
                                 seq0=seq0, now=now, method=method)
        return ColumnBatch(r, make)
    return build


def _structs(r: EstimateRows, idx: list[int], batch: Batch, s: Solved, snap: tuple | None, *,
             seq0: int, now: int, method: str) -> list[M.PositionEstimateV2]:
    """The :class:`PositionEstimateV2` of the rows ``idx`` of a batch (``r``: their
    columns; ``snap``: :func:`_snapshot_columns` at build time)."""
    res = s.res
    zb_l = finite_or_none_all(res.zb)
    used = res.used  # the columns of each row's group's used_idx, row-major
    resid_used_l = np.where(np.isfinite(res.resid), res.resid, 0.0)[used].tolist()
    r_offs = np.concatenate([[0], np.cumsum(np.count_nonzero(used, axis=1))]).tolist()
    links_l, offs = _links(batch.use, s.mechanism, res.resid, batch.names)
    snap_pos, snap_cov, snap_prob, snap_fin = snap if snap is not None else (None,) * 4
    cov_l = r.cov.tolist()
    out = []
    for k, i in enumerate(idx):
        _, used_ids, excluded, _ = r.shared[r.group[k]]
        has = r.has_pos[k]
        out.append(M.PositionEstimateV2(
            node_id=r.node_id[k], t_ns=r.t_ns[k], epoch=r.epoch[k], seq=seq0 + k + 1,
            method=method, status=r.status[k],
            position_m=tuple(r.pos[k]) if has else None,
            covariance_m2=tuple(map(tuple, cov_l[k])) if has and r.has_cov[k] else None,
            peb_m=r.peb[k] if has else None,
            z_bound_m=zb_l[i] if has else None,
            floor_index=r.floor[k], floor_probabilities=r.probs[k],
            snapshot=_snapshot_msg(s, i, snap_pos, snap_cov, snap_prob, snap_fin),
            links=links_l[offs[i]:offs[i + 1]], used_anchors=list(used_ids),
            residuals_m=resid_used_l[r_offs[i]:r_offs[i + 1]],
            excluded=list(excluded), message=res.msg[i] if not s.tracking else "",
            t_input_wall_ns=max(r.in_wall[k], 0), t_pub_wall_ns=now))
    return out
