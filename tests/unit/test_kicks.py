"""The timed plan's iterated local search (covnet.core.allocation.assignment_search._kicks):
random reassignments of a few sensors, then the local search and the ejection chains, kept
only when ``F`` falls.  It never makes the value worse; every state it returns keeps the
allowed pairs, the caps, the budget and the required sensors (checked with all of them
binding, so a kick that ignored one would be caught); it finds better assignments where the
local search and the chains stop (so the tests can fail); the same problem and clock give the
same decision; and the metrics without it (``Metric.kicks``) decide bit for bit as before."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from covnet.core.allocation import assignment_search as srch
from covnet.core.allocation.assignment import (
    NO_CONSTRAINTS,
    OFF,
    MultiConstraints,
    _Inputs,
    allocate_assignments,
)
from covnet.core.metrics import METRICS
from covnet.covariance_control import bench_multitarget as bm


def _local_optimum(prob, metric, cons=NO_CONSTRAINTS):
    P, J, D, w, feas = prob
    cs = srch._Columns(_Inputs(P, J, D, metric, w, feas, cons, 1e-9))
    st = srch._State(cs)
    srch._forward(st)
    srch._local_search(st, None)
    srch._chain_moves(st, None)
    return cs, st


def _after(n):
    """An ``until`` that says so at its ``n``-th reading (a kick reads it, and so do its local
    search and chains)."""
    count = itertools.count()
    return lambda: next(count) >= n


def _feasible(cs, a, cons):
    assert all(c == OFF or cs.allow[c, j] for j, c in enumerate(a))
    assert all(sum(x == c for x in a) <= cs.caps[c] for c in range(cs.ncol))
    assert sum(x != OFF for x in a) <= cs.K
    assert all(a[j] != OFF for j in cons.required)


@pytest.mark.parametrize("metric", ["spectral", "abs_trace", "trace_diff"])
def test_kicks_never_worse_and_better_where_the_local_search_stops(metric):
    better = 0
    for seed in range(4):
        prob = bm.problems(16, 4, metric, 2, seed=seed)[1]
        cs, st = _local_optimum(prob, metric)
        F0 = st.F
        best, n = srch._kicks(st, _after(60), np.random.default_rng(srch.KICK_SEED))
        assert best.F <= F0
        assert (n > 0) == (best.F < F0)
        # the working values are the state's: F of its sets, recomputed
        a = [int(x) for x in best.a]
        sets = [[j for j in range(cs.N) if a[j] == c] for c in range(cs.ncol)]
        F = sum(float(cs.w[c]) * cs.cols[c].val(sets[c]) for c in range(cs.ncol))
        assert F == pytest.approx(best.F, rel=1e-12)
        _feasible(cs, a, NO_CONSTRAINTS)
        better += n > 0
    assert better >= 2  # the kicks find what the moves, swaps and chains do not


@pytest.mark.parametrize("metric", ["spectral", "trace_diff"])
def test_every_kicked_state_keeps_the_constraints(metric, monkeypatch):
    """Caps of 2, a budget of 5 and two required sensors, all binding: every state the kicks
    make (before the local search) is feasible."""
    prob = bm.problems(12, 3, metric, 2, seed=3)[1]
    cons = MultiConstraints(required=frozenset({0, 5}), max_active=5, max_per_target=2)
    cs, st = _local_optimum(prob, metric, cons)
    seen = []
    real = srch._local_search

    def spy(s, deadline):
        seen.append([int(x) for x in s.a])  # the kicked state, before its local search
        return real(s, deadline)

    monkeypatch.setattr(srch, "_local_search", spy)
    best, _ = srch._kicks(st, _after(600), np.random.default_rng(1))
    assert len(seen) >= 30
    for a in seen:
        _feasible(cs, a, cons)
    _feasible(cs, [int(x) for x in best.a], cons)


def _timed(prob, metric):
    P, J, D, w, feas = prob
    ticks = (i * 1e-3 for i in itertools.count())  # 1 ms a reading, lazily
    return srch.allocate_assignments_bounded(
        P, J, D, metric, w, feas, rel_gap=0.0, time_limit_s=0.3,
        clock=lambda: float(next(ticks)),
    )  # fmt: skip


@pytest.mark.parametrize("metric", ["spectral", "abs_trace", "trace_diff", "one_norm", "kl"])
def test_the_timed_plan_with_kicks(metric, monkeypatch):
    """N = 16 (beyond the exact fallback), a tick clock: the same decision twice; for the
    metrics with ``Metric.kicks`` the kicks run and the value is at most the plan's without
    them (the state they start from is the same), the bound at most the exact optimum; for the
    others the plan is bit for bit the one without."""
    prob = bm.problems(16, 2, metric, 2, seed=5)[1]
    calls = []
    real = srch._kicks

    def spy(st, until, rng):
        out = real(st, until, rng)
        calls.append(out[1])
        return out

    monkeypatch.setattr(srch, "_kicks", spy)
    r1, r2 = _timed(prob, metric), _timed(prob, metric)
    assert (r1.assignment, r1.value, r1.lower_bound) == (r2.assignment, r2.value, r2.lower_bound)
    kicked = METRICS[metric].kicks
    assert bool(calls) == kicked
    monkeypatch.setitem(METRICS, metric, dataclasses.replace(METRICS[metric], kicks=False))
    r0 = _timed(prob, metric)
    if kicked or calls:
        assert r1.value <= r0.value
    else:
        assert (r1.assignment, r1.value, r1.lower_bound, r1.n_nodes) == (
            r0.assignment,
            r0.value,
            r0.lower_bound,
            r0.n_nodes,
        )
    P, J, D, w, feas = prob
    ref = allocate_assignments(P, J, D, metric, w, feas)  # exact (2^16 tables a target)
    assert r1.lower_bound <= ref.value * (1 + 1e-9) + 1e-12 <= r1.value * (1 + 2e-9) + 1e-12
