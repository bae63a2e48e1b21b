"""Other modes of a hypothesis' posterior (``TrackerConfig.mode_search_outliers``; issue 34,
docs/tracking_evidence.md "Session 23: other modes of a hypothesis").

* :func:`diffpos.tracking.tracker._reprior` carries a Laplace fit made under one Gaussian
  prior to another in closed form: for a linear-Gaussian likelihood it must equal the
  marginal likelihood and the posterior computed directly under the new prior (the textbook
  formulas ``N(y; H x0, H P0 H' + R)`` and the Kalman update, independent of the tracker).
* The lost mode: a node of the paper building tracked from the emulator's channel (ranges and
  SNR, fixed seeds) whose true floor's tracks are moved 0.85 m off (both modes), where the
  mechanisms of two links no longer exist at the prior: without the search that floor calls
  links outliers and the published floor is lost for several epochs at p_true < 1e-3; with
  it the floor stays published in every epoch (the reference: the emulator's truth, the
  floor the node stands on).
* The new-misfit gate (``mode_search_new_misfit``): a link biased out of the path model from
  the first epoch on (Sionna's persistent out-of-model first arrivals) starts no search, the
  outputs identical to the search off; the same bias appearing on a link the tracks fitted (a
  first-arrival switch) starts one in that epoch; the moved track keeps its floor as with the
  ungated search.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking import tracker
from diffpos.tracking.state import TrackerConfig, floor_probabilities
from diffpos.tracking.tracker import _reprior, init_state, update

SC = default_scenario()
B, RADIO = SC.building, SC.radio
ANCHORS = np.asarray(SC.anchor_positions_m(0.0))
# the detector's skipped paths off (first_arrival_prior, default 0.8): with them one of the
# moved tracks keeps its floor without the search; here the search is tested alone
OFF = TrackerConfig(first_arrival_prior=0.0)
ON = dataclasses.replace(OFF, mode_search_outliers=1, mode_jump_sigma_m=1.0, mode_search_max=2)
GATED = dataclasses.replace(ON, mode_search_min_links=4, mode_search_new_misfit=0.1)


def _gauss_log(y, mean, cov):
    d = y - mean
    return -0.5 * (d @ np.linalg.solve(cov, d) + np.linalg.slogdet(2 * np.pi * cov)[1])


def test_reprior_equals_the_direct_evidence_and_posterior_of_a_linear_gaussian_model():
    rng = np.random.default_rng(7)
    n = 6
    for _ in range(20):
        h = rng.normal(size=(4, n))
        h[:, 3:] *= 0.1  # velocities weakly observed, as ranges leave them
        r = np.diag(rng.uniform(0.01, 0.2, 4))
        y = rng.normal(size=4) * 3

        def spd(scale):
            a = rng.normal(size=(n, n))
            return scale * (a @ a.T / n + np.eye(n))

        xs, cs = rng.normal(size=n) * 2, spd(4.0)  # the fit's broad prior
        x0, p0 = rng.normal(size=n) * 2, spd(0.3)  # the new prior
        # the fit under N(xs, cs): Kalman posterior and marginal likelihood
        s = h @ cs @ h.T + r
        k = cs @ h.T @ np.linalg.inv(s)
        x1, p1 = xs + k @ (y - h @ xs), cs - k @ h @ cs
        ev1 = _gauss_log(y, h @ xs, s)
        ev, xm, pm = _reprior(x1[None], p1[None], np.array([ev1]), xs[None], cs[None],
                              x0[None], p0[None])
        # directly under N(x0, p0)
        s0 = h @ p0 @ h.T + r
        k0 = p0 @ h.T @ np.linalg.inv(s0)
        np.testing.assert_allclose(ev[0], _gauss_log(y, h @ x0, s0), rtol=0, atol=1e-8)
        np.testing.assert_allclose(xm[0], x0 + k0 @ (y - h @ x0), rtol=0, atol=1e-8)
        np.testing.assert_allclose(pm[0], p0 - k0 @ h @ p0, rtol=0, atol=1e-8)


def _run(node, config, seed, offset, k0=30, epochs=60, drop=None, bias=None, searched=None):
    """Published floors and the true floor's probability of a static node tracked from the
    emulator's channel; at epoch ``k0`` its true floor's tracks (both modes) are moved by
    ``offset`` first (a track left in the wrong mode of its floor). ``bias`` (k_from, anchor,
    metres): that anchor's range is longer by that much from epoch k_from on; ``searched``: a
    list that gets the number of hypotheses mode-searched in every epoch."""
    rng = np.random.default_rng(seed)
    channel = emulate_channel(ANCHORS, node[None], building=B, radio=RADIO)
    f, nf = int(B.floor_index(node[2])), B.n_floors
    state = init_state(1, B)
    floors, p_true = [], []
    for k in range(epochs):
        if k == k0:
            mean = state.mean.copy()
            mean[0, [f, f + nf], :3] += offset
            state = dataclasses.replace(state, mean=mean)
        fa = first_arrival(channel, radio=RADIO, rng=rng)
        det = fa.detected.copy()
        if drop is not None:  # an anchor never heard: the node's other ranges only
            det[..., drop] = False
        rho = fa.range_m.copy()
        if bias is not None and k >= bias[0]:  # a first arrival out of the path model
            rho[..., bias[1]] += bias[2]
        n_before = len(_SEARCHES)
        state, out = update(state, ANCHORS[None], rho, fa.sigma_m, det,
                            10**9 + k * 10**8, B, config, snr_db=fa.snr_db, radio=RADIO)
        if searched is not None:
            searched.append(sum(_SEARCHES[n_before:]))
        if k >= k0:
            floors.append(int(out.floor_index[0]))
            p_true.append(float(floor_probabilities(state.log_prob)[0, f]))
    return f, np.array(floors), np.array(p_true)


@pytest.mark.parametrize("node", [(10.0, 6.12, 14.5), (0.0, 12.0, 11.5)])
@pytest.mark.parametrize("seed", [1, 2])
def test_a_track_moved_off_its_mode_keeps_its_floor_with_the_mode_search(node, seed):
    node = np.array(node)
    offset = np.array([0.6, 0.6, 0.0])
    f, before, p_before = _run(node, OFF, seed, offset)
    assert np.sum(before != f) >= 5 and p_before.min() < 1e-3  # lost without the search
    f, after, p_after = _run(node, ON, seed, offset)
    assert np.all(after == f), after
    assert p_after.min() > 0.3, p_after.min()  # (measured 0.53-1.00; before < 1e-8)


_SEARCHES: list[int] = []  # hypotheses searched per call of the search's local grid


@pytest.fixture
def count_searches(monkeypatch):
    """Count the hypotheses the mode search runs its local grid for."""
    grid = tracker.local_starts

    def counted(links, *args, **kwargs):
        _SEARCHES.append(links.rho.shape[0])
        return grid(links, *args, **kwargs)

    monkeypatch.setattr(tracker, "local_starts", counted)
    _SEARCHES.clear()
    yield
    _SEARCHES.clear()


@pytest.mark.parametrize("seed", [1, 2])
def test_a_link_biased_all_along_starts_no_search_but_a_new_bias_does(seed, count_searches):
    node = np.array([10.0, 6.12, 14.5])
    bias = (0, 0, 2.0)  # anchor 0's first arrival 2 m beyond the model from the first epoch
    ungated = []
    _run(node, ON, seed, np.zeros(3), bias=bias, searched=ungated)
    assert sum(ungated) >= 40  # without the gate: searched every epoch once TRACKING
    gated = []
    off = _run(node, OFF, seed, np.zeros(3), bias=bias)
    on = _run(node, GATED, seed, np.zeros(3), bias=bias, searched=gated)
    assert sum(gated) == 0
    assert np.array_equal(off[1], on[1]) and np.array_equal(off[2], on[2])
    switch = []  # the same bias from epoch 30 on a link the tracks fitted: a switch
    _run(node, GATED, seed, np.zeros(3), bias=(30, 0, 2.0), searched=switch)
    assert sum(switch[:30]) == 0 and switch[30] > 0, switch


@pytest.mark.parametrize("seed", [1, 2])
def test_the_gated_search_keeps_a_moved_track_on_its_floor(seed):
    node = np.array([10.0, 6.12, 14.5])
    f, after, p_after = _run(node, GATED, seed, np.array([0.6, 0.6, 0.0]))
    assert np.all(after == f), after
    assert p_after.min() > 0.3, p_after.min()


def test_off_by_default_and_identical_when_off():
    assert OFF.mode_search_outliers == 0 and OFF.mode_search_new_misfit == 0.0
    node = np.array([10.0, 6.12, 14.5])
    a = _run(node, OFF, 3, np.zeros(3), epochs=40)
    b = _run(node, dataclasses.replace(OFF, mode_jump_sigma_m=0.3, mode_jump_rate_hz=0.1,
                                       mode_search_max=1),
             3, np.zeros(3), epochs=40)
    assert np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])


def test_three_ranges_are_not_searched_with_mode_search_min_links_4():
    """With three ranges a position fits them on any floor: ``mode_search_min_links`` 4 leaves
    such a node exactly as without the search, while the search does run there at 0."""
    node = np.array([10.0, 6.12, 14.5])
    offset = np.array([0.6, 0.6, 0.0])
    off = _run(node, OFF, 1, offset, epochs=45, drop=3)
    m4 = _run(node, dataclasses.replace(ON, mode_search_min_links=4), 1, offset, epochs=45,
              drop=3)
    on = _run(node, ON, 1, offset, epochs=45, drop=3)
    assert np.array_equal(off[1], m4[1]) and np.array_equal(off[2], m4[2])
    assert not np.array_equal(off[2], on[2])  # the search changed something at 0
