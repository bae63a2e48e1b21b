"""Offline replay: determinism, reproduction of the live estimates, accuracy statistics
against a brute-force reference, what-if settings, damaged and foreign input, CLI outputs.

Recordings are written without Zenoh by ``write_synthetic_recording`` (known truth, and a
FusionCore playing the live fusion); the Zenoh path is covered by test_recorder.py.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.errors import ConfigError
from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from diffpos_services.wire import messages as M
from mcap.reader import make_reader
from mcap.writer import Writer


@pytest.fixture(scope="module")
def rec(tmp_path_factory) -> Path:
    """3 s, 5 anchors, 3 nodes, 10 Hz, 8 % NLoS-like outliers, live estimates recorded."""
    path = tmp_path_factory.mktemp("replay") / "synthetic.mcap"
    write_synthetic_recording(path, n_anchors=5, n_nodes=3, duration_s=3.0,
                              outlier_probability=0.08, seed=11, flush_every=200)
    return path


@pytest.fixture(scope="module")
def base(rec):
    """The replay of ``rec`` with its recorded settings (read-only: shared by the tests)."""
    return replay(rec)


@pytest.fixture(scope="module")
def no_motion_comp(rec):
    """The replay of ``rec`` without motion compensation (read-only, shared)."""
    return replay(rec, overrides={"motion_compensation": False})


def _encoded(ests):
    return [M.encode(e) for e in ests]


def test_replay_is_deterministic_bit_for_bit(rec, base):
    a = base
    b = replay(rec)
    assert len(a.estimates) == 3 * 30  # every node, every epoch
    assert _encoded(a.estimates) == _encoded(b.estimates)
    ra, rb = dict(a.report), dict(b.report)
    ra.pop("timing"), rb.pop("timing")
    assert json.dumps(ra, sort_keys=True) == json.dumps(rb, sort_keys=True)


def test_replay_with_live_settings_reproduces_live_estimates(base, no_motion_comp):
    r = base
    c = r.report["compare"]
    assert r.report["settings_source"] == "metadata fusion_config"
    # the recorded live fusion stepped on the same receive times: identical fixes; the only
    # extra replayed fixes are the last epoch, which the live run never flushed
    assert c["only_live"] == 0 and c["only_replayed"] == 3
    assert c["matched"] == len(r.live_estimates) and c["status_agree"] == 1.0
    assert c["identical_positions"] == c["with_positions"] > 0
    live = {(e.node_id, e.epoch): e for e in r.live_estimates}
    for e in r.estimates:
        if (e.node_id, e.epoch) in live:
            le = live[(e.node_id, e.epoch)]
            assert (le.position_m, le.peb_m, le.used_anchors, le.excluded) == (
                e.position_m, e.peb_m, e.used_anchors, e.excluded)


def test_accuracy_report_matches_brute_force_reference(rec, base):
    r = base
    truth: dict[str, list] = {}
    for m in McapScanner(rec).messages():
        if "/truth/node/" in m.topic:
            d = json.loads(m.data)
            truth.setdefault(d["id"], []).append((d["t_ns"], d["position_m"], d["floor_index"]))
    errs, zerrs, floor_ok = [], [], []
    for e in r.estimates:
        if e.status not in ("OK", "OK_UNVERIFIED") or e.position_m is None:
            continue
        samples = sorted(truth[e.node_id])
        # linear interpolation by hand between the bracketing samples
        for (t0, p0, f0), (t1, p1, f1) in itertools.pairwise(samples):
            if t0 <= e.t_ns <= t1:
                w = (e.t_ns - t0) / (t1 - t0)
                p = [p0[k] + w * (p1[k] - p0[k]) for k in range(3)]
                f = f0 if e.t_ns - t0 <= t1 - e.t_ns else f1
                break
        else:
            t, p, f = min(samples, key=lambda s: abs(s[0] - e.t_ns))
            assert abs(t - e.t_ns) <= 0.5e9
        d = [e.position_m[k] - p[k] for k in range(3)]
        errs.append(sum(x * x for x in d) ** 0.5)
        zerrs.append(abs(d[2]))
        floor_ok.append(e.floor_index == f)
    acc = r.report["accuracy"]["overall"]
    assert acc["evaluated"] == len(errs) > 60
    for p in (50, 90, 95):  # the report keeps errors as float32 (rounding 6e-8 relative)
        assert acc["error_3d_m"][f"p{p}"] == pytest.approx(np.percentile(errs, p), rel=1e-7)
        assert acc["error_z_m"][f"p{p}"] == pytest.approx(np.percentile(zerrs, p), rel=1e-7)
    assert acc["floor_accuracy"] == pytest.approx(np.mean(floor_ok))
    # and the fusion works on this data: sub-metre median with 10 cm ranging noise
    assert acc["error_3d_m"]["p50"] < 1.0
    per_node = r.report["accuracy"]["per_node"]
    assert sum(v["evaluated"] for v in per_node.values()) == len(errs)


def test_what_if_settings_change_the_outcome(rec, base):
    gated = sum(g["excluded"].get("RAIM", 0) for g in base.report["gating"].values())
    assert gated > 0  # the outliers are caught
    off = replay(rec, overrides={"gating": False})
    assert off.report["settings"]["gating"] is False
    assert all("RAIM" not in g["excluded"] for g in off.report["gating"].values())
    strict = replay(rec, overrides={"false_alarm_probability": 0.2})
    assert strict.report["settings"]["false_alarm_probability"] == 0.2
    gated_strict = sum(g["excluded"].get("RAIM", 0) for g in strict.report["gating"].values())
    assert gated_strict > gated  # a larger false-alarm rate excludes more
    lls = replay(rec, method="lls")
    assert lls.report["method"] == "lls"
    assert _encoded(lls.estimates) != _encoded(base.estimates)
    with pytest.raises(ConfigError, match="not a fusion setting"):
        replay(rec, overrides={"no_such_field": 1})
    with pytest.raises(ConfigError, match="false_alarm_probability"):
        replay(rec, overrides={"false_alarm_probability": 3})


def test_truncated_and_foreign_input(rec, tmp_path):
    data = rec.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    r = replay(cut)
    assert r.report["complete"] is False and r.report["damage"]["truncated"] is True
    n_prefix = sum(1 for _ in McapScanner(cut).messages())
    assert r.report["messages"]["total"] == n_prefix > 0
    assert 0 < len(r.estimates) < 90
    # unknown channels and a corrupt payload on a range key: skipped and counted
    mixed = tmp_path / "mixed.mcap"
    with McapSink(mixed) as sink:
        for m in McapScanner(rec).messages():
            sink.write(m.topic, m.data, m.log_ns)
        sink.write("/camera/front", b"\x01\x02", 1)
        sink.write("diffpos/synth/anchor/uav1/range/n01", b"{not json", 2)
    r = replay(mixed)
    assert r.report["messages"]["skipped_unknown"] == 1
    assert r.report["messages"]["fusion_rejected"] == {"json": 1}
    # a foreign MCAP with nothing to replay: a clear error, no traceback
    foreign = tmp_path / "foreign.mcap"
    with open(foreign, "wb") as f:
        w = Writer(f)
        w.start()
        cid = w.register_channel("/imu", "cdr", 0)
        w.add_message(cid, log_time=1, data=b"\x00", publish_time=1)
        w.finish()
    with pytest.raises(RecordingError, match="nothing to replay"):
        replay(foreign)


def test_cli_writes_report_plot_and_replayed_mcap(rec, tmp_path, capsys):
    out = tmp_path / "out"
    new = tmp_path / "replayed.mcap"
    rc = cli_main(["replay", str(rec), "--out", str(out), "--compare", "--write-mcap", str(new),
                   "--no-progress"])
    text = capsys.readouterr().out
    assert rc == 0
    assert "recorded live vs replayed" in text and "ALL" in text
    rep = json.loads((out / "report.json").read_text())
    assert rep["fixes"]["total"] == 90
    # estimate v1 (no floor probabilities): the calibration is absent, and the report says so
    assert rep["node_epochs"]["node_epochs"] > 0 and rep["node_epochs"]["floor_calibration"] is None
    assert "calibration not measured" in text
    assert (out / "cdf.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with open(new, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        replayed = [m for _, ch, m in reader.iter_messages() if "/replay/node/" in ch.topic]
        topics = {ch.topic: summary.schemas[ch.schema_id].name
                  for ch in summary.channels.values()}
    assert len(replayed) == 90
    # the current version of the estimate schema (v1, v2 once the wire moves)
    assert topics["diffpos/synth/replay/node/n01/estimate"].startswith("diffpos.estimate.v")
    assert summary.statistics.message_count == 90 + sum(1 for _ in McapScanner(rec).messages())
    # bad input: exit 2 with a one-line reason
    assert cli_main(["replay", str(tmp_path / "nope.mcap"), "--no-files"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert cli_main(["replay", str(rec), "--set", "deadline_s", "--no-files"]) == 2
    assert "FIELD=VALUE" in capsys.readouterr().err


SAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "sample.mcap"


def test_committed_sample_recording(tmp_path):
    """recordings/sample.mcap (a real emulate run): self-describing, valid, consistent counts,
    and the replay reproduces the recorded live fixes (see recordings/README.md for why not
    bit for bit)."""
    from diffpos_services.recording.summary import summarize, validate_file

    s = summarize(SAMPLE)
    assert s.complete and s.damage.ok and sum(s.gaps.values()) == 0
    assert s.anchors == ["uav1", "uav2", "uav3", "uav4"] and len(s.nodes) == 6
    v = validate_file(SAMPLE)
    assert v["invalid"] == 0 and v["no_schema"] == 0 and v["checked"] == s.messages
    kinds: dict[str, int] = {}
    for c in s.channels:
        kinds[c.kind] = kinds.get(c.kind, 0) + c.count
    # every anchor state comes with one range per node; one fix per node per epoch
    assert kinds["range"] == kinds["anchor_state"] * len(s.nodes)
    assert kinds["estimate"] == kinds["anchor_state"] // len(s.anchors) * len(s.nodes)
    assert {"run", "recorder_stats"} <= set(s.metadata)
    assert [a[0] for a in s.attachments] == ["paper.toml"]
    joined = {ev["id"] for ev in s.liveliness if ev["role"] == "anchor" and ev["alive"]}
    assert joined == set(s.anchors)

    r = replay(SAMPLE, out_mcap=None)
    assert r.report["settings_source"].startswith("derived")
    assert list(r.report["settings"]["edge_x_m"]) == [-20.0, 20.0]  # the attached scenario
    c = r.report["compare"]
    assert c["matched"] == len(r.live_estimates) == len(r.estimates) == kinds["estimate"]
    assert c["status_agree"] == 1.0 and c["position_diff_m"]["p50"] < 1e-3
    live = {(e.node_id, e.epoch): e.used_anchors for e in r.live_estimates}
    assert all(live[(e.node_id, e.epoch)] == e.used_anchors for e in r.estimates)
    acc = r.report["accuracy"]["overall"]
    assert acc["error_3d_m"]["p50"] < 0.3 and acc["floor_accuracy"] > 0.95
    ne = r.report["node_epochs"]  # estimate v1: scored, without a floor calibration
    assert ne["node_epochs"] > 0 and ne["floor_calibration"] is None


def test_replay_rrd_holds_the_replayed_estimates(rec, base, tmp_path, capsys):
    """`diffpos replay --rrd` writes the dashboard of the *replayed* fixes (read back by Rerun)."""
    from diffpos_services.dashboard.convert import rrd_rows

    out = tmp_path / "replay.rrd"
    assert cli_main(["replay", str(rec), "--no-files", "--no-progress", "--rrd", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    expected = {}
    for e in base.estimates:
        if e.position_m is not None:
            expected[(e.node_id, e.t_ns)] = np.asarray(e.position_m)
    rows = rrd_rows(out)
    got = {}
    for entity, entries in rows.items():
        parts = entity.strip("/").split("/")
        if parts[:2] != ["world", "nodes"] or parts[-1] != "estimate":
            continue
        for t_ns, comps in entries:
            positions = comps.get("Points3D:positions") or []
            stale = (comps.get("Points3D:labels") or [""])[0].endswith("?")
            if positions and not stale:  # a fix without a position: the last fix, grey, "?"
                got[(parts[2], t_ns)] = np.asarray(positions[0])
    assert expected, "the synthetic recording must yield fixes"
    assert got.keys() == expected.keys()
    for key, pos in expected.items():
        np.testing.assert_allclose(got[key], pos, atol=1e-5)  # float32 in the .rrd


def test_replay_method_lls_gives_the_lls_fix_of_each_epoch(rec, no_motion_comp):
    """``--method lls`` goes through FusionConfig.method: every fix equals diffpos.estimators.lls
    called directly on that epoch's recorded anchor positions and ranges (static anchors, no
    motion compensation, so the fusion's inputs are exactly the recorded values)."""
    from diffpos.estimators.lls import lls

    r = replay(rec, method="lls", overrides={"motion_compensation": False})
    assert r.report["method"] == r.report["settings"]["method"] == "lls"
    period = round(r.report["settings"]["epoch_period_s"] * 1e9)
    anchor_pos, ranges = {}, {}
    reader = make_reader(rec.open("rb"))
    for _s, ch, msg in reader.iter_messages():
        parts = ch.topic.split("/")
        if parts[2:3] == ["anchor"] and parts[4] == "state":
            anchor_pos[parts[3]] = json.loads(msg.data)["position_m"]
        elif parts[2:3] == ["anchor"] and parts[4] == "range":
            d = json.loads(msg.data)
            ranges[(d["node_id"], d["t_ns"] // period, d["anchor_id"])] = d["range_m"]
    checked = 0
    for e in r.estimates:
        if e.position_m is None:
            continue
        ids = sorted(e.used_anchors)
        a = np.array([anchor_pos[i] for i in ids])
        rr = np.array([ranges[(e.node_id, e.epoch, i)] for i in ids])
        ref = lls(a[None], rr[None])
        np.testing.assert_allclose(e.position_m, ref.position_m[0], rtol=0, atol=1e-9)
        checked += 1
    assert checked >= 80  # 3 nodes x 30 epochs, LLS solves every complete epoch
    # the default is still D-NLS, and it differs
    d = no_motion_comp
    assert d.report["method"] == "dnls"
    assert _encoded(d.estimates) != _encoded(r.estimates)


def test_range_batch_recording_replays_like_single_ranges(base, tmp_path):
    """Anchors publishing one RangeBatch per epoch (``--range-batch``): the replay feeds the
    batches to the fusion (it used to skip them), reproduces the recorded live estimates,
    and gives the same fixes as the same run recorded with one message per range."""
    path = tmp_path / "batched.mcap"
    counts = write_synthetic_recording(path, n_anchors=5, n_nodes=3, duration_s=3.0,
                                       outlier_probability=0.08, seed=11, flush_every=200,
                                       range_batch=True)
    assert counts["range_batch"] == 5 * 30 and "range" not in counts
    r = replay(path)
    assert r.report["messages"]["fusion_received"]["range_batch"] == 5 * 30
    c = r.report["compare"]
    assert c["only_live"] == 0 and c["status_agree"] == 1.0
    assert c["identical_positions"] == c["with_positions"] > 0
    single = {(e.node_id, e.epoch): e for e in base.estimates}
    assert len(r.estimates) == len(single) == 3 * 30
    for e in r.estimates:
        s = single[(e.node_id, e.epoch)]
        assert (e.status, e.position_m, e.used_anchors, e.excluded) == (
            s.status, s.position_m, s.used_anchors, s.excluded)


def test_replay_restores_the_garbage_collector_thresholds(rec, tmp_path):
    """Replay runs the cyclic GC less often while it holds its estimates; the process's own
    thresholds are back afterwards, also when the replay fails."""
    import gc

    before = gc.get_threshold()
    assert len(replay(rec).estimates) == 3 * 30
    assert gc.get_threshold() == before
    bad = tmp_path / "not.mcap"
    bad.write_bytes(b"not an mcap file")
    with pytest.raises(RecordingError):
        replay(bad)
    assert gc.get_threshold() == before


def test_split_recording_replays_as_one(rec, base, tmp_path):
    """A recording the recorder split into parts (``--split-duration``: r.mcap, r_0001.mcap, ...,
    channel ids restarting in every part) replays as the whole run: the same fixes and report
    as the unsplit file, the parts named in the report."""
    from diffpos_services.recording.reader import side_records
    from diffpos_services.recording.writer import SplitPolicy, existing_parts

    first = tmp_path / "split.mcap"
    side = side_records(rec)
    sink = McapSink(first, split=SplitPolicy(max_duration_s=1.0))
    for md in side.metadata:
        sink.add_metadata(md.name, md.metadata)
    for i, m in enumerate(McapScanner(rec).messages()):
        sink.write(m.topic, m.data, m.log_ns, publish_ns=m.publish_ns, sequence=m.sequence)
        if i % 50 == 49:
            sink.flush()  # the recorder's flush: where a full part is closed
    sink.close()
    parts = existing_parts(first)
    assert len(parts) >= 3
    r = replay(first)
    assert r.report["parts"] == [p.name for p in parts]
    assert r.report["complete"] and r.report["damage"]["ok"]
    assert _encoded(r.estimates) == _encoded(base.estimates)
    assert r.report["compare"] == base.report["compare"]
    assert r.report["accuracy"] == base.report["accuracy"]
    assert r.report["messages"]["by_kind"] == base.report["messages"]["by_kind"]


def test_streamed_report_stays_bounded_and_within_its_stated_error():
    """The report of a long run: 2 nodes x 10 Hz x 10 min of fixes against a known truth
    (the truth at the fix times, errors from a seeded generator) through the replay's
    FixStream: every fix evaluated, the percentiles within 0.5 % of numpy's over all errors
    (the sketches left their exact mode), counts exact, and nothing kept per fix."""
    from diffpos_services.replay.report_stream import FixStream, SlimEstimate, TruthBook

    rng = np.random.default_rng(5)
    period, n = 100_000_000, 6_000
    noise = rng.normal(scale=0.5, size=(n, 2, 3)).tolist()
    tb = TruthBook(window_ns=30_000_000_000)
    fs = FixStream(tb, max_truth_gap_ns=500_000_000, window_ns=30_000_000_000)
    errs = []
    for k in range(n):
        t = (k + 1) * period
        for j, node in enumerate(("n1", "n2")):
            truth = (float(k % 50), 2.0, 1.0)
            tb.add(node, t, truth, 0)
            d = noise[k][j]
            errs.append(math.hypot(*d))
            pos = (truth[0] + d[0], truth[1] + d[1], truth[2] + d[2])
            fs.add(SlimEstimate("diffpos.estimate.v1", node, t, k, "OK", position_m=pos,
                                peb_m=0.4, floor_index=0))
        if k % 100 == 99:
            fs.advance(t)
    fs.advance(n * period, final=True)
    acc, arrays = fs.accuracy()
    overall = acc["overall"]
    assert overall["evaluated"] == overall["fixes"] == 2 * n
    assert overall["floor_accuracy"] == 1.0 and overall["without_truth"] == 0
    assert not fs._overall.e3.exact  # beyond 4,096 values: the histogram
    ref = np.percentile(errs, [50, 90, 99])
    got = [overall["error_3d_m"][k] for k in ("p50", "p90", "p99")]
    np.testing.assert_allclose(got, ref, rtol=0.005)
    assert overall["error_3d_m"]["max"] == pytest.approx(max(errs), rel=1e-12)
    assert overall["within_2peb"] == pytest.approx(np.mean(np.array(errs) <= 0.8))
    ne = fs.node_epochs()
    assert ne["node_epochs"] == ne["fixes"] == 2 * (n - 20)  # the first 2 s are skipped
    # nothing per fix is left: the pending queues and buffers are empty, truth is windowed
    assert fs.pending_fixes == 0 and len(fs._store) == 0 and len(fs._err.e3) == 0
    assert len(tb.t["n1"]) <= 2 * 300 + 1
    assert arrays["e3"].size == 2 * n  # for plots, made on access


def test_streamed_report_has_the_floor_calibration_of_the_node_epochs():
    """Replay's report (FixStream) over v2 fixes with floor probabilities: the calibration of
    its node-epochs is the core's over the same node-epochs (misses and a NaN vector
    included), whatever the batching; over v1 fixes (no probabilities) it is absent."""
    from diffpos_services.replay.report_stream import FixStream, SlimEstimate, TruthBook

    from diffpos.floor_calibration import floor_calibration

    rng = np.random.default_rng(8)
    period, n, nf = 100_000_000, 300, 3
    results = []
    for schema in ("diffpos.estimate.v2", "diffpos.estimate.v1"):
        tb = TruthBook(window_ns=5_000_000_000)
        fs = FixStream(tb, max_truth_gap_ns=500_000_000, window_ns=5_000_000_000)
        ef, tf, probs, has = [], [], [], []
        for k in range(n):
            t = (k + 1) * period
            for j, node in enumerate(("n1", "n2")):
                floor = (k // 50 + j) % nf
                tb.add(node, t, (1.0, 2.0, 1.5 + 3.0 * floor), floor)
                p = rng.dirichlet(np.ones(nf) * 0.4)
                pub = int(np.argmax(p))
                if k == 77:
                    p[1] = np.nan  # counted as without probabilities
                miss = rng.random() < 0.05
                if not miss:
                    fs.add(SlimEstimate(schema, node, t, k, "TRACKING",
                                        position_m=(1.0, 2.0, 1.5 + 3.0 * floor),
                                        floor_index=pub,
                                        floor_probabilities=p.tolist() if "v2" in schema
                                        else []))
                if k >= 20:  # the report skips the first 2 s
                    ef.append(-1 if miss else pub), tf.append(floor), probs.append(p)
                    has.append(not miss)
            if k % 9 == 8:  # the replay advances every few epochs of recording time
                fs.advance(t)
        fs.advance(n * period, final=True)
        results.append((fs.node_epochs(), floor_calibration(ef, tf, np.array(probs),
                                                           has_position=has)))
    (ne, ref), (ne1, _) = results
    c = ne["floor_calibration"]
    assert ne["node_epochs"] == c["node_epochs"] == ref["node_epochs"] == 2 * (n - 20)
    assert c["without_probabilities"] == ref["without_probabilities"] >= 1
    assert c["confidently_wrong_count"] == ref["confidently_wrong_count"] > 0
    assert [r["count"] for r in c["reliability"]] == [r["count"] for r in ref["reliability"]]
    for key in ("ece", "log_score", "brier", "confidently_wrong"):
        assert c[key] == pytest.approx(ref[key], rel=1e-12)
    assert ne1["floor_calibration"] is None and ne1["node_epochs"] == 2 * (n - 20)
