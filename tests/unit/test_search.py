"""Branch and bound, bounded mode and greedy (covnet.core.allocation.search): the result record,
the tie
rule (identical and zero-gain sensors), constraints, limits, input validation as the reference,
and the safety of every node bound of the actual tree (reduced form, error model included)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from covnet.core.allocation import search as S
from covnet.core.allocation.exact import (
    Constraints,
    InfeasibleAllocation,
    allocate,
    allocate_exhaustive,
    prepare,
)
from covnet.core.allocation.search import STATUS, SearchResult, allocate_bnb, allocate_greedy
from covnet.core.metrics import METRICS
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensing import correlated_noise, information_gain, position_matrix
from covnet.covariance_control.bench_allocation import PAPER_TABLE

PAPER = PAPER_TABLE  # the paper's 8 sensors (sx [m], sy [m], rho)
D1 = np.diag([25.0, 1.4, 25.0, 1.4])
D2 = np.diag([7.0, 0.8, 7.0, 0.8])


def paper_gains(N):
    H = position_matrix()
    out = []
    for j in range(N):
        sx, sy, rho = PAPER[j % 8]
        k = 1.0 + 0.5 * (j // 8)
        out.append(information_gain(H, correlated_noise(sx * k, sy * k, rho)))
    return np.array(out)


def paper_run(gains, metric, scans, search=allocate):
    """``(P_pred, P_d)`` at the given scans of the paper's covariance recursion (with
    :func:`allocate`, on a plan prepared once: the same bits as preparing it every call, which
    took most of the recursion's time)."""
    F, Q = cv_transition(1.0), dwna_process_noise(1.0, 0.5)
    P = np.diag([1e4, 1e2, 1e4, 1e2])
    if search is allocate:
        gains = prepare(gains)
    out = []
    for scan in range(1, max(scans) + 1):
        P_pred = F @ P @ F.T + Q
        D = D1 if scan <= 50 else D2
        if scan in scans:
            out.append((P_pred, D))
        P = search(P_pred, gains, D, metric).P
    return out


def _f_lo(ref, tie_rtol=1e-9):
    """A lower bound of the minimum ``f*`` from the reference's choice, whose value is within
    ``tie_rtol`` of it (the tie rule may prefer a smaller subset of a slightly larger value)."""
    return ref.value - tie_rtol * abs(ref.value)


@pytest.fixture(scope="module")
def gains8():
    return paper_gains(8)


@pytest.fixture(scope="module")
def problems8(gains8):
    return {name: paper_run(gains8, name, [3, 30, 51, 80]) for name in sorted(METRICS)}


@pytest.mark.parametrize("name", sorted(METRICS))
def test_paper_scenario_equals_exhaustive(name, gains8, problems8):
    for P_pred, P_d in problems8[name]:
        ref = allocate_exhaustive(P_pred, gains8, P_d, name)
        got = allocate_bnb(P_pred, gains8, P_d, name)
        assert (got.subset, got.value) == (ref.subset, ref.value)
        np.testing.assert_array_equal(got.P, ref.P)


def test_result_record(gains8, problems8):
    P_pred, P_d = problems8["spectral"][1]
    r = allocate_bnb(P_pred, gains8, P_d, "spectral")
    assert isinstance(r, SearchResult)
    assert r.exact and r.success and r.status == 0 and r.message == STATUS[0]
    assert r.lower_bound == r.value and r.gap == 0.0
    assert r.n_nodes > 0 and r.n_evaluated >= 1
    assert r.P.shape == (4, 4)
    assert list(r.subset) == sorted(r.subset)


def _identical(k, scale=1.0):
    H = position_matrix()
    return np.stack([information_gain(H, correlated_noise(20.0, 20.0, 0.0)) * scale] * k)


