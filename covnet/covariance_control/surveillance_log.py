"""A surveillance episode's log and its arrays (spec ``surveillance.md`` §5): per scan the
truth present, the tracks (tentative, confirmed, and those deleted at the scan), the cells'
undetected mass, the dwells on search against track, the objective; at the end GOSPA (``α =
2``) with its localisation / missed / false decomposition and OSPA over the **confirmed**
tracks, the cardinality, the time to confirm, track breaks and id switches
(:func:`covnet.core.surveillance.continuity.evaluate_continuity` over the per-scan frames)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from covnet.core.surveillance.continuity import ContinuityFrame, evaluate_continuity
from covnet.core.surveillance.tracks import Track, TrackState
from covnet.covariance_control.surveillance import SurveillanceModel
from covnet.covariance_control.surveillance_centre import ScanEvents, SurvPlan

__all__ = ["SurveillanceLog", "SurveillanceRun"]

#: a track row: ``(id, state, x (4,), P (4, 4))``
TrackRow = tuple[int, str, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class SurveillanceRun:
    """One metric's surveillance run: per scan (``(K,)`` arrays) ``gospa`` and its parts
    (``gospa_loc``, ``gospa_missed``, ``gospa_false``: the ``p``-th powers, as GOSPA sums
    them), ``ospa``, ``n_truth`` and ``n_confirmed`` / ``n_tentative``, ``u_sum`` (``Σ u_c``
    after the scan), ``search_dwells`` / ``track_dwells``, ``value`` and its tracks' part
    ``track_value`` (``Σ_t w_t f(P_t, P_d,t)``), ``decision_s``; the
    tracks of every scan (``tracks[k-1]``: rows ``(id, state, x, P)`` after the scan's
    fusion, deleted ones included at the scan they were deleted), the cells' mass ``u``
    ``(K, C)``, the GOSPA ``pairs[k-1]`` (truth index, track id), and the continuity summary
    (``time_to_confirm`` per truth, scans, NaN: never confirmed; ``breaks``,
    ``id_switches``)."""

    metric: str
    gospa: np.ndarray
    gospa_loc: np.ndarray
    gospa_missed: np.ndarray
    gospa_false: np.ndarray
    ospa: np.ndarray
    n_truth: np.ndarray
    n_confirmed: np.ndarray
    n_tentative: np.ndarray
    u_sum: np.ndarray
    u: np.ndarray
    search_dwells: np.ndarray
    track_dwells: np.ndarray
    value: np.ndarray
    track_value: np.ndarray
    decision_s: np.ndarray
    tracks: list[list[TrackRow]]
    pairs: list[list[tuple[int, int]]]
    time_to_confirm: np.ndarray
    breaks: int
    id_switches: int
    n_tracks_started: int
    n_false_tracks: int

    @property
    def enabled(self) -> np.ndarray:
        """Dwells per scan over sensors (the share of sensor-scans on): ``(K, 1)``."""
        return (self.search_dwells + self.track_dwells)[:, None]


@dataclass
class SurveillanceLog:
    """Rows of one episode, appended per scan (module docstring); ``value`` (one per scan)
    is what the shared code counts scans by."""

    metric: str
    sm: SurveillanceModel
    value: list[float] = field(default_factory=list)
    rows: list[dict[str, Any]] = field(default_factory=list)
    frames: list[ContinuityFrame] = field(default_factory=list)
    failures: list[dict[str, Any]] = field(default_factory=list)
    fused_from: list[list[str]] = field(default_factory=list)

    def record(
        self,
        plan: SurvPlan,
        tracks: Sequence[Track],
        ev: ScanEvents,
        deleted: Sequence[Track],
        u: np.ndarray,
        fused: list[str],
    ) -> None:
        sm, k = self.sm, plan.k
        present = sm.present(k)
        conf = [t for t in tracks if t.state is TrackState.CONFIRMED]
        self.frames.append(
            ContinuityFrame(
                k,
                present,
                sm.truth[present, k - 1][:, [0, 2]],
                np.array([t.id for t in conf], dtype=np.intp),
                np.array([t.estimate.x[[0, 2]] for t in conf]).reshape(-1, 2),
            )
        )
        rows: list[TrackRow] = [
            (t.id, t.state.value, t.estimate.x.copy(), t.estimate.P.copy()) for t in tracks
        ]
        rows += [(t.id, "deleted", t.estimate.x.copy(), t.estimate.P.copy()) for t in deleted]
        T = len(plan.tracks)
        self.rows.append(
            {
                "n_tentative": len(tracks) - len(conf),
                "u": u.copy(),
                "search": sum(1 for j in plan.subset if plan.modes[j] >= T),
                "track": sum(1 for j in plan.subset if plan.modes[j] < T),
                "tracks": rows,
                "started": list(ev.started),
                "decision_s": plan.decision_s,
                "track_value": float(plan.value - plan.search_value),
            }
        )
        self.value.append(float(plan.value))
        self.fused_from.append(fused)

    def as_run(self) -> SurveillanceRun:
        R = self.rows
        K = len(R)
        C = self.sm.n_cells
        rep = evaluate_continuity(self.frames, self.sm.tm.ospa_c, self.sm.tm.ospa_p)
        S = rep.scans

        def col(key: str, dtype: Any = float) -> np.ndarray:
            return np.array([r[key] for r in R], dtype=dtype)

        def per_scan(key: str, dtype: Any = float) -> np.ndarray:
            return np.array([getattr(x, key) for x in S], dtype=dtype)

        pairs = [list(x.held) for x in S]
        n = len(self.sm.truth_ids)
        ttc = np.full(n, np.nan)
        for tau, v in rep.time_to_confirm.items():
            if v is not None:
                ttc[tau] = v
        held = {tid for ps in pairs for _, tid in ps}
        ever_confirmed = {tid for r in R for (tid, st, _, _) in r["tracks"] if st == "confirmed"}
        return SurveillanceRun(
            self.metric,
            per_scan("gospa"),
            per_scan("localisation"),
            per_scan("missed"),
            per_scan("false"),
            per_scan("ospa"),
            per_scan("n_true", int),
            per_scan("n_confirmed", int),
            col("n_tentative", int),
            np.array([float(r["u"].sum()) for r in R]),
            np.array([r["u"] for r in R]).reshape(K, C),
            col("search", int),
            col("track", int),
            np.asarray(self.value, dtype=float),
            col("track_value"),
            col("decision_s"),
            [r["tracks"] for r in R],
            pairs,
            ttc,
            rep.n_breaks,
            rep.n_switches,
            sum(len(r["started"]) for r in R),
            len(ever_confirmed - held),
        )
