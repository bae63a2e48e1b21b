"""Range batches with undetected entries (range, sigma and SNR all null: the realistic
channel's usual batch) take the fusion's vectorised acceptance path (issue 37: no Python call
per range) and store exactly what the same ranges sent one message each store; a partly null
or implausible entry still goes through the per-entry checks. Reference: the single-range
path of the same core."""

from __future__ import annotations

import pytest
from diffpos_services.fusion.core import FusionCore
from diffpos_services.wire import messages as M
from fusion_scene import KEYS, PERIOD_NS
from fusion_scene import fusion_config as _cfg

NODES = ["n01", "n02", "n03", "n04"]


def _feed(batched: FusionCore, single: FusionCore, r, sg, snr, epochs: range = range(3)
          ) -> None:
    for e in epochs:  # epoch 0 registers the nodes (checked path)
        t = e * PERIOD_NS + 7
        b = M.RangeBatch(anchor_id="uav1", t_ns=t, seq=e, node_ids=NODES, range_m=r,
                         sigma_m=sg, snr_db=snr, t_pub_wall_ns=t + 1)
        batched.on_sample(KEYS.anchor_range_batch("uav1"), M.encode(b), t + 2)
        for i, n in enumerate(NODES):
            rm = M.RangeMeasurement(anchor_id="uav1", node_id=n, t_ns=t, seq=10 * e + i,
                                    range_m=r[i], sigma_m=sg[i], snr_db=snr[i],
                                    t_pub_wall_ns=t + 1)
            single.on_sample(KEYS.anchor_range("uav1", n), M.encode(rm), t + 2)


def _stored(core: FusionCore) -> dict:
    return {k: dict(pe.ranges) for k, pe in core.book.pending.items()}


@pytest.mark.parametrize("min_snr_db", [None, 15.0])
@pytest.mark.parametrize("undetected", [[1], [0, 3], [0, 1, 2, 3]])
def test_undetected_entries_take_the_vectorised_path_and_store_the_same(
        monkeypatch, min_snr_db, undetected):
    r, sg, snr = [20.0, 21.5, 23.25, 30.0], [0.05, 0.1, 0.2, 0.3], [20.0, 10.0, 16.0, 30.0]
    for i in undetected:
        r[i] = sg[i] = snr[i] = None
    batched, single = FusionCore(_cfg(min_snr_db=min_snr_db)), FusionCore(_cfg(
        min_snr_db=min_snr_db))
    _feed(batched, single, r, sg, snr, range(1))  # registers the nodes
    calls = []
    entry = FusionCore._entry
    monkeypatch.setattr(FusionCore, "_entry", lambda self, *a: calls.append(a) or entry(self, *a))
    _feed(batched, single, r, sg, snr, range(1, 4))
    assert len(calls) == 3 * len(NODES)  # the single ranges only: the batches none
    assert not batched.rejected and not single.rejected
    got, want = _stored(batched), _stored(single)
    assert got == want and sum(map(len, got.values())) == 4 * len(NODES)
    for (node, _), ranges in got.items():
        if NODES.index(node) in undetected:
            e = ranges["uav1"]
            assert (e.range_m, e.sigma_m, e.snr_db) == (None, 1.0, float("-inf"))
    assert batched.anchors["uav1"].ranges == single.anchors["uav1"].ranges


@pytest.mark.parametrize(("r1", "sg1", "snr1", "rejected"), [
    (None, 0.1, None, {}),  # partly null: checked per entry (accepted, not detected)
    (None, None, 10.0, {}),
    (1e9, 0.1, 10.0, {"absurd_value": 3}),  # implausible beside an undetected entry
    (20.0, 0.1, 400.0, {"absurd_value": 3}),
])
def test_partly_null_or_implausible_entries_are_checked_one_by_one(r1, sg1, snr1, rejected):
    r, sg, snr = [20.0, r1, 23.25, None], [0.05, sg1, 0.2, None], [20.0, snr1, 16.0, None]
    batched, single = FusionCore(_cfg()), FusionCore(_cfg())
    _feed(batched, single, r, sg, snr)
    assert dict(batched.rejected) == dict(single.rejected) == rejected
    assert _stored(batched) == _stored(single)
