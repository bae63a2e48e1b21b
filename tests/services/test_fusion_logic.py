"""FusionCore in memory: epochs, accuracy vs PEB, gating, lost anchors, bad input, degraded geometry."""

from __future__ import annotations

import types

import msgspec
import numpy as np
import pytest
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.core import FusionCore
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys
from fusion_scene import ANCHORS, EDGE, KEYS, NODES, PERIOD_NS, W
from fusion_scene import fusion_config as _cfg

from diffpos.geometry import window_edge_path


def _feed_epoch(core, e, nodes, rng, *, anchors=ANCHORS, sigma=0.05, bias=None,
                node_vel=None, phases=None, wall=0, t_base_ns=0):
    """All anchors report state + a range to every node at their own phase in epoch e."""
    for j, (aid, apos) in enumerate(anchors.items()):
        ph = (phases or {}).get(aid, 0.1 + 0.15 * j)
        t_ns = t_base_ns + e * PERIOD_NS + int(ph * PERIOD_NS)
        st = M.AnchorState(anchor_id=aid, t_ns=t_ns, seq=e, position_m=M.vec3(apos),
                           velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.01, 0.01, 0.01),
                           velocity_sigma_m_s=0.0, range_rate_hz=10.0, t_pub_wall_ns=wall)
        core.on_sample(KEYS.anchor_state(aid), M.encode(st), wall)
        for nid, npos in nodes.items():
            p = npos if node_vel is None else npos + node_vel[nid] * ((t_ns - t_base_ns) * 1e-9)
            r = float(window_edge_path(apos, p, window_height_m=W, edge_x_m=EDGE).length_m)
            r += rng.normal(0, sigma) + (bias or {}).get((aid, nid), 0.0)
            msg = M.RangeMeasurement(anchor_id=aid, node_id=nid, t_ns=t_ns, seq=e, range_m=r,
                                     sigma_m=sigma, snr_db=20.0, t_pub_wall_ns=wall)
            core.on_sample(KEYS.anchor_range(aid, nid), M.encode(msg), wall)



