"""benchmarks/bench_floor_calibration.py's pooling of per-recording calibrations against one
calibration (diffpos.floor_calibration) over the concatenated node-epochs, a recording without
floor probabilities (estimate v1) included: its node-epochs are in the denominator of
"confidently wrong", its fixes counted as without probabilities."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from diffpos.floor_calibration import floor_calibration

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_floor_calibration as B


def _recording(rng, n, nf, probabilities=True):
    p = rng.dirichlet(np.full(nf, 0.3), size=n)
    ef = np.argmax(p, axis=1)
    tf = np.where(rng.random(n) < 0.9, ef, rng.integers(0, nf, n))
    has = rng.random(n) > 0.1
    ef[~has] = -1
    if not probabilities:
        p[:] = np.nan
    return ef, tf, p, has


def test_pool_equals_one_calibration_over_the_union():
    rng = np.random.default_rng(5)
    recs = [_recording(rng, n, 4) for n in (300, 41, 512)]
    v1 = _recording(rng, 200, 4, probabilities=False)
    calibs = [floor_calibration(*r[:3], has_position=r[3]) for r in recs]
    assert floor_calibration(*v1[:3], has_position=v1[3]) is None
    got = B.pool([*calibs, None], uncalibrated=[(200, int(v1[3].sum()))])
    ref = floor_calibration(*(np.concatenate([r[i] for r in [*recs, v1]]) for i in range(3)),
                            has_position=np.concatenate([r[3] for r in [*recs, v1]]))
    assert got["node_epochs"] == ref["node_epochs"] == 300 + 41 + 512 + 200
    for key in ("with_probabilities", "without_probabilities", "confidently_wrong_count"):
        assert got[key] == ref[key], key
    assert ref["confidently_wrong_count"] > 0 and ref["without_probabilities"] > 150
    for key in ("ece", "log_score", "brier", "confidently_wrong",
                "confidently_wrong_of_probabilities"):
        assert got[key] == pytest.approx(ref[key], rel=1e-12), key
    for a, b in zip(got["reliability"], ref["reliability"], strict=True):
        assert a["count"] == b["count"]
        if b["count"]:
            assert a["fraction_right"] == pytest.approx(b["fraction_right"], rel=1e-12)
            assert a["mean_probability"] == pytest.approx(b["mean_probability"], rel=1e-12)
