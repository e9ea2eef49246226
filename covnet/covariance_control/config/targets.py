"""The targets' config: the paper's one ``target:`` and its filter's initialisation
(``filter:``), the desired-covariance schedule (``desired:``), and for many targets the
``targets:`` list (state, truth manoeuvres, own schedule and weight), ``association`` and
``ospa``; a target's manoeuvres as the core's segments (:func:`segments`)."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np

from covnet.config import Bool, ConfigModel, Float, Ident, Int, Pair, Quad
from covnet.config import positive as _positive
from covnet.covariance_control.config.fields import positive_or_none
from covnet.records import Field, field_validator, model_validator


class TargetSpec(ConfigModel):
    """One constant-velocity target in the plane, state ``[x, vx, y, vy]``."""

    initial_position_m: Pair = (0.0, 0.0)
    initial_velocity_mps: Pair = (426.0, 0.0)
    accel_noise_std_mps2: Float = 0.5

    @field_validator("accel_noise_std_mps2")
    @classmethod
    def _q(cls, v: float) -> float:
        if not v >= 0:
            raise ValueError(f"must be >= 0, got {v}")
        return v


class FilterSpec(ConfigModel):
    """Filter initialisation: ``P0 = diag(P0_diag)``; the estimate is the truth plus one draw
    from ``N(0, P0)`` (``perturbed``, the default) or the truth itself (``truth``)."""

    P0_diag: Quad = (1.0e4, 1.0e2, 1.0e4, 1.0e2)
    initial_estimate: Literal["perturbed", "truth"] = "perturbed"

    @field_validator("P0_diag")
    @classmethod
    def _p0(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(d > 0 for d in v):
            raise ValueError(f"every entry must be > 0, got {list(v)}")
        return v


class DesiredSpec(ConfigModel):
    """Desired covariance from scan ``from_scan`` on: ``diag`` (4 entries) or a full ``matrix``."""

    from_scan: Int = Field(ge=1)
    diag: Quad | None = None
    matrix: Annotated[tuple[Quad, ...], Field(min_length=4, max_length=4)] | None = None

    def as_matrix(self) -> np.ndarray:
        if self.diag is not None:
            return np.diag(np.asarray(self.diag, dtype=np.float64))
        return np.asarray(self.matrix, dtype=np.float64)


class TargetDesiredSpec(DesiredSpec):
    """One entry of a target's desired-covariance schedule; ``weight`` (optional) changes the
    target's weight ``w_t`` from ``from_scan`` on (a priority change)."""

    weight: Float | None = None

    _w = field_validator("weight")(positive_or_none)


class ManoeuvreSpec(ConfigModel):
    """A truth-only manoeuvre over the steps from scan ``from_scan`` to scan ``to_scan``
    (:mod:`covnet.core.manoeuvre`): a coordinated ``turn`` at ``turn_rate_deg_s`` (counter-
    clockwise positive) or a constant ``acceleration`` ``accel_mps2`` ``[ax, ay]``.  The
    filters never know: they keep the constant-velocity model."""

    kind: Literal["turn", "acceleration"]
    from_scan: Int = Field(ge=0)
    to_scan: Int = Field(ge=1)
    turn_rate_deg_s: Float | None = None
    accel_mps2: Pair | None = None


