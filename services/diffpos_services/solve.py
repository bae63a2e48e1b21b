"""The batch solver behind ``diffpos solve``: decoded problems in, result records out.

Problems are validated by :func:`diffpos_services.wire.solve_io.parse_problem`, grouped by
what must be equal for one batched estimator call (method, anchor count, options), solved with
the vectorised estimators of :mod:`diffpos.estimators` and returned in input order. A problem
that breaks its batch is re-solved alone, so one bad line never costs the others their fixes.

Bounded work: every line is decoded (one typed msgspec decode of the whole line; the generic
checked path only for unusual lines, see :mod:`diffpos_services.wire.solve_line`) as soon as
it is read. A *plain* D-NLS line (every option at its default but a scalar sigma, the window
height and delta; at most ``--max-anchors`` anchors and
:data:`~diffpos_services.wire.solve_line.PLAIN_MAX_CHARS` characters) is kept decoded, with
its text, until its batch is checked and solved from stacked arrays (a row that fails a check
is re-read on the one-line path, so its message is the checked path's); any other line is
validated at once and only the compact validated problem is kept, never its text or decoded
JSON. The per-problem limits of :class:`~diffpos_services.wire.solve_io.Limits` bound each
problem's arrays, and a group is solved in chunks of at most :data:`CHUNK_ELEMENTS` solver
elements (anchors^2 x starts per problem), so a batch of large problems cannot add up to
gigabytes.

Only a status with a trustworthy position (``ok``, ``ok_unverified``) publishes one: every
other status has ``position_m``, ``covariance_m2``, ``peb_m`` and ``z_bound_m`` null (an
unidentifiable or diverged fit can sit hundreds of kilometres away).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.gating import GatingConfig
from diffpos.estimators.ippa import ippa
from diffpos.estimators.lls import lls
from diffpos.estimators.mnls.solver import mnls
from diffpos.estimators.starts import DEFAULT_Z_STARTS_M
from diffpos_services.wire.solve_io import (
    DEFAULT_LIMITS,
    RESULT_KEYS,
    Limits,
    Problem,
    ProblemError,
    check_id,
    decode_line,
    invalid_record,
    parse_problem,
)
from diffpos_services.wire.solve_line import (
    decode_plain,
    parse_line,
    plain_arrays,
    plain_group_key,
)

__all__ = ["CHUNK_ELEMENTS", "POSITION_STATUSES", "solve_lines", "solve_records"]

#: Statuses whose position is published; any other status has no trustworthy position.
POSITION_STATUSES = ("ok", "ok_unverified")
#: Result fields that only exist with a trustworthy position.
_POSITION_KEYS = ("position_m", "covariance_m2", "peb_m", "z_bound_m", "floor",
                  "floor_probability")
#: M-NLS's coarse start grid per floor (cells; its default ``grid_shape``) and path slots,
#: for the chunk size of its working arrays (problems x floors x cells x anchors x slots).
_MNLS_CELLS = 18
_MNLS_SLOTS = 18
#: Problems of one group are solved together up to this many solver elements
#: (anchors^2 x (starts + 2) each): at most about 70 MB of working memory (measured).
CHUNK_ELEMENTS = 1 << 18

# (line number or index, id, validated problem or the record of an invalid line)
_Prepared = tuple[int, Any, Problem | dict[str, Any]]
#: result keys that a :meth:`FixResult.to_records` record holds, in the result's order
_FIX_KEYS = RESULT_KEYS[2:17]
_NO_FLOOR = {"floor": None, "floor_probability": None}
_DEFAULT_GATING = GatingConfig()


class _Plain:
    """A plain line (:func:`~diffpos_services.wire.solve_line.decode_plain`) waiting for its
    batch: checked and stacked with the batch's other plain lines, solved without a
    :class:`Problem` per line."""

    __slots__ = ("decoded", "ident", "line", "text")

    def __init__(self, line: int, ident: Any, decoded: Any, text: str) -> None:
        self.line, self.ident, self.decoded, self.text = line, ident, decoded, text


def _solve_group(problems: list[Problem]) -> list[dict[str, Any]]:
    """One batched estimator call for problems with equal :meth:`Problem.group_key`."""
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
    elif p0.method == "mnls":
        return _solve_mnls(problems, a, r, sig, mask)
    else:
        fix = ippa(
            a, r, sig, mask=mask, nlos=np.stack([p.nlos for p in problems]),
            nlos_bias_m=np.stack([p.nlos_bias_m for p in problems]), x0_m=x0,
            z_starts_m=p0.z_starts_m,
        )
    return fix.to_records()


def _solve_mnls(problems: list[Problem], a: np.ndarray, r: np.ndarray, sig: np.ndarray | None,
                mask: np.ndarray) -> list[dict[str, Any]]:
    """M-NLS in the ``--scenario`` building; the records get the floor and its posterior."""
    p0 = problems[0]
    sc = p0.scenario
    snr = None if p0.snr_db is None else np.stack([p.snr_db for p in problems])
    pfa = (p0.gating or {}).get("false_alarm_probability")
    fix = mnls(a, r, sig, building=sc.building, mask=mask, snr_db=snr, radio=sc.radio,
               bandwidth_hz=sc.radio.bandwidth_hz, error_floor_m=sc.radio.range_error_floor_m,
               chunk_size=_chunk_size(p0), **({} if pfa is None else
                                              {"false_alarm_probability": pfa}))
    recs = fix.to_records()
    for i, rec in enumerate(recs):
        has = int(fix.floor[i]) >= 0
        rec["floor"] = int(fix.floor[i]) if has else None
        rec["floor_probability"] = ([float(v) for v in fix.floor_probability[i]] if has
                                    else None)
    return recs


def _solve_alone(prob: Problem) -> dict[str, Any]:
    try:
        return _solve_group([prob])[0]
    except Exception as exc:  # reported on this line; the filter goes on
        return invalid_record(f"the solver failed on this problem ({type(exc).__name__}: "
                              f"{str(exc)[:200]}); check the values for plausibility")


def _prepare(line: int, obj: Any, default_method: str, limits: Limits, scenario: Any = None
             ) -> _Prepared:
    """Validate one decoded problem (or the :class:`ProblemError` of an unreadable line)."""
    ident = None
    try:
        if isinstance(obj, ProblemError):
            raise obj
        if isinstance(obj, dict) and obj.get("id") is not None:
            ident = check_id(obj["id"])
        return line, ident, parse_problem(obj, default_method=default_method, limits=limits,
                                          scenario=scenario)
    except ProblemError as exc:
        return line, ident, invalid_record(str(exc))


def _read_line(line: int, text: str | ProblemError, default_method: str, limits: Limits,
               scenario: Any = None) -> _Prepared | _Plain:
    """One input line as it is read: a plain D-NLS line kept for its batch (:class:`_Plain`),
    or prepared alone (:func:`_prepare_line`)."""
    if not isinstance(text, ProblemError):
        plain = decode_plain(text, default_method=default_method, limits=limits)
        if plain is not None:
            return _Plain(line, plain[0], plain[1], text)
    return _prepare_line(line, text, default_method, limits, scenario)


def _prepare_line(line: int, text: str | ProblemError, default_method: str, limits: Limits,
                  scenario: Any = None) -> _Prepared:
    """One input line: the typed fast decode (:func:`~diffpos_services.wire.solve_line.
    parse_line`), or for anything unusual the checked path that names the error."""
    if not isinstance(text, ProblemError):
        fast = parse_line(text, default_method=default_method, limits=limits, scenario=scenario)
        if fast is not None:
            return line, fast[0], fast[1]
    return _prepare(line, decode_line(text), default_method, limits, scenario)


def _chunk_size(prob: Problem) -> int:
    """How many problems like ``prob`` are solved in one estimator call."""
    m = prob.ranges_m.size
    if prob.method == "mnls":
        floors = prob.scenario.building.n_floors
        return max(1, CHUNK_ELEMENTS // (m * floors * _MNLS_CELLS * _MNLS_SLOTS))
    starts = 1 if prob.x0_m is not None else len(prob.z_starts_m or DEFAULT_Z_STARTS_M)
    return _chunk_size_of(m, starts)


def _chunk_size_of(m: int, starts: int = len(DEFAULT_Z_STARTS_M)) -> int:
    """How many D-NLS problems of ``m`` anchors and ``starts`` start heights are solved in
    one estimator call (:data:`CHUNK_ELEMENTS`)."""
    return max(1, CHUNK_ELEMENTS // (m * m * (starts + 2)))


def _solve_prepared(items: list[_Prepared]) -> list[dict[str, Any]]:
    """Result records of validated items, in order: groups solved in bounded chunks."""
    out: list[dict[str, Any]] = []
    groups: dict[tuple, list[tuple[int, Problem]]] = {}
    for k, (_, _, prob) in enumerate(items):
        out.append(prob if isinstance(prob, dict) else {})
        if isinstance(prob, Problem):
            groups.setdefault(prob.group_key(), []).append((k, prob))
    for members in groups.values():
        step = _chunk_size(members[0][1])
        for lo in range(0, len(members), step):
            part = members[lo:lo + step]
            try:
                recs = _solve_group([p for _, p in part])
            except Exception:  # isolate the problem that broke the batch
                recs = [_solve_alone(p) for _, p in part]
            for (k, _), rec in zip(part, recs, strict=True):
                out[k] = rec
    final = []
    for (line, ident, _), rec in zip(items, out, strict=True):
        rec = {key: rec.get(key) for key in RESULT_KEYS}
        if rec["status"] not in POSITION_STATUSES:
            rec.update(dict.fromkeys(_POSITION_KEYS))  # no trustworthy position: publish none
        rec["line"] = line
        rec["id"] = ident
        final.append(rec)
    return final


def solve_records(
    problems: Iterable[Any], *, default_method: str = "dnls", first_line: int = 1,
    limits: Limits = DEFAULT_LIMITS, scenario: Any = None,
) -> list[dict[str, Any]]:
    """Solve decoded problems (dicts, or :class:`ProblemError` instances for lines that
    failed to decode); return one JSON-ready result dict per problem, in order.

    ``scenario`` (a :class:`diffpos.scenario.Scenario`): the building of every problem
    (``mnls`` needs it; ``dnls`` takes its window height and edges where a line has none).
    """
    return _solve_prepared([_prepare(first_line + k, obj, default_method, limits, scenario)
                            for k, obj in enumerate(problems)])


def solve_lines(lines: Iterable[str | ProblemError], *, batch: int = 256,
                default_method: str = "dnls", limits: Limits = DEFAULT_LIMITS,
                scenario: Any = None) -> Iterator[dict[str, Any]]:
    """Solve JSON Lines, yielding exactly one result per line that is not blank.

    Blank (whitespace-only) lines are skipped without a result but counted in ``line``, so
    results keep the input's line numbers. Items may be :class:`ProblemError` instances for
    lines that could not be read (too long, not UTF-8, see
    :func:`~diffpos_services.wire.solve_io.read_lines`): they are answered with
    ``invalid_input``. Each line is decoded as soon as it is read; a batch holds validated
    problems (bounded by ``limits``) and plain lines (bounded: see the module docstring).
    ``scenario``: as :func:`solve_records`.
    """
    numbered = ((n, ln) for n, ln in enumerate(lines, start=1)
                if isinstance(ln, ProblemError) or ln.strip())
    prepared = (_read_line(n, ln, default_method, limits, scenario) for n, ln in numbered)
    while True:
        chunk = list(itertools.islice(prepared, max(batch, 1)))
        if not chunk:
            return
        yield from _solve_chunk(chunk, default_method, limits, scenario)


def _solve_chunk(chunk: list[_Prepared | _Plain], default_method: str, limits: Limits,
                 scenario: Any) -> list[dict[str, Any]]:
    """Result records of one batch of read lines, in order: the plain lines solved from
    stacked arrays (:func:`_solve_plain`), the others by :func:`_solve_prepared`."""
    plain: dict[tuple, list[int]] = {}
    for k, item in enumerate(chunk):
        if isinstance(item, _Plain):
            plain.setdefault(plain_group_key(item.decoded), []).append(k)
    if not plain:
        return _solve_prepared(chunk)  # type: ignore[arg-type]
    out: list[Any] = [None] * len(chunk)
    building = None if scenario is None else scenario.building
    for rows in plain.values():
        # fixed before the loop: a failing row is replaced in ``chunk`` by its prepared tuple
        step = _chunk_size_of(len(chunk[rows[0]].decoded.anchors_m))
        for lo in range(0, len(rows), step):
            part = rows[lo:lo + step]
            for k, rec in _solve_plain([chunk[k] for k in part], part, building):
                if rec is None:  # fails a check (or broke the batch): the one-line path
                    it = chunk[k]
                    chunk[k] = _prepare_line(it.line, it.text, default_method, limits, scenario)
                else:
                    out[k] = rec
    rest = [k for k, rec in enumerate(out) if rec is None]
    for k, rec in zip(rest, _solve_prepared([chunk[k] for k in rest]), strict=True):
        out[k] = rec
    return out


def _solve_plain(items: list[_Plain], rows: list[int], building: Any
                 ) -> list[tuple[int, dict[str, Any] | None]]:
    """Plain lines of one group solved in one D-NLS call from stacked arrays: ``(row,
    record)`` per line, the record ``None`` where the line must take the one-line path (it
    fails a check of :func:`~diffpos_services.wire.solve_line.problem_of`, or the call
    failed). The call's arguments are those :func:`_solve_group` builds from the same
    lines' problems, so the records are the same."""
    ok, *arrays = plain_arrays([it.decoded for it in items], building)
    good = np.flatnonzero(ok).tolist()
    if not good:
        return [(k, None) for k in rows]
    a, r, mask, sig, wh, delta = (None if v is None else v[good] if len(good) < len(items)
                                  else v for v in arrays)
    try:
        fix = dnls(a, r, sig, mask=mask, window_height_m=wh, delta_m=delta,
                   edge_x_m=None if building is None else tuple(
                       float(v) for v in building.edge_x_m),
                   gating=_DEFAULT_GATING, loss="linear", x0_m=None, z_starts_m=None)
    except Exception:  # the one-line path isolates the line that broke the batch
        return [(k, None) for k in rows]
    out: list[tuple[int, dict[str, Any] | None]] = [(k, None) for k in rows]
    for i, rec in zip(good, fix.to_records(), strict=True):
        it = items[i]
        out[i] = (rows[i], _final(it.line, it.ident, rec))
    return out


def _final(line: int, ident: Any, rec: dict[str, Any]) -> dict[str, Any]:
    """The result record of a solved line in :data:`RESULT_KEYS` order (as the end of
    :func:`_solve_prepared` builds it, without a lookup per key when ``rec`` is a
    :meth:`FixResult.to_records` record)."""
    if tuple(rec) != _FIX_KEYS:
        rec = {key: rec.get(key) for key in RESULT_KEYS}
        rec["line"], rec["id"] = line, ident
    else:
        rec = {"line": line, "id": ident, **rec, **_NO_FLOOR}
    if rec["status"] not in POSITION_STATUSES:
        rec.update(dict.fromkeys(_POSITION_KEYS))  # no trustworthy position: publish none
    return rec
