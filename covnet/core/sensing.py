"""Linear measurement models: position sensors with correlated noise.

A position sensor on the state ``[x, vx, y, vy]`` measures ``z = H x + v``, ``v ~ N(0, R)`` with

    H = [[1, 0, 0, 0],
         [0, 0, 1, 0]],      R = [[σx², ρ σx σy], [ρ σx σy, σy²]].
"""

from __future__ import annotations

from typing import cast

import numpy as np

from covnet.core.cholesky import cho_factor, cho_solve
from covnet.core.gaussian import Mat, Vec


def position_matrix(n_axes: int = 2) -> Mat:
    """``H`` picking the position of every axis out of ``[p, v]``-per-axis states."""
    H = np.zeros((n_axes, 2 * n_axes))
    H[np.arange(n_axes), 2 * np.arange(n_axes)] = 1.0
    return H


def correlated_noise(sigma_x: float, sigma_y: float, rho: float) -> Mat:
    """``R = [[σx², ρ σx σy], [ρ σx σy, σy²]]``; positive definite for ``|ρ| < 1``."""
    c = rho * sigma_x * sigma_y
    return np.array([[sigma_x**2, c], [c, sigma_y**2]])


def information_gain(H: Mat, R: Mat) -> Mat:
    """Information a sensor adds per update: ``J = Hᵀ R⁻¹ H`` (Cholesky solve, no inverse).

    Batched over leading axes of ``R`` (and ``H``) when given.
    """
    if R.ndim == 2:
        RinvH = cho_solve(cho_factor(R), H)
        J = H.T @ RinvH
    else:
        # float64 in, float64 out (numpy's stubs promise only some floating type)
        RinvH = cast(Mat, np.linalg.solve(R, np.broadcast_to(H, R.shape[:-1] + H.shape[-1:])))
        J = np.swapaxes(H, -1, -2) @ RinvH
    return 0.5 * (J + np.swapaxes(J, -1, -2))


def measure(H: Mat, R: Mat, x: Vec, rng: np.random.Generator) -> Vec:
    """Draw one measurement ``z = H x + v``, ``v ~ N(0, R)``, from the given generator.

    The noise is ``L e`` with ``L`` the lower Cholesky factor of ``R`` and ``e ~ N(0, I)``,
    so the draw is the same for the same generator state whatever the caller.
    """
    return measure_factored(H, cast(Mat, np.linalg.cholesky(R)), x, rng)


def measure_factored(H: Mat, L: Mat, x: Vec, rng: np.random.Generator) -> Vec:
    """:func:`measure` given ``L``, the lower Cholesky factor of ``R`` (``R = L Lᵀ``): the same
    bits, for a caller that draws from the same ``R`` at every scan and factors it once."""
    return H @ x + L @ rng.standard_normal(L.shape[0])
