"""NEES / NIS values and χ² bands (oracle table values), and fixed-seed Monte Carlo checks that
the filters of the many-target capability are consistent where they should be."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.consistency import (
    chi2_band,
    mean_chi2_band,
    nees,
    nees_band,
    nis,
    nis_band,
)
from covnet.core.ekf import ekf_update
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import nees as kalman_nees
from covnet.core.kalman import predict
from covnet.core.motion import cv_transition, dwna_noise_gain, dwna_process_noise
from covnet.core.sensor_models import BearingModel, PositionModel, RangeBearingModel


def test_nees_and_nis_oracle():
    """e = (1, 2), P = diag(1, 4): ε = 1 + 4/4 = 2.  With correlation, ε = eᵀ P⁻¹ e."""
    assert float(nees([1.0, 2.0], [0.0, 0.0], np.diag([1.0, 4.0]))) == pytest.approx(2.0)
    P = np.array([[2.0, 1.0], [1.0, 2.0]])  # P⁻¹ = [[2, −1], [−1, 2]] / 3
    e = np.array([1.0, -1.0])
    assert float(nis(e, P)) == pytest.approx((2 + 2 + 2) / 3)


def test_batched_and_equal_to_kalman_nees():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(7, 4, 4))
    P = A @ np.swapaxes(A, -1, -2) + np.eye(4)
    x, xh = rng.normal(size=(7, 4)), rng.normal(size=(7, 4))
    got = nees(x, xh, P)
    assert got.shape == (7,)
    for i in range(7):
        assert got[i] == pytest.approx(kalman_nees(Gaussian(xh[i], P[i]), x[i]), rel=1e-10)
    with pytest.raises(ValueError, match="nees"):
        nees(np.zeros(3), np.zeros(3), np.eye(4))
    with pytest.raises(np.linalg.LinAlgError):
        nis(np.ones(2), -np.eye(2))


@pytest.mark.parametrize(
    "dof, runs, low, high",
    [
        (1, 1, 0.000982, 5.0239),  # χ²₁ 2.5 % / 97.5 %
        (2, 1, 0.050636, 7.3778),
        (4, 1, 0.4844, 11.1433),
        (2, 50, 74.2219 / 50, 129.5612 / 50),  # Bar-Shalom's example: [1.5, 2.6]
        (4, 50, 162.728 / 50, 241.058 / 50),
    ],
    ids=["1x1", "2x1", "4x1", "2x50", "4x50"],
)
def test_band_table_values(dof, runs, low, high):
    band = chi2_band(dof, runs)
    assert band.low == pytest.approx(low, rel=2e-4)
    assert band.high == pytest.approx(high, rel=2e-4)
    assert (band.dof, band.n_runs, band.probability) == (dof, runs, 0.95)
    assert nees_band(dof, runs) == band == nis_band(dof, runs)
    assert mean_chi2_band(dof * runs, runs) == (band.low, band.high)


def test_band_contains_and_errors():
    band = chi2_band(2, 50)
    np.testing.assert_array_equal(band.contains([1.0, 2.0, 3.0]), [False, True, False])
    assert chi2_band(2, 50, 0.99).low < band.low
    for kwargs, match in [
        (dict(dof=0), "dof"),
        (dict(dof=2, n_runs=0), "n_runs"),
        (dict(dof=2, probability=1.0), "probability"),
    ]:
        with pytest.raises(ValueError, match=match):
            chi2_band(**kwargs)


def _monte_carlo(model, n_runs, n_scans, seed, x0, P0):
    """Run the EKF with ``model`` on CV truth; return NEES (runs, scans) and NIS (runs, scans)."""
    T, q = 1.0, 0.5
    F, Q, G = cv_transition(T), dwna_process_noise(T, q), dwna_noise_gain(T)
    rng = np.random.default_rng(seed)
    LR, L0 = np.linalg.cholesky(model.R), np.linalg.cholesky(P0)
    eps = np.zeros((n_runs, n_scans))
    eps_nu = np.zeros((n_runs, n_scans))
    for i in range(n_runs):
        x = x0 + L0 @ rng.standard_normal(4)
        est = Gaussian(x0.copy(), P0)
        for k in range(n_scans):
            x = F @ x + G @ (q * rng.standard_normal(2))
            est = predict(est, F, Q)
            z = model.h(x) + LR @ rng.standard_normal(model.dim_z)
            res = ekf_update(est, z, model)
            est = res.posterior
            eps[i, k] = float(nees(x, est.x, est.P))
            eps_nu[i, k] = res.nis
    return eps, eps_nu


def test_linear_filter_is_consistent():
    """Position sensor, linear KF (via the EKF): the 50-run average NEES and NIS at a scan
    lie in their 95 % bands at most scans (about 95 %)."""
    m = PositionModel(sigma_x=21.1, sigma_y=8.2, rho=0.82)
    x0 = np.array([0.0, 426.0, 0.0, 0.0])
    eps, eps_nu = _monte_carlo(m, 50, 20, 7, x0, np.diag([1e2, 1e1, 1e2, 1e1]))
    inside = chi2_band(4, 50).contains(eps.mean(axis=0))
    inside_nu = chi2_band(2, 50).contains(eps_nu.mean(axis=0))
    assert inside.mean() >= 0.85 and inside_nu.mean() >= 0.85
    # the innovations are white, so the NIS of all scans and runs is one χ²(2·1000) / 1000
    assert chi2_band(2, 50 * 20).contains(eps_nu.mean())


@pytest.mark.parametrize(
    "model",
    [
        RangeBearingModel(sensor_xy=(-20000.0, -5000.0), sigma_r=20.0, sigma_bearing=2e-3),
        BearingModel(sensor_xy=(-20000.0, -5000.0), sigma_bearing=1e-3),
    ],
    ids=["range_bearing", "bearing"],
)
def test_ekf_is_consistent_when_nearly_linear(model):
    """Far from the sensor with a small prior the EKF's linearisation error is negligible:
    the 100-run average NEES is inside its band at most scans, and the NIS over all runs and
    scans (white innovations) inside its band."""
    x0 = np.array([0.0, 200.0, 0.0, 50.0])
    eps, eps_nu = _monte_carlo(model, 100, 30, 11, x0, np.diag([100.0, 4.0, 100.0, 4.0]))
    assert chi2_band(model.dim_z, eps_nu.size).contains(eps_nu.mean())
    assert chi2_band(4, 100).contains(eps.mean(axis=0)).mean() >= 0.85
