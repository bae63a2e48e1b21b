"""`diffpos solve`'s batch path for plain D-NLS lines (wire/solve_line.plain_arrays,
solve._solve_plain) against the checked one-problem-at-a-time path.

Reference: :func:`diffpos_services.solve.solve_records` validates every decoded problem with
``parse_problem`` (the checked parser that names the field at fault) and never takes the plain
path, so equal records line for line (positions bit for bit: the D-NLS kernel solves each fix
on its own) show that stacking plain lines changes nothing, and that a plain-looking line
with a bad value still gets the checked path's message."""

from __future__ import annotations

import json

import numpy as np
import pytest
from diffpos_services.scenario_io import load_scenario
from diffpos_services.solve import solve_lines, solve_records
from diffpos_services.wire.solve_io import DEFAULT_LIMITS, ProblemError
from diffpos_services.wire.solve_line import (
    PLAIN_MAX_CHARS,
    decode_plain,
    parse_line,
    plain_arrays,
    plain_group_key,
)

from diffpos.geometry import window_edge_path


def _lines(seed: int, n: int) -> list[str]:
    """Plain lines of random geometries (3-9 anchors, some beyond the facade ends and above
    the windows, window heights 0.6-2.5 m, sigmas or none, ids int/null/absent/string),
    plain-looking lines with one bad value, and lines that are not plain."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        m = int(rng.integers(3, 10))
        anchors = np.column_stack([rng.uniform(-60, 60, m), rng.uniform(-45, -3, m),
                                   rng.uniform(0, 40, m)])
        node = np.array([rng.uniform(-8, 8), rng.uniform(1, 12), rng.uniform(0.5, 25)])
        wh = float(rng.uniform(0.6, 2.5))
        r = window_edge_path(anchors, node, window_height_m=wh).length_m
        r = r + 0.03 * rng.standard_normal(m)
        prob = {"anchors_m": anchors.tolist(), "ranges_m": np.abs(r).tolist(),
                "window_height_m": wh}
        kind = k % 4
        if kind != 3:
            prob["sigmas_m"] = 0.03
        if kind == 1:
            prob["delta_m"] = float(rng.uniform(-2, 2))
        prob["id"] = [k, None, -k, f"n{k}"][k % 4] if k % 5 else prob.pop("id", None)
        out.append(prob)
    bad = [("anchors_m", lambda p: p["anchors_m"][0].__setitem__(1, 0.5)),   # anchor not outside
           ("ranges_m", lambda p: p["ranges_m"].__setitem__(1, -1.0)),
           ("ranges_m", lambda p: p["ranges_m"].__setitem__(0, 2e7)),
           ("sigmas_m", lambda p: p.__setitem__("sigmas_m", 0)),
           ("window_height_m", lambda p: p.__setitem__("window_height_m", -1.0)),
           ("window_height_m", lambda p: p.pop("window_height_m")),
           ("delta_m", lambda p: p.__setitem__("delta_m", 3e7)),
           ("anchors_m", lambda p: p["anchors_m"][1].pop()),                 # ragged
           ("anchors_m", lambda p: p["anchors_m"].__setitem__(2, [1e8, -1.0, 0.0]))]
    for j, (_, spoil) in enumerate(bad):
        prob = json.loads(json.dumps(out[j]))
        spoil(prob)
        out.insert(3 * j + 1, prob)
    out.insert(5, dict(out[0], gating=False))  # not plain: other options
    out.insert(9, dict(out[1], ranges_m=[None, *out[1]["ranges_m"][1:]]))
    out.insert(11, dict(out[2], method="lls"))
    return [json.dumps(p) for p in out]


@pytest.mark.parametrize("batch", [1, 7, 256])
def test_plain_batches_give_the_checked_paths_records(batch):
    lines = _lines(3, 60)
    fast = list(solve_lines(lines, batch=batch))
    slow = solve_records([json.loads(x) for x in lines])
    assert len(fast) == len(slow) == len(lines)
    for a, b in zip(fast, slow, strict=True):
        assert list(a) == list(b)  # same keys in the same order: the same JSON text
        assert a == b
    statuses = {r["status"] for r in fast}
    assert "invalid_input" in statuses and "ok" in statuses and "ok_unverified" in statuses


def test_plain_lines_with_the_scenario_building_as_default():
    """Lines without window_height_m take the --scenario building's (and its edges)."""
    scenario = load_scenario("paper")
    lines = [json.loads(x) for x in _lines(5, 24)]
    for p in lines:
        p.pop("window_height_m", None)
    texts = [json.dumps(p) for p in lines]
    fast = list(solve_lines(texts, batch=16, scenario=scenario))
    assert fast == solve_records(lines, scenario=scenario)
    assert sum(r["status"] == "ok" for r in fast) > 5


