"""Many targets at scale: greedy and bounded searches of the assignment problem of
:mod:`covnet.core.allocation.assignment`, with a certified lower bound and gap.

The problem (that module's docstring): each sensor ``j`` takes one *column* ``c`` (a target
``t < T`` or a search cell ``T + c``, :class:`~covnet.core.allocation.assignment.CellTerms`) or
``OFF``; a column's term depends only on its set ``S_c``::

    F(a) = Σ_c w_c g_c(S_c),   g_t(S) = f(P_t(S), P_d,t),   g_{T+c}(S) = λ u_c Π_{j∈S} miss_jc,

(``w = 1`` for cells) under coverage, exclusions, required sensors, the budget ``max_active``
and the per-target caps.  Exact search enumerates ``(T+C+1)^N`` assignments (or ``2^N``-entry
tables); here:

**Greedy** (:func:`allocate_assignments_greedy`).  Working values from the reduced
information form of each target (:class:`covnet.core.allocation.search_problem._Problem`:
``Z_t = C_t⁻¹ + Σ_{j∈S} S_jt``, ``P = P∞ + K Z⁻¹ Kᵀ``).  *Forward*: the required sensors first
(each time the (sensor, column) pair that raises ``F`` least), then the pair that lowers ``F``
most, while one does (at least one sensor on).  *Local search* (best improvement, a strict
relative improvement ``IMPROVE``): every *move* (one sensor to another column or off: two
columns change, ``ΔF = Δ_rem + Δ_add``) and every *1-swap* (two sensors on different columns,
or one on and one off, exchange columns: ``ΔF = M[j, k] + M[k, j]`` with ``M[j, k]`` the change
of ``j``'s column when ``k`` replaces ``j``); the tables of the columns a step changes are
recomputed, the others kept.  This is the plain forward greedy with 1-swaps.  *Set moves*
(:func:`_enum_moves`, once the lower bound's enumeration exists): a target's whole set replaced
by one of its best enumerated sets (up to ``d`` sensors, each off or already on it), the best
strict improvement while one exists, then the local search again: a local optimum of moves and
1-swaps can miss a better pair that shares no sensor with the target's set.  Both searches
only accept improvements from the plain greedy's local optimum, so neither is worse.  The final
assignment is evaluated exactly (the reference's arithmetic).

**Lower bound** (Lagrangian relaxation of "each sensor on at most one column", over counts).
For every column ``c`` and size ``k`` a bound ``h_c(k) <= min { w_c g_c(S) : S ⊆ F_c, |S| = k }``
(``F_c`` the sensors allowed on ``c``), the *count bound*:

- a target: with ``Q = C⁻¹ + Σ_{j∈F_c} S_j`` (positive definite) and ``μ_j^max``, ``μ_j^min``
  the extreme eigenvalues of ``Q^{-1/2} S_j Q^{-1/2}`` (``S_j ⪰ 0``), every ``|S| = k`` has
  ``β_k Q ⪯ Σ_{j∈S} S_j ⪯ α_k Q`` with ``α_k`` the sum of the ``k`` largest ``μ^max`` and
  ``β_k`` of the ``k`` smallest ``μ^min`` (``S_j ⪯ μ_j^max Q``; a sum of ``k`` of them is at most
  the ``k`` largest); so ``Z(S) ∈ [C⁻¹ + β_k Q, C⁻¹ + α_k Q]`` and, inversion being antitone,
  ``P(S)`` lies in the Loewner interval ``[P(C⁻¹ + α_k Q), P(C⁻¹ + β_k Q)]`` and also above
  ``P(F_c)``: the interval bounds of :mod:`covnet.core.allocation.interval_bounds` (and the
  reduced relaxation where it applies) bound ``g_t(S)`` from below (``α``, ``β`` widened by a
  relative ``1e-9`` against the eigenvalues' rounding);
- a cell: ``λ u_c`` times the product of the ``k`` smallest ``miss_jc`` (deflated by a relative
  ``4 (k + 2) eps``).

The count interval is wide when the sensors differ (a bearing-only sensor has ``μ^min = 0``,
so ``β_k`` is the prior's), so each target column also has an *enumeration bound* of depth
``d_c`` (:func:`_depths`: the depths raised while at most ``ENUM_BUDGET`` sets are enumerated in
all; ``d_c <= ENUM_DEPTH``): every ``S ⊆ F_c`` with ``|S| <= d_c`` gets the certified bound
``e(S)`` of ``w_c g_c(S)`` (the degenerate interval ``[Z(S), Z(S)]``), and every ``d_c``-set
``S0`` the bound ``u(S0)`` of the interval ``[Z(S0), Z(F_c)]``.  **Proof**: a set ``S`` with
``|S| > d_c`` contains some ``d_c``-set ``S0``, and ``Z(S0) ⪯ Z(S) ⪯ Z(F_c)`` (the ``S_j`` are
PSD), so ``w_c g_c(S) >= u(S0)``; with prices, ``π(S) >= π(S0) + (the k - d_c smallest prices
on F_c)`` (the other members are ``k - d_c`` distinct sensors of ``F_c``, prices ``>= 0``).  So
for every ``k``::

    min_{|S|=k} w_c g_c(S) + π(S) >= b_c(k, π) = max( h_c(k) + π_c(k),
        min_{|S|=k} e(S) + π(S)                  (k <= d_c),
        min_{S0} u(S0) + π(S0) + π_c(k - d_c)     (k > d_c) ),

``π_c(k)`` the sum of the ``k`` smallest prices on ``F_c``.  The count and enumeration bounds
are raised, lazily (the smallest first, at most ``REFINE_ROWS`` a column, within the time
limit), by the reduced relaxation where the metric has one (kl, frobenius, logdet); the norm
metrics' barrier dual bound is too slow for these decisions and is not used here.

*Single-target floors* (the bounded search, with a time limit, while at least
``FLOOR_MIN_S`` is left: :func:`_floors`, the targets furthest below their incumbent first): the
single-target bounded search (:func:`covnet.core.allocation.search.allocate_bnb`) over the
target's allowed sensors ``F_c`` (no budget, no required sensor) returns a certified ``ℓ_c <=
min {g_c(S) : ∅ ≠ S ⊆ F_c}``.  **Proof** of ``b_c(k, π) >= w_c ℓ_c + π_c(k)`` for ``k >= 1``:
a ``k``-set of ``F_c`` is one of that problem's feasible subsets, so ``w_c g_c(S) >= w_c ℓ_c``
(``w_c > 0``; the same per-target arithmetic), and ``π(S) >= π_c(k)`` as above.  Its branching
over the target's own sensors bounds the sets of three or more members far better than the
intervals ``[Z(S0), Z(F_c)]`` (spectral at N = 64, T = 8: the light targets' bounds rise by
20-50 %), but it does not see the prices: the coupling between targets is still only the
count limit's and the dual steps'.

With prices ``π_j >= 0`` and ``n_c`` the most sensors column ``c`` can take, the dual function::

    L(π) = min { Σ_c b_c(k_c, π) : 0 <= k_c <= n_c, Σ_c k_c <= K' } - Σ_j π_j,

``K'`` the budget (or the sensors that can be on), is a dynamic programme over the columns
(``O((T + C) K'^2)``; when ``Σ_c n_c <= K'`` the count limit cannot bind and the columns
separate: each takes its least ``b_c``).  **Proof that ``L(π) <= F*``**: take any feasible
assignment with sets ``S_c``, ``k_c = |S_c|``; then ``Σ k_c <= K'`` and ``k_c <= n_c``; since
the sets are disjoint and ``π >= 0``, ``Σ_c π(S_c) <= Σ_j π_j``, so ``F = Σ_c w_c g_c(S_c) >=
Σ_c [w_c g_c(S_c) + π(S_c)] - Σ_j π_j >= Σ_c b_c(k_c, π) - Σ_j π_j >= L(π)``.  The required
sensors and "at least one on" are dropped (a relaxation).  ``π = 0`` treats every target as if
it could have any of its feasible sensors (only their number limited); subgradient steps
(``g_j = (columns using j in the minimiser) - 1``, the minimiser's set the enumerated one where
that bound is the larger, else the ``k`` cheapest; Polyak step towards the incumbent) raise it
where targets compete for the same sensors (on the bench's problems they gain little: the
per-target bounds are the weak part).  The reported bound is the best ``L`` seen, less a
rounding allowance, at most the value.

*Kept levels* (the timed plan below): a column enumerated to depth 1 first and deepened later
keeps its depth-1 superset bounds ``u1(j)`` (of the intervals ``[Z({j}), Z(F_c)]``, refined)
beside the deeper ones: for every ``k > 1``, ``b_c(k, π) >= min_j [u1(j) + π_j] + π_c(k - 1)``
as well (**proof**: the enumeration bound's with ``d_c = 1``: a set of ``k > 1`` members
contains each of its members ``j``, ``Z({j}) ⪯ Z(S) ⪯ Z(F_c)``, and its other ``k - 1``
members cost at least ``π_c(k - 1)``); the column's cost is the largest of its bounds.  At
N = 64 a depth-1 superset bound refined by the relaxation is often above the unrefined
intervals of the pairs (which only the ``REFINE_ROWS`` smallest of about 1 800 are refined).

*The dual steps' cost* (round mt8): a step evaluates every column's bounds at the new
prices and the minimiser's members; the enumerated sets' prices are sums of their members'
columns (:meth:`_Enum._psum`, the same roundings as the fancy-indexed sums), the minimisers'
argmins are kept from the bound for the subgradient (the same prices), the dynamic programme's
index grids are built once: 0.42 ms a step instead of 1.25 at N = 64, T = 8 (svd), the
same bits step for step, so with a clock about 2.5 times the steps in the same time.  The
local search's rows ``R``, ``M`` are refreshed once before a pass (:meth:`_State.fresh`), not
at every put.

**Bounded** (:func:`allocate_assignments_bounded`): greedy, then dual steps until the relative
gap is at most ``rel_gap`` (or the node or time limit); a *node* is one dual step.

*The timed plan* (with ``time_limit_s`` only; with ``node_limit`` alone the order above, bit
for bit): (1) the count bound and depth 1 everywhere, the count bound's rows and the depth-1
superset bounds' rows refined in **one** call of the relaxation a column
(:meth:`_Rows.together`: its cost is mostly per call, 1.3-1.5 ms at 1 to 60 rows, kl and
frobenius at N = 64, so this halves the refinement's cost; each row's result is a certified
bound of its own interval whatever the other rows of the call); (2) for the metrics of
``Metric.floors_first`` (kl, frobenius, logdet, trace_diff: a short single-target search closes a
column's slack there; for the others short floors left the bound weak and took the pairs' and
dual steps' time, measured), a first round of single-target floors (the targets furthest
below their incumbent first, each at most ``TIMED_FLOOR_SLICE`` of the limit, the round at most
``TIMED_FLOOR_SHARE`` of the time left: at N = 64, T = 8 a kl floor closes most of its column's
slack in about 10 ms of CPU, where the columns' pair enumerations cost 20-30 ms); (3) the
columns deepened, the largest slack left first (floors in), keeping their depth-1 superset
bounds; (4) the set moves on what is enumerated, the local search, then (round br16) the
*ejection chains* (:func:`_chain_moves`: a sensor to another target, an idle sensor in its
place, the local search again); (5) a second round of floors for the targets without one, as
before the plan (an equal share of the time left each, none started without ``FLOOR_MIN_S``:
many short floors bound more than a few long ones where the single-target bound is weak,
spectral at N = 256, and at N = 64 the time under ``FLOOR_MIN_S`` is better spent on dual
steps, svd); (6) dual steps, and among them (round mt12; the metrics without
``floors_first`` whose single-target problem has a refinement: spectral, the norms,
abs_trace), once the steps stall or half their time is spent, the *root floors* at the best
prices so far (:func:`_root_floors`: each target's single-target root bound, the largest
relative slack first, 12 barrier iterations, about 3.6 ms of CPU a target at N = 64 against
at least ``FLOOR_MIN_S`` for a single-target search), then the steps go on.  With root floors
(round mt13) step (5) comes after (6): the second round of floors
(every target column, floored by its root or not) in the time the stalled steps leave, then
the steps again from their best prices (any ``π >= 0`` gives a bound); at N = 64, T = 8 the
steps and roots take the time the floors took (spectral at 90 ms of CPU: 1.3 % -> 1.04 % of
the distance from doing nothing), at N = 256 the steps stall after about 300 ms and the
floors take the rest.  Round mt15: after the root floors, at the same prices, the *vertex
rows* (:func:`_vertex_rows`; the metrics whose dual bound has a vertex bound: one_norm,
inf_norm, abs_trace): the columns still holding a share of the slack get their count rows,
superset rows and kept levels' rows raised by the dual bound's vertex bound (a few dual points
in closed form, :meth:`_Rows.vertex`), the least price-adjusted first, one call a column;
and the induced norms' roots run 20 barrier iterations (``ROOT_ITERS_OF``).  At N = 64, T = 8
the first closes the heavy targets whose best set has one sensor (bounded at three by the
pairs' superset intervals), the second the light targets whose 12-iteration root was far
from its end (one_norm at 90 ms of CPU: 2.15 % -> 0.65 % of the distance from doing
nothing).  Also round mt15, the floor rounds (:func:`_floors`): a floor cut by its time
limit is searched again by the second round, a column with little of the slack takes none
(the ``floors_first`` metrics), and the first round leaves to the second a floor whose share
would be below the last one's time (trace_diff: 3.0 % -> 1.41 %).  Round at16, the *chain
rows* (the metrics of ``Metric.chain_rows``: abs_trace, trace_diff): after step (1) each
target column's sensors are ordered by their depth-1 superset bound (the largest first), and
the sets are split by their first member in that order: the sets whose first member is ``j``
lie in ``[Z({j}), Z({j} ∪ later)]``, a narrower interval than ``[Z({j}), Z(F_c)]`` (the late
members' intervals hold only the weak sensors), so row ``j`` becomes that interval's bound
(:meth:`_Dual.chain`); the deepened rows likewise by their first ``d`` members
(:meth:`_Dual.chain2`), and among the dual steps, after the root floors, the deepest rows are
expanded by their next member (:meth:`_Dual.expand`, :func:`_expand_rows`).  Each row then
bounds every set whose first members it is, which is all the dual's use of a superset row
needs (the proofs are in those methods).  At N = 64, T = 8 the heavy targets (best sets of one
sensor) are closed at about 0.5 ms a column, where the single-target search took 70-120 ms:
abs_trace at 90 ms of CPU 10.3 % -> 1.11 % of the distance from doing nothing (trace_diff,
whose plan has no root floors and so no expansion, 1.41 % -> 1.20 %).  Every piece is a bound
of its own, so whatever the clock cuts, ``L(π) <= F*``.

The incumbent (round ki16): for spectral, abs_trace and trace_diff the bound settles early (runs
of seconds leave the same median gap), and their incumbents were the larger part of the gap: an
iterated local search from the 90 ms run's assignment (5 s of kicks) lowered their median gaps
at N = 64, T = 8 from 1.05 % to 0.49 %, 1.11 % to 0.15 % and 0.41 % to 0.11 % with the same
bound, by assignments that keep more sensors on, spread over several targets (three to nine
sensors a step; no pair of additions to one target improves).  So for the metrics of
``Metric.kicks`` the timed plan gives the *kicks* (:func:`_kicks`: a few random sensors
reassigned, the local search and the chains to their ends, kept only if ``F`` falls) a share
``KICK_SHARE`` of the time left after the ejection chains (90 ms of CPU, over 8 seeds of the
kicks' generator: abs_trace 1.11 % -> 0.48-0.92 %, trace_diff 0.40 % -> 0.23-0.40 %, spectral
1.03 % -> 0.89-1.12 %, within the seeds' spread); the other metrics' bounds need
the time (one_norm 0.65 % -> 1.13 % with them), so they keep their plan bit for bit.  The kicks'
generator has a fixed seed: the same problem and clock give the same decision.

*Plans on a slower machine* (round mt20): the set-up, the enumeration, the set moves and the
chains cost a fixed amount of CPU, so on a slower machine they take more of the limit, and
shares of what is left then leave the bound too little: on a 2-core Intel Xeon host, N = 64,
T = 8, 90 ms of CPU, the chains ended at 48-60 ms and spectral's median gap was 2.9 % where
130 ms gave 1.1 %.  So the kicks start only while ``KICK_MIN_LEFT`` of the limit is left,
and the root floors start at the latest when ``ROOT_START_SHARE`` of it is left (each root
costs the same at any limit).  Where the limit is generous for the machine neither rule
binds, and the plan is the one above.

When the gap is still open and the allowed sensors are at most ``EXACT_FALLBACK`` (the exact
tables are then small), the exact allocator decides: status 0, the reference's assignment.

**Gaps.**  ``gap = (value - L) / max(|value|, tiny)``; and, relative to the distance from doing
nothing, ``gap_nothing = (value - L) / max(F(nothing) - value, tiny)``, with ``F(nothing)`` every
sensor off: as ``L <= F* <= value``, ``(value - F*) / (F(nothing) - F*) <= gap_nothing``, a
certified bound of the suboptimality relative to what the sensors can gain (meaningful when
``F*`` is near 0, where the first gap says nothing).

**Clocks**: only with ``time_limit_s`` (``time.perf_counter`` or ``clock``); it is checked
between the local-search passes after the set moves, the deeper enumerations, the refinement
batches, the floors and the dual steps.  What always runs to its end: the columns' set-up, the
forward greedy and its first local search (moves and 1-swaps to their local optimum, so that
even out of time the result is never worse than the plain forward greedy with 1-swaps: cut
short under a heavy load, it was), the depth-1 enumeration (``n_c`` sets a target), the exact
evaluation (``T`` solves) and a started floor's set-up (hence ``FLOOR_MARGIN``), so a decision
can pass a limit shorter than those (measured 35-60 ms at N = 64, T = 8, the machine shared).
``node_limit`` is the deterministic alternative (no floors: they are timed).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation.assignment import (
    MAX_SENSORS,
    NO_CONSTRAINTS,
    OFF,
    CellTerms,
    MultiConstraints,
    _Inputs,
    allocate_assignments,
)
from covnet.core.allocation.exact import Constraints, InfeasibleAllocation, _spd_error
from covnet.core.allocation.search import allocate_bnb
from covnet.core.allocation.search_problem import _Problem
from covnet.core.gaussian import Mat
from covnet.core.metrics import MetricFn

__all__ = [
    "AssignmentSearch",
    "allocate_assignments_bounded",
    "allocate_assignments_greedy",
]

TINY = float(np.finfo(np.float64).tiny)
EPS = float(np.finfo(np.float64).eps)
#: a local-search step must improve ``F`` by this much, relatively
IMPROVE = 1e-12
#: local search: at most this many passes per sensor
PASSES_PER_SENSOR = 4
#: dual steps of greedy's bound (bounded: until its gap, node or time limit)
GREEDY_DUAL_STEPS = 4
#: the bounded search's dual steps when no limit is given
DUAL_STEPS = 400
#: bounded: with the gap still open, the exact allocator decides up to this many allowed sensors
EXACT_FALLBACK = 12
#: ... and, with search cells, while ``(T + C + 1)^m`` (m allowed sensors) is at most this: cells
#: of equal mass tie exactly, and the exact allocator enumerates every tie
EXACT_FALLBACK_CELLS = 4**8
#: the enumeration bound: at most this many sets (of every target column) in all
ENUM_BUDGET = 20_000
#: ... of at most this many members
ENUM_DEPTH = 3
#: per column, at most this many intervals of the bound are refined (lazily, the smallest
#: first) by the relaxation or the dual bound of the metric
REFINE_ROWS = 64
#: ... this many at a time
REFINE_BATCH = 64
#: set moves: per target and size, this many of the best enumerated sets are tried
ENUM_MOVES = 8
#: the single-target floors (bounded, with a time limit): each target's search stops at this
#: relative gap, or at its equal share of the time left (the targets not yet bounded)
FLOOR_GAP = 0.002
#: ... and one starts only with at least this many seconds left, and this multiple of what the
#: previous one took (the single-target search's set-up is not timed: at N = 256 a 30 ms limit
#: took 26-154 ms)
FLOOR_MIN_S = 0.03
FLOOR_MARGIN = 1.5
#: ... and (round mt15; the metrics of ``Metric.floors_first``) only on the columns whose slack
#: is at least this share of the summed slack (trace_diff at N = 64, T = 8: a column at its
#: single-target optimum took a floor's time from one that needed it; svd, whose only round is
#: the second, lost 0.03-0.07 points on one problem with it and keeps every column)
FLOOR_PART = 0.05
#: the timed plan (bounded with a time limit, :func:`_search`): the first round of floors
#: takes at most this share of the time left after the depth-1 bounds (the rest: deepening, set
#: moves, then a second round of floors); each floor at most ``TIMED_FLOOR_SLICE`` of the
#: decision's limit, and one starts only with ``TIMED_FLOOR_MIN`` of it left (12 ms and 8 ms at
#: the bench's 90 ms, N = 64; a kl floor closes most of its column's slack in about 10 ms there)
TIMED_FLOOR_SHARE = 0.3
TIMED_FLOOR_SLICE = 0.13
TIMED_FLOOR_MIN = 0.09
#: the root floors (:func:`_root_floors`, round mt12): one starts only with this share of the
#: decision's limit left, at most ``ROOT_FLOOR_MIN_CAP`` seconds (9 ms at the bench's 90 ms and
#: at its 0.9 s, N = 256: a root's cost hardly grows with N)
ROOT_FLOOR_MIN = 0.1
ROOT_FLOOR_MIN_CAP = 0.009
#: ... each root's barrier (the dual bound) stops after this many iterations (its bound so
#: far: at 12 of the 30 within 0.05 % of the full run's on spectral, 0.5-3 % on one_norm, at
#: 3.6 ms of CPU instead of 8, N = 64)
ROOT_ITERS = 12
#: ... except for these metrics (round mt15: for the induced norms, at 12 the barrier is still
#: far from its end on some light targets, N = 64, one_norm's problem 2: 11.0 and 11.7 at 12
#: iterations, 15.6 at 20, 15.7-15.8 at 30, the targets' best sets 15.97 and 16.06; about 4 ms
#: of CPU a target at 20; abs_trace and spectral gained nothing beyond the noise from 20)
ROOT_ITERS_OF: dict[str, int] = {"one_norm": 20, "inf_norm": 20}
#: ... only on the columns whose slack is above this share of their incumbent's value, and
#: which hold at least ``ROOT_FLOOR_PART`` of the summed slack
ROOT_FLOOR_SLACK = 1e-3
ROOT_FLOOR_PART = 0.05
#: ... among the dual steps, at the best prices so far, once the steps stall (``θ <=
#: MID_THETA``) or ``1 - ROOT_FLOOR_AFTER`` of the time left for the steps is spent
ROOT_FLOOR_AFTER = 0.5
MID_THETA = 0.125
#: the vertex rows (:func:`_vertex_rows`, round mt15): at most this many rows of a column (its
#: count rows, its superset rows, each kept level's) are raised ...
VERTEX_ROWS = 512
#: ... in rounds of this many of each piece, every piece's in one call
VERTEX_BATCH = 256
#: the chain rows (:meth:`_Dual.chain`, round at16; the metrics with ``Metric.chain_rows``):
#: their rows expanded by the next member (:meth:`_Dual.expand`) this many at a time
EXPAND_BATCH = 64
EXPAND_ROWS = 512
#: the iterated local search (:func:`_kicks`, the timed plan after the ejection chains; the
#: metrics with ``Metric.kicks``): the share of the time left it takes (0.2-0.4 measured with
#: the fixed seed: spectral 0.93-0.96 %; 0.5: 2.0 %, the bound starved), the sensors a kick
#: reassigns (drawn from ``[lo, hi)``) and its generator's seed (fixed: the same problem and
#: clock, the same decision)
KICK_SHARE = 0.3
KICK_SENSORS = (2, 7)
KICK_SEED = 2029
#: ... and it stops after this many kicks in a row that found nothing better (a long time
#: limit is not spent on a search that has settled)
KICK_STALL = 60
#: ... and they start only while this share of the decision's limit is left after the ejection
#: chains (round mt20: on a slower machine the set-up, the enumeration and the chains take more
#: of the limit, and the kicks' share then starved the bound; on a 2-core Intel Xeon host,
#: N = 64, T = 8, 90 ms of CPU, spectral's median over 45 problems 2.88 % -> 1.63 % of the
#: distance from doing nothing with ``ROOT_START_SHARE``, better on 38 and worse on 5; at 130
#: and 200 ms no significant difference: many_targets.md, round mt20)
KICK_MIN_LEFT = 0.5
#: the root floors start once the dual steps stall, or half of their time is spent
#: (``ROOT_FLOOR_AFTER``), or no more than this share of the decision's limit is left, whichever
#: comes first (round mt20, as ``KICK_MIN_LEFT``: a root costs about the same at any limit, so a
#: plan that reached its steps late left too few of them)
ROOT_START_SHARE = 0.35

STATUS: dict[int, str] = {
    0: "optimal: the exact allocator decided (the reference's assignment)",
    1: "node limit reached: best assignment found, with a certified lower bound",
    2: "time limit reached: best assignment found, with a certified lower bound",
    3: "relative gap reached: the assignment is within rel_gap of the optimum",
    4: "greedy local optimum, with a certified lower bound",
    5: "dual steps exhausted: best assignment found, with a certified lower bound",
}


@dataclass(frozen=True, slots=True)
class AssignmentSearch:
    """A greedy or bounded decision: the fields of
    :class:`~covnet.core.allocation.assignment.Assignment` (``assignment``: per sensor a target
    ``t``, a cell ``T + c`` or ``OFF``; ``sets`` per column; ``value``, ``values``,
    ``cell_values``, ``P`` exact with the reference's arithmetic) and the certificate:
    ``lower_bound <= F*``, ``gap`` (relative to the value), ``value_nothing`` (every sensor
    off), ``gap_nothing`` (relative to ``value_nothing - value``), ``n_nodes`` (moves evaluated
    and dual steps), ``n_evaluated`` (exact per-target evaluations), ``exact``, ``status`` (a
    key of :data:`STATUS`) and ``message``."""

    assignment: tuple[int, ...]
    sets: tuple[tuple[int, ...], ...]
    value: float
    values: tuple[float, ...]
    cell_values: tuple[float, ...]
    P: NDArray[np.float64]
    lower_bound: float
    gap: float
    value_nothing: float
    gap_nothing: float
    n_nodes: int
    n_evaluated: int
    exact: bool
    status: int
    message: str

    @property
    def n_active(self) -> int:
        return sum(a != OFF for a in self.assignment)


def _gap(value: float, lower: float) -> float:
    return max(value - lower, 0.0) / max(abs(value), TINY)


def _gap_nothing(value: float, lower: float, nothing: float) -> float:
    return max(value - lower, 0.0) / max(nothing - value, TINY)


# --------------------------------------------------------------------------------------------
# the columns: working values
# --------------------------------------------------------------------------------------------


class _TargetCol:
    """A target's working values in the reduced form: ``S`` ``(N, r*r)`` every sensor's
    reduced gain (zero where not allowed or zero gain), ``base`` ``C⁻¹``."""

    def __init__(self, inp: _Inputs, t: int, allow: NDArray[np.bool_]) -> None:
        N = inp.N
        excl = frozenset(j for j in range(N) if not allow[j])
        self.prob: _Problem | None = None
        self.none = len(excl) >= N
        self.prob = _Problem(
            inp.P_pred[t],
            inp.J[:, t],
            inp.D[t],
            inp.f,
            Constraints(frozenset() if self.none else excl),
            inp.tie_rtol,
        )
        prob = self.prob
        rr = prob.r * prob.r
        self.S = np.zeros((N, rr))
        if not self.none and prob.m:
            self.S[prob.free] = prob.S
        self.base = prob.Cinv.reshape(rr).copy()
        self.moves = 0

    def z(self, members: Sequence[int]) -> Mat:
        out: Mat = self.base + self.S[list(members)].sum(axis=0)
        return out

    def vals(self, Z: Mat) -> Mat:
        assert self.prob is not None
        self.moves += Z.shape[0]
        return self.prob.approx_values(Z)

    def val(self, members: Sequence[int]) -> float:
        return float(self.vals(self.z(members)[None])[0])

    def vals_of(self, blocks: Sequence[NDArray[np.intp]]) -> Mat:
        """The working values of the sets of ``blocks`` (each ``(m, k)``, a set a row, in
        order) in one batch; each ``Z`` is summed as :meth:`z` (the members in turn onto
        ``base``: the same bits as :meth:`val` one at a time)."""
        Z = np.concatenate([self.base[None] + self.S[b].sum(axis=1) for b in blocks])
        return self.vals(Z)

    def add(self, members: Sequence[int], cands: NDArray[np.intp]) -> Mat:
        return self.vals(self.z(members)[None] + self.S[cands])

    def rem(self, members: Sequence[int]) -> Mat:
        return self.vals(self.z(members)[None] - self.S[list(members)])

    def swap(self, members: Sequence[int], cands: NDArray[np.intp]) -> Mat:
        Zr = self.z(members)[None] - self.S[list(members)]
        Zs = Zr[:, None, :] + self.S[cands][None, :, :]
        return self.vals(Zs.reshape(-1, Zr.shape[1])).reshape(len(members), cands.size)


class _CellCol:
    """A cell's working values: ``λ u_c Π miss``."""

    def __init__(self, inp: _Inputs, c: int) -> None:
        assert inp.cells is not None
        self.scale = inp.cells.weight * float(inp.cells.u[c])
        self.miss = inp.cells.miss[:, c].astype(np.float64)
        self.moves = 0

    def _prod(self, members: Sequence[int]) -> float:
        return float(np.prod(self.miss[list(members)])) if len(members) else 1.0

    def vals_of(self, blocks: Sequence[NDArray[np.intp]]) -> Mat:
        return np.array([self.val(mem) for b in blocks for mem in b.tolist()])

    def val(self, members: Sequence[int]) -> float:
        return self.scale * self._prod(members)

    def add(self, members: Sequence[int], cands: NDArray[np.intp]) -> Mat:
        self.moves += cands.size
        return self.scale * self._prod(members) * self.miss[cands]

    def rem(self, members: Sequence[int]) -> Mat:
        self.moves += len(members)
        m = self.miss[list(members)]
        out = np.empty(m.size)
        for i in range(m.size):
            out[i] = np.prod(np.delete(m, i))
        return self.scale * out

    def swap(self, members: Sequence[int], cands: NDArray[np.intp]) -> Mat:
        return self.rem(members)[:, None] * self.miss[cands][None, :]


class _Columns:
    """The validated problem as the searches see it: columns (targets then cells), weights,
    ``allow`` ``(ncol, N)`` which sensor may take which column, caps, budget, required."""

    def __init__(self, inp: _Inputs) -> None:
        self.inp = inp
        N, T, C = inp.N, inp.T, inp.C
        ncol = T + C
        allow = np.zeros((ncol, N), dtype=bool)
        for j, opts in enumerate(inp.options):
            for o in opts:
                if o != OFF:
                    allow[o, j] = True
        self.allow = allow
        self.N, self.T, self.C, self.ncol = N, T, C, ncol
        self.cols: list[_TargetCol | _CellCol] = [_TargetCol(inp, t, allow[t]) for t in range(T)]
        self.cols += [_CellCol(inp, c) for c in range(C)]
        self.w = np.array(inp.w + [1.0] * C)
        self.caps = np.array(inp.caps + [N] * C)
        self.K = inp.K
        self.required = np.zeros(N, dtype=bool)
        self.required[sorted(inp.required)] = True

    @property
    def moves(self) -> int:
        return sum(c.moves for c in self.cols)

    def exact(self, a: Sequence[int]) -> tuple[float, list[float], list[Mat], list[float]]:
        """``F``, the targets' ``v_t`` and ``P_t``, the cells' ``g_c``: the reference's
        arithmetic."""
        inp = self.inp
        values, Ps = [], []
        for t in range(self.T):
            v, P_t = inp.target_value(t, [j for j in range(self.N) if a[j] == t])
            values.append(v)
            Ps.append(P_t)
        gs = [
            inp.cell_value(c, [j for j in range(self.N) if a[j] == self.T + c])
            for c in range(self.C)
        ]
        return inp.total(values, gs), values, Ps, gs


# --------------------------------------------------------------------------------------------
# greedy: forward and local search
# --------------------------------------------------------------------------------------------


class _State:
    """An assignment with its working column values and the move tables (module docstring):
    ``A[c, j]`` the change of column ``c`` when ``j`` joins it (``inf``: not allowed, or ``j``
    on it), ``R[j]`` the change of ``j``'s column when ``j`` leaves it, ``M[j, k]`` the change
    of ``j``'s column when ``k`` replaces ``j`` there (all weighted)."""

    def __init__(self, cols: _Columns) -> None:
        self.cs = cols
        N, ncol = cols.N, cols.ncol
        self.a = np.full(N, OFF, dtype=np.int64)
        self.sets: list[list[int]] = [[] for _ in range(ncol)]
        self.v = np.array([c.val([]) for c in cols.cols])
        self.A = np.full((ncol, N), np.inf)
        self.R = np.zeros(N)
        self.M = np.zeros((N, N))
        self.M[:, cols.required] = np.inf  # an off sensor's row: a required one cannot leave
        #: the columns whose members' rows of ``R`` and ``M`` are not yet refreshed (only the
        #: local search reads them: :meth:`fresh`)
        self.stale: set[int] = set()
        for c in range(ncol):
            self._refresh_add(c)

    @property
    def F(self) -> float:
        return float(np.dot(self.cs.w, self.v))

    def _refresh_add(self, c: int) -> None:
        cs = self.cs
        cand = np.flatnonzero(cs.allow[c] & (self.a != c))
        self.A[c] = np.inf
        if cand.size:
            self.A[c, cand] = cs.w[c] * (cs.cols[c].add(self.sets[c], cand) - self.v[c])

    def _refresh_members(self, c: int) -> None:
        cs = self.cs
        mem = self.sets[c]
        if not mem:
            return
        mem_a = np.array(mem)
        self.R[mem_a] = cs.w[c] * (cs.cols[c].rem(mem) - self.v[c])
        cand = np.flatnonzero(cs.allow[c] & (self.a != c))
        self.M[mem_a] = np.inf
        if cand.size:
            sw = cs.w[c] * (cs.cols[c].swap(mem, cand) - self.v[c])
            self.M[np.ix_(mem_a, cand)] = sw

    def put(self, j: int, c: int) -> None:
        """Sensor ``j`` to column ``c`` (or ``OFF``), tables of the changed columns updated."""
        self.move(((j, c),))

    def move(self, changes: Sequence[tuple[int, int]]) -> None:
        """Each sensor ``j`` of ``changes`` to its column ``c`` (or ``OFF``), in turn; then
        the changed columns' values and ``A`` rows once.  A column's value and ``A`` row
        depend only on its own set and on which sensors are on it, so they are the same bits
        as :meth:`put` one change at a time (a swap is three puts, two columns: refreshed
        once each instead of three times in all)."""
        changed: list[int] = []
        for j, c in changes:
            old = int(self.a[j])
            self.a[j] = c
            if old != OFF:
                self.sets[old].remove(j)
            if c != OFF:
                self.sets[c].append(j)
                self.sets[c].sort()
            else:
                self.R[j] = 0.0
                self.M[j] = 0.0
                self.M[j, self.cs.required] = np.inf
            changed += [x for x in (old, c) if x != OFF and x not in changed]
        for x in changed:
            self.v[x] = self.cs.cols[x].val(self.sets[x])
        for x in changed:
            self._refresh_add(x)
        self.stale.update(changed)

    def fresh(self) -> None:
        """The stale columns' rows of ``R`` and ``M`` refreshed: the same values as refreshed
        at every :meth:`put` (a column's rows depend only on its own set and value, and the
        rows of different columns' members are disjoint; an off sensor's row is set by
        :meth:`put`), computed once however many puts changed the column since (the forward
        greedy reads only ``A``; a swap is three puts)."""
        for c in sorted(self.stale):
            self._refresh_members(c)
        self.stale.clear()

    def copy(self) -> _State:
        """An independent copy (the tables and sets copied, the columns shared)."""
        new = object.__new__(_State)
        new.cs = self.cs
        new.a = self.a.copy()
        new.sets = [list(x) for x in self.sets]
        new.v = self.v.copy()
        new.A = self.A.copy()
        new.R = self.R.copy()
        new.M = self.M.copy()
        new.stale = set(self.stale)
        return new

    def n_on(self) -> int:
        return int((self.a != OFF).sum())

    def counts(self) -> NDArray[np.int64]:
        return np.array([len(s) for s in self.sets])


def _forward(st: _State) -> None:
    """Required sensors first (the pair raising ``F`` least), then the pair lowering ``F``
    most while one does (at least one sensor on)."""
    cs = st.cs
    while True:
        req_off = cs.required & (st.a == OFF)
        if not req_off.any():
            break
        open_ = st.counts() < cs.caps
        A = np.where(open_[:, None] & req_off[None, :], st.A, np.inf)
        c, j = np.unravel_index(int(np.argmin(A)), A.shape)
        if not math.isfinite(float(A[c, j])):
            raise InfeasibleAllocation("the required sensors do not fit the per-target limits")
        st.put(int(j), int(c))
    while st.n_on() < cs.K:
        open_ = st.counts() < cs.caps
        A = np.where(open_[:, None] & (st.a == OFF)[None, :], st.A, np.inf)
        k = int(np.argmin(A))
        c, j = np.unravel_index(k, A.shape)
        d = float(A[c, j])
        if not math.isfinite(d):
            break
        F = st.F
        if st.n_on() and not d < -IMPROVE * max(abs(F), TINY):
            break
        st.put(int(j), int(c))
    if st.n_on() == 0:
        raise InfeasibleAllocation("no assignment satisfies the constraints")


def _local_search(st: _State, deadline: Callable[[], bool] | None) -> None:
    """Best-improvement moves and 1-swaps (module docstring)."""
    cs = st.cs
    N = cs.N
    idx = np.arange(N)
    for _ in range(PASSES_PER_SENSOR * N + 1):
        if deadline is not None and deadline():
            return
        st.fresh()
        F = st.F
        thr = -IMPROVE * max(abs(F), TINY)
        on = st.a != OFF
        n_on = int(on.sum())
        counts = st.counts()
        open_ = counts < cs.caps
        # moves: j to column c (from its own or from off); to off
        mv = st.R[None, :] + np.where(open_[:, None], st.A, np.inf)
        if n_on >= cs.K:
            mv[:, ~on] = np.inf
        c1, j1 = np.unravel_index(int(np.argmin(mv)), mv.shape)
        best = float(mv[c1, j1])
        move: tuple[str, int, int] = ("move", int(j1), int(c1))
        off = np.where(on & ~cs.required, st.R, np.inf)
        if n_on <= 1:
            off[:] = np.inf
        j2 = int(np.argmin(off))
        if off[j2] < best:
            best, move = float(off[j2]), ("off", j2, OFF)
        # swaps: j and k on different columns (at most one off)
        sw = st.M + st.M.T
        same = st.a[:, None] == st.a[None, :]
        sw[same] = np.inf
        sw[idx, idx] = np.inf
        k3 = int(np.argmin(sw))
        j3, k3b = divmod(k3, N)
        if sw[j3, k3b] < best:
            best, move = float(sw[j3, k3b]), ("swap", j3, k3b)
        if not best < thr:
            return
        kind, j, x = move
        if kind == "swap":
            aj, ak = int(st.a[j]), int(st.a[x])
            st.move(((j, OFF), (x, aj), (j, ak)))
        else:
            st.put(j, x)


def _chain_moves(st: _State, deadline: Callable[[], bool] | None) -> int:
    """Round br16 (the timed plan, after the set moves): *ejection chains* of two moves, then
    the local search again, while one improves.  Sensor ``j`` leaves its column ``c`` for
    another column ``c'`` and an off sensor ``k`` takes ``j``'s place on ``c``::

        ΔF = A[c', j] + M[j, k],

    (the :class:`_State` tables, weighted): ``c'`` changes only by ``j`` joining its set
    (``A[c', j]``, computed from ``c'``'s set, which the move does not otherwise touch) and
    ``c`` only by ``k`` replacing ``j`` (``M[j, k]``); the columns differ (``A[c, j] = inf``:
    ``j`` is on ``c``) and ``k != j`` is off, so the two changes add, and ``F`` after the
    chain is ``F + ΔF`` in the working values.  One sensor more is on: only while ``n_on < K``
    (the budget), ``c'`` below its cap (``c``'s count is unchanged); ``j`` stays on (a required
    ``j`` too) and ``k`` is allowed on ``c`` (else ``M[j, k] = inf``).  Neither a move (``j``
    to ``c'`` leaves ``c`` without ``j``: ``R[j] + A[c', j]``) nor a 1-swap (``j`` and ``k``
    exchange columns) is this step: a target whose best sensor another target holds gets it
    only if that target can be given an idle sensor at once (trace_diff at N = 64, T = 8,
    90 ms of CPU: problem 3's target 0 gains sensor 41 from target 3, which takes the idle
    sensor 53, ``F`` 76.93 -> 62.10; problem 4 111.82 -> 105.36; the median gap relative to
    the distance from doing nothing 1.20 % -> 0.41 %).  Only strict improvements (``ΔF <
    -IMPROVE |F|``) are taken, so the value is never worse; the best chain first (``O(T N +
    N^2)`` a step on the tables the local search keeps).  The clock is read only after a chain
    is taken (by the local search and before the next chain): where none improves, the plan
    reads it exactly as before.  Returns how many chains were taken."""
    cs = st.cs
    N = cs.N
    taken = 0
    for _ in range(PASSES_PER_SENSOR * N + 1):
        if taken and deadline is not None and deadline():
            break
        st.fresh()
        on = st.a != OFF
        if int(on.sum()) >= cs.K or not on.any():
            break
        thr = -IMPROVE * max(abs(st.F), TINY)
        open_ = st.counts() < cs.caps
        A = np.where(open_[:, None], st.A, np.inf)  # inf where j is on the column already
        c_best = np.argmin(A, axis=0)  # per j its best other column
        a_best = A[c_best, np.arange(N)]
        Mk = np.where((~on)[None, :], st.M, np.inf)  # k off (M[j, j] = inf: j on)
        k_best = np.argmin(Mk, axis=1)
        tot = np.where(on, a_best + Mk[np.arange(N), k_best], np.inf)
        j = int(np.argmin(tot))
        if not tot[j] < thr:
            break
        c, c2, k = int(st.a[j]), int(c_best[j]), int(k_best[j])
        st.move(((j, c2), (k, c)))
        taken += 1
        _local_search(st, deadline)
    return taken


def _kicks(st: _State, until: Callable[[], bool], rng: np.random.Generator) -> tuple[_State, int]:
    """The iterated local search (the timed plan, after the ejection chains; premise measured
    at N = 64, T = 8: the incumbent, not the bound, held most of spectral's and abs_trace's
    gap, 5 s of these kicks lowering their median gaps from 1.05 % to 0.49 % and from 1.11 %
    to 0.15 % with the same bound): until ``until()``, a *kick* reassigns ``KICK_SENSORS``
    random sensors (each to a random column that allows it and has room, or off: a required
    sensor never off, a sensor turned on only under the budget ``K``), then the local search
    and the ejection chains run to their ends from there; the result replaces the incumbent
    only if its ``F`` is strictly lower, so the value is never worse, and every state a kick
    makes satisfies the constraints the moves keep (allowed pairs, caps, budget, required).
    The better assignments it finds keep more sensors on, spread over several targets at
    once: three to nine sensors a step, which no single move, swap or chain reaches.  Returns
    the best state and how many kicks improved it; it stops at ``until()`` or after
    ``KICK_STALL`` kicks in a row without improvement."""
    cs = st.cs
    best = st
    better = stall = 0
    lo, hi = KICK_SENSORS
    while not until() and stall < KICK_STALL:
        cur = best.copy()
        a, counts, n_on = cur.a.copy(), cur.counts(), cur.n_on()
        kick: list[tuple[int, int]] = []
        for j in rng.choice(cs.N, size=min(int(rng.integers(lo, hi)), cs.N), replace=False):
            j = int(j)
            was = int(a[j])
            opts = [c for c in range(cs.ncol)
                    if cs.allow[c, j] and c != was and counts[c] < cs.caps[c]]  # fmt: skip
            if was == OFF and n_on >= cs.K:
                opts = []
            if was != OFF and not cs.required[j]:
                opts.append(OFF)
            if opts:
                c = opts[int(rng.integers(len(opts)))]
                kick.append((j, c))
                a[j] = c
                if was != OFF:
                    counts[was] -= 1
                if c != OFF:
                    counts[c] += 1
                n_on += (c != OFF) - (was != OFF)
        cur.move(kick)
        _local_search(cur, until)
        _chain_moves(cur, until)
        if cur.F < best.F - IMPROVE * max(abs(best.F), TINY):
            best, better, stall = cur, better + 1, 0
        else:
            stall += 1
    return best, better


def _enum_moves(st: _State, dual: _Dual, deadline: Callable[[], bool] | None) -> bool:
    """Set moves from the enumeration bound: a target's whole set replaced by one of its
    ``ENUM_MOVES`` best enumerated sets of each size (by their bound) whose members are off or
    already on it (the old members not in it go off), within the caps and the budget, the
    required sensors kept; the move lowering ``F`` most (strictly, ``IMPROVE``) while one
    does.  A local optimum of moves and 1-swaps can miss a better pair that shares no sensor
    with the target's set; these find it.  Returns whether one was taken."""
    cs = st.cs
    moved = False
    for _ in range(2 * cs.ncol):
        if deadline is not None and deadline():
            break
        F = st.F
        best_d, best_c, best_mem = -IMPROVE * max(abs(F), TINY), -1, [0]
        n_on = st.n_on()
        for c, en in enumerate(dual.enum):
            if en is None:
                continue
            free = (st.a == OFF) | (st.a == c)
            keep = [j for j in st.sets[c] if cs.required[j]]
            blocks: list[NDArray[np.intp]] = []  # (m, k) rows of ascending members
            for k in range(1, min(en.d, en.nc) + 1):
                sets = en.o[en.sets[k]]
                cand = np.flatnonzero(free[sets].all(axis=1))
                if cand.size == 0:
                    continue
                order = cand[np.argsort(en.exact[k][cand], kind="stable")[:ENUM_MOVES]]
                if not keep:  # the enumerated sets as they are (ascending already)
                    n_new = n_on - len(st.sets[c]) + k
                    if k <= cs.caps[c] and 1 <= n_new <= cs.K:
                        blocks.append(sets[order])
                    continue
                for i in order:
                    mem = sorted(set(sets[i].tolist()) | set(keep))
                    n_new = n_on - len(st.sets[c]) + len(mem)
                    if len(mem) > cs.caps[c] or n_new > cs.K or n_new < 1:
                        continue
                    blocks.append(np.array([mem], dtype=np.intp))
            if not blocks:
                continue
            d = cs.w[c] * (cs.cols[c].vals_of(blocks) - st.v[c])  # one batch a column
            i_best = int(np.argmin(d))  # the first of the least, as one at a time
            if float(d[i_best]) < best_d:
                flat = [r for b in blocks for r in b.tolist()]
                best_d, best_c, best_mem = float(d[i_best]), c, flat[i_best]
        if best_c < 0:
            break
        for j in list(st.sets[best_c]):
            if j not in best_mem:
                st.put(j, OFF)
        for j in best_mem:
            if st.a[j] != best_c:
                st.put(j, best_c)
        moved = True
    return moved


# --------------------------------------------------------------------------------------------
# the lower bound
# --------------------------------------------------------------------------------------------


def _weighted(lb: Mat, w: float) -> Mat:
    """``w`` times bounds of a metric's values, which are ``>= 0``: clipped at 0, and 0 where
    a bound is not finite."""
    return w * np.where(np.isfinite(lb), np.maximum(lb, 0.0), 0.0)


def _interval_rows(prob: _Problem, Z_lo: Mat, Z_hi: Mat, w: float) -> Mat:
    """The interval bound over each ``[Z_lo, Z_hi]``, weighted (:func:`_weighted`)."""
    return _weighted(prob.combine(prob.summary(Z_hi), prob.summary(Z_lo)), w)


class _Dual:
    """The Lagrangian bound (module docstring): per column ``c`` the count bound ``h[c]``
    ``(n_c + 1,)``, ``opts[c]`` its allowed sensors, ``Kp`` the count limit; per target column
    the enumeration bound ``enum[c]`` (:class:`_Enum`, or ``None``)."""

    def __init__(
        self,
        cs: _Columns,
        budget: int = ENUM_BUDGET,
        refine_rows: int = REFINE_ROWS,
        deadline: Callable[[], bool] | None = None,
        upper: Mat | None = None,
        timed: bool = False,
    ) -> None:
        """``upper``: the incumbent's weighted column values; the columns whose count bound
        is furthest below them are enumerated (and refined) first, so a deadline leaves the
        least bound behind.  ``timed`` (the timed plan of :func:`_search`): depth 1 only, its
        superset bounds refined at once; :meth:`deepen` enumerates deeper later, keeping them."""
        self.cs = cs
        self.pieces: list[_Rows | None] = []
        n_any = int(cs.allow.any(axis=0).sum())
        self.Kp = min(cs.K, n_any)
        self.opts = [np.flatnonzero(cs.allow[c]) for c in range(cs.ncol)]
        self.h: list[Mat] = []
        self.nc: list[int] = []
        #: per column the weighted single-target floor (``-inf``: none; :func:`_floors`)
        self.floor = np.full(cs.ncol, -math.inf)
        #: the columns whose last floor search stopped at its time limit (:func:`_floors`)
        self.cut: set[int] = set()
        #: per column with chain rows (:meth:`chain`) each option's position in the chain
        self.chain_pos: dict[int, NDArray[np.intp]] = {}
        #: the metric has chain rows (``Metric.chain_rows``)
        self.chained = cs.inp.entry is not None and cs.inp.entry.chain_rows
        for c, col in enumerate(cs.cols):
            nc = int(min(self.opts[c].size, cs.caps[c], self.Kp))
            self.nc.append(nc)
            if isinstance(col, _TargetCol):
                hc, rows = self._target(col, self.opts[c], nc)
                self.pieces.append(rows)
            else:
                self.pieces.append(None)
                m = np.sort(col.miss[self.opts[c]])[:nc]
                prods = np.concatenate(([1.0], np.cumprod(m)))
                k = np.arange(nc + 1)
                hc = col.scale * prods * (1.0 - 4.0 * (k + 2) * EPS)
            self.h.append(np.maximum(cs.w[c] * hc, 0.0))
        for c in range(cs.ncol):  # the count bound refined first (cheap where it applies)
            rows = self.pieces[c]
            if timed:
                break  # refined with the depth-1 superset bounds, in one call a column
            if rows is not None and not (deadline is not None and deadline()):
                rows.lazy(self.h[c], float(cs.w[c]), refine_rows, deadline)
        self.enum: list[_Enum | None] = [None] * cs.ncol
        depth = _depths([self.nc[c] if isinstance(col, _TargetCol) and self._bounded(col)
                         else 0 for c, col in enumerate(cs.cols)], budget)  # fmt: skip
        order = list(range(cs.ncol))
        if upper is not None:
            slack = [float(upper[c]) - float(self.h[c].min()) for c in order]
            order.sort(key=lambda c: -slack[c])
        self.order = order
        self.depth = depth
        self.refine_rows = refine_rows
        self.sep = self.Kp >= sum(self.nc)  # the count limit never binds: columns separate
        self._grids: dict[int, tuple[NDArray[np.bool_], NDArray[np.intp]]] = {}
        if timed:
            for c in order:
                col = cs.cols[c]
                if depth[c] and isinstance(col, _TargetCol):
                    self.enum[c] = _Enum(col, self.opts[c], self.nc[c], 1, float(cs.w[c]))
            for c in order:
                if deadline is not None and deadline():
                    break
                en = self.enum[c]
                pieces = [(self.pieces[c], self.h[c])]
                pieces.append((en.rows, en.sup) if en is not None else (None, self.h[c]))
                _Rows.together(pieces, float(cs.w[c]), refine_rows)
            for c in order if self.chained else ():  # round at16: the chain rows
                if not isinstance(cs.cols[c], _TargetCol):
                    continue
                if deadline is not None and deadline():
                    break
                self.chain(c)
            return
        for first in (True, False):  # depth 1 everywhere (cheap: n_c sets), then deeper
            for c in order:
                col = cs.cols[c]
                d = min(depth[c], 1) if first else depth[c]
                if not first and (d <= 1 or (deadline is not None and deadline())):
                    continue  # the columns not deepened keep their depth-1 bound
                if d and isinstance(col, _TargetCol):
                    self.enum[c] = _Enum(col, self.opts[c], self.nc[c], d, float(cs.w[c]))
        self._refine_sup(order, deadline)

    def _refine_sup(self, cols: Sequence[int], deadline: Callable[[], bool] | None) -> None:
        """The enumerations' superset bounds of ``cols`` refined lazily, in turn."""
        for c in cols:
            if deadline is not None and deadline():
                break
            en = self.enum[c]
            if en is not None and en.rows is not None:
                en.rows.lazy(en.sup, float(self.cs.w[c]), self.refine_rows, deadline)

    def deepen(
        self,
        deadline: Callable[[], bool] | None,
        upper: Mat | None = None,
        remaining: Callable[[], float] | None = None,
    ) -> int:
        """The timed plan: each column in :attr:`order` (the largest slack first) enumerated to
        its depth, reusing its depth-1 sets and keeping their superset bounds
        (:attr:`_Enum.lower`), its new superset bounds refined, while the deadline allows and
        (with ``remaining``) at least the last column's time is left (a column's enumeration
        is not interruptible: under a heavy load one took 15-20 ms of the bench's 90).
        Returns how many columns were deepened."""
        done = 0
        last = 0.0
        order = list(self.order)
        if upper is not None:  # the slack now (floors in), the largest first
            zero = np.zeros(self.cs.N)
            slack = [float(upper[c]) - float(self._cost(c, zero)[0].min()) for c in order]
            order = [order[i] for i in np.argsort(-np.array(slack), kind="stable")]
        for c in order:
            if deadline is not None and deadline():
                break
            en = self.enum[c]
            col = self.cs.cols[c]
            if en is None or self.depth[c] <= en.d or not isinstance(col, _TargetCol):
                continue
            left = remaining() if remaining is not None else math.inf
            if left < last:
                break
            self.enum[c] = _Enum(
                col, self.opts[c], self.nc[c], self.depth[c], float(self.cs.w[c]), prev=en
            )
            self.chain2(c)  # round at16: where the column has chain rows
            self._refine_sup([c], deadline)
            done += 1
            if remaining is not None:
                last = left - remaining()
        return done

    def chain(self, c: int) -> bool:
        """Round at16 (the timed plan, the metrics of ``Metric.chain_rows``): column ``c``'s
        depth-1 superset rows raised by the *chain*.  Order the column's sensors ``o`` by their
        depth-1 superset bound, the largest first (ties by index): ``j_1, ..., j_m``.  Every
        non-empty ``S ⊆ F_c`` has a first member ``j_i`` in that order, and then ``S ⊆ F_i =
        {j_i, ..., j_m}``, so ``Z({j_i}) ⪯ Z(S) ⪯ Z(F_i)`` (the ``S_j`` are PSD): the bound
        ``ℓ_i`` of the interval ``[Z({j_i}), Z(F_i)]`` (the interval bound, raised by the
        vertex bound where the metric has one) bounds ``w_c g_c(S)``.  As the depth-1 superset
        bound ``u1(j_i)`` (the interval ``[Z({j_i}), Z(F_c)]``, wider) holds for these sets too,
        row ``j`` becomes ``max(u1(j), ℓ_j)``: a bound of every set whose first member is
        ``j``.  **Proof** of its use in the dual (:meth:`_Enum.cost`, ``d0 = 1``, ``k > 1``):
        a ``k``-set ``S`` with first member ``j`` has ``w_c g_c(S) + π(S) >= row(j) + π_j +
        π_c(k - 1)`` (its other ``k - 1`` members are distinct sensors of ``F_c``, prices ``>=
        0``), so ``min_{|S|=k} w_c g_c(S) + π(S) >= min_j [row(j) + π_j] + π_c(k - 1)``: the
        formula of the superset rows, whose proof needs only that each set is above the row of
        one of its members.  The later raises of these rows (the relaxation, the vertex rows)
        bound the wider interval ``[Z({j}), Z(F_c)]``, so they stay valid.  Why: abs_trace's
        heavy targets (best sets of one sensor, values 83-137 at N = 64, T = 8) are bounded
        at three or more sensors only by intervals reaching ``Z(F_c)`` (38-90), where every
        diagonal term can reach ``P_d``; the chain's late intervals hold only the weak sensors
        (their ``Z(F_i)`` small), which is where ``min_i ℓ_i`` lies, and it equals the
        single-target optimum on 5 of 8 such targets (the single-target search proves it in
        70-120 ms of CPU, about 110 nodes; the chain costs one batch, about 0.5 ms).  Returns
        whether the rows were raised."""
        en = self.enum[c]
        col = self.cs.cols[c]
        if en is None or en.d != 1 or not isinstance(col, _TargetCol) or en.nc < 2:
            return False
        prob = col.prob
        if prob is None or not self.chained:
            return False
        sup = en.sup
        order = np.argsort(-sup, kind="stable")
        S = col.S[en.o[order]]
        Z_lo = col.base[None] + S
        Z_hi = col.base[None] + np.cumsum(S[::-1], axis=0)[::-1]  # Z(F_i): j_i and the later
        lb = prob.combine(prob.summary(Z_hi), prob.summary(Z_lo))
        if prob.dual is not None and prob.dual.dual.vertices is not None:
            lb = np.fmax(lb, prob.dual.vertex_bound(Z_lo, Z_hi))
        lb = _weighted(lb, float(self.cs.w[c]))
        sup[order] = np.fmax(sup[order], lb)
        if en.rows is not None:  # the later raises (vertex rows) on the narrower intervals
            Z_up = np.empty_like(Z_hi)
            Z_up[order] = Z_hi
            en.rows.Z_hi = Z_up
        pos = np.empty(order.size, dtype=np.intp)
        pos[order] = np.arange(order.size)
        self.chain_pos[c] = pos
        return True

    def chain2(self, c: int) -> bool:
        """Round at16: after :meth:`chain`, column ``c``'s deeper superset rows (its enumeration
        deepened to ``d >= 2``, :meth:`deepen`) raised by the chain's level ``d``.  With the
        chain's order ``j_1, ..., j_m``, every ``S`` with more than ``d`` members has a first
        ``d`` members ``S0`` (the last of them ``j_b``), and ``S ⊆ S0 ∪ {j_e : e > b}``, so
        ``Z(S0) ⪯ Z(S) ⪯ Z(S0) + Σ_{e > b} S_{j_e}``: that interval's bound bounds ``w_c
        g_c(S)``, and with the wider ``[Z(S0), Z(F_c)]`` (the old row) ``S0``'s row becomes a
        bound of every set whose first ``d`` members are ``S0``; the dual's use of the rows
        (``min_{S0} [row(S0) + π(S0)] + π_c(k - d)``, ``k > d``) needs only that each set is
        above the row of one of its ``d``-subsets (:meth:`chain`'s proof).  The rows'
        intervals become these narrower ones, so the vertex rows raise them there.  Returns
        whether the rows were raised."""
        en = self.enum[c]
        col = self.cs.cols[c]
        pos = self.chain_pos.get(c)
        if pos is None or en is None or en.d < 2 or not isinstance(col, _TargetCol):
            return False
        prob = col.prob
        assert prob is not None
        sets = en.sets[en.d]
        S = col.S[en.o]
        order = np.argsort(pos, kind="stable")
        # after[p]: the sum of S over the chain's positions > p
        after = np.zeros_like(S)
        after[:-1] = np.cumsum(S[order][::-1], axis=0)[::-1][1:]
        last = pos[sets].max(axis=1)
        Z_lo = col.base[None] + S[sets].sum(axis=1)
        Z_hi = Z_lo + after[last]
        en.sup = np.fmax(en.sup, _interval_rows(prob, Z_lo, Z_hi, float(self.cs.w[c])))
        if en.rows is not None:
            en.rows.Z_hi = Z_hi
        en.after = after
        return True

    def expand(self, c: int, pi: Mat, limit: int, deadline: Callable[[], bool] | None) -> int:
        """Round at16: column ``c``'s chain rows of its deepest level ``d`` (after
        :meth:`chain2`) raised by the chain's next member, the least ``row + π(S0)`` first at
        the prices ``pi``, ``EXPAND_BATCH`` rows at a time, until the least is an expanded one,
        ``limit`` rows are expanded or the deadline passes.  Row ``S0`` (last member at the
        chain's position ``b``) bounds the sets with more than ``d`` members whose first ``d``
        members are ``S0``; each has a next member ``j_q`` (``q > b``) and lies in ``S0 ∪
        {j_q} ∪ {j_e : e > q}``, so ``Z(S0 + j_q) ⪯ Z(S) ⪯ Z(S0 + j_q) + Σ_{e > q} S_{j_e}``:
        **proof** that ``min_q ℓ_q`` (``ℓ_q`` that interval's bound) bounds every set of the
        row's class, so the row becomes ``max(row, min_q ℓ_q)`` (a row whose class is empty,
        ``b`` the last position, is left as it is).  Each ``ℓ_q`` is the interval bound (no
        vertex bound: about a thousand intervals a batch).  Returns how many rows were
        expanded."""
        en = self.enum[c]
        col = self.cs.cols[c]
        pos = self.chain_pos.get(c)
        if pos is None or en is None or en.after is None or not isinstance(col, _TargetCol):
            return 0
        prob = col.prob
        assert prob is not None
        sets = en.sets[en.d]
        if en.xdone is None:
            en.xdone = np.zeros(sets.shape[0], dtype=bool)
        m = pos.size
        order = np.argsort(pos, kind="stable")
        S = col.S[en.o]
        price = en._psum(pi[en.o], en.d)
        w = float(self.cs.w[c])
        n = 0
        while n < limit:
            if deadline is not None and deadline():
                break
            rank = np.argsort(en.sup + price, kind="stable")
            if en.xdone[rank[0]]:
                break
            pick = rank[~en.xdone[rank]][: min(EXPAND_BATCH, limit - n)]
            last = pos[sets[pick]].max(axis=1)
            cnt = m - 1 - last  # the next members: positions last + 1 .. m - 1
            live = pick[cnt > 0]
            if live.size:
                cl = cnt[cnt > 0]
                row = np.repeat(np.arange(live.size), cl)
                start = np.concatenate(([0], np.cumsum(cl)[:-1]))
                q = (last[cnt > 0] + 1)[row] + (np.arange(row.size) - start[row])
                Z_lo = col.base[None] + S[sets[live]].sum(axis=1)
                Z_lo = Z_lo[row] + S[order[q]]
                Z_hi = Z_lo + en.after[q]
                lb = _interval_rows(prob, Z_lo, Z_hi, w)
                en.sup[live] = np.fmax(en.sup[live], np.minimum.reduceat(lb, start))
            en.xdone[pick] = True
            n += pick.size
        return n

    def vertex(self, c: int, pi: Mat, limit: int, deadline: Callable[[], bool] | None) -> int:
        """Round mt15: column ``c``'s intervals (the count bound's rows, the enumeration's
        superset rows and its kept levels') raised by the vertex bound (:meth:`_Rows.vertex`),
        the least price-adjusted first at the prices ``pi`` (a ``k``-set pays at least the
        ``k`` smallest prices of the column, a superset of ``S0`` at least ``π(S0)``).  Returns
        how many rows were raised."""
        o = self.opts[c]
        nc = self.nc[c]
        ps = np.concatenate(([0.0], np.cumsum(np.sort(pi[o])[:nc])))
        pieces: list[tuple[_Rows, Mat, Mat]] = []
        rows = self.pieces[c]
        if rows is not None:
            pieces.append((rows, self.h[c], ps[rows.idx]))
        en = self.enum[c]
        if en is not None:
            po = pi[en.o]
            if en.rows is not None:
                pieces.append((en.rows, en.sup, en._psum(po, en.d)))
            for (d0, sup), lrows in zip(en.lower, en.lower_rows, strict=True):
                if lrows is not None:
                    pieces.append((lrows, sup, en._psum(po, d0)))
        n = _Rows.vertex(pieces, float(self.cs.w[c]), limit, deadline)
        if en is not None:
            en.rescale()
        return n

    @staticmethod
    def _bounded(col: _TargetCol) -> bool:
        prob = col.prob
        return prob is not None and not col.none and prob.bound is not None and prob.r > 0

    @staticmethod
    def _target(col: _TargetCol, opts: NDArray[np.intp], nc: int) -> tuple[Mat, _Rows | None]:
        prob = col.prob
        assert prob is not None
        if col.none or prob.bound is None or prob.r == 0:
            if prob.bound is None:  # no interval bound: a registered metric is >= 0
                return np.zeros(nc + 1), None
            Z0 = col.base[None]
            s0 = prob.summary(Z0)
            return np.full(nc + 1, float(prob.combine(s0, s0)[0])), None
        r = prob.r
        Sj = col.S[opts].reshape(-1, r, r)
        Q = col.base.reshape(r, r) + Sj.sum(axis=0)
        Q = 0.5 * (Q + Q.T)
        L = np.linalg.cholesky(Q)
        Li = np.linalg.inv(L)
        G = Li[None] @ Sj @ Li.T[None]
        G = 0.5 * (G + np.swapaxes(G, 1, 2))
        ev = np.linalg.eigvalsh(G)
        mu_max = np.maximum(ev[:, -1], 0.0)
        mu_min = np.maximum(ev[:, 0], 0.0)
        alpha = np.concatenate(([0.0], np.cumsum(np.sort(mu_max)[::-1])[:nc])) * (1 + 1e-9)
        beta = np.concatenate(([0.0], np.cumsum(np.sort(mu_min))[:nc])) * (1 - 1e-9)
        Qf = Q.reshape(r * r)
        Z_hi = col.base[None] + alpha[:, None] * Qf[None]
        Z_lo = col.base[None] + beta[:, None] * Qf[None]
        Z_all = (col.base + col.S[opts].sum(axis=0))[None]
        sA = prob.summary(Z_hi)
        sB = prob.summary(Z_lo)
        lb = prob.combine(sA, sB)
        sAll = prob.summary(Z_all)
        lb = np.fmax(lb, prob.combine(np.repeat(sAll, nc + 1, axis=0), sB))
        lb[0] = float(prob.combine(sB[:1], sB[:1])[0])  # k = 0: the degenerate interval
        rows = _Rows(prob, Z_lo, Z_hi, sB, np.arange(1, nc + 1))
        return np.where(np.isfinite(lb), lb, 0.0), rows

    def _cost(self, c: int, pi: Mat) -> tuple[Mat, Mat]:
        """Per count ``k``: a lower bound of ``min {w_c g_c(S) + π(S) : |S| = k}`` and the
        per-count minimisers' sum of prices of the enumerated part (for the subgradient)."""
        o = self.opts[c]
        nc = self.nc[c]
        ps = np.concatenate(([0.0], np.cumsum(np.sort(pi[o])[:nc])))
        cost = self.h[c] + ps
        en = self.enum[c]
        if en is not None:
            cost = np.fmax(cost, en.cost(pi, ps))
        if math.isfinite(self.floor[c]):
            cost[1:] = np.fmax(cost[1:], self.floor[c] + ps[1:])
        return cost, ps

    def value(self, pi: Mat) -> tuple[float, list[int]]:
        """``L(π)`` (less a rounding allowance) and the minimiser's counts."""
        Kp = self.Kp
        costs = [self._cost(c, pi)[0] for c in range(self.cs.ncol)]
        if self.sep:
            counts = [int(np.argmin(cost)) for cost in costs]
            total = float(sum(float(cost[k]) for cost, k in zip(costs, counts, strict=True)))
        else:
            G = np.zeros(Kp + 1)
            choice: list[NDArray[np.intp]] = []
            rows = np.arange(Kp + 1)
            for cost in costs:
                nc = cost.size - 1
                grid = self._grids.get(nc)
                if grid is None:  # the DP's index grid of this count, built once
                    s = rows[:, None] - np.arange(nc + 1)[None, :]
                    grid = self._grids[nc] = (s >= 0, np.maximum(s, 0))
                cand = np.where(grid[0], G[grid[1]] + cost[None, :], np.inf)
                k = np.argmin(cand, axis=1)
                choice.append(k)
                G = cand[rows, k]
            s_best = int(np.argmin(G))
            total = float(G[s_best])
            counts = []
            left = s_best
            for c in range(self.cs.ncol - 1, -1, -1):
                kc = int(choice[c][left])
                counts.append(kc)
                left -= kc
            counts.reverse()
        psum = float(pi.sum())
        hmax = sum(float(h.max()) for h in self.h)
        hmax += sum(e.scale for e in self.enum if e is not None)
        hmax += float(np.abs(self.floor[np.isfinite(self.floor)]).sum())
        allow = 64.0 * (self.cs.N + self.cs.ncol + 2) * EPS * (psum + hmax + abs(total))
        return total - psum - allow, counts

    def subgradient(self, pi: Mat, counts: list[int]) -> Mat:
        """``g_j`` = (columns whose minimiser uses ``j``) - 1: the enumerated set where the
        enumeration bound is the larger, else the ``k`` cheapest sensors."""
        use = np.zeros(self.cs.N)
        for c, k in enumerate(counts):
            if not k:
                continue
            o = self.opts[c]
            en = self.enum[c]
            members = en.members(pi, k) if en is not None else None
            if members is None:
                order = np.lexsort((o, pi[o]))[:k]
                members = o[order]
            use[members] += 1.0
        return use - 1.0


class _Rows:
    """Intervals ``[Z_lo[i], Z_hi[i]]`` (``i`` in ``idx``) whose bounds ``out[i]`` (weighted)
    the reduced relaxation or the dual bound of :meth:`_Problem.refine` may raise: lazily, the
    smallest first."""

    def __init__(self, prob: _Problem, Z_lo: Mat, Z_hi: Mat, sB: Mat, idx: NDArray[np.intp]):
        self.prob, self.Z_lo, self.Z_hi, self.sB, self.idx = prob, Z_lo, Z_hi, sB, idx
        self.done = np.zeros(idx.size, dtype=bool)
        self.useful = prob.relax is not None  # the dual bound's barrier: too slow here
        #: the rows the vertex bound has raised (:meth:`vertex`; built on first use)
        self.vdone: NDArray[np.bool_] | None = None

    def lazy(self, out: Mat, w: float, limit: int, deadline: Callable[[], bool] | None) -> None:
        """Refine the rows of ``out[idx]`` smallest first, ``REFINE_BATCH`` at a time, until
        the smallest is a refined one, ``limit`` rows are refined or the deadline passes.
        Each refined value is a certified bound (``fmax`` with the old one): the bound stays
        valid whenever this stops."""
        if not self.useful or self.idx.size == 0:
            return
        n_done = 0
        while n_done < limit:
            if deadline is not None and deadline():
                return
            vals = out[self.idx]
            order = np.argsort(vals, kind="stable")
            if self.done[order[0]]:
                return
            pick = order[~self.done[order]][: min(REFINE_BATCH, limit - n_done)]
            r = np.asarray(pick, dtype=np.intp)
            cur = vals[r] / w if w > 0 else vals[r]
            i = self.idx[r]
            new = self.prob.refine(self.Z_lo[i], self.Z_hi[i], cur, self.sB[i], math.inf)
            new = np.where(np.isfinite(new), np.maximum(new, 0.0), 0.0)
            out[i] = np.fmax(vals[r], w * new)
            self.done[r] = True
            n_done += r.size

    @staticmethod
    def vertex(
        pieces: Sequence[tuple[_Rows, Mat, Mat]],
        w: float,
        limit: int,
        deadline: Callable[[], bool] | None,
    ) -> int:
        """Round mt15: the rows of each piece ``(rows, out, prices)`` (``out[rows.idx]`` the
        weighted bounds of the intervals ``[Z_lo, Z_hi]`` of one column, ``prices`` the price
        sum each row's sets pay at least) raised by the dual bound's *vertex bound*
        (:meth:`~covnet.core.allocation.lower_bounds._DualBound.vertex_bound`: one_norm,
        inf_norm, abs_trace; a few dual points in closed form), in rounds: per piece its
        ``VERTEX_BATCH`` least ``out + prices`` not yet raised, every piece's in one call (its
        cost is mostly per call: about 0.5 ms, then 2-3 µs a row at N = 64, one_norm; the
        barrier costs 0.2-0.5 ms a row), until each piece's least is a raised one, ``limit``
        rows are raised or the deadline passes.  **Proof**: the vertex bound is a certified
        lower bound of the metric over every information in ``[Z_lo[i], Z_hi[i]]`` (that
        module's docstring: ``φ(Y)`` for a ``Y`` in the dual ball, deflated by the rounding),
        so of every set whose information lies there, which is what row ``i`` bounds (the count
        bound's ``k``-sets, an enumerated set's supersets); ``fmax`` with the old bound keeps it
        a bound whenever this stops.  Returns how many rows were raised."""
        got = [(r, out, pr) for r, out, pr in pieces if r.idx.size]
        if not got:
            return 0
        db = got[0][0].prob.dual
        if db is None or db.dual.vertices is None:
            return 0
        for r, _, _ in got:
            if r.vdone is None:
                r.vdone = np.zeros(r.idx.size, dtype=bool)
        n = 0
        while n < limit:
            if deadline is not None and deadline():
                break
            picks = []
            for r, out, pr in got:
                assert r.vdone is not None
                order = np.argsort(out[r.idx] + pr, kind="stable")
                if r.vdone[order[0]]:
                    picks.append(order[:0])
                else:
                    picks.append(order[~r.vdone[order]][:VERTEX_BATCH])
            m = sum(p.size for p in picks)
            if m == 0:
                break
            i_all = [r.idx[p] for (r, _, _), p in zip(got, picks, strict=True)]
            Z_lo = np.concatenate([r.Z_lo[i] for (r, _, _), i in zip(got, i_all, strict=True)])
            Z_hi = np.concatenate([r.Z_hi[i] for (r, _, _), i in zip(got, i_all, strict=True)])
            vb = db.vertex_bound(Z_lo, Z_hi)
            vb = _weighted(vb, w)
            at = 0
            for (r, out, _), p, i in zip(got, picks, i_all, strict=True):
                out[i] = np.fmax(out[i], vb[at : at + i.size])
                assert r.vdone is not None
                r.vdone[p] = True
                at += i.size
            n += m
        return n

    @staticmethod
    def together(pieces: Sequence[tuple[_Rows | None, Mat]], w: float, limit: int) -> None:
        """The first batch of :meth:`lazy` of each piece (its ``min(limit, REFINE_BATCH)``
        smallest rows not yet refined, of ``out``) in one call of the relaxation: its cost
        is mostly per call (1.3-1.5 ms at 1 to 60 rows, kl and frobenius, N = 64), so one call
        per column instead of one per piece.  Each refined value is a certified bound of its
        own interval (``fmax`` with the old one), whatever the other rows of the call."""
        got = [(r, out) for r, out in pieces if r is not None and r.useful and r.idx.size]
        if not got:
            return
        prob = got[0][0].prob
        picks = []
        for r, out in got:
            vals = out[r.idx]
            order = np.argsort(vals, kind="stable")
            pick = order[~r.done[order]][: min(REFINE_BATCH, limit)]
            picks.append(np.asarray(pick, dtype=np.intp))
        i_all = [r.idx[p] for (r, _), p in zip(got, picks, strict=True)]
        Z_lo = np.concatenate([r.Z_lo[i] for (r, _), i in zip(got, i_all, strict=True)])
        Z_hi = np.concatenate([r.Z_hi[i] for (r, _), i in zip(got, i_all, strict=True)])
        sB = np.concatenate([r.sB[i] for (r, _), i in zip(got, i_all, strict=True)])
        cur = np.concatenate([out[i] for (_, out), i in zip(got, i_all, strict=True)])
        cur = cur / w if w > 0 else cur
        new = prob.refine(Z_lo, Z_hi, cur, sB, math.inf)
        new = np.where(np.isfinite(new), np.maximum(new, 0.0), 0.0)
        at = 0
        for (r, out), p, i in zip(got, picks, i_all, strict=True):
            out[i] = np.fmax(out[i], w * new[at : at + i.size])
            r.done[p] = True
            at += i.size


def _depths(sizes: list[int], budget: int) -> list[int]:
    """The enumeration depth per column: raised one column at a time (smallest cost first)
    while the sets enumerated in all (``Σ_c Σ_{k<=d_c} C(n_c, k)``) stay within ``budget``;
    0 for a column not enumerated."""
    depth = [0] * len(sizes)
    used = 0
    while True:
        best, c_best = None, -1
        for c, n in enumerate(sizes):
            d = depth[c] + 1
            if d > min(n, ENUM_DEPTH):
                continue
            extra = math.comb(n, d)
            if best is None or extra < best:
                best, c_best = extra, c
        if best is None or used + best > budget:
            return depth
        used += best
        depth[c_best] += 1


def _combinations(n: int, k: int) -> NDArray[np.intp]:
    """``itertools.combinations(range(n), k)`` as an ``(m, k)`` array, the same rows in the
    same (lexicographic) order; ``k <= 2`` without the tuples (``np.triu_indices`` runs row
    by row, ``i < j``: the pairs' order)."""
    if k == 0:
        return np.zeros((1, 0), dtype=np.intp)
    if k == 1:
        return np.arange(n, dtype=np.intp)[:, None]
    if k == 2:
        i, j = np.triu_indices(n, 1)
        return np.stack((i, j), axis=1).astype(np.intp)
    combos = list(itertools.combinations(range(n), k))
    return np.array(combos, dtype=np.intp).reshape(len(combos), k)


class _Enum:
    """The enumeration bound of one target column (module docstring, *Lower bound*): the
    sets of its allowed sensors ``o`` with at most ``d`` members, each with a certified lower
    bound of ``w g(S)`` (the degenerate interval ``[Z(S), Z(S)]``) and, for the ``d``-sets,
    of every superset's (the interval ``[Z(S0), Z(F_c)]``)."""

    def __init__(
        self,
        col: _TargetCol,
        o: NDArray[np.intp],
        nc: int,
        d: int,
        w: float,
        prev: _Enum | None = None,
    ) -> None:
        """``prev`` (the timed plan, :func:`_search`): a shallower enumeration of the same
        column; its sets and bounds are reused, and its superset bounds (refined or not) are
        kept as :attr:`lower` (``(d0, sup)`` pairs), each a bound of its own (module
        docstring: every ``S`` with ``|S| > d0`` contains a ``d0``-set)."""
        prob = col.prob
        assert prob is not None
        self.o, self.nc, self.d = o, nc, d
        S = col.S[o]
        Z_all = (col.base + S.sum(axis=0))[None]
        sAll = prob.summary(Z_all)
        self.sets: list[NDArray[np.intp]] = []  # k-sets as indices into o, k = 0..d
        self.exact: list[Mat] = []  # their degenerate bounds
        self.sup = np.zeros(0)  # the d-sets' superset bounds
        self.rows: _Rows | None = None
        #: shallower levels' superset bounds ``(d0, sup)`` (``d0 < d``), kept from ``prev``
        self.lower: list[tuple[int, Mat]] = []
        #: ... and their intervals (``None`` where the level had none; the vertex bound,
        #: :meth:`_Dual.vertex`), in the order of :attr:`lower`
        self.lower_rows: list[_Rows | None] = []
        k0 = 0
        if prev is not None and 0 < prev.d < d:
            self.sets = list(prev.sets)
            self.exact = list(prev.exact)
            self.lower = [*prev.lower, (prev.d, prev.sup)]
            self.lower_rows = [*prev.lower_rows, prev.rows]
            k0 = prev.d + 1
        for k in range(k0, d + 1):
            idx = _combinations(o.size, k)
            Z = col.base[None] + S[idx].sum(axis=1)
            sZ = prob.summary(Z)
            lb = prob.combine(sZ, sZ)
            self.sets.append(idx)
            self.exact.append(_weighted(lb, w))
            if k == d:
                sup = prob.combine(np.repeat(sAll, idx.shape[0], axis=0), sZ)
                self.sup = _weighted(sup, w)
                Z_hi = np.repeat(Z_all, idx.shape[0], axis=0)
                self.rows = _Rows(prob, Z, Z_hi, sZ, np.arange(idx.shape[0]))
        #: per ``k <= 2`` the members' columns of the ``k``-sets (:meth:`_psum`)
        self._cols = {k: [np.ascontiguousarray(self.sets[k][:, i]) for i in range(k)]
                      for k in (1, 2) if k < len(self.sets)}  # fmt: skip
        self._pi: Mat | None = None  # the prices of the last :meth:`cost` and its argmins
        #: the chain's suffix sums by position and the rows it expanded (round at16,
        #: :meth:`_Dual.chain2`, :meth:`_Dual.expand`)
        self.after: Mat | None = None
        self.xdone: NDArray[np.bool_] | None = None
        self._arg: dict[int, int] = {}
        self.scale = float(max(float(e.max()) for e in self.exact))
        self.rescale()

    def rescale(self) -> None:
        """:attr:`scale` (the rounding allowance of :meth:`_Dual.value`) raised to the kept
        levels' superset bounds, which a refinement may have raised since."""
        for _, sup in self.lower:
            self.scale = max(self.scale, float(sup.max(initial=0.0)))

    def cost(self, pi: Mat, ps: Mat) -> Mat:
        """Per ``k = 0..nc``: ``min_{|S|=k} w g(S) + π(S)`` for ``k <= d`` (the enumerated
        sets' bounds), and for ``k > d`` ``min_{S0} [sup(S0) + π(S0)]`` plus the ``k - d``
        smallest prices of the column (``ps``: the cumulative sums; any ``k - d`` other
        members cost at least that)."""
        po = pi[self.o]
        out = np.empty(self.nc + 1)
        self._pi = pi.copy()
        self._arg = {}
        sums = [self._psum(po, k) for k in range(min(self.d, self.nc) + 1)]
        for k in range(min(self.d, self.nc) + 1):
            v = self.exact[k] + sums[k]
            i = int(np.argmin(v))
            self._arg[k] = i
            out[k] = float(v[i])
        if self.nc > self.d:
            v = self.sup + sums[self.d]
            i = int(np.argmin(v))
            self._arg[-1] = i
            base = float(v[i])
            out[self.d + 1 :] = base + ps[1 : self.nc - self.d + 1]
        for d0, sup in self.lower:  # every k > d0: above one of its d0-subsets
            if self.nc > d0:
                s0 = sums[d0] if d0 < len(sums) else self._psum(po, d0)
                base = float(np.min(sup + s0))
                out[d0 + 1 :] = np.fmax(out[d0 + 1 :], base + ps[1 : self.nc - d0 + 1])
        return out

    def _psum(self, po: Mat, k: int) -> Mat:
        """The prices of the enumerated ``k``-sets, ``po[sets[k]].sum(axis=1)`` bit for bit:
        for ``k <= 2`` by additions of the members' columns (the same one or two roundings,
        without the fancy-indexed ``(m, k)`` copy and the reduction: the dual steps' cost),
        else that expression."""
        if k == 0:
            return np.zeros(1)
        if k == 1:
            return po[self._cols[1][0]]
        if k == 2:
            c0, c1 = self._cols[2]
            return po[c0] + po[c1]
        return np.asarray(po[self.sets[k]].sum(axis=1))

    def members(self, pi: Mat, k: int) -> NDArray[np.intp] | None:
        """A minimiser's members for count ``k`` (global sensor indices)."""
        po = pi[self.o]
        # :meth:`cost`'s argmins at these prices (the dual steps: the same prices)
        cached = self._pi is not None and np.array_equal(self._pi, pi)
        if k <= self.d:
            if cached:
                i = self._arg[k]
            else:
                i = int(np.argmin(self.exact[k] + po[self.sets[k]].sum(axis=1)))
            return np.asarray(self.o[self.sets[k][i]])
        if cached:
            i = self._arg[-1]
        else:
            i = int(np.argmin(self.sup + po[self.sets[self.d]].sum(axis=1)))
        first = self.sets[self.d][i]
        keep = np.ones(self.o.size, dtype=bool)
        keep[first] = False
        rest = np.flatnonzero(keep)  # np.setdiff1d(arange, first): sorted, the same
        order = rest[np.lexsort((rest, po[rest]))][: k - self.d]
        return np.asarray(self.o[np.concatenate((first, order))])


def _floors(
    dual: _Dual,
    upper: Mat,
    remaining: Callable[[], float],
    min_s: float = FLOOR_MIN_S,
    slice_s: float | None = None,
    clock: Callable[[], float] | None = None,
    rooted: bool = False,
    part: float = 0.0,
) -> int:
    """The single-target floors (module docstring): the target columns in decreasing slack
    (the incumbent's weighted value less the column's least bound), each decided by the
    single-target bounded search (:func:`~covnet.core.allocation.search.allocate_bnb`, its
    allowed sensors, ``FLOOR_GAP``, an equal share of the time left) while ``FLOOR_MIN_S``
    and ``FLOOR_MARGIN`` times the previous one's time are left; its certified lower bound,
    weighted, is the column's floor (the larger of it and one there already).  A column with
    a floor is skipped (the timed plan's first round), unless ``rooted`` (round mt13: after
    the root floors, which leave one) or its search stopped at its time limit
    (:attr:`_Dual.cut`, round mt15: trace_diff's single-target bound is 0 until its search
    ends, about 8-10 ms of CPU at N = 64, and the first round's shares of 6-8 ms cut it on the
    targets that hold the gap).  Round mt15: with ``part > 0`` only the columns holding at
    least that share of the summed slack (and some slack: a column at its bound gains
    nothing); the first round (``slice_s``) stops where a share would be below what the last
    floor took (left to the second round, with more time).  Returns how many ran."""
    cs = dual.cs
    inp = cs.inp
    metric = inp.entry.name if inp.entry is not None else inp.f
    slack = []
    for c in range(cs.T):
        col = cs.cols[c]
        # a metric without an interval bound would be searched exhaustively: no floor
        if math.isfinite(dual.floor[c]) and not rooted and c not in dual.cut:
            continue  # floored already, its search to its end (the timed plan's first round)
        if isinstance(col, _TargetCol) and dual._bounded(col) and dual.opts[c].size:
            least = float(dual._cost(c, np.zeros(cs.N))[0][1:].min(initial=math.inf))
            slack.append((-(float(upper[c]) - least), c))
    if part > 0.0:  # round mt15: none where it cannot raise much
        total = sum(max(-g, 0.0) for g, _ in slack)
        slack = [(g, c) for g, c in slack if -g > 0.0 and -g >= part * total]
    done = 0
    last = 0.0
    order = [c for _, c in sorted(slack)]
    for i, c in enumerate(order):
        left = remaining()
        if left < max(min_s, FLOOR_MARGIN * last):
            break  # its set-up is not timed: the last one's time says what one costs
        excl = frozenset(int(j) for j in np.flatnonzero(~cs.allow[c]))
        share = left / (len(order) - i) if slice_s is None else min(slice_s, left - min_s)
        if slice_s is not None and share < last:
            break  # round mt15: less than the last one took: left to the second round
        res = allocate_bnb(
            inp.P_pred[c], inp.J[:, c], inp.D[c], metric, Constraints(excl), inp.tie_rtol,
            rel_gap=FLOOR_GAP, time_limit_s=share, clock=clock,
        )  # fmt: skip
        if math.isfinite(res.lower_bound):
            dual.floor[c] = max(dual.floor[c], float(cs.w[c]) * res.lower_bound)
        if res.status == 2:
            dual.cut.add(c)
        else:
            dual.cut.discard(c)
        done += 1
        last = left - remaining()
    return done


def _slack_columns(
    dual: _Dual, upper: Mat, pi: Mat, usable: Callable[[_Problem], bool]
) -> dict[int, float]:
    """The target columns worth a root floor or vertex rows at the prices ``pi``: their slack
    (``upper[c]`` less the column's least bound), by column, where the column is bounded, has
    options and a problem ``usable`` says yes to, the slack is above ``ROOT_FLOOR_SLACK`` of
    ``|upper[c]|`` and at least ``ROOT_FLOOR_PART`` of those columns' summed slack."""
    cs = dual.cs
    gaps: dict[int, float] = {}
    for c in range(cs.T):
        col = cs.cols[c]
        if not (isinstance(col, _TargetCol) and dual._bounded(col) and dual.opts[c].size):
            continue
        if col.prob is None or not usable(col.prob):
            continue
        gap = float(upper[c]) - float(dual._cost(c, pi)[0].min(initial=math.inf))
        if gap > ROOT_FLOOR_SLACK * abs(float(upper[c])):
            gaps[c] = gap
    total = sum(gaps.values())
    return {c: g for c, g in gaps.items() if g >= ROOT_FLOOR_PART * total}


def _root_floors(
    dual: _Dual,
    upper: Mat,
    remaining: Callable[[], float],
    min_s: float,
    pi: Mat | None = None,
) -> int:
    """The *root floors* (the timed plan, for the metrics without ``Metric.floors_first``):
    per target column, the largest slack first (the incumbent's weighted value less the
    column's least bound at zero prices; none where that is below ``ROOT_FLOOR_SLACK`` of the
    incumbent's value), the single-target problem's root bound
    (:meth:`~covnet.core.allocation.search_problem._Problem.root_bound`: the interval
    ``[P(F_c), P(∅)]`` raised by the metric's relaxation or dual bound; only where the column
    has one), weighted, is the column's floor, while at least ``min_s`` seconds are left.
    **Proof**: every ``S ⊆ F_c`` has ``Z(∅) ⪯ Z(S) ⪯ Z(F_c)``, so ``g_c(S)`` is at least the
    root interval's bound (the single-target search's own root), and the floor's use in the
    dual (``b_c(k, π) >= w_c ℓ_c + π_c(k)``, :func:`_floors`) holds for any ``ℓ_c <= min_S
    g_c(S)``.  At N = 64, T = 8 one costs 6-9 ms of CPU (spectral, the norms, abs_trace)
    against at least ``FLOOR_MIN_S`` for a single-target search, and it gives the light
    targets most of what that search does.  A running root's barrier stops at the deadline
    (its bound so far, valid).  Returns how many ran."""
    cs = dual.cs
    zero = np.zeros(cs.N) if pi is None else pi
    # the root's interval bound alone: the depth-1 bounds have it already
    gaps = _slack_columns(dual, upper, zero, lambda p: p.dual is not None or p.relax is not None)
    done = 0

    for c in sorted(gaps, key=lambda c: -gaps[c] / max(abs(float(upper[c])), TINY)):
        if remaining() < min_s:
            break
        col = cs.cols[c]
        assert isinstance(col, _TargetCol) and col.prob is not None
        prob = col.prob
        iters = ROOT_ITERS_OF.get(prob.name, ROOT_ITERS) if prob.name is not None else ROOT_ITERS
        prob.stop = _iterations(iters, lambda: remaining() < 0.0)
        try:
            root = prob.root_bound()
        finally:
            prob.stop = None
        if math.isfinite(root):
            dual.floor[c] = max(dual.floor[c], float(cs.w[c]) * max(root, 0.0))
        done += 1
    return done


def _vertex_rows(
    dual: _Dual,
    upper: Mat,
    pi: Mat,
    deadline: Callable[[], bool] | None,
) -> int:
    """Round mt15 (the timed plan, with the root floors, for the metrics whose dual bound has
    a vertex bound: one_norm, inf_norm, abs_trace): at the prices ``pi``, per target column
    the largest slack first (``upper[c]``, the incumbent's weighted value plus its set's
    prices, less the column's least bound; only the columns holding at least
    ``ROOT_FLOOR_PART`` of the summed slack, and above ``ROOT_FLOOR_SLACK`` of their
    incumbent), the column's intervals raised by the vertex bound (:meth:`_Dual.vertex`, at
    most ``VERTEX_ROWS`` rows a column), while the deadline allows.  Each raised row is a bound
    of its own interval (:meth:`_Rows.vertex`), so the dual function stays ``<= F*``.  At
    N = 64, T = 8 (one_norm) the heavy targets whose best set has one sensor hold most of the
    gap on one problem in five, at ``k >= 3`` where the pairs' superset intervals bound it
    (141 against 157): the vertex bound closes them for about 500 rows, 6 ms of CPU.
    Returns how many rows were raised."""
    gaps = _slack_columns(
        dual, upper, pi, lambda p: p.dual is not None and p.dual.dual.vertices is not None
    )
    done = 0
    for c in sorted(gaps, key=lambda c: -gaps[c]):
        if deadline is not None and deadline():
            break
        done += dual.vertex(c, pi, VERTEX_ROWS, deadline)
    return done


def _expand_rows(dual: _Dual, pi: Mat, deadline: Callable[[], bool] | None) -> int:
    """Round at16 (the timed plan, with the root floors; the columns with chain rows,
    ``Metric.chain_rows``): at the prices ``pi`` every such column's deepest chain rows
    expanded by their next member (:meth:`_Dual.expand`, at most ``EXPAND_ROWS`` a column),
    while the deadline allows.  Each expanded row bounds its own class of sets (that method's
    proof), so the dual function stays ``<= F*``.  Returns how many rows were expanded."""
    done = 0
    for c in sorted(dual.chain_pos):  # none: no clock reading, the other metrics' plan as before
        if deadline is not None and deadline():
            break
        done += dual.expand(c, pi, EXPAND_ROWS, deadline)
    return done


def _iterations(n: int, out: Callable[[], bool]) -> Callable[[], bool]:
    """A ``stop`` for :attr:`_Problem.stop` that says so after ``n`` readings (the barrier
    and the relaxation read it once an iteration) or once ``out()``."""
    calls = itertools.count()

    def stop() -> bool:
        return next(calls) >= n or out()

    return stop


def _dual_bound(
    dual: _Dual,
    upper: float,
    steps: int,
    target_gap: float,
    deadline: Callable[[], bool] | None,
    mid: Callable[[Mat], object] | None = None,
    mid_when: Callable[[], bool] | None = None,
    pi0: Mat | None = None,
    best_out: list[Mat] | None = None,
) -> tuple[float, int]:
    """The best ``L(π)`` over ``steps`` subgradient steps from ``π = 0`` (Polyak steps towards
    ``upper``, ``θ`` halved after 5 steps without progress); stops early at ``target_gap``.
    ``mid`` (the timed plan's root floors, round mt12): called once with the best prices so
    far when ``mid_when()`` or ``θ <= MID_THETA`` (the steps stall); it may only raise the
    columns' bounds, so the steps go on from where they are, the best ``L`` re-evaluated.
    ``pi0`` (round mt13): start from these prices (``>= 0``) instead; ``best_out``: the best
    prices are appended to it.  Every ``L(π)`` with ``π >= 0`` is a bound, whatever the start."""
    pi = np.zeros(dual.cs.N) if pi0 is None else pi0
    best, counts = dual.value(pi)
    best_pi = pi
    n = 1
    theta, stall = 1.0, 0
    while n < steps and _gap(upper, best) > target_gap and theta > 1e-4:
        if deadline is not None and deadline():
            break
        if mid is not None and (theta <= MID_THETA or (mid_when is not None and mid_when())):
            mid(best_pi)
            mid = None
            best = max(best, dual.value(best_pi)[0])
            _, counts = dual.value(pi)
            if deadline is not None and deadline():
                break
        g = dual.subgradient(pi, counts)
        g = np.where((pi <= 0) & (g < 0), 0.0, g)
        nrm = float(g @ g)
        if nrm == 0.0:
            break
        step = theta * max(upper - best, 1e-12 * max(abs(upper), TINY)) / nrm
        pi = np.maximum(pi + step * g, 0.0)
        val, counts = dual.value(pi)
        n += 1
        if val > best:
            best, stall, best_pi = val, 0, pi
        else:
            stall += 1
            if stall >= 5:
                theta, stall = theta / 2.0, 0
    if best_out is not None:
        best_out.append(best_pi)
    return best, n


# --------------------------------------------------------------------------------------------
# the entry points
# --------------------------------------------------------------------------------------------


def _deadline(
    time_limit_s: float | None, clock: Callable[[], float] | None
) -> tuple[Callable[[], bool] | None, Callable[[], float] | None]:
    """``deadline()`` (the time is up) and ``remaining()`` (seconds left); ``None`` without a
    limit."""
    if time_limit_s is None:
        return None, None
    if not time_limit_s >= 0:
        raise ValueError(f"time_limit_s must be >= 0 or None, got {time_limit_s}")
    if clock is None:
        # only with a time limit (start-up: the core needs no clock otherwise)
        import time

        clock = time.perf_counter
    tick = clock
    t_end = tick() + time_limit_s

    def deadline() -> bool:
        return tick() >= t_end

    def remaining() -> float:
        return t_end - tick()

    return deadline, remaining


def _search(
    inp: _Inputs,
    rel_gap: float,
    steps: int,
    deadline: Callable[[], bool] | None,
    status_done: int,
    fallback: bool,
    refine_rows: int = REFINE_ROWS,
    remaining: Callable[[], float] | None = None,
    clock: Callable[[], float] | None = None,
    time_limit_s: float | None = None,
) -> AssignmentSearch:
    try:
        cs = _Columns(inp)
        st = _State(cs)
        _forward(st)
        _local_search(st, None)  # to its end: never worse than the plain greedy with 1-swaps
        timed = remaining is not None and time_limit_s is not None
        m = int(cs.allow.any(axis=0).sum())
        few = inp.cells is None or (inp.T + inp.C + 1) ** m <= EXACT_FALLBACK_CELLS
        exact_next = fallback and m <= min(EXACT_FALLBACK, MAX_SENSORS) and few
        # the kicks where the exact allocator would not decide next, for the metrics whose
        # bound settles early (Metric.kicks)
        kicks = timed and not exact_next and inp.entry is not None and inp.entry.kicks
        dual = _Dual(cs, refine_rows=refine_rows, deadline=deadline, upper=cs.w * st.v, timed=timed)
        if timed:
            assert remaining is not None and time_limit_s is not None
            min_s, slice_s = TIMED_FLOOR_MIN * time_limit_s, TIMED_FLOOR_SLICE * time_limit_s
            keep = (1.0 - TIMED_FLOOR_SHARE) * remaining()
            rem = remaining

            def first() -> float:
                return rem() - keep

            if inp.entry is not None and inp.entry.floors_first:  # Metric.floors_first
                _floors(dual, cs.w * st.v, first, min_s, slice_s, clock, part=FLOOR_PART)
            dual.deepen(deadline, cs.w * st.v, remaining)
        if _enum_moves(st, dual, deadline):
            _local_search(st, deadline)
        if timed:  # br16: ejection chains, then the local search again
            _chain_moves(st, deadline)
        # mt20: the kicks only while KICK_MIN_LEFT of the limit is left (a slower machine
        # gives the bound the time it needs before the incumbent's polish)
        if (
            kicks
            and deadline is not None
            and remaining is not None
            and time_limit_s is not None
            and remaining() >= KICK_MIN_LEFT * time_limit_s
        ):
            stop_at = (1.0 - KICK_SHARE) * remaining()  # the kicks: their share of what is left
            st, _ = _kicks(st, lambda: deadline() or remaining() <= stop_at,
                           np.random.default_rng(KICK_SEED))  # fmt: skip
        a = [int(x) for x in st.a]
        F, values, Ps, gs = cs.exact(a)
        rooted = any(isinstance(col, _TargetCol) and col.prob is not None
                     and (col.prob.dual is not None or col.prob.relax is not None)
                     for col in cs.cols)  # fmt: skip
        roots = timed and rooted and inp.entry is not None and not inp.entry.floors_first
        if timed and not roots:  # with root floors the second round comes after the steps
            part = FLOOR_PART if inp.entry is not None and inp.entry.floors_first else 0.0
            _floors(dual, cs.w * st.v, rem, FLOOR_MIN_S, None, clock, part=part)  # the second
        mid: Callable[[Mat], object] | None = None
        mid_when: Callable[[], bool] | None = None
        if roots:  # mt12
            assert time_limit_s is not None
            # mt20: the roots once half the steps' time is spent, or ROOT_START_SHARE of the
            # limit is all that is left, whichever comes first
            half = max(ROOT_FLOOR_AFTER * rem(), ROOT_START_SHARE * time_limit_s)
            min_s = min(ROOT_FLOOR_MIN * time_limit_s, ROOT_FLOOR_MIN_CAP)

            def mid_when() -> bool:
                return rem() < half

            def mid(pi: Mat) -> int:
                upper = cs.w * st.v + np.array([float(pi[s].sum()) for s in st.sets])
                done = _root_floors(dual, upper, rem, min_s, pi)
                _expand_rows(dual, pi, deadline)  # at16: the chain rows' next members
                _vertex_rows(dual, upper, pi, deadline)  # mt15: where the roots left slack
                return done

        best_pi: list[Mat] = []
        L, n_steps = _dual_bound(dual, F, steps, rel_gap, deadline, mid, mid_when, None, best_pi)
        if roots and n_steps < steps and _gap(F, L) > rel_gap:
            # round mt13: the second round of floors after the steps stall, in the time they
            # leave (N = 256), then the steps again from their best prices
            if _floors(dual, cs.w * st.v, rem, FLOOR_MIN_S, None, clock, True):
                L2, n2 = _dual_bound(dual, F, steps - n_steps, rel_gap, deadline, pi0=best_pi[0])
                L, n_steps = max(L, L2), n_steps + n2
        nothing = cs.exact([OFF] * cs.N)[0]
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    L = min(L, F)
    n_nodes = cs.moves + n_steps
    gap = _gap(F, L)
    if exact_next and gap > rel_gap:
        if deadline is None or not deadline():
            ex = allocate_assignments(
                inp.P_pred, inp.J, inp.D, inp.f, inp.w, inp.feasible,
                _constraints(inp), inp.tie_rtol, inp.cells,
            )  # fmt: skip
            return AssignmentSearch(
                ex.assignment, ex.sets, ex.value, ex.values, ex.cell_values, ex.P, ex.value,
                0.0, nothing, 0.0, n_nodes, ex.n_evaluated, True, 0, STATUS[0],
            )  # fmt: skip
    if status_done == 4:
        status = 4
    elif gap <= rel_gap:
        status = 3
    elif deadline is not None and deadline():
        status = 2
    elif n_steps >= steps:
        status = 1 if steps < DUAL_STEPS else 5
    else:
        status = 5
    sets = tuple(tuple(j for j in range(cs.N) if a[j] == c) for c in range(cs.ncol))
    return AssignmentSearch(
        tuple(a), sets, F, tuple(values), tuple(gs), np.array(Ps), L, gap, nothing,
        _gap_nothing(F, L, nothing), n_nodes, inp.T, False, status, STATUS[status],
    )  # fmt: skip


def _constraints(inp: _Inputs) -> MultiConstraints:
    return MultiConstraints(
        inp.excluded, inp.required, inp.K, tuple(inp.caps) if inp.caps else None
    )


def allocate_assignments_greedy(
    P_pred: Mat,
    J: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    weights: Sequence[float] | Mat | None = None,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: MultiConstraints = NO_CONSTRAINTS,
    tie_rtol: float = 1e-9,
    *,
    cells: CellTerms | None = None,
) -> AssignmentSearch:
    """Forward greedy, best-improvement moves and 1-swaps, set moves (module docstring), the
    value exact, with the Lagrangian bound (count and enumeration bounds, the relaxation's
    refinement where the metric has one) after ``GREEDY_DUAL_STEPS`` dual steps (status 4).
    Arguments as :func:`~covnet.core.allocation.assignment.allocate_assignments`."""
    inp = _Inputs(P_pred, J, P_d, metric, weights, feasible, constraints, tie_rtol, cells)
    return _search(inp, 0.0, GREEDY_DUAL_STEPS, None, 4, False)


def allocate_assignments_bounded(
    P_pred: Mat,
    J: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    weights: Sequence[float] | Mat | None = None,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: MultiConstraints = NO_CONSTRAINTS,
    tie_rtol: float = 1e-9,
    *,
    cells: CellTerms | None = None,
    rel_gap: float = 0.01,
    time_limit_s: float | None = None,
    node_limit: int | None = None,
    clock: Callable[[], float] | None = None,
) -> AssignmentSearch:
    """Greedy, then dual steps until the certified relative gap is at most ``rel_gap``, the
    ``node_limit`` (dual steps) or ``time_limit_s`` (the whole decision; ``clock`` seconds,
    default ``time.perf_counter``); with the gap still open and at most ``EXACT_FALLBACK``
    allowed sensors, the exact allocator (status 0).  Never worse than the plain forward greedy
    with 1-swaps; without a time limit the same start as :func:`allocate_assignments_greedy`
    (so never worse than it), with one the set moves see only the sets enumerated in time."""
    if not (math.isfinite(rel_gap) and 0.0 <= rel_gap < 1.0):
        raise ValueError(f"rel_gap must be in [0, 1), got {rel_gap}")
    if node_limit is not None and (not isinstance(node_limit, int) or node_limit < 1):
        raise ValueError(f"node_limit must be an integer >= 1 or None, got {node_limit!r}")
    deadline, remaining = _deadline(time_limit_s, clock)
    inp = _Inputs(P_pred, J, P_d, metric, weights, feasible, constraints, tie_rtol, cells)
    steps = DUAL_STEPS if node_limit is None else min(node_limit, DUAL_STEPS)
    return _search(
        inp, rel_gap, steps, deadline, 3, True,
        remaining=remaining, clock=clock, time_limit_s=time_limit_s,
    )  # fmt: skip
