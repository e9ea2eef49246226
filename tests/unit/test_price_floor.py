"""The price-aware floor (covnet.core.allocation.price_floor) and the timed plan's root floors
(covnet.core.allocation.assignment_search, round mt12): each bound never exceeds the exhaustive
minimum it bounds; the Lagrangian dual function with them never exceeds the exhaustive
assignment optimum at any prices; an inflated floor is caught."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from test_assignment_search import _problem

from covnet.core.allocation.assignment import MultiConstraints, allocate_assignments_exhaustive
from covnet.core.allocation.exact import Constraints, subset_covariance
from covnet.core.allocation.price_floor import price_floor
from covnet.core.allocation.search_problem import _Problem
from covnet.core.metrics import METRICS


def _exhaustive(P, J, D, metric, w, allowed, pi):
    """``min_S w f(P(S)) + π(S)`` over every subset of ``allowed`` (the empty one too)."""
    best = math.inf
    for k in range(len(allowed) + 1):
        for S in itertools.combinations(allowed, k):
            Jt = J[list(S)].sum(axis=0) if S else np.zeros_like(P)
            v = w * float(METRICS[metric](subset_covariance(P, Jt), D)) + float(pi[list(S)].sum())
            best = min(best, v)
    return best


METRIC_NAMES = ["spectral", "kl", "abs_trace", "one_norm", "frobenius", "svd", "trace_diff"]


@pytest.mark.parametrize("metric", METRIC_NAMES)
@pytest.mark.parametrize("seed", range(3))
def test_price_floor_exact_when_it_ends(metric, seed):
    """Run to its end (no limit, ``rel_gap = 0``), the search's best value is the exhaustive
    minimum with prices and its certified bound is at most that (and within rounding of it
    unless a leaf's bound is loose); with the metric's refinement and the root bound as its
    floor too; at N = 10, prices from none to dominant."""
    N = 10
    P, J, D, w, feas = _problem(N, 2, 20 + seed)
    t = 1
    excl = frozenset(np.flatnonzero(~feas[:, t]).tolist())
    allowed = [j for j in range(N) if j not in excl]
    prob = _Problem(P[t], J[:, t], D[t], metric, Constraints(excl), 1e-9)
    rng = np.random.default_rng(seed)
    base = float(METRICS[metric](P[t], D[t]))
    for scale in (0.0, 0.02, 0.2, 1.0):
        pi = scale * base * rng.uniform(size=N)
        best = _exhaustive(P[t], J[:, t], D[t], metric, w[t], allowed, pi)
        root = prob.root_bound()
        for refine, floor in ((False, -math.inf), (True, -math.inf), (False, root)):
            r = price_floor(prob, pi, w[t], refine=refine, floor=floor)
            assert r.done
            assert r.lower <= best + 1e-12 * abs(best), (scale, refine, r.lower, best)
            assert abs(r.upper - best) <= 1e-9 * abs(best), (scale, refine, r.upper, best)
            got = w[t] * float(
                METRICS[metric](subset_covariance(P[t], J[list(r.members), t].sum(axis=0)
                                                  if r.members else np.zeros((4, 4))), D[t])
            ) + float(pi[list(r.members)].sum())  # fmt: skip
            assert abs(got - r.upper) <= 1e-9 * abs(best)


@pytest.mark.parametrize("metric", ["spectral", "kl", "abs_trace"])
@pytest.mark.parametrize("limit", [1, 3, 9, 40])
def test_price_floor_certified_when_cut_short(metric, limit):
    """Stopped by its node limit (or a clock that has passed), the bound is still at most the
    exhaustive minimum with prices."""
    N = 10
    P, J, D, w, feas = _problem(N, 2, 31)
    allowed = [j for j in range(N) if feas[j, 0]]
    excl = frozenset(j for j in range(N) if j not in allowed)
    prob = _Problem(P[0], J[:, 0], D[0], metric, Constraints(excl), 1e-9)
    rng = np.random.default_rng(limit)
    for scale in (0.0, 0.05, 0.5):
        pi = scale * float(METRICS[metric](P[0], D[0])) * rng.uniform(size=N)
        best = _exhaustive(P[0], J[:, 0], D[0], metric, w[0], allowed, pi)
        for r in (
            price_floor(prob, pi, w[0], node_limit=limit),
            price_floor(prob, pi, w[0], rel_gap=0.05, node_limit=limit),
            price_floor(prob, pi, w[0], deadline=lambda: True),
        ):
            assert r.lower <= best + 1e-12 * abs(best)
            assert r.upper >= best - 1e-9 * abs(best)


def _dual(P, J, D, w, feas, metric, cons):
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    inp = _Inputs(P, J, D, metric, w, feas, cons, 1e-9)
    return srch._Dual(srch._Columns(inp), budget=10_000)


@pytest.mark.parametrize("metric", ["spectral", "kl", "abs_trace", "one_norm"])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("max_active", [None, 3])
def test_dual_with_price_floors_below_the_exhaustive_optimum(metric, seed, max_active):
    """Price-aware floors computed at some prices ``π⁰`` (each target's branch and bound,
    kept as ``(ℓ, π⁰)``, :meth:`_Dual._cost`: ``ℓ`` plus the ``k`` smallest ``π - π⁰``) leave
    ``L(π) <= F*`` at any prices ``π``, with the count limit binding or not; and at ``π⁰``
    they raise ``L`` to at least the sum of the floors less the prices."""
    N, T = 7, 3
    P, J, D, w, feas = _problem(N, T, 60 + seed)
    cons = MultiConstraints(max_active=max_active)
    ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas, cons)
    dual = _dual(P, J, D, w, feas, metric, cons)
    rng = np.random.default_rng(seed)
    for scale0 in (0.0, 0.05, 0.5):
        pi0 = scale0 * abs(ref.value) * rng.uniform(size=N)
        for c in range(T):
            col = dual.cs.cols[c]
            res = price_floor(col.prob, pi0, float(dual.cs.w[c]))
            dual.pfloors[c].append((res.lower, pi0[dual.opts[c]].copy()))
        for scale in (0.0, 0.01, 0.3, 3.0):
            for pi in (scale * abs(ref.value) * rng.uniform(size=N), pi0):
                L, counts = dual.value(pi)
                assert L <= ref.value, (scale0, scale, L, ref.value)
                assert dual.sep or sum(counts) <= (max_active or N)


@pytest.mark.parametrize("metric", ["spectral", "kl", "abs_trace"])
def test_an_inflated_price_floor_is_caught(metric):
    """The check above can fail: the floors at zero prices each raised by the same amount
    until their sum passes ``F*`` by 1 % put ``L(0)`` above ``F*`` (exact floors sum to at
    most ``F*``: the targets' best sets may overlap, the assignment's may not)."""
    N, T = 7, 3
    for seed in range(3):
        P, J, D, w, feas = _problem(N, T, 60 + seed)
        ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas)
        dual = _dual(P, J, D, w, feas, metric, MultiConstraints())
        pi0 = np.zeros(N)
        res = [price_floor(dual.cs.cols[c].prob, pi0, float(dual.cs.w[c])) for c in range(T)]
        assert sum(r.lower for r in res) <= ref.value
        lift = (1.01 * ref.value - sum(r.lower for r in res)) / T
        for c in range(T):
            dual.pfloors[c].append((res[c].lower + lift, pi0[dual.opts[c]]))
        assert dual.value(pi0)[0] > ref.value


@pytest.mark.parametrize("metric", ["spectral", "one_norm", "abs_trace", "inf_norm"])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("max_active", [None, 3])
def test_root_floors_below_the_exhaustive_optimum(metric, seed, max_active):
    """The root floors (:func:`_root_floors`, every target column, no clock) are at most each
    target's best set of its allowed sensors (exhaustive, weighted), and ``L(π) <= F*`` at any
    prices with them in; a floor raised above its target's best set is caught."""
    from covnet.core.allocation import assignment_search as srch

    N, T = 7, 3
    P, J, D, w, feas = _problem(N, T, 40 + seed)
    cons = MultiConstraints(max_active=max_active)
    ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas, cons)
    dual = _dual(P, J, D, w, feas, metric, cons)
    upper = np.full(T, 1e300)
    assert srch._root_floors(dual, upper, lambda: 10.0, 0.0) == T
    best = []
    for t in range(T):
        allowed = [j for j in range(N) if feas[j, t]]
        best.append(_exhaustive(P[t], J[:, t], D[t], metric, w[t], allowed, np.zeros(N)))
        assert dual.floor[t] <= best[t] * (1 + 1e-12)
    rng = np.random.default_rng(seed)
    for scale in (0.0, 0.01, 0.3, 3.0):
        pi = scale * abs(ref.value) * rng.uniform(size=N)
        assert dual.value(pi)[0] <= ref.value
    dual.floor[:T] = np.array(best) + 0.5 * abs(ref.value)
    assert dual.value(np.zeros(N))[0] > ref.value


