"""Scoring of a live emulation against the true trajectories, and its summary table.

The statistics are :mod:`diffpos.metrics` (the one scorer of emulate, replay and the
benchmarks); this module only collects the estimates as they arrive.
"""

from __future__ import annotations

import collections
from typing import Any

import numpy as np

from diffpos.metrics import floor_accuracy, percentiles
from diffpos_services.wire import messages as M

__all__ = ["SUMMARY_PERCENTILES", "Scorer", "format_summary"]

#: percentiles of the emulate summary
SUMMARY_PERCENTILES = (50, 67, 90, 95)


class Scorer:
    """Errors of the estimates against the true node trajectories (emulation only)."""

    def __init__(self, nodes: list[tuple[str, Any]], building, t0_ns: int) -> None:
        self.traj = dict(nodes)
        self.building = building
        self.t0_ns = t0_ns
        self.count = 0
        self.status: collections.Counter[str] = collections.Counter()
        self.err3d: list[float] = []
        self.errz: list[float] = []
        self.floor_est: list[int | None] = []
        self.floor_true: list[int] = []
        self.peb: list[float] = []
        self.epochs: dict[str, set[int]] = collections.defaultdict(set)

    def add(self, est: M.PositionEstimate) -> float | None:
        """Count ``est``; its 3D error [m] if it has a position and a known node, else None."""
        self.count += 1
        self.status[est.status] += 1
        self.epochs[est.node_id].add(est.epoch)
        tr = self.traj.get(est.node_id)
        if tr is None or est.position_m is None:
            return None
        truth = np.asarray(tr.position_m((est.t_ns - self.t0_ns) * 1e-9), float)
        d = np.asarray(est.position_m) - truth
        e = float(np.linalg.norm(d))
        self.err3d.append(e)
        self.errz.append(abs(float(d[2])))
        if est.peb_m is not None:
            self.peb.append(est.peb_m)
        self.floor_est.append(est.floor_index)
        self.floor_true.append(int(self.building.floor_index(truth[2])))
        return e

    def summary(self) -> dict[str, Any]:
        def pct(v: list[float]) -> dict[str, float | None]:
            return percentiles(v, SUMMARY_PERCENTILES, max_mean=False)

        # a fix without a floor index never matches a true floor
        floors = np.array([-(2**31) if f is None else f for f in self.floor_est], np.int64)
        return {
            "estimates": self.count,
            "with_position": len(self.err3d),
            "status": dict(self.status),
            "error_3d_m": pct(self.err3d),
            "error_z_m": pct(self.errz),
            "peb_m": pct(self.peb),
            # over the fixes with a position (each has its floor)
            "floor_accuracy": floor_accuracy(floors, np.array(self.floor_true, np.int64))[0],
        }


def format_summary(s: dict[str, Any]) -> str:
    """The summary as a plain-text table."""
    def f(v: float | None, unit: str = " m") -> str:
        return "-" if v is None else f"{v:.3f}{unit}"

    rows = [
        ("run", f"{s.get('run_id', '-')}  ({s.get('anchors')} anchors x {s.get('nodes')} nodes, "
                f"{s.get('duration_s')} s at x{s.get('speed')}, channel {s.get('channel')})"),
        ("model", s.get("model", "-")),
        ("estimates", f"{s.get('estimates', 0)} ({s.get('with_position', 0)} with a position)"),
        ("status", ", ".join(f"{k} {v}" for k, v in sorted(s.get("status", {}).items())) or "-"),
    ]
    for name, key in (("3D error", "error_3d_m"), ("z error", "error_z_m"), ("PEB", "peb_m")):
        p = s.get(key, {})
        rows.append((name, "  ".join(f"p{q} {f(p.get(f'p{q}'))}" for q in SUMMARY_PERCENTILES)))
    fa = s.get("floor_accuracy")
    rows.append(("floor accuracy", "-" if fa is None else f"{100 * fa:.1f} %"))
    fu = s.get("fusion")
    if fu:
        lat = fu["latency_ms"]
        rows.append(("gating", f"{fu['gated']} measurements excluded; rejected {fu['rejected'] or 0}; "
                               f"late ranges {fu['late_ranges']}"))
        rows.append(("fusion latency", f"p50 {f(lat['p50'], ' ms')}  p99 {f(lat['p99'], ' ms')}"))
    if s.get("lost"):
        rows.append(("lost", ", ".join(s["lost"])))
    if s.get("recording"):
        rows.append(("recording", f"{s['recording']}  (diffpos replay / inspect / to-rerun FILE)"))
    w = max(len(r[0]) for r in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)
