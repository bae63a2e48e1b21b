"""Position fixes from JSON Lines problems on stdin (D-NLS, LLS, IPPA)

A filter: reads one positioning problem per line (JSON object) from stdin or --input, writes
one result per line (JSON object) to stdout, in the same order. Problems are solved in
batches (--batch lines at a time) with the vectorised estimators of diffpos.estimators.

Coordinates (building frame): the facade with the windows is the plane y = 0, the inside is
y > 0, anchors are outside (y < 0), x runs along the window edges, z is up. SI units.

Problem fields (JSON Schema: schemas/solve_problem.v1.json):
  anchors_m        [[x, y, z], ...]   anchor positions [m], at least 3
  ranges_m         [r, ...]           measured ranges [m], one per anchor; null = not measured
  sigmas_m         s or [s, ...]      ranging standard deviations [m] (optional; without them
                                      the residual test is skipped and the covariance is
                                      scaled by the a-posteriori variance factor)
  window_height_m  w                  window height [m] (required for dnls)
  edge_x_m         [x1, x2]           extent of the window edges along x [m] (default unbounded)
  delta_m          d                  Case-2 offset of the node below mid-window [m] (default 0)
  method           "dnls" | "lls" | "ippa"   (default dnls, or --method)
  gating           true | false | {"false_alarm_probability": 1e-3, "max_exclusions": 2,
                                      "pregate": true, "multistart_exclusion": true,
                                      "z_range_m": [0, 1e9] or null}   (dnls only; default true;
                                      a fix outside z_range_m is gating_failed)
  loss             "linear" | "huber" | "soft_l1"   (dnls only; default linear)
  x0_m             [x, y, z]          one start instead of the floor grid (dnls, ippa)
  z_starts_m       [z, ...]           start heights (default every 3 m from 0 to 30 m)
  nlos             bool or [bool,...] IPPA NLoS flags (default all true)
  nlos_bias_m      b or [b, ...]      IPPA mean NLoS bias subtracted from the ranges [m]
  id               any JSON value     echoed back unchanged

Result fields (JSON Schema: schemas/solve_result.v1.json): line, id, status (ok,
ok_unverified, not_converged, not_identifiable, too_few_anchors, gating_failed,
invalid_input), message, method, position_m, covariance_m2 (3x3, the inverse FIM at the
estimate; covariance_model says which model), peb_m, z_bound_m, iterations, converged,
used_anchors, excluded_anchors ([{"index", "reason"}]), residuals_m (null where unused),
test_statistic, test_threshold. Numbers that do not exist are null.

A bad line (invalid JSON, wrong lengths, NaN/inf, negative range, fewer than 3 anchors, unknown
field, a value beyond the limits below, a line longer than --max-line-bytes, JSON nested too
deeply, bytes that are not UTF-8) gives a result with status "invalid_input" and a message
naming the field; the filter keeps going with the next line. Limits: at most 1024 anchors and
1000 z_starts_m per problem, |coordinates|, ranges, sigmas and lengths at most 1e7 m, an id
of at most 1000 characters of JSON. The exit status is 0 unless --strict is given and some
line was invalid (1), or the input cannot be read (2).

examples:
  echo '{"anchors_m": [[-15,-20,1],[0,-15,0],[0,-7,4],[15,-20,1]],
         "ranges_m": [32.233, 23.711, 15.058, 30.315], "sigmas_m": 0.005, "window_height_m": 1.0}' \\
    | tr -d '\\n' | diffpos solve
  diffpos solve --input problems.jsonl > fixes.jsonl
  diffpos solve --method lls --strict < problems.jsonl
  diffpos solve --batch 1 < fifo         answer each line as soon as it arrives

From Python: diffpos_services.cli.solve.solve_records(list_of_problem_dicts) returns the
result dicts; diffpos.estimators.dnls / lls / ippa work on numpy arrays directly.
"""