def test_every_node_every_epoch_and_error_within_peb():
    core = FusionCore(_cfg())
    rng = np.random.default_rng(7)
    got = []
    for e in range(20):
        _feed_epoch(core, e, NODES, rng)
        got += core.step(0)
    got += core.step(10**12)  # deadline flushes the last epoch
    by = {(g.node_id, g.epoch) for g in got}
    assert by == {(n, e) for n in NODES for e in range(20)}
    ok = [g for g in got if g.status in ("OK", "OK_UNVERIFIED")]
    assert len(ok) >= 0.95 * len(got)
    err = np.array([np.linalg.norm(np.array(g.position_m) - NODES[g.node_id]) for g in ok])
    peb = np.array([g.peb_m for g in ok])
    assert np.median(err) < 2 * np.median(peb), (np.median(err), np.median(peb))
    # floor index from the fitted height (floors start at 3 m, 3 m each)
    assert all(g.floor_index == int((NODES[g.node_id][2] - 3.0) // 3.0) for g in ok)
    # every estimate validates against the schema and roundtrips
    dec = M.decoder(M.PositionEstimate)
    assert dec(M.encode(got[0])) == got[0]
    d = core.diagnostics(1)
    assert d.solved == len(got) and d.received["range"] == 20 * 5 * 3
    assert d.fixes_by_status.get("OK", 0) + d.fixes_by_status.get("OK_UNVERIFIED", 0) == len(ok)


def test_epoch_waits_for_all_live_anchors_then_solves_immediately():
    core = FusionCore(_cfg())
    rng = np.random.default_rng(1)
    four = {k: v for k, v in ANCHORS.items() if k != "uav5"}
    _feed_epoch(core, 0, NODES, rng, anchors=four)
    # uav5 is known (state seen earlier) and alive: epoch 0 must wait for it
    st = M.AnchorState(anchor_id="uav5", t_ns=-5, seq=0, position_m=M.vec3(ANCHORS["uav5"]),
                       velocity_m_s=(0, 0, 0), position_sigma_m=(0, 0, 0), velocity_sigma_m_s=0,
                       range_rate_hz=10, t_pub_wall_ns=0)
    core.on_sample(KEYS.anchor_state("uav5"), M.encode(st), 0)
    assert core.step(0) == []
    # uav5 reports epoch 0: ready at once, no deadline needed
    _feed_epoch(core, 0, NODES, rng, anchors={"uav5": ANCHORS["uav5"]}, phases={"uav5": 0.9})
    out = core.step(0)
    assert len(out) == 3 and all(len(g.used_anchors) == 5 for g in out if g.status == "OK")


def test_lost_anchor_is_not_waited_for_and_is_reported():
    core = FusionCore(_cfg())
    rng = np.random.default_rng(2)
    for e in range(3):
        _feed_epoch(core, e, NODES, rng)
        core.step(0)
    core.on_liveliness("uav3", False, 123)
    rest = {k: v for k, v in ANCHORS.items() if k != "uav3"}
    _feed_epoch(core, 3, NODES, rng, anchors=rest)
    _feed_epoch(core, 4, NODES, rng, anchors=rest)
    out = core.step(0)  # no deadline passed: released because uav3 is not live
    assert {g.epoch for g in out} >= {3}
    for g in out:
        assert M.Exclusion("uav3", "ANCHOR_LOST") in g.excluded
        assert "uav3" not in g.used_anchors
        assert g.status in ("OK", "OK_UNVERIFIED")
    d = core.diagnostics(1)
    h = {a.anchor_id: a for a in d.anchors}
    assert h["uav3"].alive is False and h["uav3"].lost_wall_ns == 123
    assert "uav3" not in d.live_anchors
    # back again with its token
    core.on_liveliness("uav3", True, 200)
    assert "uav3" in core.live_anchors


def test_outlier_is_gated_and_fix_stays_accurate():
    core = FusionCore(_cfg())
    rng = np.random.default_rng(3)
    bias = {("uav2", "n02"): 6.0}
    out = []
    for e in range(5):
        _feed_epoch(core, e, NODES, rng, bias=bias, sigma=0.03)
        out += core.step(0)
    out += core.step(10**12)
    n2 = [g for g in out if g.node_id == "n02"]
    assert len(n2) == 5
    for g in n2:
        assert any(x.anchor_id == "uav2" and x.reason in ("RAIM", "PREGATE_SHORTER_THAN_LOS")
                   for x in g.excluded), g.excluded
        assert g.status in ("OK", "OK_UNVERIFIED")
        assert np.linalg.norm(np.array(g.position_m) - NODES["n02"]) < 0.5
    assert core.diagnostics(0).gated >= 5


def test_too_few_anchors_reports_status_not_a_position():
    core = FusionCore(_cfg())
    rng = np.random.default_rng(4)
    two = {k: ANCHORS[k] for k in ("uav1", "uav2")}
    _feed_epoch(core, 0, NODES, rng, anchors=two)
    out = core.step(10**12)
    assert len(out) == 3
    for g in out:
        assert g.status in ("TOO_FEW_ANCHORS", "NOT_IDENTIFIABLE")
        assert g.position_m is None and g.peb_m is None and g.floor_index is None


def test_malformed_messages_are_counted_never_raise():
    core = FusionCore(_cfg())
    good = M.RangeMeasurement(anchor_id="uav1", node_id="n01", t_ns=5, seq=0, range_m=3.0,
                              sigma_m=0.1, snr_db=1.0, t_pub_wall_ns=0)
    core.on_sample(KEYS.anchor_range("uav1", "n01"), b"{oops", 0)
    core.on_sample(KEYS.anchor_range("uav1", "n01"), b'{"schema":"diffpos.range.v1"}', 0)
    core.on_sample(KEYS.anchor_range("uav2", "n01"), M.encode(good), 0)  # id mismatch
    core.on_sample(KEYS.anchor_state("uav1"), M.encode(good), 0)  # wrong type for the key
    core.on_sample("diffpos/t/bogus", b"{}", 0)
    core.on_sample("diffpos/other/anchor/uav1/state", b"{}", 0)
    for _ in range(3):
        core.on_sample(KEYS.anchor_range("uav1", "n01"), b"\xff\xfe", 0)
    d = core.diagnostics(0)
    assert d.rejected == {"json": 4, "schema": 2, "key_mismatch": 1, "unexpected_key": 2}
    # logged once per (key, reason), counted every time
    assert core.log_once.seen[(KEYS.anchor_range("uav1", "n01"), "json")] == 4
    assert core.step(10**12) == []


def test_motion_compensation_reduces_error_for_moving_nodes():
    vel = {"n01": np.array([1.5, 0.5, 0.0]), "n02": np.array([-1.5, 0.3, 0.0])}
    nodes = {k: NODES[k] for k in vel}
    phases = {"uav1": 0.02, "uav2": 0.3, "uav3": 0.55, "uav4": 0.8, "uav5": 0.97}

    def run(comp):
        core = FusionCore(_cfg(motion_compensation=comp, node_speed_sigma_m_s=0.0))
        rng = np.random.default_rng(5)
        out = []
        for e in range(15):
            _feed_epoch(core, e, nodes, rng, sigma=0.005, node_vel=vel, phases=phases)
            out += core.step(0)
        out += core.step(10**12)
        errs = [np.linalg.norm(np.array(g.position_m) - (nodes[g.node_id] + vel[g.node_id] * g.t_ns * 1e-9))
                for g in out if g.epoch >= 5 and g.position_m is not None]
        return np.median(errs)

    e_on, e_off = run(True), run(False)
    assert e_on < 0.5 * e_off, (e_on, e_off)


def test_config_errors_name_the_field():
    with pytest.raises(ConfigError, match="window_height_m"):
        _cfg(window_height_m=-1)
    with pytest.raises(ConfigError, match="site"):
        _cfg(site="a/b")
    with pytest.raises(ConfigError, match="epoch_period_s"):
        _cfg(epoch_period_s="fast")


def test_absolute_unix_times_with_many_anchors_do_not_overflow():
    """8 anchors at ~1.8e18 ns: the fix time must stay inside the epoch (int64 sums overflow)."""
    many = {f"u{i}": np.array([-20.0 + 5 * i, -10.0 - i, 1.0 + (i % 3) * 3]) for i in range(8)}
    t_base = 1_795_257_866 * 10**9
    core = FusionCore(_cfg())
    rng = np.random.default_rng(8)
    _feed_epoch(core, 0, NODES, rng, anchors=many, t_base_ns=t_base,
                phases={a: 0.1 * (i + 1) for i, a in enumerate(many)})
    out = core.step(0)
    assert len(out) == 3
    for g in out:
        assert t_base <= g.t_ns < t_base + PERIOD_NS
        assert g.t_ns == t_base + round(np.mean([0.1 * (i + 1) for i in range(8)]) * PERIOD_NS)
        assert g.status == "OK"


def test_range_batches_give_the_same_fixes_as_single_ranges():
    """An anchor publishing RangeBatch messages is equivalent to one message per node."""

    def run(batch: bool):
        core = FusionCore(_cfg())
        rng = np.random.default_rng(9)
        out = []
        for e in range(4):
            if not batch:
                _feed_epoch(core, e, NODES, rng)
            else:
                for j, (aid, apos) in enumerate(ANCHORS.items()):
                    t_ns = e * PERIOD_NS + int((0.1 + 0.15 * j) * PERIOD_NS)
                    st = M.AnchorState(anchor_id=aid, t_ns=t_ns, seq=e, position_m=M.vec3(apos),
                                       velocity_m_s=(0.0, 0.0, 0.0),
                                       position_sigma_m=(0.01, 0.01, 0.01), velocity_sigma_m_s=0.0,
                                       range_rate_hz=10.0, t_pub_wall_ns=0)
                    core.on_sample(KEYS.anchor_state(aid), M.encode(st), 0)
                    rs = [float(window_edge_path(apos, p, window_height_m=W, edge_x_m=EDGE).length_m)
                          + rng.normal(0, 0.05) for p in NODES.values()]
                    b = M.RangeBatch(anchor_id=aid, t_ns=t_ns, seq=e, node_ids=list(NODES),
                                     range_m=rs, sigma_m=[0.05] * 3, snr_db=[20.0] * 3,
                                     t_pub_wall_ns=0)
                    core.on_sample(KEYS.anchor_range_batch(aid), M.encode(b), 0)
            out += core.step(0)
        out += core.step(10**12)
        return core, sorted(out, key=lambda g: (g.epoch, g.node_id))

    c1, single = run(False)
    c2, batched = run(True)
    assert len(single) == len(batched) == 12
    for a, b in zip(single, batched, strict=True):
        assert (a.node_id, a.epoch, a.status) == (b.node_id, b.epoch, b.status)
        np.testing.assert_allclose(a.position_m, b.position_m, atol=1e-9)
    assert c2.diagnostics(0).received["range"] == c1.diagnostics(0).received["range"] == 60
    # a batch with inconsistent lists is rejected, not half-applied
    bad = M.RangeBatch(anchor_id="uav1", t_ns=10**9, seq=1, node_ids=["n01", "n02"], range_m=[1.0],
                       sigma_m=[0.1, 0.1], snr_db=[1.0, 1.0], t_pub_wall_ns=0)
    c2.on_sample(KEYS.anchor_range_batch("uav1"), M.encode(bad), 0)
    assert c2.diagnostics(0).rejected.get("schema") == 1


def _run_stream(core, *, wall0):
    """A fixed 8-epoch stream with an outlier, a lost anchor and a final flush; every wall
    time is ``wall0`` + a fixed offset, and the estimates are returned encoded."""
    rng = np.random.default_rng(5)
    out = []
    for a in ANCHORS:
        core.on_liveliness(a, True, wall0)
    for e in range(8):
        wall = wall0 + e * PERIOD_NS
        _feed_epoch(core, e, NODES, rng, wall=wall, bias={("uav2", "n02"): 6.0})
        if e == 5:
            core.on_liveliness("uav5", False, wall)
        out += core.step(wall + 1000)
    out += core.flush(wall0 + 10**9)
    return out


def test_output_depends_only_on_inputs_never_on_the_machine_clock(monkeypatch):
    import diffpos_services.fusion.core as fusion_mod
    import diffpos_services.fusion.ingest as ingest_mod
    import diffpos_services.fusion.step as step_mod

    def no_clock():
        raise AssertionError("FusionCore read the machine clock")

    # the core must not read the clock at all (only run_fusion does): the fusion module's
    # `time` is replaced by a clock that fails (logging keeps the real one)
    clock = types.SimpleNamespace(time_ns=no_clock, time=no_clock, monotonic_ns=no_clock,
                                  monotonic=no_clock, perf_counter=no_clock)
    for mod in (fusion_mod, ingest_mod, step_mod):  # the core's modules (none imports time)
        monkeypatch.setattr(mod, "time", clock, raising=False)
    a = _run_stream(FusionCore(_cfg()), wall0=10**15)
    b = _run_stream(FusionCore(_cfg()), wall0=10**15)
    assert len(a) == len(NODES) * 8
    assert [M.encode(x) for x in a] == [M.encode(x) for x in b]
    # the caller's wall clock is what the estimates carry
    step_walls = {10**15 + e * PERIOD_NS + 1000 for e in range(8)} | {10**15 + 10**9}
    assert {x.t_pub_wall_ns for x in a} <= step_walls
    # shifting every wall time shifts only the wall-clock fields, never a fix
    c = _run_stream(FusionCore(_cfg()), wall0=3 * 10**15)

    def strip(x):
        return M.encode(msgspec.structs.replace(x, t_pub_wall_ns=0, t_input_wall_ns=0))

    assert [strip(x) for x in a] == [strip(x) for x in c]
    assert [x.t_pub_wall_ns - 10**15 for x in a] == [x.t_pub_wall_ns - 3 * 10**15 for x in c]


def test_single_subscription_sees_every_input_and_never_truth():
    """run_fusion's one key expression covers states, ranges and batches of any anchor (so
    an anchor's messages keep their publish order) and cannot intersect a truth key."""
    zenoh = pytest.importorskip("zenoh")
    from diffpos_services.fusion.service import fusion_subscription

    k = Keys("s")
    sub = zenoh.KeyExpr(fusion_subscription(k))
    for key in (k.anchor_state("uav1"), k.anchor_range("uav1", "n01"),
                k.anchor_range_batch("uav-2_x")):
        assert sub.intersects(zenoh.KeyExpr(key)), key
    for key in (k.truth_node("n01"), k.truth_anchor("uav1"), k.truth_all(),
                k.node_estimate("n01"), k.fusion_diagnostics(), k.alive_anchor("uav1"),
                Keys("other").anchor_state("uav1")):
        assert not sub.intersects(zenoh.KeyExpr(key)), key


def _fusion_args(*argv):
    import argparse

    from diffpos_services.cli import fusion as cmd_fusion

    p = argparse.ArgumentParser()
    cmd_fusion.add_arguments(p)
    return cmd_fusion, p.parse_args(list(argv))


def test_cli_allow_lists_from_ids_and_from_the_scenario():
    from diffpos.emulation import emulation_nodes
    from diffpos.scenario import default_scenario

    sc = default_scenario()
    cmd, args = _fusion_args("--anchors", " uav1, uav3 ,", "--nodes", "n01")
    cfg = cmd.config_from_args(args, sc)
    assert cfg.anchors == ("uav1", "uav3") and cfg.nodes == ("n01",)
    cmd, args = _fusion_args()
    cfg = cmd.config_from_args(args, sc)
    # the default method: mnls + tracking (the first-arrival model), with the scenario's
    # building and radio; D-NLS is opt-in
    assert cfg.anchors is None and cfg.nodes is None and cfg.method == "mnls" and cfg.tracking
    assert cfg.building is not None and cfg.radio is not None
    cmd, args = _fusion_args("--anchors", "scenario", "--nodes", "scenario", "--method", "ippa")
    cfg = cmd.config_from_args(args, sc)
    assert cfg.method == "ippa"
    assert cfg.anchors == tuple(a.id for a in sc.anchors) and len(cfg.anchors) >= 3
    # the paper scenario has only a study grid: its nodes are the emulated responders,
    # not scenario.nodes (empty)
    assert not sc.nodes
    assert cfg.nodes == tuple(n for n, _ in emulation_nodes(sc)) and len(cfg.nodes) == 6
    # the allow-list works in the core: an unlisted anchor and node are rejected
    core = FusionCore(_cfg(anchors=("uav1", "uav2"), nodes=("n01",)))
    _feed_epoch(core, 0, {"n01": NODES["n01"], "n02": NODES["n02"]}, np.random.default_rng(0))
    assert core.rejected["unknown_anchor"] == 3 * 3  # uav3..5: state + 2 ranges each
    assert core.rejected["unknown_node"] == 2  # uav1, uav2 -> n02
    assert set(core.anchors) == {"uav1", "uav2"}


def test_cli_max_backlog_is_the_live_default_and_0_never_drops():
    """--max-backlog-s goes to FusionConfig.max_backlog_s: the live default, a given value,
    and 0 = never drop (the struct's None; 0 itself is not a valid backlog)."""
    from diffpos_services.fusion.config import LIVE_MAX_BACKLOG_S

    from diffpos.scenario import default_scenario

    sc = default_scenario()
    for argv, expected in (((), LIVE_MAX_BACKLOG_S), (("--max-backlog-s", "0.7"), 0.7),
                           (("--max-backlog-s", "0"), None)):
        cmd, args = _fusion_args(*argv)
        assert cmd.config_from_args(args, sc).max_backlog_s == expected, argv


@pytest.mark.parametrize("argv, message", [
    (["--anchors", ","], "--anchors ','"),
    (["--nodes", "n01,bad/id"], "nodes[1]"),
    (["--anchors=-uav"], "anchors[0]"),
])
def test_cli_allow_list_errors_name_the_option(argv, message, capsys, monkeypatch):
    import logging

    from diffpos_services.cli import fusion as cmd_fusion
    from diffpos_services.cli.main import main as cli_main

    # the CLI configures process-wide logging: keep it out of the other tests
    monkeypatch.setattr(cmd_fusion, "setup_logging",
                        lambda *a, **k: logging.getLogger("diffpos.test.cli"))
    assert cli_main(["fusion", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_persistently_failing_node_is_not_cold_solved_every_epoch(monkeypatch):
    """A node whose fixes keep failing (4 anchors, one biased: detectable, not removable) gets a
    multi-start (cold) solve at most once per cold_retry_period_s of measurement time; in
    between it is warm-started from the last attempt. A healthy node stays warm throughout."""
    from diffpos.estimators.dnls import solver as est

    calls = []
    real = est.dnls

    def counting(*args, **kw):
        calls.append(("warm" if kw.get("x0_m") is not None else "cold", len(args[1])))
        return real(*args, **kw)

    monkeypatch.setattr(est, "dnls", counting)
    four = {k: ANCHORS[k] for k in ("uav1", "uav2", "uav3", "uav4")}
    nodes = {"n02": NODES["n02"]}
    core = FusionCore(_cfg(cold_retry_period_s=0.5))
    rng = np.random.default_rng(7)
    out = []
    epochs = 20  # 2 s of measurement time
    for e in range(epochs):
        _feed_epoch(core, e, nodes, rng, anchors=four, sigma=0.03, bias={("uav2", "n02"): 8.0})
        out += core.step(0)
    out += core.step(10**12)
    assert len(out) == epochs
    assert sum(g.status == "GATING_FAILED" for g in out) >= epochs - 2  # the premise
    cold_rows = sum(n for kind, n in calls if kind == "cold")
    # first epoch + at most one retry per 0.5 s: <= 1 + 2 s / 0.5 s (+1 for phase rounding)
    assert cold_rows <= 1 + 2 / 0.5 + 1, calls
    assert cold_rows >= 2, "retries must still happen (re-acquisition)"


def test_cli_edge_lower_is_the_upper_edge_model_one_window_lower():
    from diffpos_services.scenario_io import load_scenario_option

    sc = load_scenario_option(None)  # the paper's geometry: every UAV below the windows
    w = sc.building.window_height_m
    deltas = {}
    for edge in ("upper", "lower", "auto"):
        cmd_fusion, args = _fusion_args("--edge", edge, "--delta-m", "0.2")
        deltas[edge] = cmd_fusion.config_from_args(args, sc).delta_m
    assert deltas["upper"] == pytest.approx(0.2)
    assert deltas["lower"] == pytest.approx(0.2 + w)
    assert deltas["auto"] == deltas["lower"]
    # the lower-edge model equals window_edge_path(edge="lower") at the same Delta
    a, n = np.array([3.0, -15.0, 1.0]), np.array([-2.0, 6.0, 10.5])
    lower = window_edge_path(a, n, window_height_m=w, delta_m=0.2, edge="lower").length_m
    shifted = window_edge_path(a, n, window_height_m=w, delta_m=deltas["lower"]).length_m
    assert float(lower) == pytest.approx(float(shifted), rel=1e-12)
