"""The D-NLS exclusion search is a recorded fusion setting (``dnls_exclusion_search``): new
recordings say ``bounded`` (the default), recordings made before the setting replay with the
``exhaustive`` search they ran with, and the step runs the one it is given."""

from __future__ import annotations

import numpy as np
import pytest
from diffpos_services.fusion.config import (
    LEGACY_DNLS_EXCLUSION_SEARCH,
    FusionConfig,
    with_legacy_defaults,
)
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording


def test_recordings_without_the_setting_replay_the_exhaustive_search():
    assert FusionConfig().dnls_exclusion_search == "bounded"
    old = with_legacy_defaults({"method": "dnls", "gating": True})
    assert old["dnls_exclusion_search"] == LEGACY_DNLS_EXCLUSION_SEARCH == "exhaustive"
    new = with_legacy_defaults({"method": "dnls", "dnls_exclusion_search": "bounded"})
    assert new["dnls_exclusion_search"] == "bounded"
    assert "dnls_exclusion_search" not in with_legacy_defaults({})  # no settings at all


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    """3 s, 5 anchors, 3 nodes, 8 % outliers (the exclusion search runs), live D-NLS fixes."""
    path = tmp_path_factory.mktemp("dnls_search") / "synthetic.mcap"
    write_synthetic_recording(path, n_anchors=5, n_nodes=3, duration_s=3.0,
                              outlier_probability=0.08, seed=11, flush_every=200)
    return path


def _fixes(r):
    return {(e.node_id, e.epoch): (e.status, tuple(e.used_anchors or ()), e.position_m)
            for e in r.estimates}


def test_the_step_runs_the_recorded_search(rec):
    bounded = replay(rec, out_mcap=None)
    assert bounded.report["settings"]["dnls_exclusion_search"] == "bounded"
    assert bounded.report["compare"]["position_diff_m"]["max"] == 0.0  # live ran the same
    exhaustive = replay(rec, out_mcap=None, overrides={"dnls_exclusion_search": "exhaustive"})
    assert exhaustive.report["settings"]["dnls_exclusion_search"] == "exhaustive"
    a, b = _fixes(bounded), _fixes(exhaustive)
    assert a.keys() == b.keys()
    moved = [np.linalg.norm(np.subtract(a[k][2], b[k][2])) for k in a
             if a[k][2] is not None and b[k][2] is not None]
    # the searches stop at different tolerances: the same anchors and fixes within 1 mm,
    # but not the same bits (so the setting reached the solver)
    assert max(moved) > 0.0 and max(moved) < 1e-3
    assert sum(a[k][:2] != b[k][:2] for k in a) <= len(a) // 50
