"""Multi-target covariance control: which target each sensor dwells on, or off (spec:
``multitarget.md`` §3).

An assignment ``a = (a_0..a_{N-1})``, ``a_j ∈ {OFF, 0..T-1}``, gives each target ``t``::

    P_t(a) = ((P_t⁻)⁻¹ + Σ_{j : a_j = t} J_{j,t})⁻¹

with the per-(sensor, target) information ``J_{j,t}`` (``(N, T, n, n)``, the caller's, already
scaled by the detection probability), and the decision is::

    a* = argmin_{a feasible}  F(a),    F(a) = Σ_t w_t · f(P_t(a), P_d,t).

**Feasible**: ``a_j = t`` only where ``feasible[j, t]`` (coverage); excluded sensors off;
required sensors on (any feasible target); at most ``max_active`` sensors on, at most
``max_per_target`` on each target; at least one sensor on (as the single-target problem, whose
subsets are non-empty).  The entries ``J[j, t]`` of infeasible pairs are ignored.

**Arithmetic** (both allocators, bit for bit): per target ``J_t = 0; J_t = J_t + J[j, t]`` over
its sensors in ascending index order, ``P_t = spd_inverse(spd_inverse(P_t⁻) + J_t)``
(:func:`covnet.core.allocation.subset_covariance`), ``v_t = f(P_t, P_d,t)``, and ``F = 0;
F = F + w_t · v_t`` over ``t = 0..T-1``.  Inputs are validated and symmetrised as the
single-target allocator does (per target).

**Tie rule**: among the assignments with ``F <= F* + tie_rtol · max(|F*|, tiny)``, the fewest
sensors on, then the lexicographically smallest vector ``(a_0..a_{N-1})`` under the order
``target 0 < target 1 < ... < target T-1 < OFF``.  For ``T = 1`` this is exactly the
single-target rule (among subsets of one size, the lexicographically smallest ascending index
tuple is the one that has the lowest index where two differ, i.e. *on* before *off*; note that
the order ``OFF < target 0 < ...`` the spec names would pick the opposite for ``T = 1``).

**Search cells** (spec ``surveillance.md`` §3-4; optional, ``cells``: a :class:`CellTerms`):
``C`` extra columns a sensor may be assigned to (``feasible[j, c]``), each scored by the set
``S_c`` of sensors searching it::

    g_c(S) = λ · u_c · Π_{j∈S} (1 - pd_j)   (>= 0),

which is the spec's term ``-λ u_c (1 - Π_{j∈S}(1 - pd_j))`` plus the constant ``λ u_c``
(``-λ u_c (1 - Π) = λ u_c Π - λ u_c``): the same minimiser, and every term stays ``>= 0`` (the
bounds' and the tie threshold's premise).  The decision is then ``argmin Σ_t w_t v_t +
Σ_c g_c(S_c)``; ``a_j = T + c`` means sensor ``j`` searches cell ``c`` (the result's assignment
uses indices ``T..T+C-1`` for cells, ``sets`` has ``T + C`` entries, ``values`` the ``T`` targets'
``v_t`` and ``cell_values`` the ``g_c``).  Arithmetic: ``g = λ · u_c; g = g · miss[j, c]`` over
``S_c`` ascending, added after the targets: ``F = F + g_c`` for ``c = 0..C-1``.  A cell counts as
*on* (budget, required sensors, at least one on); ``max_per_target`` limits targets only; tie
order ``targets < cells < OFF``.  Without cells every result is as before, bit for bit.

Two implementations return the same :class:`Assignment`:

- :func:`allocate_assignments_exhaustive`: the plain reference, a loop over every assignment of
  ``{OFF} ∪ feasible targets`` per sensor, one information-form solve and one metric call per
  target each;
- :func:`allocate_assignments`: exact and fast, from the structure of ``F``.  Once the sensor
  sets ``S_t = {j : a_j = t}`` are fixed ``F = Σ_t w_t g_t(S_t)`` separates over targets.  For
  every target a table of *lower bounds* ``L_t(S) <= g_t(S)`` of every subset of its feasible
  sensors (the reduced information form and the degenerate-interval bounds of
  :mod:`covnet.core.allocation.interval_bounds`, batched: no metric call), then a dynamic programme
  over the
  set ``R`` of sensors still free (``H_t(R) = min_{S ⊆ R} w_t L_t(S) + H_{t+1}(R - S)``, a
  min-plus subset convolution, ``O(3^N)``; the last stage holds the constraints on the sensors
  left off), gives a lower bound of every completion of a partial assignment.  The bound's
  optimum is evaluated exactly (the incumbent ``U``), every assignment whose bound does not
  exceed ``τ = U + tie_rtol · max(|U|, tiny)`` is enumerated (each step of the enumeration keeps
  only prefixes with a completion below ``τ``), evaluated exactly per (target, set), and the tie
  rule runs on the reference's values.  As ``0 <= F* <= U`` and every bound is below the value it
  bounds (nonnegative terms: the sums' rounding is covered by a relative ``16 T eps`` on ``τ``),
  no member of the reference's tie set is missed.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation._fast import gain_sums, spd_inverse, tie_threshold
from covnet.core.allocation.exact import (
    Constraints,
    InfeasibleAllocation,
    _check_rtol,
    _checked_pd,
    _prepare,
    _resolve_metric,
    _spd_error,
    subset_covariance,
)
from covnet.core.allocation.search_problem import _Problem
from covnet.core.gaussian import Mat
from covnet.core.metrics import MetricFn

__all__ = [
    "OFF",
    "Assignment",
    "CellTerms",
    "MultiConstraints",
    "TooManySensors",
    "allocate_assignments",
    "allocate_assignments_exhaustive",
]

#: ``a_j = OFF``: sensor ``j`` dwells on no target
OFF = -1
TINY = float(np.finfo(np.float64).tiny)
EPS = float(np.finfo(np.float64).eps)
#: the fast allocator keeps tables of ``2^N`` entries: at most this many allowed sensors
MAX_SENSORS = 22
#: the subset convolution enumerates its (subset, rest) pairs in chunks of about this many, or
#: from one cached table of all ``3^m`` pairs up to this many sensors
PAIR_CHUNK = 1 << 17
PAIR_TABLE_BITS = 12


class TooManySensors(ValueError):
    """The exact assignment search cannot enumerate this many sensors (``MAX_SENSORS``)."""


@dataclass(frozen=True, slots=True)
class MultiConstraints:
    """Which assignments are feasible (besides coverage, ``feasible``):

    - ``excluded``: sensors always off; ``required``: sensors always on (any feasible target);
    - ``max_active``: at most this many sensors on in total (``None``: no budget);
    - ``max_per_target``: at most this many on each target (an int for every target, or one per
      target; ``None``: no limit).
    """

    excluded: frozenset[int] = frozenset()
    required: frozenset[int] = frozenset()
    max_active: int | None = None
    max_per_target: int | tuple[int, ...] | None = None


NO_CONSTRAINTS = MultiConstraints()


@dataclass(frozen=True)
class CellTerms:
    """Search cells (module docstring): ``u`` ``(C,)`` the expected undetected targets per cell
    (``>= 0``), ``weight`` ``λ >= 0`` (in units of the metric), ``miss`` ``(N, C)`` the
    probability ``1 - pd_j`` that sensor ``j`` searching cell ``c`` misses a target there (in
    ``[0, 1]``), ``feasible`` ``(N, C)`` which sensor may search which cell (its coverage)."""

    u: NDArray[np.float64]
    weight: float
    miss: NDArray[np.float64]
    feasible: NDArray[np.bool_]

    @property
    def C(self) -> int:
        return int(np.asarray(self.u).shape[0])


def _checked_cells(cells: CellTerms | None, N: int) -> CellTerms | None:
    """Validated cells (shapes, ranges), arrays copied; ``None`` or no cell: ``None``."""
    if cells is None:
        return None
    if not isinstance(cells, CellTerms):
        raise TypeError(f"cells must be a CellTerms or None, got {type(cells)}")
    u = np.array(cells.u, dtype=np.float64)
    if u.ndim != 1 or not (np.isfinite(u).all() and (u >= 0).all()):
        raise ValueError(f"cells.u must be (C,) finite numbers >= 0, got {cells.u!r}")
    C = u.shape[0]
    lam = float(cells.weight)
    if not (math.isfinite(lam) and lam >= 0.0):
        raise ValueError(f"cells.weight must be a finite number >= 0, got {cells.weight!r}")
    miss = np.array(cells.miss, dtype=np.float64)
    if miss.shape != (N, C) or not (np.isfinite(miss).all() and (miss >= 0).all()):
        raise ValueError(f"cells.miss must be ({N}, {C}) numbers in [0, 1], got {miss.shape}")
    if (miss > 1).any():
        raise ValueError(f"cells.miss must be ({N}, {C}) numbers in [0, 1] (1 - pd)")
    feas = np.asarray(cells.feasible)
    if feas.shape != (N, C) or feas.dtype != np.bool_:
        raise ValueError(f"cells.feasible must be a ({N}, {C}) boolean array, got {feas.shape}")
    if C == 0:
        return None
    return CellTerms(u, lam, miss, feas.copy())


@dataclass(frozen=True, slots=True)
class Assignment:
    """The chosen assignment of one multi-target decision.

    ``assignment``: ``a_j`` per sensor (a target index or :data:`OFF`); ``sets``: each target's
    sensors, ascending; ``value``: ``F = Σ_t w_t v_t`` (the module's arithmetic); ``values``: the
    per-target ``v_t = f(P_t, P_d,t)``; ``P``: ``(T, n, n)`` the targets' covariances;
    ``n_candidates``: assignments whose ``F`` was computed exactly; ``n_evaluated``: exact
    per-target evaluations (one solve and one metric call each); ``n_feasible``: the number of
    feasible assignments (the reference counts them; ``None`` for the fast path).  With search
    cells (:class:`CellTerms`): ``a_j = T + c`` for cell ``c``, ``sets`` has ``T + C`` entries
    and ``cell_values`` the ``g_c`` (empty without cells).
    """

    assignment: tuple[int, ...]
    sets: tuple[tuple[int, ...], ...]
    value: float
    values: tuple[float, ...]
    P: NDArray[np.float64]
    n_candidates: int
    n_evaluated: int
    n_feasible: int | None
    cell_values: tuple[float, ...] = ()

    @property
    def n_active(self) -> int:
        return sum(a != OFF for a in self.assignment)


# --------------------------------------------------------------------------------------------
# validation, shared by both allocators
# --------------------------------------------------------------------------------------------


class _Inputs:
    """Validated inputs: ``P_pred``, ``P_d`` ``(T, n, n)`` symmetrised; ``J`` ``(N, T, n, n)``
    symmetrised, zero on infeasible pairs; ``w`` the weights (Python floats); ``feasible``
    ``(N, T)``; ``f`` the metric; ``options[j]``: the values ``a_j`` may take, in tie order
    (targets ascending, then ``OFF``); ``K`` the budget; ``caps`` per-target limits."""

    def __init__(
        self,
        P_pred: Mat,
        J: Mat,
        P_d: Mat,
        metric: str | MetricFn,
        weights: Sequence[float] | Mat | None,
        feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None,
        constraints: MultiConstraints,
        tie_rtol: float,
        cells: CellTerms | None = None,
    ) -> None:
        Pp = np.asarray(P_pred, dtype=np.float64)
        if Pp.ndim != 3 or Pp.shape[1] != Pp.shape[2] or Pp.shape[1] == 0:
            raise ValueError(f"P_pred must be (T, n, n) (one per target), got shape {Pp.shape}")
        # no target (a surveillance scan before its first track): only search cells
        if Pp.shape[0] == 0 and (cells is None or np.asarray(cells.u).shape[0] == 0):
            raise ValueError("P_pred: no target and no search cell, nothing to allocate")
        T, n = Pp.shape[0], Pp.shape[1]
        Dd = np.asarray(P_d, dtype=np.float64)
        if Dd.shape != (T, n, n):
            raise ValueError(f"P_d must be ({T}, {n}, {n}) like P_pred, got shape {Dd.shape}")
        Jj = np.asarray(J, dtype=np.float64)
        if Jj.ndim != 4 or Jj.shape[1:] != (T, n, n):
            raise ValueError(f"J must be (N, {T}, {n}, {n}) (one J_jt per pair), got {Jj.shape}")
        N = Jj.shape[0]
        if feasible is None:
            feas = np.ones((N, T), dtype=bool)
        else:
            feas = np.asarray(feasible)
            if feas.shape != (N, T) or feas.dtype != np.bool_:
                raise ValueError(f"feasible must be a ({N}, {T}) boolean array, got {feas.shape}")
        if weights is None:
            w = np.ones(T)
        else:
            w = np.asarray(weights, dtype=np.float64)
            if w.shape != (T,) or not (np.isfinite(w).all() and (w > 0).all()):
                raise ValueError(f"weights must be {T} finite positive numbers, got {weights!r}")
        self.f, self.entry = _resolve_metric(metric)
        _check_rtol(tie_rtol)
        if not isinstance(constraints, MultiConstraints):
            raise TypeError(f"constraints must be a MultiConstraints, got {type(constraints)}")
        Jz = np.where(feas[:, :, None, None], Jj, 0.0)
        P_list, D_list, G_list = [], [], []
        for t in range(T):
            P_t, D_t = _checked_pd(Pp[t], Dd[t])
            # per target: the single-target validation (shape, finiteness, symmetry, PSD)
            G_t = _prepare(Jz[:, t], Constraints(), tables=False).gains if N else Jz[:, t]
            P_list.append(P_t)
            D_list.append(D_t)
            G_list.append(G_t)
        self.P_pred = np.array(P_list).reshape(T, n, n)
        self.D = np.array(D_list).reshape(T, n, n)
        self.J = np.stack(G_list, axis=1) if N and T else Jz
        self.w = [float(x) for x in w]
        self.feasible = feas
        self.N, self.T, self.n = N, T, n
        self.cells = _checked_cells(cells, N)
        self.C = 0 if self.cells is None else self.cells.C
        cfeas = np.zeros((N, 0), dtype=bool) if self.cells is None else self.cells.feasible
        self.tie_rtol = float(tie_rtol)
        c = constraints
        for label, idx in (("excluded", c.excluded), ("required", c.required)):
            bad = sorted(
                str(j)
                for j in idx
                if not isinstance(j, Integral) or isinstance(j, bool) or not 0 <= j < N
            )
            if bad:
                raise ValueError(
                    f"{label} sensor indices must be integers in [0, {N}), got {', '.join(bad)}"
                )
        both = c.excluded & c.required
        if both:
            raise ValueError(f"sensors {sorted(both)} are both excluded and required")
        K = c.max_active
        if K is not None:
            if not isinstance(K, Integral) or isinstance(K, bool) or K < 1:
                raise ValueError(f"max_active must be an integer >= 1 or None, got {K!r}")
            if K < len(c.required):
                raise ValueError(
                    f"max_active={K} is smaller than the {len(c.required)} required sensors "
                    f"{sorted(c.required)}"
                )
        self.K = N if K is None else int(K)
        cap = c.max_per_target
        caps: list[object]
        if cap is None:
            caps = [N] * T
        elif isinstance(cap, Integral) and not isinstance(cap, bool):
            caps = [int(cap)] * T
        elif isinstance(cap, tuple | list):
            caps = list(cap)
        else:
            caps = []
        if len(caps) != T or any(
            not isinstance(x, Integral) or isinstance(x, bool) or x < 0 for x in caps
        ):
            raise ValueError(
                f"max_per_target must be an integer >= 0, {T} of them, or None, got {cap!r}"
            )
        self.caps = [int(x) for x in caps if isinstance(x, Integral)]
        self.excluded, self.required = c.excluded, c.required
        self.options: list[list[int]] = []
        for j in range(N):
            targets = [] if j in c.excluded else [t for t in range(T) if feas[j, t]]
            if j not in c.excluded:
                targets += [T + k for k in range(self.C) if cfeas[j, k]]
            if j in c.required:
                if not targets:
                    raise InfeasibleAllocation(f"required sensor {j} has no feasible target")
                self.options.append(targets)
            else:
                self.options.append(targets + [OFF])
        if N == 0:
            raise InfeasibleAllocation("no sensors: J is empty, so no assignment has one on")
        if all(opts == [OFF] for opts in self.options):
            raise InfeasibleAllocation("no sensor has a feasible target (excluded or no coverage)")

    def target_value(self, t: int, sensors: Sequence[int]) -> tuple[float, Mat]:
        """``v_t`` and ``P_t`` of target ``t`` with ``sensors`` (ascending): the reference's
        arithmetic, one solve and one metric call."""
        Jt = np.zeros((self.n, self.n))
        for j in sensors:
            Jt = Jt + self.J[j, t]
        P_t = subset_covariance(self.P_pred[t], Jt)
        v = float(np.asarray(self.f(P_t, self.D[t]), dtype=np.float64))
        if not math.isfinite(v):
            raise ValueError(f"metric returned a non-finite value for target {t}, {tuple(sensors)}")
        return v, P_t

    def cell_value(self, c: int, sensors: Sequence[int]) -> float:
        """``g_c = λ · u_c``, then ``g = g · miss[j, c]`` over ``sensors`` (ascending)."""
        assert self.cells is not None
        g = self.cells.weight * float(self.cells.u[c])
        for j in sensors:
            g = g * float(self.cells.miss[j, c])
        return g

    def total(self, values: Sequence[float], cell_values: Sequence[float] = ()) -> float:
        """``F = 0; F = F + w_t v_t`` over the targets in order, then ``F = F + g_c`` over the
        cells."""
        F = 0.0
        for t in range(self.T):
            F = F + self.w[t] * values[t]
        for g in cell_values:
            F = F + g
        return F

    def tie_key(self, a: Sequence[int]) -> tuple[int, tuple[int, ...]]:
        """Sort key of the tie rule: sensors on, then the vector with ``OFF`` after every
        target and cell."""
        off = self.T + self.C
        return (sum(x != OFF for x in a), tuple(off if x == OFF else x for x in a))


def _result(
    inp: _Inputs,
    a: Sequence[int],
    values: Sequence[float],
    P: Sequence[Mat],
    n_candidates: int,
    n_evaluated: int,
    n_feasible: int | None,
    cell_values: Sequence[float] = (),
) -> Assignment:
    sets = tuple(tuple(j for j in range(inp.N) if a[j] == t) for t in range(inp.T + inp.C))
    return Assignment(
        tuple(int(x) for x in a),
        sets,
        inp.total(values, cell_values),
        tuple(float(v) for v in values),
        np.array(P),
        n_candidates,
        n_evaluated,
        n_feasible,
        tuple(float(g) for g in cell_values),
    )


# --------------------------------------------------------------------------------------------
# the plain reference
# --------------------------------------------------------------------------------------------


def allocate_assignments_exhaustive(
    P_pred: Mat,
    J: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    weights: Sequence[float] | Mat | None = None,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: MultiConstraints = NO_CONSTRAINTS,
    tie_rtol: float = 1e-9,
    cells: CellTerms | None = None,
) -> Assignment:
    """The plain reference: every assignment (each sensor off or on one of its feasible
    targets or cells) in turn, the feasible ones scored with the module's arithmetic (``T``
    solves and metric calls each, and the cells' products), then the tie rule.
    ``(T+C+1)^N`` assignments: for small problems and tests; :func:`allocate_assignments`
    returns the same."""
    inp = _Inputs(P_pred, J, P_d, metric, weights, feasible, constraints, tie_rtol, cells)
    best: list[tuple[float, tuple[int, ...], list[float], list[Mat], list[float]]] = []
    n_feasible = 0
    try:
        for a in itertools.product(*inp.options):
            on = [x for x in a if x != OFF]
            if not on or len(on) > inp.K:
                continue
            counts = [on.count(t) for t in range(inp.T)]
            if any(counts[t] > inp.caps[t] for t in range(inp.T)):
                continue
            values, Ps = [], []
            for t in range(inp.T):
                v, P_t = inp.target_value(t, [j for j in range(inp.N) if a[j] == t])
                values.append(v)
                Ps.append(P_t)
            gs = [
                inp.cell_value(c, [j for j in range(inp.N) if a[j] == inp.T + c])
                for c in range(inp.C)
            ]
            n_feasible += 1
            best.append((inp.total(values, gs), a, values, Ps, gs))
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    if not best:
        raise InfeasibleAllocation("no assignment satisfies the constraints")
    F_star = min(b[0] for b in best)
    thr = tie_threshold(F_star, inp.tie_rtol)
    F, a, values, Ps, gs = min((b for b in best if b[0] <= thr), key=lambda b: inp.tie_key(b[1]))
    n_eval = n_feasible * inp.T
    return _result(inp, a, values, Ps, n_feasible, n_eval, n_feasible, gs)


# --------------------------------------------------------------------------------------------
# the fast exact allocator
# --------------------------------------------------------------------------------------------


def _popcount(x: NDArray[np.int64]) -> NDArray[np.int64]:
    c = np.zeros(x.shape, dtype=np.int64)
    y = x.copy()
    while y.any():
        c += y & 1
        y >>= 1
    return c


def _submasks(mask: int, m: int) -> NDArray[np.int64]:
    """Every subset of the bit set ``mask`` (bits below ``m``), as an ascending array."""
    bits = [b for b in range(m) if mask >> b & 1]
    out = np.zeros(1 << len(bits), dtype=np.int64)
    for i, b in enumerate(bits):
        half = 1 << i
        out[half : 2 * half] = out[:half] | (1 << b)
    return out


class _Target:
    """One target's table over the subsets of its feasible sensors: ``subs`` the subsets (bit
    ``b`` = allowed sensor ``b``) with at most ``cap`` sensors, ``lb`` lower bounds of
    ``g_t(S)`` (the reference's value) from the reduced form and the degenerate-interval
    bounds, and the exact values computed on demand (``value``)."""

    def __init__(self, inp: _Inputs, t: int, allowed: list[int], tab: _Problem | None) -> None:
        self.inp, self.t, self.allowed = inp, t, allowed
        m = len(allowed)
        fmask = 0
        for b, j in enumerate(allowed):
            if inp.feasible[j, t]:
                fmask |= 1 << b
        subs = _submasks(fmask, m)
        if inp.caps[t] < m:
            subs = subs[_popcount(subs) <= inp.caps[t]]
        self.subs = subs
        self.exact: dict[int, tuple[float, Mat]] = {}
        self.lb = self._bounds(tab, subs, m)

    def _bounds(self, prob: _Problem | None, subs: NDArray[np.int64], m: int) -> Mat:
        if prob is None or prob.bound is None:  # no interval bound: the exact values
            masks = self._masks(subs)
            return self._evaluate(subs, masks)
        G = prob.G
        s = prob.s
        rr = prob.r * prob.r
        S_rows = np.zeros((m, rr))
        for b, j in enumerate(self.allowed):
            if rr:
                S_rows[b] = G[j][np.ix_(s, s)].reshape(rr)
        bits = ((subs[:, None] >> np.arange(m)) & 1).astype(np.float64)
        out = np.empty(subs.size)
        step = 1 << 14
        for lo in range(0, subs.size, step):
            Z = prob.base[None] + bits[lo : lo + step] @ S_rows
            sB = prob.summary(Z)
            out[lo : lo + step] = prob.combine(sB, sB)
        return out

    def _masks(self, subs: NDArray[np.int64]) -> NDArray[np.bool_]:
        m = len(self.allowed)
        bits = ((subs[:, None] >> np.arange(m)) & 1).astype(bool)
        masks = np.zeros((subs.size, self.inp.N), dtype=bool)
        masks[:, self.allowed] = bits
        return masks

    def _evaluate(self, subs: NDArray[np.int64], masks: NDArray[np.bool_]) -> Mat:
        """Exact values (the reference's arithmetic) of the subsets, kept in ``exact``."""
        inp, t = self.inp, self.t
        Y0 = spd_inverse(inp.P_pred[t])
        out = np.empty(subs.size)
        step = 4096
        for lo in range(0, subs.size, step):
            mk = masks[lo : lo + step]
            P = spd_inverse(Y0 + gain_sums(inp.J[:, t], mk))
            if inp.entry is None or not inp.entry.batch_invariant:
                # a user's metric: called as the reference calls it
                v = np.array([float(np.asarray(inp.f(P_i, inp.D[t]))) for P_i in P])
            else:  # a batch-invariant metric: one call for the batch
                v = np.asarray(inp.f(P, inp.D[t]), dtype=np.float64).reshape(-1)
            if not np.isfinite(v).all():
                raise ValueError(f"metric returned a non-finite value for target {t}")
            for i, code in enumerate(subs[lo : lo + step].tolist()):
                self.exact[code] = (float(v[i]), P[i])
            out[lo : lo + mk.shape[0]] = v
        return out

    def values(self, codes: list[int]) -> None:
        """Make sure the exact values of ``codes`` are known."""
        todo = sorted({c for c in codes if c not in self.exact})
        if todo:
            arr = np.array(todo, dtype=np.int64)
            self._evaluate(arr, self._masks(arr))


class _Cell:
    """One search cell's table over the subsets of its feasible sensors, as :class:`_Target`:
    ``lb`` the products ``λ u_c Π miss`` deflated by a relative ``4 (m + 2) eps`` (below the
    reference's product whatever its rounding), the exact values (the reference's loop) on
    demand (``exact[code] = (g, None)``)."""

    def __init__(self, inp: _Inputs, c: int, allowed: list[int]) -> None:
        assert inp.cells is not None
        self.inp, self.c, self.allowed = inp, c, allowed
        m = len(allowed)
        col = inp.T + c
        bits = [b for b, j in enumerate(allowed) if col in inp.options[j]]
        subs = np.zeros(1 << len(bits), dtype=np.int64)
        val = np.zeros(1 << len(bits))
        val[0] = inp.cells.weight * float(inp.cells.u[c])
        for i, b in enumerate(bits):  # the subsets with bit b are those without, times miss
            half = 1 << i
            subs[half : 2 * half] = subs[:half] | (1 << b)
            val[half : 2 * half] = val[:half] * float(inp.cells.miss[allowed[b], c])
        self.subs = subs
        self.lb = val * (1.0 - 4.0 * (m + 2) * EPS)
        self.exact: dict[int, tuple[float, Mat | None]] = {}

    def values(self, codes: list[int]) -> None:
        for code in codes:
            if code not in self.exact:
                sensors = [j for b, j in enumerate(self.allowed) if code >> b & 1]
                self.exact[code] = (self.inp.cell_value(self.c, sensors), None)


def _convolve(f_subs: NDArray[np.int64], f_val: Mat, g: Mat, m: int) -> Mat:
    """The min-plus subset convolution ``h(R) = min_{S ⊆ R} f(S) + g(R - S)`` over all bit sets
    ``R`` of ``m`` bits, with ``f`` given on the subsets ``f_subs`` (``+inf`` elsewhere): every
    pair (``S``, ``Q``) with ``S ∩ Q = ∅`` once, in chunks (``np.minimum.at``)."""
    size = 1 << m
    h = np.full(size, np.inf)
    if m <= PAIR_TABLE_BITS:  # every disjoint pair at once, from a cached table
        S_all, Q_all, R_all = _pair_table(m)
        f_full = np.full(size, np.inf)
        f_full[f_subs] = f_val
        np.minimum.at(h, R_all, f_full[S_all] + g[Q_all])
        return h
    finite = np.isfinite(f_val)
    f_subs, f_val = f_subs[finite], f_val[finite]
    if f_subs.size == 0:
        return h
    # for each S, the rests Q ⊆ complement(S): chunks of S by popcount keep memory bounded
    comp_bits = m - _popcount(f_subs)
    order = np.argsort(comp_bits, kind="stable")
    f_subs, f_val, comp_bits = f_subs[order], f_val[order], comp_bits[order]
    full = size - 1
    lo = 0
    while lo < f_subs.size:
        k = int(comp_bits[lo])
        per = 1 << k
        hi = lo
        while hi < f_subs.size and comp_bits[hi] == k and (hi - lo + 1) * per <= PAIR_CHUNK:
            hi += 1
        hi = max(hi, lo + 1)
        S = f_subs[lo:hi]
        # submasks of each complement: all Q with Q & S == 0, via the sub-bit enumeration
        comp = full ^ S
        Q = _submask_rows(comp, m, k)
        vals = f_val[lo:hi, None] + g[Q]
        np.minimum.at(h, (S[:, None] | Q).reshape(-1), vals.reshape(-1))
        lo = hi
    return h


@functools.lru_cache(maxsize=4)
def _pair_table(m: int) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.int32]]:
    """Every pair of disjoint bit sets ``(S, Q)`` of ``m`` bits and ``R = S | Q`` (``3^m`` of
    them: each bit in neither, in ``Q`` or in ``S``), read-only."""
    S = np.zeros(1, dtype=np.int32)
    Q = np.zeros(1, dtype=np.int32)
    for b in range(m):
        bit = np.int32(1 << b)
        S = np.concatenate((S, S, S | bit))
        Q = np.concatenate((Q, Q | bit, Q))
    R = S | Q
    for x in (S, Q, R):
        x.flags.writeable = False
    return S, Q, R


