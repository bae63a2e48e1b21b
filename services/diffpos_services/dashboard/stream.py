"""The streaming front end (:class:`Dashboard`, live) and the bulk writers of a whole run
(:func:`write_rrd`, :func:`write_rrd_from_messages`, offline)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from diffpos_services.dashboard.blueprint import default_blueprint
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.columns import (
    AnchorColumns,
    EstimateColumns,
    EventColumns,
    TruthColumns,
    anchor_columns_from_messages,
    estimate_columns_from_messages,
    truth_columns_from_messages,
)
from diffpos_services.dashboard.common import APP_ID, node_color
from diffpos_services.dashboard.estimates import _EstimateState, log_estimates
from diffpos_services.dashboard.events import log_diagnostics, log_events
from diffpos_services.dashboard.geometry import Tracks
from diffpos_services.dashboard.plans import log_legend, log_plans_building
from diffpos_services.dashboard.scene import log_anchors, log_building, log_truth


# ============================================================================ streaming + bulk
class Dashboard:
    """Streaming front end: feed batches of decoded bus messages, log them to ``rec``.

    Keeps the little state the live dashboard needs between batches (recent anchor and
    truth history for lookups and trails, last status/exclusion per node for the events).

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to log (its sinks are the caller's business).
    building : BuildingOutline, optional
        Drawn once at construction (static).
    history_s : float [s]
        How much anchor/truth history is kept for lookups and trails.
    """

    def __init__(
        self,
        rec: rr.RecordingStream,
        *,
        building: BuildingOutline | None = None,
        history_s: float = 60.0,
        path_period_s: float = 0.5,
        trail_s: float = 30.0,
    ) -> None:
        self.rec = rec
        self.building = building
        self.history_ns = int(history_s * 1e9)
        self.path_period_s = path_period_s
        self.trail_s = trail_s
        self._anchors = AnchorColumns(np.zeros(0, np.int64), [], np.zeros((0, 3)))
        self._truth = TruthColumns(np.zeros(0, np.int64), [], np.zeros((0, 3)))
        self._est_state = _EstimateState()
        self._diag_state: dict = {"live": None}
        self.counts = {
            "anchor_states": 0,
            "truth": 0,
            "estimates": 0,
            "diagnostics": 0,
            "events": 0,
        }
        #: the responders the plots show: chosen once :data:`PICK_AFTER_S` of estimates are
        #: in (:func:`plot_nodes_of` over them), then the blueprint is sent again with them
        self.plot_nodes: list[str] | None = None
        self._seen: list[EstimateColumns] = []
        if building is not None and rec.is_enabled():
            log_building(rec, building)
            log_plans_building(rec, building)
        if rec.is_enabled():
            log_legend(rec)
            rec.send_blueprint(default_blueprint(building=building))

    def _trim(self, cols, t_now: int):
        keep = cols.t_ns >= t_now - self.history_ns
        return type(cols)(**{f: getattr(cols, f)[keep] for f in cols.__dataclass_fields__})

    def add(
        self,
        *,
        anchor_states: Sequence[Any] = (),
        truth: Sequence[Any] = (),
        estimates: Sequence[Any] = (),
        diagnostics: Sequence[Any] = (),
        events: EventColumns | None = None,
    ) -> None:
        """Log one batch of decoded messages (any of them may be empty).

        With a disabled recording stream (``--rerun off``) messages are only counted.
        """
        if not self.rec.is_enabled():
            self.counts["anchor_states"] += len(anchor_states)
            self.counts["truth"] += len(truth)
            self.counts["estimates"] += len(estimates)
            self.counts["diagnostics"] += len(diagnostics)
            return
        if anchor_states:
            new = anchor_columns_from_messages(anchor_states)
            log_anchors(self.rec, new, history=self._anchors, trail_s=self.trail_s)
            merged = AnchorColumns(
                np.concatenate([self._anchors.t_ns, new.t_ns]),
                np.concatenate([self._anchors.anchor_id, new.anchor_id]),
                np.concatenate([self._anchors.position_m, new.position_m]),
            )
            self._anchors = self._trim(merged, int(merged.t_ns.max()))
            self.counts["anchor_states"] += len(new)
        if truth:
            new_t = truth_columns_from_messages(truth)
            log_truth(self.rec, new_t)
            merged_t = TruthColumns(
                np.concatenate([self._truth.t_ns, new_t.t_ns]),
                np.concatenate([self._truth.node_id, new_t.node_id]),
                np.concatenate([self._truth.position_m, new_t.position_m]),
                np.concatenate([self._truth.floor_index, new_t.floor_index]),
            )
            if len(merged_t):
                self._truth = self._trim(merged_t, int(merged_t.t_ns.max()))
            self.counts["truth"] += len(new_t)
        if estimates:
            est = estimate_columns_from_messages(estimates)
            self._est_state = log_estimates(
                self.rec,
                est,
                anchors=Tracks(
                    self._anchors.t_ns, self._anchors.anchor_id, self._anchors.position_m
                ),
                truth=Tracks(
                    self._truth.t_ns,
                    self._truth.node_id,
                    self._truth.position_m,
                    self._truth.floor_index,
                )
                if len(self._truth)
                else None,
                building=self.building,
                path_period_s=self.path_period_s,
                state=self._est_state,
            )
            self.counts["estimates"] += len(est)
            self._pick_plot_nodes(est)
        if diagnostics:
            self._diag_state = log_diagnostics(self.rec, diagnostics, state=self._diag_state)
            self.counts["diagnostics"] += len(diagnostics)
        if events is not None and events.t_ns.size:
            log_events(self.rec, events)
            self.counts["events"] += int(events.t_ns.size)


    def _pick_plot_nodes(self, est: EstimateColumns) -> None:
        """Once the estimates span :data:`PICK_AFTER_S`: choose the plotted responders, name
        them in the legend and send the blueprint with their plots (once, early: a viewer
        whose layout the user changed since keeps the user's layout only if it was saved)."""
        if self.plot_nodes is not None or not len(est):
            return
        self._seen.append(est)
        t = np.concatenate([e.t_ns for e in self._seen])
        if t.max() - t.min() < PICK_AFTER_S * 1e9:
            return
        seen = EstimateColumns(
            t_ns=t, node_id=np.concatenate([e.node_id for e in self._seen]),
            status=np.concatenate([e.status for e in self._seen]),
            position_m=np.concatenate([e.position_m for e in self._seen]),
            covariance_m2=np.concatenate([e.covariance_m2 for e in self._seen]),
            peb_m=np.concatenate([e.peb_m for e in self._seen]),
            floor_index=np.concatenate([e.floor_index for e in self._seen]),
            floor_probability=np.concatenate([e.floor_probability for e in self._seen]))
        self._seen = []
        self.plot_nodes = plot_nodes_of(seen)
        log_legend(self.rec, {n: node_color(n) for n in self.plot_nodes})
        self.rec.send_blueprint(default_blueprint(building=self.building,
                                                  plot_nodes=self.plot_nodes))


#: live: the plotted responders are chosen over the first this many seconds of estimates
PICK_AFTER_S = 5.0


def write_rrd(
    path: str | Path,
    *,
    building: BuildingOutline | None = None,
    anchors: AnchorColumns | None = None,
    truth: TruthColumns | None = None,
    estimates: EstimateColumns | None = None,
    diagnostics: Sequence[Any] = (),
    events: EventColumns | None = None,
    recording_id: str | None = None,
    path_period_s: float = 0.5,
) -> Path:
    """Write a complete dashboard .rrd from columns, in bulk, with the blueprint embedded.

    Returns the path written.
    """
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
    chosen = plot_nodes_of(estimates) if estimates is not None else []
    rec.save(str(out), default_blueprint=default_blueprint(
        view_points_m=_view_points(building, anchors), building=building, plot_nodes=chosen))
    try:
        log_legend(rec, {n: node_color(n) for n in chosen})
        if building is not None:
            log_building(rec, building)
            log_plans_building(rec, building)
        if anchors is not None and len(anchors):
            log_anchors(rec, anchors)
        if truth is not None and len(truth):
            log_truth(rec, truth)
        if estimates is not None and len(estimates):
            log_estimates(
                rec,
                estimates,
                anchors=Tracks(anchors.t_ns, anchors.anchor_id, anchors.position_m)
                if anchors is not None
                else None,
                truth=Tracks(truth.t_ns, truth.node_id, truth.position_m, truth.floor_index)
                if truth is not None and len(truth)
                else None,
                building=building,
                path_period_s=path_period_s,
            )
        if diagnostics:
            log_diagnostics(rec, diagnostics)
        if events is not None:
            log_events(rec, events)
    finally:
        rec.flush()
        rec.disconnect()
    return out


#: how many responders the plots of a converted recording show
PLOT_NODES = 4


def plot_nodes_of(est: EstimateColumns, k: int = PLOT_NODES) -> list[str]:
    """The ``k`` responders a converted recording plots: those the fusion was least sure
    of, by the mean over their estimates of the probability of the published floor (an
    estimate without a position or without probabilities counts 0 and 1: estimate v1 ranks
    by the share of estimates without a position), ties by id; distinct plot colours
    first (:func:`~diffpos_services.dashboard.common.node_color`)."""
    if not len(est):
        return []
    has_pos = np.all(np.isfinite(est.position_m), axis=1)
    p = np.where(has_pos, np.where(np.isfinite(est.floor_probability), est.floor_probability,
                                   1.0), 0.0)
    ids, inv = np.unique(est.node_id, return_inverse=True)
    mean = np.bincount(inv, weights=p) / np.bincount(inv)
    order = sorted(range(ids.size), key=lambda i: (mean[i], ids[i]))
    out: list[str] = []
    for i in order:  # a colour already taken waits for a second pass
        if node_color(str(ids[i])) not in {node_color(n) for n in out}:
            out.append(str(ids[i]))
        if len(out) == k:
            return out
    return (out + [str(ids[i]) for i in order if str(ids[i]) not in out])[:k]


def _view_points(building: BuildingOutline | None, anchors: AnchorColumns | None) -> np.ndarray:
    """What the default camera must show: the building's corners and every anchor position."""
    pts = [np.zeros((0, 3))]
    if building is not None:
        top = building.first_floor_z_m + building.n_floors * building.floor_height_m
        pts.append(np.array([[x, y, z] for x in (building.x_min_m, building.x_max_m)
                             for y in (0.0, building.depth_m) for z in (0.0, top)]))
    if anchors is not None and len(anchors):
        pts.append(anchors.position_m)
    return np.concatenate(pts)


_KIND_BY_CLASS = {
    "AnchorState": "anchor_state",
    "GroundTruth": "truth",
    "PositionEstimate": "estimate",
    "FusionDiagnostics": "diagnostics",
    "AnchorStateView": "anchor_state",
    "TruthView": "truth",
    "EstimateView": "estimate",
    "DiagnosticsView": "diagnostics",
}


def write_rrd_from_messages(
    messages: Iterable[Any],
    path: str | Path,
    *,
    building: Any = None,
    recording_id: str | None = None,
    events: EventColumns | None = None,
    path_period_s: float = 0.5,
) -> dict[str, int]:
    """Write the dashboard .rrd from decoded bus messages (e.g. read from an MCAP file).

    Parameters
    ----------
    messages : iterable
        Decoded messages in any order: ``AnchorState``, ``GroundTruth``, ``PositionEstimate``,
        ``FusionDiagnostics`` (others, e.g. ``RangeMeasurement``, are ignored). Items may
        also be ``(topic, message)`` or ``(topic, log_time_ns, message)`` tuples.
    path : str or Path
        Output .rrd.
    building : BuildingOutline or scenario building or mapping, optional
        Enables the wireframe, the window-edge diffraction points and floors from z.
    recording_id : str, optional
        Rerun recording id (e.g. the run id), so a live recording and its replay can be
        told apart or merged in the viewer.
    events : EventColumns, optional
        Extra events (e.g. liveliness changes recorded in the MCAP).

    Returns
    -------
    dict
        Number of messages used per kind.
    """
    groups: dict[str, list[Any]] = {
        "anchor_state": [],
        "truth": [],
        "estimate": [],
        "diagnostics": [],
    }
    for item in messages:
        msg = item[-1] if isinstance(item, tuple) else item
        kind = _KIND_BY_CLASS.get(type(msg).__name__)
        if kind is not None:
            groups[kind].append(msg)
    outline = BuildingOutline.from_object(building) if building is not None else None
    truth = truth_columns_from_messages(groups["truth"])
    write_rrd(
        path,
        building=outline,
        anchors=anchor_columns_from_messages(groups["anchor_state"]),
        truth=truth,
        estimates=estimate_columns_from_messages(groups["estimate"]),
        diagnostics=groups["diagnostics"],
        events=events,
        recording_id=recording_id,
        path_period_s=path_period_s,
    )
    return {k: len(v) for k, v in groups.items()} | {"truth_nodes": len(truth)}
