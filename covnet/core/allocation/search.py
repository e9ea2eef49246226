"""Sensor allocation beyond exhaustive search: branch and bound (exact or bounded) and greedy.

The problem is :mod:`covnet.core.allocation`'s::

    D_opt = argmin_{D ∈ D_c} f(P(D), P_d),   P(D) = (P_pred⁻¹ + Σ_{j∈D} J_j)⁻¹,

with the same constraints (:class:`~covnet.core.allocation.Constraints`) and the same tie rule
(values within ``tie_rtol`` of the minimum: fewest sensors, then the lexicographically smallest
ascending index tuple).

**Branch and bound** (:func:`allocate_bnb`).  A node fixes, for the first ``d`` sensors of a
*branching order*, which are in (the included set ``I``) and which are out; the rest ``U`` are
undecided.  Every completion ``D`` obeys ``A = P(I ∪ U) ⪯ P(D) ⪯ P(I) = B`` (Loewner), so the
interval bounds of :mod:`covnet.core.allocation.interval_bounds` bound every completion's value
from below.
The include child keeps its parent's ``A`` and gets a new ``B = P(I + j)``, the exclude child
keeps ``B`` and gets a new ``A = P(I ∪ U - j)``: one new endpoint per child, its summary computed
for a whole batch of nodes at once.  Each include child *is* a feasible subset (``I + j``, the
rest left out): a *candidate*, whose value is bounded below by the degenerate interval
``[B, B]`` (no extra cost).

The covariances are computed in the reduced information form
(:mod:`covnet.core.allocation.search_problem`): a node carries the ``r x r`` information ``Z``
of ``I``, and a child costs one small inverse and one ``(r², n²)`` product.

**Relaxation** (frobenius, kl, logdet; ``r = 2``; :mod:`covnet.core.allocation.relaxation`): a
few projected-gradient steps on the node's 3-dimensional interval of ``Z`` give a tangent-plane
lower bound, applied to every node the interval bound keeps.  **Table of the last levels** (kl,
frobenius, logdet; :mod:`covnet.core.allocation.leaf_table`): the completions of a node at
depth ``d0 = m - LEAF_LEVELS`` that can still be ``<= τ`` are found in a ball by one k-d tree
query.  Both keep the exactness argument below.

**Exactness.**  The incumbent ``U`` is the smallest exactly evaluated value (greedy's subset
first); a node is pruned only when its bound exceeds ``τ = U + tie_rtol · max(|U|, tiny)``, which
is at least the reference's tie threshold ``f* + tie_rtol · max(|f*|, tiny)`` (``0 <= f* <= U``:
every registered metric is computed ``>= 0``).  Hence no subset of the reference's tie set is
ever pruned, every one is recorded as a candidate with a bound below its value, and all candidates
whose bound is at most the final ``τ`` are evaluated exactly with the reference's arithmetic
(``J`` summed in ascending sensor order from ``+0.0``, :func:`covnet.core.allocation._fast.\
gain_sums`; ``P = spd_inverse(spd_inverse(P_pred) + J)``; the metric itself, batch-invariant);
the tie rule then runs on bit-identical values: the same subset, value and ``P`` as
:func:`~covnet.core.allocation.allocate_exhaustive`.

**Tie rule** (exact mode; :mod:`covnet.core.allocation.tie_rule`): once an evaluated subset is
certified to be in the tie set (its value within the tie tolerance of the root's bound), nodes
with as many sensors are dropped (only fewer sensors can still be chosen), and of bit-identical
sensors only the canonical completions are explored (a copy only with its lower-indexed twin);
a check after the search proves the choice is the reference's, else the search runs again
without these rules.  kl has a sharper bound of single subsets (its leaf bound, the
reference's arithmetic bounded term by term): it switches the identical-sensor rule on without
a certified subset and bounds the candidates while the rules are on; then the last levels come
from the tree, not the table (the tree drops the twins at every level, the table would find
them all in its ball first).  The dual bound (spectral, one_norm, inf_norm, abs_trace) costs about a
hundred interval bounds, so exact mode applies it only to nodes with ``DUAL_MIN_REST`` or more
undecided sensors (where the metric has a vertex bound, only where that does not prune
already); the others get the vertex bound alone (one_norm, inf_norm: a few dual points a node,
each found in closed form by coordinate ascent, and the best mixture of two; abs_trace: one
diagonal point by coordinate ascent,
:meth:`~covnet.core.allocation.lower_bounds._DualBound.vertex_bound`).

**Bounded** (``rel_gap > 0``, a time or node limit): with ``rel_gap > 0`` nodes are explored best
bound first and depth first in turn, and pruned once their bound exceeds ``U - rel_gap·|U|``; a
limit stops the search (depth first without ``rel_gap``).  ``time_limit_s`` bounds the whole
decision, every step reading the clock (from the call's start; status 2 once it is reached):
greedy's start (its working values are ``+inf`` once GREEDY_SHARE of the time is spent,
``_Problem.stop``: every phase ends with the best it has, no move is evaluated; but the plain
heuristic, a floor for the incumbent, runs once until the whole limit:
:func:`~covnet.core.allocation.greedy._greedy_incs_timed`), the root (not
explored when greedy took the time: the certificate is then the root's bound, computed whole
after the deadline, one node; its dual bound stops once it certifies ``rel_gap``), the
relaxation's and the dual
bound's iterations (each stops after the iteration in progress, its bound so far valid), the tree
between batches, the leaf table (not built, and its nodes left open, once the time is up), and
the exact evaluation of the recorded candidates after the tree (lowest bound first, in batches,
the clock read in between; a tree stopped by a limit gets one batch of FINISH_FIRST), whose
candidates not evaluated stay in the certified bound.  The overshoot is one step of one batch:
one barrier iteration over a batch of nodes, one batch of at most FINISH_FIRST exact values,
greedy's phases winding down on ``+inf`` values, plus the ``O(N)`` set-up of the problem and the
result (measured: 0.05-0.11 s at N = 2000 on two loaded cores; a few ms at N = 100).  The
result is
the best subset found, with a certified lower bound ``L`` of the optimum (the least bound over
the open nodes, the pruned ones and the candidates not evaluated, or the root's bound if larger)
and ``gap = (value - L) / max(|value|, tiny)``.

**Greedy** (:func:`~covnet.core.allocation.greedy.allocate_greedy`, this module's name for it
too) gives the branch and bound its first incumbent.

For small problems (up to ~20 sensors) :func:`covnet.core.allocation.allocate`, which bounds
every subset in one batch, is faster; this module is for larger ones.

**Clocks.**  The core reads no clock, except here, and only when ``time_limit_s`` is given
(``time.perf_counter``, or the ``clock`` argument): a time-limited result depends on the machine,
``node_limit`` is the deterministic alternative.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation._fast import spd_inverse as spd_inverse
from covnet.core.allocation._fast import tie_select
from covnet.core.allocation.exact import Constraints, _spd_error, allocate
from covnet.core.allocation.greedy import _greedy_start
from covnet.core.allocation.greedy import allocate_greedy as allocate_greedy
from covnet.core.allocation.leaf_table import _Leaves
from covnet.core.allocation.relaxation import _Relaxation as _Relaxation
from covnet.core.allocation.search_problem import (
    NO_CONSTRAINTS,
    STATUS,
    TINY,
    SearchResult,
    _gap,
    _Problem,
    _subset,
    only_subset,
)
from covnet.core.allocation.tie_rule import _TieRule
from covnet.core.gaussian import Mat
from covnet.core.metrics import MetricFn

__all__ = [
    "STATUS",
    "SearchResult",
    "allocate_bnb",
    "allocate_greedy",
]

#: nodes per batch of the search (one numpy pass each)
CHUNK = 4096
#: above this many bytes of open nodes the best-first search goes depth first (bounded memory)
OPEN_BYTES = 1 << 28
#: after each batch, at most this many of the new candidates that could beat the incumbent are
#: evaluated exactly at once (the incumbent falls early); the others wait for the end
EVAL_PICKS = 4
#: the relaxation refines only nodes with at least this many undecided sensors (1: every node;
#: at 32-40 sensors 6 left two thirds of kl's nodes, in the last five levels, unrefined)
RELAX_MIN_REST = 1
#: exact mode: the dual bound (spectral, one_norm, inf_norm, abs_trace; 0.1-1 ms a node against
#: about 1 µs for the interval bound) only on nodes with at least this many undecided sensors,
#: where a prune saves a large subtree (N = 40, alternated with 18 and with every node: 26 was
#: as fast or faster on each abs_trace and spectral bench problem)
DUAL_MIN_REST = 26
#: kl, frobenius and logdet: the last this many levels of the tree come from a table of
#: ``2^LEAF_LEVELS`` sums (:class:`_Leaves`; 2^18 rows: 6 MB, and a k-d tree)
LEAF_LEVELS = 18
#: ... but the tree keeps at least the first min(LEAF_TOP, m // 2) levels (a smaller table for
#: 20-28 sensors, where the tree alone is fast)
LEAF_TOP = 10
#: nodes per table query (the threshold is updated in between)
LEAF_GROUP = 8
#: after the tree, the recorded candidates are evaluated exactly in batches, lowest bound first:
#: the first batch this many (all that is evaluated when a limit stopped the tree), each next one
#: twice the last, at most FINISH_MAX (the time limit is checked in between)
FINISH_FIRST = EVAL_PICKS * 16
FINISH_MAX = 1024
#: with a time limit, greedy's start gets at most this share of it (its working values are +inf
#: after that: it keeps the best it has), the rest is the root's bound and the tree's: without
#: the root's bound a decision certifies only the root's interval bound
GREEDY_SHARE = 0.5
#: exact mode: the children's new endpoints through the bound's pre-test where it has one
#: (spectral's inertia test, :func:`~covnet.core.allocation.interval_bounds._spectral_above`)
PRETEST = True
#: exact mode without the tie rule: the children's new endpoints through the bound's lazy
#: summary where it has one (spectral: the parent's summary on the kept rows, eigenvalues only
#: for the subsets that may be recorded, :func:`~covnet.core.allocation.interval_bounds.\
#: _spectral_lazy`); the tie rule reads the bounds of the nodes it drops, so not with it
LAZY = True


@dataclass(slots=True)
class _Chunk:
    """A batch of nodes of one depth ``d`` (the first ``d`` sensors of the order decided):
    ``Z`` ``(c, r*r)`` the information of ``I``, ``k`` ``(c,)`` ``|I|`` with the required ones,
    ``inc`` ``(c, ⌈m/8⌉)`` ``I`` as packed branching-order rows (:meth:`_Problem.unpack`),
    ``sA``/``sB`` the endpoint summaries, ``lb`` the bounds."""

    depth: int
    Z: Mat
    k: NDArray[np.int64]
    inc: NDArray[np.uint8]
    sA: Mat
    sB: Mat
    lb: Mat

    def take(self, rows: NDArray[np.bool_] | NDArray[np.intp]) -> _Chunk:
        return _Chunk(
            self.depth,
            self.Z[rows],
            self.k[rows],
            self.inc[rows],
            self.sA[rows],
            self.sB[rows],
            self.lb[rows],
        )


def _concat(chunks: list[_Chunk]) -> _Chunk:
    if len(chunks) == 1:
        return chunks[0]
    return _Chunk(
        chunks[0].depth,
        *(
            np.concatenate([getattr(c, name) for c in chunks])
            for name in ("Z", "k", "inc", "sA", "sB", "lb")
        ),
    )


class _Candidates:
    """Recorded subsets (packed branching-order rows) with lower bounds of their values, not yet
    evaluated; compacted (rows above the current threshold dropped) as it grows."""

    def __init__(self, m: int) -> None:
        self.inc: list[NDArray[np.uint8]] = []
        self.est: list[Mat] = []
        self.size = 0
        self.nb = (m + 7) // 8

    def add(self, inc: NDArray[np.uint8], est: Mat, tau: float) -> None:
        if est.size:
            self.inc.append(inc)
            self.est.append(est)
            self.size += est.size
            if len(self.est) >= 256:
                self.keep_below(tau)

    def arrays(self) -> tuple[NDArray[np.uint8], Mat]:
        if not self.est:
            return np.zeros((0, self.nb), dtype=np.uint8), np.zeros(0)
        if len(self.est) > 1:
            self.inc = [np.concatenate(self.inc)]
            self.est = [np.concatenate(self.est)]
        return self.inc[0], self.est[0]

    def keep_below(self, tau: float) -> None:
        inc, est = self.arrays()
        rows = est <= tau
        self.inc, self.est = [inc[rows]], [est[rows]]
        self.size = int(rows.sum())

    def clear(self) -> None:
        self.inc, self.est, self.size = [], [], 0


class _Search:
    """The branch and bound state (module docstring)."""

    def __init__(
        self,
        prob: _Problem,
        rel_gap: float,
        best_first: bool,
        deadline: Callable[[], bool] | None,
        node_limit: int | None,
        ties: bool = False,
    ) -> None:
        self.prob = prob
        self.rel_gap = rel_gap
        self.best_first = best_first
        self.deadline = deadline
        self.node_limit = node_limit
        self.cands = _Candidates(prob.m)
        self.ev_masks: list[NDArray[np.bool_]] = []
        self.ev_vals: list[Mat] = []
        self.U = math.inf
        self.L_pruned = math.inf
        self.n_nodes = 0
        self.open: list[_Chunk] = []
        self.keys: list[float] = []
        self.n_open = 0
        self.n_pops = 0
        # the root was bounded (before, nothing the tree did bounds the optimum)
        self.rooted = False
        # the table's depth (built when a node first reaches it), -1: none
        self.leaves: _Leaves | None = None
        self.d0 = -1
        if rel_gap == 0.0 and prob.relax is not None and prob.relax.leaves:
            u = min(LEAF_LEVELS, prob.m - min(LEAF_TOP, prob.m // 2))
            if u > 0:
                self.d0 = prob.m - u
        q = 8 * prob.n + prob.n * prob.n  # the widest summary's entries, generously
        per_node = 8 * (prob.r * prob.r + 2 + 2 * q) + (prob.m + 7) // 8
        self.open_cap = max(CHUNK, OPEN_BYTES // per_node)
        # exact mode: pruning by the tie rule (:mod:`covnet.core.allocation.tie_rule`); not
        # without a free sensor (one feasible subset: nothing to prune, and the rule would
        # bound the root first, 30-70 ms at N = 64)
        use_ties = ties and rel_gap == 0.0 and prob.m > 0
        self.ties = _TieRule(prob, symmetry=True) if use_ties else None
        self.min_rest = RELAX_MIN_REST
        if prob.dual is not None and rel_gap == 0.0:
            self.min_rest = DUAL_MIN_REST
        #: exact mode: the nodes the barrier does not refine get the dual bound's cheap vertex
        #: bound (one_norm, inf_norm, abs_trace; :meth:`_Problem.refine_vertex`)
        self.vertex = (
            rel_gap == 0.0 and prob.dual is not None and prob.dual.dual.vertices is not None
        )
        #: ... on the nodes with fewer than DUAL_MIN_REST and at least this many undecided
        #: sensors (the metric's :attr:`~covnet.core.allocation.lower_bounds.DualNorm.\
        #: vertex_min_rest`)
        self.vertex_rest = prob.dual.dual.vertex_min_rest if prob.dual is not None else 1
        #: exact mode: the children's summaries through the bound's pre-test (rows it proves
        #: above ``τ`` skip the summary and get a looser bound, still ``> τ``: pruned as
        #: before, and since a pruned bound exceeds ``τ >= U``, it never sets
        #: :meth:`lower_bound` or the tie rule's minima, ``min(U, ·)``; not with ``rel_gap``,
        #: where ``τ < U`` and the certificate would change)
        self.pretest = (
            PRETEST and rel_gap == 0.0 and prob.bound is not None and prob.bound.above is not None
        )
        #: ... and, without the tie rule (decided before :meth:`run`), lazily (:data:`LAZY`)
        self.lazy = LAZY and self.pretest and prob.bound is not None and prob.bound.lazy is not None

    # -- incumbent and thresholds ---------------------------------------------------------------

    @property
    def tau(self) -> float:
        """Prune above this: the tie threshold of the incumbent ``U + tie_rtol·max(|U|, tiny)``
        (exact), or ``U - rel_gap·|U|`` (bounded)."""
        U = self.U
        if not math.isfinite(U):
            return math.inf
        if self.rel_gap > 0.0:
            return U - self.rel_gap * abs(U)
        return U + self.prob.tie_rtol * max(abs(U), TINY)

    def evaluated(self, masks: NDArray[np.bool_], values: Mat) -> None:
        self.ev_masks.append(masks)
        self.ev_vals.append(values)
        if values.size:
            self.U = min(self.U, float(values.min()))
            if self.ties is not None:
                self.ties.observe(masks, values)

    def evaluate_inc(self, inc: NDArray[np.uint8]) -> None:
        masks = self.prob.masks(self.prob.unpack(inc))
        self.evaluated(masks, self.prob.exact(masks))

    # -- the tree ---------------------------------------------------------------------------------

    def push(self, ch: _Chunk) -> None:
        """Add open nodes, in batches of at most CHUNK (depth first: a small batch of the same
        depth as the last one is merged into it)."""
        if ch.lb.size == 0:
            return
        self.n_open += ch.lb.size
        if self.open and not self.best_first:
            top = self.open[-1]
            if top.depth == ch.depth and top.lb.size + ch.lb.size <= CHUNK:
                self.open[-1] = _concat([top, ch])
                self.keys[-1] = min(self.keys[-1], float(ch.lb.min()))
                return
        if ch.lb.size > CHUNK:
            ch = ch.take(np.argsort(ch.lb, kind="stable"))
            # the lowest bounds last: depth first pops them first
            for lo in range(((ch.lb.size - 1) // CHUNK) * CHUNK, -1, -CHUNK):
                piece = ch.take(np.arange(lo, min(lo + CHUNK, ch.lb.size)))
                self.open.append(piece)
                self.keys.append(float(piece.lb[0]))
        else:
            self.open.append(ch)
            self.keys.append(float(ch.lb.min()))

    def pop(self) -> _Chunk:
        """Depth first (the last pushed: bounded memory), or, with ``rel_gap`` and at most
        OPEN_BYTES of open nodes, best bound first on every other pop (the certified bound
        rises) and depth first in between (dives find better incumbents)."""
        self.n_pops += 1
        if self.best_first and self.n_open <= self.open_cap and self.n_pops % 2:
            i = min(range(len(self.keys)), key=self.keys.__getitem__)
        else:
            i = len(self.open) - 1
        ch = self.open.pop(i)
        self.keys.pop(i)
        self.n_open -= ch.lb.size
        return ch

    def prune(self, lb: Mat) -> NDArray[np.bool_]:
        """Rows to keep (bound <= tau); the pruned ones' least bound goes to ``L_pruned``."""
        keep = lb <= self.tau
        if not keep.all():
            self.L_pruned = min(self.L_pruned, float(lb[~keep].min()))
        return keep

    def root(self) -> None:
        prob = self.prob
        k0 = len(prob.req)
        self.rooted = True
        if prob.m == 0 or k0 >= prob.K:
            return
        Z0 = prob.base[None]
        sB = prob.summary(Z0)
        sA = prob.summary(Z0 + prob.suffix[0])
        lb = prob.combine(sA, sB)
        lb = prob.refine(Z0, Z0 + prob.suffix[0], lb, sB, self.tau)
        if prob.dual is not None and prob._root_bound is None:
            # the dual bound's run stops once it certifies the gap (lb > tau: 5-16 barrier
            # iterations at N = 100 instead of 30), kept for the certificate
            prob._root_bound = float(lb[0])
        else:  # the relaxation's full run (a few ms)
            prob.root_bound()
        self.n_nodes += 1
        nb = (prob.m + 7) // 8
        root = _Chunk(0, Z0, np.array([k0]), np.zeros((1, nb), dtype=np.uint8), sA, sB, lb)
        if self.prune(lb).all():
            self.push(root)

    def record(self, inc: NDArray[np.uint8], est: Mat) -> None:
        """New candidates: those that can still tie are kept; the best few that could beat the
        incumbent are evaluated at once (the incumbent, so the threshold, falls early)."""
        if self.ties is not None:
            self.ties.candidates(est)
        rec = self.prune(est)
        inc, est = inc[rec], est[rec]
        if est.size == 0:
            return
        better = np.flatnonzero(est < self.U)
        if better.size:
            picks = better[np.argsort(est[better], kind="stable")[:EVAL_PICKS]]
            self.evaluate_inc(inc[picks])
            rest = np.ones(est.size, dtype=bool)
            rest[picks] = False
            rest &= est <= self.tau
            inc, est = inc[rest], est[rest]
        self.cands.add(inc, est, self.tau)

    def endpoint(self, Z: Mat, lower: bool, prev: Mat, lazy: bool) -> Mat:
        """The summaries of the children's new endpoints ``Z`` (``lower``: the exclude
        children's ``A``; ``prev`` the parent's summary of the same side): lazily
        (:data:`LAZY`), through the pre-test (:data:`PRETEST`) or in full."""
        prob = self.prob
        if lazy:
            return prob.summary_lazy(Z, self.tau, lower, prev)
        if self.pretest:
            return prob.summary_above(Z, self.tau, lower)
        return prob.summary(Z)

    def expand(self, ch: _Chunk) -> None:
        """Children of every node of ``ch`` (decide sensor ``free[d]``): bounds, pruning,
        candidates, and the open children pushed."""
        prob = self.prob
        keep = self.prune(ch.lb)
        if not keep.all():
            ch = ch.take(keep)
        if ch.lb.size == 0:
            return
        d = ch.depth
        K = prob.K
        ties = self.ties
        if ties is not None:
            # the size rule: k >= s* keeps only I itself, already a candidate
            K = min(K, ties.s_star)
            big = ch.k >= K
            if big.any():
                ties.dropped(ch.lb[big])
                ch = ch.take(~big)
                if ch.lb.size == 0:
                    return
        if d == self.d0 and self.leaves_expand(ch):
            return
        last = d + 1 == prob.m
        relax = prob.m - (d + 1) >= self.min_rest
        out: list[_Chunk] = []
        # include children: I + free[d], a new B (every node here has k < K)
        src = ch
        if ties is not None and ties.same[d]:
            # identical sensors: free[d] only with its identical predecessor included
            has = (ch.inc[:, (d - 1) >> 3] >> np.uint8((d - 1) & 7)) & np.uint8(1)
            src = ch.take(has.astype(bool))
        Zi = src.Z + prob.S[d]
        lazy = self.lazy and ties is None
        sBi = self.endpoint(Zi, False, src.sB, lazy)
        ki = src.k + 1
        inc = src.inc.copy()
        inc[:, d >> 3] |= np.uint8(1 << (d & 7))
        est = prob.combine(sBi, sBi)
        if ties is not None:  # the sharper leaf bound (kl): the check's L_cand within tie_rtol
            est = prob.with_leaf(Zi, est)
        self.n_nodes += est.size
        self.record(inc, est)
        if not last:
            inner = np.flatnonzero(ki < K)
            if ties is not None and K < prob.K:
                drop = np.flatnonzero((ki >= K) & (ki < prob.K))
                if drop.size:
                    ties.dropped(prob.combine(src.sA[drop], sBi[drop]))
            if inner.size:
                sA = src.sA[inner]
                lbi = prob.combine(sA, sBi[inner])
                if relax:
                    Zn = Zi[inner]
                    lbi = prob.refine(Zn, Zn + prob.suffix[d + 1], lbi, sBi[inner], self.tau)
                elif self.vertex and prob.m - (d + 1) >= self.vertex_rest:
                    Zn = Zi[inner]
                    lbi = prob.refine_vertex(Zn, Zn + prob.suffix[d + 1], lbi, self.tau)
                kept = self.prune(lbi)
                rows = inner[kept]
                out.append(
                    _Chunk(d + 1, Zi[rows], ki[rows], inc[rows], sA[kept], sBi[rows], lbi[kept])
                )
            # exclude children: I unchanged, a new A
            Z_hi = ch.Z + prob.suffix[d + 1]
            sAe = self.endpoint(Z_hi, True, ch.sA, lazy)
            lbe = prob.combine(sAe, ch.sB)
            if relax:
                lbe = prob.refine(ch.Z, Z_hi, lbe, ch.sB, self.tau)
            elif self.vertex and prob.m - (d + 1) >= self.vertex_rest:
                lbe = prob.refine_vertex(ch.Z, Z_hi, lbe, self.tau)
            self.n_nodes += lbe.size
            kept = self.prune(lbe)
            if kept.any():
                out.append(
                    _Chunk(
                        d + 1,
                        ch.Z[kept],
                        ch.k[kept],
                        ch.inc[kept],
                        sAe[kept],
                        ch.sB[kept],
                        lbe[kept],
                    )
                )
        if out:
            self.push(_concat(out))

    def leaves_expand(self, ch: _Chunk) -> bool:
        """The whole subtrees of ``ch`` (depth ``d0``) from the table (:class:`_Leaves`):
        their completions inside the ball recorded as candidates; ``False``: no ball, expand
        as usual."""
        if self.deadline is not None and self.deadline():
            self.push(ch)  # the time is up (the table's build is a step of its own)
            return True
        if self.leaves is None:
            try:
                self.leaves = _Leaves(self.prob, self.d0)
            except (FloatingPointError, ValueError, np.linalg.LinAlgError):
                self.d0 = -1
                return False
        if self.leaves.ball(self.tau) is None:
            return False
        # the lowest bounds first, a few nodes at a time: the threshold falls in between
        order = np.argsort(ch.lb, kind="stable")
        for lo in range(0, order.size, LEAF_GROUP):
            if lo and self.limited():
                # a limit: the nodes not queried stay open (their bounds stay in the certificate)
                self.push(ch.take(order[lo:]))
                return True
            sub = ch.take(order[lo : lo + LEAF_GROUP])
            sub = sub.take(self.prune(sub.lb))
            if sub.lb.size == 0:
                continue
            tau = self.tau
            if self.ties is None:
                inc, est, looked = self.leaves.leaves(sub.Z, sub.k, sub.inc, tau)
            else:
                K = min(self.prob.K, self.ties.s_star)
                same = self.ties.same if self.ties.symmetry else None
                inc, est, looked = self.leaves.leaves(sub.Z, sub.k, sub.inc, tau, K, same)
                if K < self.prob.K:  # completions over the size rule: below the node's bound
                    self.ties.dropped(sub.lb)
                if est.size and self.prob.leaf_constants is not None:  # kl, as in the tree
                    est = self.prob.with_leaf(self.prob.information(self.prob.unpack(inc)), est)
            self.n_nodes += looked
            # every completion left out is above tau (its bound too)
            self.L_pruned = min(self.L_pruned, tau)
            self.record(inc, est)
        return True

    def limited(self) -> int:
        if self.node_limit is not None and self.n_nodes >= self.node_limit:
            return 1
        if self.deadline is not None and self.deadline():
            return 2
        return 0

    def run(self) -> int:
        """Explore until the tree is exhausted (0) or a limit is hit (1 nodes, 2 time; the time
        also before the root, when greedy's start took it all)."""
        why = self.limited()
        if why:
            return why
        self.root()
        while self.open:
            why = self.limited()
            if why:
                return why
            self.expand(self.pop())
        return 0

    def finish(self, why: int) -> int:
        """Evaluate the recorded candidates that can still win or tie (bound <= ``tau``), lowest
        bound first, in batches; ``tau`` falls with the incumbent in between (a candidate above
        it cannot be in the tie set: the exactness argument of the module docstring).  After a
        limit hit in the tree (``why``) only the first, most promising batch; otherwise all of
        them, unless the time limit is reached between two batches: then ``2``, and the
        candidates not evaluated stay in :meth:`lower_bound`.  Returns the final status."""
        inc, est = self.cands.arrays()
        if est.size == 0:
            return why
        order = np.argsort(est, kind="stable")
        inc, est = inc[order], est[order]
        lo, size = 0, FINISH_FIRST
        while lo < est.size and est[lo] <= self.tau:
            hi = min(lo + size, int(np.searchsorted(est, self.tau, side="right")))
            self.evaluate_inc(inc[lo:hi])
            lo = hi
            if why:
                break
            more = lo < est.size and est[lo] <= self.tau
            if more and self.deadline is not None and self.deadline():
                why = 2
                break
            size = min(2 * size, FINISH_MAX)
        self.cands.inc, self.cands.est = [inc[lo:]], [est[lo:]]
        self.cands.size = est.size - lo
        return why

    def lower_bound(self) -> float:
        """The least of the incumbent, the pruned nodes' and candidates' bounds, the open nodes'
        bounds and the pending candidates' bounds: at most the optimum (``-inf`` before the
        root: the caller takes the root's bound)."""
        if not self.rooted:
            return -math.inf
        L = min(self.U, self.L_pruned)
        if self.ties is not None:  # the size rule's dropped nodes
            L = min(L, self.ties.L_size)
        if self.keys:
            L = min(L, min(self.keys))
        _, est = self.cands.arrays()
        if est.size:
            L = min(L, float(est.min()))
        return L


