"""Spectral's lazy summaries (:func:`covnet.core.allocation.interval_bounds._spectral_lazy`):
a kept child's new endpoint gets its parent's summary of the same side (valid for the nested
interval), proven rows the pre-test's, and only the subsets that may become candidates get
LAPACK's eigenvalues.  Checked: the bound and the candidate estimate never above the
eigenvalue ones (random, near-threshold and ill-conditioned endpoints, both kinds), the rows
whose estimate the eigenvalues put at or below ``tau`` are LAPACK's bits, and the exact search
equals the exhaustive one; an inflated parent summary or a wrong proof step is caught."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_search_inertia import _problem, _trials

from covnet.core.allocation import interval_bounds as IB
from covnet.core.allocation import search as S
from covnet.core.allocation.exact import Constraints, allocate_exhaustive
from covnet.core.allocation.interval_bounds import (
    _eig_minus_d,
    _spectral_combine,
    _spectral_lazy,
)


def _parents(rng, X, lower):
    """Nested parent endpoints: ``X - G`` (a lower endpoint's parent ``A`` is below it) or
    ``X + G`` (an upper one's ``B`` above it), ``G`` positive definite with eigenvalues far
    above the rounding (``1e-6``-``1e-3`` of ``X``'s scale)."""
    m, n = X.shape[0], X.shape[1]
    scale = np.abs(X).max(axis=(1, 2))
    Q, _ = np.linalg.qr(rng.standard_normal((m, n, n)))
    lam = rng.uniform(1e-6, 1e-3, (m, n)) * scale[:, None]
    G = np.einsum("mij,mj,mkj->mik", Q, lam, Q)
    return X - G if lower else X + G


def _check(dc, X, ctx, tau, lower, prev_shift=0.0):
    """``(ok, eig_rows, proven_rows)``: the node bound of the lazy summary (with a partner read
    as nothing) is at most the eigenvalue one, a row that differs from the eigenvalues is a
    parent's or has a bound ``> tau``; for upper endpoints also the candidate estimate
    ``combine(s, s)``: at most the eigenvalue one, and LAPACK's bits wherever that one is
    ``<= tau``.  ``prev_shift`` inflates the parent's summary (the check must then fail)."""
    rng = np.random.default_rng(11)
    s = _eig_minus_d(X, dc)
    prev = _eig_minus_d(_parents(rng, X, lower), dc)
    if lower:
        prev[:, -1] += prev_shift
    else:
        prev[:, 0] -= prev_shift
    got = _spectral_lazy(X, dc, ctx, tau, lower, prev)
    free = np.full_like(s, np.inf)
    free[:, -1] = -np.inf
    if lower:
        lb, g = _spectral_combine(s, free, dc, ctx), _spectral_combine(got, free, dc, ctx)
    else:
        lb, g = _spectral_combine(free, s, dc, ctx), _spectral_combine(free, got, dc, ctx)
    ok = bool((g <= lb).all())
    eig = np.all(got == s, axis=1)
    par = np.all(got == prev, axis=1)
    ok &= bool((g[~eig & ~par] > tau).all()) or not lower
    proven = int((~eig & ~par).sum())
    if not lower:
        est, est_lazy = _spectral_combine(s, s, dc, ctx), _spectral_combine(got, got, dc, ctx)
        ok &= bool((est_lazy <= est).all())
        ok &= bool(eig[est <= tau].all())  # the recorded candidates: eigvalsh's bits
        ok &= bool((est_lazy[~eig] > tau).all())
    return ok, int(eig.sum()), proven


@pytest.mark.parametrize("lower", [True, False])
def test_lazy_summaries_never_exceed_the_eigenvalue_bound(lower):
    proven = eig = 0
    for dc, X, ctx, tau in _trials(lower):
        ok, e, p = _check(dc, X, ctx, tau, lower)
        assert ok
        eig += e
        proven += p
    assert proven > 0  # proofs happen
    if lower:
        assert eig == 0  # a lower endpoint never needs eigenvalues
    else:
        assert eig > 0  # near-threshold estimates get LAPACK's bits (not vacuous)


@pytest.mark.parametrize("lower", [True, False])
def test_an_inflated_parent_or_a_wrong_proof_is_caught(lower, monkeypatch):
    """The check above fails with a parent summary inflated by a small fraction of ``tau``,
    and (upper endpoints: their second, ``λmax``, proof) with a negative margin."""
    assert not all(
        _check(dc, X, ctx, tau, lower, prev_shift=0.01 * tau)[0]
        for dc, X, ctx, tau in _trials(lower)
    )
    monkeypatch.setattr(IB, "MARGIN", -0.25)
    monkeypatch.setattr(IB, "SAFETY", -math.inf)
    assert not all(_check(dc, X, ctx, tau, lower)[0] for dc, X, ctx, tau in _trials(lower))


def _lazy_rows(P, G, D, c, inflate=0.0):
    """The exact search through a wrapper of the lazy summary (read through
    :data:`SPECTRAL_BOUND`): its result and how many rows kept the parent's summary;
    ``inflate`` raises the parent's summaries (an invalid bound)."""
    n = [0]
    orig = IB._spectral_lazy

    def spy(X, dc, ctx, tau, lower, prev):
        prev = np.array(prev)
        if lower:
            prev[:, -1] += inflate
        else:
            prev[:, 0] -= inflate
        out = orig(X, dc, ctx, tau, lower, prev)
        n[0] += int(np.all(out == prev, axis=1).sum())
        return out

    bound = IB.SPECTRAL_BOUND
    object.__setattr__(bound, "lazy", spy)
    try:
        res = S.allocate_bnb(P, G, D, "spectral", c)
    finally:
        object.__setattr__(bound, "lazy", orig)
    return res, n[0]


def test_exact_search_equals_exhaustive():
    """Spectral at N = 12..16, with and without a budget and constraints: the lazy exact search
    equals the exhaustive one (subset, value, ``P`` bits), and kept rows skipped their
    eigenvalues."""
    assert S.LAZY and S.PRETEST
    skipped = 0
    for seed in range(8):
        N = 12 + seed % 5
        P, G, D = _problem(seed, N)
        for c in (Constraints(), Constraints(frozenset({3}), frozenset({1}), 6)):
            ref = allocate_exhaustive(P, G, D, "spectral", c)
            got, k = _lazy_rows(P, G, D, c)
            assert got.status == 0
            assert (got.subset, got.value) == (ref.subset, ref.value)
            np.testing.assert_array_equal(got.P, ref.P)
            skipped += k
    assert skipped > 0


def test_an_inflated_lazy_bound_changes_the_search():
    """Parent summaries raised by 0.5 (an invalid bound) change the result on some problem: the
    check above can fail."""
    changed = 0
    for seed in range(8):
        N = 12 + seed % 5
        P, G, D = _problem(seed, N)
        ref = allocate_exhaustive(P, G, D, "spectral")
        got, _ = _lazy_rows(P, G, D, Constraints(), inflate=0.5)
        changed += (got.subset, got.value) != (ref.subset, ref.value)
    assert changed > 0
