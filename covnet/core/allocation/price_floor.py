"""A price-aware floor: a certified lower bound of one target's subproblem *with prices*,

    m(π) = min { w g(S) + π(S) : S ⊆ F },   π(S) = Σ_{j∈S} π_j,  π >= 0,

(``g(S) = f(P(S), P_d)`` the target's metric of the sensors ``S`` of its allowed set ``F``,
``w > 0`` its weight), the subproblem of the many-target search's Lagrangian relaxation
(:mod:`covnet.core.allocation.assignment_search`).  That module's single-target floors bound
``min_{S ≠ ∅} w g(S)`` and add the ``k`` cheapest prices: blind to *which* sensors carry the
prices, so where two light targets compete for the same few sensors the bound does not see it
(round mt8's decomposition).  This search sees them.

**Branch and bound** (:func:`price_floor`), on the single-target search's reduced form and
interval bounds (:class:`covnet.core.allocation.search_problem._Problem`, the target's allowed
sensors, branching order ``free``): a node fixes the first ``d`` sensors of the order (the
included set ``I``); the undecided ``U`` are the rest.  **Node bound**: every completion
``S = I ∪ T`` (``T ⊆ U``) has ``Z(I) ⪯ Z(S) ⪯ Z(I ∪ U)`` (the gains are PSD), so ``g(S) >=
b(I, U)``, the interval bound of ``[P(I ∪ U), P(I)]`` (raised by the metric's relaxation or
dual bound where :meth:`_Problem.refine` has one), and ``π(S) = π(I) + π(T) >= π(I)``
(``π >= 0``)::

    w g(S) + π(S) >= w b(I, U) + π(I).

A node whose bound exceeds the *threshold* ``τ = U* - rel_gap |U*|`` (``U*`` the best value
seen, the metric's working value of an evaluated set plus its prices) is *closed*, as is a
node with nothing undecided (``d = m``: its bound is the degenerate interval ``[P(I), P(I)]``,
a bound of ``g(I)`` itself); the include child keeps the parent's ``P(I ∪ U)``, the exclude
child its ``P(I)``: one new summary each.  **The certificate** is the least bound over the
frontier: the open nodes and every closed one.  **Proof**: the frontier partitions the subsets
of ``F`` (a node's two children partition its completions, the root's are every subset), and
every subset's ``w g(S) + π(S)`` is at least the bound of the frontier node it lies in.  So
``L <= m(π)`` whatever stops the search (a limit, a clock), and independently of ``U*`` (which
only decides what is closed); a search that ends with no open node has ``L >= min(U*(1 -
rel_gap), closed bounds)``.  The sensors with an all-zero gain are not searched: with ``π >=
0`` they never lower ``w g(S) + π(S)``.

**Use in the dual** (:mod:`covnet.core.allocation.assignment_search`, ``_Dual``): a floor
computed at prices ``π⁰`` bounds the column at *any* prices ``π``: for ``|S| = k``::

    w g(S) + π(S) = [w g(S) + π⁰(S)] + (π - π⁰)(S) >= L(π⁰) + δ_k,

``δ_k`` the sum of the ``k`` smallest ``π_j - π⁰_j`` over ``F`` (the ``k`` members are ``k``
distinct sensors of ``F``; the differences may be negative).  At ``π = π⁰`` that is ``L(π⁰)``
for every ``k``; the Lagrangian dual function with these bounds is still at most the
assignment's optimum (that module's proof, with ``b_c(k, π)`` the largest of its bounds).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation.search_problem import _Problem
from covnet.core.gaussian import Mat

__all__ = ["PriceFloor", "price_floor"]

#: nodes expanded per batch (the lowest bounds first)
BATCH = 256
#: with ``refine``: the relaxation's or dual bound's iterations per call (its bound so far)
REFINE_ITERS = 6


@dataclass(frozen=True, slots=True)
class PriceFloor:
    """``lower`` ``<= m(π)`` (certified), ``upper`` the best value seen (working values),
    ``members`` its set (global sensor indices, ascending), ``n_nodes`` nodes bounded,
    ``done`` no open node left (the search ended: ``lower >= min(upper (1 - rel_gap), ...)``)."""

    lower: float
    upper: float
    members: tuple[int, ...]
    n_nodes: int
    done: bool


def price_floor(
    prob: _Problem,
    prices: Mat,
    w: float = 1.0,
    *,
    rel_gap: float = 0.0,
    node_limit: int | None = None,
    deadline: Callable[[], bool] | None = None,
    refine: bool = False,
    floor: float = -math.inf,
) -> PriceFloor:
    """The branch and bound of the module docstring: ``prices`` per sensor of the problem
    (``(N,)``, global indices, ``>= 0``), ``w > 0``; best bound first, ``BATCH`` nodes at a
    time, until no node is open, ``node_limit`` nodes are bounded or ``deadline()``.
    ``refine``: the node bounds raised by :meth:`_Problem.refine` (the relaxation or the dual
    bound; both certified).  ``floor``: a certified lower bound of ``g(S)`` for *every*
    ``S ⊆ F``, the empty set included (:meth:`_Problem.root_bound`): every node's bound is
    at least ``w floor + π(I)`` (module docstring, *Node bound*)."""
    pi = np.asarray(prices, dtype=np.float64)
    if pi.shape != (prob.N,) or not (pi >= 0).all():
        raise ValueError(f"prices must be ({prob.N},) and >= 0")
    if not w > 0:
        raise ValueError(f"w must be > 0, got {w}")
    if prob.bound is None or prob.req:
        raise ValueError("price_floor needs an interval bound and no required sensor")
    m = prob.m
    free = np.asarray(prob.free, dtype=np.intp)
    pf = pi[free] if m else np.zeros(0)
    S, suf = prob.S, prob.suffix
    wf = w * floor if math.isfinite(floor) else -math.inf
    Z0 = prob.base[None]
    sB0 = prob.summary(Z0)
    v0 = float(prob.approx_values(Z0)[0])
    best = w * v0 if math.isfinite(v0) else math.inf
    best_set = np.zeros(m, dtype=bool)
    if m == 0:
        lo = max(w * float(prob.combine(sB0, sB0)[0]), wf)
        return PriceFloor(min(lo, best), best, (), 1, True)
    sA0 = prob.summary(Z0 + suf[0])
    lb0 = np.fmax(w * _bound(prob, Z0, Z0 + suf[0], sA0, sB0, refine, np.full(1, math.inf)), wf)
    # the open nodes: Z (I's information), d (decided), pI (π(I)), sA, sB, lb, inc (I)
    Z, d, pI, sA, sB, lb = Z0.copy(), np.zeros(1, np.intp), np.zeros(1), sA0, sB0, lb0
    inc = np.zeros((1, m), dtype=bool)
    closed = math.inf
    n_nodes = 1
    while lb.size:
        tau = best - rel_gap * abs(best)
        if node_limit is not None and n_nodes >= node_limit:
            break
        if deadline is not None and deadline():
            break
        shut = lb > tau
        if shut.any():
            closed = min(closed, float(lb[shut].min()))
            op = ~shut
            Z, d, pI, sA, sB, lb, inc = Z[op], d[op], pI[op], sA[op], sB[op], lb[op], inc[op]
            if lb.size == 0:
                break
        k = min(BATCH, lb.size)
        if k < lb.size:
            pick = np.argpartition(lb, k - 1)[:k]
            rest = np.ones(lb.size, dtype=bool)
            rest[pick] = False
        else:
            pick, rest = np.arange(lb.size), np.zeros(lb.size, dtype=bool)
        Zp, dp, pp, sAp, sBp, ip = Z[pick], d[pick], pI[pick], sA[pick], sB[pick], inc[pick]
        Z, d, pI, sA, sB, lb, inc = (
            Z[rest],
            d[rest],
            pI[rest],
            sA[rest],
            sB[rest],
            lb[rest],
            inc[rest],
        )
        # include children: I + free[d] (a set of its own: evaluated), P(I ∪ U) unchanged
        Zi = Zp + S[dp]
        pi_i = pp + pf[dp]
        ii = ip.copy()
        ii[np.arange(k), dp] = True
        sBi = prob.summary(Zi)
        vi = w * prob.approx_values(Zi) + pi_i
        a = int(np.argmin(vi))
        if float(vi[a]) < best:
            best, best_set = float(vi[a]), ii[a].copy()
        tau = best - rel_gap * abs(best)
        d1 = dp + 1
        leaf = d1 >= m
        Zhi = Zp + suf[np.minimum(d1, m)]  # the exclude child's P(I ∪ U - free[d])
        bi = _bound(prob, Zi, Zi + suf[np.minimum(d1, m)], sAp, sBi, refine, (tau - pi_i) / w)
        lbi = np.fmax(np.where(leaf, prob.combine(sBi, sBi), bi) * w, wf) + pi_i
        # exclude children: I unchanged, a new P(I ∪ U - free[d])
        sAe = prob.summary(Zhi)
        be = _bound(prob, Zp, Zhi, sAe, sBp, refine, (tau - pp) / w)
        lbe = np.fmax(np.where(leaf, prob.combine(sBp, sBp), be) * w, wf) + pp
        n_nodes += 2 * k
        lc = np.concatenate((lbi, lbe))
        lc = np.where(np.isnan(lc), -math.inf, lc)
        lf = np.concatenate((leaf, leaf))
        if lf.any():
            closed = min(closed, float(lc[lf].min()))
        oi, oe = ~leaf, ~leaf
        Z = np.concatenate((Z, Zi[oi], Zp[oe]))
        d = np.concatenate((d, d1[oi], d1[oe]))
        pI = np.concatenate((pI, pi_i[oi], pp[oe]))
        sA = np.concatenate((sA, sAp[oi], sAe[oe]))
        sB = np.concatenate((sB, sBi[oi], sBp[oe]))
        inc = np.concatenate((inc, ii[oi], ip[oe]))
        lb = np.concatenate((lb, lc[:k][oi], lc[k:][oe]))
    lower = min(closed, float(lb.min()) if lb.size else math.inf)
    members = tuple(sorted(int(j) for j in free[best_set]))
    return PriceFloor(lower, best, members, n_nodes, lb.size == 0)


def _bound(
    prob: _Problem, Z_lo: Mat, Z_hi: Mat, sA: Mat, sB: Mat, refine: bool, tau: Mat
) -> NDArray[np.float64]:
    """The interval bound of ``[P(Z_hi), P(Z_lo)]`` (summaries ``sA``, ``sB``), with
    ``refine`` raised by :meth:`_Problem.refine` on the rows at most their threshold ``tau``
    (the others are closed anyway; every row's result is a bound)."""
    lb = np.asarray(prob.combine(sA, sB), dtype=np.float64)
    if refine and lb.size:
        rows = np.flatnonzero(lb <= tau)
        if rows.size:
            lb = lb.copy()
            calls = itertools.count()
            stop, prob.stop = prob.stop, lambda: next(calls) >= REFINE_ITERS
            try:
                lb[rows] = prob.refine(Z_lo[rows], Z_hi[rows], lb[rows], sB[rows], math.inf)
            finally:
                prob.stop = stop
    return lb
