"""The ``diffpos solve`` wire format: problem lines in, result records out.

One JSON object per line each way (JSON Schemas: ``schemas/solve_problem.v1.json`` and
``schemas/solve_result.v1.json``). :func:`parse_problem` validates a decoded problem in named
steps (fields, anchors and ranges, sigmas, method and model, gating, starts, IPPA options) and
raises :class:`ProblemError` naming the field; :func:`read_lines` and :func:`decode_line` turn
a byte stream into decoded problems, bounding a line's size; :func:`invalid_record` is the
result of a line that could not be solved.

The work of one line is bounded by :class:`Limits` (``--max-anchors``, ``--max-starts``,
``--max-line-bytes``): the solver's arrays for one problem grow with anchors^2 x starts
(the gating refits every leave-one-out subset from every start), so a single line with 1000
anchors would cost minutes and gigabytes. The format itself allows at most
:data:`MAX_ANCHORS` anchors and :data:`MAX_Z_STARTS` start heights (the ceilings of those
options).
"""

from __future__ import annotations

import difflib
import gc
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, BinaryIO, TextIO

import numpy as np

from diffpos_services.errors import ConfigError, DiffposError

__all__ = [
    "DEFAULT_LIMITS",
    "FIELDS",
    "GATING_FIELDS",
    "LOSSES",
    "MAX_ANCHORS",
    "MAX_LINE_BYTES",
    "MAX_Z_STARTS",
    "METHODS",
    "RESULT_KEYS",
    "Limits",
    "Problem",
    "ProblemError",
    "check_id",
    "decode_line",
    "invalid_record",
    "parse_problem",
    "read_lines",
]

#: Ceilings of the format (bad input must not exhaust memory or time); the per-run limits
#: below (:class:`Limits`) may be raised up to them.
MAX_ANCHORS = 1024
MAX_Z_STARTS = 1000
MAX_ABS_M = 1e7
MAX_ID_CHARS = 1000
#: Defaults of the per-run limits (``--max-line-bytes``, ``--max-anchors``, ``--max-starts``).
#: At these, the worst problem (random ranges, gating excluding down to 3 anchors, 32 starts)
#: costs well under a second and about 30 MB.
MAX_LINE_BYTES = 1 << 20
MAX_LINE_BYTES_CEILING = 1 << 30
DEFAULT_MAX_ANCHORS = 32
DEFAULT_MAX_STARTS = 32

FIELDS = (
    "anchors_m", "ranges_m", "sigmas_m", "window_height_m", "edge_x_m", "delta_m", "method",
    "gating", "loss", "x0_m", "z_starts_m", "nlos", "nlos_bias_m", "snr_db", "id",
)
METHODS = ("dnls", "lls", "ippa", "mnls")
#: What ``mnls`` needs and a problem line does not carry: the building (``--scenario``).
MNLS_NEEDS_SCENARIO = ("method mnls needs the building (floors, window band, depth, edges): "
                       "give it with diffpos solve --scenario FILE")
LOSSES = ("linear", "huber", "soft_l1")
GATING_FIELDS = (
    "false_alarm_probability", "max_exclusions", "pregate", "multistart_exclusion", "z_range_m",
)

RESULT_KEYS = (
    "line", "id", "status", "message", "method", "position_m", "covariance_m2",
    "covariance_model", "peb_m", "z_bound_m", "iterations", "converged", "used_anchors",
    "excluded_anchors", "residuals_m", "test_statistic", "test_threshold", "floor",
    "floor_probability",
)


class ProblemError(DiffposError, ValueError):
    """A problem line is malformed; the message names the field and what to fix.

    A line's error is answered with an ``invalid_input`` record, not an exit: the exit code
    (1) is what ``--strict`` returns when some line was invalid.
    """

    exit_code = 1


