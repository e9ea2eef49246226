"""Round mt15's floor rounds (covnet.core.allocation.assignment_search._floors): a floor whose
search stopped at its time limit is searched again by the next round; a column without slack,
or with less than ``FLOOR_PART`` of it, takes no floor; the first round stops where a share
would be below what the last floor took; the timed search's bound stays at most the exact
optimum (trace_diff, whose single-target bound is 0 until its search ends)."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import numpy as np
from test_assignment_search import _problem

from covnet.core.allocation.assignment import MultiConstraints


def _setup(monkeypatch, metric, status, spend=None):
    """A bound without enumeration, and ``allocate_bnb`` replaced by a recorder: the target
    it is called for (by its prior), ``status[t]`` (2: stopped at its time limit) and a bound
    of 0 (at most every set's value); ``spend``: what each call takes off the clock."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import _Inputs

    N, T = 8, 3
    P, J, D, w, feas = _problem(N, T, 11)
    inp = _Inputs(P, J, D, metric, w, feas, MultiConstraints(), 1e-9)
    dual = srch._Dual(srch._Columns(inp), budget=0)
    calls: list[tuple[int, float]] = []

    def bnb(P_t, *a, time_limit_s=None, **k):
        t = next(t for t in range(T) if np.array_equal(P_t, P[t]))
        calls.append((t, time_limit_s))
        if spend is not None:
            spend()
        return SimpleNamespace(lower_bound=0.0, status=status[t])

    monkeypatch.setattr(srch, "allocate_bnb", bnb)
    least = [float(dual._cost(c, np.zeros(N))[0][1:].min()) for c in range(T)]
    return srch, dual, calls, np.array(least), T


def test_a_floor_cut_by_its_time_is_searched_again(monkeypatch):
    """A floor whose search stopped at its time limit (status 2) is searched again by the next
    round; the finished ones are not (before round mt15 a cut floor, finite, was skipped)."""
    srch, dual, calls, least, T = _setup(monkeypatch, "trace_diff", {0: 3, 1: 2, 2: 3})
    upper = least + 10.0
    assert srch._floors(dual, upper, lambda: 10.0) == T
    assert sorted(t for t, _ in calls) == [0, 1, 2] and dual.cut == {1}
    calls.clear()
    assert srch._floors(dual, upper, lambda: 10.0) == 1
    assert calls[0][0] == 1 and dual.cut == {1}
    assert all(f == 0.0 for f in dual.floor[:T])


def test_no_floor_without_a_share_of_the_slack(monkeypatch):
    """With ``part`` (the ``floors_first`` metrics' rounds: ``FLOOR_PART``) a column at its
    bound (no slack) or with less than that share of the summed slack takes no floor; without
    it (svd's only round, the second floors after the root floors) every column does, as
    before."""
    srch, dual, calls, least, T = _setup(monkeypatch, "trace_diff", {0: 3, 1: 3, 2: 3})
    upper = least + np.array([10.0, 0.0, 0.2])  # 0.2 / 10.2 < FLOOR_PART
    assert srch._floors(dual, upper, lambda: 10.0, part=srch.FLOOR_PART) == 1
    assert [t for t, _ in calls] == [0]
    for kw in ({}, {"rooted": True}):
        calls.clear()
        dual.floor[:] = -np.inf
        assert srch._floors(dual, upper, lambda: 10.0, **kw) == T


def test_the_first_round_stops_below_the_last_floors_time(monkeypatch):
    """The first round (``slice_s``) stops where a floor's share would be below what the last
    one took (it is left to the second round); without the slice the shares are as before."""
    left = [24.0]

    def spend():
        left[0] -= 9.0

    srch, dual, calls, least, T = _setup(monkeypatch, "trace_diff", {0: 3, 1: 3, 2: 3}, spend)
    upper = least + 10.0
    # the first: min(20, 24 - 8) = 16; the second: 15 left passes 1.5 x 9, its share
    # min(20, 15 - 8) = 7 is below the 9 the first took
    assert srch._floors(dual, upper, lambda: left[0], 8.0, 20.0) == 1
    assert calls == [(calls[0][0], 16.0)]
    calls.clear()
    left[0] = 100.0
    assert srch._floors(dual, upper, lambda: left[0], 8.0, None) == 2  # the other two


def test_bounded_trace_diff_with_time_below_the_optimum():
    """With a clock, trace_diff's bounded search (the floor rounds above) certifies a bound at
    most the exact optimum and never a worse value than greedy's plain start."""
    from covnet.core.allocation import assignment_search as srch
    from covnet.core.allocation.assignment import allocate_assignments

    for seed in range(3):
        P, J, D, w, feas = _problem(13, 3, 30 + seed)
        ref = allocate_assignments(P, J, D, "trace_diff", w, feas)
        ticks = (i * 1e-3 for i in itertools.count())  # 1 ms a reading, lazily
        b = srch.allocate_assignments_bounded(
            P, J, D, "trace_diff", w, feas, rel_gap=0.0, time_limit_s=0.5,
            clock=lambda it=ticks: float(next(it)),
        )  # fmt: skip
        assert b.lower_bound <= ref.value * (1 + 1e-12) + 1e-12
        assert b.value >= ref.value * (1 - 1e-12) - 1e-12
