"""First-arrival path model (diffpos.paths.model) against an independent brute-force reference.

The reference does not unfold anything: for every mechanism it minimises the total length of
the polyline anchor -> P_1 -> ... -> P_k -> node over the free coordinates of the interaction
points (each on its plane, or on the edge line: a horizontal window edge, or a vertical one at
a facade end) by a damped Newton method with the analytic
gradient/Hessian of a sum of segment lengths (vectorised over thousands of geometries), and
then decides existence from the physics of the converged points: the facade crossing strictly
inside the window band, the ground point outside, every reflection point on the floor's inside
surface with both neighbours on the room side of its plane, the diffraction point strictly
inside the edge (between the edge ends, or the sill and the lintel). Lengths must agree to 1e-9 relative, existence exactly.
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from diffpos.channel.emulator import emulate_channel
from diffpos.paths.mechanisms import MECHANISMS, RECIPES, mechanism_set
from diffpos.paths.mechanisms import MECHANISMS as CHANNEL_MECHANISMS
from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import Building, Partition, Radio

# (kind, name) of the interaction points of every slot, in path order
_SEQ = {
    0: [("facade", None)],
    1: [("plane", "ground"), ("facade", None)],
    2: [("facade", None), ("plane", "floor")],
    3: [("facade", None), ("plane", "ceiling")],
    4: [("facade", None), ("plane", "back")],
    5: [("facade", None), ("plane", "side x1")],
    6: [("facade", None), ("plane", "side x2")],
    7: [("edge", "upper")],
    8: [("edge", "lower")],
    9: [("edge", "upper"), ("plane", "floor")],
    10: [("edge", "upper"), ("plane", "ceiling")],
    11: [("edge", "lower"), ("plane", "floor")],
    12: [("edge", "lower"), ("plane", "ceiling")],
    13: [("edge", "upper"), ("plane", "back")],
    14: [("plane", "ground"), ("facade", None), ("plane", "ceiling")],
    15: [("facade", None), ("plane", "ceiling"), ("plane", "floor")],
    16: [("facade", None), ("plane", "floor"), ("plane", "ceiling")],
    17: [("facade", None), ("plane", "ceiling"), ("plane", "back")],
}


def _planes(b, kf: np.ndarray) -> dict[str, tuple[int, np.ndarray, int]]:
    """name -> (axis, coordinate (N,), side of the room: +1 room at larger coordinate)."""
    zf = b.first_floor_z_m + kf * b.floor_height_m
    x0, x1 = b.edge_x_m
    n = kf.shape[0]
    out = {"ground": (2, np.zeros(n), +1), "floor": (2, zf, +1),
           "ceiling": (2, zf + b.floor_height_m, -1), "back": (1, np.full(n, b.depth_m), -1),
           "side x1": (0, np.full(n, x0), +1), "side x2": (0, np.full(n, x1), -1)}
    for j, p in enumerate(getattr(b, "partitions", ())):  # a partition reflects on either side
        out[f"partition:{j}"] = (0 if p.axis == "x" else 1, np.full(n, p.position_m), 0)
    return out


def _seq(rec) -> list[tuple[str, str | None]]:
    """The interaction points of a recipe of diffpos.paths.mechanisms, in path order."""
    pts = [("plane", "ground")] if rec.ground else []
    pts.append(("edge", rec.edge) if rec.kind == "diff" else ("facade", None))
    return pts + [("plane", p) for p in rec.planes]


def _reference(b, a: np.ndarray, n: np.ndarray, slot):
    """Brute-force length and existence of one slot (or an interaction sequence) for pairs
    a[i], n[i] (shapes (N, 3))."""
    kf = np.floor((n[:, 2] - b.first_floor_z_m) / b.floor_height_m)
    pl = _planes(b, kf)
    lo = b.first_floor_z_m + kf * b.floor_height_m + b.sill_height_m
    hi = lo + b.window_height_m
    x0, x1 = b.edge_x_m
    seq = _SEQ[slot] if isinstance(slot, int) else slot
    nb = a.shape[0]
    # each point: P = base + basis @ u
    bases, basis = [], []
    for kind, name in seq:
        base = np.zeros((nb, 3))
        if kind == "facade":
            bm = np.array([[1.0, 0], [0, 0], [0, 1.0]])
        elif kind == "edge" and name.startswith("vertical"):  # x = x0 / x1, free z
            base[:, 0] = x0 if name == "vertical x1" else x1
            bm = np.array([[0.0], [0], [1.0]])
        elif kind == "edge":
            base[:, 2] = hi if name == "upper" else lo
            bm = np.array([[1.0], [0], [0]])
        else:
            axis, coord, _ = pl[name]
            base[:, axis] = coord
            bm = np.delete(np.eye(3), axis, axis=1)
        bases.append(base)
        basis.append(bm)
    dims = [m.shape[1] for m in basis]
    dtot, k = sum(dims), len(seq)
    bfull = np.zeros((3 * k, dtot))
    off = 0
    for i, m in enumerate(basis):
        bfull[3 * i:3 * i + 3, off:off + dims[i]] = m
        off += dims[i]
    base_full = np.concatenate(bases, axis=1)  # (N, 3k)
    mid = 0.5 * (a + n)
    # start: every point in the middle of its region (away from the kinks where two points
    # meet on a plane intersection; the cost is convex, so the start only matters for speed)
    zmid = b.first_floor_z_m + (kf + 0.5) * b.floor_height_m
    starts = []
    for (kind, name), m in zip(seq, basis, strict=True):
        p = np.stack([mid[:, 0], 0.5 * n[:, 1], zmid], axis=-1)
        if kind == "facade":
            p[:, 1], p[:, 2] = 0.0, 0.5 * (lo + hi)
        elif name == "ground":
            p[:, 1], p[:, 2] = 0.5 * a[:, 1], 0.0
        starts.append(p @ m)
    u = np.concatenate(starts, axis=1)

    def evaluate(u, a, n, base_full, eps2):
        p = (base_full + u @ bfull.T).reshape(u.shape[0], k, 3)
        pts = np.concatenate([a[:, None], p, n[:, None]], axis=1)
        seg = np.diff(pts, axis=1)
        # smoothed segment length sqrt(|d|^2 + eps^2): the plain sum of norms has kinks where a
        # segment vanishes (e.g. the ground and facade points meeting at the wall's foot),
        # where Newton stalls; continuation eps^2 = 1e-2 -> 1e-6 -> 1e-12 -> 1e-20 (the last
        # changes a length by ~1e-20 m and leaves a kink's vanishing segment ~1e-8 m long)
        ln = np.sqrt(np.einsum("...i,...i->...", seg, seg) + eps2[:, None])
        return pts, seg, ln

    # continuation, per row: a row moves to the next eps^2 when its gradient is below the
    # stage's tolerance or after 20 Newton steps at that stage (200 steps in all at most). At
    # the last stage a row is done when it is stationary (gradient below 1e-12) or stalled:
    # 5 steps in a row that lower the cost by no more than rounding (1e-15 relative), as a
    # minimiser stuck on a kink does (it cycles there; more steps change nothing). Rows are
    # independent, so only the rows not yet done are iterated.
    eps2_stages = np.array([1e-2, 1e-6, 1e-12, 1e-20])
    g_tol = np.array([1e-6, 1e-9, 1e-12, 1e-12])
    stage = np.zeros(nb, dtype=int)
    steps_in_stage = np.zeros(nb, dtype=int)
    stalled = np.zeros(nb, dtype=int)
    g_max = np.full(nb, np.inf)
    active = np.arange(nb)
    for _it in range(200):
        if active.size == 0:
            break
        ua, aa, na, ba = u[active], a[active], n[active], base_full[active]
        eps2 = eps2_stages[stage[active]]
        pts, seg, ln = evaluate(ua, aa, na, ba, eps2)
        f = ln.sum(axis=1)
        e = seg / ln[..., None]
        m = active.size
        g = np.zeros((m, k, 3))
        h = np.zeros((m, 3 * k, 3 * k))
        for i in range(k + 1):  # segment i joins point i and i+1 (0: anchor, k+1: node)
            hi_ = (np.eye(3) - e[:, i, :, None] * e[:, i, None, :]) / ln[:, i, None, None]
            if i >= 1:
                g[:, i - 1] -= e[:, i]
                h[:, 3 * (i - 1):3 * i, 3 * (i - 1):3 * i] += hi_
            if i < k:
                g[:, i] += e[:, i]
                h[:, 3 * i:3 * i + 3, 3 * i:3 * i + 3] += hi_
            if 1 <= i < k:
                h[:, 3 * (i - 1):3 * i, 3 * i:3 * i + 3] -= hi_
                h[:, 3 * i:3 * i + 3, 3 * (i - 1):3 * i] -= hi_
        gu = g.reshape(m, 3 * k) @ bfull
        g_max[active] = np.abs(gu).max(axis=1)
        # regularised Newton (mu = |g| / length): a segment's Hessian has no curvature along itself,
        # so the plain Hessian can be near-singular far from the solution
        mu = (np.linalg.norm(gu, axis=1) / f)[:, None, None] + 1e-15
        hu = bfull.T @ h @ bfull + mu * np.eye(dtot)
        step = -np.linalg.solve(hu, gu[..., None])[..., 0]
        # backtracking line search on the Newton direction (the cost is convex), re-evaluating
        # only the rows whose step was rejected
        alpha = np.ones(m)
        f_ok = f + 1e-14 * f  # rounding: at the minimum a step may not decrease the cost
        f_acc = f.copy()
        bad = np.arange(m)
        for _ls in range(30):
            f_new = evaluate(ua[bad] + alpha[bad, None] * step[bad], aa[bad], na[bad], ba[bad],
                             eps2[bad])[2].sum(axis=1)
            ok = f_new <= f_ok[bad]
            f_acc[bad[ok]] = f_new[ok]
            if ok.all():
                break
            bad = bad[~ok]
            alpha[bad] *= 0.5
        else:
            alpha[bad] = 0.0
        u[active] = ua + alpha[:, None] * step
        # stage bookkeeping (the gradient is the one before this step, as a fixed point test)
        st = stage[active]
        steps_in_stage[active] += 1
        conv = g_max[active] < g_tol[st]
        last = st == len(eps2_stages) - 1
        stalled[active] = np.where(last & (f_acc >= f - 1e-15 * f), stalled[active] + 1, 0)
        finished = last & (conv | (stalled[active] >= 5))
        advance = ~finished & (st < len(eps2_stages) - 1) & (conv | (steps_in_stage[active] >= 20))
        stage[active[advance]] += 1
        steps_in_stage[active[advance]] = 0
        active = active[~finished]
    pts, seg, _ = evaluate(u, a, n, base_full, np.zeros(nb))
    seg_len = np.linalg.norm(seg, axis=-1)
    length = seg_len.sum(axis=1)
    # a minimiser where two points meet (a segment of zero length) is a kink on a plane
    # intersection, not a ray obeying the reflection law: no such mechanism
    valid = np.isfinite(length) & np.all(seg_len > 1e-6, axis=1)
    # a ray obeys the reflection/diffraction law: the polyline is stationary (a minimiser
    # stuck on a kink, where two points meet on the intersection of two planes, is not)
    valid &= g_max < 1e-7
    tol = 1e-9
    for i, (kind, name) in enumerate(seq):
        p, prev, nxt = pts[:, i + 1], pts[:, i], pts[:, i + 2]
        if kind == "facade":
            valid &= (p[:, 2] > lo) & (p[:, 2] < hi) & (p[:, 0] > x0) & (p[:, 0] < x1)
            valid &= (prev[:, 1] < 0) & (nxt[:, 1] > 0)
        elif kind == "edge" and name.startswith("vertical"):
            valid &= (p[:, 2] > lo) & (p[:, 2] < hi)
        elif kind == "edge":
            valid &= (p[:, 0] > x0) & (p[:, 0] < x1)
        else:
            axis, coord, side = pl[name]
            if side:
                valid &= ((side * (prev[:, axis] - coord) > 0)
                          & (side * (nxt[:, axis] - coord) > 0))
            else:  # both neighbours on one side, strictly inside the span
                valid &= (prev[:, axis] - coord) * (nxt[:, axis] - coord) > 0
                lo_s, hi_s = b.partitions[int(name.split(":")[1])].span_m
                valid &= (p[:, 1 - axis] > lo_s) & (p[:, 1 - axis] < hi_s)
            if name == "ground":
                valid &= p[:, 1] < 0
            else:
                zf = b.first_floor_z_m + kf * b.floor_height_m
                valid &= ((p[:, 0] >= x0 - tol) & (p[:, 0] <= x1 + tol) & (p[:, 1] >= -tol)
                          & (p[:, 1] <= b.depth_m + tol) & (p[:, 2] >= zf - tol)
                          & (p[:, 2] <= zf + b.floor_height_m + tol))
    return length, valid


def _random_case(rng: np.random.Generator, n_nodes: int, n_anchors: int):
    fh = rng.uniform(2.6, 4.5)
    w = rng.uniform(0.4, 0.7) * fh
    sill = rng.uniform(0.05, fh - w - 0.05)
    b = Building(width_m=rng.uniform(8, 60), center_x_m=rng.uniform(-5, 5),
                 depth_m=rng.uniform(6, 30), n_floors=int(rng.integers(1, 7)),
                 floor_height_m=fh, first_floor_z_m=rng.uniform(0, 8), sill_height_m=sill,
                 window_height_m=w)
    x0, x1 = b.edge_x_m
    nodes = np.stack([rng.uniform(x0 + 0.01, x1 - 0.01, n_nodes),
                      rng.uniform(0.01, b.depth_m - 0.01, n_nodes),
                      rng.uniform(b.first_floor_z_m + 0.01, b.top_z_m - 0.01, n_nodes)], -1)
    anchors = np.stack([rng.uniform(x0 - 25, x1 + 25, n_anchors),
                        rng.uniform(-45, -0.5, n_anchors),
                        rng.uniform(0.1, b.top_z_m + 10, n_anchors)], -1)
    return b, nodes, anchors


def test_mechanism_labels_are_the_emulator_slots():
    assert MECHANISMS == CHANNEL_MECHANISMS and len(MECHANISMS) == 18


def _rows(b: Building, n: int) -> SimpleNamespace:
    """The building's numbers as per-row arrays (the reference runs many buildings at once)."""
    f = lambda v: np.full(n, float(v))  # noqa: E731
    x0, x1 = b.edge_x_m
    return SimpleNamespace(first_floor_z_m=f(b.first_floor_z_m), floor_height_m=f(
        b.floor_height_m), sill_height_m=f(b.sill_height_m), window_height_m=f(
        b.window_height_m), depth_m=f(b.depth_m), edge_x_m=(f(x0), f(x1)))


