"""Track management: initiation from unassociated returns, M-of-N confirmation, deletion.

A track is ``tentative`` -> ``confirmed`` -> ``deleted`` (or ``tentative`` -> ``deleted``); its id
comes from a counter and is never reused; every listing is in ascending id order (spec
``surveillance.md`` §2).  State ``x = [x, vx, y, vy]``.

**Initiation.**  A return inside no live track's gate
(:meth:`covnet.core.surveillance.jpda.JPDAResult.ungated_rows`), from a sensor whose model is in
:data:`INITIATORS`, starts a tentative track::

    x₀ = [p_x, 0, p_y, 0],     P₀ = [[P_pp, 0], [0, σ_v² I]]  (over (x, y) and (vx, vy))

with ``σ_v = velocity_std`` and the position ``p`` and its covariance ``P_pp`` converted from
the return ``z`` with the sensor's ``R``:

- ``position``: ``p = z``, ``P_pp = R``;
- ``range_bearing``: the linearised polar -> Cartesian conversion (first order, not debiased)::

      p = s + r [cos β, sin β],     J = [[cos β, −r sin β], [sin β, r cos β]],    P_pp = J R Jᵀ

  Its bias, ``r (1 − e^{−σ_β²/2}) ≈ r σ_β²/2``, is 0.06 m at 30 km with 2 mrad: far below the
  cross-range ``σ = r σ_β`` = 60 m, so the unbiased conversion would change nothing here;
- ``bearing`` (not in the registry): a bearing alone has no range, it never starts a track.

**Dwells and hits.**  Each dwell *on* a live track (a sensor whose returns were associated to
it, whether or not one was in its gate) is recorded with :func:`record_dwell`.  The dwell is a
*hit* when some return was in the gate and ``1 − β_0 > hit_threshold`` (:func:`is_hit`; the
default threshold ``0`` makes any gated return with non-zero weight a hit, i.e. ``β_0 < 1``).

**Confirmation (M-of-N).**  The return that started the track counts as its first dwell, a
hit.  A tentative track is confirmed at the dwell where its hits reach ``M`` (``confirm_m``)
within its first ``N`` (``confirm_n``) dwells, and deleted (reason ``"confirmation"``) as soon
as that can no longer happen (``hits + (N − dwells) < M``).  With ``P_D = 1`` and the target in
the gate, a track is confirmed at its ``M``-th dwell (``M − 1`` dwells after the initiating one).

**Deletion of a confirmed track**: after ``delete_after_misses`` consecutive dwells that were
not hits (reason ``"misses"``), or when the trace of its position covariance
``P[0,0] + P[2,2]`` exceeds ``delete_trace_m2`` (reason ``"covariance"``,
:func:`check_covariance`).  Tentative tracks are deleted here only by the M-of-N rule (with
their velocity spread their position covariance is large by design); the surveillance centre
(:mod:`covnet.covariance_control.surveillance_centre`, after a scan's fusion) also deletes any
live track, tentative or confirmed, whose position trace passes ``delete_trace_m2``, or that
left the area.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from covnet.core.gaussian import Gaussian, Mat, Vec, symmetrise
from covnet.core.sensor_models import SensorModel

__all__ = [
    "INITIATORS",
    "Initiator",
    "Track",
    "TrackManager",
    "TrackRules",
    "TrackState",
    "can_initiate",
    "check_covariance",
    "initiate",
    "is_hit",
    "position_from_return",
    "position_trace",
    "record_dwell",
]

IntVec = NDArray[np.intp]


class TrackState(enum.Enum):
    """A track's life: ``tentative`` -> ``confirmed`` -> ``deleted``."""

    TENTATIVE = "tentative"
    CONFIRMED = "confirmed"
    DELETED = "deleted"


@dataclass(frozen=True, slots=True)
class TrackRules:
    """The rules of the module docstring: ``confirm_m`` of the first ``confirm_n`` dwells,
    ``delete_after_misses`` consecutive non-hits, ``delete_trace_m2`` (m², ``inf``: never),
    ``hit_threshold`` in ``[0, 1)`` and ``velocity_std`` (m/s) of a new track."""

    confirm_m: int = 2
    confirm_n: int = 3
    delete_after_misses: int = 3
    delete_trace_m2: float = math.inf
    hit_threshold: float = 0.0
    velocity_std: float = 50.0

    def __post_init__(self) -> None:
        m, n = self.confirm_m, self.confirm_n
        if not (int(m) == m and int(n) == n and 1 <= m <= n):
            raise ValueError(f"confirm: expected integers 1 <= m <= n, got m={m!r}, n={n!r}")
        k = self.delete_after_misses
        if not (int(k) == k and k >= 1):
            raise ValueError(f"delete_after_misses: expected an integer >= 1, got {k!r}")
        if not float(self.delete_trace_m2) > 0.0:
            raise ValueError(
                f"delete_trace_m2: expected a number > 0 (or inf), got {self.delete_trace_m2!r}"
            )
        if not (0.0 <= float(self.hit_threshold) < 1.0):
            raise ValueError(f"hit_threshold: expected 0 <= h < 1, got {self.hit_threshold!r}")
        v = float(self.velocity_std)
        if not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"velocity_std: expected a finite number > 0, got {v!r}")


