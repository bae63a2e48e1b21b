"""A plausible synthetic run as bus messages, for demos, tests and benchmarks (no Zenoh)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from diffpos_services.dashboard.building import BuildingOutline

__all__ = ["synthetic_run"]


def synthetic_run(
    *,
    n_anchors: int = 4,
    n_nodes: int = 6,
    duration_s: float = 20.0,
    rate_hz: float = 10.0,
    seed: int = 0,
    t0_ns: int = 1_700_000_000_000_000_000,
) -> tuple[BuildingOutline, list[Any]]:
    """A plausible synthetic run as bus messages, for demos, tests and benchmarks.

    Anchors circle outside the facade (y < 0), nodes walk slowly on their floor at the
    window mid-height, estimates are truth plus Gaussian noise drawn from their own
    covariance; every 7th fix of node 0 excludes one anchor (``RAIM``) and node 1
    is ``NOT_IDENTIFIABLE`` (no position) for one second in the middle. The last anchor leaves
    the fusion's live set after two thirds of the run (FusionDiagnostics every second).

    Returns
    -------
    building : BuildingOutline
    messages : list
        ``AnchorState``, ``GroundTruth`` (nodes), ``PositionEstimate`` and
        ``FusionDiagnostics`` structs of :mod:`diffpos_services.wire.messages`, in time order.
    """
    from diffpos_services.wire import messages as m

    rng = np.random.default_rng(seed)
    b = BuildingOutline(
        x_min_m=-12.0,
        x_max_m=12.0,
        depth_m=14.0,
        n_floors=4,
        floor_height_m=3.5,
        sill_height_m=0.9,
        window_height_m=1.6,
    )
    n_t = max(1, round(duration_s * rate_hz))
    t_ns = t0_ns + (np.arange(n_t) * (1e9 / rate_hz)).astype(np.int64)
    ts = (t_ns - t0_ns) / 1e9
    # anchors: ellipses outside the facade
    phase = rng.uniform(0, 2 * np.pi, n_anchors)
    ang = phase[None, :] + 0.05 * ts[:, None]
    a_pos = np.stack(
        [
            14.0 * np.cos(ang),
            -12.0 - 4.0 * np.sin(ang),
            np.linspace(4.0, 14.0, n_anchors)[None, :] + 1.0 * np.sin(2 * ang),
        ],
        axis=-1,
    )  # (T, A, 3)
    a_ids = [f"uav{i + 1}" for i in range(n_anchors)]
    # nodes: random walk on a floor at window mid-height
    floors = rng.integers(0, b.n_floors, n_nodes)
    z_mid = floors * b.floor_height_m + b.sill_height_m + 0.5 * b.window_height_m
    start = np.stack([rng.uniform(-9, 9, n_nodes), rng.uniform(2, 12, n_nodes), z_mid], axis=-1)
    steps = rng.normal(0.0, 0.03, (n_t, n_nodes, 3))
    steps[..., 2] = 0.0
    n_pos = start[None] + np.cumsum(steps, axis=0)
    n_pos[..., 0] = np.clip(n_pos[..., 0], -11, 11)
    n_pos[..., 1] = np.clip(n_pos[..., 1], 0.5, 13.5)
    n_ids = [f"n{i:02d}" for i in range(n_nodes)]
    # estimates: per fix a random covariance (axes 0.2..1.5 m, random rotation)
    sig = rng.uniform(0.2, 1.5, (n_t, n_nodes, 3))
    q, _ = np.linalg.qr(rng.normal(size=(n_t, n_nodes, 3, 3)))
    cov = q @ (sig[..., :, None] ** 2 * np.swapaxes(q, -1, -2))
    noise = np.einsum("...ij,...j->...i", q, sig * rng.normal(size=(n_t, n_nodes, 3)))
    e_pos = n_pos + noise
    peb = np.sqrt(np.einsum("...ii->...", cov))
    e_floor = b.floor_of(e_pos[..., 2])
    res = rng.normal(0.0, 0.3, (n_t, n_nodes, n_anchors))
    wall = 1_800_000_000_000_000_000
    out: list[Any] = []
    leave_at = int(n_t * 2 / 3)
    for i in range(n_t):
        t = int(t_ns[i])
        for j, aid in enumerate(a_ids):
            if j == n_anchors - 1 and i >= leave_at:
                continue
            out.append(
                m.AnchorState(
                    anchor_id=aid,
                    t_ns=t,
                    seq=i,
                    position_m=_vec3(a_pos[i, j]),
                    velocity_m_s=(0.0, 0.0, 0.0),
                    position_sigma_m=(0.1, 0.1, 0.2),
                    velocity_sigma_m_s=0.05,
                    range_rate_hz=rate_hz,
                    t_pub_wall_ns=wall + t - t0_ns,
                )
            )
        live = a_ids if i < leave_at else a_ids[:-1]
        for k, nid in enumerate(n_ids):
            out.append(
                m.GroundTruth(
                    entity="node",
                    id=nid,
                    t_ns=t,
                    position_m=_vec3(n_pos[i, k]),
                    velocity_m_s=(0.0, 0.0, 0.0),
                    floor_index=int(floors[k]),
                )
            )
            used = list(live)
            excluded = []
            if k == 0 and i % 7 == 3 and len(used) > 3:
                excluded.append(m.Exclusion(anchor_id=used.pop(1), reason="RAIM"))
            if i >= leave_at:
                excluded.append(m.Exclusion(anchor_id=a_ids[-1], reason="ANCHOR_LOST"))
            unident = k == 1 and n_t // 2 <= i < n_t // 2 + int(rate_hz)
            used_idx = [a_ids.index(a) for a in used]
            out.append(
                m.PositionEstimate(
                    node_id=nid,
                    t_ns=t,
                    epoch=i,
                    seq=i,
                    status="NOT_IDENTIFIABLE" if unident else "OK",
                    position_m=None if unident else _vec3(e_pos[i, k]),
                    covariance_m2=None if unident else tuple(_vec3(r) for r in cov[i, k]),
                    peb_m=None if unident else float(peb[i, k]),
                    z_bound_m=None if unident else float(np.sqrt(cov[i, k, 2, 2])),
                    floor_index=None if unident else int(e_floor[i, k]),
                    used_anchors=used,
                    residuals_m=[float(res[i, k, u]) for u in used_idx],
                    excluded=excluded,
                    message="",
                    t_input_wall_ns=wall + t - t0_ns,
                    t_pub_wall_ns=wall + t - t0_ns + 1_000_000,
                )
            )
        if i % max(1, round(rate_hz)) == 0:
            out.append(
                m.FusionDiagnostics(
                    t_wall_ns=wall + t - t0_ns,
                    watermark_ns=t,
                    received={"range": i * n_nodes},
                    rejected={},
                    gated=i // 7,
                    solved=i * n_nodes,
                    published=i * n_nodes,
                    fixes_by_status={"OK": i * n_nodes},
                    late_ranges=0,
                    pending_epochs=0,
                    live_anchors=list(live),
                    anchors=[],
                    latency=m.LatencyStats(count=0, p50_ms=None, p99_ms=None, max_ms=None),
                )
            )
    return b, out


def _vec3(v: ArrayLike) -> tuple[float, float, float]:
    """A plain (x, y, z) float tuple of a 3-vector (message fields)."""
    x, y, z = (float(c) for c in np.asarray(v).reshape(3))
    return (x, y, z)
