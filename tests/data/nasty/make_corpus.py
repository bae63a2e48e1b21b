"""Regenerate the nasty-message corpus (the files are committed; this documents their origin).

    python tests/data/nasty/make_corpus.py

Every case is one file: ``fusion/*.bin`` is a raw payload for the fusion (its key and the
expected rejection reason are in README.md, which this script also writes), ``solve/*.txt``
is one input line for ``diffpos solve`` (expected: ``invalid_input`` with the message part
given in README.md). The good stream the fusion cases are mixed into is built by
``tests/test_bad_input.py`` (site ``t``, anchors uav1..uav5, nodes n01..n03, epoch 0.1 s,
times from 0): corpus times are 250 ms, inside that stream.
"""

from __future__ import annotations

import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
T = 250_000_000  # [ns] inside the test stream (after epoch 2)

RANGE = {"schema": "diffpos.range.v1", "anchor_id": "uav1", "node_id": "n01", "t_ns": T,
         "seq": 900_001, "range_m": 25.0, "sigma_m": 0.05, "snr_db": 20.0,
         "t_pub_wall_ns": 1}
STATE = {"schema": "diffpos.anchor_state.v1", "anchor_id": "uav1", "t_ns": T, "seq": 900_002,
         "position_m": [-15.0, -20.0, 1.0], "velocity_m_s": [0.0, 0.0, 0.0],
         "position_sigma_m": [0.01, 0.01, 0.01], "velocity_sigma_m_s": 0.0,
         "range_rate_hz": 10.0, "t_pub_wall_ns": 1}
BATCH = {"schema": "diffpos.range_batch.v1", "anchor_id": "uav1", "t_ns": T, "seq": 900_003,
         "node_ids": ["n01", "n02"], "range_m": [25.0, 30.0], "sigma_m": [0.05, 0.05],
         "snr_db": [20.0, 20.0], "t_pub_wall_ns": 1}
KR = "diffpos/t/anchor/uav1/range/n01"
KS = "diffpos/t/anchor/uav1/state"
KB = "diffpos/t/anchor/uav1/ranges"


def js(obj, **changes) -> bytes:
    d = dict(obj)
    for k, v in changes.items():
        if v is ...:
            d.pop(k)
        else:
            d[k] = v
    return json.dumps(d).encode()


def raw_replace(obj, field: str, literal: str) -> bytes:
    """JSON text with one field's value replaced by a literal (NaN, 1e999: not JSON)."""
    d = dict(obj, **{field: "@@"})
    return json.dumps(d).replace('"@@"', literal).encode()


