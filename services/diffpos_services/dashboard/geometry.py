"""Time lookup of tracks and the geometry drawn from it: confidence ellipsoids and the
diffraction paths anchor -> window edge -> estimate."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.geometry import diffraction_point
from diffpos_services.dashboard.building import BuildingOutline, FloatArray
from diffpos_services.dashboard.common import CHI2_3DOF_95, _str_array


# ============================================================================ track lookup
class Tracks:
    """Time-sorted positions per id with vectorised lookup at arbitrary times.

    Parameters
    ----------
    t_ns : array_like of int, shape (K,) [ns]
    ids : array_like of str, shape (K,)
    position_m : array_like, shape (K, 3) [m]
    extra : array_like of int, shape (K,), optional
        An integer attribute (e.g. floor index) looked up as the latest value at or before
        the query time.
    """

    def __init__(
        self,
        t_ns: ArrayLike,
        ids: ArrayLike,
        position_m: ArrayLike,
        extra: ArrayLike | None = None,
    ) -> None:
        t = np.asarray(t_ns, np.int64).reshape(-1)
        ids_a = _str_array(ids)
        pos = np.asarray(position_m, np.float64).reshape(-1, 3)
        ex = np.full(t.shape, -1, np.int64) if extra is None else np.asarray(extra, np.int64)
        order = np.lexsort((t, ids_a)) if t.size else np.zeros(0, np.int64)
        ids_s, t_s, pos_s, ex_s = ids_a[order], t[order], pos[order], ex[order]
        self._data: dict[str, tuple[NDArray[np.int64], FloatArray, NDArray[np.int64]]] = {}
        if t.size:
            uniq, start = np.unique(ids_s, return_index=True)
            stops = [*start[1:], len(ids_s)]
            for name, a, b in zip(uniq, start, stops, strict=True):
                self._data[str(name)] = (t_s[a:b], pos_s[a:b], ex_s[a:b])

    @property
    def ids(self) -> list[str]:
        return sorted(self._data)

    def sample(
        self, ids: ArrayLike, t_ns: ArrayLike, *, coded: tuple[ArrayLike, ArrayLike] | None = None
    ) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.bool_]]:
        """Positions interpolated linearly in time (held constant beyond the ends).

        Parameters
        ----------
        ids : array_like of str, shape (L,)
        t_ns : array_like of int, shape (L,) [ns]
        coded : (names, codes), optional
            ``np.unique(ids, return_inverse=True)`` if the caller has it already (saves a
            string sort); ``ids`` is then ignored.

        Returns
        -------
        position_m : ndarray, shape (L, 3) [m]
            NaN where the id is unknown.
        extra : ndarray of int64, shape (L,)
            Latest ``extra`` value at or before each time (-1 where unknown).
        known : ndarray of bool, shape (L,)
        """
        if coded is None:
            names, codes = np.unique(_str_array(ids), return_inverse=True)
        else:
            names, codes = np.asarray(coded[0]), np.asarray(coded[1])
        t_q = np.asarray(t_ns, np.int64).reshape(-1)
        out = np.full((t_q.size, 3), np.nan)
        extra = np.full(t_q.size, -1, np.int64)
        known = np.zeros(t_q.size, bool)
        if not t_q.size:
            return out, extra, known
        order = np.argsort(codes, kind="stable")
        bounds = np.searchsorted(codes[order], np.arange(len(names) + 1))
        for i, name in enumerate(names):
            track = self._data.get(str(name))
            if track is None:
                continue
            sel = order[bounds[i] : bounds[i + 1]]
            t, pos, ex = track
            tq = t_q[sel].astype(np.float64)
            tf = t.astype(np.float64)
            for j in range(3):
                out[sel, j] = np.interp(tq, tf, pos[:, j])
            k = np.searchsorted(t, t_q[sel], side="right") - 1
            extra[sel] = ex[np.clip(k, 0, len(t) - 1)]
            known[sel] = True
        return out, extra, known


# ============================================================================ geometry helpers
def ellipsoid_axes(
    covariance_m2: ArrayLike, *, scale: float = math.sqrt(CHI2_3DOF_95)
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Half axes and orientation of confidence ellipsoids of 3x3 covariances.

    The ellipsoid ``{x : x^T C^-1 x <= scale^2}`` has half axes ``scale * sqrt(eig(C))``
    along the eigenvectors. The default scale makes it the 95 % region of a 3D Gaussian.

    Parameters
    ----------
    covariance_m2 : array_like, shape (K, 3, 3) [m^2]
    scale : float
        Mahalanobis radius.

    Returns
    -------
    half_sizes_m : ndarray, shape (K, 3) [m]
    quaternion_xyzw : ndarray, shape (K, 4)
        Rotation taking the local axes to the eigenvectors (Rerun's xyzw order).
    valid : ndarray of bool, shape (K,)
        False where the covariance is not finite (rows then hold zeros / identity).
    """
    c = np.asarray(covariance_m2, np.float64).reshape(-1, 3, 3)
    valid = np.all(np.isfinite(c), axis=(1, 2))
    half = np.zeros((c.shape[0], 3))
    quat = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (c.shape[0], 1))
    if valid.any():
        cs = 0.5 * (c[valid] + np.swapaxes(c[valid], 1, 2))
        w, v = np.linalg.eigh(cs)
        det = np.linalg.det(v)
        v[:, :, 2] *= np.sign(det)[:, None]  # proper rotation
        half[valid] = scale * np.sqrt(np.clip(w, 0.0, None))
        quat[valid] = _matrix_to_quat_xyzw(v)
    return half, quat, valid


