"""The covariance-control manager: the fusion centre's maths in the scan skeleton.

One *episode* per allocation metric (the paper compares three on the same scenario).  What it
plugs into :func:`manager.loop.run_scans`, per scan ``k``::

    decide   x⁻, P⁻ = predict(x, P);  D = argmin over feasible subsets of f(P_i, P_d(t_k)),
             failed sensors infeasible (the fusion rule's P_i: :mod:`covnet.covariance_control.
             decentral`)
    ahead    while the sensors measure: the Kalman gains of every enabled sensor's update and
             the decision of scan k+1 from the covariance those give (P does not depend on the
             measured values); both are used only when what arrives is exactly what they
             assumed, so they change when a result is computed, never what it is
    usable   a position measurement (or, under a track rule, a local track) the filter may take
    fuse     the fusion centre's filter (:class:`~covnet.covariance_control.centre.CentreFilter`:
             sequential updates in ascending sensor index, or the rule's track fusion; late
             messages re-filtered on slow links)
    report   the episode's log row (with NEES against the truth, which only the results use),
             Track(k), Status(k)

The steps are the functions of :mod:`covnet.covariance_control.model`, the same ones
``covnet run`` calls, so a lockstep network run reproduces the in-process run bit for bit.  In
peer mode (``fusion.mode: peer``) there is no fusion centre: this process only routes and
watches (:mod:`manager.peer_monitor`).

Many targets (a config with ``targets:``): :class:`TargetsLogic`, the steps of
:class:`covnet.covariance_control.targets_centre.TargetsCentre`: each command names every
enabled sensor's target and clutter window, each sensor answers with its dwell's returns, the
centre gates, associates and fuses them per target and publishes one Track per target.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from covnet import messages as msg
from covnet.core.allocation import Allocation
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import nees
from covnet.covariance_control.centre import (
    CentreFilter,
    EpisodeLog,
    Gains,
    ManagerResult,
    usable_position,
    usable_track,
)
from covnet.covariance_control.config import Scenario
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import (
    Model,
    build_model,
    decide,
    initial_estimate,
    predict_cov,
    predict_step,
    truth_trajectory,
)
from covnet.covariance_control.results import write_network_run
from manager import loop, peer_monitor
from manager.loop import WORLD_ID, Decision, Loop, ManagerError, ScanReport
from manager.process import main_around

__all__ = ["CovarianceLogic", "main", "run"]


@dataclass(frozen=True)
class _Speculation:
    """The allocation of scan ``k``, decided while scan ``k-1``'s measurements were on their
    way, from the covariance the filter reaches if every enabled sensor's measurement arrives.
    It is used only when the real predicted covariance is bit for bit that one and the failed
    set is unchanged, so it never changes a decision, only when it is made."""

    k: int
    P_pred: np.ndarray
    unavailable: frozenset[int]
    alloc: Allocation
    decision_s: float

    def matches(self, k: int, P_pred: np.ndarray, unavailable: frozenset[int]) -> bool:
        return (
            self.k == k and self.unavailable == unavailable and np.array_equal(self.P_pred, P_pred)
        )


def _speculate(
    model: Model, P_post: np.ndarray, k_next: int, metric: str, unavailable: frozenset[int]
) -> _Speculation | None:
    """Decide scan ``k_next`` from ``P_post``, scan ``k_next - 1``'s posterior covariance if
    every enabled sensor's measurement arrives."""
    if k_next > model.scans:
        return None
    t0 = time.perf_counter()
    P_next = predict_cov(model, P_post)
    alloc = decide(model, P_next, k_next, metric, unavailable)
    return _Speculation(k_next, P_next, unavailable, alloc, time.perf_counter() - t0)


@dataclass(frozen=True)
class _Fused:
    """What :meth:`CovarianceLogic.fuse` leaves for the report of its scan."""

    alloc: Allocation
    decision_s: float
    pred: Gaussian
    est: Gaussian
    got: dict[str, Any]
    refiltered: tuple[str, ...] | None