# (file, key, expected reason, what)
FUSION = [
    ("f01-not-json.bin", KR, "json", "truncated JSON", b'{"schema": "diffpos.range.v1", "anc'),
    ("f02-not-utf8.bin", KR, "json", "bytes that are not UTF-8", b"\xff\xfe\x00\x80garbage"),
    ("f03-empty.bin", KR, "json", "empty payload", b""),
    ("f04-deep-nesting.bin", KR, "json", "valid range plus an unknown field nested 1500 deep",
     js(RANGE)[:-1] + b', "x": ' + b"[" * 1500 + b"]" * 1500 + b"}"),
    ("f05-wrong-version.bin", KR, "schema", "schema diffpos.range.v2",
     js(RANGE, schema="diffpos.range.v2")),
    ("f06-no-schema-tag.bin", KR, "schema", "no schema field", js(RANGE, schema=...)),
    ("f07-missing-field.bin", KR, "schema", "sigma_m missing", js(RANGE, sigma_m=...)),
    ("f08-seq-is-string.bin", KR, "schema", "seq is a string", js(RANGE, seq="7")),
    ("f09-range-is-bool.bin", KR, "schema", "range_m is true", js(RANGE, range_m=True)),
    ("f10-nan-literal.bin", KR, "json", "range_m NaN (not JSON)",
     raw_replace(RANGE, "range_m", "NaN")),
    ("f11-inf-number.bin", KR, "schema", "range_m 1e999 (overflows to inf)",
     raw_replace(RANGE, "range_m", "1e999")),
    ("f12-negative-range.bin", KR, "schema", "range_m -3", js(RANGE, range_m=-3.0)),
    ("f13-absurd-range.bin", KR, "absurd_value", "range_m 1e7 m (> max_range_m)",
     js(RANGE, range_m=1e7)),
    ("f14-zero-sigma.bin", KR, "schema", "sigma_m 0", js(RANGE, sigma_m=0.0)),
    ("f15-tiny-sigma.bin", KR, "absurd_value", "sigma_m 1e-12 m (< min_sigma_m)",
     js(RANGE, sigma_m=1e-12)),
    ("f16-huge-sigma.bin", KR, "absurd_value", "sigma_m 1e9 m", js(RANGE, sigma_m=1e9)),
    ("f17-absurd-snr.bin", KR, "absurd_value", "snr_db 1e6", js(RANGE, snr_db=1e6)),
    ("f18-bad-id-grammar.bin", KR, "schema", "anchor_id 'uav 1' (space)",
     js(RANGE, anchor_id="uav 1")),
    ("f19-key-mismatch.bin", KR, "key_mismatch", "payload says uav2, key says uav1",
     js(RANGE, anchor_id="uav2")),
    ("f20-int64-overflow.bin", KR, "schema", "t_ns 10**20 (beyond int64)",
     js(RANGE, t_ns=10**20)),
    ("f21-far-future.bin", KR, "time_future", "t_ns one hour after the stream",
     js(RANGE, t_ns=T + 3600 * 10**9)),
    ("f22-far-past.bin", KR, "time_past", "t_ns one hour before the stream",
     js(RANGE, t_ns=T - 3600 * 10**9)),
    ("f23-duplicate-seq.bin", KS, "duplicate_seq",
     "state of uav1 reusing seq 1 (its first state) with another position",
     js(STATE, seq=1, position_m=[-14.0, -20.0, 1.0], t_ns=0)),
    ("f24-unknown-anchor.bin", "diffpos/t/anchor/evil/range/n01", "unknown_anchor",
     "valid range from an anchor outside the allow-list", js(RANGE, anchor_id="evil")),
    ("f25-unknown-node.bin", "diffpos/t/anchor/uav1/range/ghost", "unknown_node",
     "valid range to a node outside the allow-list", js(RANGE, node_id="ghost")),
    ("f26-oversized.bin", KR, "oversized", "8 KiB payload (the test sets max_message_bytes=4096)",
     js(RANGE, pad="x" * 8192)),
    ("f27-batch-lengths.bin", KB, "schema", "range_batch lists of different lengths",
     js(BATCH, range_m=[25.0])),
    ("f28-batch-duplicate-nodes.bin", KB, "schema", "range_batch naming n01 twice",
     js(BATCH, node_ids=["n01", "n01"])),
    ("f29-state-absurd-position.bin", KS, "absurd_value", "anchor 1e9 m away",
     js(STATE, position_m=[1e9, -20.0, 1.0])),
    ("f30-state-nan-velocity.bin", KS, "json", "velocity NaN (not JSON)",
     raw_replace(STATE, "velocity_m_s", "[0, NaN, 0]")),
    ("f31-state-too-fast.bin", KS, "absurd_value", "anchor at 1e5 m/s",
     js(STATE, velocity_m_s=[1e5, 0.0, 0.0])),
    ("f32-unexpected-key.bin", "diffpos/t/anchor/uav1/bogus", "unexpected_key",
     "a key the fusion does not read", js(RANGE)),
    ("f33-other-site.bin", "diffpos/other/anchor/uav1/range/n01", "unexpected_key",
     "a key of another site", js(RANGE)),
    ("f34-top-level-array.bin", KR, "schema", "a JSON array", b"[1, 2, 3]"),
    ("f35-state-on-range-key.bin", KR, "schema", "an anchor state on a range key", js(STATE)),
    ("f36-huge-integer.bin", KR, "schema", "seq with 3000 digits",
     raw_replace(RANGE, "seq", "9" * 3000)),
]

GOOD_PROBLEM = {"anchors_m": [[-15, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]],
                "ranges_m": [32.233, 23.711, 15.058, 30.315], "sigmas_m": 0.005,
                "window_height_m": 1.0}


def line(obj) -> bytes:
    return json.dumps(obj).encode() + b"\n"


def problem(**changes) -> bytes:
    return line(dict(GOOD_PROBLEM, **changes))


