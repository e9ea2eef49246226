"""The fast allocator picks exactly what the plain loop over all subsets picks (same subset, same
value bits), for every registered metric and a user's own, with and without constraints; and
every pruning bound is below the exact value it bounds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.core.allocation import _fast as fast
from covnet.core.allocation.exact import (
    Constraints,
    InfeasibleAllocation,
    allocate,
    allocate_exhaustive,
    prepare,
)
from covnet.core.metrics import METRICS, capability
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensing import correlated_noise, information_gain, position_matrix

#: the metrics with a fast-path bound (every built-in one)
WITH_SUBSET_BOUND = sorted(k for k, m in METRICS.items() if m.subset_bound is not None)

_elems = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


@st.composite
def spd(draw, n, floor=1e-3):
    A = draw(arrays(np.float64, (n, n), elements=_elems))
    return A @ A.T + floor * np.eye(n)


@st.composite
def paper_like(draw):
    """Position sensors on [x, vx, y, vy], a predicted covariance from the CV model."""
    N = draw(st.integers(1, 10))
    H = position_matrix()
    sig = st.floats(3.0, 60.0)
    gains = np.stack(
        [
            information_gain(
                H, correlated_noise(draw(sig), draw(sig), draw(st.floats(-0.95, 0.95)))
            )
            for _ in range(N)
        ]
    )
    scale = draw(st.sampled_from([1.0, 30.0, 1e3, 1e4]))
    P = draw(spd(4, floor=1.0)) * scale / 100.0 + np.diag([1.0, 0.1, 1.0, 0.1])
    F = cv_transition(1.0)
    P_pred = F @ P @ F.T + dwna_process_noise(1.0, 0.5)
    d = draw(st.sampled_from([(25.0, 1.4), (7.0, 0.8), (100.0, 5.0), (1.0, 0.1)]))
    return P_pred, gains, np.diag([d[0], d[1], d[0], d[1]])


@st.composite
def general(draw):
    """Any dimension 2..5, gains supported on a random subset of the coordinates (any rank)."""
    n = draw(st.integers(2, 5))
    N = draw(st.integers(1, 8))
    r = draw(st.integers(1, n))
    support = np.sort(draw(st.permutations(range(n)))[:r])
    gains = np.zeros((N, n, n))
    for j in range(N):
        k = draw(st.integers(1, r))
        Hs = draw(arrays(np.float64, (k, r), elements=_elems))
        gains[j][np.ix_(support, support)] = Hs.T @ Hs / 10.0
    return draw(spd(n, floor=0.1)), gains, draw(spd(n, floor=0.1))


@st.composite
def constraints(draw, N):
    idx = st.integers(0, N - 1)
    excluded = frozenset(draw(st.lists(idx, max_size=max(N - 1, 0))))
    required = frozenset(draw(st.lists(idx, max_size=3))) - excluded
    budget = draw(st.one_of(st.none(), st.integers(max(1, len(required)), max(1, N))))
    return Constraints(excluded, required, budget)


@st.composite
def problem(draw):
    P_pred, gains, P_d = draw(st.one_of(paper_like(), general()))
    c = draw(st.one_of(st.just(Constraints()), constraints(gains.shape[0])))
    return P_pred, gains, P_d, c


def _same(P_pred, gains, P_d, metric, c):
    try:
        ref = allocate_exhaustive(P_pred, gains, P_d, metric, c)
    except InfeasibleAllocation:
        with pytest.raises(InfeasibleAllocation):
            allocate(P_pred, gains, P_d, metric, c)
        return
    got = allocate(P_pred, gains, P_d, metric, c)
    assert got.subset == ref.subset
    assert got.value == ref.value
    np.testing.assert_array_equal(got.P, ref.P)
    assert got.n_feasible == ref.n_feasible


@pytest.mark.parametrize("name", sorted(METRICS))
@settings(max_examples=20)
@given(pb=problem())
def test_fast_equals_exhaustive(name, pb):
    P_pred, gains, P_d, c = pb
    _same(P_pred, gains, P_d, name, c)


def _eigen_gap(A, B):
    """A user's own metric: difference of the spectra (no bound registered for it)."""
    return np.abs(np.linalg.eigvalsh(A) - np.linalg.eigvalsh(B)).max(axis=-1)


@settings(max_examples=20)
@given(pb=problem())
def test_fast_equals_exhaustive_user_metric(pb):
    P_pred, gains, P_d, c = pb
    _same(P_pred, gains, P_d, _eigen_gap, c)


@pytest.mark.parametrize(
    "name", ["spectral", "svd", "abs_trace", "logdet", _eigen_gap], ids=lambda m: str(m)[:9]
)
@settings(max_examples=10)
@given(pb=problem())
def test_fast_equals_exhaustive_in_tiny_chunks(name, pb):
    """The chunking and blocking code paths (several stage-1 chunks, several exact blocks)."""
    P_pred, gains, P_d, c = pb
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(fast, "CHUNK_BITS", 2)
        mp.setattr(fast, "EXACT_BLOCK", 3)
        mp.setattr(fast, "SEED_POOL", 2)
        mp.setattr(fast, "SEED_POOL_ABOVE", 4)
        _same(P_pred, gains, P_d, name, c)