@dataclass(frozen=True, slots=True)
class Track:
    """One track: ``id``, ``state``, ``estimate``; ``hits`` per dwell on it while tentative
    (the initiating return first, ``True``); ``n_dwells`` all dwells on it (the initiating one
    included); ``misses`` consecutive non-hit dwells; ``born_scan``, ``confirmed_scan``,
    ``deleted_scan`` and ``deleted_reason`` (``"confirmation"``, ``"misses"``,
    ``"covariance"``)."""

    id: int
    state: TrackState
    estimate: Gaussian
    hits: tuple[bool, ...]
    n_dwells: int
    misses: int
    born_scan: int
    confirmed_scan: int | None = None
    deleted_scan: int | None = None
    deleted_reason: str | None = None

    @property
    def live(self) -> bool:
        return self.state is not TrackState.DELETED


# --------------------------------------------------------------------------------------------
# initiation


def _from_position(model: SensorModel, z: Vec) -> tuple[Vec, Mat]:
    return np.array(z, dtype=np.float64), np.array(model.R)


def _from_range_bearing(model: SensorModel, z: Vec) -> tuple[Vec, Mat]:
    r, b = float(z[0]), float(z[1])
    c, s = math.cos(b), math.sin(b)
    p = np.array([model.sensor_xy[0] + r * c, model.sensor_xy[1] + r * s])
    J = np.array([[c, -r * s], [s, r * c]])
    return p, symmetrise(J @ model.R @ J.T)


@dataclass(frozen=True, slots=True)
class Initiator:
    """A registry entry: the model ``kind`` whose returns can start a track and ``position``,
    ``(model, z) -> (p, P_pp)`` (module docstring)."""

    kind: str
    position: Callable[[SensorModel, Vec], tuple[Vec, Mat]]


#: model kind -> how its return gives a position; a kind not here never starts a track
INITIATORS: dict[str, Initiator] = {
    "position": Initiator("position", _from_position),
    "range_bearing": Initiator("range_bearing", _from_range_bearing),
}


def can_initiate(model: SensorModel) -> bool:
    """True when the model's returns can start a track (its kind is in :data:`INITIATORS`)."""
    return model.kind in INITIATORS


def position_from_return(model: SensorModel, z: ArrayLike) -> tuple[Vec, Mat]:
    """``(p, P_pp)`` of one return ``z`` ``(dim_z,)`` (module docstring); a model that cannot
    start a track raises ``ValueError``."""
    entry = INITIATORS.get(model.kind)
    if entry is None:
        raise ValueError(
            f"model {model.kind!r}: its returns cannot start a track "
            f"(those of {sorted(INITIATORS)} can)"
        )
    zz = np.asarray(z, dtype=np.float64)
    if zz.shape != (model.dim_z,):
        raise ValueError(f"z: expected shape ({model.dim_z},), got {zz.shape}")
    return entry.position(model, zz)


def initiate(
    Z: ArrayLike,
    rows: Sequence[int] | IntVec,
    model: SensorModel,
    velocity_std: float,
    scan: int,
    first_id: int,
    confirm_m: int = 2,
) -> tuple[Track, ...]:
    """New tentative tracks from the returns ``Z[rows]`` (rows in the given order, e.g. the
    ascending :meth:`~covnet.core.surveillance.jpda.JPDAResult.ungated_rows`), ids
    ``first_id, first_id + 1, ...``; none for a model that cannot start a track.  With
    ``confirm_m = 1`` the initiating return alone confirms: the tracks are born confirmed."""
    v = float(velocity_std)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"velocity_std: expected a finite number > 0, got {velocity_std!r}")
    if not can_initiate(model):
        return ()
    ZZ = np.asarray(Z, dtype=np.float64).reshape(-1, model.dim_z)
    out: list[Track] = []
    for k, row in enumerate(np.asarray(rows, dtype=np.intp).tolist()):
        p, Ppp = position_from_return(model, ZZ[row])
        x = np.array([p[0], 0.0, p[1], 0.0])
        P = np.zeros((4, 4))
        P[np.ix_([0, 2], [0, 2])] = Ppp
        P[1, 1] = P[3, 3] = v * v
        g = Gaussian(x, P)
        t = Track(first_id + k, TrackState.TENTATIVE, g, (True,), 1, 0, int(scan))
        if confirm_m <= 1:
            t = replace(t, state=TrackState.CONFIRMED, confirmed_scan=int(scan))
        out.append(t)
    return tuple(out)


# --------------------------------------------------------------------------------------------
# dwells, confirmation, deletion


def is_hit(beta0: float, n_gated: int, hit_threshold: float = 0.0) -> bool:
    """A dwell is a hit when ``n_gated > 0`` and ``1 − β_0 > hit_threshold``."""
    return n_gated > 0 and (1.0 - float(beta0)) > hit_threshold


