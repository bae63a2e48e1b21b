"""Tables of docs/raytrace.md's section "First-arrival mechanisms vs Sionna RT".

    python scripts/raytrace_mechanisms.py out/rt-paper-2000.npz \
        --emulator-arrivals out/emu-paper-2000.npz
    python scripts/raytrace_mechanisms.py --positioning out/rep-emu-paper out/rep-rt-paper

For a dataset written by ``diffpos raytrace`` (with ``path_vertices_m``) prints, as markdown:
every traced path classified into the 18 mechanisms of diffpos.paths.model and its length vs the
model's closed form (:func:`diffpos_services.raytrace.mechanisms.mechanism_length_check`); the
first-arrival share per mechanism, emulator vs ray tracer, the per-link agreement and the
cause of every difference (:func:`diffpos_services.raytrace.mechanism_mix.compare_mechanisms`).
``--emulator-arrivals FILE`` also writes the emulator's first arrivals for the dataset's
receivers, with the range noise ``diffpos reproduce --seed S`` draws for ``--channel
raytrace:FILE`` (the same standard normals), for ``diffpos reproduce --channel arrivals:FILE``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from diffpos_services.raytrace import mechanism_mix as mx
from diffpos_services.raytrace import mechanisms as mm
from diffpos_services.raytrace.dataset import RaytraceDataset, load_dataset

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.study import study_rngs


def length_table(ds: RaytraceDataset, mech: mm.Mechanisms) -> list[str]:
    res = mm.mechanism_length_check(ds, mech)
    n_valid = int(ds.path_valid.sum())
    n_other = int((mech.code == mm.OTHER).sum())
    rows = ["| mechanism | traced paths | model says it exists (strict / band +-0.1 mm) | "
            "max \\|traced - model\\| | 99th pct | within 1 mm |",
            "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for name, r in res.items():
        rows.append(f"| `{name}` | {int(r['paths'])} | {100 * r['model_exists']:.2f} / "
                    f"{100 * r['exists_on_band']:.2f} % | "
                    f"{r['max_abs_m'] * 1e6:.1f} um | {r['p99_abs_m'] * 1e6:.1f} um | "
                    f"{100 * r['within_1mm']:.2f} % |")
    rows.append(f"\n{n_valid} traced paths: {n_valid - n_other} in the 18 mechanisms, "
                f"{n_other} other ({100 * n_other / max(n_valid, 1):.1f} %). Most common other:")
    labels, counts = np.unique(mech.label[mech.code == mm.OTHER].astype(str),
                               return_counts=True)
    for i in np.argsort(-counts)[:12]:
        rows.append(f"- `{labels[i]}`: {counts[i]}")
    return rows


def mix_table(cmp: dict) -> list[str]:
    keys = sorted(set(cmp["share_emulator"]) | set(cmp["share_raytrace"]),
                  key=lambda k: -(cmp["share_emulator"].get(k, 0) + cmp["share_raytrace"]
                                  .get(k, 0)))
    rows = [f"{cmp['links']} links. First-arrival mechanism [% of links]:", "",
            "| mechanism | emulator | ray tracer |", "| --- | ---: | ---: |"]
    for k in keys:
        e, r = cmp["share_emulator"].get(k, 0.0), cmp["share_raytrace"].get(k, 0.0)
        if e >= 0.05 or r >= 0.05:
            rows.append(f"| `{k}` | {e:.1f} | {r:.1f} |")
    rows += ["", f"Same mechanism on {cmp['agreement']:.1f} % of links. Where they differ "
             "[% of all links]:", "", "| cause | links |", "| --- | ---: |"]
    rows += [f"| {k} | {v:.1f} |" for k, v in cmp["causes"].items()]
    return rows


def cause_details(cmp: dict) -> list[str]:
    """Lengths behind each cause: RT - emulator first-arrival length (median, p5-p95)."""
    rows = ["", "| cause | RT - emulator first-arrival length: median (p5, p95) [m] | "
            "RT has the emulator's first-arrival path |", "| --- | --- | ---: |"]
    d = cmp["rt_length_m"] - cmp["emu_length_m"]
    for c in cmp["causes"]:
        sel = cmp["cause"] == c
        x = d[sel & np.isfinite(d)]
        has = 100 * float(np.mean(cmp["rt_has_emu_path"][sel]))
        p5, p50, p95 = np.percentile(x, [5, 50, 95]) if x.size else (np.nan,) * 3
        rows.append(f"| {c} | {p50:+.2f} ({p5:+.2f}, {p95:+.2f}) | {has:.0f} % |")
    top = sorted(((v, k) for k, v in cmp["confusion"].items() if k[0] != k[1]), reverse=True)
    rows += ["", "Largest disagreements (emulator -> ray tracer: links):"]
    rows += [f"- `{e}` -> `{r}`: {v}" for v, (e, r) in top[:10]]
    return rows


def write_emulator_arrivals(ds: RaytraceDataset, path: Path, seed: int) -> None:
    sc = ds.scenario
    ch = emulate_channel(ds.anchors_m, ds.nodes_m, building=sc.building, radio=sc.radio)
    fa = first_arrival(ch, radio=sc.radio, rng=study_rngs(seed)[1])
    np.savez(path, anchors_m=ds.anchors_m, nodes_m=ds.nodes_m, range_m=fa.range_m,
             snr_db=fa.snr_db, detected=fa.detected, sigma_m=fa.sigma_m,
             mpc_class=fa.mpc_class, aoa_deg=fa.aoa_deg)


def positioning_table(dirs: list[Path]) -> list[str]:
    """3D median / p80 / p95 and right floor per method from ``diffpos reproduce`` outputs."""
    runs = [(d, json.loads((d / "summary.json").read_text())) for d in dirs]
    rows = ["| method | " + " | ".join(f"{d.name}: 3D med / p80 / p95 [m], right floor"
                                         for d, _ in runs) + " |",
            "| --- |" + " --- |" * len(runs)]
    for key in runs[0][1]["positioning_m"]:
        if key == "peb":
            continue
        cells = []
        for _, s in runs:
            p = s["positioning_m"].get(key)
            if p is None:
                cells.append("")
                continue
            q = p["3d"]
            f = [("inf" if q[k] is None else f"{q[k]:.2f}") for k in ("median", "p80", "p95")]
            cells.append(f"{f[0]} / {f[1]} / {f[2]}, "
                         f"{100 * p.get('floor_accuracy', float('nan')):.1f} %")
        rows.append(f"| {runs[0][1]['positioning_m'][key]['label']} | " + " | ".join(cells)
                    + " |")
    rows.append("receivers: " + ", ".join(f"{d.name} {s['n_receivers']}" for d, s in runs))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, nargs="?")
    ap.add_argument("--positioning", type=Path, nargs="+", metavar="DIR",
                    help="only print the position-error table of these reproduce --out dirs")
    ap.add_argument("--emulator-arrivals", type=Path, metavar="FILE")
    ap.add_argument("--seed", type=int, default=0, help="reproduce's --seed (range noise)")
    args = ap.parse_args()
    if args.positioning:
        print("\n".join(positioning_table(args.positioning)))
        return
    if args.dataset is None:
        ap.error("give a DATASET or --positioning DIR...")
    ds = load_dataset(args.dataset)
    st = ds.metadata["settings"]
    print(f"{args.dataset}: {len(ds.nodes_m)} receivers x {len(ds.anchors_m)} anchors, "
          f"scenario {ds.metadata['scenario']['name']!r}, {st['samples_per_src']:.0e} samples, "
          f"max depth {st['max_depth']}, seed {st['seed']}\n")
    mech = mm.classify_mechanisms(ds)
    print("\n".join(length_table(ds, mech)), "\n")
    cmp = mx.compare_mechanisms(ds)
    print("\n".join(mix_table(cmp) + cause_details(cmp)))
    if args.emulator_arrivals:
        write_emulator_arrivals(ds, args.emulator_arrivals, args.seed)
        print(f"\nwrote {args.emulator_arrivals}")


if __name__ == "__main__":
    main()