@pytest.mark.parametrize("n_buildings, n_nodes, n_anchors, seed", [
    (10, 10, 6, 20261123),  # 600 geometries, a few seconds
    pytest.param(25, 16, 8, 7, marks=pytest.mark.slow),  # 3,200 geometries
])
def test_lengths_and_existence_match_brute_force_and_emulator(n_buildings, n_nodes, n_anchors,
                                                              seed):
    """Random geometries (buildings x nodes x anchors): every slot's length (where it exists)
    equals the brute-force minimum to 1e-9 relative, its existence equals the physical test on
    the brute-force points, and the emulator's channel holds the same."""
    rng = np.random.default_rng(seed)
    rows, a_all, n_all, model_len, model_ok, emu_len, emu_ok = [], [], [], [], [], [], []
    nm = n_nodes * n_anchors
    for _ in range(n_buildings):
        b, nodes, anchors = _random_case(rng, n_nodes, n_anchors)
        ps = first_arrival_paths(nodes[:, None, :], anchors[None, :, :], b)
        ch = emulate_channel(anchors, nodes, building=b, radio=Radio())
        a_all.append(np.broadcast_to(anchors[None], (n_nodes, n_anchors, 3)).reshape(-1, 3))
        n_all.append(np.broadcast_to(nodes[:, None], (n_nodes, n_anchors, 3)).reshape(-1, 3))
        rows.append(_rows(b, nm))
        model_len.append(ps.length_m.reshape(-1, 18))
        model_ok.append(ps.valid.reshape(-1, 18))
        emu_len.append(ch.length_m.reshape(-1, 18))
        emu_ok.append(ch.valid.reshape(-1, 18))
    bb = SimpleNamespace(**{k: np.concatenate([getattr(r, k) for r in rows])
                            for k in vars(rows[0]) if k != "edge_x_m"})
    bb.edge_x_m = tuple(np.concatenate([r.edge_x_m[i] for r in rows]) for i in (0, 1))
    a_f, n_f = np.concatenate(a_all), np.concatenate(n_all)
    model_len, model_ok = np.concatenate(model_len), np.concatenate(model_ok)
    emu_len, emu_ok = np.concatenate(emu_len), np.concatenate(emu_ok)
    n_valid = np.zeros(18, dtype=int)
    for s in range(18):
        ref_len, ref_ok = _reference(bb, a_f, n_f, s)
        np.testing.assert_array_equal(model_ok[:, s], ref_ok, err_msg=MECHANISMS[s])
        np.testing.assert_allclose(model_len[ref_ok, s], ref_len[ref_ok], rtol=1e-9,
                                   err_msg=MECHANISMS[s])
        n_valid[s] += int(ref_ok.sum())
        # the emulator: same lengths; same existence except the through-wall direct ray
        if s == 0:
            assert emu_ok[:, 0].all()
            np.testing.assert_allclose(emu_len[:, 0], np.linalg.norm(n_f - a_f, axis=1),
                                       rtol=1e-12)
        else:
            np.testing.assert_array_equal(emu_ok[:, s], ref_ok, err_msg=MECHANISMS[s])
            np.testing.assert_allclose(emu_len[ref_ok, s], ref_len[ref_ok], rtol=1e-9)
    # every mechanism was exercised
    assert np.all(n_valid >= 3), dict(zip(MECHANISMS, n_valid.tolist(), strict=True))


