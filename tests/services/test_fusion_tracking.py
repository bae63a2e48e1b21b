"""The fusion with mnls + tracking (the default): estimate v2 for every node-epoch, determinism,
replay equivalence, coasting; the old v1 sample still replays.

The fusion's input is made independently of the fusion: the channel emulator
(:func:`diffpos.channel.emulator.emulate_channel` + the first-arrival detector) ranges from five static
UAVs to three walkers of the default building (one takes the stairs), packed into the wire
messages an anchor publishes (AnchorState + RangeBatch per anchor and epoch). No processes, no
bus; fixed seeds.
"""

from __future__ import annotations

import functools
import itertools
from pathlib import Path

import msgspec
import numpy as np
import pytest
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.tracked import TrackBank
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import quiet_logger
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.scenario import default_scenario
from diffpos.trajectory import trajectory_from_dict

SC = default_scenario()
B = SC.building
KEYS = Keys("t")
PERIOD = 100_000_000
T0 = 1_800_000_000_000_000_000  # on the epoch grid
ANCHORS = {"uav1": [-15.0, -20.0, 1.0], "uav2": [0.0, -15.0, 0.0], "uav3": [0.0, -7.0, 4.0],
           "uav4": [15.0, -20.0, 1.0], "uav5": [-25.0, -12.0, 3.0]}
H = B.nominal_node_height_m
WALKERS = {
    "w1": [[-10.0, 5.0, 4.0 + H], [0.0, 5.0, 4.0 + H]],
    "w2": [[5.0, 8.0, 7.0 + H], [5.0, 3.0, 7.0 + H], [12.0, 3.0, 7.0 + H]],
    "w3": [[2.0, 4.0, 10.0 + H], [6.0, 4.0, 11.5 + H], [8.0, 4.0, 13.0 + H]],  # up the stairs
}
EPOCHS = 20  # 2 s: initialisation (a snapshot per second), confirmation, steady tracking


def _config(**kw) -> FusionConfig:
    """The tracked fusion (mnls + tracking) unless ``kw`` names another method."""
    return FusionConfig.from_scenario(SC, site="t", epoch_period_s=0.1,
                                      **{"method": "mnls", **kw})


@functools.cache
def _arrivals(epochs: int, seed: int) -> tuple:
    """The emulated first arrivals (UAVs x walkers) of every epoch, drawn once per
    ``(epochs, seed)``: the dark variant of a run sees the same channel as the run."""
    rng = np.random.default_rng(seed)
    trajs = [trajectory_from_dict({"kind": "waypoints", "points_m": p, "speed_m_s": 1.0})
             for p in WALKERS.values()]
    anchors = np.array(list(ANCHORS.values()))
    return tuple(
        first_arrival(emulate_channel(anchors, np.stack([tr.position_m(k * 0.1) for tr in trajs]),
                                      building=B, radio=SC.radio), radio=SC.radio, rng=rng)
        for k in range(epochs))


def _inputs(epochs: int = EPOCHS, *, dark: dict[str, int] | None = None, seed: int = 0):
    """``(rx_ns, key, payload)`` of every anchor's state and range batch per epoch.

    ``dark``: node -> first epoch from which no anchor detects it (ranges null)."""
    ids = list(WALKERS)
    a_ids = list(ANCHORS)
    anchors = np.array([ANCHORS[a] for a in a_ids])
    out = []
    for k, fa in enumerate(_arrivals(epochs, seed)):
        t = T0 + k * PERIOD + 20_000_000
        for j, a in enumerate(a_ids):
            rx = t + 1_000_000 + 100_000 * j
            st = M.AnchorState(anchor_id=a, t_ns=t, seq=k, position_m=M.vec3(anchors[j]),
                               velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.02, 0.02, 0.03),
                               velocity_sigma_m_s=0.05, range_rate_hz=10.0, t_pub_wall_ns=rx)
            det = [bool(fa.detected[i, j]) and (dark or {}).get(n, 10**9) > k
                   for i, n in enumerate(ids)]
            batch = M.RangeBatch(
                anchor_id=a, t_ns=t, seq=k, node_ids=ids,
                range_m=[float(fa.range_m[i, j]) if det[i] else None for i in range(len(ids))],
                sigma_m=[float(fa.sigma_m[i, j]) if det[i] else None for i in range(len(ids))],
                snr_db=[float(fa.snr_db[i, j]) if det[i] else None for i in range(len(ids))],
                t_pub_wall_ns=rx)
            out += [(rx, KEYS.anchor_state(a), M.encode(st)),
                    (rx + 10, KEYS.anchor_range_batch(a), M.encode(batch))]
    return out


