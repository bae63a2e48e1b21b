"""Fast path of the ``diffpos solve`` line parser: one typed msgspec decode per line.

:func:`parse_line` decodes a whole problem line straight into a typed struct (msgspec checks
the JSON types, unknown fields and number ranges in C) and validates the values with a few
array operations. It accepts only what :func:`~diffpos_services.wire.solve_io.parse_problem`
accepts and builds the same :class:`~diffpos_services.wire.solve_io.Problem`; whenever a line
is unusual in any way (a type or value error, ``mnls``, an id that is not plain JSON) it
returns ``None`` and the caller takes the checked path, which names the field at fault. So a
bad line gets exactly the error message it always got, and a good line costs a fraction of
the generic decode-then-check path.
"""

from __future__ import annotations

from typing import Any

import msgspec
import numpy as np

from diffpos_services.wire.solve_io import (
    LOSSES,
    MAX_ABS_M,
    MAX_ID_CHARS,
    METHODS,
    Limits,
    Problem,
    ProblemError,
    _loads,
    _parse_gating,
    check_id,
)

__all__ = ["PLAIN_MAX_CHARS", "decode_plain", "parse_line", "plain_arrays", "plain_group_key",
           "problem_of"]


class _Line(msgspec.Struct, forbid_unknown_fields=True):
    """A problem line as JSON types (defaults as :func:`solve_io.parse_problem` reads them)."""

    anchors_m: list[list[float]]
    ranges_m: list[float | None]
    sigmas_m: float | list[float | None] | None = None
    window_height_m: float | None = None
    edge_x_m: list[float] | None = None
    delta_m: float = 0.0
    method: str | msgspec.UnsetType = msgspec.UNSET
    gating: bool | dict[str, Any] | None = True
    loss: str = "linear"
    x0_m: list[float] | None = None
    z_starts_m: list[float] | None = None
    nlos: bool | list[bool] = True
    nlos_bias_m: float | list[float] = 0.0
    snr_db: list[float | None] | None = None
    # kept as raw JSON: decoded (with the collector paused, as the checked path does) only
    # for a line that is otherwise good, so a huge id is scanned once, never built twice
    id: msgspec.Raw = msgspec.Raw(b"null")


_DECODER = msgspec.json.Decoder(_Line)


class _Unusual(ProblemError):
    """The line needs the checked path (internal; never leaves :func:`parse_line`)."""


def _in_range(arr: np.ndarray) -> bool:
    """Every value within the format's coordinate range (msgspec never yields NaN or inf:
    JSON has no such numbers and an overflowing literal fails the decode)."""
    return arr.size == 0 or float(np.abs(arr).max()) <= MAX_ABS_M


def _nullable(values: list[float | None], m: int) -> tuple[np.ndarray, np.ndarray]:
    """``m`` numbers or nulls -> (values with NaN for null, non-null mask); unusual otherwise."""
    if len(values) != m:
        raise _Unusual
    if None in values:
        given = np.array([x is not None for x in values])
        v = np.array(values, dtype=np.float64)  # None -> NaN
        if not _in_range(v[given]):
            raise _Unusual
        return v, given
    v = np.array(values, dtype=np.float64)
    if not _in_range(v):
        raise _Unusual
    return v, _ALL[m] if m < len(_ALL) else np.ones(m, bool)


_ALL = [np.ones(m, bool) for m in range(65)]  # shared read-only "all measured" masks
for _mask in _ALL:
    _mask.setflags(write=False)


def _filled(m: int, value: Any, dtype: Any = np.float64) -> np.ndarray:
    """``np.full(m, value, dtype)`` without its Python wrapper (~1 us less per call)."""
    out = np.empty(m, dtype)
    out.fill(value)
    return out


def _scalar(v: float, *, positive: bool = False) -> float:
    if abs(v) > MAX_ABS_M or (positive and v <= 0):
        raise _Unusual
    return v


def _vec(values: list[float], m: int) -> np.ndarray:
    v = np.array(values, dtype=np.float64)
    if v.shape != (m,) or not _in_range(v):
        raise _Unusual
    return v


