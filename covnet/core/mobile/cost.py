"""The cost of every candidate (target i, sensor j, mode ρ), batched: a ``(M, N, 9)`` tensor.

For the decision at scan k, with track i predicted to k+1 (``x⁻``, ``P⁻``) and sensor j where mode
ρ takes it (``q_jρ = a_j + T V_j Δ_ρ``, moving at ``q̇_jρ = V_j Δ_ρ``), spec §4::

    md_ijρ = 1 − Pd(x⁻_i, q_jρ)
    tr_ijρ = trace(P⁺),   P⁺ = P⁻ − P⁻Cᵀ (C P⁻ Cᵀ + R_ijρ)⁻¹ C P⁻
    b_jρ   = b0_j + b1_j ‖Δ_ρ‖
    c_ijρ  = γ ω_d md_ijρ + α ω_X tr_ijρ + β ω_b b_jρ

    c0_i   = γ ω_d · 1 + α ω_X trace(P⁻_i) + penalty           (target i not observed)
    penalty = 1000 + 10 max_ijρ |c_ijρ|                          (default; or a fixed number)

with ``ω = 1 / std`` of each quantity over all ``M·N·9`` candidates (population std; when the std
is ≤ 1e-9 times the mean absolute value, ``1 / mean|·|`` instead, and 1 if that is 0).

The only matrix to invert is the 2×2 innovation covariance ``S = C P⁻ Cᵀ + R``, so everything is
element-wise array work on ``(M, N, 9)`` arrays, with no loop over candidates::

    trace(P⁺) = trace(P⁻) − Σ_ab (S⁻¹)_ab W_ba,   W = (P⁻Cᵀ)ᵀ (P⁻Cᵀ)
    S⁻¹ = [[s11, −s01], [−s01, s00]] / (s00 s11 − s01²)

``trace_kind = "position"`` uses the position block only: ``trace(C P⁺ Cᵀ)``, with
``W = (C P⁻ Cᵀ)²`` and ``trace(C P⁻ Cᵀ)`` (also in ``c0``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from covnet.core.gaussian import Mat, Vec
from covnet.core.mobile.models import Sensors, bell, candidate_states, usage_cost

TraceKind = Literal["full", "position"]


@dataclass(frozen=True, slots=True)
class CostParams:
    """Everything the cost needs besides tracks and sensors (defaults: spec §7).

    ``T`` scan period (s); ``alpha, beta, gamma`` accuracy, usage, missed-detection weights;
    ``PD, a, b, c`` the detection bell; ``L`` noise-growth lengths (m, per axis);
    ``null_penalty`` ``None`` for the automatic ``1000 + 10 max|c|``.
    """

    T: float = 1.0
    alpha: float = 1.0
    beta: float = 0.1
    gamma: float = 5.0
    PD: float = 0.95
    a: float = 1.0
    b: float = 2.0
    c: float = 0.0
    L: tuple[float, float] = (25.0, 25.0)
    dist_uses_velocity: bool = True
    trace_kind: TraceKind = "full"
    pd_include_track_cov: bool = False
    null_penalty: float | None = None


@dataclass(frozen=True, slots=True)
class CostTensor:
    """The costs of one decision and their parts.

    ``c`` (M, N, 9) and ``c0`` (M,) enter the decision; ``md``, ``tr`` (M, N, 9), ``b`` (N, 9)
    are the raw terms; ``omega`` = (ω_d, ω_X, ω_b); ``penalty`` the null option's surcharge.
    """

    c: Mat
    c0: Vec
    md: Mat
    tr: Mat
    b: Mat
    omega: Vec
    penalty: float


def inverse_scale(values: Mat) -> float:
    """``1 / std(values)`` (population), or ``1 / mean|values|`` when the std is ≤ 1e-9 times
    that mean, or 1 when the mean is 0 too (or there are no values)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return 1.0
    sd = float(v.std())
    m = float(np.abs(v).mean())
    if sd > 1e-9 * m:
        return 1.0 / sd
    return 1.0 / m if m > 0.0 else 1.0


