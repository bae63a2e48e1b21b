"""Calibration of the reported floor probabilities (diffpos.floor_calibration).

References: a brute-force loop over the node-epochs written from the definitions; the batch
result for any chunking of the stream; closed forms of a calibrated source (true floors drawn
from the reported probabilities: per bin the fraction right is a sum of Bernoulli(p_i), so its
deviation from the mean reported probability has the standard deviation sqrt(sum p_i (1 - p_i))
/ n_b, and the Brier score of one node-epoch has mean 1 - sum p^2 and variance
4 (sum p^3 - (sum p^2)^2)); the same source reported over-confidently.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from diffpos import metrics
from diffpos.floor_calibration import (
    BIN_EDGES,
    FloorCalibration,
    floor_calibration,
    format_calibration,
)


def _random_case(rng: np.random.Generator, n: int, nf: int):
    """Published floors (mostly the argmax, some not), true floors, probabilities with NaN
    rows and misses."""
    p = rng.dirichlet(np.full(nf, 0.3), size=n)
    ef = np.argmax(p, axis=1)
    other = rng.random(n) < 0.1
    ef[other] = rng.integers(0, nf, other.sum())
    tf = np.where(rng.random(n) < 0.6, ef, rng.integers(0, nf, n))
    p[rng.random(n) < 0.05] = np.nan
    has = rng.random(n) > 0.1
    ef[~has] = -1
    return ef, tf, p, has


def _brute(ef, tf, p, has, confident=0.95, clip=1e-6):
    """The definitions, one node-epoch at a time."""
    edges = BIN_EDGES
    nb = len(edges) - 1
    count, right, sum_p = [0] * nb, [0] * nb, [0.0] * nb
    logs, briers, cw, without = [], [], 0, 0
    for i in range(len(ef)):
        if not has[i]:
            continue
        row = p[i]
        if not all(math.isfinite(x) for x in row) or not 0 <= ef[i] < len(row):
            without += 1
            continue
        pp = row[ef[i]]
        b = next(j for j in range(nb) if edges[j] <= pp < edges[j + 1] or j == nb - 1)
        count[b] += 1
        right[b] += ef[i] == tf[i]
        sum_p[b] += pp
        cw += (ef[i] != tf[i]) and pp >= confident
        logs.append(-math.log(max(row[tf[i]], clip)))
        briers.append(sum((row[k] - (k == tf[i])) ** 2 for k in range(len(row))))
    k = sum(count)
    ece = sum(count[b] / k * abs(sum_p[b] / count[b] - right[b] / count[b])
              for b in range(nb) if count[b])
    return {"count": count, "right": right, "ece": ece, "log": sum(logs) / k,
            "brier": sum(briers) / k, "cw": cw, "cw_share": cw / len(ef), "without": without,
            "with": k}


@pytest.mark.parametrize("nf", [2, 3, 6])
def test_matches_brute_force(nf):
    rng = np.random.default_rng(20261128 + nf)
    ef, tf, p, has = _random_case(rng, 700, nf)
    c = floor_calibration(ef, tf, p, has_position=has)
    ref = _brute(ef, tf, p, has)
    assert [r["count"] for r in c["reliability"]] == ref["count"]
    assert [round((r["fraction_right"] or 0) * r["count"]) for r in c["reliability"]] \
        == ref["right"]
    assert c["ece"] == pytest.approx(ref["ece"], rel=1e-12, abs=1e-15)
    assert c["log_score"] == pytest.approx(ref["log"], rel=1e-12)
    assert c["brier"] == pytest.approx(ref["brier"], rel=1e-12)
    assert c["confidently_wrong_count"] == ref["cw"] > 0
    assert c["confidently_wrong"] == pytest.approx(ref["cw_share"], rel=1e-15)
    assert c["without_probabilities"] == ref["without"] > 0
    assert c["with_probabilities"] == ref["with"] and c["node_epochs"] == 700


def test_streaming_equals_batch_for_any_chunking():
    rng = np.random.default_rng(7)
    ef, tf, p, has = _random_case(rng, 1000, 4)
    batch = floor_calibration(ef, tf, p, has_position=has)
    for trial in range(4):
        cuts = np.sort(rng.integers(0, 1001, size=trial * 5 + 1))
        acc = FloorCalibration()
        for a, b in zip([0, *cuts], [*cuts, 1000], strict=True):  # empty chunks included
            acc.add(ef[a:b], tf[a:b], p[a:b], has_position=has[a:b])
        got = acc.result()
        for key, v in batch.items():
            if key == "reliability":
                for r, s in zip(got[key], v, strict=True):
                    assert r["count"] == s["count"] and r["bin"] == s["bin"]
                    if s["count"]:
                        assert r["mean_probability"] == pytest.approx(s["mean_probability"],
                                                                      rel=1e-12)
                        assert r["fraction_right"] == s["fraction_right"]
            else:
                assert got[key] == pytest.approx(v, rel=1e-12), key


def test_streaming_score_equals_score():
    """The scorer's two forms agree on the calibration (and the floors), chunked."""
    rng = np.random.default_rng(3)
    ef, tf, p, has = _random_case(rng, 600, 3)
    err = rng.normal(size=(600, 3))
    err[~has] = np.nan
    s = metrics.score(err, np.zeros((600, 3)), estimate_floor=ef, truth_floor=tf,
                      floor_probabilities=p)
    st = metrics.StreamingScore()
    for a in range(0, 600, 137):
        st.add(err[a:a + 137], estimate_floor=ef[a:a + 137], truth_floor=tf[a:a + 137],
               floor_probabilities=p[a:a + 137])
    r = st.result()
    assert r.floor_accuracy_all == s.floor_accuracy_all
    assert r.floor_calibration["confidently_wrong_count"] \
        == s.floor_calibration["confidently_wrong_count"]
    assert r.floor_calibration["ece"] == pytest.approx(s.floor_calibration["ece"], rel=1e-12)
    assert s.floor_calibration == floor_calibration(ef, tf, p, has_position=has)
    # without probabilities the calibration is absent, the rest unchanged
    s0 = metrics.score(err, np.zeros((600, 3)), estimate_floor=ef, truth_floor=tf)
    assert s0.floor_calibration is None and s0.floor_accuracy_all == s.floor_accuracy_all
    st0 = metrics.StreamingScore()
    st0.add(err, estimate_floor=ef, truth_floor=tf)
    assert st0.result().floor_calibration is None


