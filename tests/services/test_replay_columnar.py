"""v1 estimates as column batches (fusion/estimates_v1.V1Batch) and the replay's report read
from the columns (FixStream.add_rows, Comparison.add_rows), issue 37 item 2.

References: the estimate structs the same batches make (every field), and the report a
replay makes from those structs one by one (``keep_estimates=True``, the per-struct path)."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import pytest
from diffpos_services.fusion import estimates_v1
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.estimates import Estimates
from diffpos_services.fusion.estimates_v1 import V1Batch
from diffpos_services.replay.report_stream import Comparison, FixStream, TruthBook
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import quiet_logger, synthetic_run, write_synthetic_recording
from diffpos_services.wire import messages as M

_RUN = dict(n_anchors=5, n_nodes=4, duration_s=3.0, outlier_probability=0.15, seed=23)


@pytest.fixture(scope="module")
def rec(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("columnar") / "synthetic.mcap"
    write_synthetic_recording(path, flush_every=150, **_RUN)
    return path


def _report(result) -> str:
    r = dict(result.report)
    r.pop("timing")
    return json.dumps(r, sort_keys=True)


def test_replay_without_kept_estimates_builds_no_structs_and_reports_the_same(rec, monkeypatch):
    made = []
    real = V1Batch._build

    def counting(self):
        made.append(len(self))
        return real(self)

    monkeypatch.setattr(V1Batch, "_build", counting)
    by_struct = replay(rec, keep_estimates=True)  # every estimate made and read as a struct
    assert sum(made) == 4 * 30
    made.clear()
    by_column = replay(rec, keep_estimates=False)
    assert made == []  # no struct made
    assert by_column.report["fixes"]["total"] == 4 * 30
    assert by_column.report["compare"]["matched"] > 100
    assert by_column.report["compare"]["identical_positions"] > 0
    assert _report(by_column) == _report(by_struct)


def _batches(seed: int = 5) -> tuple[list[V1Batch], list[str]]:
    """The v1 batches a core makes on a synthetic run with NLoS-like outliers, and the
    run's nodes."""
    run = synthetic_run(n_anchors=5, n_nodes=4, duration_s=2.0, outlier_probability=0.25,
                        seed=seed)
    core = FusionCore(run.config, logger=quiet_logger(), record_decisions=False)
    t = run.t0_ns - 100_000_000
    for a in run.anchor_ids:
        core.on_liveliness(a, True, t)
    out = Estimates()
    for items in run.epochs:
        for rx, key, payload in items:
            core.on_sample(key, payload, rx)
            t = rx
        out += core.step(t + 1000)
    out += core.flush(t + 2000)
    assert len(out.parts) > 1 and all(isinstance(p, V1Batch) for p in out.parts)
    return out.parts, run.node_ids


def test_a_batch_columns_are_its_structs():
    parts, _ = _batches()
    n_bad = 0
    for b in parts:
        r = b.rows
        for i, e in enumerate(b):
            _, used_ids, excluded, _ = r.shared[r.group[i]]
            assert (e.node_id, e.epoch, e.t_ns, e.status) == (r.node_id[i], r.epoch[i],
                                                             r.t_ns[i], r.status[i])
            assert e.seq == b.seq0 + i + 1
            assert e.used_anchors == used_ids and e.excluded == excluded
            assert (e.position_m is not None) == r.has_pos[i]
            if r.has_pos[i]:
                assert e.position_m == tuple(r.pos[i]) and e.floor_index == r.floor[i]
                assert e.peb_m == r.peb[i]
            n_bad += e.status not in M.GOOD_STATUSES
        # the structs encode as the wire's estimate and decode back to themselves
        dec = M.decoder(M.PositionEstimate)
        assert [dec(M.encode(e)) for e in b] == list(b)
    assert n_bad > 0 and sum(map(len, parts)) == 4 * 20


def test_the_report_streams_from_columns_equal_those_from_structs():
    parts, nodes = _batches(seed=8)
    t0 = min(p.rows.t_ns[0] for p in parts) - 10**8
    truth = TruthBook(window_ns=10**10)
    for t in range(t0, t0 + 2_300_000_000, 50_000_000):  # a straight truth under every node
        for k, node in enumerate(nodes):
            truth.add(node, t, (1.0 + k, 2.0, 0.5 + (t - t0) * 1e-9), 0)
    a = FixStream(truth, max_truth_gap_ns=10**9, window_ns=10**10)
    b = FixStream(truth, max_truth_gap_ns=10**9, window_ns=10**10)
    ca, cb = Comparison(10**10), Comparison(10**10)
    for p in parts:
        for e in p:
            a.add(e)
            ca.add(1, e, 7)
            ca.add(0, msgspec.structs.replace(e, status="OK_UNVERIFIED"), 7)
        b.add_rows(p.rows)
        cb.add_rows(1, p.rows, 7)
        for e in p:  # the other side as structs, after the batch
            cb.add(0, msgspec.structs.replace(e, status="OK_UNVERIFIED"), 7)
    for s in (a, b):
        s.advance(t0 + 3 * 10**9, final=True)
    assert a.accuracy()[0] == b.accuracy()[0]
    assert a.node_epochs() == b.node_epochs()
    assert a.gating() == b.gating() and a.by_status == b.by_status
    assert sum(a.excluded[x][y] for x in a.excluded for y in a.excluded[x]) > 0
    assert ca.result() == cb.result() and ca.result()["matched"] == 4 * 20


def test_estimates_read_as_a_list():
    parts, _ = _batches()
    est = Estimates(parts)
    flat = [e for p in parts for e in p]
    assert est == flat and len(est) == len(flat) and est[3] == flat[3]
    assert [] + est == flat and list(est + []) == flat  # noqa: RUF005 (the operators)
    assert Estimates() == [] and not Estimates([[]])
    assert estimates_v1.V1Batch is V1Batch
