"""The later selection passes only where the fit moved (``TrackerConfig.refit_min_m``).

:func:`diffpos.tracking.model.measurement_update` with ``refit_min_m`` > 0 runs its second
selection pass only for the nodes with a hypothesis whose first fit moved at least that far
from the prior (where the first pass' paths were evaluated). The references: the update with
every pass (``refit_min_m`` 0, as before) and the update with one pass (``select_passes`` 1).
Every node must equal the first bit for bit where its fit moved that far and the second
where it did not; which nodes moved is found from the first pass written out with the public
pieces (paths at the prior, SNR term, selection, IEKF). Random cases (fixed seeds) on a
building other than the shipped one, priors outside their floor's box, several hypotheses
per node and one (the tracker's pairs)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.scenario import Building, default_scenario
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.model import (
    _paths_at,
    cap_snr_cost,
    clamp_to_floor,
    existence_margin,
    iekf,
    measurement_update,
    select,
    snr_cost_near,
)
from diffpos.tracking.state import TrackerConfig

_B = dataclasses.replace(Building(), n_floors=4, floor_height_m=3.3, window_height_m=1.2,
                         sill_height_m=1.0, partitions=())


def _case(b, seed, n=12, h=3, m=8):
    """Priors near a common point per node (N, H, 6), covariances, links, floors, modes."""
    rng = np.random.default_rng(seed)
    x0, x1 = b.edge_x_m
    floor = rng.integers(0, b.n_floors, (n, h))
    zf = b.floor_z_m(floor)
    pos = np.stack([rng.uniform(x0 - 0.5, x1 + 0.5, (n, h)), rng.uniform(0.3, b.depth_m, (n, h)),
                    zf + b.nominal_node_height_m + rng.normal(0, 0.2, (n, h))], axis=-1)
    anc = np.stack([rng.uniform(x0 - 10, x1 + 10, (n, m)), rng.uniform(-30, -2, (n, m)),
                    rng.uniform(0, b.floor_z_m(b.n_floors - 1) + 6, (n, m))], axis=-1)
    truth = pos[:, 0] + rng.normal(0, 0.3, (n, 3))
    ranges = np.linalg.norm(truth[:, None] - anc, axis=-1) + rng.uniform(-0.05, 2.0, (n, m))
    links = Links.from_arrays(anc, ranges, rng.uniform(0.02, 0.2, (n, m)),
                              rng.random((n, m)) > 0.1, 0.03,
                              snr_db=np.where(rng.random((n, m)) < 0.2, np.nan,
                                              rng.uniform(-5, 40, (n, m))),
                              radio=default_scenario().radio)
    x = np.concatenate([pos, rng.normal(size=(n, h, 3)) * 0.5], axis=-1)
    x[0, 0, 2] = b.floor_z_m(floor[0, 0]) - 0.2  # below its floor
    a = rng.normal(size=(n, h, 6, 6)) * 0.3
    p = a @ np.swapaxes(a, -1, -2) + 0.01 * np.eye(6)
    return x, p, links, floor, rng.random((n, h)) < 0.6


def _first_fit(x, p, links, floor, b, cfg, level):
    """The first pass' fit (before its clamp to the floor), from the public pieces."""
    xc = clamp_to_floor(x[..., :3], floor, b, cfg.z_margin_m)
    moved = np.flatnonzero(np.any(xc != x[..., :3], axis=(-2, -1)))
    relax = existence_margin(p, cfg)
    pe = all_paths(xc, links, floor, b, relax)
    snr_c = cap_snr_cost(snr_cost_near(xc, links, floor, b, relax, pe), cfg)
    pe = _paths_at(pe, moved, x[..., :3], links, floor, b, relax)
    sel = select(p[..., :3, :3], links, pe, cfg, snr_c)
    return iekf(x, p, links, floor, sel, b, cfg, level)[0]


def _rows(out, i):
    x, p, ev, sel, res = out
    return [a[i].tobytes() for a in (x, p, ev, sel.slot, sel.log_weight, sel.nis,
                                     sel.extra_var, res)]


@pytest.mark.parametrize("h", [1, 3])
def test_second_pass_only_where_the_fit_moved(h):
    """Bit for bit: the two-pass update where a hypothesis' first fit moved >= refit_min_m,
    the one-pass update elsewhere; both kinds of node occur, and the two references differ
    on the refitted nodes (so the test tells them apart)."""
    base = TrackerConfig(snr_reuse_m=0.0, snr_reuse_anchor_m=0.0)
    for seed in (3 + h, 11 + h):
        x, p, links, floor, level = _case(_B, seed, h=h)
        if h == 1:
            floor, level = floor[:, :1], level[:, :1]
        fit = _first_fit(x, p, links, floor, _B, base, level)
        dist = np.sqrt(np.sum((fit[..., :3] - x[..., :3]) ** 2, axis=-1)).max(axis=1)
        thr = float(np.median(dist))
        cfg = dataclasses.replace(base, refit_min_m=thr)
        got = measurement_update(x, p, links, floor, _B, cfg, level=level)
        full = measurement_update(x, p, links, floor, _B, base, level=level)
        one = measurement_update(x, p, links, floor, _B,
                                 dataclasses.replace(base, select_passes=1), level=level)
        refit = dist >= thr
        assert 0 < refit.sum() < refit.size
        for i in range(x.shape[0]):
            assert _rows(got, i) == _rows(full if refit[i] else one, i)
        assert any(_rows(full, i) != _rows(one, i) for i in np.flatnonzero(refit))


def test_refit_zero_and_tiny_are_every_pass():
    """``refit_min_m`` 0 is the update as before; a tiny positive one takes the row-subset
    route with every node (each moved), the same values bit for bit."""
    base = TrackerConfig(snr_reuse_m=0.0, snr_reuse_anchor_m=0.0)
    x, p, links, floor, level = _case(_B, 29)
    full = measurement_update(x, p, links, floor, _B, base, level=level)
    tiny = measurement_update(x, p, links, floor, _B,
                              dataclasses.replace(base, refit_min_m=1e-300), level=level)
    assert all(_rows(full, i) == _rows(tiny, i) for i in range(x.shape[0]))


def test_snapshot_initialisation_runs_every_pass():
    """Without modes (the snapshot initialisation) every pass runs whatever ``refit_min_m``."""
    base = TrackerConfig(snr_reuse_m=0.0, snr_reuse_anchor_m=0.0)
    x, p, links, floor, _ = _case(_B, 31)
    full = measurement_update(x, p, links, floor, _B, base)
    big = measurement_update(x, p, links, floor, _B, dataclasses.replace(base, refit_min_m=1e9))
    assert all(_rows(full, i) == _rows(big, i) for i in range(x.shape[0]))
