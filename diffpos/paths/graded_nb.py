"""Compiled graded paths of flat rows for a caller of a mechanism set's later slots (the
tracker's higher-order families, :mod:`diffpos.tracking.families`): the numpy-side reference is
:func:`diffpos.paths.model.graded_paths` (its compiled :func:`~diffpos.paths.model_nb.paths_kernel`
and the band tests), held bit for bit by tests/core/test_paths_split.py.

Apart from :mod:`diffpos.paths.model_nb` so that adding it left the stamps of the kernels that
compile that module in (the channel's, M-NLS's, the tracker's) as they were."""

from __future__ import annotations

import math

from numba import njit

from diffpos.paths.model_nb import edge_axis, family_path_parts, row_planes

__all__ = ["graded_split_kernel"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py).
CALLEES_SHA256 = "ad3c7a5a677284a0"


@njit(**_OPTS)
def graded_split_kernel(nodes, anchors, floor, first_z, floor_h, sill, win_h, x0, x1, depth,
                        parts, table, band, relax, split, n_before, length, ok, jac):
    """``diffpos.paths.model.graded_paths``' ``loose & isfinite(length)`` of every row of the
    mechanism ``table`` for the flat rows ``p`` (``nodes``, ``anchors`` (P, 3), ``floor`` (P,)
    float64): writes the number of slots before ``split`` that exist, ``n_before`` (P,) int64,
    and the raw length, that existence and the Jacobian of the slots from ``split`` on,
    ``length`` (P, K - split), ``ok`` (P, K - split) bool, ``jac`` (P, K - split, 3).

    Each slot is :func:`~diffpos.paths.model_nb.family_path_parts` with ``raw=True`` (the call
    :func:`~diffpos.paths.model_nb.paths_kernel` makes for ``graded_paths``); the band test of
    a ``band`` (K,) slot (specular: the entry point's height) is ``graded_paths``' ``win_lo -
    relax < z < win_hi + relax`` with the planes of
    :func:`~diffpos.paths.model_nb.row_planes`: the same values bit for bit, without the
    flat-row copies, the ``strict`` / ``sure`` grades and the deviation outputs
    ``graded_paths`` makes, and without the Jacobians of the slots before ``split``."""
    edge = edge_axis(x0, x1)
    n_k = table.shape[0]
    for p in range(nodes.shape[0]):
        a0, a1, a2 = anchors[p, 0], anchors[p, 1], anchors[p, 2]
        n0, n1, n2 = nodes[p, 0], nodes[p, 1], nodes[p, 2]
        zf, zc, lo, hi = row_planes(floor[p], first_z, floor_h, sill, win_h)
        lo_r, hi_r = lo - relax, hi + relax
        cnt = 0
        for s in range(n_k):
            ln, v, j0, j1, j2, _, _, ez = family_path_parts(
                table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge, True,
                s >= split, parts)
            if band[s]:
                v = v and (ez > lo_r) and (ez < hi_r)
            v = v and math.isfinite(ln)
            if s < split:
                if v:
                    cnt += 1
                continue
            q = s - split
            length[p, q] = ln
            ok[p, q] = v
            jac[p, q, 0] = j0
            jac[p, q, 1] = j1
            jac[p, q, 2] = j2
        n_before[p] = cnt
