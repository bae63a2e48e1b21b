"""Path classification (pure numpy): Sionna's interaction chains -> the paper's MPC groups."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Sionna's interaction flags.
SPECULAR, DIFFUSE, REFRACTION, DIFFRACTION = 1, 2, 4, 8
_LETTER = {SPECULAR: "R", DIFFUSE: "S", REFRACTION: "T", DIFFRACTION: "D"}




def encode_chains(interactions: ArrayLike) -> NDArray[np.uint16]:
    """Pack per-depth interaction flags ``(D, ...)`` into one code per path (4 bits/depth).

    Parameters
    ----------
    interactions : array_like of int, shape (D, ...)
        Sionna's ``paths.interactions`` (0 = none, 1 R, 2 diffuse, 4 T, 8 D), ``D <= 4``.

    Returns
    -------
    ndarray of uint16, shape (...)
    """
    it = np.asarray(interactions).astype(np.uint16)
    if it.shape[0] > 4:
        raise ValueError("at most 4 interactions per path fit in a uint16 chain code")
    code = np.zeros(it.shape[1:], dtype=np.uint16)
    for d in range(it.shape[0]):
        code |= (it[d] & 0xF) << np.uint16(4 * d)
    return code


def _decode(code: NDArray[np.uint16]) -> list[NDArray[np.uint16]]:
    return [(code >> np.uint16(4 * d)) & np.uint16(0xF) for d in range(4)]


def chain_label(code: int) -> str:
    """Human-readable chain, e.g. ``0x48`` -> ``"Tx-D-T-Rx"`` (``S`` = diffuse)."""
    letters = [_LETTER.get(int(f), "?") for f in _decode(np.uint16(code)) if int(f)]
    return "-".join(["Tx", *letters, "Rx"])


def classify_chains(code: ArrayLike) -> NDArray[np.int8]:
    """MPC group 1..4 of chain codes (module docstring table).

    Parameters
    ----------
    code : array_like of uint16
        From :func:`encode_chains`.

    Returns
    -------
    ndarray of int8
        Same shape as ``code``.
    """
    c = np.asarray(code, dtype=np.uint16)
    flags = _decode(c)
    n_r = sum(((f == SPECULAR) | (f == DIFFUSE)).astype(np.int8) for f in flags)
    n_d = sum((f == DIFFRACTION).astype(np.int8) for f in flags)
    n_other = sum(((f != 0) & (f != REFRACTION) & (f != SPECULAR) & (f != DIFFUSE)
                   & (f != DIFFRACTION)).astype(np.int8) for f in flags)
    d_first = flags[0] == DIFFRACTION
    cls = np.full(c.shape, 4, dtype=np.int8)
    cls = np.where((n_r == 0) & (n_d == 0), 1, cls)
    cls = np.where((n_r == 1) & (n_d == 0), 2, cls)
    cls = np.where((n_r == 0) & (n_d == 1) & d_first, 3, cls)
    return np.where(n_other > 0, 4, cls).astype(np.int8)
