"""Learned link weights from given outlier counts, and their reference, for the tests of the
node-shared learned outlier weights (``link_eps_node``, ``link_eps_posterior``): the static
node of tests/core/static_track.py seen by three anchors, every hypothesis at the node; the
reference is the learned weight's Beta posterior mean computed from the counts
(``eps = clip((e0 S + out) / (S + all), e0, eps_max)``), a loop over nodes, hypotheses and
links; the static node tracked with one range 3 m long (a first arrival out of the model)
and the link inputs the tracker's update of an epoch uses."""

from __future__ import annotations

import numpy as np
from static_track import ANCHORS, NODE, SIGMA, first_arrivals, track

from diffpos.tracking.evidence import learned_weights
from diffpos.tracking.links import Links
from diffpos.tracking.model import SNR_SIGMA_DB, SNR_SPAN_DB
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import _link_inputs

FLOOR = 2
EXCESS_M = 3.0  # link 1's range: an unmodelled first arrival (1.5 m: a mechanism fits it)


def beta_eps(out, n_all, cfg):
    """The reference learned outlier weight from the counts (NaN counts: none learned)."""
    e0, s = cfg.outlier_weight, cfg.link_prior_updates
    eps = (e0 * s + np.nan_to_num(out)) / (s + np.nan_to_num(n_all))
    return min(max(eps, e0), max(cfg.link_outlier_max, e0))


def weights_from_counts(n_all, n_out):
    """The default config, the learned weights (n, H, L, 2) from the counts (n, H, L) (link 2
    of node 2 never learned) and the counts' reference eps (n, H, L)."""
    cfg = TrackerConfig()
    n, h, nl = n_all.shape
    lk = {"link_out": n_out.copy(), "link_all": n_all.copy(),
          "link_bias": np.full((n, h, nl), np.nan), "link_bias_var": np.full((n, h, nl), np.nan),
          "link_snr": np.full((n, h, nl), np.nan), "link_t_ns": np.zeros((n, h, nl), np.int64)}
    lk["link_out"][2, :, 2] = lk["link_all"][2, :, 2] = np.nan
    col = np.tile(np.arange(nl), (n, 1))
    links = Links(anchors=np.broadcast_to(ANCHORS[:nl], (n, 1, nl, 3)).copy(),
                  rho=np.full((n, 1, nl), 20.0), var=np.full((n, 1, nl), SIGMA**2),
                  mask=np.ones((n, 1, nl), bool), snr=np.full((n, 1, nl), 20.0))
    x = np.zeros((n, h, 6))
    x[..., :3] = NODE
    p = np.broadcast_to(np.eye(6) * 0.01, (n, h, 6, 6)).copy()
    w = learned_weights(lk, col, x, p, links, np.zeros(n, np.int64), cfg, SNR_SIGMA_DB,
                        SNR_SPAN_DB)
    ref = np.array([[[beta_eps(lk["link_out"][i, k, m], lk["link_all"][i, k, m], cfg)
                      for m in range(nl)] for k in range(h)] for i in range(n)])
    return cfg, w, ref


def long_link_states(cfg, seed=4, epochs=25):
    """The static node on ``FLOOR`` with link 1's range ``EXCESS_M`` long, tracked with
    ``cfg``: (the ranges, the states of every epoch)."""
    rho0 = first_arrivals(NODE, ANCHORS, FLOOR)
    rho0[1] += EXCESS_M
    return rho0, track(cfg, ANCHORS, rho0, epochs=epochs, seed=seed)


def link_inputs_at(state, rho0, k, cfg):
    """The link inputs the tracker's update of epoch ``k`` uses (its ``_link_inputs`` from the
    previous epoch's ``state``)."""
    n = len(ANCHORS)
    links = Links.from_arrays(ANCHORS[None], rho0[None], np.full((1, n), SIGMA),
                              np.ones((1, n), bool), cfg.sigma_model_m)
    t = np.array([10**9 + k * 10**8], np.int64)
    return _link_inputs(state, np.array([0]), links, t, state.mean, state.cov,
                        np.array([n]), cfg)
