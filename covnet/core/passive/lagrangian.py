"""Lagrangian relaxation of the 3-D assignment (Pattipati et al., IEEE TAC 1992, style; spec
§8.3), with a valid lower bound and a feasible (upper-bound) recovery at every iteration.

Relax the sensor-3 constraints with multipliers ``u_k`` (``k = 1…n3``, ``u_0 ≡ 0``).  For fixed
``u``:

* ``d_ij = min_k (C_ijk − u_k)``, ``k*_ij = argmin_k`` (``k = 0`` included), ``(i, j) ≠ (0, 0)``;
* the tuples ``(0, 0, k)`` are unconstrained: take every ``k`` with ``C_00k − u_k < 0``;
* a 2-D assignment with dummies on ``d`` (one ``linear_sum_assignment`` on the augmented
  ``(n1+n2) × (n2+n1)`` matrix: real block ``d[1:, 1:]``, row ``i`` to its own dummy column
  ``d[i, 0]``, dummy row ``j`` to column ``j`` ``d[0, j]``, dummy-dummy block 0, else ``+inf``);
* ``L(u) = value(2-D) + Σ_k min(0, C_00k − u_k) + Σ_k u_k`` is a lower bound for any ``u``;
* subgradient ``g_k = 1 − #{(i, j) chosen with k*_ij = k} − [C_00k − u_k < 0]``.

Recovery: keep the relaxed pairs and solve pairs × sensor-3 measurements with the true costs; a
pair's dummy cost is ``min(C_ij0, C_i00 + C_0j0)`` (it may dissolve into its singletons), a dummy
row to ``k`` costs ``C_00k``.  Its cost is an upper bound.

Update ``u ← u + γ (UB* − L(u)) g / ‖g‖²`` (Polyak, best UB; ``γ`` halved after
``halve_after`` iterations without a better LB).  Stop when ``UB* − LB* ≤ rel_gap · max(1,
|UB*|)``, when ``g = 0`` (the relaxed solution is feasible, hence optimal) or after
``max_iter`` iterations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from covnet.core.gaussian import Mat, Vec
from covnet.core.passive.model import Association, AssocParams, Index, PassiveScan
from covnet.core.passive.sd import SDCosts, association_from_tuples, sd_costs

__all__ = ["LRResult", "associate_lr", "solve_lr"]

#: status codes of :class:`LRResult`
CONVERGED, ITERATION_LIMIT, INFEASIBLE = 0, 1, 2


@dataclass(frozen=True, slots=True)
class LRResult:
    """The best feasible tuples ``(q, 3)`` (dummy indexing), their cost ``upper`` (UB*), the best
    dual value ``lower`` (LB*), the iterations run, and ``status``/``message``: 0 converged (gap
    closed or ``g = 0``), 1 iteration limit (best feasible returned), 2 no feasible solution."""

    tuples: Index
    upper: float
    lower: float
    iterations: int
    status: int
    message: str


def _lsa(M: Mat) -> tuple[Index, Index] | None:
    """``linear_sum_assignment`` or ``None`` when no finite assignment exists."""
    if M.size == 0:
        e = np.zeros(0, dtype=np.intp)
        return e, e
    try:
        return linear_sum_assignment(M)
    except ValueError:  # "cost matrix is infeasible"
        return None


def _relaxed(C: Mat, u: Vec) -> tuple[float, Index, Index, Index, NDArray[np.bool_]] | None:
    """Solve the relaxed problem at ``u``: ``L(u)``, the chosen pairs ``(i, j)``, their ``k*``
    and the taken ``(0, 0, k)`` singletons (boolean over ``k = 1…n3``)."""
    N1, N2, _ = C.shape
    n1, n2 = N1 - 1, N2 - 1
    Cu = C - u
    ks = np.argmin(Cu, axis=2)
    d = np.take_along_axis(Cu, ks[..., None], axis=2)[..., 0]
    s00 = Cu[0, 0, 1:]
    take = s00 < 0
    M = np.full((n1 + n2, n2 + n1), np.inf)
    M[:n1, :n2] = d[1:, 1:]
    M[np.arange(n1), n2 + np.arange(n1)] = d[1:, 0]
    M[n1 + np.arange(n2), np.arange(n2)] = d[0, 1:]
    M[n1:, n2:] = 0.0
    sol = _lsa(M)
    if sol is None:
        return None
    rows, cols = sol
    real = ~((rows >= n1) & (cols >= n2))
    rows, cols = rows[real], cols[real]
    pi = np.where(rows < n1, rows + 1, 0)
    pj = np.where(cols < n2, cols + 1, 0)
    value = float(M[sol[0], sol[1]].sum())
    L = value + float(np.minimum(0.0, s00).sum()) + float(u[1:].sum())
    return L, pi, pj, ks[pi, pj], take


def _recover(C: Mat, pi: Index, pj: Index) -> tuple[float, Index] | None:
    """Feasible completion of the relaxed pairs with sensor 3 (true costs); ``None`` if none."""
    n3 = C.shape[2] - 1
    npair = pi.shape[0]
    R = np.full((npair + n3, n3 + npair), np.inf)
    R[:npair, :n3] = C[pi, pj, 1:]
    split = C[pi, 0, 0] + C[0, pj, 0]
    whole = C[pi, pj, 0]
    R[np.arange(npair), n3 + np.arange(npair)] = np.minimum(whole, split)
    R[npair + np.arange(n3), np.arange(n3)] = C[0, 0, 1:]
    R[npair:, n3:] = 0.0
    sol = _lsa(R)
    if sol is None:
        return None
    rows, cols = sol
    out: list[tuple[int, int, int]] = []
    for r, c in zip(rows.tolist(), cols.tolist(), strict=True):
        if r < npair:
            i, j = int(pi[r]), int(pj[r])
            if c < n3:
                out.append((i, j, c + 1))
            elif whole[r] <= split[r]:
                out.append((i, j, 0))
            else:
                out += [t for t in ((i, 0, 0), (0, j, 0)) if t != (0, 0, 0)]
        elif c < n3:
            out.append((0, 0, c + 1))
    t = np.asarray(out, dtype=np.intp).reshape(-1, 3)
    return float(R[rows, cols].sum()), t


def solve_lr(
    costs: SDCosts,
    max_iter: int = 100,
    rel_gap: float = 1e-3,
    step: float = 1.0,
    halve_after: int = 5,
) -> LRResult:
    """Subgradient optimisation of the relaxation (see the module docstring)."""
    C = costs.C
    n3 = C.shape[2] - 1
    u = np.zeros(n3 + 1)
    ub, lb = math.inf, -math.inf
    best: Index = np.zeros((0, 3), dtype=np.intp)
    gamma, stall = step, 0
    for it in range(1, max_iter + 1):
        rel = _relaxed(C, u)
        if rel is None:
            return LRResult(best, ub, lb, it, INFEASIBLE, "relaxed 2-D assignment infeasible")
        L, pi, pj, kstar, take = rel
        if L > lb:
            lb, stall = L, 0
        else:
            stall += 1
            if halve_after > 0 and stall >= halve_after:
                gamma, stall = 0.5 * gamma, 0
        rec = _recover(C, pi, pj)
        if rec is not None and rec[0] < ub:
            ub, best = rec
        g = 1.0 - np.bincount(kstar, minlength=n3 + 1)[1:] - take
        if not np.any(g):
            lb = max(lb, min(ub, L))  # relaxed solution feasible: optimal
            return LRResult(best, ub, lb, it, CONVERGED, "relaxed solution feasible (optimal)")
        if math.isfinite(ub) and ub - lb <= rel_gap * max(1.0, abs(ub)):
            return LRResult(best, ub, lb, it, CONVERGED, "duality gap closed")
        gap = (ub - L) if math.isfinite(ub) else 0.1 * (abs(L) + 1.0)
        u[1:] += gamma * gap * g / float(g @ g)
    status = ITERATION_LIMIT if math.isfinite(ub) else INFEASIBLE
    msg = "iteration limit" if math.isfinite(ub) else "no feasible solution found"
    return LRResult(best, ub, lb, max_iter, status, msg)


def associate_lr(scan: PassiveScan, params: AssocParams) -> Association:
    """Lagrangian relaxation on the §8.2 costs; ``info``: ``lower``, ``upper``, ``iterations``,
    ``n_tuples``."""
    costs = sd_costs(scan, params)
    res = solve_lr(
        costs, params.lr_max_iter, params.lr_rel_gap, params.lr_step, params.lr_halve_after
    )
    return association_from_tuples(
        costs,
        res.tuples,
        res.status,
        res.message,
        lower=res.lower,
        upper=res.upper,
        iterations=res.iterations,
        n_tuples=costs.n_tuples,
    )
