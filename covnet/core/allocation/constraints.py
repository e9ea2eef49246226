"""Which subsets of the sensors an allocation may choose (:class:`Constraints`): a module of
its own so that a process that only builds a model (the world, a sensor) does not import the
allocator (:mod:`covnet.core.allocation` re-exports it)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Constraints:
    """Which subsets are feasible.

    - ``excluded``: failed / unavailable sensors (0-based), in no feasible subset;
    - ``required``: pinned sensors, in every feasible subset;
    - ``max_active``: budget, at most K sensors per subset (``None``: no budget).
    """

    excluded: frozenset[int] = frozenset()
    required: frozenset[int] = frozenset()
    max_active: int | None = None
