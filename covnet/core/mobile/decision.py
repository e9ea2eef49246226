"""The decision problem of one scan and its solvers (spec §5, §6).

Variables ``s_ijρ ∈ {0,1}`` (sensor j, in mode ρ, observes target i), ``m_jρ ∈ {0,1}`` (sensor j
uses mode ρ), ``u_i ∈ [0,1]`` (target i unobserved)::

    minimise    Σ c_ijρ s_ijρ + Σ c0_i u_i + ε Σ ‖Δ_ρ‖ m_jρ          (ε = 1e-6)
    subject to  Σ_{j,ρ} s_ijρ + u_i = 1        every target i   (coverage)
                Σ_ρ m_jρ = 1                    every sensor j   (one mode)
                s_ijρ ≤ m_jρ                    all i, j, ρ      (strong linking)
                Σ_{i,ρ} s_ijρ ≤ K_j             every sensor j with a capacity

Solvers (the :data:`SOLVERS` registry; each ``(problem, options) -> Decision``):

* ``lp_highs``: the patent's method (§6.1). The LP over ``s`` alone (no mode variables, no
  linking), by HiGHS dual simplex (``linprog(method="highs-ds")``: a vertex, integral because the
  matrix is a bipartite incidence matrix); rounding if the vertex is fractional; then the
  post-step ``ρ*_j = argmin_ρ Σ_{i ∈ I_j} c_ijρ`` for every sensor with targets, idle sensors
  stay.  Columns ``s_ijρ`` of one pair (i, j) are identical in every constraint, so only the
  cheapest mode ``ρ̂_ij = argmin_ρ c_ijρ`` can be in an optimal vertex: the LP is built over the
  ``M·N`` pairs with cost ``min_ρ c_ijρ`` (the same optimum; ``collapse_modes=False`` builds the
  full ``M·N·9`` LP, for tests).
* ``closed_form``: the same LP without capacities splits per target (argmin over ``(j, ρ)`` and
  the null option, lowest index on ties); then the same post-step.
* ``lp``: ``closed_form`` when no sensor has a capacity, ``lp_highs`` otherwise.
* ``milp``: the exact problem above by ``scipy.optimize.milp`` (HiGHS), ``s`` and ``m`` integer,
  ``u`` continuous; strong linking by default, or the aggregated ``Σ_i s_ijρ ≤ K′_j m_jρ``
  (``K′_j = min(K_j, M)``); ``time_limit`` and ``rel_gap``; on a time-out the incumbent is kept
  and HiGHS's ``mip_gap`` and ``mip_dual_bound`` are reported.

Properties (tested): ``J_LP ≤ J_relax ≤ J* ≤ J_LP+post``; with every ``K_j = 1`` the LP + post-step
is exact; the closed form equals the LP solver without capacities.

Building a program (:func:`build_lp`, :func:`build_milp`) is kept apart from solving it
(:func:`solve_lp`, :func:`solve_milp`); a solve returns a record with ``status`` and ``message``,
and its ``x`` is never used unless HiGHS reports success (or a time-out with an incumbent).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Literal, Protocol, cast

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, OptimizeResult, linprog, milp

from covnet.core.gaussian import Mat, Vec
from covnet.core.mobile.models import MODE_NORM, N_MODES, STAY, IntVec

EPS_MOTION = 1e-6
Linking = Literal["strong", "weak"]
_INTEGRAL_TOL = 1e-7
_NAN = float("nan")


class _SparseLinprog(Protocol):
    """``scipy.optimize.linprog`` as this module calls it.  HiGHS takes sparse ``A_ub`` and
    ``A_eq``; scipy-stubs' overloads list dense arrays only, hence the cast of :data:`_linprog`
    (the same function object: nothing changes at run time)."""

    def __call__(
        self,
        c: Vec,
        *,
        A_ub: sparse.csr_array | None,
        b_ub: Vec | None,
        A_eq: sparse.csr_array,
        b_eq: Vec,
        bounds: tuple[float, float],
        method: Literal["highs-ds", "highs-ipm"],
    ) -> OptimizeResult: ...


_linprog = cast(_SparseLinprog, linprog)

#: scipy's status of a HiGHS solve that ended neither optimal nor proven infeasible or
#: unbounded ("numerical difficulties", HiGHS's "model_status is Unknown")
_HIGHS_UNKNOWN = 4


def _highs_lp(
    c: Vec,
    A_ub: sparse.csr_array | None,
    b_ub: Vec | None,
    A_eq: sparse.csr_array,
    b_eq: Vec,
) -> OptimizeResult:
    """``min cᵀx`` over ``A_ub x <= b_ub``, ``A_eq x = b_eq``, ``0 <= x <= 1`` by HiGHS's dual
    simplex (a vertex); where it ends with status 4 (unknown, numerical difficulties: the
    property tests found a mobile MILP's relaxation with three sensors at one point), again by
    HiGHS's interior-point method, whose crossover also ends at a vertex; its message then says
    so.  Any other outcome is the dual simplex's."""
    res = _linprog(c, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b_eq, bounds=(0.0, 1.0),
                   method="highs-ds")  # fmt: skip
    if res.status != _HIGHS_UNKNOWN:
        return res
    ipm = _linprog(c, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b_eq, bounds=(0.0, 1.0),
                   method="highs-ipm")  # fmt: skip
    if ipm.status != 0:
        return res
    ipm["message"] = f"{ipm['message']} (by the interior point: the dual simplex ended unknown)"
    return ipm


class SolverError(RuntimeError):
    """HiGHS did not solve a program: ``status`` and ``message`` are HiGHS's (via scipy)."""

    def __init__(self, solver: str, status: int, message: str):
        self.solver, self.status, self.message = solver, status, message
        super().__init__(f"{solver}: status {status}: {message}")


@dataclass(frozen=True, slots=True)
class DecisionProblem:
    """One scan's decision: costs ``c`` (M, N, 9), null costs ``c0`` (M,), capacities ``K``
    (N,) with ``inf`` for none, and the motion tie-break ``eps``."""

    c: Mat
    c0: Vec
    capacity: Vec
    eps: float = EPS_MOTION

    def __post_init__(self) -> None:
        c = np.asarray(self.c, dtype=np.float64)
        c0 = np.asarray(self.c0, dtype=np.float64)
        K = np.asarray(self.capacity, dtype=np.float64)
        if c.ndim != 3 or c.shape[2] != N_MODES:
            raise ValueError(f"c must be (M, N, {N_MODES}), got {c.shape}")
        if c0.shape != c.shape[:1] or K.shape != c.shape[1:2]:
            raise ValueError(f"c0 must be {c.shape[:1]} and capacity {c.shape[1:2]}")
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(c0))):
            raise ValueError("costs must be finite")
        if np.any(np.isnan(K)) or np.any(K < 0):
            raise ValueError("capacities must be >= 0 (inf for none)")
        object.__setattr__(self, "c", c)
        object.__setattr__(self, "c0", c0)
        object.__setattr__(self, "capacity", K)

    @property
    def M(self) -> int:
        return int(self.c.shape[0])

    @property
    def N(self) -> int:
        return int(self.c.shape[1])

    @property
    def capacitated(self) -> bool:
        """Does any sensor have a finite capacity?"""
        return bool(np.isfinite(self.capacity).any())


