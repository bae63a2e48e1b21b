"""Positioning study over first-arrival data, and `diffpos reproduce` end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.geometry import window_edge_path
from diffpos.study import (
    FirstArrivalData,
    empirical_cdf,
    first_arrival_statistics,
    percentile_summary,
    positioning_study,
)


def _emulated(paper, n, seed):
    rng = np.random.default_rng(seed)
    nodes = paper.node_positions_m()
    nodes = nodes[np.sort(rng.choice(len(nodes), n, replace=False))]
    anchors = paper.anchor_positions_m()
    ch = emulate_channel(anchors, nodes, building=paper.building, radio=paper.radio)
    fa = first_arrival(ch, radio=paper.radio, rng=rng)
    return FirstArrivalData.from_channel(fa, anchors, nodes)


# ------------------------------------------------------------------ small pieces
def test_percentiles_count_failures_as_infinite():
    s = percentile_summary([3.0, 1.0, np.nan, 2.0])
    assert s["median"] == 2.0 and s["p95"] == np.inf and s["mean"] == 2.0 and s["n"] == 4
    v = np.random.default_rng(0).exponential(size=1001)
    s = percentile_summary(v)
    srt = np.sort(v)
    assert s["median"] == srt[500]  # smallest x with CDF(x) = (i + 1) / 1001 >= 0.5
    assert s["p80"] == srt[800]
    x, f = empirical_cdf([np.inf, 1.0, 0.5, np.nan])
    np.testing.assert_array_equal(x, [0.5, 1.0])
    np.testing.assert_array_equal(f, [0.25, 0.5])  # failures never reach the top


def test_first_arrival_data_validation_and_arrays(paper):
    d = _emulated(paper, 50, 1)
    back = FirstArrivalData.from_arrays(d.to_arrays())
    for k, v in d.to_arrays().items():
        np.testing.assert_array_equal(getattr(back, k), v)
    arrays = d.to_arrays()
    del arrays["sigma_m"]
    with pytest.raises(ValueError, match="sigma_m"):
        FirstArrivalData.from_arrays(arrays)
    again = FirstArrivalData.from_arrays(arrays, bandwidth_hz=paper.radio.bandwidth_hz,
                                         range_error_floor_m=paper.radio.range_error_floor_m)
    np.testing.assert_allclose(again.sigma_m[d.detected], d.sigma_m[d.detected], rtol=1e-12)
    with pytest.raises(ValueError, match=r"range_m: expected shape \(N, M\)"):
        FirstArrivalData(d.anchors_m, d.nodes_m, d.range_m[:, :3], d.snr_db, d.sigma_m,
                         d.detected, d.mpc_class, d.aoa_deg)
    bad = d.range_m.copy()
    bad[0, 0] = np.nan
    det = d.detected.copy()
    det[0, 0] = True
    with pytest.raises(ValueError, match="finite wherever detected"):
        FirstArrivalData(d.anchors_m, d.nodes_m, bad, d.snr_db, d.sigma_m, det, d.mpc_class,
                         d.aoa_deg)


def test_exact_diffraction_ranges_are_solved_by_dnls_case1(paper):
    """Ranges that follow the model exactly: D-NLS Case-1 recovers the nodes, the LoS
    baselines do not, and the PEB equals the bound of the core."""
    b = paper.building
    rng = np.random.default_rng(3)
    nodes = paper.node_positions_m()[rng.choice(17600, 120, replace=False)]
    anchors = paper.anchor_positions_m()
    p = window_edge_path(anchors[None], nodes[:, None], window_height_m=b.window_height_m,
                         edge_x_m=b.edge_x_m).length_m
    sig = np.full(p.shape, 0.05)
    data = FirstArrivalData(anchors, nodes, p, np.full(p.shape, 20.0), sig,
                            np.ones(p.shape, bool), np.full(p.shape, 3, np.int8),
                            np.full(p.shape, 90.0))
    st = positioning_study(data, window_height_m=b.window_height_m, edge_x_m=b.edge_x_m,
                           methods=("lls", "dnls_case1", "dnls_case2"), chunk_size=50)
    assert np.quantile(st.error_3d_m["dnls_case1"], 0.95) < 1e-4
    assert np.median(st.error_3d_m["lls"]) > 0.5
    # Case-2 (model offset 1.5 m): the z estimate absorbs the offset, ~Delta
    assert np.median(np.abs(st.error_z_m["dnls_case2"] - 1.5)) < 0.1
    from diffpos.bounds import position_error_bound

    ref = position_error_bound(anchors, nodes, sig, b.window_height_m, edge_x_m=b.edge_x_m)
    np.testing.assert_allclose(st.peb_m, ref.peb_m)
    summ = st.summary()
    assert summ["dnls_case1"]["solved_fraction"] == 1.0
    assert summ["peb"]["3d"]["median"] == pytest.approx(np.percentile(ref.peb_m, 50,
                                                                      method="inverted_cdf"))


def test_chunking_and_progress_do_not_change_results(paper):
    d = _emulated(paper, 90, 2)
    calls = []
    kw = dict(window_height_m=1.5, edge_x_m=paper.building.edge_x_m, methods=("lls", "ippa"))
    a = positioning_study(d, chunk_size=1000, **kw)
    b = positioning_study(d, chunk_size=25, progress=lambda m, k, n: calls.append((m, k, n)),
                          **kw)
    for m in ("lls", "ippa"):
        np.testing.assert_array_equal(a.positions_m[m], b.positions_m[m])
    assert calls[:4] == [("lls", 25, 90), ("lls", 50, 90), ("lls", 75, 90), ("lls", 90, 90)]
    assert calls[-1] == ("peb", 90, 90)
    with pytest.raises(ValueError, match="unknown method"):
        positioning_study(d, window_height_m=1.5, methods=("magic",))


# ------------------------------------------------------------------ the paper's claims
def test_dnls_beats_lls_and_ippa_on_the_default_scenario(paper):
    """Fixed seed, 1,200 receivers of the paper's scenario: D-NLS (both cases) has smaller
    median and 80th-percentile 3D and z errors than LLS and IPPA."""
    d = _emulated(paper, 1200, 0)
    st = positioning_study(d, window_height_m=1.5, edge_x_m=paper.building.edge_x_m)
    s = st.summary()
    for dn in ("dnls_case1", "dnls_case2"):
        for base in ("lls", "ippa"):
            for axis in ("3d", "z"):
                for q in ("median", "p80"):
                    assert s[dn][axis][q] < s[base][axis][q], (dn, base, axis, q, s)
    # where every first arrival is an edge diffraction D-NLS does better still, and better
    # again when it models the lower edge (shorter, hence usually first: see the README)
    all3 = np.all(d.mpc_class == 3, axis=1)
    assert all3.sum() > 50
    e1 = np.median(st.error_3d_m["dnls_case1"][all3])
    assert e1 < s["dnls_case1"]["3d"]["median"]
    low = positioning_study(d.subset(all3), window_height_m=1.5,
                            edge_x_m=paper.building.edge_x_m, methods=("dnls_lower",))
    assert np.median(low.error_3d_m["dnls_lower"]) < 0.75 * e1
    # the PEB lower-bounds the typical error
    assert s["peb"]["3d"]["median"] < s["dnls_case1"]["3d"]["median"]
    fs = first_arrival_statistics(d)
    assert fs["detected_pct"] > 98.0
    assert sum(fs["P_fap_pct"].values()) == pytest.approx(fs["detected_pct"])


# ------------------------------------------------------------------ CLI end to end
def test_reproduce_accepts_a_raytrace_dataset(tmp_path, paper):
    """The ray-tracer hook: a dataset in the 'diffpos raytrace' format (here filled with the
    emulator's own paths) gives the same MPC table as the emulator."""
    raytrace = pytest.importorskip("diffpos_services.raytrace.dataset")
    from diffpos_services.cli.main import main

    from diffpos.channel.emulator import MPC_CLASS, mpc_statistics

    nodes = paper.node_positions_m()[::200]
    anchors = paper.anchor_positions_m()
    ch = emulate_channel(anchors, nodes, building=paper.building, radio=paper.radio)
    shape = ch.valid.shape
    with np.errstate(divide="ignore"):
        gain_db = np.where(ch.valid, 20 * np.log10(np.abs(ch.gain)), -np.inf)
    ds = raytrace.RaytraceDataset(
        nodes_m=nodes, anchors_m=anchors, anchor_ids=tuple(paper.anchor_ids),
        path_valid=ch.valid, path_length_m=np.where(ch.valid, ch.length_m, 0.0),
        path_gain_db=gain_db.astype(np.float32), path_aod_deg=ch.aod_deg.astype(np.float32),
        path_aoa_deg=ch.aoa_deg.astype(np.float32), path_chain=np.zeros(shape, np.uint16),
        path_class=np.broadcast_to(MPC_CLASS, shape).astype(np.int8),
        path_vertex_m=np.zeros((*shape, 3), np.float32),
        metadata={"format": raytrace.DATASET_FORMAT, "scenario": paper.to_dict()},
    )
    path = raytrace.save_dataset(tmp_path / "rt.npz", ds)
    out = tmp_path / "out"
    assert main(["reproduce", "--no-progress", "--channel", f"raytrace:{path}",
                 "--methods", "dnls_case1", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["n_receivers"] == len(nodes) and s["channel_source"].startswith("raytrace:")
    want = mpc_statistics(ch, first_arrival(ch, radio=paper.radio))
    for g in ("MPC-1", "MPC-2", "MPC-3", "MPC-4"):
        for k in ("P_e", "P_fap"):
            assert s["mpc_table_pct"][g][k] == pytest.approx(want[g][k], abs=0.5)


def test_the_mnls_mechanism_families_reach_the_estimator(paper, monkeypatch):
    """``mnls_max_order`` (``diffpos reproduce --mnls-max-order``) is the order M-NLS runs
    with: 2 (the emulator's 18 mechanisms) by default, the higher-order families when asked."""
    import diffpos.study as study

    seen = []
    real = study.mnls
    monkeypatch.setattr(study, "mnls", lambda *a, **k: seen.append(k["max_order"]) or real(*a, **k))
    d = _emulated(paper, 12, 3)
    kw = dict(window_height_m=1.5, methods=("mnls",), building=paper.building, radio=paper.radio)
    positioning_study(d, **kw)
    positioning_study(d, mnls_max_order=3, **kw)
    assert seen == [2, 3]
