"""Property-based fuzzing (hypothesis) of the wire decoders, the fusion's input path and
`diffpos solve`: whatever arrives, nothing raises but the documented error, counters add up,
what is accepted is schema-valid, and the outputs stay valid JSON.

Derandomised (fixed examples in CI, see ``settings``); raise ``max_examples`` locally to dig.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import jsonschema
from diffpos_services.config import build_config
from diffpos_services.fusion.core import FusionConfig, FusionCore
from diffpos_services.solve import solve_lines, solve_records
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys
from diffpos_services.wire.solve_io import read_lines
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

SCHEMAS = Path(__file__).resolve().parents[2] / "schemas"
FUZZ = settings(max_examples=100, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
KEYS = Keys("t")

EXAMPLES: dict[type, dict] = {
    M.RangeMeasurement: {"schema": "diffpos.range.v1", "anchor_id": "uav1", "node_id": "n01",
                         "t_ns": 150_000_000, "seq": 7, "range_m": 25.0, "sigma_m": 0.05,
                         "snr_db": 20.0, "t_pub_wall_ns": 1},
    M.AnchorState: {"schema": "diffpos.anchor_state.v1", "anchor_id": "uav1",
                    "t_ns": 150_000_000, "seq": 8, "position_m": [-15.0, -20.0, 1.0],
                    "velocity_m_s": [0.0, 0.0, 0.0], "position_sigma_m": [0.01, 0.01, 0.01],
                    "velocity_sigma_m_s": 0.0, "range_rate_hz": 10.0, "t_pub_wall_ns": 1},
    M.RangeBatch: {"schema": "diffpos.range_batch.v1", "anchor_id": "uav1",
                   "t_ns": 150_000_000, "seq": 9, "node_ids": ["n01", "n02"],
                   "range_m": [25.0, None], "sigma_m": [0.05, None], "snr_db": [20.0, None],
                   "t_pub_wall_ns": 1},
    M.RunControl: {"schema": "diffpos.run_control.v1", "run_id": "r", "t0_ns": 0,
                   "wall_t0_ns": 0, "speed": 1.0, "duration_ns": 0, "seed": 0},
    M.GroundTruth: {"schema": "diffpos.truth.v1", "entity": "node", "id": "n01", "t_ns": 0,
                    "position_m": [0.0, 1.0, 2.0], "velocity_m_s": [0.0, 0.0, 0.0],
                    "floor_index": 0},
}
KEY_OF = {M.RangeMeasurement: KEYS.anchor_range("uav1", "n01"),
          M.AnchorState: KEYS.anchor_state("uav1"),
          M.RangeBatch: KEYS.anchor_range_batch("uav1")}

scalars = (st.none() | st.booleans() | st.integers(-(2**70), 2**70)
           | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=12))
json_values = st.recursive(
    scalars,
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=3),
    max_leaves=10,
)
# the numbers that matter: around the limits, huge, tiny, negative, int64 edges
edgy_numbers = st.sampled_from([
    0, -1, 1, 2**63 - 1, 2**63, -(2**63), -(2**63) - 1, 10**20, 1e-300, 1e300, -1e300,
    1e7, 1e-12, 0.0, -0.0, 3.0, 1e4 + 1, 1e6,
])


def _mutations(kind):
    base = EXAMPLES[kind]
    field = st.sampled_from([*base, "extra"])
    value = json_values | edgy_numbers | st.just(...)
    return st.lists(st.tuples(field, value), min_size=1, max_size=3).map(
        lambda changes: _apply(base, changes))


def _apply(base: dict, changes) -> dict:
    d = dict(base)
    for k, v in changes:
        if v is ...:
            d.pop(k, None)
        else:
            d[k] = v
    return d


@FUZZ
@given(kind=st.sampled_from(list(EXAMPLES)), data=st.binary(max_size=400))
def test_decoders_never_raise_anything_but_decode_error_on_bytes(kind, data):
    try:
        msg = M.decoder(kind)(data)
    except M.DecodeError as exc:
        assert exc.reason in ("json", "schema")
        return
    assert type(msg) is kind


@FUZZ
@given(data=st.data())
def test_decoder_accepts_exactly_what_the_schema_accepts(data):
    """On mutated valid messages the decoder and the checked-in JSON Schema agree."""
    kind = data.draw(st.sampled_from(list(EXAMPLES)))
    doc = data.draw(_mutations(kind))
    raw = json.dumps(doc).encode()
    validator = _validator(M.schema_filename(kind))
    valid = validator.is_valid(doc)
    try:
        msg = M.decoder(kind)(raw)
    except M.DecodeError as exc:
        assert exc.reason == "schema"
        # one known difference: JSON Schema's "integer" includes 1.0, the decoder wants an
        # integer literal for times and counters (a float loses ns precision beyond 2**53)
        assert not valid or _has_integral_float(doc), (doc, exc.detail)
        return
    assert valid, doc
    # and what was accepted encodes back to a schema-valid document
    validator.validate(json.loads(M.encode(msg)))


@functools.cache
def _validator(filename: str) -> jsonschema.Draft202012Validator:
    """The checked-in schema's validator, built once (the schema itself checked once)."""
    schema = json.loads((SCHEMAS / filename).read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _has_integral_float(obj) -> bool:
    if isinstance(obj, float):
        return obj.is_integer()
    if isinstance(obj, dict):
        return any(_has_integral_float(v) for v in obj.values())
    if isinstance(obj, list):
        return any(_has_integral_float(v) for v in obj)
    return False


def _cfg(**kw) -> FusionConfig:
    return build_config(FusionConfig, dict(site="t", window_height_m=1.5, edge_x_m=(-20, 20),
                                           **kw))


samples = st.one_of(
    st.tuples(st.sampled_from(list(KEY_OF)), st.none()).flatmap(
        lambda t: _mutations(t[0]).map(lambda d: (KEY_OF[t[0]], json.dumps(d).encode()))),
    st.tuples(st.sampled_from(list(KEY_OF.values())), st.binary(max_size=200)),
    st.tuples(st.text(max_size=40), st.binary(max_size=50)),
    st.sampled_from(list(KEY_OF)).map(lambda k: (KEY_OF[k], json.dumps(EXAMPLES[k]).encode())),
)


@FUZZ
@given(stream=st.lists(st.tuples(samples, st.integers(0, 10**10)), max_size=30))
def test_fusion_input_path_never_raises_and_counts_add_up(stream):
    core = FusionCore(_cfg())
    for (key, payload), wall in stream:
        core.on_sample(key, payload, wall)
        core.on_liveliness("uav1", wall % 3 != 0, wall)
    out = core.step(10**15)
    dec = M.decoder(M.PositionEstimate)
    for est in out:
        assert dec(M.encode(est)) == est
    d = core.diagnostics(0)
    assert M.decoder(M.FusionDiagnostics)(M.encode(d)) == d
    # without batches (whose entries are counted one by one) every sample is received once
    # and then either used or rejected once ("late" counts used ranges of solved epochs)
    if not any(k.endswith("/ranges") for (k, _), _ in stream):
        assert sum(d.received.values()) == len(stream)
        used = sum(a.states + a.ranges for a in core.anchors.values())
        rejected = sum(v for k, v in d.rejected.items() if k != "late")
        assert used + rejected == len(stream), (d.received, d.rejected)


@settings(FUZZ, max_examples=20)
@given(data=st.data())
def test_fusion_good_stream_survives_any_interleaved_garbage(data):
    """Random garbage between the messages of a clean 6-epoch stream leaves its estimates
    unchanged (the garbage never uses the good stream's sequence numbers)."""
    from test_bad_input import assert_same_estimates, good_stream, run_stream

    epochs = good_stream(6)
    garbage = data.draw(st.lists(st.tuples(st.integers(1, 5), samples), max_size=12))
    extra: dict[int, list] = {}
    for e, (key, payload) in garbage:
        extra.setdefault(e, []).append((key, _reseq(payload)))
    ref = run_stream(FusionCore(_cfg()), epochs)
    got = run_stream(FusionCore(_cfg(anchors=["uav1", "uav2", "uav3", "uav4", "uav5"],
                                     nodes=["n01", "n02", "n03"])), epochs, extra)
    assert_same_estimates(got, ref)


def _reseq(payload: bytes) -> bytes:
    """Garbage that decodes must not be a *valid* message for the stream's nodes: give it an
    absurd range so it is rejected whatever its other fields are."""
    try:
        d = json.loads(payload)
    except (ValueError, RecursionError):
        return payload
    if isinstance(d, dict):
        d["range_m"] = 1e9
        d["position_m"] = [1e9, 0, 0]
        return json.dumps(d).encode()
    return payload


PROBLEM = {"anchors_m": [[-15, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]],
           "ranges_m": [32.233, 23.711, 15.058, 30.315], "sigmas_m": 0.005,
           "window_height_m": 1.0}


@settings(FUZZ, max_examples=50)
@given(changes=st.lists(st.tuples(st.sampled_from([*PROBLEM, "method", "gating", "loss", "x0_m",
                                                    "z_starts_m", "nlos", "nlos_bias_m",
                                                    "delta_m", "edge_x_m", "id"]),
                                  json_values | edgy_numbers), max_size=3))
def test_solve_records_always_valid_json_results(changes):
    prob = _apply(PROBLEM, changes)
    (rec,) = solve_records([prob])
    text = json.dumps(rec, allow_nan=False)
    _validator("solve_result.v1.json").validate(json.loads(text))
    if rec["status"] == "invalid_input":
        assert rec["message"]
    elif rec["position_m"] is not None:
        assert all(v is None or math.isfinite(v) for v in rec["position_m"])
    if rec["status"] not in ("ok", "ok_unverified"):  # no trustworthy position: none published
        assert rec["position_m"] is None and rec["peb_m"] is None


@FUZZ
@given(data=st.binary(max_size=300), limit=st.integers(16, 64))
def test_solve_reader_and_filter_on_arbitrary_bytes(data, limit):
    import io

    good = json.dumps(PROBLEM).encode() + b"\n"
    stream = io.BytesIO(good + data + b"\n" + good)
    max_bytes = max(limit, len(good))
    recs = list(solve_lines(read_lines(stream, max_bytes=max_bytes), batch=4))
    assert recs[0]["status"] in ("ok", "ok_unverified")
    assert recs[-1]["status"] in ("ok", "ok_unverified")
    for r in recs:
        json.dumps(r, allow_nan=False)
    # one result per line that is not blank (too long or not UTF-8 counts as not blank)
    pieces = (good + data + b"\n" + good).split(b"\n")[:-1]

    def answered(p: bytes) -> bool:
        if len(p) > max_bytes:
            return True
        try:
            return bool(p.decode("utf-8").strip())
        except UnicodeDecodeError:
            return True

    want = [n for n, p in enumerate(pieces, start=1) if answered(p)]
    assert [r["line"] for r in recs] == want