def _source(rng, n, nf, sharpen):
    """True floors drawn from p; reported q = p^sharpen renormalised (1: calibrated)."""
    p = rng.dirichlet(np.full(nf, 0.5), size=n)
    tf = (rng.random((n, 1)) > np.cumsum(p, axis=1)).sum(axis=1)
    q = p**sharpen
    q /= q.sum(axis=1, keepdims=True)
    return np.argmax(q, axis=1), tf, p, q


def _ece_bound(q, ef, sigmas=4.0):
    """``sigmas`` standard deviations of each bin's |fraction right - mean p| under a
    calibrated source, weighted as the ECE weighs the bins."""
    pp = q[np.arange(len(ef)), ef]
    b = np.clip(np.searchsorted(BIN_EDGES, pp, side="right") - 1, 0, len(BIN_EDGES) - 2)
    return sum(sigmas * math.sqrt(float((pp[b == i] * (1 - pp[b == i])).sum())) / len(ef)
               for i in range(len(BIN_EDGES) - 1))


def test_calibrated_source_small_ece_overconfident_large():
    rng = np.random.default_rng(11)
    n, nf = 20_000, 3
    ef, tf, p, _ = _source(rng, n, nf, 1.0)
    c = floor_calibration(ef, tf, p)
    bound = _ece_bound(p, ef)
    assert c["ece"] <= bound < 0.03
    # Brier: mean 1 - sum p^2, variance 4 (sum p^3 - (sum p^2)^2) per node-epoch
    s2, s3 = (p**2).sum(axis=1), (p**3).sum(axis=1)
    sd = math.sqrt(float((4 * (s3 - s2**2)).sum())) / n
    assert abs(c["brier"] - float((1 - s2).mean())) <= 4 * sd
    # the same truth reported over-confidently (log-odds x 4)
    ef4, tf4, _, q4 = _source(np.random.default_rng(11), n, nf, 4.0)
    c4 = floor_calibration(ef4, tf4, q4)
    assert c4["ece"] > 0.05 > bound and c4["ece"] > _ece_bound(q4, ef4)
    assert c4["confidently_wrong"] > 0.01 and c["confidently_wrong"] < c4["confidently_wrong"]
    assert c4["log_score"] > c["log_score"]
    hi = c4["reliability"][-1]
    assert hi["fraction_right"] < hi["mean_probability"] - 0.05


