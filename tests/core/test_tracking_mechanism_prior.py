"""``TrackerConfig.mechanism_prior_min_links``: a node with fewer ranges than the setting gets
the flat inlier prior ``log(1 - eps)`` for every candidate mechanism of a link instead of the
uniform ``log((1 - eps) / n_cand)``; a node with at least that many ranges is scored as
before, bit for bit (docs/tracking_evidence.md "Session 27: the 3-UAV building").

Reference: the emulator's own first arrivals (:func:`diffpos.channel.emulator.first_arrival`)
at random level positions of the existence-margin tests' building (not a shipped scenario),
ranged from three of its UAVs (one floor hypothesis fits three ranges exactly) and from all
four; the candidate count of every link from the selection's numpy reference
(:func:`diffpos.tracking.model._select_prep_numpy`: the mechanisms that exist and carry power).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from margin_building import ANCHORS, BUILDING, SCENARIO

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.model import (
    _select_numpy,
    _select_prep_numpy,
    select,
    snr_cost_near,
)
from diffpos.tracking.state import TrackerConfig

_B = BUILDING


def _case(seed: int, n: int = 400):
    """Level positions on every floor, the emulator's first arrivals from the four UAVs; the
    first half of the nodes keep three of them (the fourth masked), the rest all four (only
    the nodes with every kept link detected); the paths and SNR costs at the truth."""
    rng = np.random.default_rng(seed)
    x0, x1 = _B.edge_x_m
    floor = rng.integers(0, _B.n_floors, n)
    nodes = np.stack([rng.uniform(x0 + 1.0, x1 - 1.0, n), rng.uniform(1.0, _B.depth_m - 1.0, n),
                      _B.floor_z_m(floor) + _B.nominal_node_height_m], axis=-1)
    fa = first_arrival(emulate_channel(ANCHORS, nodes, building=_B, radio=SCENARIO.radio),
                       radio=SCENARIO.radio, rng=rng)
    mask = fa.detected.copy()
    mask[: n // 2, 3] = False
    keep = np.flatnonzero(mask[:, :3].all(axis=1) & (mask[:, 3] | (np.arange(n) < n // 2)))
    links = Links.from_arrays(np.broadcast_to(ANCHORS, (n, 4, 3)), fa.range_m, fa.sigma_m, mask,
                              TrackerConfig().sigma_model_m, snr_db=fa.snr_db,
                              radio=SCENARIO.radio).take(keep)
    pos, fl = nodes[keep][:, None], floor[keep][:, None]
    pe = all_paths(pos, links, fl, _B, 0.2)
    snr_c = snr_cost_near(pos, links, fl, _B, 0.2, pe)
    cov = np.broadcast_to(np.diag([0.04, 0.04, 0.01]), (keep.size, 1, 3, 3)).copy()
    return cov, links, pe, snr_c


def test_three_ranges_flat_prior_four_unchanged():
    """With the setting 4: every link of a three-range node that both selections call an
    inlier with the same mechanism has the log-weight of the setting off plus ``log n_cand``
    (1e-12 nats), and no link of such a node that was an inlier becomes an outlier; the
    four-range nodes' selections are those of the setting off, bit for bit; 0 is the setting
    off."""
    for seed in (1, 2):
        cov, links, pe, snr_c = _case(seed)
        off = select(cov, links, pe, TrackerConfig(), snr_c)
        on = select(cov, links, pe, TrackerConfig(mechanism_prior_min_links=4), snr_c)
        zero = select(cov, links, pe, TrackerConfig(mechanism_prior_min_links=0), snr_c)
        three = links.mask[:, 0].sum(axis=1) == 3
        assert three.sum() > 50 and (~three).sum() > 50
        for f in ("slot", "log_weight", "nis", "extra_var"):
            np.testing.assert_array_equal(getattr(on, f)[~three], getattr(off, f)[~three])
            np.testing.assert_array_equal(getattr(zero, f), getattr(off, f))
        valid, _, _ = _select_prep_numpy(cov, links, pe, snr_c)
        n_cand = np.maximum(valid.sum(axis=-1), 1)
        same = three[:, None, None] & (on.slot == off.slot) & (off.slot >= 0)
        assert same.sum() > 100 and np.any(n_cand[same] > 1)
        np.testing.assert_allclose(on.log_weight[same] - off.log_weight[same],
                                   np.log(n_cand[same]), rtol=0, atol=1e-12)
        assert not np.any(three[:, None, None] & (off.slot >= 0) & (on.slot < 0))


def test_kernel_equals_reference_with_the_setting():
    """The compiled selection with the setting gives its numpy reference's slots, log-weights,
    NIS and variances bit for bit (three- and four-range nodes in one call)."""
    cov, links, pe, snr_c = _case(3)
    cfg = TrackerConfig(mechanism_prior_min_links=4)
    got, ref = select(cov, links, pe, cfg, snr_c), _select_numpy(cov, links, pe, cfg, snr_c)
    for f in ("slot", "log_weight", "nis", "extra_var"):
        np.testing.assert_array_equal(getattr(got, f), getattr(ref, f), err_msg=f)


def test_config_records_the_setting():
    """The setting is a recorded TrackerConfig field, 0 (off) by default."""
    assert TrackerConfig().mechanism_prior_min_links == 0
    assert "mechanism_prior_min_links" in {f.name for f in dataclasses.fields(TrackerConfig)}
