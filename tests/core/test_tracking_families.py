"""The tracker's higher-order first-arrival families (``TrackerConfig.max_order``,
:mod:`diffpos.tracking.families`): the families' path lengths against the image method, their
share of the out-of-model component, and a measurement update's evidence with them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from diffpos.paths.model import first_arrival_paths, graded_paths
from diffpos.scenario import default_scenario
from diffpos.tracking.evidence import last_fit
from diffpos.tracking.families import (
    FAMILY_SHARE,
    extra_families,
    family_log_lik,
    family_log_weight,
)
from diffpos.tracking.links import Links
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import _update_pairs

B = default_scenario().building
LABEL = "Tx-R(ceiling)-R(floor)-R(ceiling)-Rx"


def _triple_bounce(anchor, node, floor):
    """Brute force, image method: the anchor mirrored across the ceiling, the floor, the
    ceiling of ``floor`` (the path's order), its distance to the node."""
    zf = B.floor_z_m(floor)
    zc = zf + B.floor_height_m
    z = 2 * zc - anchor[2]
    z = 2 * zf - z
    z = 2 * zc - z
    return float(np.linalg.norm([node[0] - anchor[0], node[1] - anchor[1], node[2] - z]))


def _cases():
    """(anchor, node) pairs on floor 2 where the triple bounce exists (through the window)."""
    zf = B.floor_z_m(2)
    out = []
    for ax, ay, az in ((0.0, -7.0, 4.0), (-5.0, -6.0, 3.0), (4.0, -8.0, 5.0)):
        for nx, ny, dz in ((0.0, 12.0, 1.5), (-3.0, 15.0, 1.2), (6.0, 18.0, 1.0), (2.0, 9.0, 1.6)):
            out.append((np.array([ax, ay, az]), np.array([nx, ny, zf + dz])))
    return out


def _existing_case():
    """The first case of :func:`_cases` where the triple bounce exists."""
    mset, slots = extra_families(3)
    j = [r.label for r in mset.recipes].index(LABEL) - slots[0]
    for a, n in _cases():
        g = graded_paths(n[None], a[None], B, relax_m=0.0, floor=np.array([2]), slots=slots,
                         mechanisms=mset)
        if g.loose[0, j]:
            return a, n
    raise AssertionError("no case with the triple bounce")


def test_family_lengths_match_the_image_method():
    """The ceiling-floor-ceiling triple bounce (a family max_order 3 adds, not one of the 18)
    on floor 2 of the paper building: where it exists, its length equals the image method's
    within 1 mm; and :func:`family_log_lik` with the range at that length is at least the
    Gaussian peak of that family divided by the number of existing families."""
    fam = extra_families(3)
    assert fam is not None and extra_families(2) is None
    mset, slots = fam
    k = [r.label for r in mset.recipes].index(LABEL)
    assert k >= 18 and k in slots.tolist()
    seen = 0
    for a, n in _cases():
        g = graded_paths(n[None], a[None], B, relax_m=0.0, floor=np.array([2]),
                         slots=slots, mechanisms=mset)
        j = slots.tolist().index(k)
        if not g.loose[0, j]:
            continue
        seen += 1
        ref = _triple_bounce(a, n, 2)
        assert abs(g.length_m[0, j] - ref) < 1e-3, (a, n, g.length_m[0, j], ref)
        var = 0.05 ** 2
        ll, n_fam, n_base = family_log_lik(n[None], np.zeros((1, 3, 3)), a[None],
                                           np.array([ref]), np.array([var]), np.array([2]),
                                           B, 3, 0.0)
        n_ok = int(g.loose[0].sum())
        assert n_fam[0] == n_ok
        assert n_base[0] == int(graded_paths(n[None], a[None], B, relax_m=0.0,
                                             floor=np.array([2])).loose[0].sum())
        assert ll[0] >= -0.5 * np.log(2 * np.pi * var) - np.log(n_ok) - 1e-9
    assert seen >= 2, seen


def test_out_of_model_component_with_and_without_families():
    """:func:`family_log_weight` (prior outlier weight, 5 cm sigma, a point position) is
    ``log((1 - c) + c span f)``, ``f`` the mean over the existing families of the Gaussian
    about each one's length (1e-9): at the shortest family's length it rises above 0; 0.5 m
    beyond every family it is ``log(1 - c)`` within 1e-6; max_order 2: 0 (no family)."""
    a, n = _existing_case()
    mset, slots = extra_families(3)
    g = graded_paths(n[None], a[None], B, relax_m=TrackerConfig().exist_margin_m,
                     floor=np.array([2]), slots=slots, mechanisms=mset)
    lengths = g.length_m[0][g.loose[0]]
    assert lengths.size >= 2
    rho = np.array([lengths.min(), lengths.max() + 0.5])
    var = 0.05 ** 2
    links = Links.from_arrays(np.stack([a, a])[None], rho[None], np.full((1, 2), 0.05),
                              np.ones((1, 2), bool), 0.0)
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_weight="outlier")
    w = family_log_weight(n[None], np.zeros((1, 3, 3)), links, np.array([0]), np.array([2]),
                          np.ones((1, 2), bool), B, cfg)
    c, span = FAMILY_SHARE, cfg.outlier_span_m
    for i in range(2):
        f = np.mean(np.exp(-0.5 * (rho[i] - lengths) ** 2 / var) / np.sqrt(2 * np.pi * var))
        assert abs(w[0, i] - np.log((1 - c) + c * span * f)) < 1e-9, (i, w, f)
    assert w[0, 0] > 0.0
    assert abs(w[0, 1] - np.log(1 - c)) < 1e-6
    w2 = family_log_weight(n[None], np.zeros((1, 3, 3)), links, np.array([0]), np.array([2]),
                           np.ones((1, 2), bool), B, dataclasses.replace(cfg, max_order=2))
    assert np.all(w2 == 0.0)