@pytest.mark.parametrize("name", WITH_SUBSET_BOUND)
@settings(max_examples=25)
@given(pb=problem())
def test_bounds_never_exceed_the_exact_value(name, pb):
    """The safety of every pruning: for every subset, cheap and refined bounds <= the exact
    value the plain reference computes."""
    P_pred, gains, P_d, _ = pb
    N, n = gains.shape[0], gains.shape[1]
    P_pred, P_d = 0.5 * (P_pred + P_pred.T), 0.5 * (P_d + P_d.T)
    Y0 = fast.spd_inverse(P_pred)
    st_ = fast._Setup(P_pred, P_d, Y0, fast.SearchTables(gains, frozenset(), frozenset(), N))
    codes = np.arange(1, 2**N)
    masks = ((codes[:, None] >> np.arange(N)) & 1).astype(bool)
    exact = METRICS[name](fast.spd_inverse(Y0 + fast.gain_sums(gains, masks)), P_d)
    bound = capability(METRICS[name].subset_bound, fast.MetricBound)
    with np.errstate(all="ignore"):
        lbs = [bound.cheap(st_.subsets(codes), P_d, st_.ctx)]
        if bound.refine is not None:
            lbs.append(bound.refine(st_.subsets(codes), P_d, st_.ctx))
    for lb in lbs:
        assert lb.shape == exact.shape
        assert not np.any(lb > exact), (name, float(np.max(lb - exact)))
    assert n == P_pred.shape[0]


@pytest.mark.parametrize("name", WITH_SUBSET_BOUND)
@settings(max_examples=25)
@given(pb=problem())
def test_single_chunk_bounds_never_exceed_the_exact_value(name, pb):
    """The single-chunk plan's stage 1 (``_Setup.chunk_covariances``: ``Z_i`` and ``det Z_i``
    as one product with the plan's ``Q`` table, the diagonal rows fused) is as safe as the
    general one: every bound <= the exact value of every feasible subset, with constraints."""
    P_pred, gains, P_d, c = pb
    n = gains.shape[1]
    P_pred, P_d = 0.5 * (P_pred + P_pred.T), 0.5 * (P_d + P_d.T)
    plan = prepare(gains, c)
    tab = plan.tables
    if tab is None or not tab.chunk:
        return
    Y0 = fast.spd_inverse(P_pred)
    exact = METRICS[name](fast.spd_inverse(Y0 + fast.gain_sums(plan.gains, tab.masks)), P_d)
    bound = capability(METRICS[name].subset_bound, fast.MetricBound)
    st_ = fast._Setup(P_pred, P_d, Y0, tab)
    with np.errstate(all="ignore"):
        lbs = [bound.cheap(st_.chunk_covariances(), P_d, st_.ctx)]
        if bound.refine is not None:
            lbs.append(bound.refine(st_.chunk_covariances(), P_d, st_.ctx))
    for lb in lbs:
        assert lb.shape == exact.shape
        assert not np.any(lb > exact), (name, float(np.max(lb - exact)))
    assert n == P_pred.shape[0]


@st.composite
def decisions(draw):
    """One gains/constraints set and a few decisions on it, the desired covariances drawn from a
    small pool (so a plan sees the same ``P_d`` again, after others), some sensors duplicated
    (exact ties between subsets)."""
    P_pred, gains, P_d, c = draw(problem())
    if gains.shape[0] >= 2 and draw(st.booleans()):
        gains = np.concatenate([gains, gains[:1]])  # an identical sensor: tied subsets
        c = Constraints()
    n = gains.shape[1]
    pool = [P_d, draw(spd(n, floor=0.1)), np.eye(n)]
    steps = []
    for _ in range(draw(st.integers(2, 4))):
        scale = draw(st.sampled_from([0.5, 1.0, 2.0]))
        steps.append((P_pred * scale, pool[draw(st.integers(0, len(pool) - 1))]))
    return gains, c, steps


@pytest.mark.parametrize("name", sorted(METRICS))
@settings(max_examples=15)
@given(pb=decisions())
def test_a_plan_reused_over_decisions_equals_exhaustive(name, pb):
    """The small-N path with one plan over several decisions (its per-``P_d`` caches hit and
    miss) picks what the plain loop picks, bit for bit, at every decision."""
    gains, c, steps = pb
    plan = prepare(gains, c)
    for P_pred, P_d in steps:
        try:
            ref = allocate_exhaustive(P_pred, gains, P_d, name, c)
        except InfeasibleAllocation:
            with pytest.raises(InfeasibleAllocation):
                allocate(P_pred, plan, P_d, name)
            continue
        except ValueError:  # e.g. a P_d the metric cannot take (not SPD for logdet, kl)
            with pytest.raises(ValueError):
                allocate(P_pred, plan, P_d, name)
            continue
        got = allocate(P_pred, plan, P_d, name)
        assert (got.subset, got.value, got.n_feasible) == (ref.subset, ref.value, ref.n_feasible)
        np.testing.assert_array_equal(got.P, ref.P)


