"""Window-edge diffraction: Sionna RT's traced path gains vs the emulator's edge models.

Usage::

    python benchmarks/bench_wedge.py REC.mcap [--scenario TOML|NAME]

REC is a recording of ``diffpos emulate SCEN --channel raytrace`` (lockstep); the paths come
from the live trace's cache (as ``benchmarks/diag_raytrace_misses.py``: the cache files whose
node ids and first positions are the recording's). ``--scenario``: the scenario it was made
with (default the paper's; the recordings do not carry it). Every traced path whose only
interaction is a diffraction on the node floor's lower or upper window edge (chain
``Tx-D(lower)-Rx`` / ``Tx-D(upper)-Rx``, no transmission) at every traced epoch is compared
with the field of the same diffraction at the traced anchor and node positions:

* ``halfplane``: the emulator's perfectly conducting half-plane (its channel at order 2,
  ``diffpos.channel.slots._diffracted``; the tracker's SNR prediction),
* ``sheet``: Luebbers' dielectric sheet of the walls' material (the emulator at order >= 3),
* ``wedge``: :func:`diffpos.channel.wedge.wedge_field`, ``n = 2`` (Sionna's facade is a thin
  sheet), the walls' ITU material and thickness, Sionna RT 2.2's weighting.

Per edge and band of the half-plane's diffraction loss (free-space gain over the path's
length minus its gain) the median and p10 / p90 of traced minus predicted gain [dB]. Gains
without antenna patterns (the traced ``gain_db``; the x-dipole's polarisation included).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
from diffpos_services.scenario_io import scenario_or_default

from diffpos.channel.gtd_halfplane import edge_frame
from diffpos.channel.slots import _Ctx, _diffracted, _edge_frame, itu_permittivity
from diffpos.channel.wedge import wedge_field
from diffpos.paths.model import FloorFrame, diffracted_path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diag_raytrace_misses import chain_label, read_truth, run_cache_files  # noqa: E402

BANDS = ((0, 10), (10, 20), (20, 30), (30, 40), (40, 50), (50, 99))


def traced_edge_paths(rec: Path, building) -> dict[str, np.ndarray]:
    """Anchor, node, traced gain [dB] and length [m] of every single window-edge diffraction."""
    truth, _ = read_truth(rec)
    rows = []
    for _anc, _names, links in run_cache_files(truth):
        e_n, n_n, k_n, _ = links.bends.shape
        for e in range(e_n):
            for n in range(n_n):
                node = links.nodes_m[e, n]
                for k in np.flatnonzero(links.valid[e, n]):
                    v = links.vertices_m[e, n, k]
                    if np.all(np.isfinite(v), axis=1).sum() != 1 or not links.bends[e, n, k, 0]:
                        continue
                    lab = chain_label(v, links.bends[e, n, k], node[2], building)
                    if lab in ("Tx-D(lower)-Rx", "Tx-D(upper)-Rx"):
                        rows.append((lab[5:10], links.anchor_m[e], node, links.gain_db[e, n, k],
                                     links.length_m[e, n, k]))
    return {"edge": np.array([r[0] for r in rows]), "anchor": np.array([r[1] for r in rows]),
            "node": np.array([r[2] for r in rows]), "gain_db": np.array([r[3] for r in rows]),
            "length_m": np.array([r[4] for r in rows])}


def _gain_db(field: np.ndarray, wavelength_m: float) -> np.ndarray:
    amp = np.sqrt(np.einsum("...i,...i->...", field, field.conj()).real)
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(amp * wavelength_m / (4.0 * np.pi))


def predictions(p: dict[str, np.ndarray], scenario) -> dict[str, np.ndarray]:
    """Predicted gain [dB] of every path by each model (module docstring)."""
    b, r = scenario.building, dataclasses.replace(scenario.radio, tx_hpbw_deg=None)
    eta = itu_permittivity(b.wall_material, r.frequency_hz)
    out = {m: np.full(len(p["edge"]), np.nan) for m in ("halfplane", "sheet", "wedge")}
    for edge in ("lower", "upper"):
        sel = np.flatnonzero(p["edge"] == edge)
        if not len(sel):
            continue
        a, n = p["anchor"][sel], p["node"][sel]
        c = _Ctx(b, r, n, a[:, None, :])
        for name, sheet in (("halfplane", None), ("sheet", c.eta_wall)):
            gain = _diffracted(c, edge, sheet=sheet)[1][:, 0]
            with np.errstate(divide="ignore"):
                out[name][sel] = 20.0 * np.log10(np.abs(gain))
        q = diffracted_path(a, n, FloorFrame.from_building(b, b.floor_index(n[:, 2])),
                            edge).points[0]
        frame = edge_frame(a, n, q, *_edge_frame(edge))
        field = wedge_field(frame, np.asarray(r.polarization, float), frequency_hz=r.frequency_hz,
                            n=2.0, permittivity=eta, thickness_m=b.wall_thickness_m)
        out["wedge"][sel] = _gain_db(field, r.wavelength_m)
    return out


def report(p: dict[str, np.ndarray], pred: dict[str, np.ndarray], wavelength_m: float) -> None:
    loss = 20.0 * np.log10(wavelength_m / (4.0 * np.pi * p["length_m"])) - pred["halfplane"]
    print("edge   loss [dB]     n  " + "  ".join(f"{m:>26s}" for m in pred))
    for edge in ("lower", "upper"):
        for lo, hi in BANDS:
            s = (p["edge"] == edge) & (loss >= lo) & (loss < hi)
            if s.sum() < 3:
                continue
            cells = []
            for v in pred.values():
                d = p["gain_db"][s] - v[s]
                cells.append(f"{np.median(d):+6.2f} ({np.percentile(d, 10):+6.2f}, "
                             f"{np.percentile(d, 90):+6.2f})")
            print(f"{edge:5s}  {lo:2d}-{hi:2d}     {s.sum():5d}  " + "  ".join(
                f"{c:>26s}" for c in cells))
    for name, v in pred.items():
        print(f"max |traced - {name}| {np.nanmax(np.abs(p['gain_db'] - v)):.4f} dB")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("--scenario", default=None, help="scenario TOML or shipped name (paper)")
    a = ap.parse_args(argv)
    scenario = scenario_or_default(a.scenario)
    p = traced_edge_paths(a.recording, scenario.building)
    if not len(p["edge"]):
        raise SystemExit("no traced window-edge diffraction paths of this run in the cache")
    print(f"{a.recording} ({a.scenario or 'paper'}): {len(p['edge'])} traced paths "
          f"(lower {np.sum(p['edge'] == 'lower')}, upper {np.sum(p['edge'] == 'upper')}); "
          "traced minus predicted gain [dB], median (p10, p90), by the half-plane's loss")
    report(p, predictions(p, scenario), scenario.radio.wavelength_m)


if __name__ == "__main__":
    main()
