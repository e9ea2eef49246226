"""Loewner-interval lower bounds (covnet.core.allocation.interval_bounds): oracle values on hand
cases where
the minimum over the interval is known in closed form, and the safety property (bound <= the
metric as computed, on completions of actual subsets and on random points of the interval) for
every registered metric."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.allocation.exact import subset_covariance
from covnet.core.allocation.interval_bounds import (
    DesiredConstants,
    IntervalContext,
    interval_lower_bound,
    search_context,
)
from covnet.core.metrics import METRICS

#: a context without model error: only the bounds' relative rounding allowance remains
EXACT = IntervalContext(err=0.0, lam_min=0.1, lam_max=10.0, kappa=100.0, scale=10.0)


def _phi(x):
    return math.log((1 + x) / 2) - 0.5 * math.log(x)


def _psi(x):
    return 0.25 * (x + 1 / x - 2)


def test_every_built_in_metric_has_an_interval_bound():
    assert all(m.interval_bound is not None for m in METRICS.values() if m.batch_invariant)


def test_a_metric_without_an_interval_bound_is_named():
    with pytest.raises(KeyError, match="no interval bound for metric 'nope'"):
        interval_lower_bound("nope", np.eye(2), np.eye(2), np.eye(2), EXACT)


# ---- oracle values: diagonal intervals and multiples of P_d, where min over [A, B] is known ----

A_DIAG = np.array([2.0, 0.5, 3.0, 0.2])
B_DIAG = np.array([4.0, 0.9, 3.5, 0.6])
D_DIAG = np.array([5.0, 0.6, 1.0, 0.7])
# distances of each d_i to [a_i, b_i]: 1.0, 0, 2.0, 0.1
DIST = np.array([1.0, 0.0, 2.0, 0.1])


@pytest.mark.parametrize(
    "name, expected",
    [
        ("spectral", 2.0),  # max_i dist_i: P = clip(D, A, B) (diagonal) attains it
        ("abs_trace", 3.1),  # sum_i dist_i
        ("frobenius", math.sqrt(1.0 + 4.0 + 0.01)),  # sqrt(sum dist²)
        ("one_norm", 2.0),  # diagonal P - D: the largest |entry|
        ("inf_norm", 2.0),
        ("trace_diff", 0.0),  # tr D = 7.3 lies in [tr A, tr B] = [5.7, 9.0]
    ],
)
def test_diagonal_interval_oracle(name, expected):
    """For diagonal ``A <= B`` and ``P_d`` the minimum over the interval is attained at the
    diagonal ``P = clip(P_d, A, B)``; the bounds are exact there (up to their rounding
    allowance)."""
    lb = interval_lower_bound(name, np.diag(A_DIAG), np.diag(B_DIAG), np.diag(D_DIAG), EXACT)
    assert float(lb) == pytest.approx(expected, rel=1e-12, abs=1e-10)
    P_best = np.diag(np.clip(D_DIAG, A_DIAG, B_DIAG))
    if name == "trace_diff":  # the point of the segment [A, B] with the trace of P_d
        t = (D_DIAG.sum() - A_DIAG.sum()) / (B_DIAG.sum() - A_DIAG.sum())
        P_best = np.diag(A_DIAG + t * (B_DIAG - A_DIAG))
    assert float(METRICS[name](P_best, np.diag(D_DIAG))) == pytest.approx(expected, abs=1e-12)


def test_trace_diff_oracle_outside_the_trace_interval():
    D = np.diag(D_DIAG) * 3.0  # tr = 21.9 > tr B = 9.0
    lb = interval_lower_bound("trace_diff", np.diag(A_DIAG), np.diag(B_DIAG), D, EXACT)
    assert float(lb) == pytest.approx(21.9 - 9.0, rel=1e-12)


@pytest.mark.parametrize("a, b", [(0.3, 0.6), (0.5, 2.0), (1.5, 4.0)])
@pytest.mark.parametrize("name, fn", [("logdet", _phi), ("kl", _psi)])
def test_multiples_of_p_d_oracle(name, fn, a, b):
    """``A = a P_d``, ``B = b P_d``: every generalized eigenvalue lies in ``[a, b]``, and the
    minimum is ``n φ(clip(1, a, b))`` at ``P = clip(1, a, b) P_d``."""
    rng = np.random.default_rng(3)
    X = rng.standard_normal((4, 4))
    D = X @ X.T + np.eye(4)
    lb = float(interval_lower_bound(name, a * D, b * D, D, EXACT))
    c = min(max(1.0, a), b)
    assert lb <= 4 * fn(c)
    assert lb == pytest.approx(4 * fn(c), rel=1e-6, abs=1e-9)  # the rounding allowance
    assert float(METRICS[name](c * D, D)) == pytest.approx(4 * fn(c), rel=1e-9, abs=1e-12)


def test_svd_size_oracle():
    """``[P, P]`` with ``P``, ``P_d`` diagonal in the same (descending) order: the orientation
    term is 0 and the size term is the whole value."""
    P = np.diag([9.0, 4.0, 2.0, 1.0])
    D = np.diag([8.0, 5.0, 2.5, 0.5])
    lb = float(interval_lower_bound("svd", P, P, D, EXACT))
    assert lb == pytest.approx(math.sqrt(1 + 1 + 0.25 + 0.25), rel=1e-12)
    assert lb <= float(METRICS["svd"](P, D))


def test_spectral_two_sided_oracle():
    """Both sides of the spectral bound: ``A`` above ``P_d`` in one direction, ``B`` below it in
    another."""
    A = np.diag([3.0, 0.1])
    B = np.diag([4.0, 0.2])
    D = np.diag([1.0, 1.5])
    lb = float(interval_lower_bound("spectral", A, B, D, EXACT))
    assert lb == pytest.approx(2.0, rel=1e-12)  # max(3 - 1, 1.5 - 0.2)


@pytest.mark.parametrize("name", sorted(METRICS))
def test_degenerate_interval_is_below_the_value(name):
    rng = np.random.default_rng(7)
    X = rng.standard_normal((5, 4, 4))
    P = X @ np.swapaxes(X, 1, 2) + 0.5 * np.eye(4)
    Y = rng.standard_normal((4, 4))
    D = Y @ Y.T + np.eye(4)
    lb = interval_lower_bound(name, P, P, D, EXACT)
    exact = METRICS[name](P, D)
    assert lb.shape == (5,)
    assert np.all(lb <= exact)
    if name in ("spectral", "abs_trace", "frobenius", "trace_diff", "logdet", "kl"):
        np.testing.assert_allclose(lb, exact, rtol=1e-6)  # tight on a point, but for rounding


def test_shapes_and_errors():
    P = np.eye(3)
    assert interval_lower_bound("spectral", P, P, P, EXACT).shape == ()
    assert interval_lower_bound("spectral", P[None], P[None], P, EXACT).shape == (1,)
    with pytest.raises(KeyError, match="no interval bound for metric 'nope'"):
        interval_lower_bound("nope", P, P, P, EXACT)
    with pytest.raises(ValueError, match="A and B must both be"):
        interval_lower_bound("spectral", P, P[None], P, EXACT)
    with pytest.raises(ValueError, match="P_d must be"):
        interval_lower_bound("spectral", P, P, np.eye(2), EXACT)
    dc = DesiredConstants(np.eye(3))
    assert float(interval_lower_bound("kl", 2 * P, 3 * P, dc, EXACT)) > 0.0


# ---- safety: bound <= computed value on completions and on random interval points ------------

_elems = st.floats(-3, 3, allow_nan=False, allow_infinity=False)


@st.composite
def spd(draw, n, floor):
    A = draw(arrays(np.float64, (n, n), elements=_elems))
    return A @ A.T + floor * np.eye(n)


@st.composite
def interval_problem(draw):
    """``P_pred``, gains on a random support (any rank, some zero), ``P_d``, and a node: an
    included set ``I`` and undecided ``U`` (as sensor index lists)."""
    n = draw(st.integers(2, 5))
    N = draw(st.integers(1, 6))
    r = draw(st.integers(1, n))
    support = np.sort(draw(st.permutations(range(n)))[:r])
    scale = draw(st.sampled_from([1e-2, 1.0, 1e2]))
    gains = np.zeros((N, n, n))
    for j in range(N):
        k = draw(st.integers(0, r))
        Hs = draw(arrays(np.float64, (k, r), elements=_elems))
        gains[j][np.ix_(support, support)] = Hs.T @ Hs * scale
    P_pred = draw(spd(n, 0.05)) * draw(st.sampled_from([0.1, 1.0, 30.0]))
    P_pred = 0.5 * (P_pred + P_pred.T)
    P_d = draw(spd(n, 0.05))
    P_d = 0.5 * (P_d + P_d.T)
    labels = draw(st.lists(st.sampled_from("iuo"), min_size=N, max_size=N))
    inc = [j for j in range(N) if labels[j] == "i"]
    und = [j for j in range(N) if labels[j] == "u"]
    return P_pred, gains, P_d, inc, und


def _P(P_pred, gains, subset):
    J = np.zeros(gains.shape[1:])
    for j in sorted(subset):
        J = J + gains[j]
    return subset_covariance(P_pred, J)


def _ctx(P_pred, gains, P_d):
    Y0 = np.linalg.inv(P_pred)
    info = float(np.trace(Y0) + np.trace(gains.sum(axis=0)))
    return search_context(
        P_pred, info, P_d, n_terms=gains.shape[0], gain_abs_max=float(np.abs(gains).sum())
    )


@pytest.mark.parametrize("name", sorted(METRICS))
@settings(max_examples=40)
@given(pb=interval_problem(), data=st.data())
def test_bound_never_exceeds_the_value_of_a_completion(name, pb, data):
    """For every completion ``D`` of the node (``I ⊆ D ⊆ I ∪ U``) and random points ``P`` of the
    interval, ``bound([P(I ∪ U), P(I)]) <= metric(P)`` as computed."""
    P_pred, gains, P_d, inc, und = pb
    A = _P(P_pred, gains, inc + und)
    B = _P(P_pred, gains, inc)
    ctx = _ctx(P_pred, gains, P_d)
    lb = float(interval_lower_bound(name, A, B, P_d, ctx))
    assert lb >= 0.0
    f = METRICS[name]
    values = []
    for code in range(2 ** len(und)):
        D = inc + [u for b, u in enumerate(und) if code >> b & 1]
        try:
            values.append(float(f(_P(P_pred, gains, D), P_d)))
        except np.linalg.LinAlgError:  # a P_d the metric cannot take (logdet, kl)
            return
    assert lb <= min(values), (lb, min(values))
    # random points of the Loewner interval: P = A + R X R with 0 <= X <= I, R = (B - A)^½
    w, V = np.linalg.eigh(B - A)
    R = (V * np.sqrt(np.maximum(w, 0.0))) @ V.T
    n = A.shape[0]
    for _ in range(4):
        Q, _ = np.linalg.qr(data.draw(arrays(np.float64, (n, n), elements=_elems)) + 4 * np.eye(n))
        x = np.array(data.draw(st.lists(st.floats(0, 1), min_size=n, max_size=n)))
        X = (Q * x) @ Q.T
        P = A + R @ X @ R
        P = 0.5 * (P + P.T)
        assert lb <= float(f(P, P_d)), (lb, float(f(P, P_d)))


@pytest.mark.parametrize("name", sorted(METRICS))
def test_batched_equals_one_at_a_time(name):
    rng = np.random.default_rng(11)
    X = rng.standard_normal((6, 4, 4))
    A = X @ np.swapaxes(X, 1, 2) + 0.5 * np.eye(4)
    B = A + 0.3 * np.eye(4)
    Y = rng.standard_normal((4, 4))
    D = Y @ Y.T + np.eye(4)
    ctx = search_context(np.eye(4) * 10.0, 30.0, D)
    batched = interval_lower_bound(name, A, B, D, ctx)
    single = [float(interval_lower_bound(name, a, b, D, ctx)) for a, b in zip(A, B, strict=True)]
    np.testing.assert_allclose(batched, single, rtol=1e-12, atol=1e-14)
