"""Many targets at scale (covnet.core.allocation.assignment_search) and search cells: the
certified bound never exceeds the exhaustive optimum, the searches' values are exact and
never worse than a plain forward greedy with 1-swaps, cells agree with the reference."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from covnet.core.allocation.assignment import (
    OFF,
    CellTerms,
    MultiConstraints,
    TooManySensors,
    allocate_assignments,
    allocate_assignments_exhaustive,
)
from covnet.core.allocation.assignment_search import (
    allocate_assignments_bounded,
    allocate_assignments_greedy,
)
from covnet.core.allocation.exact import subset_covariance
from covnet.core.metrics import METRICS
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensing import correlated_noise, information_gain, position_matrix


def _problem(N, T, seed):
    rng = np.random.default_rng(seed)
    H = position_matrix()
    J = np.zeros((N, T, 4, 4))
    for j in range(N):
        for t in range(T):
            sx, sy = rng.uniform(5.0, 40.0, 2)
            J[j, t] = 0.9 * information_gain(H, correlated_noise(sx, sy, rng.uniform(-0.8, 0.8)))
    F, Q = cv_transition(1.0), dwna_process_noise(1.0, 0.5)
    P = np.array([F @ np.diag([60.0, 6.0, 60.0, 6.0]) * (1 + t) @ F.T + Q for t in range(T)])
    D = np.array([np.diag([d, d / 15, d, d / 15]) for d in rng.uniform(5.0, 30.0, T)])
    w = rng.uniform(0.5, 2.0, T)
    feas = rng.uniform(size=(N, T)) < 0.8
    feas[:, 0] = True
    return P, J, D, w, feas



def _timed_bounded(metric, seed=4, N=13, T=3):
    """A problem of ``_problem``, its exact optimum (``allocate_assignments``) and the bounded
    search on it with time to spare: a fake clock, 1 ms a reading, a 50 s limit (the module's
    functions looked up when called, so a test's monkeypatching takes effect)."""
    from covnet.core.allocation import assignment_search as srch

    P, J, D, w, feas = _problem(N, T, seed)
    ref = allocate_assignments(P, J, D, metric, w, feas)
    ticks = (i * 1e-3 for i in itertools.count())  # 1 ms a reading, lazily
    b = srch.allocate_assignments_bounded(
        P, J, D, metric, w, feas, rel_gap=0.0, time_limit_s=50.0,
        clock=lambda: float(next(ticks)),
    )  # fmt: skip
    return ref, b

def _cells(N, C, seed):
    rng = np.random.default_rng([seed, 7])
    return CellTerms(
        rng.uniform(0.0, 2.0, C),
        3.0,
        rng.uniform(0.05, 0.9, (N, C)),
        rng.uniform(size=(N, C)) < 0.7,
    )


def _F(P, J, D, w, metric, a, cells=None):
    """F by hand: targets' w_t f, then the cells' λ u_c Π miss."""
    T = P.shape[0]
    F = 0.0
    for t in range(T):
        Jt = np.zeros((4, 4))
        for j, x in enumerate(a):
            if x == t:
                Jt = Jt + J[j, t]
        F = F + w[t] * float(METRICS[metric](subset_covariance(P[t], Jt), D[t]))
    if cells is not None:
        for c in range(cells.C):
            g = cells.weight * cells.u[c]
            for j, x in enumerate(a):
                if x == T + c:
                    g = g * cells.miss[j, c]
            F = F + g
    return F


def _plain_greedy(P, J, D, w, feas, metric, cells=None):
    """A plain forward greedy (best improving pair while one improves, at least one on) with
    best-improvement moves and 1-swaps, on exact values."""
    N, T = feas.shape
    C = 0 if cells is None else cells.C
    allow = [[t for t in range(T) if feas[j, t]] + [T + c for c in range(C) if cells.feasible[j, c]]
             for j in range(N)]  # fmt: skip

    def val(a):
        return _F(P, J, D, w, metric, a, cells)

    a = [OFF] * N
    cur = val(a)
    while True:
        best = None
        for j in range(N):
            if a[j] == OFF:
                for c in allow[j]:
                    b = list(a)
                    b[j] = c
                    v = val(b)
                    if best is None or v < best[0]:
                        best = (v, b)
        if best is None or (any(x != OFF for x in a) and not best[0] < cur):
            break
        cur, a = best
    while True:
        best = None
        for j in range(N):
            for c in allow[j] + [OFF]:
                if c != a[j]:
                    b = list(a)
                    b[j] = c
                    if any(x != OFF for x in b):
                        v = val(b)
                        if best is None or v < best[0]:
                            best = (v, b)
            for k in range(j + 1, N):
                if a[j] != a[k] and (a[k] in allow[j] + [OFF]) and (a[j] in allow[k] + [OFF]):
                    b = list(a)
                    b[j], b[k] = a[k], a[j]
                    v = val(b)
                    if best is None or v < best[0]:
                        best = (v, b)
        if best is None or not best[0] < cur - 1e-12 * abs(cur):
            return cur
        cur, a = best


@pytest.mark.parametrize("metric", ["kl", "spectral", "abs_trace", "logdet"])
@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("with_cells", [False, True])
def test_bound_below_the_exhaustive_optimum_and_values_exact(metric, seed, with_cells):
    N, T = 5, 2
    P, J, D, w, feas = _problem(N, T, seed)
    cells = _cells(N, 2, seed) if with_cells else None
    ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas, cells=cells)
    for search in (allocate_assignments_greedy, allocate_assignments_bounded):
        res = search(P, J, D, metric, w, feas, cells=cells)
        assert res.lower_bound <= ref.value
        assert res.value >= ref.value * (1 - 1e-12)
        assert res.value == _F(P, J, D, w, metric, res.assignment, cells)
        assert 0.0 <= res.gap and res.value_nothing == _F(P, J, D, w, metric, [OFF] * N, cells)
    # bounded at this size falls back on the exact allocator: the reference's assignment
    b = allocate_assignments_bounded(P, J, D, metric, w, feas, cells=cells, rel_gap=0.0)
    assert (b.assignment, b.value) == (ref.assignment, ref.value) and b.exact


