"""Search cells: the grid, the undetected mass ``u_c`` and the allocator's term of a cell.

**Grid.**  The area ``[xmin, xmax] × [ymin, ymax]`` is cut into ``nx × ny`` equal cells; cell
``c = ix + nx · iy`` (x fastest) has the box ``[xmin + ix Δx, xmin + (ix+1) Δx] × [ymin + iy Δy,
...]`` and its centre.  A point on an inner edge belongs to the cell above / to the right; the
area's outer edges belong to the last cells.

**Undetected mass** ``u_c``: the expected number of targets in cell ``c`` that no track holds
(the intensity of the undetected targets, integrated over the cell; spec ``surveillance.md``
§3).  Per scan:

1. ``u_c ← u_c + b_c`` (:func:`grow`), ``b_c`` the birth intensity reaching the cell
   (:func:`birth_intensity_per_cell`: a birth process of rate ``ρ`` per scan, uniform over the
   union of its regions, gives ``b_c = ρ · Σ_r |r ∩ c| / Σ_r |r|``);
2. after the scan's searches, ``u_c ← u_c Π_{j∈S_c} (1 − P_D,j)`` (:func:`after_search`), ``S_c``
   the sensors that searched ``c``.

The rule for the mass of a detection that starts a track: **the search update already moved
it.**  ``u_c · (1 − Π(1 − P_D,j))`` is exactly the expected number of undetected targets the
scan found in ``c`` -- it left ``u_c`` whether or not a return was received, and the tracks a
search starts are that mass (this is the undetected-target update of the Poisson
multi-Bernoulli mixture filter, exact for Poisson undetected targets).  Nothing more is
subtracted for them.  A track started from a return that no search produced (a target found
while dwelling on another track) did not go through step 2; for it :func:`remove_found`
subtracts ``min(u_c, 1)`` from its cell: the found target, at most the mass there.  (A search
of cell ``c`` whose window reaches into cell ``c'`` searched that part of ``c'`` too; the exact
update would apply ``(1 − P_D)`` to the mass of ``c'`` inside the window.  Neither that nor a
whole unit is taken from ``c'`` for the tracks such a search starts there: a whole unit per
clutter-started tentative track drains the cells, README *Surveillance*.)

**Coverage.**  Sensor ``j`` can search cell ``c`` when the cell's **centre** is inside its
coverage (:meth:`~covnet.core.sensor_models.SensorModel.in_coverage`: ``max_range_m``,
``fov``); a search then detects with the sensor's ``pd`` every target in the cell (the targets of
the cell's parts outside coverage too -- the approximation of judging by the centre, small
when cells are small against the coverage).

**The allocator's term of a cell.**  Spec §4 scores an assignment ``a`` (to be minimised) with
``F(a) = Σ_t w_t f(P_t(a), P_d,t) − λ Σ_c u_c (1 − Π_{j: a_j = c} (1 − pd_j))``.  Per cell::

    −λ u_c (1 − Π_j (1 − pd_j)) = λ u_c Π_j (1 − pd_j) − λ u_c

and ``−λ u_c`` does not depend on ``a``, so minimising ``F`` is minimising ``Σ_t w_t f(...) +
Σ_c λ u_c Π_{j: a_j = c} (1 − pd_j)``: :func:`cell_value` is that nonnegative term, which
depends only on the set of sensors searching the cell (empty set: ``λ u_c``), exactly like a
target's term -- the exact and bounded assignment allocators take a cell as one more
"target".  :func:`cell_found` is the spec's ``λ u_c (1 − Π(1 − pd_j))`` (expected finds ×
``λ``), for reports.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from covnet.core.gaussian import Mat, Vec
from covnet.core.sensor_models import SensorModel

__all__ = [
    "SearchGrid",
    "after_search",
    "birth_intensity_per_cell",
    "cell_found",
    "cell_value",
    "coverage_of",
    "grow",
    "remove_found",
    "uniform_mass",
]

IntVec = NDArray[np.intp]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class SearchGrid:
    """``nx × ny`` cells over the box ``[xmin, xmax] × [ymin, ymax]`` (m; module docstring)."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float
    nx: int
    ny: int

    def __post_init__(self) -> None:
        for name in ("xmin", "xmax", "ymin", "ymax"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise ValueError(f"search area {name}: expected a finite number, got {v!r}")
            object.__setattr__(self, name, v)
        if not (self.xmin < self.xmax and self.ymin < self.ymax):
            raise ValueError(
                "search area: expected xmin < xmax and ymin < ymax, got "
                f"[{self.xmin}, {self.xmax}] x [{self.ymin}, {self.ymax}]"
            )
        for name in ("nx", "ny"):
            v = getattr(self, name)
            if not (int(v) == v and v >= 1):
                raise ValueError(f"search {name}: expected an integer >= 1, got {v!r}")
            object.__setattr__(self, name, int(v))

    @property
    def n_cells(self) -> int:
        return self.nx * self.ny

    @property
    def cell_size(self) -> tuple[float, float]:
        """``(Δx, Δy)``."""
        return (self.xmax - self.xmin) / self.nx, (self.ymax - self.ymin) / self.ny

    @property
    def cell_area(self) -> float:
        dx, dy = self.cell_size
        return dx * dy

    def boxes(self) -> Mat:
        """``(C, 4)``: per cell ``[x0, x1, y0, y1]``."""
        dx, dy = self.cell_size
        ix = np.tile(np.arange(self.nx), self.ny)
        iy = np.repeat(np.arange(self.ny), self.nx)
        x0 = self.xmin + ix * dx
        y0 = self.ymin + iy * dy
        return np.stack([x0, x0 + dx, y0, y0 + dy], axis=1)

    def centres(self) -> Mat:
        """``(C, 2)``: per cell ``(x, y)`` of its centre."""
        b = self.boxes()
        return np.stack([0.5 * (b[:, 0] + b[:, 1]), 0.5 * (b[:, 2] + b[:, 3])], axis=1)

    def cell_of(self, xy: ArrayLike) -> IntVec:
        """The cell of each point ``(..., 2)``; ``-1`` outside the area."""
        p = np.asarray(xy, dtype=np.float64)
        if p.ndim == 0 or p.shape[-1] != 2:
            raise ValueError(f"xy: expected points of shape (..., 2), got {p.shape}")
        dx, dy = self.cell_size
        ix = np.minimum(np.floor((p[..., 0] - self.xmin) / dx), self.nx - 1)
        iy = np.minimum(np.floor((p[..., 1] - self.ymin) / dy), self.ny - 1)
        inside = (
            (p[..., 0] >= self.xmin)
            & (p[..., 0] <= self.xmax)
            & (p[..., 1] >= self.ymin)
            & (p[..., 1] <= self.ymax)
        )
        c = np.where(inside, ix + self.nx * iy, -1)
        return np.asarray(c, dtype=np.intp)


def _mass(u: ArrayLike, n: int | None = None) -> Vec:
    uu = np.asarray(u, dtype=np.float64)
    if uu.ndim != 1 or (n is not None and uu.shape[0] != n):
        raise ValueError(f"u: expected one mass per cell, shape ({n},), got {uu.shape}")
    if not np.all(np.isfinite(uu) & (uu >= 0.0)):
        raise ValueError("u: expected finite masses >= 0")
    return uu


def uniform_mass(grid: SearchGrid, total: float) -> Vec:
    """``u_c(0) = total / C`` in every cell: ``total`` undetected targets expected at the start,
    spread uniformly over the area."""
    t = float(total)
    if not (math.isfinite(t) and t >= 0.0):
        raise ValueError(f"initial undetected mass: expected a finite number >= 0, got {total!r}")
    return np.full(grid.n_cells, t / grid.n_cells)


def grow(u: ArrayLike, birth_per_cell: ArrayLike) -> Vec:
    """``u_c + b_c``."""
    uu = _mass(u)
    return uu + _mass(birth_per_cell, uu.shape[0])


def after_search(u: ArrayLike, searched_by: Sequence[Sequence[float]]) -> Vec:
    """``u_c Π_{j ∈ S_c} (1 − pd_j)``; ``searched_by[c]`` the ``pd`` of each sensor that searched
    cell ``c`` this scan (empty: not searched)."""
    uu = _mass(u)
    if len(searched_by) != uu.shape[0]:
        raise ValueError(f"searched_by: expected one list per cell ({uu.shape[0]})")
    return np.asarray(uu * np.array([_miss(pds) for pds in searched_by]))


def _miss(pds: Sequence[float]) -> float:
    out = 1.0
    for p in pds:
        pf = float(p)
        if not (0.0 <= pf <= 1.0):
            raise ValueError(f"pd: expected a probability in [0, 1], got {p!r}")
        out *= 1.0 - pf
    return out


def remove_found(u: ArrayLike, cells: Sequence[int] | IntVec) -> Vec:
    """For each new track started outside a search of its cell (module docstring):
    ``u_c ← u_c − min(u_c, 1)``, once per entry of ``cells`` (``-1``, outside the area, is
    ignored)."""
    out = _mass(u).copy()
    for c in np.asarray(cells, dtype=np.intp).tolist():
        if c >= 0:
            out[c] -= min(out[c], 1.0)
    return out


def coverage_of(grid: SearchGrid, model: SensorModel) -> BoolArray:
    """``(C,)``: True where the sensor can search the cell (its centre in coverage)."""
    c = grid.centres()
    states = np.stack([c[:, 0], np.zeros(len(c)), c[:, 1], np.zeros(len(c))], axis=1)
    return np.asarray(model.in_coverage(states), dtype=bool)


def cell_value(u_c: float, weight: float, pds: Sequence[float]) -> float:
    """``λ u_c Π_j (1 − pd_j)``: the cell's term for the allocator to minimise (module
    docstring; ``weight`` is ``λ``)."""
    return float(weight) * float(u_c) * _miss(pds)


def cell_found(u_c: float, weight: float, pds: Sequence[float]) -> float:
    """``λ u_c (1 − Π_j (1 − pd_j))``: ``λ`` times the expected number of targets found."""
    return float(weight) * float(u_c) * (1.0 - _miss(pds))


def birth_intensity_per_cell(
    grid: SearchGrid, regions: Sequence[tuple[float, float, float, float]], birth_rate: float
) -> Vec:
    """``b_c = ρ Σ_r |r ∩ c| / Σ_r |r|`` for boxes ``(x0, x1, y0, y1)`` (births uniform over
    the regions, :mod:`covnet.core.surveillance.births`); the part of a region outside the grid
    is lost."""
    rate = float(birth_rate)
    if not (math.isfinite(rate) and rate >= 0.0):
        raise ValueError(f"birth_rate: expected a finite number >= 0, got {birth_rate!r}")
    b = grid.boxes()
    out = np.zeros(grid.n_cells)
    total = 0.0
    for r in regions:
        x0, x1, y0, y1 = (float(v) for v in r)
        total += (x1 - x0) * (y1 - y0)
        wx = np.clip(np.minimum(b[:, 1], x1) - np.maximum(b[:, 0], x0), 0.0, None)
        wy = np.clip(np.minimum(b[:, 3], y1) - np.maximum(b[:, 2], y0), 0.0, None)
        out += wx * wy
    if total <= 0.0:
        return np.zeros(grid.n_cells)
    return rate * out / total
