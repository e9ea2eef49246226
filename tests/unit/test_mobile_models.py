"""Mobile models (spec §2, §3): the mode table, platform motion, R, Pd, streams."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.mobile.models import (
    MODE_NAMES,
    MODE_NORM,
    MODES,
    Sensors,
    TargetModels,
    bell,
    candidate_states,
    cv_model,
    detection_probability,
    draw_detection,
    move_platforms,
    noise_covariance,
    noise_growth,
    pair_stream,
    predict_tracks,
    stream,
    usage_cost,
)

H = np.sqrt(2.0) / 2.0


def test_mode_table_is_counter_clockwise_from_east_after_stay():
    assert MODE_NAMES == ("stay", "E", "NE", "N", "NW", "W", "SW", "S", "SE")
    np.testing.assert_array_equal(MODES[0], [0.0, 0.0])
    angles = np.degrees(np.arctan2(MODES[1:, 1], MODES[1:, 0])) % 360.0
    np.testing.assert_allclose(angles, [0, 45, 90, 135, 180, 225, 270, 315], atol=1e-12)
    # the patent's two fixed points (1-based): 3rd "up and to the right", 8th "straight down"
    np.testing.assert_allclose(MODES[2], [H, H])
    np.testing.assert_allclose(MODES[7], [0.0, -1.0])


def test_mode_norms_are_zero_or_one():
    norms = np.linalg.norm(MODES, axis=1)
    np.testing.assert_allclose(norms, MODE_NORM, atol=1e-15)
    assert set(np.round(norms, 12)) == {0.0, 1.0}
    assert not MODES.flags.writeable


def test_platform_motion_and_candidates():
    pos = np.array([[0.0, 0.0], [300.0, 300.0]])
    speed = np.array([3.0, 2.5])
    new, vel = move_platforms(pos, speed, np.array([3, 6]), T=2.0)
    np.testing.assert_allclose(new, [[0.0, 6.0], [300.0 - 5.0 * H, 300.0 - 5.0 * H]])
    np.testing.assert_allclose(vel, [[0.0, 3.0], [-2.5 * H, -2.5 * H]])
    q, qdot = candidate_states(pos, speed, T=2.0)
    assert q.shape == qdot.shape == (2, 9, 2)
    np.testing.assert_allclose(q[0, 3], new[0])
    np.testing.assert_allclose(q[1, 6], new[1])
    np.testing.assert_array_equal(q[:, 0], pos)  # stay


def test_cv_model_and_batched_prediction():
    A, B = cv_model(2.0)
    np.testing.assert_array_equal(A[:2, :2], [[1.0, 2.0], [0.0, 1.0]])
    np.testing.assert_array_equal(B[:, 0], [2.0, 2.0, 0.0, 0.0])
    tm = TargetModels(np.stack([A, A]), np.stack([B, B]), np.array([0.05, 0.5]))
    x = np.array([[1.0, 1.0, 2.0, -1.0], [0.0, 0.0, 0.0, 0.0]])
    P = np.stack([np.eye(4), 2 * np.eye(4)])
    xp, Pp = predict_tracks(x, P, tm)
    for i in range(2):
        Q = tm.sigma_a[i] ** 2 * B @ B.T
        np.testing.assert_allclose(xp[i], A @ x[i])
        np.testing.assert_allclose(Pp[i], A @ P[i] @ A.T + Q, rtol=1e-14)


def test_noise_growth_matches_the_patent_product_for_diagonal_R0():
    x = np.array([130.0, 1.0, 40.0, -2.0])
    q, qdot = np.array([100.0, 0.0]), np.array([3.0, 0.0])
    L = np.array([25.0, 50.0])
    R0 = np.diag([4.0, 6.25])
    D = np.array([np.hypot(30.0, -2.0), np.hypot(40.0, -2.0)])
    expected = (np.eye(2) + np.diag(D / L)) @ R0  # the patent's (I + D L⁻¹) R0
    R = noise_covariance(noise_growth(x, q, qdot, L, True), R0)
    np.testing.assert_allclose(R, expected, rtol=1e-14)
    R_pos = noise_covariance(noise_growth(x, q, qdot, L, False), R0)
    np.testing.assert_allclose(np.diag(R_pos), [4.0 * (1 + 30 / 25), 6.25 * (1 + 40 / 50)])


def test_noise_covariance_is_symmetric_positive_definite_with_correlation():
    R0 = np.array([[4.0, 1.5], [1.5, 2.0]])
    g = np.array([[1.0, 1.0], [3.0, 1.2], [10.0, 1.0]])
    R = noise_covariance(g, R0)
    np.testing.assert_array_equal(R, np.swapaxes(R, -1, -2))
    assert np.linalg.eigvalsh(R).min() > 0
    np.testing.assert_allclose(R[0], R0)
    G = np.diag(np.sqrt(g[1]))
    np.testing.assert_allclose(R[1], G @ R0 @ G)


def test_bell_detection_probability():
    x = np.array([150.0, 0.0, 0.0, 0.0])
    q = np.zeros(2)
    # d = 150 / 60 = 2.5: 0.95 / (1 + 2.5⁴) ≈ 0.0237 (spec: "Pd ≈ 0.02 at 150 m")
    Pd = detection_probability(x, q, 60.0, 0.95, 1.0, 2.0, 0.0)
    assert Pd == pytest.approx(0.95 / (1 + 2.5**4), rel=1e-14)
    assert detection_probability(np.zeros(4), q, 60.0, 0.95, 1.0, 2.0, 0.0) == 0.95
    # c > 0: a ring, best at d = c, blind inside
    ring = [detection_probability(np.array([r, 0, 0, 0.0]), q, 10.0, 0.9, 1.0, 2.0, 3.0)
            for r in (0.0, 30.0, 60.0)]  # fmt: skip
    assert ring[1] == pytest.approx(0.9) and ring[0] < 0.2 and ring[2] < 0.2
    # a track covariance widens the field
    P_pos = np.diag([900.0, 900.0])
    wide = detection_probability(x, q, 60.0, 0.95, 1.0, 2.0, 0.0, P_pos=P_pos)
    d = 150.0 / np.sqrt(3600.0 + 900.0)
    assert wide == pytest.approx(0.95 / (1 + d**4), rel=1e-14) and wide > Pd


def test_far_away_detection_is_zero_without_warnings():
    assert bell(np.array([1e200]), 0.95, 1.0, 2.0, 0.0)[0] == 0.0


def test_streams_follow_the_spec_keys():
    a = stream(7, 1).standard_normal(3)
    b = np.random.default_rng([7, 1]).standard_normal(3)
    np.testing.assert_array_equal(a, b)
    c = pair_stream(7, 4, 2, 1).random()
    assert c == np.random.default_rng([7, 3, 4, 2, 1]).random()


def test_draw_detection_consumes_the_stream_the_same_way():
    R = np.array([[4.0, 1.0], [1.0, 3.0]])
    hit, z1 = draw_detection(np.random.default_rng(3), 1.0, np.zeros(2), R)
    miss, z0 = draw_detection(np.random.default_rng(3), 0.0, np.zeros(2), R)
    assert hit and not miss
    np.testing.assert_array_equal(z0, z1)


def test_usage_cost_and_subset():
    b = usage_cost(np.array([1.0, 0.8]), np.array([0.0, 0.5]))
    np.testing.assert_allclose(b[0], 1.0)
    np.testing.assert_allclose(b[1], [0.8] + [1.3] * 8)
    s = Sensors(
        np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]), np.array([1.0, 2.0, 3.0]),
        np.stack([np.eye(2)] * 3), np.full(3, 60.0), np.ones(3), np.zeros(3),
        np.array([np.inf, 1.0, 2.0]),
    )  # fmt: skip
    sub = s.subset(np.array([2, 0]))
    assert sub.count == 2
    np.testing.assert_array_equal(sub.speed, [3.0, 1.0])
    np.testing.assert_array_equal(sub.capacity, [2.0, np.inf])