def allocate_bnb(
    P_pred: Mat,
    gains: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    constraints: Constraints = NO_CONSTRAINTS,
    tie_rtol: float = 1e-9,
    *,
    rel_gap: float = 0.0,
    time_limit_s: float | None = None,
    node_limit: int | None = None,
    clock: Callable[[], float] | None = None,
) -> SearchResult:
    """Branch and bound over include / exclude / undecided (module docstring).

    With ``rel_gap = 0`` and no limit hit (``status 0``, ``exact``): the same subset, value and
    ``P`` bits as :func:`covnet.core.allocation.allocate_exhaustive`, the same exceptions for bad
    input (:class:`~covnet.core.allocation.InfeasibleAllocation` included).  ``rel_gap > 0``,
    ``time_limit_s`` or ``node_limit``: bounded mode, the best subset found with a certified
    ``lower_bound`` and ``gap``; status 1 (node limit), 2 (time limit) or 3 (completed within
    ``rel_gap``).  ``clock``: seconds, for the time limit (default ``time.perf_counter``).

    A metric without an interval bound (a user's own function) is solved exactly by
    :func:`covnet.core.allocation.allocate` (its batched search), limits ignored.
    """
    if not (math.isfinite(rel_gap) and 0.0 <= rel_gap < 1.0):
        raise ValueError(f"rel_gap must be in [0, 1), got {rel_gap}")
    if time_limit_s is not None and not time_limit_s >= 0:
        raise ValueError(f"time_limit_s must be >= 0 or None, got {time_limit_s}")
    if node_limit is not None and (not isinstance(node_limit, int) or node_limit < 1):
        raise ValueError(f"node_limit must be an integer >= 1 or None, got {node_limit!r}")
    deadline: Callable[[], bool] | None = None
    greedy_deadline: Callable[[], bool] | None = None
    if time_limit_s is not None:
        if clock is None:
            # only with a time limit (start-up: the core needs no clock otherwise)
            import time

            clock = time.perf_counter
        t0 = clock()
        t_end = t0 + time_limit_s
        t_greedy = t0 + GREEDY_SHARE * time_limit_s
        tick = clock

        def deadline() -> bool:
            return tick() >= t_end

        def greedy_deadline_() -> bool:
            return tick() >= t_greedy

        greedy_deadline = greedy_deadline_

    if rel_gap == 0.0 and time_limit_s is None and node_limit is None:
        # one feasible subset: the search's result without its set-up
        one = only_subset(P_pred, gains, P_d, metric, constraints, tie_rtol)
        if one is not None:
            return one
    prob = _Problem(P_pred, gains, P_d, metric, constraints, tie_rtol)
    if prob.bound is None:
        ref = allocate(P_pred, gains, P_d, metric, constraints, tie_rtol)
        return SearchResult(
            ref.subset,
            ref.value,
            ref.P,
            ref.value,
            0.0,
            0,
            ref.n_evaluated,
            True,
            0,
            STATUS[0] + "; no interval bound for this metric: covnet.core.allocation.allocate",
        )
    # best bound first when a gap is asked for (the certified bound rises fastest); depth first
    # otherwise (bounded memory), also when only a limit guards an exact search
    try:
        prob.stop = greedy_deadline  # greedy's phases, GREEDY_SHARE of the time
        start = _greedy_start(prob, deadline)
        prob.stop = deadline  # the relaxation's and the dual bound's iterations
        for ties in (True, False):
            # the tie rule's pruning first; again without it when its check fails
            search = _Search(prob, rel_gap, rel_gap > 0.0, deadline, node_limit, ties)
            search.evaluated(*start)
            if search.ties is not None and not search.ties.active:
                search.ties = None  # nothing certified: the rules would prune nothing sure
            elif search.ties is not None and search.ties.leaf_sharp:
                # the identical-sensor rule on a sharp leaf bound (kl): the tree prunes the
                # twins at every level, where the table would find them all in its ball and
                # drop them after (kl's tie problems at N = 40: 95 M rows looked at, 7.4 s,
                # against 82 k nodes, 0.12 s)
                search.d0 = -1
            why = search.finish(search.run())
            masks = np.concatenate(search.ev_masks)
            values = np.concatenate(search.ev_vals)
            k = tie_select(values, masks, prob.tie_rtol)
            if search.ties is None or why or search.ties.verified(masks, values, k):
                break
        mask, value = masks[k], float(values[k])
        P = prob.exact_covariances(mask[None])[0]
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    if why == 0 and rel_gap == 0.0:
        return SearchResult(
            _subset(mask),
            value,
            P,
            value,
            0.0,
            search.n_nodes,
            prob.n_evaluated,
            True,
            0,
            STATUS[0],
        )
    prob.stop = None  # the root's bound runs whole (one node: one step of overshoot) when
    # the tree did not reach it, until it certifies rel_gap (the dual bound's barrier stops
    # there: 5-16 iterations instead of 30 at N = 100)
    goal = value - rel_gap * abs(value) if rel_gap > 0.0 else math.inf
    lb = min(max(search.lower_bound(), prob.root_bound(goal)), value)
    if _gap(value, lb) > rel_gap and (deadline is None or not deadline()):
        # rel_gap not certified, time left: at least the root's bound whole (greedy's, which
        # was larger on the same subset when the root's stopped early)
        lb = min(max(lb, prob.root_bound_whole()), value)
    status = why if why else 3
    return SearchResult(
        _subset(mask),
        value,
        P,
        lb,
        _gap(value, lb),
        search.n_nodes,
        prob.n_evaluated,
        False,
        status,
        STATUS[status],
    )
