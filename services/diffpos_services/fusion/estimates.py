"""The estimates of a fusion step in order, as the batches they were made in.

:meth:`FusionCore.step <diffpos_services.fusion.core.FusionCore.step>` returns an
:class:`Estimates`: a sequence of estimate structs (iterate, index, ``len``, compare with a
list, add to one) whose :attr:`~Estimates.parts` are the batches it was made of: column
batches (:class:`ColumnBatch`: a solved batch's :class:`EstimateRows`, whose
:class:`~diffpos_services.wire.messages.PositionEstimate` /
:class:`~diffpos_services.wire.messages.PositionEstimateV2` structs and verdict texts are made
only when read as such, identical to building them one by one) or lists of structs. A caller
that can use the columns (the replay's report) reads the parts; every other caller sees a
list of structs.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ColumnBatch", "EstimateRows", "Estimates", "finite_or_none_all"]


def finite_or_none_all(a: np.ndarray) -> list[float | None]:
    """:func:`~diffpos_services.wire.messages.finite_or_none` of every value of ``a`` (B,)."""
    o = a.astype(object)
    o[~np.isfinite(a)] = None
    return o.tolist()


@dataclass
class EstimateRows:
    """A batch's estimates as columns (one value per row, in publish order) and the anchor
    lists they share (``group[i]`` indexes ``shared``, see
    :func:`~diffpos_services.fusion.step.exclusion_groups`). Each value is the estimate's:
    ``pos[i]`` (``position_m``) where ``has_pos[i]``, else ``None`` is published; ``cov[i]``
    (``covariance_m2``) where ``has_pos[i] and has_cov[i]``; ``peb[i]`` (``peb_m``) where
    ``ok[i]``; ``floor[i]`` (``floor_index``) where ``has_pos[i]``; ``probs[i]``
    (``floor_probabilities``, v2; ``None``: a v1 batch, which has none)."""

    node_id: list[str]
    epoch: list[int]
    t_ns: list[int]
    status: list[str]
    ok: list[bool]
    has_pos: list[bool]
    has_cov: list[bool]
    pos: list[list[float]]
    cov: np.ndarray  # (B, 3, 3)
    peb: list[float | None]
    floor: list[int | None]
    group: list[int]
    shared: list[tuple[list[int], list[str], list[Any], bool]]
    in_wall: list[int]  # latest publish wall time of the row's ranges [ns], 0: none
    probs: list[list[float]] | None = None

    def latencies(self, now: int) -> list[int]:
        """The latencies [ns] a fusion records for these estimates published at ``now``
        (those with an input time, in order)."""
        return [now - w for w in self.in_wall if w > 0]


class ColumnBatch(Sequence):
    """The estimates of one solved batch: :attr:`rows` (columns), and their structs made by
    ``make()`` on first access (then kept)."""

    def __init__(self, rows: EstimateRows, make: Callable[[], list]) -> None:
        self.rows, self._make = rows, make
        self._items: list | None = None

    @property
    def items(self) -> list:
        if self._items is None:
            self._items = self._make()
        return self._items

    @property
    def made(self) -> bool:
        """Whether the structs were made."""
        return self._items is not None

    def __len__(self) -> int:
        return len(self.rows.node_id)

    def __getitem__(self, i):  # type: ignore[override]
        return self.items[i]

    def __iter__(self) -> Iterator[Any]:
        return iter(self.items)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and list(self) == list(other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"ColumnBatch({len(self)} estimates)"


class Estimates(Sequence):
    """Estimates in order, held as their batches (:attr:`parts`, none empty)."""

    def __init__(self, parts: Sequence[Sequence[Any]] = ()) -> None:
        self.parts: list[Sequence[Any]] = []
        for p in parts:
            self._take(p)

    def _take(self, p: Sequence[Any]) -> None:
        if isinstance(p, Estimates):
            self.parts += p.parts
        elif len(p):
            self.parts.append(p)

    def __iadd__(self, other: Sequence[Any]) -> Estimates:
        self._take(other)
        return self

    def __add__(self, other: Sequence[Any]) -> Estimates:
        return Estimates([self, other])

    def __radd__(self, other: Sequence[Any]) -> list:
        return list(other) + list(self)

    def __len__(self) -> int:
        return sum(map(len, self.parts))

    def __bool__(self) -> bool:
        return bool(self.parts)

    def __iter__(self) -> Iterator[Any]:
        return itertools.chain.from_iterable(self.parts)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, int) and len(self.parts) == 1:
            return self.parts[0][i]
        return list(self)[i]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and list(self) == list(other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"Estimates({list(self)!r})"