from __future__ import annotations

import argparse
import difflib
import itertools
import json
import math
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, BinaryIO, TextIO

import numpy as np

__all__ = ["ProblemError", "parse_problem", "read_lines", "solve_lines", "solve_records"]

#: Limits of one problem (bad input must not exhaust memory or time).
MAX_ANCHORS = 1024
MAX_Z_STARTS = 1000
MAX_ABS_M = 1e7
MAX_ID_CHARS = 1000
MAX_LINE_BYTES = 1 << 20

FIELDS = (
    "anchors_m", "ranges_m", "sigmas_m", "window_height_m", "edge_x_m", "delta_m", "method",
    "gating", "loss", "x0_m", "z_starts_m", "nlos", "nlos_bias_m", "id",
)
METHODS = ("dnls", "lls", "ippa")
LOSSES = ("linear", "huber", "soft_l1")
GATING_FIELDS = (
    "false_alarm_probability", "max_exclusions", "pregate", "multistart_exclusion", "z_range_m",
)

RESULT_KEYS = (
    "line", "id", "status", "message", "method", "position_m", "covariance_m2",
    "covariance_model", "peb_m", "z_bound_m", "iterations", "converged", "used_anchors",
    "excluded_anchors", "residuals_m", "test_statistic", "test_threshold",
)


class ProblemError(ValueError):
    """A problem line is malformed; the message names the field and what to fix."""


@dataclass
class Problem:
    """A validated problem (internal)."""

    anchors_m: np.ndarray  # (M, 3)
    ranges_m: np.ndarray  # (M,)
    mask: np.ndarray  # (M,)
    sigmas_m: np.ndarray | None  # (M,)
    method: str
    window_height_m: float | None
    delta_m: float
    edge_x_m: tuple[float, float] | None
    gating: dict[str, Any] | None
    loss: str
    x0_m: np.ndarray | None
    z_starts_m: tuple[float, ...] | None
    nlos: np.ndarray
    nlos_bias_m: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)

    def group_key(self) -> tuple:
        """Problems with equal keys are solved in one batched call."""
        g = None if self.gating is None else tuple(sorted(self.gating.items()))
        return (
            self.method, self.ranges_m.size, self.edge_x_m, g, self.loss, self.z_starts_m,
            self.sigmas_m is None, self.x0_m is None,
        )


def _number(value: Any, name: str, *, positive: bool = False, nonneg: bool = False,
            limit: float | None = MAX_ABS_M) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ProblemError(f"{name} must be a number, got {_short(value)}")
    try:
        v = float(value)
    except OverflowError:  # an integer beyond the float range
        v = math.inf
    if not math.isfinite(v):
        raise ProblemError(f"{name} must be finite, got {_short(value)}")
    if limit is not None and abs(v) > limit:
        raise ProblemError(f"{name} = {v:g} is out of range (allowed [-{limit:g}, {limit:g}])")
    if positive and v <= 0:
        raise ProblemError(f"{name} must be > 0, got {value}")
    if nonneg and v < 0:
        raise ProblemError(f"{name} must be >= 0, got {value}")
    return v


def _short(value: Any) -> str:
    """JSON text of a value, cut to 40 characters (messages stay one short line)."""
    try:
        text = json.dumps(value)
    except (ValueError, TypeError, RecursionError):
        text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _vector(value: Any, name: str, length: int | None = None, *, allow_null: bool = False,
            max_length: int | None = None):
    if not isinstance(value, list):
        raise ProblemError(f"{name} must be a list, got {_short(value)}")
    if max_length is not None and len(value) > max_length:
        raise ProblemError(f"{name} has {len(value)} entries; at most {max_length} are allowed")
    if length is not None and len(value) != length:
        raise ProblemError(f"{name} must have {length} entries (one per anchor), got {len(value)}")
    out = []
    for k, v in enumerate(value):
        if v is None and allow_null:
            out.append(math.nan)
        else:
            out.append(_number(v, f"{name}[{k}]"))
    return out


