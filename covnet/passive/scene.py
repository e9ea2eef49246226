"""Scenes of the passive association study (spec §2 "Paper scenario", §3): the sensor layout,
the two target formations, missed detections and clutter, drawn from per-(seed, trial)
generators.

Common random numbers: a scan is drawn from ``numpy.random.default_rng([seed, trial])`` and
the draws come in a fixed order whose shapes do not depend on σ, d or the formation, so grid
cells see the same random stream:

1. ``(3, N)`` detection uniforms (detected when ``u < P_D``);
2. ``(3, N, 2)`` standard normals (``α + σ_α n₀``, ``ε + σ_ε n₁``);
3. ``(3, N)`` uniform sort keys (the shuffle of the lists);
4. ``(3,)`` uniforms turned into Poisson(λ_fa) clutter counts by the inverse CDF;
5. per sensor: ``(N_fa, 2)`` uniforms in the clutter window and ``N_fa`` sort keys.

Clutter (spec §3 [choice]): ``N_fa ~ Poisson(λ_fa)`` per sensor and scan, each false return
uniform in a window ``W`` (azimuth × elevation, rad) centred on the true direction from that
sensor to the formation centroid; the S-D costs use the density ``β = λ_fa / |W|``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.stats import poisson

from covnet.core.passive.model import AssocParams, Index, PassiveScan, angles, wrap

__all__ = [
    "FORMATIONS",
    "PAPER_SENSORS",
    "Scene",
    "SceneModel",
    "draw",
    "formation",
]

F64 = NDArray[np.float64]
Formation = Literal["horizontal", "cross"]
FORMATIONS: tuple[Formation, ...] = ("horizontal", "cross")

#: s1 = (0, 10, 0), s2 = (10, 0, 0), s3 = (0, 0, 0) km (s3 at the right-angle corner)
PAPER_SENSORS: F64 = np.array([[0.0, 10.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
PAPER_SENSORS.flags.writeable = False

_OFFSETS: dict[str, F64] = {
    # T1…T5 as multiples of d around the centre (spec §2)
    "horizontal": np.array([[0, 0], [1, 0], [-1, 0], [2, 0], [-2, 0]], dtype=np.float64),
    "cross": np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.float64),
}


def formation(
    name: str, d_km: float, center_km: tuple[float, float] = (5.0, 5.0), altitude_km: float = 1.0
) -> F64:
    """The five targets ``(5, 3)`` of a formation, paper numbering T1…T5 (rows 0…4).

    horizontal: T1 (c), T2 (c + d x̂), T3 (c − d x̂), T4 (c + 2d x̂), T5 (c − 2d x̂);
    cross: T1 (c), T2 (c + d x̂), T3 (c − d x̂), T4 (c + d ŷ), T5 (c − d ŷ); all at the altitude.
    """
    try:
        off = _OFFSETS[name]
    except KeyError:
        raise ValueError(f"unknown formation {name!r}; choose from {sorted(_OFFSETS)}") from None
    xy = np.asarray(center_km, dtype=np.float64) + d_km * off
    return np.column_stack([xy, np.full(len(xy), float(altitude_km))])


@dataclass(frozen=True, slots=True)
class SceneModel:
    """What a scan is drawn from: sensors ``(3, 3)`` km, targets ``(N, 3)`` km, per-sensor noise
    std (rad), ``P_D``, the clutter rate ``λ_fa`` per sensor and scan, and the clutter window
    ``(width_azimuth, width_elevation)`` rad."""

    sensors: F64
    targets: F64
    sigma_azimuth: F64
    sigma_elevation: F64
    p_detect: float = 1.0
    clutter_rate: float = 0.0
    window_rad: tuple[float, float] = (0.1, 0.1)

    @property
    def clutter_density(self) -> float:
        """``β = λ_fa / |W|`` in rad⁻²."""
        return self.clutter_rate / (self.window_rad[0] * self.window_rad[1])

    def params(self, **kw: object) -> AssocParams:
        """:class:`AssocParams` matching this model (noise, ``P_D``, ``β``) plus ``kw``."""
        return AssocParams(
            sigma_azimuth=self.sigma_azimuth,
            sigma_elevation=self.sigma_elevation,
            p_detect=self.p_detect,
            clutter_density=self.clutter_density,
            **kw,  # type: ignore[arg-type]
        )


@dataclass(frozen=True, slots=True)
class Scene:
    """One drawn scan with its truth (for scoring only).

    ``labels[s]`` ``(n_s,)``: the target index of each measurement of sensor ``s``, ``-1`` for
    clutter.  ``truth`` ``(g, 3)``: for every target detected by all three sensors
    (``truth_targets`` ``(g,)``, ascending), the triple of its measurement indices: the set G of
    §9.
    """

    scan: PassiveScan
    labels: tuple[Index, Index, Index]
    targets: F64
    truth: Index
    truth_targets: Index


def draw(model: SceneModel, seed: int, trial: int) -> Scene:
    """Draw scan ``trial`` of run ``seed`` (see the module docstring for the stream layout)."""
    rng = np.random.default_rng([seed, trial])
    targets = np.asarray(model.targets, dtype=np.float64)
    N = targets.shape[0]
    det_u = rng.random((3, N))
    noise = rng.standard_normal((3, N, 2))
    keys_t = rng.random((3, N))
    count_u = rng.random(3)
    true_ang = angles(model.sensors, targets)  # (N, 3, 2)
    centre = angles(model.sensors, targets.mean(axis=0))  # (3, 2)
    counts = poisson.ppf(count_u, model.clutter_rate).astype(np.intp)
    detected = det_u < model.p_detect
    z: list[F64] = []
    labels: list[Index] = []
    where = np.full((3, N), -1, dtype=np.intp)
    for s in range(3):
        m = detected[s]
        az = wrap(true_ang[m, s, 0] + model.sigma_azimuth[s] * noise[s, m, 0])
        el = true_ang[m, s, 1] + model.sigma_elevation[s] * noise[s, m, 1]
        u = rng.random((int(counts[s]), 2))
        keys_c = rng.random(int(counts[s]))
        caz = wrap(centre[s, 0] + (u[:, 0] - 0.5) * model.window_rad[0])
        cel = centre[s, 1] + (u[:, 1] - 0.5) * model.window_rad[1]
        zs = np.concatenate([np.column_stack([az, el]), np.column_stack([caz, cel])])
        lab = np.concatenate([np.flatnonzero(m), np.full(int(counts[s]), -1)]).astype(np.intp)
        order = np.argsort(np.concatenate([keys_t[s, m], keys_c]), kind="stable")
        zs, lab = zs[order], lab[order]
        pos = np.flatnonzero(lab >= 0)
        where[s, lab[pos]] = pos
        z.append(zs)
        labels.append(lab)
    seen = np.flatnonzero(detected.all(axis=0))
    truth = where[:, seen].T.copy()
    scan = PassiveScan(np.asarray(model.sensors, dtype=np.float64), (z[0], z[1], z[2]))
    return Scene(scan, (labels[0], labels[1], labels[2]), targets, truth, seen.astype(np.intp))


def score(truth: Index, triples: Index) -> tuple[int, int, int, bool]:
    """``(|Z ∩ G|, |G|, |Z|, Z == G)`` for truth triples G and output triples Z (§9)."""
    g = {tuple(map(int, t)) for t in np.asarray(truth).reshape(-1, 3)}
    zz = [tuple(map(int, t)) for t in np.asarray(triples).reshape(-1, 3)]
    zs = set(zz)
    hit = len(g & zs)
    return hit, len(g), len(zz), zs == g and len(zz) == len(zs)
