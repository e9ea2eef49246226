"""``time_limit_s`` bounds every step of :func:`~covnet.core.allocation.search.allocate_bnb`: the
greedy start, the root's dual bound (a barrier run), the children's refinement (dual bound and
convex relaxation), the leaf table, the exact evaluation of the candidates.  Deterministic tests
use the ``clock`` argument with a clock that jumps past the deadline at a chosen step and check
that the step stops there (no further iterations, no further tree); one test uses the real clock
on a problem that takes seconds unbounded.  Whatever the step the time runs out in, the certified
lower bound stays at most the exhaustive optimum."""

from __future__ import annotations

import time

import numpy as np
import pytest

from covnet.core.allocation import search as S
from covnet.core.allocation.exact import allocate_exhaustive
from covnet.core.allocation.lower_bounds import _DualBound
from covnet.core.allocation.relaxation import _Relaxation
from covnet.core.allocation.search import STATUS, allocate_bnb
from covnet.core.allocation.search_problem import _Problem
from covnet.core.metrics import METRICS
from covnet.covariance_control.bench_search import decision_problems, paper_gains


class JumpClock:
    """Reads 0 until :meth:`expire` (or the ``after``-th read), then far past any deadline."""

    def __init__(self, after: int | None = None) -> None:
        self.reads = 0
        self.after = after
        self.expired = False

    def expire(self) -> None:
        self.expired = True

    def __call__(self) -> float:
        self.reads += 1
        if self.after is not None and self.reads > self.after:
            self.expired = True
        return 1e9 if self.expired else 0.0


def _problem(N: int, metric: str, scan: int = 1):
    gains = paper_gains(N)
    P_pred, P_d = decision_problems(gains, metric, [scan])[0]
    return P_pred, gains, P_d


def _count(monkeypatch, cls, name, clock=None, expire_on=None):
    """Count calls of ``cls.name`` made after the clock expired (and expire it on the
    ``expire_on``-th call, before running it)."""
    real = getattr(cls, name)
    calls = {"all": 0, "late": 0}

    def wrapped(*a, **kw):
        calls["all"] += 1
        if clock is not None and expire_on is not None and calls["all"] == expire_on:
            clock.expire()
        if clock is not None and clock.expired:
            calls["late"] += 1
        return real(*a, **kw)

    monkeypatch.setattr(cls, name, wrapped)
    return calls


def test_time_up_in_greedy_start_skips_the_tree_and_winds_greedy_down(monkeypatch):
    P_pred, gains, P_d = _problem(12, "kl")
    ref = allocate_exhaustive(P_pred, gains, P_d, "kl")
    clock = JumpClock(after=1)  # the deadline's own read, then expired: greedy's first step
    real = _Problem.approx_values
    finite_late = []

    def approx(self, Z):
        v = real(self, Z)
        if clock.expired:
            finite_late.append(int(np.isfinite(v).sum()))
        return v

    monkeypatch.setattr(_Problem, "approx_values", approx)
    r = allocate_bnb(P_pred, gains, P_d, "kl", rel_gap=0.01, time_limit_s=1.0, clock=clock)
    assert r.status == 2 and r.message == STATUS[2] and not r.exact
    assert r.n_nodes == 0  # the tree never started
    assert finite_late and sum(finite_late) == 0  # no working value computed after the deadline
    assert r.lower_bound <= ref.value <= r.value
    assert r.gap == pytest.approx((r.value - r.lower_bound) / r.value)


def test_time_up_in_the_root_barrier_stops_it_after_one_iteration(monkeypatch):
    P_pred, gains, P_d = _problem(12, "spectral")
    ref = allocate_exhaustive(P_pred, gains, P_d, "spectral")
    clock = JumpClock()
    solves = _count(monkeypatch, _DualBound, "_solve", clock, expire_on=1)
    steps = _count(monkeypatch, _DualBound, "_line_search", clock)
    r = allocate_bnb(P_pred, gains, P_d, "spectral", rel_gap=1e-9, time_limit_s=1.0, clock=clock)
    assert r.status in (2, 3)  # 3: the bound already certified the gap
    assert solves["all"] == 1  # the root's run only: no child was bounded
    assert steps["late"] == 0  # the barrier's first iteration gave the bound, no Newton step
    assert r.n_nodes == 1
    assert r.lower_bound <= ref.value <= r.value


@pytest.mark.parametrize("metric", ["spectral", "one_norm", "abs_trace"])
def test_time_up_while_refining_children_stops_the_batch_and_the_tree(monkeypatch, metric):
    P_pred, gains, P_d = _problem(12, metric)
    ref = allocate_exhaustive(P_pred, gains, P_d, metric)
    clock = JumpClock()
    # the first call is the root's: the time runs out as the first children are bounded
    solves = _count(monkeypatch, _DualBound, "_solve", clock, expire_on=2)
    steps = _count(monkeypatch, _DualBound, "_line_search", clock)
    r = allocate_bnb(P_pred, gains, P_d, metric, rel_gap=1e-6, time_limit_s=1.0, clock=clock)
    if solves["all"] < 2:  # the root certified the gap already: nothing to stop
        assert r.status == 3
        return
    assert r.status == 2
    assert solves["late"] <= 2  # that batch (include and exclude children), nothing after
    assert steps["late"] == 0
    assert r.lower_bound <= ref.value <= r.value


