"""Live Sionna RT checks (optional extra): skipped, with the reason printed, without it.

Install: ``pip install -e '.[raytrace]'`` and ``apt-get install libllvm19``. A small receiver
set keeps this under a minute on 2 cores.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from diffpos_services.raytrace import mechanisms as mm
from diffpos_services.raytrace.backend import VARIANT, RaytraceUnavailable, check_sionna
from diffpos_services.raytrace.dataset import DATASET_FORMAT, RaytraceDataset
from diffpos_services.raytrace.evaluate import dataset_first_arrival, edge_fermat_check
from diffpos_services.raytrace.paths import chain_label
from diffpos_services.raytrace.tracing import RaytraceSettings, trace

from diffpos.geometry import diffraction_point
from diffpos.scenario import Partition, default_scenario

try:
    VERSIONS = check_sionna()
except RaytraceUnavailable as exc:  # pragma: no cover - depends on the environment
    pytest.skip(f"Sionna RT unavailable, ray-tracer tests skipped: {exc}", allow_module_level=True)

pytestmark = pytest.mark.slow


def _receivers() -> np.ndarray:
    """24 receivers on floors 0, 2, 4: near the window, mid-room and behind the corridor."""
    sc = default_scenario()
    b = sc.building
    xs = [-17.3, -4.6, 7.9, 15.2]
    ys = [0.8, 6.3, 15.7]
    h = b.nominal_node_height_m
    pts = [(x, y, float(b.floor_z_m(k)) + h) for k in (0, 2) for y in ys for x in xs]
    return np.asarray(pts, dtype=float)


@pytest.fixture(scope="module")
def traced() -> RaytraceDataset:
    sc = default_scenario()
    return trace(sc, _receivers(), settings=RaytraceSettings(samples_per_src=100_000,
                                                                     seed=5))


def test_versions_and_metadata(traced: RaytraceDataset) -> None:
    assert VERSIONS["sionna-rt"] == "2.2.0" and VERSIONS["variant"] == VARIANT
    md = traced.metadata
    assert md["format"] == DATASET_FORMAT and md["settings"]["seed"] == 5
    assert md["s_per_1000_links"] > 0
    assert traced.path_valid.shape[:2] == (24, 4)


def test_diffraction_paths_match_the_fermat_length_to_a_millimetre(traced) -> None:
    fc = edge_fermat_check(traced)
    assert len(fc["error_m"]) >= 40
    assert np.max(np.abs(fc["error_m"])) < 1e-3
    # the first arrivals that are window-edge diffraction, checked one by one
    fa = dataset_first_arrival(traced)
    b = traced.scenario.building
    lo, hi = b.window_z_m(np.arange(b.n_floors))
    edges = np.concatenate([lo, hi])
    checked = 0
    for n, m in np.argwhere(fa.mpc_class == 3):
        v = traced.path_vertex_m[n, m, fa.slot[n, m]].astype(float)
        ze = edges[np.argmin(np.abs(edges - v[2]))]
        if abs(v[1]) > 1e-3 or abs(v[2] - ze) > 1e-3:
            continue  # a vertical edge (partition end / side wall): not the paper's model
        x0, x1 = b.edge_x_m
        dp = diffraction_point(traced.anchors_m[m], traced.nodes_m[n], [x0, 0, ze], [x1, 0, ze])
        assert fa.true_path_m[n, m] == pytest.approx(float(dp.length_m), abs=1e-3)
        checked += 1
    assert checked >= 12


def test_classification_counts_are_sane(traced) -> None:
    v = traced.path_valid
    cls = traced.path_class[v]
    assert set(np.unique(cls)) <= {1, 2, 3, 4}
    counts = np.bincount(cls, minlength=5)
    # diffraction everywhere, LoS only for the receivers near the window
    assert counts[3] > counts[1] and counts[4] > counts[1]
    per_link3 = np.any(v & (traced.path_class == 3), axis=-1)
    assert per_link3.mean() > 0.6
    # group 1 only where the straight segment enters through the receiver's own window
    b = traced.scenario.building
    a, nd = traced.anchors_m[None], traced.nodes_m[:, None]
    t = -a[..., 1] / (nd[..., 1] - a[..., 1])
    zc = a[..., 2] + t * (nd[..., 2] - a[..., 2])
    lo, hi = b.window_z_m(b.floor_index(traced.nodes_m[:, 2]))
    through = (zc > lo[:, None]) & (zc < hi[:, None])
    g1 = v & (traced.path_class == 1)
    has1 = np.any(g1 & (traced.path_gain_db > -150), axis=-1)
    assert not np.any(has1 & ~through)
    assert 0 < has1.sum() <= through.sum()
    # the others cross concrete (a slab or the wall next to the window): > 100 dB below LoS
    fs_db = 20 * np.log10(299_792_458.0 / 28e9 / (4 * np.pi * 40.0))
    assert np.all(traced.path_gain_db[g1 & ~through[..., None]] < fs_db - 80)
    # group 1 paths have the Euclidean length (through the window or partitions)
    d = np.linalg.norm(traced.nodes_m[:, None] - traced.anchors_m[None], axis=-1)
    l1 = np.where(v & (traced.path_class == 1), traced.path_length_m, np.nan)
    ok = ~np.isnan(l1)
    np.testing.assert_allclose(l1[ok], np.broadcast_to(d[..., None], l1.shape)[ok], atol=1e-3)


def test_dipole_transmitter_normalisation(traced) -> None:
    """LoS gain = free-space (lambda / 4 pi d)^2 x |E_0 x u|^2 (short dipole along the
    polarisation, 0 dBi peak: the emulator's normalisation), summed over both receive
    polarisations."""
    sc = traced.scenario
    lam = 299_792_458.0 / sc.radio.frequency_hz
    e0 = np.asarray(sc.radio.polarization)
    sel = traced.path_valid & (traced.path_chain == 0)
    n, m, k = np.nonzero(sel)
    assert len(n) >= 3
    u = traced.nodes_m[n] - traced.anchors_m[m]
    d = np.linalg.norm(u, axis=-1)
    u /= d[:, None]
    expect = 20 * np.log10(lam / (4 * np.pi * d)) + 10 * np.log10(
        1 - np.einsum("ij,j->i", u, e0) ** 2)
    np.testing.assert_allclose(traced.path_gain_db[n, m, k], expect, atol=0.05)


def test_same_seed_same_paths() -> None:
    sc = default_scenario()
    nodes = _receivers()[::6]
    s = RaytraceSettings(samples_per_src=20_000, seed=11, deterministic=True)
    a = trace(sc, nodes, settings=s)
    b = trace(sc, nodes, settings=s)
    np.testing.assert_array_equal(a.path_valid, b.path_valid)
    np.testing.assert_array_equal(a.path_chain, b.path_chain)
    np.testing.assert_allclose(a.path_length_m[a.path_valid], b.path_length_m[b.path_valid],
                               atol=1e-6)


def test_receivers_outside_the_building_are_refused() -> None:
    with pytest.raises(ValueError, match="outside the building"):
        trace(default_scenario(), [[0.0, -1.0, 5.0]])


def test_traced_mechanisms_have_the_model_length_on_another_building() -> None:
    """A building unlike the paper's (3.4 m floors, 1.1 m windows at 1.0 m, 31 m wide, one
    partition): every traced path classified into one of diffpos.paths.model' 18 mechanisms has the
    model's closed-form length on the receiver's floor to 0.1 mm (Sionna's float32 leaves
    ~10 um), and the model says the mechanism exists for almost all of them."""
    sc = default_scenario()
    b = dataclasses.replace(sc.building, floor_height_m=3.4, sill_height_m=1.0,
                            window_height_m=1.1, width_m=31.0, center_x_m=2.0, n_floors=4,
                            partitions=(Partition(axis="x", position_m=5.5, span_m=(0.0, 18.0),
                                                  material="plasterboard"),))
    sc = dataclasses.replace(sc, building=b)
    nodes = [(x, y, float(b.floor_z_m(k)) + h) for k, h in ((0, 1.2), (2, 2.6))
             for x, y in ((-9.0, 2.5), (0.5, 7.0), (11.0, 4.0), (14.0, 13.0))]
    ds = trace(sc, np.asarray(nodes), settings=RaytraceSettings(seed=3))
    res = mm.mechanism_length_check(ds)
    assert len(res) >= 8, sorted(res)
    for name, r in res.items():
        assert r["max_abs_m"] < 1e-4, (name, r)
        assert r["model_exists"] >= 0.9, (name, r)
        assert r["exists_on_band"] == 1.0, (name, r)  # the rest enter on a band limit


def test_a_diffracted_path_has_the_same_gain_at_any_max_depth() -> None:
    """The ray tracer's correction (raytrace.corrections): a diffracted path shorter than
    ``max_depth`` gets the gain it gets when it is as long as ``max_depth`` allows. Sionna RT
    2.2.0 alone gave 37 of 102 such paths here 3-6 dB less at depth 4 than at depth 2 (a slot
    past the path's end counted in the diffraction's distances)."""
    assert VERSIONS["corrections"] == "diffraction-distances-stop-at-path-end"
    sc = default_scenario()  # its building has the four plasterboard partitions
    sc = dataclasses.replace(sc, anchors=(sc.anchors[0],))
    nodes = np.array([[-19.75, 0.5, 5.5], [1.25, 3.0, 5.5], [13.75, 4.5, 5.5],
                      [-17.75, 6.0, 5.5], [7.75, 9.0, 5.5], [-15.25, 11.5, 5.5]])
    a, b = (trace(sc, nodes, settings=RaytraceSettings(max_depth=d, samples_per_src=100_000,
                                                       seed=1)) for d in (2, 4))
    pairs = []
    for n in range(len(nodes)):
        for k in np.flatnonzero(a.path_valid[n, 0]):
            same = np.flatnonzero(b.path_valid[n, 0] & (b.path_chain[n, 0] == a.path_chain[n, 0, k])
                                  & (np.abs(b.path_length_m[n, 0] - a.path_length_m[n, 0, k])
                                     < 1e-3))
            if same.size:
                pairs.append((a.path_chain[n, 0, k],
                              float(b.path_gain_db[n, 0, same[0]] - a.path_gain_db[n, 0, k])))
    diffracted = [d for c, d in pairs if "D" in chain_label(int(c))]
    assert len(diffracted) >= 20, len(diffracted)
    assert max(abs(d) for d in diffracted) < 0.01, sorted(diffracted)
