"""What one scan of the covariance-control engine (:mod:`covnet.covariance_control.engine`)
decides and reports, as every episode type makes them: :class:`Plan` (the decision, what the
command says) and :class:`Outcome` (what the bus and the replay compare).  Its own module so
that an episode type in another module (the surveillance one) makes them without importing
the engine."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from covnet.core.gaussian import Gaussian

__all__ = ["Outcome", "Plan"]




@dataclass(frozen=True)
class Plan:
    """Scan ``k``'s decision: the command's fields (``enabled`` sensor ids; with targets each
    one's target ``{sensor: (target id,)}`` and clutter window ``{sensor: vector}``), the
    objective ``value``, the sensors' indices ``subset``, how long deciding took, and the
    centre's own record of the decision (``detail``)."""

    k: int
    subset: tuple[int, ...]
    enabled: tuple[str, ...]
    value: float
    decision_s: float
    detail: Any
    targets: dict[str, tuple[str, ...]] | None = None
    windows: dict[str, np.ndarray] | None = None


@dataclass(frozen=True)
class Outcome:
    """What a fused scan reports: ``tracks`` (target id or None, estimate), the enabled set,
    the objective value, ``tr P`` and ``tr P_d`` (summed over targets), the sensors whose
    messages were fused, the late ones re-filtered into earlier scans (``None``: no late
    handling), and what a bounded or greedy search certified (``lower_bound``, ``gap``)."""

    k: int
    tracks: tuple[tuple[str | None, Gaussian], ...]
    enabled: tuple[str, ...]
    value: float
    trace_P: float
    trace_Pd: float
    fused: tuple[str, ...]
    refiltered: tuple[str, ...] | None
    lower_bound: float | None = None
    gap: float | None = None
    per_target: tuple[tuple[str, int], ...] | None = None  # sensors on each target
    # surveillance: each track's state (aligned with tracks) and the cells' u_c after the scan
    track_states: tuple[str, ...] | None = None
    cells: np.ndarray | None = None

    def lines(self, scans: int, n_sensors: int) -> dict[str, Any]:
        """The live view's numbers and lines of this scan (``info``, ``info_short``)."""
        k, on = self.k, len(self.enabled)
        live: dict[str, Any] = {"trace_P": self.trace_P, "trace_Pd": self.trace_Pd}
        if self.per_target is not None:
            per = "  ".join(f"{tid}:{n}" for tid, n in self.per_target)
            info = (
                f"scan {k}/{scans}  on {on}/{n_sensors} ({per})  "
                f"tr P {self.trace_P:.1f} / tr Pd {self.trace_Pd:.1f}"
            )
        else:
            info = (
                f"scan {k}/{scans}  enabled {','.join(self.enabled) or '-'}  "
                f"tr P {self.trace_P:.1f} / tr Pd {self.trace_Pd:.1f}"
            )
        short = f"{k}/{scans} {on}/{n_sensors} on  trP {self.trace_P:.0f}/{self.trace_Pd:.0f}"
        if self.lower_bound is not None and self.gap is not None:
            lb = self.lower_bound if math.isfinite(self.lower_bound) else None
            live |= {"value": self.value, "lower_bound": lb, "gap": self.gap}
            info += f"  f {self.value:.4g} (gap {100 * self.gap:.3g} %)"
            short += f"  gap {100 * self.gap:.3g}%"
        return live | {"info": info, "info_short": short}
