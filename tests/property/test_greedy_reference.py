"""``greedy`` and ``bounded`` never lose to the plain heuristic: on random heterogeneous problems
(position, velocity and full-state sensors of very different quality, random predictions and
desired covariances, random constraints), every metric, covnet's greedy
(:func:`~covnet.core.allocation.search.allocate_greedy`) and the bounded branch and bound
(:func:`~covnet.core.allocation.search.allocate_bnb` with a gap and a node limit) return a value
no worse than :func:`plain_greedy` below: forward selection, then first-improvement 1-swaps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.core.allocation.exact import Constraints, subset_covariance
from covnet.core.allocation.search import allocate_bnb, allocate_greedy
from covnet.core.metrics import METRICS
from covnet.core.motion import cv_transition, dwna_process_noise
from covnet.core.sensing import correlated_noise, information_gain, position_matrix

#: strict improvement required of a move (relative), as covnet's local search
IMPROVE = 1e-12


def _values(P_pred, G, P_d, name, masks):
    """Exact values of the subsets ``masks`` ``(c, N)`` with the reference's arithmetic (``J``
    summed in ascending sensor order from ``+0.0``; ``P = (P_pred⁻¹ + J)⁻¹``); the empty subset
    (infeasible unless something is required) is ``inf``."""
    J = np.zeros((masks.shape[0],) + G.shape[1:])
    for j in range(G.shape[0]):
        J = J + np.where(masks[:, j, None, None], G[j], 0.0)
    J = J + 0.0
    v = np.asarray(METRICS[name](subset_covariance(P_pred, J), P_d), dtype=np.float64)
    return np.where(masks.any(axis=1), v, math.inf)


def plain_greedy(P_pred, G, P_d, name, c):
    """The plain heuristic: from the required set, add the sensor that lowers ``f`` most while
    one lowers it and the budget allows; then first-improvement local search (in this order:
    add one, remove one, swap one in for one out; sensors ascending) until no move improves by a
    relative ``IMPROVE``.  Returns ``(subset, value)``."""
    N = G.shape[0]
    K = N if c.max_active is None else c.max_active
    allowed = np.array([j not in c.excluded for j in range(N)])
    req = np.array([j in c.required for j in range(N)])
    cur = req.copy()
    val = float(_values(P_pred, G, P_d, name, cur[None])[0])

    def better(v, ref):
        return v < ref - IMPROVE * abs(ref) if math.isfinite(ref) else math.isfinite(v)

    while cur.sum() < K:
        outs = np.flatnonzero(allowed & ~cur)
        if outs.size == 0:
            break
        masks = np.repeat(cur[None], outs.size, axis=0)
        masks[np.arange(outs.size), outs] = True
        v = _values(P_pred, G, P_d, name, masks)
        i = int(np.argmin(v))
        if not better(float(v[i]), val):
            break
        cur, val = masks[i], float(v[i])
    while True:
        ins = np.flatnonzero(cur & ~req)
        outs = np.flatnonzero(allowed & ~cur)
        moves = []
        if cur.sum() < K:
            moves += [(-1, j) for j in outs]
        moves += [(i, -1) for i in ins]
        moves += [(i, j) for i in ins for j in outs]
        if not moves:
            break
        masks = np.repeat(cur[None], len(moves), axis=0)
        for row, (i, j) in enumerate(moves):
            if i >= 0:
                masks[row, i] = False
            if j >= 0:
                masks[row, j] = True
        v = _values(P_pred, G, P_d, name, masks)
        ok = np.flatnonzero([better(float(x), val) for x in v])
        if ok.size == 0:
            break
        cur, val = masks[ok[0]], float(v[ok[0]])
    return tuple(np.flatnonzero(cur).tolist()), val


def heterogeneous(N, seed):
    """``(P_pred, gains, P_d)``: ``N`` sensors of three kinds (position, 70 %; position and
    velocity, 20 %; velocity only, 10 %), their noise log-uniform over two decades and
    correlated; a prediction one CV step from a random covariance; a diagonal desired
    covariance."""
    rng = np.random.default_rng(seed)
    Hp = position_matrix()
    Hv = np.zeros((2, 4))
    Hv[0, 1] = Hv[1, 3] = 1.0
    gains = []
    for _ in range(N):
        kind = rng.choice(3, p=[0.7, 0.2, 0.1])
        sx, sy = np.exp(rng.uniform(np.log(2.0), np.log(200.0), 2))
        R = correlated_noise(sx, sy, rng.uniform(-0.9, 0.9))
        if kind == 0:
            g = information_gain(Hp, R)
        elif kind == 1:
            sv = np.exp(rng.uniform(np.log(0.2), np.log(20.0), 2))
            g = information_gain(Hp, R) + information_gain(Hv, np.diag(sv**2))
        else:
            g = information_gain(Hv, R / 100.0)
        gains.append(0.5 * (g + g.T))
    A = rng.normal(size=(4, 4))
    scale = np.exp(rng.uniform(np.log(1.0), np.log(1e4)))
    P = scale * (A @ A.T / 4.0 + np.diag([1.0, 0.01, 1.0, 0.01]))
    F = cv_transition(1.0)
    P_pred = F @ P @ F.T + dwna_process_noise(1.0, 0.5)
    P_pred = 0.5 * (P_pred + P_pred.T)
    dp = np.exp(rng.uniform(np.log(1.0), np.log(300.0)))
    dv = np.exp(rng.uniform(np.log(0.05), np.log(20.0)))
    return P_pred, np.array(gains), np.diag([dp, dv, dp, dv])


@st.composite
def problems(draw, max_n):
    N = draw(st.integers(2, max_n))
    seed = draw(st.integers(0, 2**32 - 1))
    P_pred, gains, P_d = heterogeneous(N, seed)
    idx = st.integers(0, N - 1)
    c = Constraints()
    if draw(st.booleans()):
        excluded = frozenset(draw(st.lists(idx, max_size=N // 3)))
        required = frozenset(draw(st.lists(idx, max_size=2))) - excluded
        if len(excluded | required) >= N:
            excluded = frozenset()
        lo = max(1, len(required))
        budget = draw(st.one_of(st.none(), st.integers(lo, max(lo, N // 2))))
        c = Constraints(excluded, required, budget)
    return P_pred, gains, P_d, c


def _check(name, pb):
    P_pred, gains, P_d, c = pb
    ref_subset, ref = plain_greedy(P_pred, gains, P_d, name, c)
    tol = IMPROVE * abs(ref)
    g = allocate_greedy(P_pred, gains, P_d, name, c)
    assert g.value <= ref + tol, ("greedy", g.subset, g.value, ref_subset, ref)
    for node_limit in (1, 2000):
        b = allocate_bnb(P_pred, gains, P_d, name, c, rel_gap=0.01, node_limit=node_limit)
        assert b.value <= ref + tol, ("bounded", node_limit, b.subset, b.value, ref_subset, ref)
        assert b.value <= g.value + IMPROVE * abs(g.value)


@pytest.mark.parametrize("name", sorted(METRICS))
@settings(max_examples=20)
@given(pb=problems(24))
def test_greedy_and_bounded_never_lose_to_plain_greedy(name, pb):
    _check(name, pb)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(METRICS))
@settings(max_examples=12)
@given(pb=problems(64))
def test_greedy_and_bounded_never_lose_to_plain_greedy_up_to_64(name, pb):
    """The same up to 64 sensors (slow: ~20 s, the plain reference's exact evaluations)."""
    _check(name, pb)
