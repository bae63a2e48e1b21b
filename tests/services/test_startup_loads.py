"""Start-up loads only what the run calls (docs/startup.md): each check in a fresh interpreter.

- the GTD half-plane module (imported by every fusion through the channel model) does not
  import ``scipy.special`` (its Faddeeva function is imported by the numpy reference that
  calls it);
- a warm-up of a D-NLS core loads no M-NLS solver, SNR, path or tracker kernel (the
  dispatchers holding a signature after it), and the kernel clock counts those loads;
- a warm-up of an M-NLS core with its tracker off loads no tracker kernel, with it on it does;
- a D-NLS replay (``diffpos replay --method dnls``, in its process) imports no M-NLS, tracker,
  SNR or path kernel module, nor does the live fusion service's module;
- :func:`diffpos._kernels.clock.kernel_load_s` counts the seconds the kernel loads take.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _run(code: str) -> dict:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT), str(ROOT / "services"), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, cwd=ROOT, check=False, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_gtd_halfplane_does_not_import_scipy_special():
    got = _run("import sys, json\n"
               "import diffpos.channel.gtd_halfplane as g\n"
               "before = 'scipy.special' in sys.modules\n"
               "g.transition_function([0.5])\n"
               "print(json.dumps([before, 'scipy.special' in sys.modules]))\n")
    assert got == [False, True]  # loaded by the reference that uses it, only then


_LOADED = """
import json, sys
from diffpos._kernels import clock
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.scenario_io import load_scenario
sc = load_scenario("scenarios/{scenario}.toml")
cfg = FusionConfig.from_scenario(sc, **{overrides})
t0 = clock.kernel_load_s()
FusionCore(cfg).warm_up()
import gc
from numba.core.dispatcher import Dispatcher
hits = sorted({{f"{{d.py_func.__module__}}.{{d.py_func.__name__}}"
               for d in gc.get_objects() if isinstance(d, Dispatcher) and d.overloads}})
print(json.dumps({{"hits": hits, "load_s": clock.kernel_load_s() - t0}}))
"""


def _loaded(scenario: str, **overrides) -> dict:
    return _run(_LOADED.format(scenario=scenario, overrides=overrides))


@pytest.mark.slow
def test_dnls_warm_up_loads_no_mnls_snr_or_tracker_kernel():
    got = _loaded("large", method="dnls")
    assert any(h.startswith("diffpos.estimators.dnls.") for h in got["hits"]), got
    assert not [h for h in got["hits"] if h.startswith(
        ("diffpos.tracking.", "diffpos.channel.", "diffpos.paths.",
         "diffpos.estimators.mnls.solver_nb"))], got
    assert got["load_s"] > 0.0


@pytest.mark.slow
def test_untracked_mnls_warm_up_loads_no_tracker_kernel():
    off = _loaded("large", method="mnls", tracking=False)
    on = _loaded("large", method="mnls")
    tracker = ("diffpos.tracking.",)
    assert not [h for h in off["hits"] if h.startswith(tracker)], off
    assert [h for h in on["hits"] if h.startswith(tracker)], on
    assert any(h.startswith("diffpos.estimators.mnls.") for h in off["hits"]), off


_REPLAYED = """
import json, sys
from diffpos_services.cli.main import main
code = main(["replay", sys.argv[1], "--no-files", "--no-progress", "--method", "dnls",
             "--write-mcap", sys.argv[2]])
import diffpos_services.fusion.service  # noqa: F401  (the live fusion's module: `diffpos fusion`)
print(json.dumps({"code": code, "modules": sorted(m for m in sys.modules
                                                  if m.startswith("diffpos."))}))
"""


@pytest.mark.slow
def test_dnls_replay_process_imports_no_mnls_or_tracker_kernel_module(tmp_path):
    """The D-NLS replay's process (and the fusion service's imports) never load M-NLS's
    modules (whose start kernels compile on import) or a tracker, SNR or path kernel module:
    the pool, the warm-up and the replay import them only where mnls runs."""
    from diffpos_services.replay.synthetic import write_synthetic_recording

    rec = tmp_path / "syn.mcap"
    write_synthetic_recording(rec, n_anchors=6, n_nodes=6, duration_s=1.5, seed=11)
    code = _REPLAYED.replace("sys.argv[1]", repr(str(rec))).replace(
        "sys.argv[2]", repr(str(tmp_path / "out.mcap")))
    got = _run(code)
    assert got["code"] == 0 and (tmp_path / "out.mcap").stat().st_size > 0, got
    mods = got["modules"]
    assert "diffpos.estimators.dnls.fit_nb" in mods, mods  # it solved with D-NLS
    bad = [m for m in mods if m.startswith("diffpos.estimators.mnls.") or (
        m.endswith("_nb") and m.startswith(("diffpos.tracking.", "diffpos.channel.",
                                            "diffpos.paths.")))]
    assert not bad, bad
