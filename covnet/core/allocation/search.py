"""Sensor allocation beyond exhaustive search: branch and bound (exact or bounded) and greedy.

The problem is :mod:`covnet.core.allocation`'s::

    D_opt = argmin_{D ∈ D_c} f(P(D), P_d),   P(D) = (P_pred⁻¹ + Σ_{j∈D} J_j)⁻¹,

with the same constraints (:class:`~covnet.core.allocation.Constraints`) and the same tie rule
(values within ``tie_rtol`` of the minimum: fewest sensors, then the lexicographically smallest
ascending index tuple).

**Branch and bound** (:func:`allocate_bnb`).  A node fixes, for the first ``d`` sensors of a
*branching order*, which are in (the included set ``I``) and which are out; the rest ``U`` are
undecided.  Every completion ``D`` obeys ``A = P(I ∪ U) ⪯ P(D) ⪯ P(I) = B`` (Loewner), so the
interval bounds of :mod:`covnet.core.allocation.interval_bounds` bound every completion's value
from below.
The include child keeps its parent's ``A`` and gets a new ``B = P(I + j)``, the exclude child
keeps ``B`` and gets a new ``A = P(I ∪ U - j)``: one new endpoint per child, its summary computed
for a whole batch of nodes at once.  Each include child *is* a feasible subset (``I + j``, the
rest left out): a *candidate*, whose value is bounded below by the degenerate interval
``[B, B]`` (no extra cost).

The covariances are computed in the reduced information form (as
:mod:`covnet.core.allocation._fast`): with ``s`` the support of the gains (the positions, for
position sensors), ``C = P_pred[s, s]``, ``Kᵀ = C⁻¹ P_pred[s, :]`` (a Cholesky solve) and
``P∞ = P_pred - K P_pred[s, :]``::

    P(S) = P∞ + K Z⁻¹ Kᵀ,    Z = C⁻¹ + Σ_{j∈S} J_j[s, s],

so a node carries the ``r x r`` information ``Z`` of ``I``, and a child costs one small inverse
and one ``(r², n²)`` product.  Their rounding error is covered by the bounds' error model
(:func:`covnet.core.allocation.interval_bounds.search_context`).

**Relaxation** (frobenius, kl, logdet; ``r = 2``): the Loewner interval ``[A, B]`` has
``n(n+1)/2`` dimensions, the node's completions only the 3 of ``Z ∈ [Z(I), Z(I ∪ U)]``.  For
these metrics, convex in ``Z`` or in ``W = Z⁻¹`` (logdet: on the nodes where it is), a few
projected-gradient steps on that 3-dimensional interval give a tangent-plane lower bound
(:class:`_Relaxation`), applied to every node the interval bound keeps (down to one undecided
sensor: at 32-40 paper-like sensors, refining only nodes with 6 or more undecided left the last
five levels unpruned, most of the tree); on the paper-like problems it removes 95-99 % of the
nodes the interval bound keeps.  What it cannot prune (kl, logdet, frobenius at 32-40 sensors):
nodes whose interval contains the continuous minimiser, whose value is within about ``1e-8`` of
the discrete optimum on those problems, so no continuous bound can separate them; the tree then
enumerates their completions near that point (not ties: one or two subsets within ``tie_rtol``,
but many within ``1e-5``).

**Table of the last levels** (kl, frobenius, logdet; :class:`_Leaves`): the completions of a
node at depth ``d0 = m - LEAF_LEVELS`` are ``Z(I) + T_t`` over a table of the ``2^LEAF_LEVELS``
subset sums of the last sensors, and, the metric being strongly convex (kl in ``Z`` on bounded
sets, frobenius² in ``W``, logdet in ``Z`` where ``y_max(Z_all) < 1 + sqrt 2``), every
completion that can still be ``<= τ`` lies in a small ball around the continuous minimiser,
found by a k-d tree query: so the last levels cost one query per node and the candidates in the
ball, not a subtree.  Those are recorded with a valid bound as the tree's own candidates, and a
completion outside the ball is above ``τ``, so the exactness argument below is unchanged.

**Exactness.**  The incumbent ``U`` is the smallest exactly evaluated value (greedy's subset
first); a node is pruned only when its bound exceeds ``τ = U + tie_rtol · max(|U|, tiny)``, which
is at least the reference's tie threshold ``f* + tie_rtol · max(|f*|, tiny)`` (``0 <= f* <= U``:
every registered metric is computed ``>= 0``).  Hence no subset of the reference's tie set is
ever pruned, every one is recorded as a candidate with a bound below its value, and all candidates
whose bound is at most the final ``τ`` are evaluated exactly with the reference's arithmetic
(``J`` summed in ascending sensor order from ``+0.0``, :func:`covnet.core.allocation._fast.\
gain_sums`; ``P = spd_inverse(spd_inverse(P_pred) + J)``; the metric itself, batch-invariant);
the tie rule then runs on bit-identical values: the same subset, value and ``P`` as
:func:`~covnet.core.allocation.allocate_exhaustive`.

**Bounded** (``rel_gap > 0``, a time or node limit): with ``rel_gap > 0`` nodes are explored best
bound first and depth first in turn, and pruned once their bound exceeds ``U - rel_gap·|U|``; a
limit stops the search (depth first without ``rel_gap``).  The result is the best subset found,
with a certified lower bound ``L`` of the optimum (the least bound over the open nodes, the
pruned ones and the candidates not evaluated, or the root's bound if larger) and
``gap = (value - L) / max(|value|, tiny)``.

**Greedy** (:func:`allocate_greedy`): the better of forward selection (add the sensor giving the
smallest value, while the bound says a superset can still win) and backward elimination (from
every sensor), then best-improvement local search over removals, additions and 1-swaps, on
reduced-form values; the final subset is evaluated exactly.  Its certified lower bound is the
bound of the root ``[P(required ∪ all allowed), P(required)]`` (with the relaxation where it
applies).

For small problems (up to ~20 sensors) :func:`covnet.core.allocation.allocate`, which bounds
every subset in one batch, is faster; this module is for larger ones.

**Zero gains.**  A free sensor with an all-zero gain never changes ``J`` (a running sum from
``+0.0`` is never ``-0.0``, and ``x + 0 = x``), so ``D ∪ {j}`` ties exactly with ``D`` and loses
the tie rule to it; such sensors leave the search, except the lowest-indexed one as the singleton
candidate ``{j}`` when nothing is required.

**Clocks.**  The core reads no clock, except here, and only when ``time_limit_s`` is given
(``time.perf_counter``, or the ``clock`` argument): a time-limited result depends on the machine,
``node_limit`` is the deterministic alternative.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation._fast import (
    _spd_inverse_soa,
    gain_sums,
    spd_inverse,
    tie_select,
)
from covnet.core.allocation.exact import (
    Constraints,
    InfeasibleAllocation,
    _check_rtol,
    _checked_pd,
    _gains_array,
    _prepare,
    _resolve_metric,
    _spd_error,
    allocate,
)
from covnet.core.allocation.interval_bounds import (
    ROUND,
    DesiredConstants,
    IntervalBound,
    search_context,
)
from covnet.core.gaussian import Mat
from covnet.core.lapack import flapack
from covnet.core.metrics import MetricFn, Relaxation, capability

lapack = flapack()  # scipy.linalg.lapack's routines, without scipy.linalg's import

__all__ = [
    "STATUS",
    "SearchResult",
    "allocate_bnb",
    "allocate_greedy",
]

TINY = float(np.finfo(np.float64).tiny)
EPS = float(np.finfo(np.float64).eps)
#: the relaxation's relative rounding allowance per unit of ``n² κ``
ROUND_REL = 64.0
#: the default: no constraint
NO_CONSTRAINTS = Constraints()
#: nodes per batch of the search (one numpy pass each)
CHUNK = 4096
#: above this many bytes of open nodes the best-first search goes depth first (bounded memory)
OPEN_BYTES = 1 << 28
#: exact evaluations per batch are capped so that the gain sums' temporary ``(c, N, n, n)`` stays
#: below this many entries
EXACT_ENTRIES = 1 << 21
#: after each batch, at most this many of the new candidates that could beat the incumbent are
#: evaluated exactly at once (the incumbent falls early); the others wait for the end
EVAL_PICKS = 4
#: local search: at most this many passes, each evaluating its moves in batches of MOVE_BLOCK
MAX_PASSES = 64
MOVE_BLOCK = 1 << 15
#: backward elimination removes one sensor at a time below this many, blocks above
BACKWARD_ONE = 64
#: local search: every 1-swap while there are at most this many, else only the swaps among the
#: SWAP_POOL best removals and additions
FULL_SWAPS = 4096
SWAP_POOL = 64
FULL_SCAN_BUDGET = 1 << 17

#: status codes (``SearchResult.status``) and their meaning
STATUS: dict[int, str] = {
    0: "optimal: the search completed (the reference's subset, value and P)",
    1: "node limit reached: best subset found, with a certified lower bound",
    2: "time limit reached: best subset found, with a certified lower bound",
    3: "relative gap reached: the best subset found is within rel_gap of the optimum",
    4: "greedy local optimum, with a certified lower bound",
}


@dataclass(frozen=True, slots=True)
class SearchResult:
    """One search's result, shaped like ``scipy.optimize.linprog``'s: ``status`` (a key of
    :data:`STATUS`), ``message``, ``success`` (property).

    ``subset``: chosen sensor indices, ascending; ``value``: its exact ``f(P, P_d)`` (the
    reference's arithmetic); ``P``: its covariance; ``lower_bound``: a certified lower bound of
    the optimum over the feasible subsets; ``gap = (value - lower_bound) / max(|value|, tiny)``;
    ``n_nodes``: branch-and-bound nodes created (greedy: moves evaluated); ``n_evaluated``: exact
    metric evaluations; ``exact``: the subset is the reference's (the search completed with
    ``rel_gap = 0``).
    """

    subset: tuple[int, ...]
    value: float
    P: NDArray[np.float64]
    lower_bound: float
    gap: float
    n_nodes: int
    n_evaluated: int
    exact: bool
    status: int
    message: str

    @property
    def success(self) -> bool:
        """The search ended by its own criterion (completed, or within ``rel_gap``)."""
        return self.status in (0, 3, 4)


# --------------------------------------------------------------------------------------------
# the problem: validation (as the reference), reduced form, exact evaluation
# --------------------------------------------------------------------------------------------


class _Problem:
    """One validated allocation problem, its branching order and its reduced form.

    ``free``: the sensors the search decides (allowed, not required, non-zero gain), in
    *branching order* (descending ``tr(P_pred J_j P_pred)``, ties by index); ``req`` the required
    ones; ``zero``: the lowest-indexed allowed, non-required sensor with an all-zero gain (or
    ``None``); ``K`` the effective budget.  Reduced form (module docstring): support ``s``,
    ``base = C⁻¹ + Σ_req S_j`` ``(r*r,)``, ``S`` ``(m, r*r)`` the free sensors' ``S_j`` in
    branching order, ``suffix[d] = Σ_{e >= d} S[e]``, ``T`` ``(r*r, n*n)`` and ``P_inf`` so that
    ``P(Z) = Z⁻¹ T + P∞`` (flattened)."""

    def __init__(
        self,
        P_pred: Mat,
        gains: Mat,
        P_d: Mat,
        metric: str | MetricFn,
        constraints: Constraints,
        tie_rtol: float,
    ) -> None:
        P, D = _checked_pd(P_pred, P_d)
        plan = _prepare(_gains_array(gains, P.shape[0]), constraints, tables=False)
        self.f, entry = _resolve_metric(metric)
        self.name = entry.name if entry is not None else None
        _check_rtol(tie_rtol)
        if plan.infeasible is not None:
            raise InfeasibleAllocation(plan.infeasible)
        self.P_pred, self.D, self.G, self.c = P, D, plan.gains, constraints
        self.tie_rtol = float(tie_rtol)
        N, n = self.G.shape[0], self.G.shape[1]
        self.N, self.n, self.K = N, n, plan.max_active
        allowed = [j for j in range(N) if j not in constraints.excluded]
        self.req = sorted(constraints.required)
        nonzero = np.asarray(self.G.reshape(N, n * n).any(axis=1), dtype=bool).tolist()
        cand = [j for j in allowed if j not in constraints.required]
        free = [j for j in cand if nonzero[j]]
        zeros = [j for j in cand if not nonzero[j]]
        self.zero = zeros[0] if zeros and not self.req else None
        try:
            self.Y0 = spd_inverse(P)  # the reference's bits
        except np.linalg.LinAlgError as exc:
            raise _spd_error(exc) from exc
        active = self.G[allowed]
        s = np.flatnonzero(active.any(axis=(0, 1)) | active.any(axis=(0, 2)))
        self.s, self.r = s, int(s.size)
        # branching order: the largest first-order covariance reduction first
        if free:
            Gf = self.G[free]
            w = np.einsum("ij,kjl,li->k", P, Gf, P)
            self.free = [free[i] for i in np.lexsort((np.array(free), -w)).tolist()]
        else:
            self.free = []
        self.m = len(self.free)
        self._reduced()
        self.dc = DesiredConstants(D)
        J_all = active.sum(axis=0)
        info_trace = float(np.trace(self.Y0)) + float(np.trace(J_all))
        gabs = float(np.abs(active).sum(axis=0).max()) if active.size else 0.0
        neg = 0.0
        if active.size:  # the PSD check allows rounding-level negative eigenvalues
            w_min = np.linalg.eigvalsh(active)[:, 0]
            neg = float(np.maximum(-w_min, 0.0).sum())
        ctx = search_context(P, info_trace, D, n_terms=len(allowed), gain_abs_max=gabs)
        lam = ctx.lam_max
        self.ctx = ctx._replace(err=ctx.err + lam * lam * n * neg)
        self.bound: IntervalBound | None = (
            capability(entry.interval_bound, IntervalBound) if entry is not None else None
        )
        self.n_evaluated = 0
        self.moves = 0
        self.relax: _Relaxation | None = None
        relaxation = entry.relaxation if entry is not None else None
        if self.bound is not None and relaxation is not None and self.r == 2:
            try:
                self.relax = _Relaxation(self, relaxation)
            except np.linalg.LinAlgError:  # P_d not SPD: the metric itself will say so
                self.relax = None

    def _reduced(self) -> None:
        P, n, s, r = self.P_pred, self.n, self.s, self.r
        if 0 < r < n:
            Ps = P[s]
            C = Ps[:, s]
            cf = _cholesky(C, "P_pred[s, s]")
            KT = _cho_solve(cf, Ps)  # C⁻¹ P[s, :]
            Cinv = _cho_solve(cf, np.eye(r))
            Cinv = 0.5 * (Cinv + Cinv.T)
            K = KT.T
            self.P_inf = (P - K @ Ps).reshape(n * n)
        elif r:  # the full form: Z = P⁻¹ + J, P(Z) = Z⁻¹
            K = np.eye(n)
            Cinv = self.Y0
            self.P_inf = np.zeros(n * n)
        else:  # no information at all: every P(S) is P_pred
            K = np.zeros((n, 0))
            Cinv = np.zeros((0, 0))
            self.P_inf = P.reshape(n * n).copy()
        self.Kmat, self.Cinv = K, Cinv
        self.T = np.einsum("ia,jb->abij", K, K).reshape(r * r, n * n)
        rr = r * r
        G = self.G
        base = Cinv.reshape(rr).copy()
        for j in self.req:
            base += G[j][np.ix_(s, s)].reshape(rr)
        self.base = base
        S = np.zeros((self.m, rr))
        for i, j in enumerate(self.free):
            S[i] = G[j][np.ix_(s, s)].reshape(rr)
        self.S = S
        suffix = np.zeros((self.m + 1, rr))
        if self.m:
            suffix[:-1] = np.cumsum(S[::-1], axis=0)[::-1]
        self.suffix = suffix

    # -- reduced-form covariances and the bound's pieces ----------------------------------------

    def covariances(self, Z: Mat) -> Mat:
        """``P(Z) = P∞ + K Z⁻¹ Kᵀ`` ``(m, n, n)`` of the information rows ``Z`` ``(m, r*r)``."""
        r, n = self.r, self.n
        m = Z.shape[0]
        if r == 0:
            return np.broadcast_to(self.P_inf.reshape(n, n), (m, n, n)).copy()
        with np.errstate(all="ignore"):
            if r == 1:
                W = 1.0 / Z
            elif r == 2:
                det = Z[:, 0] * Z[:, 3] - Z[:, 1] * Z[:, 2]
                W = np.empty_like(Z)
                W[:, 0] = Z[:, 3]
                W[:, 1] = -Z[:, 1]
                W[:, 2] = -Z[:, 2]
                W[:, 3] = Z[:, 0]
                W /= det[:, None]
            else:
                W = np.ascontiguousarray(_spd_inverse_soa(np.ascontiguousarray(Z.T), r).T)
        X = np.asarray(W @ self.T, dtype=np.float64)
        X += self.P_inf
        return X.reshape(m, n, n)

    def summary(self, Z: Mat) -> Mat:
        assert self.bound is not None
        with np.errstate(all="ignore"):
            return self.bound.summary(self.covariances(Z), self.dc)

    def refine(self, Z_lo: Mat, Z_hi: Mat, lb: Mat, sB: Mat, tau: float) -> Mat:
        """``lb`` raised by the reduced relaxation (:class:`_Relaxation`) where it applies."""
        if self.relax is None or lb.size == 0:
            return lb
        rows = np.flatnonzero(lb <= tau)
        zrows = rows[:0]
        if self.relax.form == "logdet":  # convex in W where x_max(P(I)) <= 1 + sqrt 2, else in Z
            rho = self.n * self.ctx.err / self.ctx.lam_min
            ok = sB[rows, -1] * (1.0 + 4.0 * rho) < LOGDET_CONVEX * (1.0 - 1e-9)
            zrows = rows[~ok]
            rows = rows[ok]
            if zrows.size:
                zrows = zrows[self.relax.z_convex(Z_hi[zrows])]
        if rows.size == 0 and zrows.size == 0:
            return lb
        out = lb.copy()
        if rows.size:
            out[rows] = np.fmax(lb[rows], self.relax.bound(Z_lo[rows], Z_hi[rows], tau))
        if zrows.size:
            zb = self.relax.bound(Z_lo[zrows], Z_hi[zrows], tau, zform=True)
            out[zrows] = np.fmax(lb[zrows], zb)
        return out

    def combine(self, sA: Mat, sB: Mat) -> Mat:
        assert self.bound is not None
        with np.errstate(all="ignore"):
            v = self.bound.combine(sA, sB, self.dc, self.ctx)
        return np.where(np.isnan(v), 0.0, v)

    def approx_values(self, Z: Mat) -> Mat:
        """The metric on reduced-form covariances (greedy's working values; NaN -> +inf): for
        frobenius, kl and logdet with ``r = 2`` from the closed forms of :class:`_Relaxation`."""
        if self.relax is not None:
            with np.errstate(all="ignore"):
                v = self.relax.value(Z)
            return np.where(np.isfinite(v), v, np.inf)
        out = np.empty(Z.shape[0])
        for lo in range(0, Z.shape[0], MOVE_BLOCK):
            Zb = Z[lo : lo + MOVE_BLOCK]
            with np.errstate(all="ignore"):
                try:
                    v = np.asarray(self.f(self.covariances(Zb), self.D), dtype=np.float64)
                except np.linalg.LinAlgError:
                    v = np.array([self._approx_one(z) for z in Zb])
            out[lo : lo + Zb.shape[0]] = v
        out[~np.isfinite(out)] = np.inf
        return out

    def _approx_one(self, z: Mat) -> float:
        try:
            return float(np.asarray(self.f(self.covariances(z[None])[0], self.D)))
        except np.linalg.LinAlgError:
            return math.inf

    # -- masks and exact values -----------------------------------------------------------------

    def unpack(self, packed: NDArray[np.uint8]) -> NDArray[np.bool_]:
        """Branching-order rows ``(c, m)`` of the tree's packed rows ``(c, ⌈m/8⌉)`` (bit ``d``
        of a row: byte ``d // 8``, bit ``d % 8``)."""
        return np.unpackbits(packed, axis=1, count=self.m, bitorder="little").astype(bool)

    def masks(self, inc: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Sensor rows ``(c, N)`` of subsets given by branching-order rows ``inc`` ``(c, m)``."""
        out = np.zeros((inc.shape[0], self.N), dtype=bool)
        if self.m:
            out[:, self.free] = inc
        if self.req:
            out[:, self.req] = True
        return out

    def exact(self, masks: NDArray[np.bool_]) -> Mat:
        """Exact values of the subsets ``masks`` ``(c, N)``: the reference's arithmetic."""
        out = np.empty(masks.shape[0])
        step = max(1, EXACT_ENTRIES // (self.N * self.n * self.n))
        for lo in range(0, masks.shape[0], step):
            mk = masks[lo : lo + step]
            P = self.exact_covariances(mk)
            v = np.asarray(self.f(P, self.D), dtype=np.float64)
            if v.shape != (mk.shape[0],):
                raise ValueError(f"metric returned shape {v.shape} for a batch of {mk.shape[0]}")
            if not np.isfinite(v).all():
                k = int(np.argmin(np.isfinite(v)))
                subset = tuple(np.flatnonzero(mk[k]).tolist())
                raise ValueError(f"metric returned a non-finite value for subset {subset}")
            out[lo : lo + mk.shape[0]] = v
        self.n_evaluated += masks.shape[0]
        return out

    def exact_covariances(self, masks: NDArray[np.bool_]) -> Mat:
        """``P_i = spd_inverse(spd_inverse(P_pred) + J_i)`` with ``J_i`` summed as the reference."""
        return spd_inverse(self.Y0 + gain_sums(self.G, masks))

    def root_bound(self) -> float:
        """The bound of the root interval ``[P(req ∪ all free), P(req)]``, raised by the
        reduced relaxation where it applies; without an interval bound ``0`` for a registered
        metric (an entry of :data:`covnet.core.metrics.METRICS` is ``>= 0``), ``-inf`` for a
        user's plain function."""
        if self.bound is None:
            return 0.0 if self.name is not None else -math.inf
        Z0 = self.base[None]
        Z1 = Z0 + self.suffix[0]
        sA = self.summary(Z1)
        sB = self.summary(Z0)
        lb = self.combine(sA, sB)
        lb = self.refine(Z0, Z1, lb, sB, math.inf)
        return float(lb[0])


def _cholesky(A: Mat, name: str) -> Mat:
    """The lower Cholesky factor (LAPACK ``potrf``; the upper triangle is not referenced by
    :func:`_cho_solve`); ``numpy.linalg.LinAlgError`` unless ``A`` is positive definite."""
    c, info = lapack.dpotrf(A, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"{name} is not positive definite (LAPACK info {info})")
    return np.asarray(c)


def _cho_solve(c: Mat, B: Mat) -> Mat:
    """``A⁻¹ B`` from ``A``'s factor ``c`` of :func:`_cholesky` (LAPACK ``potrs``)."""
    X, info = lapack.dpotrs(c, B, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"potrs failed (LAPACK info {info})")
    return np.asarray(X)


def _subset(mask: NDArray[np.bool_]) -> tuple[int, ...]:
    return tuple(np.flatnonzero(mask).tolist())


def _gap(value: float, lower: float) -> float:
    return max(value - lower, 0.0) / max(abs(value), TINY)


# --------------------------------------------------------------------------------------------
# greedy
# --------------------------------------------------------------------------------------------


def _forward(prob: _Problem) -> tuple[NDArray[np.bool_], float]:
    """Forward selection from the required set: add the sensor giving the smallest value; stop
    at the budget, or when the interval bound of (current set, all the rest undecided) exceeds
    the best value on the path (no superset can do better).  Returns the path's best."""
    m, K, k0 = prob.m, prob.K, len(prob.req)
    inc = np.zeros(m, dtype=bool)
    Z = prob.base.copy()
    best_val = float(prob.approx_values(Z[None])[0]) if k0 else math.inf
    best_inc = inc.copy()
    k = k0
    while k < K and not inc.all():
        rest = np.flatnonzero(~inc)
        if math.isfinite(best_val) and prob.bound is not None:
            sA = prob.summary((Z + prob.S[rest].sum(axis=0))[None])
            sB = prob.summary(Z[None])
            if float(prob.combine(sA, sB)[0]) > best_val:
                break
        v = prob.approx_values(Z[None] + prob.S[rest])
        prob.moves += rest.size
        i = int(np.argmin(v))
        if not math.isfinite(float(v[i])):
            break
        inc[rest[i]] = True
        Z = prob.base + prob.S[inc].sum(axis=0)
        k += 1
        if v[i] < best_val:
            best_val, best_inc = float(v[i]), inc.copy()
    return best_inc, best_val


def _backward(prob: _Problem) -> tuple[NDArray[np.bool_], float]:
    """Backward elimination from every free sensor: remove the sensor whose removal gives the
    smallest value (above BACKWARD_ONE sensors, the ``⌈|D| / BACKWARD_ONE⌉`` best removals at
    once, so a pass costs ``O(N · BACKWARD_ONE)`` evaluations); values count once within the
    budget.  Returns the path's best."""
    m, K, k0 = prob.m, prob.K, len(prob.req)
    inc = np.ones(m, dtype=bool)
    best_inc, best_val = inc.copy(), math.inf
    while True:
        k = k0 + int(inc.sum())
        if k <= K:
            v0 = float(prob.approx_values((prob.base + prob.S[inc].sum(axis=0))[None])[0])
            if v0 < best_val:
                best_val, best_inc = v0, inc.copy()
        ins = np.flatnonzero(inc)
        if ins.size == 0 or (ins.size == 1 and not k0):
            break
        Z = prob.base + prob.S[inc].sum(axis=0)
        v = prob.approx_values(Z[None] - prob.S[ins])
        prob.moves += ins.size
        step = max(1, -(-ins.size // BACKWARD_ONE))
        if k - K > step:  # still above the budget: remove faster, values do not count yet
            step = max(step, (k - K) // 2)
        step = min(step, ins.size - (0 if k0 else 1))
        drop = ins[np.argsort(v, kind="stable")[:step]]
        inc[drop] = False
    return best_inc, best_val


def _move_values(prob: _Problem, Z: Mat, rem: NDArray[np.intp], add: NDArray[np.intp]) -> Mat:
    """Working values of the moves ``(rem[i], add[i])`` (``-1``: none) from information ``Z``."""
    out = np.empty(rem.size)
    for lo in range(0, rem.size, MOVE_BLOCK):
        r_, a_ = rem[lo : lo + MOVE_BLOCK], add[lo : lo + MOVE_BLOCK]
        Zm = np.broadcast_to(Z, (r_.size, Z.size)).copy()
        Zm[r_ >= 0] -= prob.S[r_[r_ >= 0]]
        Zm[a_ >= 0] += prob.S[a_[a_ >= 0]]
        out[lo : lo + r_.size] = prob.approx_values(Zm)
    prob.moves += rem.size
    return out


def _local_search(prob: _Problem, inc: NDArray[np.bool_], val: float) -> NDArray[np.bool_]:
    """Best-improvement local search over removals, additions and 1-swaps (a strict relative
    improvement of 1e-12 required), at most MAX_PASSES passes.  A pass evaluates every removal
    and addition, and the swaps of every member with every non-member when there are at most
    FULL_SWAPS of them, else first the swaps among the SWAP_POOL best removals and additions and,
    if none improves, the others in blocks (members by their removal value) until one does,
    within FULL_SCAN_BUDGET such evaluations per call."""
    k0, K = len(prob.req), prob.K
    inc = inc.copy()
    budget = FULL_SCAN_BUDGET
    for _ in range(MAX_PASSES):
        Z = prob.base + prob.S[inc].sum(axis=0)
        ins, outs = np.flatnonzero(inc), np.flatnonzero(~inc)
        k = k0 + ins.size
        best_move: tuple[int, int] | None = None
        best_new = val

        def consider(rem: NDArray[np.intp], add: NDArray[np.intp], v: Mat) -> None:
            nonlocal best_move, best_new
            if v.size:
                i = int(np.argmin(v))
                if v[i] < best_new - 1e-12 * abs(best_new):
                    best_new, best_move = float(v[i]), (int(rem[i]), int(add[i]))

        v_rem = v_add = None
        if ins.size:
            v_rem = _move_values(prob, Z, ins, np.full(ins.size, -1))
            if k0 or ins.size > 1:
                consider(ins, np.full(ins.size, -1), v_rem)
        if outs.size:
            v_add = _move_values(prob, Z, np.full(outs.size, -1), outs)
            if k < K:
                consider(np.full(outs.size, -1), outs, v_add)
        if v_rem is not None and v_add is not None:
            if ins.size * outs.size <= FULL_SWAPS:
                rem, add = np.repeat(ins, outs.size), np.tile(outs, ins.size)
                consider(rem, add, _move_values(prob, Z, rem, add))
            else:
                r_order = ins[np.argsort(v_rem, kind="stable")]
                a_order = outs[np.argsort(v_add, kind="stable")]
                si, so = r_order[:SWAP_POOL], a_order[:SWAP_POOL]
                rem, add = np.repeat(si, so.size), np.tile(so, si.size)
                consider(rem, add, _move_values(prob, Z, rem, add))
                rest = a_order[SWAP_POOL:]
                per = max(1, MOVE_BLOCK // max(outs.size, 1))
                lo = 0
                while best_move is None and lo < r_order.size and budget > 0:
                    rows = r_order[lo : lo + per]
                    lo += per
                    # the pool's own swaps are done: the rest of the non-members for the pool
                    # members, every non-member for the others
                    cols = [rest if i < SWAP_POOL else a_order for i in range(lo - per, lo)]
                    rem = np.concatenate(
                        [np.full(c.size, r) for r, c in zip(rows, cols, strict=False)]
                    )
                    add = np.concatenate(cols[: rows.size])
                    budget -= rem.size
                    consider(rem, add, _move_values(prob, Z, rem, add))
        if best_move is None:
            break
        rem_i, add_i = best_move
        if rem_i >= 0:
            inc[rem_i] = False
        if add_i >= 0:
            inc[add_i] = True
        val = best_new
    return inc


def _greedy_inc(prob: _Problem) -> NDArray[np.bool_] | None:
    """Greedy's subset as a branching-order row ``(m,)``: the better of the forward and the
    backward paths, improved by :func:`_local_search` (``None``: no free sensor can be added,
    only the required set or the zero sensor is possible).  Moves evaluated: ``prob.moves``."""
    if prob.m == 0 or prob.K <= len(prob.req):
        return None
    f_inc, f_val = _forward(prob)
    b_inc, b_val = _backward(prob)
    inc, val = (b_inc, b_val) if b_val < f_val else (f_inc, f_val)
    if not math.isfinite(val) or (not inc.any() and not prob.req):
        return None
    return _local_search(prob, inc, val)


def _greedy_start(prob: _Problem) -> tuple[NDArray[np.bool_], Mat]:
    """Greedy's subset, the required set (when not empty) and the zero sensor's singleton (when
    it is a choice) as sensor rows ``(c, N)``, with their exact values: every feasible subset the
    tree does not record itself.  At least one row (the first free sensor alone if greedy finds
    nothing finite)."""
    inc = _greedy_inc(prob)
    rows = []
    if inc is not None and (inc.any() or not prob.req):
        rows.append(prob.masks(inc[None])[0])
    if prob.req:
        rows.append(prob.masks(np.zeros((1, prob.m), dtype=bool))[0])
    if prob.zero is not None:
        z = np.zeros(prob.N, dtype=bool)
        z[prob.zero] = True
        rows.append(z)
    rows = [r for r in rows if r.any()]
    if not rows:
        one = np.zeros(prob.N, dtype=bool)
        one[prob.free[0]] = True
        rows.append(one)
    masks = np.array(rows)
    return masks, prob.exact(masks)


def allocate_greedy(
    P_pred: Mat,
    gains: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    constraints: Constraints = NO_CONSTRAINTS,
    tie_rtol: float = 1e-9,
) -> SearchResult:
    """Forward greedy + best-improvement local search (removals, additions, 1-swaps); the subset
    found, its exact value and ``P`` (the reference's arithmetic), and the root interval bound as
    the certified lower bound (for a metric without an interval bound: ``0`` if registered,
    ``-inf`` for a user's plain function).

    Cost: ``O(N)`` batched evaluations per forward step and ``O(|D| · N)`` per local-search pass,
    each one ``r x r`` inverse and one metric evaluation of an ``n x n`` matrix."""
    prob = _Problem(P_pred, gains, P_d, metric, constraints, tie_rtol)
    try:
        masks, values = _greedy_start(prob)
        k = tie_select(values, masks, prob.tie_rtol)
        mask, value = masks[k], float(values[k])
        P = prob.exact_covariances(mask[None])[0]
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    lb = min(prob.root_bound(), value)
    return SearchResult(
        _subset(mask),
        value,
        P,
        lb,
        _gap(value, lb),
        prob.moves,
        prob.n_evaluated,
        False,
        4,
        STATUS[4],
    )


# --------------------------------------------------------------------------------------------
# the reduced relaxation: a convex problem over the node's 2 x 2 interval (r = 2)
# --------------------------------------------------------------------------------------------

#: symmetric 2 x 2 matrices as triples ``(a, b, c)`` of ``(m,)`` arrays: ``[[a, b], [b, c]]``
Sym2 = tuple[Mat, Mat, Mat]

#: projected-gradient iterations of the relaxation per node (each also gives a lower bound)
RELAX_ITERS = 16
#: the relaxation refines only nodes with at least this many undecided sensors (1: every node;
#: at 32-40 sensors 6 left two thirds of kl's nodes, in the last five levels, unrefined)
RELAX_MIN_REST = 1
#: kl, frobenius and logdet: the last this many levels of the tree come from a table of
#: ``2^LEAF_LEVELS`` sums (:class:`_Leaves`; 2^18 rows: 6 MB, and a k-d tree)
LEAF_LEVELS = 18
#: ... but the tree keeps at least the first min(LEAF_TOP, m // 2) levels (a smaller table for
#: 20-28 sensors, where the tree alone is fast)
LEAF_TOP = 10
#: nodes per table query (the threshold is updated in between)
LEAF_GROUP = 8
#: logdet is convex in ``W`` where every generalized eigenvalue is at most ``1 + sqrt 2``
LOGDET_CONVEX = 1.0 + math.sqrt(2.0)


def _s2(X: Mat) -> Sym2:
    """Rows ``(m, 4)`` (row-major 2 x 2) as a triple."""
    return X[:, 0], X[:, 1], X[:, 3]


def _flat2(a: Mat, b: Mat, c: Mat) -> Mat:
    return np.stack((a, b, b, c), axis=1)


def _inv2(a: Mat, b: Mat, c: Mat) -> Sym2:
    det = a * c - b * b
    return c / det, -b / det, a / det


def _mul2(x: Sym2, y: Sym2) -> tuple[Mat, Mat, Mat, Mat]:
    """``x y`` (not symmetric in general) as ``(p00, p01, p10, p11)``."""
    return (
        x[0] * y[0] + x[1] * y[1],
        x[0] * y[1] + x[1] * y[2],
        x[1] * y[0] + x[2] * y[1],
        x[1] * y[1] + x[2] * y[2],
    )


def _sandwich(R: Sym2, X: Sym2) -> Sym2:
    """``R X R`` for symmetric ``R``, ``X``."""
    p00, p01, p10, p11 = _mul2(R, X)
    return (
        p00 * R[0] + p01 * R[1],
        p00 * R[1] + p01 * R[2],
        p10 * R[1] + p11 * R[2],
    )


def _dot2(x: Sym2, y: Sym2) -> Mat:
    return x[0] * y[0] + 2.0 * x[1] * y[1] + x[2] * y[2]


def _eig2(a: Mat, b: Mat, c: Mat) -> tuple[Mat, Mat, Mat, Mat]:
    """Eigenvalues ``h + q >= h - q`` and ``(cos θ, sin θ)`` of the first eigenvector."""
    h = 0.5 * (a + c)
    d = 0.5 * (a - c)
    q = np.hypot(d, b)
    th = 0.5 * np.arctan2(b, d)
    return h + q, h - q, np.cos(th), np.sin(th)


def _negsum2(x: Sym2) -> Mat:
    """The sum of the negative eigenvalues: ``min_{0 ⪯ Y ⪯ I} <x, Y>``."""
    l1, l2, _, _ = _eig2(*x)
    return np.minimum(l1, 0.0) + np.minimum(l2, 0.0)


def _proj01(x: Sym2) -> Sym2:
    """The Frobenius projection onto ``{0 ⪯ Y ⪯ I}``: eigenvalues clipped to ``[0, 1]``."""
    l1, l2, cs, sn = _eig2(*x)
    l1 = np.clip(l1, 0.0, 1.0)
    l2 = np.clip(l2, 0.0, 1.0)
    return l1 * cs * cs + l2 * sn * sn, (l1 - l2) * cs * sn, l1 * sn * sn + l2 * cs * cs


def _sqrt2(a: Mat, b: Mat, c: Mat) -> Sym2:
    """``X^½`` of PSD 2 x 2 matrices (negative rounding clipped): ``(X + sqrt(det) I) / t``,
    ``t = sqrt(tr X + 2 sqrt(det))``."""
    a = np.maximum(a, 0.0)
    c = np.maximum(c, 0.0)
    s = np.sqrt(np.maximum(a * c - b * b, 0.0))
    t = np.sqrt(a + c + 2.0 * s)
    t = np.where(t > 0.0, t, 1.0)
    return (a + s) / t, b / t, (c + s) / t


class _Relaxation:
    """Lower bounds from the convex relaxation of a node in the reduced coordinates (``r = 2``).

    A node's completions have information ``Z ∈ [Z_lo, Z_hi]`` (Loewner, ``2 x 2``: ``Z_lo`` of
    ``I``, ``Z_hi`` of ``I ∪ U``) and covariance ``P = P∞ + K W Kᵀ`` with ``W = Z⁻¹ ∈ [Z_hi⁻¹,
    Z_lo⁻¹]``.  This set has 3 dimensions, where the Loewner interval ``[A, B]`` of the
    covariances has ``n(n+1)/2``: its minimum is much closer to the completions'.  For metrics
    convex in one of the two parametrisations ``V ∈ [V_lo, V_hi]`` (write ``V = V_lo + R X R``,
    ``R = (V_hi - V_lo)^½``, ``0 ⪯ X ⪯ I``), the value ``h(X_k)`` and gradient ``G_k`` at any
    point give (convexity, then the linear minimisation over ``{0 ⪯ Y ⪯ I}``)::

        min h >= h(X_k) - <G_k, X_k> + sum of the negative eigenvalues of G_k,

    evaluated along a projected-gradient descent; a node stops as soon as this exceeds the
    threshold (pruned) or ``h(X_k)`` is at most it (the relaxation cannot prune it).

    - **frobenius** in ``W``: ``h = ||M0 + K W Kᵀ||_F²`` (``M0 = P∞ - P_d``), gradient
      ``2 Kᵀ M K``; the bound is ``sqrt`` of the squared one;
    - **kl** in ``Z``: ``4 kl = c0 + tr(Q Z⁻¹) + <P_d[s, s], Z>`` (``Q = Kᵀ P_d⁻¹ K``,
      ``tr(P⁻¹ P_d) = tr(P_pred⁻¹ P_d) + <P_d[s, s], Z - C⁻¹>``), convex (``Z ↦ Z⁻¹`` is operator
      convex), gradient ``P_d[s, s] - Z⁻¹ Q Z⁻¹``;
    - **logdet** in ``W``: ``f = c1 + log det(I + V1 W) - ½ log det W`` (``V1 = Kᵀ (P∞ +
      P_d)⁻¹ K``, the determinant lemma and ``det P = det P∞[v, v] det W``), gradient
      ``(I + V1 W)⁻¹ V1 - ½ W⁻¹``; ``f = Σ φ(x_i)`` over the generalized eigenvalues with ``φ``
      convex on ``(0, 1 + sqrt 2]`` (``φ'' = 1/(2x²) - 1/(1 + x)²``), so ``f`` is convex (a
      spectral function of a convex ``φ``, of an affine image of ``W``) on the nodes whose
      ``x_max(P(I)) <= 1 + sqrt 2``;
    - **logdet** in ``Z`` on the other nodes where it is convex in ``Z``
      (:meth:`z_convex`: ``f = c1 + log det(Z + V1) - ½ log det Z``, the same ``φ`` of the
      eigenvalues ``y = 1/x`` of ``V1⁻¹ Z``, convex where ``y_max(Z(I ∪ U)) <= 1 + sqrt 2``),
      gradient ``(Z + V1)⁻¹ - ½ Z⁻¹``: the nodes with few sensors included (a large ``P(I)``,
      where ``W`` fails), which were most of logdet's tree at 32 sensors.  Nodes where neither
      holds are not refined.

    The iterations stop once the bound, after the final deflation below, exceeds the threshold
    (:meth:`_goal`, its pre-image); stopping before the deflation (as before) left every bound
    that had just reached the threshold deflated back below it.

    Rounding: the bound is deflated by the interval bound's model errors for the metric (the
    computed constants and the completion's computed ``P`` are within ``err``) and by a relative
    ``ROUND n² eps κ`` of every term it adds.  This holds in ``Z`` as in ``W``: ``K[s, :] = I``
    and ``P∞[s, s] = 0``, so ``W = P(S)[s, s]``, a principal submatrix, and ``cond Z = cond W <=
    cond P(S) <= κ`` (interlacing); ``Z + V1`` is no worse conditioned than ``I + V1 W``.
    """

    def __init__(self, prob: _Problem, relaxation: Relaxation) -> None:
        self.prob = prob
        #: the closed form (the metric entry's :class:`~covnet.core.metrics.Relaxation`)
        self.form = relaxation.form
        #: strongly convex: the last levels from a table (:class:`_Leaves`)
        self.leaves = relaxation.leaves
        n, ctx = prob.n, prob.ctx
        D = prob.D
        s = prob.s
        self.rel = ROUND_REL * n * n * EPS * (ctx.kappa + 1.0)
        if self.form == "frobenius":
            self.M0 = prob.P_inf - D.reshape(n * n)
            self.Tt = np.ascontiguousarray(prob.T.T)
        elif self.form == "kl":
            L_inv, kappa_D = prob.dc.chol_inv()
            LK = L_inv @ prob.Kmat
            self.Q = _s2((LK.T @ LK).reshape(1, 4))
            Dss = D[np.ix_(s, s)]
            self.Dss = _s2(Dss.reshape(1, 4))
            Pinf = prob.P_inf.reshape(n, n)
            tr1 = float(((L_inv @ Pinf) @ L_inv.T).trace())
            self.c0 = tr1 + float((prob.Y0 * D).sum()) - float((Dss * prob.Cinv).sum()) - 2 * n
            self.kappa_D = kappa_D
        else:  # logdet
            Pinf = prob.P_inf.reshape(n, n)
            W = Pinf + D
            cw = _cholesky(W, "P∞ + P_d")
            V1 = prob.Kmat.T @ _cho_solve(cw, prob.Kmat)
            self.V1 = _s2(0.5 * (V1 + V1.T).reshape(1, 4))
            ld_W = 2.0 * float(np.log(np.diag(cw)).sum())
            v = np.ones(n, dtype=bool)
            v[s] = False
            if v.any():
                cv = _cholesky(Pinf[np.ix_(v, v)], "P∞[v, v]")
                ld_v = 2.0 * float(np.log(np.diag(cv)).sum())
            else:
                ld_v = 0.0
            ld_D = 2.0 * float(np.log(np.diag(np.linalg.cholesky(D))).sum())
            self.c1 = ld_W - n * math.log(2.0) - 0.5 * ld_v - 0.5 * ld_D
            self.mag = abs(ld_W) + abs(ld_v) + abs(ld_D) + n

    def _h(self, V: Sym2, zform: bool = False) -> tuple[Mat, Sym2]:
        """The convex objective and its gradient at ``V`` (``W`` or ``Z``; logdet with
        ``zform``: in ``Z``)."""
        if zform:  # logdet in Z: c1 + log det(Z + V1) - ½ log det Z
            a, b, c = V
            v0, v1, v2 = self.V1
            e0, e1, e2 = a + v0, b + v1, c + v2
            detE = e0 * e2 - e1 * e1
            detZ = a * c - b * b
            g = self.c1 + np.log(detE) - 0.5 * np.log(detZ)
            Ei = (e2 / detE, -e1 / detE, e0 / detE)
            Zi = _inv2(a, b, c)
            return g, (Ei[0] - 0.5 * Zi[0], Ei[1] - 0.5 * Zi[1], Ei[2] - 0.5 * Zi[2])
        if self.form == "frobenius":
            M = _flat2(*V) @ self.prob.T
            M += self.M0
            g = np.einsum("mk,mk->m", M, M)
            G4 = M @ self.Tt
            return g, (2.0 * G4[:, 0], G4[:, 1] + G4[:, 2], 2.0 * G4[:, 3])
        if self.form == "kl":
            Vi = _inv2(*V)
            QVi = _sandwich(Vi, self.Q)  # Z⁻¹ Q Z⁻¹
            t = _dot2(self.Q, Vi) + _dot2(self.Dss, V)
            g = 0.25 * (self.c0 + t)
            return g, (
                0.25 * (self.Dss[0] - QVi[0]),
                0.25 * (self.Dss[1] - QVi[1]),
                0.25 * (self.Dss[2] - QVi[2]),
            )
        # logdet: c1 + log det(I + V1 W) - ½ log det W
        a, b, c = V
        v0, v1, v2 = self.V1
        p00, p01, p10, p11 = _mul2(self.V1, V)
        p00 = p00 + 1.0
        p11 = p11 + 1.0
        det1 = p00 * p11 - p01 * p10
        detW = a * c - b * b
        g = self.c1 + np.log(det1) - 0.5 * np.log(detW)
        # (I + V1 W)⁻¹ V1 = adj(I + V1 W) V1 / det1
        i00, i01, i10, i11 = p11 / det1, -p01 / det1, -p10 / det1, p00 / det1
        g00 = i00 * v0 + i01 * v1
        g01 = 0.5 * ((i00 * v1 + i01 * v2) + (i10 * v0 + i11 * v1))
        g11 = i10 * v1 + i11 * v2
        Wi = _inv2(a, b, c)
        return g, (g00 - 0.5 * Wi[0], g01 - 0.5 * Wi[1], g11 - 0.5 * Wi[2])

    def bound(self, Z_lo: Mat, Z_hi: Mat, tau: float, zform: bool = False) -> Mat:
        """Lower bounds ``(m,)`` of the metric over the nodes with information ``[Z_lo, Z_hi]``
        (rows ``(m, 4)``); ``-inf`` where nothing is proven.  ``zform`` (logdet only, on rows
        where :meth:`z_convex` holds): the objective in ``Z``."""
        m = Z_lo.shape[0]
        out = np.full(m, -np.inf)
        if m == 0:
            return out
        with np.errstate(all="ignore"):
            if self.form == "kl" or zform:
                lo, hi = _s2(Z_lo), _s2(Z_hi)
            else:
                lo, hi = _inv2(*_s2(Z_hi)), _inv2(*_s2(Z_lo))
            R = _sqrt2(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])
            goal = self._goal(tau)
            idx = np.arange(m)
            X: Sym2 = (np.full(m, 0.5), np.zeros(m), np.full(m, 0.5))
            step = np.ones(m)
            h_x, G_x = self._hx(lo, R, X, zform)
            for _ in range(RELAX_ITERS):
                lb = h_x - _dot2(G_x, X) + _negsum2(G_x)
                lb_safe = self._deflate(lb, h_x, G_x)
                out[idx] = np.fmax(out[idx], lb_safe)
                if math.isinf(goal):  # no threshold: the best bound the iterations give
                    live = np.isfinite(h_x)
                else:
                    live = ~((lb_safe > goal) | (h_x <= goal) | ~np.isfinite(h_x))
                if not live.any():
                    break
                keep = np.flatnonzero(live)
                idx = idx[keep]
                lo = _take(lo, keep)
                R = _take(R, keep)
                X, G_x, h_x, step = _take(X, keep), _take(G_x, keep), h_x[keep], step[keep]
                gn = np.sqrt(_dot2(G_x, G_x))
                s_ = step / np.where(gn > 0.0, gn, 1.0)
                Xn = _proj01((X[0] - s_ * G_x[0], X[1] - s_ * G_x[1], X[2] - s_ * G_x[2]))
                h_n, G_n = self._hx(lo, R, Xn, zform)
                ok = h_n < h_x
                X = _where(ok, Xn, X)
                G_x = _where(ok, G_n, G_x)
                h_x = np.where(ok, h_n, h_x)
                step = np.where(ok, step * 1.5, step * 0.3)
        return self._final(out)

    def value(self, Z: Mat) -> Mat:
        """The metric of the covariances of the information rows ``Z`` ``(m, 4)`` from the
        reduced formulas above (greedy's working values)."""
        V = _s2(Z) if self.form == "kl" else _inv2(*_s2(Z))
        g, _ = self._h(V)
        return np.sqrt(g) if self.form == "frobenius" else g

    def z_convex(self, Z_hi: Mat) -> NDArray[np.bool_]:
        """logdet: rows whose interval ``Z ⪯ Z_hi`` keeps ``f`` convex in ``Z``.

        In ``Z`` (``W = Z⁻¹``, ``det W = 1 / det Z``) the objective is ``c1 + log det(I + V1 Z⁻¹)
        + ½ log det Z = c1 + log det(Z + V1) - ½ log det Z = c1' + Σ φ(y_i)``, ``φ(y) = log(1 + y)
        - ½ log y`` (the same ``φ``), ``y_i`` the eigenvalues of ``Y = V1^-½ Z V1^-½`` (affine in
        ``Z``).  ``φ`` is convex on ``(0, 1 + sqrt 2]``, so ``f`` is convex (a spectral function
        of a convex ``φ``) on ``{Z : 0 ≺ Z, λmax(Y) <= 1 + sqrt 2}``, which holds on the whole
        interval when it holds at ``Z_hi`` (``Z ⪯ Z_hi`` gives ``Y(Z) ⪯ Y(Z_hi)``).
        ``λmax(V1⁻¹ Z_hi)`` is computed in closed form; a relative margin ``1e-6 + 4 ρ``
        (``ρ = n err / λmin``: the computed ``Z_hi`` against the completions') covers its
        rounding.  (Where neither this nor ``x_max(P(I)) <= 1 + sqrt 2`` holds, nothing is
        refined.)"""
        y_max, pd = self.y_max(Z_hi)
        with np.errstate(all="ignore"):
            rho = self.prob.n * self.prob.ctx.err / self.prob.ctx.lam_min
            ok = y_max * (1.0 + 1e-6 + 4.0 * rho) < LOGDET_CONVEX
        return np.asarray(ok & np.isfinite(y_max) & pd, dtype=bool)

    def y_max(self, Z: Mat) -> tuple[Mat, NDArray[np.bool_]]:
        """logdet: ``λmax(V1⁻¹ Z)`` of the rows ``Z`` ``(m, 4)`` (closed form, the larger root of
        ``det(Z - y V1) = 0``; its rounding is at most a relative ``1e-7``: ``sqrt`` of the
        discriminant's), and whether ``det Z > 0``."""
        a, b, c = _s2(Z)
        v0, v1, v2 = self.V1
        with np.errstate(all="ignore"):
            qa = v0 * v2 - v1 * v1
            qb = -(a * v2 + c * v0 - 2.0 * b * v1)
            qc = a * c - b * b
            disc = np.sqrt(np.maximum(qb * qb - 4.0 * qa * qc, 0.0))
            y = (-qb + disc) / (2.0 * qa)
        return np.asarray(y, dtype=np.float64), np.asarray(qc > 0.0, dtype=bool)

    def _hx(self, lo: Sym2, R: Sym2, X: Sym2, zform: bool) -> tuple[Mat, Sym2]:
        """``h`` and its ``X``-gradient ``R ∇h R`` at ``V = V_lo + R X R``."""
        RXR = _sandwich(R, X)
        V = (lo[0] + RXR[0], lo[1] + RXR[1], lo[2] + RXR[2])
        g, G = self._h(V, zform)
        return g, _sandwich(R, G)

    def _goal(self, tau: float) -> float:
        """The threshold in ``h``'s units: the least ``h``-bound whose :meth:`_final` exceeds
        ``tau`` (the model errors added back; frobenius: squared), slightly raised.  Only the
        iterations' stopping rule uses it: a node stops once its bound, *after* the deflation of
        :meth:`_final`, would prune it.  (Stopping at ``tau`` itself left every such bound
        deflated back below ``tau``, so only bounds far above it could prune.)"""
        if not math.isfinite(tau):
            return tau
        a, c = self._final_affine()
        if a <= 0.0:
            return math.inf
        t = (tau + c) / a
        if self.form == "frobenius":
            return t * t * (1.0 + 1e-12) if t >= 0.0 else -math.inf
        return t + 1e-12 * abs(t)

    def _final_affine(self) -> tuple[float, float]:
        """``(a, c)`` with :meth:`_final`'s ``v = a x - c``, ``x`` the ``h``-bound (frobenius:
        its square root)."""
        prob, ctx, n = self.prob, self.prob.ctx, self.prob.n
        rel = ROUND * n * EPS
        if self.form == "frobenius":
            return 1.0 - rel, 3.0 * n * ctx.err + rel * ctx.scale
        rho = n * ctx.err / ctx.lam_min
        if self.form == "kl":
            tr_inv = self.kappa_D / prob.dc.trace
            mag = tr_inv * ctx.lam_max + prob.dc.trace / ctx.lam_min + 2.0 * n
            kap = ROUND * n * n * n * EPS * (ctx.kappa + self.kappa_D)
            return 1.0 - rel - 3.0 * rho, 3.0 * rho * n + kap * mag
        kap = ROUND * n * n * n * EPS * (ctx.kappa + 1.0)
        return 1.0 - rel, 2.0 * n * rho + kap * (self.mag + abs(self.c1))

    def _deflate(self, lb: Mat, h: Mat, G: Sym2) -> Mat:
        """``lb`` less the rounding of its terms (relative ``rel`` of ``|h|`` and of the
        gradient's size), in ``h``'s units."""
        gn = np.sqrt(_dot2(G, G))
        return np.asarray(lb - self.rel * (np.abs(h) + 4.0 * gn + 1.0), dtype=np.float64)

    def _final(self, lb: Mat) -> Mat:
        """From ``h``'s units to the metric's, less the model errors (the interval bounds'):
        frobenius ``a sqrt(max(lb, 0)) - c``, kl and logdet ``a lb - c`` (:meth:`_final_affine`;
        kl: ``lb (1 - rel) - (3 ρ (lb + n) + κ' mag)``, logdet ``lb (1 - rel) - (2 n ρ + κ'
        (mag + |c1|))``, ``ρ = n err / λmin``)."""
        a, c = self._final_affine()
        x = np.sqrt(np.maximum(lb, 0.0)) if self.form == "frobenius" else lb
        v = a * x - c
        return np.where(np.isnan(v), -np.inf, v)


class _Leaves:
    """The last ``u`` levels of a kl, frobenius or logdet tree at once: a table of completions
    and a ball.

    kl in ``Z`` (:class:`_Relaxation`) is ``h(Z) = ¼ (c0 + <Q, Z⁻¹> + <P_d[s, s], Z>)``, convex
    on ``Z ≻ 0``, and on the paper-like problems its minimum over subsets is within about
    ``1e-8`` of its continuous minimum: every node whose interval contains the continuous
    minimiser survives every continuous bound, and the tree enumerates the completions near it
    one level at a time.  Instead, below depth ``d0 = m - u`` the completions of a node ``I`` are
    ``Z(I) + T_t``, ``T_t`` the sums of the subsets ``t`` of the last ``u`` sensors (a table of
    ``2^u`` rows built once), and those that can still be ``<= τ`` lie in a ball:

    **Strong convexity.**  ``∇²h(Z)[H, H] = ½ tr(Q Z⁻¹ H Z⁻¹ H Z⁻¹) = ½ tr(Q^½ B Bᵀ Q^½)``,
    ``B = Z⁻¹ H Z^-½``, ``>= ½ λmin(Q) ||B||_F² >= ½ λmin(Q) λmax(Z)⁻³ ||H||_F²``.  So on any
    convex set where ``λmax(Z) <= Λ``, ``h`` is ``μ = ½ λmin(Q) Λ⁻³``-strongly convex, and for
    ``Z0`` there (value ``h0``, gradient ``g0``)::

        h(Z) >= h0 + <g0, Z - Z0> + (μ/2) ||Z - Z0||²,   so   h(Z) <= τ'  ⟹
        ||Z - c|| <= r,  c = Z0 - g0/μ,  r² = 2 (τ' - h0)/μ + ||g0||²/μ²

    (Frobenius norm on symmetric ``2 x 2``: coordinates ``(a, √2 b, c)``).  ``Z0`` is the
    continuous minimiser (``Z P_d[s, s] Z = Q``, solved in closed form; only ``g0`` depends on
    how well); ``Λ`` first ``max(λmax(Z_all), λmax(Z0))`` (every completion is ``⪯ Z_all``, and
    ``λmax`` is convex, so this bounds it on the segments from ``Z0`` too), then, twice,
    ``max(λmax(Z0), λmax(c) + r)`` of the previous ball: every completion with ``h <= τ'`` is
    in that ball, where ``λmax <= λmax(c) + r`` (Weyl), and again convexity covers the segments
    from ``Z0``.  The computed gradient's error ``g_err`` (its two terms cancel at ``Z0``) moves
    the center by at most ``g_err / μ``: added to ``r``.

    **frobenius** (:class:`_Relaxation`: ``h(W) = ||M0 + K W Kᵀ||_F²``, the square of the
    metric, ``W = Z⁻¹``) is a quadratic in ``W`` with ``∇²h[H, H] = 2 ||K H Kᵀ||_F² >= 2
    λmin(KᵀK)² ||H||_F²`` everywhere, so the same inequality, with ``Z0`` replaced by the
    unconstrained minimiser ``W0 = -(KᵀK)⁻¹ Kᵀ M0 K (KᵀK)⁻¹`` and ``μ = 2 λmin(KᵀK)²``, puts
    every ``W`` with ``h(W) <= τ'`` in a ball ``||W - c|| <= r``.  For ``c ≻ 0`` and a
    completion ``Z = W⁻¹ ⪯ Z_all``: ``||Z - c⁻¹||_F = ||W⁻¹ (c - W) c⁻¹||_F <= λmax(Z) r /
    λmin(c)``, with ``λmax(Z) <= Λ``, first ``λmax(Z_all)``, then (twice) ``λmax(c⁻¹)`` plus the
    previous radius: the ball in ``Z`` that is queried.

    **logdet** in ``Z`` (:meth:`_Relaxation.z_convex`: ``h = c1 + log det(Z + V1) - ½ log det
    Z``): ``∇²h[H, H] = ½ ||M||_F² - ||A M Aᵀ||_F²`` with ``M = Z^-½ H Z^-½``, ``A = (Z +
    V1)^-½ Z^½``, ``||A||_2² = s = y_max / (1 + y_max)`` (``y`` the eigenvalues of ``V1⁻¹ Z``), so
    ``∇²h >= (½ - s²) / λmax(Z)²``: strongly convex on the convex set ``{λmax(Z) <= Λ,
    y_max(Z) <= Y}`` when ``Y < 1 + sqrt 2``.  Every completion is in it with ``Λ =
    max(λmax(Z_all), λmax(V1))``, ``Y = max(1, y_max(Z_all))`` (both monotone in the Loewner
    order and convex), and so is ``Z0 = V1``, the stationary point (``(Z + V1)⁻¹ = ½ Z⁻¹``,
    ``y = 1``); then the same ball, refined twice (``λmax <= λmax(c) + r``, ``y_max <=
    y_max(c) + r / λmin(V1)`` on it).  No ball (the tree goes on) when ``y_max(Z_all) >= 1 +
    sqrt 2``.

    **Threshold.**  ``τ' = (goal(τ) + rel) / (1 - rel)`` (:meth:`_Relaxation._goal`, the
    relaxation's rounding ``rel``): a completion whose exact ``h`` exceeds it has a relaxation
    bound (the degenerate interval ``[Z, Z]``: ``h`` deflated) above ``τ``, so its computed value
    is above ``τ`` and it is pruned exactly as the tree would prune it; ``h0``, ``g0``, ``r`` and
    the projections below carry a relative ``1e-6`` of slack for their own rounding.  The
    completions inside are recorded as candidates with that degenerate relaxation bound (``<=``
    their computed value); ``t = 0`` (``I`` itself) was recorded when its last sensor was
    included.  Pruned completions are above ``τ`` (the certified bound takes ``τ``).

    The table's points ``(a, √2 b, c)`` are in a k-d tree (``scipy.spatial.cKDTree``); a node's
    query is the ball around ``c - Z(I)`` (radius widened by a relative ``1e-6`` of the
    coordinates for their rounding), then the budget (``|t| <= K - |I|``).
    """

    def __init__(self, prob: _Problem, d0: int) -> None:
        relax = prob.relax
        assert relax is not None and relax.leaves
        self.prob, self.relax, self.d0 = prob, relax, d0
        u = prob.m - d0
        self.u = u
        T = np.zeros((1, 4))
        cnt = np.zeros(1, dtype=np.int64)
        for j in range(d0, prob.m):
            T = np.concatenate((T, T + prob.S[j]))
            cnt = np.concatenate((cnt, cnt + 1))
        X = np.stack((T[:, 0], math.sqrt(2.0) * T[:, 1], T[:, 3]), axis=1)
        from scipy.spatial import cKDTree  # here only: the start-up of covnet.core stays light

        self.tree = cKDTree(X, leafsize=32, balanced_tree=False)
        self._ball_of: tuple[float, tuple[NDArray[np.float64], float] | None] | None = None
        self.Xmax = float(np.abs(X).max())
        self.T, self.cnt = T, cnt
        self.lam_all = _lmax(prob.base + prob.suffix[0])
        if relax.form == "frobenius":
            self._frobenius()
            return
        if relax.form == "logdet":
            self._logdet()
            return
        # the continuous minimiser: Z Dss Z = Q  ⟺  Z = Dss^-½ (Dss^½ Q Dss^½)^½ Dss^-½
        Dh = _sqrt2(*relax.Dss)
        Dhi = _inv2(*Dh)
        M = _sqrt2(*_sandwich(Dh, relax.Q))
        Z0 = _sandwich(Dhi, M)
        self.Z0 = np.array([Z0[0][0], Z0[1][0], Z0[1][0], Z0[2][0]])
        self._anchor(self.Z0)
        # the computed gradient ¼ (Dss - Z0⁻¹ Q Z0⁻¹) (two terms that cancel at Z0) is within a
        # relative rel of their sizes
        Zi = _inv2(*_s2(self.Z0[None]))
        QZ = _sandwich(Zi, relax.Q)
        size = float(np.sqrt(_dot2(relax.Dss, relax.Dss))[0] + np.sqrt(_dot2(QZ, QZ))[0])
        self.g_err = 0.25 * size * (relax.rel + 1e-12)
        self.lmin_Q = float(_eig2(*relax.Q)[1][0])
        self.lmax0 = max(self.lam_all, _lmax(self.Z0))

    def _frobenius(self) -> None:
        """The constants of the frobenius ball (class docstring)."""
        relax, prob = self.relax, self.prob
        n = prob.n
        K = prob.Kmat
        KtK = K.T @ K
        KtK = 0.5 * (KtK + KtK.T)
        A = np.linalg.inv(KtK)
        M0 = relax.M0.reshape(n, n)
        W0 = -(A @ (K.T @ M0 @ K) @ A)
        W0 = 0.5 * (W0 + W0.T)
        self.W0 = W0.reshape(4)
        self._anchor(self.W0)
        # the gradient 2 Kᵀ (M0 + K W0 Kᵀ) K: two terms that cancel at W0
        size = 2.0 * (float(np.linalg.norm(K.T @ M0 @ K)) + float(np.linalg.norm(KtK @ W0 @ KtK)))
        self.g_err = size * (relax.rel + 1e-12)
        self.mu = 2.0 * float(np.linalg.eigvalsh(KtK)[0]) ** 2 * (1.0 - 1e-6)

    def _anchor(self, V: Mat, zform: bool = False) -> None:
        """``h0`` (rounded down), ``g0`` (``(a, b, c)``) and ``|g0|`` (rounded up) of the
        objective at the row-major ``2 x 2`` point ``V``: the anchor of the balls."""
        relax = self.relax
        with np.errstate(all="ignore"):
            h0, g0 = relax._h(_s2(V[None]), zform=zform)
        self.h0 = float(h0[0]) - relax.rel * (abs(float(h0[0])) + 1.0)
        g = np.array([g0[0][0], g0[1][0], g0[2][0]])
        self.g0 = g
        self.gn = float(np.sqrt(g[0] ** 2 + 2.0 * g[1] ** 2 + g[2] ** 2)) * (1.0 + 1e-6)

    def _threshold(self, tau: float) -> float | None:
        """``τ'`` of ``τ`` (class docstring), or None where there is none."""
        if not math.isfinite(tau):
            return None
        relax = self.relax
        tp = (relax._goal(tau) + relax.rel) / (1.0 - relax.rel)
        return tp if math.isfinite(tp) else None

    def _strong_ball(self, x0: Mat, mu: float, tp: float) -> tuple[Mat, float] | None:
        """Center (row-major ``2 x 2``) and radius of the ball holding every point with
        ``h <= tp`` of a ``mu``-strongly convex ``h`` anchored at ``x0`` (:meth:`_anchor`),
        the computed gradient's error included; None: no point reaches ``tp``."""
        gn = self.gn + self.g_err
        r2 = 2.0 * (tp - self.h0) / mu + (gn / mu) ** 2
        if r2 < 0.0:
            return None
        r = math.sqrt(r2) * (1.0 + 1e-6) + self.g_err / mu
        c = x0 - np.array([self.g0[0], self.g0[1], self.g0[1], self.g0[2]]) / mu
        return c, r

    def ball(self, tau: float) -> tuple[NDArray[np.float64], float] | None:
        """The ball of the completions that can still reach ``tau`` (center in the table's
        coordinates, radius; see the per-metric methods); the last one is kept, as ``tau``
        changes only when the incumbent does."""
        if self._ball_of is not None and self._ball_of[0] == tau:
            return self._ball_of[1]
        if self.relax.form == "frobenius":
            got = self._frobenius_ball(tau)
        elif self.relax.form == "logdet":
            got = self._logdet_ball(tau)
        else:
            got = self._kl_ball(tau)
        self._ball_of = (tau, got)
        return got

    def _logdet(self) -> None:
        """The constants of the logdet ball (class docstring)."""
        relax, prob = self.relax, self.prob
        V1 = np.array([relax.V1[0][0], relax.V1[1][0], relax.V1[1][0], relax.V1[2][0]])
        self.Z0 = V1  # the stationary point: (Z + V1)⁻¹ = ½ Z⁻¹
        self._anchor(V1, zform=True)
        Vi = _inv2(*_s2(V1[None]))
        size = float(np.sqrt(_dot2(Vi, Vi))[0])  # (2 V1)⁻¹ - ½ V1⁻¹: two terms of this size
        self.g_err = size * (relax.rel + 1e-12)
        self.lam_v = _lmax(V1)
        self.lmin_v = _lmin_below(V1)
        Z_all = prob.base + prob.suffix[0]
        y_all, pd = relax.y_max(Z_all[None])
        rho = prob.n * prob.ctx.err / prob.ctx.lam_min
        self.y_all = max(1.0, float(y_all[0]) * (1.0 + 1e-6 + 4.0 * rho))
        if not (bool(pd[0]) and math.isfinite(self.y_all)):
            self.y_all = math.inf

    def _logdet_ball(self, tau: float) -> tuple[NDArray[np.float64], float] | None:
        """The ball of :meth:`ball` for logdet in ``Z`` (class docstring)."""
        relax = self.relax
        tp = self._threshold(tau) if self.lmin_v > 0.0 else None
        if tp is None:
            return None
        lam = max(self.lam_all, self.lam_v)
        Y = self.y_all
        best: tuple[NDArray[np.float64], float] | None = None
        for _ in range(3):
            if not Y < LOGDET_CONVEX:
                return best
            s_ = Y / (1.0 + Y)
            mu = (0.5 - s_ * s_) / (lam * lam) * (1.0 - 1e-6)
            if not mu > 0.0:
                return best
            got = self._strong_ball(self.Z0, mu, tp)
            if got is None:
                return NO_BALL
            c, r = got
            cx = _coords(c)
            if best is None or r < best[1]:
                best = (cx, r)
            # on the ball: λmax <= λmax(c) + r, y_max <= y_max(c) + r / λmin(V1)
            yc, _ = relax.y_max(c[None])
            new_lam = max(self.lam_v, _lmax(c) + r * (1.0 + 1e-6))
            new_y = max(1.0, (float(yc[0]) + r / self.lmin_v) * (1.0 + 1e-6))
            if not (new_lam < lam or new_y < Y):
                break
            lam, Y = min(lam, new_lam), min(Y, new_y)
        return best

    def _frobenius_ball(self, tau: float) -> tuple[NDArray[np.float64], float] | None:
        """The ball in ``Z`` of :meth:`ball` for frobenius (class docstring)."""
        tp = self._threshold(tau) if self.mu > 0.0 else None
        if tp is None:
            return None
        got = self._strong_ball(self.W0, self.mu, tp)
        if got is None:
            return NO_BALL
        c, r = got
        # λmin(c) from below (the 2 x 2 closed form, rounded down a little)
        a, b, d = float(c[0]), float(c[1]), float(c[3])
        lmin_c = _lmin_below(c) - 1e-12 * (abs(a) + abs(b) + abs(d))
        if not lmin_c > 0.0:
            return None
        ci = _inv2(np.array([a]), np.array([b]), np.array([d]))
        zc = np.array([float(ci[0][0]), float(ci[1][0]), float(ci[1][0]), float(ci[2][0])])
        lam_ci = _lmax(zc)
        lam = self.lam_all
        rz = math.inf
        for _ in range(3):
            rz = min(rz, lam * r / lmin_c * (1.0 + 1e-6))
            new = lam_ci + rz
            if not new < lam:
                break
            lam = new
        cx = _coords(zc)
        # the computed c⁻¹ is within a relative 1e-9 of the exact one (slack in the radius)
        return cx, rz + 1e-9 * float(np.abs(cx).max())

    def _kl_ball(self, tau: float) -> tuple[NDArray[np.float64], float] | None:
        """Center ``(a, √2 b, c)`` and radius of the ball holding every completion ``Z`` with
        ``h(Z) <= τ'`` (radius ``-1``: none can; ``None``: no ball, e.g. ``τ = inf`` or
        ``λmin(Q) <= 0`` from rounding: then the tree goes on below ``d0``)."""
        tp = self._threshold(tau) if self.lmin_Q > 0.0 else None
        if tp is None:
            return None
        lam = self.lmax0
        best: tuple[NDArray[np.float64], float] | None = None
        for _ in range(3):
            mu = 0.5 * self.lmin_Q / lam**3 * (1.0 - 1e-6)
            got = self._strong_ball(self.Z0, mu, tp)
            if got is None:
                return NO_BALL  # nothing can reach τ'
            c, r = got
            cx = _coords(c)
            if best is None or r < best[1]:
                best = (cx, r)
            # every completion with h <= τ' is in this ball: λmax <= λmax(c) + r there, and
            # on the segments from Z0 to it (λmax is convex)
            new = max(_lmax(self.Z0), _lmax(c) + r * (1.0 + 1e-6))
            if not new < lam:
                break
            lam = new
        return best

    def leaves(
        self, Z: Mat, k: NDArray[np.int64], inc: NDArray[np.uint8], tau: float
    ) -> tuple[NDArray[np.uint8], Mat, int]:
        """The completions of the nodes (``Z`` ``(c, 4)``, ``k``, packed ``inc``) inside the
        ball, as packed rows with their bounds; and how many table rows were looked at."""
        prob = self.prob
        got = self.ball(tau)
        empty = (np.zeros((0, inc.shape[1]), dtype=np.uint8), np.zeros(0), 0)
        if got is None:
            return empty
        cx, r = got
        if r < 0.0:
            return empty
        Zx = np.stack((Z[:, 0], math.sqrt(2.0) * Z[:, 1], Z[:, 3]), axis=1)
        q = cx[None] - Zx  # the ball's center relative to each node
        # slack for the rounding of q and of the table's coordinates
        rad = r * (1.0 + 1e-6) + 1e-6 * (np.sqrt((q * q).sum(axis=1)) + self.Xmax)
        hits = self.tree.query_ball_point(q, rad, eps=0.0, return_sorted=False)
        n = np.array([len(h) for h in hits], dtype=np.intp)
        tot = int(n.sum())
        if tot == 0:
            return empty
        node = np.repeat(np.arange(Z.shape[0]), n)
        t = np.concatenate([np.asarray(h, dtype=np.intp) for h in hits])
        ok = (t != 0) & (self.cnt[t] <= prob.K - k[node])
        return self._rows(Z, inc, node[ok], t[ok], tau, tot)

    def _rows(
        self,
        Z: Mat,
        inc: NDArray[np.uint8],
        node: NDArray[np.intp],
        t: NDArray[np.intp],
        tau: float,
        looked: int,
    ) -> tuple[NDArray[np.uint8], Mat, int]:
        if node.size == 0:
            return np.zeros((0, inc.shape[1]), dtype=np.uint8), np.zeros(0), looked
        Zt = Z[node] + self.T[t]
        est = self.relax.bound(Zt, Zt, tau)
        bits = ((t[:, None] >> np.arange(self.u)) & 1).astype(bool)
        rows = self.prob.unpack(inc[node])
        rows[:, self.d0 :] |= bits
        packed = np.packbits(rows, axis=1, bitorder="little")
        return packed, est, looked


NO_BALL: tuple[NDArray[np.float64], float] = (np.zeros(3), -1.0)
"""What :meth:`_Leaves.ball` returns when no completion can reach the threshold."""


def _coords(Z: Mat) -> NDArray[np.float64]:
    """The k-d tree coordinates ``(a, √2 b, c)`` of one row-major ``2 x 2`` ``Z`` (the
    Frobenius norm of symmetric matrices as the Euclidean one)."""
    return np.array([Z[0], math.sqrt(2.0) * Z[1], Z[3]])


def _lmin_below(Z: Mat) -> float:
    """The smallest eigenvalue of one row-major symmetric ``2 x 2`` ``Z``, rounded down a
    little (closed form)."""
    a, b, c = float(Z[0]), float(Z[1]), float(Z[3])
    return (0.5 * (a + c) - math.hypot(0.5 * (a - c), b)) * (1.0 - 1e-9)


def _lmax(Z: Mat) -> float:
    """The largest eigenvalue of one row-major ``2 x 2`` ``Z``, rounded up a little."""
    a, b, c = float(Z[0]), float(0.5 * (Z[1] + Z[2])), float(Z[3])
    h, q = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    return (h + q) * (1.0 + 1e-9) + 1e-300


def _take(x: Sym2, rows: NDArray[np.intp]) -> Sym2:
    return x[0][rows], x[1][rows], x[2][rows]


def _where(ok: NDArray[np.bool_], x: Sym2, y: Sym2) -> Sym2:
    return np.where(ok, x[0], y[0]), np.where(ok, x[1], y[1]), np.where(ok, x[2], y[2])


# --------------------------------------------------------------------------------------------
# branch and bound
# --------------------------------------------------------------------------------------------


@dataclass(slots=True)
class _Chunk:
    """A batch of nodes of one depth ``d`` (the first ``d`` sensors of the order decided):
    ``Z`` ``(c, r*r)`` the information of ``I``, ``k`` ``(c,)`` ``|I|`` with the required ones,
    ``inc`` ``(c, ⌈m/8⌉)`` ``I`` as packed branching-order rows (:meth:`_Problem.unpack`),
    ``sA``/``sB`` the endpoint summaries, ``lb`` the bounds."""

    depth: int
    Z: Mat
    k: NDArray[np.int64]
    inc: NDArray[np.uint8]
    sA: Mat
    sB: Mat
    lb: Mat

    def take(self, rows: NDArray[np.bool_] | NDArray[np.intp]) -> _Chunk:
        return _Chunk(
            self.depth,
            self.Z[rows],
            self.k[rows],
            self.inc[rows],
            self.sA[rows],
            self.sB[rows],
            self.lb[rows],
        )


def _concat(chunks: list[_Chunk]) -> _Chunk:
    if len(chunks) == 1:
        return chunks[0]
    return _Chunk(
        chunks[0].depth,
        *(
            np.concatenate([getattr(c, name) for c in chunks])
            for name in ("Z", "k", "inc", "sA", "sB", "lb")
        ),
    )


class _Candidates:
    """Recorded subsets (packed branching-order rows) with lower bounds of their values, not yet
    evaluated; compacted (rows above the current threshold dropped) as it grows."""

    def __init__(self, m: int) -> None:
        self.inc: list[NDArray[np.uint8]] = []
        self.est: list[Mat] = []
        self.size = 0
        self.nb = (m + 7) // 8

    def add(self, inc: NDArray[np.uint8], est: Mat, tau: float) -> None:
        if est.size:
            self.inc.append(inc)
            self.est.append(est)
            self.size += est.size
            if len(self.est) >= 256:
                self.keep_below(tau)

    def arrays(self) -> tuple[NDArray[np.uint8], Mat]:
        if not self.est:
            return np.zeros((0, self.nb), dtype=np.uint8), np.zeros(0)
        if len(self.est) > 1:
            self.inc = [np.concatenate(self.inc)]
            self.est = [np.concatenate(self.est)]
        return self.inc[0], self.est[0]

    def keep_below(self, tau: float) -> None:
        inc, est = self.arrays()
        rows = est <= tau
        self.inc, self.est = [inc[rows]], [est[rows]]
        self.size = int(rows.sum())

    def clear(self) -> None:
        self.inc, self.est, self.size = [], [], 0


class _Search:
    """The branch and bound state (module docstring)."""

    def __init__(
        self,
        prob: _Problem,
        rel_gap: float,
        best_first: bool,
        deadline: Callable[[], bool] | None,
        node_limit: int | None,
    ) -> None:
        self.prob = prob
        self.rel_gap = rel_gap
        self.best_first = best_first
        self.deadline = deadline
        self.node_limit = node_limit
        self.cands = _Candidates(prob.m)
        self.ev_masks: list[NDArray[np.bool_]] = []
        self.ev_vals: list[Mat] = []
        self.U = math.inf
        self.L_pruned = math.inf
        self.n_nodes = 0
        self.open: list[_Chunk] = []
        self.keys: list[float] = []
        self.n_open = 0
        self.n_pops = 0
        # the table's depth (built when a node first reaches it), -1: none
        self.leaves: _Leaves | None = None
        self.d0 = -1
        if rel_gap == 0.0 and prob.relax is not None and prob.relax.leaves:
            u = min(LEAF_LEVELS, prob.m - min(LEAF_TOP, prob.m // 2))
            if u > 0:
                self.d0 = prob.m - u
        q = 8 * prob.n + prob.n * prob.n  # the widest summary's entries, generously
        per_node = 8 * (prob.r * prob.r + 2 + 2 * q) + (prob.m + 7) // 8
        self.open_cap = max(CHUNK, OPEN_BYTES // per_node)

    # -- incumbent and thresholds ---------------------------------------------------------------

    @property
    def tau(self) -> float:
        """Prune above this: the tie threshold of the incumbent ``U + tie_rtol·max(|U|, tiny)``
        (exact), or ``U - rel_gap·|U|`` (bounded)."""
        U = self.U
        if not math.isfinite(U):
            return math.inf
        if self.rel_gap > 0.0:
            return U - self.rel_gap * abs(U)
        return U + self.prob.tie_rtol * max(abs(U), TINY)

    def evaluated(self, masks: NDArray[np.bool_], values: Mat) -> None:
        self.ev_masks.append(masks)
        self.ev_vals.append(values)
        if values.size:
            self.U = min(self.U, float(values.min()))

    def evaluate_inc(self, inc: NDArray[np.uint8]) -> None:
        masks = self.prob.masks(self.prob.unpack(inc))
        self.evaluated(masks, self.prob.exact(masks))

    # -- the tree ---------------------------------------------------------------------------------

    def push(self, ch: _Chunk) -> None:
        """Add open nodes, in batches of at most CHUNK (depth first: a small batch of the same
        depth as the last one is merged into it)."""
        if ch.lb.size == 0:
            return
        self.n_open += ch.lb.size
        if self.open and not self.best_first:
            top = self.open[-1]
            if top.depth == ch.depth and top.lb.size + ch.lb.size <= CHUNK:
                self.open[-1] = _concat([top, ch])
                self.keys[-1] = min(self.keys[-1], float(ch.lb.min()))
                return
        if ch.lb.size > CHUNK:
            ch = ch.take(np.argsort(ch.lb, kind="stable"))
            # the lowest bounds last: depth first pops them first
            for lo in range(((ch.lb.size - 1) // CHUNK) * CHUNK, -1, -CHUNK):
                piece = ch.take(np.arange(lo, min(lo + CHUNK, ch.lb.size)))
                self.open.append(piece)
                self.keys.append(float(piece.lb[0]))
        else:
            self.open.append(ch)
            self.keys.append(float(ch.lb.min()))

    def pop(self) -> _Chunk:
        """Depth first (the last pushed: bounded memory), or, with ``rel_gap`` and at most
        OPEN_BYTES of open nodes, best bound first on every other pop (the certified bound
        rises) and depth first in between (dives find better incumbents)."""
        self.n_pops += 1
        if self.best_first and self.n_open <= self.open_cap and self.n_pops % 2:
            i = min(range(len(self.keys)), key=self.keys.__getitem__)
        else:
            i = len(self.open) - 1
        ch = self.open.pop(i)
        self.keys.pop(i)
        self.n_open -= ch.lb.size
        return ch

    def prune(self, lb: Mat) -> NDArray[np.bool_]:
        """Rows to keep (bound <= tau); the pruned ones' least bound goes to ``L_pruned``."""
        keep = lb <= self.tau
        if not keep.all():
            self.L_pruned = min(self.L_pruned, float(lb[~keep].min()))
        return keep

    def root(self) -> None:
        prob = self.prob
        k0 = len(prob.req)
        if prob.m == 0 or k0 >= prob.K:
            return
        Z0 = prob.base[None]
        sB = prob.summary(Z0)
        sA = prob.summary(Z0 + prob.suffix[0])
        lb = prob.combine(sA, sB)
        lb = prob.refine(Z0, Z0 + prob.suffix[0], lb, sB, self.tau)
        self.n_nodes += 1
        nb = (prob.m + 7) // 8
        root = _Chunk(0, Z0, np.array([k0]), np.zeros((1, nb), dtype=np.uint8), sA, sB, lb)
        if self.prune(lb).all():
            self.push(root)

    def record(self, inc: NDArray[np.uint8], est: Mat) -> None:
        """New candidates: those that can still tie are kept; the best few that could beat the
        incumbent are evaluated at once (the incumbent, so the threshold, falls early)."""
        rec = self.prune(est)
        inc, est = inc[rec], est[rec]
        if est.size == 0:
            return
        better = np.flatnonzero(est < self.U)
        if better.size:
            picks = better[np.argsort(est[better], kind="stable")[:EVAL_PICKS]]
            self.evaluate_inc(inc[picks])
            rest = np.ones(est.size, dtype=bool)
            rest[picks] = False
            rest &= est <= self.tau
            inc, est = inc[rest], est[rest]
        self.cands.add(inc, est, self.tau)

    def expand(self, ch: _Chunk) -> None:
        """Children of every node of ``ch`` (decide sensor ``free[d]``): bounds, pruning,
        candidates, and the open children pushed."""
        prob = self.prob
        keep = self.prune(ch.lb)
        if not keep.all():
            ch = ch.take(keep)
        if ch.lb.size == 0:
            return
        d = ch.depth
        if d == self.d0 and self.leaves_expand(ch):
            return
        last = d + 1 == prob.m
        relax = prob.m - (d + 1) >= RELAX_MIN_REST
        out: list[_Chunk] = []
        # include children: I + free[d], a new B (every node here has k < K)
        Zi = ch.Z + prob.S[d]
        sBi = prob.summary(Zi)
        ki = ch.k + 1
        inc = ch.inc.copy()
        inc[:, d >> 3] |= np.uint8(1 << (d & 7))
        est = prob.combine(sBi, sBi)
        self.n_nodes += est.size
        self.record(inc, est)
        if not last:
            inner = np.flatnonzero(ki < prob.K)
            if inner.size:
                sA = ch.sA[inner]
                lbi = prob.combine(sA, sBi[inner])
                if relax:
                    Zn = Zi[inner]
                    lbi = prob.refine(Zn, Zn + prob.suffix[d + 1], lbi, sBi[inner], self.tau)
                kept = self.prune(lbi)
                rows = inner[kept]
                out.append(
                    _Chunk(d + 1, Zi[rows], ki[rows], inc[rows], sA[kept], sBi[rows], lbi[kept])
                )
            # exclude children: I unchanged, a new A
            Z_hi = ch.Z + prob.suffix[d + 1]
            sAe = prob.summary(Z_hi)
            lbe = prob.combine(sAe, ch.sB)
            if relax:
                lbe = prob.refine(ch.Z, Z_hi, lbe, ch.sB, self.tau)
            self.n_nodes += lbe.size
            kept = self.prune(lbe)
            if kept.any():
                out.append(
                    _Chunk(
                        d + 1,
                        ch.Z[kept],
                        ch.k[kept],
                        ch.inc[kept],
                        sAe[kept],
                        ch.sB[kept],
                        lbe[kept],
                    )
                )
        if out:
            self.push(_concat(out))

    def leaves_expand(self, ch: _Chunk) -> bool:
        """The whole subtrees of ``ch`` (depth ``d0``) from the table (:class:`_Leaves`):
        their completions inside the ball recorded as candidates; ``False``: no ball, expand
        as usual."""
        if self.leaves is None:
            try:
                self.leaves = _Leaves(self.prob, self.d0)
            except (FloatingPointError, ValueError, np.linalg.LinAlgError):
                self.d0 = -1
                return False
        if self.leaves.ball(self.tau) is None:
            return False
        # the lowest bounds first, a few nodes at a time: the threshold falls in between
        order = np.argsort(ch.lb, kind="stable")
        for lo in range(0, order.size, LEAF_GROUP):
            sub = ch.take(order[lo : lo + LEAF_GROUP])
            sub = sub.take(self.prune(sub.lb))
            if sub.lb.size == 0:
                continue
            tau = self.tau
            inc, est, looked = self.leaves.leaves(sub.Z, sub.k, sub.inc, tau)
            self.n_nodes += looked
            # every completion left out is above tau (its bound too)
            self.L_pruned = min(self.L_pruned, tau)
            self.record(inc, est)
        return True

    def limited(self) -> int:
        if self.node_limit is not None and self.n_nodes >= self.node_limit:
            return 1
        if self.deadline is not None and self.deadline():
            return 2
        return 0

    def run(self) -> int:
        """Explore until the tree is exhausted (0) or a limit is hit (1 nodes, 2 time)."""
        self.root()
        while self.open:
            why = self.limited()
            if why:
                return why
            self.expand(self.pop())
        return 0

    def lower_bound(self) -> float:
        """The least of the incumbent, the pruned nodes' and candidates' bounds, the open nodes'
        bounds and the pending candidates' bounds: at most the optimum."""
        L = min(self.U, self.L_pruned)
        if self.keys:
            L = min(L, min(self.keys))
        _, est = self.cands.arrays()
        if est.size:
            L = min(L, float(est.min()))
        return L


def allocate_bnb(
    P_pred: Mat,
    gains: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    constraints: Constraints = NO_CONSTRAINTS,
    tie_rtol: float = 1e-9,
    *,
    rel_gap: float = 0.0,
    time_limit_s: float | None = None,
    node_limit: int | None = None,
    clock: Callable[[], float] | None = None,
) -> SearchResult:
    """Branch and bound over include / exclude / undecided (module docstring).

    With ``rel_gap = 0`` and no limit hit (``status 0``, ``exact``): the same subset, value and
    ``P`` bits as :func:`covnet.core.allocation.allocate_exhaustive`, the same exceptions for bad
    input (:class:`~covnet.core.allocation.InfeasibleAllocation` included).  ``rel_gap > 0``,
    ``time_limit_s`` or ``node_limit``: bounded mode, the best subset found with a certified
    ``lower_bound`` and ``gap``; status 1 (node limit), 2 (time limit) or 3 (completed within
    ``rel_gap``).  ``clock``: seconds, for the time limit (default ``time.perf_counter``).

    A metric without an interval bound (a user's own function) is solved exactly by
    :func:`covnet.core.allocation.allocate` (its batched search), limits ignored.
    """
    if not (math.isfinite(rel_gap) and 0.0 <= rel_gap < 1.0):
        raise ValueError(f"rel_gap must be in [0, 1), got {rel_gap}")
    if time_limit_s is not None and not time_limit_s >= 0:
        raise ValueError(f"time_limit_s must be >= 0 or None, got {time_limit_s}")
    if node_limit is not None and (not isinstance(node_limit, int) or node_limit < 1):
        raise ValueError(f"node_limit must be an integer >= 1 or None, got {node_limit!r}")
    deadline: Callable[[], bool] | None = None
    if time_limit_s is not None:
        if clock is None:
            # only with a time limit (start-up: the core needs no clock otherwise)
            import time

            clock = time.perf_counter
        t_end = clock() + time_limit_s
        tick = clock

        def deadline() -> bool:
            return tick() >= t_end

    prob = _Problem(P_pred, gains, P_d, metric, constraints, tie_rtol)
    if prob.bound is None:
        ref = allocate(P_pred, gains, P_d, metric, constraints, tie_rtol)
        return SearchResult(
            ref.subset,
            ref.value,
            ref.P,
            ref.value,
            0.0,
            0,
            ref.n_evaluated,
            True,
            0,
            STATUS[0] + "; no interval bound for this metric: covnet.core.allocation.allocate",
        )
    # best bound first when a gap is asked for (the certified bound rises fastest); depth first
    # otherwise (bounded memory), also when only a limit guards an exact search
    try:
        search = _Search(prob, rel_gap, rel_gap > 0.0, deadline, node_limit)
        search.evaluated(*_greedy_start(prob))
        why = search.run()
        inc, est = search.cands.arrays()
        todo = est <= search.tau
        if todo.any():
            order = np.flatnonzero(todo)[np.argsort(est[todo], kind="stable")]
            if why:  # limited: the most promising few only, the rest stay in the bound
                order = order[: EVAL_PICKS * 16]
            search.evaluate_inc(inc[order])
            left = np.ones(est.size, dtype=bool)
            left[order] = False
            search.cands.inc, search.cands.est = [inc[left]], [est[left]]
        masks = np.concatenate(search.ev_masks)
        values = np.concatenate(search.ev_vals)
        k = tie_select(values, masks, prob.tie_rtol)
        mask, value = masks[k], float(values[k])
        P = prob.exact_covariances(mask[None])[0]
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    if why == 0 and rel_gap == 0.0:
        return SearchResult(
            _subset(mask),
            value,
            P,
            value,
            0.0,
            search.n_nodes,
            prob.n_evaluated,
            True,
            0,
            STATUS[0],
        )
    lb = min(max(search.lower_bound(), prob.root_bound()), value)
    status = why if why else 3
    return SearchResult(
        _subset(mask),
        value,
        P,
        lb,
        _gap(value, lb),
        search.n_nodes,
        prob.n_evaluated,
        False,
        status,
        STATUS[status],
    )
