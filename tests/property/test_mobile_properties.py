"""Properties of the mobile core on random instances (spec §6.1, §8.3 items 4, 5, 7)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.mobile.cost import CostParams, cost_tensor
from covnet.core.mobile.decision import (
    DecisionProblem,
    decide_closed_form,
    decide_lp,
    decide_lp_highs,
    decide_milp,
    objective,
    relaxation,
)
from covnet.core.mobile.models import STAY, Sensors, noise_covariance, noise_growth

TOL = 1e-9


@st.composite
def geometry(draw, max_m: int = 5, max_n: int = 4):
    """Tracks and sensors in a 300 m square, with random capacities (or none)."""
    M = draw(st.integers(1, max_m))
    N = draw(st.integers(1, max_n))
    pos = st.floats(0.0, 300.0)
    x = draw(arrays(np.float64, (M, 4), elements=st.floats(-2.0, 2.0)))
    x[:, [0, 2]] = draw(arrays(np.float64, (M, 2), elements=pos))
    scale = draw(arrays(np.float64, (M,), elements=st.floats(0.1, 10.0)))
    P = np.diag([25.0, 0.25, 25.0, 0.25])[None] * scale[:, None, None]
    caps = draw(st.lists(st.one_of(st.none(), st.integers(0, 3)), min_size=N, max_size=N))
    sensors = Sensors(
        position=draw(arrays(np.float64, (N, 2), elements=pos)),
        speed=draw(arrays(np.float64, (N,), elements=st.floats(0.0, 5.0))),
        R0=draw(arrays(np.float64, (N,), elements=st.floats(1.0, 4.0)))[:, None, None] ** 2
        * np.eye(2),
        r_pd=draw(arrays(np.float64, (N,), elements=st.floats(20.0, 100.0))),
        b0=draw(arrays(np.float64, (N,), elements=st.floats(0.5, 1.5))),
        b1=np.zeros(N),
        capacity=np.array([np.inf if k is None else float(k) for k in caps]),
    )
    params = CostParams(
        trace_kind=draw(st.sampled_from(["full", "position"])),
        dist_uses_velocity=draw(st.booleans()),
        pd_include_track_cov=draw(st.booleans()),
    )
    return x, P, sensors, params


def _problem(g) -> DecisionProblem:
    x, P, sensors, params = g
    ct = cost_tensor(x, P, sensors, params)
    return DecisionProblem(ct.c, ct.c0, sensors.capacity)


@settings(max_examples=40)
@given(geometry())
def test_lp_relaxation_milp_post_step_chain(g):
    p = _problem(g)
    lp = decide_lp(p)
    exact = decide_milp(p)
    _, _, J_relax = relaxation(p)
    scale = max(1.0, abs(exact.objective))
    assert exact.status == 0
    assert lp.J_lp <= J_relax + TOL * scale
    assert J_relax <= exact.objective + TOL * scale
    assert exact.objective <= lp.objective + TOL * scale
    # every decision is feasible: capacities, one mode per sensor, idle sensors stay
    for d in (lp, exact):
        counts = np.bincount(d.assign[d.assign >= 0], minlength=p.N)
        assert np.all(counts <= p.capacity)
        idle = counts == 0
        assert np.all(d.modes[idle] == STAY)
        assert d.objective == objective(p, d.modes, d.assign)
    # with penalty, every target is covered when the capacities allow it
    room = int(min(p.M, np.minimum(p.capacity, p.M).sum()))
    assert np.count_nonzero(lp.assign >= 0) == room
    assert np.count_nonzero(exact.assign >= 0) == room


@settings(max_examples=40)
@given(geometry())
def test_closed_form_equals_lp_solver_without_capacity(g):
    x, P, sensors, params = g
    from dataclasses import replace

    sensors = replace(sensors, capacity=np.full(sensors.count, np.inf))
    p = _problem((x, P, sensors, params))
    a, b = decide_closed_form(p), decide_lp_highs(p)
    assert abs(a.J_lp - b.J_lp) <= TOL * max(1.0, abs(a.J_lp))
    # the vertex is the same unless two candidates of a target tie exactly
    flat = np.sort(p.c.reshape(p.M, -1), axis=1)
    if np.all(flat[:, 1] - flat[:, 0] > 1e-9):
        np.testing.assert_array_equal(a.assign, b.assign)
        np.testing.assert_array_equal(a.modes, b.modes)


@given(geometry())
def test_cost_tensor_batched_equals_one_target_and_one_sensor_at_a_time(g):
    x, P, sensors, params = g
    full = cost_tensor(x, P, sensors, params)
    for i in range(x.shape[0]):
        for j in range(sensors.count):
            one = cost_tensor(x[i : i + 1], P[i : i + 1], sensors.subset(np.array([j])), params)
            np.testing.assert_allclose(one.md[0, 0], full.md[i, j], rtol=1e-13, atol=1e-15)
            np.testing.assert_allclose(one.tr[0, 0], full.tr[i, j], rtol=1e-13)
    assert np.all(full.tr <= np.trace(P, axis1=1, axis2=2)[:, None, None] * (1 + 1e-12))
    assert np.all((full.md >= 0.0) & (full.md <= 1.0))


@given(
    arrays(np.float64, (4,), elements=st.floats(-500, 500)),
    arrays(np.float64, (2,), elements=st.floats(-500, 500)),
    arrays(np.float64, (2,), elements=st.floats(-5, 5)),
    st.floats(1.0, 100.0),
    st.floats(1.0, 100.0),
    st.floats(0.5, 5.0),
    st.floats(0.5, 5.0),
    st.floats(-0.95, 0.95),
    st.booleans(),
)
def test_noise_covariance_is_spd_and_patent_form_when_diagonal(x, q, qd, Lx, Ly, sx, sy, rho, v):
    g = noise_growth(x, q, qd, np.array([Lx, Ly]), v)
    R0 = np.array([[sx * sx, rho * sx * sy], [rho * sx * sy, sy * sy]])
    R = noise_covariance(g, R0)
    np.testing.assert_array_equal(R, R.T)
    assert np.linalg.eigvalsh(R).min() > 0
    R0d = np.diag(np.diag(R0))
    D = np.diag(g - 1.0) * np.diag([Lx, Ly])
    patent = (np.eye(2) + D @ np.diag([1 / Lx, 1 / Ly])) @ R0d
    np.testing.assert_allclose(noise_covariance(g, R0d), patent, rtol=1e-12)
