"""Cholesky factor and solve of one small SPD matrix, straight from LAPACK.

``A = Uᵀ U`` (``U`` upper triangular, ``potrf``), then ``A X = B`` by two triangular solves
(``potrs``).  These are the LAPACK calls :func:`scipy.linalg.cho_factor` /
:func:`scipy.linalg.cho_solve` make, with the same arguments (upper factor, ``clean=False``), so
the results are bit for bit theirs; what is skipped is their Python wrapping (input conversion,
batch dispatch, finiteness checks on every argument), which costs ~14 µs per factor-and-solve
against ~2 µs for the LAPACK work on the 2 x 2 and 4 x 4 matrices of a Kalman update.  The
filter runs this once per measurement per scan, in the manager's critical loop.

Errors as scipy's: a non-finite input raises ``ValueError``, a matrix that is not positive
definite ``numpy.linalg.LinAlgError``.
"""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np

from covnet.core.gaussian import Mat
from covnet.core.lapack import flapack


def _lapack() -> ModuleType:
    """scipy's LAPACK wrappers (:mod:`covnet.core.lapack`: loaded on first use, without
    importing scipy.linalg)."""
    return flapack()


def _float_matrix(A: Mat, what: str) -> Mat:
    A = np.asarray(A)
    if A.dtype != np.float64:
        A = A.astype(np.float64)
    if A.ndim not in (1, 2):
        raise ValueError(f"{what} must be 1-D or 2-D, got shape {A.shape}")
    # a few entries: Python floats are checked faster than a numpy call is made
    finite = all(map(math.isfinite, A.ravel().tolist())) if A.size <= 64 else np.isfinite(A).all()
    if not finite:
        raise ValueError(f"{what} must contain only finite numbers")
    return A


def cho_factor(A: Mat) -> Mat:
    """The upper Cholesky factor of the SPD ``(n, n)`` matrix ``A`` (the lower triangle of the
    result holds whatever ``A`` had there, as ``scipy.linalg.cho_factor``'s does)."""
    A = _float_matrix(A, "matrix")
    if A.ndim != 2 or A.shape[0] != A.shape[1] or A.shape[0] == 0:
        raise ValueError(f"expected a non-empty square matrix, got shape {A.shape}")
    c: Mat  # LAPACK's dpotrf on a float64 matrix returns a float64 matrix (the stubs say Any)
    info: int
    c, info = _lapack().dpotrf(A, lower=0, clean=0, overwrite_a=0)
    if info > 0:
        raise np.linalg.LinAlgError(
            f"{info}-th leading minor of the array is not positive definite"
        )
    if info < 0:  # pragma: no cover - only for arguments this module never passes
        raise ValueError(f"LAPACK potrf: illegal value in argument {-info}")
    return c


def cho_solve(c: Mat, B: Mat) -> Mat:
    """``X`` with ``A X = B`` from ``c = cho_factor(A)``; ``B`` is ``(n,)`` or ``(n, m)``."""
    B = _float_matrix(B, "right-hand side")
    if B.shape[0] != c.shape[0]:
        raise ValueError(f"incompatible dimensions ({c.shape} and {B.shape})")
    x: Mat  # dpotrs on float64 arguments: float64 (the stubs say Any)
    info: int
    x, info = _lapack().dpotrs(c, B, lower=0, overwrite_b=0)
    if info != 0:  # pragma: no cover - only for arguments this module never passes
        raise ValueError(f"LAPACK potrs: illegal value in argument {-info}")
    return x