class CovarianceLogic:
    """The fusion centre's steps (module docstring) for :func:`manager.loop.run_scans`."""

    def __init__(self, sc: Scenario, loop: Loop) -> None:
        if sc.fusion.mode == "peer":
            raise ManagerError("peer mode has no fusion manager: run manager.peer_monitor")
        self.sc, self.model = sc, build_model(sc)
        self.ids = self.model.sensor_ids
        self.episodes = list(sc.allocation.metrics)
        self.scans, self.period_s = self.model.scans, self.model.T
        self.tracks = rule_for(sc.fusion).tracks  # local tracks, not measurements
        self.message_type: type[msg.Measurement] | type[msg.LocalTrack] = (
            msg.LocalTrack if self.tracks else msg.Measurement
        )
        # slow links (network.latency): late messages are re-filtered (or dropped), sensors that
        # measured on their missed-command fallback are fused too (see latency_sim)
        self.slow = not sc.network.latency.is_ideal(self.ids)
        self.accept_unsolicited = self.slow
        self.clock = loop.clock
        self.result = ManagerResult({}, loop.stats)
        self.truth = truth_trajectory(self.model)  # for the results only; never sent
        self._episode_state(0)

    def _episode_state(self, e: int) -> None:
        self.metric = self.episodes[e] if self.episodes else ""
        self.est = initial_estimate(self.model, self.sc.filter.initial_estimate)
        self.centre = CentreFilter(self.sc, self.model)
        self.spec: _Speculation | None = None
        self.gains: Gains | None = None

    # ---- the ScanLogic protocol -------------------------------------------------------------

    def start_episode(self, e: int) -> None:
        self._episode_state(e)
        self.log = self.result.episodes[self.metric] = EpisodeLog(self.metric)

    def membership(self, e: int, k: int, events: list[dict[str, Any]]) -> None:
        self.log.failures.extend(events)

    def decide(self, e: int, k: int, failed: frozenset[str]) -> Decision:
        self.pred = predict_step(self.model, self.est)
        self.unavailable = frozenset(self.ids.index(s) for s in failed if s in self.ids)
        spec = self.spec
        if spec is not None and spec.matches(k, self.pred.P, self.unavailable):
            self.alloc, self.decision_s = spec.alloc, spec.decision_s  # decided ahead, exactly
        else:
            t0 = time.perf_counter()
            self.alloc = self.centre.decide(self.pred.P, k, self.metric, self.unavailable)
            self.decision_s = time.perf_counter() - t0
        return Decision(tuple(self.ids[j] for j in self.alloc.subset))

    def ahead(self, e: int, k: int) -> None:
        self.gains = None
        if not self.tracks and not self.slow:
            self.gains = Gains.of(self.model, self.pred.P, self.alloc.subset)
            self.spec = _speculate(
                self.model, self.gains.P_post, k + 1, self.metric, self.unavailable
            )

    def usable(self, m: Any) -> bool:
        return usable_track(m) if self.tracks else usable_position(m)

    def on_late(self, m: Any) -> bool | None:
        return self.centre.insert_late(m) if self.slow else None

    def fuse(self, e: int, k: int, got: dict[str, Any]) -> _Fused:
        pred = self.centre.prior(self.pred)  # re-filtered late messages change scan k's prior
        self.est = self.centre.fuse(k, pred, got, self.gains)
        late = self.centre.late
        refiltered = late.take_refiltered() if late is not None else None
        return _Fused(self.alloc, self.decision_s, pred, self.est, got, refiltered)

    def report(self, e: int, k: int, fused: _Fused, failed: frozenset[str]) -> ScanReport:
        ids, model, now = self.ids, self.model, self.clock.now_ns
        est, t = fused.est, k * model.T
        track = msg.Track(scan=k, t=t, x=est.x, P=est.P, t_sent_ns=now(), episode=e)
        enabled = tuple(ids[j] for j in fused.alloc.subset)
        status = msg.Status(
            scan=k,
            t=t,
            enabled=enabled,
            trace_P=float(np.trace(est.P)),
            trace_Pd=float(np.trace(model.desired(k))),
            value=float(fused.alloc.value),
            t_sent_ns=now(),
            episode=e,
            fused=tuple(sorted(fused.got, key=ids.index)),
            failed=tuple(sorted(failed - {WORLD_ID})),
            refiltered=fused.refiltered,
        )
        log = self.result.episodes[self.episodes[e]]
        nees_k = nees(est, self.truth[k - 1])
        log.record(len(ids), fused.alloc, fused.pred, est, nees_k, fused.decision_s)
        info = (
            f"scan {k}/{model.scans}  enabled {','.join(enabled) or '-'}  "
            f"tr P {status.trace_P:.1f} / tr Pd {status.trace_Pd:.1f}"
        )
        short = (
            f"{k}/{model.scans} {len(enabled)}/{len(ids)} on  "
            f"trP {status.trace_P:.0f}/{status.trace_Pd:.0f}"
        )
        live: dict[str, Any] = {"trace_P": status.trace_P, "trace_Pd": status.trace_Pd}
        alloc = fused.alloc
        if alloc.lower_bound is not None and alloc.gap is not None:
            # a bounded or greedy search: what it certified for this scan
            lb = alloc.lower_bound if math.isfinite(alloc.lower_bound) else None
            live |= {"value": status.value, "lower_bound": lb, "gap": alloc.gap}
            info += f"  f {status.value:.4g} (gap {100 * alloc.gap:.3g} %)"
            short += f"  gap {100 * alloc.gap:.3g}%"
        return ScanReport([track], status, live | {"info": info, "info_short": short})


