"""The v1 estimates (``diffpos.estimate.v1``, methods dnls/lls/ippa) of a solved batch.

Split out of :mod:`diffpos_services.fusion.core` (file length); it updates the core's
counters, node tracks and latencies exactly as before.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from diffpos.alignment import PendingEpoch
from diffpos.estimators.result import FixStatus
from diffpos_services.fusion.step import GOOD_STATUS, Batch, Results, exclusion_groups, gated_count
from diffpos_services.wire import messages as M

__all__ = ["v1_estimates"]

_STATUS_NAMES = {int(st): st.name for st in FixStatus}


def v1_estimates(core: Any, epochs: list[PendingEpoch], batch: Batch, res: Results,
             now: int) -> list[M.PositionEstimate]:
    """One :class:`PositionEstimate` per epoch; updates the counters, the node tracks of
    good fixes and the latencies (numpy -> Python lists once, not per element)."""
    cfg = core.config
    core.gated += gated_count(batch, res)
    lost = {x.id for x in core.anchors.values() if not x.alive}
    group_l, shared = exclusion_groups(batch, res, lost)
    floors = np.clip(np.floor((res.pos[:, 2] - cfg.first_floor_z_m) / cfg.floor_height_m),
                     -1, cfg.n_floors)
    status_l = res.status.tolist()
    finite_pos = np.all(np.isfinite(res.pos), axis=1).tolist()
    finite_cov = np.all(np.isfinite(res.cov), axis=(1, 2)).tolist()
    pos_l, cov_l = res.pos.tolist(), res.cov.tolist()
    peb_l, zb_l, floor_l = res.peb.tolist(), res.zb.tolist(), floors.tolist()
    resid_l = np.where(np.isfinite(res.resid), res.resid, 0.0).tolist()
    t_ref_l = batch.t_ref.tolist()
    in_wall_l = np.where(batch.reported, batch.pub_wall, 0).max(axis=1).tolist()
    core.by_status.update(_STATUS_NAMES[st] for st in status_l)
    tracks = core.tracks
    out = []
    for i, (pe, gi) in enumerate(zip(epochs, group_l, strict=True)):
        st = status_l[i]
        used_idx, used_ids, excluded, all_used = shared[gi]
        resid = resid_l[i] if all_used else [resid_l[i][j] for j in used_idx]
        ok = st in GOOD_STATUS
        if ok and finite_pos[i]:
            pos = tuple(pos_l[i])
            tracks[pe.node_id].update(t_ref_l[i], pos_l[i])
            cov_t = tuple(map(tuple, cov_l[i])) if finite_cov[i] else None
            fl = int(floor_l[i])
        else:
            pos, cov_t, fl = None, None, None
        in_wall = in_wall_l[i]
        core.seq += 1
        estimate = M.PositionEstimate(
            node_id=pe.node_id,
            t_ns=t_ref_l[i],
            epoch=pe.epoch,
            seq=core.seq,
            status=_STATUS_NAMES[st],
            position_m=pos,
            covariance_m2=cov_t,  # type: ignore[arg-type]
            peb_m=M.finite_or_none(peb_l[i]) if ok else None,
            z_bound_m=M.finite_or_none(zb_l[i]) if ok else None,
            floor_index=fl,
            used_anchors=list(used_ids),
            residuals_m=resid,
            excluded=list(excluded),
            message=res.msg[i],
            t_input_wall_ns=max(in_wall, 0),
            t_pub_wall_ns=now,
        )
        if in_wall > 0:
            core.latencies_ns.append(now - in_wall)
        out.append(estimate)
    return out
