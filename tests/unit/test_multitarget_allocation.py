"""Multi-target allocation (covnet.core.allocation.assignment): the documented arithmetic and
tie rule on hand cases, constraints, coverage, the record, and input validation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from covnet.core.allocation.assignment import (
    OFF,
    Assignment,
    MultiConstraints,
    allocate_assignments,
    allocate_assignments_exhaustive,
)
from covnet.core.allocation.exact import InfeasibleAllocation, subset_covariance
from covnet.core.metrics import METRICS
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensing import correlated_noise, information_gain, position_matrix

SEARCHES = [allocate_assignments_exhaustive, allocate_assignments]


def _problem(N=5, T=3, seed=1):
    rng = np.random.default_rng(seed)
    H = position_matrix()
    J = np.zeros((N, T, 4, 4))
    for j in range(N):
        for t in range(T):
            sx, sy = rng.uniform(5.0, 40.0, 2)
            J[j, t] = 0.9 * information_gain(H, correlated_noise(sx, sy, rng.uniform(-0.8, 0.8)))
    F, Q = cv_transition(1.0), dwna_process_noise(1.0, 0.5)
    P = np.array([F @ np.diag([60.0, 6.0, 60.0, 6.0]) * (1 + t) @ F.T + Q for t in range(T)])
    D = np.array([np.diag([d, d / 15, d, d / 15]) for d in (25.0, 7.0, 12.0)[:T]])
    return P, J, D


def _value(P, J, D, w, metric, a):
    """The module's arithmetic by hand: per target the ascending sum, then F = sum w_t v_t."""
    T = P.shape[0]
    F, vals = 0.0, []
    for t in range(T):
        Jt = np.zeros((4, 4))
        for j, x in enumerate(a):
            if x == t:
                Jt = Jt + J[j, t]
        v = float(METRICS[metric](subset_covariance(P[t], Jt), D[t]))
        vals.append(v)
        F = F + w[t] * v
    return F, vals


@pytest.mark.parametrize("search", SEARCHES)
@pytest.mark.parametrize("metric", ["spectral", "abs_trace", "kl"])
def test_oracle_by_enumeration(search, metric):
    """The chosen assignment minimises the hand-computed F over all assignments (4^5 = 1024
    here), and its value and per-target values are the hand arithmetic's bits."""
    P, J, D = _problem()
    w = np.array([1.0, 2.0, 0.5])
    res = search(P, J, D, metric, w)
    best = min(
        _value(P, J, D, w, metric, a)[0]
        for a in itertools.product([OFF, 0, 1, 2], repeat=5)
        if any(x != OFF for x in a)
    )
    F, vals = _value(P, J, D, w, metric, res.assignment)
    assert res.value == F and res.values == tuple(vals)
    assert F <= best * (1 + 1e-9)
    assert isinstance(res, Assignment)
    assert res.P.shape == (3, 4, 4)
    assert res.sets == tuple(
        tuple(j for j, x in enumerate(res.assignment) if x == t) for t in range(3)
    )
    assert res.n_active == sum(x != OFF for x in res.assignment)


def test_tie_rule_prefers_fewer_sensors_then_targets_before_off():
    """Two identical sensors, two identical targets: every one-sensor assignment ties exactly.
    Fewest sensors first; then, at the first sensor where two differ, target 0 < target 1 <
    OFF: sensor 0 on target 0."""
    P, J, D = _problem(N=1, T=1)
    J2 = np.broadcast_to(J[:1, :1], (2, 2, 4, 4)).copy()
    P2 = np.broadcast_to(P[:1], (2, 4, 4)).copy()
    D2 = np.broadcast_to(np.diag([1e4, 1e3, 1e4, 1e3]), (2, 4, 4)).copy()  # loose: one is best
    for search in SEARCHES:
        res = search(P2, J2, D2, "abs_trace")
        assert res.assignment == (0, OFF)
    # with target 0 infeasible for sensor 0: sensor 0 on target 1 (not off)
    feas = np.array([[False, True], [True, True]])
    for search in SEARCHES:
        assert search(P2, J2, D2, "abs_trace", feasible=feas).assignment == (1, OFF)


