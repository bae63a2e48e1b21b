"""numba's on-disk cache of the kernels compiled ``nogil=True`` (diffpos._kernels.pool splits
their rows over threads): a second process loads them from the cache instead of compiling."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.system

_PROBE = """
import json
from diffpos.channel import snr_nb as channel_nb
from diffpos.estimators.mnls import solver_nb as mnls_nb
from diffpos.tracking import initialisation_nb, model_nb as tracking_nb
from diffpos.tracking.tracker import warm_tracking
channel_nb.warm_channel()
warm_tracking()
out = {}
for name, k in (("channel_snr_masked_kernel", channel_nb.channel_snr_masked_kernel),
                ("lm_kernel", mnls_nb.lm_kernel),
                ("all_paths_kernel", tracking_nb.all_paths_kernel),
                ("grid_cost_kernel", initialisation_nb.grid_cost_kernel)):
    out[name] = [bool(k.targetoptions.get("nogil")), sum(k.stats.cache_hits.values()),
                 sum(k.stats.cache_misses.values())]
print(json.dumps(out))
"""


def _probe() -> dict:
    r = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
                       check=True, timeout=600)
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_second_process_loads_the_nogil_kernels_from_the_cache():
    _probe()  # the first may compile (a fresh cache)
    for name, (nogil, hits, misses) in _probe().items():
        assert nogil, name
        assert hits >= 1 and misses == 0, (name, hits, misses)
