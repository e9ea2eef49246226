"""The whole scenario record (:class:`Scenario`) and the grid of ``covnet sweep``
(:class:`SweepSpec`)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from covnet.batches import MAX_SEEDS, point_text
from covnet.config import (
    Bool,
    ConfigModel,
    EvaluationSpec,
    Float,
    Int,
    NetworkSpec,
    Str,
    unique_ids,
)
from covnet.config import positive as _positive
from covnet.covariance_control.config.allocation import AllocationSpec
from covnet.covariance_control.config.fields import FusionRuleName, MetricName
from covnet.covariance_control.config.fusion import FusionSpec
from covnet.covariance_control.config.sensors import SensorSpec
from covnet.covariance_control.config.surveillance import SurveillanceSpec
from covnet.covariance_control.config.targets import (
    AssociationSpec,
    DesiredSpec,
    FilterSpec,
    OspaSpec,
    TargetEntry,
    TargetSpec,
)
from covnet.records import Field, field_validator


class SweepSpec(ConfigModel):
    """The grid of ``covnet sweep`` (README, "Network latency"): every combination of the mean
    one-way delay ``delay_ms`` (both directions; distributed as ``delay_kind``: ``constant``,
    ``exponential`` with that mean, ``uniform`` on ``[0, 2 · mean]``; the same for every
    sensor: ``network.latency.sensors`` is not used), the loss probability
    ``loss`` (both directions), the fusion ``modes``, ``account_for_loss`` and the ``late``
    policy, each run with ``seeds`` seeds from the config's.  ``metric``: the allocation metric
    (default: the config's first).  With ``surveillance:`` the grid is ``search_weight`` (each
    λ >= 0) instead, over every metric."""

    delay_ms: tuple[Float, ...] = (0.0, 100.0, 200.0, 400.0)
    delay_kind: Literal["constant", "exponential", "uniform"] = "exponential"
    loss: tuple[Float, ...] = (0.0, 0.1, 0.2)
    modes: tuple[FusionRuleName, ...] = ("central", "ci")
    account_for_loss: tuple[Bool, ...] = (False, True)
    late: tuple[Literal["oosm", "drop"], ...] = ("oosm",)
    seeds: Int = Field(default=4, ge=1, le=MAX_SEEDS)
    metric: MetricName | None = None
    # surveillance: the grid of the search weight λ (the latency axes are not used)
    search_weight: tuple[Float, ...] | None = None

    @field_validator("delay_ms")
    @classmethod
    def _delays(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v or any(d < 0 for d in v):
            raise ValueError(f"give at least one delay, each >= 0 ms; got {list(v)}")
        return v

    @field_validator("loss")
    @classmethod
    def _losses(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v or any(not 0.0 <= x < 1.0 for x in v):
            raise ValueError(f"give at least one loss probability, each in [0, 1); got {list(v)}")
        return v

    @field_validator("modes", "account_for_loss", "late")
    @classmethod
    def _non_empty(cls, v: tuple[Any, ...]) -> tuple[Any, ...]:
        if not v:
            raise ValueError("give at least one value")
        return v

    @field_validator("delay_ms", "loss", "modes", "account_for_loss", "late", "search_weight")
    @classmethod
    def _distinct(cls, v: tuple[Any, ...] | None) -> tuple[Any, ...] | None:
        """Each value of an axis once, as the trials name it (a repeated or 6-digit-equal
        value was merged into one grid point, silently, and the run count overstated)."""
        seen: dict[str, Any] = {}
        for x in v or ():
            text = point_text(x)
            if text in seen:
                same = "is given twice" if seen[text] == x else f"and {seen[text]!r} are one point"
                raise ValueError(
                    f"{x!r} {same} (a grid point is named by its values to 6 significant "
                    "digits: give each value once)"
                )
            seen[text] = x
        return v


class Scenario(ConfigModel):
    """A whole scenario: the paper's by default values where the source leaves them open."""

    kind: Literal["covariance_control"] = "covariance_control"
    name: Annotated[Str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")]
    seed: Int = Field(ge=0)
    scans: Int = Field(ge=1, le=1_000_000)
    period_s: Float = 1.0
    target: TargetSpec = TargetSpec()
    filter: FilterSpec = FilterSpec()
    sensors: Annotated[tuple[SensorSpec, ...], unique_ids("sensor")] = Field(min_length=1)
    desired: tuple[DesiredSpec, ...] = ()
    allocation: AllocationSpec = AllocationSpec()
    network: NetworkSpec = NetworkSpec()
    fusion: FusionSpec = FusionSpec()
    sweep: SweepSpec | None = None
    evaluation: EvaluationSpec = EvaluationSpec()
    targets: Annotated[tuple[TargetEntry, ...], unique_ids("target")] | None = None
    association: AssociationSpec = AssociationSpec()
    ospa: OspaSpec = OspaSpec()
    surveillance: SurveillanceSpec | None = None

    _period = field_validator("period_s")(_positive)

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return tuple(s.id for s in self.sensors)

    @property
    def multitarget(self) -> bool:
        """The config lists ``targets:`` (the many-target scenario of ``multitarget.md``)."""
        return self.targets is not None

    @property
    def target_ids(self) -> tuple[str, ...]:
        """The targets' ids (``T1`` for the one ``target:`` of a paper config)."""
        return ("T1",) if self.targets is None else tuple(t.id for t in self.targets)
