"""Covariance-control allocation: the information form, the fast path against the plain
reference on the paper scenario, the tie rule, constraints and input validation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.allocation.exact import (
    Allocation,
    AllocationPlan,
    Constraints,
    InfeasibleAllocation,
    MetricBound,
    allocate,
    allocate_exhaustive,
    allocation_rate,
    prepare,
    subset_covariance,
)
from covnet.core.metrics import METRICS, Metric, capability
from covnet.covariance_control.bench_allocation import PAPER_TABLE, paper_like_gains, paper_problems

D1 = np.diag([25.0, 1.4, 25.0, 1.4])
D2 = np.diag([7.0, 0.8, 7.0, 0.8])
# a realistic predicted covariance: scan 30 of the paper scenario under spectral control
P_PRED = paper_problems(paper_like_gains(PAPER_TABLE, 8), "spectral", [30])[0][0]


@pytest.fixture(scope="module")
def gains8():
    return paper_like_gains(PAPER_TABLE, 8)


# ---- the information form -----------------------------------------------------------------


def _random_spd(rng, shape, n):
    X = rng.standard_normal((*shape, n, n))
    return X @ np.swapaxes(X, -1, -2) + 0.1 * np.eye(n)


@pytest.mark.parametrize("n", [1, 2, 4, 6])
def test_subset_covariance_is_the_inverse_of_the_information_sum(n):
    rng = np.random.default_rng(n)
    P = _random_spd(rng, (), n)
    J = _random_spd(rng, (5,), n)
    expected = np.linalg.inv(np.linalg.inv(P) + J)
    np.testing.assert_allclose(subset_covariance(P, J), expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(subset_covariance(P, J[0]), expected[0], rtol=1e-9, atol=1e-12)


def test_subset_covariance_broadcasts_and_is_symmetric():
    rng = np.random.default_rng(7)
    P = _random_spd(rng, (3, 1), 4)
    J = _random_spd(rng, (1, 2), 4)
    out = subset_covariance(P, J)
    assert out.shape == (3, 2, 4, 4)
    np.testing.assert_array_equal(out, np.swapaxes(out, -1, -2))
    np.testing.assert_allclose(out[2, 1], np.linalg.inv(np.linalg.inv(P[2, 0]) + J[0, 1]))


def test_subset_covariance_rejects_indefinite():
    with pytest.raises(np.linalg.LinAlgError):
        subset_covariance(np.diag([1.0, -1.0]), np.zeros((2, 2)))


# ---- fast path == plain reference on the paper scenario -----------------------------------


def _paper_case(name):
    # the spec's three metrics at every scan from 3 on, the others at every 4th scan
    return (
        list(range(3, 101)) if name in ("spectral", "abs_trace", "svd") else list(range(3, 101, 4))
    )


@pytest.mark.parametrize("name", sorted(METRICS))
def test_fast_equals_reference_on_the_paper_scenario(name, gains8):
    for P_pred, P_d in paper_problems(gains8, name, _paper_case(name)):
        fast = allocate(P_pred, gains8, P_d, name)
        ref = allocate_exhaustive(P_pred, gains8, P_d, name)
        assert fast.subset == ref.subset
        assert fast.value == ref.value  # the same arithmetic: the same bits
        np.testing.assert_array_equal(fast.P, ref.P)
        assert fast.n_feasible == ref.n_feasible == 255
        assert ref.n_evaluated == 255
        assert 1 <= fast.n_evaluated <= 255


@pytest.mark.parametrize("N", [8, 12])
def test_svd_fast_equals_reference_on_paper_problems(N):
    """svd (the block bound of ``_svd_block``) with a prepared plan, N = 8 and 12 paper-like
    sensors, scans of both desired phases: the plain loop's subset, value and ``P`` bits, and
    (the bound being tight there) a single exact evaluation per decision."""
    gains = paper_like_gains(PAPER_TABLE, N)
    plan = prepare(gains)
    for P_pred, P_d in paper_problems(gains, "svd", [3, 5, 28, 50, 51, 73, 95]):
        fast = allocate(P_pred, plan, P_d, "svd")
        ref = allocate_exhaustive(P_pred, gains, P_d, "svd")
        assert (fast.subset, fast.value) == (ref.subset, ref.value)
        np.testing.assert_array_equal(fast.P, ref.P)
        assert fast.n_evaluated <= 4


def test_allocation_record(gains8):
    a = allocate(P_PRED, gains8, D1, "spectral")
    assert isinstance(a, Allocation)
    assert list(a.subset) == sorted(a.subset)
    J = sum(gains8[j] for j in a.subset)
    np.testing.assert_allclose(a.P, subset_covariance(P_PRED, J), rtol=1e-12)
    assert a.value == pytest.approx(float(METRICS["spectral"](a.P, D1)), rel=1e-12)


def test_metric_by_function_and_by_name_agree(gains8):
    by_fn = allocate(P_PRED, gains8, D2, METRICS["svd"])
    by_name = allocate(P_PRED, gains8, D2, "svd")
    assert (by_fn.subset, by_fn.value, by_fn.n_evaluated) == (
        by_name.subset,
        by_name.value,
        by_name.n_evaluated,
    )


def _weighted_trace(A, B):
    """A user's own metric: position errors count ten times the velocity errors."""
    d = np.abs(np.diagonal(A - B, axis1=-2, axis2=-1))
    return d @ np.array([10.0, 1.0, 10.0, 1.0])


