"""Surveillance metrics beyond GOSPA: cardinality, time to confirm, track breaks, id switches.

Input per scan ``k`` (a :class:`ContinuityFrame`): the existing true targets (ids, positions)
and the **confirmed** tracks (ids, estimated positions).  Tentative tracks are not scored.

**Association of tracks to truths, per scan**: the GOSPA assignment (:func:`covnet.core.ospa.
gospa`, ``α = 2``, cut-off ``c``, order ``p``): the optimal pairs with ``d < c``.  A target is
*held* at scan ``k`` by the track it is paired with; an unpaired target is missed, an unpaired
confirmed track false.  GOSPA (with its decomposition) and OSPA are reported per scan.

Over the run, per target ``τ`` (first scan ``a_τ``, the first frame it appears in) and its *last
holder* ``ℓ_τ`` (the track that last held it, if any):

- **cardinality**: ``n_true(k)`` against ``n_confirmed(k)``;
- **time to confirm**: ``min{k ≥ a_τ : τ held at k} − a_τ`` scans (``0``: held at its first
  scan; ``None``: never held);
- **track break**, at scan ``k`` where ``τ`` exists: ``ℓ_τ`` is no longer among the confirmed
  tracks (it was deleted while its target existed).  ``ℓ_τ`` is then forgotten, so the next track
  that holds ``τ`` is not also an id switch;
- **id switch**, at scan ``k``: ``τ`` is held by a track ``ℓ' ≠ ℓ_τ`` while ``ℓ_τ`` is set (it
  still exists, or the break rule would have cleared it); ``ℓ_τ ← ℓ'``.  A scan where ``τ`` is
  missed changes nothing (a gap is not a switch).

Everything is computed in scan order from the frames alone (deterministic; ids are compared,
never positions, once the pairs are made).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from covnet.core.gaussian import Mat
from covnet.core.ospa import gospa, ospa

__all__ = ["ContinuityFrame", "ContinuityReport", "ScanSummary", "evaluate_continuity"]

IntVec = NDArray[np.intp]


def _ids(name: str, a: ArrayLike) -> IntVec:
    v = np.asarray(a, dtype=np.intp).reshape(-1)
    if np.unique(v).size != v.size:
        raise ValueError(f"{name}: expected distinct ids, got {v.tolist()}")
    return v


def _xy(name: str, a: ArrayLike, n: int) -> Mat:
    v = np.asarray(a, dtype=np.float64)
    if v.size == 0 and n == 0:
        return np.zeros((0, 2))
    if v.shape != (n, 2):
        raise ValueError(f"{name}: expected ({n}, 2) positions, got {v.shape}")
    return v


@dataclass(frozen=True, slots=True)
class ContinuityFrame:
    """One scan: ``truth_ids`` with ``truth_xy`` ``(n, 2)``, confirmed ``track_ids`` with
    ``track_xy`` ``(m, 2)``."""

    scan: int
    truth_ids: IntVec
    truth_xy: Mat
    track_ids: IntVec
    track_xy: Mat

    def __post_init__(self) -> None:
        ti = _ids("truth_ids", self.truth_ids)
        ki = _ids("track_ids", self.track_ids)
        object.__setattr__(self, "truth_ids", ti)
        object.__setattr__(self, "track_ids", ki)
        object.__setattr__(self, "truth_xy", _xy("truth_xy", self.truth_xy, ti.size))
        object.__setattr__(self, "track_xy", _xy("track_xy", self.track_xy, ki.size))


@dataclass(frozen=True, slots=True)
class ScanSummary:
    """Per scan: counts, GOSPA ``gospa`` with ``localisation``, ``missed``, ``false`` (and
    ``n_missed``, ``n_false``), ``ospa``; ``held`` the pairs ``(truth id, track id)``; the
    ``breaks`` (truth ids) and ``switches`` ``(truth id, old track, new track)`` of this scan."""

    scan: int
    n_true: int
    n_confirmed: int
    gospa: float
    localisation: float
    missed: float
    false: float
    n_missed: int
    n_false: int
    ospa: float
    held: tuple[tuple[int, int], ...]
    breaks: tuple[int, ...]
    switches: tuple[tuple[int, int, int], ...]


@dataclass(frozen=True, slots=True)
class ContinuityReport:
    """The run: the per-scan ``scans``; per target its ``first_scan`` and ``time_to_confirm``
    (``None``: never held); totals of breaks and switches."""

    scans: tuple[ScanSummary, ...]
    first_scan: dict[int, int]
    time_to_confirm: dict[int, int | None]

    @property
    def n_breaks(self) -> int:
        return sum(len(s.breaks) for s in self.scans)

    @property
    def n_switches(self) -> int:
        return sum(len(s.switches) for s in self.scans)

    @property
    def mean_time_to_confirm(self) -> float:
        """Over the targets ever held (``nan`` if none)."""
        v = [t for t in self.time_to_confirm.values() if t is not None]
        return float(np.mean(v)) if v else math.nan

    @property
    def n_never_confirmed(self) -> int:
        return sum(t is None for t in self.time_to_confirm.values())


def evaluate_continuity(
    frames: Sequence[ContinuityFrame], c: float, p: float = 2.0
) -> ContinuityReport:
    """The metrics of the module docstring over ``frames`` (in increasing scan order)."""
    first: dict[int, int] = {}
    ttc: dict[int, int | None] = {}
    holder: dict[int, int] = {}
    out: list[ScanSummary] = []
    last_scan: int | None = None
    for f in frames:
        if last_scan is not None and f.scan <= last_scan:
            raise ValueError(f"frames: expected increasing scans, got {f.scan} after {last_scan}")
        last_scan = f.scan
        g = gospa(f.truth_xy, f.track_xy, c, p)
        o = ospa(f.truth_xy, f.track_xy, c, p)
        held = {int(f.truth_ids[i]): int(f.track_ids[j]) for i, j in g.pairs.tolist()}
        live_tracks = set(f.track_ids.tolist())
        breaks: list[int] = []
        switches: list[tuple[int, int, int]] = []
        for tau in f.truth_ids.tolist():
            if tau not in first:
                first[tau] = f.scan
                ttc[tau] = None
            old = holder.get(tau)
            if old is not None and old not in live_tracks:
                breaks.append(tau)
                del holder[tau]
                old = None
            new = held.get(tau)
            if new is None:
                continue
            if ttc[tau] is None:
                ttc[tau] = f.scan - first[tau]
            if old is not None and new != old:
                switches.append((tau, old, new))
            holder[tau] = new
        out.append(
            ScanSummary(
                scan=f.scan,
                n_true=int(f.truth_ids.size),
                n_confirmed=int(f.track_ids.size),
                gospa=g.distance,
                localisation=g.localisation,
                missed=g.missed,
                false=g.false,
                n_missed=g.n_missed,
                n_false=g.n_false,
                ospa=o,
                held=tuple(sorted(held.items())),
                breaks=tuple(breaks),
                switches=tuple(switches),
            )
        )
    return ContinuityReport(tuple(out), first, ttc)
