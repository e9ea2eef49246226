"""EKF (and UKF) update: equals the linear Kalman update for the position model, oracle values
for the radar written out from the formulas, angle wrapping, NIS."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.ekf import ekf_update, predict_measurement, ukf_update
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import update, update_sequential
from covnet.core.sensing import position_matrix
from covnet.core.sensor_models import BearingModel, PositionModel, RangeBearingModel

PAPER = [(21.1, 8.2, 0.82), (20.3, 9.1, -0.74), (8.22, 20.3, 0.78), (42.1, 43.1, 0.87)]


def _prior(seed=0, scale=30.0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(4, 4))
    return Gaussian(rng.normal(size=4) * 1e3, scale * (A @ A.T) + np.diag([1e2, 1, 1e2, 1]))


@pytest.mark.parametrize("sensor", PAPER, ids=["S1", "S2", "S3", "S7"])
def test_ekf_position_equals_kalman_update(sensor):
    sx, sy, rho = sensor
    m = PositionModel(sigma_x=sx, sigma_y=sy, rho=rho)
    prior = _prior()
    z = prior.x[[0, 2]] + np.array([13.0, -7.0])
    got = ekf_update(prior, z, m)
    ref = update(prior, z, position_matrix(), m.R)
    np.testing.assert_allclose(got.posterior.x, ref.x, rtol=1e-14, atol=1e-12)
    np.testing.assert_allclose(got.posterior.P, ref.P, rtol=1e-13, atol=1e-12)
    S = position_matrix() @ prior.P @ position_matrix().T + m.R
    np.testing.assert_allclose(got.S, S, rtol=1e-14)
    nu = z - prior.x[[0, 2]]
    np.testing.assert_allclose(got.nu, nu, rtol=1e-15)
    assert got.nis == pytest.approx(nu @ np.linalg.inv(S) @ nu, rel=1e-12)


def test_ekf_position_is_bit_for_bit_the_kalman_sequence():
    """Same operations in the same order as kalman.update: the paper scenario's numbers are
    unchanged when its position sensors go through the EKF (spec multitarget.md: T = 1,
    position sensors, P_D = 1, no clutter must give exactly today's results)."""
    prior = _prior(9)
    models = [PositionModel(sigma_x=sx, sigma_y=sy, rho=rho) for sx, sy, rho in PAPER]
    zs = [prior.x[[0, 2]] + np.array([3.0 * i, -2.0 * i]) for i in range(len(models))]
    post = prior
    for z, m in zip(zs, models, strict=True):
        post = ekf_update(post, z, m).posterior
    ref = update_sequential(
        prior, [(z, position_matrix(), m.R) for z, m in zip(zs, models, strict=True)]
    )
    np.testing.assert_array_equal(post.x, ref.x)
    np.testing.assert_array_equal(post.P, ref.P)


def test_ekf_range_bearing_oracle():
    """Written out: H at x⁻, S = H P Hᵀ + R, K = P Hᵀ S⁻¹, x⁺ = x⁻ + K ν, Joseph P⁺."""
    m = RangeBearingModel(sensor_xy=(-2000.0, 1000.0), sigma_r=20.0, sigma_bearing=2e-3)
    prior = Gaussian(np.array([3000.0, 100.0, 4000.0, -30.0]), np.diag([900.0, 50, 400, 50]))
    dx, dy = 5000.0, 3000.0
    r = math.hypot(dx, dy)
    H = np.array([[dx / r, 0, dy / r, 0], [-dy / r**2, 0, dx / r**2, 0]])
    z = np.array([r + 25.0, math.atan2(dy, dx) - 1.5e-3])
    nu = z - np.array([r, math.atan2(dy, dx)])
    P = prior.P
    R = np.diag([400.0, 4e-6])
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    I_KH = np.eye(4) - K @ H
    P_post = I_KH @ P @ I_KH.T + K @ R @ K.T
    got = ekf_update(prior, z, m)
    np.testing.assert_allclose(got.nu, nu, rtol=1e-9)
    np.testing.assert_allclose(got.S, S, rtol=1e-12)
    np.testing.assert_allclose(got.posterior.x, prior.x + K @ nu, rtol=1e-12)
    np.testing.assert_allclose(got.posterior.P, P_post, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(got.posterior.P, got.posterior.P.T)


def test_ekf_bearing_across_the_pi_cut():
    """Predicted bearing just below π, measured just above −π: the innovation is +small, not
    −2π, and the update moves the estimate a little."""
    m = BearingModel(sensor_xy=(0.0, 0.0), sigma_bearing=1e-3)
    prior = Gaussian(np.array([-10000.0, 0.0, 10.0, 0.0]), np.diag([100.0, 1, 100, 1]))
    zhat = math.atan2(10.0, -10000.0)  # just below π
    z = np.array([-math.pi + 1e-3])
    got = ekf_update(prior, z, m)
    expected_nu = (z[0] + 2 * math.pi) - zhat
    assert got.nu[0] == pytest.approx(expected_nu, abs=1e-12)
    assert abs(got.nu[0]) < 0.01
    assert np.abs(got.posterior.x - prior.x).max() < 20.0


def test_prediction_reused_is_the_same_update():
    m = RangeBearingModel(sensor_xy=(0.0, 0.0), sigma_r=10.0, sigma_bearing=1e-3)
    prior = _prior(3)
    pred = predict_measurement(prior, m)
    z = pred.zhat + np.array([5.0, 1e-3])
    a = ekf_update(prior, z, m)
    b = ekf_update(prior, z, m, prediction=pred)
    np.testing.assert_array_equal(a.posterior.x, b.posterior.x)
    np.testing.assert_array_equal(a.posterior.P, b.posterior.P)
    assert float(pred.mahalanobis2(a.nu)) == pytest.approx(a.nis, rel=1e-12)
    d2 = pred.mahalanobis2(np.stack([a.nu, 2 * a.nu]))
    np.testing.assert_allclose(d2, [a.nis, 4 * a.nis], rtol=1e-12)
    # the posterior covariance never exceeds the prior's
    assert np.linalg.eigvalsh(prior.P - pred.P_detected).min() > -1e-9 * np.abs(prior.P).max()


def test_ukf_equals_kalman_for_the_linear_model():
    m = PositionModel(sigma_x=21.1, sigma_y=8.2, rho=0.82)
    prior = _prior(5)
    z = prior.x[[0, 2]] + np.array([-40.0, 12.0])
    got = ukf_update(prior, z, m)
    ref = update(prior, z, position_matrix(), m.R)
    np.testing.assert_allclose(got.posterior.x, ref.x, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(got.posterior.P, ref.P, rtol=1e-9, atol=1e-8)


def test_ukf_close_to_ekf_when_nearly_linear():
    """Small prior at long range: linearisation error is tiny, both filters agree closely."""
    m = RangeBearingModel(sensor_xy=(0.0, 0.0), sigma_r=20.0, sigma_bearing=2e-3)
    prior = Gaussian(np.array([20000.0, 100.0, 15000.0, 0.0]), np.diag([100.0, 10, 100, 10]))
    z = m.h(prior.x) + np.array([15.0, 1e-3])
    e = ekf_update(prior, z, m)
    u = ukf_update(prior, z, m)
    np.testing.assert_allclose(u.posterior.x, e.posterior.x, atol=0.05)
    np.testing.assert_allclose(u.posterior.P, e.posterior.P, rtol=1e-3, atol=1e-3)


def test_ukf_bearing_wraps():
    m = BearingModel(sensor_xy=(0.0, 0.0), sigma_bearing=1e-3)
    prior = Gaussian(np.array([-10000.0, 0.0, 0.0, 0.0]), np.diag([100.0, 1, 2500, 1]))
    z = np.array([math.pi - 1e-3])
    u = ukf_update(prior, z, m)
    e = ekf_update(prior, z, m)
    assert abs(u.nu[0]) < 0.01
    np.testing.assert_allclose(u.posterior.x, e.posterior.x, atol=0.5)


def test_bad_inputs():
    m = PositionModel(sigma_x=1.0, sigma_y=1.0)
    with pytest.raises(ValueError, match="z: expected shape"):
        ekf_update(_prior(), np.zeros(3), m)
    with pytest.raises(ValueError, match="prior"):
        ekf_update(Gaussian(np.zeros(2), np.eye(2)), np.zeros(2), m)
    with pytest.raises(np.linalg.LinAlgError):
        ekf_update(Gaussian(np.zeros(4), -10.0 * np.eye(4)), np.zeros(2), m)
