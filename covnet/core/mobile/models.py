"""Models of the mobile problem: modes, platforms, targets, measurement noise, detection.

Conventions (spec §2): units m and s; target state ``x = [px, vx, py, vy]``; platform state
``a = [qx, qy]`` (position only, known exactly); measurement ``z = C x + v`` with
``C = [[1, 0, 0, 0], [0, 0, 1, 0]]``.

Mode table (0-based; counter-clockwise from east after "stay"; ``h = √2/2``)::

    ρ     0     1      2      3      4       5       6        7       8
    name  stay  E      NE     N      NW      W       SW       S       SE
    Δ_ρ   (0,0) (1,0)  (h,h)  (0,1)  (−h,h)  (−1,0)  (−h,−h)  (0,−1)  (h,−h)

Platform motion (spec §3.2, ξ = 0)::

    a_{k+1} = a_k + T V_j Δ_ρ,       q̇ = V_j Δ_ρ during the scan

Every function here is batched over leading axes and draws nothing itself: randomness comes in as
an explicit ``numpy.random.Generator`` (:func:`pair_stream` and friends give the spec's streams).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from covnet.core.gaussian import Mat, Vec

IntVec = NDArray[np.intp]

_H = float(np.sqrt(2.0) / 2.0)

#: Δ_ρ for ρ = 0..8, shape (9, 2): stay, E, NE, N, NW, W, SW, S, SE
MODES: Mat = np.array(
    [
        [0.0, 0.0],
        [1.0, 0.0],
        [_H, _H],
        [0.0, 1.0],
        [-_H, _H],
        [-1.0, 0.0],
        [-_H, -_H],
        [0.0, -1.0],
        [_H, -_H],
    ]
)
MODES.flags.writeable = False
MODE_NAMES: tuple[str, ...] = ("stay", "E", "NE", "N", "NW", "W", "SW", "S", "SE")
N_MODES = 9
#: ‖Δ_ρ‖ ∈ {0, 1}, shape (9,)
MODE_NORM: Vec = np.array([0.0] + [1.0] * 8)
MODE_NORM.flags.writeable = False
STAY = 0

#: position measurement matrix C (2, 4)
C_POS: Mat = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
C_POS.flags.writeable = False

# stream domains of spec §8.1: default_rng([seed, domain, ...])
TRUTH, INITIAL, PAIR = 1, 2, 3


def stream(seed: int, *key: int) -> np.random.Generator:
    """``numpy.random.default_rng([seed, *key])``: the spec's (§8.1) streams, so the numbers
    match the reference harness: truth ``[seed, 1]``, initial estimates ``[seed, 2]``, the
    detection and noise of pair (i, j) at scan k ``[seed, 3, k, i, j]``."""
    return np.random.default_rng([seed, *key])


def pair_stream(seed: int, scan: int, target: int, sensor: int) -> np.random.Generator:
    """The generator of pair (i = ``target``, j = ``sensor``) at scan ``scan``."""
    return stream(seed, PAIR, scan, target, sensor)


# --------------------------------------------------------------------------------------------
# targets


def cv_model(T: float) -> tuple[Mat, Mat]:
    """Constant velocity with white acceleration (spec §3.1)::

    A = blockdiag([[1, T], [0, 1]] ×2),   B = blockdiag([[T²/2], [T]] ×2),   Q = σ_a² B Bᵀ
    """
    A = np.kron(np.eye(2), np.array([[1.0, T], [0.0, 1.0]]))
    B = np.kron(np.eye(2), np.array([[0.5 * T * T], [T]]))
    return A, B


@dataclass(frozen=True, slots=True)
class TargetModels:
    """Per-target linear-Gaussian motion ``x_{k+1} = A_i x_k + B_i w_k``, ``w ~ N(0, σ_a,i² I₂)``.

    ``A`` (M, 4, 4), ``B`` (M, 4, 2), ``sigma_a`` (M,); ``Q`` (M, 4, 4) = ``σ_a² B Bᵀ``.
    """

    A: Mat
    B: Mat
    sigma_a: Vec

    @property
    def Q(self) -> Mat:
        return self.sigma_a[:, None, None] ** 2 * (self.B @ np.swapaxes(self.B, -1, -2))

    @property
    def count(self) -> int:
        return int(self.A.shape[0])


def predict_tracks(x: Mat, P: Mat, models: TargetModels) -> tuple[Mat, Mat]:
    """Batched prediction of every track: ``x⁻ = A x``, ``P⁻ = A P Aᵀ + Q`` (symmetrised).

    ``x`` (M, 4), ``P`` (M, 4, 4).
    """
    A = models.A
    xp = np.einsum("mab,mb->ma", A, x)
    Pp = A @ P @ np.swapaxes(A, -1, -2) + models.Q
    return xp, 0.5 * (Pp + np.swapaxes(Pp, -1, -2))


def truth_trajectories(x0: Mat, models: TargetModels, scans: int, rng: np.random.Generator) -> Mat:
    """True states ``(scans + 1, M, 4)``: row k is time ``kT`` (row 0 is ``x0``).

    All process noise is drawn in one call, ``w`` of shape ``(scans, M, 2)`` times ``σ_a,i``,
    so the trajectories depend only on the generator's state.
    """
    M = x0.shape[0]
    w = rng.standard_normal((scans, M, 2)) * models.sigma_a[None, :, None]
    out = np.empty((scans + 1, M, 4))
    out[0] = x0
    for k in range(scans):
        out[k + 1] = np.einsum("mab,mb->ma", models.A, out[k]) + np.einsum(
            "mab,mb->ma", models.B, w[k]
        )
    return out


def initial_estimates(x0: Mat, P0: Mat, rng: np.random.Generator) -> Mat:
    """``x̂0 = x0 + L e``, ``P0 = L Lᵀ``, ``e ~ N(0, I)``; one ``(M, 4)`` draw."""
    L = np.linalg.cholesky(P0)
    e = rng.standard_normal(x0.shape)
    out: Mat = x0 + np.einsum("...ab,...b->...a", L, e)
    return out


# --------------------------------------------------------------------------------------------
# sensors and platforms


@dataclass(frozen=True, slots=True)
class Sensors:
    """N sensors on platforms (arrays over sensors j on the leading axis).

    ``position`` (N, 2) m; ``speed`` (N,) m/s; ``R0`` (N, 2, 2) m²; ``r_pd`` (N,) m, the
    detection scale (``S = r² I``); ``b0``, ``b1`` (N,) usage cost and motion surcharge;
    ``capacity`` (N,) targets per scan, ``inf`` for none.
    """

    position: Mat
    speed: Vec
    R0: Mat
    r_pd: Vec
    b0: Vec
    b1: Vec
    capacity: Vec

    @property
    def count(self) -> int:
        return int(self.position.shape[0])

    def subset(self, index: IntVec) -> Sensors:
        """The sensors ``index`` (e.g. the live ones), in that order."""
        idx = np.asarray(index, dtype=np.intp)
        return Sensors(
            self.position[idx],
            self.speed[idx],
            self.R0[idx],
            self.r_pd[idx],
            self.b0[idx],
            self.b1[idx],
            self.capacity[idx],
        )


def candidate_states(position: Mat, speed: Vec, T: float) -> tuple[Mat, Mat]:
    """Where every mode takes every platform: ``q_jρ = a_j + T V_j Δ_ρ`` and ``q̇_jρ = V_j Δ_ρ``,
    both ``(N, 9, 2)``."""
    qdot = speed[:, None, None] * MODES[None, :, :]
    return position[:, None, :] + T * qdot, qdot


def move_platforms(position: Mat, speed: Vec, modes: IntVec, T: float) -> tuple[Mat, Mat]:
    """One scan of the commanded ``modes`` (N,): returns the new positions ``a + T V Δ_ρ`` and
    the velocities ``V Δ_ρ`` during the scan, both (N, 2)."""
    qdot = speed[:, None] * MODES[np.asarray(modes, dtype=np.intp)]
    return position + T * qdot, qdot


def usage_cost(b0: Vec, b1: Vec) -> Mat:
    """``b_jρ = b0_j + b1_j ‖Δ_ρ‖``, shape (N, 9)."""
    return b0[:, None] + b1[:, None] * MODE_NORM[None, :]


# --------------------------------------------------------------------------------------------
# measurement noise and detection


def noise_growth(x: Mat, q: Mat, qdot: Mat, L: Vec, use_velocity: bool) -> Mat:
    """Per-axis growth ``g = (1 + D_x / L_x, 1 + D_y / L_y)`` (shape ``(..., 2)``, broadcast).

    ``D_x = ‖(px − qx, vx − q̇x)‖`` and ``D_y = ‖(py − qy, vy − q̇y)‖`` (the patent's per-axis
    distance in the (position, velocity) plane), or ``|px − qx|``, ``|py − qy|`` when
    ``use_velocity`` is false.
    """
    dp = np.stack([x[..., 0] - q[..., 0], x[..., 2] - q[..., 1]], axis=-1)
    if use_velocity:
        dv = np.stack([x[..., 1] - qdot[..., 0], x[..., 3] - qdot[..., 1]], axis=-1)
        D = np.sqrt(dp * dp + dv * dv)
    else:
        D = np.abs(dp)
    return 1.0 + D / np.asarray(L, dtype=np.float64)


def noise_covariance(g: Mat, R0: Mat) -> Mat:
    """``R = G^{1/2} R0 G^{1/2}`` with ``G = diag(g)``, i.e. ``R_ab = sqrt(g_a g_b) R0_ab``.

    Symmetric positive definite whenever ``R0`` is and ``g > 0``; equals the patent's
    ``(I + D L⁻¹) R0`` when ``R0`` is diagonal.  ``g`` ``(..., 2)``, ``R0`` ``(..., 2, 2)``.
    """
    return np.sqrt(g[..., :, None] * g[..., None, :]) * R0  # exactly symmetric


def bell(d: Mat, PD: float, a: float, b: float, c: float) -> Mat:
    """Generalised bell ``Pd = PD / (1 + |(d − c) / a|^{2b})`` (→ 0 far away, no warning)."""
    with np.errstate(over="ignore"):
        return PD / (1.0 + np.abs((d - c) / a) ** (2.0 * b))


def detection_probability(
    x: Mat,
    q: Mat,
    r_pd: Vec | float,
    PD: float,
    a: float,
    b: float,
    c: float,
    P_pos: Mat | None = None,
) -> Mat:
    """Bell detection probability of a target at ``x`` (…, 4) by a sensor at ``q`` (…, 2).

    ``d = sqrt((p − q)ᵀ S⁻¹ (p − q))`` with ``p = (px, py)`` and ``S = r² I`` (``r`` broadcast
    against the leading axes), or ``S = r² I + C P⁻ Cᵀ`` when the position covariance
    ``P_pos`` (…, 2, 2) is given (spec §3.4, ``pd_include_track_cov``).
    """
    e0 = x[..., 0] - q[..., 0]
    e1 = x[..., 2] - q[..., 1]
    r2 = np.asarray(r_pd, dtype=np.float64) ** 2
    if P_pos is None:
        d2 = (e0 * e0 + e1 * e1) / r2
    else:
        s00 = r2 + P_pos[..., 0, 0]
        s11 = r2 + P_pos[..., 1, 1]
        s01 = P_pos[..., 0, 1]
        det = s00 * s11 - s01 * s01
        d2 = (s11 * e0 * e0 - 2.0 * s01 * e0 * e1 + s00 * e1 * e1) / det
    return bell(np.sqrt(d2), PD, a, b, c)


def draw_detection(rng: np.random.Generator, Pd: float, z_mean: Vec, R: Mat) -> tuple[bool, Vec]:
    """One pair's draw (spec §2 step 6): ``u ~ U(0, 1)``, detected iff ``u < Pd``; then
    ``z = C x + L e`` with ``R = L Lᵀ``, ``e ~ N(0, I₂)``.  Both are always drawn, in this
    order, so a stream is consumed the same way whatever the outcome."""
    u = rng.random()
    e = rng.standard_normal(2)
    z = z_mean + np.linalg.cholesky(R) @ e
    return bool(u < Pd), z
