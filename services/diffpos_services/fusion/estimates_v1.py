"""The v1 estimates (``diffpos.estimate.v1``, methods dnls/lls/ippa) of a solved batch.

Split out of :mod:`diffpos_services.fusion.core` (file length); it updates the core's
counters, node tracks and latencies exactly as before. The estimates of a batch are kept as
columns (:class:`~diffpos_services.fusion.estimates.ColumnBatch`): the
:class:`PositionEstimate` structs and their verdict texts are built only when something reads
them as messages (to publish, keep or write them); a replay's report reads the columns.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from diffpos.alignment import PendingEpoch
from diffpos.estimators.result import FixStatus
from diffpos_services.fusion.estimates import ColumnBatch, EstimateRows, finite_or_none_all
from diffpos_services.fusion.step import GOOD_STATUS, Batch, Results, exclusion_groups, gated_count
from diffpos_services.wire import messages as M

__all__ = ["v1_estimates"]

_STATUS_NAMES = {int(st): st.name for st in FixStatus}


def _structs(r: EstimateRows, res: Results, seq0: int, now: int) -> list[M.PositionEstimate]:
    """The :class:`PositionEstimate` of every row of ``r`` (numbered ``seq0 + 1 ...``)."""
    zb = finite_or_none_all(res.zb)
    resid_l = np.where(np.isfinite(res.resid), res.resid, 0.0).tolist()
    shared, make = r.shared, M.PositionEstimate
    out = []
    for i, (node, t, ep, st, ok, has, has_cov, pos, cov, peb, fl, g, w, msg) in enumerate(zip(
            r.node_id, r.t_ns, r.epoch, r.status, r.ok, r.has_pos, r.has_cov, r.pos,
            r.cov.tolist(), r.peb, r.floor, r.group, r.in_wall, res.msg, strict=True)):
        used_idx, used_ids, excluded, all_used = shared[g]
        resid = resid_l[i] if all_used else [resid_l[i][j] for j in used_idx]
        out.append(make(
            node_id=node,
            t_ns=t,
            epoch=ep,
            seq=seq0 + i + 1,
            status=st,
            position_m=tuple(pos) if has else None,
            covariance_m2=tuple(map(tuple, cov)) if has and has_cov else None,
            peb_m=peb if ok else None,
            z_bound_m=zb[i] if ok else None,
            floor_index=fl if has else None,
            used_anchors=list(used_ids),
            residuals_m=resid,
            excluded=list(excluded),
            message=msg,
            t_input_wall_ns=max(w, 0),
            t_pub_wall_ns=now,
        ))
    return out


def v1_estimates(core: Any, epochs: list[PendingEpoch], batch: Batch, res: Results,
                 now: int) -> ColumnBatch:
    """The batch's estimates (a :class:`ColumnBatch` of :class:`PositionEstimate`); updates
    the counters, the node tracks of good fixes and the latencies now, in row order (numpy ->
    Python lists once per batch)."""
    cfg = core.config
    core.gated += gated_count(batch, res)
    lost = {x.id for x in core.anchors.values() if not x.alive}
    group_l, shared = exclusion_groups(batch, res, lost)
    floors = np.clip(np.floor((res.pos[:, 2] - cfg.first_floor_z_m) / cfg.floor_height_m),
                     -1, cfg.n_floors)
    ok_a = np.isin(res.status, GOOD_STATUS)
    has_a = ok_a & np.all(np.isfinite(res.pos), axis=1)
    rows = EstimateRows(
        node_id=[pe.node_id for pe in epochs], epoch=[pe.epoch for pe in epochs],
        t_ns=batch.t_ref.tolist(), status=[_STATUS_NAMES[st] for st in res.status.tolist()],
        ok=ok_a.tolist(), has_pos=has_a.tolist(),
        has_cov=np.all(np.isfinite(res.cov), axis=(1, 2)).tolist(),
        pos=res.pos.tolist(), cov=res.cov, peb=finite_or_none_all(res.peb),
        floor=np.where(has_a, floors, 0).astype(np.int64).tolist(),
        group=group_l, shared=shared,
        in_wall=np.where(batch.reported, batch.pub_wall, 0).max(axis=1).tolist())
    core.by_status.update(rows.status)
    tracks, t_l, pos_l, node_l = core.tracks, rows.t_ns, rows.pos, rows.node_id
    for i in np.flatnonzero(has_a).tolist():
        tracks[node_l[i]].update(t_l[i], pos_l[i])
    core.latencies_ns.extend(rows.latencies(now))
    out = ColumnBatch(rows, functools.partial(_structs, rows, res, core.seq, now))
    core.seq += len(epochs)
    return out
