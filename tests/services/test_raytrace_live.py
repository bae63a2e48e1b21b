"""The ray-traced channel of the live loop (``--channel raytrace``).

The core (:mod:`diffpos.channel.traced`) against independent references: at a traced epoch
its first arrivals are those of ``diffpos raytrace``'s dataset path through the emulator's own
detector (:func:`diffpos_services.raytrace.evaluate.dataset_first_arrival`), with the same
noise draws; between epochs, the interpolated lengths of a ceiling reflection and a window-edge
diffraction are the closed forms (image method, :func:`diffpos.geometry.diffraction_point`) at
the actual positions. The cache key changes with every setting; without the extra, one error
names the install command (exit 3). The last test runs Sionna RT (skipped without the extra).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import subprocess
import sys

import numpy as np
import pytest
from diffpos_services.anchor.service import AnchorConfig, AnchorEmulator
from diffpos_services.emulate.options import EmulationOptions, channel_argv
from diffpos_services.errors import ConfigError
from diffpos_services.raytrace import live
from diffpos_services.raytrace.backend import INSTALL_HINT, RaytraceUnavailable, check_sionna
from diffpos_services.raytrace.dataset import RaytraceDataset
from diffpos_services.raytrace.evaluate import dataset_first_arrival

from diffpos.channel.traced import TracedLinks, paths_at, traced_first_arrivals
from diffpos.emulation import emulation_nodes, first_arrivals
from diffpos.geometry import diffraction_point
from diffpos.scenario import default_scenario

SCENARIO = default_scenario()
B = SCENARIO.building
LO_EDGE_Z = float(B.window_z_m(0)[0])  # floor 0's lower window edge


def _ceiling(p: np.ndarray) -> float:
    """The ceiling above a node."""
    return float(B.floor_z_m(int(B.floor_index(p[2])) + 1))


def _mirror_z(p: np.ndarray, z: float) -> np.ndarray:
    q = np.array(p, dtype=float)
    q[..., 2] = 2 * z - q[..., 2]
    return q


def _reflection_point(a: np.ndarray, n: np.ndarray, z: float) -> np.ndarray:
    """Where ``a -> plane z -> n`` reflects (image method)."""
    img = _mirror_z(n, z)
    s = (z - a[2]) / (img[2] - a[2])
    return a + s * (img - a)


def _edge_point(a: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, float]:
    x0, x1 = B.edge_x_m
    dp = diffraction_point(a, n, np.array([x0, 0.0, LO_EDGE_Z]), np.array([x1, 0.0, LO_EDGE_Z]))
    return np.asarray(dp.point_m), float(dp.length_m)


def _links(t_s: np.ndarray, anchor: np.ndarray, nodes: np.ndarray, *, seed: int = 0,
           drop: tuple[tuple[int, int, int], ...] = ()) -> TracedLinks:
    """Five paths per link with known geometry at each epoch (``drop``: (epoch, node, path)
    left out): LOS; a ceiling reflection; a lower-edge diffraction; the diffraction then a
    transmission (its point off the straight line: must not count); two random bends."""
    rng = np.random.default_rng(seed)
    e, n = nodes.shape[:2]
    k, d = 5, 3
    verts = np.full((e, n, k, d, 3), np.nan)
    bends = np.zeros((e, n, k, d), bool)
    length = np.zeros((e, n, k))
    rand = rng.uniform([-15, -5, 0], [15, 20, 12], (n, 2, 3))
    for i in range(e):
        for j in range(n):
            a, p = anchor[i], nodes[i, j]
            r = _reflection_point(a, p, _ceiling(p))
            q, lq = _edge_point(a, p)
            verts[i, j, 1, 0], bends[i, j, 1, 0] = r, True
            verts[i, j, 2, 0], bends[i, j, 2, 0] = q, True
            verts[i, j, 3, 0], bends[i, j, 3, 0] = q, True
            verts[i, j, 3, 1] = 0.5 * (q + p) + np.array([0.0, 0.0, 0.7])  # a transmission
            verts[i, j, 4, :2], bends[i, j, 4, :2] = rand[j], True
            length[i, j] = [np.linalg.norm(p - a), np.linalg.norm(_mirror_z(p, _ceiling(p)) - a),
                            lq, lq, np.linalg.norm(rand[j, 0] - a)
                            + np.linalg.norm(rand[j, 1] - rand[j, 0])
                            + np.linalg.norm(p - rand[j, 1])]
    valid = np.ones((e, n, k), bool)
    for i, j, kk in drop:
        valid[i, j, kk] = False
    gain = rng.uniform(-120, -60, (e, n, k)).astype(np.float32).astype(np.float64)
    key = np.broadcast_to(np.arange(1, k + 1) * 1009, (e, n, k)).copy()
    return TracedLinks(t_s=t_s, anchor_m=anchor, nodes_m=nodes, valid=valid,
                       key=np.where(valid, key, 0), length_m=np.where(valid, length, np.nan),
                       gain_db=np.where(valid, gain, -np.inf), vertices_m=verts,
                       bends=bends & valid[..., None])


def _walk(t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A static anchor and 6 nodes walking at 1.2 m/s along x and y on floors 0 and 1."""
    anchor = np.broadcast_to(np.array([-15.0, -20.0, 1.0]), (t_s.size, 3)).copy()
    start = np.array([[-12, 2, 5.5], [-3, 6, 5.5], [4, 13, 5.5], [10, 1, 5.5], [-8, 8, 8.5],
                      [6, 4, 8.5]], float)
    vel = np.array([[1.2, 0, 0], [0, 1.2, 0], [-1.2, 0, 0], [0, 0.8, 0], [0.9, 0.8, 0],
                    [-0.7, 1.0, 0]])
    return anchor, start[None] + t_s[:, None, None] * vel[None]