@dataclass(frozen=True)
class Limits:
    """Work limits of one problem line; :class:`ConfigError` (exit 2) if out of range.

    ``max_anchors`` (``--max-anchors``): anchors per problem, at most :data:`MAX_ANCHORS`;
    ``max_starts`` (``--max-starts``): ``z_starts_m`` entries, at most :data:`MAX_Z_STARTS`;
    ``max_line_bytes`` (``--max-line-bytes``): bytes of one input line.
    """

    max_anchors: int = DEFAULT_MAX_ANCHORS
    max_starts: int = DEFAULT_MAX_STARTS
    max_line_bytes: int = MAX_LINE_BYTES

    def __post_init__(self) -> None:
        for option, value, lo, hi in (
            ("--max-anchors", self.max_anchors, 3, MAX_ANCHORS),
            ("--max-starts", self.max_starts, 1, MAX_Z_STARTS),
            ("--max-line-bytes", self.max_line_bytes, 16, MAX_LINE_BYTES_CEILING),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
                raise ConfigError(f"{option} must be an integer in [{lo}, {hi}], got {value!r}")


DEFAULT_LIMITS = Limits()


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
    snr_db: np.ndarray | None = None  # (M,), NaN where unknown
    scenario: Any = None  # --scenario's Scenario (the same object for every line)

    def group_key(self) -> tuple:
        """Problems with equal keys are solved in one batched call."""
        g = None if self.gating is None else tuple(sorted(self.gating.items()))
        return (
            self.method, self.ranges_m.size, self.edge_x_m, g, self.loss, self.z_starts_m,
            self.sigmas_m is None, self.x0_m is None, self.snr_db is None,
        )


# ----------------------------------------------------------------------------- value checks
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


def _vector(value: Any, name: str, length: int | None = None, *, allow_null: bool = False):
    if not isinstance(value, list):
        raise ProblemError(f"{name} must be a list, got {_short(value)}")
    if length is not None and len(value) != length:
        raise ProblemError(f"{name} must have {length} entries (one per anchor), got {len(value)}")
    out = []
    for k, v in enumerate(value):
        if v is None and allow_null:
            out.append(math.nan)
        else:
            out.append(_number(v, f"{name}[{k}]"))
    return out


# ----------------------------------------------------------------------------- problem steps
def _check_fields(obj: Any) -> None:
    """A JSON object with known fields and the two required ones."""
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


def _parse_anchors(value: Any, limits: Limits) -> np.ndarray:
    """``anchors_m`` -> ``(M, 3)``: at most ``limits.max_anchors``, every one outside (y < 0)."""
    if not isinstance(value, list) or not value:
        raise ProblemError("anchors_m must be a non-empty list of [x, y, z] positions [m]")
    if len(value) > limits.max_anchors:
        raise ProblemError(
            f"anchors_m has {len(value)} anchors; at most {limits.max_anchors} per problem are "
            f"allowed (raise it with --max-anchors, default {DEFAULT_MAX_ANCHORS}, at most "
            f"{MAX_ANCHORS}; the work per problem grows with the square of the anchor count)"
        )
    a = np.array(
        [_vector(p, f"anchors_m[{k}]", 3) for k, p in enumerate(value)], dtype=np.float64
    )
    not_outside = np.flatnonzero(~(a[:, 1] < 0))
    if not_outside.size:
        k = int(not_outside[0])
        y = a[k, 1]
        where = "on the facade (y = 0)" if y == 0 else f"inside the building (y = {y:g} > 0)"
        more = f" ({not_outside.size} anchors are not outside)" if not_outside.size > 1 else ""
        raise ProblemError(
            f"anchors_m[{k}] = {_short(value[k])} is {where}; anchors must be outside, y < 0 "
            f"(the facade with the windows is the plane y = 0){more}"
        )
    return a


def _parse_ranges(value: Any, m: int) -> tuple[np.ndarray, np.ndarray]:
    """``ranges_m`` -> (ranges with NaN where not measured, measured mask); >= 3 measured."""
    r = np.array(_vector(value, "ranges_m", m, allow_null=True))
    mask = np.isfinite(r)
    if np.any(r[mask] < 0):
        k = int(np.flatnonzero(mask & (r < 0))[0])
        raise ProblemError(f"ranges_m[{k}] is negative ({r[k]}); ranges must be >= 0 [m]")
    if mask.sum() < 3:
        raise ProblemError(
            f"fewer than 3 anchors with a range ({int(mask.sum())}); a 3D fix needs >= 3 "
            "(anchors_m / ranges_m)"
        )
    return r, mask


def _parse_sigmas(value: Any, m: int, mask: np.ndarray) -> np.ndarray | None:
    """``sigmas_m`` (one value or one per anchor) -> ``(M,)``, 1 where no range is given."""
    if value is None:
        return None
    if isinstance(value, list):
        sig = np.array(_vector(value, "sigmas_m", m, allow_null=True))
    else:
        sig = np.full(m, _number(value, "sigmas_m"))
    bad = mask & ~(np.isfinite(sig) & (sig > 0))
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise ProblemError(f"sigmas_m[{k}] must be a number > 0 where a range is given")
    return np.where(mask, sig, 1.0)


def _parse_snr(value: Any, m: int) -> np.ndarray | None:
    """``snr_db`` (one per anchor, null = unknown) -> ``(M,)`` with NaN where unknown."""
    if value is None:
        return None
    return np.array(_vector(value, "snr_db", m, allow_null=True))


def _parse_model(obj: dict[str, Any], default_method: str, building: Any = None
                 ) -> tuple[str, float | None, float, tuple[float, float] | None]:
    """``method``, ``window_height_m`` (required for dnls), ``delta_m`` and ``edge_x_m``.

    With a ``building`` (``--scenario``), a missing ``window_height_m`` / ``edge_x_m`` is the
    building's; without one, ``mnls`` is refused.
    """
    method = obj.get("method", default_method)
    if method not in METHODS:
        raise ProblemError(f"method must be one of {list(METHODS)}, got {json.dumps(method)}")
    if method == "mnls" and building is None:
        raise ProblemError(MNLS_NEEDS_SCENARIO)
    wh = obj.get("window_height_m")
    if wh is not None:
        wh = _number(wh, "window_height_m", positive=True)
    elif building is not None:
        wh = float(building.window_height_m)
    elif method == "dnls":
        raise ProblemError("window_height_m is required for method dnls (window height w [m]; "
                           "or give the building with --scenario)")
    delta = _number(obj.get("delta_m", 0.0), "delta_m")
    edge = obj.get("edge_x_m")
    if edge is not None:
        ev = _vector(edge, "edge_x_m", 2)
        if ev[0] == ev[1]:
            raise ProblemError("edge_x_m must be two different x values [x1, x2] [m]")
        edge = (min(ev), max(ev))
    elif building is not None:
        edge = tuple(float(v) for v in building.edge_x_m)
    return method, wh, delta, edge


def _parse_starts(obj: dict[str, Any], limits: Limits
                  ) -> tuple[str, np.ndarray | None, tuple[float, ...] | None]:
    """``loss``, ``x0_m`` and ``z_starts_m`` (at most ``limits.max_starts``)."""
    loss = obj.get("loss", "linear")
    if loss not in LOSSES:
        raise ProblemError(f"loss must be one of {list(LOSSES)}, got {json.dumps(loss)}")
    x0 = obj.get("x0_m")
    if x0 is not None:
        x0 = np.array(_vector(x0, "x0_m", 3))
    zs = obj.get("z_starts_m")
    if zs is not None:
        if isinstance(zs, list) and len(zs) > limits.max_starts:  # before parsing them
            raise ProblemError(
                f"z_starts_m has {len(zs)} entries; at most {limits.max_starts} per problem are "
                f"allowed (raise it with --max-starts, default {DEFAULT_MAX_STARTS}, at most "
                f"{MAX_Z_STARTS})"
            )
        zs = tuple(_vector(zs, "z_starts_m"))
        if not zs:
            raise ProblemError("z_starts_m must not be empty")
    return loss, x0, zs


def _parse_ippa(obj: dict[str, Any], m: int) -> tuple[np.ndarray, np.ndarray]:
    """IPPA's ``nlos`` flags and ``nlos_bias_m``, one per anchor."""
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
    return nlos, bias


def _gating_value(k: str, v: Any) -> Any:
    """One validated gating setting."""
    if k in ("pregate", "multistart_exclusion"):
        if not isinstance(v, bool):
            raise ProblemError(f"gating.{k} must be true or false")
        return v
    if k == "z_range_m":
        if v is None:
            return None
        if not isinstance(v, list) or len(v) != 2:
            raise ProblemError("gating.z_range_m must be null or [z_min, z_max] in metres")
        lo = _number(v[0], "gating.z_range_m[0]", limit=None)
        hi = _number(v[1], "gating.z_range_m[1]", limit=None)
        if not lo < hi:
            raise ProblemError("gating.z_range_m must have z_min < z_max")
        return (lo, hi)
    if k == "max_exclusions":
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= MAX_ANCHORS:
            raise ProblemError(f"gating.max_exclusions must be an integer in "
                               f"[0, {MAX_ANCHORS}]")
        return v
    p = _number(v, "gating.false_alarm_probability", limit=None)
    if not 0 < p < 1:
        raise ProblemError("gating.false_alarm_probability must be in (0, 1)")
    return p


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
        gating[k] = _gating_value(k, v)
    return gating


def parse_problem(obj: Any, *, default_method: str = "dnls",
                  limits: Limits = DEFAULT_LIMITS, scenario: Any = None) -> Problem:
    """Validate one decoded JSON problem; raise :class:`ProblemError` naming the field.

    The steps run in the order the fields are checked (the first problem found is reported).
    ``scenario`` (``--scenario``, a :class:`diffpos.scenario.Scenario`) gives the building
    every line is in: ``mnls`` needs it, and it is the default window height and edge extent
    of ``dnls``.
    """
    building = None if scenario is None else scenario.building
    _check_fields(obj)
    a = _parse_anchors(obj["anchors_m"], limits)
    m = a.shape[0]
    r, mask = _parse_ranges(obj["ranges_m"], m)
    sig = _parse_sigmas(obj.get("sigmas_m"), m, mask)
    method, wh, delta, edge = _parse_model(obj, default_method, building)
    gating = _parse_gating(obj.get("gating", True))
    loss, x0, zs = _parse_starts(obj, limits)
    nlos, bias = _parse_ippa(obj, m)
    return Problem(
        anchors_m=a, ranges_m=np.where(mask, r, 0.0), mask=mask, sigmas_m=sig, method=method,
        window_height_m=wh, delta_m=delta, edge_x_m=edge, gating=gating, loss=loss, x0_m=x0,
        z_starts_m=zs, nlos=nlos, nlos_bias_m=bias, snr_db=_parse_snr(obj.get("snr_db"), m),
        scenario=scenario,
    )


def check_id(value: Any) -> Any:
    """The id if it can be echoed as plain JSON (no NaN/Infinity) of bounded size."""
    try:
        text = json.dumps(value, allow_nan=False)
    except (ValueError, TypeError, RecursionError):
        raise ProblemError("id must be plain JSON without NaN or Infinity") from None
    if len(text) > MAX_ID_CHARS:
        raise ProblemError(f"id is {len(text)} characters of JSON; at most {MAX_ID_CHARS} "
                           "are allowed")
    return value


# ----------------------------------------------------------------------------- results
def invalid_record(message: str) -> dict[str, Any]:
    """The result of a line that could not be solved (status ``invalid_input``)."""
    rec: dict[str, Any] = dict.fromkeys(RESULT_KEYS)
    rec.update(status="invalid_input", message=message, iterations=0, converged=False,
               used_anchors=[], excluded_anchors=[])
    return rec


# ----------------------------------------------------------------------------- lines
def _loads(line: str) -> Any:
    """``json.loads`` with the cyclic garbage collector paused: a decoded JSON value has no
    cycles, and a 1 MiB line of nested empty lists decodes 2-3x faster without the collector
    scanning its hundreds of thousands of new containers."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        return json.loads(line)
    finally:
        if enabled:
            gc.enable()


def decode_line(line: str | ProblemError) -> Any:
    """A line's JSON value, or :class:`ProblemError` (returned, not raised) if it is not JSON."""
    if isinstance(line, ProblemError):
        return line
    try:
        return _loads(line)
    except json.JSONDecodeError as exc:
        return ProblemError(f"invalid JSON: {exc.msg} at column {exc.colno}")
    except RecursionError:
        return ProblemError("invalid JSON: nested too deeply")
    except ValueError as exc:  # e.g. an integer literal with more than 4300 digits
        return ProblemError(f"invalid JSON: {str(exc)[:120]}")


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
