"""Round mt20 of the timed plan (covnet.core.allocation.assignment_search._search): on a slower
machine the fixed-cost phases (set-up, enumeration, set moves, ejection chains) take more of
the limit.  The kicks then start only while ``KICK_MIN_LEFT`` of the limit is left, and the
root floors start at the latest when ``ROOT_START_SHARE`` of it is left.  A controlled clock
stands for the machine: it advances a little at every reading, and jumps once, right after the
plan's ejection chains, as if they had been slow."""

from __future__ import annotations

import pytest

from covnet.core.allocation import assignment_search as srch
from covnet.core.allocation.assignment import allocate_assignments
from covnet.covariance_control import bench_multitarget as bm

LIMIT = 1.0


class _SlowChains:
    """A clock of ``tick`` seconds a reading that jumps by ``jump`` seconds when the plan's ejection
    chains (its first call of ``_chain_moves``) return; the kicks' and the roots' calls are
    recorded with the time left when they start."""

    def __init__(self, monkeypatch, jump, tick=1e-5):
        self.t, self.jump, self.tick, self.chains = 0.0, jump, tick, 0
        self.kicks: list[float] = []
        self.roots: list[float] = []
        real_chains, real_kicks, real_roots = srch._chain_moves, srch._kicks, srch._root_floors

        def chains(st, deadline):
            out = real_chains(st, deadline)
            self.chains += 1
            if self.chains == 1:
                self.t += self.jump
            return out

        def kicks(st, until, rng):
            self.kicks.append(LIMIT - self.t)
            return real_kicks(st, until, rng)

        def roots(dual, upper, rem, min_s, pi):
            self.roots.append(rem())
            return real_roots(dual, upper, rem, min_s, pi)

        monkeypatch.setattr(srch, "_chain_moves", chains)
        monkeypatch.setattr(srch, "_kicks", kicks)
        monkeypatch.setattr(srch, "_root_floors", roots)

    def __call__(self) -> float:
        self.t += self.tick
        return self.t


def _decide(clock, prob, metric="spectral"):
    P, J, D, w, feas = prob
    return srch.allocate_assignments_bounded(
        P, J, D, metric, w, feas, rel_gap=0.0, time_limit_s=LIMIT, clock=clock
    )


@pytest.fixture(scope="module")
def prob():
    return bm.problems(16, 2, "spectral", 2, seed=5)[1]


def _certified(res, prob):
    P, J, D, w, feas = prob
    ref = allocate_assignments(P, J, D, "spectral", w, feas)  # exact (2^16 tables a target)
    assert res.lower_bound <= ref.value * (1 + 1e-9) + 1e-12 <= res.value * (1 + 2e-9) + 1e-12


def test_the_kicks_run_where_the_limit_is_generous_and_not_where_the_chains_took_it(
    monkeypatch, prob
):
    fast = _SlowChains(monkeypatch, jump=0.0)
    res = _decide(fast, prob)
    assert fast.kicks and fast.kicks[0] >= srch.KICK_MIN_LEFT * LIMIT
    _certified(res, prob)
    # the chains end with less than KICK_MIN_LEFT of the limit left: no kicks
    slow = _SlowChains(monkeypatch, jump=(1.0 - srch.KICK_MIN_LEFT) * LIMIT + 0.01)
    res = _decide(slow, prob)
    assert slow.chains >= 1 and slow.kicks == []
    _certified(res, prob)


def test_the_roots_start_by_the_time_their_share_is_left(monkeypatch):
    """N = 24, T = 4 (a problem whose dual steps run on), 1 ms a reading, the steps' stall
    switched off as a trigger (``MID_THETA``), so only the time starts the roots.  The steps
    start with about 0.42 of the limit left (no kicks: less than ``KICK_MIN_LEFT``): half of
    the steps' time would start the roots at about 0.21 left; with the rule they start by
    ``ROOT_START_SHARE``, and without it (the share 0) at half."""
    prob = bm.problems(24, 4, "spectral", 2, seed=2)[0]
    monkeypatch.setattr(srch, "MID_THETA", -1.0)
    jump = 0.55
    on = _SlowChains(monkeypatch, jump, tick=1e-3)
    res = _decide(on, prob)
    assert res.lower_bound <= res.value
    assert on.kicks == [] and on.roots
    assert srch.ROOT_START_SHARE * LIMIT - 0.01 <= on.roots[0] <= srch.ROOT_START_SHARE * LIMIT
    monkeypatch.setattr(srch, "ROOT_START_SHARE", 0.0)
    off = _SlowChains(monkeypatch, jump, tick=1e-3)
    _decide(off, prob)
    assert off.roots and off.roots[0] < 0.5 * (LIMIT - jump)
    assert off.roots[0] < on.roots[0] - 0.05
