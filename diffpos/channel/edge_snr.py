"""The 18's window-edge slots with the window edge as Sionna RT traces it.

The emulator's window edge is a half-plane (:mod:`diffpos.channel.gtd_halfplane`); Sionna RT
2.2 traces the facade's window edge as a thin wedge (``n = 2``) of the walls' material whose
faces weight every UTD term (:func:`diffpos.channel.wedge.wedge_field`; docs/channel_mix.md
"Session 30"). :func:`edge_slots_snr_db` gives the SNR of the window-edge slots
:data:`EDGE_SLOTS` (7-13) with either edge, the rest of each slot (geometry, inside
reflection, partitions, antenna patterns, link budget) the emulator's;
:func:`with_wedge_edges` puts the wedge's into predictions of
:func:`diffpos.channel.emulator.pair_snr_db` (the tracker's ``snr_edge_model="wedge"``).
Numpy, not compiled: about 20 times the compiled slots' cost per pair.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.channel.gtd_halfplane import edge_frame
from diffpos.channel.slots import _Ctx, _diffracted, _power_snr
from diffpos.channel.wedge import EdgeModel, wedge_field
from diffpos.scenario import Building, Radio

__all__ = ["EDGE_SLOTS", "edge_slots_snr_db", "with_wedge_edges"]

FloatArray = NDArray[np.float64]

#: The 18's slots over a horizontal window edge (7-13: ``Tx-D(upper|lower)-Rx`` and the
#: edge then one inside reflection), in slot order, with their edge and inside plane.
EDGE_SLOTS: tuple[tuple[int, str, str | None], ...] = (
    (7, "upper", None), (8, "lower", None), (9, "upper", "floor"), (10, "upper", "ceiling"),
    (11, "lower", "floor"), (12, "lower", "ceiling"), (13, "upper", "back"))


def _sionna_edge(c: _Ctx, a: FloatArray, obs: FloatArray, q: FloatArray, e_dir: FloatArray,
                 face: FloatArray) -> NDArray:
    """The window edge's field at ``obs`` as Sionna RT traces it: a thin sheet, ``n = 2``,
    of the walls' ITU material and thickness, Sionna's reflection weighting."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return wedge_field(edge_frame(a, obs, q, e_dir, face), c.e0, frequency_hz=c.f, n=2.0,
                           permittivity=c.eta_wall, thickness_m=c.b.wall_thickness_m)


def edge_slots_snr_db(building: Building, radio: Radio, anchors_m: ArrayLike,
                      nodes_m: ArrayLike, model: EdgeModel = "wedge") -> FloatArray:
    """SNR [dB] of the window-edge slots :data:`EDGE_SLOTS` with the edge ``model``
    (``"wedge"``: Sionna's window edge; ``"halfplane"``: the emulator's 18), per-node anchors
    ``(N, M, 3)``, nodes ``(N, 3)``: shape (N, M, 7), -inf where a slot is not valid."""
    c = _Ctx(building, radio, nodes_m, anchors_m)
    field = _sionna_edge if model == "wedge" else None
    out = []
    for _k, edge, then in EDGE_SLOTS:
        length, gain, _aod, aoa, valid = _diffracted(
            c, edge, then, sheet=c.edge_permittivity(edge), field=field)
        out.append(_power_snr(gain, aoa, valid & np.isfinite(length), radio)[1])
    return np.stack(out, axis=-1)


def with_wedge_edges(out: FloatArray, anchors_m: ArrayLike, nodes_m: ArrayLike, *,
                     building: Building, radio: Radio,
                     need: NDArray | None = None) -> FloatArray:
    """Predictions ``out`` (N, M, K) of :func:`diffpos.channel.emulator.pair_snr_db` with
    their window-edge slots replaced by the wedge's (in place, and returned), on the nodes
    where one of them is ``need``-ed (all with ``need`` None; NaN kept where not needed).
    Every other slot is untouched, bit for bit. Anchors ``(N, M, 3)`` or ``(M, 3)``."""
    nodes = np.asarray(nodes_m, dtype=np.float64)
    anchors = np.asarray(anchors_m, dtype=np.float64)
    if anchors.ndim == 2:
        anchors = np.broadcast_to(anchors[None], (nodes.shape[0], *anchors.shape))
    cols = np.array([k for k, _e, _t in EDGE_SLOTS])
    need = None if need is None else np.broadcast_to(np.asarray(need, dtype=np.bool_),
                                                     out.shape)
    rows = (np.arange(out.shape[0]) if need is None
            else np.flatnonzero(need[..., cols].any(axis=(1, 2))))
    if rows.size == 0:
        return out
    w = edge_slots_snr_db(building, radio, anchors[rows], nodes[rows], "wedge")
    if need is not None:
        w = np.where(need[rows][..., cols], w, np.nan)
    sub = out[rows]
    sub[..., cols] = w
    out[rows] = sub
    return out