@pytest.mark.parametrize("metric", ["kl", "spectral", "frobenius"])
@pytest.mark.parametrize("seed", range(3))
def test_never_worse_than_plain_forward_greedy_with_swaps(metric, seed):
    P, J, D, w, feas = _problem(7, 3, 10 + seed)
    cells = _cells(7, 1, seed) if seed == 2 else None
    plain = _plain_greedy(P, J, D, w, feas, metric, cells)
    for search in (allocate_assignments_greedy, allocate_assignments_bounded):
        res = search(P, J, D, metric, w, feas, cells=cells)
        assert res.value <= plain * (1 + 1e-9)


@pytest.mark.parametrize("seed", range(5))
def test_cells_exact_agrees_with_the_reference(seed):
    P, J, D, w, feas = _problem(5, 2, seed)
    cells = _cells(5, 2, seed)
    for metric in ("kl", "abs_trace"):
        ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas, cells=cells)
        fast = allocate_assignments(P, J, D, metric, w, feas, cells=cells)
        assert (fast.assignment, fast.value, fast.cell_values) == (
            ref.assignment, ref.value, ref.cell_values,
        )  # fmt: skip
        assert len(ref.sets) == 4
        assert ref.value == _F(P, J, D, w, metric, ref.assignment, cells)
        best = min(
            _F(P, J, D, w, metric, a, cells)
            for a in itertools.product([OFF, 0, 1, 2, 3], repeat=5)
            if any(x != OFF for x in a)
            and all(
                x == OFF or (x < 2 and feas[j, x]) or (x >= 2 and cells.feasible[j, x - 2])
                for j, x in enumerate(a)
            )  # fmt: skip
        )
        assert ref.value <= best * (1 + 1e-9)


