"""The dual bound's vertex bound (covnet.core.allocation.lower_bounds, one_norm / inf_norm, the
exact search's bound on the nodes its barrier does not refine): its dual points attain the
column sums (oracle: the formula) and are atoms of the dual ball; on random nodes it is below
every completion's computed value (exhaustive over the completions) and raises the interval
bound; the exact search with it returns the exhaustive search's subset, value and P bits
(N = 8-16); and the same search with the bound deliberately inflated by 1 % does not, so these
tests can fail."""

from __future__ import annotations

import numpy as np
import pytest
from bound_problems import completion_values, random_problem

from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.allocation.lower_bounds import (
    INF_NORM_DUAL,
    ONE_NORM_DUAL,
    _DualBound,
    column_atoms,
    column_vertices,
)
from covnet.core.allocation.search import allocate_bnb
from covnet.core.allocation.search_problem import _Problem

NAMES = ("one_norm", "inf_norm")


def test_the_vertex_points_are_registered_for_the_induced_norms_only():
    from covnet.core.allocation.lower_bounds import ABS_TRACE_DUAL, SPECTRAL_DUAL

    assert ONE_NORM_DUAL.vertices is column_vertices
    assert INF_NORM_DUAL.vertices is column_vertices
    assert SPECTRAL_DUAL.vertices is None and ABS_TRACE_DUAL.vertices is None


@pytest.mark.parametrize("n", [1, 3, 4])
def test_column_vertices_attain_the_column_sums_and_are_atoms(n):
    rng = np.random.default_rng(n)
    A = rng.normal(size=(30, n, n))
    M = A + np.swapaxes(A, 1, 2)
    M[0, :, 0] = 0.0  # a zero column (and row): sign +1
    M[0, 0, :] = 0.0
    atoms = column_atoms(n)
    sym = 0.5 * (atoms + np.swapaxes(atoms, 1, 2))
    for j, Y in enumerate(column_vertices(M)):
        got = np.einsum("mij,mij->m", Y, M)
        np.testing.assert_allclose(got, np.abs(M[:, :, j]).sum(axis=1), rtol=1e-12, atol=1e-12)
        for row in Y:  # each row is a symmetrised atom: in the dual ball
            assert np.any(np.all(sym == row, axis=(1, 2)))


def _nodes(name, n_cases, rng):
    cases = np.random.default_rng(20261204)
    for k in range(n_cases):
        N = int(cases.integers(4, 11))
        P_pred, gains, P_d = random_problem(cases, N, loose=bool(k % 2 == 0))
        prob = _Problem(P_pred, gains, P_d, name, Constraints(), 1e-9)
        assert prob.dual is not None
        for _ in range(6):
            state = rng.integers(0, 3, size=prob.m)  # 0 out, 1 in, 2 undecided
            yield prob, state


@pytest.mark.parametrize("name", NAMES)
def test_vertex_bound_of_random_nodes_is_below_every_completion(name):
    rng = np.random.default_rng(11)
    checked = raised = 0
    for prob, state in _nodes(name, 10, rng):
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


def _problems():
    rng = np.random.default_rng(4)
    for k in range(6):
        N = (8, 10, 12, 14, 16, 12)[k]
        yield random_problem(rng, N, loose=bool(k % 2))


@pytest.mark.parametrize("name", NAMES)
def test_exact_search_with_the_vertex_bound_equals_the_exhaustive_one(name):
    """Every node of these searches (N <= 16 < DUAL_MIN_REST undecided) gets the vertex
    bound, none the barrier."""
    for P_pred, gains, P_d in _problems():
        for c in (Constraints(), Constraints(max_active=3)):
            ref = allocate_exhaustive(P_pred, gains, P_d, name, c)
            got = allocate_bnb(P_pred, gains, P_d, name, c)
            assert got.exact and got.subset == ref.subset
            assert got.value == ref.value
            assert got.P.tobytes() == ref.P.tobytes()


def test_an_inflated_vertex_bound_is_caught(monkeypatch):
    """The same check with the vertex bound raised by 1 %: some search prunes the optimum."""
    plain = _DualBound.vertex_bound

    def inflated(self, Z_lo, Z_hi):
        return plain(self, Z_lo, Z_hi) * 1.01

    monkeypatch.setattr(_DualBound, "vertex_bound", inflated)
    wrong = 0
    for P_pred, gains, P_d in _problems():
        ref = allocate_exhaustive(P_pred, gains, P_d, "one_norm")
        got = allocate_bnb(P_pred, gains, P_d, "one_norm")
        wrong += got.subset != ref.subset or got.value != ref.value
    assert wrong >= 1
