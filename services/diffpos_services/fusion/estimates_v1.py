"""The v1 estimates (``diffpos.estimate.v1``, methods dnls/lls/ippa) of a solved batch.

Split out of :mod:`diffpos_services.fusion.core` (file length); it updates the core's
counters, node tracks and latencies exactly as before. The estimates of a batch are kept as
columns (:class:`V1Batch`): the :class:`PositionEstimate` structs and their verdict texts
are built only when something reads them as messages (to publish, keep or write them); a
replay's report reads the columns (:meth:`V1Batch.rows`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from diffpos.alignment import PendingEpoch
from diffpos.estimators.result import FixStatus
from diffpos_services.fusion.step import GOOD_STATUS, Batch, Results, exclusion_groups, gated_count
from diffpos_services.wire import messages as M

__all__ = ["V1Batch", "V1Rows", "v1_estimates"]

_STATUS_NAMES = {int(st): st.name for st in FixStatus}


@dataclass
class V1Rows:
    """A v1 batch's estimates as columns (lists, one value per row, in row order) and the
    anchor lists they share (``group[i]`` indexes ``shared``, see
    :func:`~diffpos_services.fusion.step.exclusion_groups`). ``has_pos[i]``: the row
    publishes a position (``pos[i]``, and ``cov[i]`` where ``has_cov[i]``; ``peb[i]``,
    ``floor[i]``); the other rows' values of these columns are not messages' values."""

    node_id: list[str]
    epoch: list[int]
    t_ns: list[int]
    status: list[str]
    ok: list[bool]  # a good status (peb_m / z_bound_m published)
    has_pos: list[bool]
    has_cov: list[bool]
    pos: list[list[float]]
    cov: np.ndarray  # (B, 3, 3)
    peb: list[float | None]
    zb: list[float | None]
    floor: list[int]
    resid: list[list[float]]
    group: list[int]
    shared: list[tuple[list[int], list[str], list[M.Exclusion], bool]]
    in_wall: list[int]


class V1Batch(Sequence):
    """The v1 estimates of one solved batch, a sequence of :class:`PositionEstimate` made on
    first access (identical to building them one by one), numbered ``seq0 + 1 ...`` and
    stamped ``t_pub_wall_ns = now``. :attr:`rows` are the columns they are made of."""

    def __init__(self, rows: V1Rows, res: Results, seq0: int, now: int) -> None:
        self.rows, self._res, self.seq0, self.now = rows, res, seq0, now
        self._items: list[M.PositionEstimate] | None = None

    def __len__(self) -> int:
        return len(self.rows.node_id)

    def __getitem__(self, i):  # type: ignore[override]
        return self.items[i]

    def __iter__(self) -> Iterator[M.PositionEstimate]:
        return iter(self.items)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and list(self) == list(other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"V1Batch({len(self)} estimates, seq {self.seq0 + 1}..)"

    @property
    def items(self) -> list[M.PositionEstimate]:
        if self._items is None:
            self._items = self._build()
        return self._items

    def _build(self) -> list[M.PositionEstimate]:
        r, msg, now = self.rows, self._res.msg, self.now
        cov_l = r.cov.tolist()
        out = []
        for i, st in enumerate(r.status):
            used_idx, used_ids, excluded, all_used = r.shared[r.group[i]]
            resid = r.resid[i] if all_used else [r.resid[i][j] for j in used_idx]
            ok, has = r.ok[i], r.has_pos[i]
            out.append(M.PositionEstimate(
                node_id=r.node_id[i],
                t_ns=r.t_ns[i],
                epoch=r.epoch[i],
                seq=self.seq0 + i + 1,
                status=st,
                position_m=tuple(r.pos[i]) if has else None,
                covariance_m2=tuple(map(tuple, cov_l[i])) if has and r.has_cov[i] else None,
                peb_m=r.peb[i] if ok else None,
                z_bound_m=r.zb[i] if ok else None,
                floor_index=r.floor[i] if has else None,
                used_anchors=list(used_ids),
                residuals_m=resid,
                excluded=list(excluded),
                message=msg[i],
                t_input_wall_ns=max(r.in_wall[i], 0),
                t_pub_wall_ns=now,
            ))
        return out


def _finite_or_none(a: np.ndarray) -> list[float | None]:
    """:func:`~diffpos_services.wire.messages.finite_or_none` of every value of ``a`` (B,)."""
    o = a.astype(object)
    o[~np.isfinite(a)] = None
    return o.tolist()


def v1_estimates(core: Any, epochs: list[PendingEpoch], batch: Batch, res: Results,
                 now: int) -> V1Batch:
    """The batch's estimates (:class:`V1Batch`); updates the counters, the node tracks of
    good fixes and the latencies now, in row order (numpy -> Python lists once per batch)."""
    cfg = core.config
    core.gated += gated_count(batch, res)
    lost = {x.id for x in core.anchors.values() if not x.alive}
    group_l, shared = exclusion_groups(batch, res, lost)
    floors = np.clip(np.floor((res.pos[:, 2] - cfg.first_floor_z_m) / cfg.floor_height_m),
                     -1, cfg.n_floors)
    ok_a = np.isin(res.status, GOOD_STATUS)
    has_a = ok_a & np.all(np.isfinite(res.pos), axis=1)
    in_wall = np.where(batch.reported, batch.pub_wall, 0).max(axis=1)
    rows = V1Rows(
        node_id=[pe.node_id for pe in epochs], epoch=[pe.epoch for pe in epochs],
        t_ns=batch.t_ref.tolist(), status=[_STATUS_NAMES[st] for st in res.status.tolist()],
        ok=ok_a.tolist(), has_pos=has_a.tolist(),
        has_cov=np.all(np.isfinite(res.cov), axis=(1, 2)).tolist(),
        pos=res.pos.tolist(), cov=res.cov,
        peb=_finite_or_none(res.peb), zb=_finite_or_none(res.zb),
        floor=np.where(has_a, floors, 0).astype(np.int64).tolist(),
        resid=np.where(np.isfinite(res.resid), res.resid, 0.0).tolist(),
        group=group_l, shared=shared, in_wall=in_wall.tolist())
    core.by_status.update(rows.status)
    tracks, t_l, pos_l, node_l = core.tracks, rows.t_ns, rows.pos, rows.node_id
    for i in np.flatnonzero(has_a).tolist():
        tracks[node_l[i]].update(t_l[i], pos_l[i])
    core.latencies_ns.extend((now - in_wall[in_wall > 0]).tolist())
    out = V1Batch(rows, res, core.seq, now)
    core.seq += len(epochs)
    return out