def cost_tensor(x_pred: Mat, P_pred: Mat, sensors: Sensors, params: CostParams) -> CostTensor:
    """The cost tensor of spec §4 for predicted tracks ``x_pred`` (M, 4), ``P_pred`` (M, 4, 4).

    See the module docstring for the equations.  Shapes: targets on axis 0, sensors on axis 1,
    modes on axis 2.
    """
    q, qdot = candidate_states(sensors.position, sensors.speed, params.T)  # (N, 9, 2)
    x = x_pred[:, None, None, :]  # (M, 1, 1, 4)

    # position differences and the per-axis distance of spec §3.3
    ex = x[..., 0] - q[None, :, :, 0]  # (M, N, 9)
    ey = x[..., 2] - q[None, :, :, 1]
    if params.dist_uses_velocity:
        fx = x[..., 1] - qdot[None, :, :, 0]
        fy = x[..., 3] - qdot[None, :, :, 1]
        Dx = np.sqrt(ex * ex + fx * fx)
        Dy = np.sqrt(ey * ey + fy * fy)
    else:
        Dx, Dy = np.abs(ex), np.abs(ey)
    gx = 1.0 + Dx / params.L[0]
    gy = 1.0 + Dy / params.L[1]

    # S = C P⁻ Cᵀ + R,  R_ab = sqrt(g_a g_b) R0_ab
    R0 = sensors.R0
    p00 = P_pred[:, 0, 0][:, None, None]
    p01 = P_pred[:, 0, 2][:, None, None]
    p11 = P_pred[:, 2, 2][:, None, None]
    s00 = p00 + gx * R0[:, 0, 0][None, :, None]
    s11 = p11 + gy * R0[:, 1, 1][None, :, None]
    r01 = R0[:, 0, 1]
    if np.any(r01 != 0.0):
        s01 = p01 + np.sqrt(gx * gy) * r01[None, :, None]
    else:
        s01 = np.broadcast_to(p01, s00.shape)
    det = s00 * s11 - s01 * s01

    # trace(P⁺) = trace(P⁻) − tr(S⁻¹ W)
    if params.trace_kind == "full":
        G = P_pred[:, :, [0, 2]]  # P⁻Cᵀ (M, 4, 2)
        tr_prior = np.trace(P_pred, axis1=1, axis2=2)
    else:
        G = P_pred[:, [0, 2]][:, :, [0, 2]]  # C P⁻ Cᵀ (M, 2, 2)
        tr_prior = P_pred[:, 0, 0] + P_pred[:, 2, 2]
    W = np.swapaxes(G, -1, -2) @ G  # (M, 2, 2)
    w00 = W[:, 0, 0][:, None, None]
    w01 = W[:, 0, 1][:, None, None]
    w11 = W[:, 1, 1][:, None, None]
    tr = tr_prior[:, None, None] - (s11 * w00 - 2.0 * s01 * w01 + s00 * w11) / det

    # md = 1 − Pd, d² = eᵀ S_d⁻¹ e with S_d = r² I (+ C P⁻ Cᵀ)
    r2 = (sensors.r_pd**2)[None, :, None]
    if params.pd_include_track_cov:
        a00, a11, a01 = r2 + p00, r2 + p11, p01
        d2 = (a11 * ex * ex - 2.0 * a01 * ex * ey + a00 * ey * ey) / (a00 * a11 - a01 * a01)
    else:
        d2 = (ex * ex + ey * ey) / r2
    md = 1.0 - bell(np.sqrt(d2), params.PD, params.a, params.b, params.c)

    b = usage_cost(sensors.b0, sensors.b1)  # (N, 9)
    omega = np.array([inverse_scale(md), inverse_scale(tr), inverse_scale(b)])
    c = (
        params.gamma * omega[0] * md
        + params.alpha * omega[1] * tr
        + params.beta * omega[2] * b[None, :, :]
    )
    if params.null_penalty is None:
        penalty = 1000.0 + 10.0 * (float(np.abs(c).max()) if c.size else 0.0)
    else:
        penalty = float(params.null_penalty)
    c0 = params.gamma * omega[0] + params.alpha * omega[1] * tr_prior + penalty
    return CostTensor(c=c, c0=c0, md=md, tr=tr, b=b, omega=omega, penalty=penalty)
