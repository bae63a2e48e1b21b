"""`diffpos reproduce`: M-NLS in the default run, floor accuracy per method, the 95 % ellipsoid
coverage, per-method wall time, the written reports and the CLI end to end.

References are independent of the code under test: floors by a per-receiver ``math.floor``
loop, the ellipsoid test by an explicit inverse and the chi-square(3) 95 % quantile as a
number, on a held-out building (not a shipped scenario) with fixed seeds.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from diffpos_services.reports import study as report

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import Scenario
from diffpos.study import (
    Arrivals,
    FirstArrivalData,
    ReproduceConfig,
    build_summary,
    reproduce,
)
from diffpos.study_methods import REPRODUCE_METHODS

#: chi-square quantile, 3 degrees of freedom, p = 0.95 (tables: 7.8147).
CHI2_3_95 = 7.814727903251178


def _held_out() -> Scenario:
    """3 floors of 3.4 m from 2 m, 1.2 m windows on a 0.9 m sill, 24 x 12 m; 6 UAVs: below,
    at and above the window bands, one beyond each facade end."""
    return Scenario.from_dict({
        "name": "held-out",
        "building": {"width_m": 24.0, "center_x_m": 3.0, "depth_m": 12.0, "n_floors": 3,
                     "floor_height_m": 3.4, "first_floor_z_m": 2.0, "sill_height_m": 0.9,
                     "window_height_m": 1.2},
        "anchors": [
            {"id": "a1", "position_m": [-14.0, -9.0, 1.0]},
            {"id": "a2", "position_m": [3.0, -6.0, 3.5]},
            {"id": "a3", "position_m": [20.0, -10.0, 6.8]},
            {"id": "a4", "position_m": [9.0, -4.0, 11.5]},
            {"id": "a5", "position_m": [-5.0, -12.0, 0.5]},
            {"id": "a6", "position_m": [12.0, -15.0, 2.0]},
        ],
        "nodes": {"grid": {"spacing_m": 3.0, "x_margin_m": 1.0, "y_min_m": 1.0,
                           "y_max_m": 10.0}},
    })


def _floor_ref(z: float, first_m: float, height_m: float) -> int | None:
    return None if not math.isfinite(z) else math.floor((z - first_m) / height_m)


def _floor_accuracy_ref(est: np.ndarray, truth: np.ndarray, b) -> float:
    hits = 0
    for e, t in zip(est, truth, strict=True):
        k = _floor_ref(float(e[2]), b.first_floor_z_m, b.floor_height_m)
        hits += k is not None and k == _floor_ref(float(t[2]), b.first_floor_z_m,
                                                  b.floor_height_m)
    return hits / len(truth)


def _coverage_ref(est: np.ndarray, cov: np.ndarray, truth: np.ndarray) -> float:
    inside = total = 0
    for e, c, t in zip(est, cov, truth, strict=True):
        if not (np.all(np.isfinite(e)) and np.all(np.isfinite(c))):
            continue
        d = e - t
        total += 1
        inside += float(d @ np.linalg.inv(c) @ d) <= CHI2_3_95
    return inside / total


@pytest.fixture(scope="module")
def held_out_run():
    sc = _held_out()
    cfg = ReproduceConfig(seed=4)
    return sc, cfg, reproduce(sc, cfg)


def test_default_run_has_mnls_and_floor_accuracy_of_every_method(held_out_run):
    sc, cfg, res = held_out_run
    assert "mnls" in REPRODUCE_METHODS and cfg.methods == REPRODUCE_METHODS
    st = res.study
    assert st.methods == REPRODUCE_METHODS
    truth = np.asarray(res.data.nodes_m)
    assert len(truth) == 8 * 4 * 3  # held-out grid: 8 columns x 4 rows x 3 floors
    s = build_summary(cfg, sc, res)["positioning_m"]
    for m in REPRODUCE_METHODS:
        want = _floor_accuracy_ref(st.positions_m[m], truth, sc.building)
        assert s[m]["floor_accuracy"] == pytest.approx(want, abs=1e-12), m
    # the ellipsoid coverage only where a covariance is reported (mnls)
    want = _coverage_ref(st.positions_m["mnls"], st.extra["covariance_m2"]["mnls"], truth)
    assert s["mnls"]["ellipsoid95_coverage"] == pytest.approx(want, abs=1e-12)
    assert all("ellipsoid95_coverage" not in s[m] for m in REPRODUCE_METHODS if m != "mnls")
    # the physics: M-NLS, which models the first arrival, finds more right floors than
    # the single-edge D-NLS on this building (6 anchors, all mechanisms present)
    assert s["mnls"]["floor_accuracy"] > s["dnls_case1"]["floor_accuracy"]


def test_wall_time_of_every_method(held_out_run):
    _, cfg, res = held_out_run
    t = res.timing
    assert set(t["method_s"]) == {*cfg.methods, "peb"}
    assert all(v >= 0 for v in t["method_s"].values())
    # the stages run one after another inside the positioning time
    assert sum(t["method_s"].values()) <= t["positioning_s"] + 1e-6
    assert t["positioning_s"] <= t["total_s"]


def test_a_failed_fix_is_a_floor_miss():
    """Receivers left with two links get no 3D fix; they stay in the denominator."""
    sc = _held_out()
    rng = np.random.default_rng(11)
    nodes = sc.node_positions_m()
    anchors = sc.anchor_positions_m()
    ch = emulate_channel(anchors, nodes, building=sc.building, radio=sc.radio)
    fa = first_arrival(ch, radio=sc.radio, rng=rng)
    arrays = FirstArrivalData.from_channel(fa, anchors, nodes).to_arrays()
    starved = np.arange(0, len(nodes), 3)  # every third receiver keeps only 2 links
    det = arrays["detected"].copy()
    det[np.ix_(starved, np.arange(2, anchors.shape[0]))] = False
    arrays["detected"] = det
    arrays["range_m"] = np.where(det, arrays["range_m"], np.nan)
    arrays["sigma_m"] = np.where(det, arrays["sigma_m"], np.inf)
    data = FirstArrivalData.from_arrays(arrays)
    res = reproduce(sc, ReproduceConfig(seed=0, methods=("dnls_case1", "mnls")),
                    kind="arrivals", load=lambda noise_rng: Arrivals(data))
    st = res.study
    s = res.study.summary()
    for m in ("dnls_case1", "mnls"):
        failed = ~np.isfinite(st.positions_m[m][:, 2])
        assert failed[starved].all(), m
        want = _floor_accuracy_ref(st.positions_m[m], nodes, sc.building)
        assert s[m]["floor_accuracy"] == pytest.approx(want, abs=1e-12)
        assert s[m]["floor_accuracy"] <= 1.0 - len(starved) / len(nodes) + 1e-12
        assert s[m]["solved_fraction"] == pytest.approx(1.0 - failed.mean())


def test_reports_show_floor_accuracy_and_coverage(held_out_run, tmp_path, capsys):
    sc, cfg, res = held_out_run
    summary = build_summary(cfg, sc, res)
    files = report.write_outputs(tmp_path, summary, res, cfg.delta_m)
    md = (tmp_path / "summary.md").read_text()
    assert "| right floor | 95% ellipsoid holds truth |" in md
    pos = summary["positioning_m"]
    row = next(line for line in md.splitlines() if line.startswith("| M-NLS"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[-2] == f"{100 * pos['mnls']['floor_accuracy']:.1f}%"
    assert cells[-1] == f"{100 * pos['mnls']['ellipsoid95_coverage']:.1f}%"
    lls_row = next(line for line in md.splitlines() if line.startswith("| LLS"))
    assert lls_row.rstrip().endswith(f"| {100 * pos['lls']['floor_accuracy']:.1f}% |  |")
    assert "Time per method:" in md and "ms CPU per fix" in md
    js = json.loads((tmp_path / "summary.json").read_text())
    assert set(js["timing_s"]["method_s"]) == {*REPRODUCE_METHODS, "peb"}
    assert set(js["timing_s"]["method_cpu_s"]) == {*REPRODUCE_METHODS, "peb"}
    for f in ("cdf_3d_error.png", "cdf_z_error.png"):
        assert (tmp_path / f).stat().st_size > 0
    report.print_report(summary, files)
    out = capsys.readouterr().out
    assert "mnls" in out and f"{100 * pos['mnls']['floor_accuracy']:.1f}%" in out


# ------------------------------------------------------------------ CLI end to end
def test_reproduce_cli_quick_and_arrivals_round_trip(tmp_path, capsys):
    from diffpos_services.cli.main import main

    out = tmp_path / "r"
    rc = main(["reproduce", "--quick", "--quick-nodes", "50", "--no-progress", "--seed", "3",
               "--out", str(out)])
    assert rc == 0
    for f in ("summary.json", "summary.md", "first_arrival.npz", "cdf_3d_error.png",
              "cdf_z_error.png", "first_arrival_boxplots.png"):
        assert (out / f).stat().st_size > 0, f
    s = json.loads((out / "summary.json").read_text())
    assert s["n_receivers"] == 50 and s["seed"] == 3 and s["quick"]
    assert set(s["positioning_m"]) == {"lls", "ippa", "dnls_case1", "dnls_case2", "mnls",
                                       "peb"}
    assert all(0.0 <= s["positioning_m"][m]["floor_accuracy"] <= 1.0
               for m in REPRODUCE_METHODS)
    assert 0.0 <= s["positioning_m"]["mnls"]["ellipsoid95_coverage"] <= 1.0
    assert set(s["mpc_table_pct"]) == {"MPC-1", "MPC-2", "MPC-3", "MPC-4", "none"}
    assert "| MPC-3 |" in (out / "summary.md").read_text()
    # the same first arrivals fed back give the same positioning numbers
    out2 = tmp_path / "r2"
    rc = main(["reproduce", "--no-progress", "--channel",
               f"arrivals:{out / 'first_arrival.npz'}", "--out", str(out2)])
    assert rc == 0
    s2 = json.loads((out2 / "summary.json").read_text())
    assert s2["positioning_m"] == s["positioning_m"]
    assert s2["mpc_table_pct"] is None
    capsys.readouterr()


def test_reproduce_cli_errors_are_one_line(tmp_path, capsys):
    from diffpos_services.cli.main import main

    bad = tmp_path / "bad.toml"
    bad.write_text("[[anchors]]\nid = 'a'\nposition_m = [0, 2, 0]\n[nodes.grid]\n")
    assert main(["reproduce", "--scenario", str(bad), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "anchors[0].position_m: y=2 is inside the building" in err
    assert "Traceback" not in err
    assert main(["reproduce", "--channel", "raytrace", "--out", str(tmp_path)]) == 2
    assert "--channel" in capsys.readouterr().err
