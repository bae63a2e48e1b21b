"""The chi-square thresholds of the gating without scipy.special at import
(``diffpos.estimators.gating._CHI2_ISF_TABLE``): scipy's values bit for bit, scipy asked for
anything else."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from scipy.special import chdtri

from diffpos.estimators import gating


def test_table_is_scipys_values_bit_for_bit():
    for p, row in gating._CHI2_ISF_TABLE.items():
        ref = np.array([chdtri(d, p) for d in range(1, len(row) + 1)], dtype=np.float64)
        assert np.array(row, dtype=np.float64).tobytes() == ref.tobytes(), p


def test_threshold_equals_scipy_inside_and_outside_the_table():
    dof = np.array([0, 1, 5, 64, 65, 100])
    for p in (1e-3, 0.1, 0.5, 0.01):  # 0.01 and dof > 64: scipy's own call
        got = gating.chi2_threshold(dof, p)
        assert np.isnan(got[0])
        ref = np.array([chdtri(d, p) for d in dof[1:]], dtype=np.float64)
        assert got[1:].tobytes() == ref.tobytes(), p


def test_gating_does_not_import_scipy_special():
    code = ("import sys, diffpos.estimators.gating as g; "
            "g.chi2_threshold(__import__('numpy').arange(20), 1e-3); "
            "print('scipy.special' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"
