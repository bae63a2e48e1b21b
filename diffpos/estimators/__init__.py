"""Batched position estimators: D-NLS (with outlier gating), LLS and IPPA.

All estimators take ``(B, M, 3)`` anchors, ``(B, M)`` ranges, optional ``(B, M)`` sigmas and a
``(B, M)`` bool mask, solve all ``B`` fixes together with numpy, and return a
:class:`FixResult` of batched arrays.

* :func:`dnls` - Levenberg-Marquardt on the paper's diffraction path model (Corollary 1,
  Case-1/Case-2 offset), multi-start over floor heights, FIM covariance, RAIM-style gating.
* :func:`lls` - linearised LoS ToA least squares (reference-anchor differencing), with
  rank / conditioning checks.
* :func:`mnls` - mechanism-aware NLS on the first-arrival path model (:mod:`diffpos.paths`):
  floor hypotheses, the mechanism of each link as a latent choice, robust one-sided likelihood,
  floor posterior and a model-aware covariance (:class:`MnlsResult`).
* :func:`ippa` - iterative parallel projection (Jia & Buehrer 2010) as used by the paper's
  authors, with NLoS ranges projected only when the estimate lies outside their ball.
"""

from .dnls import DEFAULT_Z_STARTS_M, dnls
from .gating import GatingConfig, chi2_threshold
from .ippa import ippa
from .lls import lls
from .mnls import MnlsResult, mnls
from .result import ExclusionReason, FixResult, FixStatus, InputError

__all__ = [
    "DEFAULT_Z_STARTS_M",
    "ExclusionReason",
    "FixResult",
    "FixStatus",
    "GatingConfig",
    "InputError",
    "MnlsResult",
    "chi2_threshold",
    "dnls",
    "ippa",
    "lls",
    "mnls",
]
