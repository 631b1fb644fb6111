"""Model parameter values of many sets as one array: the fits' batches hand the forward
model's launches their sets' values as rows, not as a dict of arrays per name."""

from __future__ import annotations

import functools
from collections.abc import Mapping

import numpy as np


class ValueTable(Mapping):
    """{name: (n,)} model parameter values of ``n`` sets held as one array (names, n): a
    fit group's sets (:meth:`tawarp.fit.problems.ValueLayout.table`) and a launch's merged
    groups (:func:`tawarp.fit.problems.run_sets`) move to the engine's table as blocks of
    rows, where a dict of rows cost a launch of a hundred groups a copy per group and name.
    Reads as the dict it stands for."""

    __slots__ = ("names", "array", "_row")

    def __init__(self, names: tuple[str, ...], array: np.ndarray):
        self.names, self.array = names, array
        self._row = row_of(names)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.array[self._row[name]]

    def __contains__(self, name) -> bool:
        return name in self._row

    def __iter__(self):
        return iter(self.names)

    def __len__(self) -> int:
        return len(self.names)


@functools.lru_cache(maxsize=256)
def row_of(names: tuple[str, ...]) -> dict[str, int]:
    """{name: its row} of a table of ``names`` (a fit's groups share a few name lists)."""
    return {k: r for r, k in enumerate(names)}


@functools.lru_cache(maxsize=1024)
def rows_in(names: tuple[str, ...], of: tuple[str, ...]) -> np.ndarray:
    """The rows of a table of ``names`` that hold the names ``of``, in their order."""
    row = row_of(names)
    return np.array([row[k] for k in of], dtype=np.intp)
