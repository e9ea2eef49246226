"""Manoeuvring ground truth: constant velocity with coordinated-turn and acceleration segments.

State ``x = [x, vx, y, vy]``, period ``T``; row ``k − 1`` of the result is the state at scan
``k`` (time ``k T``), ``x0`` the state at time 0, as in
:func:`covnet.core.truth.linear_gaussian_trajectory`.  Every step is

    x(k+1) = F_k x(k) + G (a_k + w(k)),      w(k) ~ N(0, σ_a² I)   (the paper's white acceleration)

with ``G = blockdiag([T²/2, T]ᵀ)`` and, per step:

- constant velocity (default): ``F_k = F_CV``, ``a_k = 0``;
- a :class:`Turn` with rate ``ω`` (rad/s, counter-clockwise positive): ``a_k = 0`` and the
  exact discretisation of the coordinated turn (Bar-Shalom, Li & Kirubarajan 2001, ch. 11)::

      F_CT(ω) = [[1, sin ωT/ω,       0, −(1 − cos ωT)/ω],
                 [0, cos ωT,         0, −sin ωT        ],
                 [0, (1 − cos ωT)/ω, 1, sin ωT/ω       ],
                 [0, sin ωT,         0, cos ωT         ]]

  (``ω = 0`` is ``F_CV`` exactly; it preserves the speed and turns the velocity by ``ωT``);
- an :class:`Acceleration` ``(ax, ay)`` m/s²: ``F_k = F_CV``, ``a_k = (ax, ay)`` (exact for a
  constant acceleration over the step).

A segment ``[k0, k1)`` governs the steps from scan ``k0`` to scan ``k1`` (``x(k0) → … →
x(k1)``; ``0 ≤ k0 < k1 ≤ n_scans``); segments may not overlap.  So a turn of ``θ`` rad between
scans 40 and 60 has ``ω = θ / (20 T)``.

All process noise is drawn in one call, ``σ_a · rng.standard_normal((n_scans, 2))``, exactly as
:func:`covnet.core.truth.linear_gaussian_trajectory` draws it: without segments the two
functions give the same trajectory for the same generator state.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from covnet.core.gaussian import Mat
from covnet.core.motion import cv_transition, dwna_noise_gain

__all__ = [
    "Acceleration",
    "Segment",
    "Turn",
    "ct_transition",
    "manoeuvring_trajectory",
]


def _check_span(k0: int, k1: int) -> None:
    if int(k0) != k0 or int(k1) != k1 or not (0 <= k0 < k1):
        raise ValueError(f"segment scans: expected integers 0 <= k0 < k1, got k0={k0}, k1={k1}")


@dataclass(frozen=True, slots=True)
class Turn:
    """A coordinated turn at ``omega`` rad/s (counter-clockwise positive) from scan ``k0`` to
    scan ``k1``."""

    k0: int
    k1: int
    omega: float

    def __post_init__(self) -> None:
        _check_span(self.k0, self.k1)
        if not math.isfinite(float(self.omega)):
            raise ValueError(f"omega: expected a finite turn rate (rad/s), got {self.omega!r}")


@dataclass(frozen=True, slots=True)
class Acceleration:
    """A constant acceleration ``(ax, ay)`` m/s² from scan ``k0`` to scan ``k1``."""

    k0: int
    k1: int
    ax: float
    ay: float

    def __post_init__(self) -> None:
        _check_span(self.k0, self.k1)
        if not (math.isfinite(float(self.ax)) and math.isfinite(float(self.ay))):
            raise ValueError(f"ax, ay: expected finite accelerations, got {self.ax!r}, {self.ay!r}")


Segment = Turn | Acceleration


def ct_transition(omega: float, T: float) -> Mat:
    """``F_CT(ω)`` of the module docstring; ``ω = 0`` returns ``F_CV`` exactly.

    ``(1 − cos ωT)/ω`` is evaluated as ``2 sin²(ωT/2)/ω`` (no cancellation for small ``ωT``).
    """
    w = float(omega)
    if w == 0.0:
        return cv_transition(T)
    wT = w * T
    c, s = math.cos(wT), math.sin(wT)
    a = s / w  # sin(ωT)/ω
    b = 2.0 * math.sin(0.5 * wT) ** 2 / w  # (1 − cos ωT)/ω
    return np.array(
        [
            [1.0, a, 0.0, -b],
            [0.0, c, 0.0, -s],
            [0.0, b, 1.0, a],
            [0.0, s, 0.0, c],
        ]
    )


def manoeuvring_trajectory(
    x0: ArrayLike,
    T: float,
    sigma_a: float,
    n_scans: int,
    rng: np.random.Generator,
    segments: Sequence[Segment] = (),
) -> Mat:
    """States at scans ``1..n_scans``, ``(n_scans, 4)`` (module docstring for the model)."""
    x = np.asarray(x0, dtype=np.float64)
    if x.shape != (4,):
        raise ValueError(f"x0: expected the state [x, vx, y, vy] of shape (4,), got {x.shape}")
    if not (math.isfinite(float(T)) and T > 0.0):
        raise ValueError(f"T: expected a period > 0, got {T!r}")
    if not (math.isfinite(float(sigma_a)) and sigma_a >= 0.0):
        raise ValueError(f"sigma_a: expected a finite number >= 0, got {sigma_a!r}")
    if int(n_scans) != n_scans or n_scans < 0:
        raise ValueError(f"n_scans: expected an integer >= 0, got {n_scans!r}")
    n = int(n_scans)
    F_cv = cv_transition(T)
    G = dwna_noise_gain(T)
    # per step k (x(k) -> x(k+1)): transition and deterministic acceleration
    F_of: list[Mat] = [F_cv] * n
    acc: list[tuple[float, float] | None] = [None] * n
    owner: list[int | None] = [None] * n
    for i, seg in enumerate(segments):
        if not isinstance(seg, Turn | Acceleration):
            raise ValueError(f"segments[{i}]: expected a Turn or an Acceleration, got {seg!r}")
        if seg.k1 > n:
            raise ValueError(f"segments[{i}]: k1 = {seg.k1} is beyond n_scans = {n}")
        F_seg = ct_transition(seg.omega, T) if isinstance(seg, Turn) else F_cv
        for k in range(seg.k0, seg.k1):
            if owner[k] is not None:
                raise ValueError(f"segments[{i}] overlaps segments[{owner[k]}] at step {k}")
            owner[k] = i
            F_of[k] = F_seg
            if isinstance(seg, Acceleration):
                acc[k] = (float(seg.ax), float(seg.ay))
    w = sigma_a * rng.standard_normal((n, G.shape[1]))
    out = np.empty((n, 4))
    for k in range(n):
        a = acc[k]
        x = F_of[k] @ x + G @ (w[k] if a is None else w[k] + np.asarray(a))
        out[k] = x
    return out
