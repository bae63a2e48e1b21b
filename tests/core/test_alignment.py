"""diffpos.alignment: interpolation, epoch grouping/readiness, sigma inflation, compensation."""

from __future__ import annotations

import numpy as np
import pytest

from diffpos.alignment import (
    AlignmentConfig,
    EpochBook,
    RangeEntry,
    compensate_node_motion,
    effective_sigma_m,
    epoch_of,
)
from diffpos.anchor_history import StateHistory, hermite_interpolate
from diffpos.geometry import window_edge_path


def test_epoch_of_floor_semantics():
    assert epoch_of([0, 99, 100, -1, -100, -101], 100).tolist() == [0, 0, 1, -1, -1, -2]


def test_hermite_exact_for_cubic_motion():
    rng = np.random.default_rng(1)
    c = rng.normal(size=(4, 3))  # p(t) = c0 + c1 t + c2 t^2 + c3 t^3

    def p(t):
        return c[0] + c[1] * t + c[2] * t**2 + c[3] * t**3

    def v(t):
        return c[1] + 2 * c[2] * t + 3 * c[3] * t**2

    t0, t1 = 0.3, 0.7
    tq = np.linspace(t0, t1, 9)
    got = hermite_interpolate(tq, np.full(9, t0), np.full(9, t1), p(t0), p(t1), v(t0), v(t1))
    want = np.stack([p(t) for t in tq])
    np.testing.assert_allclose(got, want, atol=1e-12)


def _orbit(t_s):
    w = 2 * np.pi / 20.0
    return (
        np.stack([10 * np.cos(w * t_s), -20 + 10 * np.sin(w * t_s), 5 + 0.1 * t_s], -1),
        np.stack([-10 * w * np.sin(w * t_s), 10 * w * np.cos(w * t_s), 0.1 + 0 * t_s], -1),
    )


def test_state_history_interpolates_orbit_and_handles_extrapolation():
    h = StateHistory(16, max_extrapolation_ns=200_000_000)
    ts = np.arange(0, 2.0, 0.1)
    order = np.random.default_rng(0).permutation(ts.size)  # out of order insertion
    for k in order:
        p, v = _orbit(ts[k])
        h.add(round(ts[k] * 1e9), p, v, (0.02, 0.02, 0.05), 0.1)
    assert len(h) == 16  # capacity: the oldest were dropped
    assert h.t_ns[0] == round(ts[4] * 1e9)
    tq = np.array([0.55, 1.234, 1.9, 1.95, 2.05, 2.5, 0.15])
    pos, sig, ok = h.at(np.round(tq * 1e9).astype(np.int64))
    want, _ = _orbit(tq)
    # Hermite on a 10 m orbit sampled at 0.1 s: error << 1 mm
    assert ok.tolist() == [True, True, True, True, True, False, False]
    np.testing.assert_allclose(pos[:3], want[:3], atol=2e-5)
    # 0.05 / 0.15 s past the newest state: linear, error ~ a dt^2 / 2 (a = 1 m/s^2 here)
    np.testing.assert_allclose(pos[3], want[3], atol=0.5 * 0.99 * 0.05**2 + 1e-4)
    np.testing.assert_allclose(pos[4], want[4], atol=0.5 * 0.99 * 0.15**2 + 1e-4)
    np.testing.assert_allclose(sig[4], np.array([0.02, 0.02, 0.05]) + 0.015, atol=1e-9)
    assert np.all(np.isnan(pos[5:]))


