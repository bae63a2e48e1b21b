"""The committed ray-traced dataset (Sionna RT, paper scenario) against independent references.

No Sionna needed: ``tests/data/raytrace_small.npz`` was written by
``diffpos raytrace scenarios/paper.toml --receivers 160 --out tests/data/raytrace_small.npz``
(1e5 samples, seed 1). The references are closed forms computed here (Euclidean distance,
image method, a brute-force minimisation of the edge path length) and the channel emulator.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from diffpos_services.raytrace.backend import INSTALL_HINT, RaytraceUnavailable
from diffpos_services.raytrace.dataset import (
    DATASET_FORMAT,
    RaytraceDataset,
    load_dataset,
    save_dataset,
)
from diffpos_services.raytrace.evaluate import (
    compare_with_emulator,
    dataset_first_arrival,
    dataset_mpc_statistics,
    edge_fermat_check,
    path_snr_db,
)
from diffpos_services.raytrace.paths import (
    DIFFRACTION,
    DIFFUSE,
    REFRACTION,
    SPECULAR,
    chain_label,
    classify_chains,
    encode_chains,
)
from diffpos_services.raytrace.scene import building_surfaces
from diffpos_services.raytrace.tracing import RaytraceSettings
from scipy.optimize import minimize_scalar

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.geometry import diffraction_point
from diffpos.scenario import default_scenario

DATA = Path(__file__).resolve().parents[1] / "data" / "raytrace_small.npz"


@pytest.fixture(scope="module")
def ds() -> RaytraceDataset:
    return load_dataset(DATA)


@pytest.fixture(scope="module")
def emu(ds: RaytraceDataset):
    sc = ds.scenario
    ch = emulate_channel(ds.anchors_m, ds.nodes_m, building=sc.building, radio=sc.radio)
    return ch, first_arrival(ch, radio=sc.radio)


# ------------------------------------------------------------------ format


def test_dataset_format_and_invariants(ds: RaytraceDataset) -> None:
    n, m, k = ds.path_valid.shape
    assert (n, m) == (160, 4) and k >= 10
    assert ds.metadata["format"] == DATASET_FORMAT
    assert ds.metadata["settings"]["samples_per_src"] == 100_000
    assert ds.anchor_ids == ("uav1", "uav2", "uav3", "uav4")
    assert ds.path_vertex_m.shape == (n, m, k, 3)
    v = ds.path_valid
    # classes are the documented function of the chains; padding is class 0 / NaN
    np.testing.assert_array_equal(ds.path_class[v], classify_chains(ds.path_chain[v]))
    assert np.all(ds.path_class[~v] == 0) and np.all(np.isnan(ds.path_length_m[~v]))
    # valid paths first, sorted by delay
    assert not np.any(~v[..., :-1] & v[..., 1:])
    L = np.where(v, ds.path_length_m, 0.0)
    assert np.all(np.diff(L, axis=-1)[v[..., 1:]] >= 0)
    # every path is at least the straight-line distance
    d = np.linalg.norm(ds.nodes_m[:, None, :] - ds.anchors_m[None], axis=-1)
    assert np.all(ds.path_length_m[v] >= np.broadcast_to(d[..., None], v.shape)[v] - 1e-4)


def test_scenario_round_trip_matches_the_shipped_scenario(ds: RaytraceDataset) -> None:
    assert ds.scenario.building == default_scenario().building
    load_dataset(DATA, scenario=default_scenario())  # no mismatch error


def test_load_errors_name_the_problem(tmp_path: Path, ds: RaytraceDataset) -> None:
    with pytest.raises(ValueError, match="no such ray-trace dataset"):
        load_dataset(tmp_path / "missing.npz")
    bad = tmp_path / "other.npz"
    np.savez(bad, x=np.zeros(3))
    with pytest.raises(ValueError, match="missing"):
        load_dataset(bad)
    d = default_scenario().to_dict()
    d["anchors"][0]["trajectory"] = {"kind": "static", "position_m": [-14.0, -20.0, 1.0]}
    from diffpos.scenario import Scenario

    with pytest.raises(ValueError, match="re-run 'diffpos raytrace'"):
        load_dataset(DATA, scenario=Scenario.from_dict(d))


def test_save_load_round_trip(tmp_path: Path, ds: RaytraceDataset) -> None:
    sub = ds.subset(np.arange(0, 160, 7))
    p = save_dataset(tmp_path / "sub.npz", sub)
    back = load_dataset(p)
    for name in ("nodes_m", "path_valid", "path_length_m", "path_chain", "path_vertex_m"):
        np.testing.assert_array_equal(getattr(back, name), getattr(sub, name))
    assert back.metadata == json.loads(json.dumps(sub.metadata))


# ------------------------------------------------------------------ geometry of the traced paths


def test_window_edge_diffraction_matches_fermat_length_brute_force(ds: RaytraceDataset
                                                                   ) -> None:
    """Every traced Tx-D[-T..]-Rx path over a horizontal window edge has the minimal length
    over that edge, found here by a bounded scalar minimisation (not diffpos.geometry)."""
    fc = edge_fermat_check(ds)
    assert len(fc["error_m"]) > 300
    b = ds.scenario.building
    x0, x1 = b.edge_x_m
    rng = np.random.default_rng(3)
    pick = rng.choice(len(fc["error_m"]), 60, replace=False)
    for i in pick:
        n, m, k = fc["index"][i]
        ze = float(ds.path_vertex_m[n, m, k, 2])
        lo, hi = b.window_z_m(np.arange(b.n_floors))
        ze = float(np.concatenate([lo, hi])[np.argmin(np.abs(np.concatenate([lo, hi]) - ze))])
        a, o = ds.anchors_m[m], ds.nodes_m[n]
        f = lambda x, a=a, o=o, ze=ze: (np.linalg.norm(a - [x, 0, ze])  # noqa: E731
                                        + np.linalg.norm(o - [x, 0, ze]))
        res = minimize_scalar(f, bounds=(x0, x1), method="bounded",
                              options={"xatol": 1e-9})
        assert ds.path_length_m[n, m, k] == pytest.approx(res.fun, abs=1e-3)
    # and all of them against diffpos.geometry: the paper's 1 mm requirement, met by far
    assert np.max(np.abs(fc["error_m"])) < 1e-3
    assert np.max(np.abs(fc["error_m"])) < 5e-5  # float32 vertices/delays: micrometres
    assert np.all(fc["on_edge"])


def _partition_crossed(ds: RaytraceDataset, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """True where segment p -> q crosses a partition rectangle (from the metadata)."""
    out = np.zeros(np.broadcast_shapes(p.shape, q.shape)[:-1], dtype=bool)
    for s in ds.metadata["surfaces"]:
        if not s["name"].startswith("partition"):
            continue
        for axis, c, (u0, u1), (v0, v1) in s["rects"]:
            ua, va = [a for a in range(3) if a != axis]
            da, db = p[..., axis] - c, q[..., axis] - c
            with np.errstate(invalid="ignore", divide="ignore"):
                t = da / (da - db)
            hit = p + t[..., None] * (q - p)
            out |= ((da * db < 0) & (hit[..., ua] > u0) & (hit[..., ua] < u1)
                    & (hit[..., va] > v0) & (hit[..., va] < v1))
    return out


def test_line_of_sight_paths_exactly_where_the_window_is_open(ds: RaytraceDataset) -> None:
    """Tx-Rx exists iff the straight segment enters through the receiver's own window band
    without crossing a partition; its length is the Euclidean distance."""
    b = ds.scenario.building
    a = ds.anchors_m[None, :, :]
    n = ds.nodes_m[:, None, :]
    t = -a[..., 1] / (n[..., 1] - a[..., 1])
    cross = a + t[..., None] * (n - a)
    lo, hi = b.window_z_m(b.floor_index(ds.nodes_m[:, 2]))
    x0, x1 = b.edge_x_m
    open_ = ((cross[..., 2] > lo[:, None]) & (cross[..., 2] < hi[:, None])
             & (cross[..., 0] > x0) & (cross[..., 0] < x1))
    expect = open_ & ~_partition_crossed(ds, cross, np.broadcast_to(n, cross.shape))
    has_los = np.any(ds.path_valid & (ds.path_chain == 0), axis=-1)
    assert expect.sum() >= 20
    np.testing.assert_array_equal(has_los, expect)
    d = np.linalg.norm(n - a, axis=-1)
    los_len = np.where(ds.path_valid & (ds.path_chain == 0), ds.path_length_m, np.inf)
    np.testing.assert_allclose(los_len.min(axis=-1)[expect], d[expect], atol=1e-3)


def test_single_reflections_match_the_image_method(ds: RaytraceDataset) -> None:
    """Tx-R-Rx: length = distance from the anchor's mirror image (in the plane holding the
    reflection point) to the receiver."""
    planes = [(ax, c) for s in ds.metadata["surfaces"] for ax, c, _, _ in s["rects"]]
    sel = ds.path_valid & (ds.path_chain == SPECULAR)
    idx = np.argwhere(sel)
    assert len(idx) >= 50
    for n, m, k in idx:
        v = ds.path_vertex_m[n, m, k].astype(float)
        ax, c = min(planes, key=lambda pc: abs(v[pc[0]] - pc[1]))
        assert abs(v[ax] - c) < 1e-3
        img = ds.anchors_m[m].copy()
        img[ax] = 2 * c - img[ax]
        assert ds.path_length_m[n, m, k] == pytest.approx(np.linalg.norm(img - ds.nodes_m[n]),
                                                          abs=1e-3)


# ------------------------------------------------------------------ first arrival


def test_first_arrival_matches_a_per_link_loop(ds: RaytraceDataset) -> None:
    """The paper's definition, evaluated link by link in plain Python."""
    radio = ds.scenario.radio
    fa = dataset_first_arrival(ds, radio=radio)
    snr = path_snr_db(ds, radio)
    for n in range(0, 160, 3):
        for m in range(4):
            ok = [k for k in range(snr.shape[-1])
                  if ds.path_valid[n, m, k] and snr[n, m, k] >= radio.detection_snr_db]
            if not ok:
                assert not fa.detected[n, m] and fa.mpc_class[n, m] == 0
                continue
            pmax = max(snr[n, m, k] for k in ok)
            thr = max(pmax - radio.fap_threshold_db, radio.detection_snr_db)
            best = min((k for k in ok if snr[n, m, k] >= thr),
                       key=lambda k: ds.path_length_m[n, m, k])
            assert fa.detected[n, m]
            assert fa.true_path_m[n, m] == ds.path_length_m[n, m, best]
            assert fa.mpc_class[n, m] == ds.path_class[n, m, best]
            assert fa.range_m[n, m] == fa.true_path_m[n, m]  # no rng: noise-free


