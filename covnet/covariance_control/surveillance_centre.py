"""The surveillance fusion centre (spec ``surveillance.md``): tracks it starts, confirms and
deletes, JPDA over the returns of every dwell, the search cells' undetected mass, and the
allocation over the modes {off, dwell on live track t, search cell c}.  What ``covnet run``
(through the engine's :class:`~covnet.covariance_control.engine.ScanEngine`), the manager over
zenoh and ``covnet replay`` all step.

Per scan ``k``:

``decide``
    every live track predicted (``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``, ``Q`` the filter's white
    acceleration of the first target entry, or of the births); the cells' mass grows by the
    birth intensity (``u_c ← u_c + b_c``, from scan 2 on); then the assignment ``a`` of sensors
    to modes minimising (spec §4, up to the constant ``-λ Σ_c u_c``)::

        F(a) = Σ_t w_t f(P_t(a), P_d,t) + λ Σ_c u_c Π_{j: a_j = c} (1 - pd_j)

    with ``P_d,t``, ``w_t`` by the track's state (``surveillance.desired``), a track feasible
    for the sensors that cover its prediction, a cell for the sensors that can start a track
    and cover its centre.  Each dwell gets its window: ``h(x̂_t⁻) ± n_σ √diag S`` on a track,
    the box of the sensor's measurements over the cell on a search.
``fuse``
    sensor by sensor in ascending index, the returns of its dwell are associated by JPDA with
    the live tracks whose predicted measurement lies in its window (the dwelt track always):
    :func:`covnet.core.surveillance.jpda.jpda_update`; each of those tracks counts a dwell (a
    hit when a return was gated with weight: :func:`~covnet.core.surveillance.tracks.is_hit`),
    which runs the M-of-N confirmation and the deletion after misses
    (:class:`~covnet.core.surveillance.tracks.TrackManager`); a return no live track gates
    starts a tentative track when the sensor's model can start one
    (:data:`~covnet.core.surveillance.tracks.INITIATORS`).  Then the searched cells' mass
    ``u_c ← u_c Π_j (1 - pd_j)`` (:func:`~covnet.core.surveillance.search_cells.after_search`;
    a track started by a dwell that was not a search of its cell also takes its unit out of
    the cell: :func:`~covnet.core.surveillance.search_cells.remove_found`), and the deletion
    of tracks whose position covariance outgrew ``delete_trace_m2`` (tentative ones too: one
    nobody dwells on would otherwise never end), of tracks whose position left the area (the
    truth leaves there too) and of **duplicates**: of two live tracks
    whose positions are inside the χ² gate of their summed position covariance
    (``Δpᵀ (P_a + P_b)⁻¹ Δp <= χ²₂(gate_probability)``) a tentative one goes before a
    confirmed one, then the less certain one (larger position trace; on a tie the younger).
    Without it a track started from clutter beside a target, once JPDA shares the target's
    returns with it, follows that target for ever; with the trace alone, a fresh tentative
    track (its covariance from one return of a fine sensor) replaced the target's confirmed
    track, a track break and a new id for nothing.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from covnet.core.allocation.assignment import MultiConstraints
from covnet.core.association import gate_threshold
from covnet.core.detection import ClutterWindow, clutter_window
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import predict
from covnet.core.metrics import get_metric
from covnet.core.motion import dwna_process_noise
from covnet.core.surveillance.jpda import jpda_update
from covnet.core.surveillance.search_cells import (
    after_search,
    birth_intensity_per_cell,
    coverage_of,
    grow,
    remove_found,
)
from covnet.core.surveillance.tracks import (
    Track,
    TrackManager,
    TrackRules,
    TrackState,
    can_initiate,
    is_hit,
    position_trace,
)
from covnet.covariance_control import targets
from covnet.covariance_control.searches import decide_many
from covnet.covariance_control.surveillance import SurveillanceModel, cell_window

__all__ = ["ScanEvents", "SurveillanceCentre", "SurvPlan"]

OFF = -1
TENTATIVE, CONFIRMED, DELETED = "tentative", "confirmed", "deleted"


@dataclass(frozen=True)
class SurvPlan:
    """Scan ``k``'s decision: the live tracks (columns ``0..T-1``) and their predictions, the
    mode of every sensor (:data:`OFF`, a track column, or ``T + c`` for cell ``c``), each
    dwell's window, the cells' mass when decided, the objective and its parts."""

    k: int
    tracks: tuple[int, ...]  # track ids, one per column
    preds: tuple[Gaussian, ...]
    modes: tuple[int, ...]
    windows: Mapping[int, ClutterWindow]
    u: np.ndarray
    value: float
    track_values: tuple[float, ...]
    search_value: float
    decision_s: float

    @property
    def subset(self) -> tuple[int, ...]:
        return tuple(j for j, a in enumerate(self.modes) if a != OFF)

    def is_search(self, j: int) -> bool:
        return self.modes[j] >= len(self.tracks)


@dataclass
class ScanEvents:
    """What a scan's fusion did: tracks started (with the cell whose search found them, or
    None); after it, the live tracks, those deleted at the scan and the cells' mass."""

    started: list[tuple[int, int | None]] = field(default_factory=list)
    # after the scan (a driver may decide the next scan before it reports this one)
    tracks: tuple[Track, ...] = ()
    deleted: tuple[Track, ...] = ()
    u: np.ndarray = field(default_factory=lambda: np.zeros(0))