def _arrays(p: _Line, limits: Limits) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                np.ndarray | None]:
    """Anchors, ranges (0 where not measured), measured mask and sigmas."""
    if not 1 <= len(p.anchors_m) <= limits.max_anchors:
        raise _Unusual
    try:
        a = np.array(p.anchors_m, dtype=np.float64)
    except ValueError:  # ragged
        raise _Unusual from None
    if a.ndim != 2 or a.shape[1] != 3 or not _in_range(a) or not float(a[:, 1].max()) < 0:
        raise _Unusual
    m = a.shape[0]
    r, mask = _nullable(p.ranges_m, m)
    all_measured = mask is _ALL[m] if m < len(_ALL) else bool(mask.all())
    if all_measured:
        if m < 3 or float(r.min()) < 0:
            raise _Unusual
    elif (r[mask] < 0).any() or mask.sum() < 3:
        raise _Unusual
    sig = None
    if p.sigmas_m is not None:
        if isinstance(p.sigmas_m, list):
            sig, _ = _nullable(p.sigmas_m, m)
            if (mask & ~(np.isfinite(sig) & (sig > 0))).any():
                raise _Unusual
            sig = np.where(mask, sig, 1.0)
        elif _scalar(p.sigmas_m) > 0:
            sig = _filled(m, p.sigmas_m) if all_measured else np.where(mask, p.sigmas_m, 1.0)
        else:
            raise _Unusual
    return a, r if all_measured else np.where(mask, r, 0.0), mask.copy(), sig


def _model(p: _Line, method: str, building: Any) -> tuple[float | None, float,
                                                           tuple[float, float] | None]:
    """Window height, delta and edge extent (the building's where a line has none)."""
    wh = p.window_height_m
    if wh is not None:
        wh = _scalar(wh, positive=True)
    elif building is not None:
        wh = float(building.window_height_m)
    elif method == "dnls":
        raise _Unusual
    edge = None
    if p.edge_x_m is not None:
        ev = _vec(p.edge_x_m, 2).tolist()
        if ev[0] == ev[1]:
            raise _Unusual
        edge = (min(ev), max(ev))
    elif building is not None:
        edge = tuple(float(v) for v in building.edge_x_m)
    return wh, _scalar(p.delta_m), edge


def _options(p: _Line, m: int, limits: Limits) -> dict[str, Any]:
    """Loss, starts, IPPA options and SNRs."""
    if p.loss not in LOSSES:
        raise _Unusual
    zs = None
    if p.z_starts_m is not None:
        if not 1 <= len(p.z_starts_m) <= limits.max_starts:
            raise _Unusual
        zs = tuple(_vec(p.z_starts_m, len(p.z_starts_m)).tolist())
    if isinstance(p.nlos, bool):
        nlos = _filled(m, p.nlos, bool)  # the same array parse_problem builds
    elif len(p.nlos) == m:
        nlos = np.array(p.nlos, dtype=bool)
    else:
        raise _Unusual
    nb = p.nlos_bias_m
    bias = _vec(nb, m) if isinstance(nb, list) else _filled(m, _scalar(nb))
    snr = None if p.snr_db is None else _nullable(p.snr_db, m)[0]
    x0 = None if p.x0_m is None else _vec(p.x0_m, 3)
    return {"loss": p.loss, "x0_m": x0, "z_starts_m": zs, "nlos": nlos, "nlos_bias_m": bias,
            "snr_db": snr}


def parse_line(line: str, *, default_method: str, limits: Limits, scenario: Any = None
               ) -> tuple[Any, Problem] | None:
    """``(id, problem)`` of a well-formed problem line, or ``None``: take the checked path
    (:func:`~diffpos_services.wire.solve_io.decode_line` and
    :func:`~diffpos_services.wire.solve_io.parse_problem`), which reports what is wrong."""
    try:
        p = _DECODER.decode(line)
    except msgspec.DecodeError:
        return None
    return problem_of(p, default_method=default_method, limits=limits, scenario=scenario)


def problem_of(p: _Line, *, default_method: str, limits: Limits, scenario: Any = None
               ) -> tuple[Any, Problem] | None:
    """:func:`parse_line` of an already decoded line."""
    try:
        method = default_method if p.method is msgspec.UNSET else p.method
        if method not in METHODS or method == "mnls":
            return None
        raw_id = bytes(p.id)
        ident = _plain_id(raw_id)
        if ident is _NOT_PLAIN:
            ident = check_id(_loads(raw_id))
        a, r, mask, sig = _arrays(p, limits)
        wh, delta, edge = _model(p, method, None if scenario is None else scenario.building)
        gating = _parse_gating(p.gating)
        opt = _options(p, a.shape[0], limits)
    except (msgspec.DecodeError, ProblemError):  # incl. _Unusual
        return None
    return ident, Problem(anchors_m=a, ranges_m=r, mask=mask, sigmas_m=sig, method=method,
                          window_height_m=wh, delta_m=delta, edge_x_m=edge, gating=gating,
                          scenario=scenario, **opt)