def _submask_rows(masks: NDArray[np.int64], m: int, k: int) -> NDArray[np.int64]:
    """``(len(masks), 2^k)``: every submask of each mask, all masks having ``k`` bits set."""
    rows = masks.size
    out = np.zeros((rows, 1 << k), dtype=np.int64)
    rem = masks.copy()
    for i in range(k):
        low = rem & -rem  # the lowest remaining bit of each mask
        rem = rem ^ low
        half = 1 << i
        out[:, half : 2 * half] = out[:, :half] | low[:, None]
    return out


def allocate_assignments(
    P_pred: Mat,
    J: Mat,
    P_d: Mat,
    metric: str | MetricFn,
    weights: Sequence[float] | Mat | None = None,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: MultiConstraints = NO_CONSTRAINTS,
    tie_rtol: float = 1e-9,
    cells: CellTerms | None = None,
) -> Assignment:
    """The fast exact allocator (module docstring): the same :class:`Assignment` as
    :func:`allocate_assignments_exhaustive` (assignment, value and ``P`` bits), with tables of
    ``2^N`` entries per target (and cell) and a dynamic programme of ``O((T + C) 3^N)`` steps
    over the allowed sensors (at most ``MAX_SENSORS``: :class:`TooManySensors` beyond).  A
    metric without an interval bound gets exact tables (one metric call per subset and target),
    still exact."""
    inp = _Inputs(P_pred, J, P_d, metric, weights, feasible, constraints, tie_rtol, cells)
    N, T = inp.N, inp.T
    allowed = [j for j in range(N) if inp.options[j] != [OFF]]
    m = len(allowed)
    if m > MAX_SENSORS:
        raise TooManySensors(
            f"the exact assignment search keeps tables of 2^N entries: at most {MAX_SENSORS} "
            f"sensors that can be on, got {m} (use the bounded or greedy search)"
        )
    full = (1 << m) - 1
    req_mask = 0
    for b, j in enumerate(allowed):
        if j in inp.required:
            req_mask |= 1 << b
    try:
        targets = []
        for t in range(T):
            prob = None
            if inp.entry is not None and inp.entry.interval_bound is not None:
                excl = frozenset(j for j in range(N) if j not in allowed or not inp.feasible[j, t])
                if len(excl) < N:
                    prob = _Problem(
                        inp.P_pred[t], inp.J[:, t], inp.D[t], inp.f, Constraints(excl), tie_rtol
                    )
            targets.append(_Target(inp, t, allowed, prob))
        cols: list[_Target | _Cell] = [*targets]
        cols += [_Cell(inp, c, allowed) for c in range(inp.C)]
        ws = inp.w + [1.0] * inp.C
        ncol = len(cols)
        # the last stage: the sensors left off, R; feasible iff no required one, within the
        # budget, and at least one sensor on
        R = np.arange(1 << m, dtype=np.int64)
        used = m - _popcount(R)
        ok = ((R & req_mask) == 0) & (used <= inp.K) & (R != full)
        H: list[Mat] = [np.where(ok, 0.0, np.inf)]  # H[ncol - t] for t = ncol..1
        for t in range(ncol - 1, 0, -1):
            tg = cols[t]
            H.insert(0, _convolve(tg.subs, ws[t] * tg.lb, H[0], m))
        # H[0] is H_1 (columns 1..ncol-1 and the last stage), H[t - 1] is H_t
        Hs = {t: H[t - 1] for t in range(1, ncol + 1)}
        tg0 = cols[0]
        root = ws[0] * tg0.lb + Hs[1][full ^ tg0.subs]
        if not np.isfinite(root).any():
            raise InfeasibleAllocation("no assignment satisfies the constraints")
        # the incumbent: the bound's optimum, evaluated exactly
        sets = _backtrack(cols, Hs, ws, full, int(np.argmin(root)))
        U = _exact_total(cols, ws, np.array([sets], dtype=np.int64))[0]
        tau = U + inp.tie_rtol * max(abs(U), TINY)
        tau_b = tau * (1.0 + 16.0 * ncol * EPS) + TINY
        cands = _enumerate(cols, Hs, ws, full, root, tau_b)
        F = _exact_total(cols, ws, cands)
    except np.linalg.LinAlgError as exc:
        raise _spd_error(exc) from exc
    thr = tie_threshold(float(F.min()), inp.tie_rtol)
    chosen = cands[_tie_choice(cands, np.flatnonzero(F <= thr), m, inp.T + inp.C)].tolist()
    a = _vector(chosen, allowed, N)
    values = [targets[t].exact[chosen[t]][0] for t in range(T)]
    Ps = [targets[t].exact[chosen[t]][1] for t in range(T)]
    gs = [cols[T + c].exact[chosen[T + c]][0] for c in range(inp.C)]
    n_eval = sum(len(tg.exact) for tg in targets)
    return _result(inp, a, values, Ps, len(cands), n_eval, None, gs)