def parse_problem(obj: Any, *, default_method: str = "dnls") -> Problem:
    """Validate one decoded JSON problem; raise :class:`ProblemError` naming the field."""
    if not isinstance(obj, dict):
        raise ProblemError(f"a problem must be a JSON object, got {type(obj).__name__}")
    for key in obj:
        if key not in FIELDS:
            hint = difflib.get_close_matches(key, FIELDS, n=1)
            raise ProblemError(
                f"unknown field {key!r}" + (f" (did you mean {hint[0]!r}?)" if hint else "")
            )
    if "anchors_m" not in obj:
        raise ProblemError("anchors_m is required: a list of [x, y, z] anchor positions [m]")
    if "ranges_m" not in obj:
        raise ProblemError("ranges_m is required: a list of measured ranges [m], one per anchor")
    anchors = obj["anchors_m"]
    if not isinstance(anchors, list) or not anchors:
        raise ProblemError("anchors_m must be a non-empty list of [x, y, z] positions [m]")
    if len(anchors) > MAX_ANCHORS:
        raise ProblemError(f"anchors_m has {len(anchors)} anchors; at most {MAX_ANCHORS} are "
                           "allowed")
    a = np.array(
        [_vector(p, f"anchors_m[{k}]", 3) for k, p in enumerate(anchors)], dtype=np.float64
    )
    m = a.shape[0]
    r = np.array(_vector(obj["ranges_m"], "ranges_m", m, allow_null=True))
    mask = np.isfinite(r)
    if np.any(r[mask] < 0):
        k = int(np.flatnonzero(mask & (r < 0))[0])
        raise ProblemError(f"ranges_m[{k}] is negative ({r[k]}); ranges must be >= 0 [m]")
    if mask.sum() < 3:
        raise ProblemError(
            f"fewer than 3 anchors with a range ({int(mask.sum())}); a 3D fix needs >= 3 "
            "(anchors_m / ranges_m)"
        )
    sig = None
    if obj.get("sigmas_m") is not None:
        sv = obj["sigmas_m"]
        if isinstance(sv, list):
            sig = np.array(_vector(sv, "sigmas_m", m, allow_null=True))
        else:
            sig = np.full(m, _number(sv, "sigmas_m"))
        bad = mask & ~(np.isfinite(sig) & (sig > 0))
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            raise ProblemError(f"sigmas_m[{k}] must be a number > 0 where a range is given")
        sig = np.where(mask, sig, 1.0)
    method = obj.get("method", default_method)
    if method not in METHODS:
        raise ProblemError(f"method must be one of {list(METHODS)}, got {json.dumps(method)}")
    wh = obj.get("window_height_m")
    if wh is not None:
        wh = _number(wh, "window_height_m", positive=True)
    elif method == "dnls":
        raise ProblemError("window_height_m is required for method dnls (window height w [m])")
    delta = _number(obj.get("delta_m", 0.0), "delta_m")
    edge = obj.get("edge_x_m")
    if edge is not None:
        ev = _vector(edge, "edge_x_m", 2)
        if ev[0] == ev[1]:
            raise ProblemError("edge_x_m must be two different x values [x1, x2] [m]")
        edge = (min(ev), max(ev))
    gating = _parse_gating(obj.get("gating", True))
    loss = obj.get("loss", "linear")
    if loss not in LOSSES:
        raise ProblemError(f"loss must be one of {list(LOSSES)}, got {json.dumps(loss)}")
    x0 = obj.get("x0_m")
    if x0 is not None:
        x0 = np.array(_vector(x0, "x0_m", 3))
    zs = obj.get("z_starts_m")
    if zs is not None:
        zs = tuple(_vector(zs, "z_starts_m", max_length=MAX_Z_STARTS))
        if not zs:
            raise ProblemError("z_starts_m must not be empty")
    nl = obj.get("nlos", True)
    if isinstance(nl, bool):
        nlos = np.full(m, nl)
    elif isinstance(nl, list) and len(nl) == m and all(isinstance(v, bool) for v in nl):
        nlos = np.array(nl)
    else:
        raise ProblemError(f"nlos must be true, false or a list of {m} booleans")
    nb = obj.get("nlos_bias_m", 0.0)
    if isinstance(nb, list):
        bias = np.array(_vector(nb, "nlos_bias_m", m))
    else:
        bias = np.full(m, _number(nb, "nlos_bias_m"))
    return Problem(
        anchors_m=a, ranges_m=np.where(mask, r, 0.0), mask=mask, sigmas_m=sig, method=method,
        window_height_m=wh, delta_m=delta, edge_x_m=edge, gating=gating, loss=loss, x0_m=x0,
        z_starts_m=zs, nlos=nlos, nlos_bias_m=bias,
    )


