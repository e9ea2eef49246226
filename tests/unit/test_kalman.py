"""Oracle values for the motion model and the Kalman steps, written out from the formulas."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.gaussian import Gaussian
from covnet.core.kalman import (
    nees,
    predict,
    update,
    update_information,
    update_sequential,
)
from covnet.core.motion import cv_transition, dwna_noise_gain, dwna_process_noise
from covnet.core.sensing import correlated_noise, information_gain, position_matrix


def test_cv_transition_oracle():
    F = cv_transition(2.0)
    expected = np.array([[1, 2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_array_equal(F, expected)


@pytest.mark.parametrize(
    "T, sigma", [(1.0, 0.5), (0.5, 2.0), (3.0, 0.1)], ids=["paper", "fast", "slow"]
)
def test_dwna_q_oracle(T, sigma):
    block = sigma**2 * np.array([[T**4 / 4, T**3 / 2], [T**3 / 2, T**2]])
    expected = np.zeros((4, 4))
    expected[:2, :2] = block
    expected[2:, 2:] = block
    np.testing.assert_allclose(dwna_process_noise(T, sigma), expected, rtol=1e-15)
    G = dwna_noise_gain(T)
    np.testing.assert_allclose(G, [[T * T / 2, 0], [T, 0], [0, T * T / 2], [0, T]])


def test_correlated_r_and_information_gain_oracle():
    R = correlated_noise(21.1, 8.2, 0.82)
    np.testing.assert_allclose(R, [[21.1**2, 0.82 * 21.1 * 8.2], [0.82 * 21.1 * 8.2, 8.2**2]])
    H = position_matrix()
    J = information_gain(H, R)
    Rinv = np.linalg.inv(R)
    expected = np.zeros((4, 4))
    expected[np.ix_([0, 2], [0, 2])] = Rinv
    np.testing.assert_allclose(J, expected, rtol=1e-12, atol=1e-16)


def test_predict_oracle():
    F, Q = cv_transition(1.0), dwna_process_noise(1.0, 0.5)
    prior = Gaussian(np.array([1.0, 2.0, 3.0, 4.0]), np.diag([4.0, 1.0, 9.0, 2.0]))
    post = predict(prior, F, Q)
    np.testing.assert_allclose(post.x, [3.0, 2.0, 7.0, 4.0])
    expected = F @ prior.P @ F.T + Q
    np.testing.assert_allclose(post.P, expected, rtol=1e-15)
    # written out: P11 = 4 + 1 + q/4, P12 = 1 + q/2, P22 = 1 + q
    q = 0.25
    assert post.P[0, 0] == pytest.approx(5.0 + q / 4)
    assert post.P[0, 1] == pytest.approx(1.0 + q / 2)
    assert post.P[1, 1] == pytest.approx(1.0 + q)


def test_scalar_update_oracle():
    """1-D: K = P/(P+R), x⁺ = x + K(z-x), P⁺ = P R/(P+R)."""
    prior = Gaussian(np.array([0.0]), np.array([[4.0]]))
    post = update(prior, np.array([2.0]), np.array([[1.0]]), np.array([[1.0]]))
    assert post.x[0] == pytest.approx(2.0 * 4.0 / 5.0)
    assert post.P[0, 0] == pytest.approx(4.0 / 5.0)


def _paper_measurements(rng):
    H = position_matrix()
    out = []
    for sx, sy, rho in [(21.1, 8.2, 0.82), (8.22, 20.3, 0.78), (42.1, 43.1, 0.87)]:
        out.append((rng.normal(size=2) * 30, H, correlated_noise(sx, sy, rho)))
    return out


def test_sequential_equals_information_form_paper_sensors():
    rng = np.random.default_rng(7)
    F, Q = cv_transition(1.0), dwna_process_noise(1.0, 0.5)
    prior = predict(Gaussian(rng.normal(size=4) * 100, np.diag([1e4, 1e2, 1e4, 1e2])), F, Q)
    meas = _paper_measurements(rng)
    a = update_sequential(prior, meas)
    b = update_information(prior, meas)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(a.x, b.x, rtol=1e-10, atol=1e-8)


def test_update_rejects_non_spd_innovation():
    prior = Gaussian(np.zeros(2), np.eye(2))
    with pytest.raises(np.linalg.LinAlgError):
        update(prior, np.zeros(1), np.array([[1.0, 0.0]]), np.array([[-5.0]]))


def test_nees_oracle():
    est = Gaussian(np.zeros(2), np.diag([4.0, 9.0]))
    assert nees(est, np.array([2.0, 3.0])) == pytest.approx(1.0 + 1.0)


def test_gaussian_checks_shapes():
    with pytest.raises(ValueError, match="Gaussian.P"):
        Gaussian(np.zeros(3), np.eye(2))
    with pytest.raises(ValueError, match="Gaussian.x"):
        Gaussian(np.zeros((3, 1)), np.eye(3))


def test_covariance_only_update_is_bitwise_the_same():
    """The manager decides scan k+1 before scan k's measurements arrive: that relies on the
    covariance-only path reproducing the full update's P exactly."""
    from covnet.core.kalman import update_covariance

    rng = np.random.default_rng(3)
    H = position_matrix()
    prior = Gaussian(rng.normal(size=4), np.diag([1e4, 1e2, 1e4, 1e2]))
    R = correlated_noise(9.23, 20.9, -0.61)
    post = update(prior, rng.normal(size=2), H, R)
    np.testing.assert_array_equal(update_covariance(prior.P, H, R), post.P)
