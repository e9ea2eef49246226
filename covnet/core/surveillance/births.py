"""Truth with targets that appear and leave, and an optional Poisson birth process.

Scans are ``k = 1..K``.  A target exists for the scans ``first_scan ≤ k < leaves_at_scan``
(``leaves_at_scan = None``: to the end); the result lists per scan the existing targets by id
(spec ``surveillance.md`` §1).

**Scheduled targets** (the config's): each is given its whole trajectory ``(K, 4)`` (row
``k − 1`` at scan ``k``, e.g. :func:`covnet.core.manoeuvre.manoeuvring_trajectory`, drawn by the
caller exactly as for a run without births) with ``appears_at_scan`` (default 1) and
``leaves_at_scan``; they take ids ``0..T−1`` in the given order.  Nothing is drawn for them here,
so a run with every target present from scan 1 and no births keeps its truth unchanged.

**Birth process** (:class:`BirthProcess`): at each scan ``k``, ``n_k ~ Poisson(rate)`` targets
enter.  Each picks a region with probability proportional to its area (so births are uniform
over the regions' union when they do not overlap), a position uniform in it, a speed uniform in
``[speed_min, speed_max]`` and a heading uniform in ``[heading_min_deg, heading_max_deg]``
(counter-clockwise from +x): its state at scan ``k`` is ``[x, v cos h, y, v sin h]``.  It then
moves with the paper's constant velocity plus white acceleration (``x(k+1) = F x(k) + G w(k)``,
``w ~ N(0, σ_a² I)``, :mod:`covnet.core.motion`) and leaves at the first scan its position is
outside the area box.  Ids continue after the scheduled ones, in order of birth.

Draws, from the one generator given, scan by scan: the count ``n_k``; then per new target the
region uniform, the two position uniforms, the speed uniform, the heading uniform, and its
motion noise for all its remaining steps in one call ``σ_a · standard_normal((K − k, 2))``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from covnet.core.gaussian import Mat
from covnet.core.motion import cv_transition, dwna_noise_gain

__all__ = [
    "BirthProcess",
    "BirthRegion",
    "ScheduledTarget",
    "TruthHistory",
    "TruthTarget",
    "simulate_truth",
]

IntVec = NDArray[np.intp]


def _finite(name: str, v: float) -> float:
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"{name}: expected a finite number, got {v!r}")
    return f


@dataclass(frozen=True, slots=True)
class ScheduledTarget:
    """A config's target: its ``trajectory`` ``(K, 4)`` and the scans it exists in
    (``appears_at_scan ≤ k < leaves_at_scan``)."""

    trajectory: Mat
    appears_at_scan: int = 1
    leaves_at_scan: int | None = None

    def __post_init__(self) -> None:
        tr = np.asarray(self.trajectory, dtype=np.float64)
        if tr.ndim != 2 or tr.shape[1] != 4:
            raise ValueError(f"trajectory: expected shape (n_scans, 4), got {tr.shape}")
        object.__setattr__(self, "trajectory", tr)
        a = self.appears_at_scan
        if not (int(a) == a and a >= 1):
            raise ValueError(f"appears_at_scan: expected an integer >= 1, got {a!r}")
        b = self.leaves_at_scan
        if b is not None and not (int(b) == b and b > a):
            raise ValueError(
                f"leaves_at_scan: expected an integer > appears_at_scan ({a}), got {b!r}"
            )


@dataclass(frozen=True, slots=True)
class BirthRegion:
    """A box ``[x0, x1] × [y0, y1]`` (m) where targets enter, with their speed (m/s) and
    heading (degrees, counter-clockwise from +x) ranges."""

    x0: float
    x1: float
    y0: float
    y1: float
    speed_min: float
    speed_max: float
    heading_min_deg: float
    heading_max_deg: float

    def __post_init__(self) -> None:
        for name in self.__slots__:
            object.__setattr__(self, name, _finite(f"birth region {name}", getattr(self, name)))
        if not (self.x0 < self.x1 and self.y0 < self.y1):
            raise ValueError("birth region: expected x0 < x1 and y0 < y1")
        if not (0.0 <= self.speed_min <= self.speed_max):
            raise ValueError("birth region: expected 0 <= speed_min <= speed_max")
        if not self.heading_min_deg <= self.heading_max_deg:
            raise ValueError("birth region: expected heading_min_deg <= heading_max_deg")

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    @property
    def box(self) -> tuple[float, float, float, float]:
        return (self.x0, self.x1, self.y0, self.y1)


@dataclass(frozen=True, slots=True)
class BirthProcess:
    """``Poisson(rate)`` births per scan from ``regions`` (each inside ``area``
    ``(xmin, xmax, ymin, ymax)``), moving with period ``T`` and white acceleration
    ``sigma_a``."""

    rate: float
    regions: tuple[BirthRegion, ...]
    area: tuple[float, float, float, float]
    T: float
    sigma_a: float

    def __post_init__(self) -> None:
        r = _finite("birth_rate", self.rate)
        if r < 0.0:
            raise ValueError(f"birth_rate: expected a number >= 0, got {r}")
        if r > 0.0 and not self.regions:
            raise ValueError("birth regions: expected at least one region when birth_rate > 0")
        xmin, xmax, ymin, ymax = (_finite("area", v) for v in self.area)
        if not (xmin < xmax and ymin < ymax):
            raise ValueError("area: expected xmin < xmax and ymin < ymax")
        for i, g in enumerate(self.regions):
            if not (xmin <= g.x0 and g.x1 <= xmax and ymin <= g.y0 and g.y1 <= ymax):
                raise ValueError(f"birth regions[{i}]: expected a box inside the area {self.area}")
        if not _finite("T", self.T) > 0.0:
            raise ValueError(f"T: expected a period > 0, got {self.T!r}")
        if not _finite("sigma_a", self.sigma_a) >= 0.0:
            raise ValueError(f"sigma_a: expected a number >= 0, got {self.sigma_a!r}")

    def inside(self, xy: ArrayLike) -> bool:
        x, y = (float(v) for v in np.asarray(xy, dtype=np.float64))
        xmin, xmax, ymin, ymax = self.area
        return xmin <= x <= xmax and ymin <= y <= ymax


@dataclass(frozen=True, slots=True)
class TruthTarget:
    """One true target: ``id``, ``first_scan``, ``states`` ``(n, 4)`` for the scans
    ``first_scan .. first_scan + n − 1``, and ``born`` (from the birth process)."""

    id: int
    first_scan: int
    states: Mat
    born: bool

    @property
    def leaves_at_scan(self) -> int:
        """The first scan it no longer exists (``K + 1`` if it stays to the end)."""
        return self.first_scan + int(self.states.shape[0])

    def exists(self, scan: int) -> bool:
        return self.first_scan <= scan < self.leaves_at_scan


@dataclass(frozen=True, slots=True)
class TruthHistory:
    """All targets of a run of ``n_scans`` scans (ids ascending = scheduled, then born)."""

    n_scans: int
    targets: tuple[TruthTarget, ...]

    def at_scan(self, scan: int) -> tuple[IntVec, Mat]:
        """``(ids, states)`` of the targets existing at ``scan`` (ids ascending)."""
        ids = [t.id for t in self.targets if t.exists(scan)]
        states = [t.states[scan - t.first_scan] for t in self.targets if t.exists(scan)]
        X = np.array(states, dtype=np.float64).reshape(len(states), 4)
        return np.array(ids, dtype=np.intp), X


def _births(
    proc: BirthProcess, n_scans: int, first_id: int, rng: np.random.Generator
) -> list[TruthTarget]:
    F = cv_transition(proc.T)
    G = dwna_noise_gain(proc.T)
    areas = np.array([g.area for g in proc.regions])
    cum = np.cumsum(areas) / areas.sum() if areas.size else areas
    out: list[TruthTarget] = []
    for k in range(1, n_scans + 1):
        n_new = int(rng.poisson(proc.rate))
        for _ in range(n_new):
            i = min(int(np.searchsorted(cum, rng.random(), side="right")), len(cum) - 1)
            g = proc.regions[i]
            x = g.x0 + (g.x1 - g.x0) * rng.random()
            y = g.y0 + (g.y1 - g.y0) * rng.random()
            v = g.speed_min + (g.speed_max - g.speed_min) * rng.random()
            hd = math.radians(
                g.heading_min_deg + (g.heading_max_deg - g.heading_min_deg) * rng.random()
            )
            w = proc.sigma_a * rng.standard_normal((n_scans - k, 2))
            s = np.array([x, v * math.cos(hd), y, v * math.sin(hd)])
            rows = [s]
            for step in range(n_scans - k):
                s = F @ s + G @ w[step]
                if not proc.inside(s[[0, 2]]):
                    break
                rows.append(s)
            out.append(TruthTarget(first_id + len(out), k, np.array(rows), True))
    return out


def simulate_truth(
    scheduled: Sequence[ScheduledTarget],
    n_scans: int,
    rng: np.random.Generator,
    births: BirthProcess | None = None,
) -> TruthHistory:
    """The truth of a run (module docstring); ``rng`` is drawn from only by the birth process."""
    if not (int(n_scans) == n_scans and n_scans >= 0):
        raise ValueError(f"n_scans: expected an integer >= 0, got {n_scans!r}")
    K = int(n_scans)
    targets: list[TruthTarget] = []
    for i, st in enumerate(scheduled):
        if st.trajectory.shape[0] < K:
            raise ValueError(
                f"targets[{i}].trajectory: expected {K} scans, got {st.trajectory.shape[0]}"
            )
        a = int(st.appears_at_scan)
        end = K + 1 if st.leaves_at_scan is None else min(int(st.leaves_at_scan), K + 1)
        states = st.trajectory[a - 1 : max(end - 1, a - 1)]
        targets.append(TruthTarget(i, a, states, False))
    if births is not None and births.rate > 0.0:
        targets.extend(_births(births, K, len(targets), rng))
    return TruthHistory(K, tuple(targets))
