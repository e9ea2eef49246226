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

    def without(self, unavailable: frozenset[int]) -> Constraints:
        """These constraints while the sensors ``unavailable`` are down (failed, seen at run
        time): they join the excluded set, in no feasible subset, and a required one stops
        being required.  (A failed required sensor once stopped being required without being
        excluded: the allocator went on choosing a dead sensor and counting its information.)"""
        if not unavailable:
            return self
        return Constraints(
            excluded=self.excluded | unavailable,
            required=self.required - unavailable,
            max_active=self.max_active,
        )
