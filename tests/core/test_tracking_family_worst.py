"""``TrackerConfig.family_worst_min_links`` / ``family_worst_nis``: at a node with that many
ranges but fewer than ``family_min_links`` the higher-order families are offered on ONE link
per hypothesis, its worst in-model link (:func:`diffpos.tracking.tracker._worst_link`).

Why (docs/channel_mix.md "Session 29"): on the emulator at ``channel_max_order`` 3 a 4-UAV
node on floor 2 whose first arrival from one UAV is the order-3 slab series
D(lower)-R(ceiling)-R(floor) is fitted at the true floor with a wrong one of the 18 (inside
``nis_limit``: never a misfit, never offered the exact family), while floor 3 explains all four
ranges with in-model mechanisms a floor up and 2 m nearer the facade: the mirror floor wins
every update (the README's main command at order 3, seed 6, r03: 87.7 % right floor).

References: the gate's definition written out as loops on hand-made learned arrays; the
emulator's own first arrivals (:func:`diffpos.channel.emulator.pair_first_arrival`, order 3,
noise-free) and the 18 mechanisms' lengths (:func:`diffpos.paths.model.first_arrival_paths`)
for the physical case.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from diffpos.channel.emulator import pair_first_arrival
from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import default_scenario
from diffpos.tracking.links import Links
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import _family_gate, _update_pairs

INF, NAN = np.inf, np.nan
#: five hypotheses of one node, four link columns; NIS of the last real update per link
#: (inf: called an outlier; NaN: never fitted); column 3 is absent in PRESENT_4
FIT = np.array([[[0.5, 3.0, 2.0, 0.1],      # worst in-model link 1
                 [INF, 0.5, 4.0, 0.2],      # an outlier (not this gate's) and link 2
                 [0.3, 0.2, 0.9, 0.1],      # every NIS below 1: none
                 [INF, 12.0, 0.5, 0.2],     # two misfits of four: the minority rule
                 [0.5, NAN, 2.0, 30.0]]])   # an unfitted link (a misfit) and an absent one
PRESENT_4 = np.array([[True, True, True, False]])
PRESENT = np.array([[True, True, True, True]])
COL = np.arange(4)[None]


def _gate(n_meas, present=PRESENT, history=None, **kw):
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_history=1,
                              family_min_links=5, family_learned_links=0, **kw)
    seen = np.ones(FIT.shape) if history is None else history
    lk = {"link_fit": FIT, "link_all": seen, "link_out": np.zeros(FIT.shape)}
    return _family_gate(lk, COL, np.array([n_meas]), cfg, present)


def _reference(n_meas, present, history, minority, k=4, nis=1.0, outliers=False):
    """The setting's links, loop by loop: per hypothesis the present link with the largest
    finite NIS (at least ``nis``, with a fit history); none where 2 x misfits >= ranges.
    ``outliers`` (``family_worst_outliers``): a link called an outlier (NIS inf) is the worst
    of all (the first such link in column order); an unfitted link (NaN) still never counts."""
    out = np.zeros(FIT.shape, bool)
    if not k <= n_meas < 5:
        return out
    for h in range(FIT.shape[1]):
        best, arg = -INF, None
        misfits = 0
        for j in range(FIT.shape[2]):
            if not present[0, j]:
                continue
            f = FIT[0, h, j]
            if history[0, h, j] >= 1 and not f <= 9.0:
                misfits += 1
            key = 1e308 if outliers and f == INF else f
            if np.isfinite(key) and key > best:
                best, arg = key, j
        if arg is None or best < nis or history[0, h, arg] < 1:
            continue
        if minority and 2 * misfits >= n_meas:
            continue
        out[0, h, arg] = True
    return out


def test_on_by_default_and_off_is_the_misfit_gate_alone():
    """Default 4 from session 30 (a history entry in the fusion's settings); 0: the gate is
    the misfit gate alone (no family for a four-range node here)."""
    assert TrackerConfig().family_worst_min_links == 4
    assert TrackerConfig().family_worst_nis == 1.0
    assert not _gate(4, family_worst_min_links=0).any()


def test_one_worst_in_model_link_per_hypothesis():
    """Four ranges: the loops' links exactly, with and without the minority rule, with an
    absent column, with a worst link that has no fit history (then none, not the next one)."""
    seen = np.ones(FIT.shape)
    for present in (PRESENT, PRESENT_4):
        for minority in (True, False):
            got = _gate(4, present, family_worst_min_links=4, family_minority=minority)
            ref = _reference(4, present, seen, minority)
            assert np.array_equal(got, ref), (present, minority, got, ref)
    got = _gate(4, PRESENT, family_worst_min_links=4)
    assert got[0, 0].tolist() == [False, True, False, False]
    assert got[0, 1].tolist() == [False, False, True, False]  # not the outlier link 0
    assert not got[0, 2].any() and not got[0, 3].any()
    assert not got[0, 4].any()  # link 3 present: 30 and the unfitted link 1 are 2 misfits
    assert _gate(4, PRESENT_4, family_worst_min_links=4)[0, 4].tolist() == [
        False, False, True, False]
    unfit = np.ones(FIT.shape)
    unfit[0, 0, 1] = 0.0
    got = _gate(4, PRESENT, unfit, family_worst_min_links=4)
    assert not got[0, 0].any()
    assert np.array_equal(got, _reference(4, PRESENT, unfit, True))
    got = _gate(4, PRESENT, family_worst_min_links=4, family_worst_nis=2.5)
    assert np.array_equal(got, _reference(4, PRESENT, seen, True, nis=2.5))
    assert got[0, 0, 1] and got[0, 1, 2] and got.sum() == 2


def test_other_range_counts_unchanged():
    """Three ranges (below the setting) and five (the misfit gate's ``family_min_links``):
    exactly the gate without the setting."""
    for n in (3, 5, 6):
        assert np.array_equal(_gate(n, family_worst_min_links=4), _gate(n)), n


def test_the_true_floor_wins_with_the_family_of_its_worst_link():
    """The physical case (main command at order 3, seed 6, r03; anchors of the paper
    scenario's four UAVs): a node on floor 2, the emulator's noise-free order-3 first
    arrivals and SNRs. Link 2's true first arrival is none of the 18 (>= 0.3 m from every one
    of their lengths at the truth). One measurement update of floor 2's level hypothesis at
    the truth and floor 3's at the mirror point the tracker held (+0.05, -1.97, +2.42 m):
    without families floor 3's evidence is the larger (by > 2 nats); the setting's gate
    offers the families on link 2 of floor 2 only; with it floor 2's is the larger (> 2)."""
    sc = default_scenario()
    b = sc.building
    radio = dataclasses.replace(sc.radio, channel_max_order=3)
    anchors = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                        [15.0, -20.0, 1.0]])
    nf = b.n_floors
    cfg0 = dataclasses.replace(TrackerConfig(), max_order=3, family_worst_min_links=0)
    cfg = dataclasses.replace(cfg0, family_worst_min_links=4)
    for x in (6.3, 10.52):
        node = np.array([x, 8.41, 11.5])
        rho, sig, snr, true, det = pair_first_arrival(anchors, np.repeat(node[None], 4, 0),
                                                      building=b, radio=radio)
        assert det.all()
        ps = first_arrival_paths(np.broadcast_to(node, (4, 3)), anchors, b, floor=2)
        off = np.nanmin(np.abs(np.where(ps.valid, ps.length_m, np.nan) - true[:, None]), -1)
        assert off[2] > 0.3 and np.all(off[[0, 1, 3]] < 1e-6), off
        links = Links.from_arrays(anchors[None], rho[None], sig[None], det[None],
                                  cfg0.sigma_model_m, snr[None], radio)
        mean = np.zeros((1, 2 * nf, 6))
        mean[0, :, :3] = node
        mean[0, 3, :3] = node + np.array([0.05, -1.97, 2.42])
        cov = np.broadcast_to(np.diag([0.04, 0.04, 0.01, 0.01, 0.01, 0.01]),
                              (1, 2 * nf, 6, 6)).copy()
        rr, cc = np.array([0, 0]), np.array([2, 3])
        none = np.zeros((1, 2 * nf, 4), bool)
        _, _, ev, slot, nis, *_ = _update_pairs(mean, cov, links, rr, cc, nf, b, cfg0,
                                                fam_gate=none)
        assert ev[1] - ev[0] > 2.0, ev
        assert np.all(slot >= 0)  # every link in the model at both floors
        fit = np.full((1, 2 * nf, 4), NAN)
        fit[0, 2], fit[0, 3] = nis[0], nis[1]
        lk = {"link_fit": fit, "link_all": np.ones(fit.shape), "link_out": np.zeros(fit.shape)}
        gate = _family_gate(lk, COL, np.array([4]), cfg, det[None])
        assert gate[0, 2].tolist() == [False, False, True, False], gate[0, 2]
        assert not np.any(np.delete(gate[0], 2, axis=0))
        assert not _family_gate(lk, COL, np.array([4]), cfg0, det[None]).any()
        _, _, ev2, slot2, *_ = _update_pairs(mean, cov, links, rr, cc, nf, b, cfg,
                                             fam_gate=gate)
        assert ev2[0] - ev2[1] > 2.0, ev2
        assert slot2[0, 2] == -1 and np.all(slot2[0, [0, 1, 3]] >= 0)


