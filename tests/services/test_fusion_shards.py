"""Scale-out by responder (``diffpos fusion --shard K/N``, FusionConfig.shard/shards): N
fusion cores, each fed every message of a run, together publish exactly what one fusion
publishes (every estimate's fields bit for bit but its per-publisher ``seq``), and each
publishes only the responders its shard owns.

Input: seeded synthetic runs (replay/synthetic.py: anchors outside the facade, nodes walking
inside, diffraction ranges plus noise and NLoS outliers), single ranges and range batches; no
processes, no bus.
"""

from __future__ import annotations

import zlib

import msgspec
import pytest
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import FusionConfig, parse_shard, shard_of
from diffpos_services.fusion.core import FusionCore
from diffpos_services.replay.synthetic import quiet_logger, synthetic_run


def _run(config: FusionConfig, run) -> list:
    """Every estimate of ``run`` by one core with ``config``, stepped after each epoch's
    messages and flushed at the end (as a replay steps it)."""
    core = FusionCore(config, logger=quiet_logger(), record_decisions=False)
    t = run.t0_ns - 100_000_000
    for a in run.anchor_ids:
        core.on_liveliness(a, True, t)
    out = []
    for items in run.epochs:
        for rx, key, payload in items:
            core.on_sample(key, payload, rx)
            t = rx
        out += core.step(t + 1000)
    out += core.flush(t + 2000)
    return out


def _by_node_epoch(estimates) -> dict:
    """``(node, epoch) -> estimate`` bytes without the publisher's sequence number."""
    out = {}
    for e in estimates:
        key = (e.node_id, e.epoch)
        assert key not in out, f"two estimates of {key}"
        out[key] = msgspec.json.encode(msgspec.structs.replace(e, seq=0))
    return out


def _synthetic(batch: bool):
    return synthetic_run(n_anchors=5, n_nodes=7, duration_s=2.5, outlier_probability=0.1,
                         seed=11, range_batch=batch)


@pytest.mark.parametrize(("method", "batch", "n"), [
    ("dnls", False, 2), ("dnls", True, 3), ("mnls", True, 2), ("mnls", False, 3)])
def test_shards_together_publish_what_one_fusion_publishes(method, batch, n):
    one_cfg = msgspec.structs.replace(_synthetic(batch).config, method=method)
    one = _by_node_epoch(_run(one_cfg, _synthetic(batch)))
    assert len({node for node, _ in one}) == 7 and len(one) >= 7 * 20
    union: dict = {}
    owners = set()
    for k in range(n):
        cfg = msgspec.structs.replace(one_cfg, shard=k, shards=n)
        part = _by_node_epoch(_run(cfg, _synthetic(batch)))
        # only its own responders (an independent CRC-32 of the id, not the code's helper)
        assert all(zlib.crc32(node.encode()) % n == k for node, _ in part)
        owners |= {k} if part else set()
        assert not union.keys() & part.keys()
        union.update(part)
    assert len(owners) >= 2  # the run's responders are really split
    assert union.keys() == one.keys()
    assert all(union[k] == one[k] for k in one)  # positions, floors, statuses, ... bit for bit


def test_shard_of_is_a_stable_hash_and_parse_shard_checks():
    # CRC-32 of the UTF-8 id (fixed values: the same in every process and Python)
    assert [shard_of(f"n{i}", 2) for i in range(6)] == [zlib.crc32(f"n{i}".encode()) % 2
                                                        for i in range(6)]
    assert shard_of("anything", 1) == 0
    assert parse_shard("1/3") == (1, 3)
    for bad in ("3/3", "-1/2", "1", "a/b", "0/0"):
        with pytest.raises(ConfigError, match="K/N"):
            parse_shard(bad)
    with pytest.raises(ValueError, match="shard=2 must be < shards=2"):
        FusionConfig(shard=2, shards=2).check()
    assert FusionConfig(shard=1, shards=2).owns("n0") == (zlib.crc32(b"n0") % 2 == 1)


def test_emulate_merges_the_shards_diagnostics_and_supervises_each_shard_as_the_fusion():
    from diffpos_services.emulate.orchestrator import merged_diagnostics
    from diffpos_services.emulate.supervise import ESSENTIAL, RESTARTABLE, fusion_name, service_role
    from diffpos_services.wire import messages as M

    def diag(t, wm, pending, solved, p99, rejected):
        return M.FusionDiagnostics(
            t_wall_ns=t, watermark_ns=wm, received={"range": 10, "other_shard": 5},
            rejected=rejected, gated=1, solved=solved, published=solved,
            fixes_by_status={"TRACKING": solved}, late_ranges=2, pending_epochs=pending,
            live_anchors=["a"], anchors=[], latency=M.LatencyStats(3, 1.0, p99, p99),
            late_by_anchor={"a": 2}, deadline_ns=1, max_lag_ns=1, lag_by_anchor={},
            releases={"complete": solved})

    m = merged_diagnostics([diag(5, 300, 0, 7, 9.0, {"late": 1}),
                            diag(6, 200, 3, 4, 2.0, {"late": 2, "schema": 1})])
    assert (m.t_wall_ns, m.watermark_ns, m.pending_epochs, m.solved, m.published) == (
        6, 200, 3, 11, 11)
    assert m.received == {"range": 20, "other_shard": 10}
    assert m.rejected == {"late": 3, "schema": 1} and m.late_by_anchor == {"a": 4}
    assert m.latency.p99_ms == 9.0 and m.releases == {"complete": 11}
    assert merged_diagnostics([diag(5, None, 0, 1, 1.0, {}),
                               diag(6, 200, 0, 1, 1.0, {})]).watermark_ns is None
    assert [fusion_name(k, 2) for k in range(2)] == ["fusion-0", "fusion-1"]
    assert fusion_name(0, 1) == "fusion"
    assert {service_role(fusion_name(k, 3)) for k in range(3)} == {"fusion"}
    assert "fusion" in RESTARTABLE and "fusion" in ESSENTIAL
    assert service_role("anchor-uav1") == "anchor-uav1"