def test_noisy_ranges_follow_the_crlb(ds: RaytraceDataset) -> None:
    radio = ds.scenario.radio
    fa = dataset_first_arrival(ds, radio=radio, rng=np.random.default_rng(7))
    z = ((fa.range_m - fa.true_path_m) / fa.sigma_m)[fa.detected]
    assert z.size > 300
    assert abs(z.mean()) < 4 / np.sqrt(z.size) and 0.85 < z.std() < 1.15


def test_snr_recomputed_from_radio(ds: RaytraceDataset) -> None:
    import dataclasses

    r = ds.scenario.radio
    s0 = path_snr_db(ds, r)
    s1 = path_snr_db(ds, dataclasses.replace(r, tx_power_dbm=r.tx_power_dbm + 7.0))
    v = ds.path_valid
    np.testing.assert_allclose(s1[v] - s0[v], 7.0, atol=1e-9)
    assert np.all(np.isneginf(s0[~v]))


# ------------------------------------------------------------------ emulator vs ray tracer


def test_emulator_and_ray_tracer_agree_on_los_and_single_reflections(ds, emu) -> None:
    _, fe = emu
    fr = dataset_first_arrival(ds)
    for g in (1, 2):
        both = (fe.mpc_class == g) & (fr.mpc_class == g)
        # every emulator first arrival of group g is group g in the ray trace too (LoS: all)
        frac = both.sum() / max((fe.mpc_class == g).sum(), 1)
        assert frac == 1.0 if g == 1 else frac > 0.9
        np.testing.assert_allclose(fr.true_path_m[both], fe.true_path_m[both], atol=1e-3)
    st_e = dataset_mpc_statistics(ds, fr)
    assert st_e["MPC-1"]["P_fap"] == pytest.approx(100 * np.mean(fe.mpc_class == 1))