def test_dual_steps_with_an_idle_mid_are_unchanged():
    """The dual steps' ``mid`` hook (the root floors among the steps) only re-evaluates: with
    a hook that raises nothing, the same best ``L`` bits and step count as without it."""
    from covnet.core.allocation import assignment_search as srch

    P, J, D, w, feas = _problem(9, 3, 7)
    ref = allocate_assignments_exhaustive(P, J, D, "spectral", w, feas)
    ran = []
    a = srch._dual_bound(_dual(P, J, D, w, feas, "spectral", MultiConstraints()), ref.value, 60,
                         0.0, None)  # fmt: skip
    b = srch._dual_bound(
        _dual(P, J, D, w, feas, "spectral", MultiConstraints()), ref.value, 60, 0.0, None,
        mid=ran.append, mid_when=lambda: True,
    )  # fmt: skip
    assert a == b and len(ran) == 1


def test_bounded_with_time_runs_the_root_floors(monkeypatch):
    """With a clock and a metric without ``floors_first`` (spectral), the bounded search runs
    the root floors among its dual steps; its bound stays at most the exact optimum."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import allocate_assignments

    ran = []
    roots = srch._root_floors
    monkeypatch.setattr(srch, "_root_floors", lambda *a: ran.append(roots(*a)) or ran[-1])
    N, T = 13, 3
    P, J, D, w, feas = _problem(N, T, 4)
    ref = allocate_assignments(P, J, D, "spectral", w, feas)
    ticks = iter(np.arange(0.0, 1e6, 1e-3))
    b = srch.allocate_assignments_bounded(
        P, J, D, "spectral", w, feas, rel_gap=0.0, time_limit_s=50.0,
        clock=lambda: float(next(ticks)),
    )  # fmt: skip
    assert ran and not b.exact
    assert b.lower_bound <= ref.value
