"""The allocation problem as the search sees it (:mod:`covnet.core.allocation.search`,
:mod:`covnet.core.allocation.greedy`): validation (as the reference), the branching order, the
reduced form, exact evaluation, and the result record.

The covariances are computed in the reduced information form (as
:mod:`covnet.core.allocation._fast`): with ``s`` the support of the gains (the positions, for
position sensors), ``C = P_pred[s, s]``, ``Kᵀ = C⁻¹ P_pred[s, :]`` (a Cholesky solve) and
``P∞ = P_pred - K P_pred[s, :]``::

    P(S) = P∞ + K Z⁻¹ Kᵀ,    Z = C⁻¹ + Σ_{j∈S} J_j[s, s],

so a node carries the ``r x r`` information ``Z`` of ``I``, and a child costs one small inverse
and one ``(r², n²)`` product.  Their rounding error is covered by the bounds' error model
(:func:`covnet.core.allocation.interval_bounds.search_context`).

**Zero gains.**  A free sensor with an all-zero gain never changes ``J`` (a running sum from
``+0.0`` is never ``-0.0``, and ``x + 0 = x``), so ``D ∪ {j}`` ties exactly with ``D`` and loses
the tie rule to it; such sensors leave the search, except the lowest-indexed one as the singleton
candidate ``{j}`` when nothing is required.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from covnet.core.allocation._fast import _spd_inverse_soa, gain_sums, spd_inverse
from covnet.core.allocation.exact import Constraints, _checked, _spd_error
from covnet.core.allocation.interval_bounds import DesiredConstants, IntervalBound, search_context
from covnet.core.allocation.lower_bounds import DualNorm, _DualBound
from covnet.core.allocation.relaxation import LOGDET_CONVEX, _cho_solve, _cholesky, _Relaxation
from covnet.core.gaussian import Mat
from covnet.core.metrics import MetricFn, capability

TINY = float(np.finfo(np.float64).tiny)
#: the default: no constraint
NO_CONSTRAINTS = Constraints()
#: exact evaluations per batch are capped so that the gain sums' temporary ``(c, N, n, n)`` stays
#: below this many entries
EXACT_ENTRIES = 1 << 21
#: greedy's working values (and local search's moves) are computed in blocks of this many
MOVE_BLOCK = 1 << 15

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
    the optimum over the feasible subsets; ``gap = (value - lower_bound) / max(|value|, tiny)``.
    "The optimum" is the tie rule's choice: among the values within ``tie_rtol`` of the least,
    the fewest sensors.  So with status 0 ``lower_bound = value`` may lie up to ``tie_rtol``
    (relative) above the least value of all subsets, and status 3 means ``gap <= rel_gap +
    tie_rtol`` (``tie_rtol`` defaults to 1e-9; the config caps it at 1e-3);
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
        P, D, plan, self.f, entry = _checked(P_pred, gains, P_d, metric, constraints, tie_rtol)
        self.name = entry.name if entry is not None else None
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
        self._allowed = allowed  # the gains a subset may hold (:attr:`leaf_constants`)
        self.n_evaluated = 0
        self.moves = 0
        #: the time limit of a search (``True`` once reached; set by the branch and bound for
        #: its call): greedy's working values are then ``+inf`` (no move improves, every phase
        #: ends with what it has) and the relaxation's and dual bound's iterations stop (their
        #: bound so far, valid at every iteration)
        self.stop: Callable[[], bool] | None = None
        self.relax: _Relaxation | None = None
        relaxation = entry.relaxation if entry is not None else None
        if self.bound is not None and relaxation is not None and self.r == 2:
            try:
                self.relax = _Relaxation(self, relaxation)
            except np.linalg.LinAlgError:  # P_d not SPD: the metric itself will say so
                self.relax = None
        self.dual: _DualBound | None = None
        self._root_bound: float | None = None
        self._root_whole: float | None = None
        dual = capability(entry.dual_bound, DualNorm) if entry is not None else None
        if self.bound is not None and dual is not None and self.r == 2:
            try:
                self.dual = _DualBound(self, dual)
            except ValueError:  # too many atoms for this state dimension
                self.dual = None

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
        # the diagonal's columns (:meth:`diagonals`)
        diag = np.arange(n) * (n + 1)
        self.T_diag = np.ascontiguousarray(self.T[:, diag])
        self.P_inf_diag = self.P_inf[diag].copy()
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
        n = self.n
        m = Z.shape[0]
        if self.r == 0:
            return np.broadcast_to(self.P_inf.reshape(n, n), (m, n, n)).copy()
        X = np.asarray(self._inverse(Z) @ self.T, dtype=np.float64)
        X += self.P_inf
        return X.reshape(m, n, n)

    def diagonals(self, Z: Mat) -> Mat:
        """The diagonals ``(m, n)`` of :meth:`covariances`, bit for bit (the same dot product
        and sum per entry, on the diagonal's columns of ``T`` and ``P∞`` only)."""
        m = Z.shape[0]
        if self.r == 0:
            return np.broadcast_to(self.P_inf_diag, (m, self.n)).copy()
        d = np.asarray(self._inverse(Z) @ self.T_diag, dtype=np.float64)
        d += self.P_inf_diag
        return d

    def _inverse(self, Z: Mat) -> Mat:
        """``W = Z⁻¹`` (rows ``(m, r*r)``; ``r >= 1``)."""
        r = self.r
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
        return W

    def summary(self, Z: Mat) -> Mat:
        """The bound's endpoint summaries of the information rows ``Z`` (from the diagonals
        alone where the bound reads only them: abs_trace, trace_diff)."""
        assert self.bound is not None
        with np.errstate(all="ignore"):
            if self.bound.from_diagonal is not None:
                return self.bound.from_diagonal(self.diagonals(Z), self.dc)
            return self.bound.summary(self.covariances(Z), self.dc)

    def summary_above(self, Z: Mat, tau: float, lower: bool) -> Mat:
        """:meth:`summary`, except on rows the bound's pre-test proves to bound above ``tau``
        with any partner (:attr:`IntervalBound.above`: a summary read as ``+inf`` there;
        ``lower``: ``Z`` gives lower endpoints ``A``); :meth:`summary` where the bound has no
        pre-test or ``tau`` is not finite."""
        assert self.bound is not None
        if self.bound.above is None or not math.isfinite(tau):
            return self.summary(Z)
        with np.errstate(all="ignore"):
            return self.bound.above(self.covariances(Z), self.dc, self.ctx, tau, lower)

    def summary_lazy(self, Z: Mat, tau: float, lower: bool, prev: Mat) -> Mat:
        """:meth:`summary_above` through the bound's lazy summary (:attr:`IntervalBound.lazy`:
        ``prev``, the parent's summary of the same side, on the rows kept that need no
        eigenvalues); :meth:`summary_above` where the bound has none or ``tau`` is not
        finite."""
        assert self.bound is not None
        if self.bound.lazy is None or not math.isfinite(tau):
            return self.summary_above(Z, tau, lower)
        with np.errstate(all="ignore"):
            return self.bound.lazy(self.covariances(Z), self.dc, self.ctx, tau, lower, prev)

    def refine(self, Z_lo: Mat, Z_hi: Mat, lb: Mat, sB: Mat, tau: float) -> Mat:
        """``lb`` raised by the reduced relaxation (:class:`_Relaxation`) or the dual bound
        (:class:`~covnet.core.allocation.lower_bounds._DualBound`) where it applies."""
        if self.dual is not None and lb.size:
            rows = np.flatnonzero(lb <= tau)
            if rows.size == 0:
                return lb
            out = lb.copy()
            db = self.dual.bound(Z_lo[rows], Z_hi[rows], tau, self.stop)
            out[rows] = np.fmax(lb[rows], db)
            return out
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
            rb = self.relax.bound(Z_lo[rows], Z_hi[rows], tau, stop=self.stop)
            out[rows] = np.fmax(lb[rows], rb)
        if zrows.size:
            zb = self.relax.bound(Z_lo[zrows], Z_hi[zrows], tau, zform=True, stop=self.stop)
            out[zrows] = np.fmax(lb[zrows], zb)
        return out

    def refine_vertex(self, Z_lo: Mat, Z_hi: Mat, lb: Mat, tau: float) -> Mat:
        """``lb`` raised by the dual bound's vertex bound (:meth:`~covnet.core.allocation.\
lower_bounds._DualBound.vertex_bound`; one_norm, inf_norm, abs_trace) on the rows ``<= tau``: the
        exact search's bound on the nodes its barrier does not refine."""
        if self.dual is None or self.dual.dual.vertices is None or lb.size == 0:
            return lb
        rows = np.flatnonzero(lb <= tau)
        if rows.size == 0:
            return lb
        out = lb.copy()
        out[rows] = np.fmax(lb[rows], self.dual.vertex_bound(Z_lo[rows], Z_hi[rows]))
        return out

    @functools.cached_property
    def leaf_constants(self) -> object | None:
        """The constants of the bound's sharper bound of single subsets (kl's
        :class:`~covnet.core.allocation.interval_bounds.LeafBound`; the tie rule's pruning
        only), built on first use; ``None`` without one."""
        if self.bound is None or self.bound.leaf is None:
            return None
        try:
            return self.bound.leaf.constants(
                self.Y0, self.G[self._allowed], self.Cinv, self.s, self.P_pred, self.D
            )
        except np.linalg.LinAlgError:
            return None

    def leaf_bound(self, Z: Mat) -> Mat | None:
        """The bound's sharper bound of the single subsets with reduced information ``Z``
        ``(m, r*r)`` (:class:`~covnet.core.allocation.interval_bounds.LeafBound`; valid for
        every subset with the same exact information), or ``None`` without one."""
        lc = self.leaf_constants
        if lc is None:
            return None
        assert self.bound is not None and self.bound.leaf is not None
        with np.errstate(all="ignore"):
            v = self.bound.leaf.bound(Z, self.covariances(Z), lc, self.ctx)
        return np.where(np.isfinite(v), v, 0.0)  # a row it cannot bound: 0 (every value >= 0)

    def with_leaf(self, Z: Mat, est: Mat) -> Mat:
        """Candidate bounds ``est`` of the single subsets ``Z`` raised by :meth:`leaf_bound`
        where the bound has one."""
        leaf = self.leaf_bound(Z)
        return est if leaf is None else np.fmax(est, leaf)

    def information(self, rows: NDArray[np.bool_]) -> Mat:
        """The reduced information ``Z`` ``(c, r*r)`` of subsets given by branching-order rows
        ``(c, m)`` (the required sensors in ``base``)."""
        return self.base[None] + rows.astype(np.float64) @ self.S

    def combine(self, sA: Mat, sB: Mat) -> Mat:
        assert self.bound is not None
        with np.errstate(all="ignore"):
            v = self.bound.combine(sA, sB, self.dc, self.ctx)
        return np.where(np.isnan(v), 0.0, v)

    def approx_values(self, Z: Mat) -> Mat:
        """The metric on reduced-form covariances (greedy's working values; NaN -> +inf): for
        frobenius, kl and logdet with ``r = 2`` from the closed forms of :class:`_Relaxation`;
        all ``+inf`` once :attr:`stop` says the time is up."""
        if self.stop is not None and self.stop():
            return np.full(Z.shape[0], np.inf)
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
        out = _exact_values(self.f, self.D, self.Y0, self.G, masks)
        self.n_evaluated += masks.shape[0]
        return out

    def exact_covariances(self, masks: NDArray[np.bool_]) -> Mat:
        """``P_i = spd_inverse(spd_inverse(P_pred) + J_i)`` with ``J_i`` summed as the reference."""
        return spd_inverse(self.Y0 + gain_sums(self.G, masks))

    def root_bound(self, tau: float = math.inf) -> float:
        """The bound of the root interval ``[P(req ∪ all free), P(req)]``, raised by the
        reduced relaxation or the dual bound where it applies; without an interval bound ``0``
        for a registered metric (an entry of :data:`covnet.core.metrics.METRICS` is ``>= 0``),
        ``-inf`` for a user's plain function.  ``tau``: the raising may stop once the bound
        exceeds it (valid either way); the first call's bound is kept."""
        if self.bound is None:
            return 0.0 if self.name is not None else -math.inf
        if self._root_bound is None:
            self._root_bound = self._root(tau)
        return self._root_bound

    def root_bound_whole(self) -> float:
        """:meth:`root_bound` raised to the end (``tau = inf``), computed once: the first
        call's bound may have stopped early (a dual bound stops once its own primal value shows
        it cannot reach ``tau``), and greedy's, always whole, was then the larger certificate
        on the same subset."""
        if self.bound is None:
            return self.root_bound()
        if self._root_whole is None:
            self._root_whole = self._root(math.inf)
        return max(self._root_whole, self.root_bound())

    def _root(self, tau: float = math.inf) -> float:
        Z0 = self.base[None]
        Z1 = Z0 + self.suffix[0]
        sA = self.summary(Z1)
        sB = self.summary(Z0)
        lb = self.combine(sA, sB)
        lb = self.refine(Z0, Z1, lb, sB, tau)
        return float(lb[0])


def _exact_values(f: MetricFn, D: Mat, Y0: Mat, G: Mat, masks: NDArray[np.bool_]) -> Mat:
    """``f(P_i, P_d)`` of the subsets ``masks`` ``(c, N)``, ``P_i = spd_inverse(Y0 + J_i)``
    (``Y0 = spd_inverse(P_pred)``, ``J_i`` summed as the reference), in batches whose gain
    sums' temporary stays below :data:`EXACT_ENTRIES` entries."""
    N, n = G.shape[0], G.shape[1]
    out = np.empty(masks.shape[0])
    step = max(1, EXACT_ENTRIES // (N * n * n))
    for lo in range(0, masks.shape[0], step):
        mk = masks[lo : lo + step]
        P = spd_inverse(Y0 + gain_sums(G, mk))
        v = np.asarray(f(P, D), dtype=np.float64)
        if v.shape != (mk.shape[0],):
            raise ValueError(f"metric returned shape {v.shape} for a batch of {mk.shape[0]}")
        if not np.isfinite(v).all():
            k = int(np.argmin(np.isfinite(v)))
            subset = tuple(np.flatnonzero(mk[k]).tolist())
            raise ValueError(f"metric returned a non-finite value for subset {subset}")
        out[lo : lo + mk.shape[0]] = v
    return out


def only_subset(
    P_pred: Mat,
    gains: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    constraints: Constraints,
    tie_rtol: float,
) -> SearchResult | None:
    """The exact search's result where the constraints leave one feasible subset (every
    allowed sensor required, as in ``covnet bench up --sensors``' networks), without the
    search's set-up (the branching order, the reduced form, the bounds' constants: such a
    decision took 0.57 ms at N = 64 and 1.58 ms at N = 256 with it, 0.29 and 0.38 ms without,
    CPU); ``None`` otherwise, or for a metric without an interval bound
    (:func:`~covnet.core.allocation.search.allocate_bnb` hands those to the reference).  The
    same checks and errors as :class:`_Problem`, and the same record as the search's: that
    subset, its value and ``P`` by the reference's arithmetic
    (:meth:`_Problem.exact`, :meth:`_Problem.exact_covariances`), the value as its own lower
    bound (gap 0), no node, one exact evaluation, status 0."""
    P, D, plan, f, entry = _checked(P_pred, gains, P_d, metric, constraints, tie_rtol)
    req = constraints.required
    N = plan.gains.shape[0]
    if not req or any(j not in req for j in range(N) if j not in constraints.excluded):
        return None
    if entry is None or capability(entry.interval_bound, IntervalBound) is None:
        return None
    try:
        Y0 = spd_inverse(P)
        mask = np.zeros((1, N), dtype=bool)
        mask[0, sorted(req)] = True
        value = float(_exact_values(f, D, Y0, plan.gains, mask)[0])
        P_S = spd_inverse(Y0 + gain_sums(plan.gains, mask))[0]
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    subset = tuple(sorted(req))
    return SearchResult(subset, value, P_S, value, 0.0, 0, 1, True, 0, STATUS[0])


def _subset(mask: NDArray[np.bool_]) -> tuple[int, ...]:
    return tuple(np.flatnonzero(mask).tolist())


def _gap(value: float, lower: float) -> float:
    return max(value - lower, 0.0) / max(abs(value), TINY)


def gap_from_nothing(value: ArrayLike, lower: ArrayLike, nothing: ArrayLike) -> NDArray[np.float64]:
    """The certified gap relative to the distance from doing nothing, elementwise: an upper
    bound of ``(value - f*) / (f(P⁻, P_d) - f*)``, namely ``(value - L) / (nothing - value)``
    with ``nothing = f(P⁻, P_d)`` (``L <= f* <= value``: the numerator can only shrink and the
    denominator only grow with ``f*``).  Meaningful where the optimum is near 0 and the gap
    relative to the value says nothing (abs_trace, trace_diff); 0 without a gap, ``inf`` where
    the decision does no better than doing nothing but has a gap, NaN where ``L`` is."""
    v, lo, no = (np.asarray(x, dtype=np.float64) for x in (value, lower, nothing))
    num = np.maximum(v - lo, 0.0)
    den = no - v
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(num == 0.0, 0.0, np.where(den > 0.0, num / den, np.inf))
    return np.where(np.isnan(lo), np.nan, out)
