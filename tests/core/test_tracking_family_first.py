"""A higher-order family explains a link only where it can be the first arrival
(``TrackerConfig.family_first``, off by default; :func:`diffpos.tracking.families.first_arrival_log_prob`).

Under a hypothesis' position a family path is the first arrival only if none of the 18
mechanisms that is shorter was detected: each such mechanism is missed with probability
``Phi((T - S_j) / sigma)`` (its SNR ``S_j`` predicted by the emulator's amplitude model, the
link's detector threshold ``T``). Reference: a plain loop over the mechanisms with
``scipy.stats.norm`` (and its cap: ``snr_cost_cap_nats``); and the weight with ``family_first`` off (or without a radio model)
is the family term as before, bit for bit.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.stats import norm

from diffpos.channel.emulator import pair_snr_db
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.paths.model import graded_paths
from diffpos.scenario import default_scenario
from diffpos.tracking.families import extra_families, family_log_weight, first_arrival_log_prob
from diffpos.tracking.links import Links
from diffpos.tracking.model import SNR_SIGMA_DB
from diffpos.tracking.state import TrackerConfig

SCEN = default_scenario()
B, RADIO = SCEN.building, SCEN.radio
#: (anchor, node) pairs on floor 2 of the paper building: UAVs in front of and below the
#: window band, nodes near and far from the facade. The second: the UAV level with the window
#: 3 m in front of it, the node 15 m inside (a strong direct path, shorter than every family);
#: the third: a UAV below the band, every mechanism shorter than the shortest family weak
ZF = B.floor_z_m(2)
PAIRS = [(np.array([0.0, -7.0, 4.0]), np.array([0.0, 12.0, ZF + 1.5])),
         (np.array([0.0, -3.0, ZF + 1.5]), np.array([0.0, 12.0, ZF + 1.5])),
         (np.array([4.0, -8.0, 1.0]), np.array([-3.0, 3.0, ZF + 1.2])),
         (np.array([15.0, -20.0, 1.0]), np.array([2.0, 9.0, ZF + 1.6]))]


def _lengths(anchor, node):
    mset, _ = extra_families(3)
    g = graded_paths(node[None], anchor[None], B, relax_m=TrackerConfig().exist_margin_m,
                     floor=np.array([2]), mechanisms=mset)
    return g.length_m[0], g.loose[0] & np.isfinite(g.length_m[0])


def test_first_arrival_probability_against_a_loop():
    """Every pair's and family's log-probability equals the loop's product over the shorter
    (by more than 3 sigma) mechanisms that carry power of ``norm.sf((S_j - T) / sigma)``
    (1e-9 nats); a family shorter than every powered mechanism gets 0."""
    nb = len(MECHANISMS)
    sigma = 0.05
    for anchor, node in PAIRS:
        length, _ = _lengths(anchor, node)
        got = first_arrival_log_prob(node[None], anchor[None], length[None],
                                     np.array([sigma]), B, RADIO, SNR_SIGMA_DB)[0]
        s = pair_snr_db(anchor[None, None, :], node[None], building=B, radio=RADIO)[0, 0]
        thr = max(np.max(s[np.isfinite(s)]) - RADIO.fap_threshold_db, RADIO.detection_snr_db)
        for k in range(nb, length.size):
            want = 0.0
            for j in range(nb):
                if np.isfinite(s[j]) and np.isfinite(length[j]) and \
                        length[j] < length[k] - 3 * sigma:
                    want += np.log(norm.sf((s[j] - thr) / SNR_SIGMA_DB))
            if not np.isfinite(length[k]):
                continue
            assert abs(got[k - nb] - want) < 1e-9, (anchor, node, k, got[k - nb], want)
        capped = first_arrival_log_prob(node[None], anchor[None], length[None],
                                        np.array([sigma]), B, RADIO, SNR_SIGMA_DB, 4.5)[0]
        assert np.array_equal(capped, np.maximum(got, -4.5))


def _weights(anchor, node, cfg, radio):
    """:func:`family_log_weight` of one link whose range is the shortest existing family's
    length (a point position)."""
    nb = len(MECHANISMS)
    length, ok = _lengths(anchor, node)
    fam = np.where(ok[nb:], length[nb:], np.inf)
    rho = np.array([[fam.min()]])
    links = Links.from_arrays(anchor[None, None], rho, np.full((1, 1), 0.05),
                              np.ones((1, 1), bool), 0.0,
                              snr_db=None if radio is None else np.full((1, 1), 20.0),
                              radio=radio)
    return family_log_weight(node[None], np.zeros((1, 3, 3)), links, np.array([0]),
                             np.array([2]), np.ones((1, 1), bool), B, cfg,
                             snr_sigma_db=SNR_SIGMA_DB)[0, 0]


def test_a_family_behind_a_strong_shorter_path_keeps_only_the_capped_share():
    """The UAV level with the window in front of the node: the direct path through the
    window is far above the detector's threshold and shorter than every family, so with
    ``family_first`` a range at a family's length gains from the family only
    ``exp(-snr_cost_cap_nats)`` of what it gains without it (0.01 nats), nearly nothing
    without the cap (< 0.01 nats); without ``family_first`` (or without a radio model) it
    gains > 5 nats."""
    anchor, node = PAIRS[1]
    cfg = dataclasses.replace(TrackerConfig(), family_first=True, max_order=3, family_few_links=0)
    assert cfg.max_order == 3 and cfg.snr_cost_cap_nats > 0
    on = _weights(anchor, node, cfg, RADIO)
    uncapped = _weights(anchor, node, dataclasses.replace(cfg, snr_cost_cap_nats=0.0), RADIO)
    off = _weights(anchor, node, dataclasses.replace(cfg, family_first=False), RADIO)
    no_radio = _weights(anchor, node, cfg, None)
    assert off > 5.0, off
    assert no_radio == off
    assert abs(on - np.log1p(np.expm1(off) * np.exp(-cfg.snr_cost_cap_nats))) < 0.01, (on, off)
    assert 0.0 <= uncapped < 0.01, uncapped


def test_a_family_with_no_detectable_shorter_path_is_unchanged():
    """Where every mechanism shorter than the families is far below the threshold (or none
    is shorter), ``family_first`` changes the family term by less than 1 %."""
    found = 0
    for anchor, node in PAIRS:
        length, ok = _lengths(anchor, node)
        lp = first_arrival_log_prob(node[None], anchor[None], length[None], np.array([0.05]),
                                    B, RADIO, SNR_SIGMA_DB)[0]
        nb = len(MECHANISMS)
        k = int(np.argmin(np.where(ok[nb:], length[nb:], np.inf)))
        if lp[k] > -0.01:
            found += 1
            cfg = dataclasses.replace(TrackerConfig(), family_first=True, max_order=3, family_few_links=0)
            on = _weights(anchor, node, cfg, RADIO)
            off = _weights(anchor, node, dataclasses.replace(cfg, family_first=False), RADIO)
            assert off > 1.0 and abs(on - off) < 0.01 * off, (anchor, node, on, off)
    assert found >= 1
