"""The ray-traced channel of the live loop: first arrivals from paths traced before the run.

A ray tracer (``diffpos_services.raytrace.live``: Sionna RT) traces every path from one anchor
to every node at a few *traced epochs* ``t_0 < t_1 < ...`` of the run (:class:`TracedLinks`:
per path its length, gain, interaction points and an identity ``key``: the interaction chain
and the surfaces it meets). At any time in between, :func:`paths_at` gives the paths of each
link and :func:`traced_first_arrivals` the first arrival the anchor measures, with the
emulator's detector and noise (:func:`diffpos.channel.emulator.first_arrival`: the earliest
path with ``SNR >= max(P_max - fap_threshold_db, detection_snr_db)``, range ``c tau + n``,
``n ~ N(0, sigma^2)`` at the ranging CRLB, the same generator calls).

Between two traced epochs ``t_0 <= t <= t_1`` (weight ``w = (t - t_0) / (t_1 - t_0)``):

- a path traced at both epochs with the same ``key`` (same chain over the same surfaces) is
  one path that moved: its interaction points and its gain [dB] are interpolated linearly in
  ``w`` and its length is recomputed from the anchor's and node's *actual* positions at ``t``
  through the interpolated points. The traced length is stationary in the interaction points
  (Fermat: reflection points on their planes, diffraction points on their edges), so an error
  ``d`` in a point makes an error of order ``d^2 / L`` in the length, not ``d``;
- a path traced at one epoch only (it appears, disappears, or the other trace missed it) is
  taken from the nearer epoch (``w < 0.5``: ``t_0``'s, else ``t_1``'s), its length again
  recomputed through its traced points from the actual end points.

Transmissions (``bends == False``: a thin wall does not bend the ray) are left out of the
length: the path is straight through them. At a traced epoch (``w = 0``) the paths are the
traced ones. Pure numpy; no files, no ray tracer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.channel.emulator import _detect
from diffpos.channel.linkbudget import noise_floor_dbm
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.scenario import Radio

__all__ = ["PathsAt", "TracedArrivals", "TracedLinks", "path_snr_db", "paths_at",
           "polyline_length_m", "traced_first_arrivals"]

FloatArray = NDArray[np.float64]
_C = SPEED_OF_LIGHT_M_S


@dataclass(frozen=True)
class TracedLinks:
    """The traced paths of one anchor to N nodes at E traced epochs, K paths per link (padded).

    Attributes
    ----------
    t_s : ndarray, shape (E,) [s]
        Traced epochs (strictly increasing), seconds since the start of the run.
    anchor_m : ndarray, shape (E, 3) [m]
        The anchor's position at each traced epoch.
    nodes_m : ndarray, shape (E, N, 3) [m]
        The nodes' positions at each traced epoch.
    valid : ndarray of bool, shape (E, N, K)
        A traced path (the rest is padding).
    key : ndarray of int64, shape (E, N, K)
        Path identity: equal keys at two epochs are the same path (interaction chain and
        surfaces); 0 for padding.
    length_m : ndarray, shape (E, N, K) [m]
        Traced length ``c tau`` (NaN for padding).
    gain_db : ndarray, shape (E, N, K) [dB]
        Path gain with a 0 dBi transmitter and an isotropic receiver, antenna patterns not
        applied (:func:`path_snr_db` applies the radio's).
    vertices_m : ndarray, shape (E, N, K, D, 3) [m]
        Interaction points in order from the anchor (NaN past the path's last).
    bends : ndarray of bool, shape (E, N, K, D)
        The interaction changes the ray's direction (reflection, diffraction); False for a
        transmission and past the last interaction.
    """

    t_s: FloatArray
    anchor_m: FloatArray
    nodes_m: FloatArray
    valid: NDArray[np.bool_]
    key: NDArray[np.int64]
    length_m: FloatArray
    gain_db: FloatArray
    vertices_m: FloatArray
    bends: NDArray[np.bool_]

    def __post_init__(self) -> None:
        e = np.shape(self.t_s)[0] if np.ndim(self.t_s) == 1 else -1
        n = np.shape(self.nodes_m)[1] if np.ndim(self.nodes_m) == 3 else -1
        if e < 1 or n < 1 or np.shape(self.anchor_m) != (e, 3) \
                or np.shape(self.nodes_m) != (e, n, 3):
            raise ValueError(f"TracedLinks: t_s (E,), anchor_m (E, 3), nodes_m (E, N, 3) "
                             f"expected, got {np.shape(self.t_s)}, {np.shape(self.anchor_m)}, "
                             f"{np.shape(self.nodes_m)}")
        k = np.shape(self.valid)[-1] if np.ndim(self.valid) == 3 else -1
        for name in ("valid", "key", "length_m", "gain_db"):
            if np.shape(getattr(self, name)) != (e, n, k):
                raise ValueError(f"TracedLinks.{name}: expected shape {(e, n, k)}, got "
                                 f"{np.shape(getattr(self, name))}")
        d = np.shape(self.bends)[-1] if np.ndim(self.bends) == 4 else -1
        if np.shape(self.bends) != (e, n, k, d) or np.shape(self.vertices_m) != (e, n, k, d, 3):
            raise ValueError(f"TracedLinks: bends (E, N, K, D) and vertices_m (E, N, K, D, 3) "
                             f"expected with E, N, K = {(e, n, k)}, got {np.shape(self.bends)}, "
                             f"{np.shape(self.vertices_m)}")
        if np.any(np.diff(self.t_s) <= 0):
            raise ValueError("TracedLinks.t_s: traced epochs must be strictly increasing")

    @property
    def span_s(self) -> tuple[float, float]:
        """First and last traced epoch [s]."""
        return float(self.t_s[0]), float(self.t_s[-1])


@dataclass(frozen=True)
class PathsAt:
    """The paths of every link at B query times (:func:`paths_at`), K2 = 2 K slots.

    Attributes
    ----------
    valid : ndarray of bool, shape (B, N, K2)
    key : ndarray of int64, shape (B, N, K2)
    length_m : ndarray, shape (B, N, K2) [m]
        NaN where not valid.
    gain_db : ndarray, shape (B, N, K2) [dB]
    aod_deg, aoa_deg : ndarray, shape (B, N, K2) [deg]
        Zenith angle of departure (anchor -> first bend) and of arrival (node -> last bend).
    """

    valid: NDArray[np.bool_]
    key: NDArray[np.int64]
    length_m: FloatArray
    gain_db: FloatArray
    aod_deg: FloatArray
    aoa_deg: FloatArray


@dataclass(frozen=True)
class TracedArrivals:
    """First arrivals at B query times to N nodes (:func:`traced_first_arrivals`).

    Attributes
    ----------
    range_m, sigma_m, snr_db, true_path_m : ndarray, shape (B, N)
        As :class:`diffpos.channel.emulator.FirstArrival` (NaN / inf / -inf where not detected).
    detected : ndarray of bool, shape (B, N)
    key : ndarray of int64, shape (B, N)
        The first-arriving path's identity (0 where not detected).
    """

    range_m: FloatArray
    sigma_m: FloatArray
    snr_db: FloatArray
    true_path_m: FloatArray
    detected: NDArray[np.bool_]
    key: NDArray[np.int64]


def polyline_length_m(start_m: ArrayLike, points_m: ArrayLike, use: ArrayLike,
                      end_m: ArrayLike) -> FloatArray:
    """Length of ``start -> points[use] (in order) -> end`` [m].

    Parameters
    ----------
    start_m, end_m : array_like, shape (..., 3) [m]
    points_m : array_like, shape (..., D, 3) [m]
    use : array_like of bool, shape (..., D)
        The points the polyline goes through (the others are skipped).

    Returns
    -------
    ndarray, shape (...)
    """
    pts, use = _compact(np.asarray(points_m, dtype=np.float64), np.asarray(use, dtype=bool))
    start = np.asarray(start_m, dtype=np.float64)
    end = np.asarray(end_m, dtype=np.float64)
    count = use.sum(axis=-1)
    first = np.where((count > 0)[..., None], pts[..., 0, :], end)
    total = np.linalg.norm(first - start, axis=-1)
    seg = np.linalg.norm(np.diff(pts, axis=-2), axis=-1)  # (..., D-1)
    both = use[..., 1:] & use[..., :-1]
    total = total + np.where(both, seg, 0.0).sum(axis=-1)
    last = np.take_along_axis(pts, np.maximum(count - 1, 0)[..., None, None], axis=-2)[..., 0, :]
    return total + np.where(count > 0, np.linalg.norm(end - last, axis=-1), 0.0)


def _compact(points: FloatArray, use: NDArray[np.bool_]) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The used points first (in order), the rest after: ``(points, use)`` reordered."""
    order = np.argsort(~use, axis=-1, kind="stable")
    return (np.take_along_axis(points, order[..., None], axis=-2),
            np.take_along_axis(use, order, axis=-1))


def _zenith_deg(vec: FloatArray) -> FloatArray:
    norm = np.linalg.norm(vec, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.degrees(np.arccos(np.clip(vec[..., 2] / norm, -1.0, 1.0)))


def _bracket(t_traced: FloatArray, t_s: FloatArray) -> tuple[NDArray[np.int_], FloatArray]:
    """Index ``e0`` of the traced epoch at or before each query and the weight ``w`` in
    ``[0, 1]`` towards ``e0 + 1``; ValueError outside the traced span."""
    lo, hi = float(t_traced[0]), float(t_traced[-1])
    tol = 1e-9 * max(1.0, abs(hi))
    bad = (t_s < lo - tol) | (t_s > hi + tol) | ~np.isfinite(t_s)
    if np.any(bad):
        raise ValueError(f"t_s: {float(t_s[bad][0]):.6g} s is outside the traced epochs "
                         f"[{lo:.6g}, {hi:.6g}] s (trace a longer run)")
    if len(t_traced) == 1:
        return np.zeros(t_s.shape, dtype=np.int_), np.zeros(t_s.shape)
    e0 = np.clip(np.searchsorted(t_traced, t_s, side="right") - 1, 0, len(t_traced) - 2)
    w = np.clip((t_s - t_traced[e0]) / (t_traced[e0 + 1] - t_traced[e0]), 0.0, 1.0)
    return e0, w


def _match(key0: NDArray, valid0: NDArray, key1: NDArray, valid1: NDArray
           ) -> tuple[NDArray[np.int_], NDArray[np.bool_], NDArray[np.bool_]]:
    """For each path at epoch 0 the index of the same path at epoch 1 (``(..., K)``, where
    ``matched``), and which epoch-1 paths are matched by none."""
    eq = (key0[..., :, None] == key1[..., None, :]) & valid0[..., :, None] & valid1[..., None, :]
    # one partner each: the first equal key (keys are unique per link; were one repeated,
    # the repeats would share a partner)
    j = np.argmax(eq, axis=-1)
    matched = np.any(eq, axis=-1)
    cols = np.arange(eq.shape[-1])
    taken = np.any(matched[..., :, None] & (j[..., :, None] == cols), axis=-2)
    return j, matched, valid1 & ~taken


def paths_at(links: TracedLinks, t_s: ArrayLike, anchor_m: ArrayLike,
             nodes_m: ArrayLike) -> PathsAt:
    """Every link's paths at query times (module docstring: interpolation between epochs).

    Parameters
    ----------
    links : TracedLinks
    t_s : array_like, shape (B,) [s]
        Query times inside the traced span.
    anchor_m : array_like, shape (B, 3) [m]
        The anchor's actual position at each query time.
    nodes_m : array_like, shape (B, N, 3) [m]
        The nodes' actual positions at each query time.

    Returns
    -------
    PathsAt
        Slots ``0..K-1``: the paths of the epoch before (interpolated when matched), slots
        ``K..2K-1``: the unmatched paths of the epoch after.

    Raises
    ------
    ValueError
        A query time outside the traced span, or shapes that do not fit.
    """
    t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
    a = np.asarray(anchor_m, dtype=np.float64).reshape(-1, 3)
    nodes = np.asarray(nodes_m, dtype=np.float64)
    n = links.nodes_m.shape[1]
    if a.shape[0] != t.size or nodes.shape != (t.size, n, 3):
        raise ValueError(f"anchor_m (B, 3) and nodes_m (B, {n}, 3) expected for B = {t.size} "
                         f"times, got {a.shape} and {nodes.shape}")
    e0, w = _bracket(links.t_s, t)
    e1 = np.minimum(e0 + 1, len(links.t_s) - 1)
    L = links
    j, matched, only1 = _match(L.key[e0], L.valid[e0], L.key[e1], L.valid[e1])
    wk = w[:, None, None]
    take1 = lambda arr: np.take_along_axis(arr[e1], j.reshape(  # noqa: E731
        j.shape + (1,) * (arr.ndim - 3)), axis=2)
    v0, v1 = L.vertices_m[e0], take1(L.vertices_m)
    verts0 = np.where(matched[..., None, None], (1 - wk[..., None, None]) * v0
                      + wk[..., None, None] * v1, v0)
    with np.errstate(invalid="ignore"):  # (-inf padding times 0)
        gain0 = np.where(matched, (1 - wk) * L.gain_db[e0] + wk * take1(L.gain_db),
                         L.gain_db[e0])
    valid0 = L.valid[e0] & (matched | (wk < 0.5))
    valid1 = only1 & (wk >= 0.5) & (e1 != e0)[:, None, None]
    verts = np.concatenate([verts0, L.vertices_m[e1]], axis=2)
    bends = np.concatenate([L.bends[e0], L.bends[e1]], axis=2)
    valid = np.concatenate([valid0, valid1], axis=2)
    start = np.broadcast_to(a[:, None, None, :], (*verts.shape[:3], 3))
    end = np.broadcast_to(nodes[:, :, None, :], (*verts.shape[:3], 3))
    use = bends & valid[..., None]
    length = np.where(valid, polyline_length_m(start, verts, use, end), np.nan)
    pts, use_c = _compact(verts, use)
    cnt = use_c.sum(axis=-1)
    first = np.where((cnt > 0)[..., None], pts[..., 0, :], end)
    last = np.where((cnt > 0)[..., None], np.take_along_axis(
        pts, np.maximum(cnt - 1, 0)[..., None, None], axis=-2)[..., 0, :], start)
    return PathsAt(
        valid=valid, key=np.where(valid, np.concatenate([L.key[e0], L.key[e1]], axis=2), 0),
        length_m=length, gain_db=np.where(valid, np.concatenate([gain0, L.gain_db[e1]], axis=2),
                                          -np.inf),
        aod_deg=_zenith_deg(first - start), aoa_deg=_zenith_deg(last - end))


def _pattern_db(zenith_deg: FloatArray, hpbw_deg: float | None, peak_deg: float) -> FloatArray:
    """The radio's elevation pattern (3GPP style, 30 dB floor; 0 dB when isotropic)."""
    if hpbw_deg is None:
        return np.zeros(np.shape(zenith_deg))
    return -np.minimum(12.0 * ((zenith_deg - peak_deg) / hpbw_deg) ** 2, 30.0)


def path_snr_db(paths: PathsAt, radio: Radio) -> FloatArray:
    """SNR of every path with the radio's link budget [dB] (``-inf`` where not valid).

    ``P_tx + G_tx + G_rx + pattern_tx(aod) + pattern_rx(aoa) + path gain + processing gain -
    kTB``: the link budget of the emulator and of ``diffpos raytrace``'s datasets.
    """
    r = radio
    n0 = float(noise_floor_dbm(r.bandwidth_hz, temperature_k=r.noise_temperature_k,
                               noise_figure_db=r.noise_figure_db))
    with np.errstate(invalid="ignore"):
        snr = (r.tx_power_dbm + r.tx_gain_dbi + r.rx_gain_dbi + paths.gain_db
               + _pattern_db(paths.aod_deg, r.tx_hpbw_deg, r.tx_peak_deg)
               + _pattern_db(paths.aoa_deg, r.rx_hpbw_deg, r.rx_peak_deg)
               + r.processing_gain_db - n0)
    return np.where(paths.valid, snr, -np.inf)


def traced_first_arrivals(links: TracedLinks, t_s: ArrayLike, anchor_m: ArrayLike,
                          nodes_m: ArrayLike, *, radio: Radio,
                          rng: np.random.Generator | None) -> TracedArrivals:
    """The first arrival from the anchor to every node at B query times.

    The paths of :func:`paths_at`, their SNR (:func:`path_snr_db`) and the emulator's
    detector and range noise (:func:`diffpos.channel.emulator.first_arrival`; one
    ``rng.standard_normal((B, N))`` call, as the emulator's compiled detector draws for B
    epochs of N nodes).

    Parameters
    ----------
    links : TracedLinks
    t_s : array_like, shape (B,) [s]
    anchor_m : array_like, shape (B, 3) [m]
    nodes_m : array_like, shape (B, N, 3) [m]
    radio : Radio
    rng : numpy.random.Generator or None
        ``None``: noise-free ranges.

    Returns
    -------
    TracedArrivals
    """
    paths = paths_at(links, t_s, anchor_m, nodes_m)
    snr = path_snr_db(paths, radio)
    measured, true_path, snr_f, sigma, slot, detected = _detect(
        paths.valid & np.isfinite(snr), snr, paths.length_m / _C, paths.length_m, radio, rng)
    key = np.take_along_axis(paths.key, slot[..., None], axis=-1)[..., 0]
    return TracedArrivals(range_m=measured, sigma_m=sigma, snr_db=snr_f, true_path_m=true_path,
                          detected=detected, key=np.where(detected, key, 0))
