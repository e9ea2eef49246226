"""The many-target fusion centre over the bus: what the manager (:mod:`manager.covariance`) and
``covnet replay`` (:mod:`covnet.covariance_control.replay`) both step, so that a replay
recomputes exactly what the manager did; and its log.

Per scan ``k`` the centre predicts every target, decides the assignment from the failed set
(:func:`covnet.covariance_control.targets.decide`) and makes the command's fields: the enabled
sensors, each one's target (``targets``: ``{sensor: (target id,)}``) and clutter window
(``windows``: ``{sensor: [centre..., half-width...]}``, for the sensors with clutter).  Each
sensor simulates its own dwell from the world's truth and that window and sends its returns
(``Measurement.z`` ``(m, dim_z)``, unlabeled, ``R`` its noise); the centre gates, associates
and fuses them per target (:func:`covnet.covariance_control.targets.fuse`).  With
``fusion.mode: info`` each sensor sends its own filter's track of the target it dwelt on
instead (:class:`~covnet.wire.messages.LocalTrack` with its ``target_id``), and the centre fuses
the tracks by information-matrix fusion (:func:`covnet.covariance_control.targets.
fuse_tracks`).  The steps are the ones ``covnet run`` calls, so a lockstep network run is
``covnet run`` bit for bit.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from covnet.core.detection import ClutterWindow
from covnet.core.fusion import LocalTrack
from covnet.core.gaussian import Gaussian, is_spd
from covnet.covariance_control import targets
from covnet.covariance_control.runs import TargetRows, TargetsRun
from covnet.covariance_control.targets import Dwell, TargetDecision, TargetsModel

if TYPE_CHECKING:
    from covnet.wire import messages as msg

__all__ = ["ScanPlan", "TargetEpisodeLog", "TargetsCentre"]


@dataclass(frozen=True)
class ScanPlan:
    """Scan ``k``'s decision with what its fusion needs: the predictions, the decision and the
    dwells' clutter windows (sensor index -> window, ``None`` without clutter)."""

    k: int
    preds: list[Gaussian]
    decision: TargetDecision
    windows: dict[int, ClutterWindow | None]
    decision_s: float


