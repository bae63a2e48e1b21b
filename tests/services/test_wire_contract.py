"""Wire contract: checked-in schemas == generated ones; real messages validate; keys parse."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import msgspec
import pytest
from diffpos_services.wire import keys as K
from diffpos_services.wire import messages as M

from diffpos.paths.mechanisms import MECHANISMS

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "schemas"


def _examples() -> dict[type, list[msgspec.Struct]]:
    est_ok = M.PositionEstimate(
        node_id="n01",
        t_ns=1_700_000_000_000_000_000,
        epoch=17_000_000_000,
        seq=3,
        status="OK",
        position_m=(1.0, 2.0, 7.5),
        covariance_m2=((0.01, 0.0, 0.0), (0.0, 0.02, 0.0), (0.0, 0.0, 0.03)),
        peb_m=0.245,
        z_bound_m=0.17,
        floor_index=2,
        used_anchors=["uav1", "uav2", "uav3"],
        residuals_m=[0.01, -0.02, 0.003],
        excluded=[M.Exclusion("uav4", "GATED")],
        message="ok",
        t_input_wall_ns=5,
        t_pub_wall_ns=6,
    )
    est_bad = M.PositionEstimate(
        node_id="n02",
        t_ns=-5,
        epoch=-1,
        seq=0,
        status="UNIDENTIFIABLE",
        position_m=None,
        covariance_m2=None,
        peb_m=M.finite_or_none(float("inf")),
        z_bound_m=None,
        floor_index=None,
        used_anchors=[],
        residuals_m=[],
        excluded=[M.Exclusion("uav1", "ANCHOR_LOST")],
        message="2 anchors: z not identifiable",
        t_input_wall_ns=0,
        t_pub_wall_ns=0,
    )
    est_v2 = _estimate_v2()
    est_v2_lost = M.PositionEstimateV2(
        node_id="n03", t_ns=7, epoch=0, seq=1, method="mnls+tracking", status="LOST",
        position_m=None, covariance_m2=None, peb_m=None, z_bound_m=None, floor_index=None,
        floor_probabilities=[], snapshot=None, links=[], used_anchors=[], residuals_m=[],
        excluded=[M.Exclusion("uav1", "NOT_DETECTED")], message="", t_input_wall_ns=0,
        t_pub_wall_ns=0)
    return {
        M.PositionEstimateV2: [est_v2, est_v2_lost],
        M.AnchorState: [
            M.AnchorState(
                anchor_id="uav1",
                t_ns=10,
                seq=0,
                position_m=(-20.0, -30.0, 5.0),
                velocity_m_s=(0.0, 1.0, 0.0),
                position_sigma_m=(0.02, 0.02, 0.05),
                velocity_sigma_m_s=0.05,
                range_rate_hz=10.0,
                t_pub_wall_ns=11,
            )
        ],
        M.RangeMeasurement: [
            M.RangeMeasurement(
                anchor_id="uav1",
                node_id="n01",
                t_ns=10,
                seq=1,
                range_m=41.25,
                sigma_m=0.01,
                snr_db=23.5,
                t_pub_wall_ns=12,
            ),
            M.RangeMeasurement(
                anchor_id="uav2",
                node_id="n-7_x",
                t_ns=10,
                seq=2,
                range_m=None,
                sigma_m=None,
                snr_db=None,
                t_pub_wall_ns=12,
            ),
        ],
        M.RangeBatch: [
            M.RangeBatch(anchor_id="uav3", t_ns=7, seq=9, node_ids=["n01", "n02"],
                         range_m=[12.5, None], sigma_m=[0.01, None], snr_db=[20.0, None],
                         t_pub_wall_ns=8),
        ],
        M.PositionEstimate: [est_ok, est_bad],
        M.FusionDiagnosticsV1: [
            M.FusionDiagnosticsV1(
                t_wall_ns=1,
                watermark_ns=None,
                received={"range": 10, "anchor_state": 2},
                rejected={"schema": 1},
                gated=2,
                solved=3,
                published=3,
                fixes_by_status={"OK": 3},
                late_ranges=0,
                pending_epochs=1,
                live_anchors=["uav1"],
                anchors=[M.AnchorHealth("uav1", True, 2, 10, 5, None)],
                latency=M.LatencyStats(3, 1.0, 2.0, 2.5),
            )
        ],
        M.FusionDiagnostics: [
            M.FusionDiagnostics(
                t_wall_ns=1,
                watermark_ns=None,
                received={"range": 10, "anchor_state": 2},
                rejected={"schema": 1},
                gated=2,
                solved=3,
                published=3,
                fixes_by_status={"OK": 3},
                late_ranges=0,
                pending_epochs=1,
                live_anchors=["uav1"],
                anchors=[M.AnchorHealth("uav1", True, 2, 10, 5, None)],
                latency=M.LatencyStats(3, 1.0, 2.0, 2.5),
            ),
            _diagnostics_v2(),
        ],
        M.GroundTruth: [
            M.GroundTruth(
                entity="node",
                id="n01",
                t_ns=1,
                position_m=(1.0, 2.0, 3.0),
                velocity_m_s=(0.0, 0.0, 0.0),
                floor_index=0,
            ),
        ],
        M.RunControl: [
            M.RunControl(
                run_id="r1", t0_ns=0, wall_t0_ns=5, speed=4.0, duration_ns=10**10, seed=1
            ),
            M.RunControl(run_id="r2", t0_ns=0, wall_t0_ns=5, speed=1.0, duration_ns=0, seed=0,
                         lockstep=True),
        ],
        M.RunClock: [M.RunClock(run_id="r2", t_ns=299_999_999)],
        M.Heartbeat: [
            M.Heartbeat(service="fusion", instance="0f1e2d3c4b5a6978", pid=4242, seq=7,
                        t_wall_ns=1_700_000_000_000_000_000, period_ns=500_000_000,
                        progress=1234, pending=3, last_epoch=17_000_000_000, published=600),
            M.Heartbeat(service="anchor", instance="00", pid=1, seq=0, t_wall_ns=0,
                        period_ns=1, progress=0, pending=0, last_epoch=None, published=0,
                        anchor_id="uav1"),
        ],
    }


def _estimate_v2() -> M.PositionEstimateV2:
    """A tracked estimate with a snapshot, mechanisms and an outlier (the golden message)."""
    cov = ((0.04, 0.001, 0.0), (0.001, 0.05, 0.0), (0.0, 0.0, 0.09))
    return M.PositionEstimateV2(
        node_id="r01", t_ns=1_700_000_000_100_000_000, epoch=17_000_000_001, seq=42,
        method="mnls+tracking", status="TRACKING", position_m=(1.5, 4.25, 8.5),
        covariance_m2=cov, peb_m=0.4243, z_bound_m=0.3, floor_index=1,
        floor_probabilities=[0.0, 0.97, 0.03, 0.0, 0.0],
        snapshot=M.SnapshotFix(method="mnls", status="OK", position_m=(1.4, 4.3, 8.4),
                               covariance_m2=cov, floor_index=1,
                               floor_probabilities=[0.0, 0.9, 0.1, 0.0, 0.0]),
        links=[M.AnchorLink("uav1", "Tx-D(lower)-Rx", 0.012),
               M.AnchorLink("uav2", "Tx-R(ceiling)-Rx", -0.03),
               M.AnchorLink("uav3", None, 2.5)],
        used_anchors=["uav1", "uav2"], residuals_m=[0.012, -0.03],
        excluded=[M.Exclusion("uav3", "RAIM"), M.Exclusion("uav4", "NOT_DETECTED")],
        message="", t_input_wall_ns=1_700_000_000_101_000_000,
        t_pub_wall_ns=1_700_000_000_102_500_000)


#: the golden encoding of _estimate_v2 (field order = the struct's; a change here is a change
#: of the wire format: bump the version)
GOLDEN_V2 = (
    b'{"schema":"diffpos.estimate.v2","node_id":"r01","t_ns":1700000000100000000,'
    b'"epoch":17000000001,"seq":42,"method":"mnls+tracking","status":"TRACKING",'
    b'"position_m":[1.5,4.25,8.5],"covariance_m2":[[0.04,0.001,0.0],[0.001,0.05,0.0],'
    b'[0.0,0.0,0.09]],"peb_m":0.4243,"z_bound_m":0.3,"floor_index":1,'
    b'"floor_probabilities":[0.0,0.97,0.03,0.0,0.0],"snapshot":{"method":"mnls",'
    b'"status":"OK","position_m":[1.4,4.3,8.4],"covariance_m2":[[0.04,0.001,0.0],'
    b'[0.001,0.05,0.0],[0.0,0.0,0.09]],"floor_index":1,'
    b'"floor_probabilities":[0.0,0.9,0.1,0.0,0.0]},"links":[{"anchor_id":"uav1",'
    b'"mechanism":"Tx-D(lower)-Rx","residual_m":0.012},{"anchor_id":"uav2",'
    b'"mechanism":"Tx-R(ceiling)-Rx","residual_m":-0.03},{"anchor_id":"uav3",'
    b'"mechanism":null,"residual_m":2.5}],"used_anchors":["uav1","uav2"],'
    b'"residuals_m":[0.012,-0.03],"excluded":[{"anchor_id":"uav3","reason":"RAIM"},'
    b'{"anchor_id":"uav4","reason":"NOT_DETECTED"}],"message":"",'
    b'"t_input_wall_ns":1700000000101000000,"t_pub_wall_ns":1700000000102500000}'
)


def _diagnostics_v2() -> M.FusionDiagnostics:
    """Diagnostics v2 with every new field set (the golden message)."""
    return M.FusionDiagnostics(
        t_wall_ns=1, watermark_ns=7, received={"range": 2}, rejected={}, gated=0, solved=1,
        published=1, fixes_by_status={"OK": 1}, late_ranges=1, pending_epochs=0,
        live_anchors=["uav1"], anchors=[M.AnchorHealth("uav1", True, 1, 2, 7, None)],
        latency=M.LatencyStats(1, 1.0, 1.0, 1.0), late_by_anchor={"uav1": 1},
        deadline_ns=300_000_000, max_lag_ns=3_000_000_000, lag_by_anchor={"uav1": 5},
        releases={"complete": 1, "flush": 0},
        decisions=M.DecisionChunk(chunk=0, keys=["diffpos/s/anchor/uav1/ranges", ""],
                                  ops=[0, 4], refs=[0, 1], values=[123, -1],
                                  wall_delta_ns=[10, 5], dropped=0))


_DIAG_V2_GOLDEN = (
    b'{"schema":"diffpos.fusion_diagnostics.v2","t_wall_ns":1,"watermark_ns":7,'
    b'"received":{"range":2},"rejected":{},"gated":0,"solved":1,"published":1,'
    b'"fixes_by_status":{"OK":1},"late_ranges":1,"pending_epochs":0,"live_anchors":["uav1"],'
    b'"anchors":[{"anchor_id":"uav1","alive":true,"states":1,"ranges":2,"last_t_ns":7,'
    b'"lost_wall_ns":null}],"latency":{"count":1,"p50_ms":1.0,"p99_ms":1.0,"max_ms":1.0},'
    b'"late_by_anchor":{"uav1":1},"deadline_ns":300000000,"max_lag_ns":3000000000,'
    b'"lag_by_anchor":{"uav1":5},"releases":{"complete":1,"flush":0},"decisions":{"chunk":0,'
    b'"keys":["diffpos/s/anchor/uav1/ranges",""],"ops":[0,4],"refs":[0,1],"values":[123,-1],'
    b'"wall_delta_ns":[10,5],"dropped":0},"instance":"","duplicate_publishers":{},'
    b'"contested_anchors":[],"shard":0,"shards":1}'
)


def test_diagnostics_v2_golden_bytes_and_v1_still_decodes():
    """Diagnostics v2 encodes to the golden bytes (valid against the checked-in v2 schema);
    a v1 message (old recordings) decodes through the same decoder as v2 with the new fields
    at their defaults, and the v1 schema file still validates it."""
    d = _diagnostics_v2()
    raw = M.encode(d)
    assert raw == _DIAG_V2_GOLDEN
    jsonschema.Draft202012Validator(json.loads(
        (SCHEMA_DIR / "fusion_diagnostics.v2.json").read_text())).validate(json.loads(raw))
    dec = M.decoder(M.FusionDiagnostics)
    assert dec(raw) == d
    old = _examples()[M.FusionDiagnosticsV1][0]
    old_raw = M.encode(old)
    jsonschema.Draft202012Validator(json.loads(
        (SCHEMA_DIR / "fusion_diagnostics.v1.json").read_text())).validate(json.loads(old_raw))
    up = dec(old_raw)
    assert type(up) is M.FusionDiagnostics
    assert all(getattr(up, f) == getattr(old, f) for f in old.__struct_fields__)
    assert (up.late_by_anchor, up.releases, up.decisions, up.deadline_ns) == ({}, {}, None, None)
    with pytest.raises(M.DecodeError):  # a v2 decoder still wants a diagnostics tag
        dec(M.encode(_examples()[M.RunClock][0]))


def test_estimate_v2_golden_bytes_and_both_versions_decode():
    """Estimate v2 encodes to the golden bytes (validated by the checked-in schema), decodes
    back equal; :func:`estimate_decoder` reads v1 and v2 by their tag and rejects anything
    else (another message, an unknown version) as a schema error."""
    raw = M.encode(_estimate_v2())
    assert raw == GOLDEN_V2
    schema = json.loads((SCHEMA_DIR / "estimate.v2.json").read_text())
    jsonschema.Draft202012Validator(schema).validate(json.loads(raw))
    for label in [x["mechanism"] for x in json.loads(raw)["links"] if x["mechanism"]]:
        assert label in MECHANISMS
    dec = M.estimate_decoder()
    assert dec(raw) == _estimate_v2()
    v1 = _examples()[M.PositionEstimate][0]
    got = dec(M.encode(v1))
    assert type(got) is M.PositionEstimate and got == v1
    for bad in (M.encode(_examples()[M.RunClock][0]),
                raw.replace(b"diffpos.estimate.v2", b"diffpos.estimate.v3"),
                raw.replace(b'"epoch":17000000001,', b"")):
        with pytest.raises(M.DecodeError) as info:
            dec(bad)
        assert info.value.reason == "schema"
    # a v1 reader still rejects v2 (a new version is a new tag)
    with pytest.raises(M.DecodeError):
        M.decoder(M.PositionEstimate)(raw)


@pytest.mark.parametrize("kind", list(M.MESSAGE_TYPES), ids=lambda k: k.__name__)
def test_checked_in_schema_matches_code(kind):
    path = SCHEMA_DIR / M.schema_filename(kind)
    assert path.exists(), f"{path} missing: run diffpos schemas --write schemas/"
    assert path.read_text() == M.schema_text(kind), (
        f"{path.name} drifted from the {kind.__name__} struct: regenerate with "
        "diffpos schemas --write schemas/ (and bump the version "
        "if the change is breaking)"
    )


@pytest.mark.parametrize("kind", list(M.MESSAGE_TYPES), ids=lambda k: k.__name__)
def test_schema_is_2020_12_object_at_top(kind):
    schema = json.loads((SCHEMA_DIR / M.schema_filename(kind)).read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["type"] == "object"
    text = json.dumps(schema)
    # only internal references (Foxglove / MCAP viewers)
    assert all(ref.startswith("#/") for ref in _refs(schema))
    # every time field is an integer, every physical float names its unit
    for name, prop in schema["properties"].items():
        if name.endswith("_ns"):
            assert "integer" in json.dumps(prop), name
    assert "schema" in schema["required"]
    assert M.MESSAGE_TYPES[kind].split(".")[0] in text


def _refs(obj):
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k == "$ref":
                yield v
            else:
                yield from _refs(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _refs(v)


@pytest.mark.parametrize("kind", list(M.MESSAGE_TYPES), ids=lambda k: k.__name__)
def test_encoded_messages_validate_and_roundtrip(kind):
    schema = json.loads((SCHEMA_DIR / M.schema_filename(kind)).read_text())
    validator = jsonschema.Draft202012Validator(schema)
    dec = M.decoder(kind)
    for msg in _examples()[kind]:
        raw = M.encode(msg)
        doc = json.loads(raw)
        validator.validate(doc)
        assert doc["schema"] == "diffpos." + M.MESSAGE_TYPES[kind]
        assert dec(raw) == msg


def test_schema_rejects_what_the_decoder_rejects():
    """Negative cases: a NaN turned into null, a wrong tag, a float time, a bad id."""
    schema = json.loads((SCHEMA_DIR / "range.v1.json").read_text())
    validator = jsonschema.Draft202012Validator(schema)
    good = json.loads(M.encode(_examples()[M.RangeMeasurement][0]))
    dec = M.decoder(M.RangeMeasurement)
    for field, value in [
        ("sigma_m", 0.0),
        ("schema", "diffpos.range.v2"),
        ("t_ns", 1.5),
        ("node_id", "a/b"),
        ("range_m", -1.0),
        ("seq", -1),
    ]:
        bad = dict(good, **{field: value})
        assert not validator.is_valid(bad), field
        with pytest.raises(M.DecodeError) as info:
            dec(json.dumps(bad).encode())
        assert info.value.reason == "schema"
    with pytest.raises(M.DecodeError) as info:
        dec(b"{not json")
    assert info.value.reason == "json"


def test_nonfinite_values_never_reach_the_wire():
    assert M.finite_or_none(float("nan")) is None
    assert M.finite_or_none(float("inf")) is None
    assert M.finite_or_none(2) == 2.0


def test_keys_roundtrip_and_patterns():
    k = K.Keys("site-1")
    cases = {
        k.anchor_state("uav1"): ("anchor_state", "uav1", None),
        k.anchor_range("uav1", "n01"): ("range", "uav1", "n01"),
        k.anchor_range_batch("uav1"): ("range_batch", "uav1", None),
        k.node_estimate("n01"): ("estimate", None, "n01"),
        k.fusion_diagnostics(): ("diagnostics", None, None),
        k.truth_node("n01"): ("truth_node", None, "n01"),
        k.truth_anchor("uav2"): ("truth_anchor", "uav2", None),
        k.run_control(): ("run_control", None, None),
        k.run_clock(): ("run_clock", None, None),
        k.alive_anchor("uav2"): ("alive_anchor", "uav2", None),
        k.alive_fusion(): ("alive_fusion", None, None),
        k.alive_recorder(): ("alive_recorder", None, None),
    }
    for key, (kind, a, n) in cases.items():
        p = K.parse_key(key)
        assert p == K.ParsedKey(kind, "site-1", a, n), key
        assert key.startswith(k.root + "/")
    assert K.parse_key("other/x/anchor/a/state") is None
    assert K.parse_key("diffpos/s/anchor/a/bogus") is None
    with pytest.raises(ValueError, match="site"):
        K.Keys("a/b")
    with pytest.raises(ValueError, match="anchor_id"):
        K.check_id("*", field="anchor_id")


def test_fusion_inputs_never_include_truth():
    """The fusion's subscriptions must not intersect the truth keys (checked structurally)."""
    import zenoh

    k = K.Keys("s")
    truth = [zenoh.KeyExpr(k.truth_node("n01")), zenoh.KeyExpr(k.truth_anchor("uav1")),
             zenoh.KeyExpr(k.truth_all())]
    for pattern in k.fusion_inputs():
        ke = zenoh.KeyExpr(pattern)
        for t in truth:
            assert not ke.intersects(t), (pattern, str(t))
    # and they do see what they need
    assert zenoh.KeyExpr(k.anchor_ranges()).intersects(zenoh.KeyExpr(k.anchor_range("uav1", "n1")))
    assert zenoh.KeyExpr(k.everything()).intersects(truth[0])


def test_keys_of_every_message_type():
    """Keys.of knows every published message type, estimate v2 and diagnostics v1 included."""
    k = K.Keys("s")
    ex = _examples()
    assert k.of(_estimate_v2()) == k.node_estimate(_estimate_v2().node_id)
    assert k.of(ex[M.PositionEstimate][0]) == k.node_estimate(ex[M.PositionEstimate][0].node_id)
    assert k.of(ex[M.FusionDiagnosticsV1][0]) == k.of(_diagnostics_v2()) == k.fusion_diagnostics()
    for kind in M.MESSAGE_TYPES:
        for msg in ex[kind]:
            assert K.parse_key(k.of(msg)) is not None, kind
