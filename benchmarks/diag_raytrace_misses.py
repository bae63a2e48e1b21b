"""Where a live ray-traced recording's wrong floors are, and which first arrivals they had.

Usage::

    python benchmarks/diag_raytrace_misses.py REC.mcap [--set KEY=VALUE ...] [--node ID]
        [--every K] [--skip-s 2]

REC is a recording of ``diffpos emulate SCEN --channel raytrace`` (lockstep). The recording
keeps the ranges, not Sionna's paths, so the paths come from the live trace's cache
(:func:`diffpos_services.raytrace.live.cache_dir`): the cache files whose node ids equal the
recording's and whose traced node positions at the first grid time equal the recorded truth
(1 cm) are this run's. Three steps:

1. The recording is replayed in this process (:func:`diffpos_services.replay.run.replay`,
   ``--set`` tracker settings as ``diffpos replay --set tracker.KEY=VALUE``) with the tracker
   bank's update wrapped: after every call, every node's published floor and probabilities and
   every hypothesis' log-probability and mean are kept.
2. For every range the tracker got, the first arrival Sionna's trace gives at that time (the
   anchor at the position the fusion used, the node at its recorded truth, the emulator's
   detector without noise: the earliest path within ``fap_threshold_db`` of the strongest and
   above ``detection_snr_db``) is named by its chain (:func:`chain_label`: every bend named by
   the surface or edge it lies on) and is in the path model's 18 mechanisms or not
   (*out of model*). ``|range - length|`` of that path is printed (the noise: a few cm).
3. Every node-epoch after ``--skip-s`` (published floor vs the truth at the estimate's time):
   per node the wrong stretches (times, length, true and published floors, the published
   probability), and the wrong node-epochs by their number of out-of-model first arrivals and
   the distance of the true floor's most probable hypothesis from the truth (near < 0.5 m,
   mid < 1.5 m, far); the out-of-model chains of the wrong epochs.

``--node ID --every K``: that node's epochs, every K-th, with each link's chain. Measured
figures: docs/tracking_evidence.md "Session 24: where Sionna paper's misses are".
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from diffpos_services.fusion import tracked
from diffpos_services.raytrace.live import cache_dir, load_links
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.topics import parse_topic
from diffpos_services.replay.run import replay
from diffpos_services.wire import messages as M

from diffpos.channel.traced import path_snr_db, paths_at
from diffpos.metrics import truth_at
from diffpos.paths.mechanisms import MECHANISMS

#: a bend lies on a plane or an edge within this distance [m] (Sionna's vertices are float32)
TOL_M = 2e-3
#: a bend this close to the facade plane may be on a window edge (the traced side walls run
#: 5 cm past the facade: their vertical edges are at y = -0.05) [m]
FACADE_TOL_M = 0.1


def _edge_token(v: np.ndarray, b: Any, nf: int) -> str | None:
    x0, x1 = b.edge_x_m
    x, y, z = v
    if abs(y) >= FACADE_TOL_M:
        return None
    for k in range(b.n_floors):
        lo, hi = (float(q) for q in b.window_z_m(k))
        for zc, name in ((hi, "upper"), (lo, "lower")):
            if abs(z - zc) < TOL_M and x0 + TOL_M < x < x1 - TOL_M:
                return f"D({name})" if k == nf else f"D({name} floor{k - nf:+d})"
    if abs(x - x0) < TOL_M or abs(x - x1) < TOL_M:
        return "D(vertical)"
    return "R(facade)" if abs(y) < TOL_M else None


def _surface_token(v: np.ndarray, b: Any, nf: int) -> str | None:
    x0, x1 = b.edge_x_m
    x, y, z = v
    if y < -TOL_M:
        return "R(ground)" if abs(z) < 0.05 else None
    for k in range(-1, b.n_floors + 1):
        if abs(z - float(b.floor_z_m(k))) < TOL_M:
            return "R(floor)" if k == nf else "R(ceiling)" if k == nf + 1 else f"R(slab{k - nf:+d})"
    for c, name in ((b.depth_m, "R(back)"), (x0, "R(side x1)"), (x1, "R(side x2)")):
        if abs((y if name == "R(back)" else x) - c) < TOL_M:
            return name
    for p in b.partitions:
        if abs(v[0 if p.axis == "x" else 1] - p.position_m) < TOL_M:
            return "R(partition)"
    return None


def chain_label(vertices: np.ndarray, bends: np.ndarray, node_z_m: float, building: Any) -> str:
    """The chain of one traced path, in the tokens of :data:`MECHANISMS` relative to the floor
    of a node at height ``node_z_m`` (``Tx-D(lower)-R(ceiling)-R(floor)-Rx``); transmissions
    (``bends`` False) are left out; an unnamed bend is ``?(x,y,z)``."""
    nf = int(building.floor_index(node_z_m))
    toks = []
    for v, bend in zip(vertices, bends, strict=True):
        if not bend or not np.all(np.isfinite(v)):
            continue
        tok = _edge_token(v, building, nf) or _surface_token(v, building, nf)
        toks.append(tok or f"?({v[0]:.1f},{v[1]:.1f},{v[2]:.1f})")
    return "-".join(["Tx", *toks, "Rx"])


def read_truth(path: Path) -> tuple[dict[str, tuple], int]:
    """Per node its truth samples (times, positions, floors) and the run's start time."""
    dec, dec_rc = M.decoder(M.GroundTruth), M.decoder(M.RunControl)
    by: dict[str, list] = {}
    t0 = None
    for batch in McapScanner(path).iter_batches():
        for m in batch:
            kind = parse_topic(m.topic)[0]
            if kind == "truth_node":
                g = dec(m.data)
                by.setdefault(g.id, []).append(g)
            elif kind == "run_control" and t0 is None:
                t0 = dec_rc(m.data).t0_ns
    tracks = {}
    for k, v in by.items():
        v = sorted({g.t_ns: g for g in v}.values(), key=lambda g: g.t_ns)
        tracks[k] = (np.array([g.t_ns for g in v], np.int64), np.array([g.position_m for g in v]),
                     np.array([g.floor_index for g in v]))
    if t0 is None:
        t0 = min(int(v[0][0]) for v in tracks.values())
    return tracks, int(t0)


