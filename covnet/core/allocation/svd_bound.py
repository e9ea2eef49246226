"""Two bounds of the ``svd`` metric: a *working floor*, a cheaper lower bound of its value on a
stack of covariances, with which greedy's local search skips the moves that cannot improve
(:class:`WorkingFloor`, registered as ``Metric.working_floor``; used by
:func:`covnet.core.allocation.greedy._screened_values`), and the *orientation bound through
eigen-subspaces* (:func:`orientation_sum_bound`, used by the interval bound
:func:`covnet.core.allocation.interval_bounds._svd_combine`; its proof below the floor's).

**The floor.**  :func:`covnet.core.metrics.svd` is ``f(A, B) = o(A, B) + ||s_A - s_B||_2`` with
the orientation term ``o = max((n - Σ_i |u_Ai · u_Bi|) / n, 0) >= 0`` and ``s_A``, ``s_B`` the
eigenvalues in descending order.  So ``f >= ||s_A - s_B||_2`` (the size term), which needs the
eigenvalues only: ``np.linalg.eigvalsh`` (LAPACK without eigenvectors) costs about 0.6 of
``np.linalg.eigh`` on ``4 x 4`` stacks, and on greedy's swaps at N = 100 the size term alone
shows 73-98 % of them unable to improve (the orientation term is about 7 % of the optimum's
value on the bench problems).

**Rounding.**  The floor is compared with the *computed* value ``f̂``, whose eigenvalues ``ŝ_A``
come from ``eigh``, the floor's ``s'_A`` from ``eigvalsh`` (and ``B``'s likewise: the
metric's from :func:`~covnet.core.metrics.ordered_eigh`, the floor's from ``eigvalsh``).  Both
LAPACK drivers are backward stable: each computed eigenvalue is within ``p(n) ε ||A||_2`` of
the exact one (Weyl), so
``||ŝ_A - s'_A||_2 <= 2 sqrt(n) p(n) ε ||A||_2`` with ``p(n)`` a modest polynomial (``≈ 10 n``
in practice, ``ε = 2.2e-16``).  The computed sums and square roots add a relative ``(n + 2) ε``
each.  ``f̂ = fl(ô + ŝize)`` with ``ô >= 0`` (clipped), so ``f̂ >= ŝize`` (rounding is
monotone).  The floor is therefore ``size' - μ`` with the margin ``μ = MARGIN · n · (max_k |s'_k|
+ max_k |s_Bk| + size')``, ``MARGIN = 1e-10``: four orders of magnitude above the error
``≈ 10 n^{3/2} ε (||A||_2 + ...)`` it covers, and far below any gap between two subsets'
values that matters to a local search (``IMPROVE = 1e-12`` relative is the step it must beat,
and a skipped move has a floor *at or above* the threshold, so the margin only makes fewer
moves skipped).  Rows with a non-finite entry get ``-inf`` (never skipped: ``eigvalsh`` raises
on them where ``eigh`` returns NaN), as does the whole stack if ``eigvalsh`` raises.
``tests/unit/test_svd_bound.py`` checks ``floor <= svd`` on random stacks with nearly tied and
tied eigenvalues, and greedy's local search with and without the floor, subset for subset.

**The orientation bound** (twelfth round, issue 29).  The orientation term is
``o(P) = (n - Σ_i |u_Pi · u_Di|) / n``, ``u_Pi`` the metric's ``i``-th eigenvector of ``P``
(descending eigenvalues, tie groups rebuilt by :func:`~covnet.core.metrics.ordered_eigh`),
``u_Di`` ``P_d``'s.  Where ``P_d``'s eigenvalues come in tied pairs (the paper's
``diag(7, 0.8, 7, 0.8)``) and the completions' pairs nearly tie, a single eigenvector of ``P``
turns freely inside its pair's plane and no per-vector bound (Davis-Kahan on one eigenvalue's
gap) credits anything; but the *plane* of a pair is pinned by the large gap between the pairs,
and its tilt against ``P_d``'s plane (the position-velocity correlation) costs every completion
about 0.03 of orientation on the bench problems.  Bounded here through subspaces:

1. *A block's sum is at most a nuclear norm.*  Let ``g`` be a block of consecutive ranks
   (``k = |g|``) whose eigenvalues are separated from the others' in ``P``, ``V = [u_Pi]_{i∈g}``
   (``n x k``, orthonormal: any orthonormal basis of ``P``'s invariant subspace of the block,
   LAPACK's or the tie convention's) and ``Q = [u_Di]_{i∈g}``.  Then ``Σ_{i∈g} |u_Pi · u_Di| =
   Σ_i |(QᵀV)_ii| = |tr(S QᵀV)|`` for a diagonal sign matrix ``S``, and ``|tr(S X)| <= ||S||_2
   ||X||_* = ||X||_*`` (von Neumann's trace inequality): at most ``Σ_j σ_j(QᵀV)``, whose
   squares are the eigenvalues of ``Qᵀ Π_P Q``, ``Π_P = V Vᵀ`` the block's spectral projector.
   This holds whatever basis of the subspace the metric uses, so the tie convention does not
   enter, provided no tie group of ``P`` crosses the block's ends (below).
2. *The projector moves little* (Davis-Kahan ``sin Θ``, Bhatia, Matrix Analysis, Thm VII.3.1):
   for a centre ``M`` with ``||P - M||_2 <= r`` and the same block's projector ``Π_M``, if
   ``M``'s block eigenvalues lie in ``[λ_b(M), λ_a(M)]`` and ``P``'s other eigenvalues lie
   outside ``(λ_b(M) - δ, λ_a(M) + δ)``, then ``||Π_P - Π_M||_2 = ||sin Θ||_2 <= r / δ``.  By
   Weyl ``λ_{b+1}(P) <= λ_{b+1}(M) + r`` and ``λ_{a-1}(P) >= λ_{a-1}(M) - r``, so ``δ =
   min(λ_b(M) - λ_{b+1}(M), λ_{a-1}(M) - λ_a(M)) - r`` (the gaps at the block's ends that
   exist), wherever it is positive.
3. *Weyl on the compression*: ``Qᵀ Π_P Q ⪯ Qᵀ Π_M Q + s QᵀQ`` with ``s = min(r / δ, 1)`` and
   ``QᵀQ = I``, so ``σ_j(QᵀV_P)² <= c_j + s``, ``c_j`` the eigenvalues of ``Qᵀ Π_M Q``
   (descending, both sides), and ``σ_j <= 1``.  Also, writing ``V_P = V_M Y₁ + V_⊥ Y₂``
   (``V_⊥`` an orthonormal basis of ``V_M``'s complement, ``||Y₁||_2 <= 1``, ``||Y₂||_2 =
   ||sin Θ||_2 <= s``), Weyl for singular values gives ``σ_j(QᵀV_P) <= σ_j(QᵀV_M Y₁) +
   ||QᵀV_⊥||_2 s <= sqrt(c_j) + sin φ_max s``, with ``sin² φ_max = ||QᵀV_⊥||² = 1 - c_min``
   (``QᵀV_⊥V_⊥ᵀQ = I - Qᵀ Π_M Q``): about half the first form's widening at a tilt of 15°.
   So ``Σ_{i∈g} |u_Pi · u_Di| <= Σ_j min(1, sqrt(c_j + s), sqrt(c_j) + sin φ_max s)``.
   A block of one (``k = 1``) takes the sharper angle form: ``u_P = cos θ' u_M + sin θ' w``
   (``w ⟂ u_M``, ``sin θ' <= s``, sign absorbed), and ``q = u_D``'s component orthogonal to
   ``u_M`` has norm ``sin φ`` (``cos φ = |u_M · q|``), so ``|u_P · q| <= cos(φ - θ')
   <= cos(max(φ - θ, 0))``, ``sin θ = s``: ``c cos θ + sin φ s`` when ``s <= sin φ``, else 1.
4. *Blocks*: a boundary between ranks ``k`` and ``k + 1`` counts where ``M``'s gap exceeds
   ``4r + 2 rtol (max|λ(M)| + r)`` (``rtol`` :data:`~covnet.core.metrics.EIG_TIE_RTOL`): then
   ``P``'s gap there exceeds ``2r`` plus ``rtol max|λ(P)|``, so :func:`~covnet.core.metrics.\
ordered_eigh`'s tie groups (chained between neighbours closer than ``rtol max|λ|``) never cross
   it, and ``δ >= 3r > 0``.  The blocks are the runs between counted boundaries; a run without
   any boundary (the whole spectrum) is credited ``k`` (nothing).  Summing 1.-3. over the
   blocks gives ``Σ_i |u_Pi · u_Di| <= credit`` and ``o(P) >= (n - credit) / n``.

**Rounding.**  The caller passes ``M`` as computed with its LAPACK eigenvectors, which are
exact for a matrix ``M'`` within LAPACK's backward error of the computed ``M``; the completion's
vectors likewise for ``P'``; ``r`` must bound ``||P' - M'||_2`` (the caller's error model:
:func:`covnet.core.allocation.interval_bounds._svd_combine`).  Computed eigenvectors and
``u_D`` are orthonormal up to ``O(n ε)``, which moves ``Qᵀ Π Q``'s eigenvalues and the sums by
``O(n ε)``: the caller deflates the orientation by ``ROUND n ε`` as before.
``tests/unit/test_svd_orientation.py`` checks the bound against the exhaustive minimum of the
subtree (random nodes, the bench problems, tied ``P_d`` pairs) and that an inflated one fails.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from covnet.core.gaussian import Mat

#: the floor's rounding margin, relative (module docstring)
MARGIN = 1e-10


@dataclass(frozen=True)
class WorkingFloor:
    """``fn(A, B)``: a lower bound of the metric's computed value ``f(A, B)`` for a stack ``A``
    ``(m, n, n)`` of finite symmetric matrices and one ``B`` ``(n, n)``, returning ``(m,)``
    (``-inf`` where it says nothing), cheaper than the metric itself."""

    fn: Callable[[Mat, Mat], Mat]

    def __call__(self, A: Mat, B: Mat) -> Mat:
        return self.fn(A, B)


def svd_floor(A: Mat, B: Mat) -> Mat:
    """The size term of :func:`covnet.core.metrics.svd` from ``eigvalsh``, less the rounding
    margin: ``||s'_A - s_B||_2 - MARGIN · n · (max|s'_A| + max|s_B| + ||s'_A - s_B||_2)``, a
    lower bound of the computed ``svd(A, B)`` (module docstring); ``-inf`` for rows with a
    non-finite entry."""
    m, n = A.shape[0], A.shape[-1]
    out = np.full(m, -np.inf)
    if m == 0 or n == 0:
        return out
    s_B = np.linalg.eigvalsh(B)[::-1]
    if not np.isfinite(s_B).all():
        return out
    ok = np.isfinite(A.reshape(m, n * n)).all(axis=1)
    rows = np.flatnonzero(ok)
    if rows.size == 0:
        return out
    try:
        w = np.linalg.eigvalsh(A[rows] if rows.size < m else A)[:, ::-1]
    except np.linalg.LinAlgError:
        return out
    size = np.sqrt(((w - s_B) ** 2).sum(axis=1))
    scale = np.abs(w).max(axis=1) + float(np.abs(s_B).max()) + size
    out[rows] = size - MARGIN * n * scale
    return out


SVD_FLOOR = WorkingFloor(svd_floor)


def orientation_sum_bound(T: Mat, w_M: Mat, radius: Mat, rtol: float) -> Mat:
    """An upper bound ``(m,)`` of ``Σ_i |u_Pi · u_Di|`` (the metric's eigenvector products,
    module docstring, *the orientation bound*) for every symmetric ``P`` with ``||P - M||_2 <=
    radius``, from the centres' eigenvalues ``w_M`` ``(m, n)`` (descending) and the products
    ``T[:, j, i] = u_Dj · u_Mi`` ``(m, n, n)`` of ``P_d``'s eigenvectors (the metric's, ``j``-th
    largest) with the centre's (``u_Mi`` for ``w_M[:, i]``), the radii ``(m,)``; ``n`` where
    nothing is proved (no block boundary, or a non-finite row)."""
    n = w_M.shape[1]
    m = np.broadcast_shapes(w_M.shape[:1], radius.shape, T.shape[:1])[0]
    out = np.full(m, float(n))
    if m == 0 or n < 2:
        return out
    with np.errstate(all="ignore"):
        r = radius[:, None]
        gap = w_M[:, :-1] - w_M[:, 1:]  # descending: >= 0
        top = np.maximum(w_M[:, :1], -w_M[:, -1:])  # max|λ| (descending)
        cut = gap > 4.0 * r + 2.0 * rtol * (top + r)  # False on NaN
        delta = gap - r
        if n <= 16:
            code = cut @ (1 << np.arange(n - 1))
            present = np.flatnonzero(np.bincount(code, minlength=1)).tolist()
            rows_cuts = [[k for k in range(n - 1) if c >> k & 1] for c in present]
        else:
            rows_cuts = [np.flatnonzero(row).tolist() for row in np.unique(cut, axis=0)]
        blocks: set[tuple[int, int]] = set()
        for cuts in rows_cuts:
            if cuts:
                edges = [0, *[k + 1 for k in cuts], n]
                blocks.update(zip(edges[:-1], edges[1:], strict=True))
        save = np.zeros(m)
        for a, b in sorted(blocks):
            # the rows whose blocks include [a, b): cuts at its ends, none inside
            valid = ~cut[:, a : b - 1].any(axis=1) if b - a > 1 else np.ones(m, dtype=bool)
            ends = []
            if a > 0:
                valid &= cut[:, a - 1]
                ends.append(delta[:, a - 1])
            if b < n:
                valid &= cut[:, b - 1]
                ends.append(delta[:, b - 1])
            s = np.minimum(radius / (ends[0] if len(ends) == 1 else np.minimum(*ends)), 1.0)
            credit = _block_credit(T, a, b, s)
            save += np.where(valid, (b - a) - credit, 0.0)
        out -= save
    return np.where(np.isfinite(out), out, float(n))


def _block_credit(T: Mat, a: int, b: int, s: Mat) -> Mat:
    """``Σ_j min(1, sqrt(c_j + s))`` over the eigenvalues ``c_j`` of ``Qᵀ Π_M Q`` for the block
    ``[a, b)`` (module docstring, steps 1-3; a block of one: the angle form)."""
    if b - a == 1:
        cphi = np.minimum(np.abs(T[:, a, a]), 1.0)
        sphi = np.sqrt(np.maximum(1.0 - cphi * cphi, 0.0))
        turn = cphi * np.sqrt(np.maximum(1.0 - s * s, 0.0)) + sphi * s
        one: Mat = np.where(s <= sphi, np.minimum(turn, 1.0), 1.0)
        return one
    if b - a == 2:  # Qᵀ Π_M Q's 2 x 2 entries, its eigenvalues in closed form
        t00, t01 = T[:, a, a], T[:, a, a + 1]
        t10, t11 = T[:, a + 1, a], T[:, a + 1, a + 1]
        g00 = t00 * t00 + t01 * t01
        g11 = t10 * t10 + t11 * t11
        g01 = t00 * t10 + t01 * t11
        h = 0.5 * (g00 + g11)
        q = np.sqrt(0.25 * (g00 - g11) ** 2 + g01 * g01)
        hi, lo = np.maximum(h + q, 0.0), np.maximum(h - q, 0.0)
        tilt2 = np.sqrt(np.maximum(1.0 - lo, 0.0)) * s
        c_hi = np.minimum(np.minimum(np.sqrt(hi + s), np.sqrt(hi) + tilt2), 1.0)
        c_lo = np.minimum(np.minimum(np.sqrt(lo + s), np.sqrt(lo) + tilt2), 1.0)
        two: Mat = c_hi + c_lo
        return two
    Tb = T[:, a:b, a:b]
    c2 = np.maximum(np.linalg.eigvalsh(np.matmul(Tb, np.swapaxes(Tb, 1, 2))), 0.0)
    ss = s[:, None]
    tilt = np.sqrt(np.maximum(1.0 - c2.min(axis=1, keepdims=True), 0.0))  # sin φ_max(M)
    cred = np.minimum(np.sqrt(c2 + ss), np.sqrt(c2) + tilt * ss)
    many: Mat = np.minimum(cred, 1.0).sum(axis=1)
    return many
