"""Target motion models: transition ``F(T)`` and process noise ``Q(T)`` builders.

State ordering is per axis, position then velocity: ``[x, vx, y, vy]`` in 2-D.
"""

from __future__ import annotations

import numpy as np

from covnet.core.gaussian import Mat


def cv_transition(T: float, n_axes: int = 2) -> Mat:
    """Constant-velocity transition for ``n_axes`` independent axes, state ``[p, v]`` per axis.

    ``F = blockdiag([[1, T], [0, 1]], ...)``.
    """
    block = np.array([[1.0, T], [0.0, 1.0]])
    return np.kron(np.eye(n_axes), block)


def dwna_noise_gain(T: float, n_axes: int = 2) -> Mat:
    """Noise gain of the discrete white-noise-acceleration model, ``G = blockdiag([T²/2, T]ᵀ)``.

    The acceleration ``w(k)`` is constant over one period, so ``x(k+1) = F x(k) + G w(k)``.
    """
    g = np.array([[0.5 * T * T], [T]])
    return np.kron(np.eye(n_axes), g)


def dwna_process_noise(T: float, sigma_a: float, n_axes: int = 2) -> Mat:
    """Discrete white-noise-acceleration process noise ``G Q_w Gᵀ`` with ``Q_w = σ_a² I``.

    Per axis: ``σ_a² [[T⁴/4, T³/2], [T³/2, T²]]`` (Bar-Shalom, Li & Kirubarajan, §6.3.3).
    """
    G = dwna_noise_gain(T, n_axes)
    return sigma_a**2 * (G @ G.T)
