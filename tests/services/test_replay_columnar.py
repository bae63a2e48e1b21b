"""Estimates as column batches (fusion/estimates.ColumnBatch, v1 and v2) and the replay's
report read from the columns (FixStream.add_rows, Comparison.add_rows), issue 37 item 2.

References: the estimate structs the same batches make (every field), and the report a
replay makes from those structs one by one (``keep_estimates=True``, the per-struct path)."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import numpy as np
import pytest
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.estimates import ColumnBatch, Estimates
from diffpos_services.replay.report_stream import Comparison, FixStream, TruthBook
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import quiet_logger, synthetic_run, write_synthetic_recording
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario

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
    real = ColumnBatch.items

    def counting(self):
        if not self.made:
            made.append(len(self))
        return real.fget(self)

    monkeypatch.setattr(ColumnBatch, "items", property(counting))
    by_struct = replay(rec, keep_estimates=True)  # every estimate made and read as a struct
    assert sum(made) == 4 * 30
    made.clear()
    by_column = replay(rec, keep_estimates=False)
    assert made == []  # no struct made
    assert by_column.report["fixes"]["total"] == 4 * 30
    assert by_column.report["compare"]["matched"] > 100
    assert by_column.report["compare"]["identical_positions"] > 0
    assert _report(by_column) == _report(by_struct)


def _batches(seed: int = 5) -> tuple[list[ColumnBatch], list[str]]:
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
    assert len(out.parts) > 1 and all(isinstance(p, ColumnBatch) for p in out.parts)
    return out.parts, run.node_ids


def _check_columns(parts: list[ColumnBatch], decode) -> int:
    """Every struct of ``parts`` against its row's columns; the structs' wire round trip.
    Returns the number of rows without a good status."""
    n_bad = 0
    for b in parts:
        r = b.rows
        for i, e in enumerate(b):
            _, used_ids, excluded, _ = r.shared[r.group[i]]
            assert (e.node_id, e.epoch, e.t_ns, e.status) == (r.node_id[i], r.epoch[i],
                                                             r.t_ns[i], r.status[i])
            assert e.seq == b[0].seq + i
            assert e.used_anchors == used_ids and e.excluded == excluded
            assert (e.position_m is not None) == r.has_pos[i]
            assert e.peb_m == (r.peb[i] if r.ok[i] else None)
            if r.has_pos[i]:
                assert e.position_m == tuple(r.pos[i]) and e.floor_index == r.floor[i]
                assert (e.covariance_m2 is not None) == r.has_cov[i]
                if r.has_cov[i]:
                    assert e.covariance_m2 == tuple(map(tuple, r.cov[i].tolist()))
            assert getattr(e, "floor_probabilities", None) == (
                None if r.probs is None else r.probs[i])
            n_bad += e.status not in M.GOOD_STATUSES
        assert [decode(M.encode(e)) for e in b] == list(b)
    return n_bad


def test_a_batch_columns_are_its_structs():
    parts, _ = _batches()
    assert _check_columns(parts, M.decoder(M.PositionEstimate)) > 0
    assert sum(map(len, parts)) == 4 * 20


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


# ---------------------------------------------------------------- v2: mnls + tracking
def _tracked_parts() -> tuple[list[ColumnBatch], dict[str, np.ndarray]]:
    """The v2 batches of the tracked fusion (mnls + tracking, the default) on the emulated
    channel of the default building: five static UAVs, three walkers (12 epochs), and the
    walkers' truth per epoch [m]."""
    sc = default_scenario()
    b = sc.building
    keys, period, t0 = Keys("t"), 100_000_000, 1_800_000_000_000_000_000
    anchors = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                        [15.0, -20.0, 1.0], [-25.0, -12.0, 3.0]])
    h = b.nominal_node_height_m
    walk = {"w1": ([-10.0, 5.0, 4.0 + h], [1.0, 0.0, 0.0]),
            "w2": ([5.0, 8.0, 7.0 + h], [0.0, -1.0, 0.0]),
            "w3": ([2.0, 4.0, 10.0 + h], [0.7, 0.0, 0.0])}
    ids = list(walk)
    rng = np.random.default_rng(3)
    core = FusionCore(FusionConfig.from_scenario(sc, site="t", epoch_period_s=0.1,
                                                 method="mnls"),
                      logger=quiet_logger(), record_decisions=False)
    out, truth = Estimates(), {n: [] for n in ids}
    for k in range(12):
        nodes = np.array([np.add(p, np.multiply(v, 0.1 * k)) for p, v in walk.values()])
        for n, p in zip(ids, nodes, strict=True):
            truth[n].append(p)
        fa = first_arrival(emulate_channel(anchors, nodes, building=b, radio=sc.radio),
                           radio=sc.radio, rng=rng)
        t = t0 + k * period + 20_000_000
        for j in range(len(anchors)):
            a, rx = f"uav{j + 1}", t + 1_000_000 + 100_000 * j
            det = fa.detected[:, j]
            col = lambda x, d=det: [float(v) if ok else None for v, ok in zip(x, d, strict=True)]  # noqa: E731
            core.on_sample(keys.anchor_state(a), M.encode(M.AnchorState(
                anchor_id=a, t_ns=t, seq=k, position_m=M.vec3(anchors[j]),
                velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.02, 0.02, 0.03),
                velocity_sigma_m_s=0.05, range_rate_hz=10.0, t_pub_wall_ns=rx)), rx)
            core.on_sample(keys.anchor_range_batch(a), M.encode(M.RangeBatch(
                anchor_id=a, t_ns=t, seq=k, node_ids=ids, range_m=col(fa.range_m[:, j]),
                sigma_m=col(fa.sigma_m[:, j]), snr_db=col(fa.snr_db[:, j]),
                t_pub_wall_ns=rx)), rx + 10)
        out += core.step(t + 50_000_000)
    out += core.flush(t0 + 10**10)
    assert len(out) == 3 * 12 and all(isinstance(p, ColumnBatch) for p in out.parts)
    return out.parts, {n: np.array(v) for n, v in truth.items()}


def test_tracked_batches_columns_are_their_structs_and_report_the_same():
    parts, truth_xyz = _tracked_parts()
    _check_columns(parts, M.decoder(M.PositionEstimateV2))
    assert len({st for b in parts for st in b.rows.status}) > 1  # initialising, tracking...
    assert any(p is not None and len(p) for b in parts for p in b.rows.probs)
    t_first = min(b.rows.t_ns[0] for b in parts)
    truth = TruthBook(window_ns=10**10)
    for n, xyz in truth_xyz.items():
        for k, p in enumerate(xyz):
            truth.add(n, t_first + k * 100_000_000, tuple(p.tolist()), int(p[2] // 3.0))
    a = FixStream(truth, max_truth_gap_ns=10**9, window_ns=10**10, skip_s=0.0)
    b = FixStream(truth, max_truth_gap_ns=10**9, window_ns=10**10, skip_s=0.0)
    for p in parts:
        for e in p:
            a.add(e)
        b.add_rows(p.rows)
    for s in (a, b):
        s.advance(t_first + 5 * 10**9, final=True)
    assert a.accuracy()[0] == b.accuracy()[0] and a.node_epochs() == b.node_epochs()
    assert a.node_epochs()["node_epochs"] == 3 * 12
    assert a.gating() == b.gating() and a.no_track == b.no_track and a.by_status == b.by_status
