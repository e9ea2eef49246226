"""Gaussian state records and small covariance helpers.

``Vec`` and ``Mat`` are the array aliases used across the core: ``x`` is ``(n,)``, ``P`` is
``(n, n)``, batches go on leading axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]


def symmetrise(P: Mat) -> Mat:
    """Return ``(P + Pᵀ) / 2`` over the last two axes (removes rounding asymmetry)."""
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def is_spd(P: Mat, tol: float = 0.0) -> bool:
    """True when ``P`` is symmetric and its Cholesky factor exists (eigenvalues > ``tol``)."""
    P = np.asarray(P, dtype=np.float64)
    if P.ndim != 2 or P.shape[0] != P.shape[1] or not np.all(np.isfinite(P)):
        return False
    if not np.allclose(P, P.T, rtol=1e-10, atol=1e-12 * max(1.0, float(np.abs(P).max()))):
        return False
    try:
        np.linalg.cholesky(P - tol * np.eye(P.shape[0]))
    except np.linalg.LinAlgError:
        return False
    return True


@dataclass(frozen=True, slots=True)
class Gaussian:
    """A Gaussian density ``N(x, P)``: mean ``x`` of shape ``(n,)``, covariance ``P`` ``(n, n)``.

    Shapes are checked once here, at the boundary, not in every function that uses it.
    """

    x: Vec
    P: Mat

    def __post_init__(self) -> None:
        x = np.asarray(self.x, dtype=np.float64)
        P = np.asarray(self.P, dtype=np.float64)
        if x.ndim != 1:
            raise ValueError(f"Gaussian.x must be 1-D, got shape {x.shape}")
        if P.shape != (x.shape[0], x.shape[0]):
            raise ValueError(f"Gaussian.P must be {(x.shape[0],) * 2}, got {P.shape}")
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "P", P)

    @property
    def dim(self) -> int:
        return int(self.x.shape[0])
