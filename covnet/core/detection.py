"""Simulation of one dwell: the target's return (if detected), Poisson clutter, shuffled.

A dwell of sensor ``model`` on a target with true state ``x`` (spec multitarget.md §2):

- **window**: a box in measurement space around the predicted measurement ``ẑ = h(x̂⁻)``,
  ``ẑ ± n_σ √diag S`` (``S`` the innovation covariance, ``n_σ = clutter_window_sigma``, e.g.
  6); an angle component's half-width is capped at ``π`` (the whole circle).  Its volume is
  ``V = Π_i 2 a_i`` (``a_i`` the half-widths), and the clutter density the PDA needs is
  ``λ = clutter_rate / V``;
- **target**: detected with probability ``pd`` when ``model.in_coverage(x)``; its return is
  ``h(x) + v``, ``v ~ N(0, R)`` (``v = L e``, ``L`` the lower Cholesky factor of ``R``), angles
  wrapped.  It is kept wherever it falls (the gate, not the window, decides what is used);
- **clutter**: ``m_c ~ Poisson(clutter_rate)`` false returns, uniform in the window, angles
  wrapped;
- the returns are shuffled: the sensor does not say which is which.

Draws, always in this order, from the one generator given: the detection uniform, the ``dim_z``
noise normals, the clutter count, the clutter uniforms ``(m_c, dim_z)``, the permutation.  The
first two are drawn even when the target is out of coverage or missed, so with the same
generator a change of ``pd`` or of coverage changes only whether the target is reported, never
its noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from covnet.core.gaussian import Mat, Vec
from covnet.core.sensor_models import SensorModel, innovation, wrap_angle

__all__ = ["ClutterWindow", "Dwell", "clutter_window", "simulate_dwell"]

BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class ClutterWindow:
    """A box ``center ± half_width`` in measurement space; ``angle_mask`` marks the angle
    components (their half-width ≤ π, the box wraps around)."""

    center: Vec
    half_width: Vec
    angle_mask: tuple[bool, ...]

    def __post_init__(self) -> None:
        c = np.asarray(self.center, dtype=np.float64)
        a = np.asarray(self.half_width, dtype=np.float64)
        if c.ndim != 1 or a.shape != c.shape or len(self.angle_mask) != c.shape[0]:
            raise ValueError(
                "ClutterWindow: center, half_width and angle_mask must be 1-D of one length, got "
                f"{c.shape}, {a.shape}, {len(self.angle_mask)}"
            )
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(a)) and np.all(a > 0.0)):
            raise ValueError("ClutterWindow: center must be finite and half_width finite and > 0")
        am = np.asarray(self.angle_mask, dtype=bool)
        if np.any(a[am] > math.pi):
            raise ValueError("ClutterWindow: an angle component's half_width must be <= pi")
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "half_width", a)
        object.__setattr__(self, "angle_mask", tuple(bool(b) for b in am))

    @property
    def volume(self) -> float:
        """``V = Π_i 2 a_i``."""
        return float(np.prod(2.0 * self.half_width))

    def contains(self, z: ArrayLike) -> BoolArray:
        """True for the rows of ``z`` ``(..., dim_z)`` inside the box (angles compared wrapped)."""
        d = innovation(z, self.center, self.angle_mask)
        return np.asarray(np.all(np.abs(d) <= self.half_width, axis=-1))


def clutter_window(
    model: SensorModel, x_pred: ArrayLike, S: ArrayLike, n_sigma: float = 6.0
) -> ClutterWindow:
    """The box ``h(x̂⁻) ± n_σ √diag S`` (angle half-widths capped at ``π``)."""
    ns = float(n_sigma)
    if not (math.isfinite(ns) and ns > 0.0):
        raise ValueError(f"clutter_window_sigma: expected a finite number > 0, got {n_sigma!r}")
    SS = np.asarray(S, dtype=np.float64)
    dz = model.dim_z
    if SS.shape != (dz, dz):
        raise ValueError(f"S: expected the ({dz}, {dz}) innovation covariance, got {SS.shape}")
    diag = np.diagonal(SS)
    if not np.all(diag > 0.0):
        raise ValueError("S: expected a positive diagonal")
    xp = np.asarray(x_pred, dtype=np.float64)
    if xp.ndim != 1:
        raise ValueError(f"x_pred: expected one predicted state (4,), got shape {xp.shape}")
    a = ns * np.sqrt(diag)
    am = model.angle_mask
    a = np.where(am, np.minimum(a, math.pi), a)
    return ClutterWindow(model.h(xp), a, model.angle_components)


@dataclass(frozen=True, slots=True)
class Dwell:
    """The returns of one dwell: ``z`` ``(m, dim_z)`` shuffled; the ``window`` the clutter was
    drawn in and ``clutter_density = clutter_rate / window.volume`` (the PDA's ``λ``);
    ``truth_row`` the row that came from the target (``None`` if not detected) -- simulation
    truth for scoring, never for the tracker."""

    z: Mat
    window: ClutterWindow
    clutter_density: float
    truth_row: int | None

    @property
    def n_returns(self) -> int:
        return int(self.z.shape[0])


def simulate_dwell(
    model: SensorModel,
    x_true: ArrayLike,
    x_pred: ArrayLike | None,
    S: ArrayLike | None,
    rng: np.random.Generator,
    clutter_window_sigma: float = 6.0,
    window: ClutterWindow | None = None,
) -> Dwell:
    """Simulate one dwell (module docstring): target return with probability ``pd`` inside
    coverage, ``Poisson(clutter_rate)`` clutter in the window, all shuffled.

    The window is :func:`clutter_window` ``(model, x_pred, S, clutter_window_sigma)``, unless
    ``window`` is given (then ``x_pred`` and ``S`` may be ``None``).
    """
    xt = np.asarray(x_true, dtype=np.float64)
    if xt.ndim != 1:
        raise ValueError(f"x_true: expected one true state (4,), got shape {xt.shape}")
    if window is None:
        if x_pred is None or S is None:
            raise ValueError("x_pred, S: both needed when no window is given")
        window = clutter_window(model, x_pred, S, clutter_window_sigma)
    dz = model.dim_z
    if window.center.shape != (dz,):
        raise ValueError(f"window: expected a {dz}-dimensional window, got {window.center.shape}")
    am = np.asarray(model.angle_components, dtype=bool)
    L = model.L
    # fixed draw order (module docstring)
    u_detect = rng.random()
    e = rng.standard_normal(dz)
    n_clutter = int(rng.poisson(model.clutter_rate))
    U = rng.random((n_clutter, dz))
    detected = bool(model.in_coverage(xt)) and u_detect < model.pd
    clutter = window.center + (2.0 * U - 1.0) * window.half_width
    rows = [clutter]
    if detected:
        rows.insert(0, (model.h(xt) + L @ e)[None, :])
    z = np.concatenate(rows, axis=0)
    if am.any():
        z = np.where(am, wrap_angle(z), z)
    perm = rng.permutation(z.shape[0])
    z = z[perm]
    truth_row = int(np.flatnonzero(perm == 0)[0]) if detected else None
    return Dwell(z, window, model.clutter_rate / window.volume, truth_row)
