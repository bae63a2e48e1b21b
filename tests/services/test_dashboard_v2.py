"""Dashboard and estimate v2: mechanism paths, floor probabilities, decoding both versions.

References: the path model's own lengths (:func:`diffpos.paths.model.first_arrival_paths`, image
method / Fermat point) against the length of the drawn polyline; the message fields against
the logged rows read back with Rerun's reader.
"""

from __future__ import annotations

import numpy as np
import pytest
import rerun as rr
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.columns import estimate_columns_from_messages
from diffpos_services.dashboard.convert import rrd_rows
from diffpos_services.dashboard.decode import VIEW_DECODERS, estimate_extras
from diffpos_services.dashboard.estimates import log_estimates
from diffpos_services.dashboard.geometry import Tracks
from diffpos_services.dashboard.mechanisms import building_of_outline, mechanism_strips, recipe
from diffpos_services.wire import messages as M

from diffpos.paths.mechanisms import MECHANISMS
from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import default_scenario

B = default_scenario().building
OUTLINE = BuildingOutline(x_min_m=B.edge_x_m[0], x_max_m=B.edge_x_m[1], depth_m=B.depth_m,
                          n_floors=B.n_floors, floor_height_m=B.floor_height_m,
                          sill_height_m=B.sill_height_m, window_height_m=B.window_height_m,
                          first_floor_z_m=B.first_floor_z_m)


def test_outline_gives_the_path_models_building():
    b = building_of_outline(OUTLINE)
    for f in ("edge_x_m", "depth_m", "n_floors", "floor_height_m", "first_floor_z_m",
              "sill_height_m", "window_height_m"):
        assert getattr(b, f) == getattr(B, f), f


def test_every_label_has_a_recipe():
    assert recipe("Tx-Rx") == ("direct",)
    assert recipe("Tx-R(ground)-R(ceiling)-Rx") == ("spec", ("ceiling",), True)
    assert recipe("Tx-D(lower)-R(floor)-Rx") == ("diff", "lower", "floor")
    assert recipe("Tx-R(side x2)-Rx") == ("spec", ("side x2",), False)
    assert all(recipe(m)[0] in ("direct", "spec", "diff") for m in MECHANISMS)
    with pytest.raises(ValueError):
        recipe("Tx-Q-Rx")


def test_drawn_path_length_equals_the_path_model_for_every_mechanism():
    """2,000 random anchor/node pairs: for every existing mechanism the polyline through the
    drawn interaction points is as long as the path model's length (rel 1e-9)."""
    rng = np.random.default_rng(3)
    n = 2000
    anchors = np.stack([rng.uniform(-30, 30, n), rng.uniform(-25, -3, n),
                        rng.uniform(0, 12, n)], -1)
    floor = rng.integers(0, B.n_floors, n)
    nodes = np.stack([rng.uniform(-19.5, 19.5, n), rng.uniform(0.5, 22, n),
                      B.floor_z_m(floor) + rng.uniform(0.1, 2.9, n)], -1)
    ps = first_arrival_paths(nodes[:, None], anchors[:, None], B, floor=floor[:, None])
    checked = 0
    for k, label in enumerate(MECHANISMS):
        rows = np.flatnonzero(ps.valid[:, 0, k])
        if rows.size == 0:
            continue
        strips = mechanism_strips(anchors[rows], nodes[rows], floor[rows],
                                  np.full(rows.size, label), OUTLINE)
        length = np.linalg.norm(np.diff(strips, axis=1), axis=-1).sum(axis=1)
        np.testing.assert_allclose(length, ps.length_m[rows, 0, k], rtol=1e-9, err_msg=label)
        np.testing.assert_array_equal(strips[:, 0], anchors[rows])
        np.testing.assert_array_equal(strips[:, -1], nodes[rows])
        checked += 1
    assert checked >= 12
    none = mechanism_strips(anchors[:2], nodes[:2], floor[:2], np.array(["", ""]), OUTLINE)
    assert np.isnan(none).all()


