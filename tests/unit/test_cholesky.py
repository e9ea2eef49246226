"""covnet.core.cholesky: the LAPACK calls of scipy's cho_factor/cho_solve, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import linalg

from covnet.core.cholesky import cho_factor, cho_solve


def _spd(rng: np.random.Generator, n: int) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return A @ A.T + n * np.eye(n)


@pytest.mark.parametrize("n", [1, 2, 4, 6])
def test_same_bits_as_scipy(n: int) -> None:
    rng = np.random.default_rng(n)
    for _ in range(20):
        A = _spd(rng, n) * 10.0 ** rng.uniform(-6, 6)
        B = rng.standard_normal((n, 3))
        b = rng.standard_normal(n)
        c = cho_factor(A)
        c_ref, lower = linalg.cho_factor(A)
        assert not lower
        assert np.array_equal(c, c_ref)
        assert np.array_equal(cho_solve(c, B), linalg.cho_solve((c_ref, False), B))
        assert np.array_equal(cho_solve(c, b), linalg.cho_solve((c_ref, False), b))
        assert np.allclose(A @ cho_solve(c, B), B, rtol=1e-8, atol=1e-8 * np.abs(B).max())


def test_inputs_are_not_modified() -> None:
    A = _spd(np.random.default_rng(1), 3)
    B = np.ones((3, 2))
    A0, B0 = A.copy(), B.copy()
    cho_solve(cho_factor(A), B)
    assert np.array_equal(A, A0) and np.array_equal(B, B0)


def test_errors() -> None:
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        cho_factor(np.array([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ValueError, match="finite"):
        cho_factor(np.array([[1.0, np.nan], [np.nan, 1.0]]))
    with pytest.raises(ValueError, match="finite"):
        cho_factor(np.array([[np.inf, 0.0], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="square"):
        cho_factor(np.ones((2, 3)))
    c = cho_factor(np.eye(2))
    with pytest.raises(ValueError, match="finite"):
        cho_solve(c, np.array([1.0, np.inf]))
    with pytest.raises(ValueError, match="incompatible"):
        cho_solve(c, np.ones(3))
    # finite entries whose sum overflows are still accepted
    big = np.diag([1e308, 1e308])
    assert np.array_equal(cho_factor(big), linalg.cho_factor(big)[0])
