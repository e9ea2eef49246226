"""abs_trace's vertex bound (covnet.core.allocation.lower_bounds, diagonal_ascent /
diagonal_bound: the best diag(y), y in the box, by closed-form coordinate steps): the point is
in the dual ball and its value equals the generic phi (oracle: LAPACK eigenvalues), each
coordinate step is the maximum of a fine grid, the bound never exceeds the relaxation's primal
value (weak duality); on random nodes it is below every completion (exhaustive), also as the
barrier's pre-filter; the exact search with it returns the exhaustive search's subset, value
and P bits (N = 8-16, with and without a budget); and the same search with the bound inflated
by 1 % does not, so these tests can fail."""

from __future__ import annotations

import numpy as np
import pytest
from bound_problems import completion_values, random_problem

from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.allocation.lower_bounds import (
    ABS_TRACE_DUAL,
    _DualBound,
    diagonal_ascent,
    diagonal_bound,
)
from covnet.core.allocation.search import allocate_bnb
from covnet.core.allocation.search_problem import _Problem


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
    rng = np.random.default_rng(3)
    Xs = [np.zeros((2, 2)), np.eye(2)]
    for _ in range(300):
        Q, _ = np.linalg.qr(rng.normal(size=(2, 2)))
        Xs.append(Q @ np.diag(rng.uniform(0.0, 1.0, size=2) ** 0.3) @ Q.T)
        Xs.append(np.outer(Q[:, 0], Q[:, 0]))
    primal = np.full(M_lo.shape[0], np.inf)
    for X in Xs:
        M = M_lo + V @ X @ np.swapaxes(V, 1, 2)
        primal = np.minimum(primal, np.abs(np.einsum("mii->mi", M)).sum(axis=1))
    assert np.all(got <= primal + 1e-9 * (1.0 + primal))


def _nodes(n_cases, rng):
    cases = np.random.default_rng(20261204)
    for k in range(n_cases):
        N = int(cases.integers(4, 11))
        P_pred, gains, P_d = random_problem(cases, N, loose=bool(k % 2 == 0))
        prob = _Problem(P_pred, gains, P_d, "abs_trace", Constraints(), 1e-9)
        if prob.dual is None:
            continue
        for _ in range(6):
            yield prob, rng.integers(0, 3, size=prob.m)  # 0 out, 1 in, 2 undecided


def test_the_bound_of_random_nodes_is_below_every_completion():
    rng = np.random.default_rng(11)
    checked = raised = 0
    for prob, state in _nodes(12, rng):
        inc = [prob.free[i] for i in np.flatnonzero(state == 1)]
        und = [prob.free[i] for i in np.flatnonzero(state == 2)]
        Z_lo = prob.base + prob.S[state == 1].sum(axis=0)
        Z_hi = Z_lo + prob.S[state == 2].sum(axis=0)
        assert prob.dual is not None
        vb = float(prob.dual.vertex_bound(Z_lo[None], Z_hi[None])[0])
        lb = float(prob.combine(prob.summary(Z_hi[None]), prob.summary(Z_lo[None]))[0])
        values = completion_values(prob, inc, und)
        if values:
            assert vb <= min(values), (vb, min(values))
            checked += 1
            raised += vb > lb
            for tau in (0.0, 0.5 * vb, vb, min(values), np.inf):
                got = float(prob.dual.bound(Z_lo[None], Z_hi[None], tau)[0])
                assert got <= min(values), (tau, got, min(values))
                if tau < vb:
                    assert got == vb  # pruned by the pre-filter, the barrier not run
    assert checked >= 40
    assert raised >= 5  # it adds something to the interval bound


def _problems():
    rng = np.random.default_rng(4)
    for k in range(6):
        N = (8, 10, 12, 14, 16, 12)[k]
        yield random_problem(rng, N, loose=bool(k % 2))


def test_exact_search_with_the_diagonal_bound_equals_the_exhaustive_one():
    """Every node of these searches (N <= 16 < DUAL_MIN_REST undecided) gets the vertex
    bound, none the barrier."""
    for P_pred, gains, P_d in _problems():
        for c in (Constraints(), Constraints(max_active=3)):
            ref = allocate_exhaustive(P_pred, gains, P_d, "abs_trace", c)
            got = allocate_bnb(P_pred, gains, P_d, "abs_trace", c)
            assert got.exact and got.subset == ref.subset
            assert got.value == ref.value
            assert got.P.tobytes() == ref.P.tobytes()


def test_an_inflated_diagonal_bound_is_caught(monkeypatch):
    """The same check with the vertex bound raised by 1 %: some search prunes the optimum."""
    plain = _DualBound.vertex_bound

    def inflated(self, Z_lo, Z_hi):
        return plain(self, Z_lo, Z_hi) * 1.01

    monkeypatch.setattr(_DualBound, "vertex_bound", inflated)
    wrong = 0
    for P_pred, gains, P_d in _problems():
        for c in (Constraints(), Constraints(max_active=3)):
            ref = allocate_exhaustive(P_pred, gains, P_d, "abs_trace", c)
            got = allocate_bnb(P_pred, gains, P_d, "abs_trace", c)
            wrong += got.subset != ref.subset or got.value != ref.value
    assert wrong >= 1


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
