"""Equivalences and invariants of the many-target filters, over random problems:
EKF == KF for the linear model, PDA(pd = 1, no clutter, one return) == EKF, nearest neighbour ==
EKF with the nearest return, posteriors symmetric PSD and never above the prior, the UKF equals
the KF for the linear model, and the allocator's information form equals the filter's
covariance."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.association import gate_threshold, nearest_neighbour_update, pda_update
from covnet.core.ekf import ekf_update, predict_measurement, ukf_update
from covnet.core.gaussian import Gaussian
from covnet.core.kalman import update, update_information
from covnet.core.sensing import position_matrix
from covnet.core.sensor_models import (
    BearingModel,
    PositionModel,
    RangeBearingModel,
    predicted_information,
)

_unit = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)


@st.composite
def priors(draw):
    """A prior 1-10 km from the origin with an SPD covariance of 10-1000 m scale."""
    A = draw(arrays(np.float64, (4, 4), elements=_unit))
    scale = draw(st.floats(10.0, 1000.0))
    P = scale * (A @ A.T + 0.1 * np.eye(4))
    r = draw(st.floats(1000.0, 10000.0))
    a = draw(st.floats(-np.pi, np.pi))
    v = draw(arrays(np.float64, (2,), elements=st.floats(-300.0, 300.0)))
    return Gaussian(np.array([r * np.cos(a), v[0], r * np.sin(a), v[1]]), P)


@st.composite
def models(draw, kinds=("position", "range_bearing", "bearing")):
    kind = draw(st.sampled_from(kinds))
    xy = (draw(st.floats(-500.0, 500.0)), draw(st.floats(-500.0, 500.0)))
    if kind == "position":
        return PositionModel(
            sensor_xy=xy,
            sigma_x=draw(st.floats(1.0, 50.0)),
            sigma_y=draw(st.floats(1.0, 50.0)),
            rho=draw(st.floats(-0.95, 0.95)),
        )
    if kind == "range_bearing":
        return RangeBearingModel(
            sensor_xy=xy,
            sigma_r=draw(st.floats(1.0, 50.0)),
            sigma_bearing=draw(st.floats(1e-4, 1e-2)),
        )
    return BearingModel(sensor_xy=xy, sigma_bearing=draw(st.floats(1e-4, 1e-2)))


def _offsets(draw, pred, k):
    """k measurements within ±2σ of the prediction (σ from S)."""
    u = draw(arrays(np.float64, (k, pred.dim_z), elements=st.floats(-2.0, 2.0)))
    return pred.zhat + u * np.sqrt(np.diag(pred.S))


def _close(a, b, scale, rtol=1e-9):
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * scale)


@given(priors(), models(("position",)), arrays(np.float64, (2,), elements=st.floats(-100, 100)))
def test_ekf_equals_kalman_for_the_position_model(prior, model, dz):
    z = prior.x[[0, 2]] + dz
    got = ekf_update(prior, z, model)
    ref = update(prior, z, position_matrix(), model.R)
    _close(got.posterior.x, ref.x, np.abs(ref.x).max(), 1e-12)
    _close(got.posterior.P, ref.P, np.abs(ref.P).max(), 1e-12)


@given(priors(), models(("position",)), arrays(np.float64, (2,), elements=st.floats(-100, 100)))
def test_ukf_equals_kalman_for_the_position_model(prior, model, dz):
    z = prior.x[[0, 2]] + dz
    got = ukf_update(prior, z, model)
    ref = update(prior, z, position_matrix(), model.R)
    _close(got.posterior.x, ref.x, np.abs(ref.x).max(), 1e-8)
    _close(got.posterior.P, ref.P, np.abs(ref.P).max(), 1e-8)


@given(st.data(), priors(), models())
def test_pda_with_certain_detection_and_no_clutter_is_the_ekf(data, prior, model):
    pred = predict_measurement(prior, model)
    z = _offsets(data.draw, pred, 1)
    d2 = float(pred.mahalanobis2(pred.innovations(z[0])))
    for pg in (0.99, 1.0):
        res = pda_update(prior, z, model, clutter_density=0.0, pd=1.0, gate_probability=pg)
        if d2 > gate_threshold(pred.dim_z, pg):  # outside the gate: nothing to update with
            assert res.posterior is prior
            continue
        ref = ekf_update(prior, z[0], model, prediction=pred)
        _close(res.posterior.x, ref.posterior.x, np.abs(ref.posterior.x).max(), 1e-14)
        _close(res.posterior.P, ref.posterior.P, np.abs(ref.posterior.P).max(), 1e-14)


@given(st.data(), priors(), models(), st.integers(0, 6))
def test_nearest_neighbour_is_the_ekf_with_the_nearest_gated_return(data, prior, model, k):
    pred = predict_measurement(prior, model)
    # returns up to ±5σ away, so some fall outside the gate
    Z = 2.5 * (_offsets(data.draw, pred, k) - pred.zhat) + pred.zhat
    res = nearest_neighbour_update(prior, Z, model, prediction=pred)
    d2 = pred.mahalanobis2(pred.innovations(Z))
    gated = np.flatnonzero(d2 <= gate_threshold(pred.dim_z, 0.99))
    np.testing.assert_array_equal(res.gated, gated)
    if gated.size == 0:
        assert res.posterior is prior and res.chosen is None
        return
    best = int(gated[np.argmin(d2[gated])])
    assert res.chosen == best
    ref = ekf_update(prior, Z[best], model, prediction=pred)
    np.testing.assert_array_equal(res.posterior.x, ref.posterior.x)
    np.testing.assert_array_equal(res.posterior.P, ref.posterior.P)


@given(
    st.data(),
    priors(),
    models(),
    st.integers(0, 8),
    st.floats(0.05, 1.0),
    st.floats(0.0, 1e-2),
)
def test_pda_posterior_symmetric_psd(data, prior, model, k, pd, lam):
    pred = predict_measurement(prior, model)
    Z = _offsets(data.draw, pred, k)
    res = pda_update(prior, Z, model, clutter_density=lam, pd=pd, prediction=pred)
    P = res.posterior.P
    np.testing.assert_array_equal(P, P.T)
    scale = np.abs(prior.P).max()
    assert np.linalg.eigvalsh(P).min() > -1e-9 * scale
    assert np.isclose(res.beta.sum() + res.beta0, 1.0, atol=1e-12)
    # the PDA posterior never goes below the one-correct-return posterior
    assert np.linalg.eigvalsh(P - pred.P_detected).min() > -1e-9 * scale


@given(priors(), models())
def test_ekf_covariance_never_above_the_prior(prior, model):
    pred = predict_measurement(prior, model)
    P = pred.P_detected
    np.testing.assert_array_equal(P, P.T)
    scale = np.abs(prior.P).max()
    assert np.linalg.eigvalsh(prior.P - P).min() > -1e-9 * scale
    assert np.linalg.eigvalsh(P).min() > -1e-9 * scale


@given(priors(), models())
def test_information_form_equals_the_filter_covariance(prior, model):
    """P(a) = (P⁻⁻¹ + J)⁻¹ with J = Hᵀ R⁻¹ H at x̂⁻ (pd = 1) is the EKF's Joseph P⁺: what the
    allocator scores is what the filter gets when the dwell detects."""
    J = predicted_information(model, prior.x, pd=1.0)
    P_info = np.linalg.inv(np.linalg.inv(prior.P) + J)
    pred = predict_measurement(prior, model)
    _close(pred.P_detected, P_info, np.abs(prior.P).max(), 1e-7)
    # the same through kalman.update_information with the Jacobian as H
    zero = np.zeros(model.dim_z)
    post = update_information(prior, [(zero, model.jacobian(prior.x), model.R)])
    _close(pred.P_detected, post.P, np.abs(prior.P).max(), 1e-7)
