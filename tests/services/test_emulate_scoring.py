"""The emulate summary counts every node-epoch after the first 2 s (a miss is a miss).

Reference: the counts by hand for a small made-up run (two static nodes, 3 s at 10 Hz, some
epochs without an estimate, one without a position, one on the wrong floor)."""

from __future__ import annotations

import numpy as np
import pytest
from diffpos_services.emulate.scoring import Scorer, format_summary
from diffpos_services.wire import messages as M

from diffpos.scenario import default_scenario
from diffpos.trajectory import Static

B = default_scenario().building
P = 100_000_000
T0 = 1_800_000_000_000_000_000
TRUTH = {"a": (1.0, 5.0, 5.5), "b": (-3.0, 8.0, 8.5)}  # floors 0 and 1


def _est(node, k, pos, floor, status="TRACKING"):
    cov = ((0.01, 0.0, 0.0), (0.0, 0.01, 0.0), (0.0, 0.0, 0.01))
    return M.PositionEstimateV2(
        node_id=node, t_ns=T0 + k * P, epoch=T0 // P + k, seq=k, method="mnls+tracking",
        status=status, position_m=pos, covariance_m2=cov if pos else None, peb_m=None,
        z_bound_m=None, floor_index=floor, floor_probabilities=[], snapshot=None, links=[],
        used_anchors=[], residuals_m=[], excluded=[], message="", t_input_wall_ns=0,
        t_pub_wall_ns=0)


def test_every_node_epoch_after_2_s_counts():
    sc = Scorer([(n, Static(p)) for n, p in TRUTH.items()], B, T0, period_ns=P,
                end_ns=T0 + 3 * 10**9)
    n_in = 0
    for k in range(30):
        if k % 5 != 4:  # every fifth epoch of node a is missing
            off = 0.1 if k != 25 else 0.0
            sc.add(_est("a", k, (1.0 + off, 5.0, 5.5), 0))
            n_in += k >= 20
        if k == 22:
            sc.add(_est("b", k, None, None, status="LOST"))
        elif k == 23:
            sc.add(_est("b", k, (-3.0, 8.0, 5.5), 0))  # wrong floor, 3 m off in z
        else:
            sc.add(_est("b", k, (-3.0, 8.0, 8.5), 1))
    s = sc.summary()
    # epochs 20..29 of 2 nodes; a: 8 with a position (24 and 29 missing), b: 9 (22 LOST)
    assert s["node_epochs"] == 20 and s["node_epochs_without_estimate"] == 2
    assert s["availability"] == pytest.approx(17 / 20)
    assert s["floor_accuracy"] == pytest.approx(16 / 20)
    assert s["floor_accuracy_fixes"] == pytest.approx(16 / 17)
    errs = sorted([0.1] * 7 + [0.0] + [0.0] * 8 + [3.0])
    assert s["error_3d_m"]["p50"] == pytest.approx(np.percentile(errs, 50))
    assert s["error_z_m"]["p90"] == pytest.approx(np.percentile([0.0] * 16 + [3.0], 90))
    assert s["status"] == {"TRACKING": 24 + 29, "LOST": 1} and s["estimates"] == 54
    assert sc.live_counts() == (n_in + 10, n_in + 9)
    text = format_summary(s)
    assert "availability    85.0 %" in text and "80.0 % of all node-epochs" in text
    assert "mnls+tracking" in text
