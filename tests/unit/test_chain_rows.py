"""The timed plan's chain rows (covnet.core.allocation.assignment_search, round at16):
abs_trace's and trace_diff's depth-1 superset rows raised by the chain (the sets whose first
member, in the order of those rows, is ``j``: the interval ``[Z({j}), Z({j} ∪ later)]``), their
deeper rows by the chain's next level and then by their next member (``_expand_rows``) stay
at most the exhaustive minimum over the sets they bound; each column's bound at every count and
price at most the exhaustive minimum with prices; the Lagrangian dual function never exceeds
the exhaustive assignment optimum at any prices (with and without a binding budget, and after
the vertex rows raise the chain's intervals); rows raised above their sets' minimum are
caught; the other metrics get no chain.

The exhaustive assignment optimum is the fast exact allocator's (``allocate_assignments``:
the exhaustive reference's bits, tests/property/test_multitarget_equivalence.py); the
exhaustive loop itself took seconds a case here."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from test_assignment_search import _problem, _timed_bounded
from test_vertex_rows import _values

from covnet.core.allocation.assignment import MultiConstraints, allocate_assignments
from covnet.core.metrics import METRICS


def _dual(P, J, D, w, feas, metric, cons, chain=True, monkeypatch=None):
    """The timed plan's bound (depth 1 with the chain rows, deepened to pairs)."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    if not chain:
        assert monkeypatch is not None
        entry = METRICS[metric]
        monkeypatch.setitem(METRICS, metric, dataclasses.replace(entry, chain_rows=False))
    inp = _Inputs(P, J, D, metric, w, feas, cons, 1e-9)
    dual = srch._Dual(srch._Columns(inp), budget=200, timed=True)
    dual.deepen(None)
    if not chain:
        monkeypatch.undo()
    return dual


def _first(dual, c, S, d0):
    """The first ``d0`` members of ``S`` in column ``c``'s chain order."""
    at = {int(j): int(p) for j, p in zip(dual.enum[c].o, dual.chain_pos[c], strict=True)}
    return frozenset(sorted(S, key=at.__getitem__)[:d0])


def _levels(dual, c):
    en = dual.enum[c]
    return [(en.d, en.sup)] + [(d0, sup) for d0, sup in en.lower]


def _check_chain(dual, c, vals, slack=1e-12):
    """Every chain row of column ``c`` (its depth-1 and pair rows) at most the least weighted
    value of the sets whose first members (``|S| > d0``) they are; returns how many rows bound
    a non-empty class."""
    en = dual.enum[c]
    o = [int(j) for j in en.o]
    checked = 0
    for d0, sup in _levels(dual, c):
        best: dict[frozenset[int], float] = {}
        for S, v in vals.items():
            if len(S) > d0:
                key = _first(dual, c, S, d0)
                best[key] = min(best.get(key, math.inf), v)
        for i, row in enumerate(en.sets[d0]):
            S0 = frozenset(o[x] for x in row)
            if S0 in best:
                assert sup[i] <= best[S0] * (1 + slack) + 1e-12, (c, d0, sorted(S0))
                checked += 1
    return checked


def _check_costs(dual, c, vals, pi, slack=1e-12):
    """Column ``c``'s bound at count ``k`` at most ``min_{|S|=k} w g(S) + π(S)``."""
    cost = dual._cost(c, pi)[0]
    for k in range(cost.size):
        best = min((v + float(pi[list(S)].sum()) for S, v in vals.items() if len(S) == k),
                   default=math.inf)  # fmt: skip
        assert cost[k] <= best * (1 + slack) + 1e-12, (c, k)


@pytest.mark.parametrize("metric", ["abs_trace", "trace_diff"])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("max_active", [None, 3])
def test_chain_rows_below_the_exhaustive_optimum(monkeypatch, metric, seed, max_active):
    """abs_trace, trace_diff, N = 8, T = 3: the chain raises rows above the plain superset
    rows, each row
    is at most the exhaustive minimum over its sets, every column's bound at most the
    exhaustive minimum with prices, and ``L(π) <= F*`` at any prices, before and after the
    vertex rows raise the chain's intervals."""
    from covnet.core.allocation import assignment_search as srch

    N, T = 8, 3
    P, J, D, w, feas = _problem(N, T, 90 + seed)
    cons = MultiConstraints(max_active=max_active)
    ref = allocate_assignments(P, J, D, metric, w, feas, cons)
    plain = _dual(P, J, D, w, feas, metric, cons, chain=False, monkeypatch=monkeypatch)
    dual = _dual(P, J, D, w, feas, metric, cons)
    assert not plain.chain_pos and set(dual.chain_pos) == set(range(T))
    old = np.concatenate([np.concatenate([s for _, s in _levels(plain, c)]) for c in range(T)])
    new = np.concatenate([np.concatenate([s for _, s in _levels(dual, c)]) for c in range(T)])
    assert (new >= old).all() and (new > old * (1 + 1e-9) + 1e-12).any()
    vals = []
    for c in range(T):
        allowed = [j for j in range(N) if feas[j, c]]
        vals.append(_values(P[c], J[:, c], D[c], metric, w[c], allowed))
        assert _check_chain(dual, c, vals[c]) > 0
    rng = np.random.default_rng(seed)
    prices = [s * abs(ref.value) * rng.uniform(size=N) for s in (0.0, 0.01, 0.1, 0.3, 3.0)]
    for pi in prices:
        for c in range(T):
            _check_costs(dual, c, vals[c], pi)
        assert dual.value(pi)[0] <= ref.value
    # the chain rows expanded by their next member (every row of every column, at each price)
    before = np.concatenate([dual.enum[c].sup for c in range(T)])
    monkeypatch.setattr(srch, "EXPAND_ROWS", 10**6)
    assert sum(srch._expand_rows(dual, pi, None) for pi in prices) > 0
    raised = np.concatenate([dual.enum[c].sup for c in range(T)])
    assert (raised >= before).all()
    if metric == "abs_trace":  # (trace_diff: on some seeds the next member raises none)
        assert (raised > before * (1 + 1e-9) + 1e-12).any()
    for c in range(T):
        assert dual.enum[c].xdone is not None and dual.enum[c].xdone.all()
        _check_chain(dual, c, vals[c])
    for pi in prices:
        for c in range(T):
            _check_costs(dual, c, vals[c], pi)
        assert dual.value(pi)[0] <= ref.value
    # the vertex rows on the chain's intervals (every row of every column)
    for c in range(T):
        dual.vertex(c, np.zeros(N), 10**6, None)
    srch._vertex_rows(dual, np.full(T, 1e300), prices[2], None)
    for c in range(T):
        _check_chain(dual, c, vals[c])
    for pi in prices:
        for c in range(T):
            _check_costs(dual, c, vals[c], pi)
        assert dual.value(pi)[0] <= ref.value