def _zenith(v: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(v[..., 2] / np.linalg.norm(v, axis=-1)))


@pytest.mark.parametrize("hpbw", [None, 30.0])
def test_first_arrival_at_a_traced_epoch_is_the_dataset_detectors(hpbw) -> None:
    radio = dataclasses.replace(SCENARIO.radio, tx_hpbw_deg=hpbw, rx_hpbw_deg=hpbw,
                                rx_peak_deg=75.0)
    scenario = dataclasses.replace(SCENARIO, radio=radio)
    t = np.array([0.0, 0.5])
    anchor, nodes = _walk(t)
    links = _links(t, anchor, nodes, seed=3, drop=((0, 2, 0), (0, 2, 1), (0, 4, 0)))
    # the same paths as a `diffpos raytrace` dataset (one anchor), angles computed here
    first = np.where(links.bends[0, ..., 0, None], links.vertices_m[0, :, :, 0], nodes[0, :, None])
    last_idx = np.array([[np.flatnonzero(b)[-1] if b.any() else -1 for b in row]
                         for row in links.bends[0]])
    last = np.where((last_idx >= 0)[..., None], np.take_along_axis(
        links.vertices_m[0], np.maximum(last_idx, 0)[..., None, None], axis=2)[:, :, 0],
        anchor[0])
    aod, aoa = _zenith(first - anchor[0]), _zenith(last - nodes[0][:, None])
    ds = RaytraceDataset(
        nodes_m=nodes[0], anchors_m=anchor[:1], anchor_ids=("uav1",),
        path_valid=links.valid[0][:, None], path_length_m=links.length_m[0][:, None],
        path_gain_db=links.gain_db[0][:, None].astype(np.float32),
        path_aod_deg=aod[:, None].astype(np.float32), path_aoa_deg=aoa[:, None].astype(np.float32),
        path_chain=np.zeros((6, 1, 5), np.uint16), path_class=np.ones((6, 1, 5), np.int8),
        path_vertex_m=np.zeros((6, 1, 5, 3), np.float32),
        metadata={"scenario": scenario.to_dict()})
    ref = dataset_first_arrival(ds, radio=radio, rng=np.random.default_rng(11))
    got = traced_first_arrivals(links, t[:1], anchor[:1], nodes[:1], radio=radio,
                                rng=np.random.default_rng(11))
    assert ref.detected[:, 0].sum() >= 5
    np.testing.assert_array_equal(got.detected[0], ref.detected[:, 0])
    det = ref.detected[:, 0]
    np.testing.assert_allclose(got.true_path_m[0][det], ref.true_path_m[det, 0], atol=1e-9)
    np.testing.assert_allclose(got.snr_db[0][det], ref.snr_db[det, 0], atol=1e-4)
    np.testing.assert_allclose(got.sigma_m[0][det], ref.sigma_m[det, 0], rtol=1e-5)
    np.testing.assert_allclose(got.range_m[0][det], ref.range_m[det, 0], atol=1e-7)
    # the first-arriving path's identity is the dataset's slot
    np.testing.assert_array_equal(got.key[0][det], (ref.slot[det, 0] + 1) * 1009)


