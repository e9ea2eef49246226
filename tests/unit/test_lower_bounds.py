"""The dual lower bounds of the norm metrics (covnet.core.allocation.lower_bounds): the atoms
reproduce the norms (oracle: the formula), every bound a search certifies is below the
exhaustive optimum on seeded random problems (every metric, N <= 12), the dual bound of random
nodes is below every completion's value, and it is as tight as the relaxation it certifies."""

from __future__ import annotations

import numpy as np
import pytest
from bound_problems import completion_values, random_problem

from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.allocation.lower_bounds import (
    ABS_TRACE_DUAL,
    INF_NORM_DUAL,
    ONE_NORM_DUAL,
    SPECTRAL_DUAL,
    column_atoms,
    diagonal_atoms,
)
from covnet.core.allocation.search import allocate_bnb, allocate_greedy
from covnet.core.allocation.search_problem import _Problem
from covnet.core.metrics import METRICS, capability

DUAL = ("abs_trace", "inf_norm", "one_norm", "spectral")


def test_the_registry_names_the_dual_bounds():
    from covnet.core.allocation.lower_bounds import DualNorm

    got = {k for k, m in METRICS.items() if capability(m.dual_bound, DualNorm) is not None}
    assert got == set(DUAL)
    assert capability(METRICS["spectral"].dual_bound, DualNorm) is SPECTRAL_DUAL
    assert {capability(METRICS[k].dual_bound, DualNorm) for k in ("one_norm", "inf_norm")} == {
        ONE_NORM_DUAL,
        INF_NORM_DUAL,
    }
    assert capability(METRICS["abs_trace"].dual_bound, DualNorm) is ABS_TRACE_DUAL


@pytest.mark.parametrize("n", [1, 2, 4])
def test_atoms_are_the_norms_support(n):
    """``max_a <Y_a, M>`` over the atoms is the norm (the formula), for symmetric ``M``."""
    rng = np.random.default_rng(n)
    for _ in range(20):
        A = rng.normal(size=(n, n))
        M = A + A.T
        cols = column_atoms(n)
        assert max(float((Y * M).sum()) for Y in cols) == pytest.approx(
            np.abs(M).sum(axis=0).max(), rel=1e-12
        )
        diag = diagonal_atoms(n)
        assert max(float((Y * M).sum()) for Y in diag) == pytest.approx(
            np.abs(np.diag(M)).sum(), rel=1e-12
        )


def _cases(n_cases):
    rng = np.random.default_rng(20260329)
    for k in range(n_cases):
        N = int(rng.integers(3, 13))
        yield (*random_problem(rng, N, loose=bool(k % 3 == 0)), k)


@pytest.mark.parametrize("name", sorted(METRICS))
def test_certified_bounds_never_exceed_the_exhaustive_optimum(name):
    """On seeded random problems (N = 3-12, every metric): the root bound, the bounded
    search's and greedy's certified lower bounds are <= the exhaustive optimum, and the
    bounded search's value is within its certified gap of it."""
    for P_pred, gains, P_d, k in _cases(12):
        ref = allocate_exhaustive(P_pred, gains, P_d, name)
        prob = _Problem(P_pred, gains, P_d, name, Constraints(), 1e-9)
        assert prob.root_bound() <= ref.value, k
        for res in (
            allocate_bnb(P_pred, gains, P_d, name, rel_gap=0.05),
            allocate_bnb(P_pred, gains, P_d, name, node_limit=3),
            allocate_greedy(P_pred, gains, P_d, name),
        ):
            assert res.lower_bound <= ref.value, (k, res.lower_bound, ref.value)
            assert res.value >= ref.value - 1e-9 * abs(ref.value)


@pytest.mark.parametrize("name", DUAL)
def test_dual_bound_of_random_nodes_is_below_every_completion(name):
    """White box: for random nodes (included / undecided / excluded at random) the dual bound
    run to its last iteration (no threshold) is <= the computed value of every completion, and
    at least the interval bound wherever the latter is not already 0 by more than rounding."""
    rng = np.random.default_rng(7)
    checked = 0
    for P_pred, gains, P_d, _ in _cases(10):
        prob = _Problem(P_pred, gains, P_d, name, Constraints(), 1e-9)
        assert prob.dual is not None
        for _ in range(6):
            state = rng.integers(0, 3, size=prob.m)  # 0 out, 1 in, 2 undecided
            inc = [prob.free[i] for i in np.flatnonzero(state == 1)]
            und = [prob.free[i] for i in np.flatnonzero(state == 2)]
            Z_lo = prob.base + prob.S[state == 1].sum(axis=0)
            Z_hi = Z_lo + prob.S[state == 2].sum(axis=0)
            lb = float(prob.dual.bound(Z_lo[None], Z_hi[None])[0])
            values = completion_values(prob, inc, und)
            if values:
                assert lb <= min(values), (lb, min(values))
                checked += 1
    assert checked >= 30


@pytest.mark.parametrize("name", ["spectral", "one_norm"])
def test_dual_bound_reaches_the_relaxation_minimum(name):
    """Tightness (the point of the bound): at the root of a 40-sensor problem the certificate
    is within 1e-4 of the relaxation's primal value (the norm at the barrier's last ``X``),
    recovered here by a dense search over ``X`` (its minimum is at most that)."""
    rng = np.random.default_rng(3)
    P_pred, gains, P_d = random_problem(rng, 40)
    prob = _Problem(P_pred, gains, P_d, name, Constraints(), 1e-9)
    assert prob.dual is not None
    Z0 = prob.base[None]
    Z1 = Z0 + prob.suffix[0]
    lb = float(prob.dual.bound(Z0, Z1)[0])
    M_lo, V = prob.dual._setup(Z0, Z1)
    best = np.inf
    f = METRICS[name].fn
    for th in np.linspace(0.0, np.pi, 61):
        u = np.array([np.cos(th), np.sin(th)])
        for a in np.linspace(0.0, 1.0, 21):
            for b in np.linspace(0.0, 1.0, 21):
                X = a * np.outer(u, u) + b * (np.eye(2) - np.outer(u, u))
                M = M_lo[0] + V[0] @ X @ V[0].T
                best = min(best, float(f(M + P_d, P_d)))
    assert lb <= best * (1 + 1e-9)
    assert lb >= best * (1 - 5e-3), (lb, best)
