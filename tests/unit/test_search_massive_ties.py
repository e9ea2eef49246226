"""Exact branch and bound on problems with massive exact ties (issue 29): the generator of
:mod:`covnet.covariance_control.tie_problems` does tie, and every metric's exact search returns
the exhaustive search's subset, value and ``P`` bits on it, with the tie rule's pruning
(:mod:`covnet.core.allocation.tie_rule`) on, forced to fail its check, and fed a wrong
certificate (the check must catch it).

The fast suite runs every rule at N = 10 (1 023 subsets, against the exhaustive search: a wrong
pruning shows there as at N = 14); the ``slow`` tests repeat them at N = 12-14."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from covnet.core.allocation import interval_bounds as IB
from covnet.core.allocation import search as S
from covnet.core.allocation import tie_rule as TR
from covnet.core.allocation._fast import tie_threshold
from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.metrics import METRICS
from covnet.covariance_control.tie_problems import tie_problem

#: (sensors, seed, types): copies of 3 or 4 types, and distinct sensors (ties by tolerance only)
FAST_CASES = [(10, 0, 3), (10, 1, 4), (10, 2, 10)]
#: the same kinds at 4-16 times as many subsets (``slow``)
CASES = [(12, 0, 3), (12, 1, 4), (12, 2, 12), (14, 3, 4)]


def _values(P_pred, gains, P_d, name):
    vals, sizes = [], []
    Y0 = S.spd_inverse(P_pred)
    for size in range(1, gains.shape[0] + 1):
        for D in itertools.combinations(range(gains.shape[0]), size):
            J = np.zeros((4, 4))
            for j in D:
                J = J + gains[j]
            vals.append(float(METRICS[name](S.spd_inverse(Y0 + J), P_d)))
            sizes.append(size)
    return np.array(vals), np.array(sizes)


@pytest.mark.parametrize(
    ("n", "seed", "types", "name", "least"),
    [
        (10, 1, 4, "spectral", 1023),
        (10, 1, 4, "one_norm", 1023),
        (10, 1, 4, "frobenius", 1023),
        (10, 1, 4, "abs_trace", 4),
        (10, 1, 4, "svd", 3),
        pytest.param(12, 0, 3, "spectral", 4095, marks=pytest.mark.slow),
        pytest.param(12, 0, 3, "one_norm", 4095, marks=pytest.mark.slow),
        pytest.param(12, 0, 3, "frobenius", 4095, marks=pytest.mark.slow),
        pytest.param(12, 0, 3, "abs_trace", 6, marks=pytest.mark.slow),
        pytest.param(12, 0, 3, "svd", 4, marks=pytest.mark.slow),
    ],
)
def test_generator_makes_massive_ties(n, seed, types, name, least):
    """Every one of the ``2^n - 1`` subsets ties for the norms the velocity term dominates; for
    the others the copies of the optimum tie (types of 3-4 copies)."""
    P_pred, gains, P_d = tie_problem(n, seed, types)
    v, _ = _values(P_pred, gains, P_d, name)
    assert (v <= tie_threshold(float(v.min()), 1e-9)).sum() >= least


def _all_cases():
    fast = [pytest.param(*c, id="-".join(map(str, c))) for c in FAST_CASES]
    slow = [pytest.param(*c, id="-".join(map(str, c)), marks=pytest.mark.slow) for c in CASES]
    return fast + slow


@pytest.mark.parametrize(("n", "seed", "types"), _all_cases())
@pytest.mark.parametrize("name", sorted(METRICS))
def test_bnb_equals_exhaustive_on_massive_ties(name, n, seed, types):
    P_pred, gains, P_d = tie_problem(n, seed, types)
    ref = allocate_exhaustive(P_pred, gains, P_d, name)
    got = S.allocate_bnb(P_pred, gains, P_d, name)
    assert got.status == 0
    assert (got.subset, got.value) == (ref.subset, ref.value)
    np.testing.assert_array_equal(got.P, ref.P)
    c = Constraints(frozenset({5}), frozenset({0}), 4)
    ref = allocate_exhaustive(P_pred, gains, P_d, name, c)
    got = S.allocate_bnb(P_pred, gains, P_d, name, c)
    assert (got.subset, got.value) == (ref.subset, ref.value)
    np.testing.assert_array_equal(got.P, ref.P)


def test_tie_rules_prune_and_pass_their_check(monkeypatch):
    """On a copies problem the size rule and the identical-sensor rule are used, the check
    passes (no second search) and the tree is a small fraction of the plain one."""
    P_pred, gains, P_d = tie_problem(14, 1, 4)
    checks = []
    verified = TR._TieRule.verified

    def spy(self, masks, values, k):
        ok = verified(self, masks, values, k)
        checks.append((ok, self.symmetry, self.s_star))
        return ok

    monkeypatch.setattr(TR._TieRule, "verified", spy)
    got = S.allocate_bnb(P_pred, gains, P_d, "spectral")
    assert checks == [(True, True, 1)]
    monkeypatch.setattr(TR._TieRule, "active", property(lambda self: False))
    plain = S.allocate_bnb(P_pred, gains, P_d, "spectral")
    assert (plain.subset, plain.value) == (got.subset, got.value)
    assert got.n_nodes * 20 < plain.n_nodes


@pytest.mark.parametrize(
    "cases",
    [
        pytest.param(FAST_CASES[:2], id="fast"),
        pytest.param(CASES[:2], id="slow", marks=pytest.mark.slow),
    ],
)
@pytest.mark.parametrize("name", ["spectral", "abs_trace", "kl", "frobenius", "svd"])
def test_failed_check_runs_the_plain_search(name, cases, monkeypatch):
    """A check that fails sends the decision to the search without the rules: still exact."""
    monkeypatch.setattr(TR._TieRule, "verified", lambda self, m, v, k: False)
    for n, seed, types in cases:
        P_pred, gains, P_d = tie_problem(n, seed, types)
        ref = allocate_exhaustive(P_pred, gains, P_d, name)
        got = S.allocate_bnb(P_pred, gains, P_d, name)
        assert (got.subset, got.value) == (ref.subset, ref.value)


@pytest.mark.parametrize(
    "cases",
    [pytest.param(FAST_CASES, id="fast"), pytest.param(CASES, id="slow", marks=pytest.mark.slow)],
)
@pytest.mark.parametrize("name", ["spectral", "abs_trace", "logdet", "trace_diff"])
def test_check_catches_a_wrong_certificate(name, cases, monkeypatch):
    """Every evaluated subset declared certified (``thr(L0) = inf``, false): the size rule then
    drops subsets that can win, and the check must send the decision to the plain search."""
    orig = TR._TieRule.__init__

    def init(self, prob, symmetry):
        orig(self, prob, symmetry)
        self.thr0 = np.inf

    monkeypatch.setattr(TR._TieRule, "__init__", init)
    for n, seed, types in cases:
        P_pred, gains, P_d = tie_problem(n, seed, types)
        ref = allocate_exhaustive(P_pred, gains, P_d, name)
        got = S.allocate_bnb(P_pred, gains, P_d, name)
        assert (got.subset, got.value) == (ref.subset, ref.value)


def test_precedes_is_the_tie_rules_order():
    rng = np.random.default_rng(5)
    masks = rng.random((200, 7)) < 0.4
    d = masks[0]
    key = lambda m: (int(m.sum()), tuple(np.flatnonzero(m)))  # noqa: E731
    want = np.array([key(m) < key(d) for m in masks])
    np.testing.assert_array_equal(TR.precedes(masks, d), want)


def test_identical_sensors_are_adjacent_in_the_branching_order():
    from covnet.core.allocation.search_problem import _Problem

    P_pred, gains, P_d = tie_problem(12, 0, 3)
    prob = _Problem(P_pred, gains, P_d, "spectral", Constraints(), 1e-9)
    same = TR.identical_to_previous(prob)
    assert same.sum() == 12 - 3  # every copy after its type's first
    for p in np.flatnonzero(same):
        assert prob.free[p - 1] < prob.free[p]


def test_a_limit_stops_the_table_of_the_last_levels(monkeypatch):
    """kl on a tie problem: the table's ball holds most completions of every node, and the limit
    is checked between its queries (before, one batch of nodes ran its every query: this call did
    not return within minutes).  Deterministic: a node limit.  Without kl's leaf bound (with it
    the identical-sensor rule decides this problem from the tree, without the table)."""
    monkeypatch.setattr(IB, "KL_BOUND", IB.IntervalBound(IB._gen_eig, IB._kl_combine))
    P_pred, gains, P_d = tie_problem(24, 0, 4)
    limit = 200_000
    r = S.allocate_bnb(P_pred, gains, P_d, "kl", node_limit=limit)
    assert r.status == 1 and not r.exact
    assert r.n_nodes < 2 * limit
    assert r.lower_bound <= r.value and r.gap == pytest.approx((r.value - r.lower_bound) / r.value)


@pytest.mark.parametrize("velocity_var", [1e8, 1e9])
@pytest.mark.parametrize(("n", "seed", "types"), FAST_CASES[:2])
def test_rules_decide_a_nontrivial_tie_set(n, seed, types, velocity_var, monkeypatch):
    """abs_trace with a larger velocity variance: a subset is certified and the tie set is not
    every subset (the choice has 2-4 sensors, not the trivial first sensor), so the size rule and
    the identical-sensor rule both shape the answer.  The check must pass at once (no second
    search: a wrong pruning that the check catches still fails here) and the result must be the
    exhaustive search's."""
    P_pred, gains, P_d = tie_problem(n, seed, types, velocity_var=velocity_var)
    checks = []
    verified = TR._TieRule.verified

    def spy(self, masks, values, k):
        ok = verified(self, masks, values, k)
        checks.append((ok, self.symmetry))
        return ok

    monkeypatch.setattr(TR._TieRule, "verified", spy)
    ref = allocate_exhaustive(P_pred, gains, P_d, "abs_trace")
    got = S.allocate_bnb(P_pred, gains, P_d, "abs_trace")
    assert checks == [(True, True)]
    assert len(ref.subset) > 1
    assert (got.subset, got.value) == (ref.subset, ref.value)
    np.testing.assert_array_equal(got.P, ref.P)
