"""The timed plan's ejection chains (covnet.core.allocation.assignment_search._chain_moves,
round br16): a sensor leaves its target for another, an idle sensor takes its place.  The
tables' change ``A[c', j] + M[j, k]`` equals the change of ``F`` recomputed by hand; after
the chains no chain improves (exhaustively, ``F`` recomputed), the value only falls, stays
at least the exhaustive optimum and keeps the budget, caps and allowed pairs; the chains are
found on the bench's small problems where the local search stops (so the tests can fail);
where no chain improves the timed plan decides bit for bit as without them (a tick clock);
a broken chain (its change mis-tabled) is caught.

The exhaustive optimum is the fast exact allocator's (``allocate_assignments``: the
exhaustive reference's bits, tests/property/test_multitarget_equivalence.py); the exhaustive
loop itself took 11-30 s a case here."""

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

#: (metric, seed) of the bench's problems (N = 8, T = 3) where a chain improves the local
#: optimum of the forward greedy with moves and 1-swaps
CASES = [("trace_diff", 6), ("trace_diff", 12), ("trace_diff", 16), ("kl", 2), ("kl", 11)]


def _problems(metric, seed, N=8):
    return bm.problems(N, 3, metric, 3, seed=seed)


def _state(prob, metric, cons=NO_CONSTRAINTS):
    P, J, D, w, feas = prob
    inp = _Inputs(P, J, D, metric, w, feas, cons, 1e-9)
    cs = srch._Columns(inp)
    st = srch._State(cs)
    srch._forward(st)
    srch._local_search(st, None)
    return cs, st


def _F(cs, a):
    """``F`` by hand: each column's weighted value of its set."""
    sets = [[j for j in range(cs.N) if a[j] == c] for c in range(cs.ncol)]
    return sum(float(cs.w[c]) * cs.cols[c].val(sets[c]) for c in range(cs.ncol))


def _chains(cs, a):
    """Every chain (``j`` on ``c`` to ``c' != c``, an off ``k`` to ``c``) the constraints allow:
    ``(j, c', k)`` and the assignment after it."""
    a = list(a)
    n_on = sum(x != OFF for x in a)
    if n_on >= cs.K:
        return
    counts = [sum(x == c for x in a) for c in range(cs.ncol)]
    for j in range(cs.N):
        c = a[j]
        if c == OFF:
            continue
        for c2 in range(cs.ncol):
            if c2 == c or not cs.allow[c2, j] or counts[c2] >= cs.caps[c2]:
                continue
            for k in range(cs.N):
                if a[k] != OFF or not cs.allow[c, k]:
                    continue
                b = list(a)
                b[j], b[k] = c2, c
                yield (j, c2, k), b


def _found(metric, seed):
    """The bench's problems of ``seed`` where a chain improves the local search's optimum."""
    out = []
    for prob in _problems(metric, seed):
        cs, st = _state(prob, metric)
        a = [int(x) for x in st.a]
        F = _F(cs, a)
        if any(_F(cs, b) < F - srch.IMPROVE * abs(F) for _, b in _chains(cs, a)):
            out.append(prob)
    return out


@pytest.mark.parametrize(("metric", "seed"), CASES)
def test_chain_change_is_the_tables(metric, seed):
    """``A[c', j] + M[j, k]`` is the change of ``F`` (recomputed by hand) of every chain."""
    probs = _found(metric, seed)
    assert probs, "no chain improves here: the case list is stale"
    for prob in probs:
        cs, st = _state(prob, metric)
        st.fresh()
        a = [int(x) for x in st.a]
        F = _F(cs, a)
        n = 0
        for (j, c2, k), b in _chains(cs, a):
            d = float(st.A[c2, j] + st.M[j, k])
            assert d == pytest.approx(_F(cs, b) - F, rel=1e-7, abs=1e-9 * abs(F)), (j, c2, k)
            n += 1
        assert n > 0


@pytest.mark.parametrize(("metric", "seed"), CASES)
@pytest.mark.parametrize("budget", [False, True])
def test_chain_moves_improve_to_a_chain_optimum(metric, seed, budget):
    """After :func:`_chain_moves` no chain improves (exhaustively), ``F`` fell (strictly: the
    cases have one), stays at least the exhaustive optimum, and the constraints hold; with the
    budget at the local optimum's count, no chain (it turns one more sensor on)."""
    for prob in _found(metric, seed):
        P, J, D, w, feas = prob
        cs0, st0 = _state(prob, metric)
        n_on = int((st0.a != OFF).sum())
        cons = MultiConstraints(max_active=n_on + 1) if budget else NO_CONSTRAINTS
        cs, st = _state(prob, metric, cons)
        a0 = [int(x) for x in st.a]
        F0 = _F(cs, a0)
        taken = srch._chain_moves(st, None)
        a = [int(x) for x in st.a]
        F = _F(cs, a)
        assert taken >= 1 and F < F0
        assert st.F == pytest.approx(F, rel=1e-9)
        thr = srch.IMPROVE * abs(F)
        assert all(_F(cs, b) >= F - thr for _, b in _chains(cs, a))
        ref = allocate_assignments(P, J, D, metric, w, feas, cons)
        assert F >= ref.value * (1 - 1e-9)
        assert sum(x != OFF for x in a) <= cs.K
        for j, c in enumerate(a):
            assert c == OFF or cs.allow[c, j]
        assert all(sum(x == c for x in a) <= cs.caps[c] for c in range(cs.ncol))
        # at a budget of the local optimum's count no chain is possible
        cs1, st1 = _state(prob, metric, MultiConstraints(max_active=n_on))
        before = [int(x) for x in st1.a]
        assert srch._chain_moves(st1, None) == 0
        assert [int(x) for x in st1.a] == before


