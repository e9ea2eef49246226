"""The timed plan's vertex rows (covnet.core.allocation.assignment_search, round mt15): the
count bound's and the enumeration's superset rows raised by the dual bound's vertex bound stay
at most the exhaustive minimum over the sets they bound; the Lagrangian dual function with them
never exceeds the exhaustive assignment optimum at any prices; an inflated row is caught; the
timed search runs them (and the induced norms' longer root barrier) for one_norm and not for
spectral (no vertex bound)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from test_assignment_search import _problem, _timed_bounded

from covnet.core.allocation.assignment import MultiConstraints, allocate_assignments_exhaustive
from covnet.core.allocation.exact import subset_covariance
from covnet.core.metrics import METRICS


def _values(P, J, D, metric, w, allowed):
    """``w f(P(S))`` of every subset ``S`` of ``allowed`` (a dict keyed by the sorted tuple)."""
    out = {}
    for k in range(len(allowed) + 1):
        for S in itertools.combinations(allowed, k):
            Jt = J[list(S)].sum(axis=0) if S else np.zeros_like(P)
            out[S] = w * float(METRICS[metric](subset_covariance(P, Jt), D))
    return out


def _timed_dual(P, J, D, w, feas, metric, cons):
    """The timed plan's bound: depth 1 first, then deepened to 2 keeping the depth-1 level."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    inp = _Inputs(P, J, D, metric, w, feas, cons, 1e-9)
    dual = srch._Dual(srch._Columns(inp), budget=100, timed=True)  # depth 2: pairs
    dual.deepen(None)
    return dual


def _bounds(dual, c, S0, S):
    """Whether column ``c``'s superset row of ``S0`` bounds the set ``S``: ``S0 ⊆ S``, and
    with the chain rows (round at16, abs_trace) ``S0`` is ``S``'s first ``|S0|`` members in
    the chain's order."""
    if not (S0 <= set(S) and len(S) > len(S0)):
        return False
    pos = dual.chain_pos.get(c)
    if pos is None:
        return True
    at = {int(j): int(p) for j, p in zip(dual.enum[c].o, pos, strict=True)}
    return set(sorted(S, key=at.__getitem__)[: len(S0)]) == S0


def _check_rows(dual, c, vals, slack=1e-12):
    """Every raised row of column ``c`` at most the least weighted value of the sets it bounds
    (count row ``k``: the ``k``-sets; a superset row of ``S0``: every superset of ``S0``, with
    the chain rows the sets whose first members they are, :func:`_bounds`); returns how many
    raised rows were checked."""
    en = dual.enum[c]
    o = [int(j) for j in en.o]
    checked = 0
    rows = dual.pieces[c]
    if rows is not None and rows.vdone is not None:
        for r, k in enumerate(rows.idx.tolist()):
            if rows.vdone[r]:
                best = min(v for S, v in vals.items() if len(S) == k)
                assert dual.h[c][k] <= best * (1 + slack) + 1e-12, (c, k)
                checked += 1
    levels = [(en.d, en.sup, en.rows)] + [
        (d0, sup, r) for (d0, sup), r in zip(en.lower, en.lower_rows, strict=True)
    ]
    for d0, sup, r in levels:
        if r is None or r.vdone is None:
            continue
        for i in np.flatnonzero(r.vdone).tolist():
            S0 = {o[x] for x in en.sets[d0][i]}
            best = min((v for S, v in vals.items() if _bounds(dual, c, S0, S)), default=math.inf)
            assert sup[i] <= best * (1 + slack) + 1e-12, (c, d0, S0)
            checked += 1
    return checked


