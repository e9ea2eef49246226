"""Proofs that a symmetric matrix's extreme eigenvalue passes a threshold, without eigenvalues.

Spectral's interval bound (:func:`covnet.core.allocation.interval_bounds._spectral_combine`)
reads ``λmax(A - P_d)`` of a lower endpoint and ``λmin(B - P_d)`` of an upper one, and a search
(:mod:`covnet.core.allocation.search`) needs of a child only the *decision* ``bound > τ``.
With ``M = X - P_d``:

    ``λmax(M) > T``  ⇔  ``T I - M`` is not positive definite,
    ``λmin(M) < -T`` ⇔  ``M + T I`` is not positive definite,

and a Cholesky factorisation that breaks down (a pivot ``<= 0``) proves "not positive definite"
up to a margin (Demmel's theorem, below).  :func:`cholesky_breaks` is a closed-form, vectorised
Cholesky of many small matrices (elementwise numpy operations on ``(m,)`` arrays: no batched
LAPACK call, no matmul), about 15 times cheaper than LAPACK's ``eigvalsh`` of a ``4 x 4`` batch.

**Demmel's theorem** (Higham, *Accuracy and Stability of Numerical Algorithms*, 2nd ed.,
Thm 10.7): let ``H`` be symmetric ``n x n`` with positive diagonal, ``D = diag(H)^{1/2}``,
``c_n = nγ_{n+1} / (1 - nγ_{n+1})`` with ``γ_k = k u / (1 - k u)``, ``u = eps / 2``.  If
``λmin(D⁻¹HD⁻¹) > c_n``, Cholesky in floating point runs to completion (every pivot ``> 0``), for
any order of evaluating its inner products.  Contrapositive, with ``y`` the unit eigenvector of
``S = D⁻¹HD⁻¹``'s least eigenvalue and ``x = D⁻¹y`` (``xᵀx >= 1 / max_i H_ii``): a breakdown
gives ``λmin(S) <= c_n`` and ``λmin(H) <= xᵀHx / xᵀx = λmin(S) / xᵀx <= c_n max_i H_ii`` (if
``λmin(S) <= 0`` the quotient is ``<= 0``).  A non-positive diagonal entry gives ``λmin(H) <=
H_ii <= 0`` directly (the first pivot that reads it breaks down, or an earlier one did).
:func:`breakdown_slack` is ``c_n`` plus the rounding of the diagonal's shift (``fl(T - M_ii)``,
relative error ``<= u / (1 - u)``; off-diagonal entries are exact negations): the computed
``H`` is then within ``u/(1-u) max|H_ii|`` of ``T I - M`` in 2-norm, so a breakdown proves

    ``λmin(T I - M) <= breakdown_slack(n) · max_i |H_ii|``,  i.e.  ``λmax(M) >= T - that``,

and likewise ``λmin(M) <= -T + breakdown_slack(n) · max_i |H_ii|`` for ``H = M + T I``.  A row
with a non-finite entry, or entries large enough to overflow (the theorem assumes none),
proves nothing: :func:`cholesky_breaks` reports it as broken and the caller must drop it
(:func:`covnet.core.allocation.interval_bounds._spectral_above` does).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from covnet.core.gaussian import Mat

__all__ = ["breakdown_slack", "cholesky_breaks", "lam_max_above", "lam_min_below"]

EPS = float(np.finfo(np.float64).eps)


def breakdown_slack(n: int) -> float:
    """``c_n + u / (1 - u)`` of the module docstring (``u = eps / 2``), rounded up generously
    (a factor 2): a breakdown of the computed ``H`` proves ``λmin <= this · max_i |H_ii|``."""
    u = EPS / 2.0
    g = (n + 1) * u / (1.0 - (n + 1) * u)
    c = n * g / (1.0 - n * g)
    return 2.0 * (c + u / (1.0 - u))


def cholesky_breaks(
    diag: list[Mat], off: dict[tuple[int, int], Mat], negated: bool = False
) -> NDArray[np.bool_]:
    """Rows whose Cholesky factorisation breaks down: the symmetric ``H`` of diagonal
    ``diag[i]`` ``(m,)`` and lower entries ``off[i, j]`` ``(m,)`` (``i > j``; ``negated``: the
    entries are ``-off[i, j]``), the standard algorithm (``L_jj = sqrt(H_jj - Σ_k L_jk²)``,
    ``L_ij = (H_ij - Σ_k L_ik L_jk) / L_jj``, the sums left to right, one rounding an
    operation).  ``True``: not every pivot is ``> 0``.  For a finite row that is a breakdown:
    the first pivot ``<= 0`` makes every later one NaN or ``-inf`` (``sqrt`` of a negative, or a
    division by 0), never ``> 0``.  A row with a NaN or infinite entry is ``True`` too, and
    proves nothing: the caller drops such rows (and rows large enough to overflow: Demmel's
    theorem assumes no overflow).

    ``negated`` computes ``L~ = -L`` below the diagonal: ``L~_ij = (off_ij + Σ_k L~_ik L~_jk)
    / L_jj``, the same bits as ``-L_ij`` (IEEE negation is exact and round-to-nearest is
    symmetric: ``fl(-a - b) = -fl(a + b)``), and the pivots read only the products
    ``L~_jk² = L_jk²``: the very pivots of ``H``, without negating ``off``."""
    n = len(diag)
    L: dict[tuple[int, int], Mat] = {}
    ok: NDArray[np.bool_] = np.ones(diag[0].shape, dtype=bool)  # every pivot so far > 0
    with np.errstate(all="ignore"):
        for j in range(n):
            p = diag[j]
            for k in range(j):
                p = p - L[j, k] * L[j, k]
            ok &= p > 0.0
            if j + 1 < n:
                r = np.sqrt(p)
                for i in range(j + 1, n):
                    s = off[i, j]
                    for k in range(j):
                        if negated:
                            s = s + L[i, k] * L[j, k]
                        else:
                            s = s - L[i, k] * L[j, k]
                    L[i, j] = s / r
    return ~ok


def lam_max_above(M: Mat, T: float) -> NDArray[np.bool_]:
    """Rows of ``M`` ``(m, n, n)`` (symmetric) whose ``T I - M`` breaks Cholesky down: each has
    ``λmax(M) >= T - breakdown_slack(n) · max_i |T - M_ii|`` (computed ``T - M_ii``; module
    docstring).  The off-diagonal entries ``-M_ij`` through :func:`cholesky_breaks`'
    ``negated``."""
    n = M.shape[1]
    diag = [T - M[:, i, i] for i in range(n)]
    off = {(i, j): M[:, i, j] for i in range(n) for j in range(i)}
    return cholesky_breaks(diag, off, negated=True)


def lam_min_below(M: Mat, T: float) -> NDArray[np.bool_]:
    """Rows of ``M`` ``(m, n, n)`` (symmetric) whose ``M + T I`` breaks Cholesky down: each has
    ``λmin(M) <= -T + breakdown_slack(n) · max_i |M_ii + T|`` (module docstring)."""
    n = M.shape[1]
    diag = [M[:, i, i] + T for i in range(n)]
    off = {(i, j): M[:, i, j] for i in range(n) for j in range(i)}
    return cholesky_breaks(diag, off)
