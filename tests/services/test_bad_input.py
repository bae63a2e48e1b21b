"""Bad input: every nasty message is rejected with a named reason, counted, logged once per
anchor and reason, never raises, and no good message is lost (estimates equal those of the
clean stream). Also `diffpos solve` on nasty lines and config/scenario errors naming the
field, all in this process (``cli.main.main``); the same as real ``diffpos`` processes (the
exit code a user sees) is tests/system/test_bad_input_process.py.

The committed corpus is tests/data/nasty/ (README.md is its index, parsed here).
"""

from __future__ import annotations

import copy
import io
import json
import logging
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from diffpos_services.cli import main as cli
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.wire import messages as M
from fusion_scene import ANCHORS, EDGE, KEYS, NODES, PERIOD_NS, W
from fusion_scene import fusion_config as _cfg

from diffpos.geometry import window_edge_path
from diffpos.scenario import PAPER_DICT, Scenario, ScenarioError

NASTY = Path(__file__).resolve().parents[1] / "data" / "nasty"
def _strict_cfg(**kw) -> FusionConfig:
    """The corpus configuration (README): allow-lists and a 1 KiB message limit."""
    return _cfg(anchors=list(ANCHORS), nodes=list(NODES), max_message_bytes=4096, **kw)


def good_stream(n_epochs: int, *, seed: int = 0) -> list[list[tuple[str, bytes, int]]]:
    """Per epoch, the (key, payload, rx wall ns) of what the 5 anchors publish: a state and a
    range to every node, one sequence counter per anchor (state, then ranges), as the anchor
    service does. Times start at 0; the wall clock runs 1 ms behind the anchors."""
    rng = np.random.default_rng(seed)
    seq = dict.fromkeys(ANCHORS, 0)
    out = []
    for e in range(n_epochs):
        msgs = []
        for j, (aid, apos) in enumerate(ANCHORS.items()):
            t_ns = e * PERIOD_NS + int((0.1 + 0.15 * j) * PERIOD_NS)
            wall = t_ns + 1_000_000
            seq[aid] += 1
            st = M.AnchorState(anchor_id=aid, t_ns=t_ns, seq=seq[aid], position_m=M.vec3(apos),
                               velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.01,) * 3,
                               velocity_sigma_m_s=0.0, range_rate_hz=10.0, t_pub_wall_ns=wall)
            msgs.append((KEYS.anchor_state(aid), M.encode(st), wall))
            for nid, npos in NODES.items():
                r = float(window_edge_path(apos, npos, window_height_m=W, edge_x_m=EDGE).length_m)
                seq[aid] += 1
                rm = M.RangeMeasurement(anchor_id=aid, node_id=nid, t_ns=t_ns, seq=seq[aid],
                                        range_m=r + rng.normal(0, 0.05), sigma_m=0.05,
                                        snr_db=20.0, t_pub_wall_ns=wall)
                msgs.append((KEYS.anchor_range(aid, nid), M.encode(rm), wall))
        out.append(msgs)
    return out


def run_stream(core: FusionCore, epochs, extra=None, *, seed: int = 1):
    """Feed the epochs (with ``extra[e]`` bad messages spread at random positions inside
    epoch e), stepping at each epoch's end; return the estimates in a comparable form."""
    rng = np.random.default_rng(seed)
    got = []
    for e, msgs in enumerate(epochs):
        items = [(k, p, w) for k, p, w in msgs]
        for k, p in (extra or {}).get(e, []):
            pos = int(rng.integers(0, len(items) + 1))
            w = items[min(pos, len(items) - 1)][2]
            items.insert(pos, (k, p, w))
        for k, p, w in items:
            core.on_sample(k, p, w)
        got += core.step((e + 1) * PERIOD_NS)
    got += core.step(10**15)
    return sorted(got, key=lambda g: (g.epoch, g.node_id))


def assert_same_estimates(a, b, *, atol=1e-9, min_epoch=None, excluded_from=0) -> None:
    if min_epoch is not None:
        a = [g for g in a if g.epoch >= min_epoch]
        b = [g for g in b if g.epoch >= min_epoch]
    assert [(g.node_id, g.epoch, g.status, g.used_anchors) for g in a] == [
        (g.node_id, g.epoch, g.status, g.used_anchors) for g in b]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_allclose(x.position_m, y.position_m, atol=atol, rtol=0)
        if x.epoch >= excluded_from:
            assert x.excluded == y.excluded


