"""OSPA and GOSPA: hand-computed oracle values, empty sets, metric properties, decomposition."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.ospa import gospa, ospa

# -- oracles ---------------------------------------------------------------------------------


def test_ospa_single_points():
    """d = 5 (3-4-5); below the cut-off it is the distance, above it the cut-off."""
    assert ospa([[0.0, 0.0]], [[3.0, 4.0]], c=10.0, p=2) == pytest.approx(5.0)
    assert ospa([[0.0, 0.0]], [[3.0, 4.0]], c=4.0, p=2) == pytest.approx(4.0)


def test_ospa_cardinality_mismatch_oracle():
    """X = {(0,0), (10,0)}, Y = {(1,0)}, c = 5: the best pair costs d = 1, the extra point c.
    p = 1: (1 + 5)/2 = 3;  p = 2: √((1 + 25)/2) = √13."""
    X = [[0.0, 0.0], [10.0, 0.0]]
    Y = [[1.0, 0.0]]
    assert ospa(X, Y, c=5.0, p=1) == pytest.approx(3.0)
    assert ospa(X, Y, c=5.0, p=2) == pytest.approx(math.sqrt(13.0))
    assert ospa(Y, X, c=5.0, p=2) == pytest.approx(math.sqrt(13.0))


def test_ospa_needs_the_optimal_assignment():
    """d(x₁,y₁) = 1, d(x₁,y₂) = 2, d(x₂,y₁) = 1, d(x₂,y₂) = 4.  Greedy (x₁ to its nearest y₁,
    then x₂-y₂) sums 5 at p = 1; the optimum x₁-y₂ + x₂-y₁ sums 3: OSPA = 3/2."""
    X = [[0.0, 0.0], [2.0, 0.0]]
    Y = [[1.0, 0.0], [-2.0, 0.0]]
    assert ospa(X, Y, c=10.0, p=1) == pytest.approx(1.5)


def test_ospa_empty_sets():
    empty = np.zeros((0, 2))
    assert ospa(empty, empty, c=7.0) == 0.0
    assert ospa([], [], c=7.0) == 0.0
    assert ospa(empty, [[1.0, 2.0]], c=7.0) == 7.0
    assert ospa([[1.0, 2.0], [3.0, 4.0]], [], c=7.0) == 7.0


def test_gospa_oracle_and_decomposition():
    """Truth X = {(0,0), (10,0)}, estimates Y = {(1,0), (100,100)}, c = 5, p = 2:
    (0,0)-(1,0) is a pair (d = 1); (10,0) is missed and (100,100) false, c²/2 = 12.5 each."""
    X = [[0.0, 0.0], [10.0, 0.0]]
    Y = [[1.0, 0.0], [100.0, 100.0]]
    g = gospa(X, Y, c=5.0, p=2)
    assert g.localisation == pytest.approx(1.0)
    assert (g.n_missed, g.n_false) == (1, 1)
    assert g.missed == pytest.approx(12.5) and g.false == pytest.approx(12.5)
    assert g.distance == pytest.approx(math.sqrt(26.0))
    np.testing.assert_array_equal(g.pairs, [[0, 0]])


def test_gospa_cardinality_only():
    """X = 1 point, Y = 3 far points, c = 2, p = 1: one pair at d ≥ c counts as missed + false:
    n_missed = 1, n_false = 3; d = (c/2)(1 + 3) = 4."""
    X = [[0.0, 0.0]]
    Y = [[10.0, 0.0], [0.0, 10.0], [-10.0, 0.0]]
    g = gospa(X, Y, c=2.0, p=1)
    assert (g.n_missed, g.n_false) == (1, 3)
    assert g.distance == pytest.approx(4.0)
    assert g.pairs.shape == (0, 2)


def test_gospa_empty_sets():
    assert gospa([], [], c=3.0).distance == 0.0
    g = gospa(np.zeros((0, 2)), [[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]], c=3.0, p=2)
    assert g.distance == pytest.approx(math.sqrt(3 * 9.0 / 2))
    assert (g.n_missed, g.n_false) == (0, 3)
    g = gospa([[0.0, 0.0]], [], c=3.0, p=2)
    assert (g.n_missed, g.n_false, g.missed) == (1, 0, 4.5)


def test_bad_arguments():
    with pytest.raises(ValueError, match="c:"):
        ospa([[0.0]], [[1.0]], c=0.0)
    with pytest.raises(ValueError, match="p:"):
        gospa([[0.0]], [[1.0]], c=1.0, p=0.5)
    with pytest.raises(ValueError, match="different dimension"):
        ospa([[0.0, 0.0]], [[1.0]], c=1.0)
    with pytest.raises(ValueError, match="X:"):
        ospa([0.0, 1.0], [[1.0]], c=1.0)


# -- properties ------------------------------------------------------------------------------

_elem = st.floats(-20, 20, allow_nan=False, allow_infinity=False)


def _set(max_size=4):
    return st.integers(0, max_size).flatmap(lambda n: arrays(np.float64, (n, 2), elements=_elem))


_c = st.floats(0.5, 30.0)
_p = st.sampled_from([1.0, 2.0, 3.0])


def _brute_force_ospa(X, Y, c, p):
    X, Y = np.asarray(X).reshape(-1, 2), np.asarray(Y).reshape(-1, 2)
    if len(X) > len(Y):
        X, Y = Y, X
    m, n = len(X), len(Y)
    if n == 0:
        return 0.0
    best = math.inf
    for perm in itertools.permutations(range(n), m):
        s = sum(min(c, float(np.linalg.norm(X[i] - Y[j]))) ** p for i, j in enumerate(perm))
        best = min(best, s)
    return ((best + c**p * (n - m)) / n) ** (1 / p)


@given(_set(), _set(), _c, _p)
def test_ospa_equals_brute_force(X, Y, c, p):
    assert ospa(X, Y, c, p) == pytest.approx(_brute_force_ospa(X, Y, c, p), rel=1e-9, abs=1e-12)


@given(_set(), _set(), _c, _p)
def test_symmetry_and_bounds(X, Y, c, p):
    d = ospa(X, Y, c, p)
    assert d == pytest.approx(ospa(Y, X, c, p), rel=1e-12, abs=1e-12)
    assert 0.0 <= d <= c * (1 + 1e-12)
    g = gospa(X, Y, c, p)
    assert g.distance == pytest.approx(gospa(Y, X, c, p).distance, rel=1e-12, abs=1e-12)
    # decomposition: distance^p = localisation + missed + false
    total = g.localisation + g.missed + g.false
    assert g.distance**p == pytest.approx(total, rel=1e-9, abs=1e-12)
    assert g.n_missed == len(X) - len(g.pairs) and g.n_false == len(Y) - len(g.pairs)


@given(_set(), _c, _p)
def test_identity_and_permutation_invariance(X, c, p):
    assert ospa(X, X, c, p) == pytest.approx(0.0, abs=1e-9)
    assert gospa(X, X, c, p).distance == pytest.approx(0.0, abs=1e-9)
    Xp = X[::-1]
    assert ospa(X, Xp, c, p) == pytest.approx(0.0, abs=1e-9)
    if len(X):
        moved = X + np.array([[0.0, 1.0]] + [[0.0, 0.0]] * (len(X) - 1))
        assert ospa(X, moved, c, p) > 0.0
        assert ospa(X, X[:-1], c, p) > 0.0


@given(_set(3), _set(3), _set(3), _c, _p)
def test_triangle_inequality(X, Y, W, c, p):
    for f in (lambda a, b: ospa(a, b, c, p), lambda a, b: gospa(a, b, c, p).distance):
        assert f(X, Y) <= f(X, W) + f(W, Y) + 1e-9