def test_state_history_storage_matches_sorted_list_reference():
    """Mostly in-order appends with some late, duplicate and far-past states, over many
    growths and compactions of the arrays: the kept states equal a plain sorted-list model
    (capacity and age limits applied after every insert) and ``at`` returns the kept rows."""
    rng = np.random.default_rng(7)
    for capacity, max_age_ns in [(64, None), (40, 2_000_000_000), (5, None), (300, 500_000_000)]:
        h = StateHistory(capacity, max_extrapolation_ns=10**12, max_age_ns=max_age_ns)
        ref: dict[int, tuple] = {}
        t = 0
        for k in range(1500):
            u = rng.random()
            if u < 0.8:
                t += int(rng.integers(1, 200_000_000))
                tk = t
            elif u < 0.9 and ref:
                tk = int(rng.choice(list(ref)))  # duplicate time: replaces
            else:
                tk = t - int(rng.integers(1, 3_000_000_000))  # late
            row = tuple(rng.normal(size=10).tolist())
            h.add(tk, row[0:3], row[3:6], row[6:9], row[9])
            ref[tk] = row
            keep = sorted(ref)
            drop = max(0, len(keep) - capacity)
            if max_age_ns is not None:
                drop = max(drop, sum(1 for x in keep if x < keep[-1] - max_age_ns))
            for x in keep[:drop]:
                del ref[x]
            if k % 97 == 0 or k > 1490:
                keep = sorted(ref)
                assert h.t_ns.tolist() == keep
                assert h.latest_t_ns == keep[-1] and len(h) == len(keep)
                pos, _, ok = h.at(np.array(keep))
                assert ok.all()
                np.testing.assert_array_equal(pos, [ref[x][0:3] for x in keep])


def test_state_history_single_time_path_is_bitwise_the_array_path():
    """Queries that all share one time take a scalar path; it must give exactly what the
    array path gives (the fusion's results must not depend on which one ran): inside the
    history, at state times, before/after it within and beyond the extrapolation limit."""
    rng = np.random.default_rng(3)
    h = StateHistory(64, max_extrapolation_ns=300_000_000)
    for k in range(40):
        t = 10**17 + k * 100_000_000 + int(rng.integers(-5_000_000, 5_000_000))
        h.add(t, rng.normal(0, 20, 3), rng.normal(0, 2, 3), rng.uniform(0.01, 0.2, 3),
              float(rng.uniform(0, 0.3)))
    t0, t1 = int(h.t_ns[0]), int(h.t_ns[-1])
    queries = [*rng.integers(t0 - 600_000_000, t1 + 600_000_000, 400).tolist(),
               *h.t_ns.tolist(), t0 - 300_000_000, t1 + 300_000_000, t1 + 300_000_001]
    others = [t0 + 12_345 + k * 77_777_777 for k in range(5)]  # 6 times: the array path
    for tq in queries:
        p1, s1, ok1 = h.at(np.array([tq, tq, tq]))
        p2, s2, ok2 = h.at(np.array([tq, *others]))
        np.testing.assert_array_equal(p1, np.repeat(p2[:1], 3, axis=0))
        np.testing.assert_array_equal(s1, np.repeat(s2[:1], 3, axis=0))
        assert ok1.tolist() == [bool(ok2[0])] * 3
    # a few distinct times (scalar path per time, scattered back) == the array path
    for _ in range(200):
        tq = rng.choice(queries, size=int(rng.integers(2, 5)), replace=False)
        tq = tq[rng.integers(0, tq.size, 9)].reshape(3, 3)
        p1, s1, ok1 = h.at(tq)
        p2, s2, ok2 = h._at_array(tq.reshape(-1), tq.shape)
        np.testing.assert_array_equal(p1, p2)
        np.testing.assert_array_equal(s1, s2)
        assert ok1.shape == ok2.shape == (3, 3) and (ok1 == ok2).all()
    p0, _, ok0 = h.at(np.int64(t1 + 1))  # a scalar query keeps its shape
    assert p0.shape == (3,) and ok0.shape == () and bool(ok0)


