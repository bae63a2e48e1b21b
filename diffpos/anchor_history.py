"""Anchor state history for the fusion's time alignment (pure: numpy + stdlib).

An anchor reports its state (position, velocity) stamped with its own clock; the position
used with a range is that state interpolated at the range's own ``t_ns``
(:class:`StateHistory`: cubic Hermite between the two bracketing reports, bounded
extrapolation beyond them, :func:`hermite_interpolate`), so an anchor's clock offset cancels
between its state and its ranges. Re-exported by :mod:`diffpos.alignment` (the model and its
assumptions are described there).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["StateHistory", "hermite_interpolate"]

FloatArray = NDArray[np.float64]

#: :meth:`StateHistory.at` evaluates up to this many distinct query times one by one on
#: Python floats (each ~5 us) instead of on arrays (~30 small array operations).
_FEW_TIMES = 4


def hermite_interpolate(
    t_s: ArrayLike,
    t0_s: ArrayLike,
    t1_s: ArrayLike,
    p0_m: ArrayLike,
    p1_m: ArrayLike,
    v0_m_s: ArrayLike,
    v1_m_s: ArrayLike,
) -> FloatArray:
    """Cubic Hermite interpolation of positions between two states with velocities.

    Exact for polynomial motion up to degree 3 (constant acceleration included).

    Parameters
    ----------
    t_s, t0_s, t1_s : array_like, shape (...) [s]
        Query time and bracketing state times (``t0 < t1``).
    p0_m, p1_m : array_like, shape (..., 3) [m]
    v0_m_s, v1_m_s : array_like, shape (..., 3) [m/s]

    Returns
    -------
    ndarray, shape (..., 3) [m]
    """
    t = np.asarray(t_s, float)
    t0 = np.asarray(t0_s, float)
    h = np.asarray(t1_s, float) - t0
    s = ((t - t0) / h)[..., None]
    hh = h[..., None]
    s2, s3 = s * s, s * s * s
    h00 = 2 * s3 - 3 * s2 + 1
    h10 = s3 - 2 * s2 + s
    h01 = -2 * s3 + 3 * s2
    h11 = s3 - s2
    return (
        h00 * np.asarray(p0_m, float)
        + h10 * hh * np.asarray(v0_m_s, float)
        + h01 * np.asarray(p1_m, float)
        + h11 * hh * np.asarray(v1_m_s, float)
    )


class StateHistory:
    """Ring buffer of one anchor's reported states, interpolated at range times.

    Parameters
    ----------
    capacity : int
        States kept (older ones are dropped). 64 states at 10 Hz cover 6.4 s.
    max_extrapolation_ns : int [ns]
        See :class:`diffpos.alignment.AlignmentConfig`.
    max_age_ns : int or None [ns]
        Also drop states older than this before the newest one (``None``: only the
        capacity limits the history).
    """

    def __init__(self, capacity: int = 64, *, max_extrapolation_ns: int = 500_000_000,
                 max_age_ns: int | None = None) -> None:
        if capacity < 1:
            raise ValueError("capacity must be >= 1")
        self.capacity = int(capacity)
        self.max_extrapolation_ns = int(max_extrapolation_ns)
        self.max_age_ns = None if max_age_ns is None else int(max_age_ns)
        # rows [lo, hi) of growable arrays hold the kept states, sorted by time: an in-order
        # append writes one row, dropping old states moves ``lo`` (compacted when the
        # arrays are full), so no per-state rebuild of the arrays
        self._t = np.empty(16, dtype=np.int64)
        self._rows = np.empty((16, 10))
        self._lo = self._hi = 0

    def __len__(self) -> int:
        return self._hi - self._lo

    @property
    def latest_t_ns(self) -> int | None:
        return int(self._t[self._hi - 1]) if self._hi > self._lo else None

    @property
    def t_ns(self) -> NDArray[np.int64]:
        return self._t[self._lo:self._hi]

    def add(
        self,
        t_ns: int,
        position_m: ArrayLike,
        velocity_m_s: ArrayLike,
        sigma_m: ArrayLike,
        velocity_sigma_m_s: float = 0.0,
    ) -> None:
        """Insert a state (kept sorted by time; a duplicate time replaces the old state)."""
        t = int(t_ns)
        row = (*(float(v) for v in position_m), *(float(v) for v in velocity_m_s),
               *(float(v) for v in sigma_m), float(velocity_sigma_m_s))
        if len(row) != 10:
            raise ValueError("position_m, velocity_m_s and sigma_m must have 3 components each")
        lo, hi = self._lo, self._hi
        if hi == lo or t > self._t[hi - 1]:
            if hi == self._t.size:
                self._make_room()
                lo, hi = self._lo, self._hi
            self._t[hi] = t
            self._rows[hi] = row
            self._hi = hi = hi + 1
        else:
            i = lo + int(np.searchsorted(self._t[lo:hi], t, side="left"))
            if i < hi and self._t[i] == t:
                self._rows[i] = row
            else:  # out of order (rare): shift the newer rows by one
                if hi == self._t.size:
                    self._make_room()
                    i += self._lo - lo
                    lo, hi = self._lo, self._hi
                self._t[i + 1:hi + 1] = self._t[i:hi].copy()
                self._rows[i + 1:hi + 1] = self._rows[i:hi].copy()
                self._t[i] = t
                self._rows[i] = row
                self._hi = hi = hi + 1
        k = (hi - lo) - self.capacity
        if self.max_age_ns is not None and self._t[lo] < self._t[hi - 1] - self.max_age_ns:
            cut = int(np.searchsorted(self._t[lo:hi], self._t[hi - 1] - self.max_age_ns,
                                      side="left"))
            k = max(k, cut)
        if k > 0:
            self._lo = lo + k

    def _at_one(self, t: int) -> tuple[list[float], list[float], bool]:
        """:meth:`at` for a single time (non-empty history), on Python floats."""
        lo, hi = self._lo, self._hi
        th = self._t
        n = hi - lo
        j = int(np.searchsorted(th[lo:hi], t, side="right"))  # t[j-1] <= t < t[j]
        inside = 0 < j < n
        if inside:
            t0, t1 = int(th[lo + j - 1]), int(th[lo + j])
            r0 = self._rows[lo + j - 1].tolist()
            r1 = self._rows[lo + j].tolist()
            pos = _hermite_one((t - t0) * 1e-9, (t1 - t0) * 1e-9 - 0.0, r0[0:3], r1[0:3],
                               r0[3:6], r1[3:6])
            sig = [max(r0[6 + k], r1[6 + k]) for k in range(3)]
            gap = 0
        else:
            k = 0 if j == 0 else n - 1
            tk = int(th[lo + k])
            rk = self._rows[lo + k].tolist()
            dt_s = (t - tk) * 1e-9
            pos = [rk[c] + rk[3 + c] * dt_s for c in range(3)]
            grow = rk[9] * abs(dt_s)
            sig = [rk[6 + c] + grow for c in range(3)]
            exact = j > 0 and int(th[lo + j - 1]) == t
            gap = 0 if exact else min(abs(t - int(th[lo])), abs(t - int(th[hi - 1])))
        ok = gap <= self.max_extrapolation_ns
        if not ok:
            pos = [math.nan] * 3
        return pos, sig, ok

    def _make_room(self) -> None:
        """Move the kept rows to the front, growing the arrays if they are more than half
        full (amortised O(1) per appended state)."""
        lo, hi = self._lo, self._hi
        n = hi - lo
        size = self._t.size if 2 * n <= self._t.size else 2 * self._t.size
        t = np.empty(size, dtype=np.int64)
        rows = np.empty((size, 10))
        t[:n] = self._t[lo:hi]
        rows[:n] = self._rows[lo:hi]
        self._t, self._rows, self._lo, self._hi = t, rows, 0, n

    def at(self, t_ns: ArrayLike) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """Anchor position and its one-sigma per axis at the query times.

        Between two states: cubic Hermite (positions and velocities). Outside the history,
        up to ``max_extrapolation_ns``: linear extrapolation with the nearest state's
        velocity, the sigma growing by ``velocity_sigma * |dt|``. Further: ``ok`` False.

        Returns
        -------
        position_m : ndarray, shape (..., 3) [m]
        sigma_m : ndarray, shape (..., 3) [m]
        ok : ndarray of bool, shape (...)
        """
        tq = np.asarray(t_ns, dtype=np.int64)
        shape = tq.shape
        tq = tq.reshape(-1)
        if tq.size and self._hi > self._lo and (tq.size == 1 or (tq == tq[0]).all()):
            # one query time (an anchor's ranges of one epoch share its time): the same
            # arithmetic on Python floats, without the fixed cost of ~30 small array ops
            p1, s1, ok1 = self._at_one(int(tq[0]))
            pos = np.empty((tq.size, 3))
            sig = np.empty((tq.size, 3))
            pos[:] = p1
            sig[:] = s1
            return pos.reshape(*shape, 3), sig.reshape(*shape, 3), np.full(shape, ok1)
        if tq.size and self._hi > self._lo:
            times = np.unique(tq)
            if times.size <= _FEW_TIMES:
                # a few query times (a solve step of a few epochs): the scalar path once per
                # distinct time, scattered back (identical values, see _at_one)
                pos = np.empty((times.size, 3))
                sig = np.empty((times.size, 3))
                ok = np.empty(times.size, bool)
                for k, tk in enumerate(times.tolist()):
                    pos[k], sig[k], ok[k] = self._at_one(tk)
                idx = np.searchsorted(times, tq)
                return (pos[idx].reshape(*shape, 3), sig[idx].reshape(*shape, 3),
                        ok[idx].reshape(shape))
        return self._at_array(tq, shape)

    def _at_array(self, tq: NDArray[np.int64], shape: tuple[int, ...]
                  ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """:meth:`at` on arrays: the query times ``tq`` (flat), reshaped to ``shape``."""
        t_hist = self._t[self._lo:self._hi]
        rows = self._rows[self._lo:self._hi]
        pos_hist, vel_hist, sig_hist, vsig_hist = rows[:, 0:3], rows[:, 3:6], rows[:, 6:9], rows[:, 9]
        n = t_hist.size
        pos = np.full((tq.size, 3), np.nan)
        sig = np.full((tq.size, 3), np.nan)
        if n == 0:
            return pos.reshape(*shape, 3), sig.reshape(*shape, 3), np.zeros(shape, bool)
        j = np.searchsorted(t_hist, tq, side="right")  # t[j-1] <= tq < t[j]
        inside = (j > 0) & (j < n)
        exact = (j > 0) & (t_hist[np.clip(j - 1, 0, n - 1)] == tq)
        if np.any(inside):
            i1 = j[inside]
            i0 = i1 - 1
            ts = 1e-9
            pos[inside] = hermite_interpolate(
                (tq[inside] - t_hist[i0]) * ts,
                np.zeros(i0.size),
                (t_hist[i1] - t_hist[i0]) * ts,
                pos_hist[i0],
                pos_hist[i1],
                vel_hist[i0],
                vel_hist[i1],
            )
            sig[inside] = np.maximum(sig_hist[i0], sig_hist[i1])
        out = ~inside
        if np.any(out):
            k = np.where(j[out] == 0, 0, n - 1)
            dt_s = (tq[out] - t_hist[k]) * 1e-9
            pos[out] = pos_hist[k] + vel_hist[k] * dt_s[:, None]
            sig[out] = sig_hist[k] + (vsig_hist[k] * np.abs(dt_s))[:, None]
        gap = np.where(
            inside | exact,
            0,
            np.minimum(np.abs(tq - t_hist[0]), np.abs(tq - t_hist[-1])),
        )
        ok = gap <= self.max_extrapolation_ns
        pos[~ok] = np.nan
        return pos.reshape(*shape, 3), sig.reshape(*shape, 3), ok.reshape(shape)


def _hermite_one(t_s: float, h_s: float, p0: list[float], p1: list[float], v0: list[float],
                 v1: list[float]) -> list[float]:
    """:func:`hermite_interpolate` for one query (``t0 = 0``) on Python floats, operation for
    operation the same (identical results)."""
    s = t_s / h_s
    s2, s3 = s * s, s * s * s
    h00 = 2 * s3 - 3 * s2 + 1
    h10 = s3 - 2 * s2 + s
    h01 = -2 * s3 + 3 * s2
    h11 = s3 - s2
    a, b = h10 * h_s, h11 * h_s
    return [h00 * p0[k] + a * v0[k] + h01 * p1[k] + b * v1[k] for k in range(3)]
