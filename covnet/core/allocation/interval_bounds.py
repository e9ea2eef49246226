"""Lower bounds of every registered metric over a Loewner interval of covariances.

A node of a branch and bound over sensor subsets (:mod:`covnet.core.allocation.search`) has an
*included*
set ``I`` and an *undecided* set ``U``; every completion ``D`` (``I ⊆ D ⊆ I ∪ U``) satisfies,
because every gain ``J_j = H_jᵀ R_j⁻¹ H_j ⪰ 0`` and inversion is Loewner-antitone::

    A = P(I ∪ U)  ⪯  P(D)  ⪯  P(I) = B,        P(S) = (P_pred⁻¹ + Σ_{j∈S} J_j)⁻¹.

This module gives, for every built-in metric of :data:`covnet.core.metrics.METRICS` (its entry's
``interval_bound``, ``<NAME>_BOUND`` here), a valid lower bound
of ``min { f(P, P_d) : A ⪯ P ⪯ B }``, batched over many intervals (``A``, ``B`` ``(m, n, n)``).
Each bound is split into a per-endpoint **summary** (e.g. the eigenvalues of ``X - P_d``) and a
**combination** of the two endpoints' summaries, so a search that shares one endpoint between a
node and its child (the include child keeps ``A``, the exclude child keeps ``B``) computes one
summary per child; the *degenerate* interval ``[B, B]`` (the subset ``I`` itself) costs nothing
more than ``B``'s summary.

The facts used (``λ_i`` ascending eigenvalues, ``X ⪯ Y`` the Loewner order):

- **Weyl monotonicity**: ``X ⪯ Y  ⇒  λ_i(X) <= λ_i(Y)`` for every ``i``;
- **congruence**: ``X ⪯ Y  ⇒  Lᵀ X L ⪯ Lᵀ Y L`` for any ``L``;
- **entries of an interval**: for ``A ⪯ P ⪯ B`` with ``Δ = B - A``: ``A_ii <= P_ii <= B_ii`` and,
  since ``P - A`` and ``B - P`` are PSD and ``⪯ Δ`` (2 x 2 principal minors),
  ``|P_ij - A_ij| <= sqrt(Δ_ii Δ_jj)`` and ``|P_ij - B_ij| <= sqrt(Δ_ii Δ_jj)``.

**Floating point.**  ``A``, ``B`` and the completion's ``P`` are computed, not exact; a bound must
stay below the metric *as computed* on the computed ``P``.  :class:`IntervalContext` carries
``err``, an entrywise bound on ``|X_computed - X_exact|`` for every covariance involved (the
endpoints and the completion alike), and the spectral limits valid for all of them; every bound
widens its enclosures by the error they can carry (``||E||_2 <= ||E||_F <= n·err`` for an
entrywise-``err`` symmetric ``E``) and deflates by a relative rounding allowance of its own
arithmetic and of the metric's.  :func:`search_context` builds the context with the error model of
:mod:`covnet.core.allocation._fast` (``ERR_FACTOR · n² · eps · κ · λmax``, a worst-case model with
a generous constant, not a certified interval computation); the property tests check
``bound <= computed value`` on sampled completions.  kl's *leaf bound* (single subsets,
:func:`kl_leaf_bound`, for the tie rule) bounds its large trace term instead from the
reference's own arithmetic, each step a cited backward-error result relative to its own term
(Cholesky, triangular inverse, Gaussian elimination), and uses the error model only for the
small term.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation import inertia, svd_bound
from covnet.core.gaussian import Mat
from covnet.core.lapack import flapack
from covnet.core.metrics import EIG_TIE_RTOL, METRICS, capability, ordered_eigh

lapack = flapack()  # scipy.linalg.lapack's routines, without scipy.linalg's import

__all__ = [
    "ERR_FACTOR",
    "DesiredConstants",
    "IntervalBound",
    "IntervalContext",
    "interval_lower_bound",
    "search_context",
]

EPS = float(np.finfo(np.float64).eps)
TINY = float(np.finfo(np.float64).tiny)
#: the error model's constant, as :data:`covnet.core.allocation._fast.ERR_FACTOR`
ERR_FACTOR = 64.0
#: relative rounding allowance per unit of dimension, of a bound's own arithmetic and the metric's
ROUND = 64.0


class IntervalContext(NamedTuple):
    """What a bound may assume about the covariances behind its computed inputs:

    - ``|X_computed - X_exact| <= err`` entrywise, for both endpoints and for the completion's
      ``P`` the metric is computed on;
    - ``lam_min <= λ(X) <= lam_max`` for every such exact ``X``;
    - ``kappa >= lam_max / lam_min``;
    - ``scale >= max(lam_max, sum |P_d|)``, the magnitude of the metric's inputs.
    """

    err: float
    lam_min: float
    lam_max: float
    kappa: float
    scale: float


def search_context(
    P_pred: Mat, info_trace: float, P_d: Mat, n_terms: int = 0, gain_abs_max: float = 0.0
) -> IntervalContext:
    """The error model of a subset search (:mod:`covnet.core.allocation._fast`, same constant).

    Every ``P(S)`` lies between ``(P_pred⁻¹ + J_all)⁻¹`` and ``P_pred``, so
    ``λmax <= tr P_pred`` and ``λmin >= 1 / tr(P_pred⁻¹ + J_all)`` (``info_trace``, the trace of
    the largest information), ``κ = tr(P_pred) · info_trace >= cond P(S)``; the entrywise error of
    any computed ``P(S)`` (reduced form, or the reference's Cholesky inverses) is taken as
    ``ERR_FACTOR · n² · eps · κ · λmax``, plus, for information sums of up to ``n_terms`` gains
    added in another order than the reference's, ``λmax² · n · n_terms · eps · gain_abs_max``
    (``|ΔJ| <= n_terms · eps · Σ|J_j|`` entrywise moves ``P`` by at most ``λmax² ||ΔJ||_2``).
    """
    n = P_pred.shape[0]
    lam_max = float(np.trace(P_pred))
    kappa = lam_max * info_trace
    err = ERR_FACTOR * n * n * EPS * kappa * lam_max
    err += lam_max * lam_max * n * n_terms * EPS * gain_abs_max
    scale = lam_max + float(np.abs(P_d).sum())
    return IntervalContext(err, 1.0 / info_trace, lam_max, kappa, scale)


class DesiredConstants:
    """Constants of one desired covariance ``P_d`` the bounds use, computed on first use:
    ``diag``, ``trace``, :meth:`eig_desc` (eigenvalues, descending), :meth:`eigvecs`,
    :meth:`chol_inv`
    (``L⁻¹`` with ``P_d = L Lᵀ``, and ``κ_D = tr(P_d) tr(P_d⁻¹) >= cond P_d``)."""

    __slots__ = ("D", "n", "diag", "trace", "_eig", "_vec", "_chol")

    def __init__(self, P_d: Mat) -> None:
        self.D = np.array(P_d, dtype=np.float64)
        self.n = int(self.D.shape[0])
        self.diag = self.D.diagonal().copy()
        self.trace = float(self.diag.sum())
        self._eig: Mat | None = None
        self._vec: Mat | None = None
        self._chol: tuple[Mat, float] | None = None

    def eig_desc(self) -> Mat:
        if self._eig is None:
            self._eig = np.asarray(np.linalg.eigvalsh(self.D)[::-1], dtype=np.float64).copy()
        return self._eig

    def eigvecs(self) -> Mat:
        """The eigenvectors of :func:`covnet.core.metrics.ordered_eigh` (the svd metric's
        convention for ``P_d``), column ``i`` for the ``i``-th largest eigenvalue."""
        if self._vec is None:
            self._vec = np.asarray(ordered_eigh(self.D)[1], dtype=np.float64)
        return self._vec

    def chol_inv(self) -> tuple[Mat, float]:
        """``L⁻¹`` (LAPACK ``trtri`` on the triangular factor) and ``κ_D``; raises
        ``numpy.linalg.LinAlgError`` unless ``P_d`` is positive definite."""
        if self._chol is None:
            L = np.linalg.cholesky(self.D)
            L_inv, info = lapack.dtrtri(L, lower=1)  # the triangular inverse (L⁻¹ is the map)
            if info != 0:
                raise np.linalg.LinAlgError(f"P_d's Cholesky factor is singular (info {info})")
            L_inv = np.tril(np.asarray(L_inv))
            self._chol = (L_inv, self.trace * float((L_inv * L_inv).sum()))
        return self._chol


SummaryFn = Callable[[Mat, DesiredConstants], Mat]
CombineFn = Callable[[Mat, Mat, DesiredConstants, IntervalContext], NDArray[np.float64]]
#: ``above(X, dc, ctx, tau, lower)``: :attr:`IntervalBound.above`
AboveFn = Callable[[Mat, DesiredConstants, IntervalContext, float, bool], Mat]
#: ``lazy(X, dc, ctx, tau, lower, prev)``: :attr:`IntervalBound.lazy`
LazyFn = Callable[[Mat, DesiredConstants, IntervalContext, float, bool, Mat], Mat]


@dataclass(frozen=True, slots=True)
class LeafBound:
    """A sharper bound of single subsets (degenerate intervals) than ``combine(s, s)``, valid
    for every subset with the same exact information (the tie rule's twins): ``constants(Y0,
    gains, Cinv, s, P_pred, P_d)`` once per problem (``None``: not available), then
    ``bound(Z, X, constants, ctx)`` ``(m,)`` for reduced informations ``Z`` ``(m, r*r)`` and
    their reduced-form covariances ``X`` ``(m, n, n)`` (kl: :func:`kl_leaf_bound`)."""

    constants: Callable[[Mat, Mat, Mat, NDArray[np.intp], Mat, Mat], object | None]
    bound: Callable[[Mat, Mat, Any, IntervalContext], NDArray[np.float64]]


@dataclass(frozen=True, slots=True)
class IntervalBound:
    """A metric's interval bound: ``summary(X, dc)`` ``(m, q)`` of endpoints ``X`` ``(m, n, n)``,
    and ``combine(s_A, s_B, dc, ctx)`` ``(m,)``, a lower bound of the metric over ``[A, B]``.
    ``from_diagonal(d, dc)``, where the summary reads only the diagonal: the same summary from
    the diagonals ``d`` ``(m, n)`` (a search then computes only those:
    :meth:`covnet.core.allocation.search_problem._Problem.diagonals`).
    ``above(X, dc, ctx, tau, lower)``, optionally: ``summary(X, dc)`` except on rows it proves
    ``combine(..) > tau`` for *any* partner summary (``lower``: ``X`` is a lower endpoint
    ``A``, else an upper one ``B``), which get a looser summary whose combination with any
    partner is still ``> tau`` and a valid bound (at most that of ``summary``): rows whose
    bound from ``summary`` is ``> tau`` (spectral's inertia pre-test,
    :func:`_spectral_above`).  ``lazy(X, dc, ctx, tau, lower, prev)``, optionally: as
    ``above`` for a search's child whose parent's summary of the same side is ``prev``, with
    ``prev`` (valid for the nested interval) on the rows kept, except where a subset may become
    a candidate (spectral, :func:`_spectral_lazy`).  ``leaf``, optionally: a sharper bound of
    single subsets (:class:`LeafBound`; kl), which the tie rule's pruning reads."""

    summary: SummaryFn
    combine: CombineFn
    from_diagonal: SummaryFn | None = None
    above: AboveFn | None = None
    leaf: LeafBound | None = None
    lazy: LazyFn | None = None


def _f64(x: object) -> Mat:
    return np.asarray(x, dtype=np.float64)


def _deflate(v: Mat, n: int, ctx: IntervalContext, shift: float) -> Mat:
    """``v (1 - ROUND n eps) - shift - ROUND n eps · scale``, clipped at 0 (every registered
    metric is computed ``>= 0``): an absolute error ``shift`` the caller derived, plus the
    rounding of the bound and of the metric relative to the value and to the input scale."""
    rel = ROUND * n * EPS
    out = v * (1.0 - rel)
    out -= shift + rel * ctx.scale
    return np.maximum(out, 0.0)


# ---- spectral: ||P - P_d||_2 ----------------------------------------------------------------


def _eig_minus_d(X: Mat, dc: DesiredConstants) -> Mat:
    """Eigenvalues of ``X - P_d``, ascending ``(m, n)``."""
    return _f64(np.linalg.eigvalsh(X - dc.D))


def _spectral_combine(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> NDArray[np.float64]:
    """``||P - P_d||_2 >= max(λmax(A - P_d), -λmin(B - P_d), 0)`` on ``A ⪯ P ⪯ B``.

    Proof: ``||M||_2 = max(λmax(M), -λmin(M))`` for symmetric ``M``.  ``P ⪰ A`` gives
    ``P - P_d ⪰ A - P_d``, so ``λmax(P - P_d) >= λmax(A - P_d)`` (Weyl); ``P ⪯ B`` gives
    ``λmin(P - P_d) <= λmin(B - P_d)``.  Errors: each eigenvalue moves by at most ``||E||_2 <=
    n err`` with an endpoint's error, the metric by at most ``n err`` with the completion's."""
    v = np.maximum(sA[:, -1], -sB[:, 0])
    return _deflate(v, dc.n, ctx, 2.0 * dc.n * ctx.err)


#: the inertia pre-test's shift of the threshold, relative to ``|v0| + scale``
#: (:func:`_spectral_above`)
MARGIN = 2.0**-30
#: a bound on LAPACK's eigenvalue error relative to ``||M||_2`` (:func:`_spectral_above`)
EIG_REL = 2.0**-32
#: the factor on the required gap a proven row's check asks for (rounding of the check itself)
SAFETY = 2.0
#: a proven row's diagonal of ``H`` stays below this (no overflow in the Cholesky's squares)
BIG = 2.0**500


def _spectral_threshold(tau: float, dc: DesiredConstants, ctx: IntervalContext) -> float:
    """A ``v0`` with ``_deflate(v) > tau`` for every ``v >= v0`` as :func:`_spectral_combine`
    computes it (``nan`` if none is found): ``(tau + shift) / (1 - rel)`` raised ulp by ulp
    until the same floating-point operations as :func:`_deflate`'s give ``> tau`` (python
    floats are IEEE doubles like numpy's; rounding is monotone, so every ``v >= v0`` passes)."""
    n = dc.n
    rel = ROUND * n * EPS
    sub = 2.0 * n * ctx.err + rel * ctx.scale
    v0 = (tau + sub) / (1.0 - rel)
    for _ in range(64):
        if not math.isfinite(v0):
            break
        if v0 * (1.0 - rel) - sub > tau:
            return v0
        v0 = math.nextafter(v0, math.inf)
    return math.nan


def _spectral_above(
    X: Mat, dc: DesiredConstants, ctx: IntervalContext, tau: float, lower: bool
) -> Mat:
    """:func:`_eig_minus_d`, except on the rows an inertia test proves prunable, which get no
    eigenvalues but bounds of the two that :func:`_spectral_combine` reads: a lower endpoint
    ``[+inf, ..., +inf, v0]`` (``λmax(M) >= v0``), an upper one ``[-v0, -inf, ..., -inf]``
    (``λmin(M) <= -v0``); the combination is then ``_deflate(v0) > tau`` with any partner, and
    still a valid lower bound (at most today's, from the computed eigenvalues).

    A lower endpoint's bound needs ``λmax(M) > t``, an upper one's ``-λmin(M) > t`` (``M = X -
    P_d``, ``t`` the threshold of ``_deflate(v) > tau``): :func:`_spectral_combine`'s ``v =
    max(λmax(A - P_d), -λmin(B - P_d))`` is at least either.  Proof that a proven row's bound
    from :func:`_eig_minus_d` is ``> tau``: ``v0`` (:func:`_spectral_threshold`) has
    ``_deflate(v) > tau`` for every computed ``v >= v0``.  The test factors ``T I - M`` (lower)
    or ``M + T I`` (upper) with ``T = v0 + MARGIN (|v0| + scale)``; a breakdown proves
    ``λmax(M) >= T - c·h`` or ``λmin(M) <= -T + c·h`` (:mod:`covnet.core.allocation.inertia`,
    Demmel's theorem; ``c`` = ``breakdown_slack(n)``, ``h = max_i |H_ii| <= |T| + max_i
    |M_ii|``).  LAPACK's computed eigenvalues are within ``EIG_REL ||M||_2 <= EIG_REL ||M||_F``
    of the exact ones of the computed ``M`` (backward stability of the symmetric eigensolvers,
    LAPACK Users' Guide §4.7: ``p(n) eps ||M||_2`` with a modest ``p``; ``EIG_REL = 2^-32`` is
    ``2^20 eps``).  So a proven row with ``T - v0 >= c h + EIG_REL ||M||_F`` has a computed
    ``λmax >= v0`` (lower) or ``-λmin >= v0`` (upper): its bound is ``> tau`` with any partner
    summary.  Each proven row is checked so (times SAFETY, for the check's own rounding; the
    whole batch at once with ``max |M_ij|``, ``||M||_F <= n max |M_ij|``), must be finite and
    have ``h <= BIG`` (no overflow: ``|L_ij| <= sqrt(H_ii)`` while the pivots are positive);
    a row that fails, or does not break down, gets LAPACK's eigenvalues, the very bits of
    :func:`_eig_minus_d` (``eigvalsh`` factors each matrix on its own)."""
    M = X - dc.D
    m, n = M.shape[0], dc.n
    v0 = _spectral_threshold(tau, dc, ctx)
    if m == 0 or not math.isfinite(v0):
        return _f64(np.linalg.eigvalsh(M))
    rows = _spectral_proven(M, v0, ctx, lower)
    if rows.size == 0:
        return _f64(np.linalg.eigvalsh(M))
    keep = np.ones(m, dtype=bool)
    keep[rows] = False
    out = np.empty((m, n))
    if rows.size < m:
        out[keep] = np.linalg.eigvalsh(M[keep])
    _mark_proven(out, rows, v0, lower)
    return out


def _mark_proven(out: Mat, rows: NDArray[np.intp], v0: float, lower: bool) -> None:
    """The summaries of proven rows, in place: a lower endpoint's ``[+inf, ..., +inf, v0]``
    (``λmax >= v0``, ``λmin <= +inf``), an upper one's ``[-v0, -inf, ..., -inf]`` (``λmin <=
    -v0``, ``λmax >= -inf``): the bound ``deflate(v0) > tau`` with any partner."""
    if lower:
        out[rows, :-1] = math.inf
        out[rows, -1] = v0
    else:
        out[rows, 0] = -v0
        out[rows, 1:] = -math.inf


def _spectral_lazy(
    X: Mat, dc: DesiredConstants, ctx: IntervalContext, tau: float, lower: bool, prev: Mat
) -> Mat:
    """Summaries of a search's children's new endpoints without eigenvalues wherever the search
    does not need them (exact mode; :attr:`IntervalBound.lazy`): ``prev`` ``(m, n)`` is the
    parent's summary of the same side (the exclude child's new ``A`` replaces the parent's
    ``A``, the include child's new ``B`` the parent's ``B``).

    - rows :func:`_spectral_proven` proves: :func:`_spectral_above`'s summaries (the bound
      ``> tau`` with any partner, at most the eigenvalue one);
    - a lower endpoint's other rows: ``prev``, no eigenvalues;
    - an upper endpoint's other rows (the include child's ``B``, whose ``combine(s_B, s_B)`` is
      the subset ``I``'s candidate estimate, read at both extremes): a second inertia test
      proves ``λmax(B - P_d) >= v0`` (its estimate ``> tau``: not a candidate) on most; those
      get ``prev`` with ``v0`` as the ``λmax`` entry, and only the rest (the subsets that may be
      recorded) get ``eigvalsh``, the very bits of :func:`_eig_minus_d`, so the recorded
      candidates and their estimates are those of :func:`_spectral_above`'s summaries.

    Proof that every summary is valid: the child's completions are some of the parent's, and
    its new endpoint is nested in the parent's interval (``A_parent ⪯ A_child``, ``B_child ⪯
    B_parent``), so with ``prev`` in place of the new endpoint's summary
    :func:`_spectral_combine` bounds the metric over the larger interval ``[A_parent, B]``
    (resp. ``[A, B_parent]``, and ``[B_child, B_parent]`` for the estimate, whose completions
    include ``B_child`` itself), with the same error allowance (every covariance involved is
    within ``err`` of its exact value).  ``λmax(B - P_d) >= v0`` as LAPACK would compute it is
    :func:`_spectral_proven`'s proof: the estimate with ``v0`` is at most the one with
    ``eigvalsh``'s value, and ``> tau``.  The bound of a kept child is then at most the
    eigenvalue one (only the search's node counts may change: a node whose bound rises above
    a falling ``tau`` is pruned later, and best-first keys and sorts see smaller bounds)."""
    M = X - dc.D
    m = M.shape[0]
    v0 = _spectral_threshold(tau, dc, ctx)
    if m == 0 or not math.isfinite(v0):
        return _f64(np.linalg.eigvalsh(M))
    rows = _spectral_proven(M, v0, ctx, lower)
    out = np.array(prev, dtype=np.float64)
    _mark_proven(out, rows, v0, lower)
    if lower:
        return out
    rest = np.ones(m, dtype=bool)
    rest[rows] = False
    rest_rows = np.flatnonzero(rest)
    if rest_rows.size:
        Mr = M[rest_rows]
        top = rest_rows[_spectral_proven(Mr, v0, ctx, True)]
        out[top, -1] = v0  # λmax >= v0: the estimate > tau; λmin <= prev's
        rest[top] = False
        if rest.any():
            out[rest] = np.linalg.eigvalsh(M[rest])
    return out


def _spectral_proven(M: Mat, v0: float, ctx: IntervalContext, lower: bool) -> NDArray[np.intp]:
    """The rows of ``M = X - P_d`` whose computed ``λmax`` (``lower``) or ``-λmin`` is proven
    ``>= v0`` (as LAPACK's ``eigvalsh`` would compute it): the inertia test and its check of
    :func:`_spectral_above`'s docstring (``T = v0 + MARGIN (|v0| + scale)``, a breakdown with
    ``T - v0 >= SAFETY (c h + EIG_REL ||M||_F)``)."""
    n = M.shape[1]
    T = v0 + MARGIN * (abs(v0) + ctx.scale)
    broken = inertia.lam_max_above(M, T) if lower else inertia.lam_min_below(M, T)
    rows = np.flatnonzero(broken)
    if rows.size:
        c = inertia.breakdown_slack(n)
        with np.errstate(all="ignore"):
            # the whole batch at once (||M||_F <= n max |M_ij|), else row by row; a NaN or
            # infinite row fails (its ``need`` is NaN or inf), and so does one near overflow
            a = float(np.abs(M).max())
            h1 = abs(T) + a
            if not (h1 <= BIG and (T - v0) >= SAFETY * (c * h1 + EIG_REL * n * a)):
                Mr = M[rows]
                h = abs(T) + np.abs(np.diagonal(Mr, axis1=1, axis2=2)).max(axis=1)
                fro = np.sqrt((Mr * Mr).sum(axis=(1, 2)))
                need = np.where(h <= BIG, c * h + EIG_REL * fro, np.nan)
                rows = rows[(T - v0) >= SAFETY * need]
    return rows


# ---- abs_trace and trace_diff: the diagonal -------------------------------------------------


def _diag_minus_d(X: Mat, dc: DesiredConstants) -> Mat:
    """``X_ii - P_d,ii`` ``(m, n)``."""
    return np.diagonal(X, axis1=-2, axis2=-1) - dc.diag


def _diag_minus_d_from(d: Mat, dc: DesiredConstants) -> Mat:
    """:func:`_diag_minus_d` from the diagonals ``d`` ``(m, n)``."""
    return d - dc.diag


def _abs_trace_combine(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> NDArray[np.float64]:
    """``sum_i |P_ii - d_ii| >= sum_i dist(d_ii, [A_ii, B_ii])`` on ``A ⪯ P ⪯ B``, as
    ``A_ii <= P_ii <= B_ii`` (diagonal of an interval).  ``dist`` is written
    ``max(A_ii - d_ii, d_ii - B_ii, 0)``, valid even if rounding inverts an interval.  Errors:
    ``n err`` from each endpoint's diagonal, ``n err`` from the completion's."""
    v = _row_sums(np.maximum(np.maximum(sA, -sB), 0.0))
    return _deflate(v, dc.n, ctx, 2.0 * dc.n * ctx.err)


def _row_sums(c: Mat) -> Mat:
    """``c.sum(axis=1)``, the same bits: below 8 columns numpy adds a row left to right (no
    pairwise blocks), which the column additions here repeat at a quarter of the cost for
    ``(m, 4)`` (a reduction over a short last axis is slow)."""
    k = c.shape[1]
    if k >= 8 or k == 0:
        return _f64(c.sum(axis=1))
    v = c[:, 0].copy()
    for i in range(1, k):
        v += c[:, i]
    return v


def _trace_minus_d(X: Mat, dc: DesiredConstants) -> Mat:
    """``tr X - tr P_d`` ``(m, 1)``."""
    return _f64((np.trace(X, axis1=-2, axis2=-1) - dc.trace)[:, None])


def _trace_minus_d_from(d: Mat, dc: DesiredConstants) -> Mat:
    """:func:`_trace_minus_d` from the diagonals ``d`` ``(m, n)``."""
    return _f64((d.sum(axis=1) - dc.trace)[:, None])


def _trace_diff_combine(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> NDArray[np.float64]:
    """``|tr P - tr P_d| >= dist(tr P_d, [tr A, tr B])``: the trace is Loewner-monotone
    (``tr A <= tr P <= tr B``).  Errors as :func:`_abs_trace_combine`."""
    v = np.maximum(np.maximum(sA[:, 0], -sB[:, 0]), 0.0)
    return _deflate(v, dc.n, ctx, 2.0 * dc.n * ctx.err)


# ---- frobenius, one_norm, inf_norm: eigenvalue intervals and entry intervals ----------------


def _eig_and_entries(X: Mat, dc: DesiredConstants) -> Mat:
    """``[eigenvalues of X - P_d (ascending), entries of X (row-major)]`` ``(m, n + n²)``."""
    m, n = X.shape[0], dc.n
    out = np.empty((m, n + n * n))
    out[:, :n] = np.linalg.eigvalsh(X - dc.D)
    out[:, n:] = X.reshape(m, n * n)
    return out


def _entry_distances(sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext) -> Mat:
    """``|P_ij - (P_d)_ij|`` lower bounds ``(m, n, n)`` for the computed completion ``P``.

    Exact ``P`` in ``[A, B]``: ``P_ii ∈ [A_ii, B_ii]`` and ``P_ij ∈ [max(A_ij, B_ij) - ρ_ij,
    min(A_ij, B_ij) + ρ_ij]``, ``ρ_ij = sqrt(Δ_ii Δ_jj)`` (module docstring; on the diagonal
    ``ρ_ii = Δ_ii`` gives the same interval).  With computed endpoints the exact ``Δ_ii`` is at
    most the computed one ``+ 2 err``, each centre is off by ``err``, and the computed completion's
    entry by another ``err``: the intervals are widened by ``2 err`` after inflating ``Δ``."""
    n, e = dc.n, ctx.err
    A = sA[:, n:].reshape(-1, n, n)
    B = sB[:, n:].reshape(-1, n, n)
    dlt = np.maximum(np.diagonal(B, axis1=1, axis2=2) - np.diagonal(A, axis1=1, axis2=2), 0.0)
    dlt += 2.0 * e
    rho = np.sqrt(dlt[:, :, None] * dlt[:, None, :])
    lo = np.maximum(A, B) - rho
    hi = np.minimum(A, B) + rho
    d = np.arange(n)
    lo[:, d, d] = np.diagonal(A, axis1=1, axis2=2)
    hi[:, d, d] = np.diagonal(B, axis1=1, axis2=2)
    lo -= 2.0 * e
    hi += 2.0 * e
    return _f64(np.maximum(np.maximum(lo - dc.D, dc.D - hi), 0.0))


def _eig_distances(sA: Mat, sB: Mat, n: int) -> Mat:
    """``|λ_i(P - P_d)|`` lower bounds ``(m, n)``: ``λ_i(A - P_d) <= λ_i(P - P_d) <= λ_i(B -
    P_d)`` (Weyl), so ``|λ_i| >= max(λ_i(A - P_d), -λ_i(B - P_d), 0)``."""
    return np.maximum(np.maximum(sA[:, :n], -sB[:, :n]), 0.0)


def _frobenius_combine(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> NDArray[np.float64]:
    """``||P - P_d||_F`` is at least

    - ``sqrt(sum_i dist_i²)`` with ``dist_i`` the eigenvalue distances (``||M||_F² = sum_i
      λ_i(M)²``, :func:`_eig_distances`); errors: the sorted eigenvalue vector of an endpoint moves
      by at most ``||E||_F <= n err`` in 2-norm (Mirsky), twice, and the metric by ``n err`` with
      the completion's error: ``3 n err``;
    - ``sqrt(sum_ij dist_ij²)`` with the entry distances of :func:`_entry_distances` (their
      errors already included)."""
    n = dc.n
    ev = _eig_distances(sA, sB, n)
    v_eig = _deflate(np.sqrt((ev * ev).sum(axis=1)), n, ctx, 3.0 * n * ctx.err)
    en = _entry_distances(sA, sB, dc, ctx)
    v_ent = _deflate(np.sqrt((en * en).sum(axis=(1, 2))), n, ctx, 0.0)
    return np.maximum(v_eig, v_ent)


def _induced_combine(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> NDArray[np.float64]:
    """``||P - P_d||_1`` (= ``||P - P_d||_inf`` for symmetric matrices) is at least

    - ``max_j sum_i dist_ij`` with the entry distances of :func:`_entry_distances`;
    - the spectral bound (``||M||_2 <= sqrt(||M||_1 ||M||_inf) = ||M||_1`` for symmetric ``M``),
      errors as :func:`_spectral_combine`."""
    n = dc.n
    v_sp = _deflate(np.maximum(sA[:, n - 1], -sB[:, 0]), n, ctx, 2.0 * n * ctx.err)
    en = _entry_distances(sA, sB, dc, ctx)
    v_ent = _deflate(en.sum(axis=1).max(axis=1), n, ctx, 0.0)
    return np.maximum(v_sp, v_ent)


# ---- logdet and kl: generalized eigenvalues of (P, P_d) -------------------------------------


def _gen_eig(X: Mat, dc: DesiredConstants) -> Mat:
    """Eigenvalues of ``L⁻¹ X L⁻ᵀ`` (``P_d = L Lᵀ``), ascending ``(m, n)``: the generalized
    eigenvalues ``x_i`` of the pencil ``(X, P_d)``."""
    L_inv, _ = dc.chol_inv()
    return _f64(np.linalg.eigvalsh(L_inv @ X @ L_inv.T))


def _gen_eig_clip(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> tuple[Mat, float] | None:
    """The point of each widened interval ``[x_i(A), x_i(B)]`` closest to 1, ``(m, n)``, and the
    rounding allowance of the metric's Cholesky log-determinants / solves relative to the
    condition numbers; ``None`` when the error model is too coarse to say anything.

    ``A ⪯ P ⪯ B`` gives ``L⁻¹AL⁻ᵀ ⪯ L⁻¹PL⁻ᵀ ⪯ L⁻¹BL⁻ᵀ`` (congruence), so ``x_i(A) <= x_i(P) <=
    x_i(B)`` (Weyl).  Errors: ``P_exact ⪰ lam_min I`` and ``||E||_2 <= n err`` give
    ``(1 - ρ) P_exact ⪯ P_computed ⪯ (1 + ρ) P_exact``, ``ρ = n err / lam_min``, for each endpoint
    and for the completion (so ``x_i`` moves by a relative ``ρ`` each); computing ``L⁻¹ X L⁻ᵀ``
    and its eigenvalues adds a relative ``ROUND n² eps κ_D`` and an absolute ``ROUND n eps
    max x``."""
    n = dc.n
    _, kappa_D = dc.chol_inv()
    rho = n * ctx.err / ctx.lam_min
    w = 2.0 * rho + ROUND * n * n * EPS * (kappa_D + 1.0)
    if not w < 0.5:
        return None
    top = np.abs(sB).max(axis=1, keepdims=True) * (ROUND * n * EPS)
    lo = sA * (1.0 - w) - top
    hi = sB * (1.0 + w) + top
    x = np.minimum(np.maximum(1.0, lo), hi)
    # the metric's rounding: Cholesky backward error (relative c n² eps per factor, times the
    # condition number in the eigenvalues), n of them per log-determinant or solve
    kap = ctx.kappa + kappa_D
    return x, ROUND * n * n * n * EPS * kap


def _logdet_combine(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> NDArray[np.float64]:
    """``log det((P + P_d)/2) - ½ log det P - ½ log det P_d = sum_i φ(x_i)``, ``x_i`` the
    generalized eigenvalues of ``(P, P_d)``, ``φ(x) = log((1 + x)/2) - ½ log x``:
    ``φ'(x) = (x - 1) / (2x(1 + x))``, so ``φ`` decreases on ``(0, 1]``, increases on ``[1, ∞)``,
    ``φ(1) = 0``.  Hence ``f >= sum_i φ(clip(1, [x_i(A), x_i(B)]))``
    (:func:`_gen_eig_clip`).  Deflated by the rounding of the metric's three Cholesky
    log-determinants, relative to ``n`` plus their magnitudes."""
    got = _gen_eig_clip(sA, sB, dc, ctx)
    m = sA.shape[0]
    if got is None:
        return np.zeros(m)
    x, rel = got
    v = (np.log1p(x) - math.log(2.0) - 0.5 * np.log(x)).sum(axis=1)
    mag = dc.n * (1.0 + abs(math.log(ctx.lam_max)) + abs(math.log(ctx.lam_min)))
    mag += dc.n * (1.0 + abs(math.log(max(dc.eig_desc()[0], TINY))))
    mag += dc.n * abs(math.log(max(dc.eig_desc()[-1], TINY)))
    return _deflate(v, dc.n, ctx, rel * mag)


def _kl_combine(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> NDArray[np.float64]:
    """``¼[tr(P_d⁻¹P) + tr(P⁻¹P_d) - 2n] = ¼ sum_i ψ(x_i)``, ``ψ(x) = x + 1/x - 2``, which
    decreases on ``(0, 1]`` and increases on ``[1, ∞)`` with ``ψ(1) = 0``; hence ``f >= ¼ sum_i
    ψ(clip(1, [x_i(A), x_i(B)]))`` (:func:`_gen_eig_clip`).  Deflated by the rounding of the
    metric's two traces, relative to their magnitude ``tr(P_d⁻¹) λmax + tr(P_d) / λmin``."""
    got = _gen_eig_clip(sA, sB, dc, ctx)
    m = sA.shape[0]
    if got is None:
        return np.zeros(m)
    x, rel = got
    v = 0.25 * (x + 1.0 / x - 2.0).sum(axis=1)
    _, kappa_D = dc.chol_inv()
    tr_inv = kappa_D / dc.trace
    mag = tr_inv * ctx.lam_max + dc.trace / ctx.lam_min + 2.0 * dc.n
    return _deflate(v, dc.n, ctx, rel * mag)


# ---- kl's leaf bound: a degenerate interval, sharp (the tie rule's certificates) ------------

#: the unit roundoff (IEEE double, round to nearest)
UNIT = EPS / 2.0


def _gamma(k: float) -> float:
    """Higham's ``γ_k = k u / (1 - k u)`` (``inf`` once ``k u >= 1``)."""
    ku = k * UNIT
    return ku / (1.0 - ku) if ku < 1.0 else math.inf


def _inverse_factors(kappa: float, n: int) -> tuple[float, float] | None:
    """``(a, b)`` with ``a A⁻¹ ⪯ spd_inverse(A) ⪯ b A⁻¹`` (Loewner) for every SPD ``n x n``
    float ``A`` with ``cond A <= kappa``, the inverse computed as :func:`covnet.core.allocation.\
_fast.spd_inverse` does (LAPACK ``potrf``, ``potri`` = ``trtri`` then ``lauum``, the lower
    triangle mirrored); ``None`` when the factors are not below ``1/2`` away from 1.

    Proof (``γ_k`` of :func:`_gamma`, ``||·||`` the 2-norm, ``||E||_2 <= ||E||_F``):

    1. ``potrf``: ``L̂L̂ᵀ = A + E1``, ``|E1| <= γ_{n+1} |L̂||L̂ᵀ|`` (Higham, *Accuracy and
       Stability*, Thm 10.3), so ``||E1||_F <= γ_{n+1} ||L̂||_F² = γ_{n+1} tr(A + E1) <=
       γ_{n+1} (n λmax(A) + n ||E1||)``: ``||E1|| <= γ_{n+1} n λmax / (1 - n γ_{n+1})`` and
       ``(1 - ε1) A ⪯ L̂L̂ᵀ ⪯ (1 + ε1) A``, ``ε1 = γ_{n+1} n κ / (1 - n γ_{n+1})``.
    2. ``trtri`` (``xTRTI2``, Du Croz and Higham's method 2: column ``j`` of ``X`` is
       ``-x_jj X₂₂ l₂₁`` from the already computed ``X₂₂``): ``X̂L̂ = I + R``, ``|R| <= γ_{n+1}
       |X̂||L̂|`` (column ``j``: ``x̂_ij l_jj + (X̂₂₂ l₂₁)_i = -θ₂ s_i - e_i (1 + θ₂)``, the
       product's error ``|e_i| <= γ_{n-1} (|X̂₂₂||l₂₁|)_i``; the diagonal ``fl(1/l) l - 1``).
       ``||R|| <= γ_{n+1} ||X̂||_F ||L̂||_F`` with ``||L̂||_F² <= n λmax(L̂L̂ᵀ)``, ``||X̂||_F² <=
       n (1 + r)² / λmin(L̂L̂ᵀ)`` (``X̂ = (I + R) L̂⁻¹``): ``r <= c (1 + r)``, ``c = γ_{n+1} n
       sqrt(κ (1 + ε1)/(1 - ε1))``, so ``r = ||R|| <= c / (1 - c)``.  Then ``M = X̂ᵀX̂ = L̂⁻ᵀ
       (I + R)ᵀ(I + R) L̂⁻¹`` lies in ``[(1 - r)², (1 + r)²] (L̂L̂ᵀ)⁻¹`` (congruence: the
       singular values of ``I + R`` are within ``r`` of 1).
    3. ``lauum``: every entry of ``M``'s lower triangle is an inner product of at most ``n``
       terms, so the mirrored result is ``M + E3``, ``|E3| <= γ_n |X̂|ᵀ|X̂|``, ``||E3|| <= γ_n
       ||X̂||_F² = γ_n tr M``: relative ``ε3 = γ_n n κ(M)``, ``κ(M) <= ((1 + r)/(1 - r))² κ (1 +
       ε1)/(1 - ε1)``.

    Hence ``a = (1 - r)² (1 - ε3) / (1 + ε1)``, ``b = (1 + r)² (1 + ε3) / (1 - ε1)``.  (Every
    step holds whatever the order of the inner products and with fused multiply-adds.)"""
    g1 = _gamma(n + 1)
    if not n * g1 < 0.5:
        return None
    e1 = g1 * n * kappa / (1.0 - n * g1)
    if not e1 < 0.5:
        return None
    c = g1 * n * math.sqrt(kappa * (1.0 + e1) / (1.0 - e1))
    if not c < 0.5:
        return None
    r = c / (1.0 - c)
    k_m = ((1.0 + r) / (1.0 - r)) ** 2 * kappa * (1.0 + e1) / (1.0 - e1)
    e3 = _gamma(n) * n * k_m
    if not e3 < 0.5:
        return None
    return (1.0 - r) ** 2 * (1.0 - e3) / (1.0 + e1), (1.0 + r) ** 2 * (1.0 + e3) / (1.0 - e1)


def _lam_min_below(X: Mat) -> float:
    """A lower bound of ``λmin(X)`` of a symmetric float ``X``, the larger of two:

    - LAPACK's eigenvalue less ``EIG_REL ||X||_F`` (backward stability, as
      :func:`_spectral_above`); useless when ``λmin`` is below ``EIG_REL`` of ``||X||``;
    - from the Cholesky factor and its computed inverse (SPD ``X``): ``L̂L̂ᵀ = X + E1``,
      ``||E1||_2 <= γ_{n+1} tr X / (1 - n γ_{n+1})`` (:func:`_inverse_factors`, step 1), and
      ``X̂L̂ = I + R`` with ``||R||_F <= r = γ_{n+1} ||X̂||_F ||L̂||_F`` (step 2), so ``L̂⁻¹ =
      (I + R)⁻¹ X̂``, ``||L̂⁻¹||_2 <= ||X̂||_F / (1 - r)`` and ``λmin(X) >= (1 - r)² /
      ||X̂||_F² - ||E1||_2``: relative to ``λmin`` itself (within ``n`` of it), not to
      ``||X||``."""
    n = int(X.shape[0])
    lo = float(np.linalg.eigvalsh(X)[0]) - EIG_REL * float(np.sqrt((X * X).sum()))
    c, info = lapack.dpotrf(X, lower=1)
    if info != 0:
        return lo
    L = np.tril(np.asarray(c))
    Xi, info = lapack.dtrtri(L, lower=1)
    if info != 0:
        return lo
    Xi = np.tril(np.asarray(Xi))
    g1 = _gamma(n + 1)
    fx = float(np.sqrt((Xi * Xi).sum())) * (1.0 + n * n * UNIT)
    fl = float(np.sqrt((L * L).sum())) * (1.0 + n * n * UNIT)
    r = g1 * fx * fl
    if not (r < 0.5 and n * g1 < 0.5 and fx > 0.0):
        return lo
    e1 = g1 * float(np.trace(X)) * (1.0 + n * UNIT) / (1.0 - n * g1)
    chol = ((1.0 - r) ** 2 / (fx * fx)) * (1.0 - 4.0 * UNIT) - e1
    return max(lo, chol)


class KlLeaf(NamedTuple):
    """The constants of :func:`kl_leaf_bound` for one problem (:func:`kl_leaf_constants`)."""

    c_ab: float  # tr(Ŷ0 P_d) - <C⁻¹, P_d[s, s]>, computed
    c_err: float  # its error, plus the reduced sums' (Ẑ against the exact Z), in the trace
    D_ss: Mat  # P_d[s, s] (r*r,)
    D_abs: Mat  # |P_d[s, s]| (r*r,)
    ab_scale: float  # t_ab >= ab_scale · tr(Ŷ P_d) - ab_sub
    ab_sub: float
    y_sub: float  # <Δ_Y, |P_d|>: tr(Ŷ P_d) >= tr(Y* P_d) - y_sub
    D_inv: Mat  # the computed P_d⁻¹ (n*n,)
    D_inv_abs_sum: float
    ba_scale: float  # t_ba >= ba_scale · (<P_d⁻¹, B̂> - errors)


def kl_leaf_constants(
    Y0: Mat,
    gains: Mat,
    Cinv: Mat,
    s: NDArray[np.intp],
    P_pred: Mat,
    P_d: Mat,
) -> KlLeaf | None:
    """:func:`kl_leaf_bound`'s constants: ``Y0`` the reference's ``spd_inverse(P_pred)`` (its
    bits), ``gains`` ``(N, n, n)`` every gain a subset may hold, ``Cinv`` ``(r, r)`` and ``s``
    the reduced form's (:mod:`covnet.core.allocation.search_problem`); ``None`` where the
    rounding factors are not small (then no leaf bound: the interval bound alone)."""
    n = int(P_d.shape[0])
    N = int(gains.shape[0])
    r = int(s.size)
    if r == 0 or N == 0:
        return None
    D = np.asarray(P_d, dtype=np.float64)
    try:
        neg_g = np.maximum(-np.linalg.eigvalsh(gains)[:, 0], 0.0)
    except np.linalg.LinAlgError:
        return None
    fro_g = np.sqrt((gains * gains).sum(axis=(1, 2)))
    nu = float((neg_g + EIG_REL * fro_g).sum()) * (1.0 + 4.0 * N * UNIT)  # J ⪰ -ν I
    abs_J = np.abs(gains).sum(axis=0) * (1.0 + _gamma(N))
    # Δ_Y: the reference's Ŷ = fl(Y0 + fl(Σ J_j)) against Y* = Y0 + Σ J_j (exact), entrywise
    delta_Y = _gamma(N + 1) * (np.abs(Y0) + abs_J) * (1.0 + 4.0 * UNIT)
    dY = float(np.sqrt((delta_Y * delta_Y).sum())) * (1.0 + 4.0 * UNIT)
    y_max = (float(np.sqrt((Y0 * Y0).sum())) + float(fro_g.sum())) * (1.0 + 4.0 * N * UNIT) + dY
    y_min = (_lam_min_below(Y0) - nu - dY) * (1.0 - 4.0 * UNIT)
    lam_min_D = _lam_min_below(D) * (1.0 - 4.0 * UNIT)
    lam_min_P = _lam_min_below(P_pred) * (1.0 - 4.0 * UNIT)
    if not (y_min > 0.0 and lam_min_D > 0.0 and lam_min_P > 0.0):
        return None
    k_Y = y_max / y_min
    got = _inverse_factors(k_Y, n)
    if got is None:
        return None
    a, b = got
    k_P = k_Y * b / a
    g1 = _gamma(n + 1)
    e4 = g1 * n * k_P / (1.0 - n * g1)
    # GEPP (numpy's solve): (A + Δ) x̂ = b, ||Δ||_2 <= n γ_{3n} (1 + 2(n² - n) ρ_n) ||A||_2
    ge = n * _gamma(3 * n) * (1.0 + 2.0 * (n * n - n) * 2.0**n)
    if not e4 < 0.5:
        return None
    f_A = ge * math.sqrt(k_P * (1.0 + e4) / (1.0 - e4))
    tr_D = float(np.trace(D)) * (1.0 + n * UNIT)
    e_D = g1 * tr_D / (1.0 - n * g1)  # ||E_D||_F of P_d's Cholesky factor
    fro_D = float(np.sqrt((D * D).sum())) * (1.0 + 4.0 * UNIT)
    eps_D = e_D / lam_min_D
    k_D = fro_D / lam_min_D
    if not (f_A < 0.5 and eps_D < 0.5):
        return None
    f_B = ge * math.sqrt(k_D * (1.0 + eps_D) / (1.0 - eps_D))
    g_sum = 1.0 - _gamma(n * n + 1)
    ab_scale = g_sum / (1.0 + f_A) ** 2 / ((1.0 + e4) * b)
    ab_sub = g_sum / (1.0 + f_A) ** 2 * math.sqrt(n) * y_max * e_D / ((1.0 - e4) * a)
    # the reduced information: Ẑ against Z = C⁻¹ + Σ S_j (any summation order)
    S_abs = np.abs(gains[:, s][:, :, s]).sum(axis=0) * (1.0 + _gamma(N))
    delta_Z = _gamma(2 * N + 2) * (np.abs(Cinv) + S_abs) * (1.0 + 4.0 * UNIT)
    D_ss = np.ascontiguousarray(D[np.ix_(s, s)]).reshape(r * r)
    D_abs = np.abs(D_ss)
    c_ab = float((Y0 * D).sum()) - float((Cinv.reshape(r * r) * D_ss).sum())
    c_err = _gamma(2 * n * n + 2) * (
        float((np.abs(Y0) * np.abs(D)).sum()) + float((np.abs(Cinv).reshape(r * r) * D_abs).sum())
    )
    c_err += float((delta_Z.reshape(r * r) * D_abs).sum())
    y_sub = float((delta_Y * np.abs(D)).sum()) * (1.0 + _gamma(n * n))
    # t_ba: P_d⁻¹ computed as spd_inverse, and Y0 against P_pred⁻¹ (the err model's exact P)
    got_D = _inverse_factors(k_D, n)
    got_0 = _inverse_factors(float(np.sqrt((P_pred * P_pred).sum())) / lam_min_P, n)
    if got_D is None or got_0 is None:
        return None
    c_d, info = lapack.dpotrf(D, lower=1)
    if info != 0:
        return None
    D_inv, info = lapack.dpotri(c_d, lower=1)
    if info != 0:
        return None
    D_inv = np.tril(np.asarray(D_inv))
    D_inv = D_inv + np.tril(D_inv, -1).T
    lam_P = float(np.trace(P_pred)) * (1.0 + n * UNIT)  # >= λmax(P_pred)
    if not nu * lam_P < 0.5:
        return None
    b0 = (got_0[1] - nu * lam_P) / (1.0 - nu * lam_P)
    e_Y = dY / y_min
    ba_scale = g_sum / (1.0 + f_B) ** 2 * (1.0 - e4) * a / (1.0 + eps_D)
    ba_scale /= (1.0 + e_Y) * b0 * got_D[1]
    return KlLeaf(
        c_ab,
        c_err,
        D_ss,
        D_abs,
        ab_scale,
        ab_sub,
        y_sub,
        D_inv.reshape(n * n),
        float(np.abs(D_inv).sum()),
        ba_scale,
    )


def kl_leaf_bound(Z: Mat, X: Mat, lc: KlLeaf, ctx: IntervalContext) -> NDArray[np.float64]:
    """A lower bound of the kl metric *as the reference computes it* on every subset whose
    reduced information is ``Z`` ``(m, r*r)`` (computed: any order of the sums), ``X`` ``(m, n,
    n)`` its reduced-form covariance (:meth:`~covnet.core.allocation.search_problem._Problem.\
covariances`), within ``ROUND n eps`` of the value plus the few terms below: far sharper than
    the degenerate interval bound ``[X, X]`` of :func:`_kl_combine` (whose rounding allowance,
    ``rel · mag`` and the eigenvalues' widening, is relative to ``tr(P_d) / λmin(P)``), so the
    tie rule's check (:mod:`covnet.core.allocation.tie_rule`) can certify ties of ``tie_rtol``.

    The reference computes ``P̂ = spd_inverse(Ŷ)``, ``Ŷ = fl(Y0 + fl(Σ_j J_j))``, then
    ``kl = ¼ ((t_ba + t_ab) - 2n)`` with ``L_A = chol(P̂)``, ``L_B = chol(P_d)``, ``t_ab =
    ||solve(L_A, L_B)||_F²`` (``≈ tr(P̂⁻¹ P_d)``) and ``t_ba = ||solve(L_B, L_A)||_F²``
    (``≈ tr(P_d⁻¹ P̂)``).  Let ``Y* = Y0 + Σ_j J_j`` exactly (``Y0``'s bits), the same for
    every subset with the same multiset of gains (the tie rule's twins).

    **t_ab**, the large term (the velocity term of the tie problems), bounded in the
    information form, where it is linear: ``tr(Y* P_d) = tr(Y0 P_d) + <Z - C⁻¹, P_d[s, s]>``
    (every gain vanishes outside ``s x s``).  The errors, each relative to its own term:

    - ``|Ŷ - Y*| <= Δ_Y = γ_{N+1} (|Y0| + Σ|J_j|)`` (recursive sums), so ``tr(Ŷ P_d) >=
      tr(Y* P_d) - <Δ_Y, |P_d|>``, and ``λ(Ŷ) ∈ [y_min, y_max]``: ``y_max = ||Y0||_F + Σ
      ||J_j||_F + ||Δ_Y||_F``, ``y_min = λmin(Y0) - ν - ||Δ_Y||_F`` (``J_j ⪰ -ν_j I``, Weyl);
    - ``a Ŷ⁻¹ ⪯ P̂ ⪯ b Ŷ⁻¹`` (:func:`_inverse_factors` with ``κ_Y = y_max / y_min``);
    - ``L_A L_Aᵀ = P̂ + E4``, ``(1 - ε4) P̂ ⪯ P̂ + E4 ⪯ (1 + ε4) P̂``, ``ε4 = γ_{n+1} n κ(P̂) /
      (1 - n γ_{n+1})``, ``κ(P̂) <= κ_Y b / a`` (Cholesky, as step 1 there);
    - ``L̂_B L̂_Bᵀ = P_d + E_D``, ``||E_D||_F <= γ_{n+1} tr(P_d) / (1 - n γ_{n+1})``;
    - each column of ``solve(L_A, L_B)`` is ``(L_A + Δ_j)⁻¹ l_j`` with ``||Δ_j|| <= n γ_{3n}
      (1 + 2(n² - n) 2^n) ||L_A||`` (Gaussian elimination with partial pivoting, Higham Thm
      9.4 and Lemma 9.6, growth ``<= 2^{n-1}``, doubled for the computed one; ``||·||_∞ <=
      sqrt n ||·||_2`` twice), so its norm is at least ``||L_A⁻¹ l_j|| / (1 + f)``, ``f = n
      γ_{3n} (1 + 2(n² - n) 2^n) κ(L_A)``, ``κ(L_A)² <= κ(P̂) (1 + ε4)/(1 - ε4)``;
    - ``Σ_j ||L_A⁻¹ l_j||² = tr((P̂ + E4)⁻¹ (P_d + E_D)) >= tr(Ŷ P_d) / ((1 + ε4) b) - sqrt n
      y_max ||E_D||_F / ((1 - ε4) a)`` (``(P̂ + E4)⁻¹ ⪰ Ŷ / ((1 + ε4) b)``; ``|tr(A E)| <=
      ||A||_2 sqrt n ||E||_F``);
    - the sum of the ``n²`` squares: a relative ``γ_{n²+1}``.

    **t_ba**, the small term (``tr(P_d⁻¹ P)``, about the position term), through the error
    model's ``P(S)`` (:class:`IntervalContext`: ``|X - P(S)| <= err`` entrywise): ``t_ba >=
    (1 - γ_{n²+1}) / (1 + f_B)² · tr((P_d + E_D)⁻¹ (P̂ + E4))``, ``f_B`` as ``f`` with
    ``κ(P_d + E_D)``; ``(P_d + E_D)⁻¹ ⪰ P_d⁻¹ / (1 + ε_D)`` (``ε_D = ||E_D|| / λmin(P_d)``),
    ``P̂ + E4 ⪰ (1 - ε4) a Ŷ⁻¹``, ``Ŷ⁻¹ ⪰ Y*⁻¹ / (1 + ||Δ_Y|| / y_min)``, ``Y*⁻¹ ⪰ P(S) / b0'``
    (``Y0 ⪯ b0 P_pred⁻¹``, :func:`_inverse_factors` on ``P_pred``; ``b0' = (b0 - ν λ) / (1 -
    ν λ)``, ``λ = tr P_pred``, for gains ``⪰ -ν I``), ``P_d⁻¹ ⪰ P̂_d⁻¹ / b_D`` (the computed
    inverse), and ``tr(P̂_d⁻¹ P(S)) >= <P̂_d⁻¹, X> - err Σ|P̂_d⁻¹|`` (and ``>= 0``).

    **The value.**  ``V = max(¼ ((t_ba + t_ab)(1 + δ1) - 2n)(1 + δ2), 0) >= ¼ (t_ba + t_ab)(1 -
    2u) - ¼ 2n``; this function's own few operations (relative ``u`` each, no cancellation
    before the last subtraction) are covered by :func:`_deflate`'s ``ROUND n eps`` of the value
    and of the scale.  The inner products ``<Ẑ, P_d[s, s]>`` and ``<P̂_d⁻¹, X>`` carry their
    ``γ`` of the absolute sums, and ``Ẑ`` is within ``γ_{2N+2} (|C⁻¹| + Σ|S_j|)`` of ``Z``."""
    n = int(X.shape[-1])
    m = Z.shape[0]
    if m == 0:
        return np.zeros(0)
    t = Z @ lc.D_ss
    t_err = _gamma(Z.shape[1] + 1) * (np.abs(Z) @ lc.D_abs)
    tr_y = lc.c_ab + t - (lc.c_err + t_err) - lc.y_sub
    t_ab = lc.ab_scale * tr_y - lc.ab_sub
    Xf = X.reshape(m, n * n)
    q = Xf @ lc.D_inv
    q_err = _gamma(n * n + 1) * (np.abs(Xf) @ np.abs(lc.D_inv)) + ctx.err * lc.D_inv_abs_sum
    t_ba = lc.ba_scale * np.maximum(q - q_err, 0.0)
    v = 0.25 * ((t_ab + t_ba) * (1.0 - 2.0 * UNIT) - 2.0 * n)
    return _deflate(_f64(v), n, ctx, 0.0)


# ---- svd: size and orientation ------------------------------------------------------------


def _eigh_desc(X: Mat, dc: DesiredConstants) -> Mat:
    """``[eigenvalues of X descending (n), eigenvectors (n x n, column i for value i)]``
    ``(m, n + n²)``."""
    m, n = X.shape[0], dc.n
    w, U = np.linalg.eigh(X)
    out = np.empty((m, n + n * n))
    out[:, :n] = w[:, ::-1]
    out[:, n:] = U[:, :, ::-1].reshape(m, n * n)
    return out


def _svd_combine(
    sA: Mat, sB: Mat, dc: DesiredConstants, ctx: IntervalContext
) -> NDArray[np.float64]:
    """The svd metric is ``orientation + ||s_P - s_D||_2``; a lower bound of each term, valid for
    every ``P`` of the interval, is a lower bound of their sum.

    **Size.**  The descending eigenvalues obey ``s_i(A) <= s_i(P) <= s_i(B)`` (Weyl), so
    ``||s_P - s_D||_2 >= sqrt(sum_i dist(s_D,i, [s_i(A), s_i(B)])²)``; errors: ``n err`` (Mirsky)
    for each endpoint and for the completion.

    **Orientation** ``(n - sum_i |u_Pi · u_Di|) / n`` (computed clipped at 0), from ``B``'s
    eigenvectors: every completion's computed ``P`` is within ``e = tr(B - A) + 4 n err + ROUND
    n eps scale`` of the computed ``B`` in 2-norm (``0 ⪯ B - P ⪯ B - A``, ``||·||_2 <= tr`` for
    PSD, the errors, LAPACK's backward error), so ``Σ_i |u_Pi · u_Di|`` is at most
    :func:`covnet.core.allocation.svd_bound.orientation_sum_bound` at the centre ``B`` with
    radius ``e`` (proof in that module; twelfth round, issue 29): the ranks of ``B`` split into
    blocks at gaps ``> 4e + 2 rtol (max|s| + e)`` (``rtol`` the eigenvalue tie tolerance of
    :func:`covnet.core.metrics.ordered_eigh`, so no tie group of ``P`` crosses a block's end);
    a block's sum is at most the sum of the cosines of the principal angles between its
    eigen-subspace and ``P_d``'s, widened by Davis-Kahan (``sin Θ <= e / (gap - e)``).  A block of
    one eigenvector is the per-vector Davis-Kahan credit of earlier rounds, sharper (the angle
    form: ``|u_Pi · u_Di| <= cos(max(φ - θ, 0))`` where it used ``|u_Bi · u_Di| + sqrt 2 e /
    (gap - e)``); a block of a tied pair (the paper's ``P_d``, whose pairs the completions
    nearly tie) is credited the tilt of the pair's plane, which the per-vector bound could not
    see.  Eigenvectors in no block with a gap are credited nothing (``|u_Pi · u_Di| <= 1``)."""
    n = dc.n
    s = dc.eig_desc()
    lo, hi = sA[:, :n], sB[:, :n]
    dist = np.maximum(np.maximum(lo - s, s - hi), 0.0)
    size = _deflate(np.sqrt(_row_sums(dist * dist)), n, ctx, 3.0 * n * ctx.err)
    U_D = dc.eigvecs()
    m = sB.shape[0]
    U = sB[:, n : n + n * n].reshape(m, n, n)
    e = np.maximum(_row_sums(hi) - _row_sums(lo), 0.0)
    e += 4.0 * n * ctx.err + ROUND * n * EPS * ctx.scale
    T = np.matmul(U_D.T, U)  # T[:, j, i] = u_Dj · u_Bi
    credit = svd_bound.orientation_sum_bound(T, hi, e, EIG_TIE_RTOL) if n > 1 else np.ones(m)
    orient = (n - credit) / n - ROUND * n * EPS
    return _f64(size + np.maximum(orient, 0.0))


# the interval bound of every built-in metric (its entry's ``interval_bound`` in
# :data:`covnet.core.metrics.METRICS`)
SPECTRAL_BOUND = IntervalBound(
    _eig_minus_d, _spectral_combine, above=_spectral_above, lazy=_spectral_lazy
)
ABS_TRACE_BOUND = IntervalBound(_diag_minus_d, _abs_trace_combine, _diag_minus_d_from)
TRACE_DIFF_BOUND = IntervalBound(_trace_minus_d, _trace_diff_combine, _trace_minus_d_from)
FROBENIUS_BOUND = IntervalBound(_eig_and_entries, _frobenius_combine)
ONE_NORM_BOUND = IntervalBound(_eig_and_entries, _induced_combine)
INF_NORM_BOUND = IntervalBound(_eig_and_entries, _induced_combine)
LOGDET_BOUND = IntervalBound(_gen_eig, _logdet_combine)
KL_BOUND = IntervalBound(_gen_eig, _kl_combine, leaf=LeafBound(kl_leaf_constants, kl_leaf_bound))
SVD_BOUND = IntervalBound(_eigh_desc, _svd_combine)


def interval_lower_bound(
    metric: str,
    A: Mat,
    B: Mat,
    P_d: Mat | DesiredConstants,
    ctx: IntervalContext,
) -> NDArray[np.float64]:
    """A lower bound of ``min { metric(P, P_d) : A ⪯ P ⪯ B }`` for every interval of the batch
    (``A``, ``B`` ``(m, n, n)`` or one ``(n, n)`` pair, giving ``(m,)`` or a 0-d array), valid for
    the metric as computed on any ``P`` within ``ctx.err`` of the interval.

    ``metric``: a name of :data:`covnet.core.metrics.METRICS` whose entry has an
    ``interval_bound``; ``P_d``: the desired covariance or its :class:`DesiredConstants` (reused
    across calls)."""
    entry = METRICS.get(metric)
    bound: IntervalBound | None = capability(entry.interval_bound, IntervalBound) if entry else None
    if bound is None:
        known = sorted(k for k, m in METRICS.items() if m.interval_bound is not None)
        raise KeyError(f"no interval bound for metric {metric!r}; known: {', '.join(known)}")
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if A.shape != B.shape or A.ndim not in (2, 3) or A.shape[-1] != A.shape[-2]:
        raise ValueError(f"A and B must both be (m, n, n) or (n, n), got {A.shape} and {B.shape}")
    one = A.ndim == 2
    if one:
        A, B = A[None], B[None]
    dc = P_d if isinstance(P_d, DesiredConstants) else DesiredConstants(np.asarray(P_d))
    if dc.D.shape != A.shape[1:]:
        raise ValueError(f"P_d must be {A.shape[1:]} like A and B, got {dc.D.shape}")
    with np.errstate(all="ignore"):
        v = bound.combine(bound.summary(A, dc), bound.summary(B, dc), dc, ctx)
    v = np.where(np.isnan(v), 0.0, v)
    return v[0] if one else v