def corpus_rows() -> list[tuple[str, str, str]]:
    """(file, key, reason) rows of the fusion table of tests/data/nasty/README.md."""
    rows = []
    for line in (NASTY / "README.md").read_text().splitlines():
        m = re.match(r"\| `(fusion/[^`]+)` \| `([^`]+)` \| `([^`]+)` \|", line)
        if m:
            rows.append(m.groups())
    return rows


def solve_rows() -> list[tuple[str, str]]:
    rows = []
    for line in (NASTY / "README.md").read_text().splitlines():
        m = re.match(r"\| `(solve/[^`]+)` \| `([^`]+)` \|", line)
        if m:
            rows.append(m.groups())
    return rows


# ---------------------------------------------------------------------------- corpus
def test_corpus_index_lists_every_file():
    listed = {f for f, *_ in corpus_rows()} | {f for f, _ in solve_rows()}
    on_disk = {str(p.relative_to(NASTY)) for p in NASTY.glob("*/*") if p.is_file()}
    assert listed == on_disk
    assert len(corpus_rows()) >= 30 and len(solve_rows()) >= 15


@pytest.mark.parametrize("row", corpus_rows(), ids=lambda r: r[0])
def test_each_nasty_payload_is_rejected_with_its_reason(row, caplog):
    fname, key, reason = row
    core = FusionCore(_strict_cfg())
    epochs = good_stream(4)
    run_stream(core, epochs[:3])
    before_rej, before_rx = dict(core.rejected), dict(core.received)
    states = {a.id: (a.states, a.ranges) for a in core.anchors.values()}
    pending = {k: dict(v.ranges) for k, v in core.book.pending.items()}
    with caplog.at_level(logging.WARNING, logger="diffpos.fusion"):
        core.on_sample(key, (NASTY / fname).read_bytes(), 3 * PERIOD_NS)
    diff = {k: v - before_rej.get(k, 0) for k, v in core.rejected.items()
            if v != before_rej.get(k, 0)}
    assert diff == {reason: 1}, (fname, diff)
    assert sum(core.received.values()) == sum(before_rx.values()) + 1
    # nothing was used: counters, pending epochs and the anchor set are unchanged
    assert {a.id: (a.states, a.ranges) for a in core.anchors.values()} == states
    assert {k: dict(v.ranges) for k, v in core.book.pending.items()} == pending
    logged = [r for r in caplog.records if r.getMessage().startswith(f"rejected {reason}")]
    assert len(logged) == 1 and logged[0].fields["reason"] == reason
    d = core.diagnostics(0)
    assert d.rejected[reason] == before_rej.get(reason, 0) + 1
    M.decoder(M.FusionDiagnostics)(M.encode(d))  # diagnostics stay schema-valid


def test_no_good_message_lost_when_nasty_messages_are_interleaved():
    """The whole corpus, three times, spread inside epochs 3..8 of a 12-epoch stream, plus
    exact duplicates of good messages, replays of old ones and good messages delivered out of
    order inside their epoch: the estimates equal those of the clean stream."""
    epochs = good_stream(12)
    clean = run_stream(FusionCore(_strict_cfg()), epochs)
    assert len(clean) == 12 * 3 and all(g.status == "OK" for g in clean)
    rows = corpus_rows()
    rng = np.random.default_rng(5)
    extra: dict[int, list] = {}
    for _ in range(3):
        for fname, key, _ in rows:
            e = int(rng.integers(3, 9))
            extra.setdefault(e, []).append((key, (NASTY / fname).read_bytes()))
    for e in range(2, 12):  # exact duplicates (same seq) and replays from two epochs back
        for k, p, _ in [epochs[e][int(i)] for i in rng.integers(0, len(epochs[e]), 4)]:
            extra.setdefault(e, []).append((k, p))
        for k, p, _ in [epochs[e - 2][int(i)] for i in rng.integers(0, len(epochs[e - 2]), 4)]:
            extra.setdefault(e, []).append((k, p))
    shuffled = [list(ep) for ep in epochs]
    for e in (4, 7):  # out of order: ranges before their anchor's state, anchors reversed
        shuffled[e] = shuffled[e][::-1]
    core = FusionCore(_strict_cfg())
    dirty = run_stream(core, shuffled, extra)
    assert_same_estimates(dirty, clean)
    d = core.diagnostics(0)
    n_bad = 3 * len(rows)
    assert sum(v for k, v in d.rejected.items() if k != "duplicate_seq") == n_bad - 3
    assert d.rejected["duplicate_seq"] == 3 + 2 * 4 * 10
    # accepted = everything good exactly once
    assert sum(a.states for a in core.anchors.values()) == 12 * 5
    assert sum(a.ranges for a in core.anchors.values()) == 12 * 5 * 3