class TargetsCentre:
    """One episode of the many-target centre (module docstring)."""

    def __init__(
        self, tm: TargetsModel, history: targets.History | None = None, *, tracks: bool = False
    ) -> None:
        self.tm = tm
        self.tracks = tracks  # the sensors send local tracks (fusion.mode: info), not returns
        self.ids = tm.sensor_ids
        self.est = targets.initial_estimates(tm)
        self.history = history
        self.refiltered: list[str] = []  # "<sensor>:<scan>" since the last Status

    def insert_late(self, m: Any) -> bool:
        """Slow links: a late message (returns, or a local track) of an earlier scan: True
        when it was re-filtered into its scan (:class:`covnet.covariance_control.targets.
        History`)."""
        if self.history is None or m.sensor_id not in self.ids:
            return False
        j = self.ids.index(m.sensor_id)
        if self.tracks:  # a track of the target the sensor dwelt on then
            a = self.history.assignment(m.scan, j)
            if a is None or a < 0 or self.tm.target_ids[a] != m.target_id:
                return False
        done = self.history.insert(m.scan, j, self._payload(m))
        if done:
            self.refiltered.append(f"{m.sensor_id}:{m.scan}")
        return done

    def take_refiltered(self) -> tuple[str, ...] | None:
        if self.history is None:
            return None
        out, self.refiltered = tuple(self.refiltered), []
        return out

    def _payload(self, m: Any) -> Any:
        if self.tracks:
            return LocalTrack(post=Gaussian(m.x, m.P), prior=Gaussian(m.x_prior, m.P_prior))
        return m.z

    def decide(self, k: int, metric: str, unavailable: frozenset[int]) -> ScanPlan:
        preds = targets.predict_all(self.tm, self.est)
        t0 = time.perf_counter()
        dec = targets.decide(self.tm, preds, k, metric, unavailable)
        dt = time.perf_counter() - t0
        windows = {j: targets.window(self.tm, j, preds[dec.assignment[j]]) for j in dec.subset}
        return ScanPlan(k, preds, dec, windows, dt)

    def command_fields(
        self, plan: ScanPlan
    ) -> tuple[tuple[str, ...], dict[str, tuple[str, ...]], dict[str, np.ndarray] | None]:
        """``(enabled, targets, windows)`` of scan ``plan.k``'s :class:`~covnet.wire.messages.
        Command`."""
        ids, tids = self.ids, self.tm.target_ids
        dec = plan.decision
        enabled = tuple(ids[j] for j in dec.subset)
        tasks: dict[str, tuple[str, ...]] = {ids[j]: (tids[dec.assignment[j]],) for j in dec.subset}
        windows: dict[str, np.ndarray] = {}
        for j in dec.subset:
            v = targets.window_vec(plan.windows[j])
            if v is not None:
                windows[ids[j]] = v
        return enabled, tasks, windows or None

    def usable(self, m: msg.Measurement) -> bool:
        """A dwell's returns the centre may use (:func:`covnet.covariance_control.targets.
        usable_returns`), from one of this run's sensors."""
        if m.sensor_id not in self.ids:
            return False
        return targets.usable_returns(self.tm, self.ids.index(m.sensor_id), m.z, m.R)

    def usable_track(self, m: msg.LocalTrack, plan: ScanPlan | None = None) -> bool:
        """``fusion.mode: info``: a local track of a 4-state target with symmetric positive
        definite covariances, of one of the targets, and (given the scan's ``plan``) of the
        target its sensor was to dwell on."""
        if m.sensor_id not in self.ids or m.target_id not in self.tm.target_ids:
            return False
        if not (m.x.shape == (4,) and is_spd(m.P) and is_spd(m.P_prior)):
            return False
        if plan is None or m.scan != plan.k:  # a late one: checked when it is inserted
            return True
        a = plan.decision.assignment[self.ids.index(m.sensor_id)]
        return a >= 0 and self.tm.target_ids[a] == m.target_id

    def fuse(
        self, plan: ScanPlan, got: Mapping[str, Any]
    ) -> tuple[list[Gaussian], list[Gaussian], list[list[Dwell]]]:
        """``(prior, posteriors, dwells)`` of scan ``plan.k`` from what arrived (``sensor id ->
        Measurement``, or under ``info`` ``-> LocalTrack``; a sensor that dwelt and sent nothing
        leaves its target's prediction as it was); on slow links the prior is the re-filtered
        one when late messages came in."""
        payloads = {self.ids.index(sid): self._payload(m) for sid, m in got.items()}
        prior = plan.preds
        h = self.history
        if h is not None:
            if h.changed:
                prior = h.predicted()
            posts, dwells = h.step(plan.k, prior, plan.decision, plan.windows, payloads)
        elif self.tracks:
            posts, dwells = targets.fuse_tracks(self.tm, prior, plan.decision, payloads)
        else:
            posts, dwells = targets.fuse(self.tm, prior, plan.decision, payloads, plan.windows)
        self.est = posts
        return prior, posts, dwells


@dataclass
class TargetEpisodeLog:
    """Rows of one many-target episode, appended per scan; a :class:`~covnet.covariance_control.
    simulate.TargetsRun` at the end (``as_run``).  ``value`` (one per scan) is what the
    shared code counts scans by."""

    metric: str
    truth: np.ndarray  # (T, K, 4)
    rows: TargetRows
    value: list[float] = field(default_factory=list)
    fused_from: list[list[str]] = field(default_factory=list)
    failures: list[dict[str, Any]] = field(default_factory=list)

    @staticmethod
    def start(metric: str, tm: TargetsModel, truth: np.ndarray) -> TargetEpisodeLog:
        return TargetEpisodeLog(
            metric, truth, TargetRows(tm.scans, len(tm.sensors), len(tm.targets))
        )

    def record(
        self,
        plan: ScanPlan,
        prior: list[Gaussian],
        posts: list[Gaussian],
        dwells: list[list[Dwell]],
        fused: list[str],
    ) -> None:
        i = plan.k - 1
        self.rows.put(i, plan.decision, prior, posts, dwells, self.truth[:, i], plan.decision_s)
        self.value.append(float(plan.decision.value))
        self.fused_from.append(fused)

    def as_run(self) -> TargetsRun:
        return self.rows.run(self.metric)