def test_recipes_name_the_interaction_sequences():
    assert [_seq(r) for r in RECIPES] == [_SEQ[s] for s in range(18)]


@pytest.mark.parametrize("n_buildings, n_nodes, n_anchors, seed", [(8, 10, 6, 4)])
def test_higher_order_families_match_brute_force(n_buildings, n_nodes, n_anchors, seed):
    """Every family of mechanism_set(4) beyond the 18 (slab image series, ground bounce then
    diffraction, wall reflections, vertical window-edge diffraction): length (where it exists) equal to the brute-force minimum
    of the polyline through its interaction points to 1e-9 relative, existence equal to the
    physical test on the brute-force points."""
    mech = mechanism_set(4)
    rng = np.random.default_rng(seed)
    rows, a_all, n_all, model_len, model_ok = [], [], [], [], []
    for _ in range(n_buildings):
        b, nodes, anchors = _random_case(rng, n_nodes, n_anchors)
        ps = first_arrival_paths(nodes[:, None, :], anchors[None, :, :], b, mechanisms=mech)
        a_all.append(np.broadcast_to(anchors[None], (n_nodes, n_anchors, 3)).reshape(-1, 3))
        n_all.append(np.broadcast_to(nodes[:, None], (n_nodes, n_anchors, 3)).reshape(-1, 3))
        rows.append(_rows(b, n_nodes * n_anchors))
        model_len.append(ps.length_m.reshape(-1, len(mech)))
        model_ok.append(ps.valid.reshape(-1, len(mech)))
    bb = SimpleNamespace(**{k: np.concatenate([getattr(r, k) for r in rows])
                            for k in vars(rows[0]) if k != "edge_x_m"})
    bb.edge_x_m = tuple(np.concatenate([r.edge_x_m[i] for r in rows]) for i in (0, 1))
    a_f, n_f = np.concatenate(a_all), np.concatenate(n_all)
    model_len, model_ok = np.concatenate(model_len), np.concatenate(model_ok)
    n_valid = {}
    for s in range(18, len(mech)):
        ref_len, ref_ok = _reference(bb, a_f, n_f, _seq(mech.recipes[s]))
        np.testing.assert_array_equal(model_ok[:, s], ref_ok, err_msg=mech.labels[s])
        np.testing.assert_allclose(model_len[ref_ok, s], ref_len[ref_ok], rtol=1e-9,
                                   err_msg=mech.labels[s])
        n_valid[mech.labels[s]] = int(ref_ok.sum())
    rare = {k: v for k, v in n_valid.items() if v < 3}
    assert len(rare) <= len(n_valid) // 10, rare