def test_rejections_are_logged_once_per_anchor_and_reason(caplog):
    core = FusionCore(_cfg())
    run_stream(core, good_stream(3))
    bad = json.loads((NASTY / "fusion/f13-absurd-range.bin").read_bytes())
    caplog.clear()  # only what the nasty samples log counts (not the good stream's INFO lines)
    with caplog.at_level(logging.INFO, logger="diffpos.fusion"):
        for i in range(2000):  # 200 keys of uav1, then the same from uav2
            aid = "uav1" if i < 1000 else "uav2"
            nid = f"x{i % 200:03d}"
            payload = json.dumps(dict(bad, anchor_id=aid, node_id=nid, seq=10**6 + i)).encode()
            core.on_sample(KEYS.anchor_range(aid, nid), payload, 3 * PERIOD_NS)
        for i in range(500):
            core.on_sample(f"diffpos/t/junk/{i}", b"{}", 0)
    lines = [r.getMessage() for r in caplog.records]
    assert len([x for x in lines if x.startswith("rejected absurd_value")]) == 2
    assert len([x for x in lines if x.startswith("rejected unexpected_key")]) == 1
    assert len(lines) == 3
    assert core.rejected["absurd_value"] == 2000 and core.rejected["unexpected_key"] == 500


def test_first_message_far_in_the_future_does_no_lasting_harm():
    """Before any time reference exists a bogus time is accepted; the node it names must not
    be marked solved up to the future (its good ranges would all be late), and its anchor
    follows the consensus again at once."""
    epochs = good_stream(8)
    bogus = json.loads((NASTY / "fusion/f21-far-future.bin").read_bytes())
    first = (KEYS.anchor_range("uav1", "n01"), json.dumps(bogus).encode(), 0)
    core = FusionCore(_cfg())
    dirty = run_stream(core, [[first, *epochs[0]], *epochs[1:]])
    stray = [g for g in dirty if g.epoch > 1000]
    assert len(stray) == 1 and stray[0].position_m is None
    assert core.book.strays == 1 and core.rejected.get("late", 0) == 0
    # the cost: uav1's messages before a consensus existed (its own first epoch) were
    # rejected against its bogus time; everything else is exactly the stream without them
    assert core.rejected["time_past"] == 4
    without = [[m for m in epochs[0] if "/uav1/" not in m[0]], *epochs[1:]]
    reference = run_stream(FusionCore(_cfg()), without)
    # (same fixes to the solver's convergence tolerance: the batch had one more column)
    assert_same_estimates([g for g in dirty if g.epoch < 1000], reference, excluded_from=1,
                          atol=1e-6)
    assert all(g.excluded == [M.Exclusion("uav1", "NOT_REPORTED")] for g in dirty if g.epoch == 0)
    assert core.anchors["uav1"].last_t_ns < 10 * PERIOD_NS


def test_clock_jump_of_all_anchors_resynchronises():
    """A new run on a running fusion (every anchor jumps one hour ahead): rejected first as
    time_future, then each anchor is re-synchronised and the stream is used again."""
    epochs = good_stream(30)
    jump = 3600 * 10**9
    core = FusionCore(_cfg())
    run_stream(core, epochs[:5])
    later = []
    for msgs in epochs[5:]:
        ep = []
        for k, p, w in msgs:
            d = json.loads(p)
            d["t_ns"] += jump
            ep.append((k, json.dumps(d).encode(), w + jump))
        later.append(ep)
    got = []
    for e, msgs in enumerate(later):
        for k, p, w in msgs:
            core.on_sample(k, p, w)
        got += core.step(jump + (e + 6) * PERIOD_NS)
    assert core.rejected["time_future"] > 0
    ok = [g for g in got if g.status == "OK"]
    assert len({g.epoch for g in ok}) >= 15  # most of the 25 epochs after the jump