def run_cache_files(truth: dict[str, tuple]) -> list:
    """This run's traced links (one per anchor) from the live trace's cache (module doc)."""
    out = []
    ids = sorted(truth)
    for f in sorted(cache_dir().glob("*.npz")):
        links, meta = load_links(f)
        if sorted(meta.get("nodes", [])) != ids:
            continue
        first = np.array([truth[n][1][0] for n in meta["nodes"]])
        if np.all(np.linalg.norm(links.nodes_m[0] - first, axis=1) < 0.01):
            out.append((meta["anchor"], meta["nodes"], links))
    return out


def capture(path: Path, sets: dict[str, Any]) -> list[dict]:
    """Replay ``path``; per tracker call its inputs and every node's outputs and hypotheses."""
    calls: list[dict] = []
    orig = tracked.TrackBank.update

    def wrapped(self, node_ids, anchors, ranges, sigmas, mask, t_ns, snr_db=None, radio=None):
        out = orig(self, node_ids, anchors, ranges, sigmas, mask, t_ns, snr_db, radio)
        rows = self.rows_of(node_ids)
        calls.append(dict(
            node_ids=list(node_ids), anchors=np.array(anchors), ranges=np.array(ranges),
            mask=np.array(mask), t_ns=np.broadcast_to(np.asarray(t_ns), (len(node_ids),)).copy(),
            radio=radio if radio is not None else self.radio, building=self.building,
            floor=out.floor_index.copy(), fp=out.floor_probabilities.copy(),
            lp=self.state.log_prob[rows].copy(), mean=self.state.mean[rows, :, :3].copy()))
        return out

    tracked.TrackBank.update = wrapped
    try:
        replay(path, overrides={"tracker": sets} if sets else None, keep_estimates=False)
    finally:
        tracked.TrackBank.update = orig
    return calls


