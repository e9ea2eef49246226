"""The exact assignment allocator's tie rule applied to all tied candidates at once
(:func:`covnet.core.allocation.assignment._tie_choice`) against the loop over
:meth:`_Inputs.tie_key` it replaced: the same index on random candidate sets with repeated
keys; and a desired covariance far above every reachable one (every candidate ties: a 4-scan
many-target run took 7 s, most of it in that loop) decides as the exhaustive allocator does."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.core.allocation.assignment import (
    OFF,
    _tie_choice,
    _vector,
    allocate_assignments,
    allocate_assignments_exhaustive,
)
from tests.unit.test_multitarget_allocation import _problem


def _loop_choice(cands, tied, allowed, N, off):
    best = best_key = None
    for i in tied.tolist():
        a = _vector(cands[i], allowed, N)
        key = (sum(x != OFF for x in a), tuple(off if x == OFF else x for x in a))
        if best_key is None or key < best_key:
            best, best_key = i, key
    return best


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_the_choice_is_the_loops(data):
    N = data.draw(st.integers(1, 9))
    allowed = sorted(data.draw(st.sets(st.integers(0, N - 1), min_size=1)))
    m, ncol = len(allowed), data.draw(st.integers(1, 4))
    n = data.draw(st.integers(1, 40))
    lowest = data.draw(st.sampled_from([-1, 0]))  # 0: every sensor on, the count ties
    cands = []
    for _ in range(n):  # each allowed sensor in one column or none (disjoint sets)
        where = data.draw(st.lists(st.integers(lowest, ncol - 1), min_size=m, max_size=m))
        codes = [0] * ncol
        for b, t in enumerate(where):
            if t >= 0:
                codes[t] |= 1 << b
        cands.append(codes)
    if data.draw(st.booleans()):  # repeated candidates: equal keys, the first must win
        cands += [list(c) for c in cands[: n // 2]]
    tied = np.array(sorted(data.draw(st.sets(st.integers(0, len(cands) - 1), min_size=1))))
    off = ncol + data.draw(st.integers(0, 2))
    got = _tie_choice(np.array(cands, dtype=np.int64), tied, m, off)
    assert got == _loop_choice(cands, tied, allowed, N, off)


def test_a_hand_case():
    """Three sensors, two columns, all on (the count ties): the key is the columns in sensor
    order, the first of equal keys wins."""
    cands = np.array([[0b110, 0b001], [0b011, 0b100], [0b111, 0], [0b011, 0b100], [0b101, 0b010]])
    # columns by sensor: (1, 0, 0), (0, 0, 1), (0, 0, 0), (0, 0, 1), (0, 1, 0)
    assert _tie_choice(cands, np.arange(5), 3, 2) == 2
    assert _tie_choice(cands, np.array([0, 1, 3, 4]), 3, 2) == 1
    assert _tie_choice(cands, np.array([0, 3, 4]), 3, 2) == 3
    assert _tie_choice(cands, np.array([0, 4]), 3, 2) == 4


@pytest.mark.parametrize("metric", ["spectral", "frobenius", "abs_trace"])
def test_a_desired_covariance_nothing_reaches_ties_every_candidate_and_decides_exactly(metric):
    P, J, _ = _problem(N=6, T=3, seed=4)
    D = np.array([1e14 * np.eye(4)] * 3)
    fast = allocate_assignments(P, J, D, metric)
    ref = allocate_assignments_exhaustive(P, J, D, metric)
    assert fast.assignment == ref.assignment
    assert fast.value == ref.value and np.array_equal(fast.P, ref.P)
    assert fast.n_candidates > 100  # the many ties this is about


def _enumerate_loop(targets, Hs, ws, full, root, tau):
    """The loop over the prefixes :func:`assignment._enumerate` replaced (reference)."""
    keep = np.flatnonzero(root <= tau)
    tg0 = targets[0]
    partial = [
        ([int(tg0.subs[i])], full ^ int(tg0.subs[i]), ws[0] * float(tg0.lb[i]))
        for i in keep.tolist()
    ]
    for t in range(1, len(targets)):
        tg = targets[t]
        nxt = []
        for sets, R, acc in partial:
            sel = (tg.subs & ~R) == 0
            sub, lbs = tg.subs[sel], tg.lb[sel]
            part = acc + ws[t] * lbs
            v = part + Hs[t + 1][R ^ sub]
            for k in np.flatnonzero(v <= tau).tolist():
                code = int(sub[k])
                nxt.append((sets + [code], R ^ code, float(part[k])))
        partial = nxt
    return [sets for sets, _, _ in partial]


@pytest.mark.parametrize("chunk", [1, 7, 1 << 20])
@pytest.mark.parametrize(
    ("seed", "scale", "metric"),
    [(1, 1.0, "spectral"), (2, 1.0, "kl"), (3, 1e14, "abs_trace"), (4, 1.0, "logdet")],
)
def test_the_enumeration_is_the_loops_row_for_row(monkeypatch, chunk, seed, scale, metric):
    from covnet.core.allocation import assignment

    real = assignment._enumerate
    calls = []

    def both(*args):
        got = real(*args)
        want = _enumerate_loop(*args)
        assert got.tolist() == want
        calls.append(len(want))
        return got

    monkeypatch.setattr(assignment, "ENUM_CHUNK", chunk)
    monkeypatch.setattr(assignment, "_enumerate", both)
    P, J, D = _problem(N=6, T=3, seed=seed)
    D = D * scale
    fast = allocate_assignments(P, J, D, metric)
    ref = allocate_assignments_exhaustive(P, J, D, metric)
    assert calls and fast.assignment == ref.assignment and fast.value == ref.value