def test_effective_sigma_closed_form():
    s = effective_sigma_m(0.03, np.array([0.0, 0.04, 0.0]), np.array([0.0, 2.0, 0.0]), 0.05, 2.0)
    assert s == pytest.approx(np.sqrt(0.03**2 + 0.04**2 + 0.1**2))
    # anchor uncertainty perpendicular to the line of sight does not count
    s2 = effective_sigma_m(0.03, np.array([5.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), 0.0, 2.0)
    assert s2 == pytest.approx(0.03)


def test_motion_compensation_matches_true_range_at_reference_time():
    anchors = np.array([[-15.0, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]])
    p_ref = np.array([2.0, 6.0, 10.5])
    v = np.array([1.2, -0.4, 0.3])
    dt = np.array([-0.04, 0.01, 0.03, 0.045])
    measured = window_edge_path(anchors, p_ref + v * dt[:, None], window_height_m=1.5).length_m
    jac = window_edge_path(anchors, p_ref, window_height_m=1.5).jacobian
    comp = compensate_node_motion(measured, jac, v, dt)
    true_ref = window_edge_path(anchors, p_ref, window_height_m=1.5).length_m
    raw_err = np.abs(measured - true_ref).max()
    comp_err = np.abs(comp - true_ref).max()
    assert raw_err > 0.01
    assert comp_err < 1e-3 * raw_err + 1e-5  # second-order residual only


def _entry(t_ns, rx=0, r=10.0):
    return RangeEntry(t_ns=t_ns, range_m=r, sigma_m=0.1, snr_db=20.0, t_pub_wall_ns=rx, rx_wall_ns=rx)


def test_epoch_ready_when_all_live_anchors_reported():
    book = EpochBook(AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=5, deadline_ns=10**9))
    live = {"a", "b", "c"}
    book.add("a", "n1", _entry(110))
    book.add("b", "n1", _entry(150))
    assert book.ready(live, 0) == []
    book.add("c", "n1", _entry(199))
    out = book.ready(live, 0)
    assert [(pe.node_id, pe.epoch, sorted(pe.ranges)) for pe in out] == [("n1", 1, ["a", "b", "c"])]
    # a range for the solved epoch is late
    assert book.add("a", "n1", _entry(120)) is False and book.late == 1


def test_epoch_ready_when_missing_anchor_moved_on_or_deadline():
    cfg = AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=5, deadline_ns=1000,
                          min_reports=1, max_lag_ns=1000)  # the wall fallback at 1000
    book = EpochBook(cfg)
    live = {"a", "b"}
    book.add("a", "n1", _entry(110, rx=0))
    book.add("a", "n2", _entry(110, rx=0))
    # b reported n2 only, then moved to the next epoch but not past end + tolerance
    book.add("b", "n2", _entry(120, rx=0))
    book.note_anchor_time("b", 204)
    assert [pe.node_id for pe in book.ready(live, 10)] == ["n2"]
    book.note_anchor_time("b", 205)  # end (200) + tolerance (5): b will not report n1 any more
    assert [pe.node_id for pe in book.ready(live, 10)] == ["n1"]
    # deadline: anchor c hung without ever passing the epoch
    book.add("a", "n3", _entry(310, rx=50))
    assert book.ready(live | {"c"}, 1049) == []
    assert book.next_deadline_wall_ns() == 1050
    assert [pe.node_id for pe in book.ready(live | {"c"}, 1050)] == ["n3"]


def test_first_anchor_alone_does_not_complete_an_epoch_at_start_up():
    """Before the other anchors are known, too few reports must not release the epoch early."""
    book = EpochBook(AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=0, deadline_ns=500,
                                     max_lag_ns=500))
    book.add("a", "n1", _entry(110, rx=0))
    book.add("b", "n1", _entry(120, rx=0))
    # a and b are the anchors known so far (all "live"), but 2 reports < min_reports = 3
    assert book.ready({"a", "b"}, 10) == []
    book.add("c", "n1", _entry(130, rx=0))
    assert [pe.epoch for pe in book.ready({"a", "b", "c"}, 10)] == [1]
    # and the deadline always releases
    book.add("a", "n3", _entry(110, rx=0))
    assert book.ready({"a", "b", "c"}, 499) == []
    assert [pe.node_id for pe in book.ready({"a", "b", "c"}, 500)] == ["n3"]


