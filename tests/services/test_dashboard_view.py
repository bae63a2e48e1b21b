"""What the coordinator sees when a recording is opened: the .rrd read back with Rerun's own
reader (``rerun.chunk.RrdReader``: the recording store and the blueprint store).

References: the blueprint's view names and origins from ``dashboard.blueprint``; the camera
checked geometrically (every anchor position and building corner inside a 60 degree cone
around the viewing direction); the time cursor the blueprint opens at (``following``: the
newest time of the recording) and, at that time, a marker for every responder that ever had
a fix (latest-at over the logged rows); the building of a recording whose only description
is the run configuration ``diffpos emulate`` attaches; foreign and empty MCAP files refused
with exit code 1 and no output."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rerun.chunk as rc
from diffpos_services.dashboard import blueprint as bp
from diffpos_services.dashboard.convert import mcap_to_rrd, rrd_rows
from mcap.writer import Writer
from test_dashboard import _write_mcap, of, synthetic_run


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    """A synthetic run recorded to MCAP with the run configuration emulate attaches (no
    scenario TOML), converted by ``mcap_to_rrd``."""
    building, msgs = synthetic_run(n_anchors=6, n_nodes=7, duration_s=6.0, rate_hz=10.0, seed=5)
    tmp = tmp_path_factory.mktemp("view")
    mcap = tmp / "run.mcap"
    _write_mcap(mcap, msgs)
    table = {"width_m": building.x_max_m - building.x_min_m,
             "center_x_m": 0.5 * (building.x_min_m + building.x_max_m),
             "depth_m": building.depth_m, "n_floors": building.n_floors,
             "floor_height_m": building.floor_height_m,
             "first_floor_z_m": building.first_floor_z_m,
             "sill_height_m": building.sill_height_m,
             "window_height_m": building.window_height_m}
    run_config = {"fusion": {"building": table}, "emulate": {"edge": "upper"}}
    _append_attachment(mcap, "run_config.json", json.dumps(run_config).encode())
    out = tmp / "run.rrd"
    counts = mcap_to_rrd(mcap, out)
    return building, msgs, counts, out


def _append_attachment(mcap, name, data):
    """Rewrite ``mcap`` with an extra attachment (the recorder's own writer attaches at
    start; here the messages were written first)."""
    from mcap.reader import make_reader

    with open(mcap, "rb") as f:
        reader = make_reader(f)
        items = list(reader.iter_messages())
    tmp = mcap.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        w = Writer(f)
        w.start()
        schemas, channels = {}, {}
        for schema, channel, message in items:
            if schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(
                    channel.topic, channel.message_encoding, schemas[schema.id], channel.metadata)
            w.add_message(channels[channel.id], log_time=message.log_time, data=message.data,
                          publish_time=message.publish_time)
        w.add_attachment(0, 0, name, "application/json", data)
        w.finish()
    tmp.replace(mcap)


def _blueprint(path):
    """Entity path -> {column: first value} of the blueprint store (time columns skipped)."""
    reader = rc.RrdReader(path)
    out: dict[str, dict] = {}
    for chunk in reader.stream(store=reader.blueprints()[0]):
        rb = chunk.to_record_batch()
        for name in rb.schema.names:
            if "RowId" in name or "timestamp" in str(rb.schema.field(name).type):
                continue
            vals = rb.column(name).to_pylist()
            if vals and vals[0] is not None:
                out.setdefault(str(chunk.entity_path), {})[name] = vals[0]
    return out


def _views(blueprint):
    """Display name -> (class, origin, view entity path)."""
    return {
        v["ViewBlueprint:display_name"][0]: (v["ViewBlueprint:class_identifier"][0],
                                             v["ViewBlueprint:space_origin"][0], path)
        for path, v in blueprint.items() if "ViewBlueprint:display_name" in v
    }


def test_blueprint_views_camera_and_hidden_paths(converted):
    building, msgs, _, out = converted
    blueprint = _blueprint(out)
    views = _views(blueprint)
    assert views[bp.BUILDING_VIEW][:2] == ("3D", "world")
    assert views[bp.FLOOR_VIEW][:2] == ("TextDocument", "floors")
    assert views[bp.EVENTS_VIEW][:2] == ("TextLog", "events")
    # the fleet's error as three lines; the floor plans, top floor first, and the legend
    assert any(v[1] == "metrics/fleet/error_3d_m" for v in views.values())
    plans = [v[1] for v in views.values() if v[0] == "2D" and v[1].startswith("plan/")]
    assert sorted(plans) == [f"plan/F{k}" for k in range(building.n_floors)]
    assert any(v[:2] == ("2D", "legend") for v in views.values())
    # the plotted responders: one floor-probability tab each, and their error plots
    chosen = [v[1].rsplit("/", 1)[1] for v in views.values()
              if v[1].startswith("metrics/floor_probability/")]
    assert 1 <= len(chosen) <= 4
    view3d = views[bp.BUILDING_VIEW][2]
    # paths: hidden in the building view until shown per responder
    hidden = [p for p, v in blueprint.items() if p.startswith(view3d) and
              v.get("EntityBehavior:visible") == [False]]
    assert hidden and all(f"/overrides/{bp.PATHS_ENTITY}/" in p for p in hidden)
    # the camera sees every anchor position and the building (within a 60 degree cone)
    eye = blueprint[f"{view3d}/EyeControls3D"]
    pos, target = np.array(eye["EyeControls3D:position"][0]), np.array(
        eye["EyeControls3D:look_target"][0])
    axis = (target - pos) / np.linalg.norm(target - pos)
    top = building.first_floor_z_m + building.n_floors * building.floor_height_m
    corners = [[x, y, z] for x in (building.x_min_m, building.x_max_m)
               for y in (0.0, building.depth_m) for z in (0.0, top)]
    pts = np.array([a.position_m for a in of(msgs, "AnchorState")] + corners)
    ray = pts - pos
    cos = ray @ axis / np.linalg.norm(ray, axis=1)
    assert np.degrees(np.arccos(cos.min())) < 30.0
    # the time panel follows the newest data (the cursor opens at the end of the file)
    assert blueprint["/time_panel"]["TimePanelBlueprint:play_state"] == [3]  # following


def test_every_responder_has_a_marker_at_the_cursor_time(converted):
    _, msgs, _, out = converted
    rows = rrd_rows(out)
    t_cursor = max(t for r in rows.values() for t, _ in r if t is not None)
    fixed = {e.node_id for e in of(msgs, "PositionEstimate") if e.position_m is not None}
    assert len(fixed) == 7
    for nid in fixed:
        latest = [r for t, r in rows[f"/world/nodes/{nid}/estimate"] if t <= t_cursor
                  and "Points3D:positions" in r][-1]
        assert len(latest["Points3D:positions"]) == 1, nid
    # the floor table at the cursor lists every responder on a floor
    table = [r for t, r in rows["/floors"] if t <= t_cursor][-1]["TextDocument:text"][0]
    for nid in fixed:
        assert nid in table
    # and every responder is on exactly one floor plan, its full id in its marker's label
    on_plans = []
    for path, rr_ in rows.items():
        if path.startswith("/plan/F") and path.endswith("/responders"):
            latest = [r for t, r in rr_ if t is not None and t <= t_cursor][-1]
            on_plans += [label.split()[0] for label in latest["Points2D:labels"] or []]
    assert sorted(on_plans) == sorted(fixed)
    assert "no fix yet" not in table


def test_building_from_the_run_configuration(converted):
    building, _, counts, out = converted
    assert counts["building"]
    rows = rrd_rows(out)
    strips = rows["/world/building/floors"][0][1]["LineStrips3D:strips"]
    xs = np.concatenate([np.asarray(s)[:, 0] for s in strips])
    assert xs.min() == pytest.approx(building.x_min_m) and xs.max() == pytest.approx(
        building.x_max_m)


@pytest.mark.parametrize("kind", ["foreign", "no messages"])
def test_foreign_or_empty_mcap_exits_1_and_writes_nothing(tmp_path, capsys, kind):
    from diffpos_services.cli import main as cli

    path = tmp_path / "in.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        if kind == "foreign":
            s = w.register_schema("x", "jsonschema", b"{}")
            c = w.register_channel("/camera/image", "json", s)
            w.add_message(c, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    out = tmp_path / "out.rrd"
    assert cli.main(["to-rerun", str(path), "-o", str(out)]) == 1
    assert "not a diffpos recording" in capsys.readouterr().err
    assert not out.exists()
