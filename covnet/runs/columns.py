"""Per-scan rows kept for a run's results, stored compactly, off the heap once a block is full.

A long network run keeps every scan's row (the allocation, the estimate, its covariance, NEES,
latencies) until it writes its results once at the end.  Kept as Python lists of small numpy
arrays and Python numbers that costs about 1 KB per scan of object headers; a :class:`Column`
stores the same values in blocks of :data:`BLOCK` rows of one dtype, so a scan costs its rows'
own bytes (8 sensors' mask, a 4-vector and two 4 x 4 matrices: ~330 B).  A full block is
written to the column's spill file (an anonymous temporary file: unlinked at once, so nothing
is left behind even after a SIGKILL) and dropped, so a process's resident memory stays flat
however long the run (the soak of ``covnet bench soak``): only the block being filled is in
memory.  :meth:`Column.array` gives the stacked array, with the values bit for bit as
``np.array(list_of_rows, dtype)`` would.
"""

from __future__ import annotations

import contextlib
import json
import math
import tempfile
from collections.abc import Iterator
from typing import IO, Any

import numpy as np
from numpy.typing import ArrayLike, DTypeLike, NDArray

__all__ = ["BLOCK", "Column", "Records"]

BLOCK = 1024
"""Rows per block."""


class _Spilling:
    """What a store with a spill file shares: closing it, also when garbage-collected."""

    #: no spill file yet; also on an instance whose ``__init__`` a Ctrl-C cut short, which
    #: ``__del__`` then closes without an "Exception ignored ... AttributeError" traceback
    _spill: IO[bytes] | None = None

    _n = 0  # rows or records held

    def _spill_out(self, prefix: str, data: bytes) -> None:
        """Append ``data`` to the spill file (made at the first block; an error of it names
        the folder: :func:`_named_spill_errors`)."""
        with _named_spill_errors():
            if self._spill is None:
                self._spill = tempfile.TemporaryFile(prefix=prefix)
            self._spill.seek(0, 2)
            self._spill.write(data)

    def __len__(self) -> int:
        return self._n

    def __bool__(self) -> bool:
        return self._n > 0

    def close(self) -> None:
        """Drop the spill file (also done when the store is garbage-collected)."""
        if self._spill is not None:
            self._spill.close()
            self._spill = None

    def __del__(self) -> None:
        self.close()


class Column(_Spilling):
    """Rows of one ``shape`` and ``dtype`` appended one at a time (a list's ``append``,
    ``len`` and truthiness; iteration yields the rows)."""

    def __init__(self, shape: tuple[int, ...] = (), dtype: DTypeLike = np.float64) -> None:
        self.shape, self.dtype = tuple(shape), np.dtype(dtype)
        self._block: NDArray[Any] | None = None
        self._spill: IO[bytes] | None = None
        self._spilled = 0  # rows in the spill file (whole blocks)
        self._n = 0

    def append(self, row: ArrayLike) -> None:
        """Append one row (cast to the column's dtype; its shape must be the column's)."""
        i = self._n % BLOCK
        if i == 0:
            if self._block is not None:
                self._write(self._block)
            self._block = np.empty((BLOCK, *self.shape), dtype=self.dtype)
        assert self._block is not None
        self._block[i] = row
        self._n += 1

    def _write(self, block: NDArray[Any]) -> None:
        self._spill_out("covnet-column-", np.ascontiguousarray(block).tobytes())
        self._spilled += BLOCK

    def _read_spilled(self) -> NDArray[Any]:
        if self._spill is None or self._spilled == 0:
            return np.empty((0, *self.shape), dtype=self.dtype)
        self._spill.seek(0)
        data = self._spill.read(self._spilled * self.dtype.itemsize * math.prod(self.shape))
        return np.frombuffer(data, dtype=self.dtype).reshape((self._spilled, *self.shape)).copy()

    def __iter__(self) -> Iterator[Any]:
        yield from self.array()

    def array(self) -> NDArray[Any]:
        """The rows so far as one new ``(len, *shape)`` array."""
        head = self._read_spilled()
        if self._block is None:
            return head
        tail = self._block[: self._n - self._spilled]
        if not len(head):
            return tail.copy()
        return np.concatenate([head, tail])


@contextlib.contextmanager
def _named_spill_errors() -> Iterator[None]:
    """An ``OSError`` of a spill file (an anonymous file: its error names no file, so a full
    ``$TMPDIR`` was reported as a bare "No space left on device", the disk of ``--out``
    having room) raised again naming the folder and what the file holds."""
    try:
        yield
    except OSError as exc:
        if exc.filename is not None or exc.errno is None:
            raise
        where = f"{tempfile.gettempdir()} (the spill file of a long run's per-scan rows; $TMPDIR)"
        raise OSError(exc.errno, exc.strerror, where) from exc


class Records(_Spilling):
    """Per-scan records of varying shape (JSON-able dicts: what a run's JSON file lists scan by
    scan), appended one at a time (a list's ``append``, ``len``, truthiness and iteration);
    every :data:`BLOCK` records go to a spill file (an anonymous temporary file, as
    :class:`Column`'s) as lines of JSON, so only the block being filled is in memory.  Read
    back (iteration, :meth:`list`) they are what ``json.loads(json.dumps(record))`` gives: the
    same JSON when written again (a tuple is a list there too)."""

    def __init__(self) -> None:
        self._tail: list[Any] = []
        self._spill = None
        self._n = 0

    def append(self, record: Any) -> None:
        self._tail.append(record)
        self._n += 1
        if len(self._tail) >= BLOCK:
            self._spill_out(
                "covnet-records-", "".join(json.dumps(r) + "\n" for r in self._tail).encode()
            )
            self._tail = []

    def __iter__(self) -> Iterator[Any]:
        if self._spill is not None:
            self._spill.seek(0)
            for line in self._spill:
                yield json.loads(line)
        yield from (json.loads(json.dumps(r)) for r in self._tail)

    def list(self) -> list[Any]:
        """Every record, in order."""
        return list(self)