def _run(samples, *, step_every: int = 1, config: FusionConfig | None = None):
    """The live fusion over ``samples``: stepped after every ``step_every`` samples, flushed."""
    core = FusionCore(config or _config(), logger=quiet_logger())
    for a in ANCHORS:
        core.on_liveliness(a, True, T0 - 10**8)
    out = []
    for i, (rx, key, payload) in enumerate(samples):
        core.on_sample(key, payload, rx)
        if i % step_every == step_every - 1:
            out += [msgspec.structs.replace(e, t_pub_wall_ns=rx) for e in core.step(rx)]
    last = samples[-1][0]
    out += [msgspec.structs.replace(e, t_pub_wall_ns=last) for e in core.step(last + 10**12)]
    out += [msgspec.structs.replace(e, t_pub_wall_ns=last) for e in core.flush(last)]
    return core, out


def _by_key(ests):
    """(node, epoch) -> encoded estimate without the publish-order fields (seq, publish time)."""
    return {(e.node_id, e.epoch): M.encode(msgspec.structs.replace(e, seq=0, t_pub_wall_ns=0))
            for e in ests}


@pytest.fixture(scope="module")
def live():
    samples = _inputs()
    core, ests = _run(samples)
    return samples, core, ests


def test_every_node_epoch_gets_a_v2_estimate(live):
    """One PositionEstimateV2 per node and epoch; a position with a consistent floor, floor
    probabilities summing to 1 and a mechanism label per used anchor once initialised."""
    _, core, ests = live
    assert core.method_name == "mnls+tracking"
    assert all(type(e) is M.PositionEstimateV2 and e.method == "mnls+tracking" for e in ests)
    keys = [(e.node_id, e.epoch) for e in ests]
    assert len(keys) == len(set(keys)) == len(WALKERS) * EPOCHS
    assert {e.status for e in ests} <= set(M.TRACK_STATUSES)
    with_pos = [e for e in ests if e.position_m is not None]
    assert len(with_pos) >= 0.9 * len(ests)
    for e in with_pos:
        assert e.status in M.GOOD_STATUSES and e.covariance_m2 is not None
        assert sum(e.floor_probabilities) == pytest.approx(1.0, abs=1e-9)
        assert e.floor_index == int(np.argmax(e.floor_probabilities))
        assert np.all(np.linalg.eigvalsh(np.array(e.covariance_m2)) > 0)
        assert e.peb_m == pytest.approx(np.sqrt(np.trace(np.array(e.covariance_m2))))
        used = {lk.anchor_id: lk for lk in e.links if lk.mechanism is not None}
        assert set(e.used_anchors) == set(used)
        assert all(lk.mechanism in MECHANISMS for lk in used.values())
        assert e.residuals_m == pytest.approx([used[a].residual_m for a in e.used_anchors])
    # no snapshot in the epoch a node's track starts (FusionConfig.snapshot_at_start False),
    # later only while its floor is in doubt, at most one per snapshot period
    first = min(e.epoch for e in ests)
    assert core.config.snapshot_at_start is False
    assert all(e.snapshot is None for e in ests if e.epoch == first)
    assert sum(e.snapshot is not None for e in ests) <= len(WALKERS) * EPOCHS // 10


