"""Truth with appearing and leaving targets, and the Poisson birth process."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.manoeuvre import manoeuvring_trajectory
from covnet.core.surveillance.births import (
    BirthProcess,
    BirthRegion,
    ScheduledTarget,
    simulate_truth,
)

AREA = (0.0, 10_000.0, 0.0, 10_000.0)


def _traj(seed: int, K: int) -> np.ndarray:
    return manoeuvring_trajectory([0.0, 10.0, 0.0, 5.0], 1.0, 0.1, K, np.random.default_rng(seed))


def test_scheduled_targets_exist_between_appear_and_leave() -> None:
    K = 10
    a, b = _traj(1, K), _traj(2, K)
    rng = np.random.default_rng(0)
    before = rng.bit_generator.state
    hist = simulate_truth(
        [ScheduledTarget(a), ScheduledTarget(b, appears_at_scan=3, leaves_at_scan=7)], K, rng
    )
    assert rng.bit_generator.state == before  # nothing drawn without births
    ids, X = hist.at_scan(1)
    assert ids.tolist() == [0] and np.array_equal(X[0], a[0])
    for k in range(1, K + 1):
        ids, X = hist.at_scan(k)
        assert ids.tolist() == ([0, 1] if 3 <= k < 7 else [0])
        np.testing.assert_array_equal(X[0], a[k - 1])
        if 1 in ids.tolist():
            np.testing.assert_array_equal(X[1], b[k - 1])
    assert hist.targets[1].leaves_at_scan == 7 and hist.targets[0].leaves_at_scan == K + 1


def test_births_straight_lines_leave_where_they_exit() -> None:
    """σ_a = 0: a born target flies straight; it exists exactly while inside the area."""
    region = BirthRegion(100.0, 9900.0, 100.0, 9900.0, 50.0, 300.0, -180.0, 180.0)
    proc = BirthProcess(0.7, (region,), AREA, T=2.0, sigma_a=0.0)
    K = 60
    hist = simulate_truth([ScheduledTarget(_traj(1, K))], K, np.random.default_rng(4), proc)
    born = [t for t in hist.targets if t.born]
    assert len(born) > 10
    assert [t.id for t in hist.targets] == list(range(len(hist.targets)))
    for t in born:
        s0 = t.states[0]
        assert region.x0 <= s0[0] <= region.x1 and region.y0 <= s0[2] <= region.y1
        assert 50.0 <= math.hypot(s0[1], s0[3]) <= 300.0
        steps = np.arange(t.states.shape[0])
        np.testing.assert_allclose(t.states[:, 0], s0[0] + 2.0 * s0[1] * steps, atol=1e-6)
        np.testing.assert_allclose(t.states[:, 2], s0[2] + 2.0 * s0[3] * steps, atol=1e-6)
        # the first step out of the area (if before the end) is where it left
        n = t.states.shape[0]
        if t.first_scan + n <= K:
            nxt = (s0[0] + 2.0 * s0[1] * n, s0[2] + 2.0 * s0[3] * n)
            assert not (0 <= nxt[0] <= 10_000 and 0 <= nxt[1] <= 10_000)
        assert hist.at_scan(t.first_scan)[0].tolist().count(t.id) == 1


def test_birth_count_is_poisson_rate_per_scan_and_reproducible() -> None:
    region = BirthRegion(0.0, 5000.0, 0.0, 100.0, 10.0, 10.0, 90.0, 90.0)
    proc = BirthProcess(1.5, (region,), AREA, T=1.0, sigma_a=0.5)
    K = 400
    h1 = simulate_truth([], K, np.random.default_rng(9), proc)
    h2 = simulate_truth([], K, np.random.default_rng(9), proc)
    assert len(h1.targets) == len(h2.targets)
    for u, v in zip(h1.targets, h2.targets, strict=True):
        np.testing.assert_array_equal(u.states, v.states)
    n = len(h1.targets)
    assert abs(n - 1.5 * K) < 5 * math.sqrt(1.5 * K)


def test_regions_chosen_by_area() -> None:
    small = BirthRegion(0.0, 100.0, 0.0, 100.0, 1.0, 1.0, 0.0, 0.0)
    big = BirthRegion(5000.0, 5300.0, 0.0, 100.0, 1.0, 1.0, 0.0, 0.0)  # 3x the area
    proc = BirthProcess(5.0, (small, big), AREA, T=1.0, sigma_a=0.0)
    hist = simulate_truth([], 200, np.random.default_rng(2), proc)
    x0 = np.array([t.states[0, 0] for t in hist.targets])
    frac_big = float(np.mean(x0 >= 5000.0))
    assert frac_big == pytest.approx(0.75, abs=0.03)


def test_inputs_checked_with_names() -> None:
    with pytest.raises(ValueError, match="leaves_at_scan"):
        ScheduledTarget(np.zeros((5, 4)), appears_at_scan=3, leaves_at_scan=3)
    with pytest.raises(ValueError, match="inside the area"):
        BirthProcess(1.0, (BirthRegion(-5.0, 1.0, 0.0, 1.0, 0, 1, 0, 1),), AREA, 1.0, 0.0)
    with pytest.raises(ValueError, match="trajectory"):
        simulate_truth([ScheduledTarget(np.zeros((3, 4)))], 5, np.random.default_rng(0))
    with pytest.raises(ValueError, match="speed_min"):
        BirthRegion(0.0, 1.0, 0.0, 1.0, 5.0, 1.0, 0.0, 0.0)