def test_restarted_anchor_may_reuse_sequence_numbers():
    core = FusionCore(_cfg())
    epochs = good_stream(6)
    run_stream(core, epochs[:3])
    core.on_liveliness("uav1", False, 3 * PERIOD_NS)
    core.on_liveliness("uav1", True, 3 * PERIOD_NS)
    st = M.AnchorState(anchor_id="uav1", t_ns=3 * PERIOD_NS + 10, seq=1,
                       position_m=M.vec3(ANCHORS["uav1"]), velocity_m_s=(0.0, 0.0, 0.0),
                       position_sigma_m=(0.01,) * 3, velocity_sigma_m_s=0.0,
                       range_rate_hz=10.0, t_pub_wall_ns=1)
    n = core.anchors["uav1"].states
    core.on_sample(KEYS.anchor_state("uav1"), M.encode(st), 3 * PERIOD_NS)
    assert core.anchors["uav1"].states == n + 1 and "duplicate_seq" not in core.rejected
    core.on_sample(KEYS.anchor_state("uav1"), M.encode(st), 3 * PERIOD_NS)
    assert core.rejected["duplicate_seq"] == 1


def test_unknown_anchor_token_is_ignored_and_never_waited_for():
    core = FusionCore(_strict_cfg())
    core.on_liveliness("evil", True, 0)
    assert "evil" not in core.live_anchors and "evil" not in core.anchors
    out = run_stream(core, good_stream(2))
    assert len(out) == 6
    # released as soon as the five known anchors reported (no deadline needed): step(0)
    core2 = FusionCore(_strict_cfg())
    core2.on_liveliness("evil", True, 0)
    for k, p, w in good_stream(1)[0]:
        core2.on_sample(k, p, w)
    assert len(core2.step(0)) == 3


def test_id_caps_bound_memory():
    core = FusionCore(_cfg(max_anchors=5, max_nodes=3))
    run_stream(core, good_stream(2))
    rm = M.RangeMeasurement(anchor_id="uav6", node_id="n01", t_ns=2 * PERIOD_NS, seq=1,
                            range_m=20.0, sigma_m=0.1, snr_db=10.0, t_pub_wall_ns=1)
    core.on_sample(KEYS.anchor_range("uav6", "n01"), M.encode(rm), 2 * PERIOD_NS)
    core.on_liveliness("uav7", True, 0)
    rm2 = M.RangeMeasurement(anchor_id="uav1", node_id="n99", t_ns=2 * PERIOD_NS, seq=10**6,
                             range_m=20.0, sigma_m=0.1, snr_db=10.0, t_pub_wall_ns=1)
    core.on_sample(KEYS.anchor_range("uav1", "n99"), M.encode(rm2), 2 * PERIOD_NS)
    b = M.RangeBatch(anchor_id="uav2", t_ns=2 * PERIOD_NS + 5, seq=10**6, node_ids=["n01", "zz"],
                     range_m=[20.0, 21.0], sigma_m=[0.1, 0.1], snr_db=[1.0, 1.0], t_pub_wall_ns=1)
    core.on_sample(KEYS.anchor_range_batch("uav2"), M.encode(b), 2 * PERIOD_NS)
    assert core.rejected["too_many_anchors"] == 1
    assert core.rejected["too_many_nodes"] == 2
    assert set(core.anchors) == set(ANCHORS)
    assert core.anchors["uav2"].ranges == 2 * 3 + 1  # the batch's good entry was used


def test_batch_entries_are_checked_one_by_one():
    core = FusionCore(_strict_cfg())
    run_stream(core, good_stream(3))
    n = core.anchors["uav3"].ranges
    b = M.RangeBatch(anchor_id="uav3", t_ns=3 * PERIOD_NS + 7, seq=10**6,
                     node_ids=["n01", "n02", "ghost", "n03"], range_m=[20.0, 1e9, 20.0, None],
                     sigma_m=[0.05, 0.05, 0.05, None], snr_db=[10.0, 10.0, 10.0, None],
                     t_pub_wall_ns=1)
    core.on_sample(KEYS.anchor_range_batch("uav3"), M.encode(b), 3 * PERIOD_NS)
    assert core.rejected["absurd_value"] == 1 and core.rejected["unknown_node"] == 1
    assert core.anchors["uav3"].ranges == n + 2  # n01 and the undetected n03