@dataclass(frozen=True, slots=True)
class SolverOptions:
    """MILP options (the LP family ignores them): HiGHS ``time_limit`` (s), ``mip_rel_gap``,
    and the linking form."""

    time_limit: float = 60.0
    rel_gap: float = 1e-6
    linking: Linking = "strong"


@dataclass(frozen=True, slots=True)
class Decision:
    """The outcome of a solver.

    ``modes`` (N,): each sensor's mode; ``assign`` (M,): the sensor observing each target, or -1
    (unobserved); ``objective``: J of the exact problem at this decision (with the ε term).
    ``status``/``message``: HiGHS's (0 optimal; 1 time or iteration limit with an incumbent);
    ``J_lp``: the LP optimum before the post-step (LP family); ``conflicts``: sensors whose LP
    pairs wanted two or more different modes (resolved by the post-step); ``fractional``: the LP
    vertex was not integral and was rounded; ``mip_gap``/``dual_bound``: HiGHS's (MILP);
    ``fallback``: the MILP proved no optimum in its time and the LP + post-step decision is
    returned (no incumbent, or one worse than it).
    """

    solver: str
    modes: IntVec
    assign: IntVec
    objective: float
    status: int = 0
    message: str = "ok"
    J_lp: float = _NAN
    conflicts: int = 0
    fractional: bool = False
    mip_gap: float = _NAN
    dual_bound: float = _NAN
    fallback: bool = False

    @property
    def pair_modes(self) -> IntVec:
        """The mode of the pair observing each target (-1 when unobserved), (M,)."""
        out = np.full(self.assign.shape, -1, dtype=np.intp)
        obs = self.assign >= 0
        out[obs] = self.modes[self.assign[obs]]
        return out