def test_emulator_diffraction_paths_are_found_by_the_ray_tracer(ds, emu) -> None:
    """Where the emulator's upper/lower edge path needs no partition crossing, the ray tracer
    finds a path of the same length (to 1 mm) on almost every link, with a UTD power within
    a few dB; crossing partitions (Tx-D-T-Rx) is found less often at 1e5 samples."""
    ch, _ = emu
    snr_rt = path_snr_db(ds, ds.scenario.radio)
    for slot in (7, 8):  # Tx-D(upper)-Rx, Tx-D(lower)-Rx
        assert ch.mechanism[slot].startswith("Tx-D(")
        L = ch.length_m[..., slot]
        d = np.where(ds.path_valid, np.abs(ds.path_length_m - L[..., None]), np.inf)
        found = d.min(axis=-1) < 1e-3
        k = d.argmin(axis=-1)
        valid = ch.valid[..., slot]
        pts = np.broadcast_to(ds.nodes_m[:, None, :], (*L.shape, 3))
        anchors = np.broadcast_to(ds.anchors_m[None], pts.shape)
        # the emulator's diffraction point, to know which partitions its path crosses
        b = ds.scenario.building
        lo, hi = b.window_z_m(b.floor_index(ds.nodes_m[:, 2]))
        ze = np.broadcast_to((hi if slot == 7 else lo)[:, None], L.shape)
        x0, x1 = b.edge_x_m
        p0 = np.stack([np.full(L.shape, x0), np.zeros(L.shape), ze], axis=-1)
        p1 = np.stack([np.full(L.shape, x1), np.zeros(L.shape), ze], axis=-1)
        q = diffraction_point(anchors, pts, p0, p1).point_m
        free = valid & ~_partition_crossed(ds, q, pts)
        assert free.sum() > 150
        assert found[free].mean() > 0.9
        assert found[valid & ~free].mean() > 0.05  # some D-T paths are found too
        diff_db = (np.take_along_axis(snr_rt, k[..., None], -1)[..., 0]
                   - ch.snr_db[..., slot])[free & found]
        assert np.all(np.abs(diff_db) < 12.0) and abs(np.median(diff_db)) < 4.0


