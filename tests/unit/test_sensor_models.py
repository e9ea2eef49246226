"""Sensor models: oracle values, Jacobians against finite differences, wrapping, coverage."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from covnet.core.sensing import correlated_noise, information_gain, position_matrix
from covnet.core.sensor_models import (
    SENSOR_MODELS,
    BearingModel,
    FieldOfView,
    PositionModel,
    RangeBearingModel,
    innovation,
    predicted_information,
    wrap_angle,
)

PAPER_S1 = dict(sigma_x=21.1, sigma_y=8.2, rho=0.82)


def _models(sensor_xy=(0.0, 0.0)):
    return [
        PositionModel(sensor_xy=sensor_xy, **PAPER_S1),
        RangeBearingModel(sensor_xy=sensor_xy, sigma_r=20.0, sigma_bearing=2e-3),
        BearingModel(sensor_xy=sensor_xy, sigma_bearing=1e-3),
    ]


# -- oracles ---------------------------------------------------------------------------------


def test_position_model_is_the_paper_sensor():
    m = PositionModel(**PAPER_S1)
    np.testing.assert_array_equal(m.R, correlated_noise(21.1, 8.2, 0.82))
    x = np.array([100.0, 426.0, -50.0, 3.0])
    np.testing.assert_array_equal(m.jacobian(x), position_matrix())
    np.testing.assert_array_equal(m.h(x), position_matrix() @ x)
    assert m.angle_components == (False, False)
    J = predicted_information(m, x, pd=1.0)
    np.testing.assert_allclose(J, information_gain(position_matrix(), m.R), rtol=1e-12, atol=1e-18)


def test_range_bearing_oracle_3_4_5():
    """Sensor at (1, 2), target at (4, 6): dx = 3, dy = 4, r = 5."""
    m = RangeBearingModel(sensor_xy=(1.0, 2.0), sigma_r=10.0, sigma_bearing=0.01)
    x = np.array([4.0, 7.0, 6.0, -1.0])
    np.testing.assert_allclose(m.h(x), [5.0, math.atan2(4.0, 3.0)], rtol=1e-15)
    expected = [[3 / 5, 0, 4 / 5, 0], [-4 / 25, 0, 3 / 25, 0]]
    np.testing.assert_allclose(m.jacobian(x), expected, rtol=1e-15)
    np.testing.assert_array_equal(m.R, np.diag([100.0, 1e-4]))
    assert m.angle_components == (False, True)


def test_bearing_oracle():
    m = BearingModel(sensor_xy=(0.0, 0.0), sigma_bearing=1e-3)
    x = np.array([0.0, 1.0, 2.0, 0.0])  # straight north of the sensor
    np.testing.assert_allclose(m.h(x), [math.pi / 2], rtol=1e-15)
    np.testing.assert_allclose(m.jacobian(x), [[-2 / 4, 0, 0, 0]], atol=1e-17)
    np.testing.assert_array_equal(m.R, [[1e-6]])
    assert m.dim_z == 1 and m.angle_components == (True,)


def test_predicted_information_oracle_bearing():
    """J = pd Hᵀ H / σ² with H = [−dy/r², 0, dx/r², 0]."""
    m = BearingModel(sensor_xy=(0.0, 0.0), sigma_bearing=0.01, pd=0.9)
    x = np.array([300.0, 0.0, 400.0, 0.0])
    h = np.array([-400.0 / 250000, 0.0, 300.0 / 250000, 0.0])
    np.testing.assert_allclose(predicted_information(m, x), 0.9 * np.outer(h, h) / 1e-4, rtol=1e-12)
    np.testing.assert_allclose(
        predicted_information(m, x, pd=1.0), np.outer(h, h) / 1e-4, rtol=1e-12
    )


@pytest.mark.parametrize("model", _models((10.0, -20.0)), ids=["position", "rb", "bearing"])
def test_the_noise_factor_is_rs_cholesky_factor_read_only(model):
    assert model.L.tobytes() == np.linalg.cholesky(model.R).tobytes()
    assert not model.L.flags.writeable


@pytest.mark.parametrize("model", _models((10.0, -20.0)), ids=["position", "rb", "bearing"])
def test_batched_equals_one_at_a_time(model):
    rng = np.random.default_rng(0)
    X = rng.normal(scale=1000.0, size=(3, 5, 4))
    h = model.h(X)
    H = model.jacobian(X)
    J = predicted_information(model, X, pd=0.7)
    assert h.shape == (3, 5, model.dim_z) and H.shape == (3, 5, model.dim_z, 4)
    assert J.shape == (3, 5, 4, 4)
    for i in range(3):
        for j in range(5):
            np.testing.assert_array_equal(h[i, j], model.h(X[i, j]))
            np.testing.assert_array_equal(H[i, j], model.jacobian(X[i, j]))
            np.testing.assert_allclose(
                J[i, j], predicted_information(model, X[i, j], pd=0.7), rtol=1e-13, atol=0
            )
            Rinv = np.linalg.inv(model.R)
            expected = 0.7 * H[i, j].T @ Rinv @ H[i, j]
            np.testing.assert_allclose(J[i, j], expected, rtol=1e-9, atol=1e-12 * np.abs(J).max())


# -- Jacobians against central finite differences ----------------------------------------------

_coord = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)


@given(sx=_coord, sy=_coord, x=_coord, y=_coord, vx=_coord, vy=_coord)
def test_jacobian_matches_central_differences(sx, sy, x, y, vx, vy):
    state = np.array([x, vx, y, vy])
    r = math.hypot(x - sx, y - sy)
    assume(r >= 10.0)  # away from the sensor: the bearing's derivatives blow up as 1/r²
    for model in _models((sx, sy)):
        H = model.jacobian(state)
        H_fd = np.zeros_like(H)
        delta = 1e-4 * r
        for k in range(4):
            step = np.zeros(4)
            step[k] = delta
            diff = innovation(model.h(state + step), model.h(state - step), model.angle_mask)
            H_fd[:, k] = diff / (2 * delta)
        scale = np.abs(H).max()
        np.testing.assert_allclose(H_fd, H, rtol=1e-6, atol=1e-7 * scale)


def test_jacobian_at_the_sensor_raises():
    m = RangeBearingModel(sensor_xy=(5.0, 5.0), sigma_r=1.0, sigma_bearing=1.0)
    with pytest.raises(ValueError, match="r = 0"):
        m.jacobian(np.array([5.0, 1.0, 5.0, 1.0]))
    with pytest.raises(ValueError, match="r = 0"):
        BearingModel(sigma_bearing=1.0).jacobian(np.zeros(4))


# -- wrapping --------------------------------------------------------------------------------


@given(st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False))
def test_wrap_angle_properties(a):
    w = wrap_angle(a)
    assert isinstance(w, float)
    assert -math.pi < w <= math.pi
    k = (a - w) / (2 * math.pi)
    assert abs(k - round(k)) < 1e-9 * max(1.0, abs(a))
    assert wrap_angle(w) == w


def test_wrap_angle_edges():
    assert wrap_angle(math.pi) == math.pi
    assert wrap_angle(-math.pi) == math.pi
    assert wrap_angle(0.0) == 0.0
    above = math.nextafter(math.pi, 4.0)
    assert -math.pi < wrap_angle(above) <= math.pi
    a = np.array([3 * math.pi, -3 * math.pi, 2 * math.pi, -1e-300, 7.0])
    w = wrap_angle(a)
    assert isinstance(w, np.ndarray) and w.shape == a.shape
    assert np.all((w > -math.pi) & (w <= math.pi))
    np.testing.assert_allclose(w[:4], [math.pi, math.pi, 0.0, -1e-300], atol=1e-15)
    np.testing.assert_allclose(w[4], 7.0 - 2 * math.pi, rtol=1e-15)


def test_innovation_wraps_only_angle_components():
    z = np.array([[10.0, math.pi - 0.01], [10.0, 0.5]])
    zhat = np.array([4.0 * math.pi, -math.pi + 0.01])
    nu = innovation(z, zhat, (False, True))
    np.testing.assert_allclose(nu[:, 0], 10.0 - 4.0 * math.pi)  # range: not wrapped
    np.testing.assert_allclose(nu[0, 1], -0.02, atol=1e-14)
    np.testing.assert_allclose(nu[1, 1], wrap_angle(0.5 + math.pi - 0.01))
    with pytest.raises(ValueError, match="zhat"):
        innovation(z, np.zeros(3), (False, True))


# -- coverage --------------------------------------------------------------------------------


def test_coverage_range_and_sector():
    m = RangeBearingModel(
        sensor_xy=(0.0, 0.0),
        sigma_r=1.0,
        sigma_bearing=1.0,
        max_range_m=1000.0,
        fov=FieldOfView(center_deg=90.0, half_width_deg=45.0),
    )
    X = np.array(
        [
            [0.0, 0, 500.0, 0],  # north, 500 m: in
            [0.0, 0, 1001.0, 0],  # north, too far
            [500.0, 0, 500.0, 0],  # 45°: on the sector edge, in
            [500.0, 0, 400.0, 0],  # 38.7°: outside the sector
            [0.0, 0, -500.0, 0],  # south: outside
            [0.0, 0, 0.0, 0],  # at the sensor: no bearing
        ]
    )
    np.testing.assert_array_equal(m.in_coverage(X), [True, False, True, False, False, False])


def test_sector_across_the_pi_cut():
    fov = FieldOfView(center_deg=180.0, half_width_deg=10.0)
    b = np.radians([175.0, -175.0, 165.0, 0.0])
    np.testing.assert_array_equal(fov.contains(b), [True, True, False, False])
    assert bool(FieldOfView(0.0, 180.0).contains(math.pi))


def test_position_model_covers_everything_by_default():
    m = PositionModel(**PAPER_S1)
    X = np.array([[0.0, 0, 0, 0], [1e9, 0, -1e9, 0]])
    np.testing.assert_array_equal(m.in_coverage(X), [True, True])


# -- registry and validation -----------------------------------------------------------------


def test_registry():
    assert sorted(SENSOR_MODELS) == ["bearing", "position", "range_bearing"]
    for kind, cls in SENSOR_MODELS.items():
        assert cls.kind == kind
    m = SENSOR_MODELS["range_bearing"](sigma_r=20, sigma_bearing=0.002, sensor_xy=[0, 1])
    assert m.sensor_xy == (0.0, 1.0) and m.sigma_r == 20.0 and isinstance(m.sigma_r, float)


def _example_fields(cls):
    """A model's config fields with 0.5 for every required key (a valid sigma, rho), each
    passing its check."""
    f = cls.config_fields
    assert dataclasses.is_dataclass(f), f"{cls.kind}: config_fields is not a dataclass"
    required = [k for k in dataclasses.fields(f) if k.default is dataclasses.MISSING]
    for k in required:
        assert k.metadata.get("check", float)(0.5) == 0.5
    return f(**{k.name: 0.5 for k in required})


@pytest.mark.parametrize("kind", sorted(SENSOR_MODELS))
def test_every_registry_entry_carries_what_the_runners_ask(kind):
    """Each entry: built from its config fields, its h and H agree, its shapes follow dim_z,
    its coverage follows undefined_at_sensor, ``W = L⁻¹H`` gives ``HᵀR⁻¹H``."""
    cls = SENSOR_MODELS[kind]
    m = cls.from_fields(_example_fields(cls), sensor_xy=(10.0, -20.0), pd=0.5)
    assert type(m) is cls and m.kind == kind and m.pd == 0.5
    assert len(m.angle_components) == m.dim_z == m.R.shape[0] == m.R.shape[1]
    X = np.array([[3010.0, 5.0, 3980.0, -3.0], [-200.0, 0.0, 700.0, 1.0]])
    assert m.h(X).shape == (2, m.dim_z) and m.jacobian(X).shape == (2, m.dim_z, 4)
    eps = 1e-4
    for x in X:
        fd = np.stack([innovation(m.h(x + eps * e), m.h(x - eps * e), m.angle_components)
                       / (2 * eps) for e in np.eye(4)], axis=-1)  # fmt: skip
        np.testing.assert_allclose(m.jacobian(x), fd, rtol=1e-6, atol=1e-9)
    W = m.whitened_jacobian(X)
    np.testing.assert_allclose(
        np.swapaxes(W, -1, -2) @ W, predicted_information(m, X, pd=1.0), rtol=1e-10, atol=1e-14
    )
    at_sensor = np.array([10.0, 0.0, -20.0, 0.0])
    assert bool(m.in_coverage(at_sensor)) is not cls.undefined_at_sensor


def test_models_are_frozen_and_R_read_only():
    m = BearingModel(sigma_bearing=1e-3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.pd = 0.5  # type: ignore[misc]
    with pytest.raises(ValueError):
        m.R[0, 0] = 1.0
    assert m == BearingModel(sigma_bearing=1e-3)
    assert hash(m) == hash(BearingModel(sigma_bearing=1e-3))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(sigma_x=-1.0, sigma_y=1.0), "sigma_x"),
        (dict(sigma_x=1.0, sigma_y=1.0, rho=1.0), "rho"),
        (dict(sigma_x=1.0, sigma_y=1.0, pd=1.5), "pd"),
        (dict(sigma_x=1.0, sigma_y=1.0, clutter_rate=-0.1), "clutter_rate"),
        (dict(sigma_x=1.0, sigma_y=1.0, max_range_m=0.0), "max_range_m"),
        (dict(sigma_x=1.0, sigma_y=1.0, sensor_xy=(1.0, 2.0, 3.0)), "sensor_xy"),
    ],
    ids=["sigma", "rho", "pd", "clutter", "range", "xy"],
)
def test_position_model_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PositionModel(**kwargs)


def test_other_validation():
    with pytest.raises(ValueError, match="sigma_bearing"):
        BearingModel(sigma_bearing=0.0)
    with pytest.raises(ValueError, match="sigma_r"):
        RangeBearingModel(sigma_r=math.nan, sigma_bearing=1.0)
    with pytest.raises(ValueError, match="half_width_deg"):
        FieldOfView(center_deg=0.0, half_width_deg=0.0)
    with pytest.raises(ValueError, match="x: expected shape"):
        BearingModel(sigma_bearing=1.0).h(np.zeros(3))
    with pytest.raises(ValueError, match="pd"):
        predicted_information(BearingModel(sigma_bearing=1.0), np.ones(4), pd=-1.0)