@pytest.mark.parametrize("search", SEARCHES)
def test_constraints_and_coverage(search):
    P, J, D = _problem()
    feas = np.ones((5, 3), dtype=bool)
    feas[0, :2] = False  # sensor 0 covers target 2 only
    feas[3, 1] = False
    c = MultiConstraints(
        excluded=frozenset({4}), required=frozenset({0}), max_active=3, max_per_target=(1, 2, 2)
    )
    res = search(P, J, D, "spectral", None, feas, c)
    a = res.assignment
    assert a[4] == OFF and a[0] == 2
    assert res.n_active <= 3
    assert all(len(res.sets[t]) <= (1, 2, 2)[t] for t in range(3))
    assert all(feas[j, x] for j, x in enumerate(a) if x != OFF)
    ref = allocate_assignments_exhaustive(P, J, D, "spectral", None, feas, c)
    assert (res.assignment, res.value) == (ref.assignment, ref.value)


def test_infeasible_pair_information_is_ignored():
    """Garbage (even NaN) in J on infeasible pairs changes nothing."""
    P, J, D = _problem()
    feas = np.ones((5, 3), dtype=bool)
    feas[1, 0] = feas[2, 2] = False
    J2 = J.copy()
    J2[1, 0] = np.nan
    J2[2, 2] = -np.eye(4)
    for search in SEARCHES:
        a = search(P, J, D, "kl", None, feas)
        b = search(P, J2, D, "kl", None, feas)
        assert (a.assignment, a.value) == (b.assignment, b.value)


@pytest.mark.parametrize("search", SEARCHES)
def test_infeasible(search):
    P, J, D = _problem()
    none = np.zeros((5, 3), dtype=bool)
    with pytest.raises(InfeasibleAllocation, match="no sensor has a feasible target"):
        search(P, J, D, "spectral", None, none)
    feas = np.ones((5, 3), dtype=bool)
    feas[2] = False
    with pytest.raises(InfeasibleAllocation, match="required sensor 2"):
        search(P, J, D, "spectral", None, feas, MultiConstraints(required=frozenset({2})))
    c = MultiConstraints(required=frozenset({0, 1}), max_per_target=0)
    with pytest.raises(InfeasibleAllocation, match="no assignment"):
        search(P, J, D, "spectral", None, None, c)
    with pytest.raises(InfeasibleAllocation, match="excluded"):
        search(P, J, D, "spectral", None, None, MultiConstraints(excluded=frozenset(range(5))))


@pytest.mark.parametrize("search", SEARCHES)
def test_validation_messages(search):
    P, J, D = _problem()
    bad = [
        (dict(P_pred=P[0]), ValueError, "P_pred must be"),
        (dict(P_d=D[:2]), ValueError, "P_d must be"),
        (dict(J=J[:, :2]), ValueError, "J must be"),
        (dict(weights=[1.0, -1.0, 1.0]), ValueError, "weights"),
        (dict(feasible=np.ones((5, 2), dtype=bool)), ValueError, "feasible"),
        (dict(metric="nope"), KeyError, "unknown metric"),
        (dict(tie_rtol=-1.0), ValueError, "tie_rtol"),
        (dict(constraints=MultiConstraints(max_active=0)), ValueError, "max_active"),
        (dict(constraints=MultiConstraints(max_per_target=(1, 1))), ValueError, "max_per_target"),
        (dict(constraints=MultiConstraints(required={7})), ValueError, "required sensor indices"),
        (dict(constraints=Ellipsis), TypeError, "MultiConstraints"),
        (dict(P_pred=-P), ValueError, "positive definite"),
    ]
    for override, exc, match in bad:
        kw = dict(P_pred=P, J=J, P_d=D, metric="spectral")
        kw.update(override)
        with pytest.raises(exc, match=match):
            search(**kw)


def test_fast_path_records_its_work():
    P, J, D = _problem(N=6)
    res = allocate_assignments(P, J, D, "spectral")
    ref = allocate_assignments_exhaustive(P, J, D, "spectral")
    assert ref.n_feasible == 4**6 - 1 and ref.n_candidates == ref.n_feasible
    assert res.n_feasible is None
    assert 1 <= res.n_candidates <= 4**6 and 1 <= res.n_evaluated < ref.n_evaluated
    assert (res.assignment, res.value) == (ref.assignment, ref.value)
