"""Linear Kalman filter: prediction, sequential (Joseph-form) update and the information form.

Prediction::

    x⁻ = F x,            P⁻ = F P Fᵀ + Q

Update with one sensor (Joseph form; no explicit inverse, a non-SPD ``S`` raises)::

    S = H P⁻ Hᵀ + R,     K = P⁻ Hᵀ S⁻¹,
    x⁺ = x⁻ + K (z − H x⁻),
    P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ

Processing the sensors of a subset one after another (:func:`update_sequential`) gives the same
posterior as the information form (:func:`update_information`)::

    Y⁺ = Y⁻ + Σ_j H_jᵀ R_j⁻¹ H_j,          Y = P⁻¹
    y⁺ = y⁻ + Σ_j H_jᵀ R_j⁻¹ z_j,          y = P⁻¹ x
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from covnet.core.cholesky import cho_factor, cho_solve
from covnet.core.gaussian import Gaussian, Mat, Vec, symmetrise
from covnet.core.lapack import flapack


def predict(prior: Gaussian, F: Mat, Q: Mat) -> Gaussian:
    """``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``."""
    return Gaussian(F @ prior.x, predict_covariance(prior.P, F, Q))


def predict_covariance(P: Mat, F: Mat, Q: Mat) -> Mat:
    """The covariance part of :func:`predict` alone (it never depends on the measurements)."""
    return symmetrise(F @ P @ F.T + Q)


@functools.lru_cache(maxsize=8)
def _eye(n: int) -> Mat:
    I = np.eye(n)
    I.flags.writeable = False
    return I


def gain_and_covariance(P: Mat, H: Mat, R: Mat) -> tuple[Mat, Mat]:
    """``K = P Hᵀ S⁻¹`` and the Joseph-form ``P⁺``; neither depends on the measured value."""
    HP = H @ P
    S = HP @ H.T + R
    # K = P Hᵀ S⁻¹  ⇔  S Kᵀ = H P  (S and P symmetric); a Cholesky solve, never inv/pinv.
    K = cho_solve(cho_factor(S), HP).T
    I_KH = _eye(P.shape[0]) - K @ H
    return K, symmetrise(I_KH @ P @ I_KH.T + K @ R @ K.T)


def gains_sequential(P: Mat, H: Mat, Rs: Sequence[Mat]) -> tuple[list[Mat], Mat]:
    """:func:`gain_and_covariance` for each ``R`` of ``Rs`` in turn (the sequential update of
    several sensors' covariance), bit for bit: the gains and the last ``P⁺``.  The same
    arithmetic and LAPACK calls (``potrf``/``potrs`` on ``S`` and ``H P``), with the input
    checks of :func:`covnet.core.cholesky.cho_factor` made once at the end instead of twice
    per update (hundreds of updates a scan in a large network): a non-finite result, or a
    factorisation that fails, runs the checked updates again, which raise as they would.
    :func:`~covnet.core.gaussian.symmetrise` is written out (``0.5 * (A + Aᵀ)``, the same
    elementwise operations on the same 2-D array) and the gains' finiteness is checked in one
    call over all of them (the same test, ``isfinite`` of every entry)."""
    lapack = flapack()
    dpotrf, dpotrs = lapack.dpotrf, lapack.dpotrs
    P0 = np.asarray(P, dtype=np.float64)
    H = np.asarray(H, dtype=np.float64)
    I, Ht = _eye(P0.shape[0]), H.T
    Ks: list[Mat] = []
    P = P0
    for R in Rs:
        HP = H @ P
        S = HP @ Ht + R
        c, info = dpotrf(S, lower=0, clean=0, overwrite_a=0)
        if info != 0:
            break
        X, info = dpotrs(c, HP, lower=0, overwrite_b=0)
        if info != 0:  # pragma: no cover - only for arguments never passed here
            break
        K = X.T
        I_KH = I - K @ H
        A = I_KH @ P @ I_KH.T + K @ R @ K.T
        P = 0.5 * (A + A.T)  # symmetrise(A)
        Ks.append(K)
    else:
        if np.isfinite(P).all() and (not Ks or np.isfinite(np.concatenate(Ks)).all()):
            return Ks, P
    Ks, P = [], P0  # the checked path: the same numbers, or its error
    for R in Rs:
        K, P = gain_and_covariance(P, H, R)
        Ks.append(K)
    return Ks, P


def update(prior: Gaussian, z: Vec, H: Mat, R: Mat) -> Gaussian:
    """One Kalman update in Joseph form (see the module docstring for the equations)."""
    K, P = gain_and_covariance(prior.P, H, R)
    return Gaussian(prior.x + K @ (z - H @ prior.x), P)


def update_covariance(P: Mat, H: Mat, R: Mat) -> Mat:
    """The covariance of :func:`update` alone, bit for bit the same: in a linear Kalman filter
    the posterior covariance does not depend on the measured value, so it can be computed
    before the measurement arrives."""
    return gain_and_covariance(P, H, R)[1]


def update_sequential(prior: Gaussian, measurements: Sequence[tuple[Vec, Mat, Mat]]) -> Gaussian:
    """Apply :func:`update` for each ``(z, H, R)`` in turn (independent measurement noises)."""
    post = prior
    for z, H, R in measurements:
        post = update(post, z, H, R)
    return post


def update_information(prior: Gaussian, measurements: Sequence[tuple[Vec, Mat, Mat]]) -> Gaussian:
    """Information-form update: ``Y⁺ = Y⁻ + Σ Hᵀ R⁻¹ H``, ``y⁺ = y⁻ + Σ Hᵀ R⁻¹ z``.

    ``Y⁻ = P⁻⁻¹`` and the final ``P⁺ = Y⁺⁻¹`` are formed through Cholesky solves.
    """
    n = prior.dim
    cP = cho_factor(prior.P)
    Y = cho_solve(cP, _eye(n))
    y = cho_solve(cP, prior.x)
    for z, H, R in measurements:
        cR = cho_factor(R)
        Y = Y + H.T @ cho_solve(cR, H)
        y = y + H.T @ cho_solve(cR, z)
    cY = cho_factor(symmetrise(Y))
    return Gaussian(cho_solve(cY, y), symmetrise(cho_solve(cY, _eye(n))))


def nees(estimate: Gaussian, truth: Vec) -> float:
    """Normalised estimation error squared ``ε = (x − x̂)ᵀ P⁻¹ (x − x̂)``."""
    e = truth - estimate.x
    return float(e @ cho_solve(cho_factor(estimate.P), e))
