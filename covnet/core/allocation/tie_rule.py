"""Exact branch and bound on problems with massive ties: pruning by the tie rule.

The reference (:func:`~covnet.core.allocation.allocate_exhaustive`) returns, among the subsets
whose computed value ``V`` is within ``thr(v*) = v* + tie_rtol · max(|v*|, tiny)`` of the least
computed value ``v*`` (the *tie set* ``T``), the first in the order ``≺``: fewest sensors, then
the lexicographically smallest ascending index tuple.  The plain exactness argument of
:mod:`covnet.core.allocation.search` keeps every member of ``T`` and evaluates it, which is
impossible when ``T`` is huge (every subset with a small position error scoring the same velocity
term: ``T`` holds almost every subset).  Two rules prune members of ``T`` that cannot be chosen,
and a check after the search proves the choice is the reference's (else the search is run again
without them).

**Size rule.**  ``L0`` (the root's bound, :meth:`_Problem.root_bound`) is below every subset's
computed value, so ``v* >= L0`` and an evaluated subset ``X`` with ``V(X) <= thr(L0)`` is
*certified*: ``X ∈ T`` (``thr`` is increasing).  With ``s*`` the size of the smallest certified
subset, a node whose included set (required ones counted) has ``k >= s*`` sensors keeps only
its own subset (recorded as a candidate when its last sensor was included; every other
completion has more than ``s*`` sensors) and is dropped; the least bound of what is dropped,
``L_size``, is kept.

**Identical sensors.**  Free sensors with bit-identical gains are adjacent in the branching order
(same key, ascending index).  For such a pair ``(p, p+1)`` the include child of ``p+1`` is
dropped where ``p`` is excluded: every subset ``E`` lost that way has a *canonical* twin ``c(E)``
(each copy swapped for the lower-indexed excluded one) of the same size, lexicographically
smaller, with the same information ``Z`` in exact arithmetic, hence every node bound and
candidate bound valid for ``c(E)`` is valid for ``E`` (the bounds cover the reference's
rounding of any subset whose exact ``P`` lies in the node's interval).

**Check** (:meth:`_TieRule.verified`).  Let ``D`` be the choice among the evaluated subsets
(``v_c`` their least value, ``thr_c = thr(v_c) >= thr(v*)``, the tie set ``T_c``).

1. ``D ∈ T``: every subset not evaluated is pruned by its bound (``> τ >= v_c``), dropped by
   the size rule (``>= L_size``) or, with identical sensors, the twin of a canonical subset
   whose recorded bound is ``>= L_cand`` (the least bound of every candidate recorded) or that
   was itself pruned; so ``v* >= L1 = max(L0, min(v_c, L_size, L_cand))`` and
   ``V(D) <= thr(L1)`` proves ``D ∈ T``.
2. No ``X ≺ D`` is in ``T``.  Such an ``X`` has ``|X| <= |D| <= s*`` (``D ⪯`` every certified
   subset, as those are in ``T_c``), so the size rule did not drop it, and its bounds are ``<=
   V(X) <= thr(v*) <= τ``: if ``X`` is canonical it was recorded and evaluated, so ``X ∈ T_c``
   and ``D`` would not be chosen.  If not (identical sensors), ``c(X) ≺ X ≺ D`` was, with a
   bound ``est <= V(X) <= thr_c``; ``c(X) ∉ T_c`` (as above), so ``V(c(X)) > thr_c``.  Hence it
   suffices that every evaluated ``Y ≺ D`` with ``V(Y) > thr_c`` has its degenerate interval
   bound (``[P(Y), P(Y)]``) above ``thr_c``.

Both hold, so ``D`` is the reference's choice; its value and ``P`` come from the reference's
arithmetic.  When the check fails the search runs again without these rules.

**Leaf bounds** (kl; :class:`~covnet.core.allocation.interval_bounds.LeafBound`).  Step 1
needs the candidates' bounds (``L_cand``) within ``tie_rtol`` of their values, and kl's
degenerate interval bound is hundreds below on the tie problems (its rounding allowance is
relative to ``tr(P_d) / λmin(P)``).  Its leaf bound
(:func:`~covnet.core.allocation.interval_bounds.kl_leaf_bound`) bounds the reference's own
arithmetic term by term, within about ``1e-10`` of the value there, and is valid for every
subset with the same exact information (so for the twins ``E`` of step 1, whose sums run in
another order): the search takes the larger of the two for every candidate while the rules
are on, and step 2 does too.  The rules are switched on either by a certified subset (the
size rule and the identical-sensor rule) or, with identical sensors and a leaf bound, when the
best evaluated subset's leaf bound is within ``tie_rtol`` of its value (``V <= thr(est)``:
then the identical-sensor rule alone, ``s*`` left above the budget, nothing dropped by size;
the check is unchanged, so a wrong guess costs only the second search).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation._fast import tie_threshold
from covnet.core.gaussian import Mat

if TYPE_CHECKING:
    from covnet.core.allocation.search_problem import _Problem


def identical_to_previous(prob: _Problem) -> NDArray[np.bool_]:
    """``(m,)``: branching position ``p`` holds a sensor whose gain is bit-identical to that of
    position ``p - 1`` (adjacent: the branching key is the same, ties by ascending index)."""
    out = np.zeros(prob.m, dtype=bool)
    for p in range(1, prob.m):
        a, b = prob.G[prob.free[p - 1]], prob.G[prob.free[p]]
        out[p] = bool(np.array_equal(a, b)) and a.tobytes() == b.tobytes()
    return out


def precedes(masks: NDArray[np.bool_], d: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Rows of ``masks`` ``(c, N)`` that come before ``d`` in the tie rule's order: fewer
    sensors, or as many and containing the lowest index at which they differ."""
    size, ds = masks.sum(axis=1), int(d.sum())
    diff = masks ^ d[None]
    first = np.argmax(diff, axis=1)
    lex = diff.any(axis=1) & masks[np.arange(masks.shape[0]), first]
    out: NDArray[np.bool_] = (size < ds) | ((size == ds) & lex)
    return out


