"""Every registered metric is a matrix metric on SPD inputs: f >= 0, f(A, A) = 0,
f(A, B) = f(B, A), and batched evaluation equals one-at-a-time evaluation bit for bit for the
metrics whose entry says ``batch_invariant`` (the allocator relies on that), to rounding for the
others."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.metrics import METRICS

_elems = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


@st.composite
def spd(draw, n):
    A = draw(arrays(np.float64, (n, n), elements=_elems))
    return A @ A.T + 1e-3 * np.eye(n)


@st.composite
def spd_pair(draw):
    n = draw(st.integers(2, 5))
    return draw(spd(n)), draw(spd(n))


@st.composite
def spd_stack(draw):
    n = draw(st.integers(2, 5))
    k = draw(st.integers(1, 4))
    return np.stack([draw(spd(n)) for _ in range(k)]), draw(spd(n))


def _scale(A, B):
    return 1.0 + float(np.abs(A).max() + np.abs(B).max())


NAMES = sorted(METRICS)


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=40)
@given(pair=spd_pair())
def test_nonnegative(name, pair):
    A, B = pair
    assert float(METRICS[name](A, B)) >= 0.0


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=40)
@given(pair=spd_pair())
def test_zero_on_identical(name, pair):
    A, _ = pair
    assert float(METRICS[name](A, A)) == pytest.approx(0.0, abs=1e-8 * _scale(A, A))


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=40)
@given(pair=spd_pair())
def test_symmetric(name, pair):
    A, B = pair
    f_ab, f_ba = float(METRICS[name](A, B)), float(METRICS[name](B, A))
    assert f_ab == pytest.approx(f_ba, rel=1e-9, abs=1e-9 * _scale(A, B))


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=40)
@given(stack=spd_stack())
def test_batched_equals_one_at_a_time(name, stack):
    A, B = stack
    batched = METRICS[name](A, B)
    single = np.array([float(METRICS[name](a, B)) for a in A])
    if METRICS[name].batch_invariant:
        np.testing.assert_array_equal(batched, single)
    else:  # a metric not marked batch-invariant: the searches recheck its near ties
        np.testing.assert_allclose(batched, single, rtol=1e-9, atol=1e-9 * _scale(A[0], B))
