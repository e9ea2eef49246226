"""Greedy allocation (:func:`allocate_greedy`), also the start of the branch and bound
(:mod:`covnet.core.allocation.search`).

**Greedy** (:func:`allocate_greedy`): two starts, evaluated exactly at the end, the tie rule
picks.  (1) The plain heuristic (:class:`_Plain`): from the required set, add the sensor of the
smallest value while one improves (by a relative ``IMPROVE``) and the budget allows, ties by the
lowest sensor index; then first-improvement local search over, in this order, additions,
removals and 1-swaps, sensors by index, until no move improves; its decisions are taken on
*exact* values (the reference's arithmetic), screened by working values: only the moves whose
working value lies within a margin of the decision are evaluated exactly.  (2) The better of the
forward path continued from (1)'s forward end past non-improving steps (while the bound says a
superset can still win) and backward elimination (from every sensor), then best-improvement
local search over removals, additions and 1-swaps, on working (reduced-form) values.  The result
and the branch and bound's first incumbent is the tie rule's pick among these subsets, the
required set and the zero sensor's singleton.  Its certified lower bound is the bound of the
root ``[P(required ∪ all allowed), P(required)]`` (with the relaxation where it applies).

**Never worse than the plain heuristic** (issue 29).  Start (1) takes the decisions of the plain
forward greedy with 1-swaps on exact values (``tests/property/test_greedy_reference.py``'s
oracle) whenever every working value it screens is within the margin ``δ = VERIFY · max(f(P_pred,
P_d), |value|)`` of its exact value (the proofs are in :class:`_Plain`'s methods; rounding
measured at most ``6e-11`` of that scale on ill-conditioned random problems, against ``VERIFY =
1e-8``), so it ends on the plain heuristic's subset ``S_p``, bit for bit.  ``S_p`` is one of the
rows the tie rule chooses from, so the result's value is at most ``f(S_p) + tie_rtol · max(|f(S_p)|,
tiny)`` (the rule may prefer fewer sensors within that tolerance); the branch and bound records
these rows as evaluated and its result is the same rule over a superset of them, so ``bounded``
inherits the guarantee (without a time limit cutting the start short).  Before, start (1) ran on
working values: those differ from exact ones by up to ``6e-11`` relatively, far above the
``1e-12`` a move must improve by, so at (near-)ties the path could turn elsewhere (40 of 1 350
random (problem, metric) pairs, mostly with duplicated sensors) and, once in 900 tie-prone pairs
(precisions a few ulps apart), end worse.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation._fast import EPS, tie_select
from covnet.core.allocation.exact import Constraints, _spd_error
from covnet.core.allocation.search_problem import (
    EXACT_ENTRIES,
    MOVE_BLOCK,
    NO_CONSTRAINTS,
    STATUS,
    SearchResult,
    _gap,
    _Problem,
    _subset,
)
from covnet.core.allocation.svd_bound import WorkingFloor
from covnet.core.allocation.tie_rule import identical_to_previous
from covnet.core.gaussian import Mat
from covnet.core.metrics import METRICS, Metric, MetricFn, capability

#: local search: at most this many passes, each evaluating its moves in batches of MOVE_BLOCK
MAX_PASSES = 64
#: backward elimination removes one sensor at a time below this many, blocks above
BACKWARD_ONE = 64
#: local search: every 1-swap while there are at most this many, else only the swaps among the
#: SWAP_POOL best removals and additions
FULL_SWAPS = 4096
SWAP_POOL = 64
FULL_SCAN_BUDGET = 1 << 17
#: a move improves when its value is below the current one by this much, relatively
IMPROVE = 1e-12
#: the plain first-improvement local search evaluates at most this many moves per call
PLAIN_BUDGET = 1 << 20
#: the plain heuristic decides on working values only farther than this (relative to
#: ``max(f(P_pred, P_d), |value|)``) from a decision, on exact values nearer (:class:`_Plain`)
VERIFY = 1e-8
#: and evaluates the moves near a decision exactly in batches of this many, in order
VERIFY_BATCH = 16
#: greedy's local search evaluates first this many swaps of a block, those of the lowest
#: working floor, then only those whose floor is at most the smallest value found
#: (:func:`_screened_values`)
FLOOR_FIRST = 64


def _improves(v: float, ref: float) -> bool:
    """``v`` is better than ``ref`` by a relative ``IMPROVE`` (anything finite beats ``inf``)."""
    return v < ref - IMPROVE * abs(ref) if math.isfinite(ref) else math.isfinite(v)


class _Plain:
    """The plain heuristic's decisions on exact values, screened by working values.

    Exact values (:meth:`exact`: the reference's arithmetic, non-finite -> ``inf``, counted in
    ``prob.n_evaluated``) are cached by subset.  The screening margin of a working value ``w``
    is ``δ_w = VERIFY · max(f(P_pred, P_d), |w|)``.  A decision is taken on working values only
    where every value it compares is farther than the margins from the decision (:meth:`_margins`);
    nearer, the values are evaluated exactly.  So the decisions are the exact ones whenever
    ``|w - e| <= δ_w`` for every working value compared (rounding: at most ``6e-11`` of
    ``max(f(P_pred, P_d), |e|)`` measured on ill-conditioned random problems, ``VERIFY`` is
    ``1e-8``); usually one exact evaluation per decision at most, none where a move improves by
    more than the margin.  One exception, by design: the free sensors exclude zero gains, so
    where the plain heuristic would pick a zero-gain sensor alone (doing nothing is best) this
    path picks another, and greedy's own zero-sensor row (:func:`_greedy_start`) is the plain
    heuristic's subset.

    The margin holds while the working values' rounding does, about ``n² eps κ`` of the value
    (``κ`` the problem's condition bound, valid for every subset's ``P``).  On a problem so
    ill-conditioned that ``n² eps κ > VERIFY`` (a sensor ``10⁵`` times finer than another one
    along a nearly degenerate direction: ``κ ~ 10¹⁶``), a working value can be far off or
    ``inf`` (the reduced form not positive definite) while the exact value is finite, and a
    move it screened out was never looked at: greedy ended 1 % above the plain heuristic.
    There (:attr:`trusted` false) every value compared is the exact one."""

    def __init__(self, prob: _Problem) -> None:
        self.prob = prob
        self.by_id = np.argsort(np.asarray(prob.free, dtype=np.int64), kind="stable")
        with np.errstate(all="ignore"):
            f0 = np.asarray(prob.f(prob.P_pred[None], prob.D), dtype=np.float64).reshape(-1)
        self.f0 = float(abs(f0[0])) if f0.size and math.isfinite(float(f0[0])) else 0.0
        self.cache: dict[bytes, float] = {}
        kappa = float(prob.ctx.kappa)
        #: the working values' rounding is within the screening margin (class docstring)
        self.trusted = math.isfinite(kappa) and prob.n**2 * EPS * (kappa + 1.0) <= VERIFY
        # bit-identical sensors are adjacent in the branching order (the tie rule's twins)
        same = identical_to_previous(prob)
        #: per branching position, the class of bit-identical gains its sensor is in
        self.twin_class = np.cumsum(~same)
        self.has_twins = bool(same.any())

    def values(
        self, inc: NDArray[np.bool_], w: Mat, rem: NDArray[np.intp], add: NDArray[np.intp]
    ) -> Mat:
        """The values the decisions compare for the moves ``(rem, add)`` from ``inc`` whose
        working values are ``w`` (``-1``: no removal / addition): ``w`` itself, or the exact
        values where the working values are not :attr:`trusted`."""
        if self.trusted:
            return w
        rows = np.repeat(inc[None], rem.size, axis=0)
        at = np.arange(rem.size)
        rows[at[rem >= 0], rem[rem >= 0]] = False
        rows[at[add >= 0], add[add >= 0]] = True
        return self.exact(rows)

    def exact(self, inc: NDArray[np.bool_]) -> Mat:
        """Exact values of the branching-order rows ``inc`` ``(c, m)``, in batches whose gain
        sums stay below EXACT_ENTRIES entries; once ``prob.stop`` says the time is up, the
        rows of the batches not started are ``inf`` (not cached; the first batch always
        runs).  One uninterrupted batch of 2 000 tied candidates at N = 2 000 took 14 s and
        half a gigabyte."""
        out = np.empty(inc.shape[0])
        todo = []
        for i, row in enumerate(inc):
            hit = self.cache.get(np.packbits(row).tobytes())
            if hit is None:
                todo.append(i)
            else:
                out[i] = hit
        prob = self.prob
        step = max(1, EXACT_ENTRIES // max(prob.N * prob.n * prob.n, 1))
        for lo in range(0, len(todo), step):
            part = todo[lo : lo + step]
            if lo and prob.stop is not None and prob.stop():
                out[todo[lo:]] = np.inf
                break
            masks = prob.masks(inc[part])
            with np.errstate(all="ignore"):
                v = np.asarray(prob.f(prob.exact_covariances(masks), prob.D), dtype=np.float64)
            v = np.where(np.isfinite(v) & masks.any(axis=1), v, np.inf)
            prob.n_evaluated += len(part)
            for i, x in zip(part, v.tolist(), strict=True):
                out[i] = x
                self.cache[np.packbits(inc[i]).tobytes()] = x
        return out

    def _margins(self, w: float, val_w: float, val_e: float | None) -> tuple[float, float]:
        """``(t, slack)``: a value ``e`` improves on the current one iff ``e < thr(val_e)``
        (``thr(v) = v - IMPROVE·|v|``); with ``|w - e| <= d`` and, when the current value is
        known only as ``val_w``, ``|val_w - val_e| <= d``, a working value ``w < t - slack``
        improves for certain and ``w >= t + slack`` for certain not (``thr`` is increasing with
        slope at most ``1 + IMPROVE``)."""
        d = VERIFY * max(self.f0, abs(val_w), abs(w) if math.isfinite(w) else 0.0)
        if val_e is not None:
            return val_e - IMPROVE * abs(val_e), d
        return val_w - IMPROVE * abs(val_w), d + (1.0 + IMPROVE) * d

    def forward(self) -> tuple[NDArray[np.bool_], float]:
        """Forward selection from the required set: add the sensor of the smallest exact value
        (ties: the lowest sensor index) while it improves (by a relative ``IMPROVE``) and the
        budget allows.  With ``|w - e| <= δ_w = VERIFY · max(f(P_pred, P_d), |w|)``, the exact
        minimum is within ``3 δ`` (``δ`` of the working minimum ``w*``) of ``w*``: for any ``k``
        outside, ``e_k >= w_k - δ_k > w* + δ >= e_*``, so only the candidates there are
        evaluated exactly (usually none: one candidate, and it improves for certain,
        :meth:`_margins`).  Of sensors with bit-identical gains only the lowest-index one not
        yet added is a candidate (the exact search's canonical twin,
        :mod:`covnet.core.allocation.tie_rule`): the copies' subsets have the same information
        and differ only in the order of the reference's sum, so their exact values differ by
        rounding; evaluating every copy exactly, to pick the rounding's least, took 16 of the
        18 s of CPU of one decision of a 1000-sensor network of 64 repeated models (2.6 s
        now).  Returns the subset and its value (exact where known, else working)."""
        prob = self.prob
        inc = np.zeros(prob.m, dtype=bool)
        val_e: float | None = float(self.exact(inc[None])[0]) if prob.req else math.inf
        val_w = val_e if val_e is not None else math.inf
        while len(prob.req) + int(inc.sum()) < prob.K:
            outs = self.by_id[~inc[self.by_id]]
            if outs.size == 0:
                break
            Z = prob.base + prob.S[inc].sum(axis=0)
            w = prob.approx_values(Z[None] + prob.S[outs])
            w = self.values(inc, w, np.full(outs.size, -1), outs)
            prob.moves += outs.size
            w_min = float(w.min())
            if not math.isfinite(w_min):
                break
            d = VERIFY * max(self.f0, abs(w_min))
            near = np.flatnonzero(w <= w_min + 3.0 * d)
            if self.has_twins and near.size > 1:  # the lowest-index copy of identical ones
                _, first = np.unique(self.twin_class[outs[near]], return_index=True)
                near = near[np.sort(first)]
            rows = np.repeat(inc[None], near.size, axis=0)
            rows[np.arange(near.size), outs[near]] = True
            e_j: float | None = None
            i = 0
            if near.size > 1:
                e = self.exact(rows)
                i = int(np.argmin(e))  # candidates in sensor order: the lowest index of the ties
                e_j = float(e[i])
            w_j = float(w[near[i]])
            if not math.isfinite(val_w):  # the first sensor: any finite value improves on nothing
                if e_j is None:
                    e_j = float(self.exact(rows[i : i + 1])[0])
                if not math.isfinite(e_j):
                    break
            else:
                t, slack = self._margins(w_j, val_w, val_e)
                sure = w_j < t - slack
                if not sure and w_j < t + slack:  # near the threshold: decide exactly
                    if val_e is None:
                        val_e = float(self.exact(inc[None])[0])
                    if e_j is None:
                        e_j = float(self.exact(rows[i : i + 1])[0])
                    sure = e_j < val_e - IMPROVE * abs(val_e)
                if not sure:
                    break
            inc, val_w, val_e = rows[i], w_j, e_j
        return inc, val_w if val_e is None else val_e

    def local_search(self, inc: NDArray[np.bool_], val: float) -> NDArray[np.bool_]:
        """First-improvement local search over, in this order, additions, removals and 1-swaps
        (out ascending, then in ascending), sensors by index: the first move whose exact value
        improves by a relative ``IMPROVE`` is taken, until none does (or PLAIN_BUDGET moves were
        evaluated: far beyond what 64 sensors need).  A move can improve exactly only if its
        working value is below the threshold plus the slack (:meth:`_margins`); those are taken
        in order: one below the threshold minus the slack improves for certain and is taken
        without an exact evaluation, the uncertain ones before it are evaluated exactly (in
        batches, with the current subset's exact value) and the first that improves is taken."""
        prob = self.prob
        k0, K = len(prob.req), prob.K
        inc = inc.copy()
        val_w, val_e = val, None
        budget = PLAIN_BUDGET
        while budget > 0 and math.isfinite(val_w):
            Z = prob.base + prob.S[inc].sum(axis=0)
            ins, outs = self.by_id[inc[self.by_id]], self.by_id[~inc[self.by_id]]
            parts: list[tuple[NDArray[np.intp], NDArray[np.intp]]] = []
            if k0 + ins.size < K:
                parts.append((np.full(outs.size, -1), outs))
            if k0 or ins.size > 1:
                parts.append((ins, np.full(ins.size, -1)))
            parts.append((np.repeat(ins, outs.size), np.tile(outs, ins.size)))
            rem = np.concatenate([p[0] for p in parts])
            add = np.concatenate([p[1] for p in parts])
            move: NDArray[np.bool_] | None = None
            for lo in range(0, rem.size, MOVE_BLOCK):
                r_, a_ = rem[lo : lo + MOVE_BLOCK], add[lo : lo + MOVE_BLOCK]
                w = self.values(inc, _move_values(prob, Z, r_, a_), r_, a_)
                budget -= w.size
                w_big = float(np.max(np.abs(w), initial=0.0, where=np.isfinite(w)))
                t, slack = self._margins(w_big, val_w, val_e)  # the widest slack of the block
                cand = np.flatnonzero(w < t + slack)
                pos = 0
                while pos < cand.size and move is None:
                    run: list[int] = []
                    while pos < cand.size and len(run) < VERIFY_BATCH:
                        c = int(cand[pos])
                        t, slack = self._margins(float(w[c]), val_w, val_e)
                        if w[c] < t - slack:
                            break
                        if w[c] < t + slack:
                            run.append(c)
                        pos += 1
                    rows = np.repeat(inc[None], len(run) + 1, axis=0)
                    for k, c in enumerate(run + [int(cand[pos]) if pos < cand.size else -1]):
                        if c >= 0 and r_[c] >= 0:
                            rows[k, r_[c]] = False
                        if c >= 0 and a_[c] >= 0:
                            rows[k, a_[c]] = True
                    if run:
                        if val_e is None:
                            val_e = float(self.exact(inc[None])[0])
                        e = self.exact(rows[:-1])
                        ok = np.flatnonzero(e < val_e - IMPROVE * abs(val_e))
                        if ok.size:
                            move, val_w, val_e = rows[ok[0]], float(e[ok[0]]), float(e[ok[0]])
                            break
                    if pos < cand.size and len(run) < VERIFY_BATCH:  # a certain improvement
                        c = int(cand[pos])
                        move, val_w, val_e = rows[-1], float(w[c]), None
                if move is not None:
                    break
            if move is None:
                break
            inc = move
        return inc


def _forward(prob: _Problem, inc: NDArray[np.bool_]) -> tuple[NDArray[np.bool_], float]:
    """Forward selection continued from ``inc`` (the plain forward selection's end) on working
    values: add the sensor giving the smallest value (ties: the lowest sensor index); stop at
    the budget, or when the interval bound of (current set, all the rest undecided) exceeds the
    best value on the path (no superset can do better).  Returns the path's best (working
    values)."""
    K, k0 = prob.K, len(prob.req)
    inc = inc.copy()
    Z = prob.base + prob.S[inc].sum(axis=0)
    best_val = float(prob.approx_values(Z[None])[0]) if k0 or inc.any() else math.inf
    best_inc = inc.copy()
    by_id = np.argsort(np.asarray(prob.free, dtype=np.int64), kind="stable")
    k = k0 + int(inc.sum())
    while k < K and not inc.all():
        rest = by_id[~inc[by_id]]
        if math.isfinite(best_val) and prob.bound is not None:
            sA = prob.summary((Z + prob.S[rest].sum(axis=0))[None])
            sB = prob.summary(Z[None])
            if float(prob.combine(sA, sB)[0]) > best_val:
                break
        v = prob.approx_values(Z[None] + prob.S[rest])
        prob.moves += rest.size
        i = int(np.argmin(v))
        if not math.isfinite(float(v[i])):
            break
        inc[rest[i]] = True
        Z = prob.base + prob.S[inc].sum(axis=0)
        k += 1
        if v[i] < best_val:
            best_val, best_inc = float(v[i]), inc.copy()
    return best_inc, best_val


def _backward(prob: _Problem, reuse: bool = False) -> tuple[NDArray[np.bool_], float]:
    """Backward elimination from every free sensor: remove the sensor whose removal gives the
    smallest value (above BACKWARD_ONE sensors, the ``⌈|D| / BACKWARD_ONE⌉`` best removals at
    once, so a pass costs ``O(N · BACKWARD_ONE)`` evaluations); values count once within the
    budget.  Returns the path's best.  ``reuse`` (greedy under a time limit): after removing
    one sensor the new set's working value is the removal's (the same set, its ``Z`` summed in
    another order: working values differ by rounding only), not evaluated again (one batch of
    one row less per pass: 15-40 % of the pass), and the path stops once the interval bound of
    the current set's subsets shows that none of them can be the path's best
    (:func:`_backward_done`: the same best, fewer passes)."""
    m, K, k0 = prob.m, prob.K, len(prob.req)
    inc = np.ones(m, dtype=bool)
    best_inc, best_val = inc.copy(), math.inf
    known: float | None = None
    check = _BackwardCheck(prob) if reuse and prob.bound is not None else None
    while True:
        k = k0 + int(inc.sum())
        improved = False
        if k <= K:
            if known is None:
                v0 = float(prob.approx_values((prob.base + prob.S[inc].sum(axis=0))[None])[0])
            else:
                v0 = known
            if v0 < best_val:
                best_val, best_inc = v0, inc.copy()
                improved = True
        ins = np.flatnonzero(inc)
        if ins.size == 0 or (ins.size == 1 and not k0):
            break
        Z = prob.base + prob.S[inc].sum(axis=0)
        if check is not None and not improved and check.due() and check.done(Z, best_val):
            break
        if check is not None and improved:
            check.reset()
        v = prob.approx_values(Z[None] - prob.S[ins])
        prob.moves += ins.size
        step = max(1, -(-ins.size // BACKWARD_ONE))
        if k - K > step:  # still above the budget: remove faster, values do not count yet
            step = max(step, (k - K) // 2)
        step = min(step, ins.size - (0 if k0 else 1))
        order = np.argsort(v, kind="stable")[:step]
        drop = ins[order]
        inc[drop] = False
        known = float(v[order[0]]) if reuse and step == 1 else None
    return best_inc, best_val


class _BackwardCheck:
    """Whether backward elimination can stop (:meth:`done`): every set the path still visits is
    a subset of the current set ``D`` (with the required ones), so its covariance lies in the
    Loewner interval ``[P(req ∪ D), P(req)]`` and its exact value is at least that interval's
    bound ``L`` (:class:`~covnet.core.allocation.interval_bounds.IntervalBound`, the bound the
    tree uses); its working value is within rounding (at most ``6e-11`` of ``max(f(P(req),
    P_d), |value|)`` measured, module docstring) of the exact one.  So when ``L`` exceeds the
    path's best working value by ``VERIFY`` of that scale (``1e-8``), no later set can replace
    the best and the path's result is the same without the rest.  Checked only on passes where
    the best did not just improve, with a back-off (:meth:`due`: after a check that did not
    stop, the next one 1, 2, 4, ... passes later, back to every pass once the best improves):
    about 60 µs a check at N = 100, against the 60-150 µs of a pass, and for kl, logdet and
    frobenius the bound stops the path only near its end.  On the bench's svd problems at N =
    100 the path stops at 39-55 sensors, after about half of its 99 passes."""

    def __init__(self, prob: _Problem) -> None:
        self.prob = prob
        self.s_req: Mat | None = None
        self.scale = 0.0
        self.wait = 0
        self.gap = 1

    def reset(self) -> None:
        """The best improved: check at every pass again."""
        self.wait, self.gap = 0, 1

    def due(self) -> bool:
        """Whether this pass checks (counting the passes since the last check)."""
        if self.wait:
            self.wait -= 1
            return False
        return True

    def done(self, Z: Mat, best: float) -> bool:
        if not math.isfinite(best):
            return False
        self.wait, self.gap = self.gap, 2 * self.gap
        prob = self.prob
        if self.s_req is None:
            self.s_req = prob.summary(prob.base[None])
            f_req = float(prob.approx_values(prob.base[None])[0])
            self.scale = abs(f_req) if math.isfinite(f_req) else 0.0
        lb = float(prob.combine(prob.summary(Z[None]), self.s_req)[0])
        return lb > best + VERIFY * max(self.scale, abs(best))


def _moved(prob: _Problem, Z: Mat, r_: NDArray[np.intp], a_: NDArray[np.intp]) -> Mat:
    """The information of each move ``(r_[i], a_[i])`` (``-1``: none) from ``Z``, one row each."""
    Zm = np.broadcast_to(Z, (r_.size, Z.size)).copy()
    Zm[r_ >= 0] -= prob.S[r_[r_ >= 0]]
    Zm[a_ >= 0] += prob.S[a_[a_ >= 0]]
    return Zm


def _move_values(prob: _Problem, Z: Mat, rem: NDArray[np.intp], add: NDArray[np.intp]) -> Mat:
    """Working values of the moves ``(rem[i], add[i])`` (``-1``: none) from information ``Z``."""
    out = np.empty(rem.size)
    for lo in range(0, rem.size, MOVE_BLOCK):
        r_, a_ = rem[lo : lo + MOVE_BLOCK], add[lo : lo + MOVE_BLOCK]
        out[lo : lo + r_.size] = prob.approx_values(_moved(prob, Z, r_, a_))
    prob.moves += rem.size
    return out


def _entry(prob: _Problem) -> Metric | None:
    """The registry's entry of the problem's metric (None for a user's plain function)."""
    entry = METRICS.get(prob.name) if prob.name is not None else None
    return entry if entry is not None and entry.fn is prob.f else None


def _working_floor(prob: _Problem) -> WorkingFloor | None:
    """The registered metric's working floor (``Metric.working_floor``), if any."""
    entry = _entry(prob)
    return None if entry is None else capability(entry.working_floor, WorkingFloor)


def _screened_values(
    prob: _Problem,
    Z: Mat,
    rem: NDArray[np.intp],
    add: NDArray[np.intp],
    thr: float,
    floor: WorkingFloor | None,
) -> Mat:
    """:func:`_move_values` for a caller that needs only the smallest value and the first index
    of it, and only when it is below ``thr`` (:func:`_local_search`'s ``consider``): a move
    whose working floor ``φ`` (``Metric.working_floor``, ``φ <= v``) shows it cannot be that
    may be ``+inf`` instead of its value ``v``.

    Per block, the moves with ``φ < thr`` (or ``φ`` NaN) are evaluated in order of ``φ``: the
    FLOOR_FIRST lowest, then only those with ``φ`` at most the smallest value ``m`` found so far
    (``m`` carried over the blocks).  Why the result is the same: let ``v* < thr`` be the
    smallest value and ``i*`` any index attaining it; a skipped move has ``φ >= thr > v*`` or
    ``φ > m >= v*`` (``m`` is a value found), so its value ``v >= φ > v*``: every ``i*`` is
    evaluated, and the returned smallest value and its first index are ``v*`` and the first
    ``i*``.  When no value is below ``thr`` the caller takes no move either
    way.

    The evaluated values have the bits of :func:`_move_values`: each block's ``Zm`` and its
    covariances are those :meth:`_Problem.approx_values` computes for the block (the same
    ``MOVE_BLOCK`` blocks, the covariances of the whole block, then its rows), and the metric
    is batch-invariant (a row's value does not depend on the others in the stack: see
    :mod:`covnet.core.metrics`).  Non-finite values become ``+inf`` and the time limit makes
    every value ``+inf``, as in ``approx_values``; if the metric raises ``LinAlgError`` on the
    evaluated rows, the block is evaluated by ``approx_values`` itself (its own fallback).
    (``LinAlgError`` from ``eigh`` means non-convergence on a finite matrix, which a skipped
    row could in principle cause in the full block but not among the evaluated rows: never
    seen, and the values would then differ only in that block's last bits.)"""
    if floor is None or not math.isfinite(thr) or prob.relax is not None:
        return _move_values(prob, Z, rem, add)
    out = np.full(rem.size, np.inf)
    m = math.inf
    for lo in range(0, rem.size, MOVE_BLOCK):
        r_, a_ = rem[lo : lo + MOVE_BLOCK], add[lo : lo + MOVE_BLOCK]
        if prob.stop is not None and prob.stop():
            break
        Zm = _moved(prob, Z, r_, a_)
        with np.errstate(all="ignore"):
            X = prob.covariances(Zm)
            phi = floor(X, prob.D)
            keep = np.flatnonzero(~(phi >= thr) & ~(phi > m))
            keep = keep[np.argsort(phi[keep], kind="stable")]  # NaN last
            first, rest = keep[:FLOOR_FIRST], keep[FLOOR_FIRST:]
            try:
                for rows in (first, None):
                    if rows is None:  # the rest, now that m is known
                        rows = rest[~(phi[rest] > m)]
                    if rows.size == 0:
                        continue
                    v = np.asarray(prob.f(X[rows], prob.D), dtype=np.float64)
                    v = np.where(np.isfinite(v), v, np.inf)
                    out[lo + rows] = v
                    m = min(m, float(v.min()))
            except np.linalg.LinAlgError:
                out[lo : lo + r_.size] = prob.approx_values(Zm)
                m = min(m, float(out[lo : lo + r_.size].min()))
    prob.moves += rem.size
    return out


def _below(best: float) -> float:
    """What a move's value must be below to improve on ``best`` in :func:`_local_search`; the
    swaps above it may be skipped (:func:`_screened_values`): the smallest value, and the first
    index of it, are the same whenever it is below."""
    return best - 1e-12 * abs(best)


def _local_search(prob: _Problem, inc: NDArray[np.bool_], val: float) -> NDArray[np.bool_]:
    """Best-improvement local search over removals, additions and 1-swaps (a strict relative
    improvement of 1e-12 required), at most MAX_PASSES passes.  A pass evaluates every removal
    and addition, and the swaps of every member with every non-member when there are at most
    FULL_SWAPS of them, else first the swaps among the SWAP_POOL best removals and additions and,
    if none improves, the others in blocks (members by their removal value) until one does,
    within FULL_SCAN_BUDGET such evaluations per call."""
    k0, K = len(prob.req), prob.K
    inc = inc.copy()
    budget = FULL_SCAN_BUDGET
    floor = _working_floor(prob)
    for _ in range(MAX_PASSES):
        Z = prob.base + prob.S[inc].sum(axis=0)
        ins, outs = np.flatnonzero(inc), np.flatnonzero(~inc)
        k = k0 + ins.size
        best_move: tuple[int, int] | None = None
        best_new = val

        def consider(rem: NDArray[np.intp], add: NDArray[np.intp], v: Mat) -> None:
            nonlocal best_move, best_new
            if v.size:
                i = int(np.argmin(v))
                if v[i] < _below(best_new):
                    best_new, best_move = float(v[i]), (int(rem[i]), int(add[i]))

        v_rem = v_add = None
        if ins.size:
            v_rem = _move_values(prob, Z, ins, np.full(ins.size, -1))
            if k0 or ins.size > 1:
                consider(ins, np.full(ins.size, -1), v_rem)
        if outs.size:
            v_add = _move_values(prob, Z, np.full(outs.size, -1), outs)
            if k < K:
                consider(np.full(outs.size, -1), outs, v_add)
        if v_rem is not None and v_add is not None:
            if ins.size * outs.size <= FULL_SWAPS:
                rem, add = np.repeat(ins, outs.size), np.tile(outs, ins.size)
                v = _screened_values(prob, Z, rem, add, _below(best_new), floor)
                consider(rem, add, v)
            else:
                r_order = ins[np.argsort(v_rem, kind="stable")]
                a_order = outs[np.argsort(v_add, kind="stable")]
                si, so = r_order[:SWAP_POOL], a_order[:SWAP_POOL]
                rem, add = np.repeat(si, so.size), np.tile(so, si.size)
                v = _screened_values(prob, Z, rem, add, _below(best_new), floor)
                consider(rem, add, v)
                rest = a_order[SWAP_POOL:]
                per = max(1, MOVE_BLOCK // max(outs.size, 1))
                lo = 0
                while best_move is None and lo < r_order.size and budget > 0:
                    rows = r_order[lo : lo + per]
                    lo += per
                    # the pool's own swaps are done: the rest of the non-members for the pool
                    # members, every non-member for the others
                    cols = [rest if i < SWAP_POOL else a_order for i in range(lo - per, lo)]
                    rem = np.concatenate(
                        [np.full(c.size, r) for r, c in zip(rows, cols, strict=False)]
                    )
                    add = np.concatenate(cols[: rows.size])
                    budget -= rem.size
                    v = _screened_values(prob, Z, rem, add, _below(best_new), floor)
                    consider(rem, add, v)
        if best_move is None:
            break
        rem_i, add_i = best_move
        if rem_i >= 0:
            inc[rem_i] = False
        if add_i >= 0:
            inc[add_i] = True
        val = best_new
    return inc


def _greedy_incs(prob: _Problem) -> list[NDArray[np.bool_]]:
    """Greedy's subsets as branching-order rows ``(m,)``: the plain heuristic's (:class:`_Plain`:
    forward selection while it improves, then first-improvement local search, on exact values),
    and the better of the forward path continued from there and the backward path, improved by
    :func:`_local_search` (empty: no free sensor can be added, only the required set or the zero
    sensor is possible).  Moves evaluated: ``prob.moves``."""
    if prob.m == 0 or prob.K <= len(prob.req):
        return []
    plain = _Plain(prob)
    p_inc, p_val = plain.forward()
    f_inc, f_val = _forward(prob, p_inc)
    b_inc, b_val = _backward(prob)
    inc, val = (b_inc, b_val) if b_val < f_val else (f_inc, f_val)
    out = []
    if math.isfinite(p_val) and (p_inc.any() or prob.req):
        out.append(plain.local_search(p_inc, p_val))
    if math.isfinite(val) and (inc.any() or prob.req):
        inc = _local_search(prob, inc, val)
        if not any(np.array_equal(inc, o) for o in out):
            out.append(inc)
    return out


def _backward_whole_limit(prob: _Problem) -> bool:
    """The registered metric asks for backward elimination and its local search until the whole
    time limit (``Metric.greedy_whole_limit``), not greedy's share."""
    entry = _entry(prob)
    return entry is not None and entry.greedy_whole_limit


def _greedy_incs_timed(
    prob: _Problem, deadline: Callable[[], bool] | None
) -> list[NDArray[np.bool_]]:
    """:func:`_greedy_incs` under a time limit (``prob.stop`` set: greedy's share of it; the
    whole limit ``deadline``): the same paths, in an order that makes a short limit end on a
    good subset, and the plain heuristic (the floor of the guarantee) run once, until the whole
    limit.  (1) The plain forward selection (1-5 ms at N = 100; within 0.3 % of the root's
    bound for kl, logdet and frobenius on the bench problems); (2) backward elimination and its
    local search, within the share (the best subset of the norms, svd and abs_trace on the
    bench problems: within 0.02-1 % of the root's bound where the plain path is 2-60 % off;
    about 15 ms at N = 100); (3) the plain local search from (1), until the whole limit (1-20
    ms at N = 100; svd up to 0.2 s); (4) the forward path continued from (1)'s end and its
    local search, within the share, kept only while it beats (2) (8-30 ms at N = 100, rarely
    the best).  Every path ends with what it has once its time is up (working values
    ``+inf``).  A metric whose entry sets ``Metric.greedy_whole_limit`` (svd) gives (2) the
    whole limit instead of the share: its tree does not close the gap (its bound is loose), so
    the certificate within the limit is the incumbent's, and backward elimination cut at the
    share (half of a 40 ms limit on a loaded machine: 7-10 ms of CPU, against the 11 ms of
    svd's backward elimination at N = 100) leaves a poor one (README, *svd within the limit*)."""
    share = prob.stop
    out: list[NDArray[np.bool_]] = []

    def add(inc: NDArray[np.bool_]) -> None:
        if not any(np.array_equal(inc, o) for o in out):
            out.append(inc)

    prob.stop = deadline
    plain = _Plain(prob)
    p_inc, p_val = plain.forward()
    prob.stop = deadline if _backward_whole_limit(prob) else share
    b_inc, b_val = _backward(prob, reuse=True)
    if math.isfinite(b_val) and (b_inc.any() or prob.req):
        add(_local_search(prob, b_inc, b_val))
    prob.stop = deadline
    if math.isfinite(p_val) and (p_inc.any() or prob.req):
        add(plain.local_search(p_inc, p_val))
    prob.stop = share
    f_inc, f_val = _forward(prob, p_inc)
    if math.isfinite(f_val) and f_val < b_val and (f_inc.any() or prob.req):
        add(_local_search(prob, f_inc, f_val))
    return out


def _greedy_start(
    prob: _Problem, deadline: Callable[[], bool] | None = None
) -> tuple[NDArray[np.bool_], Mat]:
    """Greedy's subset, the required set (when not empty) and the zero sensor's singleton (when
    it is a choice) as sensor rows ``(c, N)``, with their exact values: every feasible subset the
    tree does not record itself.  At least one row (the first free sensor alone if greedy finds
    nothing finite).  ``deadline`` (a time limit, with ``prob.stop`` greedy's share of it): the
    paths of :func:`_greedy_incs_timed`, the plain heuristic (:class:`_Plain`, the floor) until
    the deadline, the others within the share."""
    if deadline is not None and prob.stop is not None:
        incs = _greedy_incs_timed(prob, deadline) if prob.m and prob.K > len(prob.req) else []
    else:
        incs = _greedy_incs(prob)
    rows = []
    for inc in incs:
        if inc.any() or not prob.req:
            rows.append(prob.masks(inc[None])[0])
    if prob.req:
        rows.append(prob.masks(np.zeros((1, prob.m), dtype=bool))[0])
    if prob.zero is not None:
        z = np.zeros(prob.N, dtype=bool)
        z[prob.zero] = True
        rows.append(z)
    rows = [r for r in rows if r.any()]
    if not rows:
        one = np.zeros(prob.N, dtype=bool)
        one[prob.free[0]] = True
        rows.append(one)
    masks = np.array(rows)
    return masks, prob.exact(masks)


def allocate_greedy(
    P_pred: Mat,
    gains: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    constraints: Constraints = NO_CONSTRAINTS,
    tie_rtol: float = 1e-9,
) -> SearchResult:
    """The plain forward greedy + first-improvement 1-swaps on exact values, and forward /
    backward greedy + best-improvement local search (removals, additions, 1-swaps) on working
    values (module docstring); the better subset found (the tie rule), its exact value and ``P``
    (the reference's arithmetic), and the root interval bound as the certified lower bound (for a
    metric without an interval bound: ``0`` if registered, ``-inf`` for a user's plain function).
    Never worse than the plain heuristic beyond the tie rule's tolerance (module docstring).

    Cost: ``O(N)`` batched evaluations per forward step and ``O(|D| · N)`` per local-search pass,
    each one ``r x r`` inverse and one metric evaluation of an ``n x n`` matrix; exact
    evaluations (a Cholesky inverse each) one per step of the plain heuristic, plus the moves
    within the margin of a decision."""
    prob = _Problem(P_pred, gains, P_d, metric, constraints, tie_rtol)
    try:
        masks, values = _greedy_start(prob)
        k = tie_select(values, masks, prob.tie_rtol)
        mask, value = masks[k], float(values[k])
        P = prob.exact_covariances(mask[None])[0]
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    lb = min(prob.root_bound(), value)
    return SearchResult(
        _subset(mask),
        value,
        P,
        lb,
        _gap(value, lb),
        prob.moves,
        prob.n_evaluated,
        False,
        4,
        STATUS[4],
    )
