"""``covnet run``'s runs of the covariance-control kind, as the tests and the API name them.

The scan loop is the kind's one engine (:class:`covnet.covariance_control.engine.ScanEngine`),
stepped in this process by :mod:`covnet.covariance_control.drive`; the manager process and the
replay step the same engine.  :func:`run_metric` and :func:`run_targets` are that driver's run
of a config (any fusion rule at a centre, ideal or slow links); what they return is in
:mod:`covnet.covariance_control.runs`.

Truth, initial estimate and every measurement come from counter-based streams of the seed
(:mod:`covnet.core.streams`), so runs with different metrics share their random numbers and a
multi-process run draws the very same ones.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from covnet.covariance_control import drive
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.model import Model
from covnet.covariance_control.runs import (
    MetricRun,
    RunRows,
    TargetRows,
    TargetsRun,
    Trajectory,
    shared_trajectory,
)

if TYPE_CHECKING:
    from covnet.covariance_control.targets import TargetsModel

__all__ = [
    "MetricRun",
    "RunRows",
    "TargetRows",
    "TargetsRun",
    "Trajectory",
    "run_metric",
    "run_targets",
    "shared_trajectory",
]


def run_metric(sc: Scenario, metric: str, model: Model | None = None) -> MetricRun:
    """``sc`` (one target) with allocation metric ``metric``: the in-process run
    (:func:`covnet.covariance_control.drive.run`)."""
    run: MetricRun = drive.run(sc, metric, model).run
    return run


def run_targets(sc: Scenario, metric: str, tm: TargetsModel | None = None) -> TargetsRun:
    """``sc``'s targets with allocation metric ``metric``: the in-process run
    (:func:`covnet.covariance_control.drive.run`)."""
    run: TargetsRun = drive.run(sc, metric, tm, many=True).run
    return run