@pytest.mark.parametrize(
    "metric",
    [_weighted_trace, lambda A, B: METRICS["frobenius"](A, B)],
    ids=["own-function", "wrapped-registered"],
)
def test_user_metric_function(metric, gains8):
    for P_pred, P_d in paper_problems(gains8, "abs_trace", [5, 40, 60, 90]):
        fast = allocate(P_pred, gains8, P_d, metric)
        ref = allocate_exhaustive(P_pred, gains8, P_d, metric)
        assert fast.subset == ref.subset
        assert fast.value == ref.value
        assert fast.n_evaluated == fast.n_feasible  # no bound known: batched exhaustive


@pytest.mark.parametrize("tie_rtol", [1e-9, 0.0], ids=["default-rtol", "zero-rtol"])
def test_a_user_registered_metric_and_bound(monkeypatch, tie_rtol, gains8):
    """The extension story: a metric entry added to METRICS with its lower bound.  A valid
    bound prunes; a bound that knows nothing (NaN) prunes nothing; no bound at all, nothing
    either; all stay exact."""
    for bound, pruned in [
        (
            capability(METRICS["abs_trace"].subset_bound, MetricBound),
            True,
        ),  # weights >= 1: abs_trace below
        (MetricBound(lambda P, D, ctx: np.full(P.size, np.nan)), False),
        (None, False),
    ]:
        entry = Metric("weighted", _weighted_trace, subset_bound=bound)
        monkeypatch.setitem(METRICS, "weighted", entry)
        for P_pred, P_d in paper_problems(gains8, "abs_trace", [20, 70]):
            fast = allocate(P_pred, gains8, P_d, "weighted", tie_rtol=tie_rtol)
            ref = allocate_exhaustive(P_pred, gains8, P_d, "weighted", tie_rtol=tie_rtol)
            assert (fast.subset, fast.value) == (ref.subset, ref.value)
            assert (fast.n_evaluated < 255) == pruned


# ---- the tie rule -------------------------------------------------------------------------


def _identical_sensors(k):
    g = paper_like_gains(PAPER_TABLE, 1)
    return np.repeat(g, k, axis=0)


@pytest.mark.parametrize("search", [allocate, allocate_exhaustive], ids=["fast", "reference"])
def test_exact_tie_picks_lowest_ids(search):
    """Four identical sensors: every subset of a size has the same P_i bit for bit, so the
    best size ties C(4, k) ways; the lexicographically smallest subset wins."""
    gains = _identical_sensors(4)
    sizes = {}
    for k in range(1, 5):
        P = subset_covariance(P_PRED, sum(gains[:k]))
        sizes[k] = P
    # desire exactly what two sensors give: size 2 is the unique best size
    a = search(P_PRED, gains, sizes[2], "abs_trace")
    assert a.subset == (0, 1)
    assert a.value == 0.0


@pytest.mark.parametrize("search", [allocate, allocate_exhaustive], ids=["fast", "reference"])
def test_constant_metric_ties_everything(search, gains8):
    flat = lambda A, B: np.zeros(np.shape(A)[:-2])  # noqa: E731
    assert search(P_PRED, gains8, D1, flat).subset == (0,)
    assert search(P_PRED, gains8, D1, flat, Constraints(excluded=frozenset({0}))).subset == (1,)
    c = Constraints(required=frozenset({5, 2}))
    assert search(P_PRED, gains8, D1, flat, c).subset == (2, 5)


