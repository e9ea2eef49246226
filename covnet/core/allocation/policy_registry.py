"""The allocation policies' registry (issue 27): one :class:`Policy` record per entry, carrying
what the rest of the system may ask of it (budget, metric, randomness, many-target form).

The one-target forms and the rewards are :mod:`covnet.core.allocation.policies`', the
many-target forms :mod:`covnet.core.allocation.policies_many`'.  ``covariance_control`` is the
paper's allocator itself (:mod:`covnet.covariance_control.searches`): its record only says so.
To add a policy: its decide function (and many-target form) beside the others, and one record
here; the config, ``covnet compare --policies`` and the engine read the record.
"""

from __future__ import annotations

from dataclasses import dataclass

from covnet.core import registries
from covnet.core.allocation.policies import (
    DecideFn,
    RewardFn,
    _decide_all_on,
    _decide_greedy_information,
    _decide_kl,
    _decide_random,
    _decide_round_robin,
    _decide_uncertainty,
    expected_kl,
    information_gain,
    uncertainty_reward,
)
from covnet.core.allocation.policies_many import DECIDE_MANY, DecideManyFn

__all__ = ["POLICIES", "Policy"]


@dataclass(frozen=True, slots=True)
class Policy:
    """One allocation policy, and what the rest of the system may ask of it:

    - ``summary``: what it does, in one line (help texts and refusals quote it);
    - ``needs_budget``: it takes a budget ``K`` (see the module docstring for which need one);
    - ``uses_metric``: it scores by the covariance-control metric (``covariance_control`` only);
    - ``stochastic``: it draws from the ``rng`` passed in (the caller derives it from seed,
      episode and scan, so every process draws the same);
    - ``many_targets``: it has a many-target form, ``decide_many``;
    - ``delegates_to_search``: the decision is the covariance-control search's
      (:mod:`covnet.covariance_control.searches`); ``decide`` and ``decide_many`` are ``None``;
    - ``reward``: the one-target reward the policy maximises, if any."""

    name: str
    summary: str
    needs_budget: bool
    uses_metric: bool
    stochastic: bool
    many_targets: bool
    decide: DecideFn | None
    decide_many: DecideManyFn | None = None
    delegates_to_search: bool = False
    reward: RewardFn | None = None


# --------------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------------


POLICIES: dict[str, Policy] = {
    p.name: p
    for p in (
        Policy(
            "covariance_control",
            "the subset whose covariance is closest to the desired one under the metric (the "
            "allocator's search)",
            needs_budget=False,
            uses_metric=True,
            stochastic=False,
            many_targets=True,
            decide=None,
            delegates_to_search=True,
        ),
        Policy(
            "all_on",
            "every available sensor, every scan",
            needs_budget=False,
            uses_metric=False,
            stochastic=False,
            many_targets=True,
            decide=_decide_all_on,
            decide_many=DECIDE_MANY["all_on"],
        ),
        Policy(
            "random",
            "K sensors drawn uniformly (required ones first) from the seeded generator",
            needs_budget=True,
            uses_metric=False,
            stochastic=True,
            many_targets=True,
            decide=_decide_random,
            decide_many=DECIDE_MANY["random"],
        ),
        Policy(
            "round_robin",
            "K sensors in a cyclic order fixed by the scan number",
            needs_budget=True,
            uses_metric=False,
            stochastic=False,
            many_targets=True,
            decide=_decide_round_robin,
            decide_many=DECIDE_MANY["round_robin"],
        ),
        Policy(
            "greedy_information",
            "adds the sensor with the largest log-det information gain until K or no gain",
            needs_budget=True,
            uses_metric=False,
            stochastic=False,
            many_targets=True,
            decide=_decide_greedy_information,
            decide_many=DECIDE_MANY["greedy_information"],
            reward=information_gain,
        ),
        Policy(
            "uncertainty_reward",
            "at most K sensors maximising Stone Soup's uncertainty reward "
            "(reduction of the covariance's Frobenius norm)",
            needs_budget=True,
            uses_metric=False,
            stochastic=False,
            many_targets=True,
            decide=_decide_uncertainty,
            decide_many=DECIDE_MANY["uncertainty_reward"],
            reward=uncertainty_reward,
        ),
        Policy(
            "expected_kl",
            "at most K sensors maximising Stone Soup's expected KL divergence from prediction "
            "to update",
            needs_budget=True,
            uses_metric=False,
            stochastic=False,
            many_targets=True,
            decide=_decide_kl,
            decide_many=DECIDE_MANY["expected_kl"],
            reward=expected_kl,
        ),
    )
}
registries.ship("covnet.core.allocation.policy_registry.POLICIES", POLICIES)
