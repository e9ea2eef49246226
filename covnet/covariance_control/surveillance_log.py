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
from covnet.runs.columns import Column

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


_STATES = ("tentative", "confirmed", "deleted")
"""A track row's state, by its code in the rows' column."""
_CODE = {name: i for i, name in enumerate(_STATES)}
_TRACK = np.dtype(
    [("id", np.int64), ("state", np.int8), ("x", np.float64, (4,)), ("P", np.float64, (4, 4))]
)
_POINT = np.dtype([("id", np.intp), ("xy", np.float64, (2,))])


class _Ragged:
    """Rows of one dtype, a varying number a scan: one spilling column of every row and one of
    each scan's count (a long run's rows go off the heap as blocks fill)."""

    def __init__(self, dtype: np.dtype[Any]) -> None:
        self.rows = Column((), dtype)
        self.counts = Column((), np.int64)

    def append(self, rows: Sequence[tuple[Any, ...]]) -> None:
        for r in rows:
            self.rows.append(np.array(r, dtype=self.rows.dtype))
        self.counts.append(len(rows))

    def scans(self) -> list[np.ndarray]:
        """Each scan's rows, in order."""
        rows, counts = self.rows.array(), self.counts.array()
        ends = np.cumsum(counts)
        return [rows[e - n : e] for n, e in zip(counts.tolist(), ends.tolist(), strict=True)]


@dataclass
class SurveillanceLog:
    """Rows of one episode, appended per scan (module docstring); ``value`` (one per scan)
    is what the shared code counts scans by.  Every per-scan row is kept in spilling columns
    (:class:`~covnet.runs.columns.Column`): as Python dicts, lists and frames they grew the
    manager by about 4 kB a scan; :meth:`as_run` reads them back as they were."""

    metric: str
    sm: SurveillanceModel
    value: Column = field(default_factory=lambda: Column((), np.float64))
    failures: list[dict[str, Any]] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._cols = {
            "n_tentative": Column((), np.int64),
            "u": Column((self.sm.n_cells,), np.float64),
            "search": Column((), np.int64),
            "track": Column((), np.int64),
            "decision_s": Column((), np.float64),
            "track_value": Column((), np.float64),
        }
        self._tracks = _Ragged(_TRACK)
        self._truth_points = _Ragged(_POINT)
        self._track_points = _Ragged(_POINT)
        self._started = 0
        self._ever_confirmed: set[int] = set()

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
        frame = ContinuityFrame(
            k,
            present,
            sm.truth[present, k - 1][:, [0, 2]],
            np.array([t.id for t in conf], dtype=np.intp),
            np.array([t.estimate.x[[0, 2]] for t in conf]).reshape(-1, 2),
        )
        self._truth_points.append(list(zip(frame.truth_ids, frame.truth_xy, strict=True)))
        self._track_points.append(list(zip(frame.track_ids, frame.track_xy, strict=True)))
        rows = [(t.id, _CODE[t.state.value], t.estimate.x, t.estimate.P) for t in tracks]
        rows += [(t.id, _CODE["deleted"], t.estimate.x, t.estimate.P) for t in deleted]
        self._tracks.append(rows)
        self._ever_confirmed.update(int(t.id) for t in conf)
        T = len(plan.tracks)
        c = self._cols
        c["n_tentative"].append(len(tracks) - len(conf))
        c["u"].append(u)
        c["search"].append(sum(1 for j in plan.subset if plan.modes[j] >= T))
        c["track"].append(sum(1 for j in plan.subset if plan.modes[j] < T))
        c["decision_s"].append(plan.decision_s)
        c["track_value"].append(float(plan.value - plan.search_value))
        self._started += len(ev.started)
        self.value.append(float(plan.value))

    def _frames(self) -> list[ContinuityFrame]:
        truths, found = self._truth_points.scans(), self._track_points.scans()
        return [
            ContinuityFrame(k, t["id"], t["xy"], f["id"], f["xy"])
            for k, (t, f) in enumerate(zip(truths, found, strict=True), start=1)
        ]

    def _track_rows(self) -> list[list[TrackRow]]:
        return [
            [(int(r["id"]), _STATES[int(r["state"])], r["x"].copy(), r["P"].copy()) for r in rows]
            for rows in self._tracks.scans()
        ]

    def as_run(self) -> SurveillanceRun:
        c = self._cols
        K = len(self.value)
        C = self.sm.n_cells
        rep = evaluate_continuity(self._frames(), self.sm.tm.ospa_c, self.sm.tm.ospa_p)
        S = rep.scans

        def col(key: str, dtype: Any = float) -> np.ndarray:
            return np.asarray(c[key].array(), dtype=dtype)

        def per_scan(key: str, dtype: Any = float) -> np.ndarray:
            return np.array([getattr(x, key) for x in S], dtype=dtype)

        pairs = [list(x.held) for x in S]
        n = len(self.sm.truth_ids)
        ttc = np.full(n, np.nan)
        for tau, v in rep.time_to_confirm.items():
            if v is not None:
                ttc[tau] = v
        held = {tid for ps in pairs for _, tid in ps}
        u = c["u"].array().reshape(K, C)
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
            np.array([float(row.sum()) for row in u]),
            u,
            col("search", int),
            col("track", int),
            self.value.array(),
            col("track_value"),
            col("decision_s"),
            self._track_rows(),
            pairs,
            ttc,
            rep.n_breaks,
            rep.n_switches,
            self._started,
            len(self._ever_confirmed - held),
        )