def _matrix_to_quat_xyzw(r: FloatArray) -> FloatArray:
    """Unit quaternions (x, y, z, w) of rotation matrices ``(K, 3, 3)`` (Shepperd's method)."""
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack([tr, m00, m11, m22], axis=1).argmax(axis=1)
    q = np.empty((r.shape[0], 4))
    for case in range(4):
        k = cand == case
        if not k.any():
            continue
        rk = r[k]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[k])
            q[k] = np.stack([(rk[:, 2, 1] - rk[:, 1, 2]) / s, (rk[:, 0, 2] - rk[:, 2, 0]) / s,
                             (rk[:, 1, 0] - rk[:, 0, 1]) / s, 0.25 * s], axis=1)  # fmt: skip
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + m00[k] - m11[k] - m22[k])
            q[k] = np.stack([0.25 * s, (rk[:, 0, 1] + rk[:, 1, 0]) / s,
                             (rk[:, 0, 2] + rk[:, 2, 0]) / s, (rk[:, 2, 1] - rk[:, 1, 2]) / s], axis=1)  # fmt: skip
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + m11[k] - m00[k] - m22[k])
            q[k] = np.stack([(rk[:, 0, 1] + rk[:, 1, 0]) / s, 0.25 * s,
                             (rk[:, 1, 2] + rk[:, 2, 1]) / s, (rk[:, 0, 2] - rk[:, 2, 0]) / s], axis=1)  # fmt: skip
        else:
            s = 2.0 * np.sqrt(1.0 + m22[k] - m00[k] - m11[k])
            q[k] = np.stack([(rk[:, 0, 2] + rk[:, 2, 0]) / s, (rk[:, 1, 2] + rk[:, 2, 1]) / s,
                             0.25 * s, (rk[:, 1, 0] - rk[:, 0, 1]) / s], axis=1)  # fmt: skip
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def path_strips(
    anchor_m: FloatArray,
    node_m: FloatArray,
    floor_index: NDArray[np.int64],
    building: BuildingOutline | None,
) -> FloatArray:
    """Diffraction paths anchor -> window-edge point -> node, one per row.

    The edge point is the Fermat point (:func:`diffpos.geometry.diffraction_point`) on the
    window edge the fusion models (:meth:`BuildingOutline.edge_z_m`) of the given floor
    (of the node's height where ``floor_index < 0``), spanning the facade ``y = 0``; without
    a building it is the midpoint (a straight line).

    Parameters
    ----------
    anchor_m, node_m : ndarray, shape (L, 3) [m]
    floor_index : ndarray of int, shape (L,)
    building : BuildingOutline, optional

    Returns
    -------
    ndarray, shape (L, 3, 3) [m]
        NaN where the inputs are (or the edge point is undefined).
    """
    if building is not None:
        fl = np.where(floor_index >= 0, floor_index, building.floor_of(node_m[:, 2]))
        ze = building.edge_z_m(fl)
        n = ze.shape[0]
        start = np.stack([np.full(n, building.x_min_m), np.zeros(n), ze], axis=1)
        end = start.copy()
        end[:, 0] = building.x_max_m
        with np.errstate(invalid="ignore"):
            q = diffraction_point(anchor_m, node_m, start, end).point_m
    else:
        q = 0.5 * (anchor_m + node_m)
    return np.stack([anchor_m, q, node_m], axis=1)
