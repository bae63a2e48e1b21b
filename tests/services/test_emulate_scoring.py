"""The emulate summary counts every node-epoch after the first 2 s (a miss is a miss).

Reference: the counts by hand for a small made-up run (two static nodes, 3 s at 10 Hz, some
epochs without an estimate, one without a position, one on the wrong floor)."""

from __future__ import annotations

import numpy as np
import pytest
from diffpos_services.emulate.scoring import Scorer, format_summary
from diffpos_services.wire import messages as M

from diffpos.floor_calibration import floor_calibration
from diffpos.scenario import default_scenario
from diffpos.trajectory import Static

B = default_scenario().building
P = 100_000_000
T0 = 1_800_000_000_000_000_000
TRUTH = {"a": (1.0, 5.0, 5.5), "b": (-3.0, 8.0, 8.5)}  # floors 0 and 1


def _est(node, k, pos, floor, status="TRACKING", probs=()):
    cov = ((0.01, 0.0, 0.0), (0.0, 0.01, 0.0), (0.0, 0.0, 0.01))
    return M.PositionEstimateV2(
        node_id=node, t_ns=T0 + k * P, epoch=T0 // P + k, seq=k, method="mnls+tracking",
        status=status, position_m=pos, covariance_m2=cov if pos else None, peb_m=None,
        z_bound_m=None, floor_index=floor, floor_probabilities=list(probs), snapshot=None, links=[],
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
    assert "availability    85.0 % of the node-epochs" in text and "80.0 % of all node-epochs" in text
    assert "mnls+tracking" in text
    # no floor probabilities reported: the calibration is absent, and said so
    assert s["floor_calibration"] is None and "calibration not measured" in text


def _full_summary() -> dict:
    """A summary with every row filled, long values included (a long recording path)."""
    return {
        "run_id": "20261123T190347Z-476082", "anchors": 8, "nodes": 50, "duration_s": 20.0,
        "speed": 0.0, "channel": "emulator", "fusion_method": "dnls",
        "model": "lower window edge, Delta 0 m (auto: every anchor below the lowest window "
                 "(4.0 m < 4.75 m): the lower-edge path arrives first)",
        "estimates": 10_000, "with_position": 9_000,
        "status": {"GATING_FAILED": 689, "NOT_CONVERGED": 20, "OK": 9_291},
        "skip_s": 2.0, "node_epochs": 9_000, "node_epochs_without_estimate": 3,
        "availability": 0.9, "floor_accuracy": 0.85, "floor_accuracy_fixes": 0.94,
        "error_3d_m": {"p50": 0.3, "p67": 0.4, "p90": 1.2, "p95": 1.6},
        "error_z_m": {"p50": 0.2, "p67": 0.3, "p90": 1.0, "p95": 1.4},
        "peb_m": {"p50": 0.5, "p67": 0.5, "p90": 0.6, "p95": 0.6},
        "ellipsoid_coverage_95": 0.9,
        "fusion": {"gated": 0, "rejected": {"late": 2, "time_future": 94}, "late_ranges": 2,
                   "latency_ms": {"p50": 25.9, "p99": 158.2}},
        "recording": "/very/long/folder/name/recordings/large-20261123T190347Z-476082.mcap",
        "notes": ["fault injected at t=5 s: anchor uav3 stopped (SIGSTOP) for 3 s; its ranges "
                  "of that window are missing from the recording and the fixes",
                  "second note"],
    }


@pytest.mark.parametrize("width", [60, 80, 100])
def test_summary_fits_the_width_and_keeps_every_value(width):
    s = _full_summary()
    text = format_summary(s, width=width)
    lines = text.splitlines()
    assert max(map(len, lines)) <= width
    flat = " ".join(x.strip() for x in lines)
    # every value is still there (wrapping only moves words to the next line)
    for word in ("GATING_FAILED 689", "90.0 %", "85.0 %", "p99 158.200 ms", "second note",
                 "(SIGSTOP)", "lower-edge"):
        assert word in flat
    # the notes: one paragraph each, the first line named "notes", continuation indented
    note_lines = [i for i, x in enumerate(lines) if x.startswith("notes")]
    assert len(note_lines) == 1 and lines[-1].strip() == "second note"
    # the gating row names the same count as the status row (no "gated 0" next to 689)
    assert "689 estimates GATING_FAILED" in flat
    assert "rejected: late 2, time_future 94" in flat


def test_summary_without_notes_has_no_notes_row():
    s = _full_summary()
    del s["notes"]
    assert "notes" not in format_summary(s, width=80)


def test_summary_says_node_epochs_the_overload_policy_dropped_apart_from_ranges():
    """``superseded`` / ``overloaded`` count node-epochs a fusion behind its input did not
    solve, not ranges: the gating row lists them apart from the rejected ranges."""
    s = _full_summary()
    s["fusion"]["rejected"] = {"late": 2, "superseded": 40, "overloaded": 3}
    flat = " ".join(x.strip() for x in format_summary(s, width=100).splitlines())
    assert "ranges rejected: late 2;" in flat
    assert "node-epochs not solved (the fusion was behind its input): superseded 40, " \
           "overloaded 3" in flat
    s["fusion"]["rejected"] = {"superseded": 5}
    flat = " ".join(x.strip() for x in format_summary(s, width=100).splitlines())
    assert "ranges rejected: 0;" in flat and "superseded 5" in flat


def test_summary_has_the_calibration_of_the_floor_probabilities():
    """Node-epochs with floor probabilities (v2): the summary's calibration is the core's
    over the same node-epochs (a miss in the denominator of "confidently wrong", not in it)."""
    nf = B.n_floors
    sc = Scorer([(n, Static(p)) for n, p in TRUTH.items()], B, T0, period_ns=P,
                end_ns=T0 + 3 * 10**9)
    ef, tf, probs, has = [], [], [], []
    for k in range(20, 30):
        for node, true_floor in (("a", 0), ("b", 1)):
            if node == "a" and k == 21:  # a miss: no estimate
                ef.append(-1), tf.append(true_floor), probs.append([np.nan] * nf)
                has.append(False)
                continue
            pub = true_floor if k % 4 else 1 - true_floor  # every 4th on the other floor
            p = np.full(nf, 0.01 / (nf - 1))
            p[pub] = 0.99 if k % 3 else 0.7
            sc.add(_est(node, k, TRUTH[node], pub, probs=p.tolist()))
            ef.append(pub), tf.append(true_floor), probs.append(p), has.append(True)
    s = sc.summary()
    ref = floor_calibration(ef, tf, np.array(probs), has_position=has)
    c = s["floor_calibration"]
    assert c["node_epochs"] == 20 and c["with_probabilities"] == 19
    assert c["confidently_wrong_count"] == ref["confidently_wrong_count"] > 0
    assert c["confidently_wrong"] == pytest.approx(c["confidently_wrong_count"] / 20)
    assert c["ece"] == pytest.approx(ref["ece"], rel=1e-12)
    flat = " ".join(x.strip() for x in format_summary(s, width=100).splitlines())
    assert f"{c['confidently_wrong_count']} = {100 * c['confidently_wrong']:.2f} % of all" in flat
