"""Rerun dashboard: .rrd files are read back with Rerun's own reader and checked value by value.

References are independent of the logging code: positions come from the published messages,
errors are recomputed here from the truth messages, the diffraction point is checked
against a brute-force minimisation of the path length, ellipsoids against the covariance
they were built from, exclusion events against a plain loop over the messages.
"""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun.chunk as rc
from diffpos_services.dashboard.blueprint import default_blueprint
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.common import (
    _EXCLUDED_COLOR,
    APP_ID,
    BOOKKEEPING_REASONS,
    CHI2_3DOF_95,
    anchor_color,
)
from diffpos_services.dashboard.convert import _kind_scanner, mcap_to_rrd, rrd_rows
from diffpos_services.dashboard.geometry import ellipsoid_axes
from diffpos_services.dashboard.scenario import building_for_option, building_from_scenario_file
from diffpos_services.dashboard.stream import Dashboard, write_rrd_from_messages
from diffpos_services.replay.synthetic import display_run
from diffpos_services.wire import messages as m
from diffpos_services.wire.keys import Keys


def synthetic_run(**kw):
    """The dashboard's synthetic run (``replay.synthetic.display_run``), its building as
    the outline the dashboard draws."""
    building, msgs = display_run(**kw)
    return BuildingOutline.from_object(building), msgs


RERUN_CLI = Path(sys.executable).with_name("rerun")


# ------------------------------------------------------------------------------- helpers
read_rrd = rrd_rows


@pytest.fixture(scope="module")
def run():
    building, msgs = synthetic_run(n_anchors=5, n_nodes=4, duration_s=8.0, rate_hz=10.0, seed=3)
    return building, msgs


@pytest.fixture(scope="module")
def bulk(run, tmp_path_factory):
    building, msgs = run
    path = tmp_path_factory.mktemp("rrd") / "bulk.rrd"
    counts = write_rrd_from_messages(msgs, path, building=building, recording_id="bulk")
    return path, counts, read_rrd(path)


def of(msgs, name):
    return [x for x in msgs if type(x).__name__ == name]


# ------------------------------------------------------------------------------- geometry
def test_ellipsoid_axes_rebuild_the_covariance():
    rng = np.random.default_rng(7)
    a = rng.normal(size=(50, 3, 3))
    cov = a @ np.swapaxes(a, 1, 2) + 0.05 * np.eye(3)
    cov[3] = np.nan
    half, quat, valid = ellipsoid_axes(cov, scale=2.0)
    from scipy.spatial.transform import Rotation

    assert not valid[3] and valid.sum() == 49
    rot = Rotation.from_quat(quat[valid]).as_matrix()
    diag = ((half[valid] / 2.0) ** 2)[..., None] * np.eye(3)
    rebuilt = rot @ diag @ np.swapaxes(rot, 1, 2)
    np.testing.assert_allclose(rebuilt, cov[valid], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)


def test_default_scale_is_the_95_percent_region():
    from scipy.stats import chi2

    assert CHI2_3DOF_95 == pytest.approx(chi2.ppf(0.95, 3), rel=1e-12)


def test_building_outline_from_scenario_building():
    from diffpos.scenario import default_scenario

    b = default_scenario().building
    o = BuildingOutline.from_object(b)
    assert (o.x_min_m, o.x_max_m) == b.edge_x_m
    assert o.first_floor_z_m == b.first_floor_z_m and o.n_floors == b.n_floors
    z = np.linspace(b.first_floor_z_m + 0.01, b.top_z_m - 0.01, 97)
    np.testing.assert_array_equal(o.floor_of(z), b.floor_index(z))
    np.testing.assert_allclose(
        o.upper_edge_z_m(np.arange(b.n_floors)), b.window_z_m(np.arange(b.n_floors))[1]
    )


