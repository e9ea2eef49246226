"""Lagrangian relaxation against the exact MILP (spec §11 item 5): LB ≤ optimum ≤ UB on random
instances, feasible tuples, the pair-splitting dummy case; the MILP against brute force on
small clean 3-D assignments."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from covnet.core.passive.exact import solve_milp
from covnet.core.passive.lagrangian import _recover, solve_lr
from covnet.core.passive.sd import SDCosts


def _random_costs(seed: int, n: tuple[int, int, int], p_inf: float) -> SDCosts:
    """A dense clutter-style instance: singletons 0, other tuples ~ U(-10, 1) (gated if > 0),
    a share ``p_inf`` of them forbidden."""
    rng = np.random.default_rng(seed)
    shape = tuple(k + 1 for k in n)
    C = rng.uniform(-10.0, 1.0, size=shape)
    C[C > 0] = np.inf
    C[rng.random(shape) < p_inf] = np.inf
    C[0, 0, 0] = 0.0
    C[1:, 0, 0] = 0.0
    C[0, 1:, 0] = 0.0
    C[0, 0, 1:] = 0.0
    return SDCosts(C, complete_only=False)


def _assert_feasible(tuples: np.ndarray, shape: tuple[int, ...]) -> None:
    for s, n in enumerate(shape):
        used = tuples[:, s][tuples[:, s] > 0]
        assert sorted(used.tolist()) == list(range(1, n)), f"sensor {s}: {used}"


sizes = st.tuples(st.integers(0, 5), st.integers(0, 5), st.integers(0, 5))


@given(st.integers(0, 2**31 - 1), sizes, st.sampled_from([0.0, 0.3, 0.7]))
def test_bounds_bracket_the_milp_optimum(seed, n, p_inf):
    costs = _random_costs(seed, n, p_inf)
    exact = solve_milp(costs)
    assert exact.status == 0, exact.message
    _assert_feasible(exact.tuples, costs.shape)
    lr = solve_lr(costs)
    assert lr.status in (0, 1), lr.message
    tol = 1e-7 * max(1.0, abs(exact.cost))
    assert lr.lower <= exact.cost + tol
    assert exact.cost <= lr.upper + tol
    _assert_feasible(lr.tuples, costs.shape)
    C = costs.C
    assert lr.upper == pytest.approx(float(C[tuple(lr.tuples.T)].sum()), abs=1e-9)


def _brute_force_clean(C: np.ndarray) -> float:
    n = C.shape[0] - 1
    best = np.inf
    for p2 in itertools.permutations(range(1, n + 1)):
        for p3 in itertools.permutations(range(1, n + 1)):
            best = min(best, sum(C[i + 1, p2[i], p3[i]] for i in range(n)))
    return best


@given(st.integers(0, 2**31 - 1), st.integers(1, 4))
def test_clean_assignment_milp_is_exact_and_lr_brackets_it(seed, n):
    rng = np.random.default_rng(seed)
    C = np.full((n + 1,) * 3, np.inf)
    C[1:, 1:, 1:] = rng.exponential(5.0, size=(n, n, n))
    C[0, 0, 0] = 0.0
    costs = SDCosts(C, complete_only=True)
    want = _brute_force_clean(C)
    exact = solve_milp(costs)
    assert exact.status == 0
    assert exact.cost == pytest.approx(want, rel=1e-9, abs=1e-9)
    lr = solve_lr(costs)
    assert lr.lower <= want + 1e-7 * max(1.0, want) <= lr.upper + 2e-7 * max(1.0, want)
    assert (lr.tuples > 0).all()  # complete triples only
    _assert_feasible(lr.tuples, costs.shape)


def test_recovery_dissolves_a_pair_into_its_singletons():
    """Two relaxed pairs want the only sensor-3 measurement and neither may stand alone
    (C_ij0 = inf): the loser dissolves into (i,0,0) + (0,j,0)."""
    C = np.full((3, 3, 2), np.inf)
    C[0, 0, 0] = 0.0
    C[1:, 0, 0] = 0.0
    C[0, 1:, 0] = 0.0
    C[0, 0, 1] = 0.0
    C[1, 1, 1] = -10.0
    C[2, 2, 1] = -9.0
    ub, tuples = _recover(C, np.array([1, 2]), np.array([1, 2]))
    assert ub == -10.0
    assert {tuple(t) for t in tuples.tolist()} == {(1, 1, 1), (2, 0, 0), (0, 2, 0)}
    lr = solve_lr(SDCosts(C, complete_only=False))
    assert lr.upper == -10.0 and lr.lower <= -10.0 + 1e-9
    _assert_feasible(lr.tuples, C.shape)


def test_empty_and_one_sided_instances():
    for n in [(0, 0, 0), (2, 0, 0), (0, 0, 3), (1, 2, 0)]:
        costs = _random_costs(1, n, 0.0)
        lr = solve_lr(costs)
        ex = solve_milp(costs)
        assert lr.upper == pytest.approx(ex.cost, abs=1e-9)
        _assert_feasible(lr.tuples, costs.shape)
