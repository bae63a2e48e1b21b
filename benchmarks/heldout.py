"""Seeded random held-out geometries for ``bench_accuracy.py --random N --random-seed S``.

Plausible buildings and UAV layouts a fire brigade would meet, none of them in scenarios/ and
none tuned for the fusion. Sample ``i`` of seed ``S`` is named ``rand-S-i`` and is a pure
function of ``(S, i)`` (its own ``numpy.random.default_rng((S, i))``), so a failing geometry is
reproduced alone. Families, by ``i mod 4``:

- ``0``: ``building`` only: a random building, the paper's four static UAVs (the default);
- ``1``: ``uavs`` only: the paper's building, a random UAV layout;
- ``2``, ``3``: ``both`` random;

so half the samples vary one family at a time (a failure can be attributed) and half both.

Building (uniform unless said otherwise):

- ``n_floors`` in {2, ..., 8}; ``floor_height_m`` in [2.7, 4.2];
- ``first_floor_z_m`` in [0, 6] (0: the lowest modelled floor is the ground floor);
- ``sill_height_m`` in [0.3, 1.5]; ``window_height_m`` in [0.6, min(2.4, floor_height_m -
  sill_height_m - 0.3)] (the window fits in its floor below a 0.3 m slab);
- ``width_m`` in [15, 60], ``depth_m`` in [8, 30], centred on ``x = 0``;
- partitions: none (probability 1/3), else 1-4 plasterboard walls perpendicular to the facade
  at random ``x`` (at least 2 m from the side walls) and, with probability 1/2, a corridor wall
  parallel to it at ``y`` in [0.35, 0.65] x depth.

UAV layout:

- 3-10 UAVs hovering (``wander_m`` in [0.1, 0.5], ``period_s`` in [12, 35], random phase);
- distance from the facade ``-y`` in [5, 40] m;
- height ``z`` in [0.5, top + 3] m (``top`` the roof: ``first_floor_z_m + n_floors *
  floor_height_m``): from below the lowest window to above the top floor;
- ``x`` within the facade (probability 3/4) or beyond one of its ends by 1-15 m (1/4; at least
  one UAV of a layout of 5 or more is beyond an end);
- UAV centres at least 3 m apart (collision avoidance; a redraw, not a filter on results).

Scenario files (the ray-traced study, docs/raytrace_study.md): ``partitioned_scenarios(N, S)``
is the first ``N`` samples of seed ``S`` with a random building, a random UAV layout and at
least one partition, and

    python benchmarks/heldout.py --write-scenarios DIR --count 3 --seed 3

writes them as ``DIR/heldout-1.toml`` ... ``heldout-N.toml`` (:func:`to_toml`; it refuses to
write over an existing file). Imported as a module, nothing runs.

Nodes: the emulator's six walking responders of the building
(:func:`diffpos.emulation.responders`: walks along the facade, a stair run between floors), as
in ``bench_accuracy.variants()``. Every sample is validated by :meth:`Scenario.from_dict`
(anchors outside, y < 0) and its responders' paths are checked to stay inside the floors.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from diffpos.emulation import responders
from diffpos.scenario import Scenario, default_scenario

FAMILIES = ("building", "uavs", "both", "both")

#: Documented sampling ranges (the test checks every sample against them).
RANGES: dict[str, tuple[float, float]] = {
    "n_floors": (2, 8),
    "floor_height_m": (2.7, 4.2),
    "first_floor_z_m": (0.0, 6.0),
    "sill_height_m": (0.3, 1.5),
    "window_height_m": (0.6, 2.4),
    "width_m": (15.0, 60.0),
    "depth_m": (8.0, 30.0),
    "n_uavs": (3, 10),
    "facade_distance_m": (5.0, 40.0),
    "uav_z_m": (0.5, 3.0),  # upper end: above the roof by this much
    "beyond_end_m": (1.0, 15.0),
    "wander_m": (0.1, 0.5),
    "period_s": (12.0, 35.0),
}
#: Slab below the window's top, minimum UAV spacing [m].
LINTEL_M, MIN_UAV_SPACING_M = 0.3, 3.0


def _u(rng: np.random.Generator, key: str) -> float:
    lo, hi = RANGES[key]
    return float(rng.uniform(lo, hi))


def random_building(rng: np.random.Generator) -> dict[str, Any]:
    """A building table (scenario dict ``building``) with its partitions."""
    nf = int(rng.integers(RANGES["n_floors"][0], RANGES["n_floors"][1] + 1))
    fh, z0, sill = _u(rng, "floor_height_m"), _u(rng, "first_floor_z_m"), _u(rng, "sill_height_m")
    w_hi = min(RANGES["window_height_m"][1], fh - sill - LINTEL_M)
    w = float(rng.uniform(RANGES["window_height_m"][0], w_hi))
    width, depth = round(_u(rng, "width_m"), 1), round(_u(rng, "depth_m"), 1)
    parts: list[dict[str, Any]] = []
    if rng.random() >= 1 / 3:
        for x in np.sort(rng.uniform(-width / 2 + 2.0, width / 2 - 2.0, int(rng.integers(1, 5)))):
            parts.append({"axis": "x", "position_m": round(float(x), 2), "span_m": [0.0, depth],
                          "material": "plasterboard", "thickness_m": 0.025})
        if rng.random() < 0.5:
            parts.append({"axis": "y", "position_m": round(depth * rng.uniform(0.35, 0.65), 2),
                          "span_m": [-width / 2, width / 2], "material": "plasterboard",
                          "thickness_m": 0.025})
    return {"n_floors": nf, "floor_height_m": round(fh, 2), "first_floor_z_m": round(z0, 2),
            "sill_height_m": round(sill, 2), "window_height_m": round(w, 2),
            "width_m": width, "depth_m": depth, "partitions": parts}


def random_uavs(rng: np.random.Generator, building: dict[str, Any]) -> list[dict[str, Any]]:
    """Hovering UAV anchors (scenario dict ``anchors``) in front of ``building``."""
    n = int(rng.integers(RANGES["n_uavs"][0], RANGES["n_uavs"][1] + 1))
    half = building["width_m"] / 2
    top = building["first_floor_z_m"] + building["n_floors"] * building["floor_height_m"]
    z_lo, above = RANGES["uav_z_m"]
    must_beyond = int(rng.integers(n)) if n >= 5 else -1
    centres: list[np.ndarray] = []
    while len(centres) < n:
        if len(centres) == must_beyond or rng.random() < 0.25:
            x = (half + _u(rng, "beyond_end_m")) * (1.0 if rng.random() < 0.5 else -1.0)
        else:
            x = float(rng.uniform(-half, half))
        c = np.array([x, -_u(rng, "facade_distance_m"), float(rng.uniform(z_lo, top + above))])
        if all(np.linalg.norm(c - o) >= MIN_UAV_SPACING_M for o in centres):
            centres.append(np.round(c, 2))
    return [{"id": f"uav{i + 1}", "trajectory": {
        "kind": "hover", "center_m": [float(v) for v in c],
        "wander_m": round(_u(rng, "wander_m"), 2), "period_s": round(_u(rng, "period_s"), 1),
        "phase_deg": round(float(rng.uniform(0.0, 360.0)), 1)}} for i, c in enumerate(centres)]


def _paper_uavs() -> list[dict[str, Any]]:
    """The paper's four anchors, static (exactly the default scenario's)."""
    return [{"id": a.id, "position_m": [float(v) for v in a.position_m]}
            for a in default_scenario().anchors]


def responders_inside(scenario: Scenario, *, count: int = 6) -> bool:
    """True if the emulator's ``count`` responders stay inside the building's floors over a
    whole loop of their walk (the vertices of their paths: the building is convex)."""
    b = scenario.building
    for _, traj in responders(b, count=count, seed=0):
        pts = np.asarray(traj.points)
        if not np.all(b.inside(pts)):
            return False
    return True


def random_scenario(seed: int, i: int) -> dict[str, Any]:
    """Sample ``i`` of seed ``seed``: a validated scenario dict named ``rand-<seed>-<i>``."""
    rng = np.random.default_rng((seed, i))
    family = FAMILIES[i % len(FAMILIES)]
    d = default_scenario().to_dict()
    if family in ("building", "both"):
        d["building"].update(random_building(rng))
    d["anchors"] = random_uavs(rng, d["building"]) if family in ("uavs", "both") else _paper_uavs()
    d["name"] = f"rand-{seed}-{i}"
    b = d["building"]
    d["description"] = (f"bench_accuracy held-out sample ({family}): {b['n_floors']} floors x "
                        f"{b['floor_height_m']:g} m from {b['first_floor_z_m']:g} m, "
                        f"{len(d['anchors'])} UAVs")
    d["nodes"] = {"grid": {"y_max_m": round(min(22.0, b["depth_m"] - 1.0), 2)}}
    s = Scenario.from_dict(json.loads(json.dumps(d)))  # raises ScenarioError if invalid
    if not responders_inside(s):
        raise ValueError(f"{d['name']}: the emulator's responders leave the building")
    return d


def random_scenarios(n: int, seed: int) -> dict[str, dict[str, Any]]:
    """``n`` samples of ``seed``, by name."""
    return {f"rand-{seed}-{i}": random_scenario(seed, i) for i in range(n)}


def partitioned_scenarios(n: int, seed: int) -> dict[str, dict[str, Any]]:
    """The first ``n`` samples of ``seed`` whose building AND UAV layout are random (family
    ``both``) and whose building has at least one interior partition, by name (the ray-traced
    study's held-out buildings: partitions change which first arrivals Sionna finds)."""
    out: dict[str, dict[str, Any]] = {}
    i = 0
    while len(out) < n:
        if family(i) == "both":
            d = random_scenario(seed, i)
            if d["building"]["partitions"]:
                out[d["name"]] = d
        i += 1
    return out


def family(i: int) -> str:
    """The family (``building``, ``uavs`` or ``both``) of sample ``i``."""
    return FAMILIES[i % len(FAMILIES)]


def summary(d: dict[str, Any]) -> str:
    """One line of a sample's key parameters."""
    b = d["building"]
    c = np.array([a["position_m"] if "position_m" in a else a["trajectory"]["center_m"]
                  for a in d["anchors"]])
    half = b["width_m"] / 2
    lo_win = b["first_floor_z_m"] + b["sill_height_m"]
    return (f"{b['n_floors']}F x {b['floor_height_m']:.2f} m @ {b['first_floor_z_m']:.1f} m, "
            f"win {b['sill_height_m']:.2f}+{b['window_height_m']:.2f}, "
            f"{b['width_m']:.0f}x{b['depth_m']:.0f} m, {len(b['partitions'])} part; "
            f"{len(c)} UAV z {c[:, 2].min():.1f}-{c[:, 2].max():.1f} "
            f"({int(np.sum(c[:, 2] < lo_win))} below win), "
            f"-y {-c[:, 1].max():.0f}-{-c[:, 1].min():.0f}, "
            f"{int(np.sum(np.abs(c[:, 0]) > half))} beyond ends")


# ----------------------------------------------------------------------------- scenario files
def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()
                               if x is not None) + "}"
    raise TypeError(f"no TOML for {v!r}")