def test_edge_cases():
    assert floor_calibration([], [], np.zeros((0, 3))) is None  # no estimates
    none_has = floor_calibration([-1, -1], [0, 1], np.full((2, 2), np.nan),
                                 has_position=[False, False])
    assert none_has is None  # all missing
    s = metrics.score(np.full((2, 3), np.nan), np.zeros((2, 3)), estimate_floor=[-1, -1],
                      truth_floor=[0, 0], floor_probabilities=np.full((2, 2), np.nan))
    assert s.floor_calibration is None and s.floor_accuracy_all == 0.0
    # one floor: always right at p = 1
    c = floor_calibration([0, 0, 0], [0, 0, 0], np.ones((3, 1)))
    assert c["reliability"][-1]["count"] == 3 and c["ece"] == 0.0
    assert c["log_score"] == 0.0 and c["brier"] == 0.0 and c["confidently_wrong"] == 0.0
    # NaN probabilities: counted as without, not scored; a miss counts only in node_epochs
    p = np.array([[0.99, 0.01], [np.nan, 0.5], [0.2, 0.8], [0.5, 0.5]])
    c = floor_calibration([0, 0, 1, -1], [1, 1, 1, 0], p, has_position=[1, 1, 1, 0])
    assert c["node_epochs"] == 4 and c["with_probabilities"] == 2
    assert c["without_probabilities"] == 1 and c["confidently_wrong_count"] == 1
    assert c["confidently_wrong"] == 0.25 and c["confidently_wrong_of_probabilities"] == 0.5
    assert c["log_score"] == pytest.approx((-math.log(0.01) - math.log(0.8)) / 2)
    with pytest.raises(ValueError, match="outside"):
        floor_calibration([0], [0], [[1.5, -0.5]])
    with pytest.raises(ValueError, match="must ascend"):
        FloorCalibration(bin_edges=(0.0, 0.5))
    # a true probability of 0 is clipped at 1e-6
    c = floor_calibration([0], [1], [[1.0, 0.0]])
    assert c["log_score"] == pytest.approx(-math.log(1e-6))
    assert c["brier"] == 2.0 and c["ece"] == 1.0
    assert "not measured" in format_calibration(None)[0]
    assert any("confidently wrong" in line for line in format_calibration(c))


def test_probability_rows_pads_missing_vectors_with_nan():
    """probability_rows: the longest vector sets F; empty or shorter vectors become NaN rows;
    no vector at all gives None (estimate v1)."""
    from diffpos.floor_calibration import probability_rows

    p = probability_rows([(0.9, 0.1, 0.0), (), (0.5, 0.5), (0.2, 0.3, 0.5)])
    assert p.shape == (4, 3)
    assert np.array_equal(p[[0, 3]], [[0.9, 0.1, 0.0], [0.2, 0.3, 0.5]])
    assert np.isnan(p[[1, 2]]).all()
    assert probability_rows([(), ()]) is None and probability_rows([]) is None
