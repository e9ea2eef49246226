"""Decision problems built to have massive exact ties (issue 29), for tests and benchmarks.

The state is ``[x, vx, y, vy]`` and every sensor measures the position.  ``P_pred`` has no
position-velocity correlation, so no subset changes the velocity block of ``P``: the metric's
velocity term is the same for every subset, and it is made large (a desired velocity variance
``v`` against ``P_pred``'s ``1``; a large ``P_pred`` instead would make the bounds' rounding
allowance, which grows with ``tr P_pred``, wider than the tie tolerance), so the tie tolerance
``tie_rtol · f`` is wide in absolute terms and every subset whose position term is within it
of the best ties ("every subset with a small position error scores the same velocity term").
On top of that the sensors come in a few *types* of bit-identical copies: subsets that use the
same number of each type have the same information, and all of them tie.
"""

from __future__ import annotations

import numpy as np

from covnet.core.gaussian import Mat
from covnet.core.sensing import correlated_noise, information_gain, position_matrix

#: desired velocity variance (``P_pred``'s is 1): the velocity term dominates
VELOCITY_VAR = 1.0e6


def tie_problem(
    n_sensors: int, seed: int, n_types: int = 4, velocity_var: float = VELOCITY_VAR
) -> tuple[Mat, Mat, Mat]:
    """``(P_pred, gains, P_d)``: ``n_sensors`` position sensors in ``n_types`` types of identical
    copies (type ``j % n_types`` for sensor ``j``: the copies interleaved), sigmas drawn in
    ``[0.5, 3]`` m, correlation in ``[-0.5, 0.5]``; ``P_pred`` a random position block of about
    ``(3 m)²`` and unit velocity variance, ``P_d`` a random position block of about ``(1 m)²`` and
    velocity variance ``velocity_var``.  ``n_types >= n_sensors``: every sensor distinct
    (ties only through the tolerance)."""
    if n_sensors < 1 or n_types < 1:
        raise ValueError(f"n_sensors and n_types must be >= 1, got {n_sensors}, {n_types}")
    rng = np.random.default_rng(seed)
    H = position_matrix()
    types = []
    for _ in range(min(n_types, n_sensors)):
        sx, sy = rng.uniform(0.5, 3.0, size=2)
        rho = float(rng.uniform(-0.5, 0.5))
        types.append(information_gain(H, correlated_noise(float(sx), float(sy), rho)))
    gains = np.array([types[j % len(types)] for j in range(n_sensors)])
    pos = [0, 2]
    vel = [1, 3]

    def block(scale: float) -> Mat:
        A = rng.normal(size=(2, 2))
        return scale * (A @ A.T / 2.0 + np.eye(2))

    P_pred = np.zeros((4, 4))
    P_pred[np.ix_(pos, pos)] = block(9.0)
    P_pred[np.ix_(vel, vel)] = np.eye(2)
    P_d = np.zeros((4, 4))
    P_d[np.ix_(pos, pos)] = block(0.3)
    P_d[np.ix_(vel, vel)] = velocity_var * np.eye(2)
    return P_pred, gains, P_d