def test_with_snapshot_at_start_a_node_s_first_epoch_carries_its_snapshot(live):
    """``snapshot_at_start=True`` (recordings made before the setting): the snapshot rides
    along with a node's first epoch, then at most once per second; the tracked positions are
    the same as without it."""
    samples, _, ests = live
    _, old = _run(samples, config=_config(snapshot_at_start=True))
    first = min(e.epoch for e in old)
    assert all(e.snapshot is not None for e in old if e.epoch == first)
    assert 0 < sum(e.snapshot is not None for e in old) < len(old)
    drop = {"seq": 0, "t_pub_wall_ns": 0, "snapshot": None}
    assert ({(e.node_id, e.epoch): M.encode(msgspec.structs.replace(e, **drop)) for e in old}
            == {(e.node_id, e.epoch): M.encode(msgspec.structs.replace(e, **drop)) for e in ests})


def test_estimates_are_close_to_the_truth_for_a_walker_on_the_level(live):
    """The tracked walker w1 (5 anchors, floor 0) stays within 1 m and on its floor after the
    first second (a loose bound: accuracy is the benchmark's job)."""
    _, _, ests = live
    traj = trajectory_from_dict({"kind": "waypoints", "points_m": WALKERS["w1"],
                                 "speed_m_s": 1.0})
    for e in ests:
        k = e.epoch - T0 // PERIOD
        if e.node_id != "w1" or k < 10:
            continue
        truth = traj.position_m((e.t_ns - T0) * 1e-9)
        assert e.floor_index == 0
        assert np.linalg.norm(np.array(e.position_m) - truth) < 1.0


def test_two_runs_are_bit_identical_and_batching_does_not_matter(live):
    """The same input gives the same bytes; stepping after every epoch's messages (larger
    batches, as a replay or a busy live service does) gives the same estimates per node-epoch."""
    samples, _, ests = live
    _, again = _run(samples)
    assert [M.encode(e) for e in again] == [M.encode(e) for e in ests]
    _, batched = _run(samples, step_every=len(ANCHORS) * 2 * 3)
    assert _by_key(batched) == _by_key(ests)


def test_replay_of_a_tracked_recording_reproduces_live(live, tmp_path):
    """Recorded like the recorder does (inputs, liveliness, the live estimates and the fusion
    settings), ``replay`` re-runs the same tracker and gets every estimate bit for bit."""
    samples, core, ests = live
    path = tmp_path / "tracked.mcap"
    with McapSink(path, library="test") as sink:
        sink.add_metadata("fusion_config", msgspec.to_builtins(core.config))
        for a in ANCHORS:
            sink.write_liveliness("t", KEYS.alive_anchor(a), True, T0 - 10**8)
        for rx, key, payload in samples:
            sink.write(key, payload, rx)
        for e in ests:
            sink.write(KEYS.node_estimate(e.node_id), M.encode(e), e.t_pub_wall_ns + 1)
    r = replay(path)
    assert r.report["settings"]["method"] == "mnls" and r.report["settings"]["tracking"]
    assert _by_key(r.estimates) == _by_key(ests)