def test_explicit_floor_hypothesis():
    """With ``floor`` given, the paths are those of that floor's planes (node shifted there)."""
    rng = np.random.default_rng(3)
    b, nodes, anchors = _random_case(rng, 30, 6)
    b = dataclasses.replace(b, n_floors=4)
    nodes[:, 2] = b.first_floor_z_m + rng.uniform(0.1, b.floor_height_m - 0.1, 30)  # floor 0
    up = nodes + np.array([0.0, 0.0, 2 * b.floor_height_m])
    p_up = first_arrival_paths(up[:, None], anchors[None], b)
    p_hyp = first_arrival_paths(up[:, None], anchors[None], b, floor=2)
    np.testing.assert_array_equal(p_up.valid, p_hyp.valid)
    np.testing.assert_array_equal(p_up.length_m, p_hyp.length_m)
    p_wrong = first_arrival_paths(up[:, None], anchors[None], b, floor=0)
    assert not np.array_equal(p_wrong.valid, p_up.valid)


def test_jacobian_matches_central_differences():
    rng = np.random.default_rng(11)
    h = 1e-6
    checked = np.zeros(18, dtype=int)
    for _ in range(10):
        b, nodes, anchors = _random_case(rng, 30, 8)
        nn, aa = nodes[:, None, :], anchors[None, :, :]
        ps = first_arrival_paths(nn, aa, b)
        for ax in range(3):
            e = np.zeros(3)
            e[ax] = h
            # same floor hypothesis on both sides (the path is smooth within a floor)
            pp = first_arrival_paths(nn + e, aa, b, floor=ps.floor)
            pm = first_arrival_paths(nn - e, aa, b, floor=ps.floor)
            ok = ps.valid & pp.valid & pm.valid
            fd = (pp.length_m - pm.length_m) / (2 * h)
            np.testing.assert_allclose(ps.jacobian[..., ax][ok], fd[ok], atol=2e-6)
            checked += ok.reshape(-1, 18).sum(axis=0)
    assert np.all(checked >= 10)