@pytest.mark.parametrize("min_snr_db", [None, 15.0])
def test_batch_fast_path_equals_single_ranges(min_snr_db):
    """A batch whose entries are all valid and whose nodes are known takes a vectorised
    acceptance path; what it stores must equal the same ranges sent one message each
    (including ``min_snr_db``: an entry below it is kept as 'not detected')."""
    nodes = ["n01", "n02", "n03"]
    batched = FusionCore(_cfg(min_snr_db=min_snr_db))
    single = FusionCore(_cfg(min_snr_db=min_snr_db))
    for e in range(3):  # epoch 0 registers the nodes (checked path), then the fast path
        t = e * PERIOD_NS + 7
        r, sg, snr = [20.0 + e, 21.5, 23.25], [0.05, 0.1, 0.2], [20.0, 10.0, 16.0]
        b = M.RangeBatch(anchor_id="uav1", t_ns=t, seq=e, node_ids=nodes, range_m=r,
                         sigma_m=sg, snr_db=snr, t_pub_wall_ns=t + 1)
        batched.on_sample(KEYS.anchor_range_batch("uav1"), M.encode(b), t + 2)
        for i, n in enumerate(nodes):
            rm = M.RangeMeasurement(anchor_id="uav1", node_id=n, t_ns=t, seq=10 * e + i,
                                    range_m=r[i], sigma_m=sg[i], snr_db=snr[i],
                                    t_pub_wall_ns=t + 1)
            single.on_sample(KEYS.anchor_range("uav1", n), M.encode(rm), t + 2)
    assert not batched.rejected and not single.rejected
    got = {k: dict(pe.ranges) for k, pe in batched.book.pending.items()}
    want = {k: dict(pe.ranges) for k, pe in single.book.pending.items()}
    assert got == want and len(got) == 9
    low = [e.range_m for pe in got.values() for e in pe.values() if e.snr_db == 10.0]
    assert low == ([None] * 3 if min_snr_db is not None else [21.5] * 3)
    assert batched.anchors["uav1"].ranges == single.anchors["uav1"].ranges == 9


def test_oversized_sample_counted_without_copy():
    core = FusionCore(_cfg())
    core.on_oversized(KEYS.anchor_range_batch("uav1"), 10**9)
    core.on_oversized("junk", 10**9)
    assert core.rejected["oversized"] == 2
    assert core.received == {"range_batch": 1, "other": 1}


# ---------------------------------------------------------------------------- diffpos solve
def _solve_bytes(data: bytes, argv=(), monkeypatch=None, capsys=None):
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(data), encoding="utf-8"))
    rc = cli.main(["solve", *argv])
    out, err = capsys.readouterr()
    return rc, [json.loads(x) for x in out.splitlines()], err


GOOD_LINE = json.dumps({"anchors_m": [[-15, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]],
                        "ranges_m": [32.233, 23.711, 15.058, 30.315], "sigmas_m": 0.005,
                        "window_height_m": 1.0}).encode() + b"\n"


def test_solve_answers_every_nasty_line_and_every_good_one(monkeypatch, capsys):
    rows = solve_rows()
    data = GOOD_LINE + b"".join((NASTY / f).read_bytes() + GOOD_LINE for f, _ in rows)
    rc, recs, err = _solve_bytes(data, ["--max-line-bytes", "65536", "--batch", "3"],
                                 monkeypatch, capsys)
    assert rc == 0 and "Traceback" not in err
    assert len(recs) == 2 * len(rows) + 1
    assert [r["line"] for r in recs] == list(range(1, len(recs) + 1))
    for k, (fname, needle) in enumerate(rows):
        good, bad = recs[2 * k], recs[2 * k + 1]
        assert good["status"] in ("ok", "ok_unverified"), good
        assert bad["status"] == "invalid_input", (fname, bad)
        assert needle in bad["message"], (fname, bad["message"])
        assert bad["id"] is None or isinstance(bad["id"], str | int)
    assert recs[-1]["status"] in ("ok", "ok_unverified")
    assert f"{len(rows)} invalid line(s)" in err


