"""The ray-trace dataset: :class:`RaytraceDataset` and its ``.npz`` file (save/load)."""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.scenario import Scenario

DATASET_FORMAT = "diffpos-raytrace/1"




@dataclass(frozen=True)
class RaytraceDataset:
    """Ray-traced paths of every receiver x anchor link (module docstring: array table).

    Attributes
    ----------
    nodes_m : ndarray, shape (N, 3) [m]
    anchors_m : ndarray, shape (M, 3) [m]
    anchor_ids : tuple of str
    path_valid : ndarray of bool, shape (N, M, K)
    path_length_m : ndarray, shape (N, M, K) [m]
    path_gain_db : ndarray, shape (N, M, K) [dB]
    path_aod_deg, path_aoa_deg : ndarray, shape (N, M, K) [deg]
    path_chain : ndarray of uint16, shape (N, M, K)
    path_class : ndarray of int8, shape (N, M, K)
    path_vertex_m : ndarray, shape (N, M, K, 3) [m]
    metadata : dict
    path_vertices_m : ndarray, shape (N, M, K, D, 3) [m], optional
        Every interaction point of every path in order (NaN past the path's last interaction);
        ``None`` for datasets traced before it was stored (the mechanism classification of
        :mod:`.mechanisms` needs it).
    """

    nodes_m: NDArray[np.float64]
    anchors_m: NDArray[np.float64]
    anchor_ids: tuple[str, ...]
    path_valid: NDArray[np.bool_]
    path_length_m: NDArray[np.float64]
    path_gain_db: NDArray[np.float32]
    path_aod_deg: NDArray[np.float32]
    path_aoa_deg: NDArray[np.float32]
    path_chain: NDArray[np.uint16]
    path_class: NDArray[np.int8]
    path_vertex_m: NDArray[np.float32]
    metadata: dict[str, Any]
    path_vertices_m: NDArray[np.float32] | None = None

    @property
    def scenario(self) -> Scenario:
        """The scenario the dataset was traced for (from the metadata)."""
        return Scenario.from_dict(self.metadata["scenario"])

    def subset(self, nodes: ArrayLike) -> RaytraceDataset:
        """The dataset restricted to receivers ``nodes`` (indices or a boolean mask)."""
        idx = np.asarray(nodes)
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for name, v in fields.items():
            if (name.startswith("path_") or name == "nodes_m") and v is not None:
                fields[name] = v[idx]
        return RaytraceDataset(**fields)


_ARRAYS = ("nodes_m", "anchors_m", "path_valid", "path_length_m", "path_gain_db", "path_aod_deg",
           "path_aoa_deg", "path_chain", "path_class", "path_vertex_m")


def save_dataset(path: str | os.PathLike[str], ds: RaytraceDataset) -> Path:
    """Write ``ds`` to ``path`` (``.npz``, compressed); returns the path written."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    arrays = {n: getattr(ds, n) for n in _ARRAYS}
    if ds.path_vertices_m is not None:
        arrays["path_vertices_m"] = ds.path_vertices_m
    with p.open("wb") as f:
        np.savez_compressed(f, anchor_ids=np.asarray(ds.anchor_ids, dtype=str),
                            metadata_json=np.asarray(json.dumps(ds.metadata)), **arrays)
    return p


def load_dataset(path: str | os.PathLike[str], *, scenario: Scenario | None = None
                 ) -> RaytraceDataset:
    """Read a dataset written by :func:`save_dataset` / ``diffpos raytrace``.

    Parameters
    ----------
    path : path-like
    scenario : Scenario, optional
        If given, its anchors must match the dataset's (the ray trace is only valid for the
        geometry it was computed for) and its building must be the traced one.

    Raises
    ------
    ValueError
        Not a dataset, wrong format version, inconsistent shapes, or a scenario mismatch; the
        message names the file and the problem.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such ray-trace dataset (create it with 'diffpos raytrace')")
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise ValueError(f"{p}: not a readable .npz ray-trace dataset ({exc})") from None
    missing = [n for n in (*_ARRAYS, "anchor_ids", "metadata_json") if n not in data]
    if missing:
        raise ValueError(f"{p}: not a diffpos ray-trace dataset (missing {', '.join(missing)})")
    meta = json.loads(str(data["metadata_json"]))
    if meta.get("format") != DATASET_FORMAT:
        raise ValueError(f"{p}: format {meta.get('format')!r}, expected {DATASET_FORMAT!r}")
    ds = RaytraceDataset(anchor_ids=tuple(str(s) for s in data["anchor_ids"]), metadata=meta,
                         path_vertices_m=data.get("path_vertices_m"),
                         **{n: data[n] for n in _ARRAYS})
    n, m = len(ds.nodes_m), len(ds.anchors_m)
    optional = ("path_vertices_m",) if ds.path_vertices_m is not None else ()
    for name in (*_ARRAYS[2:], *optional):
        if getattr(ds, name).shape[:2] != (n, m):
            raise ValueError(f"{p}: {name} has shape {getattr(ds, name).shape}, expected "
                             f"({n}, {m}, K)")
    if scenario is not None:
        a = scenario.anchor_positions_m()
        if a.shape != ds.anchors_m.shape or not np.allclose(a, ds.anchors_m, atol=1e-6):
            raise ValueError(f"{p}: traced for anchors {ds.anchors_m.tolist()}, but the scenario "
                             f"has {a.tolist()}; re-run 'diffpos raytrace' for this scenario")
        if scenario.building != ds.scenario.building:
            raise ValueError(f"{p}: traced for a different building than the scenario's; "
                             "re-run 'diffpos raytrace' for this scenario")
    return ds
