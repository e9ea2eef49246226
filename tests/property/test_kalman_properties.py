"""Properties of the Kalman steps: sequential == information form, P⁺ ⪯ P⁻, symmetry."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.gaussian import Gaussian
from covnet.core.kalman import update_information, update_sequential

_elems = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


@st.composite
def spd(draw, n):
    A = draw(arrays(np.float64, (n, n), elements=_elems))
    return A @ A.T + 1e-1 * np.eye(n)


@st.composite
def problem(draw):
    n = draw(st.integers(2, 5))
    P = draw(spd(n))
    x = draw(arrays(np.float64, (n,), elements=_elems))
    meas = []
    for _ in range(draw(st.integers(1, 4))):
        m = draw(st.integers(1, n))
        H = draw(arrays(np.float64, (m, n), elements=_elems))
        R = draw(spd(m))
        z = draw(arrays(np.float64, (m,), elements=_elems))
        meas.append((z, H, R))
    return Gaussian(x, P), meas


@given(problem())
def test_sequential_equals_information(pb):
    prior, meas = pb
    a = update_sequential(prior, meas)
    b = update_information(prior, meas)
    scale = max(1.0, float(np.abs(prior.P).max()))
    np.testing.assert_allclose(a.P, b.P, rtol=1e-6, atol=1e-7 * scale)
    np.testing.assert_allclose(a.x, b.x, rtol=1e-5, atol=1e-5 * max(1.0, float(np.abs(a.x).max())))


@given(problem())
def test_update_never_increases_covariance(pb):
    prior, meas = pb
    post = update_sequential(prior, meas)
    np.testing.assert_array_equal(post.P, post.P.T)
    scale = float(np.abs(prior.P).max())
    assert np.linalg.eigvalsh(prior.P - post.P).min() >= -1e-8 * scale
    assert np.linalg.eigvalsh(post.P).min() >= -1e-8 * scale
