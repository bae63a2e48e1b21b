"""The estimates of a fusion step in order, as the parts they were made in.

:meth:`FusionCore.step <diffpos_services.fusion.core.FusionCore.step>` returns an
:class:`Estimates`: a sequence of estimate structs (iterate, index, ``len``, compare with a
list, add to one) whose :attr:`~Estimates.parts` are the batches it was made of, lists of
structs or column batches (:class:`~diffpos_services.fusion.estimates_v1.V1Batch`) that make
their structs only when read as such. A caller that can use the columns (the replay's
report) reads the parts; every other caller sees a list.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence
from typing import Any

__all__ = ["Estimates"]


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
