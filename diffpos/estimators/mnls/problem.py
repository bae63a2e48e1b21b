"""The flattened hypotheses of M-NLS (:mod:`diffpos.estimators.mnls.solver`): one row per fix x
floor x start, with the floor's box, the floor prior and the robust likelihood's tail offset;
building them (:func:`_problem`) and taking rows of them (:func:`_take`, :func:`_sub`,
:func:`_replace_snr`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from diffpos.paths.mechanisms import MechanismSet

FloatArray = NDArray[np.float64]

#: Prior share of links whose first arrival is outside the path model (module docstring).
OUTLIER_PRIOR = 0.02
#: A link's cost is capped at the out-of-model cost only in a fix with at least this many
#: links: the links left must over-determine the position (3 unknowns + 1 check) for one link
#: to be outvoted. With four, any three links fit some mechanism exactly on every floor, so
#: every floor would cost at most the cap: measured on Sionna's paper building (4 anchors,
#: K = 3) the right floor fell from 86.4 to 80.7 % and the confidently wrong doubled
#: (docs/raytrace_study.md, 1d).
CAP_MIN_LINKS = 5


@dataclass
class _Problem:
    """Flattened hypotheses: N = fixes x floors x starts rows (internal)."""

    anchors: FloatArray  # (N, M, 3)
    r: FloatArray  # (N, M)
    sig: FloatArray  # (N, M)
    mask: NDArray[np.bool_]  # (N, M)
    floor: NDArray[np.int_]  # (N,)
    lo: FloatArray  # (N, 3) box of the floor
    hi: FloatArray
    z_mid: FloatArray  # (N,)
    prior_var: float
    tail_a: FloatArray  # (N, M) tail offset
    cap: FloatArray  # (N, M) out-of-model cost of every link (inf: no cap), :func:`_outlier_cap`
    lam: float
    excess_db: FloatArray  # (N, M) free-space SNR at the range minus measured SNR (NaN: none)
    wavelength_m: float
    allowed: NDArray[np.bool_] | None = None  # (N, M, K) optional restriction (tests/oracle)
    snr_cost: FloatArray | None = None  # (N, M, K) SNR cost of every slot (held between updates)
    snr_meas: FloatArray | None = None  # (N, M) measured SNR (with radio: SNR-aware search)
    radio: object = None
    strong: NDArray[np.bool_] | None = None  # (N, M, K) predicted surely detected
    mech: MechanismSet | None = None  # the mechanisms (None: the 18 of MECHANISMS)
    rule: object = None  # the detector's rule (rules.SnrRule; None: its default)


def _c(a, dtype=np.float64):
    """C-contiguous, writable ``dtype`` array (the kernel's one signature)."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()



def _take(p: _Problem, rows) -> _Problem:
    """The hypotheses ``rows`` of a problem."""
    kw = {f: getattr(p, f) for f in ("prior_var", "lam", "wavelength_m", "mech", "rule")}
    for f in ("anchors", "r", "sig", "mask", "floor", "lo", "hi", "z_mid", "tail_a", "cap",
              "excess_db"):
        kw[f] = getattr(p, f)[rows]
    return _Problem(**kw)



def _sub(p: _Problem, rows) -> _Problem:
    """The hypotheses ``rows`` with their SNR terms."""
    q = _take(p, rows)
    q.snr_meas, q.radio = (None if p.snr_meas is None else p.snr_meas[rows]), p.radio
    for f in ("allowed", "snr_cost", "strong"):
        v = getattr(p, f)
        setattr(q, f, None if v is None else v[rows])
    return q



def _replace_snr(p: _Problem) -> _Problem:
    """A copy of ``p`` with the SNR terms held (no refresh during the refinement)."""
    q = _take(p, slice(None))
    q.allowed, q.snr_cost, q.strong = p.allowed, p.snr_cost, p.strong
    return q



def _floor_boxes(building, floors: NDArray[np.int_], margin: float = 1e-3):
    x0, x1 = building.edge_x_m
    zf = building.floor_z_m(floors)
    lo = np.stack([np.full(floors.shape, x0 + margin), np.full(floors.shape, margin),
                   zf + margin], axis=-1)
    hi = np.stack([np.full(floors.shape, x1 - margin),
                   np.full(floors.shape, building.depth_m - margin),
                   zf + building.floor_height_m - margin], axis=-1)
    return lo, hi, zf + 0.5 * building.floor_height_m



def _outlier_cap(sig: FloatArray, mask: NDArray[np.bool_], building) -> FloatArray:
    """Cost of a link out of the model, relative to the Gaussian core's normaliser: prior
    ``eps`` (:data:`OUTLIER_PRIOR`) and a range uniform over the building's extent ``D``
    (diagonal of width x depth x all floors), ``log((1 - eps) / eps) + log(D / (sigma
    sqrt(2 pi)))`` [nats]; ``inf`` in fixes with fewer than :data:`CAP_MIN_LINKS` links."""
    d = np.sqrt(building.width_m**2 + building.depth_m**2
                + (building.n_floors * building.floor_height_m) ** 2)
    c = np.log((1 - OUTLIER_PRIOR) / OUTLIER_PRIOR) + np.log(d / (sig * np.sqrt(2 * np.pi)))
    enough = np.sum(mask, axis=-1, keepdims=True) >= CAP_MIN_LINKS
    return np.where(enough, c, np.inf)


def _problem(a, r, sig, mask, floors, building, lam, excess, wavelength,
             mech: MechanismSet | None = None, rule=None) -> _Problem:
    lo, hi, zmid = _floor_boxes(building, floors)
    # tail offset: -log(eps / lambda) + log((1 - eps) / (sigma sqrt(2 pi)))
    tail_a = np.log((1 - OUTLIER_PRIOR) / OUTLIER_PRIOR * lam / (sig * np.sqrt(2 * np.pi)))
    cap = np.broadcast_to(_outlier_cap(sig, mask, building), np.shape(r))
    return _Problem(anchors=a, r=r, sig=sig, mask=mask, floor=floors, lo=lo, hi=hi,
                    z_mid=zmid, prior_var=building.floor_height_m**2 / 12.0,
                    tail_a=tail_a, cap=cap, lam=lam, excess_db=excess, wavelength_m=wavelength,
                    mech=mech, rule=rule)