@pytest.mark.parametrize("search", [allocate_bnb, allocate_greedy])
def test_exact_tie_between_identical_sensors_picks_the_lowest_ids(search):
    """Four identical sensors: subsets of one size tie (up to rounding); the lowest ids win."""
    gains = _identical(4)
    P_pred = np.diag([400.0, 10.0, 400.0, 10.0])
    for P_d in (np.diag([150.0, 5.0, 150.0, 5.0]), np.diag([60.0, 5.0, 60.0, 5.0])):
        ref = allocate_exhaustive(P_pred, gains, P_d, "abs_trace")
        got = search(P_pred, gains, P_d, "abs_trace")
        assert got.subset == ref.subset == tuple(range(len(ref.subset)))
        assert got.value == ref.value


def test_zero_gain_sensors_lose_ties_but_win_as_a_singleton(gains8):
    """A zero-gain sensor never changes J: with it a subset ties its subset without it, which
    has fewer sensors.  With ``P_d = P_pred`` nothing beats measuring nothing, i.e. the
    lowest-indexed zero-gain sensor alone."""
    z = np.zeros((4, 4))
    gains = np.array([gains8[0], z, gains8[1], z, gains8[2]])
    P_pred = paper_run(gains8, "spectral", [30])[0][0]
    for P_d, metric in ((P_pred, "spectral"), (D1, "abs_trace"), (D2, "frobenius")):
        ref = allocate_exhaustive(P_pred, gains, P_d, metric)
        got = allocate_bnb(P_pred, gains, P_d, metric)
        assert (got.subset, got.value) == (ref.subset, ref.value)
    assert allocate_bnb(P_pred, gains, P_pred, "spectral").subset == (1,)
    # with a required sensor the zero sensors never appear
    c = Constraints(required=frozenset({4}))
    ref = allocate_exhaustive(P_pred, gains, P_pred, "spectral", c)
    assert allocate_bnb(P_pred, gains, P_pred, "spectral", c).subset == ref.subset == (4,)


def test_all_gains_zero(gains8):
    gains = np.zeros((3, 4, 4))
    P_pred = np.diag([4.0, 1.0, 4.0, 1.0])
    for c in (Constraints(), Constraints(required=frozenset({2})), Constraints(excluded={0})):
        ref = allocate_exhaustive(P_pred, gains, D1, "kl", c)
        got = allocate_bnb(P_pred, gains, D1, "kl", c)
        assert (got.subset, got.value) == (ref.subset, ref.value)
        for name in ("spectral", "svd", "kl"):  # the lower bounds of the no-information case
            ref = allocate_exhaustive(P_pred, gains, D1, name, c)
            g = allocate_greedy(P_pred, gains, D1, name, c)
            b = allocate_bnb(P_pred, gains, D1, name, c, node_limit=1)
            assert g.lower_bound <= ref.value and b.lower_bound <= ref.value
            assert g.value == ref.value


CONSTRAINTS = [
    Constraints(excluded=frozenset({0, 3})),
    Constraints(required=frozenset({5})),
    Constraints(max_active=2),
    Constraints(frozenset({1}), frozenset({2, 6}), 3),
    Constraints(required=frozenset({0, 4}), max_active=2),  # only one feasible subset
]


@pytest.mark.parametrize("c", CONSTRAINTS, ids=str)
@pytest.mark.parametrize("name", ["spectral", "svd", "logdet", "one_norm"])
def test_constraints_equal_exhaustive(c, name, gains8, problems8):
    for P_pred, P_d in problems8[name]:
        ref = allocate_exhaustive(P_pred, gains8, P_d, name, c)
        got = allocate_bnb(P_pred, gains8, P_d, name, c)
        assert (got.subset, got.value) == (ref.subset, ref.value)
        g = allocate_greedy(P_pred, gains8, P_d, name, c)
        assert set(g.subset) >= c.required and not set(g.subset) & c.excluded
        assert c.max_active is None or len(g.subset) <= c.max_active
        assert g.value >= _f_lo(ref) and g.lower_bound <= ref.value


