"""The surveillance world of a covariance-control config with ``surveillance:`` (spec
``surveillance.md`` §1, §3): targets that appear and leave, births, the search cells, and a
dwell that returns every existing target inside its window.

**Truth.**  A configured target with ``appears_at_scan = a`` starts from its
``initial_position_m`` / ``initial_velocity_mps`` at time ``(a - 1) T`` and moves as a
many-target truth does (its TRUTH stream, its manoeuvres); it exists at scans ``a ..
leaves_at_scan - 1`` (to the end without ``leaves_at_scan``), and only while it is inside the
area: outside it is no part of the surveillance problem, as a born target, which leaves there,
and a track, which is deleted there (a configured target that flew out was scored as missed,
and its deleted track as a break, every scan to the end).  With ``a = 1`` its trajectory is
today's bit for bit.  Births (``surveillance.births``): the birth process of
:mod:`covnet.core.surveillance.births` from the stream ``(seed, BIRTHS)``, each born target
leaving at the first scan it is outside the area.  ``truth`` is ``(n, scans, 4)`` with NaN
where a target does not exist; ``exists`` the mask.  Everything is a function of the config
and its seed, so every process (the world, each sensor, the manager, a replay) builds the same
world.

**A dwell** of sensor ``j`` at scan ``k`` in window ``w`` (a box in its measurement space:
around a track's predicted measurement, or the box of its measurements over a search cell)
returns, from the stream ``(seed, SENSOR, j, k)``: for every existing target in ascending index
whose noise-free measurement is inside ``w`` and which the sensor covers, one noisy measurement
detected with ``pd``; ``Poisson(clutter_rate)`` false returns uniform in ``w``; shuffled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from covnet.core import streams
from covnet.core.detection import ClutterWindow
from covnet.core.gaussian import Mat, Vec
from covnet.core.manoeuvre import manoeuvring_trajectory
from covnet.core.sensor_models import wrap_angle
from covnet.core.surveillance.births import BirthProcess, BirthRegion, simulate_truth
from covnet.core.surveillance.search_cells import SearchGrid
from covnet.covariance_control import targets
from covnet.covariance_control.config import Scenario, segments
from covnet.covariance_control.config.surveillance import SurveillanceSpec
from covnet.covariance_control.targets import TargetsModel

__all__ = ["SurveillanceModel", "build", "cell_window", "dwell", "is_task"]

#: the stream domain of the birth process: key ``(BIRTHS,)``
BIRTHS = 30


@dataclass(frozen=True)
class SurveillanceModel:
    """A surveillance scenario: the sensors' :class:`~covnet.covariance_control.targets.
    TargetsModel` (its targets are not the manager's: it knows none), the block's settings,
    the truth of every target that ever exists (configured first, then births in order of
    birth) and the search ``grid`` (None without ``search``; its ``boxes()`` ``(C, 4)``
    ``[x0, x1, y0, y1]``)."""

    tm: TargetsModel
    spec: SurveillanceSpec
    truth_ids: tuple[str, ...]
    truth: Mat  # (n, scans, 4), NaN where absent
    exists: np.ndarray  # (n, scans) bool
    grid: SearchGrid | None
    cued: tuple[bool, ...] = ()  # per configured target: known before scan 1

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return self.tm.sensor_ids

    @property
    def scans(self) -> int:
        return self.tm.scans

    @property
    def T(self) -> float:
        return self.tm.T

    @property
    def n_cells(self) -> int:
        return 0 if self.grid is None else self.grid.n_cells

    @property
    def cells(self) -> Mat:
        """The cells' boxes ``(C, 4)``: ``[x0, x1, y0, y1]``."""
        return np.zeros((0, 4)) if self.grid is None else self.grid.boxes()

    def present(self, scan: int) -> np.ndarray:
        """The indices of the targets that exist at ``scan``."""
        return np.flatnonzero(self.exists[:, scan - 1])


def _segments(sc: Scenario, i: int, shift: int) -> list[Any]:
    """Target ``i``'s manoeuvres (:func:`~covnet.covariance_control.config.targets.segments`)
    on its own clock: scans counted from its appearance (``shift = appears_at_scan - 1``)."""
    assert sc.targets is not None
    return [replace(g, k0=g.k0 - shift, k1=g.k1 - shift) for g in segments(sc.targets[i])]


def _first_stay(ex: np.ndarray) -> np.ndarray:
    """The first run of ``True`` in ``ex`` only: a target that flies out of the area has left,
    even where its path comes back in (a born target too; its track was deleted there, and a
    return would score that deletion as a break)."""
    inside = np.flatnonzero(ex)
    if inside.size == 0:
        return ex
    out = ex.copy()
    gaps = np.flatnonzero(~ex[inside[0] :])
    if gaps.size:
        out[inside[0] + gaps[0] :] = False
    return out


def _configured(sc: Scenario, tm: TargetsModel) -> tuple[list[str], list[Mat], list[Vec]]:
    """The configured targets' truth rows and existence (module docstring)."""
    assert sc.targets is not None and sc.surveillance is not None
    (x0, y0), (x1, y1) = sc.surveillance.area.min_m, sc.surveillance.area.max_m
    ids, rows, alive = [], [], []
    K = tm.scans
    for t, (entry, tg) in enumerate(zip(sc.targets, tm.targets, strict=True)):
        a = entry.appears_at_scan
        rng = streams.stream(tm.base.seed, *targets._key(streams.TRUTH, t))  # the many-target key
        n = K - a + 1
        traj = manoeuvring_trajectory(
            tg.x0,
            tm.T,
            tg.sigma_a,
            n,
            rng,
            _segments(sc, t, a - 1),
        )
        row = np.full((K, 4), np.nan)
        row[a - 1 :] = traj
        end = K if entry.leaves_at_scan is None else entry.leaves_at_scan - 1
        ex = np.zeros(K, dtype=bool)
        ex[a - 1 : end] = True
        with np.errstate(invalid="ignore"):  # NaN before it appears: outside
            ex &= (row[:, 0] >= x0) & (row[:, 0] <= x1) & (row[:, 2] >= y0) & (row[:, 2] <= y1)
        ex = _first_stay(ex)
        row[~ex] = np.nan
        ids.append(entry.id)
        rows.append(row)
        alive.append(ex)
    return ids, rows, alive


def _born(sc: Scenario, spec: SurveillanceSpec, K: int) -> tuple[list[str], list[Mat], list[Vec]]:
    """The birth process's targets (:func:`covnet.core.surveillance.births.simulate_truth`
    from the stream ``(seed, BIRTHS)``), as truth rows ``B1, B2, ...``."""
    b = spec.births
    if b is None or b.rate == 0.0:
        return [], [], []
    (x0, y0), (x1, y1) = spec.area.min_m, spec.area.max_m
    proc = BirthProcess(
        b.rate,
        tuple(
            BirthRegion(
                r.min_m[0], r.max_m[0], r.min_m[1], r.max_m[1], *r.speed_mps, *r.heading_deg
            )
            for r in b.regions
        ),
        (x0, x1, y0, y1),
        sc.period_s,
        b.accel_noise_std_mps2,
    )
    hist = simulate_truth((), K, streams.stream(sc.seed, BIRTHS), proc)
    ids, rows, alive = [], [], []
    for i, t in enumerate(hist.targets):
        row = np.full((K, 4), np.nan)
        row[t.first_scan - 1 : t.leaves_at_scan - 1] = t.states
        ex = np.zeros(K, dtype=bool)
        ex[t.first_scan - 1 : t.leaves_at_scan - 1] = True
        ids.append(f"B{i + 1}")
        rows.append(row)
        alive.append(ex)
    return ids, rows, alive


def build(sc: Scenario) -> SurveillanceModel:
    """The surveillance model of ``sc`` (a config with ``surveillance:``)."""
    spec = sc.surveillance
    assert spec is not None and sc.targets is not None
    tm = targets.build(sc)
    ids, rows, alive = _configured(sc, tm)
    b_ids, b_rows, b_alive = _born(sc, spec, tm.scans)
    ids += b_ids
    rows += b_rows
    alive += b_alive
    truth = np.stack(rows) if rows else np.zeros((0, tm.scans, 4))
    exists = np.stack(alive) if alive else np.zeros((0, tm.scans), dtype=bool)
    cued = tuple(t.cued for t in sc.targets)
    return SurveillanceModel(tm, spec, tuple(ids), truth, exists, spec.grid(), cued)


# --------------------------------------------------------------------------------------------
# windows and the dwell
# --------------------------------------------------------------------------------------------


def cell_window(sm: SurveillanceModel, j: int, c: int) -> ClutterWindow:
    """Sensor ``j``'s window on search cell ``c``: the box of its noise-free measurements over
    the cell (position: the cell itself; range and bearing: the range and the bearing interval
    the cell spans, from its corners and, where the cell straddles them, its nearest point and
    the axis directions; a cell around the sensor spans every bearing)."""
    s = sm.tm.sensors[j]
    x0, x1, y0, y1 = sm.cells[c]
    sx, sy = s.sensor_xy
    if not any(s.angle_components):  # a position sensor: z = [x, y]
        return ClutterWindow(
            np.array([(x0 + x1) / 2, (y0 + y1) / 2]),
            np.array([(x1 - x0) / 2, (y1 - y0) / 2]),
            s.angle_components,
        )
    corners = np.array([[x0, y0], [x1, y0], [x0, y1], [x1, y1]]) - (sx, sy)
    near = np.array([min(max(sx, x0), x1) - sx, min(max(sy, y0), y1) - sy])
    r_far = float(np.hypot(corners[:, 0], corners[:, 1]).max())
    r_near = float(np.hypot(*near))
    inside = x0 <= sx <= x1 and y0 <= sy <= y1
    if inside:
        b_c, b_h = 0.0, math.pi
    else:
        b = np.arctan2(corners[:, 1], corners[:, 0])
        ref = math.atan2((y0 + y1) / 2 - sy, (x0 + x1) / 2 - sx)  # the cell centre's bearing
        off = wrap_angle(b - ref)
        lo_b, hi_b = float(off.min()), float(off.max())
        b_c = float(wrap_angle(ref + (lo_b + hi_b) / 2))
        b_h = max((hi_b - lo_b) / 2, 1e-9)
    parts_c, parts_h = [], []
    if s.dim_z == 2:
        parts_c.append((r_near + r_far) / 2)
        parts_h.append(max((r_far - r_near) / 2, 1e-9))
    parts_c.append(b_c)
    parts_h.append(b_h)
    return ClutterWindow(np.array(parts_c), np.array(parts_h), s.angle_components)


def is_task(task: str, n_cells: int) -> bool:
    """A command's task for a sensor: ``K<id>`` (a track, id >= 1) or ``C<c>`` (a cell
    ``0 <= c < n_cells``)."""
    if len(task) < 2 or task[0] not in "KC" or not task[1:].isdigit():
        return False
    n = int(task[1:])
    return n >= 1 if task[0] == "K" else n < n_cells


def dwell(sm: SurveillanceModel, j: int, scan: int, states: Mat, win: ClutterWindow) -> Mat:
    """Sensor ``j``'s returns ``(m, dim_z)`` at ``scan`` in window ``win``; ``states``
    ``(n, 4)`` every target's true state at the scan (NaN rows: absent), as the world publishes
    it (module docstring for the draws)."""
    s = sm.tm.sensors[j]
    rng = streams.sensor_stream(sm.tm.base.seed, j, scan)
    dz = s.dim_z
    rows: list[Mat] = []
    X = np.asarray(states, dtype=np.float64)
    present = np.flatnonzero(np.all(np.isfinite(X), axis=1))
    if present.size:
        P = X[present]
        seen = s.in_coverage(P) & win.contains(s.h(P))
        for i in np.flatnonzero(seen).tolist():
            z = s.h(P[i]) + s.L @ rng.standard_normal(dz)
            if rng.random() < s.pd:
                rows.append(z[None, :])
    if s.clutter_rate > 0.0:
        n = int(rng.poisson(s.clutter_rate))
        U = rng.random((n, dz))
        rows.append(win.center + (2.0 * U - 1.0) * win.half_width)
    Z = np.concatenate(rows, axis=0) if rows else np.zeros((0, dz))
    am = np.asarray(s.angle_components, dtype=bool)
    if am.any() and Z.shape[0]:
        Z = np.where(am, wrap_angle(Z), Z)
    if Z.shape[0] > 1:
        Z = Z[rng.permutation(Z.shape[0])]
    return np.ascontiguousarray(Z)