@pytest.mark.parametrize("search", [allocate, allocate_exhaustive], ids=["fast", "reference"])
def test_near_tie_within_tolerance_prefers_fewer_sensors(search):
    """f differs between sizes by a relative 1e-12 < tie_rtol: fewest sensors win; with
    tie_rtol = 0 the strict minimum (all sensors) wins."""
    gains = _identical_sensors(3)

    def almost_flat(A, B):
        return 1.0 + 1e-12 * np.trace(A, axis1=-2, axis2=-1) / np.trace(B)

    assert search(P_PRED, gains, D1, almost_flat).subset == (0,)
    assert search(P_PRED, gains, D1, almost_flat, tie_rtol=0.0).subset == (0, 1, 2)


# ---- constraints --------------------------------------------------------------------------


CONSTRAINTS = [
    Constraints(excluded=frozenset({0, 3})),
    Constraints(required=frozenset({6})),
    Constraints(max_active=2),
    Constraints(excluded=frozenset({1}), required=frozenset({4, 7}), max_active=3),
    Constraints(required=frozenset({0, 1, 2})),
    Constraints(required=frozenset({0, 1, 2}), max_active=3),
]


@pytest.mark.parametrize("c", CONSTRAINTS, ids=[f"c{k}" for k in range(len(CONSTRAINTS))])
@pytest.mark.parametrize("name", ["spectral", "svd", "kl"])
def test_constraints_respected_and_fast_equals_reference(c, name, gains8):
    for P_pred, P_d in paper_problems(gains8, name, [10, 55]):
        fast = allocate(P_pred, gains8, P_d, name, c)
        ref = allocate_exhaustive(P_pred, gains8, P_d, name, c)
        assert fast.subset == ref.subset
        assert fast.n_feasible == ref.n_feasible
        chosen = set(fast.subset)
        assert c.required <= chosen
        assert not chosen & c.excluded
        assert c.max_active is None or len(chosen) <= c.max_active


def test_feasible_count():
    gains = paper_like_gains(PAPER_TABLE, 8)
    c = Constraints(excluded=frozenset({1}), required=frozenset({4, 7}), max_active=4)
    # 5 free sensors, 0..2 of them on top of the two required
    expected = sum(math.comb(5, k) for k in range(3))
    assert allocate(P_PRED, gains, D1, "abs_trace", c).n_feasible == expected
    assert allocate_exhaustive(P_PRED, gains, D1, "abs_trace", c).n_feasible == expected


@pytest.mark.parametrize("search", [allocate, allocate_exhaustive], ids=["fast", "reference"])
def test_infeasible(search, gains8):
    with pytest.raises(InfeasibleAllocation, match="all 8 sensors are excluded"):
        search(P_PRED, gains8, D1, "svd", Constraints(excluded=frozenset(range(8))))
    with pytest.raises(InfeasibleAllocation, match="no sensors"):
        search(P_PRED, np.zeros((0, 4, 4)), D1, "svd")
    assert issubclass(InfeasibleAllocation, ValueError)


BAD = [
    (
        dict(constraints=Constraints(excluded=frozenset({2}), required=frozenset({2}))),
        ValueError,
        r"sensors \[2\] are both excluded and required",
    ),
    (
        dict(constraints=Constraints(excluded=frozenset({8}))),
        ValueError,
        r"excluded sensor indices must be integers in \[0, 8\), got 8",
    ),
    (
        dict(constraints=Constraints(required=frozenset({-1}))),
        ValueError,
        r"required sensor indices must be integers in \[0, 8\)",
    ),
    (dict(constraints=Constraints(max_active=0)), ValueError, "max_active must be an integer >= 1"),
    (
        dict(constraints=Constraints(required=frozenset({0, 1, 2}), max_active=2)),
        ValueError,
        r"max_active=2 is smaller than the 3 required sensors \[0, 1, 2\]",
    ),
    (dict(P_pred=np.eye(3), P_d=np.eye(3)), ValueError, r"gains must be \(Ns, 3, 3\)"),
    (dict(P_pred=np.ones((4, 3))), ValueError, "P_pred must be a non-empty square"),
    (dict(P_d=np.eye(3)), ValueError, r"P_d must be \(4, 4\) like P_pred"),
    (dict(gains=np.zeros((8, 4))), ValueError, r"gains must be \(Ns, 4, 4\)"),
    (dict(P_pred=np.triu(np.ones((4, 4))) + np.eye(4)), ValueError, "P_pred must be symmetric"),
    (dict(P_d=np.full((4, 4), np.nan)), ValueError, "P_d has non-finite entries"),
    (dict(P_pred=-np.eye(4)), ValueError, "positive definite"),
    (dict(gains=np.stack([np.eye(4), -np.eye(4)])), ValueError, r"gains\[1\] must be positive"),
    (dict(metric="nope"), KeyError, "valid metrics: abs_trace"),
    (dict(metric=3), TypeError, "metric must be a registered name or a callable"),
    (dict(tie_rtol=-1.0), ValueError, "tie_rtol must be finite and >= 0"),
]