class TargetsLogic:
    """The many-target fusion centre's steps for :func:`manager.loop.run_scans` (module
    docstring)."""

    def __init__(self, sc: Scenario, loop: Loop) -> None:
        # start-up: the many-target steps only for configs with targets
        from covnet.covariance_control import targets
        from covnet.covariance_control.targets_centre import TargetEpisodeLog, TargetsCentre

        if sc.fusion.mode not in ("central", "info"):
            raise ManagerError(f"fusion.mode {sc.fusion.mode}: not with many targets")
        self.tracks = sc.fusion.mode == "info"  # local tracks, not returns
        self.message_type: type[msg.Measurement] | type[msg.LocalTrack] = (
            msg.LocalTrack if self.tracks else msg.Measurement
        )
        self.sc, self.tm = sc, targets.build(sc)
        self.ids = self.tm.sensor_ids
        lat = sc.network.latency
        self.slow = not lat.is_ideal(self.ids)  # late messages re-filtered (or dropped)
        self.accept_unsolicited = False
        self._history = (
            (lambda: targets.History(self.tm, lat.oosm_depth, self.tracks))
            if self.slow and lat.late == "oosm"
            else (lambda: None)
        )
        self.episodes = list(sc.allocation.metrics)
        self.scans, self.period_s = self.tm.scans, self.tm.T
        self.clock = loop.clock
        self.result = ManagerResult({}, loop.stats)
        self.truth = targets.truth_trajectories(self.tm)  # for the results only; never sent
        self._centre, self._log = TargetsCentre, TargetEpisodeLog

    def start_episode(self, e: int) -> None:
        self.metric = self.episodes[e]
        self.centre = self._centre(self.tm, self._history())
        self.log = self.result.episodes[self.metric] = self._log.start(
            self.metric, self.tm, self.truth
        )

    def membership(self, e: int, k: int, events: list[dict[str, Any]]) -> None:
        self.log.failures.extend(events)

    def decide(self, e: int, k: int, failed: frozenset[str]) -> Decision:
        unavailable = frozenset(self.ids.index(s) for s in failed if s in self.ids)
        self.plan = self.centre.decide(k, self.metric, unavailable)
        enabled, tasks, windows = self.centre.command_fields(self.plan)
        return Decision(enabled, targets=tasks, windows=windows)

    def ahead(self, e: int, k: int) -> None:
        pass

    def usable(self, m: Any) -> bool:
        if self.tracks:
            return self.centre.usable_track(m, self.plan)
        return self.centre.usable(m)

    def on_late(self, m: Any) -> bool | None:
        return self.centre.insert_late(m) if self.slow else None

    def fuse(self, e: int, k: int, got: dict[str, Any]) -> Any:
        prior, posts, dwells = self.centre.fuse(self.plan, got)
        return self.plan, prior, posts, dwells, got, self.centre.take_refiltered()

    def report(self, e: int, k: int, fused: Any, failed: frozenset[str]) -> ScanReport:
        plan, prior, posts, dwells, got, refiltered = fused
        ids, tm, now = self.ids, self.tm, self.clock.now_ns
        t = k * tm.T
        tracks = [
            msg.Track(scan=k, t=t, x=g.x, P=g.P, t_sent_ns=now(), episode=e, target_id=tid)
            for tid, g in zip(tm.target_ids, posts, strict=True)
        ]
        enabled = tuple(ids[j] for j in plan.decision.subset)
        trace_P = float(sum(np.trace(g.P) for g in posts))
        trace_Pd = float(sum(np.trace(tg.desired(k)) for tg in tm.targets))
        status = msg.Status(
            scan=k,
            t=t,
            enabled=enabled,
            trace_P=trace_P,
            trace_Pd=trace_Pd,
            value=float(plan.decision.value),
            t_sent_ns=now(),
            episode=e,
            fused=tuple(sorted(got, key=ids.index)),
            failed=tuple(sorted(failed - {WORLD_ID})),
            refiltered=refiltered,
        )
        self.result.episodes[self.episodes[e]].record(plan, prior, posts, dwells, sorted(got))
        per = "  ".join(
            f"{tid}:{len(plan.decision.on_target(i))}" for i, tid in enumerate(tm.target_ids)
        )
        info = (
            f"scan {k}/{tm.scans}  on {len(enabled)}/{len(ids)} ({per})  "
            f"tr P {trace_P:.1f} / tr Pd {trace_Pd:.1f}"
        )
        short = f"{k}/{tm.scans} {len(enabled)}/{len(ids)} on  trP {trace_P:.0f}/{trace_Pd:.0f}"
        return ScanReport(
            tracks,
            status,
            {"trace_P": trace_P, "trace_Pd": trace_Pd, "info": info, "info_short": short},
        )


def _logic(sc: Scenario, loop: Loop) -> CovarianceLogic | TargetsLogic:
    """The fusion centre's steps for ``sc``: many targets or the paper's one."""
    return TargetsLogic(sc, loop) if sc.multitarget else CovarianceLogic(sc, loop)


run = partial(loop.run, _logic)
"""``run(sc, bus, run_id, clock, stop, *, realtime, on_ready, on_status, on_progress)``: every
metric's episode (``allocation.metrics``) over the bus (:func:`manager.loop.run`); returns the
:class:`~covnet.covariance_control.centre.ManagerResult`."""


def main(args: Any, sc: Scenario, stop: threading.Event) -> int:
    """``python -m manager --config PAPER.yaml ...``: the process around :func:`run` (or, in
    peer mode, around the observer :func:`manager.peer_monitor.run`)."""
    info = {"episodes": list(sc.allocation.metrics)}
    if sc.fusion.mode == "peer":  # no fusion centre: this process only routes and watches
        if args.realtime:
            raise ValueError("--realtime: peer mode runs in lockstep only")
        return main_around(
            args, sc, stop, peer_monitor.run, peer_monitor.write_peer_run, run_info_extra=info
        )
    return main_around(args, sc, stop, run, write_network_run, run_info_extra=info)
