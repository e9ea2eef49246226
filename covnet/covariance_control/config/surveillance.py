"""The ``surveillance:`` block (spec ``surveillance.md``): targets that appear and leave, tracks
the manager starts, confirms and deletes, and the search against track.

A config with ``surveillance:`` keeps its ``targets:`` list, read as the **truth** only (each
target's ``appears_at_scan`` / ``leaves_at_scan``; no cue, no ``desired``: the manager does not
know them), and adds::

    surveillance:
      area: {min_m: [0, 0], max_m: [20000, 20000]}       # the surveilled area
      births:                                             # optional: Poisson births per scan
        rate: 0.05                                        # expected new targets per scan
        regions: [{min_m: [..], max_m: [..], speed_mps: [100, 250], heading_deg: [-30, 30]}]
      tracks:
        initiation: {velocity_std_mps: 300}               # a new track's velocity deviation
        confirm: {m: 2, n: 3}                             # M hits in the first N dwells
        delete_after_misses: 3                            # confirmed: consecutive misses
        delete_trace_m2: 1.0e6                            # position covariance trace
      search:                                             # optional: no search without it
        cells: {nx: 4, ny: 4}                             # a grid over the area
        u0: 0.1                                           # u_c(0): undetected targets per cell
        birth_intensity: 0.002                            # per cell per scan (default: births')
        weight: 50.0                                      # λ, in units of the metric
      desired:
        confirmed: {diag: [100, 2.5, 100, 2.5]}           # P_d of a confirmed track
        tentative: {diag: [400, 100, 400, 100]}           # P_d of a tentative one
      max_tracks: 32                                      # live tracks at once (a guard)
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

from covnet.config import MAX_RATE, ConfigModel, Float, Int, Pair, Quad
from covnet.config import positive as _positive
from covnet.records import Field, field_validator

if TYPE_CHECKING:
    from covnet.core.surveillance.search_cells import SearchGrid


class BoxSpec(ConfigModel):
    """An axis-aligned box ``[min_m, max_m]`` in the plane (metres)."""

    min_m: Pair
    max_m: Pair


class BirthRegionSpec(BoxSpec):
    """Where births enter: uniformly in the box, speed uniform in ``speed_mps`` and heading
    uniform in ``heading_deg`` (degrees from the x axis, counter-clockwise)."""

    speed_mps: Pair = (100.0, 250.0)
    heading_deg: Pair = (-180.0, 180.0)


class BirthSpec(ConfigModel):
    """``Poisson(rate)`` new targets per scan, each from a region chosen with probability
    proportional to its area; each leaves when it exits the area."""

    rate: Float = Field(ge=0.0, le=MAX_RATE)
    regions: tuple[BirthRegionSpec, ...] = Field(min_length=1)
    accel_noise_std_mps2: Float = Field(default=0.5, ge=0.0)


class InitiationSpec(ConfigModel):
    """A new track's velocity: zero, with this standard deviation per axis (the fastest
    expected speed)."""

    velocity_std_mps: Float = 300.0

    _v = field_validator("velocity_std_mps")(_positive)


class ConfirmSpec(ConfigModel):
    """M-of-N confirmation: ``m`` detections in the first ``n`` dwells on a tentative track."""

    m: Int = Field(default=2, ge=1)
    n: Int = Field(default=3, ge=1)


class TrackSpec(ConfigModel):
    """Track management (spec §2)."""

    initiation: InitiationSpec = InitiationSpec()
    confirm: ConfirmSpec = ConfirmSpec()
    delete_after_misses: Int = Field(default=3, ge=1)
    delete_trace_m2: Float = 1.0e6

    _d = field_validator("delete_trace_m2")(_positive)


class CellsSpec(ConfigModel):
    """A grid of ``nx`` x ``ny`` search cells over the area."""

    nx: Int = Field(ge=1, le=64)
    ny: Int = Field(ge=1, le=64)


class SearchSpec(ConfigModel):
    """The search (spec §3-4): the cells, their prior ``u0`` (expected undetected targets per
    cell at the start), the birth intensity reaching a cell per scan (default: the births'
    rate spread over the cells by the area their regions share with each) and the exchange
    rate ``weight`` (λ) between a target found and the metric."""

    cells: CellsSpec
    u0: Float = Field(default=0.0, ge=0.0)
    birth_intensity: Float | None = Field(default=None, ge=0.0)
    weight: Float = Field(ge=0.0)


class CovSpec(ConfigModel):
    """A desired covariance: ``diag`` (4 entries) or a full ``matrix``; ``weight`` ``w`` of the
    track's term."""

    diag: Quad | None = None
    matrix: Annotated[tuple[Quad, ...], Field(min_length=4, max_length=4)] | None = None
    weight: Float = 1.0

    _w = field_validator("weight")(_positive)


class SurveillanceDesired(ConfigModel):
    """``P_d`` per track state: ``confirmed`` and ``tentative`` (spec §4)."""

    confirmed: CovSpec
    tentative: CovSpec


class SurveillanceSpec(ConfigModel):
    """The ``surveillance:`` block (module docstring)."""

    area: BoxSpec
    births: BirthSpec | None = None
    tracks: TrackSpec = TrackSpec()
    search: SearchSpec | None = None
    desired: SurveillanceDesired
    max_tracks: Int = Field(default=32, ge=1, le=256)

    def grid(self) -> SearchGrid | None:
        """The search grid over the area (None without ``search``)."""
        # start-up: the surveillance core (and scipy with it) only where a grid is asked for
        from covnet.core.surveillance.search_cells import SearchGrid

        if self.search is None:
            return None
        (x0, y0), (x1, y1) = self.area.min_m, self.area.max_m
        return SearchGrid(x0, x1, y0, y1, self.search.cells.nx, self.search.cells.ny)