def test_between_epochs_lengths_are_the_closed_forms_at_the_actual_positions() -> None:
    t = np.array([0.0, 0.5, 1.0])
    anchor, nodes = _walk(t)
    links = _links(t, anchor, nodes)
    tq = np.array([0.1, 0.25, 0.4, 0.77])
    aq, nq = _walk(tq)
    p = paths_at(links, tq, aq, nq)
    for b in range(tq.size):
        for j in range(6):
            a, n = aq[b], nq[b, j]
            ok = p.valid[b, j]
            assert ok[:5].all() and not ok[5:].any()  # every path matched: one slot each
            los, refl = np.linalg.norm(n - a), np.linalg.norm(_mirror_z(n, _ceiling(n)) - a)
            edge = _edge_point(a, n)[1]
            np.testing.assert_allclose(p.length_m[b, j, :4], [los, refl, edge, edge], atol=2e-5)
    # interpolating the lengths themselves would be off by centimetres here: the point of
    # recomputing them through interpolated interaction points
    lin = 0.5 * (links.length_m[0] + links.length_m[1])
    mid = paths_at(links, [0.25], *map(lambda x: x[:1], _walk(np.array([0.25]))))
    assert np.max(np.abs(lin[:, 1] - mid.length_m[0, :, 1])) > 1e-3


def test_paths_traced_at_one_epoch_only_come_from_the_nearer_one() -> None:
    t = np.array([0.0, 1.0])
    anchor, nodes = _walk(t)
    links = _links(t, anchor, nodes, drop=((1, 0, 1), (0, 1, 2)))  # gone / appears
    for tq, near_first in ((0.3, True), (0.7, False)):
        aq, nq = _walk(np.array([tq]))
        p = paths_at(links, [tq], aq, nq)
        keys0 = set(p.key[0, 0][p.valid[0, 0]])
        keys1 = set(p.key[0, 1][p.valid[0, 1]])
        assert (2 * 1009 in keys0) == near_first  # node 0's reflection: traced at t=0 only
        assert (3 * 1009 in keys1) != near_first  # node 1's diffraction: at t=1 only
        # the reflection of node 0 is unmatched: its traced point, the actual end points
        if near_first:
            k = list(p.key[0, 0]).index(2 * 1009)
            r = links.vertices_m[0, 0, 1, 0]
            want = np.linalg.norm(r - aq[0]) + np.linalg.norm(nq[0, 0] - r)
            assert abs(p.length_m[0, 0, k] - want) < 1e-12
    with pytest.raises(ValueError, match="outside the traced epochs"):
        paths_at(links, [1.2], *map(lambda x: x[:1], _walk(np.array([1.2]))))


def test_raytrace_channel_draws_the_emulators_noise_stream() -> None:
    """The same generator calls as the emulator channel: the streams stay aligned."""
    t = np.array([0.0, 0.5])
    anchor, nodes = _walk(t)
    links = _links(t, anchor, nodes)
    tq = np.array([0.2])
    aq, nq = _walk(tq)
    r_emu, r_rt = np.random.default_rng(4), np.random.default_rng(4)
    first_arrivals(aq, nq, SCENARIO, channel="emulator", rng=r_emu)
    out = first_arrivals(aq, nq, SCENARIO, channel="raytrace", rng=r_rt, traced=links, t_s=tq)
    assert r_emu.bit_generator.state == r_rt.bit_generator.state
    assert out[0].shape == (1, 6) and out[3].all()
    with pytest.raises(ValueError, match="needs the traced paths"):
        first_arrivals(aq, nq, SCENARIO, channel="raytrace", rng=r_rt)