def test_worst_outliers_takes_the_outlier_link():
    """``family_worst_outliers``: the loops' links exactly (with and without the minority
    rule, an absent column, a nis floor); hypothesis 1's outlier link 0 instead of its worst
    in-model link 2; hypothesis 3 (an outlier and a misfit of four) still none with the
    minority rule; off by default and the gate of the setting's off state unchanged."""
    assert TrackerConfig().family_worst_outliers is False
    seen = np.ones(FIT.shape)
    for present in (PRESENT, PRESENT_4):
        for minority in (True, False):
            for nis in (1.0, 2.5):
                got = _gate(4, present, family_worst_min_links=4, family_minority=minority,
                            family_worst_nis=nis, family_worst_outliers=True)
                ref = _reference(4, present, seen, minority, nis=nis, outliers=True)
                assert np.array_equal(got, ref), (present, minority, nis, got, ref)
    got = _gate(4, PRESENT, family_worst_min_links=4, family_worst_outliers=True)
    assert got[0, 1].tolist() == [True, False, False, False]
    assert got[0, 0].tolist() == [False, True, False, False]
    assert not got[0, 3].any()
    got = _gate(4, PRESENT, family_worst_min_links=4, family_minority=False,
                family_worst_outliers=True)
    assert got[0, 3].tolist() == [True, False, False, False]
    for n in (3, 5, 6):  # the setting acts only where the worst-link gate does
        assert np.array_equal(_gate(n, family_worst_outliers=True), _gate(n)), n
    assert np.array_equal(_gate(4, family_worst_min_links=0, family_worst_outliers=True),
                          _gate(4, family_worst_min_links=0))


