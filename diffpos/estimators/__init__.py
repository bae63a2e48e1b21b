"""Batched position estimators: D-NLS (with outlier gating), LLS and IPPA.

All estimators take ``(B, M, 3)`` anchors, ``(B, M)`` ranges, optional ``(B, M)`` sigmas and a
``(B, M)`` bool mask, solve all ``B`` fixes together with numpy, and return a
:class:`FixResult` of batched arrays.

* :func:`dnls.solver.dnls` - Levenberg-Marquardt on the paper's diffraction path model (Corollary 1,
  Case-1/Case-2 offset), multi-start over floor heights, FIM covariance, RAIM-style gating.
* :func:`lls.lls` - linearised LoS ToA least squares (reference-anchor differencing), with
  rank / conditioning checks.
* :func:`mnls.solver.mnls` - mechanism-aware NLS on the first-arrival path model (:mod:`diffpos.paths.model`):
  floor hypotheses, the mechanism of each link as a latent choice, robust one-sided likelihood,
  floor posterior and a model-aware covariance (:class:`MnlsResult`).
* :func:`ippa.ippa` - iterative parallel projection (Jia & Buehrer 2010) as used by the paper's
  authors, with NLoS ranges projected only when the estimate lies outside their ball.

Shared by them: :mod:`result` (``FixResult``, input preparation), :mod:`starts` (the
floor-height multi-start of D-NLS and IPPA), :mod:`lm` / :mod:`lm_nb` (the numpy
Levenberg-Marquardt of D-NLS and its gating, and its compiled twin), :mod:`gating` (RAIM).
"""
