"""The floor table: who is on which floor now (``floors``), refreshed once per floor period."""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from diffpos_services.dashboard.columns import EstimateColumns
from diffpos_services.dashboard.common import _group, _sorted_by_time, _time_column


def _log_floor_table(
    rec: rr.RecordingStream, b: Any, floor_period_s: float, st: Any
) -> None:
    """``floors``: the floor table, refreshed at most once per floor period (latest fix per
    node at the end of each period)."""
    t = b.t
    floor_period_ns = max(1, int(floor_period_s * 1e9))
    fb = t // floor_period_ns
    ub = np.unique(fb)
    if st.last_floor_bucket is not None:
        ub = ub[ub != st.last_floor_bucket]
    if not ub.size:
        return
    snap_t = np.array([t[fb == k].max() for k in ub], np.int64)
    texts = _floor_tables(b.est, b.est_floor, b.true_floor, snap_t, st, b.has_pos)
    st.last_floor_bucket = int(ub[-1])
    rec.send_columns(
        "floors",
        indexes=[_time_column(snap_t)],
        columns=rr.TextDocument.columns(text=texts, media_type=["text/markdown"] * len(texts)),
    )


def _latest_fixes(
    est: EstimateColumns, b_floor: tuple[NDArray[np.int64], NDArray[np.int64]],
    has_pos: NDArray[np.bool_], snap_t: NDArray[np.int64], st: Any,
) -> tuple[list[str], np.ndarray]:
    """Nodes, and per node and snapshot time the (estimated floor, true floor, probability,
    fix time) of its latest fix with a position up to the snapshot: array (N, S, 4), fix
    time -1 where the node had none (``st.floors`` holds the last one of earlier batches)."""
    est_floor, true_floor = b_floor
    groups = _group(est.node_id)
    nodes = sorted(set(st.floors) | {g for g, _ in groups})
    out = np.full((len(nodes), snap_t.size, 4), np.nan)
    out[..., 3] = -1
    pos = {n: i for i, n in enumerate(nodes)}
    for nid, prior in st.floors.items():
        out[pos[nid], :, :] = prior
    for nid, rows in groups:
        rows = _sorted_by_time(est.t_ns, rows)
        rows = rows[has_pos[rows]]
        k = np.searchsorted(est.t_ns[rows], snap_t, side="right") - 1
        have = k >= 0
        r = rows[k[have]]
        out[pos[nid], have] = np.stack(
            [est_floor[r], true_floor[r], est.floor_probability[r], est.t_ns[r]], axis=1)
    return nodes, out


def _floor_tables(
    est: EstimateColumns,
    est_floor: NDArray[np.int64],
    true_floor: NDArray[np.int64],
    snap_t: NDArray[np.int64],
    st: Any,
    has_pos: NDArray[np.bool_] | None = None,
) -> list[str]:
    """Markdown tables (one per snapshot time): per floor, top floor first, who is there now
    (each responder on the floor of its latest fix with a position), with the probability of
    that floor (estimate v2) and the age of the fix; a responder not on its true floor is
    marked; responders without any fix yet are listed last."""
    if has_pos is None:
        has_pos = np.all(np.isfinite(est.position_m), axis=1)
    nodes, latest = _latest_fixes(est, (est_floor, true_floor), has_pos, snap_t, st)
    texts = []
    for j in range(snap_t.size):
        by_floor: dict[int, list[str]] = {}
        hits = judged = 0
        waiting = []
        for i, nid in enumerate(nodes):
            ef, tf, p, t_fix = latest[i, j]
            if t_fix < 0:
                waiting.append(nid)
                continue
            ef, tf = int(ef), int(tf)
            age = (snap_t[j] - t_fix) * 1e-9
            cell = f"{nid}" + (f" {100 * p:.0f} %" if np.isfinite(p) else "")
            cell += f" ({age:.0f} s ago)" if age >= 1.5 else ""
            if tf >= 0 and ef >= 0:
                judged += 1
                hits += ef == tf
                if ef != tf:
                    cell += f" **true F{tf}**"
            by_floor.setdefault(ef, []).append(cell)
        head = (f"**{hits}/{judged} responders on their true floor**" if judged else
                "**Responders per floor** (no ground truth)" if nodes else
                "**No responder has a fix yet**")
        # one wrapped line per floor (a markdown table would cut long rows of 50 names)
        lines = [head, "", "*per floor, top first: responder, probability of the floor, age "
                 "of the last fix*", ""]
        for f in sorted(by_floor, reverse=True):
            name = f"F{f}" if f >= 0 else "floor ?"
            lines.append(f"- **{name}** ({len(by_floor[f])}): {', '.join(by_floor[f])}")
        if waiting:
            lines.append(f"- **no fix yet** ({len(waiting)}): {', '.join(waiting)}")
        texts.append("\n".join(lines))
    return texts