def _b() -> Building:
    return Building(width_m=20.0, center_x_m=0.0, depth_m=10.0, n_floors=3, floor_height_m=3.0,
                    first_floor_z_m=4.0, sill_height_m=0.75, window_height_m=1.5)


def test_direct_existence_at_the_window_band_boundaries():
    """Floor 1 of _b(): window band z in (7.75, 9.25), x in (-10, 10); strict inequalities."""
    b = _b()
    for z, inside in [(7.75, False), (7.75 + 1e-9, True), (9.25, False), (9.25 - 1e-9, True)]:
        a = np.array([0.0, -5.0, z])
        n = np.array([0.0, 4.0, z])  # horizontal ray: crosses the facade exactly at z
        ps = first_arrival_paths(n, a, b, floor=1)
        assert bool(ps.valid[0]) is inside, z
    # an anchor beyond the facade end whose ray enters exactly at the window's end x = 10
    a = np.array([14.0, -4.0, 8.5])
    for xn, inside in [(6.0, False), (6.0 - 1e-6, True)]:
        ps = first_arrival_paths(np.array([xn, 4.0, 8.5]), a, b, floor=1)
        assert bool(ps.valid[0]) is inside


def test_diffraction_existence_at_the_edge_ends():
    """Fermat abscissa exactly at the edge end: dropped (corner diffraction), in the model and
    in the emulator; just inside: kept. Upper edge of floor 0 at z = 6.25, x from -10 to 10.
    Anchor 5 m from the edge line (3, 4), node 2.5 m (1.5, 2): t* = (s r_o + o r_s)/(r_s + r_o)
    = 0 for s = -2, o = 1 (relative to x0 = -10)."""
    b = _b()
    a = np.array([-12.0, -3.0, 6.25 + 4.0])
    for xn, on in [(-9.0, False), (-9.0 + 1e-6, True)]:
        n = np.array([xn, 1.5, 6.25 - 2.0])
        ps = first_arrival_paths(n, a, b)
        assert bool(ps.valid[7]) is on
        ch = emulate_channel(a[None], n[None], building=b, radio=Radio())
        assert bool(ch.valid[0, 0, 7]) is on
    # the anchor beyond the facade end: the diffraction point is inside the edge for a node
    # deep enough, and its length is the unfolded one
    n = np.array([-5.0, 6.0, 5.0])
    ps = first_arrival_paths(n, a, b)
    assert ps.valid[7]
    r_s, r_o = np.hypot(3.0, 4.0), np.hypot(6.0, 1.25)
    assert ps.length_m[7] == pytest.approx(np.hypot(7.0, r_s + r_o), rel=1e-12)