# (file, expected message part, what); the test runs with --max-line-bytes 65536
SOLVE = [
    ("s01-not-json.txt", "invalid JSON", "truncated JSON", b'{"anchors_m": [[1, 2\n'),
    ("s02-not-utf8.txt", "not UTF-8", "Latin-1 bytes", b'{"id": "caf\xe9"}\n'),
    ("s03-deep-nesting.txt", "nested too deeply", "1500 nested arrays",
     b"[" * 1500 + b"]" * 1500 + b"\n"),
    ("s04-oversized-line.txt", "longer than --max-line-bytes", "a 70 kB line",
     problem(id="x" * 70000)),
    ("s05-huge-array.txt", "at most 1024", "2000 anchors",
     line(dict(GOOD_PROBLEM, anchors_m=[[0, -5, 1]] * 2000, ranges_m=[1.0] * 2000))),
    ("s06-huge-int.txt", "ranges_m[0] must be finite", "a 400-digit integer range",
     problem(ranges_m=[10**400, 23.711, 15.058, 30.315])),
    ("s07-int-too-long.txt", "invalid JSON", "a 4400-digit integer (Python's int limit)",
     b'{"ranges_m": [' + b"9" * 4400 + b"]}\n"),
    ("s08-nan-id.txt", "id must be plain JSON", "id NaN",
     raw_replace(GOOD_PROBLEM, "id", "NaN") + b"\n"),
    ("s09-absurd-coordinate.txt", "out of range", "an anchor 1e300 m away",
     problem(anchors_m=[[1e300, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]])),
    ("s10-bool-range.txt", "ranges_m[1] must be a number", "true as a range",
     problem(ranges_m=[32.233, True, 15.058, 30.315])),
    ("s11-string-height.txt", "window_height_m must be a number", "window height as text",
     problem(window_height_m="1.0")),
    ("s12-null-line.txt", "JSON object", "the line null", b"null\n"),
    ("s13-empty-object.txt", "anchors_m is required", "{}", b"{}\n"),
    ("s14-nested-anchor.txt", "anchors_m[0][0] must be a number", "an anchor coordinate that "
     "is a list", problem(anchors_m=[[[1], -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]])),
    ("s15-many-z-starts.txt", "at most 1000", "5000 start heights",
     problem(z_starts_m=[1.0] * 5000)),
    ("s16-nul-bytes.txt", "invalid JSON", "NUL bytes", b"\x00\x00\x00\n"),
    ("s17-infinity.txt", "must be finite", "Infinity as a sigma",
     raw_replace(GOOD_PROBLEM, "sigmas_m", "Infinity") + b"\n"),
]


def main() -> None:
    (HERE / "fusion").mkdir(exist_ok=True)
    (HERE / "solve").mkdir(exist_ok=True)
    rows = ["| file | key | expected reason | what |", "| --- | --- | --- | --- |"]
    for name, key, reason, what, data in FUSION:
        (HERE / "fusion" / name).write_bytes(data)
        rows.append(f"| `fusion/{name}` | `{key}` | `{reason}` | {what} |")
    srows = ["| file | expected message contains | what |", "| --- | --- | --- |"]
    for name, needle, what, data in SOLVE:
        (HERE / "solve" / name).write_bytes(data)
        srows.append(f"| `solve/{name}` | `{needle}` | {what} |")
    readme = f"""# Nasty messages (committed corpus)

One file per case. `tests/test_bad_input.py` checks every row: the fusion rejects each
`fusion/` payload on its key with the named reason (counted once in
`diagnostics.rejected`, nothing else changes, and the good stream around it gives the same
estimates as without it); `diffpos solve` answers each `solve/` line with `invalid_input` and a
message containing the given text, and still answers the good lines around it. The files are
written by `make_corpus.py` (run it after changing a case; the tables below are generated too).

The fusion cases are fed to a core with site `t`, anchors `uav1`..`uav5` (allow-list),
nodes `n01`..`n03` (allow-list), `max_message_bytes=4096`, in the middle of a good stream whose
times start at 0 (corpus times are 250 ms). What each reason means: `docs/bad_input.md`.

## Fusion payloads

{chr(10).join(rows)}

## `diffpos solve` lines (run with `--max-line-bytes 65536`)

{chr(10).join(srows)}
"""
    (HERE / "README.md").write_text(readme)


if __name__ == "__main__":
    main()
