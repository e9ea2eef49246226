"""Greedy allocation (:func:`allocate_greedy`), also the start of the branch and bound
(:mod:`covnet.core.allocation.search`).

**Greedy** (:func:`allocate_greedy`): the better of forward selection (add the sensor giving the
smallest value, while the bound says a superset can still win) and backward elimination (from
every sensor), then best-improvement local search over removals, additions and 1-swaps, on
reduced-form values; and, as a second start, the plain heuristic (forward selection while a
sensor improves, then first-improvement additions, removals and 1-swaps, sensors by index), so
that greedy is never worse than it; the better final subset (the tie rule on exact values) is
the result, and the branch and bound's first incumbent.  Its certified lower bound is the
bound of the root ``[P(required ∪ all allowed), P(required)]`` (with the relaxation where it
applies).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation._fast import tie_select
from covnet.core.allocation.exact import Constraints, _spd_error
from covnet.core.allocation.search_problem import (
    MOVE_BLOCK,
    NO_CONSTRAINTS,
    STATUS,
    SearchResult,
    _gap,
    _Problem,
    _subset,
)
from covnet.core.gaussian import Mat
from covnet.core.metrics import MetricFn

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


def _improves(v: float, ref: float) -> bool:
    """``v`` is better than ``ref`` by a relative ``IMPROVE`` (anything finite beats ``inf``)."""
    return v < ref - IMPROVE * abs(ref) if math.isfinite(ref) else math.isfinite(v)


def _forward(prob: _Problem) -> tuple[NDArray[np.bool_], float, NDArray[np.bool_], float]:
    """Forward selection from the required set: add the sensor giving the smallest value (ties:
    the lowest sensor index); stop at the budget, or when the interval bound of (current set, all
    the rest undecided) exceeds the best value on the path (no superset can do better).  Returns
    the path's best, and the *plain* forward selection's subset and value: the path up to the
    first step that does not improve (by a relative ``IMPROVE``), where the plain heuristic stops
    (the bound never stops the path before: a step that improves is a superset below the best)."""
    m, K, k0 = prob.m, prob.K, len(prob.req)
    inc = np.zeros(m, dtype=bool)
    Z = prob.base.copy()
    best_val = float(prob.approx_values(Z[None])[0]) if k0 else math.inf
    best_inc = inc.copy()
    plain: tuple[NDArray[np.bool_], float] | None = None
    by_id = np.argsort(np.asarray(prob.free, dtype=np.int64), kind="stable")
    k = k0
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
        if plain is None and not _improves(float(v[i]), best_val):
            plain = (inc.copy(), best_val)
        inc[rest[i]] = True
        Z = prob.base + prob.S[inc].sum(axis=0)
        k += 1
        if v[i] < best_val:
            best_val, best_inc = float(v[i]), inc.copy()
    if plain is None:  # every step improved: the path's end
        plain = (best_inc.copy(), best_val)
    return best_inc, best_val, plain[0], plain[1]


def _backward(prob: _Problem) -> tuple[NDArray[np.bool_], float]:
    """Backward elimination from every free sensor: remove the sensor whose removal gives the
    smallest value (above BACKWARD_ONE sensors, the ``⌈|D| / BACKWARD_ONE⌉`` best removals at
    once, so a pass costs ``O(N · BACKWARD_ONE)`` evaluations); values count once within the
    budget.  Returns the path's best."""
    m, K, k0 = prob.m, prob.K, len(prob.req)
    inc = np.ones(m, dtype=bool)
    best_inc, best_val = inc.copy(), math.inf
    while True:
        k = k0 + int(inc.sum())
        if k <= K:
            v0 = float(prob.approx_values((prob.base + prob.S[inc].sum(axis=0))[None])[0])
            if v0 < best_val:
                best_val, best_inc = v0, inc.copy()
        ins = np.flatnonzero(inc)
        if ins.size == 0 or (ins.size == 1 and not k0):
            break
        Z = prob.base + prob.S[inc].sum(axis=0)
        v = prob.approx_values(Z[None] - prob.S[ins])
        prob.moves += ins.size
        step = max(1, -(-ins.size // BACKWARD_ONE))
        if k - K > step:  # still above the budget: remove faster, values do not count yet
            step = max(step, (k - K) // 2)
        step = min(step, ins.size - (0 if k0 else 1))
        drop = ins[np.argsort(v, kind="stable")[:step]]
        inc[drop] = False
    return best_inc, best_val


def _move_values(prob: _Problem, Z: Mat, rem: NDArray[np.intp], add: NDArray[np.intp]) -> Mat:
    """Working values of the moves ``(rem[i], add[i])`` (``-1``: none) from information ``Z``."""
    out = np.empty(rem.size)
    for lo in range(0, rem.size, MOVE_BLOCK):
        r_, a_ = rem[lo : lo + MOVE_BLOCK], add[lo : lo + MOVE_BLOCK]
        Zm = np.broadcast_to(Z, (r_.size, Z.size)).copy()
        Zm[r_ >= 0] -= prob.S[r_[r_ >= 0]]
        Zm[a_ >= 0] += prob.S[a_[a_ >= 0]]
        out[lo : lo + r_.size] = prob.approx_values(Zm)
    prob.moves += rem.size
    return out


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
                if v[i] < best_new - 1e-12 * abs(best_new):
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
                consider(rem, add, _move_values(prob, Z, rem, add))
            else:
                r_order = ins[np.argsort(v_rem, kind="stable")]
                a_order = outs[np.argsort(v_add, kind="stable")]
                si, so = r_order[:SWAP_POOL], a_order[:SWAP_POOL]
                rem, add = np.repeat(si, so.size), np.tile(so, si.size)
                consider(rem, add, _move_values(prob, Z, rem, add))
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
                    consider(rem, add, _move_values(prob, Z, rem, add))
        if best_move is None:
            break
        rem_i, add_i = best_move
        if rem_i >= 0:
            inc[rem_i] = False
        if add_i >= 0:
            inc[add_i] = True
        val = best_new
    return inc


def _first_improvement(prob: _Problem, inc: NDArray[np.bool_], val: float) -> NDArray[np.bool_]:
    """The plain local search: first-improvement over, in this order, additions, removals and
    1-swaps (out ascending, then in ascending), sensors by index; the first move that improves
    by a relative ``IMPROVE`` is taken, until none does (or PLAIN_BUDGET moves were evaluated:
    far beyond what 64 sensors need).  Moves are evaluated in blocks of MOVE_BLOCK in that order,
    stopping at the first block with an improving move."""
    k0, K = len(prob.req), prob.K
    by_id = np.argsort(np.asarray(prob.free, dtype=np.int64), kind="stable")
    inc = inc.copy()
    budget = PLAIN_BUDGET
    while budget > 0:
        Z = prob.base + prob.S[inc].sum(axis=0)
        ins, outs = by_id[inc[by_id]], by_id[~inc[by_id]]
        none_o, none_i = np.full(outs.size, -1), np.full(ins.size, -1)
        parts: list[tuple[NDArray[np.intp], NDArray[np.intp]]] = []
        if k0 + ins.size < K:
            parts.append((none_o, outs))
        if k0 or ins.size > 1:
            parts.append((ins, none_i))
        parts.append((np.repeat(ins, outs.size), np.tile(outs, ins.size)))
        rem = np.concatenate([p[0] for p in parts])
        add = np.concatenate([p[1] for p in parts])
        move: int | None = None
        for lo in range(0, rem.size, MOVE_BLOCK):
            v = _move_values(prob, Z, rem[lo : lo + MOVE_BLOCK], add[lo : lo + MOVE_BLOCK])
            budget -= v.size
            ok = np.flatnonzero(v < val - IMPROVE * abs(val))
            if ok.size:
                move, val = lo + int(ok[0]), float(v[ok[0]])
                break
        if move is None:
            break
        if rem[move] >= 0:
            inc[rem[move]] = False
        if add[move] >= 0:
            inc[add[move]] = True
    return inc


def _greedy_incs(prob: _Problem) -> list[NDArray[np.bool_]]:
    """Greedy's subsets as branching-order rows ``(m,)``: the better of the forward and the
    backward paths improved by :func:`_local_search`, and the plain heuristic's (forward
    selection while it improves, then :func:`_first_improvement`), so that greedy is never worse
    than the plain heuristic (empty: no free sensor can be added, only the required set or the
    zero sensor is possible).  Moves evaluated: ``prob.moves``."""
    if prob.m == 0 or prob.K <= len(prob.req):
        return []
    f_inc, f_val, p_inc, p_val = _forward(prob)
    b_inc, b_val = _backward(prob)
    inc, val = (b_inc, b_val) if b_val < f_val else (f_inc, f_val)
    out = []
    if math.isfinite(val) and (inc.any() or prob.req):
        out.append(_local_search(prob, inc, val))
    if math.isfinite(p_val) and (p_inc.any() or prob.req):
        p_inc = _first_improvement(prob, p_inc, p_val)
        if not any(np.array_equal(p_inc, o) for o in out):
            out.append(p_inc)
    return out


def _greedy_start(
    prob: _Problem, deadline: Callable[[], bool] | None = None
) -> tuple[NDArray[np.bool_], Mat]:
    """Greedy's subset, the required set (when not empty) and the zero sensor's singleton (when
    it is a choice) as sensor rows ``(c, N)``, with their exact values: every feasible subset the
    tree does not record itself.  At least one row (the first free sensor alone if greedy finds
    nothing finite).  ``deadline`` (a time limit): when ``prob.stop`` cut greedy short, forward
    selection again until the deadline (the plain heuristic's first phase, as a floor)."""
    incs = _greedy_incs(prob)
    if deadline is not None and prob.stop is not None and prob.stop():
        prob.stop = deadline
        if prob.m and prob.K > len(prob.req):
            incs.append(_forward(prob)[0])
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
    """Forward greedy + best-improvement local search (removals, additions, 1-swaps), and the
    plain forward greedy + first-improvement 1-swaps (module docstring); the better subset
    found, its exact value and ``P`` (the reference's arithmetic), and the root interval bound as
    the certified lower bound (for a metric without an interval bound: ``0`` if registered,
    ``-inf`` for a user's plain function).

    Cost: ``O(N)`` batched evaluations per forward step and ``O(|D| · N)`` per local-search pass,
    each one ``r x r`` inverse and one metric evaluation of an ``n x n`` matrix."""
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