def test_families_weighed_as_mechanisms():
    """``family_weight="mechanism"`` (the default; prior outlier weight ``e0``, 5 cm sigma, a
    point position): :func:`family_log_weight` is ``log(1 + (1 - e0) / e0 * span * n_fam /
    (n_18 + n_fam) * f)`` (1e-9), ``n_fam`` / ``n_18`` the families / mechanisms of the 18
    that exist (loose at ``exist_margin_m``), ``f`` the mean Gaussian of the existing families;
    at the shortest family's length it exceeds the ``"outlier"`` weighting's value by more
    than 2 nats (one more mechanism, not half of the 2 % outlier), 0.5 m beyond every family
    it is 0 within 1e-6 (the uniform outlier alone); with a learned outlier weight ``eps``
    (``log_eps``) the family keeps the inlier weight ``1 - eps``."""
    a, n = _existing_case()
    mset, slots = extra_families(3)
    relax = TrackerConfig().exist_margin_m
    g = graded_paths(n[None], a[None], B, relax_m=relax, floor=np.array([2]), slots=slots,
                     mechanisms=mset)
    lengths = g.length_m[0][g.loose[0]]
    n_18 = int(graded_paths(n[None], a[None], B, relax_m=relax,
                            floor=np.array([2])).loose[0].sum())
    rho = np.array([lengths.min(), lengths.max() + 0.5])
    var = 0.05 ** 2
    links = Links.from_arrays(np.stack([a, a])[None], rho[None], np.full((1, 2), 0.05),
                              np.ones((1, 2), bool), 0.0)
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_weight="mechanism")
    args = (n[None], np.zeros((1, 3, 3)), links, np.array([0]), np.array([2]),
            np.ones((1, 2), bool), B)
    w = family_log_weight(*args, cfg)
    w_old = family_log_weight(*args, dataclasses.replace(cfg, family_weight="outlier"))
    e0, span, k = cfg.outlier_weight, cfg.outlier_span_m, lengths.size
    for i in range(2):
        f = np.mean(np.exp(-0.5 * (rho[i] - lengths) ** 2 / var) / np.sqrt(2 * np.pi * var))
        want = np.log1p((1 - e0) / e0 * span * k / (n_18 + k) * f)
        assert abs(w[0, i] - want) < 1e-9, (i, w, want)
    assert w[0, 0] > w_old[0, 0] + 2.0, (w, w_old)
    assert abs(w[0, 1]) < 1e-6
    eps = 0.3
    w_l = family_log_weight(*args, cfg, log_eps=np.full((1, 2), np.log(eps)))
    f0 = np.mean(np.exp(-0.5 * (rho[0] - lengths) ** 2 / var) / np.sqrt(2 * np.pi * var))
    assert abs(w_l[0, 0] - np.log1p((1 - eps) / eps * span * k / (n_18 + k) * f0)) < 1e-9