class SurveillanceCentre:
    """One episode of the surveillance centre (module docstring)."""

    def __init__(self, sm: SurveillanceModel) -> None:
        self.sm = sm
        self.tm = sm.tm
        self.ids = sm.sensor_ids
        spec = sm.spec
        ts = spec.tracks
        self.manager = TrackManager(
            TrackRules(
                confirm_m=ts.confirm.m,
                confirm_n=ts.confirm.n,
                delete_after_misses=ts.delete_after_misses,
                delete_trace_m2=ts.delete_trace_m2,
                velocity_std=ts.initiation.velocity_std_mps,
            ),
            first_id=1,
        )
        # the cued targets: confirmed tracks from their initial estimates before scan 1
        cues = targets.initial_estimates(self.tm)
        for i, entry in enumerate(sm.cued):
            if entry:
                self.manager.cue(cues[i], 0)
        s = spec.search
        self.grid = sm.grid
        self.u = np.full(sm.n_cells, 0.0 if s is None else s.u0)
        self.grown = 0  # the last scan whose birth intensity is in u
        self.birth = _birth_per_cell(sm)
        self.weight = 0.0 if s is None else s.weight
        d = spec.desired
        self.P_d = {CONFIRMED: _cov(d.confirmed), TENTATIVE: _cov(d.tentative)}
        self.w = {CONFIRMED: d.confirmed.weight, TENTATIVE: d.tentative.weight}
        self.Q = dwna_process_noise(sm.T, _filter_q(sm), 2)
        self.can_start = [can_initiate(s) for s in self.tm.sensors]
        # (N, C): sensor j can search cell c (it can start a track and covers the centre)
        self.cell_ok = np.zeros((len(self.ids), sm.n_cells), dtype=bool)
        if self.grid is not None:
            for j, sen in enumerate(self.tm.sensors):
                if self.can_start[j]:
                    self.cell_ok[j] = coverage_of(self.grid, sen)
        self.pd = np.array([s.pd for s in self.tm.sensors])
        self.cell_miss = np.repeat(1.0 - self.pd[:, None], sm.n_cells, axis=1)  # (N, C) 1 - pd_j
        # two tracks closer than the association gate (summed position covariance) are one
        self.dup_gate = gate_threshold(2, self.tm.gate_probability)

    @property
    def tracks(self) -> tuple[Track, ...]:
        """The live tracks (tentative and confirmed), ids ascending."""
        return self.manager.live()

    # ---------------------------------------------------------------------------- decide

    def decide(self, k: int, metric: str, unavailable: frozenset[int]) -> SurvPlan:
        if k > self.grown and self.grid is not None:  # once per scan, whoever asks again
            if k > 1:
                self.u = grow(self.u, self.birth)
            self.grown = k
        preds = tuple(predict(t.estimate, self.tm.base.F, self.Q) for t in self.tracks)
        t0 = time.perf_counter()
        modes, value, tv, sv = self._assign(k, preds, metric, unavailable)
        dt = time.perf_counter() - t0
        T = len(preds)
        windows: dict[int, ClutterWindow] = {}
        for j, a in enumerate(modes):
            if a == OFF:
                continue
            if a < T:
                S = targets._innovation_cov(self.tm, j, preds[a])
                windows[j] = clutter_window(self.tm.sensors[j], preds[a].x, S, self.tm.window_sigma)
            else:
                windows[j] = cell_window(self.sm, j, a - T)
        ids = tuple(t.id for t in self.tracks)
        return SurvPlan(k, ids, preds, modes, windows, self.u.copy(), value, tv, sv, dt)

    def _assign(
        self, k: int, preds: Sequence[Gaussian], metric: str, unavailable: frozenset[int]
    ) -> tuple[tuple[int, ...], float, tuple[float, ...], float]:
        """The modes of every sensor and ``(F, per-track f, search term)`` (module docstring)."""
        # start-up: the assignment allocator's records
        from covnet.core.allocation.assignment import CellTerms

        N = len(self.ids)
        P_d = np.array([self.P_d[t.state.value] for t in self.tracks]).reshape(-1, 4, 4)
        w = [self.w[t.state.value] for t in self.tracks]
        if preds:
            J, feas = targets.information(self.tm, preds)
        else:  # no track yet: only the cells
            J, feas = np.zeros((N, 0, 4, 4)), np.zeros((N, 0), dtype=bool)
        cell_ok = self.cell_ok.copy()
        if self.weight == 0.0:
            cell_ok[:] = False
        for j in unavailable:
            feas[j] = False
            cell_ok[j] = False
        f = get_metric(metric)
        if not feas.any() and not cell_ok.any():
            tv = tuple(float(f(g.P, P_d[i])) for i, g in enumerate(preds))
            total = 0.0
            for i, v in enumerate(tv):
                total = total + w[i] * v
            sv = float(self.weight * self.u.sum())
            return (OFF,) * N, total + sv, tv, sv
        c = self.tm.base.constraints
        mc = MultiConstraints(
            excluded=frozenset(c.excluded),
            required=frozenset(),
            max_active=c.max_active,
            max_per_target=self.tm.max_per_target,
        )
        cells = CellTerms(self.u.copy(), self.weight, self.cell_miss, cell_ok)
        P_pred = np.array([g.P for g in preds]).reshape(-1, 4, 4)
        if self.tm.base.policy != "covariance_control":
            return self._by_policy(k, P_pred, J, P_d, w, metric, feas, mc, cell_ok)
        # the configured search (exact, bounded, greedy, auto: the SEARCHES registry)
        d = decide_many(
            self.tm.base.search,
            P_pred,
            J,
            P_d,
            metric,
            w,
            feas,
            mc,
            self.tm.base.tie_rtol,
            cells,
        )
        T = len(preds)
        sv = float(d.value - sum(w[i] * d.values[i] for i in range(T)))
        return tuple(d.assignment), float(d.value), tuple(d.values[:T]), sv

    def _by_policy(
        self, k: int, P_pred: np.ndarray, J: np.ndarray, P_d: np.ndarray, w: list[float],
        metric: str, feas: np.ndarray, mc: MultiConstraints, cell_ok: np.ndarray,
    ) -> tuple[tuple[int, ...], float, tuple[float, ...], float]:  # fmt: skip
        """A baseline policy (``allocation.policy``) with search: the policy's many-target form
        assigns sensors to the tracks as it would to known targets
        (:func:`~covnet.covariance_control.policies.decide_many_by_policy`); then every sensor
        it leaves off that can search (ascending index, within ``max_active``) searches the
        cell where it adds the most expected finds, ``u_c pd_j Π_{i already on c}(1 - pd_i)``
        (the lowest cell on a tie; none when nothing is left to find).  The value is the
        covariance-control objective of the result, as for every policy."""
        # start-up: the baseline policies only when one is configured
        from covnet.covariance_control.policies import decide_many_by_policy

        N, T = len(self.ids), P_pred.shape[0]
        a = [OFF] * N
        tv: tuple[float, ...] = ()
        if T and feas.any():
            got, _, tv, _, _ = decide_many_by_policy(
                self.tm, P_pred, J, P_d, w, k, metric, feas, mc
            )
            a = list(got)
        elif T:
            f = get_metric(metric)
            tv = tuple(float(f(P_pred[i], P_d[i])) for i in range(T))
        left = np.ones(self.sm.n_cells)  # Π (1 - pd) of the sensors on each cell so far
        cap = mc.max_active if mc.max_active is not None else N
        on = sum(x != OFF for x in a)
        for j in range(N):
            if on >= cap or a[j] != OFF or j in mc.excluded or not cell_ok[j].any():
                continue
            gain = np.where(cell_ok[j], self.u * left * self.pd[j], -1.0)
            c = int(np.argmax(gain))
            if gain[c] <= 0.0:
                continue
            a[j] = T + c
            left[c] *= 1.0 - self.pd[j]
            on += 1
        sv = float(self.weight * float(np.dot(self.u, left)))
        total = 0.0
        for i, v in enumerate(tv):
            total = total + w[i] * v
        return tuple(a), total + sv, tv, sv

    def command_fields(
        self, plan: SurvPlan
    ) -> tuple[tuple[str, ...], dict[str, tuple[str, ...]], dict[str, np.ndarray]]:
        """``(enabled, targets, windows)`` of the scan's command: a sensor's task is ``K<id>``
        (a track) or ``C<c>`` (a search cell); every dwell has a window."""
        T = len(plan.tracks)
        enabled = tuple(self.ids[j] for j in plan.subset)
        tasks: dict[str, tuple[str, ...]] = {}
        windows: dict[str, np.ndarray] = {}
        for j in plan.subset:
            a = plan.modes[j]
            tasks[self.ids[j]] = (f"K{plan.tracks[a]}",) if a < T else (f"C{a - T}",)
            v = targets.window_vec(plan.windows[j])  # every surveillance dwell has a window
            assert v is not None
            windows[self.ids[j]] = v
        return enabled, tasks, windows

    def usable(self, m: Any) -> bool:
        """A dwell's returns the centre may use: one of this run's sensors, ``(m, dim_z)``
        finite returns and its own noise ``R``; any number of them, clutter or not (a dwell
        returns every target in its window)."""
        if m.sensor_id not in self.ids:
            return False
        j = self.ids.index(m.sensor_id)
        return targets.usable_returns(self.tm, j, m.z, m.R, one_target_per_dwell=False)

    # ---------------------------------------------------------------------------- fuse

    def fuse(self, plan: SurvPlan, got: Mapping[str, Any]) -> ScanEvents:
        """Scan ``plan.k``'s fusion (module docstring); the live tracks afterwards are
        :attr:`tracks`."""
        ev = ScanEvents()
        k, T = plan.k, len(plan.tracks)
        mgr = self.manager
        n_deleted = len(mgr.deleted)
        for tid, pred in zip(plan.tracks, plan.preds, strict=True):
            mgr.set_estimate(tid, pred)
        searched: list[list[float]] = [[] for _ in range(self.sm.n_cells)]
        found: list[int] = []  # the cells of tracks started outside a search of their cell
        for j in plan.subset:
            m = got.get(self.ids[j])
            if m is None:
                continue
            Z = np.asarray(m.z, dtype=np.float64)
            a, win, sen = plan.modes[j], plan.windows[j], self.tm.sensors[j]
            cell = a - T if a >= T else None
            if cell is not None:
                searched[cell].append(float(sen.pd))
            dwelt = plan.tracks[a] if cell is None else None
            live = mgr.live()
            X = np.array([t.estimate.x for t in live]).reshape(-1, 4)
            seen = (sen.in_coverage(X) & win.contains(sen.h(X))).tolist() if live else []
            looked = [t for t, in_win in zip(live, seen, strict=True) if in_win or t.id == dwelt]
            res = jpda_update(
                [t.estimate for t in looked],
                Z,
                sen,
                sen.clutter_rate / win.volume,
                None,
                self.tm.gate_probability,
            )
            for t, up in zip(looked, res.updates, strict=True):
                hit = is_hit(up.beta0, int(up.gated.size))
                mgr.record_dwell(t.id, up.posterior, hit, k)
            if not self.can_start[j]:
                continue
            rows = res.ungated_rows(Z.shape[0])
            room = self.sm.spec.max_tracks - len(mgr.live())
            for t in mgr.initiate(Z, rows[: max(room, 0)], sen, k):
                ev.started.append((t.id, cell))
                if cell is None and self.grid is not None:
                    found.append(int(self.grid.cell_of(t.estimate.x[[0, 2]])))
        if self.grid is not None:
            self.u = after_search(self.u, searched)
            # a target found by a dwell that did not search its cell takes its unit out
            self.u = remove_found(self.u, found)
        self._too_wide(k)
        ev.tracks, ev.u = mgr.live(), self.u.copy()
        ev.deleted = tuple(mgr.deleted[n_deleted:])
        return ev

    def _too_wide(self, k: int) -> None:
        """Delete the live tracks (tentative too) whose position covariance trace exceeds
        ``delete_trace_m2``, those outside the area, then the duplicates (module docstring)."""
        mgr = self.manager
        limit = mgr.rules.delete_trace_m2
        for t in mgr.live():
            if position_trace(t.estimate) > limit:
                mgr.delete(t.id, k, "covariance")
        (x0, y0), (x1, y1) = self.sm.spec.area.min_m, self.sm.spec.area.max_m
        for t in mgr.live():
            px, py = t.estimate.x[0], t.estimate.x[2]
            if not (x0 <= px <= x1 and y0 <= py <= y1):
                mgr.delete(t.id, k, "left the area")
        live = list(mgr.live())
        gone: set[int] = set()
        for i, a in enumerate(live):
            for b in live[i + 1 :]:
                if a.id in gone or b.id in gone:
                    continue
                if _same_target(a.estimate, b.estimate, self.dup_gate):
                    loser = max(a, b, key=_duplicate_rank)
                    mgr.delete(loser.id, k, "duplicate")
                    gone.add(loser.id)