def test_bad_building_names_the_field():
    with pytest.raises(ValueError, match="depth_m"):
        BuildingOutline.from_object(
            {
                "x_extent_m": (0, 1),
                "n_floors": 2,
                "floor_height_m": 3,
                "sill_height_m": 1,
                "window_height_m": 1,
            }
        )
    with pytest.raises(ValueError, match="x_max_m"):
        BuildingOutline(1.0, 0.0, 5.0, 2, 3.0, 1.0, 1.0)


# ------------------------------------------------------------------------------- bulk .rrd
def test_entities_blueprint_and_timeline(bulk, run):
    path, counts, rows = bulk
    _, msgs = run
    nodes = sorted({e.node_id for e in of(msgs, "PositionEstimate")})
    anchors = sorted({a.anchor_id for a in of(msgs, "AnchorState")})
    expected = {
        "/world/building/floors",
        "/world/building/windows",
        "/events",
        "/floors",
        "/metrics/gating/excluded",
        "/metrics/gating/used",
        "/metrics/fusion/gated",
    }
    for n in nodes:
        expected |= {f"/world/nodes/{n}/{e}" for e in ("truth", "estimate")}
        expected.add(f"/world/paths/{n}")
        expected |= {f"/metrics/{s}/{n}" for s in ("error_3d_m", "error_z_m", "peb_m")}
    for a in anchors:
        expected |= {f"/world/anchors/{a}", f"/world/anchors/{a}/trail", f"/metrics/residual_m/{a}"}
    assert expected <= set(rows)
    reader = rc.RrdReader(path)
    assert [s.kind for s in reader.blueprints()] == ["blueprint"], "blueprint embedded"
    assert reader.recordings()[0].recording_id == "bulk"
    # measurement timeline: estimate rows carry exactly the published t_ns
    t_pub = sorted(e.t_ns for e in of(msgs, "PositionEstimate") if e.node_id == nodes[0])
    assert [t for t, _ in rows[f"/world/nodes/{nodes[0]}/estimate"]] == t_pub
    assert counts["estimate"] == len(of(msgs, "PositionEstimate"))


