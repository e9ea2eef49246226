"""Filter consistency: NEES and NIS and their two-sided χ² acceptance bands.

Bar-Shalom, Li & Kirubarajan 2001, §5.4 (chi-square consistency tests)::

    NEES  ε = (x − x̂)ᵀ P⁻¹ (x − x̂)     ~ χ²(n)       for a consistent filter (n = dim x)
    NIS   ε_ν = νᵀ S⁻¹ ν               ~ χ²(n_z)

For ``M`` independent runs the average ``ε̄ = (1/M) Σ ε_i`` has ``M ε̄ ~ χ²(M n)``, so the
two-sided ``1 − α`` band is::

    [ χ²_{Mn}⁻¹(α/2) / M ,  χ²_{Mn}⁻¹(1 − α/2) / M ]       (α = 0.05: the 95 % band)

``M = 1`` is the single-run band of one value.  Averaging over the ``K`` scans of one run
is the same band with ``M = K`` for the NIS (the innovations of a consistent filter are white)
but only approximate for the NEES (its errors are correlated from scan to scan).
E.g. ``n = 2, M = 50`` gives ``[1.48, 2.59]`` (Bar-Shalom's example: ``[1.5, 2.6]``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

__all__ = ["Band", "chi2_band", "mean_chi2_band", "nees", "nees_band", "nis", "nis_band"]


def _quadratic_form(e: ArrayLike, P: ArrayLike, what: str) -> NDArray[np.float64]:
    """``eᵀ P⁻¹ e`` over leading axes, via the Cholesky factor: ``‖L⁻¹ e‖²``, ``P = L Lᵀ``."""
    ee = np.asarray(e, dtype=np.float64)
    PP = np.asarray(P, dtype=np.float64)
    if ee.ndim == 0 or PP.shape[-2:] != (ee.shape[-1], ee.shape[-1]):
        raise ValueError(
            f"{what}: expected vectors (..., n) and covariances (..., n, n), got {ee.shape} "
            f"and {PP.shape}"
        )
    L = np.linalg.cholesky(PP)  # a non-SPD covariance raises LinAlgError
    y = np.linalg.solve(L, ee[..., None])[..., 0]
    return np.asarray(np.sum(y * y, axis=-1))


def nees(x_true: ArrayLike, x_hat: ArrayLike, P: ArrayLike) -> NDArray[np.float64]:
    """``ε = (x − x̂)ᵀ P⁻¹ (x − x̂)``, batched over leading axes (``(..., n)``, ``(..., n, n)``
    -> ``(...)``)."""
    e = np.asarray(x_true, dtype=np.float64) - np.asarray(x_hat, dtype=np.float64)
    return _quadratic_form(e, P, "nees")


def nis(nu: ArrayLike, S: ArrayLike) -> NDArray[np.float64]:
    """``ε_ν = νᵀ S⁻¹ ν``, batched over leading axes."""
    return _quadratic_form(nu, S, "nis")


@dataclass(frozen=True, slots=True)
class Band:
    """A two-sided acceptance interval ``[low, high]`` for a (mean) χ² statistic."""

    low: float
    high: float
    dof: int
    n_runs: int
    probability: float

    def contains(self, value: ArrayLike) -> NDArray[np.bool_]:
        """True where ``low ≤ value ≤ high``."""
        v = np.asarray(value, dtype=np.float64)
        return np.asarray((v >= self.low) & (v <= self.high))


def chi2_band(dof: int, n_runs: int = 1, probability: float = 0.95) -> Band:
    """Band of the average of ``n_runs`` independent ``χ²(dof)`` values (module docstring)."""
    if int(dof) != dof or dof < 1:
        raise ValueError(f"dof: expected a positive integer, got {dof!r}")
    if int(n_runs) != n_runs or n_runs < 1:
        raise ValueError(f"n_runs: expected a positive integer, got {n_runs!r}")
    lo, hi = _mean_band(int(dof) * int(n_runs), int(n_runs), probability)
    return Band(lo, hi, int(dof), int(n_runs), float(probability))


def mean_chi2_band(total_dof: int, n_values: int, probability: float = 0.95) -> tuple[float, float]:
    """Band of the mean of ``n_values`` independent χ² values whose degrees of freedom sum to
    ``total_dof`` (e.g. a NIS averaged over scans with 1-D and 2-D sensors):
    ``[χ²_D⁻¹(α/2) / N, χ²_D⁻¹(1 − α/2) / N]``, ``D = total_dof``, ``N = n_values``."""
    if int(total_dof) != total_dof or total_dof < 1:
        raise ValueError(f"total_dof: expected a positive integer, got {total_dof!r}")
    if int(n_values) != n_values or n_values < 1:
        raise ValueError(f"n_values: expected a positive integer, got {n_values!r}")
    return _mean_band(int(total_dof), int(n_values), probability)


def _mean_band(D: int, N: int, probability: float) -> tuple[float, float]:
    q = float(probability)
    if not (0.0 < q < 1.0):
        raise ValueError(f"probability: expected 0 < probability < 1, got {probability!r}")
    tail = 0.5 * (1.0 - q)
    return float(stats.chi2.ppf(tail, D)) / N, float(stats.chi2.ppf(1.0 - tail, D)) / N


def nees_band(state_dim: int, n_runs: int = 1, probability: float = 0.95) -> Band:
    """The NEES band: :func:`chi2_band` with ``dof = dim x``."""
    return chi2_band(state_dim, n_runs, probability)


def nis_band(dim_z: int, n_runs: int = 1, probability: float = 0.95) -> Band:
    """The NIS band: :func:`chi2_band` with ``dof = dim z``."""
    return chi2_band(dim_z, n_runs, probability)