def first_chain(links: Any, t_s: float, anchor_m: np.ndarray, node_m: np.ndarray, k: int,
                radio: Any, building: Any) -> tuple[str, float]:
    """Chain label and length of node ``k``'s noise-free first arrival at ``t_s`` ("none")."""
    t = float(np.clip(t_s, links.t_s[0], links.t_s[-1]))
    e = int(np.clip(np.searchsorted(links.t_s, t, side="right") - 1, 0, len(links.t_s) - 1))
    nodes = links.nodes_m[e][None].copy()
    nodes[0, k] = node_m
    p = paths_at(links, [t], anchor_m[None], nodes)
    snr = path_snr_db(p, radio)[0, k]
    ok = p.valid[0, k] & np.isfinite(snr) & (snr >= radio.detection_snr_db)
    if not ok.any():
        return "none", np.nan
    ok &= snr >= max(snr[ok].max() - radio.fap_threshold_db, radio.detection_snr_db)
    s = int(np.argmin(np.where(ok, p.length_m[0, k], np.inf)))
    kk = links.valid.shape[2]
    e1 = min(e + 1, len(links.t_s) - 1)
    ee, ss = (e, s) if s < kk else (e1, s - kk)
    return (chain_label(links.vertices_m[ee, k, ss], links.bends[ee, k, ss], node_m[2], building),
            float(p.length_m[0, k, s]))


def chains(calls: list[dict], traced: list, truth: dict[str, tuple], t0: int) -> dict:
    """``(call, node, column) -> (label, in the 18, range - length)`` of every range."""
    slots = set(MECHANISMS)
    out = {}
    for ci, c in enumerate(calls):
        for j, nid in enumerate(c["node_ids"]):
            t = int(c["t_ns"][j])
            t_s = (t - t0) / 1e9
            node_m = truth_at([t], *truth[nid][:2])[0][0]
            for col in np.flatnonzero(c["mask"][j]):
                a = c["anchors"][j, col]
                e = int(np.clip(np.searchsorted(traced[0][2].t_s, t_s) - 1, 0, None))
                _, names, links = min(traced, key=lambda x: np.linalg.norm(
                    x[2].anchor_m[min(e, len(x[2].t_s) - 1)] - a))
                lab, length = first_chain(links, t_s, a, node_m, names.index(nid), c["radio"],
                                          c["building"])
                out[(ci, nid, int(col))] = (lab, lab in slots,
                                            float(c["ranges"][j, col]) - length)
    return out


def node_epochs(calls: list[dict], truth: dict[str, tuple], t0: int, skip_s: float
                ) -> list[dict]:
    """Every node-epoch after ``skip_s``: published vs true floor (the building's floor of
    the true position at the estimate's time), the true floor's most probable hypothesis'
    distance from the truth."""
    rows = []
    for ci, c in enumerate(calls):
        nf = c["lp"].shape[1] // 2
        for j, nid in enumerate(c["node_ids"]):
            t = int(c["t_ns"][j])
            if t < t0 + skip_s * 1e9 or nid not in truth or c["floor"][j] < 0:
                continue
            p, f = truth_at([t], *truth[nid], floor_of=c["building"].floor_index)
            tf = int(f[0])
            h = tf if c["lp"][j, tf] >= c["lp"][j, tf + nf] else tf + nf
            rows.append(dict(call=ci, node=nid, t_s=(t - t0) / 1e9, tf=tf, z=float(p[0, 2]),
                             pub=int(c["floor"][j]), p_pub=float(c["fp"][j, c["floor"][j]]),
                             d_true=float(np.linalg.norm(c["mean"][j, h] - p[0])),
                             cols=np.flatnonzero(c["mask"][j])))
    return rows


