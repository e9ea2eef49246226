"""Records and geometry of the passive 3-sensor association problem (spec §2, §3).

Frame: flat-earth Cartesian, x east, y north, z up, lengths in km, angles in rad.

* azimuth   ``α = atan2(Δy, Δx)`` in ``(−π, π]``, counter-clockwise from +x;
* elevation ``ε = atan2(Δz, sqrt(Δx² + Δy²))`` in ``(−π/2, π/2)``;

with ``Δ = target − s_i``.  Sensor ``i`` (0-based here, 1-based in the spec) sits at ``s_i``.
A measurement is the pair ``(α, ε)``; a sensor's list is an ``(n_i, 2)`` array whose order
carries no information.  Measurement indices are 0-based in every record (the S-D tensors use
index 0 for "no measurement" and ``m + 1`` for measurement ``m``, spec §8.1: see
:mod:`covnet.core.passive.sd`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from covnet.core.gaussian import Mat, Vec

Index = NDArray[np.intp]

__all__ = [
    "AssocParams",
    "Association",
    "PassiveScan",
    "angles",
    "bearing_to_azimuth",
    "los_vectors",
    "wrap",
]


def wrap(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """Wrap angles to ``(−π, π]``: ``a − 2π ⌈(a − π) / 2π⌉``."""
    a = np.asarray(a, dtype=np.float64)
    return a - 2.0 * np.pi * np.ceil((a - np.pi) / (2.0 * np.pi))


def bearing_to_azimuth(beta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Compass bearing ``β`` (clockwise from north) to azimuth: ``α = π/2 − β`` (so
    ``cot α = tan β``), wrapped to ``(−π, π]``."""
    return wrap(0.5 * np.pi - np.asarray(beta, dtype=np.float64))


def angles(sensors: Mat, points: Mat) -> NDArray[np.float64]:
    """Noise-free ``(α, ε)`` of ``points`` ``(..., 3)`` seen from ``sensors`` ``(S, 3)``.

    Returns ``(..., S, 2)``: ``α = atan2(Δy, Δx)``, ``ε = atan2(Δz, sqrt(Δx² + Δy²))``,
    ``Δ = point − s``.
    """
    d = np.asarray(points, dtype=np.float64)[..., None, :] - np.asarray(sensors, dtype=np.float64)
    az = np.arctan2(d[..., 1], d[..., 0])
    el = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    return np.stack([az, el], axis=-1)


