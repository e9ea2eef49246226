"""The dual bound's vertex bound (covnet.core.allocation.lower_bounds, one_norm / inf_norm, the
exact search's bound on the nodes its barrier does not refine): its column points are in the
dual ball and their closed form equals the generic phi (oracle: phi of the matrix), each
coordinate step is the exact maximum (oracle: a fine grid), the bound never exceeds the
relaxation's primal value (weak duality) nor the signs' bound it starts from; on random nodes
it is below every completion's computed value (exhaustive over the completions) and raises the
interval bound, also as the barrier's pre-filter; the exact search with it returns the
exhaustive search's subset, value and P bits (N = 8-16); and the same search with the bound
deliberately inflated by 1 % does not, so these tests can fail."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from bound_problems import completion_values, random_problem, relaxation_points

from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.allocation.lower_bounds import (
    INF_NORM_DUAL,
    ONE_NORM_DUAL,
    DualNorm,
    _DualBound,
    column_ascent,
    column_bound,
)
from covnet.core.allocation.search import allocate_bnb
from covnet.core.allocation.search_problem import _Problem
from covnet.core.metrics import METRICS, capability

NAMES = ("one_norm", "inf_norm")
#: the metrics whose exact search takes a vertex bound (abs_trace's diagonal points:
#: tests/unit/test_diagonal_vertex_bound.py)
SEARCHED = (*NAMES, "abs_trace")


def test_the_vertex_points_are_registered_for_the_norms_with_closed_forms():
    from covnet.core.allocation.lower_bounds import (
        ABS_TRACE_DUAL,
        SPECTRAL_DUAL,
        diagonal_bound,
    )

    assert ONE_NORM_DUAL.vertices is column_bound
    assert INF_NORM_DUAL.vertices is column_bound
    assert ABS_TRACE_DUAL.vertices is diagonal_bound  # tests/unit/test_diagonal_vertex_bound.py
    assert SPECTRAL_DUAL.vertices is None


def _node_arrays(n, m, seed):
    """Random symmetric ``M_lo`` ``(m, n, n)`` and ``V`` ``(m, n, 2)``, some columns of ``V``
    zero, some entries of ``M_lo`` zero (the closed form's edge cases)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(m, n, n))
    M_lo = A + np.swapaxes(A, 1, 2)
    V = rng.normal(size=(m, n, 2)) * rng.choice([0.1, 1.0, 3.0], size=(m, 1, 1))
    V[0] = 0.0
    V[1, :, 1] = 0.0  # rank one
    M_lo[2, :, 0] = 0.0
    M_lo[2, 0, :] = 0.0
    return M_lo, V


def _sym_points(y):
    m, n = y.shape[0], y.shape[1]
    out = []
    for j in range(n):
        Y = np.zeros((m, n, n))
        Y[:, :, j] = y[:, j, :]
        out.append(0.5 * (Y + np.swapaxes(Y, 1, 2)))
    return out


def _generic_phi(Y, M_lo, V):
    """``<Y, M_lo> + (sum of the negative eigenvalues of Vᵀ Y V)`` by LAPACK (the oracle)."""
    G = np.einsum("mia,mij,mjb->mab", V, Y, V)
    w = np.linalg.eigvalsh(0.5 * (G + np.swapaxes(G, 1, 2)))
    return np.einsum("mij,mij->m", Y, M_lo) + np.minimum(w, 0.0).sum(axis=1)


@pytest.mark.parametrize("n", [1, 3, 4])
@pytest.mark.parametrize("sweeps", [0, 1, 2, 5])
def test_column_points_are_in_the_ball_and_their_closed_form_is_phi(n, sweeps):
    M_lo, V = _node_arrays(n, 40, 100 * n + sweeps)
    y, h = column_ascent(M_lo, V, sweeps)
    assert np.all(np.abs(y) <= 1.0)  # y e_jᵀ in the convex hull of the atoms s e_jᵀ
    for j, Y in enumerate(_sym_points(y)):
        np.testing.assert_allclose(h[:, j], _generic_phi(Y, M_lo, V), rtol=1e-10, atol=1e-10)
    if sweeps == 0:  # the signs at the middle: the column sums there less the spread term
        b = np.swapaxes(M_lo + 0.5 * V @ np.swapaxes(V, 1, 2), 1, 2)
        np.testing.assert_array_equal(y, np.where(b < 0.0, -1.0, 1.0))


@pytest.mark.parametrize("sweeps", [1, 2, 3])
def test_the_last_coordinate_step_is_the_exact_maximum(sweeps):
    """After a sweep the last coordinate maximises ``h_j`` with the others fixed (oracle: a
    grid of 20 001 points on ``[-1, 1]``); and no sweep lowers ``h`` (each step an exact
    maximum)."""
    n = 4
    M_lo, V = _node_arrays(n, 25, 7 + sweeps)
    y, h = column_ascent(M_lo, V, sweeps)
    _, h_before = column_ascent(M_lo, V, sweeps - 1)
    assert np.all(h >= h_before - 1e-12 * (1.0 + np.abs(h)))
    t = np.linspace(-1.0, 1.0, 20001)
    b = np.swapaxes(M_lo + 0.5 * V @ np.swapaxes(V, 1, 2), 1, 2)
    rho = 0.5 * np.sqrt((V * V).sum(axis=2))
    for k in range(M_lo.shape[0]):
        for j in range(n):
            Y = np.repeat(y[k, j][None], t.size, axis=0)
            Y[:, n - 1] = t
            a = Y @ V[k]
            grid = Y @ b[k, j] - rho[k, j] * np.sqrt((a * a).sum(axis=1))
            assert h[k, j] >= grid.max() - 1e-9 * (1.0 + abs(grid.max()))


@pytest.mark.parametrize("n", [2, 4])
def test_column_bound_is_between_the_signs_and_the_primal_value(n):
    """Weak duality: below ``||M_lo + V X Vᵀ||_1`` at every ``X`` with ``0 ⪯ X ⪯ I`` (sampled,
    the corners included) so a wrong mixture formula that overshoots fails; and at least the
    signs' bound it starts from, raised on many nodes."""
    M_lo, V = _node_arrays(n, 60, 31 + n)
    got = column_bound(M_lo, V)
    signs = column_ascent(M_lo, V, 0)[1].max(axis=1)
    assert np.all(got >= signs - 1e-12 * (1.0 + np.abs(signs)))
    assert np.mean(got > signs + 1e-9) > 0.3
    primal = np.full(M_lo.shape[0], np.inf)
    for X in relaxation_points(5):
        M = M_lo + V @ X @ np.swapaxes(V, 1, 2)
        primal = np.minimum(primal, np.abs(M).sum(axis=1).max(axis=1))
    assert np.all(got <= primal + 1e-9 * (1.0 + primal))
    # and the mixture lifts the best single column on some nodes
    assert np.any(got > column_bound(M_lo, V, steps=0) + 1e-9)


def _nodes(name, n_cases, rng):
    cases = np.random.default_rng(20261204)
    for k in range(n_cases):
        N = int(cases.integers(4, 11))
        P_pred, gains, P_d = random_problem(cases, N, loose=bool(k % 2 == 0))
        prob = _Problem(P_pred, gains, P_d, name, Constraints(), 1e-9)
        if prob.dual is None:  # no dual bound on this problem (the counts below then fall)
            continue
        for _ in range(6):
            state = rng.integers(0, 3, size=prob.m)  # 0 out, 1 in, 2 undecided
            yield prob, state


@pytest.mark.parametrize("name", SEARCHED)
def test_vertex_bound_of_random_nodes_is_below_every_completion(name):
    rng = np.random.default_rng(11)
    checked = raised = 0
    for prob, state in _nodes(name, 12, rng):
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
    assert checked >= 40
    assert raised >= 5  # it adds something to the interval bound


@pytest.mark.parametrize("name", SEARCHED)
def test_the_barrier_with_the_vertex_prefilter_is_below_every_completion(name):
    """``_DualBound.bound`` with a finite threshold takes the vertex bound first (the barrier
    only on the rows it leaves): still below every completion, whatever the threshold."""
    rng = np.random.default_rng(12)
    checked = 0
    for prob, state in _nodes(name, 6, rng):
        inc = [prob.free[i] for i in np.flatnonzero(state == 1)]
        und = [prob.free[i] for i in np.flatnonzero(state == 2)]
        Z_lo = prob.base + prob.S[state == 1].sum(axis=0)
        Z_hi = Z_lo + prob.S[state == 2].sum(axis=0)
        values = completion_values(prob, inc, und)
        if not values:
            continue
        assert prob.dual is not None
        vb = float(prob.dual.vertex_bound(Z_lo[None], Z_hi[None])[0])
        for tau in (0.0, 0.5 * vb, vb, min(values), np.inf):
            got = float(prob.dual.bound(Z_lo[None], Z_hi[None], tau)[0])
            assert got <= min(values), (tau, got, min(values))
            if tau < vb:
                assert got == vb  # pruned by the pre-filter, the barrier not run
        checked += 1
    assert checked >= 20


def _problems():
    rng = np.random.default_rng(4)
    for k in range(6):
        N = (8, 10, 12, 14, 16, 12)[k]
        yield random_problem(rng, N, loose=bool(k % 2))


def _every_node(name):
    """The metric's entry with its vertex bound on every node (``vertex_min_rest = 1``;
    abs_trace's own is 8, which leaves the small problems here mostly without it)."""
    entry = METRICS[name]
    dual = capability(entry.dual_bound, DualNorm)
    assert dual is not None
    return dataclasses.replace(entry, dual_bound=dataclasses.replace(dual, vertex_min_rest=1))


@pytest.mark.parametrize("name", SEARCHED)
def test_exact_search_with_the_vertex_bound_equals_the_exhaustive_one(name):
    """Every node of these searches (N <= 16 < DUAL_MIN_REST undecided) gets the vertex
    bound, none the barrier."""
    for P_pred, gains, P_d in _problems():
        for c in (Constraints(), Constraints(max_active=3)):
            ref = allocate_exhaustive(P_pred, gains, P_d, name, c)
            got = allocate_bnb(P_pred, gains, P_d, _every_node(name), c)
            assert got.exact and got.subset == ref.subset
            assert got.value == ref.value
            assert got.P.tobytes() == ref.P.tobytes()


@pytest.mark.parametrize("name", ["one_norm", "abs_trace"])
def test_an_inflated_vertex_bound_is_caught(name, monkeypatch):
    """The same check with the vertex bound raised by 1 %: some search prunes the optimum."""
    plain = _DualBound.vertex_bound

    def inflated(self, Z_lo, Z_hi):
        return plain(self, Z_lo, Z_hi) * 1.01

    monkeypatch.setattr(_DualBound, "vertex_bound", inflated)
    wrong = 0
    for P_pred, gains, P_d in _problems():
        for c in (Constraints(), Constraints(max_active=3)):
            ref = allocate_exhaustive(P_pred, gains, P_d, name, c)
            got = allocate_bnb(P_pred, gains, P_d, _every_node(name), c)
            wrong += got.subset != ref.subset or got.value != ref.value
    assert wrong >= 1