def _parse_gating(value: Any) -> dict[str, Any] | None:
    """The ``gating`` field: ``None`` (off), ``{}`` (defaults) or the validated settings."""
    if value is True:
        return {}
    if value is False or value is None:
        return None
    if not isinstance(value, dict):
        raise ProblemError("gating must be true, false or an object of gating settings")
    gating: dict[str, Any] = {}
    for k, v in value.items():
        if k not in GATING_FIELDS:
            raise ProblemError(f"gating.{k} is not a gating setting; use {list(GATING_FIELDS)}")
        if k in ("pregate", "multistart_exclusion"):
            if not isinstance(v, bool):
                raise ProblemError(f"gating.{k} must be true or false")
            gating[k] = v
        elif k == "z_range_m":
            if v is None:
                gating[k] = None
                continue
            if not isinstance(v, list) or len(v) != 2:
                raise ProblemError("gating.z_range_m must be null or [z_min, z_max] in metres")
            lo = _number(v[0], "gating.z_range_m[0]", limit=None)
            hi = _number(v[1], "gating.z_range_m[1]", limit=None)
            if not lo < hi:
                raise ProblemError("gating.z_range_m must have z_min < z_max")
            gating[k] = (lo, hi)
        elif k == "max_exclusions":
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_ANCHORS:
                raise ProblemError(f"gating.max_exclusions must be an integer in "
                                   f"[0, {MAX_ANCHORS}]")
            gating[k] = v
        else:
            p = _number(v, "gating.false_alarm_probability", limit=None)
            if not 0 < p < 1:
                raise ProblemError("gating.false_alarm_probability must be in (0, 1)")
            gating[k] = p
    return gating


def _invalid_record(message: str) -> dict[str, Any]:
    rec: dict[str, Any] = dict.fromkeys(RESULT_KEYS)
    rec.update(status="invalid_input", message=message, iterations=0, converged=False,
               used_anchors=[], excluded_anchors=[])
    return rec


def _solve_group(problems: list[Problem]) -> list[dict[str, Any]]:
    from diffpos.estimators import GatingConfig, dnls, ippa, lls

    p0 = problems[0]
    a = np.stack([p.anchors_m for p in problems])
    r = np.stack([p.ranges_m for p in problems])
    mask = np.stack([p.mask for p in problems])
    sig = None if p0.sigmas_m is None else np.stack([p.sigmas_m for p in problems])
    x0 = None if p0.x0_m is None else np.stack([p.x0_m for p in problems])
    if p0.method == "dnls":
        gating = None if p0.gating is None else GatingConfig(**p0.gating)
        fix = dnls(
            a, r, sig, mask=mask,
            window_height_m=np.array([p.window_height_m for p in problems]),
            delta_m=np.array([p.delta_m for p in problems]),
            edge_x_m=p0.edge_x_m, gating=gating, loss=p0.loss, x0_m=x0,
            z_starts_m=p0.z_starts_m,
        )
    elif p0.method == "lls":
        fix = lls(a, r, sig, mask=mask)
    else:
        fix = ippa(
            a, r, sig, mask=mask, nlos=np.stack([p.nlos for p in problems]),
            nlos_bias_m=np.stack([p.nlos_bias_m for p in problems]), x0_m=x0,
            z_starts_m=p0.z_starts_m,
        )
    return fix.to_records()


