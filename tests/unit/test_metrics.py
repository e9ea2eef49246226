"""Matrix metrics: oracle values written out from the formulas, the svd eigenvector convention,
the registry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.metrics import METRICS, get_metric, metric_names, ordered_eigh, svd

A1, B1 = np.diag([3.0, 1.0]), np.diag([1.0, 2.0])  # M = A - B = diag(2, -1)
A2, B2 = np.array([[2.0, 1.0], [1.0, 2.0]]), np.eye(2)  # M = [[1, 1], [1, 1]], eig(M) = (2, 0)

# (name, A, B, expected) with the expected value worked out by hand from the formula
ORACLES = [
    ("spectral", A1, B1, 2.0),  # max |eig(diag(2, -1))|
    ("spectral", A2, B2, 2.0),
    ("abs_trace", A1, B1, 3.0),  # |2| + |-1|
    ("abs_trace", A2, B2, 2.0),
    ("frobenius", A1, B1, math.sqrt(5.0)),
    ("frobenius", A2, B2, 2.0),
    ("one_norm", A1, B1, 2.0),
    ("one_norm", np.array([[1.0, 0.5], [0.5, 1.0]]), np.zeros((2, 2)), 1.5),
    ("inf_norm", A1, B1, 2.0),
    ("inf_norm", A2, B2, 2.0),
    ("trace_diff", A1, B1, 1.0),  # |4 - 3|
    ("trace_diff", A2, B2, 2.0),
    # log det((A+B)/2) - ½ log det A - ½ log det B
    ("logdet", A1, B1, math.log(2.0 * 1.5) - 0.5 * math.log(3.0) - 0.5 * math.log(2.0)),
    ("logdet", A2, B2, math.log(2.0) - 0.5 * math.log(3.0)),  # det([[1.5,.5],[.5,1.5]]) = 2
    # ¼[tr(B⁻¹A) + tr(A⁻¹B) - 2n]
    ("kl", A1, B1, 0.25 * ((3.0 + 0.5) + (1.0 / 3.0 + 2.0) - 4.0)),
    ("kl", A2, B2, 0.25 * (4.0 + 4.0 / 3.0 - 4.0)),
    # A1: s = (3, 1), U = (e1, e2); B1: s = (2, 1), U = (e2, e1): orientation (2 - 0)/2, size 1
    ("svd", A1, B1, 1.0 + 1.0),
    # A2: s = (3, 1), U = ((1,1), (1,-1))/√2; B2 = I: tie, U = (e1, e2): cos = 1/√2 each
    ("svd", A2, B2, (2.0 - math.sqrt(2.0)) / 2.0 + 2.0),
]


@pytest.mark.parametrize(
    ("name", "A", "B", "expected"),
    ORACLES,
    ids=[f"{o[0]}-{k}" for k, o in enumerate(ORACLES)],
)
def test_oracle_values(name, A, B, expected):
    assert float(METRICS[name](A, B)) == pytest.approx(expected, rel=1e-12, abs=1e-14)


def test_registry_names():
    assert metric_names() == sorted(METRICS)
    assert {"spectral", "abs_trace", "svd", "frobenius", "one_norm", "inf_norm"} <= set(METRICS)
    assert {"trace_diff", "logdet", "kl"} <= set(METRICS)
    assert get_metric("svd") is svd


def test_unknown_metric_lists_valid_names():
    with pytest.raises(KeyError, match="unknown metric 'nope'.*abs_trace.*spectral.*svd"):
        get_metric("nope")


@pytest.mark.parametrize("name", sorted(METRICS))
def test_batched_broadcast_shape(name):
    rng = np.random.default_rng(3)
    X = rng.standard_normal((2, 3, 4, 4))
    A = X @ np.swapaxes(X, -1, -2) + np.eye(4)
    out = METRICS[name](A, np.diag([25.0, 1.4, 25.0, 1.4]))
    assert out.shape == (2, 3)
    assert out.dtype == np.float64


@pytest.mark.parametrize("name", ["logdet", "kl"])
def test_spd_metrics_reject_indefinite(name):
    with pytest.raises(np.linalg.LinAlgError):
        METRICS[name](np.diag([1.0, -1.0]), np.eye(2))


# ---- the svd eigenvector convention -------------------------------------------------------


def test_convention_on_the_desired_covariance():
    """diag(25, 1.4, 25, 1.4) on [x, vx, y, vy]: values descending, ties broken by the index of
    the largest component, so the eigenvectors are the unit axes in the order x, y, vx, vy."""
    s, U = ordered_eigh(np.diag([25.0, 1.4, 25.0, 1.4]))
    np.testing.assert_array_equal(s, [25.0, 25.0, 1.4, 1.4])
    e = np.eye(4)
    np.testing.assert_array_equal(U, np.stack([e[0], e[2], e[1], e[3]], axis=1))


def test_convention_diagonal_single_equals_batched():
    """The diagonal shortcut and the general (LAPACK) path give the same bits."""
    for d in ([25.0, 1.4, 25.0, 1.4], [7.0, 0.8, 7.0, 0.8], [3.0, 3.0, 3.0], [1.0, 2.0, 5.0]):
        D = np.diag(d)
        s1, U1 = ordered_eigh(D)
        s2, U2 = ordered_eigh(D[None])
        np.testing.assert_array_equal(s1, s2[0])
        np.testing.assert_array_equal(U1, U2[0])


def _rotation(n, i, j, angle):
    R = np.eye(n)
    c, s = math.cos(angle), math.sin(angle)
    R[i, i] = R[j, j] = c
    R[i, j], R[j, i] = -s, s
    return R


def test_convention_does_not_depend_on_the_basis_of_a_tie_group():
    """The same matrix built from two different bases of its repeated eigenspace (so LAPACK may
    return either) yields the same eigenvectors."""
    Q = np.linalg.qr(np.random.default_rng(0).standard_normal((4, 4)))[0]
    lam = np.diag([5.0, 5.0, 2.0, 1.0])
    Q2 = Q @ _rotation(4, 0, 1, 0.7)  # another orthonormal basis of the 5-eigenspace
    s1, U1 = ordered_eigh(Q @ lam @ Q.T)
    s2, U2 = ordered_eigh(Q2 @ lam @ Q2.T)
    np.testing.assert_allclose(s1, s2, atol=1e-12)
    np.testing.assert_allclose(U1, U2, atol=1e-7)


def test_convention_rotated_desired_equals_diagonal():
    """Rotating within the x/y tie group leaves diag(25, 1.4, 25, 1.4) unchanged, and so the
    convention's answer (up to rounding)."""
    D = np.diag([25.0, 1.4, 25.0, 1.4])
    R = _rotation(4, 0, 2, 0.3)
    np.testing.assert_allclose(ordered_eigh(R @ D @ R.T)[1], ordered_eigh(D)[1], atol=1e-7)


def test_sign_convention_and_reconstruction():
    rng = np.random.default_rng(5)
    X = rng.standard_normal((6, 5, 5))
    A = X @ np.swapaxes(X, -1, -2)
    s, U = ordered_eigh(A)
    assert np.all(np.diff(s, axis=-1) <= 0)
    big = np.take_along_axis(U, np.abs(U).argmax(axis=-2)[:, None, :], axis=-2)
    assert np.all(big > 0)
    np.testing.assert_allclose(U @ (s[..., None] * np.swapaxes(U, -1, -2)), A, atol=1e-10)


def test_svd_invariant_to_eigenvector_signs():
    """svd only sees |u_A · u_B|, and the convention fixes the signs anyway: flipping the sign of
    the input's eigen-basis (same matrix) changes nothing."""
    Q = np.linalg.qr(np.random.default_rng(1).standard_normal((4, 4)))[0]
    lam = np.diag([9.0, 4.0, 2.0, 1.0])
    A = Q @ lam @ Q.T
    A_flipped = (-Q) @ lam @ (-Q).T
    D = np.diag([25.0, 1.4, 25.0, 1.4])
    assert float(svd(A, D)) == pytest.approx(float(svd(A_flipped, D)), abs=1e-12)
