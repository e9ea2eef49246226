"""Per-scan rows kept for a run's results, stored compactly.

A long network run keeps every scan's row (the allocation, the estimate, its covariance, NEES,
latencies) until it writes its results once at the end.  Kept as Python lists of small numpy
arrays and Python numbers that costs about 1 KB per scan of object headers; a :class:`Column`
stores the same values in blocks of :data:`BLOCK` rows of one dtype, so a scan costs its rows'
own bytes (8 sensors' mask, a 4-vector and two 4 x 4 matrices: ~330 B) and memory grows by one
block at a time.  :meth:`Column.array` gives the stacked array, with the values bit for bit as
``np.array(list_of_rows, dtype)`` would.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

__all__ = ["BLOCK", "Column"]

BLOCK = 1024
"""Rows per block."""


class Column:
    """Rows of one ``shape`` and ``dtype`` appended one at a time (a list's ``append``,
    ``len`` and truthiness; iteration yields the rows)."""

    def __init__(self, shape: tuple[int, ...] = (), dtype: DTypeLike = np.float64) -> None:
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        self._blocks: list[NDArray[Any]] = []
        self._n = 0

    def append(self, row: ArrayLike) -> None:
        """Append one row (cast to the column's dtype; its shape must be the column's)."""
        i = self._n % BLOCK
        if i == 0:
            self._blocks.append(np.empty((BLOCK, *self.shape), dtype=self.dtype))
        self._blocks[-1][i] = row
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def __bool__(self) -> bool:
        return self._n > 0

    def __iter__(self) -> Iterator[Any]:
        for b, block in enumerate(self._blocks):
            yield from block[: min(BLOCK, self._n - b * BLOCK)]

    def array(self) -> NDArray[Any]:
        """The rows so far as one new ``(len, *shape)`` array."""
        if not self._blocks:
            return np.empty((0, *self.shape), dtype=self.dtype)
        out = np.concatenate(self._blocks)[: self._n]
        return out.copy() if out.base is not None else out