def test_worst_outlier_family_explains_the_true_floors_outlier():
    """The physical case of ``family_worst_outliers`` (the paper scenario's four UAVs, the
    emulator at order 3, noise-free): a node on floor 3 whose first arrival from UAV 2 is
    none of the 18 (>= 2 m from every one of their lengths at the truth; the others exact).
    Floor 3's level hypothesis at the truth calls that link an outlier. Without the setting
    the worst-link gate offers the families on a fitted link, not on link 1; with it on link 1
    only, and the update's evidence at the truth rises by > 2 nats with the link still out of
    the IEKF (slot -1) and the other slots unchanged; with link 1's range 1.5 m longer (no
    family's length) the same gate gains less than half of that (the family explains the
    range it predicts, not any outlier)."""
    sc = default_scenario()
    b = sc.building
    radio = dataclasses.replace(sc.radio, channel_max_order=3)
    anchors = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                        [15.0, -20.0, 1.0]])
    nf, f = b.n_floors, 3
    node = np.array([-6.16, 9.03, 14.5])
    rho, sig, snr, true, det = pair_first_arrival(anchors, np.repeat(node[None], 4, 0),
                                                  building=b, radio=radio)
    assert det.all()
    ps = first_arrival_paths(np.broadcast_to(node, (4, 3)), anchors, b, floor=f)
    off = np.nanmin(np.abs(np.where(ps.valid, ps.length_m, np.nan) - true[:, None]), -1)
    assert off[1] > 2.0 and np.all(off[[0, 2, 3]] < 1e-6), off
    cfg0 = dataclasses.replace(TrackerConfig(), max_order=3, family_worst_min_links=4)
    cfg = dataclasses.replace(cfg0, family_worst_outliers=True)
    cov = np.broadcast_to(np.diag([0.04, 0.04, 0.01, 0.01, 0.01, 0.01]),
                          (1, 2 * nf, 6, 6)).copy()
    none = np.zeros((1, 2 * nf, 4), bool)
    rr, cc = np.array([0]), np.array([f])
    mean = np.zeros((1, 2 * nf, 6))
    mean[0, :, :3] = node
    gains = []
    for shift in (0.0, 1.5):
        r = rho + np.array([0.0, shift, 0.0, 0.0])
        links = Links.from_arrays(anchors[None], r[None], sig[None], det[None],
                                  cfg0.sigma_model_m, snr[None], radio)
        _, _, ev, slot, nis, *_ = _update_pairs(mean, cov, links, rr, cc, nf, b, cfg0,
                                                fam_gate=none)
        if shift == 0.0:
            assert slot[0, 1] == -1 and np.all(slot[0, [0, 2, 3]] >= 0), slot
            fit = np.full((1, 2 * nf, 4), NAN)
            fit[0, f] = np.where(slot[0] >= 0, nis[0], INF)
            lk = {"link_fit": fit, "link_all": np.ones(fit.shape),
                  "link_out": np.zeros(fit.shape)}
            g0 = _family_gate(lk, COL, np.array([4]), cfg0, det[None])
            assert not g0[0, f, 1] and g0[0, f].sum() <= 1
            gate = _family_gate(lk, COL, np.array([4]), cfg, det[None])
            assert gate[0, f].tolist() == [False, True, False, False], gate[0, f]
            assert not np.any(np.delete(gate[0], f, axis=0))
        _, _, ev2, slot2, *_ = _update_pairs(mean, cov, links, rr, cc, nf, b, cfg,
                                             fam_gate=gate)
        if shift == 0.0:
            assert np.array_equal(slot2, slot), (slot2, slot)
        gains.append(float(ev2[0] - ev[0]))
    assert gains[0] > 2.0 and gains[1] < 0.5 * gains[0], gains


def test_worst_outliers_settled_nodes_only():
    """``family_worst_outliers_settled``: the gate's ``settled`` mask (the tracker's nodes not
    contested within ``floor_contest_s``) False gives exactly the gate without
    ``family_worst_outliers`` (the worst in-model link), True the loops' outlier reference."""
    seen = np.ones(FIT.shape)
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_history=1,
                              family_min_links=5, family_learned_links=0,
                              family_worst_min_links=4, family_worst_outliers=True,
                              family_worst_outliers_settled=True)
    lk = {"link_fit": FIT, "link_all": seen, "link_out": np.zeros(FIT.shape)}
    for present in (PRESENT, PRESENT_4):
        no = _family_gate(lk, COL, np.array([4]), cfg, present, None, np.array([False]))
        assert np.array_equal(no, _reference(4, present, seen, True)), no
        yes = _family_gate(lk, COL, np.array([4]), cfg, present, None, np.array([True]))
        assert np.array_equal(yes, _reference(4, present, seen, True, outliers=True)), yes
    assert TrackerConfig().family_worst_outliers_settled is False
