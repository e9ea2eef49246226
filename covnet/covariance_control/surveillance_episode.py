"""The engine's surveillance episode (:class:`~covnet.covariance_control.engine.ScanEngine`
with a config's ``surveillance:``): the steps of one metric's episode over the
:class:`~covnet.covariance_control.surveillance_centre.SurveillanceCentre`, so that ``covnet
run``, the manager and ``covnet replay`` step the same logic."""

from __future__ import annotations

from typing import Any

import numpy as np

from covnet.covariance_control.scan_records import Outcome, Plan
from covnet.covariance_control.surveillance import SurveillanceModel
from covnet.covariance_control.surveillance_centre import SurveillanceCentre
from covnet.covariance_control.surveillance_log import SurveillanceLog

__all__ = ["SurveillanceEpisode"]


class SurveillanceEpisode:
    """One episode (the engine's episode protocol: decide, ahead, verdict, insert_late, fuse,
    record, outcome)."""

    def __init__(self, sm: SurveillanceModel, metric: str) -> None:
        self.sm, self.metric = sm, metric
        self.ids = sm.sensor_ids
        self.centre = SurveillanceCentre(sm)
        self.log = SurveillanceLog(metric, sm)

    def decide(self, k: int, unavailable: frozenset[int]) -> Any:
        sp = self.centre.decide(k, self.metric, unavailable)
        enabled, tasks, windows = self.centre.command_fields(sp)
        return Plan(k, sp.subset, enabled, sp.value, sp.decision_s, sp, tasks, windows)

    def ahead(self, plan: Any) -> None:
        pass

    def verdict(self, m: Any, plan: Any) -> str | None:
        """None when ``m``'s returns may be used; else ``bad_measurement``."""
        return None if self.centre.usable(m) else "bad_measurement"

    def insert_late(self, m: Any) -> bool:
        return False  # surveillance runs on ideal links (the config refuses others)

    def fuse(self, plan: Any, got: dict[str, Any]) -> Any:
        ev = self.centre.fuse(plan.detail, got)
        return ev, list(ev.deleted)

    def record(self, plan: Any, fused: Any, got: dict[str, Any]) -> None:
        ev, deleted = fused
        self.log.record(plan.detail, ev.tracks, ev, deleted, ev.u, sorted(got))

    def outcome(self, plan: Any, fused: Any, got: dict[str, Any]) -> Any:
        """The scan's outcome: the live tracks, then those deleted at this scan (their last
        estimate), each with its state; the cells' ``u_c`` after the scan."""
        sp = plan.detail
        ev, deleted = fused
        live = ev.tracks
        shown = [*live, *deleted]
        k = plan.k
        P_d = self.centre.P_d
        return Outcome(
            k,
            tuple((f"K{t.id}", t.estimate) for t in shown),
            plan.enabled,
            float(sp.value),
            float(sum(np.trace(t.estimate.P) for t in live)),
            float(sum(np.trace(P_d[t.state.value]) for t in live)),
            tuple(sorted(got, key=self.ids.index)),
            None,
            per_target=(
                ("search", sum(1 for j in sp.subset if sp.is_search(j))),
                ("track", sum(1 for j in sp.subset if not sp.is_search(j))),
            ),
            track_states=tuple(t.state.value for t in shown),
            cells=ev.u.copy() if ev.u.size else None,
        )