def test_a_broken_chain_is_caught():
    """A chain that tables ``k``'s change as joining ``c`` beside ``j`` (``R[j] + A[c', j] +
    A[c, k]``, the moves' sum, not the replacement) differs from the recomputed change: the
    oracle of :func:`test_chain_change_is_the_tables` catches it."""
    prob = _found("trace_diff", 16)[0]
    cs, st = _state(prob, "trace_diff")
    st.fresh()
    a = [int(x) for x in st.a]
    F = _F(cs, a)
    bad = 0
    for (j, c2, k), b in _chains(cs, a):
        d = float(st.R[j] + st.A[c2, j] + st.A[a[j], k])
        if d != pytest.approx(_F(cs, b) - F, rel=1e-7, abs=1e-9 * abs(F)):
            bad += 1
    assert bad > 0


def _timed(prob, metric, cons=NO_CONSTRAINTS):
    P, J, D, w, feas = prob
    ticks = (i * 1e-3 for i in itertools.count())  # 1 ms a reading, lazily
    return srch.allocate_assignments_bounded(
        P, J, D, metric, w, feas, cons, rel_gap=0.0, time_limit_s=0.5,
        clock=lambda: float(next(ticks)),
    )  # fmt: skip


def _same(r1, r2):
    assert r1.assignment == r2.assignment
    assert r1.value == r2.value
    assert r1.lower_bound == r2.lower_bound
    assert r1.n_nodes == r2.n_nodes
    assert r1.status == r2.status


@pytest.mark.parametrize("metric", ["trace_diff", "kl", "spectral", "abs_trace", "one_norm"])
def test_timed_plan_without_a_chain_is_bit_for_bit(metric, monkeypatch):
    """Where no chain improves, the timed plan (a tick clock) decides exactly as without the
    chains: the same assignment, value, bound and nodes (the chains read no clock then);
    where one does, the value is at most the one without."""
    calls = []
    real = srch._chain_moves
    # the chains alone (the kicks call them too: tests/unit/test_kicks.py)
    monkeypatch.setitem(METRICS, metric, dataclasses.replace(METRICS[metric], kicks=False))

    def spy(st, deadline):
        n = real(st, deadline)
        calls.append(n)
        return n

    same = 0
    for prob in _problems(metric, 3, N=13):
        monkeypatch.setattr(srch, "_chain_moves", spy)
        r1 = _timed(prob, metric)
        monkeypatch.setattr(srch, "_chain_moves", lambda st, deadline: 0)
        r0 = _timed(prob, metric)
        assert calls
        if calls[-1] == 0:  # none here: the plan as before
            _same(r1, r0)
            same += 1
        else:
            assert r1.value <= r0.value
    assert same >= 2


@pytest.mark.parametrize(("metric", "seed"), [("trace_diff", 15), ("trace_diff", 17)])
def test_timed_plan_with_chains_never_worse(metric, seed, monkeypatch):
    """With the chains the timed plan's value is at most the one without (a tick clock), at
    least the exact optimum, and its bound at most it (N = 13: no exact fallback)."""
    for prob in _problems(metric, seed, N=13):
        r1 = _timed(prob, metric)
        monkeypatch.setattr(srch, "_chain_moves", lambda st, deadline: 0)
        r0 = _timed(prob, metric)
        monkeypatch.undo()
        assert r1.value <= r0.value
        P, J, D, w, feas = prob
        ref = allocate_assignments(P, J, D, metric, w, feas)
        assert r1.lower_bound <= ref.value * (1 + 1e-9)
        assert r1.value >= ref.value * (1 - 1e-9)


def test_chains_only_in_the_timed_plan(monkeypatch):
    """``node_limit`` alone (the untimed order, ``configs/large_multitarget.yaml``) and the
    greedy search take no chain."""
    calls = []
    monkeypatch.setattr(srch, "_chain_moves", lambda st, deadline: calls.append(1) or 0)
    P, J, D, w, feas = _found("trace_diff", 16)[0]
    srch.allocate_assignments_bounded(P, J, D, "trace_diff", w, feas, node_limit=20)
    srch.allocate_assignments_greedy(P, J, D, "trace_diff", w, feas)
    assert not calls
    np.testing.assert_equal(len(calls), 0)
