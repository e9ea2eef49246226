"""The ``allocation:`` table: metrics by registry name, constraints by sensor id, and the
search (:data:`~covnet.covariance_control.searches.SEARCHES`) with its options."""

from __future__ import annotations

from typing import Literal

from covnet.config import Bool, ConfigModel, Float, Int, Str
from covnet.config import positive as _positive
from covnet.covariance_control.config.fields import MetricName, PolicyName, SearchName
from covnet.records import Field, field_validator

# ``allocation.search``: how the subset is found (README, "Allocation search"), an entry of
# :data:`covnet.covariance_control.searches.SEARCHES` (``AUTO_EXACT_MAX``, ``BOUNDED_OPTIONS``
# are there too)
#: ``search: bounded``'s defaults: the relative gap, and (``auto`` beyond ``AUTO_EXACT_MAX``)
#: the node limit, deterministic where a time limit is not
BOUNDED_GAP = 0.01
AUTO_NODE_LIMIT = 200_000


class AllocationSpec(ConfigModel):
    """Covariance-control allocation: metrics by registry name, constraints by sensor id, and
    the search (:data:`SEARCHES`): ``exact`` (the exhaustive search's subset, value and ``P``
    bit for bit: the batched fast path for small networks, branch and bound beyond), ``bounded``
    (branch and bound stopped at the relative ``gap``, ``time_limit_s`` or ``node_limit``; it
    reports a certified lower bound and gap), ``greedy`` (forward/backward greedy and swaps, with
    the root lower bound), ``auto`` (the default: ``exact`` up to ``AUTO_EXACT_MAX`` candidate
    sensors, ``bounded`` beyond).

    Many targets only: ``detection`` (how a dwell's information is scored: ``expected``
    ``pd · HᵀR⁻¹H``, ``ignore`` ``HᵀR⁻¹H``, ``pda`` the PDAF's information-reduction factor
    ``q₂`` instead of ``pd``) and ``max_per_target`` (at most this many sensors on one
    target).

    ``policy`` (an entry of :data:`covnet.core.allocation.policy_registry.POLICIES`):
    ``covariance_control`` (the default: the subset closest to ``P_d`` under the metric), or a
    baseline to compare it with: ``all_on``, ``random``, ``round_robin``,
    ``greedy_information``, ``uncertainty_reward``, ``expected_kl``; ``budget``: their ``K``
    sensors per scan (``random`` and ``round_robin`` need one, here or as ``max_active``; with
    surveillance ``K`` bounds the track dwells, and the sensors left off search).
    ``account_for_loss`` is refused with the baselines that read no sensor information
    (``all_on``, ``random``, ``round_robin``)."""

    metrics: tuple[MetricName, ...] = ("spectral", "abs_trace", "svd")
    required: tuple[Str, ...] = ()
    excluded: tuple[Str, ...] = ()
    max_active: Int | None = Field(default=None, ge=1)
    tie_rtol: Float = Field(default=1e-9, ge=0.0, le=1e-3)
    account_for_loss: Bool = False
    search: SearchName = "auto"
    gap: Float | None = None
    time_limit_s: Float | None = None
    node_limit: Int | None = None
    policy: PolicyName = "covariance_control"
    budget: Int | None = Field(default=None, ge=1)

    @field_validator("metrics", "required", "excluded")
    @classmethod
    def _once_each(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        # a repeated metric ran once while config.json (and its hash) kept both
        dups = sorted({x for x in v if v.count(x) > 1})
        if dups:
            raise ValueError(f"duplicate entries {dups}: name each once")
        return v

    @field_validator("gap")
    @classmethod
    def _gap(cls, v: float | None) -> float | None:
        if v is not None and not 0.0 <= v < 1.0:
            raise ValueError(f"must be in [0, 1) (a relative gap: 0.01 is 1 %), got {v}")
        return v

    @field_validator("time_limit_s")
    @classmethod
    def _time_limit(cls, v: float | None) -> float | None:
        return None if v is None else _positive(v)

    @field_validator("node_limit")
    @classmethod
    def _node_limit(cls, v: int | None) -> int | None:
        if v is not None and v < 1:
            raise ValueError(f"must be >= 1, got {v}")
        return v

    detection: Literal["expected", "ignore", "pda"] = "expected"
    max_per_target: Int | None = Field(default=None, ge=1)


def policy_fields(al: AllocationSpec) -> dict[str, object]:
    """A run summary's ``policy`` (and ``budget``): the allocation policy when it is not the
    default covariance control (a default run's summary is what it always was).  Here, where
    the results of every kind of run read it (one target, many, surveillance)."""
    if al.policy == "covariance_control":
        return {}
    return {"policy": al.policy, "budget": al.budget if al.budget is not None else al.max_active}
