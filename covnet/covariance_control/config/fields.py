"""The field types the scenario's records share: registry names checked when a config is
validated (so that a metric, search, fusion rule or sensor model a user registers is accepted),
and the small value checks."""

from __future__ import annotations

from typing import Annotated

from covnet.config import Str, in_registry, positive
from covnet.core.metrics import METRICS
from covnet.core.sensor_models import SENSOR_MODELS
from covnet.covariance_control.fusion_rules import FUSION_RULES, fusion_modes, track_rules
from covnet.covariance_control.searches import SEARCHES
from covnet.records import AfterValidator

MetricName = Annotated[Str, in_registry(lambda: sorted(METRICS), "metric")]


def _known_search(value: str) -> str:
    """``allocation.search`` names an entry of :data:`SEARCHES` (looked up when the config is
    validated, so a search a user registers is accepted)."""
    if value not in SEARCHES:
        shown = [repr(k) for k in SEARCHES]
        text = shown[0] if len(shown) == 1 else ", ".join(shown[:-1]) + " or " + shown[-1]
        raise ValueError(f"Input should be {text}")
    return value


SearchName = Annotated[Str, AfterValidator(_known_search)]


def _known_policy(value: str) -> str:
    """``allocation.policy`` names an entry of :data:`covnet.core.allocation.policy_registry.
    POLICIES` (loaded only for a name other than the default)."""
    if value == "covariance_control":
        return value
    # start-up: the baseline policies' registry only for a config that names one
    from covnet.core.allocation.policy_registry import POLICIES

    if value not in POLICIES:
        shown = [repr(k) for k in POLICIES]
        raise ValueError(f"Input should be {', '.join(shown[:-1])} or {shown[-1]}")
    return value


PolicyName = Annotated[Str, AfterValidator(_known_policy)]
FusionMode = Annotated[Str, in_registry(fusion_modes, "fusion mode")]
TrackRule = Annotated[Str, in_registry(track_rules, "rule that fuses local tracks")]
FusionRuleName = Annotated[Str, in_registry(lambda: list(FUSION_RULES), "fusion rule")]
SensorModelName = Annotated[Str, in_registry(lambda: list(SENSOR_MODELS), "sensor model")]


def positive_or_none(v: float | None) -> float | None:
    return None if v is None else positive(v)
