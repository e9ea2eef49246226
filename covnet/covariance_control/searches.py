"""How a covariance-control decision searches the sensor subsets: the ``SEARCHES`` registry.

``allocation.search`` in a config names an entry; :func:`covnet.covariance_control.model.decide`
calls its ``decide``, and the config (:mod:`covnet.covariance_control.config`) asks the entry what
it needs and refuses, in the entry's own words, a combination it cannot serve.  To add a search:
write a ``decide(model, P_pred, P_d, metric, constraints) -> Allocation`` and add one
:class:`Search` entry to ``SEARCHES``.

**Many targets** (a ``targets:`` config): each entry's ``many`` is its decision over the
assignments of sensors to targets (:class:`ManySearch`: the exact assignment allocator, its
bounded and greedy searches of :mod:`covnet.core.allocation.assignment_search`), with the most
allowed sensors it can serve (``max_sensors``: the config refuses more in the entry's words).

The entries import the allocators when they first decide (start-up: the processes that never
decide, the world and the sensors, load no allocator).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import numpy as np

from covnet.core import registries
from covnet.core.allocation.constraints import Constraints
from covnet.core.gaussian import Mat

if TYPE_CHECKING:
    from covnet.core.allocation import Allocation, AllocationPlan


class SearchModel(Protocol):
    """What a search reads of :class:`covnet.covariance_control.model.Model`."""

    @property
    def sensor_ids(self) -> tuple[str, ...]: ...
    @property
    def constraints(self) -> Constraints: ...
    @property
    def tie_rtol(self) -> float: ...
    @property
    def gains(self) -> Mat: ...
    @property
    def plan(self) -> AllocationPlan: ...
    @property
    def search(self) -> Any: ...  # SearchSettings: its bounded_options()
    def plan_for(self, constraints: Constraints) -> AllocationPlan: ...


#: ``search(model, P_pred, P_d, metric, constraints)``: the decision of one scan
DecideFn = Callable[[SearchModel, Mat, Mat, str, Constraints], "Allocation"]

#: ``exact`` decisions over at most this many candidate sensors take the batched fast path
#: (:func:`covnet.core.allocation.allocate`, every subset bounded at once), branch and bound
#: (:func:`covnet.core.allocation.search.allocate_bnb`) beyond: the same subset, value and ``P``
#: bits, the
#: faster of the two from about 18-20 sensors on (measured on the bench problems of ``covnet
#: bench search``: at N = 20 branch and bound is faster for 4 of 5 metrics, at 16 for none)
FAST_PATH_MAX = 18

#: ``search: auto`` is ``exact`` up to this many candidate sensors (allowed, not excluded),
#: ``bounded`` beyond (``covnet bench search``: an exact decision at N = 24 takes 0.01-0.2 s,
#: at N = 32 a median of 0.04-2.2 s by metric but up to minutes at a near tie)
AUTO_EXACT_MAX = 24
#: the options that only ``bounded`` (and ``auto``, for its bounded part) uses
BOUNDED_OPTIONS = ("gap", "time_limit_s", "node_limit")


#: ``search: auto`` with search cells (surveillance) is ``exact`` while a scan has at most this
#: many assignments ``(T + C + 1)^n`` (n sensors that can be on), ``greedy`` beyond (with its
#: certified bound): cells of equal mass make exact ties that the exact allocator enumerates,
#: and the bounded search's dual steps grow with the cells (a decision over 64 cells took
#: 60-90 s with 4 sensors)
AUTO_MODES_MAX = 4**8

#: the exact assignment allocator's limit (its tables have 2^N entries:
#: :data:`covnet.core.allocation.assignment.MAX_SENSORS`, not imported here for the start-up
#: time of every node process; a test keeps the two equal)
MANY_EXACT_MAX = 22


class ManyDecision(NamedTuple):
    """A many-target decision: per sensor a target or ``-1``, ``F``, per-target values, ``P``
    ``(T, n, n)``, exact evaluations, and the certificate (``None``: exact)."""

    assignment: tuple[int, ...]
    value: float
    values: tuple[float, ...]
    P: Mat
    n_evaluated: int
    lower_bound: float | None
    gap: float | None


#: ``many(settings, P_pred, J, P_d, metric, weights, feasible, constraints, tie_rtol, cells)``
#: (``cells``: the search cells of a surveillance scan, a :class:`~covnet.core.allocation.
#: assignment.CellTerms`, or None)
ManyFn = Callable[[Any, Mat, Mat, Mat, str, Any, Any, Any, float, Any], ManyDecision]


@dataclass(frozen=True)
class ManySearch:
    """A search's many-target form: ``decide`` and the most sensors that can be on that it
    serves (``None``: any number)."""

    decide: ManyFn
    max_sensors: int | None = None


def _many_exact(
    settings: Any, P_pred: Mat, J: Mat, P_d: Mat, metric: str, w: Any, feas: Any, mc: Any,
    tie_rtol: float, cells: Any = None,
) -> ManyDecision:  # fmt: skip
    """The exact assignment allocator (the plain enumeration's assignment, bit for bit)."""
    # the allocator: start-up of the processes that never decide
    from covnet.core.allocation.assignment import allocate_assignments

    a = allocate_assignments(P_pred, J, P_d, metric, w, feas, mc, tie_rtol, cells=cells)
    return ManyDecision(a.assignment, a.value, a.values, a.P, a.n_evaluated, None, None)


def _many_bounded(
    settings: Any, P_pred: Mat, J: Mat, P_d: Mat, metric: str, w: Any, feas: Any, mc: Any,
    tie_rtol: float, cells: Any = None,
) -> ManyDecision:  # fmt: skip
    """Greedy and the Lagrangian bound, stopped at the options' gap, time or node limit."""
    # the allocator: start-up of the processes that never decide
    from covnet.core.allocation.assignment_search import allocate_assignments_bounded

    gap, limit_s, nodes = settings.bounded_options()
    r = allocate_assignments_bounded(
        P_pred, J, P_d, metric, w, feas, mc, tie_rtol,
        cells=cells, rel_gap=gap, time_limit_s=limit_s, node_limit=nodes,
    )  # fmt: skip
    return ManyDecision(r.assignment, r.value, r.values, r.P, r.n_evaluated, r.lower_bound, r.gap)


def _many_greedy(
    settings: Any, P_pred: Mat, J: Mat, P_d: Mat, metric: str, w: Any, feas: Any, mc: Any,
    tie_rtol: float, cells: Any = None,
) -> ManyDecision:  # fmt: skip
    """Forward greedy, moves and 1-swaps, with the Lagrangian bound."""
    # the allocator: start-up of the processes that never decide
    from covnet.core.allocation.assignment_search import allocate_assignments_greedy

    r = allocate_assignments_greedy(P_pred, J, P_d, metric, w, feas, mc, tie_rtol, cells=cells)
    return ManyDecision(r.assignment, r.value, r.values, r.P, r.n_evaluated, r.lower_bound, r.gap)


@dataclass(frozen=True)
class Search:
    """One way to search the subsets, and what it asks of the rest of the configuration:

    - ``words``: what it does, in a few words (the config's refusals quote them);
    - ``needs``: what each metric's entry must have (``"interval_bound"``:
      :attr:`covnet.core.metrics.Metric.interval_bound`);
    - ``information_form``: it needs a fusion centre in the information form (the gains ``J_j``
      of the decision are the centre's);
    - ``reports_gap``: its decisions carry a certified ``lower_bound`` and ``gap``;
    - ``options``: the ``allocation`` options it reads (the config refuses the others);
    - ``resolve``: for a search that stands for others (``auto``), the entry it is with this
      many candidate sensors (the needs and the decision are then that entry's);
    - ``many``: its many-target form (:class:`ManySearch`), ``resolve_many`` as ``resolve``
      for a ``targets:`` config."""

    name: str
    decide: DecideFn
    words: str
    needs: frozenset[str] = frozenset()
    information_form: bool = False
    reports_gap: bool = False
    options: tuple[str, ...] = ()
    resolve: Callable[[int], str] | None = None
    many: ManySearch | None = None
    resolve_many: Callable[[int, int | None], str] | None = None

    def resolved(self, n_candidates: int) -> Search:
        """The entry that decides with ``n_candidates`` candidate sensors."""
        return self if self.resolve is None else SEARCHES[self.resolve(n_candidates)]

    def resolved_many(self, n_candidates: int, modes: int | None = None) -> Search:
        """The entry that decides a many-target scan with ``n_candidates`` sensors (``modes``:
        with search cells, the modes a sensor has, ``T + C + 1``)."""
        if self.resolve_many is None:
            return self
        return SEARCHES[self.resolve_many(n_candidates, modes)]


def decide_many(
    settings: Any, P_pred: Mat, J: Mat, P_d: Mat, metric: str, w: Any, feas: Any, mc: Any,
    tie_rtol: float, cells: Any = None,
) -> ManyDecision:  # fmt: skip
    """A many-target scan's decision by the configured entry (``settings``: the model's
    ``SearchSettings``), ``auto`` resolved with the sensors that can be on this scan
    (``cells``: a surveillance scan's search cells, or None)."""
    can = feas.any(axis=1) if feas.shape[1] else np.zeros(feas.shape[0], dtype=bool)
    if cells is not None and cells.feasible.size:
        can = can | cells.feasible.any(axis=1)
    n = sum(1 for j in range(feas.shape[0]) if j not in mc.excluded and bool(can[j]))
    modes = None if cells is None else P_pred.shape[0] + int(cells.u.shape[0]) + 1
    entry = SEARCHES[settings.mode].resolved_many(n, modes)
    assert entry.many is not None
    return entry.many.decide(settings, P_pred, J, P_d, metric, w, feas, mc, tie_rtol, cells)


def feasible_count(n_sensors: int, c: Constraints) -> int:
    """The number of non-empty subsets of ``n_sensors`` sensors that ``c`` allows."""
    free = n_sensors - len(c.excluded) - len(c.required)
    r = len(c.required)
    K = n_sensors if c.max_active is None else c.max_active
    return sum(math.comb(free, k - r) for k in range(max(r, 1), min(K, free + r) + 1))


def _exact(model: SearchModel, P_pred: Mat, P_d: Mat, metric: str, c: Constraints) -> Allocation:
    """Up to ``FAST_PATH_MAX`` candidates the fast path with the plan for ``c``
    (:meth:`Model.plan_for`, prepared once per set), branch and bound beyond, both the
    exhaustive search's result bit for bit.  (The allocators are imported at the first
    decision: start-up of the processes that never decide.)"""
    if len(model.sensor_ids) - len(c.excluded) <= FAST_PATH_MAX:
        # the allocator (and scipy.linalg): start-up of the processes that never decide
        from covnet.core.allocation import allocate

        plan = model.plan if c == model.constraints else model.plan_for(c)
        return allocate(P_pred, plan, P_d, metric, tie_rtol=model.tie_rtol)
    from covnet.core.allocation import Allocation
    from covnet.core.allocation.search import allocate_bnb

    res = allocate_bnb(P_pred, model.gains, P_d, metric, c, model.tie_rtol)
    n_feasible = feasible_count(len(model.sensor_ids), c)
    return Allocation(res.subset, res.value, res.P, n_feasible, res.n_evaluated)


def _bounded(model: SearchModel, P_pred: Mat, P_d: Mat, metric: str, c: Constraints) -> Allocation:
    """Branch and bound stopped at the options' gap, time or node limit (``bounded_options``).
    (Imported here: start-up of the processes that never decide.)"""
    from covnet.core.allocation import Allocation
    from covnet.core.allocation.search import allocate_bnb

    n_feasible = feasible_count(len(model.sensor_ids), c)
    if n_feasible == 1:
        # one feasible subset (every allowed sensor required: ``covnet bench up --sensors``):
        # it is the optimum, so its value is its certified lower bound (gap 0), what the
        # bounded search returns too, without the root relaxation it would solve first
        # (53 ms a scan at N = 64)
        res = allocate_bnb(P_pred, model.gains, P_d, metric, c, model.tie_rtol)
        return Allocation(res.subset, res.value, res.P, 1, res.n_evaluated, res.value, 0.0)
    gap, limit_s, nodes = model.search.bounded_options()
    res = allocate_bnb(
        P_pred,
        model.gains,
        P_d,
        metric,
        c,
        model.tie_rtol,
        rel_gap=gap,
        time_limit_s=limit_s,
        node_limit=nodes,
    )
    return Allocation(
        res.subset, res.value, res.P, n_feasible, res.n_evaluated, res.lower_bound, res.gap
    )


def _greedy(model: SearchModel, P_pred: Mat, P_d: Mat, metric: str, c: Constraints) -> Allocation:
    """Forward/backward greedy and swaps, with the root lower bound.  (Imported here: start-up
    of the processes that never decide.)"""
    from covnet.core.allocation import Allocation
    from covnet.core.allocation.search import allocate_greedy

    res = allocate_greedy(P_pred, model.gains, P_d, metric, c, model.tie_rtol)
    n_feasible = feasible_count(len(model.sensor_ids), c)
    return Allocation(
        res.subset, res.value, res.P, n_feasible, res.n_evaluated, res.lower_bound, res.gap
    )


def _auto_resolve(n_candidates: int) -> str:
    return "exact" if n_candidates <= AUTO_EXACT_MAX else "bounded"


def _auto_resolve_many(n_candidates: int, modes: int | None = None) -> str:
    if modes is not None:  # search cells: exact while the assignments modes^n are few
        return "exact" if modes**n_candidates <= AUTO_MODES_MAX else "greedy"
    return "exact" if n_candidates <= MANY_EXACT_MAX else "bounded"


def _auto(model: SearchModel, P_pred: Mat, P_d: Mat, metric: str, c: Constraints) -> Allocation:
    """The decision of the entry ``auto`` stands for with the configured candidates."""
    n = len(model.sensor_ids) - len(model.constraints.excluded)
    return SEARCHES[_auto_resolve(n)].decide(model, P_pred, P_d, metric, c)


EXACT = Search(
    "exact",
    _exact,
    "the exhaustive search's subset, value and P bit for bit: the batched fast path for small "
    "networks, branch and bound beyond",
    many=ManySearch(_many_exact, MANY_EXACT_MAX),
)
BOUNDED = Search(
    "bounded",
    _bounded,
    "branch and bound stopped at the relative gap, time_limit_s or node_limit, with a "
    "certified lower bound and gap",
    needs=frozenset({"interval_bound"}),
    information_form=True,
    reports_gap=True,
    options=BOUNDED_OPTIONS,
    many=ManySearch(_many_bounded),
)
GREEDY = Search(
    "greedy",
    _greedy,
    "forward/backward greedy and swaps, with the root lower bound",
    information_form=True,
    reports_gap=True,
    many=ManySearch(_many_greedy),
)
AUTO = Search(
    "auto",
    _auto,
    f"exact up to {AUTO_EXACT_MAX} candidate sensors, bounded beyond",
    options=BOUNDED_OPTIONS,
    resolve=_auto_resolve,
    many=ManySearch(_many_exact),
    resolve_many=_auto_resolve_many,
)

SEARCHES: dict[str, Search] = {s.name: s for s in (AUTO, EXACT, BOUNDED, GREEDY)}
registries.ship("covnet.covariance_control.searches.SEARCHES", SEARCHES)