@pytest.mark.parametrize("search", [allocate_bnb, allocate_greedy])
def test_infeasible_and_validation_as_the_reference(search, gains8):
    P_pred = np.diag([4.0, 1.0, 4.0, 1.0])
    with pytest.raises(InfeasibleAllocation, match="excluded"):
        search(P_pred, gains8, D1, "spectral", Constraints(excluded=frozenset(range(8))))
    with pytest.raises(InfeasibleAllocation, match="no sensors"):
        search(P_pred, np.zeros((0, 4, 4)), D1, "spectral")
    bad = [
        (dict(P_pred=np.eye(3), P_d=np.eye(3)), ValueError, "gains must be"),
        (dict(P_d=np.eye(3)), ValueError, "P_d must be"),
        (dict(P_pred=-np.eye(4)), ValueError, "positive definite"),
        (dict(metric="nope"), KeyError, "unknown metric"),
        (dict(tie_rtol=-1.0), ValueError, "tie_rtol"),
        (dict(constraints=Constraints(max_active=0)), ValueError, "max_active"),
        (dict(constraints=Constraints(required={9})), ValueError, "required sensor indices"),
    ]
    for override, exc, match in bad:
        kw = dict(P_pred=P_pred, gains=gains8, P_d=D1, metric="spectral")
        kw.update(override)
        with pytest.raises(exc, match=match):
            allocate_exhaustive(**kw)
        with pytest.raises(exc, match=match):
            search(**kw)


def test_bnb_argument_validation(gains8):
    P_pred = np.diag([4.0, 1.0, 4.0, 1.0])
    with pytest.raises(ValueError, match="rel_gap"):
        allocate_bnb(P_pred, gains8, D1, "spectral", rel_gap=1.0)
    with pytest.raises(ValueError, match="time_limit_s"):
        allocate_bnb(P_pred, gains8, D1, "spectral", time_limit_s=-1.0)
    with pytest.raises(ValueError, match="node_limit"):
        allocate_bnb(P_pred, gains8, D1, "spectral", node_limit=0)


def test_a_user_metric_is_solved_exactly(gains8, problems8):
    def weighted(A, B):
        return np.abs(np.diagonal(A - B, axis1=-2, axis2=-1) * [1, 10, 1, 10]).sum(axis=-1)

    P_pred, P_d = problems8["spectral"][2]
    ref = allocate_exhaustive(P_pred, gains8, P_d, weighted)
    got = allocate_bnb(P_pred, gains8, P_d, weighted)
    assert (got.subset, got.value, got.exact) == (ref.subset, ref.value, True)
    assert "no interval bound" in got.message
    g = allocate_greedy(P_pred, gains8, P_d, weighted)
    assert g.value >= _f_lo(ref) and g.lower_bound == -math.inf


def test_node_limit_bounded_result(gains8, problems8):
    P_pred, P_d = problems8["spectral"][3]
    ref = allocate_exhaustive(P_pred, gains8, P_d, "spectral")
    r = allocate_bnb(P_pred, gains8, P_d, "spectral", node_limit=1)
    assert r.status == 1 and not r.exact and not r.success and r.message == STATUS[1]
    assert r.lower_bound <= ref.value and r.value >= _f_lo(ref)
    assert r.gap == pytest.approx((r.value - r.lower_bound) / r.value)


def test_time_limit_with_an_injected_clock(gains8, problems8):
    ticks = itertools.count()
    P_pred, P_d = problems8["svd"][3]
    ref = allocate_exhaustive(P_pred, gains8, P_d, "svd")
    r = allocate_bnb(P_pred, gains8, P_d, "svd", time_limit_s=1.5, clock=lambda: next(ticks))
    assert r.status == 2 and r.message == STATUS[2]
    assert r.lower_bound <= ref.value and r.value >= _f_lo(ref)


def test_rel_gap(gains8, problems8):
    for P_pred, P_d in problems8["kl"]:
        ref = allocate_exhaustive(P_pred, gains8, P_d, "kl")
        r = allocate_bnb(P_pred, gains8, P_d, "kl", rel_gap=0.05)
        assert r.status == 3 and r.success and not r.exact
        assert r.lower_bound <= ref.value and r.value >= _f_lo(ref)
        assert r.gap <= 0.05 + 1e-12
        assert r.value * (1 - 0.05) <= ref.value * (1 + 1e-12)


