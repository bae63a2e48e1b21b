"""`diffpos emulate` with its default fusion (mnls + tracking): a short lockstep run gives a
position for >= 90 % of the node-epochs after the first 2 s, and the summary reports it
(availability, floor accuracy over all node-epochs, ellipsoid coverage) consistently with an
independent count from the recording (truth and estimates read back with mcap's reader)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import parse_key
from mcap.reader import make_reader

pytestmark = pytest.mark.slow

PERIOD_NS = 100_000_000


def _recorded(path):
    """Recorded truth (node, epoch) -> floor, estimates (node, epoch) -> estimate, t0."""
    dec = M.estimate_decoder()
    truth, est, t0 = {}, {}, None
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            pk = parse_key(channel.topic)
            kind = None if pk is None else pk.kind
            if kind == "truth_node":
                g = json.loads(message.data)
                truth[(g["id"], g["t_ns"] // PERIOD_NS)] = g["floor_index"]
            elif kind == "estimate":
                e = dec(message.data)
                est[(e.node_id, e.epoch)] = e
            elif kind == "run_control":
                t0 = json.loads(message.data)["t0_ns"]
    return truth, est, t0


def test_lockstep_emulate_tracks_every_responder(services, tmp_path):
    summary_path = tmp_path / "summary.json"
    mcap = tmp_path / "run.mcap"
    p = services.start("emulate", "emulate", "--method", "mnls", "--duration", "5",
                       "--speed", "0",
                       "--record", str(mcap), "--dashboard", "off", "--json", str(summary_path),
                       "--no-progress", "--log-dir", str(tmp_path / "logs"))
    rc = p.wait(timeout=600)
    assert rc == 0, services.log("emulate")[-3000:]
    s = json.loads(summary_path.read_text())
    assert s["nodes"] == 6 and s["node_epochs"] == 6 * 30  # 5 s at 10 Hz, the first 2 s skipped
    assert s["availability"] >= 0.9
    assert set(s["status"]) <= set(M.TRACK_STATUSES)
    assert sum(s["status"].values()) == s["estimates"]
    for key in ("floor_accuracy", "floor_accuracy_fixes", "ellipsoid_coverage_95"):
        assert s[key] is not None and 0.0 <= s[key] <= 1.0, key
    # the same count from the recording: every node-epoch after 2 s, a miss without a position
    truth, est, t0 = _recorded(mcap)
    first = t0 // PERIOD_NS + 20
    scored = [k for k in truth if k[1] >= first]
    assert len(scored) == s["node_epochs"]
    has = [est.get(k) is not None and est[k].position_m is not None for k in scored]
    assert np.mean(has) == pytest.approx(s["availability"], abs=1e-12)
    right = [h and est[k].floor_index == truth[k] for h, k in zip(has, scored, strict=True)]
    assert np.mean(right) == pytest.approx(s["floor_accuracy"], abs=1e-12)
    assert all(type(e) is M.PositionEstimateV2 and e.method == "mnls+tracking"
               for e in est.values())
