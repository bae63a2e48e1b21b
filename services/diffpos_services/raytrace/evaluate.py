"""Evaluating a dataset: SNR, channel, first arrival, MPC statistics, Fermat check and the
comparison with the emulator."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.emulator import (
    Channel,
    FirstArrival,
    channel_mechanisms,
    emulate_channel,
    first_arrival,
    mpc_statistics,
)
from diffpos.channel.linkbudget import noise_floor_dbm
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.geometry import diffraction_point
from diffpos.scenario import Radio, Scenario
from diffpos.study import Arrivals, FirstArrivalData
from diffpos_services.raytrace.dataset import RaytraceDataset, load_dataset

_C = SPEED_OF_LIGHT_M_S



def _pattern_db(zenith_deg: NDArray, hpbw_deg: float | None, peak_deg: float) -> NDArray:
    if hpbw_deg is None:
        return np.zeros(np.shape(zenith_deg))
    return -np.minimum(12.0 * ((zenith_deg - peak_deg) / hpbw_deg) ** 2, 30.0)


def path_snr_db(ds: RaytraceDataset, radio: Radio) -> NDArray[np.float64]:
    """SNR of every path with ``radio``'s link budget (same formula as the emulator) [dB].

    ``P_tx + G_tx + G_rx + pattern_tx(aod) + pattern_rx(aoa) + path gain + processing gain -
    kTB``; ``-inf`` for padding.
    """
    r = radio
    n0 = float(noise_floor_dbm(r.bandwidth_hz, temperature_k=r.noise_temperature_k,
                               noise_figure_db=r.noise_figure_db))
    aod = ds.path_aod_deg.astype(np.float64)
    aoa = ds.path_aoa_deg.astype(np.float64)
    snr = (r.tx_power_dbm + r.tx_gain_dbi + r.rx_gain_dbi + ds.path_gain_db.astype(np.float64)
           + _pattern_db(aod, r.tx_hpbw_deg, r.tx_peak_deg)
           + _pattern_db(aoa, r.rx_hpbw_deg, r.rx_peak_deg) + r.processing_gain_db - n0)
    return np.where(ds.path_valid, snr, -np.inf)


def dataset_channel(ds: RaytraceDataset, radio: Radio) -> Channel:
    """The ray-traced paths as a :class:`diffpos.channel.emulator.Channel` (K = paths per link).

    ``mpc_class`` of the returned channel is a placeholder (the group varies per link); use
    ``ds.path_class`` or :func:`dataset_first_arrival`. Phases are not stored (gain is real).
    """
    snr = path_snr_db(ds, radio)
    n0 = float(noise_floor_dbm(radio.bandwidth_hz, temperature_k=radio.noise_temperature_k,
                               noise_figure_db=radio.noise_figure_db))
    valid = ds.path_valid
    k = valid.shape[-1]
    gain = np.where(valid, 10.0 ** (ds.path_gain_db.astype(np.float64) / 20.0), 0.0)
    return Channel(
        delay_s=ds.path_length_m / _C, length_m=ds.path_length_m, gain=gain.astype(np.complex128),
        power_dbm=np.where(valid, snr - radio.processing_gain_db + n0, -np.inf), snr_db=snr,
        aod_deg=ds.path_aod_deg.astype(np.float64), aoa_deg=ds.path_aoa_deg.astype(np.float64),
        valid=valid, exists=valid & (snr >= radio.detection_snr_db),
        mpc_class=np.zeros(k, dtype=np.int8), mechanism=tuple(f"path{i}" for i in range(k)),
        nodes_m=ds.nodes_m, anchors_m=ds.anchors_m,
    )


def dataset_first_arrival(
    ds: RaytraceDataset,
    *,
    radio: Radio | None = None,
    rng: np.random.Generator | None = None,
) -> FirstArrival:
    """First-arriving path and measured range per link, from the ray-traced paths.

    Uses :func:`diffpos.channel.emulator.first_arrival` (same detector, same noise model and random
    stream as the emulator) on :func:`dataset_channel`; ``mpc_class`` is the ray-traced group
    of the selected path and ``slot`` its index in the link's path list.

    Parameters
    ----------
    ds : RaytraceDataset
    radio : Radio, optional
        Link budget and detector; default the traced scenario's radio.
    rng : numpy.random.Generator, optional
        Range noise; ``None`` gives noise-free ranges.

    Returns
    -------
    diffpos.channel.emulator.FirstArrival
        Arrays of shape (N, M) that the positioning study consumes like the emulator's.
    """
    radio = radio or ds.scenario.radio
    fap = first_arrival(dataset_channel(ds, radio), radio=radio, rng=rng)
    slot = np.maximum(fap.slot, 0)
    cls = np.take_along_axis(ds.path_class, slot[..., None], axis=-1)[..., 0]
    return dataclasses.replace(fap, mpc_class=np.where(fap.detected, cls, 0).astype(np.int8))


def dataset_mpc_statistics(ds: RaytraceDataset, fap: FirstArrival, *,
                           radio: Radio | None = None) -> dict[str, dict[str, float]]:
    """The paper's ``P_e`` / ``P_fap`` table from the ray trace (same keys as
    :func:`diffpos.channel.emulator.mpc_statistics`) [%]."""
    radio = radio or ds.scenario.radio
    exists = ds.path_valid & (path_snr_db(ds, radio) >= radio.detection_snr_db)
    pairs = exists.shape[0] * exists.shape[1]
    out: dict[str, dict[str, float]] = {}
    for g in (1, 2, 3, 4):
        pe = np.any(exists & (ds.path_class == g), axis=-1).sum()
        out[f"MPC-{g}"] = {"P_e": 100.0 * pe / pairs,
                           "P_fap": 100.0 * np.sum(fap.mpc_class == g) / pairs}
    out["none"] = {"P_fap": 100.0 * np.sum(~fap.detected) / pairs}
    return out


def edge_fermat_check(ds: RaytraceDataset, *, tol_m: float = 0.02) -> dict[str, NDArray]:
    """Ray-traced single-diffraction paths over a horizontal window edge vs the Fermat length.

    Selects every valid path whose chain is a diffraction followed only by transmissions
    (group 3) and whose diffraction point lies on a horizontal window edge (``y = 0``,
    ``z`` within ``tol_m`` of a window edge height, strictly inside the edge's x-extent), and
    computes the analytic length with :func:`diffpos.geometry.diffraction_point` for that
    edge.

    Returns
    -------
    dict
        ``index`` (P, 3) int (node, anchor, path), ``traced_m``, ``analytic_m``, ``error_m``
        (traced - analytic) [m], ``edge`` ("upper"/"lower" as 1/0), ``same_floor`` (edge on
        the receiver's floor), ``on_edge`` (the analytic point is inside the edge).
    """
    b = ds.scenario.building
    lo, hi = b.window_z_m(np.arange(b.n_floors))
    heights = np.concatenate([lo, hi])
    v = ds.path_vertex_m.astype(np.float64)
    sel = ds.path_valid & (ds.path_class == 3)
    dz = np.abs(v[..., 2][..., None] - heights)
    near = np.nanmin(np.where(np.isfinite(dz), dz, np.inf), axis=-1) < tol_m
    x0, x1 = b.edge_x_m
    sel &= near & (np.abs(v[..., 1]) < tol_m) & (v[..., 0] > x0 + tol_m) & (v[..., 0] < x1 - tol_m)
    idx = np.argwhere(sel)
    if len(idx) == 0:
        empty = np.zeros(0)
        return {"index": idx, "traced_m": empty, "analytic_m": empty, "error_m": empty,
                "edge": empty.astype(int), "same_floor": empty.astype(bool),
                "on_edge": empty.astype(bool)}
    n, m, k = idx.T
    z_edge = heights[np.argmin(np.abs(v[n, m, k, 2][:, None] - heights), axis=1)]
    p0 = np.stack([np.full(len(n), x0), np.zeros(len(n)), z_edge], axis=-1)
    p1 = np.stack([np.full(len(n), x1), np.zeros(len(n)), z_edge], axis=-1)
    dp = diffraction_point(ds.anchors_m[m], ds.nodes_m[n], p0, p1)
    edge_floor = b.floor_index(z_edge - b.sill_height_m + 1e-6)
    is_upper = np.isin(z_edge, hi)
    traced = ds.path_length_m[n, m, k]
    return {"index": idx, "traced_m": traced, "analytic_m": dp.length_m,
            "error_m": traced - dp.length_m, "edge": is_upper.astype(int),
            "same_floor": edge_floor == b.floor_index(ds.nodes_m[n, 2]),
            "on_edge": dp.on_edge}


def compare_with_emulator(ds: RaytraceDataset, *, radio: Radio | None = None) -> dict[str, Any]:
    """First-arrival agreement of the emulator and the ray tracer on the same receivers.

    Runs :func:`diffpos.channel.emulator.emulate_channel` for the dataset's receivers and anchors and
    compares the noise-free first arrivals.

    Returns
    -------
    dict
        ``links``; ``class_agreement`` (fraction of links with the same first-arrival group,
        undetected = group 0); ``found_emulator_fap`` (fraction of the emulator's detected
        first-arrival paths that the ray tracer has too, same length to 1 mm) and
        ``class_agreement_found`` (group agreement on those links); ``confusion`` (5 x 5 counts, rows emulator group 0..4, columns
        ray tracer); ``both_mpc3`` (links where both first arrivals are group 3);
        ``path_diff_m`` (ray tracer - emulator first-arrival length on those links, array);
        ``path_diff_all_m`` (on every link detected by both, array); ``stats_emulator`` and
        ``stats_raytrace`` (P_e / P_fap tables); ``fermat`` (:func:`edge_fermat_check`
        summary: count, max and 99th-percentile |error| [m]).
    """
    scenario = ds.scenario
    radio = radio or scenario.radio
    ch = emulate_channel(ds.anchors_m, ds.nodes_m, building=scenario.building, radio=radio)
    fe = first_arrival(ch, radio=radio)
    fr = dataset_first_arrival(ds, radio=radio)
    conf = np.zeros((5, 5), dtype=int)
    np.add.at(conf, (fe.mpc_class.ravel(), fr.mpc_class.ravel()), 1)
    both3 = (fe.mpc_class == 3) & (fr.mpc_class == 3)
    both = fe.detected & fr.detected
    fc = edge_fermat_check(ds)
    err = np.abs(fc["error_m"])
    dmin = np.where(ds.path_valid, np.abs(ds.path_length_m - fe.true_path_m[..., None]),
                    np.inf).min(axis=-1)
    found = fe.detected & (dmin < 1e-3)
    return {
        "found_emulator_fap": float(found.sum() / max(fe.detected.sum(), 1)),
        "class_agreement_found": float(np.mean((fe.mpc_class == fr.mpc_class)[found]))
        if found.any() else float("nan"),
        "links": int(fe.mpc_class.size),
        "class_agreement": float(np.mean(fe.mpc_class == fr.mpc_class)),
        "confusion": conf,
        "both_mpc3": int(both3.sum()),
        "path_diff_m": (fr.true_path_m - fe.true_path_m)[both3],
        "path_diff_all_m": (fr.true_path_m - fe.true_path_m)[both],
        "emulator_mechanism": np.asarray(channel_mechanisms(radio).labels, dtype=object),
        "fap_emulator": fe,
        "fap_raytrace": fr,
        "stats_emulator": mpc_statistics(ch, fe),
        "stats_raytrace": dataset_mpc_statistics(ds, fr, radio=radio),
        "fermat": {"count": int(err.size),
                   "max_abs_m": float(err.max()) if err.size else float("nan"),
                   "p99_abs_m": float(np.percentile(err, 99)) if err.size else float("nan")},
    }


def dataset_arrivals(path: str | os.PathLike[str], scenario: Scenario, *,
                     rng: np.random.Generator | None = None) -> Arrivals:
    """A dataset file's first arrivals for ``diffpos reproduce --channel raytrace:FILE``.

    The dataset must match ``scenario`` (:func:`load_dataset`); ``rng`` draws the range
    noise (:func:`dataset_first_arrival`); the MPC table uses the ray-traced groups.
    """
    ds = load_dataset(path, scenario=scenario)
    channel = dataset_channel(ds, scenario.radio)
    fa = dataset_first_arrival(ds, radio=scenario.radio, rng=rng)
    table = mpc_statistics(channel, fa, path_class=ds.path_class)
    return Arrivals(data=FirstArrivalData.from_channel(fa, ds.anchors_m, ds.nodes_m),
                    channel=channel, table=table)
