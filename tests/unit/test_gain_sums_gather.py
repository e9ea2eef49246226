"""``gain_sums`` adds only each row's members (gathered in ascending order, padded with
``+0.0``) instead of every sensor with ``+0.0`` for the others: the same bits as the masked
cumulative sum it replaced and as the reference loop ``J = 0; J = J + J_j``, signed zeros and
empty rows included."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.core.allocation._fast import gain_sums


def _masked_cumsum(gains, masks):
    """The form it replaced."""
    W = np.where(masks[:, :, None, None], gains[None], 0.0)
    return np.cumsum(W, axis=1)[:, -1] + 0.0


def _loop(gains, masks):
    out = []
    for row in masks:
        J = 0.0
        for j in np.flatnonzero(row):
            J = J + gains[j]
        out.append(np.zeros(gains.shape[1:]) + J + 0.0)
    return np.array(out)


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_the_same_bits_as_the_masked_sum_and_the_loop(data):
    N = data.draw(st.integers(1, 30))
    m = data.draw(st.integers(1, 12))
    n = data.draw(st.sampled_from([1, 2, 4]))
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    gains = rng.normal(size=(N, n, n)) * 10.0 ** rng.integers(-8, 8, size=(N, 1, 1))
    # signed zeros, whole zero gains and exact cancellations, where the order of additions shows
    gains[rng.random(gains.shape) < 0.2] = -0.0
    gains[rng.random(gains.shape) < 0.1] = 0.0
    if N > 1:
        gains[1] = -gains[0]
    masks = rng.random((m, N)) < data.draw(st.sampled_from([0.0, 0.1, 0.5, 0.95]))
    got = gain_sums(gains, masks)
    for want in (_masked_cumsum(gains, masks), _loop(gains, masks)):
        assert got.shape == want.shape
        assert got.tobytes() == want.tobytes()