SolverFn = Callable[[DecisionProblem, SolverOptions], Decision]


def objective(problem: DecisionProblem, modes: IntVec, assign: IntVec) -> float:
    """J of the exact problem: ``Σ_obs c_{i, j(i), ρ_j(i)} + Σ_unobs c0_i + ε Σ_j ‖Δ_ρj‖``."""
    obs = np.flatnonzero(assign >= 0)
    j = assign[obs]
    J = float(problem.c[obs, j, modes[j]].sum()) + float(problem.c0[assign < 0].sum())
    return J + problem.eps * float(MODE_NORM[modes].sum())


def _trivial(problem: DecisionProblem, solver: str) -> Decision:
    """No targets or no sensors: every sensor stays, every target is unobserved."""
    modes = np.full(problem.N, STAY, dtype=np.intp)
    assign = np.full(problem.M, -1, dtype=np.intp)
    J = objective(problem, modes, assign)
    return Decision(solver, modes, assign, J, 0, "trivial (no targets or no sensors)", J_lp=J)


# ------------------------------------------------------------------------------------------
# the patent's LP


@dataclass(frozen=True)
class LinearProgram:
    """``min cᵀx`` s.t. ``A_eq x = b_eq``, ``A_ub x ≤ b_ub``, ``0 ≤ x ≤ 1``.

    Columns: ``s`` flattened as ``(M, N, R)`` then ``u`` (M,). ``R = 1`` when modes are
    collapsed (``mode[i, j, 0] = argmin_ρ c_ijρ``), else ``R = 9`` (``mode[i, j, r] = r``).
    """

    c: Vec
    A_eq: sparse.csr_array
    b_eq: Vec
    A_ub: sparse.csr_array | None
    b_ub: Vec | None
    shape: tuple[int, int, int]
    mode: NDArray[np.intp]


@dataclass(frozen=True)
class LPSolution:
    """A solve's record; ``s`` (M, N, R) and ``u`` (M,) are ``None`` unless ``success``."""

    status: int
    message: str
    success: bool
    s: Mat | None
    u: Vec | None
    fun: float


def build_lp(problem: DecisionProblem, collapse_modes: bool = True) -> LinearProgram:
    """The patent's LP (coverage and capacity rows, ``0 ≤ s, u ≤ 1``) as sparse arrays."""
    M, N = problem.M, problem.N
    if collapse_modes:
        R = 1
        mode = np.argmin(problem.c, axis=2)[:, :, None]
        cs = np.take_along_axis(problem.c, mode, axis=2)
    else:
        R = N_MODES
        mode = np.broadcast_to(np.arange(N_MODES, dtype=np.intp), (M, N, R))
        cs = problem.c
    NR, nS = N * R, M * N * R
    c = np.concatenate([cs.ravel(), problem.c0])
    # coverage: row i holds its N·R s-columns and u_i
    idx = np.concatenate(
        [np.arange(nS).reshape(M, NR), (nS + np.arange(M))[:, None]], axis=1
    ).ravel()
    A_eq = sparse.csr_array(
        (np.ones(idx.size), idx, np.arange(M + 1) * (NR + 1)), shape=(M, nS + M)
    )
    fin = np.flatnonzero(np.isfinite(problem.capacity))
    A_ub = b_ub = None
    if fin.size:
        F = fin.size
        cols = (np.arange(M)[:, None, None] * N + fin[None, :, None]) * R + np.arange(R)
        rows = np.broadcast_to(np.arange(F)[None, :, None], cols.shape)
        A_ub = sparse.csr_array(
            (np.ones(cols.size), (rows.ravel(), cols.ravel())), shape=(F, nS + M)
        )
        b_ub = problem.capacity[fin].copy()
    return LinearProgram(c, A_eq, np.ones(M), A_ub, b_ub, (M, N, R), np.asarray(mode))


