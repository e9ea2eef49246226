"""The in-process simulator: the whole scan loop of one scenario and one metric, no bus.

Per scan ``k = 1..N`` (time ``t_k = k T``)::

    predict  x⁻, P⁻                       (from scan k-1, or from the initial estimate)
    allocate D_opt = argmin_i f(P_i, P_d(t_k)) over the feasible subsets
    measure  z_j(k) for j in D_opt          (sensor j's own noise stream (j, k))
    fuse     sequential Joseph updates, ascending sensor index

Truth, initial estimate and every measurement come from counter-based streams of the seed
(:mod:`covnet.core.streams`), so runs with different metrics share their random numbers and a
multi-process run draws the very same ones.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from covnet.core.gaussian import Gaussian
from covnet.core.kalman import nees
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.model import (
    Model,
    build_model,
    decide,
    fuse,
    initial_estimate,
    measure,
    predict_step,
    truth_trajectory,
)


@dataclass(frozen=True)
class MetricRun:
    """Per-scan arrays of one run (row ``k-1`` is scan ``k``)."""

    metric: str
    enabled: np.ndarray  # (N, Ns) bool
    value: np.ndarray  # (N,) f(P_i, P_d) of the chosen subset
    x_est: np.ndarray  # (N, 4) posterior mean
    P_post: np.ndarray  # (N, 4, 4)
    P_pred: np.ndarray  # (N, 4, 4)
    nees: np.ndarray  # (N,)
    decision_s: np.ndarray  # (N,) wall time of each allocation decision
    n_evaluated: np.ndarray  # (N,) subsets evaluated exactly by the allocator
    # (N,) what a bounded or greedy search certifies (NaN: not reported); None: an exact search
    lower_bound: np.ndarray | None = None
    gap: np.ndarray | None = None


@dataclass(frozen=True)
class Trajectory:
    """What every metric's run shares: truth, times and the desired covariances."""

    t: np.ndarray  # (N,)
    truth: np.ndarray  # (N, 4)
    P_d: np.ndarray  # (N, 4, 4)


def shared_trajectory(model: Model) -> Trajectory:
    scans = np.arange(1, model.scans + 1)
    return Trajectory(
        t=scans * model.T,
        truth=truth_trajectory(model),
        P_d=np.stack([model.desired(int(k)) for k in scans]),
    )


class RunRows:
    """Per-scan rows of one estimate stream (a centre, or one peer node)."""

    def __init__(self, N: int, Ns: int) -> None:
        self.enabled = np.zeros((N, Ns), dtype=bool)
        self.value = np.empty(N)
        self.x_est = np.empty((N, 4))
        self.P_post = np.empty((N, 4, 4))
        self.P_pred = np.empty((N, 4, 4))
        self.nees = np.empty(N)
        self.decision_s = np.empty(N)
        self.n_eval = np.empty(N, dtype=np.int64)
        self.lower_bound = np.full(N, np.nan)
        self.gap = np.full(N, np.nan)
        self.bounded = False  # some scan reported a lower bound

    def put(
        self,
        i: int,
        subset: tuple[int, ...],
        value: float,
        pred: Gaussian,
        est: Gaussian,
        truth: np.ndarray,
        dt: float,
        n_eval: int,
        *,
        lower_bound: float | None = None,
        gap: float | None = None,
    ) -> None:
        """Row ``i``; ``lower_bound`` / ``gap``: what the search certified, if it did."""
        if lower_bound is not None and gap is not None:
            self.lower_bound[i], self.gap[i], self.bounded = lower_bound, gap, True
        self.enabled[i, list(subset)] = True
        self.value[i] = value
        self.x_est[i], self.P_post[i], self.P_pred[i] = est.x, est.P, pred.P
        self.nees[i] = nees(est, truth)
        self.decision_s[i] = dt
        self.n_eval[i] = n_eval

    def run(self, metric: str) -> MetricRun:
        return MetricRun(
            metric,
            self.enabled,
            self.value,
            self.x_est,
            self.P_post,
            self.P_pred,
            self.nees,
            self.decision_s,
            self.n_eval,
            self.lower_bound if self.bounded else None,
            self.gap if self.bounded else None,
        )


def run_metric(sc: Scenario, metric: str, model: Model | None = None) -> MetricRun:
    """Run the scan loop of ``sc`` with allocation metric ``metric``."""
    model = model or build_model(sc)
    truth = truth_trajectory(model)
    N, Ns = model.scans, len(model.sensor_ids)
    rows = RunRows(N, Ns)
    est = initial_estimate(model, sc.filter.initial_estimate)
    for i in range(N):
        k = i + 1
        pred = predict_step(model, est)
        t0 = time.perf_counter()
        alloc = decide(model, pred.P, k, metric)
        dt = time.perf_counter() - t0
        meas = [(j, measure(model, j, k, truth[i]), model.R[j]) for j in alloc.subset]
        est = fuse(model, pred, meas)
        rows.put(
            i,
            alloc.subset,
            alloc.value,
            pred,
            est,
            truth[i],
            dt,
            alloc.n_evaluated,
            lower_bound=alloc.lower_bound,
            gap=alloc.gap,
        )
    return rows.run(metric)
