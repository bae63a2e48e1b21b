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

__all__ = ["parse_line"]


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
        method = default_method if p.method is msgspec.UNSET else p.method
        if method not in METHODS or method == "mnls":
            return None
        raw_id = bytes(p.id)
        ident = None if raw_id == b"null" else _loads(raw_id)
        if not (type(ident) is int and len(raw_id) <= MAX_ID_CHARS):  # an int is plain JSON
            ident = None if ident is None else check_id(ident)
        a, r, mask, sig = _arrays(p, limits)
        wh, delta, edge = _model(p, method, None if scenario is None else scenario.building)
        gating = _parse_gating(p.gating)
        opt = _options(p, a.shape[0], limits)
    except (msgspec.DecodeError, ProblemError):  # incl. _Unusual
        return None
    return ident, Problem(anchors_m=a, ranges_m=r, mask=mask, sigmas_m=sig, method=method,
                          window_height_m=wh, delta_m=delta, edge_x_m=edge, gating=gating,
                          scenario=scenario, **opt)
