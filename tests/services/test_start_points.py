"""Warm starts and velocities of a fusion step's rows (``fusion.step._start_points``), bit for
bit against a per-row reference, and each row independent of the others in its batch.

The rows written at once (session 30, issue 37: ~0.04 s of a D-NLS replay of the 30 s
``large`` recording) must give exactly the values the per-row numpy assignment gave: a warm
start moves the estimates of every later epoch.
"""

from __future__ import annotations

import numpy as np
from diffpos_services.fusion import step
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.ingest import Track

from diffpos.alignment import PendingEpoch

T0 = 1_700_000_000_123_456_789  # ns: a wall-clock epoch, as the fusion's times are


def _track(t_ns=None, pos=None, vel=None, cold_ns=None, try_pos=None) -> Track:
    tr = Track()
    tr.t_ns, tr.pos, tr.vel, tr.cold_ns, tr.try_pos = t_ns, pos, vel, cold_ns, try_pos
    return tr


def _reference(node: str, tracks: dict, t: int, cfg: FusionConfig):
    """One row by the rule, in numpy scalars: (start or NaN, velocity or 0, used velocity)."""
    tr = tracks.get(node)
    nan, zero = np.full(3, np.nan), np.zeros(3)
    if tr is None:
        return nan, zero, False
    if tr.t_ns is not None and abs(np.int64(t) - np.int64(tr.t_ns)) <= cfg.warm_start_max_age_s * 1e9:
        dt = np.float64(np.int64(t) - np.int64(tr.t_ns)) * 1e-9
        v = tr.vel
        if v is not None and float(np.dot(v, v)) <= step.MAX_TRACK_SPEED_M_S ** 2:
            return np.array([p + u * dt for p, u in zip(tr.pos, v, strict=True)]), np.array(v), True
        return np.array(tr.pos, float), zero, False
    if tr.try_pos is not None and tr.cold_ns is not None and \
            0 <= t - tr.cold_ns < round(cfg.cold_retry_period_s * 1e9):
        return np.array(tr.try_pos, float), zero, False
    return nan, zero, False


def _cases(cfg: FusionConfig) -> tuple[dict, list[tuple[str, int]]]:
    age = int(cfg.warm_start_max_age_s * 1e9)
    retry = round(cfg.cold_retry_period_s * 1e9)
    rng = np.random.default_rng(7)
    p = [float(x) for x in rng.normal(0.0, 20.0, 3)]
    v = [float(x) for x in rng.normal(0.0, 1.0, 3)]
    tracks = {
        "moving": _track(T0, p, v),
        "still": _track(T0, p, None),
        "fast": _track(T0, p, [30.0, 0.0, 0.0]),
        "old": _track(T0 - 3 * age, p, v, cold_ns=T0 - 10, try_pos=[1.5, 2.5, 3.5]),
        "stale_cold": _track(T0 - 3 * age, p, v, cold_ns=T0 - 2 * retry, try_pos=[1.0, 2.0, 3.0]),
        "cold_only": _track(cold_ns=T0, try_pos=[4.0, 5.0, 6.0]),
        "cold_no_pos": _track(cold_ns=T0),
        "empty": _track(),
    }
    rows = [("moving", T0 + 25_000_000), ("none", T0), ("still", T0 + 1), ("fast", T0 + 7),
            ("old", T0), ("stale_cold", T0), ("cold_only", T0 + retry - 1),
            ("cold_only", T0 + retry), ("cold_no_pos", T0), ("empty", T0),
            ("moving", T0 - 40_000_000), ("moving", T0 + age), ("moving", T0 + age + 1)]
    return tracks, rows


def test_start_points_equal_the_per_row_rule_bit_for_bit():
    cfg = FusionConfig()
    tracks, rows = _cases(cfg)
    epochs = [PendingEpoch(n, 3, 0) for n, _ in rows]
    t_ref = np.array([t for _, t in rows], np.int64)
    x0, vel, has_vel = step._start_points(epochs, tracks, t_ref, cfg)
    assert x0.shape == vel.shape == (len(rows), 3) and has_vel.shape == (len(rows),)
    assert x0.dtype == vel.dtype == np.float64 and has_vel.dtype == bool
    for i, (node, t) in enumerate(rows):
        ref_x0, ref_vel, ref_has = _reference(node, tracks, t, cfg)
        assert x0[i].tobytes() == ref_x0.tobytes(), (node, x0[i], ref_x0)
        assert vel[i].tobytes() == ref_vel.tobytes(), (node, vel[i], ref_vel)
        assert has_vel[i] == ref_has, node
    # every kind of row is there: warm moving, warm still, cold retry, none
    assert has_vel.sum() == 3 and np.isnan(x0[:, 0]).sum() == 6


def test_each_row_is_its_own_batch_of_one():
    cfg = FusionConfig()
    tracks, rows = _cases(cfg)
    epochs = [PendingEpoch(n, 3, 0) for n, _ in rows]
    t_ref = np.array([t for _, t in rows], np.int64)
    whole = step._start_points(epochs, tracks, t_ref, cfg)
    for i in range(len(rows)):
        alone = step._start_points(epochs[i:i + 1], tracks, t_ref[i:i + 1], cfg)
        for a, b in zip(whole, alone, strict=True):
            assert a[i:i + 1].tobytes() == b.tobytes()


def test_no_tracks_no_rows():
    cfg = FusionConfig()
    x0, vel, has_vel = step._start_points([PendingEpoch("n", 1, 0)] * 4, {},
                                          np.full(4, T0, np.int64), cfg)
    assert np.isnan(x0).all() and (vel == 0.0).all() and not has_vel.any()
    x0, vel, has_vel = step._start_points([], {"n": _track(T0, [0.0] * 3)},
                                          np.zeros(0, np.int64), cfg)
    assert x0.shape == vel.shape == (0, 3) and has_vel.shape == (0,)