def solve_records(
    problems: Iterable[Any], *, default_method: str = "dnls", first_line: int = 1
) -> list[dict[str, Any]]:
    """Solve decoded problems (dicts, or :class:`ProblemError` instances for lines that
    failed to decode); return one JSON-ready result dict per problem, in order."""
    items = list(problems)
    out: list[dict[str, Any] | None] = [None] * len(items)
    groups: dict[tuple, list[tuple[int, Problem]]] = {}
    ids: list[Any] = [None] * len(items)
    for k, obj in enumerate(items):
        try:
            if isinstance(obj, ProblemError):
                raise obj
            if isinstance(obj, dict) and obj.get("id") is not None:
                ids[k] = _check_id(obj["id"])
            prob = parse_problem(obj, default_method=default_method)
        except ProblemError as exc:
            out[k] = _invalid_record(str(exc))
            continue
        groups.setdefault(prob.group_key(), []).append((k, prob))
    for members in groups.values():
        try:
            recs = _solve_group([p for _, p in members])
        except Exception:  # isolate the problem that broke the batch
            recs = [_solve_alone(p) for _, p in members]
        for (k, _), rec in zip(members, recs, strict=True):
            out[k] = rec
    final = []
    for k, rec in enumerate(out):
        assert rec is not None
        rec = {key: rec.get(key) for key in RESULT_KEYS}
        rec["line"] = first_line + k
        rec["id"] = ids[k]
        final.append(rec)
    return final


def _check_id(value: Any) -> Any:
    """The id if it can be echoed as plain JSON (no NaN/Infinity) of bounded size."""
    try:
        text = json.dumps(value, allow_nan=False)
    except (ValueError, TypeError, RecursionError):
        raise ProblemError("id must be plain JSON without NaN or Infinity") from None
    if len(text) > MAX_ID_CHARS:
        raise ProblemError(f"id is {len(text)} characters of JSON; at most {MAX_ID_CHARS} "
                           "are allowed")
    return value


def _solve_alone(prob: Problem) -> dict[str, Any]:
    try:
        return _solve_group([prob])[0]
    except Exception as exc:  # reported on this line; the filter goes on
        return _invalid_record(f"the solver failed on this problem ({type(exc).__name__}: "
                               f"{str(exc)[:200]}); check the values for plausibility")


def _decode(line: str | ProblemError) -> Any:
    if isinstance(line, ProblemError):
        return line
    try:
        return json.loads(line)
    except json.JSONDecodeError as exc:
        return ProblemError(f"invalid JSON: {exc.msg} at column {exc.colno}")
    except RecursionError:
        return ProblemError("invalid JSON: nested too deeply")
    except ValueError as exc:  # e.g. an integer literal with more than 4300 digits
        return ProblemError(f"invalid JSON: {str(exc)[:120]}")


