"""benchmarks/heldout.py: the seeded random held-out geometries of ``bench_accuracy.py
--random``: valid (the scenario loader accepts their TOML), distinct, a pure function of
(seed, index), within the ranges its docstring documents, with the emulator's responders
walking inside the building."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from diffpos_services.scenario_io import load_scenario

from diffpos.emulation import emulation_nodes
from diffpos.scenario import Scenario, default_scenario

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import heldout

N = 24  # samples of seed 0 checked in detail (6 of each family slot)


@pytest.fixture(scope="module")
def samples():
    return heldout.random_scenarios(N, 0)


def _centres(d):
    return np.array([a["position_m"] if "position_m" in a else a["trajectory"]["center_m"]
                     for a in d["anchors"]])


def test_samples_are_seeded_named_and_distinct(samples):
    assert list(samples) == [f"rand-0-{i}" for i in range(N)]
    # a pure function of (seed, index): the same alone, in another batch, twice
    assert heldout.random_scenario(0, 7) == samples["rand-0-7"]
    assert heldout.random_scenarios(3, 0) == {k: samples[k] for k in list(samples)[:3]}
    other = heldout.random_scenarios(N, 1)
    keys = [repr((d["building"], d["anchors"])) for d in [*samples.values(), *other.values()]]
    assert len(set(keys)) == 2 * N  # no two samples (of either seed) the same geometry


def test_samples_load_through_the_toml_loader(samples, tmp_path):
    for name, d in samples.items():
        path = tmp_path / f"{name}.toml"
        path.write_text(heldout.to_toml(d), encoding="utf-8")
        s = load_scenario(path)
        assert s == Scenario.from_dict(d)
        assert s.name == name and not s.warnings  # >= 3 anchors


def test_samples_stay_in_the_documented_ranges(samples):
    R, paper = heldout.RANGES, default_scenario().to_dict()

    def within(v, key, slack=1e-9):
        lo, hi = R[key]
        return lo - slack <= v <= hi + slack

    for i, d in enumerate(samples.values()):
        fam, b = heldout.family(i), d["building"]
        if fam == "uavs":
            assert b == paper["building"]
        else:
            assert within(b["n_floors"], "n_floors") and isinstance(b["n_floors"], int)
            for k in ("floor_height_m", "first_floor_z_m", "sill_height_m", "window_height_m",
                      "width_m", "depth_m"):
                assert within(b[k], k, slack=0.051), (d["name"], k, b[k])
            # the window fits in its floor below the slab (rounding: 1 cm)
            assert b["sill_height_m"] + b["window_height_m"] <= (
                b["floor_height_m"] - heldout.LINTEL_M + 0.011)
            for p in b["partitions"]:
                assert p["material"] == "plasterboard"
                if p["axis"] == "x":
                    assert abs(p["position_m"]) <= b["width_m"] / 2 - 2.0 + 0.01
        c = _centres(d)
        if fam == "building":
            assert d["anchors"] == [{"id": a["id"], "position_m": a["position_m"]} for a in [
                {"id": x.id, "position_m": [float(v) for v in x.position_m]}
                for x in default_scenario().anchors]]
            continue
        top = b["first_floor_z_m"] + b["n_floors"] * b["floor_height_m"]
        assert within(len(c), "n_uavs")
        assert np.all((-c[:, 1] >= 5.0 - 0.01) & (-c[:, 1] <= 40.0 + 0.01))
        assert np.all((c[:, 2] >= 0.5 - 0.01) & (c[:, 2] <= top + 3.0 + 0.01))
        excess = np.abs(c[:, 0]) - b["width_m"] / 2
        assert np.all(excess <= 15.0 + 0.01)
        assert np.all((excess <= 0) | (excess >= 1.0 - 0.01))  # beyond: by 1-15 m
        if len(c) >= 5:
            assert np.any(excess > 0)
        gaps = np.linalg.norm(c[:, None] - c[None], axis=-1) + np.eye(len(c)) * 1e9
        assert gaps.min() >= heldout.MIN_UAV_SPACING_M - 0.02
        for a in d["anchors"]:
            t = a["trajectory"]
            assert t["kind"] == "hover" and within(t["wander_m"], "wander_m", 0.006)
            assert within(t["period_s"], "period_s", 0.06)


def test_the_samples_reach_the_ends_of_their_ranges(samples):
    """Over the samples, UAVs below the lowest window and above the roof, beyond the facade
    ends, ground-floor buildings and tall ones all occur (the ranges are really sampled)."""
    below = above = beyond = 0
    for d in samples.values():
        b, c = d["building"], _centres(d)
        below += int(np.sum(c[:, 2] < b["first_floor_z_m"] + b["sill_height_m"]))
        above += int(np.sum(c[:, 2] > b["first_floor_z_m"] + b["n_floors"] * b["floor_height_m"]))
        beyond += int(np.sum(np.abs(c[:, 0]) > b["width_m"] / 2))
    assert below > 0 and above > 0 and beyond > 0
    rand_b = [d["building"] for i, d in enumerate(samples.values()) if heldout.family(i) != "uavs"]
    assert min(b["first_floor_z_m"] for b in rand_b) < 1.5
    assert max(b["n_floors"] for b in rand_b) >= 7
    assert min(b["depth_m"] for b in rand_b) < 15.0


def test_the_responders_walk_inside_every_sample(samples):
    """Sampled along a whole loop in time (not only the path's vertices)."""
    t_s = np.linspace(0.0, 200.0, 801)
    for d in samples.values():
        s = Scenario.from_dict(d)
        nodes = emulation_nodes(s)
        assert len(nodes) == 6
        for _, traj in nodes:
            assert np.all(s.building.inside(traj.position_m(t_s))), d["name"]


class _Est:
    """The fields heldout_diag's ``changes`` reads of an estimate."""

    def __init__(self, f):
        self.floor_index, self.status = f, "TRACKING"


class _Run:
    """A stand-in of heldout_diag.Run for one node "n1": its truth floors and the published
    floors at the sample times ``tt`` [ns]."""

    def __init__(self, tt, truth, est, *, t0=0, period=100_000_000):
        self.t0, self.period = t0, period
        self.tracks = {"n1": (tt, np.zeros((len(tt), 3)), truth)}
        self.set_estimates(tt, est)

    def set_estimates(self, tt, est):
        self.est = {("n1", int(t // self.period)): _Est(int(f))
                    for t, f in zip(tt, est, strict=True)}


def test_floor_change_delay_counts_the_settling_epoch():
    """heldout_diag's ``changes``: a truth that climbs from floor 1 to 2 at t = 5 s and comes
    back down at 12 s; the published floor follows 1.5 s late up but flickers back once at
    6.8 s (settled from the epoch after it), and never down (a lock): delays 1.9 s and inf; a
    change within the first 2 s or whose new floor lasts < 1 s is not counted."""
    import heldout_diag as H

    period = 100_000_000
    t = np.arange(0, 200) * period  # 0-19.9 s
    ts = t * 1e-9
    truth = np.where((ts >= 5.0) & (ts < 12.0), 2, 1)
    truth[(ts >= 1.0) & (ts < 1.5)] = 3  # in the skipped start
    truth[ts >= 19.5] = 0  # the last 0.5 s: not a change that lasts
    est = np.where(ts >= 6.5, 2, 1)
    est[68] = 1  # t = 6.8 s flickers back: settled from 6.9 s
    run = _Run(t, truth, est)
    rows = H._settle_delays(run, "x")
    assert [(r[1], round(r[4], 1)) for r in rows] == [(1, 5.0), (-1, 12.0)]
    assert rows[0][0] == pytest.approx(1.9) and rows[1][0] == np.inf
    # the last change lasts to the end of the recording: a published floor that reaches it
    # only in the last 0.5 s has not held it for 1 s: never settled (the window is not cut
    # short by the recording's end), while one that reaches it 1 s before the end has
    truth[ts >= 19.5] = 1  # no excursion: floor 1 from 12 s to the end
    for last_s, settled in ((19.5, False), (19.0, True)):
        run.set_estimates(t, np.where(ts >= last_s, 1, est))
        assert np.isfinite(H._settle_delays(run, "x")[1][0]) == settled


def test_floor_change_hold_and_delay_count_whole_epochs():
    """heldout_diag's ``changes``: the truth's stay on a new floor is counted in epochs like
    the estimate's (HOLD_S = 1 s = 10 epochs at 10 Hz: a stay of exactly 10 epochs counts, 9
    do not), and a delay of exactly 20 epochs is 2 s to the bit (within the 2 s bar) wherever
    the change falls: the differences of float seconds were an ulp over 2.0 for some."""
    import heldout_diag as H

    period = 100_000_000
    t0 = 1_764_300_000_000_000_000  # a wall-clock t0, as the recordings have
    for start in range(30, 60):  # 3.0-5.9 s: where the float differences differ
        k = np.arange(0, start + 80)
        truth = np.ones(k.size, int)
        truth[start:start + 10] = 2  # 10 epochs up: counts
        truth[start + 10:start + 19] = 3  # 9 epochs: does not count
        truth[start + 19:] = 4  # stays to the end
        est = np.ones(k.size, int)
        est[start + 20:] = 2  # floor 2 reached late: never settled (truth left it)
        est[start + 19 + 20:] = 4  # floor 4 reached 20 epochs (2.0 s) after the truth
        tt = t0 + k * period
        run = _Run(tt, truth, est, t0=t0, period=period)
        rows = H._settle_delays(run, "x")
        assert [(r[1], round(r[4], 1)) for r in rows] == [(1, start / 10), (1, (start + 19) / 10)]
        assert rows[0][0] == np.inf and rows[1][0] == 2.0
        report = H.changes([("x", run)])  # one never (inf) and one 2.0 s: no NaN quantile
        assert "within 2 s 50.0 %, delay p50 2.0 s p90 inf s, never settled 1" in report