#: entries of one chunk of :func:`_enumerate` (prefixes times the next target's sets)
ENUM_CHUNK = 1 << 20


def _tie_choice(cands: NDArray[np.int64], tied: NDArray[np.intp], m: int, off: int) -> int:
    """The index among ``tied`` (ascending indices into the rows of ``cands``, each a set
    code per column over the ``m`` allowed sensors) that :meth:`_Inputs.tie_key` ranks
    first, the first one of equal keys.  The key is (sensors on, each allowed sensor's
    column, ``off`` for none, in sensor order); the sensors that are not allowed are off in
    every candidate and do not change the order.  It is compared a part at a time over all
    the candidates still in the running, which keep their order (a desired covariance far
    above every reachable one ties nearly every candidate, millions of them: a loop over
    their keys took most of such a decision)."""
    if len(tied) == 1:
        return int(tied[0])
    codes = cands[tied]  # (n, columns)
    on = _popcount(codes[:, 0])
    for t in range(1, codes.shape[1]):
        on += _popcount(codes[:, t])  # the sets are disjoint
    keep = np.flatnonzero(on == on.min())
    for b in range(m):
        if len(keep) == 1:
            break
        column = np.full(len(keep), off, dtype=np.int64)
        for t in range(codes.shape[1] - 1, -1, -1):  # at most one column holds the sensor
            column[((codes[keep, t] >> b) & 1) == 1] = t
        keep = keep[column == column.min()]
    return int(tied[keep[0]])


