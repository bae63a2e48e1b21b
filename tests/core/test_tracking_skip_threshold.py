"""The detector's threshold of the skipped-path term raised to the strongest closed-form family
(``TrackerConfig.skip_threshold_order``, ``skip_threshold_max_links``;
:func:`diffpos.tracking.model.family_threshold`).

* The tracker's SNR term (:func:`diffpos.tracking.model.snr_term`) with the setting, on the
  default building, anchors low beside and below the windows (strong slab series): at every
  present link of a node with three ranges it equals the skipped paths' numpy reference
  (:func:`diffpos.tracking.model.skip_cost`) fed the threshold ``max(T18, S_fam - fap)``,
  ``S_fam`` the strongest family beyond the 18 of the numpy emulator's own channel at order 3
  (:func:`diffpos.channel.emulator.emulate_channel` with ``channel_max_order`` 3, one call per
  hypothesis position: all its paths), 1e-9 nats; every slot of a node with four ranges is
  bit for bit the term without the setting; no cost rises (a higher threshold only makes a
  skipped path likelier); and the setting lowers some slot by more than 0.1 nats (fails with
  the tracker ignoring it).
* ``skip_threshold_max_links`` 0: the four-range nodes get it too (the same reference).
Fixed seeds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis_cases import random_hypotheses

import diffpos.tracking.model as tm
from diffpos.channel.emulator import emulate_channel, pair_snr_db
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.scenario import Radio
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.state import TrackerConfig

K18 = len(MECHANISMS)


def _case(seed: int):
    """12 nodes x 3 hypotheses on random floors of the default building, 4 anchors each low
    in front of the facade (0.3-4 m) so the slab series through the windows are strong; the
    first half of the nodes with three ranges. Measured SNRs around the strongest slot."""
    rng, b, pos, floor, anchors, mask = random_hypotheses(seed, anchor_top_m=4.0)
    n, m = mask.shape
    pred = pair_snr_db(anchors, pos[:, 0], building=b, radio=Radio())
    best = np.max(np.where(np.isfinite(pred), pred, -np.inf), axis=-1)
    snr = np.where(np.isfinite(best), best, 0.0) + rng.uniform(-25.0, 3.0, (n, m))
    rho = np.linalg.norm(pos[:, :1] - anchors, axis=-1) + 0.5
    links = Links.from_arrays(anchors, rho, np.full((n, m), 0.1), mask, 0.03, snr_db=snr,
                              radio=Radio())
    return b, pos, floor, links, mask


def _strongest_family(b, pos, anchors) -> np.ndarray:
    """(N, H, M) [dB]: the strongest path beyond the 18 of the numpy emulator's channel at
    order 3 (every MPC of every anchor at each hypothesis position), -inf where none."""
    radio3 = dataclasses.replace(Radio(), channel_max_order=3)
    n, h = pos.shape[:2]
    out = np.full((n, h, anchors.shape[1]), -np.inf)
    for i in range(n):
        for j in range(h):
            ch = emulate_channel(anchors[i], pos[i, j][None], building=b, radio=radio3)
            s = np.where(ch.valid[0, :, K18:], ch.snr_db[0, :, K18:], -np.inf)
            out[i, j] = np.max(s, axis=-1)
    return out


def _terms(seed: int, max_links: int):
    b, pos, floor, links, mask = _case(seed)
    base = TrackerConfig(snr_reuse_m=0.0, snr_reuse_anchor_m=0.0, first_arrival_prior=0.8)
    on = dataclasses.replace(base, skip_threshold_order=3, skip_threshold_max_links=max_links)
    relax = np.full(pos.shape[:2], 0.2)
    pe = all_paths(pos, links, floor, b, relax)
    pre = tm.snr_term(pos, links, floor, b, relax, pe,
                      dataclasses.replace(base, first_arrival_prior=0.0))
    c_off = tm.snr_term(pos, links, floor, b, relax, pe, base)
    c_on = tm.snr_term(pos, links, floor, b, relax, pe, on)
    pred = pair_snr_db(np.broadcast_to(links.anchors[:, 0][:, None], (*pos.shape[:2], 4, 3))
                       .reshape(-1, 4, 3), pos.reshape(-1, 3), building=b,
                       radio=Radio()).reshape(*pos.shape[:2], 4, -1)
    pred = np.where(pe.loose | tm.ALWAYS_PREDICTED, pred, -np.inf)
    _, thr = tm._snr_cost_thr(pos, links, b, trust=pe.sure)
    fam = _strongest_family(b, pos, links.anchors[:, 0])
    few = mask.sum(axis=-1) <= max_links if max_links > 0 else np.ones(len(mask), bool)
    use = (few[:, None] & mask)[:, None, :]
    thr_ref = np.where(use, np.fmax(thr, fam - Radio().fap_threshold_db), thr)
    ref = tm.skip_cost(pe, pred, thr_ref, links.snr[:, 0], pre.copy(), Radio(), 0.8)
    return c_off, c_on, ref, few, mask.sum(axis=-1) == 4


@pytest.mark.parametrize("seed", [0, 1])
def test_the_skipped_paths_read_the_strongest_family(seed):
    c_off, c_on, ref, few, _ = _terms(seed, 3)
    fin = np.isfinite(ref)
    assert np.array_equal(fin, np.isfinite(c_on))
    assert np.allclose(c_on[fin], ref[fin], atol=1e-9, rtol=0)
    assert np.array_equal(c_on[~few], c_off[~few], equal_nan=True)
    assert np.all(c_on[fin] <= c_off[fin] + 1e-12)
    assert np.max(c_off[fin] - c_on[fin]) > 0.1


def test_every_node_with_max_links_zero():
    c_off, c_on, ref, _, four = _terms(2, 0)
    fin = np.isfinite(ref)
    assert np.allclose(c_on[fin], ref[fin], atol=1e-9, rtol=0)
    f4 = fin & four[:, None, None, None]
    assert np.max(c_off[f4] - c_on[f4]) > 0.1