def test_first_arrival_lengths_agree_where_both_pick_diffraction(ds, emu) -> None:
    _, fe = emu
    fr = dataset_first_arrival(ds)
    both = (fe.mpc_class == 3) & (fr.mpc_class == 3)
    d = np.abs(fr.true_path_m - fe.true_path_m)[both]
    assert both.sum() > 100
    # same edge -> same Fermat length; the rest pick the other window edge (< 1.5 m apart)
    assert np.mean(d < 1e-3) > 0.75 and np.all(d < 1.5)


# ------------------------------------------------------------------ pure helpers


def test_classify_chains_hand_cases() -> None:
    R, S, T, D = SPECULAR, DIFFUSE, REFRACTION, DIFFRACTION
    cases = {
        (): 1, (T,): 1, (T, T): 1,
        (R,): 2, (T, R): 2, (R, T): 2, (S,): 2,
        (D,): 3, (D, T): 3, (D, T, T): 3,
        (R, R): 4, (D, R): 4, (R, D): 4, (T, D): 4, (D, T, R): 4, (R, R, R): 4,
    }
    inter = np.zeros((3, len(cases)), dtype=np.uint32)
    for j, chain in enumerate(cases):
        inter[: len(chain), j] = chain
    codes = encode_chains(inter)
    np.testing.assert_array_equal(classify_chains(codes), list(cases.values()))
    assert chain_label(codes[list(cases).index((D, T, T))]) == "Tx-D-T-T-Rx"
    assert chain_label(0) == "Tx-Rx"
    with pytest.raises(ValueError, match="at most 4"):
        encode_chains(np.zeros((5, 2), dtype=np.uint32))