def test_epochs_of_a_node_are_released_in_order_and_late_ranges_dropped():
    book = EpochBook(AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=0, deadline_ns=10,
                                     max_lag_ns=10))
    live = {"a", "b", "hung"}
    book.add("a", "n1", _entry(110, rx=5))
    book.add("a", "n1", _entry(10, rx=0))
    assert book.ready(live, 9) == []
    got = book.ready(live, 15)
    assert [pe.epoch for pe in got] == [0, 1]
    assert book.add("b", "n1", _entry(50)) is False
    assert book.late == 1


def test_watermark_releases_without_a_hung_anchor_and_without_wall_time():
    """Measurement time only: three anchors move on, the hung fourth is not waited for once
    the watermark (3rd newest time) passed the epoch end by the allowance; the wall clock
    never advances."""
    cfg = AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=0, deadline_ns=50)
    book = EpochBook(cfg)
    live = {"a", "b", "c", "hung"}
    book.note_anchor_time("hung", 5)
    for a in ("a", "b", "c"):
        book.add(a, "n1", _entry(110))
    assert book.ready(live, 0) == []  # hung is live and has not passed epoch 1
    for a in ("a", "b", "c"):
        book.note_anchor_time(a, 249)
    assert book.watermark_ns == 249 and book.ready(live, 0) == []  # 200 + 50 > 249
    book.note_anchor_time("c", 250)
    assert book.ready(live, 0) == []  # the 3rd newest is still 249
    book.note_anchor_time("b", 250)
    assert book.watermark_ns == 249 and book.ready(live, 0) == []
    book.note_anchor_time("a", 250)
    assert [pe.epoch for pe in book.ready(live, 0)] == [1]
    # the hung anchor's backlog is late, counted as its own
    assert book.add("hung", "n1", _entry(150)) is False
    assert dict(book.late_by_anchor) == {"hung": 1}
    # the former rule would still wait (wall 0 < deadline)
    old = EpochBook(AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=0, deadline_ns=50,
                                    release="wall"))
    old.note_anchor_time("hung", 5)
    for a in ("a", "b", "c"):
        old.add(a, "n1", _entry(110))
        old.note_anchor_time(a, 250)
    assert old.ready(live, 0) == [] and [pe.epoch for pe in old.ready(live, 50)] == [1]


def test_allowance_follows_observed_lags_within_bounds_and_ignores_a_stalled_anchor():
    cfg = AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=0, deadline_ns=50,
                          max_lag_ns=1000)
    book = EpochBook(cfg)
    for k in range(1, 80):  # a, b, c on time; d always 200 behind; e replays a 5000 backlog
        for a in ("a", "b", "c"):
            book.note_anchor_time(a, 100 * k)
        book.note_anchor_time("d", 100 * k - 200)
        book.note_anchor_time("e", 100 * k - 5000)
    assert book.lag_ns("d") == 200 and book.lag_ns("e") > 1000
    assert book._allowance() == 250  # d's lag + 25 %; e (beyond max_lag_ns) not waited for
    for k in range(80, 200):  # d falls 900 behind
        for a in ("a", "b", "c"):
            book.note_anchor_time(a, 100 * k)
        book.note_anchor_time("d", 100 * k - 900)
    assert book._allowance() == 1000  # 900 + 25 %, bounded


def test_config_validation_names_field():
    with pytest.raises(ValueError, match="epoch_period_ns"):
        AlignmentConfig(epoch_period_ns=0)
    with pytest.raises(ValueError, match="node_speed_sigma_m_s"):
        AlignmentConfig(node_speed_sigma_m_s=-1)
    with pytest.raises(ValueError, match="max_lag_ns"):
        AlignmentConfig(deadline_ns=100, max_lag_ns=10)
    with pytest.raises(ValueError, match="release"):
        AlignmentConfig(release="sometimes")
