"""Problems for the lower-bound tests (`tests/unit/test_lower_bounds.py`,
`tests/unit/test_vertex_bound.py`): heterogeneous position sensors and a reference value."""

from __future__ import annotations

import itertools

import numpy as np

from covnet.core.allocation._fast import spd_inverse
from covnet.core.sensing import correlated_noise, information_gain, position_matrix


def random_problem(rng, N, loose=False):
    """Heterogeneous position sensors (random sigmas and correlations), a random SPD
    ``P_pred`` (loose: large, as the early scans) and ``P_d`` (near the reachable range)."""
    H = position_matrix()
    gains = []
    for _ in range(N):
        sx, sy = rng.uniform(5.0, 60.0, size=2)
        rho = rng.uniform(-0.9, 0.9)
        gains.append(information_gain(H, correlated_noise(sx, sy, rho)))
    A = rng.normal(size=(4, 4))
    scale = np.array([1e3, 30.0, 1e3, 30.0]) if loose else np.array([200.0, 8.0, 200.0, 8.0])
    P_pred = A @ A.T + np.diag(scale)
    B = rng.normal(size=(4, 4)) * 0.3
    P_d = np.diag(rng.uniform(0.3, 1.5, size=4) * np.array([40.0, 2.0, 40.0, 2.0])) + B @ B.T
    return P_pred, np.array(gains), P_d


def subset_value(prob, D):
    """The reference's computed value of the subset ``D`` of ``prob`` (a search ``_Problem``)."""
    J = np.zeros((prob.n, prob.n))
    for j in sorted(D):
        J = J + prob.G[j]
    return float(prob.f(spd_inverse(prob.Y0 + J), prob.D))


def completion_values(prob, inc, und):
    """The reference values of every non-empty completion of a node: the sensors ``inc`` and
    any subset of the undecided ``und``."""
    return [
        subset_value(prob, list(inc) + list(extra))
        for size in range(len(und) + 1)
        for extra in itertools.combinations(und, size)
        if inc or extra
    ]


def relaxation_points(seed, count=300):
    """Sampled ``X`` with ``0 ⪯ X ⪯ I`` (``2 x 2``; the corners ``0`` and ``I``, random
    interior points and rank-one projectors): where a dual bound must stay below the primal
    value ``f(M_lo + V X Vᵀ)`` (weak duality)."""
    rng = np.random.default_rng(seed)
    Xs = [np.zeros((2, 2)), np.eye(2)]
    for _ in range(count):
        Q, _ = np.linalg.qr(rng.normal(size=(2, 2)))
        Xs.append(Q @ np.diag(rng.uniform(0.0, 1.0, size=2) ** 0.3) @ Q.T)
        Xs.append(np.outer(Q[:, 0], Q[:, 0]))
    return Xs