def test_no_cells_is_todays_result():
    P, J, D, w, feas = _problem(5, 3, 4)
    a = allocate_assignments(P, J, D, "kl", w, feas)
    b = allocate_assignments(P, J, D, "kl", w, feas, cells=None)
    assert (a.assignment, a.value, a.cell_values) == (b.assignment, b.value, ())


def test_constraints_hold():
    P, J, D, w, feas = _problem(9, 3, 2)
    mc = MultiConstraints(excluded=frozenset({0}), required=frozenset({1}), max_active=3,
                          max_per_target=1)  # fmt: skip
    for search in (allocate_assignments_greedy, allocate_assignments_bounded):
        r = search(P, J, D, "kl", w, feas, mc)
        assert r.assignment[0] == OFF and r.assignment[1] != OFF
        assert r.n_active <= 3 and all(len(r.sets[t]) <= 1 for t in range(3))


def test_exact_refuses_what_it_cannot_enumerate_and_bounded_serves_it():
    P, J, D, w, feas = _problem(24, 2, 5)
    with pytest.raises(TooManySensors, match="at most 22"):
        allocate_assignments(P, J, D, "kl", w, feas)
    r = allocate_assignments_bounded(P, J, D, "kl", w, feas, node_limit=5)
    assert r.lower_bound <= r.value and r.n_active >= 1


def test_time_limit_bounds_the_decision():
    P, J, D, w, feas = _problem(30, 4, 6)
    ticks = iter(range(1000))
    r = allocate_assignments_bounded(
        P, J, D, "kl", w, feas, rel_gap=0.0, time_limit_s=3.0, clock=lambda: float(next(ticks))
    )
    assert r.status in (2, 3) and r.lower_bound <= r.value