def solve_lines(lines: Iterable[str | ProblemError], *, batch: int = 256,
                default_method: str = "dnls") -> Iterator[dict[str, Any]]:
    """Solve JSON Lines (blank lines skipped, but counted in ``line``), yielding results.

    Items may be :class:`ProblemError` instances for lines that could not be read (too
    long, not UTF-8, see :func:`read_lines`): they are answered with ``invalid_input``.
    """
    numbered = ((n, ln) for n, ln in enumerate(lines, start=1)
                if isinstance(ln, ProblemError) or ln.strip())
    while True:
        chunk = list(itertools.islice(numbered, max(batch, 1)))
        if not chunk:
            return
        # results are numbered by input line even across blank lines
        for (n, _), rec in zip(
            chunk,
            solve_records([_decode(ln) for _, ln in chunk], default_method=default_method),
            strict=True,
        ):
            rec["line"] = n
            yield rec


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--input", "-i", metavar="FILE",
                        help="read problems from FILE instead of stdin ('-' = stdin)")
    parser.add_argument("--method", choices=METHODS, default="dnls",
                        help="method for problems without a 'method' field (default dnls)")
    parser.add_argument("--batch", type=int, default=256, metavar="N",
                        help="solve N lines together (default 256; 1 = answer every line "
                        "as soon as it is read)")
    parser.add_argument("--strict", action="store_true",
                        help="exit with status 1 if any line was invalid (all lines are "
                        "still answered)")
    parser.add_argument("--max-line-bytes", type=int, default=MAX_LINE_BYTES, metavar="N",
                        help=f"longer lines are answered with invalid_input without being "
                        f"held in memory (default {MAX_LINE_BYTES})")


def read_lines(stream: BinaryIO | TextIO, *, max_bytes: int = MAX_LINE_BYTES
               ) -> Iterator[str | ProblemError]:
    """Lines of a byte (or text) stream as ``str``, or :class:`ProblemError` for a line that
    is longer than ``max_bytes`` (skipped in bounded memory) or not UTF-8.

    ``readline`` rather than iteration, so ``--batch 1`` answers interactively.
    """
    chunk = max(int(max_bytes), 1) + 1
    while True:
        line = stream.readline(chunk)
        if not line:
            return
        nl = b"\n" if isinstance(line, bytes) else "\n"
        if len(line) >= chunk and not line.endswith(nl):
            size = len(line)
            while line and not line.endswith(nl):  # drain the rest of the line
                line = stream.readline(1 << 16)
                size += len(line)
            yield ProblemError(f"line is longer than --max-line-bytes={max_bytes} "
                               f"({size} bytes or more); split the problem or raise the limit")
            continue
        if isinstance(line, bytes):
            try:
                yield line.decode("utf-8")
            except UnicodeDecodeError as exc:
                yield ProblemError(f"line is not UTF-8 text (byte 0x{line[exc.start]:02x} at "
                                   f"column {exc.start + 1}); encode the input as UTF-8")
        else:
            yield line


def run(args: argparse.Namespace) -> int:
    if args.batch < 1:
        print("diffpos solve: --batch must be >= 1", file=sys.stderr)
        return 2
    if args.max_line_bytes < 16:
        print("diffpos solve: --max-line-bytes must be >= 16", file=sys.stderr)
        return 2
    if args.input and args.input != "-":
        try:
            stream: BinaryIO | TextIO = open(args.input, "rb")
        except OSError as exc:
            print(f"diffpos solve: cannot read --input {args.input}: {exc.strerror}",
                  file=sys.stderr)
            return 2
    else:
        # bytes, so that a non-UTF-8 line is one invalid line, not the end of the input
        stream = getattr(sys.stdin, "buffer", sys.stdin)
    invalid = 0
    out = sys.stdout
    try:
        for rec in solve_lines(read_lines(stream, max_bytes=args.max_line_bytes),
                               batch=args.batch, default_method=args.method):
            if rec["status"] == "invalid_input":
                invalid += 1
            out.write(json.dumps(rec, allow_nan=False, separators=(",", ":")) + "\n")
            if args.batch == 1:
                out.flush()
        out.flush()
    except OSError as exc:
        if isinstance(exc, BrokenPipeError):
            return 0
        print(f"diffpos solve: cannot read the input ({exc.strerror or exc})", file=sys.stderr)
        return 2
    finally:
        if args.input and args.input != "-":
            stream.close()
    if invalid:
        print(f"diffpos solve: {invalid} invalid line(s)", file=sys.stderr)
    return 1 if (args.strict and invalid) else 0
