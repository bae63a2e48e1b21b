"""``cold_retry_max_period_s``: the cold (multi-start) D-NLS solves of a node whose fixes keep
failing back off (1, 2, 4, 4 ... x ``cold_retry_period_s``, at most the setting), start again
at the period when the node's anchors change or a fix succeeds, and are every period without
the setting (the default)."""

from __future__ import annotations

import numpy as np
from diffpos_services.fusion.config import FusionConfig, with_legacy_defaults
from diffpos_services.fusion.core import FusionCore
from diffpos_services.wire import messages as M
from fusion_scene import ANCHORS, EDGE, KEYS, NODES, PERIOD_NS, W
from fusion_scene import fusion_config as _cfg

from diffpos.estimators.dnls import solver as est
from diffpos.geometry import window_edge_path

NODE = "n02"


def _feed(core, e, anchors, bias, rng):
    """Every anchor of ``anchors`` reports its state and a range to NODE in epoch ``e`` (no
    range from an anchor whose bias is None: not detected)."""
    for j, aid in enumerate(anchors):
        apos = ANCHORS[aid]
        t_ns = e * PERIOD_NS + int((0.1 + 0.15 * j) * PERIOD_NS)
        st = M.AnchorState(anchor_id=aid, t_ns=t_ns, seq=e, position_m=M.vec3(apos),
                           velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.01, 0.01, 0.01),
                           velocity_sigma_m_s=0.0, range_rate_hz=10.0, t_pub_wall_ns=0)
        core.on_sample(KEYS.anchor_state(aid), M.encode(st), 0)
        if aid in bias and bias[aid] is None:
            continue
        r = float(window_edge_path(apos, NODES[NODE], window_height_m=W, edge_x_m=EDGE).length_m)
        r += rng.normal(0, 0.03) + bias.get(aid, 0.0)
        msg = M.RangeMeasurement(anchor_id=aid, node_id=NODE, t_ns=t_ns, seq=e, range_m=r,
                                 sigma_m=0.03, snr_db=20.0, t_pub_wall_ns=0)
        core.on_sample(KEYS.anchor_range(aid, NODE), M.encode(msg), 0)


def _run(monkeypatch, cfg, plan):
    """Feed ``plan`` (per epoch: anchors, biases); the epochs whose step made a cold solve
    and every estimate."""
    cold, out = [], []
    real = est.dnls
    e_now = [0]

    def counting(*args, **kw):
        if kw.get("x0_m") is None:
            cold.append(e_now[0])
        return real(*args, **kw)

    monkeypatch.setattr(est, "dnls", counting)
    core = FusionCore(cfg)
    rng = np.random.default_rng(5)
    for e, (anchors, bias) in enumerate(plan):
        e_now[0] = e
        _feed(core, e, anchors, bias, rng)
        out += core.step(0)
    out += core.step(10**12)
    return cold, out


FOUR = ("uav1", "uav2", "uav3", "uav4")
FAIL = {"uav2": 8.0}  # 4 anchors, one biased: detected, not removable


def test_default_is_off_and_legacy_recordings_keep_it_off():
    assert FusionConfig().cold_retry_max_period_s is None
    assert with_legacy_defaults({"method": "dnls"}).get("cold_retry_max_period_s") is None


def test_failing_node_backs_off_and_default_retries_every_period(monkeypatch):
    plan = [(FOUR, FAIL)] * 130  # 13 s
    base, out = _run(monkeypatch, _cfg(cold_retry_period_s=1.0), plan)
    assert sum(g.status == "GATING_FAILED" for g in out) >= len(plan) - 2  # the premise
    # without the setting: one cold solve per second (the first epoch's, then retries)
    assert np.all(np.abs(np.diff(base) - 10) <= 1), base
    assert len(base) >= 12
    cold, out2 = _run(monkeypatch, _cfg(cold_retry_period_s=1.0, cold_retry_max_period_s=4.0),
                      plan)
    gaps = np.diff(cold)
    # 1, 2, 4, 4 s between the cold solves (+-1 epoch: the epochs' reference times)
    assert len(gaps) >= 4 and np.all(np.abs(gaps - [10, 20, 40, 40][:len(gaps)]) <= 1), cold
    assert [g.status for g in out2].count("OK") == [g.status for g in out].count("OK")


def test_new_anchors_or_a_good_fix_end_the_back_off(monkeypatch):
    five = (*FOUR, "uav5")
    before, swapped = {**FAIL, "uav5": None}, {**FAIL, "uav4": None}  # uav4's range lost
    plan = ([(five, before)] * 75 + [(five, swapped)] * 25 + [(five, {"uav5": None})] * 10
            + [(five, before)] * 40)
    cold, out = _run(monkeypatch, _cfg(cold_retry_period_s=1.0, cold_retry_max_period_s=8.0),
                     plan)
    # backed off: 0, 10, 30, 70 (+1: an epoch is released when the anchors move past it);
    # the wait then 8 s, but uav4's range is lost at 75: the next cold solve is due 1 s
    # after the last (at ~80), the second on the new anchors 1 s later again
    assert np.all(np.abs(np.array(cold[:4]) - [0, 10, 30, 70]) <= 1), cold
    assert 75 <= cold[4] <= 81, cold
    status = {g.epoch: g.status for g in out}
    assert all(status[e] == "OK" for e in range(102, 110))  # the bias gone: good fixes
    # failing again after a good fix: retried at once, then 1 s, 2 s (not 8 s) later
    after = [c - 110 for c in cold if c >= 110]
    assert np.all(np.abs(np.array(after[:3]) - [0, 10, 30]) <= 1), cold