def test_anchor_emulator_serves_the_traced_links() -> None:
    nodes = emulation_nodes(SCENARIO)
    t = np.arange(0.0, 1.01, 0.5)
    anchor = np.broadcast_to(SCENARIO.anchors[0].trajectory.position_m(0.0), (3, 3)).copy()
    pos = np.stack([np.asarray(tr.position_m(t), float).reshape(3, 3) for _, tr in nodes], 1)
    links = _links(t, anchor, pos)
    cfg = AnchorConfig(anchor_id="uav1", channel="raytrace", wait_start=True, seed=2)
    emu = AnchorEmulator(SCENARIO, cfg, traced=links)
    from diffpos.emulation import TimeBase
    tb = TimeBase(0, 0, 1.0, 10**9)
    t_true, (r, sg, _snr, det) = emu.measure_block(3, 1, tb)
    t_s = tb.t_s(t_true).astype(float)
    ref = traced_first_arrivals(links, t_s, anchor[:1], np.stack(
        [np.asarray(tr.position_m(t_s), float).reshape(1, 3) for _, tr in nodes], 1),
        radio=SCENARIO.radio, rng=None)
    np.testing.assert_allclose(r[0] - ref.true_path_m[0], 0.0, atol=6 * sg[0].max())
    np.testing.assert_array_equal(det[0], ref.detected[0])
    with pytest.raises(ConfigError, match="--wait-start"):
        AnchorConfig(anchor_id="uav1", channel="raytrace").check()
    with pytest.raises(ConfigError, match="needs its traced paths"):
        AnchorEmulator(SCENARIO, cfg)


# ----------------------------------------------------------------------------- cache, options
def test_cache_key_changes_with_every_setting() -> None:
    nodes = emulation_nodes(SCENARIO)
    st = live.LiveTraceSettings()
    times = live.grid_times(20.0, st.step_s)
    base = live.cache_key(SCENARIO, "uav1", nodes, times, st)
    assert base == live.cache_key(SCENARIO, "uav1", nodes, times, st)  # deterministic
    other_b = dataclasses.replace(B, partitions=B.partitions[:1])
    variants = {
        "samples": live.cache_key(SCENARIO, "uav1", nodes, times,
                                  dataclasses.replace(st, samples=st.samples + 1)),
        "depth": live.cache_key(SCENARIO, "uav1", nodes, times, dataclasses.replace(st, depth=5)),
        "step": live.cache_key(SCENARIO, "uav1", nodes, live.grid_times(20.0, 0.25),
                               dataclasses.replace(st, step_s=0.25)),
        "step only": live.cache_key(SCENARIO, "uav1", nodes, times,
                                    dataclasses.replace(st, step_s=0.25)),
        "sionna seed": live.cache_key(SCENARIO, "uav1", nodes, times,
                                      dataclasses.replace(st, seed=2)),
        "overlap": live.cache_key(SCENARIO, "uav1", nodes, times,
                                  dataclasses.replace(st, overlap_m=0.04)),
        "duration": live.cache_key(SCENARIO, "uav1", nodes, live.grid_times(30.0, st.step_s), st),
        "anchor": live.cache_key(SCENARIO, "uav2", nodes, times, st),
        "nodes": live.cache_key(SCENARIO, "uav1", nodes[:5], times, st),
        "scenario": live.cache_key(dataclasses.replace(SCENARIO, building=other_b), "uav1",
                                   nodes, times, st),
        "radio": live.cache_key(dataclasses.replace(SCENARIO, radio=dataclasses.replace(
            SCENARIO.radio, frequency_hz=26e9)), "uav1", nodes, times, st),
        "trajectory": live.cache_key(SCENARIO, "uav1", [(nodes[0][0], nodes[1][1]), *nodes[1:]],
                                     times, st),
    }
    assert all(v != base for v in variants.values()), [k for k, v in variants.items() if v == base]
    assert len(set(variants.values())) == len(variants)