class TargetEntry(ConfigModel):
    """One target of a many-target scenario: state ``[x, vx, y, vy]`` at time 0, its truth's
    white acceleration noise and manoeuvres, its own desired-covariance schedule and weight
    ``w_t > 0``, and optionally its own ``P0_diag`` (default ``filter.P0_diag``) and its
    filter's white acceleration ``filter_accel_noise_std_mps2`` (default: the truth's; a
    tracker expecting a manoeuvre its constant-velocity model does not have raises it)."""

    id: Ident
    initial_position_m: Pair
    initial_velocity_mps: Pair
    accel_noise_std_mps2: Float = 0.5
    filter_accel_noise_std_mps2: Float | None = None
    manoeuvres: tuple[ManoeuvreSpec, ...] = ()
    desired: tuple[TargetDesiredSpec, ...] = ()
    weight: Float = 1.0
    P0_diag: Quad | None = None
    # with surveillance: (truth only) the scans it exists at: appears_at_scan ..
    # leaves_at_scan - 1; its initial state is its state at its appearance
    appears_at_scan: Int = Field(default=1, ge=1)
    leaves_at_scan: Int | None = Field(default=None, ge=2)
    # with surveillance: known to the manager before scan 1 (a confirmed track from its cue,
    # the filter's initial estimate)
    cued: Bool = False

    _w = field_validator("weight")(_positive)

    @field_validator("accel_noise_std_mps2", "filter_accel_noise_std_mps2")
    @classmethod
    def _q(cls, v: float | None) -> float | None:
        if v is not None and not v >= 0:
            raise ValueError(f"must be >= 0, got {v}")
        return v

    @field_validator("P0_diag")
    @classmethod
    def _p0(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is not None and not all(d > 0 for d in v):
            raise ValueError(f"every entry must be > 0, got {list(v)}")
        return v


class AssociationSpec(ConfigModel):
    """How the manager uses a dwell's unlabeled returns (spec §4): ``method`` ``pda`` (the
    PDAF), ``nearest`` (the gated return nearest in Mahalanobis distance) or, with
    ``surveillance:``, ``jpda`` (returns shared by the tracks whose gates they fall in); the χ²
    gate's ``gate_probability``; the clutter window, ``± clutter_window_sigma`` standard
    deviations of the innovation around the predicted measurement.  A sensor without clutter
    (``clutter_rate: 0``) needs no association: its return, if any, is the target's."""

    method: Literal["pda", "nearest", "jpda"] = "pda"
    gate_probability: Float = 0.99
    clutter_window_sigma: Float = 6.0

    _cw = field_validator("clutter_window_sigma")(_positive)

    @field_validator("gate_probability")
    @classmethod
    def _pg(cls, v: float) -> float:
        if not 0.0 < v < 1.0:
            raise ValueError(f"must be in (0, 1), got {v}")
        return v


class OspaSpec(ConfigModel):
    """OSPA and GOSPA of the estimated target positions against the truth, per scan: cut-off
    ``cutoff_m`` (``c``) and order ``order`` (``p``)."""

    cutoff_m: Float = 1000.0
    order: Float = 2.0

    _c = field_validator("cutoff_m")(_positive)

    @field_validator("order")
    @classmethod
    def _p(cls, v: float) -> float:
        if not v >= 1.0:
            raise ValueError(f"must be >= 1, got {v}")
        return v

    @model_validator(mode="after")
    def _no_overflow(self) -> OspaSpec:
        """Every distance is cut at ``c`` and raised to ``p``, and the target set's sum of
        them must stay finite: ``c^p`` at most 1e300 (an order of 1e14 ended the run in the
        assignment's "cost matrix is infeasible")."""
        if self.order * math.log10(self.cutoff_m) > 300.0:
            raise ValueError(
                f"order: cutoff_m ** order = {self.cutoff_m:g} ** {self.order:g} overflows "
                "double precision; take a smaller order (1 or 2 are usual)"
            )
        return self


def segments(t: TargetEntry) -> list[Any]:
    """The target's manoeuvres as the core's segments (:mod:`covnet.core.manoeuvre`)."""
    from covnet.core.manoeuvre import Acceleration, Turn  # start-up: configs with targets

    out: list[Any] = []
    for m in t.manoeuvres:
        if m.kind == "turn":
            assert m.turn_rate_deg_s is not None
            out.append(Turn(m.from_scan, m.to_scan, math.radians(m.turn_rate_deg_s)))
        else:
            assert m.accel_mps2 is not None
            out.append(Acceleration(m.from_scan, m.to_scan, *m.accel_mps2))
    return out
