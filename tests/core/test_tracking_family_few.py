"""``TrackerConfig.family_few_links``: a node with at most that many ranges gets the extra
families on every fitted link (as ``family_select``, no minority rule), each scored with its
SNR there (as ``family_snr``); nodes with more ranges keep the other settings' gate and
scoring (docs/tracking_evidence.md "Session 30").

* The gate (:func:`diffpos.tracking.tracker._family_gate`) on hand-made learned arrays
  (``nis_limit`` 9, one update with every link): at three ranges every link with a fit
  history, also of a hypothesis misfitting two of its three ranges (no minority rule), none
  without one; at four ranges (below ``family_min_links`` 5) and at two (fewer than
  ``min_anchors_tracking``) nothing, as with the setting off; off: nothing at three ranges.
* The families' weight (:func:`diffpos.tracking.families.family_log_weight`) at the static
  node of the paper building (floor 2), a link's range at its strongest extra family's length
  and a measured SNR 4 dB from that family's prediction: the three-range node's weight equals
  ``family_snr``'s (itself tested against the numpy emulator's family SNR in
  tests/core/test_tracking_family_snr.py) to 1e-12 and differs from the weight without SNR by
  more than 0.1 nats; the four-range node's equals the weight without SNR bit for bit.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from static_track import ANCHORS, NODE, SIGMA, B

from diffpos.channel.emulator import pair_family_snr_db
from diffpos.paths.model import graded_paths
from diffpos.scenario import default_scenario
from diffpos.tracking.families import extra_families, family_log_weight
from diffpos.tracking.links import Links
from diffpos.tracking.model import SNR_SIGMA_DB, SNR_SPAN_DB
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import _family_gate

RADIO = default_scenario().radio
#: one node, two hypotheses, four link columns (the last absent at three ranges); NIS of the
#: last real update (inf: called an outlier)
FIT = np.array([[[20.0, 1.0, 1.0, 1.0],
                 [np.inf, 30.0, 1.0, 1.0]]])
COL = np.arange(4)[None]


def _gate(n_meas, history=None, **kw):
    kw = {"family_worst_min_links": 0, **kw}  # the worst-link gate (default 4) apart
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_history=1, **kw)
    seen = np.ones(FIT.shape) if history is None else history
    lk = {"link_fit": FIT, "link_all": seen, "link_out": np.zeros(FIT.shape)}
    present = np.array([[True] * n_meas + [False] * (4 - n_meas)])
    return _family_gate(lk, COL, np.array([n_meas]), cfg, present)


def test_gate_at_few_ranges_only():
    assert TrackerConfig().family_few_links == 3  # default since 2026-12-08
    g = _gate(3, family_few_links=3)
    assert g.all()  # every fitted link, the minority rule off (hypothesis 1 misfits 2 of 3)
    unseen = np.ones(FIT.shape)
    unseen[..., 1] = 0.0  # a link not fitted yet is not offered
    g = _gate(3, unseen, family_few_links=3)
    assert not g[..., 1].any() and g[..., [0, 2, 3]].all()
    assert not _gate(3, family_few_links=0).any()  # off: family_min_links 5
    assert np.array_equal(_gate(4, family_few_links=3), _gate(4, family_few_links=0))
    assert not _gate(4, family_few_links=3).any()
    # two ranges do not fix a position (min_anchors_tracking 3): nothing
    assert not _gate(2, family_few_links=3).any()


def test_few_range_nodes_score_the_families_with_their_snr():
    a, n = ANCHORS[0], NODE
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_weight="mechanism",
                              family_snr=False, family_few_links=3)
    mset, _ = extra_families(3)
    g = graded_paths(n[None], a[None], B, relax_m=cfg.exist_margin_m, floor=np.array([2]),
                     mechanisms=mset)
    pred = pair_family_snr_db(a[None], n[None], building=B, radio=RADIO, max_order=3)[0]
    ok = g.loose[0, 18:] & np.isfinite(g.length_m[0, 18:]) & np.isfinite(pred)
    assert ok.sum() >= 2
    k = int(np.argmax(np.where(ok, pred, -np.inf)))
    rho, snr = float(g.length_m[0, 18 + k]), float(pred[k] + 4.0)
    # row 0: three ranges (the fourth absent), row 1: four ranges; the same first link
    mask = np.array([[True, True, True, False], [True, True, True, True]])
    links = Links.from_arrays(np.stack([np.stack([a] * 4)] * 2), np.full((2, 4), rho),
                              np.full((2, 4), SIGMA), mask, cfg.sigma_model_m,
                              snr_db=np.full((2, 4), snr), radio=RADIO)

    def weights(c):
        return family_log_weight(np.stack([n, n]), np.zeros((2, 3, 3)), links,
                                 np.array([0, 1]), np.array([2, 2]),
                                 np.ones((2, 4), bool), B, c, snr_sigma_db=SNR_SIGMA_DB,
                                 snr_span_db=SNR_SPAN_DB)

    w = weights(cfg)
    w_snr = weights(dataclasses.replace(cfg, family_snr=True, family_few_links=0))
    w_off = weights(dataclasses.replace(cfg, family_few_links=0))
    assert np.allclose(w[0, :3], w_snr[0, :3], atol=1e-12, rtol=0)
    assert np.all(np.abs(w[0, :3] - w_off[0, :3]) > 0.1)
    assert np.array_equal(w[1], w_off[1])
    assert not np.array_equal(w_snr[1], w_off[1])
