"""Dwell simulation: the target's return, Poisson clutter uniform in the window, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from covnet.core.detection import ClutterWindow, clutter_window, simulate_dwell
from covnet.core.sensor_models import (
    BearingModel,
    FieldOfView,
    PositionModel,
    RangeBearingModel,
    wrap_angle,
)

X_TRUE = np.array([3000.0, 100.0, 4000.0, -20.0])
S_RB = np.array([[900.0, 0.1], [0.1, 1e-5]])


def _radar(**kw):
    return RangeBearingModel(sensor_xy=(0.0, 0.0), sigma_r=20.0, sigma_bearing=2e-3, **kw)


def test_pd_1_no_clutter_gives_exactly_the_noisy_target_return():
    m = _radar(pd=1.0, clutter_rate=0.0)
    dwell = simulate_dwell(m, X_TRUE, X_TRUE, S_RB, np.random.default_rng(5))
    assert dwell.z.shape == (1, 2) and dwell.truth_row == 0
    # the same draws by hand: detection uniform, then the noise normals
    rng = np.random.default_rng(5)
    rng.random()
    e = rng.standard_normal(2)
    expected = m.h(X_TRUE) + np.linalg.cholesky(m.R) @ e
    expected[1] = wrap_angle(expected[1])
    np.testing.assert_allclose(dwell.z[0], expected, rtol=1e-15, atol=0)
    assert dwell.clutter_density == 0.0


def test_out_of_coverage_never_detected():
    far = _radar(pd=1.0, max_range_m=1000.0)
    behind = _radar(pd=1.0, fov=FieldOfView(center_deg=-90.0, half_width_deg=30.0))
    for m in (far, behind):
        for seed in range(20):
            d = simulate_dwell(m, X_TRUE, X_TRUE, S_RB, np.random.default_rng(seed))
            assert d.z.shape == (0, 2) and d.truth_row is None


def test_deterministic_for_a_given_generator():
    m = _radar(pd=0.8, clutter_rate=3.0)
    a = simulate_dwell(m, X_TRUE, X_TRUE, S_RB, np.random.default_rng(42))
    b = simulate_dwell(m, X_TRUE, X_TRUE, S_RB, np.random.default_rng(42))
    np.testing.assert_array_equal(a.z, b.z)
    assert a.truth_row == b.truth_row


def test_pd_changes_only_whether_the_target_is_reported():
    """The detection uniform and the noise come first: with the same generator the target's
    return is the same for any pd under which it is detected."""
    for seed in range(30):
        a = simulate_dwell(_radar(pd=1.0), X_TRUE, X_TRUE, S_RB, np.random.default_rng(seed))
        b = simulate_dwell(_radar(pd=0.6), X_TRUE, X_TRUE, S_RB, np.random.default_rng(seed))
        if b.truth_row is not None:
            np.testing.assert_array_equal(a.z[a.truth_row], b.z[b.truth_row])


def test_truth_row_marks_the_target_return_among_clutter():
    m = _radar(pd=1.0, clutter_rate=5.0)
    rows = []
    for seed in range(200):
        d = simulate_dwell(m, X_TRUE, X_TRUE, S_RB, np.random.default_rng(seed))
        assert d.truth_row is not None
        # the target's return is the one close to h(x) (clutter is spread over ±6σ)
        resid = np.abs(d.z[d.truth_row] - m.h(X_TRUE)) / np.sqrt(np.diag(m.R))
        assert resid.max() < 6.0
        rows.append(d.truth_row / max(1, d.n_returns - 1))
    assert 0.3 < float(np.mean(rows)) < 0.7  # shuffled: not always first or last


def test_clutter_count_is_poisson_with_the_rate_and_uniform_in_the_window():
    rate = 2.5
    m = _radar(pd=0.0, clutter_rate=rate)  # pd = 0: every return is clutter
    rng = np.random.default_rng(2026)
    counts, U = [], []
    for _ in range(4000):
        d = simulate_dwell(m, X_TRUE, X_TRUE, S_RB, rng, clutter_window_sigma=6.0)
        counts.append(d.n_returns)
        assert np.all(d.window.contains(d.z))
        U.append((d.z - d.window.center) / d.window.half_width)
    counts_a = np.array(counts)
    # mean and variance of a Poisson(2.5) count: standard error of the mean √(2.5/4000) = 0.025
    assert abs(counts_a.mean() - rate) < 0.1
    assert abs(counts_a.var() - rate) < 0.3
    # positions uniform on [−1, 1] in each component (KS test, fixed seed)
    Ua = np.concatenate(U)
    for k in range(2):
        assert stats.kstest((Ua[:, k] + 1) / 2, "uniform").pvalue > 0.01


def test_window_volume_and_density():
    m = _radar(clutter_rate=0.5)
    w = clutter_window(m, X_TRUE, S_RB, 6.0)
    np.testing.assert_allclose(w.center, m.h(X_TRUE))
    np.testing.assert_allclose(w.half_width, 6.0 * np.sqrt(np.diag(S_RB)))
    assert w.volume == pytest.approx(np.prod(12.0 * np.sqrt(np.diag(S_RB))))
    d = simulate_dwell(m, X_TRUE, X_TRUE, S_RB, np.random.default_rng(0))
    assert d.clutter_density == pytest.approx(0.5 / w.volume)


def test_bearing_window_capped_at_the_circle_and_wrapped():
    m = BearingModel(sensor_xy=(0.0, 0.0), sigma_bearing=0.5, pd=0.0, clutter_rate=20.0)
    x = np.array([-1000.0, 0.0, 1.0, 0.0])  # bearing just below π
    w = clutter_window(m, x, np.array([[1.0]]), 6.0)
    assert w.half_width[0] == math.pi and w.volume == pytest.approx(2 * math.pi)
    d = simulate_dwell(m, x, x, np.array([[1e-2]]), np.random.default_rng(1))
    assert d.n_returns > 5
    center = m.h(x)[0]
    assert np.all(np.abs(wrap_angle(d.z - center)) <= 0.6 + 1e-12)  # ±6σ, σ = 0.1
    assert np.all((d.z > -math.pi) & (d.z <= math.pi))
    assert np.any(d.z < 0.0) and np.any(d.z > 0.0)  # the window straddles the ±π cut


def test_explicit_window_and_errors():
    m = PositionModel(sigma_x=1.0, sigma_y=1.0, clutter_rate=1.0)
    w = ClutterWindow(np.zeros(2), np.array([5.0, 10.0]), (False, False))
    d = simulate_dwell(m, np.zeros(4), None, None, np.random.default_rng(0), window=w)
    assert d.window is w and d.clutter_density == pytest.approx(1.0 / 200.0)
    with pytest.raises(ValueError, match="x_pred, S"):
        simulate_dwell(m, np.zeros(4), None, None, np.random.default_rng(0))
    with pytest.raises(ValueError, match="S: expected"):
        clutter_window(m, np.zeros(4), np.eye(3))
    with pytest.raises(ValueError, match="clutter_window_sigma"):
        clutter_window(m, np.zeros(4), np.eye(2), 0.0)
    with pytest.raises(ValueError, match="half_width"):
        ClutterWindow(np.zeros(1), np.array([4.0]), (True,))
