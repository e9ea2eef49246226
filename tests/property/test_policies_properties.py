"""Allocation policies over random problems: every decision honours the constraints (required
in, excluded out, at most K, non-empty, coverage with many targets), and the rewards grow with
every sensor."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from covnet.core.allocation.assignment import MultiConstraints
from covnet.core.allocation.constraints import Constraints
from covnet.core.allocation.policies import expected_kl, uncertainty_reward
from covnet.core.allocation.policies_many import OFF
from covnet.core.allocation.policy_registry import POLICIES

DECIDING = sorted(n for n, p in POLICIES.items() if p.decide is not None)


@st.composite
def problems(draw, many=False):
    N = draw(st.integers(1, 7))
    T = draw(st.integers(1, 3)) if many else 1
    n = draw(st.integers(1, 4))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(T, n, n))
    P = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(n)
    H = rng.normal(size=(N, T, 1, n)) * rng.uniform(0.0, 3.0, size=(N, T, 1, 1))
    J = np.swapaxes(H, -1, -2) @ H
    roles = draw(st.lists(st.sampled_from("fer"), min_size=N, max_size=N))
    if all(r == "e" for r in roles):
        roles[0] = "f"
    excluded = frozenset(j for j, r in enumerate(roles) if r == "e")
    required = frozenset(j for j, r in enumerate(roles) if r == "r")
    avail = N - len(excluded)
    K = draw(st.integers(max(1, len(required)), avail + 1))
    feas = rng.random((N, T)) < 0.6
    feas[np.arange(N), rng.integers(0, T, N)] = True  # every sensor covers some target
    max_active = draw(st.sampled_from([None, K]))
    name = draw(st.sampled_from(DECIDING))
    return name, P, J, feas, excluded, required, K, max_active, seed


def _kwargs(name, K, seed):
    budget = K if POLICIES[name].needs_budget else None
    return {"budget": budget, "scan": seed % 50 + 1, "rng": np.random.default_rng(seed)}


@given(problems())
def test_one_target_decisions_honour_the_constraints(case):
    name, P, J, _, excluded, required, K, max_active, seed = case
    if name == "all_on":
        max_active = None
    c = Constraints(excluded, required, max_active)
    d = POLICIES[name].decide(P[0], J[:, 0], c, **_kwargs(name, K, seed))
    D = set(d.subset)
    assert list(d.subset) == sorted(D) and D
    assert required <= D and not (excluded & D)
    N = J.shape[0]
    if name == "all_on":
        assert D == set(range(N)) - excluded
    else:
        assert len(D) <= K
    if name in ("random", "round_robin"):
        assert len(D) == min(K, N - len(excluded))


@given(problems(many=True))
def test_many_target_decisions_honour_the_constraints_and_coverage(case):
    name, P, J, feas, excluded, required, K, max_active, seed = case
    if name == "all_on":
        max_active = None
    c = MultiConstraints(excluded, required, max_active)
    d = POLICIES[name].decide_many(P, J, feas, c, **_kwargs(name, K, seed))
    a = d.assignment
    D = set(d.subset)
    assert len(a) == J.shape[0] and D
    assert required <= D and not (excluded & D)
    assert all(x == OFF or feas[j, x] for j, x in enumerate(a))
    if name != "all_on":
        assert len(D) <= K


@given(problems())
def test_the_rewards_grow_with_every_sensor(case):
    _, P, J, _, _, _, _, _, _ = case
    N = J.shape[0]
    for reward in (uncertainty_reward, expected_kl):
        prev = 0.0
        for k in range(1, N + 1):
            v = reward(P[0], J[:, 0], range(k))
            assert v >= prev - 1e-9 * max(abs(prev), 1.0)
            prev = v
