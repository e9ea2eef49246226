"""Track management: initiation per sensor model, M-of-N confirmation, deletion, ids."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from covnet.core.gaussian import Gaussian
from covnet.core.sensor_models import BearingModel, PositionModel, RangeBearingModel
from covnet.core.surveillance.tracks import (
    TrackManager,
    TrackRules,
    TrackState,
    can_initiate,
    check_covariance,
    initiate,
    is_hit,
    position_from_return,
    record_dwell,
)

POS = PositionModel(sigma_x=10.0, sigma_y=20.0, rho=0.3)
RB = RangeBearingModel(sensor_xy=(1000.0, -500.0), sigma_r=20.0, sigma_bearing=2e-3)
BRG = BearingModel(sensor_xy=(0.0, 0.0), sigma_bearing=1e-3)


def test_position_return_starts_a_track_with_R_and_velocity_spread() -> None:
    Z = np.array([[100.0, 200.0], [5.0, 6.0], [-1.0, 3.0]])
    new = initiate(Z, [0, 2], POS, 40.0, scan=7, first_id=11)
    assert [t.id for t in new] == [11, 12]
    t = new[1]
    np.testing.assert_array_equal(t.estimate.x, [-1.0, 0.0, 3.0, 0.0])
    np.testing.assert_array_equal(t.estimate.P[np.ix_([0, 2], [0, 2])], POS.R)
    assert t.estimate.P[1, 1] == t.estimate.P[3, 3] == 1600.0
    assert t.estimate.P[0, 1] == t.estimate.P[1, 2] == 0.0
    assert t.state is TrackState.TENTATIVE and t.born_scan == 7 and t.hits == (True,)
    assert t.n_dwells == 1 and t.misses == 0


def test_range_bearing_conversion_is_the_linearised_polar_one() -> None:
    r, b = 12_000.0, 0.7
    p, P = position_from_return(RB, np.array([r, b]))
    np.testing.assert_allclose(p, [1000.0 + r * math.cos(b), -500.0 + r * math.sin(b)])

    # Jacobian by central differences of the conversion
    def conv(z: np.ndarray) -> np.ndarray:
        return np.array([1000.0 + z[0] * math.cos(z[1]), -500.0 + z[0] * math.sin(z[1])])

    J = np.zeros((2, 2))
    for k, h in enumerate((1e-3, 1e-9)):
        e = np.zeros(2)
        e[k] = h
        J[:, k] = (conv(np.array([r, b]) + e) - conv(np.array([r, b]) - e)) / (2 * h)
    np.testing.assert_allclose(P, J @ RB.R @ J.T, rtol=1e-6)
    # and it is the spread of converted noisy returns (small σ_β: the linearisation holds)
    rng = np.random.default_rng(3)
    zs = np.array([r, b]) + rng.standard_normal((5000, 2)) @ RB.L.T
    pts = np.stack([conv(z) for z in zs])
    C = np.cov(pts.T)
    np.testing.assert_allclose(C, P, rtol=0.08, atol=0.05 * math.sqrt(P[0, 0] * P[1, 1]))
    # the back-and-forth: the sensor sees the converted point at the measured range and bearing
    x = np.array([p[0], 0.0, p[1], 0.0])
    np.testing.assert_allclose(RB.h(x), [r, b], rtol=1e-12)


def test_bearing_only_returns_never_start_a_track() -> None:
    assert not can_initiate(BRG) and can_initiate(POS) and can_initiate(RB)
    assert initiate(np.array([[0.3]]), [0], BRG, 40.0, scan=1, first_id=0) == ()
    with pytest.raises(ValueError, match="bearing.*cannot start a track"):
        position_from_return(BRG, np.array([0.3]))


def _plain_m_of_n(seq: tuple[bool, ...], m: int, n: int) -> tuple[str, int]:
    """(outcome, dwell index 1-based) by the rule in words: the initiating return is dwell 1, a
    hit; confirmed at the first dwell k <= n with m hits among dwells 1..k; deleted at the first
    dwell k where even all the remaining dwells up to n hitting would not make m."""
    hits = [True, *seq]
    for k in range(1, len(hits) + 1):
        c = sum(hits[:k])
        if c >= m and k <= n:
            return "confirmed", k
        if c + max(n - k, 0) < m:
            return "deleted", k
    return "tentative", len(hits)


@pytest.mark.parametrize(("m", "n"), [(2, 2), (2, 3), (3, 3), (2, 5), (3, 4)])
def test_m_of_n_against_the_rule_in_words(m: int, n: int) -> None:
    rules = TrackRules(confirm_m=m, confirm_n=n)
    start = initiate(np.array([[0.0, 0.0]]), [0], POS, 10.0, scan=1, first_id=0)[0]
    g = start.estimate
    for length in range(n + 1):
        for seq in itertools.product([False, True], repeat=length):
            t = start
            outcome: tuple[str, int] = ("tentative", 1)
            for k, h in enumerate(seq, start=2):
                t = record_dwell(t, g, h, scan=10 + k, rules=rules)
                if t.state is not TrackState.TENTATIVE:
                    outcome = (t.state.value, k)
                    break
            else:
                outcome = ("tentative", len(seq) + 1)
            ref = _plain_m_of_n(seq[: outcome[1] - 1], m, n)
            assert outcome == ref, (seq, outcome, ref)
            if outcome[0] == "confirmed":
                assert t.confirmed_scan == 10 + outcome[1]
            if outcome[0] == "deleted":
                assert t.deleted_reason == "confirmation" and t.deleted_scan == 10 + outcome[1]


def test_one_of_n_confirms_at_birth() -> None:
    mgr = TrackManager(TrackRules(confirm_m=1, confirm_n=3))
    (t,) = mgr.initiate(np.array([[0.0, 0.0]]), [0], POS, scan=4)
    assert t.state is TrackState.CONFIRMED and t.confirmed_scan == 4


def _confirmed(rules: TrackRules):
    t = initiate(np.array([[0.0, 0.0]]), [0], POS, 10.0, scan=1, first_id=0)[0]
    t = record_dwell(t, t.estimate, True, 2, rules)
    assert t.state is TrackState.CONFIRMED
    return t


def test_confirmed_track_deleted_after_consecutive_misses_only() -> None:
    rules = TrackRules(confirm_m=2, confirm_n=3, delete_after_misses=3)
    t = _confirmed(rules)
    g = t.estimate
    for k, h in enumerate([False, False, True, False, False], start=3):
        t = record_dwell(t, g, h, k, rules)
        assert t.live
    assert t.misses == 2
    t = record_dwell(t, g, False, 8, rules)
    assert t.state is TrackState.DELETED and t.deleted_reason == "misses"
    assert t.deleted_scan == 8
    with pytest.raises(ValueError, match="deleted"):
        record_dwell(t, g, True, 9, rules)


def test_covariance_rule_deletes_confirmed_not_tentative() -> None:
    rules = TrackRules(delete_trace_m2=1000.0)
    big = Gaussian(np.zeros(4), np.diag([600.0, 1.0, 600.0, 1.0]))
    small = Gaussian(np.zeros(4), np.diag([400.0, 1.0, 500.0, 1.0]))
    t = _confirmed(rules)
    assert check_covariance(replace_estimate(t, small), 5, rules).live
    d = check_covariance(replace_estimate(t, big), 5, rules)
    assert d.state is TrackState.DELETED and d.deleted_reason == "covariance"
    tent = initiate(np.array([[0.0, 0.0]]), [0], POS, 100.0, scan=1, first_id=0)[0]
    assert check_covariance(replace_estimate(tent, big), 5, rules).live


def replace_estimate(t, g):
    return dataclasses.replace(t, estimate=g)


def test_is_hit() -> None:
    assert not is_hit(1.0, 0)
    assert not is_hit(0.0, 0)  # nothing gated is never a hit
    assert is_hit(0.999, 2)
    assert not is_hit(1.0, 2)
    assert not is_hit(0.6, 1, hit_threshold=0.5) and is_hit(0.4, 1, hit_threshold=0.5)


def test_manager_ids_ascending_never_reused() -> None:
    mgr = TrackManager(TrackRules(confirm_m=2, confirm_n=2), first_id=3)
    Z = np.array([[0.0, 0.0], [100.0, 0.0], [200.0, 0.0]])
    a = mgr.initiate(Z, [0, 1], POS, scan=1)
    assert [t.id for t in a] == [3, 4]
    mgr.record_dwell(3, a[0].estimate, False, 2)  # 1 of 2: deleted
    assert [t.id for t in mgr.live()] == [4] and [t.id for t in mgr.deleted] == [3]
    b = mgr.initiate(Z, [2], POS, scan=2)
    assert [t.id for t in b] == [5]
    mgr.record_dwell(5, b[0].estimate, True, 3)
    assert [t.id for t in mgr.live()] == [4, 5]
    assert [t.id for t in mgr.confirmed()] == [5] and [t.id for t in mgr.tentative()] == [4]
    assert mgr.initiate(np.array([[0.1]]), [0], BRG, scan=3) == ()
    assert mgr.next_id == 6


def test_rules_are_checked_with_their_names() -> None:
    with pytest.raises(ValueError, match="confirm"):
        TrackRules(confirm_m=3, confirm_n=2)
    with pytest.raises(ValueError, match="delete_after_misses"):
        TrackRules(delete_after_misses=0)
    with pytest.raises(ValueError, match="delete_trace_m2"):
        TrackRules(delete_trace_m2=0.0)
    with pytest.raises(ValueError, match="velocity_std"):
        TrackRules(velocity_std=-1.0)
    with pytest.raises(ValueError, match="hit_threshold"):
        TrackRules(hit_threshold=1.0)