class _TieRule:
    """The state of the size rule and of the identical-sensor rule (module docstring)."""

    def __init__(self, prob: _Problem, symmetry: bool) -> None:
        self.prob = prob
        self.L0 = prob.root_bound()
        self.thr0 = tie_threshold(self.L0, prob.tie_rtol) if math.isfinite(self.L0) else -math.inf
        self.s_star = prob.K + len(prob.req) + 1  # no certified subset yet: nothing dropped
        self.L_size = math.inf
        self.L_cand = math.inf
        same = identical_to_previous(prob) if symmetry else np.zeros(prob.m, dtype=bool)
        self.same = same
        self.symmetry = bool(same.any())
        #: the identical-sensor rule alone is worth it: the leaf bound
        #: (:meth:`~covnet.core.allocation.search_problem._Problem.leaf_bound`) of the best
        #: evaluated subset is within ``tie_rtol`` of its value (the check's step 1 then
        #: passes when the choice's twins are bounded as tightly)
        self.leaf_sharp = False

    def observe(self, masks: NDArray[np.bool_], values: Mat) -> None:
        """Evaluated subsets: the certified ones (``V <= thr(L0)``) lower ``s*``; with
        identical sensors and a leaf bound, whether the best one's leaf bound is sharp."""
        ok = values <= self.thr0
        if ok.any():
            self.s_star = min(self.s_star, int(masks[ok].sum(axis=1).min()))
        if self.symmetry and not self.leaf_sharp and values.size:
            k = int(np.argmin(values))
            est = self.leaf(masks[k : k + 1])
            if est is not None:
                thr = tie_threshold(float(est[0]), self.prob.tie_rtol)
                self.leaf_sharp = bool(values[k] <= thr)

    def leaf(self, masks: NDArray[np.bool_]) -> Mat | None:
        """The leaf bounds of the subsets ``masks`` ``(c, N)`` (``None``: no leaf bound)."""
        prob = self.prob
        return prob.leaf_bound(prob.information(masks[:, prob.free]))

    @property
    def active(self) -> bool:
        """A certified subset has been seen, or (identical sensors) the leaf bound is sharp
        (the rules are used only then: the check's ``V(D) <= thr(L1)`` needs bounds within
        ``tie_rtol`` of the values, which the rounding allowances of the bounds often are not,
        and a failed check costs a second search).  Without a certified subset ``s*`` stays
        above the budget: only the identical-sensor rule prunes."""
        return self.s_star <= self.prob.K + len(self.prob.req) or self.leaf_sharp

    def candidates(self, est: Mat) -> None:
        if est.size:
            self.L_cand = min(self.L_cand, float(est.min()))

    def dropped(self, lb: Mat) -> None:
        if lb.size:
            self.L_size = min(self.L_size, float(lb.min()))

    def verified(self, masks: NDArray[np.bool_], values: Mat, k: int) -> bool:
        """The check of the module docstring for the choice ``masks[k]``."""
        prob = self.prob
        v_c = float(values.min())
        low = min(v_c, self.L_size, self.L_cand if self.symmetry else math.inf)
        L1 = max(self.L0, low)
        if low < v_c and not values[k] <= tie_threshold(L1, prob.tie_rtol):
            return False
        if not self.symmetry:
            return True
        thr_c = tie_threshold(v_c, prob.tie_rtol)
        rows = np.flatnonzero((values > thr_c) & precedes(masks, masks[k]))
        if rows.size == 0:
            return True
        Z = prob.information(masks[rows][:, prob.free])
        sB = prob.summary(Z)
        est = prob.with_leaf(Z, prob.combine(sB, sB))
        return bool((est > thr_c).all())
