"""Cost and path discovery of the Sionna RT ray tracer (optional extra) vs samples per source.

Run:  /work/venv-rt/bin/python benchmarks/bench_raytrace.py [--receivers 500]
          [--samples 1e4 1e5 3e5] [--anchors 1]

Needs ``pip install -e '.[raytrace]'`` and Debian's ``libllvm19``. For each sample count it
traces the same receivers (evenly spread over the paper scenario's grid) from the first
``--anchors`` anchors and prints:

- seconds per 1000 links (one link = one receiver x one anchor), excluding the first solver
  call, which includes Dr.Jit's kernel compilation (reported separately);
- the fraction of the emulator's window-edge diffraction paths (``Tx-D(upper)-Rx``,
  ``Tx-D(lower)-Rx``) that the ray tracer finds with the same length (to 1 mm): the
  sampling-limited part of the ray tracer;
- the largest |traced - analytic Fermat length| over all traced window-edge diffraction paths.

The machine is shared with other jobs, so times are noisy; run it once and quote the command.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from diffpos_services.raytrace.backend import check_sionna
from diffpos_services.raytrace.evaluate import edge_fermat_check
from diffpos_services.raytrace.tracing import RaytraceSettings, trace

from diffpos.channel.emulator import emulate_channel
from diffpos.scenario import Scenario, default_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--receivers", type=int, default=500)
    ap.add_argument("--samples", type=float, nargs="+", default=[1e4, 1e5, 3e5])
    ap.add_argument("--anchors", type=int, default=1)
    ap.add_argument("--batch", type=int, default=250)
    args = ap.parse_args()
    versions = check_sionna()
    sc0 = default_scenario()
    d = sc0.to_dict()
    d["anchors"] = d["anchors"][: args.anchors]
    sc = Scenario.from_dict(d)
    nodes = sc.node_positions_m()
    nodes = nodes[np.unique(np.linspace(0, len(nodes) - 1, args.receivers).round().astype(int))]
    ch = emulate_channel(sc.anchor_positions_m(), nodes, building=sc.building, radio=sc.radio)
    print(f"Sionna RT {versions['sionna-rt']} ({versions['variant']}); {len(nodes)} receivers x "
          f"{len(sc.anchors)} anchor(s); paper scenario")
    print(f"{'samples':>9} {'total s':>12} {'s/1000 links':>13} {'edge paths found':>17} "
          f"{'max Fermat err mm':>18}")
    for s in args.samples:
        t0 = time.perf_counter()
        ds = trace(sc, nodes, settings=RaytraceSettings(samples_per_src=int(s),
                                                              batch_size=args.batch))
        total = time.perf_counter() - t0
        found = []
        for slot in (7, 8):
            L = ch.length_m[..., slot]
            dmin = np.where(ds.path_valid, np.abs(ds.path_length_m - L[..., None]),
                            np.inf).min(axis=-1)
            found.append((dmin < 1e-3)[ch.valid[..., slot]])
        frac = float(np.concatenate(found).mean())
        fc = edge_fermat_check(ds)
        err = float(np.abs(fc["error_m"]).max()) * 1e3 if len(fc["error_m"]) else float("nan")
        per = ds.metadata["s_per_1000_links"]
        print(f"{s:>9.0e} {total:>12.1f} {per:>13.2f} {100 * frac:>16.1f}% {err:>18.4f}")


if __name__ == "__main__":
    main()
