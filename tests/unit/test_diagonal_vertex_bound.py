"""abs_trace's vertex bound (covnet.core.allocation.lower_bounds, diagonal_ascent /
diagonal_bound: the best diag(y), y in the box, by closed-form coordinate steps): the point is
in the dual ball and its value equals the generic phi (oracle: LAPACK eigenvalues), each
coordinate step is the maximum of a fine grid, the bound never exceeds the relaxation's primal
value (weak duality); on random nodes it is below every completion (exhaustive), also as the
barrier's pre-filter; the exact search with it returns the exhaustive search's subset, value
and P bits (N = 8-16, with and without a budget); and the same search with the bound inflated
by 1 % does not, so these tests can fail."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from bound_problems import random_problem, relaxation_points

from covnet.core.allocation.exact import allocate_exhaustive
from covnet.core.allocation.lower_bounds import (
    ABS_TRACE_DUAL,
    diagonal_ascent,
    diagonal_bound,
)
from covnet.core.allocation.search import allocate_bnb
from covnet.core.metrics import METRICS


def _node_arrays(n, m, seed):
    """Random symmetric ``M_lo`` ``(m, n, n)`` and ``V`` ``(m, n, 2)`` with the closed form's
    edge cases: ``V = 0``, rank-one ``V``, a zero row of ``V``, zero diagonal entries, and
    diagonals small against ``|v_i|²`` (the fractional steps)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, n, n))
    M_lo = A + np.swapaxes(A, 1, 2)
    V = rng.normal(size=(m, n, 2)) * rng.choice([0.1, 1.0, 3.0], size=(m, 1, 1))
    V[0] = 0.0
    V[1, :, 1] = 0.0
    V[2, 0, :] = 0.0
    M_lo[3, np.arange(n), np.arange(n)] = 0.0
    M_lo[4:, np.arange(n), np.arange(n)] *= 0.1  # most steps inside the box
    return M_lo, V


def _generic_phi(y, M_lo, V):
    """``<diag(y), M_lo> + (sum of the negative eigenvalues of Vᵀ diag(y) V)`` by LAPACK."""
    G = np.einsum("mia,mi,mib->mab", V, y, V)
    w = np.linalg.eigvalsh(G)
    return np.einsum("mi,mii->m", y, M_lo) + np.minimum(w, 0.0).sum(axis=1)


def test_abs_trace_has_the_diagonal_vertex_bound():
    assert ABS_TRACE_DUAL.vertices is diagonal_bound


