"""Where an emulator recording's wrong floors are, by each range's true first-arrival mechanism.

Usage::

    python benchmarks/diag_emulator_misses.py REC.mcap SCEN.toml [--set KEY=VALUE ...]
        [--skip-s 2] [--stretches]

The emulator's twin of ``diag_raytrace_misses.py``: REC is a lockstep recording of ``diffpos
emulate SCEN.toml`` (any ``[radio] channel_max_order``). It is replayed in this process with the
tracker bank's update wrapped (``--set`` tracker settings as ``diffpos replay --set
tracker.KEY=VALUE``), and every range the tracker got is named by the emulator's noise-free first
arrival at that epoch (the anchor where the fusion had it, the node at its recorded truth:
:func:`diffpos.channel.emulator.pair_first_arrival` without noise, its length matched to the
slot of ``mechanism_set(channel_max_order, partitions=True)``). Each range is put in one class:
``18`` (one of the tracker's 18 mechanisms), ``fam<=3`` (a family of ``mechanism_set(3)``, the
tracker's default ``max_order``), ``fam4`` (of ``mechanism_set(4)`` only), ``partition`` (a
partition reflection: no tracker order has it) or ``none``. Printed: the share of each class,
the node-epochs after ``--skip-s`` by their number of ranges outside the 18 / outside the
tracker's order 3 (wrong and confidently wrong, p >= 0.95), the labels of the out-of-model
ranges of the wrong node-epochs, and with ``--stretches`` every node's wrong stretches.
Figures: docs/channel_mix.md "Session 26".
"""

from __future__ import annotations

import argparse
import json
import tomllib
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from diag_raytrace_misses import capture, node_epochs, read_truth, stretches

from diffpos.channel.emulator import pair_first_arrival
from diffpos.metrics import truth_at
from diffpos.paths.mechanisms import mechanism_set
from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import Scenario

#: a range's noise-free length matches a slot's within this [m]
MATCH_M = 1e-6


def classify(recipe: Any, order3: tuple, order4: tuple) -> str:
    """The class of a first arrival's recipe (module docstring)."""
    if "partition" in recipe.planes:
        return "partition"
    if recipe in order3[:18]:
        return "18"
    if recipe in order3:
        return "fam<=3"
    return "fam4" if recipe in order4 else "other"


def true_mechanisms(calls: list[dict], truth: dict, radio: Any, building: Any) -> dict:
    """``(call, node, column) -> (label, class, range - true length)`` of every range."""
    mset = mechanism_set(radio.channel_max_order, partitions=True)
    o3, o4 = mechanism_set(3).recipes, mechanism_set(4).recipes
    keys, anchors, nodes, rho = [], [], [], []
    for ci, c in enumerate(calls):
        for j, nid in enumerate(c["node_ids"]):
            node_m = truth_at([int(c["t_ns"][j])], *truth[nid][:2])[0][0]
            for col in np.flatnonzero(c["mask"][j]):
                keys.append((ci, nid, int(col)))
                anchors.append(c["anchors"][j, col])
                nodes.append(node_m)
                rho.append(c["ranges"][j, col])
    a, n = np.array(anchors), np.array(nodes)
    _, _, _, true_m, det = pair_first_arrival(a, n, building=building, radio=radio)
    length = first_arrival_paths(n, a, building, mechanisms=mset).length_m
    err = np.abs(length - true_m[:, None])
    slot = np.argmin(np.where(np.isfinite(err), err, np.inf), axis=-1)
    hit = det & (np.take_along_axis(err, slot[:, None], axis=-1)[:, 0] < MATCH_M)
    out = {}
    for k, s, ok, d, r, t in zip(keys, slot, hit, det, rho, true_m, strict=True):
        if not d:
            out[k] = ("none", "none", np.nan)
        else:
            rec = mset.recipes[s]
            out[k] = (mset.labels[s] if ok else "unmatched",
                      classify(rec, o3, o4) if ok else "other", float(r - t))
    return out


def by_count(rows: list[dict], ch: dict, name: str, pick) -> None:
    """The node-epochs by their number of ranges of the classes ``pick`` accepts."""
    tab, wrong, cw = Counter(), Counter(), Counter()
    for r in rows:
        n = min(sum(pick(ch[(r["call"], r["node"], int(k))][1]) for k in r["cols"]), 4)
        tab[n] += 1
        if r["pub"] != r["tf"]:
            wrong[n] += 1
            cw[n] += r["p_pub"] >= 0.95
    print(f"-- node-epochs by ranges {name} (4 = 4 or more): " + "; ".join(
        f"{n}: {tab[n]}, wrong {wrong[n]} ({100 * wrong[n] / tab[n]:.1f} %), conf. wrong {cw[n]}"
        for n in sorted(tab)))


def report(rec: Path, rows: list[dict], ch: dict) -> None:
    res = np.array([v[2] for v in ch.values() if np.isfinite(v[2])])
    print(f"{rec.name}: {len(ch)} ranges, |range - true length| p50 {np.median(np.abs(res)):.3f}"
          f" m, p95 {np.percentile(np.abs(res), 95):.3f} m")
    cls = Counter(v[1] for v in ch.values())
    print("ranges by class:", ", ".join(f"{k} {100 * v / len(ch):.1f} %"
                                        for k, v in cls.most_common()))
    right = sum(r["pub"] == r["tf"] for r in rows)
    cw = sum(r["pub"] != r["tf"] and r["p_pub"] >= 0.95 for r in rows)
    print(f"node-epochs {len(rows)}: right floor {100 * right / max(len(rows), 1):.2f} %, "
          f"confidently wrong {100 * cw / max(len(rows), 1):.2f} %")
    by_count(rows, ch, "outside the 18", lambda c: c not in ("18", "none"))
    by_count(rows, ch, "outside the tracker's order 3", lambda c: c in ("fam4", "partition",
                                                                        "other"))
    labs: Counter = Counter()
    for r in rows:
        if r["pub"] != r["tf"]:
            labs.update(ch[(r["call"], r["node"], int(k))][0] for k in r["cols"]
                        if ch[(r["call"], r["node"], int(k))][1] not in ("18", "none"))
    print("out-of-model first arrivals of the wrong node-epochs:", labs.most_common(8))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("scenario", type=Path, help="the recording's scenario (its radio's order)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a tracker setting (JSON value), as diffpos replay --set tracker.KEY=VALUE")
    ap.add_argument("--skip-s", type=float, default=2.0)
    ap.add_argument("--stretches", action="store_true", help="every node's wrong stretches")
    a = ap.parse_args(argv)
    sets = {k: json.loads(v) for k, v in (x.split("=", 1) for x in a.set)}
    scen = Scenario.from_dict(tomllib.loads(a.scenario.read_text()))
    truth, t0 = read_truth(a.recording)
    calls = capture(a.recording, sets)
    ch = true_mechanisms(calls, truth, scen.radio, scen.building)
    rows = node_epochs(calls, truth, t0, a.skip_s)
    report(a.recording, rows, ch)
    if a.stretches:
        stretches(rows)


if __name__ == "__main__":
    main()
