"""Spectral's inertia pre-test (:func:`covnet.core.allocation.interval_bounds._spectral_above`,
:mod:`covnet.core.allocation.inertia`): a row it proves prunable has today's eigenvalue bound
``> tau`` (random, near-threshold and ill-conditioned matrices), the other rows get LAPACK's
eigenvalues bit for bit, a zero or negative margin is caught, and the exact search with it
builds the same tree (node count) and equals the exhaustive search."""

from __future__ import annotations

import math

import numpy as np
import pytest

from covnet.core.allocation import inertia
from covnet.core.allocation import interval_bounds as IB
from covnet.core.allocation import search as S
from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.allocation.interval_bounds import (
    DesiredConstants,
    IntervalContext,
    _eig_minus_d,
    _spectral_above,
    _spectral_combine,
    _spectral_threshold,
)


def _ctx(scale: float, err: float = 1e-13) -> IntervalContext:
    return IntervalContext(err, 1e-3, scale, 1e6, scale)


def _sym(rng, m, n, lam):
    """``m`` symmetric matrices with eigenvalues ``lam`` ``(m, n)`` and random eigenvectors."""
    Q, _ = np.linalg.qr(rng.standard_normal((m, n, n)))
    return np.einsum("mij,mj,mkj->mik", Q, lam, Q)


def _cases(rng, D, ctx, tau, lower, m=400):
    """Endpoints ``X`` whose bound is near ``tau``: random, within a few ulps of the threshold
    (the adversarial ones), and ill-conditioned (eigenvalues over 14 decades)."""
    dc = DesiredConstants(D)
    v0 = _spectral_threshold(tau, dc, ctx)
    n = D.shape[0]
    out = []
    for kind in ("random", "ulps", "ill"):
        if kind == "random":
            ext = v0 * (1.0 + rng.uniform(-0.05, 0.05, m))
            rest = rng.uniform(-3.0, 3.0, (m, n - 1)) * v0
        elif kind == "ulps":
            k = np.where(rng.random(m) < 0.5, 40, 4096)
            ext = v0 * (1.0 + rng.integers(-k, k) * 2.0**-52)
            rest = -rng.uniform(0.0, 1e3, (m, n - 1)) * v0
        else:
            ext = v0 * (1.0 + rng.uniform(-1e-9, 1e-9, m))
            rest = -(10.0 ** rng.uniform(-14.0, 0.0, (m, n - 1))) * v0
        rest = np.minimum(rest, ext[:, None])  # the extreme eigenvalue stays the extreme one
        lam = np.concatenate([rest, ext[:, None]], axis=1)
        if not lower:  # -λmin(M) near v0
            lam = -lam
        out.append(_sym(rng, m, n, lam) + D)
    return dc, np.concatenate(out)


def _violations(X, dc, ctx, tau, lower):
    """Rows the pre-test proves while today's bound keeps them, the rows proven, and whether the
    other rows are today's summaries bit for bit."""
    got = _spectral_above(X, dc, ctx, tau, lower)
    s = _eig_minus_d(X, dc)
    free = np.full_like(s, np.inf)  # a partner read as -inf: the bound of this endpoint alone
    free[:, -1] = -np.inf
    lb = _spectral_combine(s, free, dc, ctx) if lower else _spectral_combine(free, s, dc, ctx)
    proven = np.isinf(got[:, -2])
    bits = bool(np.array_equal(got[~proven], s[~proven]))
    # a proven row's looser bound is > tau, and at most today's (so a valid bound) where the
    # pre-test is right
    g = _spectral_combine(got, free, dc, ctx) if lower else _spectral_combine(free, got, dc, ctx)
    valid = bool((g[proven] > tau).all() and (g[proven] <= lb[proven]).all())
    return int((proven & ~(lb > tau)).sum()), int(proven.sum()), bits and valid


def _trials(lower):
    """Six near-threshold batches at three scales and rounding allowances: ``(dc, X, ctx,
    tau)``."""
    rng = np.random.default_rng(7 if lower else 8)
    for trial in range(6):
        D = np.diag(rng.uniform(0.1, 3.0, 4))
        scale = [1.0, 1e3, 1e-3][trial % 3]
        ctx = _ctx(scale * 10.0, err=[0.0, 1e-13, 1e-9][trial % 3] * scale)
        tau = scale * rng.uniform(0.5, 2.0)
        dc, X = _cases(rng, D * scale, ctx, tau, lower)
        yield dc, X, ctx, tau