# ---- the svd block bound (n = 4): ties and near ties of P_d and of the subsets' P_i ----------

_TIE_STEPS = [0.0, 1e-13, 1e-11, 5e-10, 1e-9, 2e-9, 1e-8, 1e-6, 1e-3]


@st.composite
def tied_diagonal(draw):
    """A diagonal ``P_d`` with repeated or nearly repeated entries (the spec's two desired
    covariances are of this kind), in any order of the axes."""
    a = draw(st.floats(0.05, 50.0))
    b = draw(st.floats(0.05, 50.0))
    eps = [draw(st.sampled_from(_TIE_STEPS)) for _ in range(2)]
    vals = [a, a * (1.0 + eps[0]), b, b * (1.0 + eps[1])]
    return np.diag([vals[i] for i in draw(st.permutations(range(4)))])


@st.composite
def rotated_tied(draw):
    """``Q diag(s) Qᵀ`` with repeated or nearly repeated ``s`` and a random rotation ``Q``."""
    Q, _ = np.linalg.qr(draw(arrays(np.float64, (4, 4), elements=_elems)) + 11.0 * np.eye(4))
    a = draw(st.floats(0.05, 50.0))
    s = [a, a * (1.0 + draw(st.sampled_from(_TIE_STEPS))), draw(st.floats(0.05, 50.0)), a]
    return (Q * s) @ Q.T


@st.composite
def svd_problem(draw):
    """``n = 4`` problems for the svd bound: random SPD or paper-like ``P_pred``, position or
    random gains, ``P_d`` random SPD, diagonal with (near) ties or a rotated one with (near) ties;
    also isotropic ``P_pred`` and gains, so that the subsets' ``P_i`` have (nearly) repeated
    eigenvalues themselves."""
    kind = draw(st.sampled_from(["paper", "general", "isotropic"]))
    if kind == "paper":
        P_pred, gains, _ = draw(paper_like())
    elif kind == "general":
        N = draw(st.integers(1, 6))
        gains = np.stack(
            [draw(spd(4, floor=0.0)) / draw(st.sampled_from([1.0, 1e2, 1e4])) for _ in range(N)]
        )
        P_pred = draw(spd(4, floor=0.1))
    else:  # P_pred = diag(p, q, p, q) (+ a tiny perturbation), equal position sensors
        p, q = draw(st.floats(1.0, 100.0)), draw(st.floats(0.1, 10.0))
        P_pred = np.diag([p, q, p, q]) + draw(st.sampled_from([0.0, 1e-12, 1e-8])) * np.ones((4, 4))
        N = draw(st.integers(1, 5))
        gains = np.stack(
            [
                np.diag([g, 0.0, g, 0.0])
                for g in draw(st.lists(st.floats(0.01, 1.0), min_size=N, max_size=N))
            ]
        )
    P_d = draw(st.one_of(spd(4, floor=0.05), tied_diagonal(), rotated_tied()))
    return 0.5 * (P_pred + P_pred.T), gains, 0.5 * (P_d + P_d.T)


@settings(max_examples=150)
@given(pb=svd_problem())
def test_svd_block_bound_never_exceeds_the_exact_value(pb):
    """``_svd_block`` (the n = 4 cheap bound: eigenvalue enclosures of a 2 + 2 block split and
    eigenvector-component bounds) <= the exact svd value of every subset, on both stage-1
    representations, with ties and near ties of ``P_d``'s and of the ``P_i``'s eigenvalues."""
    P_pred, gains, P_d = pb
    N = gains.shape[0]
    plan = prepare(gains)
    tab = plan.tables
    Y0 = fast.spd_inverse(P_pred)
    exact = METRICS["svd"](fast.spd_inverse(Y0 + fast.gain_sums(plan.gains, tab.masks)), P_d)
    st_ = fast._Setup(P_pred, P_d, Y0, tab)
    st_general = fast._Setup(
        P_pred, P_d, Y0, fast.SearchTables(plan.gains, frozenset(), frozenset(), N)
    )
    with np.errstate(all="ignore"):
        lbs = [
            fast._svd_block(st_.chunk_covariances(), P_d, st_.ctx),
            fast._svd_block(st_general.subsets(tab.codes), P_d, st_general.ctx),
        ]
    for lb in lbs:
        assert lb.shape == exact.shape
        assert not np.any(lb > exact), float(np.max(lb - exact))


@settings(max_examples=60)
@given(pb=svd_problem(), c=st.data())
def test_svd_fast_equals_exhaustive_with_ties(pb, c):
    """The fast path with the svd block bound picks the plain loop's subset, value and ``P``
    bits on the tie-heavy problems above, with and without constraints."""
    P_pred, gains, P_d = pb
    cons = c.draw(st.one_of(st.just(Constraints()), constraints(gains.shape[0])))
    _same(P_pred, gains, P_d, "svd", cons)
