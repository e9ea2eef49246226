"""A working floor of the ``svd`` metric: a cheaper lower bound of its value on a stack of
covariances, with which greedy's local search skips the moves that cannot improve
(:class:`WorkingFloor`, registered as ``Metric.working_floor``; used by
:func:`covnet.core.allocation.greedy._screened_values`).

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
