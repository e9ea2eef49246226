"""The baseline allocation policies of a covariance-control config (``allocation.policy``,
:mod:`covnet.core.allocation.policy_registry`) as the kind's decision: one target
(:func:`decide_by_policy`, called by :func:`covnet.covariance_control.model.decide`) and many
(:func:`decide_many_by_policy`, called by :func:`covnet.covariance_control.targets.decide`).

Every driver of the kind's engine decides through those two functions, so a policy runs alike
in ``covnet run``, ``covnet up``, the slow-link simulation, the replay and the batch commands.
The policy picks the subset (or the assignment); the value logged is still the covariance-
control objective of what it picked, so that every policy's ``f`` reads alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from covnet.core import streams
from covnet.core.allocation.assignment import MultiConstraints
from covnet.core.allocation.constraints import Constraints
from covnet.core.allocation.exact import Allocation, subset_covariance
from covnet.core.allocation.policy_registry import POLICIES
from covnet.core.gaussian import Mat
from covnet.core.metrics import METRICS

__all__ = ["decide_by_policy", "decide_many_by_policy"]


def decide_by_policy(model: Any, P_pred: Mat, scan: int, metric: str, c: Constraints) -> Allocation:
    """Scan ``k``'s subset by the baseline policy ``model.policy``
    (:data:`covnet.core.allocation.policy_registry.POLICIES`: ``all_on``, ``random``,
    ``round_robin``, ``greedy_information``, ``uncertainty_reward``, ``expected_kl``), which
    ignores ``P_d``; its ``value`` is still the covariance-control objective
    ``f(P_i, P_d(t_k))`` of the chosen subset, ``P_i = (P⁻⁻¹ + Σ_{j∈D} J_j)⁻¹``, so that every
    policy's log reads alike.  A stochastic policy draws from
    :func:`covnet.core.streams.policy_stream` ``(seed, k)``."""
    pol = POLICIES[model.policy]
    assert pol.decide is not None  # covariance_control is the search's
    rng = streams.policy_stream(model.seed, scan) if pol.stochastic else None
    d = pol.decide(
        P_pred, model.gains, c, budget=model.budget, scan=scan, rng=rng, tie_rtol=model.tie_rtol
    )
    subset = tuple(d.subset)
    P = subset_covariance(P_pred, model.gains[list(subset)].sum(axis=0))
    value = float(METRICS[metric](P, model.desired(scan)))
    return Allocation(subset, value, P, d.n_evaluated, d.n_evaluated)


def decide_many_by_policy(
    tm: Any,
    P_pred: Mat,
    J: Mat,
    P_d: Mat,
    w: Sequence[float],
    scan: int,
    metric: str,
    feas: np.ndarray,
    mc: MultiConstraints,
) -> tuple[tuple[int, ...], float, tuple[float, ...], Mat, int]:
    """Scan ``k``'s assignment by the baseline policy ``allocation.policy`` (its many-target
    form, :mod:`covnet.core.allocation.policies_many`), which ignores ``P_d``; the value is
    still the covariance-control objective ``F = Σ_t w_t f(P_t, P_d,t)`` of the assignment,
    ``P_t = (P_t⁻⁻¹ + Σ_{a_j = t} J_jt)⁻¹``, so that every policy's log reads alike.  Returns
    the fields of a :class:`~covnet.covariance_control.targets.TargetDecision`:
    ``(assignment, F, v_t, P_t, n_evaluated)``; ``tm``: the targets model."""
    base = tm.base
    pol = POLICIES[base.policy]
    assert pol.decide_many is not None  # covariance_control is the allocator's
    rng = streams.policy_stream(base.seed, scan) if pol.stochastic else None
    d = pol.decide_many(
        P_pred, J, feas, mc, budget=base.budget, scan=scan, rng=rng, tie_rtol=base.tie_rtol
    )
    a = tuple(int(x) for x in d.assignment)
    T = P_pred.shape[0]
    P = np.array(
        [
            subset_covariance(P_pred[t], J[[j for j in range(len(a)) if a[j] == t], t].sum(axis=0))
            for t in range(T)
        ]
    )
    values = tuple(float(METRICS[metric](P[t], P_d[t])) for t in range(T))
    value = float(sum(wt * v for wt, v in zip(w, values, strict=True)))
    return a, value, values, P, d.n_evaluated