@pytest.mark.parametrize("metric", ["kl", "spectral", "abs_trace", "frobenius"])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("budget", [0, 12, 60, 10_000])
@pytest.mark.parametrize("max_active", [None, 3])
def test_dual_function_below_the_exhaustive_optimum_at_any_prices(metric, seed, budget, max_active):
    """L(π) <= F* for every π >= 0: the enumeration bound at every depth (none, 1, 2, all
    sets), with the count limit binding (the dynamic programme) or not (separable)."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    N, T = 6, 3
    P, J, D, w, feas = _problem(N, T, 50 + seed)
    cons = MultiConstraints(max_active=max_active)
    ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas, cons)
    inp = _Inputs(P, J, D, metric, w, feas, cons, 1e-9)
    dual = srch._Dual(srch._Columns(inp), budget=budget)
    assert not dual.sep  # 3 targets x ~5 sensors > 6
    rng = np.random.default_rng(seed)
    # the separable form drops "Σ k_c <= K'": a relaxation, valid (weaker) here too
    for scale, dual.sep in itertools.product((0.0, 0.01, 0.3, 3.0), (False, True)):
        pi = scale * abs(ref.value) * rng.uniform(size=N)
        L, counts = dual.value(pi)
        assert L <= ref.value, (scale, L, ref.value)
        assert len(counts) == T and (dual.sep or sum(counts) <= (max_active or N))
        g = dual.subgradient(pi, counts)
        assert g.shape == (N,) and (g >= -1).all()


def test_enumeration_depths_within_the_budget():
    from covnet.core.allocation.assignment_search import ENUM_DEPTH, _depths

    assert _depths([64] * 8, 20_000) == [2] * 8  # 8 x (64 + 2016) sets
    assert _depths([256] * 16, 20_000) == [1] * 16
    assert _depths([5, 0, 3], 10**6) == [min(5, ENUM_DEPTH), 0, 3]
    assert _depths([10, 10], 15) == [1, 0]


def test_enumeration_bound_exact_for_a_single_sensor_per_target():
    """With every target allowed one sensor only, the enumeration bound is the exact value
    less its rounding allowance (relative 1e-6 here): the gap closes without any search."""
    N, T = 4, 4
    P, J, D, w, _ = _problem(N, T, 3)
    feas = np.eye(N, dtype=bool)
    for metric in ("spectral", "abs_trace", "kl"):
        ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas)
        res = allocate_assignments_greedy(P, J, D, metric, w, feas)
        assert res.value == ref.value
        assert ref.value * (1 - 1e-6) <= res.lower_bound <= ref.value


@pytest.mark.parametrize("metric", ["kl", "spectral", "abs_trace"])
@pytest.mark.parametrize("seed", [0, 9, 1])
def test_no_improving_set_move_is_left(metric, seed, monkeypatch):
    """With every enumerated set tried (ENUM_MOVES large), the result admits no improving
    set move: no target's set replaced by a set of at most 2 sensors that are off or on it
    (checked by hand on exact values) lowers F.  (Seeds 0 and 9: moves and 1-swaps alone
    leave one for spectral and abs_trace.)"""
    from covnet.core.allocation import assignment_search as srch

    monkeypatch.setattr(srch, "ENUM_MOVES", 10**6)
    N, T = 12, 2
    P, J, D, w, feas = _problem(N, T, 70 + seed)
    res = allocate_assignments_greedy(P, J, D, metric, w, feas)
    a = list(res.assignment)
    F = _F(P, J, D, w, metric, a)
    for t in range(T):
        free = [j for j in range(N) if feas[j, t] and a[j] in (OFF, t)]
        for k in (1, 2):
            for mem in itertools.combinations(free, k):
                b = [OFF if x == t else x for x in a]
                for j in mem:
                    b[j] = t
                assert _F(P, J, D, w, metric, b) >= F * (1 - 1e-9), (t, mem)


@pytest.mark.parametrize("metric", ["kl", "spectral", "abs_trace"])
@pytest.mark.parametrize("seed", range(3))
def test_single_target_floors_below_the_exhaustive_optimum(metric, seed):
    """Each target's floor (the single-target bounded search's certified bound, weighted) is at
    most its best non-empty set of allowed sensors (exhaustive), and L(π) <= F* at any prices
    with the floors in."""
    from covnet.core.allocation import allocate_exhaustive
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs
    from covnet.core.allocation.exact import Constraints

    N, T = 7, 3
    P, J, D, w, feas = _problem(N, T, 80 + seed)
    ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas)
    inp = _Inputs(P, J, D, metric, w, feas, MultiConstraints(), 1e-9)
    cs = srch._Columns(inp)
    dual = srch._Dual(cs, budget=0)  # no enumeration: the floors carry the bound
    assert srch._floors(dual, np.full(T, np.inf), lambda: 10.0) == T
    for t in range(T):
        excl = frozenset(int(j) for j in np.flatnonzero(~feas[:, t]))
        best = allocate_exhaustive(P[t], J[:, t], D[t], metric, Constraints(excl))
        assert dual.floor[t] <= w[t] * best.value
    rng = np.random.default_rng(seed)
    for scale in (0.0, 0.01, 0.3, 3.0):
        pi = scale * abs(ref.value) * rng.uniform(size=N)
        assert dual.value(pi)[0] <= ref.value


def test_bounded_with_time_takes_the_floors(monkeypatch):
    """With time to spare (a fake clock) the bounded search runs a floor for every target,
    and its bound is at least greedy's (the same start; the floors and more dual steps on top)
    and at most the exact optimum (N = 13: above the exact fallback)."""
    from covnet.core.allocation import assignment_search as srch

    ran = []
    floors = srch._floors
    monkeypatch.setattr(srch, "_floors", lambda *a: ran.append(floors(*a)) or ran[-1])
    N, T = 13, 3
    P, J, D, w, feas = _problem(N, T, 4)
    ref = allocate_assignments(P, J, D, "spectral", w, feas)
    g = allocate_assignments_greedy(P, J, D, "spectral", w, feas)
    ticks = (i * 1e-3 for i in itertools.count())  # 1 ms a reading, lazily
    b = allocate_assignments_bounded(
        P, J, D, "spectral", w, feas, rel_gap=0.0, time_limit_s=50.0,
        clock=lambda: float(next(ticks)),
    )  # fmt: skip
    assert sum(ran) == T and not b.exact  # the timed plan's two rounds: each target once
    # (up to the rounding allowance, which the floors' scale enlarges)
    assert g.lower_bound <= b.lower_bound + 1e-9 * abs(ref.value)
    assert b.lower_bound <= ref.value


def test_no_floor_for_a_metric_without_an_interval_bound(monkeypatch):
    """A user's plain metric has no interval bound: its single-target search would be
    exhaustive, so the bounded search runs no floor for it."""
    from covnet.core.allocation import assignment_search as srch

    def called(*a, **k):
        raise AssertionError("a floor ran")

    monkeypatch.setattr(srch, "allocate_bnb", called)

    def mine(A, B):
        return np.abs(np.trace(A, axis1=-2, axis2=-1) - np.trace(B, axis1=-2, axis2=-1))

    N, T = 13, 2
    P, J, D, w, feas = _problem(N, T, 5)
    ticks = (i * 1e-3 for i in itertools.count())  # 1 ms a reading, lazily
    r = allocate_assignments_bounded(
        P, J, D, mine, w, feas, time_limit_s=50.0, clock=lambda: float(next(ticks))
    )
    assert r.lower_bound <= r.value


@pytest.mark.parametrize("metric", ["spectral", "abs_trace"])
@pytest.mark.parametrize("seed", range(3))
def test_never_worse_than_plain_greedy_even_out_of_time(metric, seed):
    """A limit that has passed before the local search (a fake clock: every reading a second
    on) still leaves the forward greedy's moves and 1-swaps run to their local optimum: never
    worse than the plain forward greedy with 1-swaps."""
    P, J, D, w, feas = _problem(13, 2, 30 + seed)
    plain = _plain_greedy(P, J, D, w, feas, metric)
    ticks = iter(range(10**6))
    res = allocate_assignments_bounded(
        P, J, D, metric, w, feas, time_limit_s=0.5, clock=lambda: float(next(ticks))
    )
    assert res.status == 2 and res.value <= plain * (1 + 1e-9)


@pytest.mark.parametrize("metric", ["kl", "frobenius", "logdet", "spectral"])
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("max_active", [None, 3])
def test_timed_plan_dual_below_the_exhaustive_optimum_at_any_prices(metric, seed, max_active):
    """The timed plan's bound (depth 1 with its superset bounds and the count bound refined in
    one call a column, then each column deepened to depth 2 keeping the depth-1 superset
    bounds, :attr:`_Enum.lower`) never exceeds the exhaustive optimum at any prices; at zero
    prices it is at least the depth-2 enumeration's without the kept level (the kept level
    only raises a column's cost)."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    N, T = 7, 3
    P, J, D, w, feas = _problem(N, T, 90 + seed)
    cons = MultiConstraints(max_active=max_active)
    ref = allocate_assignments_exhaustive(P, J, D, metric, w, feas, cons)
    inp = _Inputs(P, J, D, metric, w, feas, cons, 1e-9)
    cs = srch._Columns(inp)
    dual = srch._Dual(cs, budget=10_000, timed=True)
    assert all(e is None or e.d == 1 for e in dual.enum)
    assert dual.deepen(None) == sum(1 for e in dual.enum if e is not None)
    deep = [(c, e) for c, e in enumerate(dual.enum) if e is not None]
    assert deep and all(e.d == dual.depth[c] > 1 and [d0 for d0, _ in e.lower] == [1]
                        for c, e in deep)  # fmt: skip
    rng = np.random.default_rng(seed)
    for scale in (0.0, 0.01, 0.3, 3.0):
        pi = scale * abs(ref.value) * rng.uniform(size=N)
        L, counts = dual.value(pi)
        assert L <= ref.value, (scale, L, ref.value)
        assert sum(counts) <= (max_active or N)
    zero = np.zeros(N)
    for c, en in enumerate(dual.enum):
        if en is None:
            continue
        with_lower = dual._cost(c, zero)[0]
        kept, en.lower = en.lower, []
        without = dual._cost(c, zero)[0]
        en.lower = kept
        assert (with_lower >= without).all()


