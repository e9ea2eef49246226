"""Allocation: which sensors (or which assignment of sensors to targets) a scan uses.

- :mod:`covnet.core.allocation.exact`: the problem (plans, constraints, the exact batched search
  ``allocate`` and the plain reference ``allocate_exhaustive``);
- :mod:`covnet.core.allocation._fast`: the fast path's batched bounds and evaluation;
- :mod:`covnet.core.allocation.search`: beyond exhaustive search, branch and bound (exact or
  bounded) and greedy, on :mod:`covnet.core.allocation.interval_bounds`' Loewner-interval
  bounds;
- :mod:`covnet.core.allocation.assignment`: many targets, each sensor on one target or off;
- :mod:`covnet.core.allocation.constraints`: excluded, required, at most ``max_active``.

The names most callers need are here, loaded when first asked for (start-up: a process that
only needs :mod:`covnet.core.allocation.constraints`, a sensor or the world, never loads the
allocator and its LAPACK routines).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from covnet.core.allocation.exact import (
        Allocation,
        AllocationPlan,
        BoundContext,
        Constraints,
        InfeasibleAllocation,
        MetricBound,
        allocate,
        allocate_exhaustive,
        allocation_rate,
        prepare,
        subset_covariance,
    )

__all__ = [
    "Allocation",
    "AllocationPlan",
    "BoundContext",
    "Constraints",
    "InfeasibleAllocation",
    "MetricBound",
    "allocate",
    "allocate_exhaustive",
    "allocation_rate",
    "prepare",
    "subset_covariance",
]


def __getattr__(name: str) -> Any:
    """The allocator's names, imported on first use (start-up: see the module docstring)."""
    if name in __all__:
        from covnet.core.allocation import exact

        return getattr(exact, name)
    raise AttributeError(f"module 'covnet.core.allocation' has no attribute {name!r}")
