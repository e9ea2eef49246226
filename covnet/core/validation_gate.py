"""The fusion centre's validation gate: a message whose innovation is impossible under the
filter's own model is not fused (a forged or corrupted measurement, not a tracking decision).

For a measurement ``z`` of ``H x + v`` with prediction ``N(x⁻, P⁻)`` the innovation
``ν = z − H x⁻`` has covariance ``S = H P⁻ Hᵀ + R``, and ``d² = νᵀ S⁻¹ ν`` is χ² with
``dim z`` degrees of freedom; for a local track ``N(x, P)`` of the same target, conservatively
``d² = (x − x⁻)ᵀ (P + P⁻)⁻¹ (x − x⁻)`` with ``dim x`` degrees of freedom (the common prior only
makes the true spread smaller).  The gate passes ``d² ≤ γ`` with ``P(χ²_n > γ) = TAIL``:
``TAIL = 10⁻⁹``, so a genuine message fails it about once in a billion, while one kilometres
away fails it by orders of magnitude.

``γ`` for even ``n`` from the closed-form survival function
``P(χ²_n > x) = e^{−x/2} Σ_{i<n/2} (x/2)^i / i!`` (bisection: no scipy.stats at start-up).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from covnet.core.gaussian import Mat, Vec

__all__ = ["TAIL", "passes_innovation", "passes_measurement", "passes_track", "threshold"]

TAIL = 1e-9
"""The probability that a genuine message fails the gate."""


def _survival(x: float, dof: int) -> float:
    """``P(χ²_dof > x)`` for even ``dof``."""
    h = x / 2.0
    term, total = 1.0, 1.0
    for i in range(1, dof // 2):
        term *= h / i
        total += term
    return math.exp(-h) * total


@lru_cache(maxsize=16)
def threshold(dof: int, tail: float = TAIL) -> float:
    """``γ`` with ``P(χ²_dof > γ) = tail`` (``dof`` even, >= 2)."""
    if dof < 2 or dof % 2:
        raise ValueError(f"the closed form needs an even number of degrees of freedom, got {dof}")
    lo, hi = 0.0, 1.0
    while _survival(hi, dof) > tail:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _survival(mid, dof) > tail:
            lo = mid
        else:
            hi = mid
    return hi


def passes_measurement(z: Vec, R: Mat, H: Mat, x_pred: Vec, P_pred: Mat) -> bool:
    """``νᵀ S⁻¹ ν ≤ γ`` (module docstring)."""
    return passes_innovation(z - H @ x_pred, H @ P_pred @ H.T + R)


def passes_innovation(nu: Vec, S: Mat) -> bool:
    """``νᵀ S⁻¹ ν ≤ γ`` for an innovation ``ν`` and its covariance ``S = H P⁻ Hᵀ + R`` (a
    caller gating several measurements of one prediction computes ``H x⁻`` and ``H P⁻ Hᵀ``
    once); a 2-vector in closed form (it is on every measurement's path:
    ``d² = (s₂₂ ν₁² − 2 s₁₂ ν₁ ν₂ + s₁₁ ν₂²) / det S``)."""
    if nu.shape == (2,):
        (a, b), (_, d) = S.tolist()
        n1, n2 = nu.tolist()
        det = a * d - b * b
        if det > 0.0:
            return bool((d * n1 * n1 - 2.0 * b * n1 * n2 + a * n2 * n2) / det <= threshold(2))
    return bool(nu @ np.linalg.solve(S, nu) <= threshold(len(nu)))


def passes_track(x: Vec, P: Mat, x_pred: Vec, P_pred: Mat) -> bool:
    """``(x − x⁻)ᵀ (P + P⁻)⁻¹ (x − x⁻) ≤ γ`` (module docstring)."""
    d = x - x_pred
    return bool(d @ np.linalg.solve(P + P_pred, d) <= threshold(len(d)))
