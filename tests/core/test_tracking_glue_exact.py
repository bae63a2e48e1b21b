"""Four exact rewrites of the tracker's numpy glue (issue 37; docs/replay_speed.md "Session 32")
against the expressions they replace, bit for bit (tolerance 0), on random inputs with fixed
seeds:

* :func:`diffpos.tracking.evidence._gather` (one flat index) against ``np.take_along_axis``
  (:func:`diffpos.tracking.evidence._gather_numpy`), with columns that have no link (-1),
  NaN entries, a non-contiguous input and a (n, H, L) of one hypothesis;
* :func:`diffpos.tracking.evidence._distances` (one coordinate plane at a time) against
  ``np.sqrt(np.sum((tab[:, None] - anc[:, :, None]) ** 2, axis=-1))``, with free (NaN) links;
* :func:`diffpos.tracking.model.diffraction_slack` (the rows of the nodes with few ranges
  only) against the whole-array expression it replaced, for ``snr_slack_max_links`` 3 (some
  nodes, none) and 0 (every node), with non-finite costs, predictions and SNRs; it fails with
  a row of a node with many ranges slackened;
* :func:`diffpos.tracking.tracker._publish` with ``cov_kept_only`` (the covariance only of
  the rows ``_published_floor_cov`` keeps) then ``_published_floor_cov``: every field equal
  to the covariance computed for every row first; ``mixture_mse_cov`` of a subset of the
  nodes equal to those rows of the call on all.

And :func:`diffpos.channel.emulator._params_for` returns the same constants for the same
objects again and for an equal but distinct building (the identity shortcut never serves
another building's constants).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import diffpos.tracking.model as tm
from diffpos.channel import emulator
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.scenario import Building, Radio
from diffpos.tracking.evidence import _distances, _gather, _gather_numpy
from diffpos.tracking.state import (
    TrackerConfig,
    TrackerState,
    TrackStatus,
    few_ranges,
    mixture_mse_cov,
)
from diffpos.tracking.tracker import _publish, _published_floor_cov, init_state


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and bool(
        np.all(a.view(np.uint64) == b.view(np.uint64)))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("shape", [(50, 10, 16, 8), (7, 1, 5, 3), (1, 4, 2, 6)])
def test_gather_equals_take_along_axis(seed, shape):
    rng = np.random.default_rng(seed)
    n, h, n_l, m = shape
    a = rng.normal(size=(n, h, n_l))
    a[rng.random(a.shape) < 0.2] = np.nan
    col = rng.integers(-1, n_l, size=(n, m))
    col[0, 0], col[-1, -1] = -1, n_l - 1  # a column without a link, the table's last link
    assert _same_bits(_gather(a, col), _gather_numpy(a, col))
    wide = rng.normal(size=(n, h, 2 * n_l))[:, :, ::2]  # not C-contiguous
    assert _same_bits(_gather(wide, col), _gather_numpy(wide, col))
    ints = rng.integers(0, 1000, size=(n, h, n_l))  # an integer table: float out, NaN holes
    assert _same_bits(_gather(ints, col), _gather_numpy(ints, col))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_distances_equal_numpy_sum(seed):
    rng = np.random.default_rng(seed)
    tab = rng.normal(size=(40, 16, 3)) * rng.uniform(0.1, 100.0)
    tab[rng.random((40, 16)) < 0.3] = np.nan  # free links
    anc = rng.normal(size=(40, 8, 3)) * 30.0
    with np.errstate(invalid="ignore"):
        ref = np.sqrt(np.sum((tab[:, None] - anc[:, :, None]) ** 2, axis=-1))
    assert _same_bits(_distances(tab, anc), ref)


def _slack_reference(cost, pred, thr, snr, mask, config):
    """diffraction_slack as it was (every row evaluated), on copies."""
    cost = cost.copy()
    d, sig = float(config.snr_diffraction_slack_db), float(tm.SNR_SIGMA_DB)
    meas = snr[:, None, :, None]
    use = tm._IS_DIFF & np.isfinite(cost) & np.isfinite(pred) & np.isfinite(meas)
    use = use & few_ranges(np.sum(mask, axis=-1), int(config.snr_slack_max_links))[
        :, None, None, None]
    if not use.any():
        return cost
    with np.errstate(invalid="ignore"):
        r = meas - pred
        r = np.where(r > d, r - d, np.minimum(r, 0.0))
        short = np.maximum(thr[..., None] - sig - meas, 0.0)
        g = 0.5 * (r / sig) ** 2 + 0.5 * (short / sig) ** 2
    if config.snr_cost_cap_nats > 0:
        g = np.minimum(g, float(config.snr_cost_cap_nats))
    g = g + float(np.log1p(d / (sig * np.sqrt(2.0 * np.pi))))
    cost[use] = g[use]
    return cost


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("max_links", [3, 0])
@pytest.mark.parametrize("few_nodes", [True, False])
def test_diffraction_slack_rows_equal_whole_array(seed, max_links, few_nodes):
    rng = np.random.default_rng(seed)
    n, h, m, k = 30, 6, 8, len(MECHANISMS)
    cost = rng.uniform(0.0, 8.0, size=(n, h, m, k))
    cost[rng.random(cost.shape) < 0.1] = np.inf
    pred = rng.normal(10.0, 15.0, size=(n, h, m, k))
    pred[rng.random(pred.shape) < 0.1] = -np.inf
    thr = rng.normal(0.0, 5.0, size=(n, h, m))
    snr = rng.normal(12.0, 10.0, size=(n, m))
    snr[rng.random(snr.shape) < 0.1] = np.nan
    mask = rng.random((n, m)) < (0.3 if few_nodes else 0.95)
    if not few_nodes:
        mask[:, :4] = True  # at least four ranges everywhere: no node with three or fewer
    cfg = TrackerConfig(snr_diffraction_slack_db=6.0, snr_slack_max_links=max_links,
                        snr_cost_cap_nats=4.5)
    ref = _slack_reference(cost, pred, thr, snr, mask, cfg)
    out = tm.diffraction_slack(cost.copy(), pred, thr, snr, mask, cfg)
    assert _same_bits(out, ref)
    if max_links == 0 or few_nodes:  # the setting does something here
        assert not _same_bits(ref, cost)
    if few_nodes and max_links == 3:  # a node with many ranges slackened as well: not equal
        many = np.flatnonzero(mask.sum(axis=-1) > 3)
        wrong = out.copy()
        wrong[many] = tm.diffraction_slack(cost[many].copy(), pred[many], thr[many], snr[many],
                                           np.ones((many.size, m), bool),
                                           dataclasses.replace(cfg, snr_slack_max_links=0))
        assert not _same_bits(wrong, ref)


def test_params_for_same_objects_and_equal_buildings():
    b, r = Building(), Radio()
    p1 = emulator._params_for(b, r)
    assert emulator._params_for(b, r) is p1  # the same objects: the same constants
    other = dataclasses.replace(b, floor_height_m=b.floor_height_m + 0.5)
    p2 = emulator._params_for(other, r)
    assert not np.array_equal(p2[0], p1[0])  # another building: its own constants
    p3 = emulator._params_for(b, r)
    for x, y in zip(p3, emulator._params(b, r), strict=True):
        assert _same_bits(np.asarray(x, dtype=np.complex128).view(np.float64),
                          np.asarray(y, dtype=np.complex128).view(np.float64))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("which", ["credible", "all"])
def test_publish_covariance_of_kept_rows_only(seed, which):
    """``_publish(cov_kept_only=True)`` then ``_published_floor_cov``: every published field
    bit for bit that of the covariance computed for every row first, on 40 random nodes of
    which some have no position (UNINITIALISED / LOST), some a NaN log-probability (the rows
    whose covariance ``_published_floor_cov`` keeps: computed on their own) and the rest the
    rows it replaces; and the replaced rows are not computed (NaN before the replacement).
    The rows kept have no finite position here; that a subset of the nodes gets the same
    covariances as all of them: :func:`test_mixture_covariance_rows_on_their_own`."""
    rng = np.random.default_rng(seed)
    b = Building()
    n, h = 40, 2 * b.n_floors
    st = init_state(n, b)
    a = rng.normal(size=(n, h, 6, 6)) * 0.3
    lp = rng.normal(size=(n, h)) * 3.0
    lp[rng.random(n) < 0.2, 1] = np.nan
    status = rng.choice([TrackStatus.TRACKING, TrackStatus.COASTING, TrackStatus.INITIALISING,
                         TrackStatus.UNINITIALISED, TrackStatus.LOST], size=n).astype(np.int8)
    st = TrackerState(**{**st.__dict__, "mean": rng.normal(size=(n, h, 6)) * 5.0,
                         "cov": a @ np.swapaxes(a, -1, -2) + 0.01 * np.eye(6), "log_prob": lp,
                         "status": status, "nis": rng.uniform(0.5, 5.0, n)})
    mech, resid = rng.integers(-1, 18, size=(n, 8)), rng.normal(size=(n, 8))
    cfg = TrackerConfig(cov_published_floors=which)
    full = _publish(st, mech, resid, cfg)
    kept = _publish(st, mech, resid, cfg, cov_kept_only=True)
    replaced = np.isfinite(full.position_m).all(axis=1) & np.isfinite(
        full.floor_probabilities).all(axis=1)
    has = np.isin(status, [TrackStatus.TRACKING, TrackStatus.COASTING,
                           TrackStatus.INITIALISING])
    assert replaced.any() and (has & ~replaced).any() and (~has).any()
    assert np.isnan(kept.covariance_m2[replaced]).all()  # not computed
    assert _same_bits(kept.covariance_m2[~replaced], full.covariance_m2[~replaced])
    a_out, b_out = _published_floor_cov(st, full, which), _published_floor_cov(st, kept, which)
    for f in a_out.__dataclass_fields__:
        x, y = np.asarray(getattr(a_out, f)), np.asarray(getattr(b_out, f))
        assert x.dtype == y.dtype and np.array_equal(x.view(np.uint8), y.view(np.uint8)), f


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mixture_covariance_rows_on_their_own(seed):
    """``mixture_mse_cov`` of a subset of the nodes: those nodes' rows of the call on all of
    them, bit for bit (what ``_publish(cov_kept_only=True)`` relies on)."""
    rng = np.random.default_rng(seed)
    n, h = 60, 10
    a = rng.normal(size=(n, h, 6, 6)) * 0.3
    mean, cov = rng.normal(size=(n, h, 6)) * 5.0, a @ np.swapaxes(a, -1, -2)
    w = rng.dirichlet(np.ones(h), size=n)
    pos, best = rng.normal(size=(n, 3)) * 5.0, rng.integers(0, h // 2, n)
    p_best, vf = rng.uniform(0.2, 1.0, n), rng.uniform(1.0, 3.0, n)
    full = mixture_mse_cov(mean, cov, w, pos, best, p_best, vf)
    for sub in (rng.random(n) < 0.3, np.arange(n) == 7, np.arange(n) >= 1):
        part = mixture_mse_cov(mean[sub], cov[sub], w[sub], pos[sub], best[sub], p_best[sub],
                               vf[sub])
        assert _same_bits(part, full[sub])