def stretches(rows: list[dict]) -> None:
    """Per node its wrong stretches."""
    by: dict[str, list] = {}
    for r in rows:
        by.setdefault(r["node"], []).append(r)
    for node, rs in sorted(by.items()):
        wrong = [r["pub"] != r["tf"] for r in rs]
        print(f"{node}: {len(rs)} node-epochs, {sum(wrong)} wrong")
        i = 0
        while i < len(rs):
            j = i
            while j < len(rs) and wrong[j]:
                j += 1
            if j > i:
                seg = rs[i:j]
                print(f"   {seg[0]['t_s']:5.1f}-{seg[-1]['t_s']:5.1f} s ({j - i:3d}) true "
                      f"{sorted({r['tf'] for r in seg})} published {sorted({r['pub'] for r in seg})}"
                      f" z {min(r['z'] for r in seg):.2f}-{max(r['z'] for r in seg):.2f} m, "
                      f"p_pub median {np.median([r['p_pub'] for r in seg]):.2f}, true floor's "
                      f"track {np.median([r['d_true'] for r in seg]):.2f} m off (median)")
            i = j + 1 if j == i else j


def classes(rows: list[dict], ch: dict) -> None:
    """Wrong and right node-epochs by out-of-model first arrivals and the true track's
    distance from the truth; the out-of-model chains of the wrong ones."""
    for name, sel in (("wrong", True), ("right", False)):
        rs = [r for r in rows if (r["pub"] != r["tf"]) == sel]
        c: Counter = Counter()
        labs: Counter = Counter()
        for r in rs:
            oom = [ch[(r["call"], r["node"], int(k))][0] for k in r["cols"]
                   if not ch[(r["call"], r["node"], int(k))][1]]
            d = "near" if r["d_true"] < 0.5 else "mid" if r["d_true"] < 1.5 else "far"
            c[(min(len(oom), 3), d)] += 1
            labs.update(oom)
        print(f"-- {name}: {len(rs)} node-epochs; (out-of-model first arrivals, true floor's "
              "track near < 0.5 m / mid < 1.5 m / far):")
        for k in sorted(c):
            print(f"   {k[0]}{'+' if k[0] == 3 else ' '} {k[1]:4s} {c[k]:5d}")
        print("   out-of-model chains:", labs.most_common(8))


def show_node(rows: list[dict], ch: dict, node: str, every: int) -> None:
    for r in [r for r in rows if r["node"] == node][::max(every, 1)]:
        links = " | ".join(f"{ch[(r['call'], node, int(k))][0].removeprefix('Tx-')[:-3]}"
                           f"{'' if ch[(r['call'], node, int(k))][1] else ' (out)'}"
                           for k in r["cols"])
        print(f"{r['t_s']:5.1f} s z {r['z']:5.2f} true {r['tf']} published {r['pub']} "
              f"(p {r['p_pub']:.2f}) true track {r['d_true']:4.1f} m off | {links}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a tracker setting (JSON value), as diffpos replay --set tracker.KEY=VALUE")
    ap.add_argument("--node", help="print this node's epochs with each link's chain")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--skip-s", type=float, default=2.0)
    a = ap.parse_args(argv)
    sets = {k: json.loads(v) for k, v in (x.split("=", 1) for x in a.set)}
    truth, t0 = read_truth(a.recording)
    traced = run_cache_files(truth)
    if not traced:
        raise SystemExit(f"no traced links of this run in {cache_dir()} (re-run its emulate)")
    calls = capture(a.recording, sets)
    ch = chains(calls, traced, truth, t0)
    rows = node_epochs(calls, truth, t0, a.skip_s)
    res = np.array([v[2] for v in ch.values() if np.isfinite(v[2])])
    print(f"{a.recording}: {len(calls)} tracker calls, {len(ch)} ranges, anchors "
          f"{[x[0] for x in traced]}; |range - first-arrival length| p50 "
          f"{np.median(np.abs(res)):.3f} m, p95 {np.percentile(np.abs(res), 95):.3f} m")
    right = sum(r["pub"] == r["tf"] for r in rows)
    print(f"node-epochs after {a.skip_s:g} s with a floor: {len(rows)}, right {right} "
          f"({100 * right / max(len(rows), 1):.2f} %)")
    print("first arrivals:", Counter(v[0] for v in ch.values()).most_common(12))
    stretches(rows)
    classes(rows, ch)
    if a.node:
        show_node(rows, ch, a.node, a.every)


if __name__ == "__main__":
    main()
