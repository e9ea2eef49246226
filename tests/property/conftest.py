"""Hypothesis settings for the property layer: profile ``ci`` (derandomised, no deadline),
registered and loaded here so these tests behave the same when run on their own."""

from __future__ import annotations

from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    max_examples=60,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("ci")
