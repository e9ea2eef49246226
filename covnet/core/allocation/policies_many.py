"""The many-target forms of the allocation policies (:mod:`covnet.core.allocation.policies`).

The problem is the many-target allocator's (:mod:`covnet.core.allocation.assignment`): per
target ``t`` the predicted covariance ``P_t⁻`` (``P_pred``, ``(T, n, n)``), per (sensor, target)
the information ``J_{j,t}`` (``J``, ``(N, T, n, n)``, already scaled by the detection
probability), the coverage ``feasible`` (``(N, T)``: sensor ``j`` may dwell on target ``t`` only
where it is ``True``; ``None``: everywhere) and the constraints (a
:class:`~covnet.core.allocation.assignment.MultiConstraints` or anything with its fields:
``excluded``, ``required`` (on, on any covered target), ``max_active`` (sensors on in total),
``max_per_target``).  A decision is an assignment ``a = (a_0..a_{N-1})``, ``a_j`` a target index
or :data:`OFF` (``-1``, as :data:`covnet.core.allocation.assignment.OFF`), with at least one
sensor on, giving each target ``P_t(a) = ((P_t⁻)⁻¹ + Σ_{j : a_j = t} J_{j,t})⁻¹``.

*Eligible* sensors are those not excluded that cover at least one target.  The budget ``K`` is
the one-target policies' (``budget`` / ``max_active``, over the eligible count).  A target is
*open* to another sensor while it has fewer than its ``max_per_target``.

The forms (``score`` as in one target):

- ``all_on``: every eligible sensor on, each (in index order) on the open covered target where
  its own log-det gain ``log det((P_t⁻)⁻¹ + J_{j,t}) − log det((P_t⁻)⁻¹)`` is largest (ties: the
  lowest target); refused when ``max_active`` is below the eligible count or a sensor finds no
  open target;
- ``random``: ``K`` eligible sensors as in one target (``rng.choice``), then each chosen sensor,
  in index order, on a uniformly drawn open covered target (``rng.integers``);
- ``round_robin``: the sensors of :func:`~covnet.core.allocation.policies.round_robin_order`;
  sensor ``j`` in round ``r`` (the required ones: ``r = scan - 1``) dwells on its covered targets
  ``c_j`` taken cyclically, ``c_j[(r + j) mod |c_j|]`` (the next open one after it if that one is
  full): its successive turns visit its targets in turn;
- ``greedy_information``: from nothing, place the required sensors, then add sensors, each step
  the (sensor, open covered target) pair with the largest gain ``log det(P_t⁻¹ + J_{j,t}) − log
  det(P_t⁻¹)`` at the target's current ``P_t`` (ties: the lowest ``(j, t)``), until ``K`` or no
  pair gains more than :data:`~covnet.core.allocation.policies.INFO_GAIN_TOL`;
- ``uncertainty_reward`` / ``expected_kl``: the sum over targets of the one-target reward of each
  target's set (Stone Soup adds its tracks' rewards), maximised over every feasible assignment
  when there are at most :data:`MANY_BRUTE_FORCE_MAX` candidate assignments (``Π_j |options_j|
  <= (T+1)^N``), else by greedy forward selection over (sensor, target) pairs (the required ones
  first).  Ties (within ``tie_rtol``): the fewest sensors on, then the smallest vector under the
  allocator's order ``target 0 < ... < target T-1 < OFF``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation.constraints import Constraints
from covnet.core.allocation.policies import (
    INFO_GAIN_TOL,
    REWARD_BATCH,
    TIE_RTOL,
    TINY,
    _gain_batch,
    budget_of,
    checked_indices,
    checked_prior,
    infeasible,
    round_robin_order,
)
from covnet.core.gaussian import Mat

__all__ = ["MANY_BRUTE_FORCE_MAX", "OFF", "AssignmentDecision", "DECIDE_MANY", "total_reward"]

#: ``a_j = OFF``: sensor ``j`` dwells on no target (the many-target allocator's encoding)
OFF = -1
#: the reward policies enumerate the assignments up to this many candidates (``2^16``)
MANY_BRUTE_FORCE_MAX = 1 << 16


class DecideManyFn(Protocol):
    """``decide_many(P_pred, J, feasible, constraints, *, budget, scan, rng, tie_rtol)``: an
    assignment of sensors to targets (:mod:`covnet.core.allocation.policies_many`)."""

    def __call__(
        self,
        P_pred: Mat,
        J: Mat,
        feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = ...,
        constraints: Any = ...,
        *,
        budget: int | None = ...,
        scan: int = ...,
        rng: np.random.Generator | None = ...,
        tie_rtol: float = ...,
    ) -> AssignmentDecision: ...


#: ``reward(P_pred, gains, subset)`` of one target


@dataclass(frozen=True, slots=True)
class AssignmentDecision:
    """One scan's many-target decision: ``assignment`` (``a_j`` per sensor, a target or
    :data:`OFF`), ``score``, ``n_evaluated`` and ``exhaustive`` as
    :class:`~covnet.core.allocation.policies.PolicyDecision`."""

    assignment: tuple[int, ...]
    score: float | None
    n_evaluated: int
    exhaustive: bool

    @property
    def subset(self) -> tuple[int, ...]:
        """The sensors on, ascending."""
        return tuple(j for j, a in enumerate(self.assignment) if a != OFF)

    def sets(self, T: int) -> tuple[tuple[int, ...], ...]:
        """Each target's sensors, ascending."""
        return tuple(tuple(j for j, a in enumerate(self.assignment) if a == t) for t in range(T))