@pytest.mark.parametrize("lower", [True, False])
def test_the_pretest_never_prunes_what_the_bound_keeps(lower):
    for dc, X, ctx, tau in _trials(lower):
        bad, proven, bits = _violations(X, dc, ctx, tau, lower)
        assert bad == 0
        assert bits
        assert proven > X.shape[0] // 10  # the test does prune (not vacuous)


@pytest.mark.parametrize("lower", [True, False])
@pytest.mark.parametrize("margin", [0.0, -(2.0**-44)])
def test_a_zero_or_negative_margin_is_caught(lower, margin, monkeypatch):
    """Without the margin (the threshold itself or below it, and no check of a proven row),
    some near-threshold row breaks down while LAPACK's eigenvalue keeps it: the check above
    fails."""
    monkeypatch.setattr(IB, "MARGIN", margin)
    monkeypatch.setattr(IB, "SAFETY", 0.0 if margin == 0.0 else -math.inf)
    bad = sum(_violations(X, dc, ctx, tau, lower)[0] for dc, X, ctx, tau in _trials(lower))
    assert bad > 0


def test_threshold_is_the_deflations():
    """``v0`` passes the deflation (as :func:`_spectral_combine` computes it) and its
    predecessor by many ulps does not: the pre-test's threshold is tight, not loose."""
    rng = np.random.default_rng(3)
    dc = DesiredConstants(np.eye(4))
    for _ in range(200):
        ctx = _ctx(10.0 ** rng.uniform(-3, 3), 10.0 ** rng.uniform(-16, -8))
        tau = 10.0 ** rng.uniform(-3, 3)
        v0 = _spectral_threshold(tau, dc, ctx)
        lo = v0 * (1.0 - 2.0**-44)
        v = np.array([[v0, -math.inf], [lo, -math.inf]])
        s = np.zeros((2, 4))
        s[:, -1] = v[:, 0]
        free = np.full((2, 4), np.inf)
        lb = _spectral_combine(s, free, dc, ctx)
        assert lb[0] > tau and not lb[1] > tau
    assert math.isnan(_spectral_threshold(math.inf, dc, _ctx(1.0)))


def test_cholesky_breakdown_decides_definiteness_away_from_the_margin():
    """Breakdown on clearly indefinite matrices, none on clearly definite ones (condition up
    to 1e12); the negated form gives the very bits of the explicitly negated entries."""
    rng = np.random.default_rng(5)
    m, n = 2000, 4
    lam = 10.0 ** rng.uniform(-6.0, 6.0, (m, n))
    neg = rng.random(m) < 0.5
    lam[neg, 0] = -lam[neg, 0]
    H = _sym(rng, m, n, lam)
    diag = [H[:, i, i] for i in range(n)]
    off = {(i, j): H[:, i, j] for i in range(n) for j in range(i)}
    got = inertia.cholesky_breaks(diag, off)
    np.testing.assert_array_equal(got, neg)
    offn = {k: -v for k, v in off.items()}
    np.testing.assert_array_equal(inertia.cholesky_breaks(diag, offn, negated=True), got)
    assert inertia.breakdown_slack(4) < 1e-14


@pytest.mark.parametrize("lower", [True, False])
def test_non_finite_rows_are_never_proven(lower):
    """A NaN or infinite endpoint is reported broken by the factorisation but never proven: it
    reaches LAPACK, which raises or answers as it did without the pre-test; a huge one (past
    ``BIG``) is not proven either."""
    rng = np.random.default_rng(9)
    D = np.eye(4)
    dc, ctx, tau = DesiredConstants(D), _ctx(10.0), 1.0
    X = _sym(rng, 6, 4, rng.uniform(-5.0, 5.0, (6, 4))) + D
    for bad in (np.nan, np.inf, -np.inf):
        Y = X.copy()
        Y[2, 0, 0] = bad
        Y[3, 1, 2] = Y[3, 2, 1] = bad
        M = Y - D
        broken = inertia.lam_max_above(M, 1.0) if lower else inertia.lam_min_below(M, 1.0)
        assert broken[2] or broken[3]  # the factorisation alone would claim one
        try:
            ref = _eig_minus_d(Y, dc)
        except np.linalg.LinAlgError:
            with pytest.raises(np.linalg.LinAlgError):
                _spectral_above(Y, dc, ctx, tau, lower)
        else:
            got = _spectral_above(Y, dc, ctx, tau, lower)
            np.testing.assert_array_equal(got[2:4], ref[2:4])
    Y = X.copy()
    Y[1] *= 2.0**520
    got = _spectral_above(Y, dc, ctx, tau, lower)
    np.testing.assert_array_equal(got[1], _eig_minus_d(Y, dc)[1])


