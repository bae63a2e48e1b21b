"""The batch solver behind ``diffpos solve``: decoded problems in, result records out.

Problems are validated by :func:`diffpos_services.wire.solve_io.parse_problem`, grouped by
what must be equal for one batched estimator call (method, anchor count, options), solved with
the vectorised estimators of :mod:`diffpos.estimators` and returned in input order. A problem
that breaks its batch is re-solved alone, so one bad line never costs the others their fixes.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from diffpos.estimators import GatingConfig, dnls, ippa, lls
from diffpos_services.wire.solve_io import (
    RESULT_KEYS,
    Problem,
    ProblemError,
    check_id,
    decode_line,
    invalid_record,
    parse_problem,
)

__all__ = ["solve_lines", "solve_records"]


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
    else:
        fix = ippa(
            a, r, sig, mask=mask, nlos=np.stack([p.nlos for p in problems]),
            nlos_bias_m=np.stack([p.nlos_bias_m for p in problems]), x0_m=x0,
            z_starts_m=p0.z_starts_m,
        )
    return fix.to_records()


def _solve_alone(prob: Problem) -> dict[str, Any]:
    try:
        return _solve_group([prob])[0]
    except Exception as exc:  # reported on this line; the filter goes on
        return invalid_record(f"the solver failed on this problem ({type(exc).__name__}: "
                              f"{str(exc)[:200]}); check the values for plausibility")


def _validate_all(items: list[Any], default_method: str, out: list, ids: list
                  ) -> dict[tuple, list[tuple[int, Problem]]]:
    """Parse every item; invalid ones get their record in ``out``, valid ones are grouped."""
    groups: dict[tuple, list[tuple[int, Problem]]] = {}
    for k, obj in enumerate(items):
        try:
            if isinstance(obj, ProblemError):
                raise obj
            if isinstance(obj, dict) and obj.get("id") is not None:
                ids[k] = check_id(obj["id"])
            prob = parse_problem(obj, default_method=default_method)
        except ProblemError as exc:
            out[k] = invalid_record(str(exc))
            continue
        groups.setdefault(prob.group_key(), []).append((k, prob))
    return groups


def solve_records(
    problems: Iterable[Any], *, default_method: str = "dnls", first_line: int = 1
) -> list[dict[str, Any]]:
    """Solve decoded problems (dicts, or :class:`ProblemError` instances for lines that
    failed to decode); return one JSON-ready result dict per problem, in order."""
    items = list(problems)
    out: list[dict[str, Any] | None] = [None] * len(items)
    ids: list[Any] = [None] * len(items)
    groups = _validate_all(items, default_method, out, ids)
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


def solve_lines(lines: Iterable[str | ProblemError], *, batch: int = 256,
                default_method: str = "dnls") -> Iterator[dict[str, Any]]:
    """Solve JSON Lines (blank lines skipped, but counted in ``line``), yielding results.

    Items may be :class:`ProblemError` instances for lines that could not be read (too
    long, not UTF-8, see :func:`~diffpos_services.wire.solve_io.read_lines`): they are
    answered with ``invalid_input``.
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
            solve_records([decode_line(ln) for _, ln in chunk], default_method=default_method),
            strict=True,
        ):
            rec["line"] = n
            yield rec