def test_solve_long_line_is_skipped_in_bounded_memory(monkeypatch, capsys):
    big = b'{"id": "' + b"x" * (5 * 2**20) + b'"}\n'  # 5 MiB, default limit 1 MiB
    rc, recs, _ = _solve_bytes(GOOD_LINE + big + GOOD_LINE, [], monkeypatch, capsys)
    assert rc == 0
    assert [r["status"] for r in recs] == ["ok", "invalid_input", "ok"]
    assert "longer than --max-line-bytes=1048576" in recs[1]["message"]
    assert [r["line"] for r in recs] == [1, 2, 3]


# ---------------------------------------------------------------------------- configs
@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"deadline_s": 100}, r"<= 60.* at `\$.deadline_s`"),
        ({"epoch_period_s": 0}, r"> 0.* at `\$.epoch_period_s`"),
        ({"max_future_s": -1}, r"> 0.* at `\$.max_future_s`"),
        ({"clock_tolerance_s": 2}, r"<= 1.* at `\$.clock_tolerance_s`"),
        ({"anchors": ["uav1", "a/b"]}, r"anchors\[1\]='a/b' is not a valid identifier"),
        ({"min_sigma_m": 5, "max_sigma_m": 1}, r"min_sigma_m=5.* must be < max_sigma_m=1"),
        ({"max_nodes": 0}, r">= 1.* at `\$.max_nodes`"),
        ({"site": "a b"}, r"site='a b' is not a valid identifier"),
    ],
)
def test_fusion_config_errors_name_field_and_range(change, needle):
    with pytest.raises(ConfigError, match=needle):
        _cfg(**change)


def _scenario(mutate):
    d = copy.deepcopy(PAPER_DICT)
    mutate(d)
    return Scenario.from_dict(d)


@pytest.mark.parametrize(
    ("mutate", "needle"),
    [
        (lambda d: d["building"].update(n_floors=0),
         "building.n_floors: expected an integer in [1, 200], got 0"),
        (lambda d: d["radio"].update(frequency_hz=1e12),
         "radio.frequency_hz: 1e+12 is out of range (allowed [1e+09, 1e+11])"),
        (lambda d: d["building"].update(window_height_m=-1),
         "building.window_height_m: -1 is out of range (allowed (0, inf])"),
        (lambda d: d["building"].update(depth_m=float("nan")),
         "building.depth_m: expected a finite number, got nan"),
        (lambda d: d["anchors"][1].update(position_m=[0.0, 15.0, 0.0]),
         "anchors[1].position_m: y=15 is inside the building (anchors must be outside, y < 0)"),
        (lambda d: d["nodes"]["grid"].update(spacing_m=0.01),
         "nodes.grid.spacing_m: 0.01 is out of range (allowed [0.05, 40])"),
        (lambda d: d["radio"].update(bandwith_hz=1e6), "radio.bandwith_hz: unknown key (allowed:"),
        (lambda d: d["anchors"][0].update(id="uav2"), "anchors[1].id: duplicate id 'uav2'"),
    ],
)
def test_scenario_errors_name_field_and_allowed_range(mutate, needle):
    with pytest.raises(ScenarioError) as info:
        _scenario(mutate)
    assert needle in str(info.value)


@pytest.mark.parametrize("bad_id", ["-uav", "u" * 65, "uäv"])
def test_scenario_ids_follow_the_wire_grammar(bad_id):
    with pytest.raises(ScenarioError, match=r"anchors\[0\]\.id"):
        _scenario(lambda d: d["anchors"][0].update(id=bad_id))


def test_service_cli_config_errors_are_one_line_naming_the_field(tmp_path, capsys):
    """Every case through the CLI's one error mapping (cli.main.main, in this process); the
    first as a real ``diffpos`` process (exit code and stderr as a user sees them) is
    tests/system/test_bad_input_process.py."""
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[building]\nn_floors = 0\n[[anchors]]\nposition_m = [0, -5, 1]\n'
                   "[nodes.grid]\n")
    cases = [
        (["fusion", "--deadline-s", "100"], "deadline_s"),
        (["fusion", "--scenario", str(bad)], "building.n_floors: expected an integer in [1, 200]"),
        (["anchor", "--id", "a/b"], "anchor_id='a/b' is not a valid identifier"),
        (["fusion", "--scenario", str(tmp_path / "missing.toml")], "missing.toml"),
    ]
    for argv, needle in cases:
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err
        assert needle in err and err.count("\n") == 1 and "Traceback" not in err, (argv, err)
