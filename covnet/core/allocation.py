"""Covariance-control sensor allocation: pick the subset whose fused covariance is closest to the
desired one (spec: /shared/spec/covariance_control.md)::

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
- :func:`allocate`, the fast exact path (:mod:`covnet.core._allocation_fast`): all subsets'
  reduced information form in batched numpy, per-metric lower bounds that prune only subsets that
  provably cannot reach the tie set, and exact evaluation (the reference's arithmetic) of the rest.
  A metric without a registered bound (e.g. a user's own function) gets a batched exhaustive
  search, still exact.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral

import numpy as np
from numpy.typing import NDArray

from covnet.core._allocation_fast import (
    METRIC_BOUNDS,
    BoundContext,
    MetricBound,
    fast_search,
    spd_inverse,
    tie_threshold,
)
from covnet.core.gaussian import Mat
from covnet.core.metrics import METRICS, MetricFn, get_metric

__all__ = [
    "METRIC_BOUNDS",
    "Allocation",
    "BoundContext",
    "Constraints",
    "InfeasibleAllocation",
    "MetricBound",
    "allocate",
    "allocate_exhaustive",
    "allocation_rate",
    "subset_covariance",
]


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


@dataclass(frozen=True, slots=True)
class Allocation:
    """The chosen subset of one allocation decision.

    ``subset``: chosen sensor indices, ascending (0-based); ``value``: ``f(P_i, P_d)`` of it;
    ``P``: its ``P_i = (P_pred⁻¹ + J_i)⁻¹``; ``n_feasible``: number of feasible subsets;
    ``n_evaluated``: subsets whose metric was evaluated exactly (``== n_feasible`` for the plain
    reference).
    """

    subset: tuple[int, ...]
    value: float
    P: NDArray[np.float64]
    n_feasible: int
    n_evaluated: int


class InfeasibleAllocation(ValueError):
    """No non-empty feasible subset exists (the message says why)."""


def subset_covariance(P_pred: Mat, gain_sum: Mat) -> Mat:
    """Information form ``P_i = (P_pred⁻¹ + J_i)⁻¹``, via Cholesky factorisations.

    ``P_pred⁻¹`` and ``(P_pred⁻¹ + J_i)⁻¹`` are each the SPD inverse ``L⁻ᵀ L⁻¹`` built from the
    Cholesky factor ``L`` (LAPACK ``potrf`` + ``potri``,
    :func:`covnet.core._allocation_fast.spd_inverse`), exactly symmetric.  Batched over
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
# validation (shared by both paths)
# --------------------------------------------------------------------------------------------


def _symmetrised(P: Mat, D: Mat, G: Mat) -> tuple[Mat, Mat, Mat]:
    """``(A + Aᵀ)/2`` of ``P_pred``, ``P_d`` and every gain, after checking each is finite and
    symmetric to a relative 1e-9 (``max|A - Aᵀ| <= 1e-9 max(A + Aᵀ)``; the largest entry of a
    PSD matrix is on its diagonal).  Both allocators then work on exactly symmetric inputs."""
    X = np.concatenate((P[None], D[None], G))
    Xt = X.transpose(0, 2, 1)
    S = X + Xt
    ok = (X - Xt).max(axis=(1, 2)) <= 1e-9 * S.max(axis=(1, 2))  # X - Xᵀ is antisymmetric
    if not ok.all():
        k = int(np.argmin(ok))
        name = "P_pred" if k == 0 else "P_d" if k == 1 else f"gains[{k - 2}]"
        if not np.isfinite(X[k]).all():
            raise ValueError(f"{name} has non-finite entries")
        raise ValueError(f"{name} must be symmetric (and positive semi-definite)")
    S *= 0.5
    return S[0], S[1], S[2:]