def test_greedy_record(gains8, problems8):
    P_pred, P_d = problems8["abs_trace"][1]
    ref = allocate_exhaustive(P_pred, gains8, P_d, "abs_trace")
    g = allocate_greedy(P_pred, gains8, P_d, "abs_trace")
    assert g.status == 4 and g.success and not g.exact and g.message == STATUS[4]
    assert g.lower_bound <= ref.value and g.value >= _f_lo(ref)
    assert g.gap == pytest.approx((g.value - g.lower_bound) / g.value)
    again = allocate_greedy(P_pred, gains8, P_d, "abs_trace")
    assert (again.subset, again.value) == (g.subset, g.value)  # deterministic


def check_tree(P_pred, gains, P_d, name, c, monkeypatch, prune=True):
    """Run the search, recording every node it creates and every candidate it records; check
    each node's bound <= the exact value of each of its completions, each candidate's bound <=
    its own exact value.  ``prune=False``: no pruning at all (every node of the tree)."""
    seen = []
    records = []
    real_push, real_record = S._Search.push, S._Search.record

    def push(self, ch):
        seen.append((self.prob, ch))
        real_push(self, ch)

    def record(self, inc, est):
        records.append((self.prob, inc, est))
        real_record(self, inc, est)

    with monkeypatch.context() as mp:
        mp.setattr(S._Search, "push", push)
        mp.setattr(S._Search, "record", record)
        if not prune:
            mp.setattr(S._Search, "tau", property(lambda self: math.inf))
        allocate_bnb(P_pred, gains, P_d, name, c)
    f = METRICS[name]
    checked = 0
    for prob, ch in seen:
        rows = prob.unpack(ch.inc)
        for row in range(ch.lb.size):
            d, inc = ch.depth, rows[row]
            fixed = [prob.free[i] for i in range(d) if inc[i]] + prob.req
            rest = prob.free[d:]
            room = prob.K - len(fixed)
            values = []
            for size in range(min(room, len(rest)) + 1):
                for extra in itertools.combinations(rest, size):
                    D = sorted(fixed + list(extra))
                    if D:
                        values.append(_exact(prob, D, f))
            assert ch.lb[row] <= min(values), (ch.lb[row], min(values))
            checked += 1
    for prob, packed, est in records:
        inc = prob.unpack(packed)
        for row in range(est.size):
            D = sorted([prob.free[i] for i in np.flatnonzero(inc[row])] + prob.req)
            assert est[row] <= _exact(prob, D, f)
            checked += 1
    return checked


@pytest.mark.parametrize("name", sorted(METRICS))
def test_every_node_bound_of_the_tree_is_below_its_completions(name, monkeypatch):
    """White box: the bound of every node the search creates (reduced-form endpoints, the
    search's error model) is <= the exact value of every completion of that node, and every
    candidate's bound is <= its own exact value; paper problems including the loose scans 1-2,
    the searched tree (7 sensors) and the whole tree without pruning (6 sensors, constraints)."""
    for P_pred, P_d in paper_run(paper_gains(7), name, [1, 2, 40, 70]):
        assert check_tree(P_pred, paper_gains(7), P_d, name, Constraints(), monkeypatch)
    c = Constraints(frozenset({1}), frozenset({4}), 4)
    for P_pred, P_d in paper_run(paper_gains(6), name, [1, 60]):
        n_all = check_tree(P_pred, paper_gains(6), P_d, name, Constraints(), monkeypatch, False)
        assert n_all >= 2**6
        assert check_tree(P_pred, paper_gains(6), P_d, name, c, monkeypatch, False)


def _exact(prob, D, f):
    J = np.zeros((prob.n, prob.n))
    for j in D:
        J = J + prob.G[j]
    return float(f(S.spd_inverse(prob.Y0 + J), prob.D))
