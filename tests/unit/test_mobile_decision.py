"""The decision problem (spec §5, §6, §8.3 items 2–6, 9): MILP == brute force, LP + post-step,
closed form, rounding, capacities, unobservable targets, solver records."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from covnet.core.mobile import decision as dec_module
from covnet.core.mobile.cost import CostParams, cost_tensor
from covnet.core.mobile.decision import (
    SOLVERS,
    DecisionProblem,
    LinearProgram,
    SolverError,
    SolverOptions,
    build_lp,
    build_milp,
    compare,
    decide_closed_form,
    decide_lp,
    decide_lp_highs,
    decide_milp,
    objective,
    post_step,
    relaxation,
    round_selection,
    solve_lp,
)
from covnet.core.mobile.models import MODE_NORM, STAY, Sensors


def brute_force(p: DecisionProblem) -> float:
    """min J over every mode vector (9^N) and every assignment of targets to a sensor or to
    nobody ((N+1)^M) that respects the capacities."""
    M, N = p.M, p.N
    assigns = np.array(list(itertools.product(range(-1, N), repeat=M)), dtype=np.intp)  # (A, M)
    counts = np.stack([(assigns == j).sum(axis=1) for j in range(N)], axis=1)  # (A, N)
    feasible = np.all(counts <= p.capacity[None, :], axis=1)
    assigns = assigns[feasible]
    best = np.inf
    rows = np.arange(M)
    for modes in itertools.product(range(9), repeat=N):
        m = np.asarray(modes)
        table = np.empty((M, N + 1))
        table[:, 0] = p.c0
        table[:, 1:] = p.c[:, np.arange(N), m]  # (M, N): c_{i, j, ρ_j}
        J = table[rows[None, :], assigns + 1].sum(axis=1).min()
        best = min(best, J + p.eps * MODE_NORM[m].sum())
    return float(best)


def random_problem(seed: int, M: int, N: int, capacity=None, conflict: bool = False):
    rng = np.random.default_rng(seed)
    c = rng.uniform(0.0, 1.0, (M, N, 9))
    if conflict:  # one cheap sensor whose best mode differs per target
        for i in range(M):
            c[i, 0, 1 + (2 * i) % 8] -= 0.6
    K = np.full(N, np.inf) if capacity is None else np.asarray(capacity, dtype=float)
    return DecisionProblem(c, rng.uniform(2.0, 3.0, M), K)


TINY = [
    (M, N, cap, seed)
    for (M, N) in [(1, 1), (2, 1), (3, 2), (4, 2), (2, 3), (4, 3)]
    for cap in ("none", "one", "mixed")
    for seed in (0, 1)
]


@pytest.mark.parametrize("M,N,cap,seed", TINY, ids=[f"{m}x{n}-{c}-{s}" for m, n, c, s in TINY])
def test_milp_equals_brute_force(M, N, cap, seed):
    K = {"none": None, "one": [1] * N, "mixed": [2, 1, np.inf][:N]}[cap]
    p = random_problem(seed, M, N, K, conflict=seed == 1)
    d = decide_milp(p)
    assert d.status == 0
    J_bf = brute_force(p)
    assert d.objective == pytest.approx(J_bf, rel=1e-9, abs=1e-9)
    # the chain J_LP <= J_relax <= J* <= J_LP+post
    lp = decide_lp(p)
    _, _, J_relax = relaxation(p)
    tol = 1e-9
    assert lp.J_lp <= J_relax + tol and J_relax <= d.objective + tol
    assert d.objective <= lp.objective + tol
    # the aggregated linking gives the same optimum
    w = decide_milp(p, SolverOptions(linking="weak"))
    assert w.objective == pytest.approx(J_bf, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_capacity_one_lp_is_exact(seed):
    p = random_problem(seed, 4, 3, [1, 1, 1], conflict=True)
    lp, exact = decide_lp(p), decide_milp(p)
    assert lp.conflicts == 0
    assert lp.objective == pytest.approx(exact.objective, rel=1e-12)
    assert lp.objective == pytest.approx(brute_force(p), rel=1e-12)


def test_post_step_can_lose_and_counts_the_conflict():
    # sensor 0 is best for both targets but in opposite modes; sensor 1 is fine in any mode
    c = np.full((2, 2, 9), 5.0)
    c[0, 0, :] = 10.0
    c[0, 0, 1] = 1.0  # target 0 wants sensor 0 going E
    c[1, 0, :] = 10.0
    c[1, 0, 5] = 1.0  # target 1 wants sensor 0 going W
    c[:, 1, :] = 2.0  # sensor 1 is cheaper than any compromise of sensor 0
    p = DecisionProblem(c, np.full(2, 100.0), np.full(2, np.inf))
    lp = decide_lp(p)
    assert lp.conflicts == 1 and lp.J_lp == pytest.approx(2.0)
    assert lp.objective == pytest.approx(11.0 + 1e-6)  # both stay on sensor 0, one mode
    exact = decide_milp(p)
    assert exact.objective == pytest.approx(3.0 + 2e-6)  # 1 (sensor 0) + 2 (sensor 1)
    assert exact.objective < lp.objective


def test_post_step_picks_the_mode_of_least_total_cost_and_idle_sensors_stay():
    rng = np.random.default_rng(4)
    c = rng.uniform(1, 2, (3, 3, 9))
    p = DecisionProblem(c, np.full(3, 50.0), np.full(3, np.inf))
    assign = np.array([0, 0, 2])
    modes, conflicts = post_step(p, assign, np.array([1, 2, 3]))
    assert modes[0] == np.argmin(c[0, 0] + c[1, 0])
    assert modes[1] == STAY
    assert modes[2] == np.argmin(c[2, 2])
    assert conflicts == 1


@pytest.mark.parametrize("seed", range(8))
def test_closed_form_equals_the_lp_solver_without_capacity(seed):
    p = random_problem(seed, 6, 4, conflict=seed % 2 == 0)
    a, b = decide_closed_form(p), decide_lp_highs(p)
    np.testing.assert_array_equal(a.assign, b.assign)
    np.testing.assert_array_equal(a.modes, b.modes)
    assert a.J_lp == pytest.approx(b.J_lp, rel=1e-12)
    assert decide_lp(p).solver == "lp"


def test_closed_form_refuses_capacities():
    with pytest.raises(ValueError, match="capacity"):
        decide_closed_form(random_problem(0, 2, 2, [1, np.inf]))


def test_collapsed_lp_has_the_optimum_of_the_full_lp():
    p = random_problem(3, 5, 3, [2, 1, 2])
    full = solve_lp(build_lp(p, collapse_modes=False))
    small = solve_lp(build_lp(p))
    assert full.success and small.success
    assert small.fun == pytest.approx(full.fun, rel=1e-12)
    assert build_lp(p).c.size == 5 * 3 + 5 and build_lp(p, False).c.size == 5 * 3 * 9 + 5


def test_rounding_of_a_fractional_vertex():
    # targets 0 and 1 split over sensor 0 (capacity 1) and sensor 1
    s = np.array([[[0.6], [0.4]], [[0.7], [0.3]], [[0.0], [0.0]]])
    assign, pick, fractional = round_selection(s, np.array([1.0, 5.0]))
    assert fractional
    assert assign.tolist() == [1, 0, -1]  # target 1 (0.7) first takes sensor 0
    assert pick.tolist() == [0, 0, -1]
    s_int = np.array([[[0.0], [1.0]], [[1.0], [0.0]]])
    assign, _, fractional = round_selection(s_int, np.array([1.0, 1.0]))
    assert not fractional and assign.tolist() == [1, 0]


def test_unobservable_target_is_still_covered():
    sensors = Sensors(
        np.array([[0.0, 0.0], [100.0, 0.0]]), np.array([3.0, 3.0]),
        np.stack([4.0 * np.eye(2)] * 2), np.full(2, 60.0), np.ones(2), np.zeros(2),
        np.full(2, np.inf),
    )  # fmt: skip
    x = np.array([[50.0, 0.0, 10.0, 0.0], [1e5, 0.0, 1e5, 0.0]])  # target 1: Pd ≈ 0 anywhere
    P = np.stack([np.diag([25.0, 0.25, 25.0, 0.25])] * 2)
    ct = cost_tensor(x, P, sensors, CostParams())
    assert ct.md[1].min() > 1 - 1e-12
    for name in ("lp", "lp_highs", "milp"):
        d = SOLVERS[name](DecisionProblem(ct.c, ct.c0, sensors.capacity), SolverOptions())
        assert np.all(d.assign >= 0), name


def test_too_little_capacity_leaves_targets_unobserved():
    p = random_problem(2, 4, 2, [1, 0])
    for name in ("lp", "lp_highs", "milp"):
        d = SOLVERS[name](p, SolverOptions())
        assert np.count_nonzero(d.assign >= 0) == 1, name
        assert np.all(d.assign != 1)
        assert d.modes[1] == STAY
    assert decide_lp(p).objective == pytest.approx(decide_milp(p).objective, rel=1e-12)


def test_trivial_problems():
    empty_targets = DecisionProblem(np.zeros((0, 3, 9)), np.zeros(0), np.full(3, np.inf))
    no_sensors = DecisionProblem(np.zeros((2, 0, 9)), np.array([1.0, 2.0]), np.zeros(0))
    for name, fn in SOLVERS.items():
        if name == "closed_form":
            continue
        d = fn(empty_targets, SolverOptions())
        assert d.modes.tolist() == [STAY] * 3 and d.objective == 0.0
        d = fn(no_sensors, SolverOptions())
        assert d.assign.tolist() == [-1, -1] and d.objective == 3.0


def test_problem_validation():
    with pytest.raises(ValueError, match="9"):
        DecisionProblem(np.zeros((2, 2, 8)), np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="finite"):
        DecisionProblem(np.full((1, 1, 9), np.nan), np.zeros(1), np.zeros(1))
    with pytest.raises(ValueError, match=">= 0"):
        DecisionProblem(np.zeros((1, 1, 9)), np.zeros(1), np.array([-1.0]))


def test_a_failed_lp_is_a_record_and_never_reads_x():
    p = random_problem(0, 2, 2)
    lp = build_lp(p)
    bad = LinearProgram(lp.c, lp.A_eq, np.full(2, 5.0), None, None, lp.shape, lp.mode)  # infeasible
    sol = solve_lp(bad)
    assert not sol.success and sol.status == 2 and sol.s is None and sol.u is None
    assert "infeasible" in sol.message.lower()
    err = SolverError("lp_highs", sol.status, sol.message)
    assert "status 2" in str(err)


def test_milp_time_limit_reports_status_and_gap():
    rng = np.random.default_rng(0)
    p = DecisionProblem(rng.uniform(0, 1, (30, 10, 9)), np.full(30, 5.0), np.full(10, 4.0))
    d = decide_milp(p, SolverOptions(time_limit=1e-4))
    assert d.status == 1
    assert "time limit" in d.message.lower() or d.fallback
    if not d.fallback:
        assert np.isfinite(d.mip_gap)
    assert d.objective == pytest.approx(objective(p, d.modes, d.assign))
    counts = np.bincount(d.assign[d.assign >= 0], minlength=10)
    assert np.all(counts <= 4)


def _timed_out_with(monkeypatch, x_of):
    """``solve_milp`` as HiGHS at a time-out (status 1) whose incumbent is ``x_of(real x)``."""
    real = dec_module.solve_milp

    def timed_out(mp, options):
        sol = real(mp, options)
        x = x_of(sol.x, mp)
        fun = float(mp.c @ x)
        return replace(sol, status=1, message="Time limit reached.", x=x, fun=fun, mip_gap=0.5)

    monkeypatch.setattr(dec_module, "solve_milp", timed_out)


def test_a_timed_out_milp_never_returns_worse_than_the_lp_post_step(monkeypatch):
    """A kept incumbent 6.7 times worse than the LP + post-step decision (a target left
    unobserved) was commanded at a 0.21 s limit: on a time-out the better of the two is used."""
    p = random_problem(3, 4, 3)
    lp = decide_lp(p)

    def nobody_observes(x, mp):  # feasible: every sensor stays, every target unobserved
        M, N = mp.shape
        bad = np.zeros_like(x)
        bad[M * N * 9 + np.arange(N) * 9 + STAY] = 1.0
        bad[M * N * 9 + N * 9 :] = 1.0
        return bad

    _timed_out_with(monkeypatch, nobody_observes)
    d = decide_milp(p)
    assert d.fallback and d.status == 1 and d.solver == "milp" and d.mip_gap == 0.5
    assert d.objective == lp.objective and np.array_equal(d.assign, lp.assign)
    assert "worse than the LP + post-step" in d.message


def test_a_timed_out_milp_keeps_a_better_incumbent_and_has_no_j_star(monkeypatch):
    p = random_problem(3, 4, 3, conflict=True)
    best = decide_milp(p)
    _timed_out_with(monkeypatch, lambda x, mp: x)  # the optimum, but not proven in time
    d = decide_milp(p)
    assert not d.fallback and d.status == 1 and d.objective == best.objective
    # the optimality statistics leave it out: J* unknown
    c = compare(decide_lp(p), d, 0.0)
    assert np.isnan(c.J_star) and np.isnan(c.gap) and c.exact_status == 1


def test_milp_program_shapes():
    p = random_problem(0, 3, 2, [1, np.inf])
    strong, weak = build_milp(p, "strong"), build_milp(p, "weak")
    n = 3 * 2 * 9 + 2 * 9 + 3
    assert strong.A_eq.shape == weak.A_eq.shape == (3 + 2, n)
    assert strong.A_ub.shape == (3 * 2 * 9 + 1, n)  # linking + one capacity row
    assert weak.A_ub.shape == (2 * 9 + 1, n)
    with pytest.raises(ValueError, match="linking"):
        build_milp(p, "medium")  # type: ignore[arg-type]


def test_decision_pair_modes_and_registry():
    p = random_problem(1, 3, 2, conflict=True)
    d = decide_lp(p)
    pm = d.pair_modes
    for i in range(3):
        assert pm[i] == (d.modes[d.assign[i]] if d.assign[i] >= 0 else -1)
    assert sorted(SOLVERS) == ["closed_form", "lp", "lp_highs", "milp"]
    assert replace(d, solver="x").solver == "x"


def test_a_relaxation_the_dual_simplex_leaves_unknown_is_solved_by_the_interior_point():
    """Found by the property test: four targets, three sensors at one point; HiGHS's dual
    simplex ends the MILP's relaxation with "model_status is Unknown" (status 4), and the
    relaxation was NaN, so a mobile run's J_relax too.  The interior-point method (with its
    crossover) solves it; the bound is then the MILP's optimum, which it must not exceed."""
    x = np.array([[248.0, 0, 70, 0], [50, 0, 224, 0], [0, 0, 91, 0], [0, 0, 125, 0]])
    P = np.diag([25.0, 0.25, 25.0, 0.25])[None].repeat(4, 0)
    sensors = Sensors(
        position=np.array([[190.0, 0], [190, 190], [190, 190], [190, 190]]),
        speed=np.array([0.0, 3.5, 0, 0]),
        R0=np.array([4.0, 1, 4, 4])[:, None, None] * np.eye(2),
        r_pd=np.full(4, 20.0),
        b0=np.ones(4),
        b1=np.zeros(4),
        capacity=np.full(4, np.inf),
    )
    params = CostParams(trace_kind="full", dist_uses_velocity=False, pd_include_track_cov=False)
    ct = cost_tensor(x, P, sensors, params)
    p = DecisionProblem(ct.c, ct.c0, sensors.capacity)
    status, message, value = relaxation(p)
    exact = decide_milp(p)
    assert status == 0, message
    assert "interior point" in message
    assert decide_lp(p).J_lp - 1e-9 * value <= value <= exact.objective * (1 + 1e-9)