# ----------------------------------------------------------------------------- plain lines
#: A decoded line is "plain" when it is a D-NLS problem with every optional field at its
#: default except a scalar ``sigmas_m``, ``window_height_m`` and ``delta_m`` (the lines a
#: positioning pipeline writes). Plain lines of a batch are checked and stacked as arrays in
#: a few numpy operations (:func:`plain_arrays`) instead of ~15 per line; every other line
#: takes :func:`problem_of` one at a time. A plain line's text is kept (at most
#: :data:`PLAIN_MAX_CHARS`) so that a row failing the batch checks is re-read on the checked
#: path with exactly the message it always got.
PLAIN_MAX_CHARS = 4096
_NOT_PLAIN = object()


def _plain_id(raw_id: bytes) -> Any:
    """The id of a raw JSON ``null`` or integer literal (plain JSON by construction, as the
    decoder has read the whole line), else :data:`_NOT_PLAIN` (the caller decodes and checks
    it). ``int(b"-12")`` equals ``json.loads`` of the same literal."""
    if raw_id == b"null":
        return None
    digits = raw_id[1:] if raw_id[:1] == b"-" else raw_id
    if digits.isdigit() and len(raw_id) <= MAX_ID_CHARS:  # bytes.isdigit: ASCII 0-9 only
        return int(raw_id)
    return _NOT_PLAIN


def decode_plain(line: str, *, default_method: str, limits: Limits) -> tuple[Any, _Line] | None:
    """``(id, decoded line)`` of a plain line (see :data:`PLAIN_MAX_CHARS`), else ``None``
    (the caller takes :func:`parse_line`). The values are not checked here: that is
    :func:`plain_arrays`' job, for a whole batch at once."""
    if len(line) > PLAIN_MAX_CHARS:
        return None
    try:
        p = _DECODER.decode(line)
    except msgspec.DecodeError:
        return None
    if not ((default_method == "dnls" if p.method is msgspec.UNSET else p.method == "dnls")
            and p.gating is True and p.loss == "linear" and p.edge_x_m is None
            and p.x0_m is None and p.z_starts_m is None and p.snr_db is None
            and type(p.nlos) is bool and type(p.nlos_bias_m) is float and p.nlos_bias_m == 0.0
            and not isinstance(p.sigmas_m, list)
            and 3 <= len(p.anchors_m) <= limits.max_anchors
            and len(p.ranges_m) == len(p.anchors_m) and None not in p.ranges_m
            and all(len(xyz) == 3 for xyz in p.anchors_m)):
        return None
    ident = _plain_id(bytes(p.id))
    return None if ident is _NOT_PLAIN else (ident, p)


def plain_group_key(p: _Line) -> tuple[int, bool, bool]:
    """Plain lines with equal keys are stacked together: anchor count, sigmas given, window
    height given."""
    return len(p.anchors_m), p.sigmas_m is not None, p.window_height_m is not None


def plain_arrays(lines: list[_Line], building: Any = None) -> tuple[np.ndarray, ...]:
    """Plain lines of one :func:`plain_group_key` as the arrays :func:`problem_of` would build
    and stack: ``ok`` (B,) (False: the row fails a check of :func:`problem_of`; the caller
    re-reads it on the one-line path), anchors (B, M, 3), ranges (B, M), mask (B, M),
    sigmas (B, M) or None, window height (B,), delta (B,) [m]. The checks are
    :func:`_arrays`' and :func:`_model`'s for these lines, row by row.
    """
    b = len(lines)
    m, has_sig, has_wh = plain_group_key(lines[0])
    try:
        a = np.array([p.anchors_m for p in lines], dtype=np.float64)
    except ValueError:  # not reached (decode_plain checks the lengths): every row re-read alone
        a = np.zeros((b, 0))
    if a.shape != (b, m, 3):
        return (np.zeros(b, bool),)
    r = np.array([p.ranges_m for p in lines], dtype=np.float64)
    delta = np.array([p.delta_m for p in lines], dtype=np.float64)
    ok = ((np.abs(a) <= MAX_ABS_M).all(axis=(1, 2)) & (a[:, :, 1].max(axis=1) < 0)
          & (r >= 0).all(axis=1) & (r <= MAX_ABS_M).all(axis=1) & (np.abs(delta) <= MAX_ABS_M))
    sig = None
    if has_sig:
        s = np.array([p.sigmas_m for p in lines], dtype=np.float64)
        ok &= (s > 0) & (s <= MAX_ABS_M)
        sig = np.repeat(s[:, None], m, axis=1)
    if has_wh:
        wh = np.array([p.window_height_m for p in lines], dtype=np.float64)
        ok &= (wh > 0) & (wh <= MAX_ABS_M)
    elif building is not None:
        wh = np.full(b, float(building.window_height_m))
    else:  # dnls needs the window height: the one-line path says so
        return (np.zeros(b, bool),)
    return ok, a, r, np.ones((b, m), bool), sig, wh, delta
