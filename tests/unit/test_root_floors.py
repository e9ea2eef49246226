"""The timed plan's root floors (covnet.core.allocation.assignment_search, round mt12): each
root floor never exceeds the exhaustive minimum of its target; the Lagrangian dual function
with them never exceeds the exhaustive assignment optimum at any prices; an inflated floor is
caught; the dual steps' hook changes nothing when it raises nothing.

The exhaustive assignment optimum is the fast exact allocator's (``allocate_assignments``:
the exhaustive reference's bits, tests/property/test_multitarget_equivalence.py); the
exhaustive loop itself took seconds a case here."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from test_assignment_search import _problem, _timed_bounded

from covnet.core.allocation.assignment import MultiConstraints, allocate_assignments
from covnet.core.allocation.exact import subset_covariance
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



def _dual(P, J, D, w, feas, metric, cons):
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    inp = _Inputs(P, J, D, metric, w, feas, cons, 1e-9)
    return srch._Dual(srch._Columns(inp), budget=10_000)


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
    ref = allocate_assignments(P, J, D, metric, w, feas, cons)
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
    ref = allocate_assignments(P, J, D, "spectral", w, feas)
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

    ran = []
    roots = srch._root_floors
    monkeypatch.setattr(srch, "_root_floors", lambda *a: ran.append(roots(*a)) or ran[-1])
    ref, b = _timed_bounded("spectral")
    assert ran and not b.exact
    assert b.lower_bound <= ref.value


@pytest.mark.parametrize("seed", range(3))
def test_dual_steps_from_any_start_stay_below_the_optimum(seed):
    """Round mt13: the dual steps warm-started from any prices ``π0 >= 0`` (the second run of
    steps after the late floors) stay at most the exhaustive optimum, report the prices of
    their best ``L``, and ``π0 = 0`` gives the same bits as no start."""
    from covnet.core.allocation import assignment_search as srch

    N, T = 8, 3
    P, J, D, w, feas = _problem(N, T, 60 + seed)
    cons = MultiConstraints(max_active=3)
    ref = allocate_assignments(P, J, D, "spectral", w, feas, cons)
    plain = srch._dual_bound(_dual(P, J, D, w, feas, "spectral", cons), ref.value, 40, 0.0, None)
    zero = srch._dual_bound(_dual(P, J, D, w, feas, "spectral", cons), ref.value, 40, 0.0, None,
                            pi0=np.zeros(N))  # fmt: skip
    assert plain == zero
    rng = np.random.default_rng(seed)
    for scale in (0.01, 0.3, 3.0):
        dual = _dual(P, J, D, w, feas, "spectral", cons)
        out: list = []
        pi0 = scale * abs(ref.value) * rng.uniform(size=N)
        best, n = srch._dual_bound(dual, ref.value, 40, 0.0, None, pi0=pi0, best_out=out)
        assert best <= ref.value and 1 <= n <= 40
        assert best >= dual.value(pi0)[0] and dual.value(out[0])[0] == best


@pytest.mark.parametrize(("metric", "order"), [
    ("spectral", ["dual", "floors", "dual"]),  # root floors: the second round after the steps
    ("svd", ["floors", "dual"]),  # no root floors: as before
])  # fmt: skip
def test_second_floors_follow_the_steps_with_root_floors(monkeypatch, metric, order):
    """Round mt13: with root floors (spectral) the timed plan's second round of single-target
    floors runs after the dual steps stall, then the steps again from their best prices; other
    metrics (svd) keep the order before it.  The bound stays at most the exact optimum."""
    from covnet.core.allocation import assignment_search as srch

    calls: list[str] = []
    floors, steps = srch._floors, srch._dual_bound

    def rec_floors(*a, **k):
        calls.append("floors")
        return floors(*a, **k)

    def rec_steps(*a, **k):
        calls.append("dual")
        return steps(*a, **k)

    monkeypatch.setattr(srch, "_floors", rec_floors)
    monkeypatch.setattr(srch, "_dual_bound", rec_steps)
    ref, b = _timed_bounded(metric)
    assert calls == order and not b.exact
    assert b.lower_bound <= ref.value