def position_trace(g: Gaussian) -> float:
    """``P[0,0] + P[2,2]`` (m²)."""
    return float(g.P[0, 0] + g.P[2, 2])


def _delete(track: Track, scan: int, reason: str) -> Track:
    return replace(track, state=TrackState.DELETED, deleted_scan=int(scan), deleted_reason=reason)


def record_dwell(
    track: Track, posterior: Gaussian, hit: bool, scan: int, rules: TrackRules
) -> Track:
    """The track after one dwell on it: the new ``estimate``, and the M-of-N / misses rules
    (module docstring).  A deleted track raises."""
    if not track.live:
        raise ValueError(f"track {track.id}: deleted at scan {track.deleted_scan}, no more dwells")
    misses = 0 if hit else track.misses + 1
    t = replace(track, estimate=posterior, n_dwells=track.n_dwells + 1, misses=misses)
    if t.state is TrackState.TENTATIVE:
        hits = (*track.hits, bool(hit))
        t = replace(t, hits=hits)
        n_hits = sum(hits)
        if n_hits >= rules.confirm_m:
            return replace(t, state=TrackState.CONFIRMED, confirmed_scan=int(scan))
        if n_hits + (rules.confirm_n - len(hits)) < rules.confirm_m:
            return _delete(t, scan, "confirmation")
        return t
    if misses >= rules.delete_after_misses:
        return _delete(t, scan, "misses")
    return t


def check_covariance(track: Track, scan: int, rules: TrackRules) -> Track:
    """A confirmed track whose position trace exceeds ``delete_trace_m2`` is deleted
    (``"covariance"``); any other track is returned unchanged."""
    if (
        track.state is TrackState.CONFIRMED
        and position_trace(track.estimate) > rules.delete_trace_m2
    ):
        return _delete(track, scan, "covariance")
    return track


# --------------------------------------------------------------------------------------------
# the set of tracks


class TrackManager:
    """The tracks of one run: the rules, the id counter (never reused), the live tracks and
    the deleted ones, always listed by ascending id.  Every change goes through the pure
    functions above."""

    def __init__(self, rules: TrackRules, first_id: int = 0) -> None:
        self.rules = rules
        self.next_id = int(first_id)
        self._live: dict[int, Track] = {}
        self.deleted: list[Track] = []

    def live(self) -> tuple[Track, ...]:
        """Tentative and confirmed tracks, ids ascending."""
        return tuple(self._live[k] for k in sorted(self._live))

    def confirmed(self) -> tuple[Track, ...]:
        return tuple(t for t in self.live() if t.state is TrackState.CONFIRMED)

    def tentative(self) -> tuple[Track, ...]:
        return tuple(t for t in self.live() if t.state is TrackState.TENTATIVE)

    def __getitem__(self, track_id: int) -> Track:
        return self._live[track_id]

    def _store(self, t: Track) -> Track:
        if t.live:
            self._live[t.id] = t
        else:
            self._live.pop(t.id, None)
            self.deleted.append(t)
        return t

    def initiate(
        self, Z: ArrayLike, rows: Sequence[int] | IntVec, model: SensorModel, scan: int
    ) -> tuple[Track, ...]:
        """:func:`initiate` with the next ids and ``rules.velocity_std``."""
        r = self.rules
        new = initiate(Z, rows, model, r.velocity_std, scan, self.next_id, r.confirm_m)
        self.next_id += len(new)
        for t in new:
            self._store(t)
        return new

    def cue(self, estimate: Gaussian, scan: int) -> Track:
        """A confirmed track from a cue (a target known before the first scan: its initial
        estimate), with the next id."""
        t = Track(
            self.next_id, TrackState.CONFIRMED, estimate, (True,), 0, 0, int(scan), int(scan)
        )
        self.next_id += 1
        return self._store(t)

    def set_estimate(self, track_id: int, estimate: Gaussian) -> Track:
        """Replace a live track's estimate (e.g. by its prediction to the scan's time)."""
        return self._store(replace(self._live[track_id], estimate=estimate))

    def record_dwell(self, track_id: int, posterior: Gaussian, hit: bool, scan: int) -> Track:
        """:func:`record_dwell` on a live track; a deleted track moves to :attr:`deleted`."""
        return self._store(record_dwell(self._live[track_id], posterior, hit, scan, self.rules))

    def delete(self, track_id: int, scan: int, reason: str) -> Track:
        """Delete a live track for ``reason`` (e.g. ``"duplicate"``); it moves to
        :attr:`deleted`."""
        return self._store(_delete(self._live[track_id], scan, reason))

    def check_covariance(self, scan: int) -> tuple[Track, ...]:
        """:func:`check_covariance` on every live track; returns those it deleted."""
        out = []
        for t in self.live():
            u = check_covariance(t, scan, self.rules)
            if not u.live:
                out.append(self._store(u))
        return tuple(out)
