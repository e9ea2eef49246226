"""The search's diagonal-only summaries (abs_trace, trace_diff: ``IntervalBound.from_diagonal``,
``_Problem.diagonals``): the same bits as the diagonal of the full covariances and as the
summary of those, in every reduced form (``r = 0``, ``1``, ``2``, the full form); the exact
search with them equals the exhaustive search (subset, value, ``P`` bits); and a diagonal path
that is off by one ulp-scale step is caught by the equality checks here."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.allocation import search as S
from covnet.core.allocation import search_problem as SP
from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.allocation.interval_bounds import (
    ABS_TRACE_BOUND,
    TRACE_DIFF_BOUND,
    IntervalBound,
)
from covnet.core.metrics import METRICS, capability

NAMES = ["abs_trace", "trace_diff"]


def _spd(rng, n, scale=1.0):
    A = rng.standard_normal((n, n))
    return scale * (A @ A.T + 0.5 * np.eye(n))


def _gains(rng, N, n, support):
    """``N`` PSD gains on the state components ``support`` (the reduced form's ``r``)."""
    G = np.zeros((N, n, n))
    k = len(support)
    for j in range(N):
        H = rng.standard_normal((1 + j % 2, k))
        G[j][np.ix_(support, support)] = H.T @ H * rng.uniform(0.1, 2.0)
    return G


def _problem(seed, support, N=10, n=4):
    rng = np.random.default_rng(seed)
    P = _spd(rng, n, 3.0)
    D = _spd(rng, n, 0.5)
    return P, _gains(rng, N, n, support), D


SUPPORTS = [[], [0], [0, 2], [0, 1, 2, 3]]


@pytest.mark.parametrize("support", SUPPORTS)
@pytest.mark.parametrize("name", NAMES)
def test_diagonals_and_summaries_are_the_full_ones_bit_for_bit(name, support):
    for seed in range(4):
        P, G, D = _problem(seed, support)
        prob = SP._Problem(P, G, D, name, Constraints(), 1e-9)
        rng = np.random.default_rng(100 + seed)
        for m in (1, 3, 8, 257):
            pick = rng.random((m, prob.m)) < 0.5
            Z = prob.base + pick.astype(float) @ prob.S
            X = prob.covariances(Z)
            d = prob.diagonals(Z)
            np.testing.assert_array_equal(d, np.diagonal(X, axis1=1, axis2=2))
            bound = prob.bound
            assert bound is not None and bound.from_diagonal is not None
            np.testing.assert_array_equal(prob.summary(Z), bound.summary(X, prob.dc))


def test_only_the_diagonal_metrics_take_the_diagonal_path():
    assert ABS_TRACE_BOUND.from_diagonal is not None
    assert TRACE_DIFF_BOUND.from_diagonal is not None
    bounds = {k: capability(m.interval_bound, IntervalBound) for k, m in METRICS.items()}
    assert bounds["abs_trace"] is ABS_TRACE_BOUND and bounds["trace_diff"] is TRACE_DIFF_BOUND
    others = [b for k, b in bounds.items() if k not in NAMES and b is not None]
    assert others and all(b.from_diagonal is None for b in others)


@pytest.mark.parametrize("name", NAMES)
def test_exact_search_equals_exhaustive_with_the_diagonal_path(name):
    for seed in range(6):
        for support in ([0, 2], [0, 1, 2, 3]):
            P, G, D = _problem(seed, support, N=12)
            for c in (Constraints(), Constraints(frozenset({3}), frozenset({1}), 5)):
                ref = allocate_exhaustive(P, G, D, name, c)
                got = S.allocate_bnb(P, G, D, name, c)
                assert got.status == 0
                assert (got.subset, got.value) == (ref.subset, ref.value)
                np.testing.assert_array_equal(got.P, ref.P)


def test_a_diagonal_path_off_by_a_rounding_step_is_caught(monkeypatch):
    """The equality check above must be able to fail: a diagonal computed one rounding step
    differently (its last term added in another order) differs in some bits."""
    P, G, D = _problem(0, [0, 2])
    prob = SP._Problem(P, G, D, "abs_trace", Constraints(), 1e-9)
    Z = prob.base + (np.random.default_rng(1).random((257, prob.m)) < 0.5) @ prob.S

    def skewed(self, Z):
        d = np.asarray(self._inverse(Z) @ self.T_diag, dtype=np.float64)
        return self.P_inf_diag + d * (1.0 + 2.0**-52)

    monkeypatch.setattr(SP._Problem, "diagonals", skewed)
    X = prob.covariances(Z)
    assert not np.array_equal(prob.diagonals(Z), np.diagonal(X, axis1=1, axis2=2))


def test_row_sums_are_numpys_bit_for_bit():
    from covnet.core.allocation.interval_bounds import _row_sums

    rng = np.random.default_rng(5)
    for k in range(10):
        for m in (1, 7, 300):
            c = np.abs(rng.standard_normal((m, k))) * 10.0 ** rng.integers(-9, 9, (m, k))
            np.testing.assert_array_equal(_row_sums(c), c.sum(axis=1))
    # a right-to-left order (what the check must catch) differs somewhere
    c = np.abs(rng.standard_normal((300, 4))) * 10.0 ** rng.integers(-9, 9, (300, 4))
    assert not np.array_equal(c[:, 0] + ((c[:, 1] + c[:, 2]) + c[:, 3]), c.sum(axis=1))