def test_reflection_existence_at_the_inside_surfaces():
    """A floor reflection whose point lands exactly on the back wall corner is kept (1e-9 m
    tolerance, as in the emulator); beyond the room it is dropped."""
    b = _b()
    a = np.array([0.0, -2.0, 4.0 + 1.5])
    # node at height h above the floor of floor 0; the floor reflection point is at
    # y = y_n * 1.5 / (1.5 + h) along the unfolded ray from the window
    n_in = np.array([0.0, 9.0, 4.0 + 1.5])
    ps = first_arrival_paths(n_in, a, b)
    assert ps.valid[2]
    ps_b = first_arrival_paths(np.array([0.0, 9.9, 4.0 + 0.3]), a, b)
    assert np.isfinite(ps_b.length_m[2]) == ps_b.valid[2]


@pytest.mark.parametrize("n_buildings, n_nodes, n_anchors, seed", [(5, 10, 6, 11)])
def test_partition_families_match_brute_force(n_buildings, n_nodes, n_anchors, seed):
    """Every partition family of mechanism_set(3, partitions=True) on random buildings with 1-3
    random partitions: the model's existence is that of the brute-force reference with the
    partition at ANY place among the slab reflections, on ANY partition, and its length the
    shortest existing one (1e-9 relative)."""
    mech = mechanism_set(3, partitions=True)
    fams = [s for s, r in enumerate(mech.recipes) if "partition" in r.planes]
    assert len(fams) == 23
    rng = np.random.default_rng(seed)
    n_valid = np.zeros(len(fams), dtype=int)
    for _ in range(n_buildings):
        b, nodes, anchors = _random_case(rng, n_nodes, n_anchors)
        x0, x1 = b.edge_x_m
        parts = []
        for _p in range(int(rng.integers(1, 4))):
            if rng.random() < 0.6:
                parts.append(Partition("x", float(rng.uniform(x0 + 1, x1 - 1)),
                                       tuple(sorted(rng.uniform(0, b.depth_m, 2)))))
            else:
                parts.append(Partition("y", float(rng.uniform(1, b.depth_m - 1)),
                                       tuple(sorted(rng.uniform(x0, x1, 2)))))
        b = dataclasses.replace(b, partitions=tuple(parts))
        ps = first_arrival_paths(nodes[:, None, :], anchors[None, :, :], b, mechanisms=mech)
        a_f = np.broadcast_to(anchors[None], (n_nodes, n_anchors, 3)).reshape(-1, 3)
        n_f = np.broadcast_to(nodes[:, None], (n_nodes, n_anchors, 3)).reshape(-1, 3)
        bb = _rows(b, n_f.shape[0])
        bb.edge_x_m = tuple(np.full(n_f.shape[0], v) for v in b.edge_x_m)
        bb.partitions = b.partitions
        for i, s in enumerate(fams):
            rec = mech.recipes[s]
            slabs = [p for p in rec.planes if p != "partition"]
            ref_len = np.full(n_f.shape[0], np.inf)
            for j in range(len(parts)):
                for pos in range(len(slabs) + 1):
                    planes = (*slabs[:pos], f"partition:{j}", *slabs[pos:])
                    seq = _seq(rec._replace(planes=planes))
                    ln, ok = _reference(bb, a_f, n_f, seq)
                    ref_len = np.where(ok, np.minimum(ref_len, ln), ref_len)
            ref_ok = np.isfinite(ref_len)
            got_ok = ps.valid[..., s].reshape(-1)
            np.testing.assert_array_equal(got_ok, ref_ok, err_msg=mech.labels[s])
            np.testing.assert_allclose(ps.length_m[..., s].reshape(-1)[ref_ok], ref_len[ref_ok],
                                       rtol=1e-9, err_msg=mech.labels[s])
            n_valid[i] += int(ref_ok.sum())
    # most families exercised (the slab-only entries through the window are the rare ones)
    assert np.sum(n_valid >= 3) >= 14 and n_valid.sum() >= 150, dict(
        zip([mech.labels[s] for s in fams], n_valid.tolist(), strict=True))