def solve_lp(lp: LinearProgram) -> LPSolution:
    """HiGHS dual simplex (a vertex; :func:`_highs_lp`).  ``x`` is read only when the solve
    succeeded."""
    res = _highs_lp(lp.c, lp.A_ub, lp.b_ub, lp.A_eq, lp.b_eq)
    if res.status != 0 or res.x is None:
        return LPSolution(int(res.status), str(res.message), False, None, None, _NAN)
    M, N, R = lp.shape
    nS = M * N * R
    return LPSolution(
        0, str(res.message), True, res.x[:nS].reshape(M, N, R), res.x[nS:], float(res.fun)
    )


def round_selection(s: Mat, capacity: Vec) -> tuple[IntVec, IntVec, bool]:
    """Integral assignment from an LP solution ``s`` (M, N, R).

    Returns ``(assign, pick, fractional)``: the sensor of each target (-1 for none), the index
    along R of its pair, and whether ``s`` had to be rounded.  An integral ``s`` is read as is.
    Otherwise (spec §6.1 step 2): targets in decreasing order of their largest ``s``; each takes
    its largest ``s_ijρ > 0`` whose sensor still has room (ties: lowest index).
    """
    M, N, R = s.shape
    flat = s.reshape(M, N * R)
    if M == 0 or N == 0:
        return np.full(M, -1, dtype=np.intp), np.full(M, -1, dtype=np.intp), False
    if np.all(np.minimum(np.abs(flat), np.abs(flat - 1.0)) <= _INTEGRAL_TOL):
        on = flat > 0.5
        k = np.argmax(on, axis=1)
        has = on.any(axis=1)
        assign = np.where(has, k // R, -1).astype(np.intp)
        pick = np.where(has, k % R, -1).astype(np.intp)
        return assign, pick, False
    room = np.asarray(capacity, dtype=np.float64).copy()
    assign = np.full(M, -1, dtype=np.intp)
    pick = np.full(M, -1, dtype=np.intp)
    for i in np.argsort(-flat.max(axis=1), kind="stable"):
        for k in np.argsort(-flat[i], kind="stable"):
            if flat[i, k] <= _INTEGRAL_TOL:
                break
            j = k // R
            if room[j] >= 1.0:
                room[j] -= 1.0
                assign[i], pick[i] = j, k % R
                break
    return assign, pick, True


def post_step(problem: DecisionProblem, assign: IntVec, pair_mode: IntVec) -> tuple[IntVec, int]:
    """One mode per sensor (spec §6.1 step 3): ``ρ*_j = argmin_ρ Σ_{i ∈ I_j} c_ijρ`` for every
    sensor with targets (lowest index on ties), ``stay`` for idle sensors.

    Returns the modes (N,) and the number of sensors whose pairs (``pair_mode``, the LP's mode of
    each target's pair) asked for two or more different modes.
    """
    M, N = problem.M, problem.N
    obs = np.flatnonzero(assign >= 0)
    onehot = np.zeros((M, N))
    onehot[obs, assign[obs]] = 1.0
    load = np.einsum("ij,ijr->jr", onehot, problem.c)  # (N, 9)
    busy = onehot.any(axis=0)
    modes = np.where(busy, np.argmin(load, axis=1), STAY).astype(np.intp)
    asked = np.zeros((N, N_MODES), dtype=bool)
    asked[assign[obs], pair_mode[obs]] = True
    conflicts = int(np.count_nonzero(asked.sum(axis=1) >= 2))
    return modes, conflicts


def _finish_lp(
    problem: DecisionProblem,
    solver: str,
    assign: IntVec,
    pair_mode: IntVec,
    J_lp: float,
    message: str,
    fractional: bool,
) -> Decision:
    modes, conflicts = post_step(problem, assign, pair_mode)
    J = objective(problem, modes, assign)
    return Decision(
        solver, modes, assign, J, 0, message, J_lp=J_lp, conflicts=conflicts, fractional=fractional
    )


def decide_lp_highs(problem: DecisionProblem, options: SolverOptions | None = None) -> Decision:
    """The patent's LP by HiGHS dual simplex, rounding if needed, the post-step."""
    if problem.M == 0 or problem.N == 0:
        return _trivial(problem, "lp_highs")
    lp = build_lp(problem)
    sol = solve_lp(lp)
    if not sol.success or sol.s is None:
        raise SolverError("lp_highs", sol.status, sol.message)
    assign, pick, fractional = round_selection(sol.s, problem.capacity)
    obs = assign >= 0
    pair_mode = np.full(problem.M, -1, dtype=np.intp)
    pair_mode[obs] = lp.mode[np.flatnonzero(obs), assign[obs], pick[obs]]
    return _finish_lp(problem, "lp_highs", assign, pair_mode, sol.fun, sol.message, fractional)


def decide_closed_form(problem: DecisionProblem, options: SolverOptions | None = None) -> Decision:
    """Without capacities the LP splits per target: ``(j, ρ) = argmin c_i··`` (flat index, lowest
    on ties), unobserved when ``c0_i`` is strictly cheaper; then the post-step."""
    if problem.capacitated:
        raise ValueError("closed_form: the closed form holds only when no sensor has a capacity")
    if problem.M == 0 or problem.N == 0:
        return _trivial(problem, "closed_form")
    M = problem.M
    flat = problem.c.reshape(M, -1)
    k = np.argmin(flat, axis=1)
    best = flat[np.arange(M), k]
    take = best <= problem.c0
    assign = np.where(take, k // N_MODES, -1).astype(np.intp)
    pair_mode = np.where(take, k % N_MODES, -1).astype(np.intp)
    J_lp = float(np.minimum(best, problem.c0).sum())
    return _finish_lp(problem, "closed_form", assign, pair_mode, J_lp, "closed form", False)


def decide_lp(problem: DecisionProblem, options: SolverOptions | None = None) -> Decision:
    """The patent's method: the closed form when no sensor has a capacity, else HiGHS."""
    d = decide_lp_highs(problem) if problem.capacitated else decide_closed_form(problem)
    return replace(d, solver="lp")


# ------------------------------------------------------------------------------------------
# the exact MILP


@dataclass(frozen=True)
class MixedIntegerProgram:
    """``min cᵀx`` s.t. ``A_eq x = 1``, ``A_ub x ≤ b_ub``, ``0 ≤ x ≤ 1``, ``integrality``.

    Columns: ``s`` (M, N, 9) flattened, ``m`` (N, 9) flattened, ``u`` (M,).
    """

    c: Vec
    A_eq: sparse.csr_array
    b_eq: Vec
    A_ub: sparse.csr_array
    b_ub: Vec
    integrality: NDArray[np.int8]
    shape: tuple[int, int]
    linking: Linking = field(default="strong")


@dataclass(frozen=True)
class MilpSolution:
    """A MILP solve's record; ``x`` is ``None`` without an incumbent."""

    status: int
    message: str
    x: Vec | None
    fun: float
    mip_gap: float
    dual_bound: float


def build_milp(problem: DecisionProblem, linking: Linking = "strong") -> MixedIntegerProgram:
    """The exact problem of the module docstring as sparse arrays."""
    M, N = problem.M, problem.N
    N9 = N * N_MODES
    nS = M * N9
    n = nS + N9 + M
    c = np.concatenate([problem.c.ravel(), problem.eps * np.tile(MODE_NORM, N), problem.c0])
    # equalities: coverage (M rows) then one mode per sensor (N rows)
    cov = np.concatenate([np.arange(nS).reshape(M, N9), (nS + N9 + np.arange(M))[:, None]], 1)
    one = nS + np.arange(N9).reshape(N, N_MODES)
    idx = np.concatenate([cov.ravel(), one.ravel()])
    indptr = np.concatenate(
        [np.arange(M + 1) * (N9 + 1), M * (N9 + 1) + np.arange(1, N + 1) * N_MODES]
    )
    A_eq = sparse.csr_array((np.ones(idx.size), idx, indptr), shape=(M + N, n))
    rows: list[NDArray[np.intp]] = []
    cols: list[NDArray[np.intp]] = []
    vals: list[Vec] = []
    b_parts: list[Vec] = []
    r0 = 0
    s_idx = np.arange(nS)
    m_of_s = nS + s_idx % N9  # column of m_jρ for each s_ijρ
    if linking == "strong":  # s_ijρ − m_jρ ≤ 0
        rows += [s_idx, s_idx]
        cols += [s_idx, m_of_s]
        vals += [np.ones(nS), -np.ones(nS)]
        b_parts.append(np.zeros(nS))
        r0 = nS
    elif linking == "weak":  # Σ_i s_ijρ − K′_j m_jρ ≤ 0
        Kp = np.minimum(problem.capacity, M)
        rows += [s_idx % N9, np.arange(N9)]
        cols += [s_idx, nS + np.arange(N9)]
        vals += [np.ones(nS), -np.repeat(Kp, N_MODES)]
        b_parts.append(np.zeros(N9))
        r0 = N9
    else:
        raise ValueError(f"linking must be 'strong' or 'weak', got {linking!r}")
    fin = np.flatnonzero(np.isfinite(problem.capacity))
    if fin.size:  # Σ_{i,ρ} s_ijρ ≤ K_j
        cc = (np.arange(M)[:, None, None] * N9 + fin[None, :, None] * N_MODES) + np.arange(N_MODES)
        rr = r0 + np.broadcast_to(np.arange(fin.size)[None, :, None], cc.shape)
        rows.append(rr.ravel())
        cols.append(cc.ravel())
        vals.append(np.ones(cc.size))
        b_parts.append(problem.capacity[fin])
    b_ub = np.concatenate(b_parts)
    A_ub = sparse.csr_array(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(b_ub.size, n),
    )
    integrality = np.concatenate([np.ones(nS + N9, np.int8), np.zeros(M, np.int8)])
    return MixedIntegerProgram(c, A_eq, np.ones(M + N), A_ub, b_ub, integrality, (M, N), linking)


def solve_milp(mp: MixedIntegerProgram, options: SolverOptions) -> MilpSolution:
    """``scipy.optimize.milp`` (HiGHS branch and cut) with the time limit and relative gap."""
    A = sparse.vstack([mp.A_eq, mp.A_ub], format="csr")
    lb = np.concatenate([mp.b_eq, np.full(mp.b_ub.size, -np.inf)])
    ub = np.concatenate([mp.b_eq, mp.b_ub])
    res = milp(
        mp.c,
        integrality=mp.integrality,
        bounds=Bounds(0.0, 1.0),
        constraints=LinearConstraint(A, lb, ub),
        options={"time_limit": options.time_limit, "mip_rel_gap": options.rel_gap, "disp": False},
    )
    gap = getattr(res, "mip_gap", None)
    bound = getattr(res, "mip_dual_bound", None)
    usable = res.x is not None and res.status in (0, 1)
    fun = _NAN
    if usable:
        assert res.fun is not None  # HiGHS reports the objective with every incumbent
        fun = float(res.fun)
    return MilpSolution(
        int(res.status),
        str(res.message),
        np.asarray(res.x) if usable else None,
        fun,
        float(gap) if gap is not None else _NAN,
        float(bound) if bound is not None else _NAN,
    )


def decide_milp(problem: DecisionProblem, options: SolverOptions | None = None) -> Decision:
    """The exact problem by HiGHS.  On a time-out (``status`` 1, HiGHS's gap and dual bound
    reported) the better of the incumbent and the LP + post-step decision is returned: both
    are feasible points of the same problem and the LP + post-step costs milliseconds, so
    ``solver: milp`` never commands a decision worse than the patent's method (spec §6.3 keeps
    the incumbent; a kept incumbent 6.7 times worse than it, a target left unobserved, was
    seen at a 0.21 s limit).  Without an incumbent, or with a worse one, the LP + post-step
    decision, ``fallback`` set."""
    options = options or SolverOptions()
    if problem.M == 0 or problem.N == 0:
        return _trivial(problem, "milp")
    mp = build_milp(problem, options.linking)
    sol = solve_milp(mp, options)
    if sol.x is None:
        return replace(
            decide_lp(problem),
            solver="milp",
            status=sol.status,
            message=f"{sol.message} (no incumbent: the LP + post-step decision is used)",
            mip_gap=sol.mip_gap,
            dual_bound=sol.dual_bound,
            fallback=True,
        )
    M, N = mp.shape
    nS, N9 = M * N * N_MODES, N * N_MODES
    s = sol.x[:nS].reshape(M, N, N_MODES) > 0.5
    m = sol.x[nS : nS + N9].reshape(N, N_MODES)
    modes = np.argmax(m, axis=1).astype(np.intp)
    on = np.any(s, axis=2)  # (M, N)
    assign = np.where(np.any(on, axis=1), np.argmax(on, axis=1), -1).astype(np.intp)
    J = objective(problem, modes, assign)
    if sol.status != 0:
        lp = decide_lp(problem)
        if lp.objective < J:
            return replace(
                lp,
                solver="milp",
                status=sol.status,
                message=f"{sol.message} (the incumbent's J {J:.9g} is worse than the LP + "
                "post-step decision's: that is used)",
                mip_gap=sol.mip_gap,
                dual_bound=sol.dual_bound,
                fallback=True,
            )
    return Decision(
        "milp",
        modes,
        assign,
        J,
        sol.status,
        sol.message,
        mip_gap=sol.mip_gap,
        dual_bound=sol.dual_bound,
    )


def relaxation(problem: DecisionProblem, linking: Linking = "strong") -> tuple[int, str, float]:
    """``J_relax``: the LP relaxation of the exact problem (HiGHS dual simplex, the interior
    point where it ends unknown: :func:`_highs_lp`).

    Returns ``(status, message, value)``; ``value`` is NaN unless ``status == 0``.
    """
    if problem.M == 0 or problem.N == 0:
        return 0, "trivial", _trivial(problem, "relax").objective
    mp = build_milp(problem, linking)
    res = _highs_lp(mp.c, mp.A_ub, mp.b_ub, mp.A_eq, mp.b_eq)
    value = float(res.fun) if res.status == 0 else _NAN
    return int(res.status), str(res.message), value


@dataclass(frozen=True, slots=True)
class Comparison:
    """The patent's method against the optimum on one decision (spec §6.3).

    ``gap = (J_post − J*) / |J*|``; ``conflicts`` resolved by the post-step.
    """

    J_lp: float
    J_post: float
    J_star: float
    J_relax: float
    gap: float
    conflicts: int
    exact_status: int
    mip_gap: float


def compare(lp: Decision, exact: Decision, J_relax: float) -> Comparison:
    """Put an LP-family decision next to the MILP's on the same problem.  ``J*`` and the gap
    are NaN when the MILP proved no optimum (``status`` not 0: a time-out; its incumbent, or
    the LP + post-step decision itself, is not ``J*``), so that the optimality statistics
    (:func:`covnet.mobile.results.summarise`) leave that decision out; ``exact_status`` says
    why."""
    J_star = exact.objective if exact.status == 0 and not exact.fallback else _NAN
    if not math.isfinite(J_star):
        gap = _NAN
    else:
        gap = (lp.objective - J_star) / abs(J_star) if J_star != 0.0 else lp.objective - J_star
    return Comparison(
        lp.J_lp, lp.objective, J_star, J_relax, gap, lp.conflicts, exact.status, exact.mip_gap
    )


#: solvers by name (config ``solver:``, CLI ``--solver``)
SOLVERS: Mapping[str, SolverFn] = {
    "lp": decide_lp,
    "lp_highs": decide_lp_highs,
    "closed_form": decide_closed_form,
    "milp": decide_milp,
}