def test_rerun_cli_verifies_the_file(bulk):
    path, _, _ = bulk
    res = subprocess.run(
        [str(RERUN_CLI), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60
    )
    assert res.returncode == 0, res.stderr


def test_estimate_positions_equal_the_published_ones(bulk, run):
    _, _, rows = bulk
    _, msgs = run
    last_fix: dict[str, tuple] = {}
    for e in sorted(of(msgs, "PositionEstimate"), key=lambda x: x.t_ns):
        logged = dict(rows[f"/world/nodes/{e.node_id}/estimate"])[e.t_ns]
        if e.position_m is None:
            # no position: the marker stays on the node's last fix (grey, label with the age
            # of that fix), or there is none before the first fix; never an ellipsoid
            prev = last_fix.get(e.node_id)
            if prev is None:
                assert logged["Points3D:positions"] == []
            else:
                np.testing.assert_allclose(logged["Points3D:positions"][0], prev[1], atol=6e-5)
                assert logged["Points3D:labels"][0] == f"{e.node_id}?"
            assert (
                dict(rows[f"/world/nodes/{e.node_id}/estimate"])[e.t_ns]["Ellipsoids3D:half_sizes"]
                == []
            )
        else:
            last_fix[e.node_id] = (e.t_ns, e.position_m)
            np.testing.assert_allclose(
                logged["Points3D:positions"][0], e.position_m, rtol=0, atol=2e-6 * 30
            )


def test_errors_and_peb_against_the_truth(bulk, run):
    _, _, rows = bulk
    _, msgs = run
    truth = {(t.id, t.t_ns): np.array(t.position_m) for t in of(msgs, "GroundTruth")}
    n_checked = 0
    for e in of(msgs, "PositionEstimate"):
        e3 = dict(rows[f"/metrics/error_3d_m/{e.node_id}"])
        ez = dict(rows[f"/metrics/error_z_m/{e.node_id}"])
        peb = dict(rows[f"/metrics/peb_m/{e.node_id}"])
        if e.position_m is None:
            # no fake value for a missing fix: a clear (a gap in the plotted line)
            for series in (e3, peb):
                assert "Scalars:scalars" not in series[e.t_ns]
                assert series[e.t_ns]["Clear:is_recursive"] == [False]
            continue
        diff = np.array(e.position_m) - truth[(e.node_id, e.t_ns)]
        assert e3[e.t_ns]["Scalars:scalars"][0] == pytest.approx(np.linalg.norm(diff), abs=1e-9)
        assert ez[e.t_ns]["Scalars:scalars"][0] == pytest.approx(diff[2], abs=1e-9)
        assert peb[e.t_ns]["Scalars:scalars"][0] == pytest.approx(e.peb_m, abs=1e-12)
        n_checked += 1
    assert n_checked > 100


def test_uncertainty_ellipsoid_matches_the_covariance(bulk, run):
    from scipy.spatial.transform import Rotation

    _, _, rows = bulk
    _, msgs = run
    e = next(
        x for x in of(msgs, "PositionEstimate") if x.covariance_m2 is not None and x.epoch == 17
    )
    row = dict(rows[f"/world/nodes/{e.node_id}/estimate"])[e.t_ns]
    half = np.array(row["Ellipsoids3D:half_sizes"][0]) / np.sqrt(CHI2_3DOF_95)
    rot = Rotation.from_quat(row["Ellipsoids3D:quaternions"][0]).as_matrix()
    np.testing.assert_allclose(rot @ np.diag(half**2) @ rot.T, np.array(e.covariance_m2), atol=1e-5)
    np.testing.assert_allclose(row["Ellipsoids3D:centers"][0], e.position_m, atol=1e-4)


def test_diffraction_paths_cross_the_window_edge_at_the_shortest_point(bulk, run):
    """Each strip is anchor -> Q -> estimate with Q on the estimated floor's upper edge
    minimising |A - Q| + |Q - N| (brute force over 20001 points of the edge)."""
    _, _, rows = bulk
    building, msgs = run
    n_strips = 0
    for e in of(msgs, "PositionEstimate")[::3]:
        row = dict(rows[f"/world/paths/{e.node_id}"]).get(e.t_ns)
        if row is None or e.position_m is None:
            continue
        strips = row["LineStrips3D:strips"]
        gated = [x for x in e.excluded if x.reason not in BOOKKEEPING_REASONS]
        assert len(strips) == len(e.used_anchors) + len(gated)
        z_edge = building.upper_edge_z_m(e.floor_index)
        xs = np.linspace(building.x_min_m, building.x_max_m, 20001)
        grid = np.stack([xs, np.zeros_like(xs), np.full_like(xs, z_edge)], axis=1)
        node = np.array(e.position_m)
        for a_pos, q, n_pos in strips:
            a_pos, q = np.array(a_pos), np.array(q)
            np.testing.assert_allclose(n_pos, node, atol=1e-4)
            assert q[1] == 0.0 and q[2] == pytest.approx(z_edge, abs=1e-5)
            lengths = np.linalg.norm(grid - a_pos, axis=1) + np.linalg.norm(grid - node, axis=1)
            best = lengths.min()
            got = np.linalg.norm(q - a_pos) + np.linalg.norm(q - node)
            assert best - 1e-6 <= got <= best + 1e-4
            n_strips += 1
    assert n_strips > 20


def test_paths_are_drawn_over_the_edge_the_fusion_models(run, tmp_path):
    """The fusion's ``--edge auto`` rule (``first_arrival_edge``) gives the lower edge for the
    default (paper) scenario, whose UAVs fly below the windows; the dashboard draws the paths
    over that edge (it drew the upper one before), and over the upper edge when the rule says
    so or without a scenario."""
    import dataclasses

    from diffpos.scenario import default_scenario, first_arrival_edge

    assert first_arrival_edge(default_scenario())[0] == "lower"
    assert building_from_scenario_file("default").edge == "lower"
    assert building_for_option("paper").edge == first_arrival_edge(default_scenario())[0]
    assert BuildingOutline.from_object(default_scenario().building).edge == "upper"
    building, msgs = run
    for edge in ("upper", "lower"):
        b = dataclasses.replace(building, edge=edge)
        assert b == building  # the edge is the model's, not the building's geometry
        out = write_rrd_from_messages(msgs, tmp_path / f"{edge}.rrd", building=b)
        rows = rrd_rows(tmp_path / f"{edge}.rrd")
        assert out["estimate"]
        n_strips = 0
        for e in of(msgs, "PositionEstimate"):
            row = dict(rows[f"/world/paths/{e.node_id}"]).get(e.t_ns)
            if row is None or e.position_m is None:
                continue
            k = e.floor_index
            z_sill = b.first_floor_z_m + k * b.floor_height_m + b.sill_height_m
            want = z_sill if edge == "lower" else z_sill + b.window_height_m
            for _a, q, _n in row["LineStrips3D:strips"]:
                assert q[2] == pytest.approx(want, abs=1e-5)
                n_strips += 1
        assert n_strips > 20


def test_excluded_paths_are_red_and_used_ones_in_anchor_colour(bulk, run):
    _, _, rows = bulk
    _, msgs = run
    e = next(
        x
        for x in of(msgs, "PositionEstimate")
        if any(ex.reason == "RAIM" for ex in x.excluded)
        and x.position_m is not None
        and x.t_ns in dict(rows[f"/world/paths/{x.node_id}"])
    )
    row = dict(rows[f"/world/paths/{e.node_id}"])[e.t_ns]
    colors = row["LineStrips3D:colors"]

    def rgba(c):
        return [(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255, c & 255]

    gated = [x.anchor_id for x in e.excluded if x.reason not in BOOKKEEPING_REASONS]
    assert gated, "pick a fix with a gated anchor"
    order = sorted([(a, True) for a in e.used_anchors] + [(a, False) for a in gated])
    got = sorted(tuple(rgba(c)) for c in colors)
    want = sorted(
        tuple(anchor_color(a)) if used else tuple(_EXCLUDED_COLOR) for a, used in order
    )
    assert got == want


def test_exclusion_and_status_events_match_a_plain_loop(bulk, run):
    """Events (text and level) against a plain loop over the messages: an event when an anchor
    becomes excluded or changes reason, when it is used again, when the status changes;
    fusion bookkeeping reasons are DEBUG, gating WARN, unidentifiable geometry ERROR."""
    _, _, rows = bulk
    _, msgs = run
    bookkeeping = {"NOT_REPORTED", "NOT_DETECTED", "NO_ANCHOR_STATE", "STALE", "ANCHOR_LOST",
                   "MISSING", "NOT_USED"}  # fmt: skip
    good = {"OK", "OK_UNVERIFIED"}
    expected = []
    last: dict[tuple[str, str], str] = {}
    status: dict[str, str] = {}
    for e in sorted(of(msgs, "PositionEstimate"), key=lambda x: (x.t_ns, x.node_id)):
        now = {a: "" for a in e.used_anchors} | {x.anchor_id: x.reason for x in e.excluded}
        for a, reason in now.items():
            before = last.get((e.node_id, a), "")
            if reason and reason != before:
                level = "DEBUG" if reason in bookkeeping else "WARN"
                expected.append((f"node {e.node_id}: anchor {a} excluded ({reason})", level))
            elif not reason and before:
                level = "DEBUG" if before in bookkeeping else "INFO"
                expected.append((f"node {e.node_id}: anchor {a} used again", level))
            last[(e.node_id, a)] = reason
        before = status.get(e.node_id, "OK")
        if before != e.status:
            if e.status == "NOT_IDENTIFIABLE":
                level = "ERROR"
            elif e.status in good:
                level = "DEBUG" if before in good else "INFO"
            else:
                level = "WARN"
            expected.append((f"node {e.node_id}: status {e.status}", level))
        status[e.node_id] = e.status
    texts = [
        (t, lv)
        for _, r in rows["/events"]
        for t, lv in zip(r["TextLog:text"], r["TextLog:level"], strict=True)
    ]
    got = [(t.split(" (unidentifiable")[0], lv) for t, lv in texts if t.startswith("node ")]
    assert sorted(got) == sorted(expected)
    levels = {lv for _, lv in expected}
    assert {"WARN", "ERROR", "INFO", "DEBUG"} <= levels, "the synthetic run exercises every level"
    assert any("NOT_IDENTIFIABLE (unidentifiable geometry)" in t for t, _ in texts)
    # from the fusion's live-anchor set: DEBUG (the liveliness events say lost or normal end)
    assert ("fusion no longer sees anchor uav5", "DEBUG") in texts


def test_estimates_with_negative_time_are_dropped_with_an_error_event(run, tmp_path):
    """Seen in a real run: an int64 overflow in the fusion gave t_ns < 0; such fixes must not
    stretch the timeline back to 1929."""
    import msgspec

    building, msgs = run
    ests = [e for e in of(msgs, "PositionEstimate") if e.node_id == "n02"][:30]
    broken = [msgspec.structs.replace(e, t_ns=-1279199486163474944) for e in ests[:4]]
    path = tmp_path / "neg.rrd"
    write_rrd_from_messages([*ests[4:], *broken], path, building=building)
    rows = read_rrd(path)
    times = [t for t, _ in rows["/world/nodes/n02/estimate"]]
    assert times == [e.t_ns for e in ests[4:]]
    errs = [
        (t, r["TextLog:text"][0]) for t, r in rows["/events"] if r["TextLog:level"] == ["ERROR"]
    ]
    assert errs == [
        (ests[-1].t_ns, "4 estimates with a negative t_ns dropped (invalid time from the fusion)")
    ]


def test_floor_table_reports_wrong_floors(bulk, run):
    """Per floor, who is there: each node on the floor of its latest fix with a position
    (reference: the published estimates), wrong floors marked with the true one."""
    _, _, rows = bulk
    t_last, row = rows["/floors"][-1]
    text = row["TextDocument:text"][0]
    _, msgs = run
    latest = {}
    for e in sorted(of(msgs, "PositionEstimate"), key=lambda x: x.t_ns):
        if e.t_ns <= t_last and e.position_m is not None:
            latest[e.node_id] = e
    truth = {t.id: t.floor_index for t in of(msgs, "GroundTruth")}
    hits = sum(latest[n].floor_index == truth[n] for n in latest)
    assert f"{hits}/{len(latest)} responders on their true floor" in text
    table = {ln.split("**")[1]: ln.split("): ", 1)[1] for ln in text.splitlines()
             if ln.startswith("- **F")}
    for n, e in latest.items():
        cell = next(c for c in table[f"F{e.floor_index}"].split(", ") if c.split()[0] == n)
        assert ("**true F" in cell) == (e.floor_index != truth[n])


def test_gating_counts_per_fusion_time(bulk, run):
    _, _, rows = bulk
    _, msgs = run
    ex = defaultdict(int)
    for e in of(msgs, "PositionEstimate"):
        ex[e.t_ns] += len(e.excluded)
    got = {t: r["Scalars:scalars"][0] for t, r in rows["/metrics/gating/excluded"]}
    assert got == {t: float(v) for t, v in ex.items()}


# ------------------------------------------------------------------------------- streaming
def test_streaming_in_small_batches_gives_the_same_dashboard(run, bulk, tmp_path):
    """The live path (Dashboard.add per batch) and the bulk path log the same rows."""
    import rerun as rr

    building, msgs = run
    path = tmp_path / "stream.rrd"
    rec = rr.RecordingStream(APP_ID, recording_id="stream")
    rec.save(str(path), default_blueprint=default_blueprint())
    dash = Dashboard(rec, building=building)
    batch: dict[str, list] = defaultdict(list)
    key = {
        "AnchorState": "anchor_states",
        "GroundTruth": "truth",
        "PositionEstimate": "estimates",
        "FusionDiagnostics": "diagnostics",
    }
    t_batch = None
    for x in msgs:  # time-ordered; one batch per 0.3 s of measurement time
        t = getattr(x, "t_ns", None) or x.watermark_ns
        if t_batch is not None and t - t_batch >= 300_000_000:
            dash.add(**batch)
            batch.clear()
            t_batch = t
        t_batch = t if t_batch is None else t_batch
        batch[key[type(x).__name__]].append(x)
    dash.add(**batch)
    rec.flush()
    rec.disconnect()
    streamed = read_rrd(path)
    _, _, bulk_rows = bulk
    for ent in (
        "/world/nodes/n00/estimate",
        "/metrics/error_3d_m/n01",
        "/metrics/residual_m/uav1",
        "/world/paths/n02",
        "/world/anchors/uav2/trail",
        "/metrics/gating/excluded",
    ):
        assert [t for t, _ in streamed[ent]] == [t for t, _ in bulk_rows[ent]], ent
        assert streamed[ent] == bulk_rows[ent], ent
    ev = sorted(x for _, r in streamed["/events"] for x in r["TextLog:text"])
    assert ev == sorted(x for _, r in bulk_rows["/events"] for x in r["TextLog:text"])


# ------------------------------------------------------------------------------- MCAP -> rrd
def _write_mcap(path: Path, msgs, *, extra=()):
    from diffpos_services.recording.writer import McapSink

    with McapSink(path) as sink:
        for x in [*msgs, *extra]:
            t = getattr(x, "t_ns", None) or x.watermark_ns
            sink.write(Keys("demo").of(x), m.encode(x), t + 5_000_000)
        last_wall = max(x.t_pub_wall_ns for x in msgs if hasattr(x, "t_pub_wall_ns"))
        sink.write_liveliness(
            "demo", "diffpos/demo/alive/anchor/uav5", False, last_wall - 2_000_000_000
        )


def test_mcap_to_rrd_skips_ranges_and_maps_liveliness_to_measurement_time(run, tmp_path):
    building, msgs = run
    ranges = [
        m.RangeMeasurement(
            anchor_id="uav1",
            node_id="n00",
            t_ns=e.t_ns,
            seq=i,
            range_m=10.0,
            sigma_m=0.1,
            snr_db=20.0,
            t_pub_wall_ns=e.t_pub_wall_ns,
        )
        for i, e in enumerate(of(msgs, "PositionEstimate")[:50])
    ]
    mcap = tmp_path / "run.mcap"
    _write_mcap(mcap, msgs, extra=ranges)
    out = tmp_path / "run.rrd"
    counts = mcap_to_rrd(mcap, out, building=building)
    assert counts["estimate"] == len(of(msgs, "PositionEstimate"))
    assert counts["anchor_state"] == len(of(msgs, "AnchorState"))
    assert counts["liveliness"] == 1 and counts["undecodable"] == 0 and counts["complete"]
    rows = read_rrd(out)
    assert not any("/range" in k for k in rows)
    sc, wanted = _kind_scanner(mcap, {"estimate", "anchor_state"})
    seen = {r.topic for batch in sc.iter_batches(wanted) for r in batch}
    assert seen and all(t.endswith(("/estimate", "/state")) for t in seen)  # ranges skipped
    left = [(t, r) for t, r in rows["/events"] if r["TextLog:text"] in (
        ["fusion no longer sees anchor uav5"],
        ["anchor uav5 left while the others went on publishing (lost: a fault)"])]
    # one from the fusion diagnostics (DEBUG), one from liveliness (wall time - 2 s mapped to
    # t_ns; the run went on for 2 s without it: lost, WARN)
    assert sorted(r["TextLog:level"][0] for _, r in left) == ["DEBUG", "WARN"]
    a0 = of(msgs, "AnchorState")[0]
    offset = a0.t_ns - a0.t_pub_wall_ns  # synthetic clocks: measurement = wall + offset
    wall_event = max(x.t_pub_wall_ns for x in msgs if hasattr(x, "t_pub_wall_ns")) - 2_000_000_000
    # mapped through the nearest earlier message (estimates are published 1 ms after t_ns)
    assert min(abs(t - (wall_event + offset)) for t, _ in left) <= 1_000_000
    bulk_pos = {t: r["Points3D:positions"] for t, r in rows["/world/nodes/n03/estimate"]}
    for e in of(msgs, "PositionEstimate"):
        if e.node_id == "n03" and e.position_m is not None:
            np.testing.assert_allclose(bulk_pos[e.t_ns][0], e.position_m, atol=1e-4)


def test_mcap_to_rrd_replaces_estimates_for_replay(run, tmp_path):
    building, msgs = run
    mcap = tmp_path / "run.mcap"
    _write_mcap(mcap, msgs)
    ests = [e for e in of(msgs, "PositionEstimate") if e.node_id == "n01"][:10]
    counts = mcap_to_rrd(mcap, tmp_path / "r.rrd", building=building, estimates=ests)
    assert counts["estimate"] == 10
    rows = read_rrd(tmp_path / "r.rrd")
    assert len(rows["/world/nodes/n01/estimate"]) == 10 and "/world/nodes/n00/estimate" not in rows


def test_to_rerun_cli(run, tmp_path, capsys):
    from diffpos_services.cli import main as cli

    _, msgs = run
    mcap = tmp_path / "run.mcap"
    _write_mcap(mcap, msgs)
    assert cli.main(["to-rerun", str(mcap), "-o", str(tmp_path / "x.rrd")]) == 0
    out = capsys.readouterr().out
    assert "wrote" in out and "rerun " in out and (tmp_path / "x.rrd").stat().st_size > 0
    assert cli.main(["to-rerun", str(tmp_path / "missing.mcap")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert cli.main(["to-rerun", str(mcap), "-o", str(tmp_path / "x.txt")]) == 2
    assert "must end in .rrd" in capsys.readouterr().err


def test_to_rerun_time_window(run, tmp_path):
    from diffpos_services.cli import main as cli

    _, msgs = run
    mcap = tmp_path / "run.mcap"
    _write_mcap(mcap, msgs)
    out = tmp_path / "win.rrd"
    assert cli.main(["to-rerun", str(mcap), "-o", str(out), "--start", "2", "--end", "4.05"]) == 0
    t0 = min(a.t_ns for a in of(msgs, "AnchorState"))
    want = [e.t_ns for e in of(msgs, "PositionEstimate")
            if e.node_id == "n01" and t0 + 2e9 <= e.t_ns <= t0 + 4.05e9]  # fmt: skip
    assert len(want) == 21
    assert [t for t, _ in read_rrd(out)["/world/nodes/n01/estimate"]] == want
    assert cli.main(["to-rerun", str(mcap), "--start", "4", "--end", "2"]) == 2


def test_building_from_scenario_names_files_and_default(tmp_path, capsys):
    from diffpos_services.cli import main as cli
    from diffpos_services.scenario_io import load_scenario

    from diffpos.scenario import default_scenario

    assert building_from_scenario_file("default") == BuildingOutline.from_object(
        default_scenario().building
    )
    large = building_from_scenario_file("large")
    assert large == BuildingOutline.from_object(load_scenario("large").building)
    bad = tmp_path / "bad.toml"
    bad.write_text("[building]\nn_floors = -1\n")
    with pytest.raises(ValueError, match=r"bad\.toml"):
        building_from_scenario_file(bad)
    mcap = tmp_path / "x.mcap"
    mcap.write_bytes(b"")
    assert cli.main(["to-rerun", str(mcap), "--scenario", str(tmp_path / "nope.toml")]) == 2
    assert "nope.toml" in capsys.readouterr().err
