"""Covariance-control sensor allocation: pick the subset whose fused covariance is closest to the
desired one (``docs/maths/covariance_control.md``)::

    D_opt = argmin_{D_i in D_c} f(P_i, P_d),   P_i = (P⁻¹ + J_i)⁻¹,   J_i = sum_{j in D_i} J_j

with ``J_j = H_jᵀ R_j⁻¹ H_j``.

``P = P_pred`` is the predicted covariance, ``gains[j] = J_j`` each sensor's information gain,
``D_c`` the non-empty subsets allowed by :class:`Constraints`.

**Tie rule** (deterministic and implementation-independent): with ``f* = min f`` over the feasible
subsets, the tie set is ``{i : f_i <= f* + tie_rtol · max(|f*|, tiny)}``; among it the subset with
the fewest sensors wins, then the lexicographically smallest ascending index tuple.

Two implementations return the same :class:`Allocation`:

- :func:`allocate_exhaustive`, the plain reference: a loop over every feasible subset, one
  information-form solve and one metric call each;
- :func:`allocate`, the fast exact path (:mod:`covnet.core.allocation._fast`): all subsets'
  reduced information form in batched numpy, per-metric lower bounds that prune only subsets that
  provably cannot reach the tie set, and exact evaluation (the reference's arithmetic) of the rest.
  A metric without a registered bound (e.g. a user's own function) gets a batched exhaustive
  search, still exact.

**Plans.**  Everything that depends only on the gains and the constraints (their validation,
including the PSD check of every gain, the support of the reduced form, the per-subset sums of the
reduced information, the subset masks and, for small ``Ns``, every subset's exact ``J_i``) is
built once by :func:`prepare` into an :class:`AllocationPlan`; a running filter passes the plan to
:func:`allocate` at every scan (:class:`covnet.covariance_control.model.Model` holds it), leaving
only the ``P_pred`` / ``P_d`` dependent work per decision.  Passing the gains array still works: a
plan is then prepared inside the call.

**What is checked where.**  :func:`prepare`: gains shape, finiteness, symmetry, positive
semi-definiteness; constraint indices, exclusive sets, budget.  Every :func:`allocate` call:
``P_pred`` and ``P_d`` shape (against the plan), finiteness and symmetry; ``P_pred`` positive
definite (its Cholesky factorisation); the metric; ``tie_rtol``; the constraints, if given, equal
to the plan's.  (A plan remembers the last few checked ``P_d`` by their bytes: a ``P_d`` equal to
one already checked is not checked again, with the same result.)
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation._fast import (
    BoundContext,
    MetricBound,
    SearchTables,
    fast_search,
    spd_inverse,
    tie_threshold,
)
from covnet.core.allocation.constraints import Constraints
from covnet.core.gaussian import Mat
from covnet.core.metrics import METRICS, Metric, MetricFn, capability, get_entry

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


@dataclass(frozen=True, slots=True)
class Allocation:
    """The chosen subset of one allocation decision.

    ``subset``: chosen sensor indices, ascending (0-based); ``value``: ``f(P_i, P_d)`` of it;
    ``P``: its ``P_i = (P_pred⁻¹ + J_i)⁻¹``; ``n_feasible``: number of feasible subsets;
    ``n_evaluated``: subsets whose metric was evaluated exactly (``== n_feasible`` for the plain
    reference).  ``lower_bound``, ``gap``: what a search that may stop short of the optimum
    (:mod:`covnet.core.allocation.search`'s bounded and greedy modes) certifies, a lower bound of
    the
    optimum and ``(value - lower_bound) / |value|``; ``None`` from an exact search.
    """

    subset: tuple[int, ...]
    value: float
    P: NDArray[np.float64]
    n_feasible: int
    n_evaluated: int
    lower_bound: float | None = None
    gap: float | None = None


class InfeasibleAllocation(ValueError):
    """No non-empty feasible subset exists (the message says why)."""


def subset_covariance(P_pred: Mat, gain_sum: Mat) -> Mat:
    """Information form ``P_i = (P_pred⁻¹ + J_i)⁻¹``, via Cholesky factorisations.

    ``P_pred⁻¹`` and ``(P_pred⁻¹ + J_i)⁻¹`` are each the SPD inverse ``L⁻ᵀ L⁻¹`` built from the
    Cholesky factor ``L`` (LAPACK ``potrf`` + ``potri``,
    :func:`covnet.core.allocation._fast.spd_inverse`), exactly symmetric.  Batched over
    (broadcast) leading axes of both arguments; a matrix gets the same bits alone or in a stack.
    Raises ``numpy.linalg.LinAlgError`` unless both are positive definite.
    """
    P_pred = np.asarray(P_pred, dtype=np.float64)
    gain_sum = np.asarray(gain_sum, dtype=np.float64)
    return spd_inverse(spd_inverse(P_pred) + gain_sum)


def allocation_rate(counts: Sequence[int], n_sensors: int) -> float:
    """Allocation rate ``η = (1 / (N Ns)) sum_k N_k``: ``N_k = counts[k]`` sensors allocated at
    scan k, ``N = len(counts)`` scans, ``Ns = n_sensors``."""
    if n_sensors < 1:
        raise ValueError(f"n_sensors must be >= 1, got {n_sensors}")
    if len(counts) == 0:
        raise ValueError("counts is empty: the allocation rate needs at least one scan")
    c = np.asarray(counts, dtype=np.float64)
    if np.any(c < 0) or np.any(c > n_sensors):
        raise ValueError(f"every count must be in [0, {n_sensors}], got {list(counts)}")
    return float(c.sum() / (c.size * n_sensors))


# --------------------------------------------------------------------------------------------
# validation (shared by both paths) and the plan
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class AllocationPlan:
    """The part of an allocation problem that depends only on the gains and the constraints,
    validated and prepared once by :func:`prepare`, then passed to :func:`allocate` in place of
    the gains at every decision (the gains do not change between scans).

    ``gains``: the validated gains, symmetrised ``(J + Jᵀ)/2``, read-only ``(Ns, n, n)``;
    ``constraints``: the constraints it was prepared for (:func:`allocate` refuses others);
    ``n``: the state dimension; ``max_active``: the effective budget;
    ``infeasible``: why no non-empty subset is feasible (raised by :func:`allocate` as
    :class:`InfeasibleAllocation`), else ``None``; ``tables``: the search's gain-only tables
    (:class:`covnet.core.allocation._fast.SearchTables`: support of the gains, per-subset sums of
    the reduced information, subset masks, exact ``J_i`` of every subset for small ``Ns``).
    """

    gains: NDArray[np.float64]
    constraints: Constraints
    n: int
    max_active: int
    infeasible: str | None
    tables: SearchTables | None

    @property
    def n_sensors(self) -> int:
        return int(self.gains.shape[0])


def _checked_pd(
    P_pred: object, P_d: object, n: int | None = None, cache: dict[bytes, Mat] | None = None
) -> tuple[Mat, Mat]:
    """``P_pred`` and ``P_d`` as ``(n, n)`` float arrays, each checked finite and symmetric to a
    relative 1e-9 (``max|A - Aᵀ| <= 1e-9 max(A + Aᵀ)``; the largest entry of a PSD matrix is on
    its diagonal), returned as ``(A + Aᵀ)/2``.  (Positive definiteness of ``P_pred`` is checked
    by the Cholesky factorisation of the search itself, ``P_d``'s by the metrics that need it.)

    ``cache`` (a plan's): the checked ``P_d`` by the bytes of the given one, a read-only copy
    (a desired covariance changes rarely: a schedule); the same bits as checking it again."""
    P = np.asarray(P_pred, dtype=np.float64)
    if P.ndim != 2 or P.shape[0] != P.shape[1] or P.shape[0] == 0:
        raise ValueError(f"P_pred must be a non-empty square (n, n) matrix, got shape {P.shape}")
    if n is not None and P.shape[0] != n:
        raise ValueError(f"P_pred must be ({n}, {n}) like the plan's gains, got shape {P.shape}")
    n = P.shape[0]
    D = np.asarray(P_d, dtype=np.float64)
    if D.shape != (n, n):
        raise ValueError(f"P_d must be ({n}, {n}) like P_pred, got shape {D.shape}")
    if cache is None:
        return _symmetric(P, "P_pred"), _symmetric(D, "P_d")
    key = D.tobytes()
    D_checked = cache.get(key)
    if D_checked is None:
        D_checked = _symmetric(D, "P_d").copy()
        D_checked.flags.writeable = False
        if len(cache) >= 8:
            cache.clear()
        cache[key] = D_checked
    return _symmetric(P, "P_pred"), D_checked


_max = np.maximum.reduce
#: matrices of at most this many entries get :func:`_symmetric`'s shortcut test in Python floats
_SMALL = 64


def _symmetric(A: Mat, name: str) -> Mat:
    """``(A + Aᵀ)/2`` of one matrix after the check of :func:`_symmetrised` (same bits).

    Shortcut: an exactly symmetric, finite ``A`` (``A - Aᵀ`` has no non-zero and no NaN entry)
    with a non-negative largest entry passes that check and ``(A + Aᵀ)/2 = A`` (``2a/2 = a``;
    entries beyond ``DBL_MAX / 2`` aside), so ``A`` itself is returned, not copied.

    A small ``A`` with finite entries (a finite sum of its entries; else the numpy code below
    decides) is checked and symmetrised in Python floats, cheaper than numpy calls on a few
    entries and the same IEEE operations: ``a_ij == a_ji`` everywhere is the shortcut, otherwise
    the same test on ``max(A - Aᵀ)`` and ``max(A + Aᵀ)``, then ``(A + Aᵀ) * 0.5``."""
    At = A.T
    if A.size <= _SMALL:
        flat = A.ravel().tolist()
        if math.isfinite(sum(flat)):
            flat_t = At.ravel().tolist()
            if flat == flat_t:
                if max(flat) >= 0:
                    return A
            else:
                S = A + At  # the sums in numpy, the test on Python floats
                if max([a - b for a, b in zip(flat, flat_t, strict=True)]) <= 1e-9 * max(
                    [a + b for a, b in zip(flat, flat_t, strict=True)]
                ):
                    S *= 0.5
                    return S
    elif not (A - At).any() and _max(A, None) >= 0:
        return A
    S = A + At
    if not _max(A - At, None) <= 1e-9 * _max(S, None):  # written so that NaN fails
        if not np.isfinite(A).all():
            raise ValueError(f"{name} has non-finite entries")
        raise ValueError(f"{name} must be symmetric (and positive semi-definite)")
    S *= 0.5
    return S


def _symmetrised(X: Mat, names: Sequence[str] | None = None) -> Mat:
    """``(A + Aᵀ)/2`` of every matrix of the stack ``X``, after checking each is finite and
    symmetric to a relative 1e-9 (:func:`_checked_pd`).  Both allocators then work on exactly
    symmetric inputs (the same bits whichever path symmetrised them: elementwise arithmetic)."""
    Xt = X.transpose(0, 2, 1)
    S = X + Xt
    ok = (X - Xt).max(axis=(1, 2)) <= 1e-9 * S.max(axis=(1, 2))  # X - Xᵀ is antisymmetric
    if not ok.all():
        k = int(np.argmin(ok))
        name = names[k] if names is not None else f"gains[{k}]"
        if not np.isfinite(X[k]).all():
            raise ValueError(f"{name} has non-finite entries")
        raise ValueError(f"{name} must be symmetric (and positive semi-definite)")
    S *= 0.5
    return S


def prepare(gains: Mat, constraints: Constraints = Constraints()) -> AllocationPlan:
    """Validate the gains and the constraints once and build everything that depends only on
    them (:class:`AllocationPlan`); pass the plan to :func:`allocate` at every decision.

    Checks (the same messages as :func:`allocate` with a gains array): ``gains`` ``(Ns, n, n)``,
    each finite, symmetric and positive semi-definite (eigenvalues), the constraints' indices,
    exclusive sets and budget.  An infeasible constraint set (all sensors excluded, no sensors) is
    recorded, not raised: :func:`allocate` raises :class:`InfeasibleAllocation` with the plan."""
    G = np.asarray(gains, dtype=np.float64)
    if G.ndim != 3 or G.shape[1] != G.shape[2] or G.shape[1] == 0:
        raise ValueError(f"gains must be (Ns, n, n) (one J_j per sensor), got {G.shape}")
    return _prepare(G, constraints, tables=True)


def _prepare(G: Mat, constraints: Constraints, tables: bool) -> AllocationPlan:
    """:func:`prepare` on a gains array of checked shape (``tables=False``: validation only,
    for the plain reference)."""
    n = G.shape[1]
    if G.shape[0]:
        G = _symmetrised(G)
        # the fast path's bounds rest on J_j >= 0 (Loewner); a rounding-level negative is fine
        w = np.linalg.eigvalsh(G)
        negative = w[:, 0] < -64.0 * n * np.finfo(np.float64).eps * np.abs(w).max(axis=1)
        if negative.any():
            j = int(np.argmax(negative))
            raise ValueError(
                f"gains[{j}] must be positive semi-definite (an information gain Hᵀ R⁻¹ H is), "
                f"smallest eigenvalue {w[j, 0]:.3g}"
            )
    else:
        G = G.copy()
    G.flags.writeable = False
    if not isinstance(constraints, Constraints):
        raise TypeError(f"constraints must be a Constraints, got {type(constraints)}")
    Ns = G.shape[0]
    for label, idx in (("excluded", constraints.excluded), ("required", constraints.required)):
        bad = sorted(
            str(j)
            for j in idx
            if not isinstance(j, Integral) or isinstance(j, bool) or not 0 <= j < Ns
        )
        if bad:
            raise ValueError(
                f"{label} sensor indices must be integers in [0, {Ns}), got {', '.join(bad)}"
            )
    both = constraints.excluded & constraints.required
    if both:
        raise ValueError(f"sensors {sorted(both)} are both excluded and required")
    K = constraints.max_active
    if K is not None:
        if not isinstance(K, Integral) or isinstance(K, bool) or K < 1:
            raise ValueError(f"max_active must be an integer >= 1 or None, got {K!r}")
        if K < len(constraints.required):
            raise ValueError(
                f"max_active={K} is smaller than the {len(constraints.required)} required "
                f"sensors {sorted(constraints.required)}"
            )
    K_eff = Ns if K is None else int(K)
    infeasible = None
    if Ns == 0:
        infeasible = "no sensors: gains is empty, so no non-empty subset exists"
    elif len(constraints.excluded) == Ns:
        infeasible = f"all {Ns} sensors are excluded, so no non-empty subset is feasible"
    tab = None
    if tables and infeasible is None:
        tab = SearchTables(G, constraints.excluded, constraints.required, K_eff)
    return AllocationPlan(G, constraints, n, K_eff, infeasible, tab)


def _resolve_metric(metric: str | MetricFn | Metric) -> tuple[MetricFn, Metric | None]:
    """The metric function and its entry (:data:`covnet.core.metrics.METRICS`, or the
    :class:`~covnet.core.metrics.Metric` given; ``None`` for a user's plain function)."""
    if isinstance(metric, str):
        entry = get_entry(metric)
        return entry.fn, entry
    if isinstance(metric, Metric):
        return metric.fn, metric
    if callable(metric):
        return metric, next((m for m in METRICS.values() if m.fn is metric), None)
    raise TypeError(f"metric must be a registered name or a callable, got {type(metric)}")


def _check_rtol(tie_rtol: float) -> None:
    if not (math.isfinite(tie_rtol) and tie_rtol >= 0):
        raise ValueError(f"tie_rtol must be finite and >= 0, got {tie_rtol}")


def _gains_array(gains: object, n: int) -> Mat:
    G = np.asarray(gains, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (n, n):
        raise ValueError(f"gains must be (Ns, {n}, {n}) (one J_j per sensor), got {G.shape}")
    return G


class NotPositiveDefinite(ValueError):
    """A predicted covariance or an information sum that is not positive definite in the
    arithmetic (a ``ValueError``, as before): a bad input, or scales too far apart for double
    precision (``covnet`` names it as a numerical failure)."""


def _spd_error(exc: np.linalg.LinAlgError) -> ValueError:
    """The allocators' message for a matrix their arithmetic cannot factor: ``P_pred``, an
    information sum, or ``P_d`` for a metric that inverts it (kl, logdet: a singular ``P_d``
    was blamed on ``P_pred`` and the gains)."""
    return NotPositiveDefinite(
        "P_pred must be symmetric positive definite and P_pred⁻¹ + J_i positive definite "
        "(gains must be positive semi-definite), and P_d positive definite for a metric that "
        f"inverts it (kl, logdet): {exc}"
    )


# --------------------------------------------------------------------------------------------
# the two searches
# --------------------------------------------------------------------------------------------


def _checked(
    P_pred: Mat,
    gains: Mat,
    P_d: Mat,
    metric: str | MetricFn | Metric,
    constraints: Constraints,
    tie_rtol: float,
) -> tuple[Mat, Mat, AllocationPlan, MetricFn, Metric | None]:
    """The reference's checks of a problem, in its order and with its errors: ``P_pred`` and
    ``P_d``, the gains and constraints (their plan; infeasible constraints raised), the metric,
    the tie tolerance (the searches' :class:`~covnet.core.allocation.search_problem._Problem`
    makes the same)."""
    P, D = _checked_pd(P_pred, P_d)
    plan = _prepare(_gains_array(gains, P.shape[0]), constraints, tables=False)
    f, entry = _resolve_metric(metric)
    _check_rtol(tie_rtol)
    if plan.infeasible is not None:
        raise InfeasibleAllocation(plan.infeasible)
    return P, D, plan, f, entry


def allocate_exhaustive(
    P_pred: Mat,
    gains: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    constraints: Constraints = Constraints(),
    tie_rtol: float = 1e-9,
) -> Allocation:
    """The plain reference: every feasible subset in turn, ``P_i`` by the information form with
    Cholesky solves (:func:`subset_covariance`), one metric call per subset, then the tie rule
    (module docstring).  Clarity over speed: use :func:`allocate`, which returns the same."""
    P, D, plan, f, _ = _checked(P_pred, gains, P_d, metric, constraints, tie_rtol)
    G, K, n = plan.gains, plan.max_active, plan.n
    allowed = [j for j in range(G.shape[0]) if j not in constraints.excluded]
    subsets: list[tuple[int, ...]] = []
    values: list[float] = []
    try:
        # sizes ascending, each size in lexicographic order: the tie rule's preference order
        for size in range(1, min(K, len(allowed)) + 1):
            for subset in itertools.combinations(allowed, size):
                if not constraints.required <= set(subset):
                    continue
                J = np.zeros((n, n))
                for j in subset:
                    J = J + G[j]
                P_i = subset_covariance(P, J)
                value = float(np.asarray(f(P_i, D), dtype=np.float64))
                if not np.isfinite(value):
                    raise ValueError(f"metric returned a non-finite value for subset {subset}")
                subsets.append(subset)
                values.append(value)
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    threshold = tie_threshold(min(values), tie_rtol)
    best = next(i for i, v in enumerate(values) if v <= threshold)  # first in preference order
    J = np.zeros((n, n))
    for j in subsets[best]:
        J = J + G[j]
    return Allocation(
        subsets[best], values[best], subset_covariance(P, J), len(values), len(values)
    )


def allocate(
    P_pred: Mat,
    gains: Mat | AllocationPlan,
    P_d: Mat,
    metric: str | MetricFn,
    constraints: Constraints | None = None,
    tie_rtol: float = 1e-9,
) -> Allocation:
    """The fast exact path: the same :class:`Allocation` as :func:`allocate_exhaustive` (same
    subset, same value and ``P`` bits), evaluating the metric exactly on few subsets.

    ``gains``: either the ``(Ns, n, n)`` PSD gains (a plan is prepared internally, every call),
    or an :class:`AllocationPlan` from :func:`prepare`, which skips the gain-only work (validation
    incl. the PSD check, the reduced-form tables); ``constraints`` then defaults to the plan's,
    and other constraints are refused (prepare a plan per constraint set).  Checked per call:
    ``P_pred`` ``(n, n)`` and ``P_d`` ``(n, n)`` finite and symmetric (then symmetrised),
    ``P_pred`` positive definite (by its Cholesky factorisation), the metric and ``tie_rtol``.

    Metrics whose entry has a ``subset_bound`` (:class:`covnet.core.metrics.Metric`) use
    bound-based pruning (see :mod:`covnet.core.allocation._fast`); any other metric function the
    batched exhaustive search.
    """
    if isinstance(gains, AllocationPlan):
        plan = gains
        if constraints is not None and constraints != plan.constraints:
            raise ValueError(
                f"the plan was prepared for {plan.constraints}, not {constraints}: "
                "prepare a plan for these constraints"
            )
        P, D = _checked_pd(P_pred, P_d, plan.n, plan.tables.checked_d if plan.tables else None)
    else:
        P, D = _checked_pd(P_pred, P_d)
        c = Constraints() if constraints is None else constraints
        plan = _prepare(_gains_array(gains, P.shape[0]), c, tables=True)
    f, entry = _resolve_metric(metric)
    _check_rtol(tie_rtol)
    if plan.tables is None:
        raise InfeasibleAllocation(plan.infeasible)
    bound: MetricBound | None = None
    invariant = False
    if entry is not None:
        bound, invariant = capability(entry.subset_bound, MetricBound), entry.batch_invariant
    try:
        res = fast_search(P, D, f, bound, plan.tables, tie_rtol, invariant)
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    return Allocation(res.subset, res.value, res.P, res.n_feasible, res.n_evaluated)