def test_building_surfaces_open_exactly_the_window_bands() -> None:
    sc = default_scenario()
    b = sc.building
    surf = {s.name: s for s in building_surfaces(b, sc.anchor_positions_m(), overlap_m=0.05)}
    facade = surf["facade"].rects
    assert all(ax == 1 and c == 0.0 for ax, c, _, _ in facade)
    x0, x1 = b.edge_x_m
    assert all(u == (x0 - 0.05, x1 + 0.05) for _, _, u, _ in facade)
    # z intervals covered by the facade = complement of the window bands
    zs = sorted(v for *_, v in facade)
    lo, hi = b.window_z_m(np.arange(b.n_floors))
    gaps = [(zs[i][1], zs[i + 1][0]) for i in range(len(zs) - 1)]
    np.testing.assert_allclose(gaps, np.stack([lo, hi], axis=1))
    assert zs[-1][1] == pytest.approx(b.top_z_m + 0.05)
    # slabs at every floor and the roof, overlapping the walls
    slabs = surf["slabs"].rects
    np.testing.assert_allclose([c for _, c, _, _ in slabs], b.floor_z_m(np.arange(b.n_floors + 1)))
    assert all(v == (-0.05, b.depth_m + 0.05) for *_, v in slabs)
    assert len([s for s in surf if s.startswith("partition")]) == len(b.partitions)
    v, f = surf["facade"].mesh()
    assert v.shape == (4 * len(facade), 3) and f.shape == (2 * len(facade), 3)


def test_settings_validation() -> None:
    with pytest.raises(ValueError, match="max_depth"):
        RaytraceSettings(max_depth=0)
    with pytest.raises(ValueError, match="samples_per_src"):
        RaytraceSettings(samples_per_src=10)


def test_cli_without_sionna_explains_how_to_install(monkeypatch, capsys) -> None:
    from diffpos_services.cli import main as cli
    from diffpos_services.raytrace import backend

    def missing() -> dict[str, str]:
        raise RaytraceUnavailable(f"sionna-rt is not installed (test): {INSTALL_HINT}")

    monkeypatch.setattr(backend, "check_sionna", missing)  # the CLI imports it from there
    assert cli.main(["raytrace", "paper", "--quick"]) == 3
    err = capsys.readouterr().err
    assert "pip install -e '.[raytrace]'" in err and "apt-get install libllvm19" in err


def test_cli_bad_input_is_a_clear_error(capsys) -> None:
    from diffpos_services.cli import main as cli

    assert cli.main(["raytrace", "no/such/scenario.toml"]) == 2
    assert "no such file" in capsys.readouterr().err
    assert cli.main(["raytrace", "paper", "--receivers", "0"]) == 2
    assert "--receivers" in capsys.readouterr().err


def test_cli_compare_prints_the_comparison(capsys) -> None:
    from diffpos_services.cli import main as cli

    assert cli.main(["raytrace", "--compare", str(DATA)]) == 0
    err = capsys.readouterr().err
    assert "Fermat check" in err and "first-arrival group agreement" in err
    c = compare_with_emulator(load_dataset(DATA))
    assert c["confusion"].sum() == c["links"] == 640
    assert 0.5 < c["found_emulator_fap"] <= 1 and c["class_agreement_found"] > c["class_agreement"]
