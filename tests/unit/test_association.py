"""Gating, nearest neighbour and PDA: oracle values written out from the formulas, the
reductions to the EKF update, and the information-reduction factor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.association import (
    expected_clutter_in_gate,
    gate,
    gate_threshold,
    gate_volume,
    information_reduction_factor,
    information_reduction_table,
    information_reduction_table_streamed,
    nearest_neighbour_update,
    pda_update,
    pda_weights,
)
from covnet.core.detection import simulate_dwell
from covnet.core.ekf import ekf_update, predict_measurement
from covnet.core.gaussian import Gaussian
from covnet.core.sensor_models import BearingModel, PositionModel, RangeBearingModel

UNIT = PositionModel(sigma_x=1.0, sigma_y=1.0)  # R = I
PRIOR = Gaussian(np.zeros(4), np.diag([3.0, 1.0, 3.0, 1.0]))  # S = 4 I, K_pos = 3/4


def test_gate_threshold_table_values():
    assert gate_threshold(1, 0.99) == pytest.approx(6.6349, abs=1e-4)
    assert gate_threshold(2, 0.99) == pytest.approx(9.2103, abs=1e-4)
    assert gate_threshold(2, 0.95) == pytest.approx(5.9915, abs=1e-4)
    assert gate_threshold(2, 1.0) == math.inf
    assert gate_threshold(2) == gate_threshold(2, 0.99)
    with pytest.raises(ValueError, match="gate_probability"):
        gate_threshold(2, 0.0)
    with pytest.raises(ValueError, match="dim_z"):
        gate_threshold(0, 0.9)


def test_gate_volume_oracle():
    """2-D: V = π γ √det S; 1-D: V = 2 √γ √S."""
    S = np.array([[4.0, 1.0], [1.0, 9.0]])
    assert gate_volume(S, 0.99) == pytest.approx(math.pi * 9.21034 * math.sqrt(35.0), rel=1e-5)
    assert gate_volume([[0.25]], 0.99) == pytest.approx(2 * math.sqrt(6.634897) * 0.5, rel=1e-6)
    assert expected_clutter_in_gate(0.01, S, 0.99) == pytest.approx(0.01 * gate_volume(S, 0.99))
    assert expected_clutter_in_gate(0.0, S) == 0.0


def test_gate_selects_rows_by_mahalanobis_distance():
    pred = predict_measurement(PRIOR, UNIT)  # S = 4 I, γ(0.99) = 9.21: radius 6.07
    Z = np.array([[6.0, 0.0], [0.0, 6.2], [1.0, 1.0], [-4.0, -4.0]])
    rows, nu, d2 = gate(pred, Z, 0.99)
    np.testing.assert_array_equal(rows, [0, 2, 3])
    np.testing.assert_allclose(d2, [9.0, 0.5, 8.0])
    np.testing.assert_array_equal(nu, Z[rows])
    rows, _, _ = gate(pred, np.zeros((0, 2)))
    assert rows.size == 0


# -- nearest neighbour ------------------------------------------------------------------------


def test_nearest_neighbour_uses_mahalanobis_not_euclid():
    """S = diag(100, 1): (5, 0) is Euclidean-farther but Mahalanobis-nearer than (0, 2)."""
    prior = Gaussian(np.zeros(4), np.diag([99.0, 1.0, 0.0 + 1e-9, 1.0]))
    m = PositionModel(sigma_x=1.0, sigma_y=1.0)
    Z = np.array([[0.0, 2.0], [5.0, 0.0]])
    res = nearest_neighbour_update(prior, Z, m)
    assert res.chosen == 1
    np.testing.assert_array_equal(res.beta, [0.0, 1.0])
    assert res.beta0 == 0.0 and res.updated
    ref = ekf_update(prior, Z[1], m)
    np.testing.assert_array_equal(res.posterior.x, ref.posterior.x)
    np.testing.assert_array_equal(res.posterior.P, ref.posterior.P)
    np.testing.assert_array_equal(res.nu, ref.nu)
    assert res.nis == pytest.approx(ref.nis)


def test_nearest_neighbour_tie_goes_to_the_lowest_row():
    Z = np.array([[2.0, 0.0], [0.0, 2.0], [-2.0, 0.0]])
    assert nearest_neighbour_update(PRIOR, Z, UNIT).chosen == 0


def test_nothing_gated_returns_the_prior():
    Z = np.array([[100.0, 0.0]])
    for res in (
        nearest_neighbour_update(PRIOR, Z, UNIT),
        pda_update(PRIOR, Z, UNIT, clutter_density=1e-3, pd=0.9),
        pda_update(PRIOR, np.zeros((0, 2)), UNIT, clutter_density=1e-3, pd=0.9),
    ):
        assert res.posterior is PRIOR
        assert res.beta0 == 1.0 and not res.updated and res.chosen is None
        np.testing.assert_array_equal(res.nu, [0.0, 0.0])


# -- PDA -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "model",
    [
        PositionModel(sigma_x=21.1, sigma_y=8.2, rho=0.82),
        RangeBearingModel(sensor_xy=(-3000.0, 500.0), sigma_r=20.0, sigma_bearing=2e-3),
        BearingModel(sensor_xy=(100.0, -4000.0), sigma_bearing=1e-3),
    ],
    ids=["position", "range_bearing", "bearing"],
)
def test_pda_with_pd_1_and_no_clutter_is_the_ekf_update(model):
    prior = Gaussian(np.array([1000.0, 50.0, 2000.0, -20.0]), np.diag([400.0, 25, 300, 25]))
    pred = predict_measurement(prior, model)
    z = pred.zhat + 0.5 * np.sqrt(np.diag(pred.S))
    res = pda_update(prior, z[None, :], model, clutter_density=0.0, pd=1.0)
    ref = ekf_update(prior, z, model)
    assert res.beta0 == 0.0
    np.testing.assert_array_equal(res.beta, [1.0])
    np.testing.assert_allclose(res.posterior.x, ref.posterior.x, rtol=1e-15, atol=1e-12)
    np.testing.assert_allclose(res.posterior.P, ref.posterior.P, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(res.nu, ref.nu, rtol=1e-15)


def test_pda_without_gate_is_bit_for_bit_the_ekf():
    """pd = 1, λ = 0, P_G = 1 (no gate): β₁ = 1 exactly, so every operation reduces to the EKF's
    and the result is the same bits (a 0.99 gate would drop a correct return 1 % of the time)."""
    m = PositionModel(sigma_x=21.1, sigma_y=8.2, rho=0.82)
    prior = Gaussian(np.array([1000.0, 426.0, 0.0, 0.0]), np.diag([1e4, 1e2, 1e4, 1e2]))
    z = np.array([[1500.0, -400.0]])  # far outside a 0.99 gate
    res = pda_update(prior, z, m, clutter_density=0.0, pd=1.0, gate_probability=1.0)
    ref = ekf_update(prior, z[0], m)
    np.testing.assert_array_equal(res.posterior.x, ref.posterior.x)
    np.testing.assert_array_equal(res.posterior.P, ref.posterior.P)
    assert pda_update(prior, z, m, clutter_density=0.0, pd=1.0).posterior is prior


def test_pda_two_returns_oracle():
    """P⁻ = diag(3, 1, 3, 1), R = I ⇒ S = 4 I, K = 3/4 on positions, P^c = 0.75 on positions.
    z₁ = (2, 0): d² = 1; z₂ = (0, −4): d² = 4.  P_D = 0.9, P_G = 0.99, λ = 0.01:
    b = λ · 2π·4 · (1 − 0.891) / 0.9 = 0.0304385;  β = (e^{−1/2}, e^{−2}, b) / (sum)."""
    Z = np.array([[2.0, 0.0], [0.0, -4.0]])
    res = pda_update(PRIOR, Z, UNIT, clutter_density=0.01, pd=0.9, gate_probability=0.99)
    b = 0.01 * 8 * math.pi * (1 - 0.9 * 0.99) / 0.9
    e1, e2 = math.exp(-0.5), math.exp(-2.0)
    D = b + e1 + e2
    b1, b2, b0 = e1 / D, e2 / D, b / D
    assert (b1, b2, b0) == pytest.approx((0.78535173, 0.17523566, 0.03941262), abs=1e-8)
    np.testing.assert_allclose(res.beta, [b1, b2], rtol=1e-12)
    assert res.beta0 == pytest.approx(b0, rel=1e-12)
    nu_bar = np.array([2 * b1, -4 * b2])
    np.testing.assert_allclose(res.nu, nu_bar, rtol=1e-12)
    np.testing.assert_allclose(res.posterior.x, [0.75 * nu_bar[0], 0, 0.75 * nu_bar[1], 0])
    spread = np.diag([4 * b1, 16 * b2]) - np.outer(nu_bar, nu_bar)
    P_pos = b0 * 3.0 * np.eye(2) + (1 - b0) * 0.75 * np.eye(2) + 0.5625 * spread
    np.testing.assert_allclose(res.posterior.P[np.ix_([0, 2], [0, 2])], P_pos, rtol=1e-12)
    # velocities are uncorrelated with positions in P⁻, so they are untouched
    np.testing.assert_allclose(res.posterior.P[np.ix_([1, 3], [1, 3])], np.eye(2), rtol=1e-12)
    np.testing.assert_allclose(res.posterior.P[0, 1], 0.0, atol=1e-15)


def test_pda_posterior_is_symmetric_psd_and_weights_sum_to_one():
    rng = np.random.default_rng(11)
    model = RangeBearingModel(sensor_xy=(0.0, 0.0), sigma_r=20.0, sigma_bearing=2e-3)
    prior = Gaussian(np.array([5000.0, 10.0, 3000.0, -5.0]), np.diag([2500.0, 100, 2500, 100]))
    pred = predict_measurement(prior, model)
    for _ in range(50):
        Z = pred.zhat + rng.normal(size=(6, 2)) * 2.0 * np.sqrt(np.diag(pred.S))
        res = pda_update(prior, Z, model, clutter_density=1e-2, pd=0.8, prediction=pred)
        P = res.posterior.P
        np.testing.assert_array_equal(P, P.T)
        assert np.linalg.eigvalsh(P).min() > 0.0
        assert res.beta.sum() + res.beta0 == pytest.approx(1.0, abs=1e-14)


def test_pda_weights_limits():
    S = np.eye(2)
    beta, beta0 = pda_weights([0.5, 2.0], S, pd=0.0, clutter_density=1.0, gate_probability=0.99)
    assert beta0 == 1.0 and np.all(beta == 0.0)
    beta, beta0 = pda_weights([0.5, 2.0], S, pd=1.0, clutter_density=0.0, gate_probability=0.99)
    assert beta0 == 0.0
    np.testing.assert_allclose(beta, np.exp([-0.25, -1.0]) / np.exp([-0.25, -1.0]).sum())
    # no gate (P_G = 1) and far returns: no 0/0, the nearer return takes the weight
    beta, beta0 = pda_weights([4000.0, 4010.0], S, pd=1.0, clutter_density=0.0, gate_probability=1)
    np.testing.assert_allclose(beta, [1 / (1 + math.exp(-5.0)), 1 / (1 + math.exp(5.0))])
    with pytest.raises(ValueError, match="clutter_density"):
        pda_weights([1.0], S, pd=0.5, clutter_density=-1.0, gate_probability=0.99)
    with pytest.raises(ValueError, match="pd"):
        pda_weights([1.0], S, pd=1.5, clutter_density=1.0, gate_probability=0.99)


def test_pda_model_pd_is_the_default():
    m = PositionModel(sigma_x=1.0, sigma_y=1.0, pd=0.7)
    Z = np.array([[1.0, 0.0], [0.0, 1.5]])
    a = pda_update(PRIOR, Z, m, clutter_density=0.02)
    b = pda_update(PRIOR, Z, m, clutter_density=0.02, pd=0.7)
    np.testing.assert_array_equal(a.posterior.P, b.posterior.P)


# -- information-reduction factor -------------------------------------------------------------


def test_q2_without_clutter_is_pd_times_pg():
    rng = np.random.default_rng(0)
    assert information_reduction_factor(0.9, 2, 0.0, rng, 0.99) == pytest.approx(0.9 * 0.99)
    assert information_reduction_factor(1.0, 1, 0.0, rng, 1.0) == 1.0
    assert information_reduction_factor(0.0, 2, 3.0, rng) == 0.0


def test_q2_is_deterministic_decreasing_and_bounded():
    qs = [
        information_reduction_factor(0.9, 2, mu, np.random.default_rng(7), 0.99)
        for mu in (0.0, 0.1, 0.3, 1.0, 3.0)
    ]
    assert qs[1] == information_reduction_factor(0.9, 2, 0.1, np.random.default_rng(7), 0.99)
    assert all(a > b for a, b in zip(qs, qs[1:], strict=False))
    assert 0.0 < qs[-1] < qs[0] == pytest.approx(0.891)
    with pytest.raises(ValueError, match="P_G = 1"):
        information_reduction_factor(0.9, 2, 0.5, np.random.default_rng(0), 1.0)
    with pytest.raises(ValueError, match="clutter_in_gate"):
        information_reduction_factor(0.9, 2, -0.5, np.random.default_rng(0))


def test_q2_table_is_the_factor_on_a_grid():
    grid = np.array([0.0, 0.25, 0.5, 1.0, 2.0])
    tab = information_reduction_table(0.9, 2, grid, np.random.default_rng(3), 0.99, 500)
    for mu, q in zip(grid, tab, strict=True):
        one = information_reduction_factor(0.9, 2, mu, np.random.default_rng(3), 0.99, 500)
        assert q == pytest.approx(one, rel=1e-10, abs=1e-12)
    assert tab[0] == pytest.approx(0.891, rel=1e-12)
    assert np.all(np.diff(tab) < 0.0)
    np.testing.assert_array_equal(
        information_reduction_table(0.7, 1, [0.0, 0.0], np.random.default_rng(0), 1.0), [0.7, 0.7]
    )
    with pytest.raises(ValueError, match="clutter_in_gate"):
        information_reduction_table(0.9, 2, [[0.1]], np.random.default_rng(0))


def test_q2_matches_the_mean_pda_covariance_reduction():
    """E[P⁻ − P⁺] = q₂ K S Kᵀ over dwells simulated from the model (truth drawn from the
    prior, so ν ~ N(0, S); clutter uniform in the ±6σ window, which contains the gate)."""
    rng = np.random.default_rng(2026)
    m = PositionModel(sigma_x=20.0, sigma_y=8.0, rho=0.6, pd=0.9, clutter_rate=4.0)
    prior = Gaussian(np.array([0.0, 10.0, 0.0, 5.0]), np.diag([900.0, 100.0, 400.0, 100.0]))
    pred = predict_measurement(prior, m)
    L = np.linalg.cholesky(prior.P)
    n_trials = 3000
    reduction = np.zeros((4, 4))
    density = 0.0
    for _ in range(n_trials):
        x_true = prior.x + L @ rng.standard_normal(4)
        dwell = simulate_dwell(m, x_true, prior.x, pred.S, rng, clutter_window_sigma=6.0)
        density = dwell.clutter_density
        res = pda_update(prior, dwell.z, m, clutter_density=density, prediction=pred)
        reduction += prior.P - res.posterior.P
    reduction /= n_trials
    mu = expected_clutter_in_gate(density, pred.S, 0.99)
    assert 0.5 < mu < 1.5
    q2 = information_reduction_factor(0.9, 2, mu, np.random.default_rng(1), 0.99, 20000)
    KSK = pred.K @ pred.S @ pred.K.T
    empirical = np.trace(reduction) / np.trace(KSK)
    assert 0.4 < q2 < 0.85
    assert empirical == pytest.approx(q2, abs=0.03)


def test_streamed_q2_table_is_the_table_from_the_same_draws():
    """information_reduction_table_streamed: the same estimator and draws as the table, so for
    one generator state the same values (to rounding and the Poisson tails), on both sides of
    4, in one and two dimensions."""
    for dz, grid in ((1, np.linspace(0.0, 4.0, 81)), (2, np.array([0.0, 0.3, 4.0, 10.0, 30.0]))):
        a = information_reduction_table(0.9, dz, grid, np.random.default_rng(5), 0.99, 400)
        b = information_reduction_table_streamed(0.9, dz, grid, np.random.default_rng(5), 0.99, 400)
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-11)
    np.testing.assert_array_equal(
        information_reduction_table_streamed(0.7, 1, [0.0], np.random.default_rng(0), 1.0), [0.7]
    )
    with pytest.raises(ValueError, match="P_G = 1"):
        information_reduction_table_streamed(0.9, 2, [0.5], np.random.default_rng(0), 1.0)