def test_last_fit_keeps_every_present_links_nis():
    """:func:`diffpos.tracking.evidence.last_fit`: the present links of the updated
    hypotheses get this update's NIS (inf for an outlier, NaN NIS), at their learned link's
    slot; links absent, of hypotheses not updated, or without a learned link keep theirs."""
    fit = np.full((1, 2, 4), 7.0)
    col = np.array([[2, 0, -1]])
    run = np.array([[True, False]])
    mask = np.array([[True, True, True]])
    nis = np.array([[[0.5, np.nan, 3.0], [1.0, 1.0, 1.0]]])
    out = last_fit(fit.copy(), col, run, mask, nis)
    assert out[0, 0, 2] == 0.5 and out[0, 0, 0] == np.inf
    assert out[0, 0, 1] == 7.0 and out[0, 0, 3] == 7.0
    assert np.all(out[0, 1] == 7.0)
    out = last_fit(fit.copy(), col, run, np.array([[False, True, True]]), nis)
    assert out[0, 0, 2] == 7.0 and out[0, 0, 0] == np.inf


def test_update_evidence_gains_the_family_term_of_an_outlier_link():
    """One measurement update of floor 2's level hypothesis at the true position (1 cm prior)
    of a node on floor 2, ranges only: three links at the 18 mechanisms' first arrival, the
    first at the triple bounce's length (out of the 18: an outlier for both settings). The
    max_order-3 evidence minus the max_order-2 one equals that link's
    :func:`family_log_weight` (1e-9 nats) and is > 0; the inlier links and the state are
    the same (the family carries no position information)."""
    a, n = _existing_case()
    anchors = np.stack([a, [-15.0, -20.0, 1.0], [15.0, -20.0, 1.0], [0.0, -15.0, 0.0]])
    ps = first_arrival_paths(np.broadcast_to(n, (4, 3)), anchors, B, floor=2)
    rho = np.nanmin(np.where(ps.valid, ps.length_m, np.nan), axis=-1)
    assert np.all(np.isfinite(rho[1:]))
    rho[0] = _triple_bounce(a, n, 2)
    links = Links.from_arrays(anchors[None], rho[None], np.full((1, 4), 0.03),
                              np.ones((1, 4), bool), TrackerConfig().sigma_model_m)
    nf = B.n_floors
    mean = np.zeros((1, 2 * nf, 6))
    mean[0, :, :3] = n
    cov = np.broadcast_to(np.eye(6) * 1e-4, (1, 2 * nf, 6, 6)).copy()
    got = {}
    for order in (2, 3):
        cfg = dataclasses.replace(TrackerConfig(), max_order=order)
        got[order] = _update_pairs(mean, cov, links, np.array([0]), np.array([2]), nf, B, cfg)
    x2, _, ev2, slot2, *_ = got[2]
    x3, _, ev3, slot3, *_ = got[3]
    assert slot2[0, 0] == -1 and slot3[0, 0] == -1
    assert np.array_equal(slot2, slot3) and np.all(slot2[0, 1:] >= 0)
    cfg3 = dataclasses.replace(TrackerConfig(), max_order=3)
    w = family_log_weight(n[None], cov[0, 2, :3, :3][None], links, np.array([0]),
                          np.array([2]), np.array([[True, False, False, False]]), B, cfg3)
    assert w[0, 0] > 0.0
    assert abs((ev3[0] - ev2[0]) - w[0, 0]) < 1e-9, (ev3 - ev2, w)
    np.testing.assert_allclose(x3, x2, rtol=0, atol=1e-12)