def test_cache_key_ignores_the_emulated_channel_order() -> None:
    """``Radio.channel_max_order`` (the emulator's channel, not Sionna's) is no part of a
    trace: every order gives the key an order-2 scenario had (the caches written before the
    default became 3 stay valid); another radio field still changes it."""
    nodes = emulation_nodes(SCENARIO)
    st = live.LiveTraceSettings()
    times = live.grid_times(20.0, st.step_s)

    def key(**radio):
        sc = dataclasses.replace(SCENARIO, radio=dataclasses.replace(SCENARIO.radio, **radio))
        return live.cache_key(sc, "uav1", nodes, times, st)

    assert key(channel_max_order=2) == key(channel_max_order=3) == key(channel_max_order=4)
    assert key(channel_max_order=3, detection_snr_db=-9.0) != key(channel_max_order=3)


def test_cache_file_round_trip_never_overwrites(tmp_path) -> None:
    t = np.array([0.0, 0.5])
    links = _links(t, *_walk(t))
    path = live.save_links(tmp_path / "a.npz", links, {"format": live.LIVE_FORMAT, "key": "k1"})
    back, meta = live.load_links(path, key="k1")
    assert meta["key"] == "k1"
    for f in dataclasses.fields(TracedLinks):
        np.testing.assert_allclose(np.asarray(getattr(back, f.name), float),
                                   np.asarray(getattr(links, f.name), float), rtol=1e-6)
    with pytest.raises(FileExistsError):
        live.save_links(path, links, {"format": live.LIVE_FORMAT, "key": "k2"})
    with pytest.raises(ValueError, match="traced for key k1"):
        live.load_links(path, key="k2")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]  # no temporary left


def test_options_and_anchor_argv() -> None:
    o = EmulationOptions(channel="raytrace", duration_s=20.0, raytrace_samples=2e5)
    o.check()
    assert channel_argv(o) == ["--channel", "raytrace", "--raytrace-duration-s", "20.0",
                               "--raytrace-samples", "200000.0"]
    assert channel_argv(EmulationOptions()) == ["--channel", "emulator"]
    with pytest.raises(ConfigError, match="only with --channel raytrace"):
        EmulationOptions(raytrace_depth=4).check()
    with pytest.raises(ConfigError, match="--raytrace-depth"):
        live.live_settings(depth=0)
    with pytest.raises(ConfigError, match="--raytrace-step-s"):
        live.live_settings(step_s=-1.0)
    with pytest.raises(ConfigError, match="--raytrace-samples"):
        live.live_settings(samples=10)
    assert live.live_settings() == live.LiveTraceSettings()
    from diffpos_services.cli.main import main
    assert main(["emulate", "--channel", "raytrace", "--raytrace-depth", "0"]) == 2


def test_help_states_the_defaults() -> None:
    import argparse

    from diffpos_services.cli.raytrace_options import add_raytrace_arguments
    p = argparse.ArgumentParser()
    add_raytrace_arguments(p)
    text = " ".join(p.format_help().split())
    assert f"default {live.DEFAULT_SAMPLES:.0e}".replace("e+0", "e") in text
    assert f"(default {live.DEFAULT_DEPTH};" in text
    assert f"[s] (default {live.DEFAULT_STEP_S:g})" in text