def _v2(seq: int, t_ns: int, pos, mech: str | None) -> bytes:
    cov = ((0.04, 0.0, 0.0), (0.0, 0.04, 0.0), (0.0, 0.0, 0.09))
    return M.encode(M.PositionEstimateV2(
        node_id="r01", t_ns=t_ns, epoch=seq, seq=seq, method="mnls+tracking", status="TRACKING",
        position_m=pos, covariance_m2=cov, peb_m=0.41, z_bound_m=0.3, floor_index=1,
        floor_probabilities=[0.02, 0.93, 0.05, 0.0, 0.0], snapshot=None,
        links=[M.AnchorLink("uav1", mech, 0.01), M.AnchorLink("uav2", None, 3.0)],
        used_anchors=["uav1"] if mech else [], residuals_m=[0.01] if mech else [],
        excluded=[M.Exclusion("uav2", "RAIM")], message="", t_input_wall_ns=1,
        t_pub_wall_ns=2))


def test_v2_estimates_draw_the_mechanism_path_and_the_floor_probability(tmp_path):
    """Decoded by the dashboard's view (v1 and v2 alike), the mechanism the fusion used is
    drawn through its interaction points and the floor table shows the chosen floor's
    probability."""
    t0 = 1_800_000_000_000_000_000
    pos = (2.0, 6.0, float(B.floor_z_m(1)) + 1.5)
    label = "Tx-D(lower)-R(ceiling)-Rx"
    msgs = [VIEW_DECODERS["estimate"].decode(_v2(i, t0 + i * 10**8, pos, label))
            for i in range(3)]
    assert msgs[0].links[0].mechanism == label and msgs[0].floor_probabilities[1] == 0.93
    cols = estimate_columns_from_messages(msgs)
    extras = estimate_extras(msgs)
    assert list(extras["link_mechanism"]) == [label, label, label, "", "", ""]
    np.testing.assert_array_equal(extras["floor_probability"], [0.93] * 3)
    # the estimate columns carry both (and keep them through a selection of fixes)
    assert list(cols.link_mechanism) == list(extras["link_mechanism"])
    np.testing.assert_array_equal(cols.floor_probability, extras["floor_probability"])
    est = cols
    a_pos = np.array([[-15.0, -20.0, 1.0], [15.0, -20.0, 1.0]])
    anchors = Tracks([t0, t0], ["uav1", "uav2"], a_pos)
    rec = rr.RecordingStream("test-v2", recording_id="v2")
    path = tmp_path / "v2.rrd"
    rec.save(str(path))
    log_estimates(rec, est, anchors=anchors, building=OUTLINE, path_period_s=10.0,
                  floor_period_s=10.0)
    rec.flush()
    rec.disconnect()  # the file is finished (footer written) before it is read back
    rows = rrd_rows(path)
    strips = rows["/world/paths/r01"][0][1]["LineStrips3D:strips"]
    want = mechanism_strips(a_pos[:1], np.array([pos]), np.array([1]), np.array([label]),
                            OUTLINE)[0]
    np.testing.assert_allclose(np.array(strips[0], float), want, atol=1e-5)
    table = rows["/floors"][-1][1]["TextDocument:text"][0]
    assert "- **F1** (1): r01 93 %" in table
    # a v1 estimate decodes with empty v2 fields and keeps the window-edge path
    v1 = VIEW_DECODERS["estimate"].decode(M.encode(M.PositionEstimate(
        node_id="n1", t_ns=t0, epoch=0, seq=0, status="OK", position_m=pos,
        covariance_m2=None, peb_m=None, z_bound_m=None, floor_index=1,
        used_anchors=["uav1"], residuals_m=[0.0], excluded=[], message="",
        t_input_wall_ns=0, t_pub_wall_ns=0)))
    assert v1.links == [] and v1.floor_probabilities == []
    assert list(estimate_extras([v1])["link_mechanism"]) == [""]