@pytest.mark.parametrize("metric", ["kl", "frobenius"])
def test_refinement_together_is_a_bound_of_each_interval(metric):
    """The count bound's and the depth-1 superset bounds' rows refined in one call
    (:meth:`_Rows.together`): each superset bound at most the metric at ``Z(F_c)`` (a point of
    every interval ``[Z(j), Z(F_c)]``), and all close to what one call a piece gives (the
    relaxation's result per row does not depend on its neighbours beyond its stopping rule)."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    N, T = 10, 2
    P, J, D, w, feas = _problem(N, T, 3)
    inp = _Inputs(P, J, D, metric, w, feas, MultiConstraints(), 1e-9)
    cs = srch._Columns(inp)
    timed = srch._Dual(cs, budget=10_000, timed=True)
    plain = srch._Dual(cs, budget=T * (N + 1))  # depth 1 everywhere, one call a piece
    for c in range(T):
        col = cs.cols[c]
        rows, en = timed.pieces[c], timed.enum[c]
        assert rows is not None and en is not None and rows.done.all() and en.rows.done.all()
        top = col.val(range(N)) * cs.w[c]  # Z(F_c): in every superset interval [Z(j), Z(F_c)]
        assert (en.sup <= top * (1 + 1e-9)).all()
        np.testing.assert_allclose(timed.h[c], plain.h[c], rtol=1e-3, atol=1e-9)
        np.testing.assert_allclose(en.sup, plain.enum[c].sup, rtol=1e-3, atol=1e-9)


def _plain_enum_cost(en, pi, ps):
    """``_Enum.cost`` as written before round mt8 (the reference of the faster one)."""
    po = pi[en.o]
    out = np.empty(en.nc + 1)
    for k in range(min(en.d, en.nc) + 1):
        out[k] = float(np.min(en.exact[k] + po[en.sets[k]].sum(axis=1)))
    if en.nc > en.d:
        base = float(np.min(en.sup + po[en.sets[en.d]].sum(axis=1)))
        out[en.d + 1 :] = base + ps[1 : en.nc - en.d + 1]
    for d0, sup in en.lower:
        if en.nc > d0:
            base = float(np.min(sup + po[en.sets[d0]].sum(axis=1)))
            out[d0 + 1 :] = np.fmax(out[d0 + 1 :], base + ps[1 : en.nc - d0 + 1])
    return out


def _plain_members(en, pi, k):
    po = pi[en.o]
    if k <= en.d:
        i = int(np.argmin(en.exact[k] + po[en.sets[k]].sum(axis=1)))
        return en.o[en.sets[k][i]]
    i = int(np.argmin(en.sup + po[en.sets[en.d]].sum(axis=1)))
    first = en.sets[en.d][i]
    rest = np.setdiff1d(np.arange(en.o.size), first)
    return en.o[np.concatenate((first, rest[np.lexsort((rest, po[rest]))][: k - en.d]))]


@pytest.mark.parametrize("depth", [1, 2, 3])
@pytest.mark.parametrize("seed", range(3))
def test_enumeration_cost_and_members_bit_for_bit(depth, seed):
    """The dual steps' enumeration costs (prices by column additions) and minimisers (kept
    from the last cost's argmins) equal the plain fancy-indexed sums and argmins bit for bit,
    at repeated, tied and changed prices, with kept shallower levels (the timed plan)."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    N, T = 9, 2
    P, J, D, w, feas = _problem(N, T, 300 + seed)
    inp = _Inputs(P, J, D, "spectral", w, feas, MultiConstraints(), 1e-9)
    cs = srch._Columns(inp)
    col = cs.cols[0]
    o = np.flatnonzero(cs.allow[0])
    nc = o.size
    en = srch._Enum(col, o, nc, 1, float(cs.w[0]))
    if depth > 1:
        en = srch._Enum(col, o, nc, depth, float(cs.w[0]), prev=en)
    rng = np.random.default_rng(seed)
    pis = [np.zeros(N), rng.uniform(size=N), np.round(rng.uniform(size=N), 1)]
    pis.append(rng.uniform(0.0, 1e-3, size=N) * 10.0 ** rng.integers(-8, 3, size=N))
    for pi in pis:
        ps = np.concatenate(([0.0], np.cumsum(np.sort(pi[o])[:nc])))
        got = en.cost(pi, ps)
        assert got.tobytes() == _plain_enum_cost(en, pi, ps).tobytes()
        po = pi[o]
        for k in range(depth + 1):
            ref = po[en.sets[k]].sum(axis=1)
            assert en._psum(po, k).tobytes() == ref.tobytes(), k
        for k in range(1, nc + 1):
            assert en.members(pi, k).tolist() == _plain_members(en, pi, k).tolist()
    # members at prices other than the last cost's: computed afresh, not the kept argmins
    for k in range(1, nc + 1):
        assert en.members(pis[0], k).tolist() == _plain_members(en, pis[0], k).tolist()
    pi = pis[1].copy()
    en.cost(pi, np.concatenate(([0.0], np.cumsum(np.sort(pi[o])[:nc]))))
    pi[o[0]] += 5.0  # changed in place after the cost
    for k in range(1, nc + 1):
        assert en.members(pi, k).tolist() == _plain_members(en, pi, k).tolist()