def test_time_up_in_the_relaxation_stops_it_after_its_first_tangent_plane(monkeypatch):
    P_pred, gains, P_d = _problem(12, "kl")
    ref = allocate_exhaustive(P_pred, gains, P_d, "kl")
    clock = JumpClock()
    bounds = _count(monkeypatch, _Relaxation, "bound", clock, expire_on=1)
    hx = _count(monkeypatch, _Relaxation, "_hx", clock)
    r = allocate_bnb(P_pred, gains, P_d, "kl", rel_gap=1e-9, time_limit_s=1.0, clock=clock)
    assert r.status == 2
    # the call that ran out: its starting point's tangent plane only (one _hx); then at most
    # the final root bound, cut the same way
    assert bounds["late"] <= 2 and hx["late"] <= bounds["late"]
    assert r.lower_bound <= ref.value <= r.value


def test_time_up_before_the_leaf_table_is_built(monkeypatch):
    """Exact kl at N = 24 uses the table of the last levels; the time runs out as the first node
    reaches its depth: the table is not built, the node stays open in the certified bound."""
    P_pred, gains, P_d = _problem(24, "kl", scan=3)
    exact = allocate_bnb(P_pred, gains, P_d, "kl")
    assert exact.status == 0
    built = []
    real_init = S._Leaves.__init__

    def init(self, *a, **kw):
        built.append(1)
        real_init(self, *a, **kw)

    monkeypatch.setattr(S._Leaves, "__init__", init)
    clock = JumpClock()
    _count(monkeypatch, S._Search, "leaves_expand", clock, expire_on=1)
    r = allocate_bnb(P_pred, gains, P_d, "kl", time_limit_s=1.0, clock=clock)
    assert r.status == 2 and not r.exact
    assert built == []
    assert r.lower_bound <= exact.value <= r.value


def test_a_limit_hit_in_the_tree_leaves_one_batch_of_candidates(monkeypatch):
    """Exact mode with massive ties (every subset of identical sensors with the same count ties):
    the time runs out in the tree; the evaluation after it is one batch of at most FINISH_FIRST."""
    P_pred, gains, P_d = _problem(14, "spectral")
    gains = np.repeat(gains[:1], 14, axis=0)
    ref = allocate_exhaustive(P_pred, gains, P_d, "spectral")
    clock = JumpClock()
    _count(monkeypatch, S._Search, "expand", clock, expire_on=3)
    evals_before_finish = []
    real_finish = S._Search.finish

    def finish(self, why):
        evals_before_finish.append(self.prob.n_evaluated)
        return real_finish(self, why)

    monkeypatch.setattr(S._Search, "finish", finish)
    r = allocate_bnb(P_pred, gains, P_d, "spectral", time_limit_s=1.0, clock=clock)
    assert r.status == 2
    assert r.n_evaluated - evals_before_finish[0] <= S.FINISH_FIRST
    assert r.lower_bound <= ref.value <= r.value


@pytest.mark.parametrize("metric", sorted(METRICS))
def test_the_certificate_holds_wherever_the_time_runs_out(metric):
    """The clock expires after its k-th read, for many k (every step above in turn): the value
    is a feasible subset's, the bound at most the exhaustive optimum."""
    P_pred, gains, P_d = _problem(10, metric, scan=2)
    ref = allocate_exhaustive(P_pred, gains, P_d, metric)
    for k in (1, 2, 3, 5, 8, 13, 21, 34, 55, 89, 144):
        for rel_gap in (0.0, 0.01):
            r = allocate_bnb(
                P_pred, gains, P_d, metric, rel_gap=rel_gap, time_limit_s=1.0, clock=JumpClock(k)
            )
            assert r.lower_bound <= ref.value * (1 + 1e-12) + 1e-300, (k, rel_gap)
            assert r.value >= ref.value * (1 - 1e-12), (k, rel_gap)
            if r.status == 0:
                assert (r.subset, r.value) == (ref.subset, ref.value)


def test_real_clock_limit_holds_on_a_problem_far_longer_unbounded():
    """spectral at N = 2000: greedy alone takes 10 s here (2 cores, loaded; before the fix the
    decision took that long whatever the limit), the tree far longer.  With ``time_limit_s =
    0.5`` the decision returns within a generous margin (the overshoot measured here: 2-35
    ms; asserted: 5 s, so it holds beside busy cores)."""
    P_pred, gains, P_d = _problem(2000, "spectral")
    limit = 0.5
    t0 = time.perf_counter()
    r = allocate_bnb(P_pred, gains, P_d, "spectral", rel_gap=1e-9, time_limit_s=limit)
    elapsed = time.perf_counter() - t0
    assert elapsed < limit + 5.0, f"time_limit_s={limit} took {elapsed:.2f} s"
    assert r.status == 2 and r.lower_bound <= r.value