def test_plain_arrays_equal_the_stacked_problems_and_reject_what_problem_of_rejects():
    lines = _lines(8, 40)
    plain = [decode_plain(x, default_method="dnls", limits=DEFAULT_LIMITS) for x in lines]
    groups: dict[tuple, list[int]] = {}
    for k, p in enumerate(plain):
        if p is not None:
            groups.setdefault(plain_group_key(p[1]), []).append(k)
    assert len(groups) > 4
    for rows in groups.values():
        ok, *arrays = plain_arrays([plain[k][1] for k in rows])
        for i, k in enumerate(rows):
            one = parse_line(lines[k], default_method="dnls", limits=DEFAULT_LIMITS)
            assert bool(ok[i]) == (one is not None), lines[k]
            if one is None:
                continue
            assert plain[k][0] == one[0]  # the id
            prob = one[1]
            a, r, mask, sig, wh, delta = (None if v is None else v[i] for v in arrays)
            assert np.array_equal(a, prob.anchors_m) and np.array_equal(r, prob.ranges_m)
            assert np.array_equal(mask, prob.mask)
            assert (sig is None) == (prob.sigmas_m is None)
            assert sig is None or np.array_equal(sig, prob.sigmas_m)
            assert wh == prob.window_height_m and delta == prob.delta_m


def test_lines_that_are_not_plain():
    good = json.loads(_lines(1, 1)[0])
    for prob in (dict(good, id="x"), dict(good, id=[1]), dict(good, id=1.5),
                 dict(good, loss="huber"), dict(good, edge_x_m=[-5, 5]), dict(good, x0_m=[0, 1, 2]),
                 dict(good, nlos=[True] * len(good["anchors_m"])), dict(good, nlos_bias_m=0.1),
                 dict(good, sigmas_m=[0.1] * len(good["anchors_m"])), dict(good, method="ippa"),
                 dict(good, anchors_m=good["anchors_m"][:2], ranges_m=good["ranges_m"][:2])):
        assert decode_plain(json.dumps(prob), default_method="dnls", limits=DEFAULT_LIMITS) is None
    padded = json.dumps(good) + " " * PLAIN_MAX_CHARS  # bounded: a long line is not kept
    assert decode_plain(padded, default_method="dnls", limits=DEFAULT_LIMITS) is None
    assert decode_plain(json.dumps(good), default_method="lls", limits=DEFAULT_LIMITS) is None
    ident, _ = decode_plain(json.dumps(dict(good, id=-12)), default_method="dnls",
                            limits=DEFAULT_LIMITS)
    assert ident == -12 and type(ident) is int
    # a line that cannot be read stays an invalid_input record in its place
    recs = list(solve_lines([json.dumps(good), ProblemError("line is not UTF-8 text"),
                             json.dumps(good)], batch=8))
    assert [r["status"] for r in recs] == ["ok", "invalid_input", "ok"]


def test_a_bad_first_line_of_a_group_larger_than_a_solve_chunk(monkeypatch):
    """A group of plain lines solved in several chunks whose first line fails a check: the
    line is re-read on the one-line path (it was replaced in the batch while the chunk size
    was still read from it: AttributeError) and every record equals the checked path's."""
    import diffpos_services.solve as solve_mod

    m = 4
    monkeypatch.setattr(solve_mod, "CHUNK_ELEMENTS", 2 * m * m * 13)  # 2 problems per chunk
    assert solve_mod._chunk_size_of(m) == 2
    rng = np.random.default_rng(11)
    probs = []
    for k in range(7):
        a = np.column_stack([rng.uniform(-20, 20, m), rng.uniform(-25, -5, m),
                             rng.uniform(0, 15, m)])
        r = window_edge_path(a, np.array([1.0, 4.0, 4.5]), window_height_m=1.2).length_m
        probs.append({"anchors_m": a.tolist(), "ranges_m": r.tolist(), "window_height_m": 1.2,
                      "sigmas_m": 0.05, "id": k})
    probs[0]["ranges_m"][1] = -1.0  # plain-looking, fails the range check
    probs[3]["anchors_m"][2][1] = 2.0  # a bad line in a later chunk too
    fast = list(solve_lines([json.dumps(p) for p in probs], batch=len(probs)))
    assert fast == solve_records(probs)
    assert [r["status"] == "invalid_input" for r in fast] == [k in (0, 3) for k in range(7)]
