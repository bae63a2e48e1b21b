"""Bounded soak in CI: 16 anchors x 50 nodes x 10 Hz for 60 s through the real runtime
(router, recorder, fusion, 16 anchor processes, range batches, congestion control BLOCK).

Asserts zero loss (every range reaches the fusion, every node gets an estimate for every
epoch exactly once, the recorder writes everything and every anchor's sequence numbers are
complete in the recording) and bounded memory (every process grows by less than 50 MB after a
15 s warm-up). The full 16 x 200 x 10 minutes is ``benchmarks/bench_soak.py`` (docs/soak.md).

Why 50 nodes and not 200: on a shared 2-core machine 16 x 200 (32,000 ranges/s into one
Python fusion) keeps up but its p99 latency approaches the 0.3 s epoch deadline under load;
the CI test must not fail because a neighbour is busy, and 16 x 50 exercises the same paths
(16 processes, batches, recorder) with margin.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

N_ANCHORS, N_NODES, DURATION_S, WARMUP_S = 16, 50, 60.0, 15.0


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_soak_zero_loss_and_bounded_memory(tmp_path):
    from bench_soak import format_report, run_soak

    # (a fusion that falls behind on a loaded CI machine lags but drops nothing: the zero
    # loss asserted here is the transport's and the fusion's, not the live overload policy's)
    r = run_soak(N_ANCHORS, N_NODES, DURATION_S, tmp_path, recorder=True, warmup_s=WARMUP_S,
                 rss_period_s=2.0, max_backlog_s=0)
    report = format_report(r)
    n_epochs = round(DURATION_S * 10)
    # every process ended cleanly (SIGTERM -> 0; the recorder exits 1 if it lost anything)
    assert all(code == 0 for code in r["exit_codes"].values()), (r["exit_codes"], report)
    # transport: BLOCK everywhere, nothing dropped
    fu = r["fusion"]
    assert fu["ranges_received"] == fu["ranges_sent"] == N_ANCHORS * N_NODES * n_epochs, report
    assert fu["states_received"] == N_ANCHORS * n_epochs, report
    assert fu["rejected"].get("late", 0) == sum(fu["rejected"].values()), report  # no bad input
    # every node, every epoch, exactly once
    assert r["estimates_missing"] == 0 and r["estimates_duplicated"] == 0, report
    assert r["estimates_received"] == N_NODES * n_epochs
    # recorder: all received written, and the recording holds every anchor message
    rec, rg = r["recorder"], r["recording"]
    assert rec["received"] == rec["written"] > 0, report
    assert rg["anchor_seq_holes"] == {} and rg["anchors_recorded"] == N_ANCHORS, report
    kinds = rg["messages_by_kind"]
    assert kinds["anchor_state"] == kinds["range_batch"] == N_ANCHORS * n_epochs, report
    assert kinds["estimate"] == N_NODES * n_epochs, report
    # bounded memory after the warm-up
    for name, m in r["rss"].items():
        assert m["growth_mb"] < 50.0, (name, m, report)
    assert r["latency_fusion_ms"]["count"] == N_NODES * n_epochs


def test_backlog_of_epochs_keeps_its_anchor_states():
    """An overloaded fusion solves epochs long after their states arrived: the anchor state
    history is kept for ``state_history_s`` (not a fixed count), so 20 s of unsolved epochs
    are all solved with their anchors (before, 64 states = 6.4 s: NO_ANCHOR_STATE)."""
    from diffpos_services.config import build_config
    from diffpos_services.fusion.config import FusionConfig
    from diffpos_services.fusion.core import FusionCore
    from test_bad_input import good_stream, run_stream

    core = FusionCore(build_config(FusionConfig, dict(site="t", window_height_m=1.5,
                                                      edge_x_m=(-20.0, 20.0))))
    epochs = good_stream(200)
    backlog = [[m for ep in epochs for m in ep]]  # everything ingested before one solve
    out = run_stream(core, backlog)
    assert len(out) == 200 * 3
    # (gating may exclude one anchor now and then: P_fa = 1e-3 per fix)
    assert all(g.status == "OK" and len(g.used_anchors) >= 4 for g in out)
    core_short = FusionCore(build_config(FusionConfig, dict(site="t", window_height_m=1.5,
                                                            edge_x_m=(-20.0, 20.0),
                                                            state_history_s=5.0)))
    short = run_stream(core_short, backlog)
    assert sum(g.status == "OK" for g in short) < 0.5 * len(short)  # the test can fail


def test_backlog_is_solved_in_bounded_chunks_with_the_same_fixes():
    """After a stall the ready epochs are solved ``max_fixes_per_step`` at a time (bounded
    working memory, ingestion in between), oldest first, every one of them, each within its
    PEB of the truth like one big solve (the fixes differ by mm-cm: later chunks warm-start
    from the node tracks updated by earlier ones, one big batch cannot)."""
    from diffpos_services.config import build_config
    from diffpos_services.fusion.config import FusionConfig
    from diffpos_services.fusion.core import FusionCore
    from test_bad_input import NODES, good_stream, run_stream

    base = dict(site="t", window_height_m=1.5, edge_x_m=(-20.0, 20.0))
    epochs = good_stream(40)
    backlog = [[m for ep in epochs for m in ep]]
    whole = run_stream(FusionCore(build_config(FusionConfig, base)), backlog)
    core = FusionCore(build_config(FusionConfig, dict(base, max_fixes_per_step=25)))
    for k, p, w in backlog[0]:
        core.on_sample(k, p, w)
    chunks = []
    while True:
        out = core.step(10**15, limit=25)  # as the live service does
        if not out:
            break
        chunks.append(out)
        assert core.diagnostics(0).pending_epochs == core.backlog + len(core.book.pending)
    assert [len(c) for c in chunks] == [25] * 4 + [20]
    # without a limit everything ready is returned (in internal chunks): what replay expects
    core_all = FusionCore(build_config(FusionConfig, dict(base, max_fixes_per_step=25)))
    assert len(run_stream(core_all, backlog)) == 120 and core_all.backlog == 0
    assert [g.epoch for c in chunks for g in c] == sorted(g.epoch for c in chunks for g in c)
    got = sorted((g for c in chunks for g in c), key=lambda g: (g.epoch, g.node_id))
    assert [(g.node_id, g.epoch, g.status) for g in got] == [
        (g.node_id, g.epoch, g.status) for g in whole]
    assert all(g.status == "OK" for g in got)
    # every fix as good as its bound says, in both (mm-cm apart: z is the weak axis)
    for est in (got, whole):
        err = np.array([np.linalg.norm(np.subtract(g.position_m, NODES[g.node_id])) for g in est])
        peb = np.array([g.peb_m for g in est])
        assert np.all(err < 5 * peb), (err.max(), peb.min())
