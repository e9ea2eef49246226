"""``gains_sequential``: the sequential Kalman covariance updates of many sensors with the
checks made once, bit for bit the checked updates one by one, and their errors."""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core.kalman import gain_and_covariance, gains_sequential

H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def _spd(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    A = rng.standard_normal((n, n)) * scale
    return A @ A.T + np.eye(n) * scale


@pytest.mark.parametrize("seed", range(20))
def test_the_same_bits_as_one_update_after_another(seed):
    rng = np.random.default_rng(seed)
    P = _spd(rng, 4, 10.0 ** rng.uniform(-2, 4))
    Rs = [_spd(rng, 2, 10.0 ** rng.uniform(-3, 3)) for _ in range(int(rng.integers(0, 40)))]
    Ks, P_out = gains_sequential(P, H, Rs)
    ref, P_ref = [], P
    for R in Rs:
        K, P_ref = gain_and_covariance(P_ref, H, R)
        ref.append(K)
    assert len(Ks) == len(ref)
    assert all(np.array_equal(a, b) for a, b in zip(Ks, ref, strict=True))
    assert np.array_equal(P_out, P_ref)


def test_errors_are_those_of_the_checked_updates():
    P = np.eye(4)
    with pytest.raises(np.linalg.LinAlgError):
        gains_sequential(P, H, [np.eye(2), -10 * np.eye(2)])
    with pytest.raises(ValueError, match="finite"):
        gains_sequential(P, H, [np.eye(2), np.full((2, 2), np.nan)])
