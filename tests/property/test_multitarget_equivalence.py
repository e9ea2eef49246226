"""The fast multi-target allocator (covnet.core.allocation.assignment.allocate_assignments)
returns exactly what the plain loop over all (T+1)^N assignments returns (assignment, value, per
target values and covariances, bit for bit), for every registered metric, with coverage gaps,
constraints (excluded, required, max_active, max_per_target), weights and ties (duplicated and
zero-information sensors); and for T = 1 it is today's single-target allocator."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.allocation.assignment import (
    OFF,
    MultiConstraints,
    allocate_assignments,
    allocate_assignments_exhaustive,
)
from covnet.core.allocation.exact import Constraints, InfeasibleAllocation, allocate_exhaustive
from covnet.core.metrics import METRICS
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensing import correlated_noise, information_gain, position_matrix

_elems = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


@st.composite
def spd(draw, n, floor):
    A = draw(arrays(np.float64, (n, n), elements=_elems))
    return A @ A.T + floor * np.eye(n)


@st.composite
def coverage(draw, N, T):
    """A coverage mask, mostly covered (a pair is out with probability 1/5)."""
    cells = draw(
        st.lists(st.sampled_from([True, True, True, True, False]), min_size=N * T, max_size=N * T)
    )
    return np.array(cells, dtype=bool).reshape(N, T)


@st.composite
def position_problem(draw, max_n=5, max_t=3):
    """Position-like sensors (rank 1 or 2 information on the positions, some zero), CV
    predicted covariances, diagonal desired covariances, a coverage mask with gaps."""
    N = draw(st.integers(1, max_n).map(lambda k: max_n + 1 - k))  # shrinks towards max_n
    T = draw(st.integers(1, max_t))
    H = position_matrix()
    J = np.zeros((N, T, 4, 4))
    sig = st.floats(3.0, 60.0)
    for j in range(N):
        kind = draw(st.sampled_from(["pos", "pos", "rank1", "zero"]))
        for t in range(T):
            if kind == "pos":
                R = correlated_noise(draw(sig), draw(sig), draw(st.floats(-0.95, 0.95)))
                J[j, t] = 0.9 * information_gain(H, R)
            elif kind == "rank1":
                u = np.zeros(4)
                u[[0, 2]] = draw(arrays(np.float64, 2, elements=st.floats(-1, 1)))
                J[j, t] = np.outer(u, u) / draw(sig) ** 2
    if N >= 2 and draw(st.booleans()):
        J[N - 1] = J[0]  # a duplicated sensor: near-exact ties
    F, Q = cv_transition(1.0), dwna_process_noise(1.0, 0.5)
    scale = draw(st.sampled_from([1.0, 30.0, 1e3]))
    P = np.array(
        [
            F @ (draw(spd(4, 1.0)) * scale / 100.0 + np.diag([1.0, 0.1, 1.0, 0.1])) @ F.T + Q
            for _ in range(T)
        ]
    )
    d = st.sampled_from([(25.0, 1.4), (7.0, 0.8), (100.0, 5.0), (1.0, 0.1)])
    D = np.array([np.diag([a, b, a, b]) for a, b in (draw(d) for _ in range(T))])
    feas = draw(coverage(N, T))
    w = np.array(draw(st.lists(st.sampled_from([1.0, 0.5, 2.0, 1.3]), min_size=T, max_size=T)))
    return P, J, D, w, feas


@st.composite
def general_problem(draw, max_n=4, max_t=3):
    """Any dimension 2..4, information of any rank and support, random SPD P and P_d."""
    n = draw(st.integers(2, 4))
    N = draw(st.integers(1, max_n))
    T = draw(st.integers(1, max_t))
    J = np.zeros((N, T, n, n))
    for j in range(N):
        for t in range(T):
            k = draw(st.integers(0, n))
            Hs = draw(arrays(np.float64, (k, n), elements=_elems))
            J[j, t] = Hs.T @ Hs / 10.0
    P = np.array([draw(spd(n, 0.1)) for _ in range(T)])
    D = np.array([draw(spd(n, 0.1)) for _ in range(T)])
    feas = draw(coverage(N, T))
    w = np.array(draw(st.lists(st.floats(0.1, 3.0), min_size=T, max_size=T)))
    return P, J, D, w, feas


@st.composite
def multi_constraints(draw, N, T):
    idx = st.integers(0, N - 1)
    excluded = frozenset(draw(st.lists(idx, max_size=max(N - 1, 0))))
    required = frozenset(draw(st.lists(idx, max_size=2))) - excluded
    budget = draw(st.one_of(st.none(), st.integers(max(1, len(required)), max(1, N))))
    cap = draw(
        st.one_of(
            st.none(),
            st.integers(0, N),
            st.tuples(*[st.integers(0, N) for _ in range(T)]),
        )
    )
    return MultiConstraints(excluded, required, budget, cap)


@st.composite
def multi_problem(draw):
    P, J, D, w, feas = draw(st.one_of(position_problem(), general_problem()))
    N, T = J.shape[0], J.shape[1]
    c = draw(st.one_of(st.just(MultiConstraints()), multi_constraints(N, T)))
    return P, J, D, w, feas, c


def _same(P, J, D, w, feas, name, c):
    try:
        ref = allocate_assignments_exhaustive(P, J, D, name, w, feas, c)
    except InfeasibleAllocation:
        with pytest.raises(InfeasibleAllocation):
            allocate_assignments(P, J, D, name, w, feas, c)
        return None
    except ValueError:  # a P_d the metric cannot take (logdet, kl)
        with pytest.raises(ValueError):
            allocate_assignments(P, J, D, name, w, feas, c)
        return None
    got = allocate_assignments(P, J, D, name, w, feas, c)
    assert got.assignment == ref.assignment, (got.assignment, ref.assignment, got.value, ref.value)
    assert got.value == ref.value
    assert got.values == ref.values
    np.testing.assert_array_equal(got.P, ref.P)
    assert got.sets == ref.sets
    return ref


@pytest.mark.parametrize("name", sorted(METRICS))
@settings(max_examples=50)
@given(pb=multi_problem())
def test_fast_equals_exhaustive(name, pb):
    _same(*pb[:5], name, pb[5])


@pytest.mark.slow
@pytest.mark.parametrize("name", ["spectral", "svd", "kl", "logdet"])
@settings(max_examples=8)
@given(pb=position_problem(max_n=7), data=st.data())
def test_fast_equals_exhaustive_seven_sensors(name, pb, data):
    N, T = pb[1].shape[0], pb[1].shape[1]
    c = data.draw(st.one_of(st.just(MultiConstraints()), multi_constraints(N, T)))
    _same(*pb, name, c)


def _weighted_diag(A, B):
    """A user's own metric (no interval bound): exact tables, one call per subset."""
    return np.abs(np.diagonal(A - B, axis1=-2, axis2=-1)).max(axis=-1)


