"""Allocation policies (covnet.core.allocation.policies, policies_many): the registry, the
rewards' formulas on hand-computed cases, brute force against plain loops and against greedy
where greedy is exact, the schedules' determinism, constraints and refusals."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from covnet.core.allocation import policies, policies_many
from covnet.core.allocation.assignment import OFF as ALLOCATOR_OFF
from covnet.core.allocation.assignment import MultiConstraints
from covnet.core.allocation.constraints import Constraints
from covnet.core.allocation.exact import InfeasibleAllocation
from covnet.core.allocation.policies import (
    expected_kl,
    expected_kl_sequential,
    information_gain,
    round_robin_order,
    uncertainty_reward,
)
from covnet.core.allocation.policies_many import OFF, total_reward
from covnet.core.allocation.policy_registry import POLICIES

DECIDING = sorted(n for n, p in POLICIES.items() if p.decide is not None)
REWARDS = ["uncertainty_reward", "expected_kl"]

# the hand case: P⁻ = diag(4, 1); sensor 0 sees x with R = 1, sensor 1 sees y with R = 1/3
P2 = np.diag([4.0, 1.0])
G2 = np.array([np.diag([1.0, 0.0]), np.diag([0.0, 3.0])])


def _problem(N=6, n=4, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    P = A @ A.T + np.eye(n)
    G = []
    for _ in range(N):
        H = rng.normal(size=(2, n))
        B = rng.normal(size=(2, 2))
        R = B @ B.T + 0.5 * np.eye(2)
        G.append(H.T @ np.linalg.inv(R) @ H)
    return P, np.array(G)


def _textbook(name, P, G, D):
    """The rewards from their defining formulas, with explicit inverses."""
    n = P.shape[0]
    J = sum((G[j] for j in D), np.zeros((n, n)))
    Pd = np.linalg.inv(np.linalg.inv(P) + J)
    if name == "uncertainty_reward":
        return np.linalg.norm(P, "fro") - np.linalg.norm(Pd, "fro")
    if name == "expected_kl":
        return 0.5 * (
            np.trace(np.linalg.inv(Pd) @ P) - n + math.log(np.linalg.det(Pd) / np.linalg.det(P))
        )
    return math.log(np.linalg.det(np.linalg.inv(P) + J) / np.linalg.det(np.linalg.inv(P)))


# --------------------------------------------------------------------------------------------
# the registry
# --------------------------------------------------------------------------------------------


def test_the_registry_entries():
    assert set(POLICIES) == {
        "covariance_control",
        "all_on",
        "random",
        "round_robin",
        "greedy_information",
        "uncertainty_reward",
        "expected_kl",
    }
    for name, p in POLICIES.items():
        assert p.name == name and "\n" not in p.summary and p.summary
    cc = POLICIES["covariance_control"]
    assert cc.delegates_to_search and cc.uses_metric and cc.decide is None
    assert cc.decide_many is None
    for name in DECIDING:
        p = POLICIES[name]
        assert not p.delegates_to_search and not p.uses_metric
        assert p.many_targets and p.decide_many is not None
    assert [n for n, p in POLICIES.items() if p.stochastic] == ["random"]
    assert not POLICIES["all_on"].needs_budget
    assert POLICIES["expected_kl"].reward is expected_kl
    assert POLICIES["uncertainty_reward"].reward is uncertainty_reward


def test_importing_the_policies_loads_no_allocator():
    import subprocess
    import sys

    code = (
        "import sys, covnet.core.allocation.policies\n"
        "print(sorted(m for m in sys.modules if m.startswith(('covnet.core.allocation.', "
        "'scipy', 'stonesoup'))))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == str(
        ["covnet.core.allocation.constraints", "covnet.core.allocation.policies"]
    )


def test_off_is_the_allocators():
    assert OFF == ALLOCATOR_OFF


# --------------------------------------------------------------------------------------------
# the formulas, by hand
# --------------------------------------------------------------------------------------------


def test_hand_values_of_the_rewards():
    # P({0}) = diag(0.8, 1), P({1}) = diag(4, 0.25), P({0,1}) = diag(0.8, 0.25)
    fro = math.sqrt(17.0)
    assert uncertainty_reward(P2, G2, [0]) == pytest.approx(fro - math.sqrt(1.64), rel=1e-12)
    assert uncertainty_reward(P2, G2, [1]) == pytest.approx(fro - math.sqrt(16.0625), rel=1e-12)
    assert uncertainty_reward(P2, G2, [0, 1]) == pytest.approx(fro - math.sqrt(0.7025), rel=1e-12)
    # whitened information L'JL: diag(4, 0) and diag(0, 3)
    assert expected_kl(P2, G2, [0]) == pytest.approx(0.5 * (4 - math.log(5)), rel=1e-12)
    assert expected_kl(P2, G2, [1]) == pytest.approx(0.5 * (3 - math.log(4)), rel=1e-12)
    assert expected_kl(P2, G2, [0, 1]) == pytest.approx(0.5 * (7 - math.log(20)), rel=1e-12)
    assert information_gain(P2, G2, [0]) == pytest.approx(math.log(5), rel=1e-12)
    assert information_gain(P2, G2, [0, 1]) == pytest.approx(math.log(20), rel=1e-12)
    assert uncertainty_reward(P2, G2, []) == 0.0 and expected_kl(P2, G2, []) == 0.0


@pytest.mark.parametrize("name", [*REWARDS, "information_gain"])
def test_rewards_equal_their_textbook_formulas(name):
    fn = {"information_gain": information_gain, **{r: POLICIES[r].reward for r in REWARDS}}[name]
    for seed in range(5):
        P, G = _problem(N=4, seed=seed)
        for k in range(1, 5):
            for D in itertools.combinations(range(4), k):
                assert fn(P, G, D) == pytest.approx(_textbook(name, P, G, D), rel=1e-9)


def test_sequential_kl_is_the_sum_of_each_updates_kl_and_depends_on_the_order():
    P, G = _problem(N=3, seed=3)
    assert expected_kl_sequential(P, G, [1]) == pytest.approx(expected_kl(P, G, [1]), rel=1e-12)
    # by hand: KL(P⁻ ‖ P_0) + KL(P_0 ‖ P_01), P_0 the prior of the second update
    P0 = np.linalg.inv(np.linalg.inv(P) + G[0])
    want = _textbook("expected_kl", P, G, [0]) + _textbook("expected_kl", P0, G, [1])
    assert expected_kl_sequential(P, G, [0, 1]) == pytest.approx(want, rel=1e-9)
    other = expected_kl_sequential(P, G, [1, 0])
    assert abs(other - want) > 1e-6 * want  # the order matters: the joint KL is order-free
    assert expected_kl(P, G, [0, 1]) == pytest.approx(expected_kl(P, G, [1, 0]), rel=1e-14)


def test_hand_decisions():
    c = Constraints()
    d = POLICIES["greedy_information"].decide(P2, G2, c, budget=1)
    assert d.subset == (0,) and d.score == pytest.approx(math.log(5))
    d = POLICIES["greedy_information"].decide(P2, G2, c)
    assert d.subset == (0, 1) and d.score == pytest.approx(math.log(20))
    for name in REWARDS:
        d = POLICIES[name].decide(P2, G2, c, budget=1)
        assert d.subset == (0,) and d.exhaustive and d.n_evaluated == 2
        d = POLICIES[name].decide(P2, G2, c, budget=2)
        assert d.subset == (0, 1) and d.n_evaluated == 3
        assert d.score == pytest.approx(POLICIES[name].reward(P2, G2, (0, 1)), rel=1e-12)
    assert POLICIES["all_on"].decide(P2, G2, c).subset == (0, 1)


# --------------------------------------------------------------------------------------------
# brute force and greedy
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", REWARDS)
def test_brute_force_is_the_plain_loops_best(name):
    for seed in range(4):
        P, G = _problem(N=6, seed=seed)
        c = Constraints(excluded=frozenset({4}), required=frozenset({1}))
        for K in (1, 2, 3, 6):
            d = POLICIES[name].decide(P, G, c, budget=K)
            best = max(
                (
                    D
                    for k in range(1, K + 1)
                    for D in itertools.combinations(range(6), k)
                    if 1 in D and 4 not in D
                ),
                key=lambda D: _textbook(name, P, G, D),
            )
            assert d.subset == best and d.exhaustive
            # a reward that grows with every sensor: exactly K (as Stone Soup's manager)
            assert len(d.subset) == min(K, 5)


@pytest.mark.parametrize("name", REWARDS)
def test_greedy_beyond_the_limit_agrees_with_brute_force_at_budget_one(name, monkeypatch):
    for seed in range(5):
        P, G = _problem(N=7, seed=seed)
        exact = POLICIES[name].decide(P, G, Constraints(), budget=1)
        monkeypatch.setattr(policies, "BRUTE_FORCE_MAX", 0)
        greedy = POLICIES[name].decide(P, G, Constraints(), budget=1)
        monkeypatch.undo()
        assert not greedy.exhaustive and exact.exhaustive
        assert greedy.subset == exact.subset
        assert greedy.score == pytest.approx(exact.score, rel=1e-12)
        # with a budget greedy stays feasible and within the brute force's reward
        monkeypatch.setattr(policies, "BRUTE_FORCE_MAX", 0)
        g3 = POLICIES[name].decide(P, G, Constraints(required=frozenset({6})), budget=3)
        monkeypatch.undo()
        e3 = POLICIES[name].decide(P, G, Constraints(required=frozenset({6})), budget=3)
        assert len(g3.subset) == 3 and 6 in g3.subset
        assert g3.score <= e3.score * (1 + 1e-12)


def test_the_brute_force_limit_is_the_number_of_feasible_subsets(monkeypatch):
    P, G = _problem(N=6)
    n = policies.feasible_subset_count(6, 0, 6)
    assert n == 63
    monkeypatch.setattr(policies, "BRUTE_FORCE_MAX", n)
    assert POLICIES["expected_kl"].decide(P, G).exhaustive
    monkeypatch.setattr(policies, "BRUTE_FORCE_MAX", n - 1)
    assert not POLICIES["expected_kl"].decide(P, G).exhaustive


def test_reward_ties_go_to_fewer_sensors_then_the_lowest_indices():
    P = np.eye(2)
    G = np.array([np.diag([1.0, 0.0]), np.diag([1.0, 0.0]), np.zeros((2, 2))])
    for name in REWARDS:
        assert POLICIES[name].decide(P, G, budget=1).subset == (0,)
        # sensor 2 adds nothing: {0, 1} beats {0, 1, 2} by the fewer sensors
        assert POLICIES[name].decide(P, G, budget=3).subset == (0, 1)


def test_greedy_information_stops_when_nothing_gains():
    P = np.eye(2)
    G = np.array([np.zeros((2, 2)), np.diag([1.0, 0.0]), np.zeros((2, 2)), np.diag([1e-12, 0])])
    d = POLICIES["greedy_information"].decide(P, G)
    assert d.subset == (1,)
    # nothing gains at all: one sensor still (a decision is never empty), the lowest index
    assert POLICIES["greedy_information"].decide(P, np.zeros((3, 2, 2))).subset == (0,)
    # the required ones stay in whatever they gain
    d = POLICIES["greedy_information"].decide(P, G, Constraints(required=frozenset({2})))
    assert d.subset == (1, 2)


def test_greedy_information_ties_to_the_lowest_index():
    G = np.array([np.diag([1.0, 0.0])] * 3)
    assert POLICIES["greedy_information"].decide(np.eye(2), G, budget=1).subset == (0,)


# --------------------------------------------------------------------------------------------
# the schedules
# --------------------------------------------------------------------------------------------


def test_random_is_the_generators_draw():
    P, G = _problem(N=8)
    c = Constraints(excluded=frozenset({0}), required=frozenset({5}))
    a = POLICIES["random"].decide(P, G, c, budget=3, rng=np.random.default_rng(7))
    b = POLICIES["random"].decide(P, G, c, budget=3, rng=np.random.default_rng(7))
    assert a == b and 5 in a.subset and 0 not in a.subset and len(a.subset) == 3
    draw = np.random.default_rng(7).choice(np.array([1, 2, 3, 4, 6, 7]), size=2, replace=False)
    assert a.subset == tuple(sorted([5, *draw.tolist()]))
    seen = set()
    for s in range(40):
        seen |= set(
            POLICIES["random"].decide(P, G, c, budget=3, rng=np.random.default_rng(s)).subset
        )
    assert seen == {1, 2, 3, 4, 5, 6, 7}


def test_round_robin_blocks_and_coverage():
    P, G = _problem(N=7)
    rr = POLICIES["round_robin"].decide
    assert rr(P, G, budget=3, scan=1).subset == (0, 1, 2)
    assert rr(P, G, budget=3, scan=2).subset == (3, 4, 5)
    assert rr(P, G, budget=3, scan=3).subset == (0, 1, 6)  # 6, 7 mod 7 = 0, 8 mod 7 = 1
    # a function of the scan alone: any order of calls
    assert rr(P, G, budget=3, scan=2) == rr(P, G, budget=3, scan=2)
    for K in range(1, 8):
        for start in (1, 5, 11):
            seen = set()
            for k in range(start, start + math.ceil(7 / K)):
                seen |= set(rr(P, G, budget=K, scan=k).subset)
            assert seen == set(range(7)), (K, start)
    # an excluded sensor is skipped without moving the others' turns
    c = Constraints(excluded=frozenset({4}))
    assert rr(P, G, c, budget=3, scan=2).subset == (3, 5, 6)
    assert rr(P, G, c, budget=3, scan=1).subset == (0, 1, 2)
    # required: always in, the others at stride K - |required|
    c = Constraints(required=frozenset({0}))
    seen = set()
    for k in range(1, 1 + math.ceil(7 / 2)):
        d = rr(P, G, c, budget=3, scan=k)
        assert 0 in d.subset and len(d.subset) == 3
        seen |= set(d.subset)
    assert seen == set(range(7))


@pytest.mark.parametrize(
    "N, eligible, m",
    [(8, [0, 1, 3, 4, 6, 7], 4), (8, [0, 2, 3, 4, 5, 6, 7], 2), (8, [1, 2, 3, 4, 5, 6, 7], 3)],
)
def test_round_robin_gives_every_eligible_sensor_the_same_share(N, eligible, m):
    """README: "K sensors in a cyclic order". The cycle over all N indices, skipping the
    ineligible ones, put the sensor after each skipped one on twice as often (2 of 8 excluded,
    K = 4: two sensors on every scan, the paper config's S1 and S5)."""
    E = len(eligible)
    counts = dict.fromkeys(eligible, 0)
    for scan in range(1, 1 + 5 * E):  # 5 E scans: every eligible sensor exactly 5 m times
        for j, _ in round_robin_order(N, eligible, m, scan):
            counts[j] += 1
    assert set(counts.values()) == {5 * m}, counts


def test_round_robin_order_rounds():
    assert round_robin_order(4, [0, 1, 2, 3], 3, 2) == [(3, 0), (0, 1), (1, 1)]
    with pytest.raises(ValueError, match="scan number must be an integer >= 1"):
        round_robin_order(4, [0, 1], 1, 0)
    P, G = _problem(N=3)
    c = Constraints(required=frozenset({0, 1}))
    for decide in (POLICIES["round_robin"].decide, POLICIES["round_robin"].decide_many):
        args = (P, G) if decide is POLICIES["round_robin"].decide else (P[None], G[:, None], None)
        with pytest.raises(ValueError, match="scan number must be an integer >= 1"):
            decide(*args, c, budget=2, scan=0)  # even with no free slot


# --------------------------------------------------------------------------------------------
# constraints and refusals
# --------------------------------------------------------------------------------------------


def test_all_on_honours_constraints_and_refuses_a_smaller_max_active():
    P, G = _problem(N=5)
    c = Constraints(excluded=frozenset({1, 3}), required=frozenset({4}))
    assert POLICIES["all_on"].decide(P, G, c).subset == (0, 2, 4)
    assert POLICIES["all_on"].decide(P, G, Constraints(max_active=5)).subset == tuple(range(5))
    with pytest.raises(ValueError, match=r"'all_on'.*max_active=2"):
        POLICIES["all_on"].decide(P, G, Constraints(max_active=2))


def test_refusals_name_the_policy():
    P, G = _problem(N=4)
    with pytest.raises(ValueError, match="'random' needs a numpy.random.Generator"):
        POLICIES["random"].decide(P, G, budget=2)
    for name in ("random", "round_robin"):
        with pytest.raises(ValueError, match=f"policy '{name}' needs a budget K"):
            POLICIES[name].decide(P, G, rng=np.random.default_rng(0))
    for name in DECIDING:
        if POLICIES[name].needs_budget:
            with pytest.raises(ValueError, match=f"policy '{name}': the budget K=1 is smaller"):
                POLICIES[name].decide(
                    P,
                    G,
                    Constraints(required=frozenset({0, 1})),
                    budget=1,
                    rng=np.random.default_rng(0),
                )
            with pytest.raises(ValueError, match=f"policy '{name}': budget must be an integer"):
                POLICIES[name].decide(P, G, budget=0, rng=np.random.default_rng(0))
        with pytest.raises(InfeasibleAllocation, match="every sensor is excluded"):
            POLICIES[name].decide(
                P,
                G,
                Constraints(excluded=frozenset(range(4))),
                budget=1,
                rng=np.random.default_rng(0),
            )
    with pytest.raises(ValueError, match="both excluded and required"):
        POLICIES["all_on"].decide(
            P, G, Constraints(excluded=frozenset({1}), required=frozenset({1}))
        )
    with pytest.raises(ValueError, match="excluded sensor indices must be integers in"):
        POLICIES["all_on"].decide(P, G, Constraints(excluded=frozenset({9})))
    with pytest.raises(ValueError, match="P_pred is not positive definite"):
        POLICIES["expected_kl"].decide(-np.eye(4), G)
    with pytest.raises(ValueError, match=r"gains must be \(N, 4, 4\)"):
        POLICIES["expected_kl"].decide(P, G[:, :2])


def test_the_budget_is_the_smaller_of_budget_and_max_active():
    P, G = _problem(N=6)
    for name in ("round_robin", "greedy_information", *REWARDS):
        d = POLICIES[name].decide(P, G, Constraints(max_active=2), budget=4)
        assert len(d.subset) == 2
        d = POLICIES[name].decide(P, G, Constraints(max_active=2))
        assert len(d.subset) <= 2
    # larger than the available count: all of them
    d = POLICIES["random"].decide(P, G, budget=10, rng=np.random.default_rng(0))
    assert d.subset == tuple(range(6))


# --------------------------------------------------------------------------------------------
# many targets
# --------------------------------------------------------------------------------------------


def _many(N=5, T=3, seed=1):
    rng = np.random.default_rng(seed)
    P, G = _problem(N=N, seed=seed)
    Pm = np.array([P * (1 + t) for t in range(T)])
    J = np.stack([G * rng.uniform(0.2, 2.0) for _ in range(T)], axis=1)
    feas = rng.random((N, T)) < 0.7
    feas[np.arange(N), rng.integers(0, T, N)] = True
    return Pm, J, feas


@pytest.mark.parametrize("name", DECIDING)
def test_one_target_many_forms_are_the_one_target_policies(name):
    P, G = _problem(N=6, seed=2)
    J = G[:, None]
    for c, K in (
        (Constraints(), 2),
        (Constraints(excluded=frozenset({1}), required=frozenset({3})), 3),
    ):
        if name == "all_on":
            K = None
        one = POLICIES[name].decide(P, G, c, budget=K, scan=3, rng=np.random.default_rng(5))
        many = POLICIES[name].decide_many(
            P[None], J, None, c, budget=K, scan=3, rng=np.random.default_rng(5)
        )
        assert many.subset == one.subset
        assert set(many.assignment) <= {0, OFF}
        if one.score is not None:
            assert many.score == pytest.approx(one.score, rel=1e-9)


def test_many_all_on_puts_each_sensor_on_its_largest_gain():
    Pm, J, feas = _many()
    d = POLICIES["all_on"].decide_many(Pm, J, feas)
    for j, t in enumerate(d.assignment):
        gains = {u: information_gain(Pm[u], J[:, u], [j]) for u in range(3) if feas[j, u]}
        assert t == max(gains, key=lambda u: (gains[u], -u))
    with pytest.raises(ValueError, match=r"'all_on'.*max_active=2"):
        POLICIES["all_on"].decide_many(Pm, J, feas, MultiConstraints(max_active=2))


@pytest.mark.parametrize("name", REWARDS)
def test_many_brute_force_is_the_plain_loops_best(name):
    Pm, J, feas = _many(N=5, T=2)
    c = MultiConstraints(required=frozenset({2}), excluded=frozenset({0}))
    for K in (1, 2, 3):
        d = POLICIES[name].decide_many(Pm, J, feas, c, budget=K)
        best, best_v = None, -np.inf
        for a in itertools.product([OFF, 0, 1], repeat=5):
            on = [j for j in range(5) if a[j] != OFF]
            if not on or len(on) > K or a[0] != OFF or a[2] == OFF:
                continue
            if any(a[j] != OFF and not feas[j, a[j]] for j in range(5)):
                continue
            v = sum(
                _textbook(name, Pm[t], J[:, t], [j for j in range(5) if a[j] == t])
                for t in range(2)
            )
            if v > best_v * (1 + 1e-9):
                best, best_v = a, v
        assert d.assignment == best and d.exhaustive
        assert d.score == pytest.approx(best_v, rel=1e-9)
        assert total_reward(name, Pm, J, d.assignment, feas) == pytest.approx(d.score, rel=1e-12)


@pytest.mark.parametrize("name", REWARDS)
def test_many_greedy_agrees_with_brute_force_at_budget_one(name, monkeypatch):
    for seed in range(4):
        Pm, J, feas = _many(N=6, T=3, seed=seed)
        exact = POLICIES[name].decide_many(Pm, J, feas, budget=1)
        monkeypatch.setattr(policies_many, "MANY_BRUTE_FORCE_MAX", 0)
        greedy = POLICIES[name].decide_many(Pm, J, feas, budget=1)
        monkeypatch.undo()
        assert greedy.assignment == exact.assignment and not greedy.exhaustive


def test_many_greedy_information_at_budget_one_is_the_best_pair():
    Pm, J, feas = _many(N=6, T=3)
    d = POLICIES["greedy_information"].decide_many(Pm, J, feas, budget=1)
    pairs = [(j, t) for j in range(6) for t in range(3) if feas[j, t]]
    best = max(pairs, key=lambda p: information_gain(Pm[p[1]], J[:, p[1]], [p[0]]))
    assert d.assignment == tuple(best[1] if j == best[0] else OFF for j in range(6))


def test_many_round_robin_cycles_sensors_and_targets():
    T, N = 3, 4
    Pm, J, _ = _many(N=N, T=T)
    rr = POLICIES["round_robin"].decide_many
    seen = {j: set() for j in range(N)}
    for k in range(1, 1 + 2 * T * N):
        d = rr(Pm, J, None, None, budget=2, scan=k)
        assert d.n_evaluated == 0 and len(d.subset) == 2
        for j in d.subset:
            seen[j].add(d.assignment[j])
    assert all(s == set(range(T)) for s in seen.values())
    # coverage: a sensor that covers only target 1 always dwells on it
    feas = np.ones((N, T), dtype=bool)
    feas[2] = [False, True, False]
    for k in range(1, 9):
        d = rr(Pm, J, feas, None, budget=2, scan=k)
        assert 2 not in d.subset or d.assignment[2] == 1


def test_many_random_and_refusals():
    Pm, J, feas = _many()
    c = MultiConstraints(required=frozenset({1}))
    a = POLICIES["random"].decide_many(Pm, J, feas, c, budget=3, rng=np.random.default_rng(3))
    b = POLICIES["random"].decide_many(Pm, J, feas, c, budget=3, rng=np.random.default_rng(3))
    assert a == b and a.assignment[1] != OFF and len(a.subset) == 3
    with pytest.raises(ValueError, match="'random' needs a numpy.random.Generator"):
        POLICIES["random"].decide_many(Pm, J, feas, c, budget=3)
    nofeas = feas.copy()
    nofeas[1] = False
    with pytest.raises(InfeasibleAllocation, match="required sensor 1 has no feasible target"):
        POLICIES["greedy_information"].decide_many(Pm, J, nofeas, c)
    with pytest.raises(InfeasibleAllocation, match="'all_on': sensor 0 has no covered target"):
        POLICIES["all_on"].decide_many(Pm, J, None, MultiConstraints(max_per_target=0))


@pytest.mark.parametrize("name", REWARDS)
@pytest.mark.parametrize("N", [64, 65, 70, 130])
def test_many_rewards_beyond_63_sensors(name, N, monkeypatch):
    """Sensor sets are bit masks of any width: with 64 or more sensors (``configs/
    large_multitarget.yaml`` has 64) the reward policies decide as on the informative sensors
    alone.  Here the first ``N - 5`` sensors carry no information (covered, zero gain), the
    five informative ones sit at indices up to ``N - 1`` (bit 63 and beyond): the greedy's
    decision and score are the five's alone, greedily (it never takes a sensor that gains
    nothing)."""
    Pm, J5, feas5 = _many(N=5, T=3, seed=2)
    J = np.zeros((N, *J5.shape[1:]))
    J[N - 5 :] = J5
    feas = np.ones((N, 3), dtype=bool)
    feas[N - 5 :] = feas5
    big = POLICIES[name].decide_many(Pm, J, feas, budget=5)
    monkeypatch.setattr(policies_many, "MANY_BRUTE_FORCE_MAX", 0)
    small = POLICIES[name].decide_many(Pm, J5, feas5, budget=5)
    assert not big.exhaustive and not small.exhaustive  # (T + 1)^N assignments: the greedy
    assert big.assignment == (OFF,) * (N - 5) + small.assignment
    assert big.score == small.score
    assert big.score == pytest.approx(total_reward(name, Pm, J, big.assignment, feas), rel=1e-12)
