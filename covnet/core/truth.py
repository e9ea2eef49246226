"""Target ground truth as a pure function of the model and a generator."""

from __future__ import annotations

import numpy as np

from covnet.core.gaussian import Mat, Vec


def linear_gaussian_trajectory(
    x0: Vec, F: Mat, G: Mat, sigma_a: float, n_scans: int, rng: np.random.Generator
) -> Mat:
    """States ``x(1..N)`` of ``x(k+1) = F x(k) + G w(k)``, ``w(k) ~ N(0, σ_a² I)``.

    Returns ``(n_scans, n)``: row ``k-1`` is the state at scan ``k`` (time ``k T``); ``x0`` is
    the state at time 0.  All noise is drawn in one call, so the trajectory depends only on the
    generator's state.
    """
    w = sigma_a * rng.standard_normal((n_scans, G.shape[1]))
    out = np.empty((n_scans, x0.shape[0]))
    x = np.asarray(x0, dtype=np.float64)
    for k in range(n_scans):
        x = F @ x + G @ w[k]
        out[k] = x
    return out
