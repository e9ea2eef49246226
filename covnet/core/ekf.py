"""Extended (and unscented) Kalman update for the models of :mod:`covnet.core.sensor_models`.

EKF update, linearised at the predicted state ``x⁻`` (Bar-Shalom, Li & Kirubarajan 2001, ch. 10)::

    ẑ = h(x⁻),            H = ∂h/∂x (x⁻)
    ν = z − ẑ             (angle components wrapped to (−π, π])
    S = H P⁻ Hᵀ + R,      K = P⁻ Hᵀ S⁻¹         (Cholesky solve S Kᵀ = H P⁻, no inverse)
    x⁺ = x⁻ + K ν
    P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ       (Joseph form, then symmetrised)
    NIS = νᵀ S⁻¹ ν

For the linear ``position`` model this is, operation for operation,
:func:`covnet.core.kalman.update`.

:func:`predict_measurement` computes everything that does not depend on the measured value
(``ẑ, H, S, K, P⁺``) once; the nearest-neighbour and PDA updates of
:mod:`covnet.core.association` reuse it for all the returns of a dwell.

:func:`ukf_update` is the unscented alternative (Julier & Uhlmann; Wan & van der Merwe's scaled
sigma points), with the angle components of the measurement averaged as wrapped deviations
from the central sigma point.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from covnet.core.cholesky import cho_factor, cho_solve
from covnet.core.gaussian import Gaussian, Mat, Vec, symmetrise
from covnet.core.sensor_models import STATE_DIM, SensorModel, innovation, wrap_angle

__all__ = [
    "EKFResult",
    "MeasurementPrediction",
    "ekf_update",
    "predict_measurement",
    "ukf_update",
]


@functools.lru_cache(maxsize=8)
def _eye(n: int) -> Mat:
    I = np.eye(n)
    I.flags.writeable = False
    return I


@dataclass(frozen=True, slots=True)
class MeasurementPrediction:
    """What a dwell's update needs before any measurement arrives (EKF, at ``x⁻``).

    ``zhat = h(x⁻)`` ``(dim_z,)``, ``H`` ``(dim_z, n)``, ``S = H P⁻ Hᵀ + R``, ``K = P⁻ Hᵀ S⁻¹``
    ``(n, dim_z)``, ``P_detected`` the Joseph-form posterior covariance given one correct
    measurement, ``S_factor`` the upper Cholesky factor of ``S`` (``cho_factor``), and the
    model's ``angle_mask``.
    """

    zhat: Vec
    H: Mat
    S: Mat
    K: Mat
    P_detected: Mat
    S_factor: Mat
    angle_mask: tuple[bool, ...]

    @property
    def dim_z(self) -> int:
        return int(self.zhat.shape[0])

    def innovations(self, Z: ArrayLike) -> Mat:
        """``ν_i = z_i − ẑ`` (angles wrapped) for the rows of ``Z`` ``(m, dim_z)`` (or one
        ``(dim_z,)``)."""
        return innovation(Z, self.zhat, self.angle_mask)

    def mahalanobis2(self, nu: ArrayLike) -> Vec:
        """``d² = νᵀ S⁻¹ ν`` for ``ν`` ``(dim_z,)`` (a 0-d array) or ``(m, dim_z)`` (``(m,)``)."""
        v = np.asarray(nu, dtype=np.float64)
        if v.ndim not in (1, 2) or v.shape[-1] != self.dim_z:
            raise ValueError(f"nu: expected shape (dim_z,) or (m, dim_z), dim_z = {self.dim_z}")
        if v.ndim == 1:
            return np.asarray(v @ cho_solve(self.S_factor, v))
        if v.shape[0] == 0:
            return np.zeros(0)
        W = cho_solve(self.S_factor, v.T)  # (dim_z, m)
        return np.asarray(np.einsum("ij,ji->i", v, W))


def predict_measurement(prior: Gaussian, model: SensorModel) -> MeasurementPrediction:
    """Linearise ``model`` at ``prior.x`` and form ``ẑ, H, S, K`` and the Joseph-form ``P⁺``.

    A non-SPD ``S`` raises ``numpy.linalg.LinAlgError`` (never a pseudo-inverse).
    """
    if prior.dim != STATE_DIM:
        raise ValueError(f"prior: expected a state of dimension {STATE_DIM}, got {prior.dim}")
    P = prior.P
    H = model.jacobian(prior.x)
    R = model.R
    # the same operations, in the same order, as covnet.core.kalman.gain_and_covariance
    HP = H @ P
    S = HP @ H.T + R
    c = cho_factor(S)
    K = cho_solve(c, HP).T
    I_KH = _eye(P.shape[0]) - K @ H
    P_det = symmetrise(I_KH @ P @ I_KH.T + K @ R @ K.T)
    return MeasurementPrediction(
        zhat=model.h(prior.x),
        H=H,
        S=symmetrise(S),
        K=K,
        P_detected=P_det,
        S_factor=c,
        angle_mask=model.angle_components,
    )


@dataclass(frozen=True, slots=True)
class EKFResult:
    """A filter update's outcome: the posterior, the innovation ``ν`` and its covariance ``S``
    (for NIS and gating)."""

    posterior: Gaussian
    nu: Vec
    S: Mat

    @property
    def nis(self) -> float:
        """``νᵀ S⁻¹ ν``."""
        return float(self.nu @ cho_solve(cho_factor(self.S), self.nu))


def _measurement(z: ArrayLike, dim_z: int) -> Vec:
    zz = np.asarray(z, dtype=np.float64)
    if zz.shape != (dim_z,):
        raise ValueError(f"z: expected shape ({dim_z},), got {zz.shape}")
    return zz


def ekf_update(
    prior: Gaussian,
    z: ArrayLike,
    model: SensorModel,
    prediction: MeasurementPrediction | None = None,
) -> EKFResult:
    """One EKF update with measurement ``z`` ``(dim_z,)`` (equations in the module docstring).

    ``prediction`` (from :func:`predict_measurement` on the same prior and model) saves the
    linearisation when several updates of the same prior are tried.
    """
    pred = predict_measurement(prior, model) if prediction is None else prediction
    nu = pred.innovations(_measurement(z, pred.dim_z))
    x = prior.x + pred.K @ nu
    return EKFResult(Gaussian(x, pred.P_detected), nu, pred.S)


def ukf_update(
    prior: Gaussian,
    z: ArrayLike,
    model: SensorModel,
    alpha: float = 1.0,
    beta: float = 2.0,
    kappa: float = 0.0,
) -> EKFResult:
    """Unscented update with scaled sigma points.

    ``λ = α² (n + κ) − n``; ``χ_0 = x⁻``, ``χ_{±i} = x⁻ ± (√((n + λ) P⁻))_i`` (columns of the
    lower Cholesky factor); weights ``W_0^m = λ/(n+λ)``, ``W_0^c = W_0^m + 1 − α² + β``,
    ``W_i = 1/(2(n+λ))``.  With ``Z_i = h(χ_i)`` and ``δ_i = wrap(Z_i − Z_0)`` on angles::

        ẑ = Z_0 + Σ W_i^m δ_i                         (angles wrapped)
        S = Σ W_i^c (Z_i − ẑ)(Z_i − ẑ)ᵀ + R,    C = Σ W_i^c (χ_i − x⁻)(Z_i − ẑ)ᵀ
        K = C S⁻¹,   x⁺ = x⁻ + K (z − ẑ),   P⁺ = P⁻ − K S Kᵀ   (symmetrised)

    For a linear model it equals the Kalman update to rounding.  Defaults ``α = 1, β = 2,
    κ = 0`` (``λ = 0``, so every sigma point has positive mean weight).
    """
    n = prior.dim
    if not (alpha > 0.0 and n + kappa > 0.0):
        raise ValueError(f"alpha, kappa: need alpha > 0 and n + kappa > 0, got {alpha}, {kappa}")
    lam = alpha * alpha * (n + kappa) - n
    L = np.linalg.cholesky(prior.P) * math.sqrt(n + lam)
    chi = np.concatenate([prior.x[None, :], prior.x + L.T, prior.x - L.T])  # (2n+1, n)
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + 1.0 - alpha * alpha + beta
    mask = model.angle_components
    Zs = model.h(chi)  # (2n+1, dim_z)
    zz = _measurement(z, Zs.shape[1])
    dev = innovation(Zs, Zs[0], mask)
    zhat = Zs[0] + wm @ dev
    am = np.asarray(mask, dtype=bool)
    zhat = np.where(am, wrap_angle(zhat), zhat)
    dZ = innovation(Zs, zhat, mask)
    dX = chi - prior.x
    S = symmetrise((dZ.T * wc) @ dZ + model.R)
    C = (dX.T * wc) @ dZ
    c = cho_factor(S)
    K = cho_solve(c, C.T).T
    nu = innovation(zz, zhat, mask)
    P = symmetrise(prior.P - K @ S @ K.T)
    return EKFResult(Gaussian(prior.x + K @ nu, P), nu, S)