@pytest.mark.parametrize("search", [allocate, allocate_exhaustive], ids=["fast", "reference"])
@pytest.mark.parametrize(
    ("override", "exc", "match"), BAD, ids=[f"bad{k}" for k in range(len(BAD))]
)
def test_validation_messages(search, override, exc, match, gains8):
    args = dict(P_pred=P_PRED, gains=gains8, P_d=D1, metric="spectral")
    args.update(override)
    with pytest.raises(exc, match=match):
        search(**args)


# ---- allocation rate ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("counts", "n_sensors", "expected"),
    [([1, 2, 3], 4, 0.5), ([8] * 10, 8, 1.0), ([0, 0], 3, 0.0), ([2, 3, 1, 0], 8, 6 / 32)],
    ids=["mixed", "all", "none", "paper-like"],
)
def test_allocation_rate(counts, n_sensors, expected):
    assert allocation_rate(counts, n_sensors) == pytest.approx(expected)


def test_allocation_rate_rejects_bad_input():
    with pytest.raises(ValueError, match="at least one scan"):
        allocation_rate([], 8)
    with pytest.raises(ValueError, match="in \\[0, 8\\]"):
        allocation_rate([9], 8)
    with pytest.raises(ValueError, match="n_sensors must be >= 1"):
        allocation_rate([1], 0)


# ---- the plan: gain-only work prepared once -----------------------------------------------


PLAN_CONSTRAINTS = [Constraints(), *CONSTRAINTS]


@pytest.mark.parametrize("c", PLAN_CONSTRAINTS, ids=[f"c{k}" for k in range(-1, len(CONSTRAINTS))])
@pytest.mark.parametrize("name", sorted(METRICS))
def test_plan_equals_gains_equals_exhaustive(c, name, gains8):
    plan = prepare(gains8, c)
    assert isinstance(plan, AllocationPlan) and plan.constraints == c
    for P_pred, P_d in paper_problems(gains8, name, [10, 55]):
        with_plan = allocate(P_pred, plan, P_d, name)
        with_plan_c = allocate(P_pred, plan, P_d, name, c)  # the plan's own constraints: fine
        without = allocate(P_pred, gains8, P_d, name, c)
        ref = allocate_exhaustive(P_pred, gains8, P_d, name, c)
        for a in (with_plan, with_plan_c, without):
            assert (a.subset, a.value, a.n_feasible) == (ref.subset, ref.value, ref.n_feasible)
            np.testing.assert_array_equal(a.P, ref.P)
        assert with_plan.n_evaluated == without.n_evaluated


def test_plan_with_a_user_metric(gains8):
    plan = prepare(gains8, Constraints(required=frozenset({3})))
    for P_pred, P_d in paper_problems(gains8, "abs_trace", [5, 60]):
        a = allocate(P_pred, plan, P_d, _weighted_trace)
        ref = allocate_exhaustive(P_pred, gains8, P_d, _weighted_trace, plan.constraints)
        assert (a.subset, a.value) == (ref.subset, ref.value)


def test_plan_is_read_only_and_independent_of_the_caller(gains8):
    g = gains8.copy()
    plan = prepare(g)
    g[:] = 0.0  # the caller's array changes: the plan keeps its own validated copy
    assert not plan.gains.flags.writeable
    assert plan.n == 4 and plan.n_sensors == 8
    a = allocate(P_PRED, plan, D1, "spectral")
    assert a.subset == allocate_exhaustive(P_PRED, gains8, D1, "spectral").subset


def test_plan_refuses_other_constraints(gains8):
    plan = prepare(gains8, Constraints(excluded=frozenset({1})))
    with pytest.raises(ValueError, match="prepare a plan for these constraints"):
        allocate(P_PRED, plan, D1, "spectral", Constraints())
    with pytest.raises(ValueError, match=r"P_pred must be \(4, 4\) like the plan's gains"):
        allocate(np.eye(3), plan, np.eye(3), "spectral")


