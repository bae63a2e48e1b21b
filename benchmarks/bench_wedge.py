"""Window-edge diffraction: Sionna RT's traced path gains vs the emulator's edge models.

Usage::

    python benchmarks/bench_wedge.py REC.mcap [--scenario TOML|NAME]

REC is a recording of ``diffpos emulate SCEN --channel raytrace`` (lockstep); the paths come
from the live trace's cache (as ``benchmarks/diag_raytrace_misses.py``: the cache files whose
node ids and first positions are the recording's). ``--scenario``: the scenario it was made
with (default the paper's; the recordings do not carry it). Every traced path whose chain
is one of the 18's window-edge slots (``Tx-D(lower)-Rx``, ``Tx-D(upper)-R(floor)-Rx``, ...:
:data:`diffpos.channel.edge_snr.EDGE_SLOTS`, no transmission) at every traced epoch is
compared with that slot's SNR at the traced anchor and node positions
(:func:`diffpos.channel.edge_snr.edge_slots_snr_db`), antenna elevation patterns off:

* ``halfplane``: the emulator's perfectly conducting half-plane (its channel at order 2; the
  tracker's SNR prediction),
* ``sheet``: Luebbers' dielectric sheet of the walls' material (the emulator at order >= 3),
* ``wedge``: :func:`diffpos.channel.wedge.wedge_field`, ``n = 2`` (Sionna's facade is a thin
  sheet), the walls' ITU material and thickness, Sionna RT 2.2's weighting.

Per slot and band of the half-plane's diffraction loss (free-space SNR over the path's
length minus its SNR) the median and p10 / p90 of the traced minus the predicted SNR [dB]
(the traced path's ``gain_db`` through the same link budget), then p50 / p99 / max of the
absolute difference over every path.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
from diffpos_services.scenario_io import scenario_or_default

from diffpos.channel.edge_snr import EDGE_SLOTS, edge_slots_snr_db
from diffpos.channel.linkbudget import snr_db
from diffpos.paths.mechanisms import MECHANISMS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diag_raytrace_misses import chain_label, read_truth, run_cache_files

BANDS = ((0, 10), (10, 20), (20, 30), (30, 40), (40, 50), (50, 99))
#: chain label -> column of :data:`EDGE_SLOTS`
LABELS = {MECHANISMS[k]: i for i, (k, _e, _t) in enumerate(EDGE_SLOTS)}


def traced_edge_paths(rec: Path, building) -> dict[str, np.ndarray]:
    """Column of :data:`EDGE_SLOTS`, anchor, node, traced gain [dB] and length [m] of every
    traced path whose chain is one of the window-edge slots (no transmission)."""
    truth, _ = read_truth(rec)
    rows = []
    for _anc, _names, links in run_cache_files(truth):
        e_n, n_n, _k, _d = links.bends.shape
        for e in range(e_n):
            for n in range(n_n):
                node = links.nodes_m[e, n]
                for k in np.flatnonzero(links.valid[e, n]):
                    v, bends = links.vertices_m[e, n, k], links.bends[e, n, k]
                    if np.all(np.isfinite(v), axis=1).sum() != bends.sum():
                        continue  # a transmission (a partition crossed)
                    lab = chain_label(v, bends, node[2], building)
                    if lab in LABELS:
                        rows.append((LABELS[lab], links.anchor_m[e], node,
                                     links.gain_db[e, n, k], links.length_m[e, n, k]))
    return {"col": np.array([r[0] for r in rows], dtype=int),
            "anchor": np.array([r[1] for r in rows]), "node": np.array([r[2] for r in rows]),
            "gain_db": np.array([r[3] for r in rows]), "length_m": np.array([r[4] for r in rows])}


def predictions(p: dict[str, np.ndarray], scenario) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Predicted SNR [dB] of every path by each model (module docstring), and the traced
    path's SNR with the same link budget; antenna elevation patterns off on both."""
    b = scenario.building
    r = dataclasses.replace(scenario.radio, tx_hpbw_deg=None, rx_hpbw_deg=None)
    r3 = dataclasses.replace(r, channel_max_order=3)  # the 18's edges a dielectric sheet
    anc, nodes, rows = p["anchor"][:, None, :], p["node"], np.arange(len(p["col"]))
    out = {name: edge_slots_snr_db(b, radio, anc, nodes, model)[rows, 0, p["col"]]
           for name, radio, model in (("halfplane", r, "halfplane"), ("sheet", r3, "halfplane"),
                                      ("wedge", r, "wedge"))}
    traced = snr_db(r.tx_power_dbm + r.tx_gain_dbi + r.rx_gain_dbi + p["gain_db"],
                    bandwidth_hz=r.bandwidth_hz, processing_gain_db=r.processing_gain_db,
                    temperature_k=r.noise_temperature_k, noise_figure_db=r.noise_figure_db)
    return out, traced


def report(p: dict[str, np.ndarray], pred: dict[str, np.ndarray], traced: np.ndarray,
           scenario) -> None:
    r = scenario.radio
    free = snr_db(r.tx_power_dbm + r.tx_gain_dbi + r.rx_gain_dbi
                  + 20.0 * np.log10(r.wavelength_m / (4.0 * np.pi * p["length_m"])),
                  bandwidth_hz=r.bandwidth_hz, processing_gain_db=r.processing_gain_db,
                  temperature_k=r.noise_temperature_k, noise_figure_db=r.noise_figure_db)
    loss = free - pred["halfplane"]
    print("slot                        loss [dB]     n  " + "  ".join(f"{m:>24s}" for m in pred))
    for i, (k, _e, _t) in enumerate(EDGE_SLOTS):
        for lo, hi in BANDS:
            s = (p["col"] == i) & (loss >= lo) & (loss < hi) & np.isfinite(pred["halfplane"])
            if s.sum() < 3:
                continue
            cells = []
            for v in pred.values():
                d = traced[s] - v[s]
                cells.append(f"{np.median(d):+6.2f} ({np.percentile(d, 10):+6.2f}, "
                             f"{np.percentile(d, 90):+6.2f})")
            print(f"{MECHANISMS[k]:26s}  {lo:2d}-{hi:2d}     {s.sum():5d}  " + "  ".join(
                f"{c:>24s}" for c in cells))
    for name, v in pred.items():
        d = np.abs(traced - v)[np.isfinite(v)]
        far = np.isfinite(v) & (np.abs(traced - v) > 0.1)
        slots = {MECHANISMS[EDGE_SLOTS[i][0]]: int(c) for i, c in
                 zip(*np.unique(p["col"][far], return_counts=True), strict=True)}
        print(f"|traced - {name}| [dB]: p50 {np.median(d):.3f} p99 {np.percentile(d, 99):.3f} "
              f"max {d.max():.3f}; > 0.1 dB: {far.sum()} {slots} "
              f"({np.sum(~np.isfinite(v))} paths without a prediction)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--scenario", default=None, help="scenario TOML or shipped name (paper)")
    a = ap.parse_args(argv)
    scenario = scenario_or_default(a.scenario)
    p = traced_edge_paths(a.recording, scenario.building)
    if not len(p["col"]):
        raise SystemExit("no traced window-edge diffraction paths of this run in the cache")
    print(f"{a.recording} ({a.scenario or 'paper'}): {len(p['col'])} traced window-edge "
          "paths; traced minus predicted SNR [dB], median (p10, p90), by the half-plane's "
          "diffraction loss")
    report(p, *predictions(p, scenario), scenario)


if __name__ == "__main__":
    main()
