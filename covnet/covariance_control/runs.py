"""What an in-process or network run of the covariance-control kind holds, per scan: the
arrays of one metric's run (:class:`MetricRun`; many targets :class:`TargetsRun`), the rows
they are filled from, and what every metric's run shares (:class:`Trajectory`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from covnet.core.gaussian import Gaussian
from covnet.core.kalman import nees
from covnet.covariance_control.model import Model, truth_trajectory


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


@dataclass(frozen=True)
class TargetsRun:
    """Per-scan arrays of one many-target run (column ``k-1`` is scan ``k``; ``T`` targets,
    ``N`` sensors, ``K`` scans): ``assignment`` ``(K, N)`` (target index, ``-1`` off),
    ``value`` ``(K,)`` ``Σ_t w_t f_t``, ``values`` ``(T, K)`` ``f(P_t(a), P_d,t)``, the
    estimates ``x_est`` ``(T, K, 4)``, ``P_post``, ``P_pred`` ``(T, K, 4, 4)``, ``nees``
    ``(T, K)``; per target and scan the NIS of its dwells summed (``nis_sum``), their
    degrees of freedom (``nis_dof``) and count (``nis_n``); ``returns`` ``(K, N)`` returns per
    dwell (``-1``: off, or nothing arrived), ``used`` ``(K, N)`` a return moved the estimate;
    decision times and exact evaluations per scan."""

    metric: str
    assignment: np.ndarray
    value: np.ndarray
    values: np.ndarray
    x_est: np.ndarray
    P_post: np.ndarray
    P_pred: np.ndarray
    nees: np.ndarray
    nis_sum: np.ndarray
    nis_dof: np.ndarray
    nis_n: np.ndarray
    returns: np.ndarray
    used: np.ndarray
    decision_s: np.ndarray
    n_evaluated: np.ndarray
    #: a bounded or greedy search's certificate per scan (NaN: not reported); ``None``: exact
    lower_bound: np.ndarray | None = None
    gap: np.ndarray | None = None

    @property
    def enabled(self) -> np.ndarray:
        """``(K, N)``: the sensors on (dwelling on some target)."""
        return np.asarray(self.assignment >= 0)


class TargetRows:
    """Per-scan rows of a many-target run, filled by scan (the in-process runner, the
    manager's log and the replay all fill one)."""

    def __init__(self, K: int, N: int, T: int) -> None:
        self.assignment = np.full((K, N), -1, dtype=np.int64)
        self.value = np.empty(K)
        self.values = np.empty((T, K))
        self.x_est = np.empty((T, K, 4))
        self.P_post = np.empty((T, K, 4, 4))
        self.P_pred = np.empty((T, K, 4, 4))
        self.nees = np.empty((T, K))
        self.nis_sum = np.zeros((T, K))
        self.nis_dof = np.zeros((T, K), dtype=np.int64)
        self.nis_n = np.zeros((T, K), dtype=np.int64)
        self.returns = np.full((K, N), -1, dtype=np.int64)
        self.used = np.zeros((K, N), dtype=bool)
        self.decision_s = np.empty(K)
        self.n_eval = np.empty(K, dtype=np.int64)
        self.lower_bound = np.full(K, np.nan)
        self.gap = np.full(K, np.nan)
        self.bounded = False
        self.done = 0

    def put(
        self,
        i: int,
        decision: Any,
        preds: list[Gaussian],
        posts: list[Gaussian],
        dwells: list[list[Any]],
        truth: np.ndarray,
        dt: float,
    ) -> None:
        """Row ``i``: the decision, predictions, posteriors and dwell records of the scan,
        NEES against ``truth`` ``(T, 4)``."""
        self.assignment[i] = decision.assignment
        self.value[i] = decision.value
        self.values[:, i] = decision.values
        for t, (pred, est) in enumerate(zip(preds, posts, strict=True)):
            self.x_est[t, i], self.P_post[t, i], self.P_pred[t, i] = est.x, est.P, pred.P
            self.nees[t, i] = nees(est, truth[t])
            for d in dwells[t]:
                self.returns[i, d.sensor] = d.returns
                self.used[i, d.sensor] = d.used
                if d.nis is not None:
                    self.nis_sum[t, i] += d.nis
                    self.nis_dof[t, i] += d.dof
                    self.nis_n[t, i] += 1
        self.decision_s[i] = dt
        self.n_eval[i] = decision.n_evaluated
        lb, gap = getattr(decision, "lower_bound", None), getattr(decision, "gap", None)
        if lb is not None and gap is not None:
            self.lower_bound[i], self.gap[i], self.bounded = lb, gap, True
        self.done = max(self.done, i + 1)

    def run(self, metric: str) -> TargetsRun:
        n = self.done
        return TargetsRun(
            metric,
            self.assignment[:n],
            self.value[:n],
            self.values[:, :n],
            self.x_est[:, :n],
            self.P_post[:, :n],
            self.P_pred[:, :n],
            self.nees[:, :n],
            self.nis_sum[:, :n],
            self.nis_dof[:, :n],
            self.nis_n[:, :n],
            self.returns[:n],
            self.used[:n],
            self.decision_s[:n],
            self.n_eval[:n],
            self.lower_bound[:n] if self.bounded else None,
            self.gap[:n] if self.bounded else None,
        )