class _Many:
    """A validated many-target problem (module docstring)."""

    def __init__(
        self,
        P_pred: Mat,
        J: Mat,
        feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None,
        constraints: Any,
    ) -> None:
        Pp = np.asarray(P_pred, dtype=np.float64)
        if Pp.ndim != 3 or Pp.shape[0] == 0:
            raise ValueError(f"P_pred must be (T, n, n) (one per target), got shape {Pp.shape}")
        T = Pp.shape[0]
        pl = [checked_prior(Pp[t], f"P_pred[{t}]") for t in range(T)]
        self.P = np.array([p for p, _ in pl])
        self.L = np.array([lo for _, lo in pl])
        n = self.P.shape[1]
        Jj = np.asarray(J, dtype=np.float64)
        if Jj.ndim != 4 or Jj.shape[1:] != (T, n, n) or Jj.shape[0] == 0:
            raise ValueError(f"J must be (N, {T}, {n}, {n}) (one J_jt per pair), got {Jj.shape}")
        if not np.isfinite(Jj).all():
            raise ValueError("J has non-finite entries")
        N = Jj.shape[0]
        if feasible is None:
            feas = np.ones((N, T), dtype=bool)
        else:
            feas = np.asarray(feasible)
            if feas.shape != (N, T) or feas.dtype != np.bool_:
                raise ValueError(f"feasible must be a ({N}, {T}) boolean array, got {feas.shape}")
        self.J = np.where(feas[:, :, None, None], 0.5 * (Jj + np.swapaxes(Jj, -1, -2)), 0.0)
        self.N, self.T, self.n = N, T, n
        c = constraints
        excluded, required = checked_indices(c, N)
        self.max_active = c.max_active
        cap = getattr(c, "max_per_target", None)
        if cap is None:
            self.caps = [N] * T
        elif isinstance(cap, int) and not isinstance(cap, bool) and cap >= 0:
            self.caps = [cap] * T
        elif isinstance(cap, tuple | list) and len(cap) == T:
            self.caps = [int(x) for x in cap]
        else:
            raise ValueError(f"max_per_target must be an integer >= 0, {T} of them, or None")
        self.covered = [
            [] if j in excluded else [t for t in range(T) if feas[j, t]] for j in range(N)
        ]
        for j in sorted(required):
            if not self.covered[j]:
                raise infeasible(f"required sensor {j} has no feasible target")
        self.eligible = [j for j in range(N) if self.covered[j]]
        if not self.eligible:
            raise infeasible("no sensor has a feasible target (excluded or no coverage)")
        self.req = sorted(required)
        self.free = [j for j in self.eligible if j not in required]

    def budget(self, name: str, budget: int | None, needed: bool) -> int:
        return budget_of(name, budget, self.max_active, len(self.eligible), len(self.req), needed)

    def open_targets(self, j: int, counts: Sequence[int]) -> list[int]:
        return [t for t in self.covered[j] if counts[t] < self.caps[t]]

    def prior_gain(self, j: int, t: int) -> float:
        return float(_gain_batch(self.L[t], self.J[j, t]))


def _no_room(name: str, j: int) -> Exception:
    return infeasible(
        f"policy {name!r}: sensor {j} has no covered target left under max_per_target"
    )