@settings(max_examples=20)
@given(pb=multi_problem())
def test_fast_equals_exhaustive_user_metric(pb):
    _same(*pb[:5], _weighted_diag, pb[5])


@st.composite
def single_target(draw):
    P, J, D, w, feas = draw(st.one_of(position_problem(6, 1), general_problem(6, 1)))
    N = J.shape[0]
    idx = st.integers(0, N - 1)
    excluded = frozenset(draw(st.lists(idx, max_size=max(N - 1, 0))))
    required = frozenset(draw(st.lists(idx, max_size=2))) - excluded
    budget = draw(st.one_of(st.none(), st.integers(max(1, len(required)), max(1, N))))
    return P, J, D, Constraints(excluded, required, budget)


@pytest.mark.parametrize("name", sorted(METRICS))
@settings(max_examples=20)
@given(pb=single_target())
def test_one_target_is_todays_allocator(name, pb):
    """T = 1, unit weight, full coverage: the same subset and value bits as the single-target
    reference (the tie rule puts OFF after the targets, which is today's rule for T = 1)."""
    P, J, D, c = pb
    mc = MultiConstraints(c.excluded, c.required, c.max_active)
    try:
        ref = allocate_exhaustive(P[0], J[:, 0], D[0], name, c)
    except ValueError:
        with pytest.raises(ValueError):
            allocate_assignments(P, J, D, name, constraints=mc)
        return
    got = allocate_assignments(P, J, D, name, constraints=mc)
    assert got.sets[0] == ref.subset
    assert got.value == ref.value and got.values == (ref.value,)
    np.testing.assert_array_equal(got.P[0], ref.P)
    assert all((a == 0) == (j in ref.subset) for j, a in enumerate(got.assignment))
    assert all(a in (0, OFF) for a in got.assignment)