def test_plan_infeasible_is_raised_by_allocate(gains8):
    plan = prepare(gains8, Constraints(excluded=frozenset(range(8))))
    with pytest.raises(InfeasibleAllocation, match="all 8 sensors are excluded"):
        allocate(P_PRED, plan, D1, "svd")
    with pytest.raises(InfeasibleAllocation, match="no sensors"):
        allocate(P_PRED, prepare(np.zeros((0, 4, 4))), D1, "svd")


PLAN_BAD = [
    (dict(gains=np.zeros((8, 4))), r"gains must be \(Ns, n, n\)"),
    (dict(gains=np.stack([np.eye(4), -np.eye(4)])), r"gains\[1\] must be positive"),
    (dict(gains=np.stack([np.eye(4), np.triu(np.ones((4, 4)))])), r"gains\[1\] must be symm"),
    (dict(gains=np.full((2, 4, 4), np.nan)), r"gains\[0\] has non-finite entries"),
    *((dict(constraints=kw["constraints"]), match) for kw, _, match in BAD[:5]),
]


@pytest.mark.parametrize(
    ("override", "match"), PLAN_BAD, ids=[f"bad{k}" for k in range(len(PLAN_BAD))]
)
def test_prepare_rejects_bad_gains_and_constraints(override, match, gains8):
    """The same messages as allocate with a gains array (test_validation_messages)."""
    args = dict(gains=gains8, constraints=Constraints())
    args.update(override)
    with pytest.raises(ValueError, match=match):
        prepare(**args)
    if "gains" in override and override["gains"].ndim == 3:
        with pytest.raises(ValueError, match=match):
            allocate(P_PRED, override["gains"], D1, "spectral")


def test_plan_cache_does_not_keep_the_callers_P_d(gains8):
    """The plan caches the checked ``P_d`` by value: a caller reusing (mutating) one array for
    the desired covariance gets each decision for its current content."""
    plan = prepare(gains8)
    D = D1.copy()
    first = allocate(P_PRED, plan, D, "abs_trace")
    D[:] = D2  # the same array, now the tightened desire
    second = allocate(P_PRED, plan, D, "abs_trace")
    assert first.subset == allocate_exhaustive(P_PRED, gains8, D1, "abs_trace").subset
    assert second.subset == allocate_exhaustive(P_PRED, gains8, D2, "abs_trace").subset
    assert first.subset != second.subset
    D[:] = D1
    assert allocate(P_PRED, plan, D, "abs_trace").subset == first.subset


@pytest.mark.parametrize("name", sorted(METRICS))
def test_one_pair_metric_paths_equal_the_batched_ones(name):
    """Each metric on one ``(n, n)`` pair (its Python-float path) gives the same bits as the same
    pair inside a batch (the numpy path), which the allocator's exactness relies on."""
    rng = np.random.default_rng(11)
    for n in (1, 2, 4, 5):
        X = rng.standard_normal((6, n, n))
        A = X @ np.swapaxes(X, -1, -2) + 0.1 * np.eye(n)
        A[1] = np.diag(rng.choice([25.0, 1.4], n))  # diagonal, repeated values (svd ties)
        B = np.diag(rng.choice([25.0, 1.4, 7.0], n))
        batched = METRICS[name](A, B)
        for k in range(A.shape[0]):
            one = METRICS[name](A[k], B)
            assert np.asarray(one).shape == ()
            assert np.asarray(one).tobytes() == batched[k].tobytes()


@pytest.mark.parametrize("name", ["kl", "logdet"])
def test_a_singular_desired_covariance_is_named_for_the_metrics_that_invert_it(name):
    """A singular ``P_d`` with kl / logdet was blamed on ``P_pred`` and the gains only (the
    CLI's config check names it; the Python API's message did not)."""
    from covnet.core.allocation.search import allocate_bnb

    P = np.eye(2) * 10.0
    G = np.array([np.eye(2), np.diag([1.0, 0.0]), np.diag([0.0, 2.0])])
    P_d = np.diag([1.0, 0.0])
    for search in (allocate_exhaustive, allocate, allocate_bnb):
        with pytest.raises(ValueError, match=r"P_d positive definite for a metric that inverts"):
            search(P, G, P_d, name)