def _validate(
    P_pred: object,
    gains: object,
    P_d: object,
    metric: str | MetricFn,
    constraints: Constraints,
    tie_rtol: float,
) -> tuple[Mat, Mat, Mat, MetricFn, str | None, int]:
    """Check everything once, at the boundary; returns arrays, the metric, its registered name
    (``None`` for a user's function) and the effective budget."""
    P = np.asarray(P_pred, dtype=np.float64)
    if P.ndim != 2 or P.shape[0] != P.shape[1] or P.shape[0] == 0:
        raise ValueError(f"P_pred must be a non-empty square (n, n) matrix, got shape {P.shape}")
    n = P.shape[0]
    D = np.asarray(P_d, dtype=np.float64)
    if D.shape != (n, n):
        raise ValueError(f"P_d must be ({n}, {n}) like P_pred, got shape {D.shape}")
    G = np.asarray(gains, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (n, n):
        raise ValueError(f"gains must be (Ns, {n}, {n}) (one J_j per sensor), got {G.shape}")
    P, D, G = _symmetrised(P, D, G)
    if G.shape[0]:
        # the fast path's bounds rest on J_j >= 0 (Loewner); a rounding-level negative is fine
        w = np.linalg.eigvalsh(G)
        negative = w[:, 0] < -64.0 * n * np.finfo(np.float64).eps * np.abs(w).max(axis=1)
        if negative.any():
            j = int(np.argmax(negative))
            raise ValueError(
                f"gains[{j}] must be positive semi-definite (an information gain Hᵀ R⁻¹ H is), "
                f"smallest eigenvalue {w[j, 0]:.3g}"
            )
    if not (np.isfinite(tie_rtol) and tie_rtol >= 0):
        raise ValueError(f"tie_rtol must be finite and >= 0, got {tie_rtol}")
    if isinstance(metric, str):
        fn: MetricFn = get_metric(metric)
        name: str | None = metric
    elif callable(metric):
        fn = metric
        name = next((k for k, f in METRICS.items() if f is metric), None)
    else:
        raise TypeError(f"metric must be a registered name or a callable, got {type(metric)}")
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
    if Ns == 0:
        raise InfeasibleAllocation("no sensors: gains is empty, so no non-empty subset exists")
    if len(constraints.excluded) == Ns:
        raise InfeasibleAllocation(
            f"all {Ns} sensors are excluded, so no non-empty subset is feasible"
        )
    return P, G, D, fn, name, (Ns if K is None else int(K))


def _spd_error(exc: np.linalg.LinAlgError) -> ValueError:
    return ValueError(
        "P_pred must be symmetric positive definite and P_pred⁻¹ + J_i positive definite "
        f"(gains must be positive semi-definite): {exc}"
    )


# --------------------------------------------------------------------------------------------
# the two searches
# --------------------------------------------------------------------------------------------


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
    P, G, D, f, _, K = _validate(P_pred, gains, P_d, metric, constraints, tie_rtol)
    n = P.shape[0]
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
    gains: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    constraints: Constraints = Constraints(),
    tie_rtol: float = 1e-9,
) -> Allocation:
    """The fast exact path: the same :class:`Allocation` as :func:`allocate_exhaustive` (same
    subset, same value and ``P`` bits), evaluating the metric exactly on few subsets.

    Registered metrics with an entry in :data:`METRIC_BOUNDS` use bound-based pruning (see
    :mod:`covnet.core._allocation_fast`); any other metric function the batched exhaustive
    search.  ``P_pred`` ``(n, n)`` SPD, ``gains`` ``(Ns, n, n)`` PSD, ``P_d`` ``(n, n)``.
    """
    P, G, D, f, name, K = _validate(P_pred, gains, P_d, metric, constraints, tie_rtol)
    bound = METRIC_BOUNDS.get(name) if name is not None else None
    try:
        res = fast_search(
            P, G, D, f, bound, constraints.excluded, constraints.required, K, tie_rtol
        )
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    return Allocation(res.subset, res.value, res.P, res.n_feasible, res.n_evaluated)
