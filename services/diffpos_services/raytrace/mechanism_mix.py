"""First-arrival mechanism mix: the channel emulator vs the ray tracer on the same links.

The emulator's first arrival (:func:`diffpos.channel.emulator.first_arrival` on
:func:`diffpos.channel.emulator.emulate_channel`, noise-free) is one of the 18 slots of
:data:`diffpos.paths.mechanisms.MECHANISMS`; the ray tracer's (:func:`.evaluate.dataset_first_arrival`) is
classified by :func:`.mechanisms.classify_mechanisms` (a slot, or "other" with its label). Every
link whose mechanisms differ gets exactly one cause, tested in this order:

=====================  =====================================================================
cause                  meaning
=====================  =====================================================================
``rt_none``            the ray tracer detects no path on the link
``emu_none``           the emulator detects none (the ray tracer does)
``edge_tie``           both first arrivals have the same length (+-1 mm) but different labels:
                       the ray grazes a window edge (e.g. the ceiling reflection entering
                       exactly at the upper edge, where the model's strict band test says
                       "diffraction + reflection" and Sionna's float32 says "reflection")
``rt_other``           the ray tracer's first arrival is a mechanism the model leaves out
                       (label in ``other_labels``: e.g. a triple bounce)
``not_traced``         the ray tracer has no path of the emulator's first-arrival length
                       (+-1 mm): the ray was not sampled (or the ray tracer says it does not
                       exist)
``emu_weaker``         the ray tracer's first arrival is earlier; the emulator has that
                       mechanism too but below its first-arrival threshold (amplitude model)
``emu_lacks``          the ray tracer's first arrival is earlier and the emulator's channel
                       does not have that mechanism at all (existence disagreement)
``rt_threshold``       the ray tracer has the emulator's first-arrival path but it is below
                       the ray tracer's threshold ``P_max - 15 dB`` (another path is stronger
                       there), so a later path arrives first
=====================  =====================================================================
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.emulator import channel_mechanisms, emulate_channel, first_arrival
from diffpos.paths.mechanisms import MECHANISMS
from diffpos_services.raytrace.dataset import RaytraceDataset
from diffpos_services.raytrace.evaluate import dataset_first_arrival, path_snr_db
from diffpos_services.raytrace.mechanisms import NO_PATH, OTHER, classify_mechanisms

#: Disagreement causes, in the order they are tested (module docstring).
CAUSES = ("rt_none", "emu_none", "edge_tie", "rt_other", "not_traced", "emu_weaker", "emu_lacks",
          "rt_threshold")
#: Two paths with lengths within this are the same path [m].
SAME_PATH_M = 1e-3


def _take(a: NDArray, idx: NDArray) -> NDArray:
    return np.take_along_axis(a, np.maximum(idx, 0)[..., None], axis=-1)[..., 0]


def _causes(ds: RaytraceDataset, ch: Any, fe: Any, fr: Any, rt_code: NDArray,
            thr_rt: NDArray) -> tuple[NDArray[np.object_], NDArray[np.bool_]]:
    """One cause per link (``""`` where the mechanisms agree) and whether the ray tracer has
    the emulator's first-arrival path (same length to 1 mm)."""
    emu_code = np.where(fe.detected, fe.slot, NO_PATH)
    cause = np.full(emu_code.shape, "", dtype=object)
    differ = emu_code != rt_code
    dlen = np.abs(ds.path_length_m - fe.true_path_m[..., None])
    match = ds.path_valid & (dlen < SAME_PATH_M)
    has_emu_path = np.any(match, axis=-1)
    snr_rt = _rt_snr(ds)
    emu_path_snr = np.where(match, snr_rt, -np.inf).max(axis=-1)
    rt_slot = np.clip(rt_code, 0, len(MECHANISMS) - 1)
    emu_has = _take(ch.valid, rt_slot)
    earlier = fr.true_path_m < fe.true_path_m - SAME_PATH_M
    rules = (
        ("rt_none", ~fr.detected),
        ("emu_none", ~fe.detected),
        ("edge_tie", np.abs(fr.true_path_m - fe.true_path_m) < SAME_PATH_M),
        ("rt_other", rt_code == OTHER),
        ("not_traced", ~has_emu_path),
        ("emu_weaker", earlier & emu_has),
        ("emu_lacks", earlier & ~emu_has),
        ("rt_threshold", emu_path_snr < thr_rt),
    )
    for name, cond in rules:
        cause = np.where(differ & (cause == "") & cond, name, cause)
    return np.where(differ & (cause == ""), "unexplained", cause), has_emu_path


def _rt_snr(ds: RaytraceDataset) -> NDArray:
    return path_snr_db(ds, ds.scenario.radio)


def compare_mechanisms(ds: RaytraceDataset) -> dict[str, Any]:
    """Per-mechanism first-arrival shares, per-link agreement and the cause of each difference.

    Returns
    -------
    dict
        ``links``; ``share_emulator`` / ``share_raytrace`` (label -> % of links; the ray
        tracer's "other" paths under their own label with an ``other: `` prefix, undetected
        links under ``none``); ``agreement`` (% of links with the same mechanism, both
        undetected counts as agreement); ``causes`` (cause -> % of links, module docstring);
        ``other_labels`` (label -> links, the ray tracer's "other" first arrivals);
        ``confusion`` (Counter of (emulator label, ray-tracer label) pairs);
        ``emu_code`` / ``rt_code`` / ``cause`` / ``rt_has_emu_path`` / ``emu_length_m`` /
        ``rt_length_m`` (per-link arrays).
    """
    radio = ds.scenario.radio
    ch = emulate_channel(ds.anchors_m, ds.nodes_m, building=ds.scenario.building, radio=radio)
    fe = first_arrival(ch, radio=radio)
    fr = dataset_first_arrival(ds, radio=radio)
    mech = classify_mechanisms(ds)
    rt_code = np.where(fr.detected, _take(mech.code, fr.slot), NO_PATH)
    rt_label = np.where(fr.detected, _take(mech.label, fr.slot), "none")
    snr = _rt_snr(ds)
    pmax = snr.max(axis=-1)
    thr_rt = np.maximum(pmax - radio.fap_threshold_db, radio.detection_snr_db)
    cause, has_emu_path = _causes(ds, ch, fe, fr, rt_code, thr_rt)
    links = int(rt_code.size)
    names = np.array([*channel_mechanisms(radio).labels, "none"], dtype=object)
    emu_label = names[np.where(fe.detected, fe.slot, len(names) - 1)]
    rt_key = np.where(rt_code == OTHER, "other: " + rt_label.astype(str).astype(object),
                      rt_label)
    pct = lambda c: {k: 100.0 * v / links for k, v in c.most_common()}  # noqa: E731
    emu_code = np.where(fe.detected, fe.slot, NO_PATH)
    return {
        "links": links,
        "share_emulator": pct(Counter(emu_label.ravel().tolist())),
        "share_raytrace": pct(Counter(rt_key.ravel().tolist())),
        "agreement": 100.0 * float(np.mean(emu_code == rt_code)),
        "causes": pct(Counter(c for c in cause.ravel().tolist() if c)),
        "other_labels": dict(Counter(rt_label[rt_code == OTHER].tolist()).most_common()),
        "confusion": Counter(zip(emu_label.ravel().tolist(), rt_key.ravel().tolist(),
                                 strict=True)),
        "emu_code": emu_code, "rt_code": rt_code, "cause": cause,
        "rt_has_emu_path": has_emu_path,
        "emu_length_m": fe.true_path_m, "rt_length_m": fr.true_path_m,
    }
