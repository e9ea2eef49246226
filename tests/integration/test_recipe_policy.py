"""README "Adding an allocation policy", executed: a new policy (the K available sensors with
the smallest noise, ``tr R_j``: a "best sensors" rule of thumb) is its decide function and one
:class:`~covnet.core.allocation.policy_registry.Policy` record in ``POLICIES`` (registered here
in a temporary registry: the test's own ``monkeypatch``); a config naming it runs through
``covnet run``, a lockstep network run (equal bit for bit) and ``covnet replay``; and the config
refuses, in the entry's words, what it cannot do."""

from __future__ import annotations

import numpy as np
import pytest
from recipe_harness import run_all_three, write_config

from covnet.config import ConfigError
from covnet.core.allocation.policies import PolicyDecision
from covnet.core.allocation.policy_registry import POLICIES, Policy
from covnet.covariance_control.config import load
from covnet.covariance_control.simulate import run_metric

CALLS: list[int] = []


def quietest(P_pred, gains, constraints, *, budget=None, scan=1, rng=None, tie_rtol=1e-9):
    """The required sensors, then the available ones with the most information (largest
    ``tr J_j``, lowest index among equals) up to ``K``."""
    CALLS.append(scan)
    N = gains.shape[0]
    K = budget if constraints.max_active is None else min(budget, constraints.max_active)
    free = [j for j in range(N) if j not in constraints.excluded and j not in constraints.required]
    free.sort(key=lambda j: (-float(np.trace(gains[j])), j))
    chosen = sorted({*constraints.required, *free[: max(0, K - len(constraints.required))]})
    return PolicyDecision(tuple(chosen), None, len(free), False)


ENTRY = Policy(
    "quietest",
    "the K sensors with the most information, whatever the target needs",
    needs_budget=True,
    uses_metric=False,
    stochastic=False,
    many_targets=False,
    decide=quietest,
)


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(POLICIES, "quietest", ENTRY)
    CALLS.clear()


def test_a_new_policy_runs_through_run_network_and_replay(tmp_path, registered):
    cfg = write_config(tmp_path, {"metrics": ["abs_trace"], "policy": "quietest", "budget": 2})
    run_all_three(cfg, tmp_path, "abs_trace")
    assert CALLS, "the policy was never asked"
    run = run_metric(load(cfg), "abs_trace")
    on = [tuple(np.flatnonzero(r)) for r in run.enabled]
    assert len(set(on)) == 1 and len(on[0]) == 2  # the same two quietest sensors every scan


def test_the_config_refuses_in_the_entrys_words(tmp_path, registered):
    cfg = write_config(tmp_path, {"policy": "quietest"})
    with pytest.raises(ConfigError, match="the K sensors with the most information"):
        load(cfg)