def los_vectors(az: NDArray[np.float64], el: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit line-of-sight vectors ``u = (cos ε cos α, cos ε sin α, sin ε)``, shape ``(..., 3)``."""
    ce = np.cos(el)
    return np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=-1)


@dataclass(frozen=True, slots=True)
class PassiveScan:
    """One synchronous scan: sensor positions ``(3, 3)`` km and three measurement lists.

    ``z[i]`` is sensor ``i``'s ``(n_i, 2)`` array of ``(α, ε)`` in rad; ``n_i`` may be 0.
    Shapes are checked once, here.
    """

    sensors: Mat
    z: tuple[Mat, Mat, Mat]

    def __post_init__(self) -> None:
        s = np.asarray(self.sensors, dtype=np.float64)
        if s.shape != (3, 3):
            raise ValueError(f"PassiveScan.sensors must be (3, 3), got {s.shape}")
        if len(self.z) != 3:
            raise ValueError(f"PassiveScan.z must hold 3 lists, got {len(self.z)}")
        zs = []
        for i, zi in enumerate(self.z):
            a = np.asarray(zi, dtype=np.float64)
            if a.size == 0:
                a = a.reshape(0, 2)
            if a.ndim != 2 or a.shape[1] != 2:
                raise ValueError(f"PassiveScan.z[{i}] must be (n, 2), got {a.shape}")
            zs.append(a)
        object.__setattr__(self, "sensors", s)
        object.__setattr__(self, "z", tuple(zs))

    @property
    def counts(self) -> tuple[int, int, int]:
        n1, n2, n3 = (int(zi.shape[0]) for zi in self.z)
        return n1, n2, n3


@dataclass(frozen=True, slots=True)
class AssocParams:
    """Everything an association method may need besides the scan.

    * ``sigma_azimuth``, ``sigma_elevation``: per-sensor noise std ``(3,)`` in rad (σ_α, σ_ε;
      kept separate, spec §2).
    * ``gate``: the cot tests keep ``|stat| ≤ gate · σ`` (spec: 3).
    * ``cot_cost``: ``"raw"`` ``Ψ = (1/6) Σ |e_ab|`` (km, the paper's) or ``"normalised"``
      ``Σ |e_ab| / σ_ab``.
    * ``azimuth_form``: ``"cot"`` (``F``, spec §4) or ``"sine"`` (``D = F Π sin α_i``, safe when a
      line of sight is parallel to the x axis).
    * ``p_detect`` (P_D) and ``clutter_density`` (β, rad⁻²): the S-D likelihood ratio (§8.2).
      ``p_detect == 1`` and ``clutter_density == 0`` select the clean 3-D assignment (complete
      triples only, ``C = χ²/2``).
    * ``target_density``: λ_b in km⁻³ for the target-prior term τ; ``0`` drops τ (the
      literature cost).
    * ``gn_steps``: Gauss-Newton steps after the linear least-squares start (§8.2: 3).
    * ``lr_*``: Lagrangian relaxation (§8.3); ``milp_time_limit_s``: HiGHS time limit (§8.4).
    """

    sigma_azimuth: Vec
    sigma_elevation: Vec
    gate: float = 3.0
    cot_cost: Literal["raw", "normalised"] = "raw"
    azimuth_form: Literal["cot", "sine"] = "cot"
    p_detect: float = 1.0
    clutter_density: float = 0.0
    target_density: float = 0.025
    gn_steps: int = 3
    lr_max_iter: int = 100
    lr_rel_gap: float = 1e-3
    lr_step: float = 1.0
    lr_halve_after: int = 5
    milp_time_limit_s: float = 10.0

    def __post_init__(self) -> None:
        for name in ("sigma_azimuth", "sigma_elevation"):
            v = np.broadcast_to(np.asarray(getattr(self, name), dtype=np.float64), (3,)).copy()
            if not np.all(v > 0) or not np.all(np.isfinite(v)):
                raise ValueError(f"AssocParams.{name} must be > 0 and finite, got {v}")
            v.flags.writeable = False
            object.__setattr__(self, name, v)
        if not 0.0 < self.p_detect <= 1.0:
            raise ValueError(f"AssocParams.p_detect must be in (0, 1], got {self.p_detect}")
        if self.clutter_density < 0 or self.target_density < 0:
            raise ValueError("AssocParams: clutter_density and target_density must be >= 0")
        if self.p_detect < 1.0 and self.clutter_density == 0.0:
            raise ValueError(
                "AssocParams: p_detect < 1 needs clutter_density > 0 (the S-D cost compares "
                "each tuple with 'all measurements false')"
            )
        if self.cot_cost not in ("raw", "normalised"):
            raise ValueError(f"AssocParams.cot_cost: unknown {self.cot_cost!r}")
        if self.azimuth_form not in ("cot", "sine"):
            raise ValueError(f"AssocParams.azimuth_form: unknown {self.azimuth_form!r}")

    @property
    def complete_only(self) -> bool:
        """Clean case of §8.2: only complete triples, ``C = χ²/2``."""
        return self.p_detect >= 1.0 and self.clutter_density == 0.0

    @classmethod
    def isotropic(cls, sigma: float, **kw: Any) -> AssocParams:
        """σ_α = σ_ε = ``sigma`` (rad) on every sensor, as in the paper."""
        s = np.full(3, float(sigma))
        return cls(sigma_azimuth=s, sigma_elevation=s, **kw)


@dataclass(frozen=True, slots=True)
class Association:
    """What a method returns.

    * ``triples`` ``(m, 3)``: the complete triples (one measurement index per sensor): the set Z
      scored by §9;
    * ``tuples`` ``(q, 3)``: every chosen tuple with at least two real measurements, ``-1`` where
      a sensor contributes none (S-D methods; equals ``triples`` for the cot method);
    * ``cost``: the objective of the chosen set (Σ C for S-D methods, Σ Ψ for cot);
    * ``status`` / ``message``: 0 / "ok" when the method finished normally, else the solver's;
    * ``info``: method-specific numbers (candidate counts, bounds, iterations, ...).
    """

    triples: Index
    tuples: Index
    cost: float
    status: int = 0
    message: str = "ok"
    info: Mapping[str, Any] = field(default_factory=dict)

    @staticmethod
    def empty(status: int = 0, message: str = "ok", **info: Any) -> Association:
        e = np.zeros((0, 3), dtype=np.intp)
        return Association(e, e, 0.0, status, message, info)