def _spd(rng, n, scale=1.0):
    A = rng.standard_normal((n, n))
    return scale * (A @ A.T + 0.5 * np.eye(n))


def _problem(seed, N):
    rng = np.random.default_rng(seed)
    n = 4
    P = _spd(rng, n, 3.0)
    D = _spd(rng, n, 0.3)
    G = np.zeros((N, n, n))
    for j in range(N):
        H = rng.standard_normal((1 + j % 2, n))
        G[j] = H.T @ H * rng.uniform(0.1, 2.0)
    return P, G, D


def test_exact_search_equals_exhaustive_and_the_tree_is_unchanged(monkeypatch):
    """Spectral at N = 12..16: the exact search with the pre-test equals the exhaustive search
    (subset, value, ``P`` bits) and visits as many nodes as without it; the pre-test proved
    rows (it is exercised)."""
    proven = 0
    monkeypatch.setattr(S, "LAZY", False)  # the pre-test alone (tests/unit/test_search_lazy.py)
    for seed in range(8):
        N = 12 + seed % 5
        P, G, D = _problem(seed, N)
        for c in (Constraints(), Constraints(frozenset({3}), frozenset({1}), 6)):
            ref = allocate_exhaustive(P, G, D, "spectral", c)
            monkeypatch.setattr(S, "PRETEST", False)
            plain = S.allocate_bnb(P, G, D, "spectral", c)
            monkeypatch.setattr(S, "PRETEST", True)
            got = S.allocate_bnb(P, G, D, "spectral", c)
            assert got.status == 0
            assert (got.subset, got.value) == (ref.subset, ref.value)
            np.testing.assert_array_equal(got.P, ref.P)
            assert got.n_nodes == plain.n_nodes
            proven += _proven_rows(P, G, D, c)
    assert proven > 0


def _proven_rows(P, G, D, c):
    """How many rows the pre-test proves in one exact search (a wrapper on the module's
    function; the search reads it through :data:`SPECTRAL_BOUND`)."""
    n = [0]
    orig = IB._spectral_above

    def spy(X, dc, ctx, tau, lower):
        out = orig(X, dc, ctx, tau, lower)
        n[0] += int(np.isinf(out[:, -2]).sum())
        return out

    bound = IB.SPECTRAL_BOUND
    object.__setattr__(bound, "above", spy)
    try:
        S.allocate_bnb(P, G, D, "spectral", c)
    finally:
        object.__setattr__(bound, "above", orig)
    return n[0]


def test_a_negative_margin_changes_the_search(monkeypatch):
    """A margin far below zero (proving rows whose bound is below ``tau``) changes the tree or
    the result on some problem: the node-count and exhaustive checks above can fail."""
    monkeypatch.setattr(IB, "MARGIN", -0.25)
    monkeypatch.setattr(IB, "SAFETY", -math.inf)
    monkeypatch.setattr(S, "LAZY", False)
    changed = 0
    for seed in range(8):
        N = 12 + seed % 5
        P, G, D = _problem(seed, N)
        ref = allocate_exhaustive(P, G, D, "spectral")
        monkeypatch.setattr(S, "PRETEST", False)
        plain = S.allocate_bnb(P, G, D, "spectral")
        monkeypatch.setattr(S, "PRETEST", True)
        got = S.allocate_bnb(P, G, D, "spectral")
        changed += got.n_nodes != plain.n_nodes or (got.subset, got.value) != (
            ref.subset,
            ref.value,
        )
    assert changed > 0
