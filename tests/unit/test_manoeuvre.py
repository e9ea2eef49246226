"""Manoeuvring truth: CV equivalence, exact coordinated turn, constant-acceleration oracle."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.manoeuvre import Acceleration, Turn, ct_transition, manoeuvring_trajectory
from covnet.core.motion import cv_transition, dwna_noise_gain
from covnet.core.truth import linear_gaussian_trajectory

X0 = np.array([0.0, 426.0, 0.0, 0.0])


def test_no_segments_is_the_linear_gaussian_trajectory():
    a = manoeuvring_trajectory(X0, 1.0, 0.5, 100, np.random.default_rng(2026))
    b = linear_gaussian_trajectory(
        X0, cv_transition(1.0), dwna_noise_gain(1.0), 0.5, 100, np.random.default_rng(2026)
    )
    np.testing.assert_array_equal(a, b)


def test_zero_turn_rate_is_constant_velocity():
    np.testing.assert_array_equal(ct_transition(0.0, 2.0), cv_transition(2.0))
    a = manoeuvring_trajectory(X0, 1.0, 0.5, 50, np.random.default_rng(1), [Turn(10, 30, 0.0)])
    b = manoeuvring_trajectory(X0, 1.0, 0.5, 50, np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    # and a tiny rate is continuous with it
    np.testing.assert_allclose(ct_transition(1e-12, 2.0), cv_transition(2.0), atol=1e-11)


def test_quarter_turn_transition_oracle():
    """ω T = π/2, T = 1: sin = 1, cos = 0, so sin ωT/ω = (1 − cos ωT)/ω = 2/π."""
    F = ct_transition(math.pi / 2, 1.0)
    a = 2 / math.pi
    expected = [[1, a, 0, -a], [0, 0, 0, -1], [0, a, 1, a], [0, 1, 0, 0]]
    np.testing.assert_allclose(F, expected, atol=1e-15)


def test_full_turn_returns_to_the_start_and_keeps_the_speed():
    T, n_turn = 2.0, 36
    omega = 2 * math.pi / (n_turn * T)
    k0 = 5
    x0 = np.array([100.0, 150.0, -50.0, 80.0])
    traj = manoeuvring_trajectory(
        x0, T, 0.0, 60, np.random.default_rng(0), [Turn(k0, k0 + n_turn, omega)]
    )
    start, end = traj[k0 - 1], traj[k0 + n_turn - 1]  # rows are scans 1..N
    np.testing.assert_allclose(end, start, atol=1e-9 * np.abs(start).max())
    speed = np.hypot(traj[:, 1], traj[:, 3])
    np.testing.assert_allclose(speed, math.hypot(150.0, 80.0), rtol=1e-13)
    # radius of the circle v/ω: the farthest point is a diameter away from the start
    turn = traj[k0 - 1 : k0 + n_turn]
    d = np.hypot(turn[:, 0] - start[0], turn[:, 2] - start[2])
    assert d.max() == pytest.approx(2 * math.hypot(150.0, 80.0) / omega, rel=1e-3)


def test_turn_changes_the_heading_by_omega_times_duration():
    omega, k0, k1 = 0.05, 40, 60  # "turning between scans 40 and 60"
    traj = manoeuvring_trajectory(
        X0, 1.0, 0.0, 100, np.random.default_rng(0), [Turn(k0, k1, omega)]
    )
    heading = np.arctan2(traj[:, 3], traj[:, 1])
    assert heading[k0 - 1] == pytest.approx(0.0, abs=1e-15)
    assert heading[k1 - 1] == pytest.approx(omega * (k1 - k0), rel=1e-12)
    assert heading[-1] == pytest.approx(omega * (k1 - k0), rel=1e-12)  # straight again
    np.testing.assert_allclose(traj[k0 - 1], [40 * 426.0, 426.0, 0.0, 0.0], atol=1e-9)


def test_constant_acceleration_oracle():
    """p(t) = p₀ + v₀ t + a t²/2, v(t) = v₀ + a t over the segment (exact)."""
    T, k0, k1 = 0.5, 4, 14
    ax, ay = 3.0, -2.0
    traj = manoeuvring_trajectory(
        X0, T, 0.0, 20, np.random.default_rng(0), [Acceleration(k0, k1, ax, ay)]
    )
    p0 = traj[k0 - 1]
    t = (k1 - k0) * T
    expected = [
        p0[0] + p0[1] * t + 0.5 * ax * t * t,
        p0[1] + ax * t,
        p0[2] + p0[3] * t + 0.5 * ay * t * t,
        p0[3] + ay * t,
    ]
    np.testing.assert_allclose(traj[k1 - 1], expected, rtol=1e-13)
    # after the segment: constant velocity again
    np.testing.assert_allclose(traj[-1, [1, 3]], traj[k1 - 1, [1, 3]], rtol=1e-14)


def test_noise_is_added_in_every_segment():
    segs = [Turn(0, 10, 0.1), Acceleration(10, 20, 1.0, 0.0)]
    quiet = manoeuvring_trajectory(X0, 1.0, 0.0, 30, np.random.default_rng(3), segs)
    noisy = manoeuvring_trajectory(X0, 1.0, 0.5, 30, np.random.default_rng(3), segs)
    assert np.all(np.abs(noisy - quiet)[:, [1, 3]].max(axis=1) > 0.0)


@pytest.mark.parametrize(
    "segments, match",
    [
        ([Turn(0, 10, 0.1), Acceleration(9, 12, 1.0, 1.0)], "overlaps"),
        ([Turn(5, 31, 0.1)], "beyond n_scans"),
        (["turn"], "segments\\[0\\]"),
    ],
    ids=["overlap", "beyond", "type"],
)
def test_bad_segments(segments, match):
    with pytest.raises(ValueError, match=match):
        manoeuvring_trajectory(X0, 1.0, 0.5, 30, np.random.default_rng(0), segments)


def test_bad_arguments():
    with pytest.raises(ValueError, match="k0 < k1"):
        Turn(5, 5, 0.1)
    with pytest.raises(ValueError, match="omega"):
        Turn(0, 5, math.inf)
    with pytest.raises(ValueError, match="x0"):
        manoeuvring_trajectory(np.zeros(3), 1.0, 0.5, 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match="T"):
        manoeuvring_trajectory(X0, 0.0, 0.5, 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match="sigma_a"):
        manoeuvring_trajectory(X0, 1.0, -0.5, 3, np.random.default_rng(0))