def _duplicate_rank(t: Track) -> tuple[bool, float, int]:
    """Of two duplicates the one with the larger rank is deleted: a tentative one before a
    confirmed one, then the larger position trace, then the younger (the larger id)."""
    return (t.state is not TrackState.CONFIRMED, position_trace(t.estimate), t.id)


def _same_target(a: Gaussian, b: Gaussian, gate: float) -> bool:
    """Two tracks of one target: ``Δpᵀ (P_a + P_b)⁻¹ Δp <= gate`` over their positions."""
    d = a.x[[0, 2]] - b.x[[0, 2]]
    S = a.P[np.ix_([0, 2], [0, 2])] + b.P[np.ix_([0, 2], [0, 2])]
    return float(d @ np.linalg.solve(S, d)) <= gate


def _cov(c: Any) -> np.ndarray:
    if c.diag is not None:
        return np.diag(np.asarray(c.diag, dtype=np.float64))
    return np.asarray(c.matrix, dtype=np.float64)


def _filter_q(sm: SurveillanceModel) -> float:
    """The trackers' white acceleration: the largest of the configured targets' and the
    births' (a tracker does not know which target a track follows)."""
    qs = [float(np.sqrt(t.Q[0, 0] * 4.0 / sm.T**4)) for t in sm.tm.targets]
    if sm.spec.births is not None:
        qs.append(sm.spec.births.accel_noise_std_mps2)
    return max(qs) if qs else 0.5


def _birth_per_cell(sm: SurveillanceModel) -> np.ndarray:
    """``b_c``: ``search.birth_intensity`` in every cell, or the births' rate spread over the
    cells by the share of the regions' area in each
    (:func:`~covnet.core.surveillance.search_cells.birth_intensity_per_cell`)."""
    s, grid = sm.spec.search, sm.grid
    if s is None or grid is None:
        return np.zeros(0)
    if s.birth_intensity is not None:
        return np.full(grid.n_cells, s.birth_intensity)
    b = sm.spec.births
    if b is None or b.rate == 0.0:
        return np.zeros(grid.n_cells)
    regions = [(r.min_m[0], r.max_m[0], r.min_m[1], r.max_m[1]) for r in b.regions]
    return birth_intensity_per_cell(grid, regions, b.rate)