def test_inflated_chain_rows_are_caught():
    """The checks can fail: a chain row lifted 1.5-fold above its class's minimum (and a pair
    row built as if its class reached only its own pair) is caught."""
    N, T, metric = 8, 3, "abs_trace"
    P, J, D, w, feas = _problem(N, T, 90)
    dual = _dual(P, J, D, w, feas, metric, MultiConstraints())
    allowed = [j for j in range(N) if feas[j, 0]]
    vals = _values(P[0], J[:, 0], D[0], metric, w[0], allowed)
    assert _check_chain(dual, 0, vals) > 0
    en = dual.enum[0]
    o = [int(j) for j in en.o]
    d0, sup = en.lower[0]
    saved = sup.copy()
    best: dict[int, float] = {}
    for S, v in vals.items():
        if len(S) > 1:
            j = next(iter(_first(dual, 0, S, 1)))
            best[j] = min(best.get(j, math.inf), v)
    for i in range(sup.size):
        if o[i] in best:
            sup[i] = 1.5 * best[o[i]] + 1.0
    with pytest.raises(AssertionError):
        _check_chain(dual, 0, vals)
    sup[:] = saved
    _check_chain(dual, 0, vals)
    # a wrong chain: each pair row the exact value of its pair (as if no later member)
    en.sup = np.maximum(en.sup, 1.5 * en.exact[2] + 1.0)
    with pytest.raises(AssertionError):
        _check_chain(dual, 0, vals)


@pytest.mark.parametrize("metric", ["spectral", "one_norm", "inf_norm", "svd", "kl"])
def test_no_chain_for_the_other_metrics(metric):
    """Only the metrics with ``Metric.chain_rows`` (abs_trace, trace_diff) get chain rows."""
    N, T = 7, 3
    P, J, D, w, feas = _problem(N, T, 5)
    dual = _dual(P, J, D, w, feas, metric, MultiConstraints())
    assert not dual.chain_pos


def test_bounded_with_time_runs_the_chain(monkeypatch):
    """With a clock, abs_trace's bounded search raises the chain rows of every target column,
    deepens them with the chain's next level and expands them among the dual steps; the bound
    stays at most the exact optimum."""
    from covnet.core.allocation import assignment_search as srch

    calls: list[str] = []
    chain, chain2 = srch._Dual.chain, srch._Dual.chain2

    def rec_chain(self, c):
        done = chain(self, c)
        calls.append(f"chain {done}")
        return done

    def rec_chain2(self, c):
        done = chain2(self, c)
        calls.append(f"pairs {done}")
        return done

    expand = srch._expand_rows

    def rec_expand(*a):
        n = expand(*a)
        calls.append(f"expand {n > 0}")
        return n

    monkeypatch.setattr(srch._Dual, "chain", rec_chain)
    monkeypatch.setattr(srch._Dual, "chain2", rec_chain2)
    monkeypatch.setattr(srch, "_expand_rows", rec_expand)
    ref, b = _timed_bounded("abs_trace")
    assert calls.count("chain True") == 3 and "pairs True" in calls
    assert calls[-1] == "expand True"
    assert not b.exact and math.isfinite(b.lower_bound)
    assert b.lower_bound <= ref.value


def test_chain_classes_partition_the_sets():
    """The proof's premise, on the chain order of a real column: every set of at least
    ``d0`` members has exactly one first-``d0`` key, a ``d0``-subset of it (so each set is
    above exactly one row per level)."""
    N, T = 8, 3
    P, J, D, w, feas = _problem(N, T, 91)
    dual = _dual(P, J, D, w, feas, "abs_trace", MultiConstraints())
    o = [int(j) for j in dual.enum[0].o]
    for k in range(1, len(o) + 1):
        for S in itertools.combinations(o, k):
            for d0 in (1, 2):
                if k >= d0:
                    key = _first(dual, 0, S, d0)
                    assert len(key) == d0 and key <= set(S)