def _vector(sets: Sequence[int], allowed: list[int], N: int) -> list[int]:
    a = [OFF] * N
    for t, code in enumerate(sets):
        for b, j in enumerate(allowed):
            if code >> b & 1:
                a[j] = t
    return a


def _backtrack(
    targets: Sequence[_Target | _Cell], Hs: dict[int, Mat], ws: list[float], full: int, i0: int
) -> list[int]:
    """The sets of the bound's optimum, from the root choice ``i0`` of column 0 on."""
    sets = [int(targets[0].subs[i0])]
    R = full ^ sets[0]
    for t in range(1, len(targets)):
        tg = targets[t]
        sub = tg.subs[(tg.subs & ~R) == 0]
        lbs = tg.lb[(tg.subs & ~R) == 0]
        v = ws[t] * lbs + Hs[t + 1][R ^ sub]
        k = int(np.argmin(v))
        sets.append(int(sub[k]))
        R ^= int(sub[k])
    return sets


def _enumerate(
    targets: Sequence[_Target | _Cell],
    Hs: dict[int, Mat],
    ws: list[float],
    full: int,
    root: Mat,
    tau: float,
) -> NDArray[np.int64]:
    """Every assignment whose bound is at most ``tau``, a row of per-target set codes each:
    target by target, keeping the prefixes whose least completion (``H``) stays within
    ``tau``.  The prefixes are extended a chunk at a time (every prefix against every set of
    the next target, the compatible ones kept), in the order of a loop over the prefixes and,
    within one, over the sets: the rows come in that order, and each prefix's bound is
    ``acc + w_t lb`` with the loop's arithmetic (elementwise, the same IEEE operations)."""
    keep = np.flatnonzero(root <= tau)
    tg0 = targets[0]
    codes = tg0.subs[keep][:, None].astype(np.int64)
    R = full ^ tg0.subs[keep].astype(np.int64)
    acc = ws[0] * tg0.lb[keep]
    for t in range(1, len(targets)):
        tg = targets[t]
        subs = tg.subs.astype(np.int64)
        wlb = ws[t] * tg.lb
        H = Hs[t + 1]
        step = max(1, ENUM_CHUNK // max(subs.size, 1))
        parts_codes, parts_R, parts_acc = [], [], []
        for lo in range(0, R.size, step):
            Rc = R[lo : lo + step, None]
            part = acc[lo : lo + step, None] + wlb[None, :]
            v = part + H[Rc ^ subs[None, :]]
            pi, si = np.nonzero(((subs[None, :] & ~Rc) == 0) & (v <= tau))
            parts_codes.append(np.concatenate((codes[lo + pi], subs[si, None]), axis=1))
            parts_R.append(Rc[pi, 0] ^ subs[si])
            parts_acc.append(part[pi, si])
        if not parts_codes:
            return np.zeros((0, len(targets)), dtype=np.int64)
        codes = np.concatenate(parts_codes)
        R = np.concatenate(parts_R)
        acc = np.concatenate(parts_acc)
    return codes


def _exact_total(
    targets: Sequence[_Target | _Cell], ws: list[float], cands: NDArray[np.int64]
) -> Mat:
    """``F`` of each candidate (a row of set codes) with the reference's arithmetic (per-target
    values exact, summed ``F = 0; F = F + w_t v_t``, then the cells' ``F = F + g_c`` with
    ``w = 1``: ``1.0 * g`` is ``g``); each target's distinct codes looked up once."""
    F = np.zeros(len(cands))
    for t, tg in enumerate(targets):
        u, inv = np.unique(cands[:, t], return_inverse=True)
        codes = u.tolist()
        tg.values(codes)
        F = F + ws[t] * np.array([tg.exact[c][0] for c in codes])[inv.reshape(-1)]
    return F