@pytest.mark.parametrize("n", [1, 3, 4])
@pytest.mark.parametrize("sweeps", [0, 1, 2, 5])
def test_the_point_is_in_the_box_and_its_value_is_phi(n, sweeps):
    M_lo, V = _node_arrays(n, 60, 10 * n + sweeps)
    y, phi = diagonal_ascent(M_lo, V, sweeps)
    assert np.all(np.abs(y) <= 1.0)  # diag(y) in the hull of the atoms diag(s)
    np.testing.assert_allclose(phi, _generic_phi(y, M_lo, V), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(diagonal_bound(M_lo, V), diagonal_ascent(M_lo, V)[1])
    if sweeps == 0:  # the signs of the diagonal at the middle
        mid = np.einsum("mii->mi", M_lo) + 0.5 * (V * V).sum(axis=2)
        np.testing.assert_array_equal(y, np.where(mid < 0.0, -1.0, 1.0))


@pytest.mark.parametrize("sweeps", [1, 2, 3])
def test_each_coordinate_step_is_the_maximum_of_a_fine_grid(sweeps):
    """After a sweep the last coordinate maximises ``φ`` with the others fixed (oracle: 20 001
    points on ``[-1, 1]``, LAPACK), and no sweep lowers ``φ``; also a lone first-coordinate step
    (one sweep of ``n = 1``)."""
    n = 4
    M_lo, V = _node_arrays(n, 40, 70 + sweeps)
    y, phi = diagonal_ascent(M_lo, V, sweeps)
    _, before = diagonal_ascent(M_lo, V, sweeps - 1)
    assert np.all(phi >= before - 1e-12 * (1.0 + np.abs(phi)))
    t = np.linspace(-1.0, 1.0, 20001)
    fractional = 0
    for k in range(M_lo.shape[0]):
        Y = np.repeat(y[k][None], t.size, axis=0)
        Y[:, n - 1] = t
        grid = _generic_phi(
            Y, np.broadcast_to(M_lo[k], (t.size, n, n)), np.broadcast_to(V[k], (t.size, n, 2))
        )
        assert phi[k] >= grid.max() - 1e-9 * (1.0 + abs(grid.max())), k
        fractional += abs(y[k, n - 1]) < 1.0 - 1e-9
    assert fractional >= 5  # the interior (closed-form) case is exercised


@pytest.mark.parametrize("n", [2, 4])
def test_the_bound_is_below_the_primal_value_and_above_the_signs(n):
    """Weak duality: below ``Σ_i |(M_lo + V X Vᵀ)_ii|`` at every sampled ``0 ⪯ X ⪯ I`` (corners
    and rank-one projectors included); at least the signs' value, raised on many nodes."""
    M_lo, V = _node_arrays(n, 60, 5 + n)
    got = diagonal_bound(M_lo, V)
    signs = diagonal_ascent(M_lo, V, 0)[1]
    assert np.all(got >= signs - 1e-12 * (1.0 + np.abs(signs)))
    assert np.mean(got > signs + 1e-9) > 0.3
    primal = np.full(M_lo.shape[0], np.inf)
    for X in relaxation_points(3):
        M = M_lo + V @ X @ np.swapaxes(V, 1, 2)
        primal = np.minimum(primal, np.abs(np.einsum("mii->mi", M)).sum(axis=1))
    assert np.all(got <= primal + 1e-9 * (1.0 + primal))


@pytest.mark.parametrize("n", [2, 3, 4])
def test_interior_steps_on_both_sides_of_the_regimes_are_grid_maxima(n):
    """Diagonals ``β_i = -u |v_i|²``, ``u ∈ (0, 1)``: every step takes the closed form (neither
    ``t = ±1`` case), with the rest ``G_0`` of either sign (``r < 0``: the optimum may sit where
    ``λmax`` crosses 0; ``r > 0``: where ``λmin`` does).  The last coordinate after one sweep
    against a 20 001-point grid."""
    rng = np.random.default_rng(40 + n)
    m = 300
    V = rng.normal(size=(m, n, 2))
    M_lo = np.zeros((m, n, n))
    u = rng.uniform(0.0, 1.0, size=(m, n)) ** rng.choice([0.2, 1.0, 5.0], size=(m, 1))
    M_lo[:, np.arange(n), np.arange(n)] = -u * (V * V).sum(axis=2)
    y, phi = diagonal_ascent(M_lo, V, 1)
    t = np.linspace(-1.0, 1.0, 20001)
    for k in range(m):
        Y = np.repeat(y[k][None], t.size, axis=0)
        Y[:, n - 1] = t
        Mk = np.broadcast_to(M_lo[k], (t.size, n, n))
        grid = _generic_phi(Y, Mk, np.broadcast_to(V[k], (t.size, n, 2)))
        assert phi[k] >= grid.max() - 1e-9 * (1.0 + abs(grid.max())), k


def test_the_vertex_bound_starts_at_the_metrics_vertex_min_rest():
    """The search reads the metric's ``DualNorm.vertex_min_rest`` (abs_trace: 8): the vertex
    bound on more nodes (a lower threshold) prunes at least as much, with the same result."""
    assert ABS_TRACE_DUAL.vertex_min_rest == 8
    rng = np.random.default_rng(9)
    fewer = 0
    for k in range(3):
        P_pred, gains, P_d = random_problem(rng, 14, loose=bool(k % 2))
        ref = allocate_exhaustive(P_pred, gains, P_d, "abs_trace")
        nodes = []
        for rest in (1, 8, 100):
            dual = dataclasses.replace(ABS_TRACE_DUAL, vertex_min_rest=rest)
            metric = dataclasses.replace(METRICS["abs_trace"], dual_bound=dual)
            got = allocate_bnb(P_pred, gains, P_d, metric)
            assert got.exact and got.subset == ref.subset and got.value == ref.value
            nodes.append(got.n_nodes)
        assert nodes[0] <= nodes[1] <= nodes[2], nodes
        fewer += nodes[0] < nodes[2]
    assert fewer >= 1