@pytest.mark.parametrize("metric", ["one_norm", "inf_norm", "abs_trace"])
@pytest.mark.parametrize("seed", [0, 2, 3])  # 1: abs_trace's vertex bound raises no row there
@pytest.mark.parametrize("max_active", [None, 3])
def test_vertex_rows_below_the_exhaustive_optimum(metric, seed, max_active):
    """The vertex rows (:func:`_vertex_rows` at several prices, then every row of every
    column) raise the bound, each raised row is at most the exhaustive minimum over the sets it
    bounds, and ``L(π) <= F*`` at any prices with them in; rows raised above their sets'
    minimum are caught by the same checks."""
    from covnet.core.allocation import assignment_search as srch

    N, T = 7, 3
    P, J, D, w, feas = _problem(N, T, 70 + seed)
    cons = MultiConstraints(max_active=max_active)
    ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas, cons)
    dual = _timed_dual(P, J, D, w, feas, metric, cons)
    before = [dual._cost(c, np.zeros(N))[0].copy() for c in range(T)]
    rows0 = np.concatenate([np.concatenate([dual.h[c], e.sup, *(s for _, s in e.lower)])
                            for c, e in enumerate(dual.enum)])  # fmt: skip
    upper = np.full(T, 1e300)
    rng = np.random.default_rng(seed)
    prices = [np.zeros(N)] + [s * abs(ref.value) * rng.uniform(size=N) for s in (0.01, 0.3)]
    assert sum(srch._vertex_rows(dual, upper, pi, None) for pi in prices) > 0
    for c in range(T):
        dual.vertex(c, np.zeros(N), 10**6, None)
    after = [dual._cost(c, np.zeros(N))[0] for c in range(T)]
    assert all((a >= b).all() for a, b in zip(after, before, strict=True))
    rows1 = np.concatenate([np.concatenate([dual.h[c], e.sup, *(s for _, s in e.lower)])
                            for c, e in enumerate(dual.enum)])  # fmt: skip
    assert (rows1 >= rows0).all() and (rows1 > rows0 * (1 + 1e-9) + 1e-12).any()
    vals = []
    for c in range(T):
        allowed = [j for j in range(N) if feas[j, c]]
        vals.append(_values(P[c], J[:, c], D[c], metric, w[c], allowed))
        assert _check_rows(dual, c, vals[c]) > 0
    for scale in (0.0, 0.01, 0.3, 3.0):
        pi = scale * abs(ref.value) * rng.uniform(size=N)
        assert dual.value(pi)[0] <= ref.value
    # the checks can fail: every raised superset row lifted to its sets' maximum
    en = dual.enum[0]
    assert en.rows is not None and en.rows.vdone is not None
    o = [int(j) for j in en.o]
    for i in np.flatnonzero(en.rows.vdone).tolist():
        S0 = {o[x] for x in en.sets[en.d][i]}
        en.sup[i] = 2.0 * max(v for S, v in vals[0].items() if S0 <= set(S)) + 1.0
    with pytest.raises(AssertionError):
        _check_rows(dual, 0, vals[0])


def test_vertex_rows_raise_nothing_without_a_vertex_bound():
    """spectral's dual bound has no vertex bound: no row is raised, the bound's bits stay."""
    from covnet.core.allocation import assignment_search as srch

    N, T = 7, 3
    P, J, D, w, feas = _problem(N, T, 5)
    dual = _timed_dual(P, J, D, w, feas, "spectral", MultiConstraints())
    L = dual.value(np.zeros(N))[0]
    assert srch._vertex_rows(dual, np.full(T, 1e300), np.zeros(N), None) == 0
    assert dual.value(np.zeros(N))[0] == L


@pytest.mark.parametrize(("metric", "iters", "vertex"), [
    ("one_norm", 20, True),  # ROOT_ITERS_OF
    ("abs_trace", 12, True),
    ("spectral", 12, False),
])  # fmt: skip
def test_bounded_with_time_runs_the_vertex_rows(monkeypatch, metric, iters, vertex):
    """With a clock the bounded search raises the vertex rows after the root floors (one_norm,
    abs_trace; spectral raises none), one_norm's roots run 20 barrier iterations and the
    others' 12; the bound stays at most the exact optimum."""
    from covnet.core.allocation import assignment_search as srch

    calls: list[str] = []
    seen: list[int] = []
    roots, rows, its = srch._root_floors, srch._vertex_rows, srch._iterations

    def rec_roots(*a):
        calls.append("roots")
        return roots(*a)

    def rec_rows(*a):
        n = rows(*a)
        calls.append(f"vertex {n > 0}")
        return n

    def rec_its(n, out):
        seen.append(n)
        return its(n, out)

    monkeypatch.setattr(srch, "_root_floors", rec_roots)
    monkeypatch.setattr(srch, "_vertex_rows", rec_rows)
    monkeypatch.setattr(srch, "_iterations", rec_its)
    ref, b = _timed_bounded(metric)
    assert calls[:2] == ["roots", f"vertex {vertex}"] and not b.exact
    assert seen and set(seen) == {iters}
    assert b.lower_bound <= ref.value
    assert math.isfinite(b.lower_bound)