def test_a_node_without_ranges_coasts_with_growing_covariance():
    """w1 loses every range at epoch 12 (its track confirmed at 5): it coasts (a position,
    status COASTING) with a covariance trace that grows every epoch to the end; the other
    nodes keep tracking. The channel draws are the live run's."""
    samples = _inputs(EPOCHS, dark={"w1": 12})
    _, ests = _run(samples)
    w1 = sorted((e for e in ests if e.node_id == "w1"), key=lambda e: e.epoch)
    before = [e for e in w1 if e.epoch - T0 // PERIOD < 12]
    after = [e for e in w1 if e.epoch - T0 // PERIOD >= 12]
    assert len(after) == EPOCHS - 12
    assert before[-1].status in ("TRACKING", "INITIALISING") and before[-1].position_m
    assert all(e.status == "COASTING" and e.position_m is not None for e in after)
    assert all(not e.used_anchors and all(lk.mechanism is None for lk in e.links) for e in after)
    tr = [np.trace(np.array(e.covariance_m2)) for e in [before[-1], *after]]
    assert all(b > a for a, b in itertools.pairwise(tr)), tr
    others = [e for e in ests if e.node_id != "w1" and e.epoch - T0 // PERIOD >= 12]
    assert all(e.status != "COASTING" for e in others)


def test_methods_other_than_mnls_still_publish_v1_unchanged(live):
    """--method dnls keeps estimate v1 (D-NLS, bit-identical to before: no tracker involved)."""
    samples, _, _ = live
    core, ests = _run(samples[: 2 * len(ANCHORS) * 8], config=_config(method="dnls"))
    assert core.bank is None and core.building is None
    assert ests and all(type(e) is M.PositionEstimate for e in ests)


def test_mnls_without_tracking_publishes_snapshot_statuses(live):
    samples, _, _ = live
    core, ests = _run(samples[: 2 * len(ANCHORS) * 6], config=_config(tracking=False))
    assert core.method_name == "mnls"
    assert all(type(e) is M.PositionEstimateV2 and e.snapshot is None for e in ests)
    assert {e.status for e in ests} <= {s for s in M.GOOD_STATUSES | {
        "NOT_CONVERGED", "NOT_IDENTIFIABLE", "TOO_FEW_ANCHORS", "GATING_FAILED",
        "INVALID_INPUT"} if s not in M.TRACK_STATUSES}
    assert sum(e.position_m is not None for e in ests) >= 0.8 * len(ests)


def test_the_v1_sample_still_replays_with_d_nls():
    """recordings/sample.mcap (estimate v1, no stored settings) replays with the fusion that
    made it (D-NLS, derived settings) and every replayed fix is v1."""
    sample = Path(__file__).resolve().parents[2] / "recordings" / "sample.mcap"
    r = replay(sample, out_mcap=None)
    assert r.report["settings"]["method"] == "dnls"
    assert r.estimates and all(type(e) is M.PositionEstimate for e in r.estimates)
    assert len(r.estimates) == len(r.live_estimates) > 0
    # the report also scores every node-epoch after 2 s of truth (diffpos.metrics.score):
    # 720 truth samples of 6 nodes at 10 Hz minus the first 2 s
    ne, live_ne = r.report["node_epochs"], r.report["live"]["node_epochs"]
    assert ne["node_epochs"] == live_ne["node_epochs"] == 720 - 6 * 20
    assert ne["fixes"] <= ne["node_epochs"] and ne["availability"] > 0.5
    assert ne["floor_accuracy_all"] <= ne["availability"]


def test_silent_anchors_reach_the_tracker_only_with_the_setting(monkeypatch):
    """w1's anchors report no path from epoch 12 on (null ranges). With
    ``tracker.silent_anchor_nats`` the tracker gets, for each of w1's later epochs, every
    anchor as a masked link with SNR -inf at the anchor's published position (the input's
    ``ANCHORS``, 1e-9 m) and no other -inf; without it, no -inf SNR and the anchors of the
    masked links are the placeholder 0 (the run as before)."""
    calls = []
    orig = TrackBank.update

    def spy(self, node_ids, anchors, ranges, sigmas, mask, t_ns, snr_db=None, radio=None):
        calls.append((list(node_ids), np.array(anchors), np.array(mask), np.array(snr_db)))
        return orig(self, node_ids, anchors, ranges, sigmas, mask, t_ns, snr_db, radio)

    monkeypatch.setattr(TrackBank, "update", spy)
    samples = _inputs(EPOCHS, dark={"w1": 12})
    ref = np.array(list(ANCHORS.values()))
    for on in (False, True):
        calls.clear()
        cfg = _config()
        if on:
            cfg = msgspec.structs.replace(cfg, tracker=msgspec.structs.replace(
                cfg.tracker, silent_anchor_nats=2.0))
        _run(samples, config=cfg)
        silent_rows = 0
        for ids, anc, mask, snr in calls:
            for i, n in enumerate(ids):
                neg = np.isneginf(snr[i])
                if not on:
                    assert not neg.any()
                    assert np.all(anc[i][~mask[i]] == 0.0)
                    continue
                assert not (neg & mask[i]).any()
                if n == "w1" and not mask[i].any():
                    assert neg.all()
                    assert np.allclose(anc[i], ref, atol=1e-9, rtol=0)
                    silent_rows += 1
        assert silent_rows == (EPOCHS - 12 if on else 0)
