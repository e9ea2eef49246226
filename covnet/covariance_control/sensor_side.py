"""What a sensor sends for a scan, computed once for every driver of the kind's engine: the
in-process drivers hand it over directly (:mod:`covnet.covariance_control.drive`), the sensor
process (:mod:`sensors.covariance`) and the peer process (:mod:`sensors.peer`) put it on the
wire.  Its own module so that a sensor process loads neither the centre nor the allocator.

``Measured`` and ``Tracked`` are the in-process forms of :class:`covnet.wire.messages.
Measurement` and :class:`~covnet.wire.messages.LocalTrack` (the fields the engine reads), so
``covnet run`` never imports the wire schemas.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from covnet.covariance_control.config import Scenario
from covnet.covariance_control.fusion_rules import rule_for
from covnet.covariance_control.model import measure

__all__ = ["Measured", "SensorContext", "SensorSide", "Tracked"]


@dataclass(frozen=True)
class Measured:
    """A sensor's measurement (returns, with targets) of a scan, in process: the fields of
    :class:`covnet.wire.messages.Measurement` the engine reads."""

    sensor_id: str
    scan: int
    episode: int
    z: np.ndarray  # (m, dim_z)
    R: np.ndarray


@dataclass(frozen=True)
class Tracked:
    """A sensor's local track of a scan, in process: the fields of
    :class:`covnet.wire.messages.LocalTrack` the engine reads."""

    sensor_id: str
    scan: int
    episode: int
    x: np.ndarray
    P: np.ndarray
    x_prior: np.ndarray
    P_prior: np.ndarray
    target_id: str | None = None


class SensorSide:
    """What sensor ``j`` sends for a scan it measures, as the sensor process computes it
    (:mod:`sensors.covariance`): one target, its measurement ``z = H x + v`` from its noise
    stream ``(seed, j, k)``, or under a track rule its own filter's local track (predicted
    lazily up to the scan, updated with its measurement); many targets, its dwell's returns on
    the commanded target in the commanded clutter window, or under ``info`` its own filter's
    track of that target.  A new episode restarts its filters."""

    def __init__(self, engine: Any, j: int, noisy: Any = None) -> None:
        self.engine, self.j = engine, j
        self.sensor_id = engine.ids[j]
        self.episode = -1
        self.local: Any = None
        # z = H x + v for scan k: measure(model, j, k, x), or the same bits from a noise table
        # drawn ahead (the sensor process's sensors.covariance.NoiseTable)
        self.noisy = noisy if noisy is not None else partial(measure, engine.model, j)

    @classmethod
    def of_process(cls, sc: Scenario, model: Any, j: int, noisy: Any = None) -> SensorSide:
        """Sensor ``j`` in its own process (:mod:`sensors.covariance`): no engine, the truth
        from the world's messages (``truth=`` of :meth:`respond` and :meth:`dwell`)."""
        return cls(SensorContext.of(sc, model), j, noisy)

    def _start(self, episode: int) -> None:
        eng = self.engine
        self.episode = episode
        if eng.many:
            # start-up: the many-target steps only for configs with targets
            from covnet.covariance_control import targets

            self.local = targets.LocalTargets(eng.model, self.j) if eng.tracks else None
        elif eng.tracks:
            # start-up: the local filters only under a track rule
            from covnet.covariance_control.decentral import LocalFilter

            self.local = LocalFilter(eng.model, eng.sc.filter.initial_estimate)

    def respond(
        self, episode: int, scan: int, plan: Any, truth: np.ndarray | None = None
    ) -> Measured | Tracked | None:
        """The message of scan ``scan`` (``plan``: that scan's plan, which names the target
        and clutter window with many targets; ``None``: measured on a missed command's
        fallback, one target only); ``None`` when the plan gives it no dwell.  ``truth``: the
        target's true state at the scan as the world process published it (one target; default
        the engine's trajectory, the same numbers)."""
        if episode != self.episode:
            self._start(episode)
        eng, j, sid = self.engine, self.j, self.sensor_id
        if eng.many:
            return self._dwell(episode, scan, plan)
        model = eng.model
        z = self.noisy(scan, eng.truth[scan - 1] if truth is None else truth)
        if not eng.tracks:
            return Measured(sid, scan, episode, z[None, :], model.R[j])
        prior = self.local.predict_to(episode, scan)
        tr = eng.rule.local(model, j, prior, z)
        self.local.set(tr.post)
        return Tracked(sid, scan, episode, tr.post.x, tr.post.P, prior.x, prior.P)

    def _dwell(self, episode: int, scan: int, plan: Any) -> Measured | Tracked | None:
        """Many targets, in process: the plan's target and clutter window for this sensor
        (surveillance: its track or search cell's window, every target's truth)."""
        if plan is None:
            return None
        sp = plan.detail
        if self.engine.surveil:
            win = sp.windows.get(self.j)
            if win is None:  # off
                return None
            return self.survey(episode, scan, win, self.engine.truth[:, scan - 1])
        t = sp.decision.assignment[self.j]
        if t < 0:  # off
            return None
        return self.dwell(episode, scan, t, sp.windows[self.j], self.engine.truth[t, scan - 1])

    def dwell(
        self, episode: int, scan: int, t: int, win: Any, truth: np.ndarray
    ) -> Measured | Tracked:
        """Many targets: its dwell on target ``t`` (index) in clutter window ``win`` at scan
        ``scan``, the target's true state ``truth``: the returns, or under a track rule its own
        filter's track of that target."""
        # start-up: the many-target steps only for configs with targets
        from covnet.covariance_control import targets

        if episode != self.episode:
            self._start(episode)
        eng, j, sid = self.engine, self.j, self.sensor_id
        tm = eng.model
        Z = targets.dwell(tm, j, scan, truth, win)
        if not eng.tracks:
            return Measured(sid, scan, episode, Z, tm.sensors[j].R)
        tr = self.local.track(t, scan, Z, win)[0]
        tid = tm.target_ids[t]
        return Tracked(sid, scan, episode, tr.post.x, tr.post.P, tr.prior.x, tr.prior.P, tid)


    def survey(self, episode: int, scan: int, win: Any, states: np.ndarray) -> Measured:
        """Surveillance: its dwell's returns in window ``win`` at scan ``scan``, every
        target's true state ``states`` ``(n, 4)`` (NaN rows: absent)
        (:func:`covnet.covariance_control.surveillance.dwell`)."""
        # start-up: the surveillance world only for configs with surveillance
        from covnet.covariance_control import surveillance

        if episode != self.episode:
            self.episode = episode
        sm = self.engine.model
        Z = surveillance.dwell(sm, self.j, scan, states, win)
        return Measured(self.sensor_id, scan, episode, Z, sm.tm.sensors[self.j].R)


@dataclass(frozen=True)
class SensorContext:
    """What a sensor's side reads of the engine, for a sensor in its own process (no engine):
    the sensor ids, the model (one target's, or the targets model), the fusion rule and
    whether it fuses local tracks, one target or many.  ``truth`` is None: the world's
    messages give it."""

    sc: Scenario
    model: Any
    ids: tuple[str, ...]
    rule: Any
    tracks: bool
    many: bool
    truth: Any = None
    surveil: bool = False

    @classmethod
    def of(cls, sc: Scenario, model: Any) -> SensorContext:
        rule = rule_for(sc.fusion)
        return cls(
            sc, model, model.sensor_ids, rule, rule.tracks, sc.multitarget,
            surveil=sc.surveillance is not None,
        )