def _all_on(
    P_pred: Mat,
    J: Mat,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: Any = None,
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> AssignmentDecision:
    pr = _Many(P_pred, J, feasible, _constraints(constraints))
    if pr.max_active is not None and pr.max_active < len(pr.eligible):
        raise ValueError(
            f"policy 'all_on' turns on every available sensor ({len(pr.eligible)}), but "
            f"max_active={pr.max_active} allows fewer: drop max_active or use a policy with a "
            "budget"
        )
    a = [OFF] * pr.N
    counts = [0] * pr.T
    for j in pr.eligible:
        opts = pr.open_targets(j, counts)
        if not opts:
            raise _no_room("all_on", j)
        t = min(opts, key=lambda t: (-pr.prior_gain(j, t), t))
        a[j] = t
        counts[t] += 1
    return AssignmentDecision(tuple(a), None, 0, False)


def _random(
    P_pred: Mat,
    J: Mat,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: Any = None,
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> AssignmentDecision:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"policy 'random' needs a numpy.random.Generator (rng=), got {rng!r}")
    pr = _Many(P_pred, J, feasible, _constraints(constraints))
    K = pr.budget("random", budget, needed=True)
    m = K - len(pr.req)
    drawn: list[int] = (
        rng.choice(np.array(pr.free, dtype=np.int64), size=m, replace=False).tolist() if m else []
    )
    a = [OFF] * pr.N
    counts = [0] * pr.T
    for j in sorted(pr.req + [int(x) for x in drawn]):
        opts = pr.open_targets(j, counts)
        if not opts:
            if j in pr.req:
                raise _no_room("random", j)
            continue
        t = opts[int(rng.integers(len(opts)))]
        a[j] = t
        counts[t] += 1
    return _nonempty("random", AssignmentDecision(tuple(a), None, 0, False))


def _round_robin(
    P_pred: Mat,
    J: Mat,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: Any = None,
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> AssignmentDecision:
    pr = _Many(P_pred, J, feasible, _constraints(constraints))
    K = pr.budget("round_robin", budget, needed=True)
    m = K - len(pr.req)
    turns = dict(round_robin_order(pr.N, pr.free, m, scan))
    for j in pr.req:
        turns[j] = int(scan) - 1
    a = [OFF] * pr.N
    counts = [0] * pr.T
    for j in sorted(turns):
        c = pr.covered[j]
        first = (turns[j] + j) % len(c)
        cyc = c[first:] + c[:first]
        opts = [t for t in cyc if counts[t] < pr.caps[t]]
        if not opts:
            if j in pr.req:
                raise _no_room("round_robin", j)
            continue
        a[j] = opts[0]
        counts[opts[0]] += 1
    return _nonempty("round_robin", AssignmentDecision(tuple(a), None, 0, False))


def _nonempty(name: str, d: AssignmentDecision) -> AssignmentDecision:
    if not d.subset:
        raise infeasible(f"policy {name!r}: no chosen sensor has a covered target left")
    return d


# --------------------------------------------------------------------------------------------
# greedy over (sensor, target) pairs
# --------------------------------------------------------------------------------------------


class _State:
    """A partial assignment: ``a``, per-target counts and sets."""

    def __init__(self, pr: _Many) -> None:
        self.a = [OFF] * pr.N
        self.counts = [0] * pr.T

    def add(self, j: int, t: int) -> None:
        self.a[j] = t
        self.counts[t] += 1

    def members(self, t: int) -> list[int]:
        return [j for j, x in enumerate(self.a) if x == t]


def _pairs(pr: _Many, st: _State, sensors: Sequence[int]) -> list[tuple[int, int]]:
    """Candidate (sensor, open covered target) pairs, ascending."""
    return [(j, t) for j in sensors if st.a[j] == OFF for t in pr.open_targets(j, st.counts)]


def _greedy_information(
    P_pred: Mat,
    J: Mat,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: Any = None,
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> AssignmentDecision:
    pr = _Many(P_pred, J, feasible, _constraints(constraints))
    K = pr.budget("greedy_information", budget, needed=False)
    st = _State(pr)
    n_eval = 0
    active = 0

    def step(sensors: Sequence[int], stop_at_tol: bool) -> bool:
        nonlocal n_eval, active
        pairs = _pairs(pr, st, sensors)
        if not pairs:
            return False
        gains = np.empty(len(pairs))
        for t in range(pr.T):
            idx = [i for i, (_, u) in enumerate(pairs) if u == t]
            if not idx:
                continue
            Y = np.linalg.inv(pr.P[t]) + sum(
                (pr.J[j, t] for j in st.members(t)), np.zeros((pr.n, pr.n))
            )
            _, Lc = checked_prior(np.linalg.inv(0.5 * (Y + Y.T)), f"P_{t} with its sensors")
            gains[idx] = _gain_batch(Lc, pr.J[[pairs[i][0] for i in idx], t])
        n_eval += len(pairs)
        best = int(np.argmax(gains))  # pairs ascend: the first maximum is the lowest (j, t)
        if stop_at_tol and active and not gains[best] > INFO_GAIN_TOL:
            return False
        st.add(*pairs[best])
        active += 1
        return True

    while any(st.a[j] == OFF for j in pr.req):
        if not step([j for j in pr.req if st.a[j] == OFF], stop_at_tol=False):
            raise _no_room("greedy_information", next(j for j in pr.req if st.a[j] == OFF))
    while active < K and step(pr.free, stop_at_tol=True):
        pass
    if not active:
        raise infeasible("policy 'greedy_information': no sensor has a covered target left")
    score = 0.0
    for t in range(pr.T):
        mem = st.members(t)
        if mem:
            score += float(_gain_batch(pr.L[t], pr.J[mem, t].sum(axis=0)))
    return AssignmentDecision(tuple(st.a), score, n_eval, False)


# --------------------------------------------------------------------------------------------
# the reward policies
# --------------------------------------------------------------------------------------------


class _Rewards:
    """Per-target rewards of sensor sets (bit masks), computed in batches and kept."""

    def __init__(self, pr: _Many, batch: Callable[[Mat, Mat, Mat], Mat]) -> None:
        self.pr, self.batch = pr, batch
        self.known: list[dict[int, float]] = [{0: 0.0} for _ in range(pr.T)]

    def ensure(self, t: int, codes: Sequence[int]) -> None:
        todo = sorted({c for c in codes if c not in self.known[t]})
        pr = self.pr
        for lo in range(0, len(todo), 4096):
            chunk = todo[lo : lo + 4096]
            masks = _masks(chunk, pr.N).astype(np.float64)
            Js = (masks @ pr.J[:, t].reshape(pr.N, -1)).reshape(-1, pr.n, pr.n)
            vals = self.batch(pr.P[t], pr.L[t], Js)
            self.known[t].update(zip(chunk, (float(v) for v in vals), strict=True))

    def total(self, codes: Sequence[int]) -> float:
        out = 0.0
        for t, c in enumerate(codes):
            out = out + self.known[t][c]
        return out


def total_reward(
    name: str,
    P_pred: Mat,
    J: Mat,
    assignment: Sequence[int],
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
) -> float:
    """``Σ_t r_t(S_t)`` of an assignment, ``r`` the reward ``name`` (``uncertainty_reward`` or
    ``expected_kl``)."""
    pr = _Many(P_pred, J, feasible, Constraints())
    R = _Rewards(pr, REWARD_BATCH[name])
    codes = _codes(pr, assignment)
    for t in range(pr.T):
        R.ensure(t, [codes[t]])
    return R.total(codes)


def _masks(codes: Sequence[int], N: int) -> NDArray[np.uint8]:
    """0/1 rows ``(len(codes), N)``: bit ``j`` of each code (a Python int of any width: a
    numpy integer holds 63 bits, and a network may have more sensors)."""
    nb = (N + 7) // 8
    raw = np.frombuffer(b"".join(c.to_bytes(nb, "little") for c in codes), dtype=np.uint8)
    return np.unpackbits(raw.reshape(len(codes), nb), axis=1, count=N, bitorder="little")


def _codes_of(rows: NDArray[np.bool_]) -> list[int]:
    """The code (bit ``j`` set where column ``j`` is) of each row, a Python int of any width
    (the inverse of :func:`_masks`)."""
    packed = np.packbits(rows.astype(np.uint8), axis=1, bitorder="little")
    return [int.from_bytes(row.tobytes(), "little") for row in packed]


def _codes(pr: _Many, a: Sequence[int]) -> list[int]:
    codes = [0] * pr.T
    for j, t in enumerate(a):
        if t != OFF:
            codes[t] |= 1 << j
    return codes


def _tie_key(pr: _Many, a: Sequence[int]) -> tuple[int, tuple[int, ...]]:
    return (sum(x != OFF for x in a), tuple(pr.T if x == OFF else x for x in a))


def _decide_reward(
    name: str,
    P_pred: Mat,
    J: Mat,
    feasible: Any,
    constraints: Any,
    budget: int | None,
    tie_rtol: float,
) -> AssignmentDecision:
    if not (isinstance(tie_rtol, float | int) and 0.0 <= tie_rtol < 1.0):
        raise ValueError(f"tie_rtol must be in [0, 1), got {tie_rtol!r}")
    pr = _Many(P_pred, J, feasible, _constraints(constraints))
    K = pr.budget(name, budget, needed=False)
    R = _Rewards(pr, REWARD_BATCH[name])
    options = [pr.covered[j] if j in pr.req else pr.covered[j] + [OFF] for j in range(pr.N)]
    size = 1
    for o in options:
        size *= max(len(o), 1)
    if size > MANY_BRUTE_FORCE_MAX:
        return _greedy_reward(pr, R, K, tie_rtol, name)
    # every assignment at once: row i is the mixed-radix expansion of i over the options
    opts = [o if o else [OFF] for o in options]
    A = np.zeros((size, pr.N), dtype=np.int64)
    rest = np.arange(size)
    for j in range(pr.N - 1, -1, -1):
        A[:, j] = np.array(opts[j], dtype=np.int64)[rest % len(opts[j])]
        rest //= len(opts[j])
    on = (A != OFF).sum(axis=1)
    ok = (on >= 1) & (on <= K)
    for t in range(pr.T):
        ok &= (A == t).sum(axis=1) <= pr.caps[t]
    A = A[ok]
    if A.shape[0] == 0:
        raise infeasible(f"policy {name!r}: no assignment satisfies the constraints")
    vals = np.zeros(A.shape[0])
    for t in range(pr.T):  # F = 0; F = F + r_t over the targets in order (R.total's sum)
        uniq, inv = np.unique(A == t, axis=0, return_inverse=True)
        codes = _codes_of(uniq)
        R.ensure(t, codes)
        vals = vals + np.array([R.known[t][c] for c in codes])[inv.reshape(-1)]
    best = float(vals.max())
    tied = np.flatnonzero(vals >= best - tie_rtol * max(abs(best), TINY)).tolist()
    i = min(tied, key=lambda i: _tie_key(pr, A[i].tolist()))
    return AssignmentDecision(tuple(A[i].tolist()), float(vals[i]), A.shape[0], True)


def _greedy_reward(
    pr: _Many, R: _Rewards, K: int, tie_rtol: float, name: str
) -> AssignmentDecision:
    """Forward selection over (sensor, target) pairs on the total reward: the required sensors
    first (whatever the gain), then while the best pair beats the current total by more than the
    tie tolerance, up to ``K`` sensors; ties (within ``tie_rtol``): the lowest ``(j, t)``."""
    st = _State(pr)
    cur, n_eval, active = 0.0, 0, 0

    def step(sensors: Sequence[int], must: bool) -> bool:
        nonlocal cur, n_eval, active
        pairs = _pairs(pr, st, sensors)
        if not pairs:
            return False
        base = _codes(pr, st.a)
        for t in range(pr.T):
            R.ensure(t, [base[t] | (1 << j) for j, u in pairs if u == t])
        vals = np.array(
            [cur - R.known[t][base[t]] + R.known[t][base[t] | (1 << j)] for j, t in pairs]
        )
        n_eval += len(pairs)
        best = float(vals.max())
        if not must and active and not best > cur + tie_rtol * max(abs(cur), TINY):
            return False
        i = int(np.flatnonzero(vals >= best - tie_rtol * max(abs(best), TINY))[0])
        st.add(*pairs[i])
        cur = R.total(_codes(pr, st.a))
        active += 1
        return True

    while any(st.a[j] == OFF for j in pr.req):
        if not step([j for j in pr.req if st.a[j] == OFF], must=True):
            raise _no_room(name, next(j for j in pr.req if st.a[j] == OFF))
    while active < K and step(pr.free, must=False):
        pass
    if not active:
        raise infeasible(f"policy {name!r}: no sensor has a covered target left")
    return AssignmentDecision(tuple(st.a), cur, n_eval, False)


def _uncertainty(
    P_pred: Mat,
    J: Mat,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: Any = None,
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> AssignmentDecision:
    return _decide_reward("uncertainty_reward", P_pred, J, feasible, constraints, budget, tie_rtol)


def _kl(
    P_pred: Mat,
    J: Mat,
    feasible: NDArray[np.bool_] | Sequence[Sequence[bool]] | None = None,
    constraints: Any = None,
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> AssignmentDecision:
    return _decide_reward("expected_kl", P_pred, J, feasible, constraints, budget, tie_rtol)


def _constraints(c: Any) -> Any:
    """``None``: no constraints (a plain one-target :class:`Constraints` has the fields)."""
    if c is None:
        return Constraints()
    return c


DECIDE_MANY: dict[str, DecideManyFn] = {
    "all_on": _all_on,
    "random": _random,
    "round_robin": _round_robin,
    "greedy_information": _greedy_information,
    "uncertainty_reward": _uncertainty,
    "expected_kl": _kl,
}
