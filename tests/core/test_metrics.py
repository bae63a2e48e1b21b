"""diffpos.metrics against values computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from diffpos import metrics

NAN3 = [math.nan] * 3


def test_percentiles_linear_interpolation_max_mean():
    out = metrics.percentiles([4.0, 1.0, 3.0, 2.0], (50, 90))
    # sorted 1 2 3 4: p50 at index 1.5 -> 2.5, p90 at index 2.7 -> 3.7
    assert out == pytest.approx({"p50": 2.5, "p90": 3.7, "max": 4.0, "mean": 2.5})
    assert list(out) == ["p50", "p90", "max", "mean"]


def test_percentiles_empty_and_without_max_mean():
    assert metrics.percentiles([]) == {
        "p50": None, "p67": None, "p90": None, "p95": None, "p99": None, "max": None, "mean": None
    }
    assert metrics.percentiles([1.0, 3.0], (50,), max_mean=False) == {"p50": 2.0}


def test_availability_counts_a_missing_position_as_a_miss():
    assert metrics.availability([True, False, True, True]) == 0.75
    assert metrics.availability([]) is None


def test_floor_accuracy_over_all_node_epochs_and_over_fixes():
    # the 4th node-epoch has the right floor index but no position: a miss for "all"
    all_, fixes = metrics.floor_accuracy([0, 1, 2, 2], [0, 1, 1, 2], [True, True, True, False])
    assert all_ == 2 / 4
    assert fixes == 2 / 3
    assert metrics.floor_accuracy([], []) == (None, None)


def test_ellipsoid_coverage_chi2_3dof_95():
    # chi2_3 95 % quantile = 7.8147: d^T C^-1 d = 4 (in), 9 (out), 9/4 (in), NaN row left out
    d = [[2.0, 0, 0], [3.0, 0, 0], [3.0, 0, 0], NAN3]
    c = [np.eye(3), np.eye(3), 4 * np.eye(3), np.eye(3)]
    assert metrics.ellipsoid_coverage(d, c) == pytest.approx(2 / 3)
    # 99 %: quantile 11.34 -> all three inside
    assert metrics.ellipsoid_coverage(d, c, probability=0.99) == 1.0
    assert metrics.ellipsoid_coverage([NAN3], [np.eye(3)]) is None


def test_score_all_quantities():
    est = [[1.0, 0, 0], NAN3, [0, 3.0, 4.0]]
    s = metrics.score(est, np.zeros((3, 3)), estimate_floor=[0, 0, 1], truth_floor=[0, 0, 0],
                      covariance_m2=[np.eye(3), np.full((3, 3), np.nan), np.eye(3)], q=(50,))
    assert s.node_epochs == 3 and s.fixes == 2
    assert s.availability == pytest.approx(2 / 3)
    assert s.error_3d_m == pytest.approx({"p50": 3.0, "max": 5.0, "mean": 3.0})
    assert s.error_z_m == pytest.approx({"p50": 2.0, "max": 4.0, "mean": 2.0})
    assert s.error_h_m == pytest.approx({"p50": 2.0, "max": 3.0, "mean": 2.0})
    assert s.rmse_3d_m == pytest.approx(math.sqrt(13.0))
    assert s.floor_accuracy_all == pytest.approx(1 / 3)
    assert s.floor_accuracy_fixes == 0.5
    assert s.ellipsoid_coverage == 0.5  # |d|^2 = 1 inside, 25 outside
    assert s.as_dict()["fixes"] == 2


def test_score_without_floors_or_covariances():
    s = metrics.score([NAN3], [[0.0, 0, 0]])
    assert (s.fixes, s.availability, s.rmse_3d_m) == (0, 0.0, None)
    assert s.floor_accuracy_all is None and s.ellipsoid_coverage is None
    with pytest.raises(ValueError, match="shape"):
        metrics.score(np.zeros((2, 3)), np.zeros((3, 3)))


def test_error_stats_replay_group():
    e3 = np.array([1.0, 2.0])
    out = metrics.error_stats(e3, np.array([0.5, 1.0]), np.array([0.8, 1.5]),
                              np.array([True, False]), np.array([0.6, np.nan]), fixes=4)
    assert out["fixes"] == 4 and out["evaluated"] == 2 and out["availability"] == 0.5
    assert out["rmse_3d_m"] == pytest.approx(math.sqrt(2.5))
    assert out["floor_accuracy"] == 0.5
    assert out["peb_m"]["p50"] == 0.6
    assert out["within_2peb"] == 1.0  # 1.0 <= 2 * 0.6; the NaN PEB row is not counted
    empty = metrics.error_stats(np.empty(0), np.empty(0), np.empty(0), np.empty(0, bool),
                                np.empty(0), fixes=0)
    assert empty["availability"] is None and empty["within_2peb"] is None


# -- the streaming summaries (bounded memory) against the array functions -----------------


def _errors(rng, n):
    d = rng.normal(scale=0.8, size=(n, 3)) * rng.lognormal(sigma=1.0, size=(n, 1))
    d[rng.random(n) < 0.1] = np.nan  # misses
    return d


def test_quantile_sketch_is_exact_up_to_its_limit_then_within_its_relative_bound():
    rng = np.random.default_rng(7)
    v = np.abs(rng.standard_cauchy(50_000))  # heavy tail: 1e-5 .. 1e4
    v[:50] = 0.0
    exact = metrics.QuantileSketch(exact_limit=len(v))
    sk = metrics.QuantileSketch(exact_limit=1000, relative_accuracy=0.005)
    for part in np.array_split(v, 37):
        exact.add(part)
        sk.add(part)
    ref = metrics.percentiles(v, (1, 50, 67, 90, 99, 99.9))
    # exact: the same (the mean summed in sorted order: independent of the batches)
    assert exact.exact and exact.summary((1, 50, 67, 90, 99, 99.9)) == metrics.percentiles(
        np.sort(v), (1, 50, 67, 90, 99, 99.9))
    assert exact.summary((1, 50, 67, 90, 99, 99.9)) == pytest.approx(ref, rel=1e-14)
    assert not sk.exact
    out = sk.summary((1, 50, 67, 90, 99, 99.9))
    for k in ("p1", "p50", "p67", "p90", "p99", "p99.9"):
        assert abs(out[k] - ref[k]) <= 0.005 * ref[k] + 1e-6, k
    assert out["max"] == ref["max"]
    assert out["mean"] == pytest.approx(ref["mean"], rel=1e-12)
    assert sk.values().size == v.size
    # memory does not follow the stream: the histogram's size is fixed
    n_buckets = sk._hist.size
    sk.add(np.abs(rng.standard_cauchy(200_000)))
    assert sk._hist.size == n_buckets and sk.count == 250_000


def test_streaming_error_stats_equal_error_stats_while_exact_and_close_beyond():
    rng = np.random.default_rng(3)
    n = 6000
    e3 = np.abs(rng.normal(size=n)) * 2
    ez, eh = e3 * rng.random(n), e3 * rng.random(n)
    fok = rng.random(n) < 0.9
    peb = np.where(rng.random(n) < 0.2, np.nan, rng.random(n) * 3)
    order = np.argsort(e3)  # the streaming summaries sum the mean in sorted order
    e3, ez, eh, fok, peb = e3[order], np.sort(ez), np.sort(eh), fok[order], peb[order]
    peb[np.isfinite(peb)] = np.sort(peb[np.isfinite(peb)])
    ref = metrics.error_stats(e3, ez, eh, fok, peb, fixes=n + 17)
    exact = metrics.StreamingErrorStats(exact_limit=n)
    approx = metrics.StreamingErrorStats(exact_limit=500)
    for sl in np.array_split(np.arange(n), 11):
        for s in (exact, approx):
            s.add(e3[sl], ez[sl], eh[sl], fok[sl], peb[sl])
    assert exact.result(fixes=n + 17) == ref
    out = approx.result(fixes=n + 17)
    for k in ("fixes", "evaluated", "availability", "floor_accuracy", "within_2peb"):
        assert out[k] == ref[k], k
    assert out["rmse_3d_m"] == pytest.approx(ref["rmse_3d_m"], rel=1e-12)
    for dist in ("error_3d_m", "error_z_m", "error_h_m", "peb_m"):
        for k, x in ref[dist].items():
            assert out[dist][k] == pytest.approx(x, rel=0.005, abs=1e-6), (dist, k)


def test_streaming_score_equals_score_over_all_node_epochs():
    rng = np.random.default_rng(11)
    d = _errors(rng, 5000)
    ef, tf = rng.integers(0, 3, 5000), rng.integers(0, 3, 5000)
    ref = metrics.score(d, np.zeros_like(d), estimate_floor=ef, truth_floor=tf)
    exact, approx = metrics.StreamingScore(exact_limit=5000), metrics.StreamingScore(
        exact_limit=300)
    for sl in np.array_split(np.arange(5000), 7):
        for s in (exact, approx):
            s.add(d[sl], estimate_floor=ef[sl], truth_floor=tf[sl])
    got = exact.result()  # identical, but the means: summed in sorted order (rounding)
    for k, x in ref.as_dict().items():
        assert getattr(got, k) == (pytest.approx(x, rel=1e-14) if k == "rmse_3d_m" or isinstance(
            x, dict) else x), k
    assert [got.error_3d_m[k] for k in ("p50", "p99", "max")] == [
        ref.error_3d_m[k] for k in ("p50", "p99", "max")]
    out = approx.result()
    for k in ("node_epochs", "fixes", "availability", "floor_accuracy_all",
              "floor_accuracy_fixes"):
        assert getattr(out, k) == getattr(ref, k), k
    for dist in ("error_3d_m", "error_z_m", "error_h_m"):
        for k, x in getattr(ref, dist).items():
            assert getattr(out, dist)[k] == pytest.approx(x, rel=0.005, abs=1e-6), (dist, k)
    empty = metrics.StreamingScore().result()
    assert empty == metrics.score(np.empty((0, 3)), np.empty((0, 3)), estimate_floor=[],
                                  truth_floor=[])


def test_truth_at_interpolates_a_straight_walk_and_takes_the_nearest_floor() -> None:
    """A walker on a straight line at constant speed, sampled every 100 ms: the truth at any
    time between samples is the line itself (closed form); the floor is the nearest sample's;
    before/after the samples the first/last position is held."""
    from diffpos.metrics import truth_at

    t = np.arange(0, 1_000_000_001, 100_000_000, dtype=np.int64)
    v = np.array([1.2, -0.3, 0.05])  # m/s
    p0 = np.array([-3.0, 5.0, 7.5])
    pos = p0 + (t * 1e-9)[:, None] * v
    floor = (t >= 450_000_000).astype(int)  # the floor changes between two samples
    q = np.array([0, 76_300_000, 430_000_000, 460_000_000, 999_999_999], np.int64)
    got, f = truth_at(q, t, pos, floor)
    np.testing.assert_allclose(got, p0 + (q * 1e-9)[:, None] * v, atol=1e-12)
    assert f.tolist() == [0, 0, 0, 1, 1]  # 430 ms: nearest 400 ms (floor 0); 460: nearest 500
    out, none = truth_at([-5, 2_000_000_000], t, pos)
    assert none is None
    np.testing.assert_array_equal(out, pos[[0, -1]])
    with pytest.raises(ValueError):
        truth_at([0], [], np.empty((0, 3)))


def test_truth_at_takes_the_building_floor_of_the_interpolated_height_at_a_slab_crossing():
    """A responder on the stairs of the paper's building (slab between floors 1 and 2 at
    z = 10 m), sampled every 100 ms, crosses the slab between two samples. With the building
    (``floor_of``) the true floor at any time is the building's floor of the true height then
    (reference: ``Building.floor_index`` of ``np.interp`` of the samples): floor 1 just
    before the crossing height, floor 2 just after, although the nearest sample says
    otherwise (the old, building-less answer, kept when no building is known)."""
    from diffpos.metrics import truth_at
    from diffpos.scenario import default_scenario

    b = default_scenario().building  # first floor 4 m, 3 m floors: slab 1|2 at 10 m
    t = np.arange(0, 2_000_000_001, 100_000_000, dtype=np.int64)
    z = 9.5 + 0.6 * (t * 1e-9)  # 0.6 m/s up: at 10 m at t = 833.3 ms, between 800 and 900
    pos = np.stack([np.full(t.shape, -3.0), np.full(t.shape, 5.0), z], axis=-1)
    floors = b.floor_index(z)  # the recorded samples' floors (as emulate records them)
    # just before the crossing time (810, 830 ms), just after (837, 845, 880 ms), far from
    # it, and outside the samples (held: first / last)
    q = np.array([810_000_000, 830_000_000, 837_000_000, 845_000_000, 880_000_000,
                  1_500_000_000, -7, 3_000_000_000], np.int64)
    got_p, got_f = truth_at(q, t, pos, floors, floor_of=b.floor_index)
    ref_z = np.interp(q.astype(float), t.astype(float), z)
    np.testing.assert_allclose(got_p[:, 2], ref_z, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(got_f, b.floor_index(ref_z))
    assert got_f.tolist() == [1, 1, 2, 2, 2, 2, 1, 2]
    # the nearest sample's floor (no building): 837 and 845 ms are above the slab but nearer
    # the 800 ms sample (floor 1) - the scorer's old answer there
    _, near = truth_at(q, t, pos, floors)
    assert near.tolist() == [1, 1, 1, 1, 2, 2, 1, 2]
    # the building alone (no recorded floors) gives the same
    _, only = truth_at(q, t, pos, floor_of=b.floor_index)
    np.testing.assert_array_equal(only, got_f)
