"""The svd metric's faster stack path and its working floor (``allocation/svd_bound.py``).

- :func:`covnet.core.metrics.svd` on a stack against one ``P_d`` (``_svd_stack``: ``P_d``'s
  decomposition kept, no sign step) gives the bits of the general path written out here from
  :func:`~covnet.core.metrics.ordered_eigh` (tied, nearly tied, diagonal and non-finite rows);
- the working floor is below the computed svd value on every row (nearly tied eigenvalues,
  scales over ten decades) and not trivially low;
- greedy's local search and greedy itself choose the same subsets, with the same values, with
  and without the floor (it only skips moves that cannot improve).
"""

from __future__ import annotations

import numpy as np
import pytest

from covnet.core import metrics as M
from covnet.core.allocation import greedy as G
from covnet.core.allocation.search import allocate_bnb, allocate_greedy
from covnet.core.allocation.search_problem import NO_CONSTRAINTS, _Problem
from covnet.core.allocation.svd_bound import svd_floor
from covnet.core.motion import cv_transition, dwna_process_noise


def _general_svd(A, B):
    """svd's general path: ``ordered_eigh`` of both, signs included, the same sums."""
    n = A.shape[-1]
    s_A, U_A = M.ordered_eigh(A)
    s_B, U_B = M.ordered_eigh(B)
    cos = M._sum_last(np.swapaxes(U_A * U_B, -1, -2))
    orientation = np.maximum((n - M._sum_last(np.abs(cos))) / n, 0.0)
    return orientation + np.sqrt(M._sum_last((s_A - s_B) ** 2))