def to_toml(d: dict[str, Any], prefix: str = "") -> str:
    """A scenario dict (:meth:`Scenario.to_dict`) as TOML (tables, arrays of tables)."""
    lines, tables = [], []
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, dict) or (isinstance(v, list) and v
                                   and all(isinstance(x, dict) for x in v)):
            tables.append((k, v))
        else:
            lines.append(f"{k} = {_toml_value(v)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for k, v in tables:
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out += f"\n[{name}]\n" + to_toml(v, prefix=name + ".")
        else:
            for item in v:
                out += f"\n[[{name}]]\n" + to_toml(item, prefix=name + ".")
    return out


def write_scenarios(out_dir: Path, count: int, seed: int) -> list[Path]:
    """Write :func:`partitioned_scenarios` ``(count, seed)`` as ``out_dir/heldout-K.toml``
    (K = 1..count), each headed by the command that rewrites it; never over an existing
    file."""
    paths = [Path(out_dir) / f"heldout-{k + 1}.toml" for k in range(count)]
    exists = [str(p) for p in paths if p.exists()]
    if exists:
        raise FileExistsError(f"{', '.join(exists)} exist: remove them or choose another DIR")
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    cmd = f"python benchmarks/heldout.py --write-scenarios DIR --count {count} --seed {seed}"
    for p, (name, d) in zip(paths, partitioned_scenarios(count, seed).items(), strict=True):
        p.write_text(f"# {name}: written by `{cmd}`\n# {summary(d)}\n\n" + to_toml(d))
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Write held-out scenario TOMLs (random building, "
                                             "random UAVs, with partitions).")
    ap.add_argument("--write-scenarios", metavar="DIR", type=Path, required=True,
                    help="directory for heldout-1.toml ... heldout-N.toml")
    ap.add_argument("--count", type=int, default=3, help="number of buildings (default 3)")
    ap.add_argument("--seed", type=int, default=3, help="generator seed (default 3)")
    a = ap.parse_args(argv)
    try:
        paths = write_scenarios(a.write_scenarios, a.count, a.seed)
    except FileExistsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for p in paths:
        print(f"{p}: {p.read_text().splitlines()[0][2:].split(':')[0]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