@pytest.mark.parametrize("seed", range(4))
def test_state_rows_refreshed_lazily_equal_eager(seed):
    """The local search's rows ``R`` and ``M`` refreshed once before a pass (:meth:`fresh`)
    equal those refreshed at every put, after random puts (moves, swaps, offs)."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    N, T = 8, 3
    P, J, D, w, feas = _problem(N, T, 400 + seed)
    inp = _Inputs(P, J, D, "kl", w, feas, MultiConstraints(required=frozenset({seed % N})), 1e-9)
    cs = srch._Columns(inp)
    lazy, eager = srch._State(cs), srch._State(cs)
    rng = np.random.default_rng(seed)
    for _ in range(40):
        j = int(rng.integers(N))
        opts = [OFF, *np.flatnonzero(cs.allow[:, j]).tolist()]
        c = int(opts[rng.integers(len(opts))])
        for st in (lazy, eager):
            st.put(j, c)
        for x in sorted(eager.stale):
            eager._refresh_members(x)
        eager.stale.clear()
        if rng.uniform() < 0.3:
            lazy.fresh()
    lazy.fresh()
    assert lazy.R.tobytes() == eager.R.tobytes()
    assert lazy.M.tobytes() == eager.M.tobytes()
    assert lazy.A.tobytes() == eager.A.tobytes()


def test_combinations_as_itertools():
    """The enumeration's sets: the rows and order of ``itertools.combinations``."""
    from covnet.core.allocation.assignment_search import _combinations

    for n in range(6):
        for k in range(4):
            ref = list(itertools.combinations(range(n), k))
            got = _combinations(n, k)
            assert got.shape == (len(ref), k) and got.dtype == np.intp
            assert [tuple(r) for r in got.tolist()] == ref
