"""Runs over slow, lossy links in simulated time, as the batch commands and the tests name
them.  The links are :mod:`covnet.covariance_control.links` (the transport, its counts, the
delivery probabilities); the scan is the kind's one engine, stepped by
:mod:`covnet.covariance_control.drive` over that transport, the same steps as the manager's
over zenoh.  With ideal links a run here is the plain one bit for bit, with its counts."""

from __future__ import annotations

from typing import Any

from covnet.covariance_control import drive
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.links import (
    PROBABILITY_DRAWS,
    LatencyCounts,
    delivery_probabilities,
    link_specs,
    loss_aware_model,
)
from covnet.covariance_control.model import Model
from covnet.covariance_control.simulate import MetricRun, TargetsRun

__all__ = [
    "PROBABILITY_DRAWS",
    "LatencyCounts",
    "delivery_probabilities",
    "link_specs",
    "loss_aware_model",
    "run_latency",
    "run_targets_latency",
]


def _counted(
    sc: Scenario, metric: str, model: Any, many: bool | None = None
) -> tuple[Any, LatencyCounts]:
    if not sc.fusion.has_centre:
        raise ValueError("fusion.mode: peer has no fusion centre; latency runs need one")
    out = drive.run(sc, metric, model, links=True, many=many)
    assert out.counts is not None
    return out.run, out.counts


def run_latency(
    sc: Scenario, metric: str, model: Model | None = None
) -> tuple[MetricRun, LatencyCounts]:
    """One target over ``network.latency``'s links (any rule of the registry at a centre):
    the run and what the links did."""
    return _counted(sc, metric, model)


def run_targets_latency(
    sc: Scenario, metric: str, tm: Any = None
) -> tuple[TargetsRun, LatencyCounts]:
    """Many targets over ``network.latency``'s links: the run and what the links did (a
    sensor whose command never came dwells on nothing)."""
    return _counted(sc, metric, tm, many=True)