@pytest.mark.slow
def test_without_the_extra_one_error_names_the_install_command(monkeypatch, tmp_path) -> None:
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # import mitsuba -> ImportError
    monkeypatch.setitem(sys.modules, "drjit", None)
    monkeypatch.setenv("DIFFPOS_RAYTRACE_CACHE", str(tmp_path))
    with pytest.raises(RaytraceUnavailable) as info:
        live.prepare_links(SCENARIO, emulation_nodes(SCENARIO), duration_s=1.0,
                           settings=live.LiveTraceSettings())
    assert "pip install -e '.[raytrace]'" in str(info.value) and "libllvm19" in str(info.value)
    assert INSTALL_HINT in str(info.value) and info.value.exit_code == 3
    # the command, in a process of its own without the extra
    code = ("import sys; sys.modules['mitsuba'] = sys.modules['drjit'] = None; "
            "from diffpos_services.cli.main import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.run([sys.executable, "-c", code, "emulate", "--channel", "raytrace",
                           "--duration", "1", "--record", "off", "--dashboard", "off",
                           "--no-progress", "--log-format", "text"],
                          capture_output=True, text=True, timeout=120, check=False,
                          env={**os.environ, "DIFFPOS_RAYTRACE_CACHE": str(tmp_path)})
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert proc.stderr.count("pip install -e '.[raytrace]'") == 1, proc.stderr[-2000:]
    assert list(tmp_path.iterdir()) == []  # nothing written


# ----------------------------------------------------------------------------- Sionna RT
@functools.lru_cache(maxsize=1)
def _sionna() -> str | None:
    try:
        check_sionna()
    except RaytraceUnavailable as exc:  # pragma: no cover - depends on the environment
        return str(exc)
    return None


@pytest.mark.slow
def test_sionna_trace_of_a_short_run(tmp_path) -> None:
    if _sionna() is not None:  # pragma: no cover - depends on the environment
        pytest.skip(f"Sionna RT unavailable, ray-tracer test skipped: {_sionna()}")
    nodes = emulation_nodes(SCENARIO)[:3]
    st = live.LiveTraceSettings(samples=30_000, depth=4, step_s=0.1)
    prep = live.prepare_links(SCENARIO, nodes, duration_s=0.2, settings=st,
                              anchor_ids=["uav3"], directory=tmp_path)
    assert prep.traced == ("uav3",)
    links = prep.links["uav3"]
    assert links.valid.shape[:2] == (3, 3) and links.valid.sum() >= 20
    # at a traced epoch the recomputed lengths (vertices, bends) are Sionna's c tau
    for e in range(3):
        p = paths_at(links, links.t_s[e:e + 1], links.anchor_m[e:e + 1], links.nodes_m[e:e + 1])
        for i in range(3):
            got = dict(zip(p.key[0, i][p.valid[0, i]], p.length_m[0, i][p.valid[0, i]],
                           strict=True))
            want = dict(zip(links.key[e, i][links.valid[e, i]],
                            links.length_m[e, i][links.valid[e, i]], strict=True))
            assert got.keys() == want.keys()
            assert max(abs(got[k] - want[k]) for k in want) < 1e-4
    # keys recognise the same paths at the next epoch (10 cm later) ...
    same = [len(set(links.key[0, i][links.valid[0, i]]) & set(links.key[1, i][links.valid[1, i]]))
            / max(links.valid[0, i].sum(), 1) for i in range(3)]
    assert min(same) > 0.5, same
    # ... and interpolating epochs 0 and 2 gives epoch 1's traced lengths to 0.1 mm for the
    # paths traced at all three (a path traced at one end only is that end's: mm off)
    sub = TracedLinks(**{f.name: getattr(links, f.name)[[0, 2]]
                         for f in dataclasses.fields(TracedLinks)})
    mid = paths_at(sub, links.t_s[1:2], links.anchor_m[1:2], links.nodes_m[1:2])
    errs = []
    for i in range(3):
        at = [dict(zip(links.key[e, i][links.valid[e, i]], links.length_m[e, i][links.valid[e, i]],
                       strict=True)) for e in range(3)]
        common = at[0].keys() & at[1].keys() & at[2].keys()
        errs += [abs(ln - at[1][k]) for k, ln, v in zip(mid.key[0, i], mid.length_m[0, i],
                                                       mid.valid[0, i], strict=True)
                 if v and k in common]
    assert len(errs) >= 10 and max(errs) < 1e-4, (len(errs), max(errs))
    # a second call is a cache hit with the same arrays
    again = live.prepare_links(SCENARIO, nodes, duration_s=0.2, settings=st,
                               anchor_ids=["uav3"], directory=tmp_path)
    assert again.traced == () and again.keys == prep.keys
    np.testing.assert_array_equal(again.links["uav3"].key, links.key)
