"""S-D (here 3-D) assignment: maximum-likelihood triangulation, tuple costs, greedy (spec §8).

Tuple indexing (§8.1): sensor ``s`` contributes index ``i_s ∈ {0, …, n_s}``; 0 is the dummy
("no measurement from this sensor") and measurement ``m`` is index ``m + 1``.  The costs of all
tuples sit in one dense tensor ``C`` of shape ``(n1+1, n2+1, n3+1)``; ``C[0, 0, 0]`` is unused
(0), ``+inf`` marks a tuple that is not allowed (or gated).

Cost of a tuple (§8.2), with ``x̂`` the ML position from its real measurements and
``χ² = Σ_{s detected} [wrap(α_s − α_s(x̂))²/σ_α² + (ε_s − ε_s(x̂))²/σ_ε²]``:

* clean case (``P_D = 1``, no clutter): complete triples only, ``C = χ²/2``;
* clutter case: ``C = χ²/2 + Σ_det κ_s + Σ_miss μ + τ``, ``κ_s = ln(β 2π σ_α,s σ_ε,s / P_D)``,
  ``μ = −ln(1 − P_D)``, ``τ = −ln λ_b − (3/2) ln 2π + ½ ln det(Jᵀ R⁻¹ J)`` (``τ = 0`` when
  ``λ_b = 0``: the literature cost); singletons cost 0 and a tuple with ``C > 0`` is gated
  (``+inf``): its singletons dominate it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from covnet.core.gaussian import Mat, Vec
from covnet.core.passive.model import (
    Association,
    AssocParams,
    Index,
    PassiveScan,
    los_vectors,
    wrap,
)

__all__ = [
    "SDCosts",
    "Triangulation",
    "association_from_tuples",
    "greedy",
    "sd_costs",
    "solve_greedy",
    "triangulate",
]

F64 = NDArray[np.float64]
#: determinant of a 3×3 normal matrix below which the geometry is degenerate (parallel LOS)
DET_EPS = 1e-12


@dataclass(frozen=True, slots=True)
class Triangulation:
    """ML positions ``x`` ``(M, 3)`` km, their ``χ²`` ``(M,)``, ``logdet = ln det(Jᵀ R⁻¹ J)``
    at ``x`` ``(M,)``, and ``ok`` ``(M,)``: False where the geometry is degenerate."""

    x: F64
    chi2: F64
    logdet: F64
    ok: NDArray[np.bool_]


def _normal_eq(sensors: Mat, x: F64, az: F64, el: F64, wa: F64, we: F64) -> tuple[F64, F64, F64]:
    """``χ²``, ``H = Jᵀ R⁻¹ J`` and ``g = Jᵀ R⁻¹ r`` at positions ``x`` ``(M, 3)``.

    ``ρ² = Δx² + Δy²``, ``R² = ρ² + Δz²``; ``∂α/∂x = (−Δy/ρ², Δx/ρ², 0)``,
    ``∂ε/∂x = (−Δx Δz/(R² ρ), −Δy Δz/(R² ρ), ρ/R²)``; residuals ``r_α = wrap(α − α(x))``,
    ``r_ε = ε − ε(x)``; weights ``wa = w/σ_α²``, ``we = w/σ_ε²`` (``w = 0`` for a missing sensor).
    """
    d = x[:, None, :] - sensors[None, :, :]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    rho2 = np.maximum(dx * dx + dy * dy, 1e-18)
    rho = np.sqrt(rho2)
    R2 = rho2 + dz * dz
    q = dz / (R2 * rho)
    # rows: 3 azimuths then 3 elevations; J (M, 6, 3), residuals r (M, 6), weights W (M, 6)
    J = np.zeros((x.shape[0], 6, 3))
    J[:, :3, 0] = -dy / rho2
    J[:, :3, 1] = dx / rho2
    J[:, 3:, 0] = -dx * q
    J[:, 3:, 1] = -dy * q
    J[:, 3:, 2] = rho / R2
    r = np.concatenate([wrap(az - np.arctan2(dy, dx)), el - np.arctan2(dz, rho)], axis=1)
    W = np.concatenate([wa, we], axis=1)
    JtW = np.swapaxes(J, 1, 2) * W[:, None, :]
    chi2 = (W * r * r).sum(axis=1)
    return chi2, JtW @ J, (JtW @ r[..., None])[..., 0]


def _solve3(A: F64, b: F64) -> tuple[F64, NDArray[np.bool_]]:
    """Batched ``A x = b`` for ``(M, 3, 3)``; rows with ``|det A| < DET_EPS`` get ``x = 0`` and
    ``ok = False``."""
    ok = np.abs(np.linalg.det(A)) >= DET_EPS
    A = np.where(ok[:, None, None], A, np.eye(3))
    x = np.linalg.solve(A, b[..., None])[..., 0]
    return np.where(ok[:, None], x, 0.0), ok


def triangulate(
    sensors: Mat,
    az: F64,
    el: F64,
    detected: NDArray[np.bool_],
    sigma_azimuth: Vec,
    sigma_elevation: Vec,
    steps: int = 3,
) -> Triangulation:
    """Maximum-likelihood positions of ``M`` tuples from their detected angles.

    ``az``, ``el``, ``detected``: ``(M, 3)`` (values where not detected are ignored).  Start
    from the linear least-squares closest point to the LOS lines,
    ``Σ_s (I − u_s u_sᵀ) x = Σ_s (I − u_s u_sᵀ) s_s``, then run ``steps`` Gauss-Newton steps
    ``x ← x + (Jᵀ R⁻¹ J)⁻¹ Jᵀ R⁻¹ r`` on the angle residuals and keep the iterate with the
    smallest χ² (spec §8.2).
    """
    sensors = np.asarray(sensors, dtype=np.float64)
    w = np.asarray(detected, dtype=np.float64)
    u = los_vectors(az, el)
    ut_w = np.swapaxes(u, 1, 2) * w[:, None, :]  # (M, 3, S)
    A = w.sum(axis=1)[:, None, None] * np.eye(3) - ut_w @ u
    us = (u * sensors).sum(axis=2)  # u_s · s_s
    b = w @ sensors - (ut_w @ us[..., None])[..., 0]
    x, ok = _solve3(A, b)
    wa = w / np.asarray(sigma_azimuth) ** 2
    we = w / np.asarray(sigma_elevation) ** 2
    best_chi2, best_H, g = _normal_eq(sensors, x, az, el, wa, we)
    best_x, H = x, best_H
    for k in range(steps + 1):
        if k > 0:
            chi2, H, g = _normal_eq(sensors, x, az, el, wa, we)
            better = chi2 < best_chi2
            best_x = np.where(better[:, None], x, best_x)
            best_chi2 = np.where(better, chi2, best_chi2)
            best_H = np.where(better[:, None, None], H, best_H)
        if k < steps:
            dx, ok_k = _solve3(H, g)
            ok &= ok_k
            x = x + dx
    sign, logdet = np.linalg.slogdet(best_H)
    ok &= (sign > 0) & np.isfinite(best_chi2)
    return Triangulation(best_x, best_chi2, np.where(ok, logdet, 0.0), ok)


@dataclass(frozen=True, slots=True)
class SDCosts:
    """The cost tensor ``C`` ``(n1+1, n2+1, n3+1)`` of every tuple (dummy index 0), whether
    only complete triples are allowed, and ``n_tuples``: how many tuples were triangulated."""

    C: F64
    complete_only: bool
    n_tuples: int = 0

    @property
    def shape(self) -> tuple[int, int, int]:
        a, b, c = self.C.shape
        return a, b, c


def sd_costs(scan: PassiveScan, params: AssocParams) -> SDCosts:
    """The tuple costs of §8.2 (see the module docstring), triangulating every tuple whose
    structural cost is finite (in the clean case: the complete triples only)."""
    n1, n2, n3 = scan.counts
    complete = params.complete_only
    shape = (n1 + 1, n2 + 1, n3 + 1)
    C = np.full(shape, np.inf)
    C[0, 0, 0] = 0.0
    pd = params.p_detect
    mu = math.inf if pd >= 1.0 else -math.log1p(-pd)
    if not complete:
        C[1:, 0, 0] = 0.0
        C[0, 1:, 0] = 0.0
        C[0, 0, 1:] = 0.0
    idx = np.indices(shape).reshape(3, -1).T
    nreal = (idx > 0).sum(axis=1)
    need = 3 if (complete or math.isinf(mu)) else 2
    idx = idx[nreal >= need]
    if idx.shape[0] == 0:
        return SDCosts(C, complete, 0)
    det = idx > 0
    az = np.empty(idx.shape)
    el = np.empty(idx.shape)
    for s, zs in enumerate(scan.z):
        zpad = np.vstack([np.zeros((1, 2)), zs])
        az[:, s] = zpad[idx[:, s], 0]
        el[:, s] = zpad[idx[:, s], 1]
    tri = triangulate(
        scan.sensors, az, el, det, params.sigma_azimuth, params.sigma_elevation, params.gn_steps
    )
    cost = 0.5 * tri.chi2
    if not complete:
        kappa = np.log(
            params.clutter_density
            * 2.0
            * np.pi
            * params.sigma_azimuth
            * params.sigma_elevation
            / pd
        )
        cost = cost + det.astype(np.float64) @ kappa
        if need == 2:  # missing sensors (mu is finite here)
            cost = cost + (~det).sum(axis=1) * mu
        if params.target_density > 0:
            tau = -math.log(params.target_density) - 1.5 * math.log(2.0 * math.pi)
            cost = cost + tau + 0.5 * tri.logdet
        cost = np.where(cost > 0, np.inf, cost)
    cost = np.where(tri.ok, cost, np.inf)
    C[idx[:, 0], idx[:, 1], idx[:, 2]] = cost
    return SDCosts(C, complete, int(idx.shape[0]))


def association_from_tuples(
    costs: SDCosts, tuples: Index, status: int = 0, message: str = "ok", **info: object
) -> Association:
    """An :class:`Association` from chosen S-D tuples ``(q, 3)`` in dummy indexing (0 = none):
    ``triples`` are the complete ones, ``tuples`` those with two or more real measurements,
    both in 0-based measurement indices (``-1`` = none); ``cost = Σ C``."""
    t = np.asarray(tuples, dtype=np.intp).reshape(-1, 3)
    cost = float(costs.C[t[:, 0], t[:, 1], t[:, 2]].sum()) if t.shape[0] else 0.0
    nreal = (t > 0).sum(axis=1)
    multi = t[nreal >= 2] - 1
    triples = t[nreal == 3] - 1
    return Association(triples, multi, cost, status, message, dict(info))


def solve_greedy(costs: SDCosts) -> Index:
    """Greedy (§8.5): the finite tuples with at least two real measurements sorted by cost,
    each accepted unless it shares a measurement with an accepted one.  Returns the accepted
    tuples ``(q, 3)`` in dummy indexing (ties: the lexicographically smaller tuple first)."""
    C = costs.C
    flat = np.flatnonzero(np.isfinite(C.reshape(-1)))
    idx = np.stack(np.unravel_index(flat, C.shape), axis=1)
    idx = idx[(idx > 0).sum(axis=1) >= 2]
    order = np.argsort(C[idx[:, 0], idx[:, 1], idx[:, 2]], kind="stable")
    used = [np.zeros(n, dtype=bool) for n in C.shape]
    out: list[Index] = []
    for t in idx[order]:
        i, j, k = int(t[0]), int(t[1]), int(t[2])
        if (i and used[0][i]) or (j and used[1][j]) or (k and used[2][k]):
            continue
        used[0][i] = i > 0
        used[1][j] = j > 0
        used[2][k] = k > 0
        out.append(t)
    return np.asarray(out, dtype=np.intp).reshape(-1, 3)


def greedy(scan: PassiveScan, params: AssocParams) -> Association:
    """Greedy on the §8.2 costs (χ²-based); ``info``: ``n_tuples`` triangulated."""
    costs = sd_costs(scan, params)
    return association_from_tuples(costs, solve_greedy(costs), n_tuples=costs.n_tuples)