def _stack(rng, m, n, kind):
    X = rng.standard_normal((m, n, n))
    A = X @ np.swapaxes(X, -1, -2)
    if kind == "tied":  # exact and near ties (relative gaps down to 1e-12)
        Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
        d = rng.integers(1, 3, size=n).astype(float)
        d = d * (1.0 + rng.choice([0.0, 1e-12, 1e-10, 1e-7], size=n))
        A[: m // 2] = Q @ np.diag(d) @ Q.T
    if kind == "diagonal":
        A[0] = np.diag(rng.integers(0, 3, size=n).astype(float))
    if kind == "scaled":
        A *= 10.0 ** rng.uniform(-5, 5, size=(m, 1, 1))
    return A


@pytest.mark.parametrize("kind", ["plain", "tied", "diagonal", "scaled"])
def test_svd_stack_bits_equal_the_general_path(kind):
    rng = np.random.default_rng(7)
    for t in range(300):
        n = int(rng.integers(1, 6))
        A = _stack(rng, int(rng.integers(1, 40)), n, kind)
        Y = rng.standard_normal((n, n))
        B = Y @ Y.T if t % 2 else np.diag(rng.integers(1, 3, size=n).astype(float))
        got, want = M.svd(A, B), _general_svd(A, B)
        assert got.shape == want.shape
        assert np.array_equal(got.view(np.int64), want.view(np.int64)), (t, got, want)


def test_svd_stack_non_finite_rows_as_the_general_path():
    A = np.stack([np.eye(4), np.eye(4), 2.0 * np.eye(4)])
    A[1, 0, 0] = np.nan
    B = np.diag([7.0, 0.8, 7.0, 0.8])
    got, want = M.svd(A, B), _general_svd(A, B)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.array_equal(got[~np.isnan(got)], want[~np.isnan(want)])


@pytest.mark.parametrize("kind", ["plain", "tied", "scaled"])
def test_floor_is_below_the_computed_svd_and_close_to_its_size_term(kind):
    rng = np.random.default_rng(11)
    for t in range(200):
        A = _stack(rng, 50, 4, kind)
        B = np.diag([7.0, 0.8, 7.0, 0.8]) if t % 2 else _stack(rng, 1, 4, kind)[0]
        v, lb = M.svd(A, B), svd_floor(A, B)
        assert (lb <= v).all(), (t, (lb - v).max())
        s_A, s_B = M.ordered_eigh(A)[0], M.ordered_eigh(B)[0]
        size = np.sqrt(((s_A - s_B) ** 2).sum(axis=1))
        assert (lb >= size - 1e-8 * (np.abs(s_A).max(axis=1) + np.abs(s_B).max() + size)).all()


def test_floor_says_nothing_on_non_finite_rows():
    A = np.stack([np.eye(4), np.eye(4)])
    A[1, 2, 2] = np.inf
    lb = svd_floor(A, np.eye(4))
    assert lb[0] == 0.0 - 1e-10 * 4 * 2.0 and lb[1] == -np.inf


def _problem(N, seed):
    """Position sensors of the tracking model (noise over two decades, some duplicated) and the
    bench's desired covariance with its tied pairs, or a random one."""
    rng = np.random.default_rng(seed)
    F = cv_transition(1.0)
    A = rng.standard_normal((4, 4))
    P = A @ A.T / 4.0 + np.diag([1.0, 0.01, 1.0, 0.01])
    P_pred = F @ P @ F.T + dwna_process_noise(1.0, 0.5)
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    gains = []
    for _ in range(N):
        sig = 10.0 ** rng.uniform(-1, 1, size=2)
        c = rng.uniform(-0.5, 0.5) * sig[0] * sig[1]
        R = np.array([[sig[0] ** 2, c], [c, sig[1] ** 2]])
        gains.append(H.T @ np.linalg.solve(R, H))
    gains = np.array(gains)
    gains[N // 3] = gains[N // 2]
    if seed % 2:
        P_d = np.diag([7.0, 0.8, 7.0, 0.8]) * 10.0 ** rng.uniform(-2, 0)
    else:
        B = rng.standard_normal((4, 4))
        P_d = B @ B.T / 4.0 + 0.1 * np.eye(4)
    return P_pred, gains, P_d


def _no_floor(monkeypatch):
    monkeypatch.setattr(G, "_working_floor", lambda prob: None)


@pytest.mark.parametrize("seed", range(8))
def test_local_search_is_the_same_with_and_without_the_floor(seed, monkeypatch):
    P_pred, gains, P_d = _problem(24 + 8 * seed, seed)
    runs = []
    for use in (True, False):
        if not use:
            _no_floor(monkeypatch)
        prob = _Problem(P_pred, gains, P_d, "svd", NO_CONSTRAINTS, 1e-9)
        assert (G._working_floor(prob) is not None) is use
        out = []
        for start in (G._backward(prob)[0], np.arange(prob.m) % 3 == 0):
            Z = prob.base + prob.S[start].sum(axis=0)
            val = float(prob.approx_values(Z[None])[0])
            out.append(G._local_search(prob, start, val))
        runs.append((out, prob.moves))
    assert all(np.array_equal(a, b) for a, b in zip(runs[0][0], runs[1][0], strict=True))
    assert runs[0][1] == runs[1][1]


@pytest.mark.parametrize("seed", range(4))
def test_greedy_and_bounded_are_the_same_with_and_without_the_floor(seed, monkeypatch):
    P_pred, gains, P_d = _problem(40, 100 + seed)
    with_floor = (
        allocate_greedy(P_pred, gains, P_d, "svd"),
        allocate_bnb(P_pred, gains, P_d, "svd", rel_gap=0.01, node_limit=2000),
    )
    _no_floor(monkeypatch)
    without = (
        allocate_greedy(P_pred, gains, P_d, "svd"),
        allocate_bnb(P_pred, gains, P_d, "svd", rel_gap=0.01, node_limit=2000),
    )
    for a, b in zip(with_floor, without, strict=True):
        assert a.subset == b.subset and a.value == b.value and a.n_nodes == b.n_nodes
        assert np.array_equal(a.P, b.P) and a.lower_bound == b.lower_bound


@pytest.mark.parametrize("name", sorted(M.METRICS))
def test_backward_stops_early_on_the_same_best(name, monkeypatch):
    """Under a time limit (``reuse``) backward elimination stops once the interval bound shows
    no later set can be the path's best: the same best subset and value as the whole path, and
    it does stop early (fewer moves) on these problems for the metrics named below."""
    fewer = 0
    for seed in range(6):
        P_pred, gains, P_d = _problem(30 + 6 * seed, 200 + seed)
        runs = []
        for stop in (True, False):
            if not stop:
                monkeypatch.setattr(G._BackwardCheck, "done", lambda self, Z, best: False)
            prob = _Problem(P_pred, gains, P_d, name, NO_CONSTRAINTS, 1e-9)
            inc, val = G._backward(prob, reuse=True)
            runs.append((inc, val, prob.moves))
            monkeypatch.undo()
        assert np.array_equal(runs[0][0], runs[1][0]) and runs[0][1] == runs[1][1]
        assert runs[0][2] <= runs[1][2]
        fewer += runs[0][2] < runs[1][2]
    if name in ("spectral", "frobenius", "kl", "logdet"):  # (svd: on the bench problems)
        assert fewer, "the bound never stopped the path"


@pytest.mark.parametrize("name", sorted(M.METRICS))
def test_backward_stops_only_when_no_subset_can_beat_the_best(name):
    """Whenever the stop fires, every subset of the current set (the sets the path could still
    visit, and more) has a working value at least the path's best less the rounding allowance:
    checked by enumerating those subsets (N = 14).  A stop that fires on a weaker test (the
    bound against half the best) stops the path before a better set on these problems (four
    metrics fail then)."""
    fired = 0
    for seed in range(12):
        P_pred, gains, P_d = _problem(14, 300 + seed)
        prob = _Problem(P_pred, gains, P_d, name, NO_CONSTRAINTS, 1e-9)
        check = G._BackwardCheck(prob)
        seen: list[tuple[np.ndarray, float]] = []
        real_done = G._BackwardCheck.done

        def done(self, Z, best, _seen=seen, _real=real_done):
            out = _real(self, Z, best)
            if out:
                _seen.append((Z.copy(), best))
            return out

        check.done = done.__get__(check)  # type: ignore[method-assign]
        assert check.s_req is None
        orig = G._BackwardCheck
        try:
            G._BackwardCheck = lambda p, _c=check: _c  # type: ignore[misc,assignment]
            G._backward(prob, reuse=True)
        finally:
            G._BackwardCheck = orig  # type: ignore[misc]
        f_req = float(prob.approx_values(prob.base[None])[0])
        for Z, best in seen:
            fired += 1
            # the current set: the sensors whose information sums (with base) to Z
            S = prob.S
            m = S.shape[0]
            masks = np.array(
                [[(j >> i) & 1 for i in range(m)] for j in range(1 << m)], dtype=bool
            )
            sums = prob.base + masks.astype(float) @ S
            inside = np.all(np.isclose(sums, Z[None], rtol=1e-12, atol=1e-12), axis=1)
            assert inside.sum() >= 1
            cur = masks[np.flatnonzero(inside)[0]]
            sub = masks[~np.any(masks & ~cur, axis=1)]  # subsets of the current set
            vals = prob.approx_values(prob.base + sub.astype(float) @ S)
            scale = max(abs(f_req) if np.isfinite(f_req) else 0.0, abs(best))
            assert np.nanmin(vals) >= best - 1e-9 * scale, (seed, float(np.nanmin(vals)), best)
    if name in ("abs_trace", "kl", "logdet", "spectral", "trace_diff"):
        assert fired, "the stop never fired: the test checks nothing"
