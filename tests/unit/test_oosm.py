"""ReFilterBuffer bookkeeping: too-late, future and duplicate measurements, depth, and an
insert at the latest scan against a plain Kalman update."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.gaussian import Gaussian
from covnet.core.kalman import predict, update, update_sequential
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.oosm import ReFilterBuffer, ScanRecord, filter_scan
from covnet.core.sensing import correlated_noise, position_matrix

F = cv_transition(1.0)
Q = dwna_process_noise(1.0, 0.5)
H = position_matrix(2)
R = [correlated_noise(21.1, 8.2, 0.82), correlated_noise(8.22, 20.3, 0.78)]
R += [correlated_noise(42.1, 43.1, 0.87), correlated_noise(41.4, 43.7, -0.94)]
PRIOR1 = Gaussian(np.array([0.0, 426.0, 0.0, 0.0]), np.diag([1e4, 1e2, 1e4, 1e2]))


def z_of(scan: int, j: int) -> np.ndarray:
    return np.array([426.0 * scan + 3.0 * j, -2.0 * j + 0.5 * scan])


def run(depth: int, scans: int, sensors=(1, 2)) -> ReFilterBuffer:
    buf = ReFilterBuffer(F, Q, H, depth)
    for k in range(1, scans + 1):
        buf.step(k, [(j, z_of(k, j), R[j]) for j in sensors], prior=PRIOR1 if k == 1 else None)
    return buf


def snapshot(buf: ReFilterBuffer):
    return [
        (r.scan, r.sensors, r.prior.x.copy(), r.prior.P.copy(), r.post.x.copy(), r.post.P.copy())
        for r in buf.records
    ]


def assert_unchanged(buf: ReFilterBuffer, before) -> None:
    after = snapshot(buf)
    assert len(after) == len(before)
    for a, b in zip(after, before, strict=True):
        assert a[:2] == b[:2]
        for u, v in zip(a[2:], b[2:], strict=True):
            np.testing.assert_array_equal(u, v)


def test_insert_at_latest_with_highest_index_is_a_plain_update_bitwise():
    buf = run(depth=3, scans=5, sensors=(0, 1))
    old = buf.latest.post
    out = buf.insert(5, 3, z_of(5, 3), R[3])
    # the sequential order appends sensor 3 last: the very same update of the old posterior
    expected = update(old, z_of(5, 3), H, R[3])
    np.testing.assert_array_equal(out.x, expected.x)
    np.testing.assert_array_equal(out.P, expected.P)
    assert buf.latest.sensors == (0, 1, 3)


def test_insert_at_latest_with_lower_index_equals_a_plain_update_to_rounding():
    buf = run(depth=3, scans=5, sensors=(1, 2))
    old = buf.latest.post
    out = buf.insert(5, 0, z_of(5, 0), R[0])
    # a plain update of the old posterior (sensor 0 last) equals, to rounding, the canonical
    # re-filter (sensor 0 first): the sequential update is order-independent in exact arithmetic
    expected = update(old, z_of(5, 0), H, R[0])
    np.testing.assert_allclose(out.x, expected.x, rtol=1e-9)
    np.testing.assert_allclose(out.P, expected.P, rtol=1e-9, atol=1e-9 * np.abs(out.P).max())
    # ... and bit for bit the canonical order from the scan's prior
    canon = update_sequential(buf.latest.prior, [(z_of(5, j), H, R[j]) for j in (0, 1, 2)])
    np.testing.assert_array_equal(out.x, canon.x)
    np.testing.assert_array_equal(out.P, canon.P)


def test_insert_in_the_past_refilters_every_later_scan():
    buf = run(depth=4, scans=6)
    out = buf.insert(4, 0, z_of(4, 0), R[0])
    recs = {r.scan: r for r in buf.records}
    assert recs[4].sensors == (0, 1, 2)
    assert recs[5].sensors == recs[6].sensors == (1, 2)
    for k in (5, 6):
        prev = predict(recs[k - 1].post, F, Q)
        np.testing.assert_array_equal(recs[k].prior.x, prev.x)
        np.testing.assert_array_equal(recs[k].prior.P, prev.P)
    assert out is buf.latest.post
    # one more measurement shrinks the covariance of every scan from 4 on
    ref = run(depth=4, scans=6)
    for k in (4, 5, 6):
        gap = ref.covariances()[k] - buf.covariances()[k]
        assert np.linalg.eigvalsh(gap).min() > -1e-9
        assert np.trace(gap) > 0


def test_too_late_returns_none_and_leaves_the_buffer_unchanged():
    buf = run(depth=3, scans=6)
    assert buf.oldest_scan == 4
    before = snapshot(buf)
    assert buf.insert(3, 0, z_of(3, 0), R[0]) is None
    assert buf.insert(1, 0, z_of(1, 0), R[0]) is None
    assert_unchanged(buf, before)
    # the oldest buffered scan is still in time
    assert buf.insert(4, 0, z_of(4, 0), R[0]) is not None


def test_future_scan_returns_none_and_leaves_the_buffer_unchanged():
    buf = run(depth=3, scans=6)
    before = snapshot(buf)
    assert buf.insert(7, 0, z_of(7, 0), R[0]) is None
    assert_unchanged(buf, before)


def test_empty_buffer_refuses_inserts():
    buf = ReFilterBuffer(F, Q, H, 2)
    assert buf.insert(1, 0, z_of(1, 0), R[0]) is None
    assert buf.oldest_scan is None
    with pytest.raises(LookupError):
        buf.latest  # noqa: B018


def test_duplicate_raises_naming_sensor_and_scan():
    buf = run(depth=3, scans=6, sensors=(1, 3))
    before = snapshot(buf)
    with pytest.raises(ValueError, match=r"sensor 3 .*scan 5"):
        buf.insert(5, 3, z_of(5, 3), R[3])
    assert_unchanged(buf, before)
    # an inserted one is a duplicate too
    buf.insert(5, 0, z_of(5, 0), R[0])
    with pytest.raises(ValueError, match=r"sensor 0 .*scan 5"):
        buf.insert(5, 0, z_of(5, 0), R[0])


def test_failed_update_leaves_the_buffer_unchanged():
    buf = run(depth=3, scans=6)
    before = snapshot(buf)
    with pytest.raises(np.linalg.LinAlgError):
        buf.insert(4, 0, z_of(4, 0), -1e6 * np.eye(2))  # S not positive definite
    assert_unchanged(buf, before)


@pytest.mark.parametrize("depth", [1, 2, 5])
def test_never_more_than_depth_records(depth):
    buf = ReFilterBuffer(F, Q, H, depth)
    for k in range(1, 9):
        buf.step(k, [(1, z_of(k, 1), R[1])], prior=PRIOR1 if k == 1 else None)
        assert len(buf) == min(k, depth)
        assert [r.scan for r in buf.records] == list(range(max(1, k - depth + 1), k + 1))
        buf.insert(k, 0, z_of(k, 0), R[0])  # re-filtering keeps the count too
        assert len(buf) == min(k, depth)
    assert list(buf.covariances()) == list(range(9 - depth, 9))


def test_push_requires_consecutive_scans():
    buf = run(depth=3, scans=2)
    rec = filter_scan(4, predict(buf.latest.post, F, Q), [], H)
    with pytest.raises(ValueError, match="scan 4 does not follow .* 2"):
        buf.push(rec)
    with pytest.raises(ValueError, match="depth"):
        ReFilterBuffer(F, Q, H, 0)


def test_record_measurements_must_be_strictly_ascending():
    m = [(2, z_of(1, 2), R[2]), (0, z_of(1, 0), R[0])]
    with pytest.raises(ValueError, match="ascending"):
        ScanRecord(1, PRIOR1, tuple(m), PRIOR1)
    with pytest.raises(ValueError, match="ascending"):
        ScanRecord(1, PRIOR1, (m[0], m[0]), PRIOR1)
    assert filter_scan(1, PRIOR1, m, H).sensors == (0, 2)  # filter_scan sorts


def test_predicted_is_the_next_prior():
    buf = run(depth=2, scans=3)
    nxt = buf.predicted()
    ref = predict(buf.latest.post, F, Q)
    np.testing.assert_array_equal(nxt.x, ref.x)
    np.testing.assert_array_equal(nxt.P, ref.P)
