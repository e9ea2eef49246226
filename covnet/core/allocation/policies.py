"""Allocation policies besides covariance control: the baselines a result is compared against
(issue 27); their registry is :mod:`covnet.core.allocation.policy_registry`.

A policy decides, every scan, which sensors measure (one target) or which target each sensor
dwells on (many targets, :mod:`covnet.core.allocation.policies_many`).  Covariance control
(:mod:`covnet.core.allocation.exact`) picks the subset whose covariance is closest to a desired
one; the policies here ignore the desired covariance and stand for what a reader of a
sensor-management result asks "against what?":

- ``all_on``: every available sensor;
- ``random``: ``K`` sensors drawn uniformly (a seeded :class:`numpy.random.Generator`);
- ``round_robin``: ``K`` sensors in a fixed cyclic order, a function of the scan number alone;
- ``greedy_information``: adds the sensor with the largest log-det information gain;
- ``uncertainty_reward`` and ``expected_kl``: the subset of at most ``K`` sensors with the largest
  reward, the rewards of Stone Soup 1.9's ``UncertaintyRewardFunction`` and
  ``ExpectedKLDivergence`` (:func:`uncertainty_reward`, :func:`expected_kl`).

**The problem** (one target) is the allocator's: the predicted covariance ``P⁻`` (``(n, n)``,
positive definite), each sensor's information ``J_j = H_jᵀ R_j⁻¹ H_j`` (``gains``, ``(N, n, n)``,
positive semi-definite) and :class:`~covnet.core.allocation.constraints.Constraints`
(``excluded``, ``required``, ``max_active``).  A subset ``D`` gives the linear-Gaussian update::

    P(D) = (P⁻⁻¹ + J_D)⁻¹,   J_D = Σ_{j ∈ D} J_j.

*Available* sensors are those not excluded.  Every decision is a non-empty subset that contains
every required sensor and no excluded one (covariance control's feasible set).

**The budget** ``K`` (``budget=``, for the policies with ``needs_budget``): at most ``K`` sensors;
with ``max_active`` also set the smaller of the two; larger than the available count: all of
them.  ``random`` and ``round_robin`` need a ``K`` (``budget`` or ``max_active``); the others
default to every available sensor.  ``K`` smaller than the required sensors is refused.

**The result** is a :class:`PolicyDecision`: the subset (ascending indices) and, where it means
something, the policy's own score (the information gain or the reward of the subset; ``None``
for ``all_on``, ``random``, ``round_robin``).  The covariance-control metric of the chosen subset
is the caller's to compute.

Only numpy is imported (start-up: the config may read the registry in processes that never
decide); the many-target forms load on their first call.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from numbers import Integral
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from covnet.core.allocation.constraints import Constraints
from covnet.core.gaussian import Mat

__all__ = [
    "BRUTE_FORCE_MAX",
    "INFO_GAIN_TOL",
    "TIE_RTOL",
    "PolicyDecision",
    "expected_kl",
    "expected_kl_sequential",
    "information_gain",
    "round_robin_order",
    "uncertainty_reward",
]

#: the reward policies enumerate every feasible subset up to this many (``2^16``), and select
#: greedily (forward, on the same reward) beyond
BRUTE_FORCE_MAX = 1 << 16
#: ``greedy_information`` stops when no sensor adds more than this log-det gain (nats)
INFO_GAIN_TOL = 1e-9
#: rewards within ``TIE_RTOL · max(|r*|, tiny)`` of the best tie (as the allocator's ``tie_rtol``)
TIE_RTOL = 1e-9
TINY = float(np.finfo(np.float64).tiny)


@dataclass(frozen=True, slots=True)
class PolicyDecision:
    """One scan's decision of a policy (one target).

    ``subset``: the chosen sensors, ascending; ``score``: the policy's score of it (information
    gain in nats for ``greedy_information``, the reward for ``uncertainty_reward`` /
    ``expected_kl``; ``None`` for the schedules); ``n_evaluated``: subsets whose score was
    computed; ``exhaustive``: the score is the maximum over every feasible subset (brute force),
    ``False`` for a greedy selection or a schedule."""

    subset: tuple[int, ...]
    score: float | None
    n_evaluated: int
    exhaustive: bool


class DecideFn(Protocol):
    """``decide(P_pred, gains, constraints, *, budget, scan, rng, tie_rtol)``: one target."""

    def __call__(
        self,
        P_pred: Mat,
        gains: Mat,
        constraints: Constraints = ...,
        *,
        budget: int | None = ...,
        scan: int = ...,
        rng: np.random.Generator | None = ...,
        tie_rtol: float = ...,
    ) -> PolicyDecision: ...


RewardFn = Callable[[Mat, Mat, Sequence[int]], float]


def _is_int(x: object) -> bool:
    return isinstance(x, Integral) and not isinstance(x, bool)


def checked_prior(P_pred: Mat, what: str = "P_pred") -> tuple[Mat, Mat]:
    """``P⁻`` symmetrised and its Cholesky factor ``L`` (``P⁻ = L Lᵀ``); a clear error unless
    ``(n, n)``, finite and positive definite."""
    P = np.asarray(P_pred, dtype=np.float64)
    if P.ndim != 2 or P.shape[0] != P.shape[1] or P.shape[0] == 0:
        raise ValueError(f"{what} must be a square (n, n) matrix, got shape {P.shape}")
    if not np.isfinite(P).all():
        raise ValueError(f"{what} has non-finite entries")
    P = 0.5 * (P + P.T)
    try:
        L: Mat = np.asarray(np.linalg.cholesky(P), dtype=np.float64)
    except np.linalg.LinAlgError as exc:
        raise ValueError(f"{what} is not positive definite") from exc
    return P, L


def checked_gains(gains: Mat, n: int, what: str = "gains") -> Mat:
    """``(N, n, n)`` finite information matrices, symmetrised."""
    G = np.asarray(gains, dtype=np.float64)
    if G.ndim != 3 or G.shape[1:] != (n, n):
        raise ValueError(f"{what} must be (N, {n}, {n}) (one J_j per sensor), got {G.shape}")
    if not np.isfinite(G).all():
        raise ValueError(f"{what} has non-finite entries")
    out: Mat = 0.5 * (G + np.swapaxes(G, 1, 2))
    return out


def checked_indices(c: Any, N: int) -> tuple[frozenset[int], frozenset[int]]:
    """``excluded`` and ``required`` of ``c`` checked against ``N`` sensors."""
    excluded, required = frozenset(c.excluded), frozenset(c.required)
    for label, idx in (("excluded", excluded), ("required", required)):
        bad = sorted(str(j) for j in idx if not _is_int(j) or not 0 <= j < N)
        if bad:
            raise ValueError(
                f"{label} sensor indices must be integers in [0, {N}), got {', '.join(bad)}"
            )
    both = excluded & required
    if both:
        raise ValueError(f"sensors {sorted(both)} are both excluded and required")
    return excluded, required


def budget_of(
    name: str, budget: int | None, max_active: int | None, n_avail: int, n_req: int, needed: bool
) -> int:
    """The effective ``K`` (module docstring): ``min(budget, max_active)`` of those given, at
    most ``n_avail``; refused unless ``>= 1`` and ``>= n_req``, or when ``needed`` and neither
    is given."""
    for label, v in (("budget", budget), ("max_active", max_active)):
        if v is not None and (not _is_int(v) or v < 1):
            raise ValueError(f"policy {name!r}: {label} must be an integer >= 1, got {v!r}")
    given = [int(v) for v in (budget, max_active) if v is not None]
    if not given:
        if needed:
            raise ValueError(
                f"policy {name!r} needs a budget K: set the policy's budget or max_active"
            )
        return n_avail
    K = min(given)
    if K < n_req:
        raise ValueError(
            f"policy {name!r}: the budget K={K} is smaller than the {n_req} required sensors"
        )
    return min(K, n_avail)


def infeasible(msg: str) -> Exception:
    """The allocator's :class:`~covnet.core.allocation.exact.InfeasibleAllocation` (imported
    here: start-up)."""
    from covnet.core.allocation.exact import InfeasibleAllocation

    return InfeasibleAllocation(msg)


class _Single:
    """A validated one-target problem: ``P``, ``L`` (``P = L Lᵀ``), ``G`` the gains, the
    available sensors ``avail`` and the required ones ``req`` (ascending), ``free`` the
    available ones not required."""

    def __init__(self, P_pred: Mat, gains: Mat, c: Constraints) -> None:
        if not isinstance(c, Constraints):
            raise TypeError(f"constraints must be a Constraints, got {type(c).__name__}")
        self.P, self.L = checked_prior(P_pred)
        self.n = self.P.shape[0]
        self.G = checked_gains(gains, self.n)
        self.N = self.G.shape[0]
        excluded, required = checked_indices(c, self.N)
        self.avail = [j for j in range(self.N) if j not in excluded]
        self.req = sorted(required)
        self.free = [j for j in self.avail if j not in required]
        self.max_active = c.max_active
        if not self.avail:
            raise infeasible("no sensor is available: every sensor is excluded")

    def budget(self, name: str, budget: int | None, needed: bool) -> int:
        return budget_of(name, budget, self.max_active, len(self.avail), len(self.req), needed)

    def sums(self, masks: NDArray[np.bool_]) -> Mat:
        """``J_D`` of each row of ``masks`` (``(B, N)``): ``(B, n, n)``."""
        n = self.n
        flat = masks.astype(np.float64) @ self.G.reshape(self.N, n * n)
        out: Mat = flat.reshape(-1, n, n)
        return out


# --------------------------------------------------------------------------------------------
# the scores: whitened information M = Lᵀ J_D L, eigenvalues λ ≥ 0
# --------------------------------------------------------------------------------------------


def _whitened(L: Mat, J: Mat) -> Mat:
    """``M = Lᵀ J L`` (batched over ``J``'s leading axes), symmetrised."""
    M = np.swapaxes(L, -1, -2) @ J @ L
    out: Mat = 0.5 * (M + np.swapaxes(M, -1, -2))
    return out


def _whitened_eigvals(L: Mat, J: Mat) -> Mat:
    """Eigenvalues of ``M = Lᵀ J L``, clipped at 0 (``J`` is PSD: a negative one is
    rounding)."""
    out: Mat = np.maximum(np.linalg.eigvalsh(_whitened(L, J)), 0.0)
    return out


def _gain_batch(L: Mat, J: Mat) -> Mat:
    """``log det(P⁻⁻¹ + J) − log det(P⁻⁻¹) = Σ log(1 + λ_i)``."""
    out: Mat = np.log1p(_whitened_eigvals(L, J)).sum(axis=-1)
    return out


def _uncertainty_batch(P: Mat, L: Mat, J: Mat) -> Mat:
    """``‖P⁻‖_F − ‖P(D)‖_F`` with ``P(D) = L (I + M)⁻¹ Lᵀ``."""
    Pd = L @ _inv_i_plus(_whitened(L, J)) @ L.T
    out: Mat = np.linalg.norm(P) - np.linalg.norm(Pd, axis=(-2, -1))
    return out


def _kl_batch(P: Mat, L: Mat, J: Mat) -> Mat:
    """``½ Σ_i (λ_i − log(1 + λ_i))``: :func:`expected_kl`."""
    lam = _whitened_eigvals(L, J)
    out: Mat = 0.5 * (lam - np.log1p(lam)).sum(axis=-1)
    return out


def _inv_i_plus(M: Mat) -> Mat:
    """``(I + M)⁻¹`` of PSD ``M`` (eigenvalues of ``I + M`` at least 1: well conditioned)."""
    out: Mat = np.asarray(np.linalg.inv(np.eye(M.shape[-1]) + M), dtype=np.float64)
    return out


#: ``batch(P⁻, L, J_D) -> rewards`` of the reward policies
REWARD_BATCH: dict[str, Callable[[Mat, Mat, Mat], Mat]] = {
    "uncertainty_reward": _uncertainty_batch,
    "expected_kl": _kl_batch,
}


def _subset_sum(P_pred: Mat, gains: Mat, subset: Sequence[int]) -> tuple[Mat, Mat, Mat]:
    P, L = checked_prior(P_pred)
    G = checked_gains(gains, P.shape[0])
    idx = sorted({int(j) for j in subset})
    if any(not 0 <= j < G.shape[0] for j in idx):
        raise ValueError(f"subset {tuple(subset)} has indices outside [0, {G.shape[0]})")
    J = G[idx].sum(axis=0) if idx else np.zeros_like(P)
    return P, L, J


def information_gain(P_pred: Mat, gains: Mat, subset: Sequence[int]) -> float:
    """``log det(P⁻⁻¹ + J_D) − log det(P⁻⁻¹)`` (nats): the log-det information gain of ``D``."""
    _, L, J = _subset_sum(P_pred, gains, subset)
    return float(_gain_batch(L, J))


def uncertainty_reward(P_pred: Mat, gains: Mat, subset: Sequence[int]) -> float:
    """Stone Soup's ``UncertaintyRewardFunction`` for one track, linear-Gaussian::

        r(D) = ‖P⁻‖_F − ‖P(D)‖_F

    (``‖·‖_F`` the Frobenius norm, numpy's default matrix norm).  Stone Soup updates the track
    with each sensor's predicted (noise-free) measurement in turn and adds ``‖P_prev‖_F −
    ‖P_new‖_F`` per update: the sum telescopes to the above, whatever the order of the sensors.
    With several tracks the rewards add (``method_sum=True``, its default; ``False`` divides by
    a detection count and is not reproduced).  Grows with every sensor (Loewner order), so the
    brute force over subsets of at most ``K`` picks ``K`` of them, as Stone Soup's brute-force
    manager does."""
    P, L, J = _subset_sum(P_pred, gains, subset)
    return float(_uncertainty_batch(P, L, J))


def expected_kl(P_pred: Mat, gains: Mat, subset: Sequence[int]) -> float:
    """Stone Soup's ``ExpectedKLDivergence`` for one track, linear-Gaussian: the Kullback-Leibler
    divergence from the prediction to the update with the predicted measurement ``z = H x⁻``::

        r(D) = KL(N(x⁻, P⁻) ‖ N(x⁻, P(D)))
             = ½ [tr(P(D)⁻¹ P⁻) − n + log(det P(D) / det P⁻)]
             = ½ [tr(J_D P⁻) − log det(I + P⁻ J_D)] = ½ Σ_i (λ_i − log(1 + λ_i)),

    ``λ_i`` the eigenvalues of ``Lᵀ J_D L`` (``P⁻ = L Lᵀ``).  The measurement is the predicted
    one, so the innovation, and the Mahalanobis term of the KL, are zero: only covariances remain.
    Nats; increasing in ``D``.  This is Stone Soup's value whenever each track gets one update:
    one sensor, or the subset's sensors as one sensor with the stacked measurement.  With several
    separate sensors Stone Soup adds the KL of each *sequential* update (previous state to next,
    :func:`expected_kl_sequential`) in the iteration order of a ``set`` of sensor copies, which
    changes from call to call: that sum depends on the order and is not used here."""
    P, L, J = _subset_sum(P_pred, gains, subset)
    return float(_kl_batch(P, L, J))


def expected_kl_sequential(P_pred: Mat, gains: Mat, order: Sequence[int]) -> float:
    """``Σ_i KL(N(P_{i-1}) ‖ N(P_i))`` over the sequential updates with the sensors of ``order``
    (``P_0 = P⁻``, ``P_i = (P_{i-1}⁻¹ + J_{order[i]})⁻¹``): Stone Soup's ``ExpectedKLDivergence``
    of several sensors updated in that order (see :func:`expected_kl`)."""
    P, L = checked_prior(P_pred)
    G = checked_gains(gains, P.shape[0])
    total = 0.0
    cur, Lc = P, L
    for j in order:
        total += float(_kl_batch(cur, Lc, G[int(j)]))
        cur = Lc @ _inv_i_plus(_whitened(Lc, G[int(j)])) @ Lc.T
        cur, Lc = checked_prior(cur)
    return total


# --------------------------------------------------------------------------------------------
# the one-target policies
# --------------------------------------------------------------------------------------------


def _decide_all_on(
    P_pred: Mat,
    gains: Mat,
    constraints: Constraints = Constraints(),
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> PolicyDecision:
    """Every available sensor (required ones are available).  Takes no budget (``budget`` is
    ignored); a ``max_active`` below the available count is refused: all of them cannot be on."""
    pr = _Single(P_pred, gains, constraints)
    K = pr.max_active
    if K is not None and K < len(pr.avail):
        raise ValueError(
            f"policy 'all_on' turns on every available sensor ({len(pr.avail)}), but "
            f"max_active={K} allows fewer: drop max_active or use a policy with a budget"
        )
    return PolicyDecision(tuple(pr.avail), None, 0, False)


def _decide_random(
    P_pred: Mat,
    gains: Mat,
    constraints: Constraints = Constraints(),
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> PolicyDecision:
    """The required sensors, then ``K - |required|`` drawn uniformly without replacement from
    the other available ones with ``rng.choice(free, size, replace=False)`` (one call: the same
    generator state gives the same subset)."""
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"policy 'random' needs a numpy.random.Generator (rng=), got {rng!r}")
    pr = _Single(P_pred, gains, constraints)
    K = pr.budget("random", budget, needed=True)
    m = K - len(pr.req)
    drawn: list[int] = (
        rng.choice(np.array(pr.free, dtype=np.int64), size=m, replace=False).tolist() if m else []
    )
    subset = tuple(sorted(pr.req + [int(j) for j in drawn]))
    return PolicyDecision(subset, None, 0, False)


def round_robin_order(N: int, eligible: Sequence[int], m: int, scan: int) -> list[tuple[int, int]]:
    """The ``m`` sensors of scan ``scan`` (``>= 1``) in the cyclic schedule, with their round.

    The cycle is over the ``E`` eligible sensors ``e_0 < e_1 < ... < e_{E-1}``: positions
    ``q = s, s+1, ..., s+m-1`` with ``s = (scan - 1) · m``; position ``q`` is sensor
    ``e_{q mod E}`` in round ``q // E`` (``m <= E``).  Returns ``[(sensor, round), ...]`` in
    that order.  Every eligible sensor is on in ``m / E`` of the scans (``ceil(E / m)``
    consecutive scans cover them all); with every sensor eligible, scan ``k`` takes the block
    ``(k-1)m .. km - 1`` (mod N).  (A cycle over all ``N`` indices that skipped the ineligible
    ones put the sensor after each skipped one on twice as often: with 2 of 8 excluded and
    ``m = 4``, two sensors were on every scan.)"""
    if not _is_int(scan) or scan < 1:
        raise ValueError(
            f"policy 'round_robin': the scan number must be an integer >= 1, got {scan!r}"
        )
    order = sorted(set(eligible))
    E = len(order)
    s = (int(scan) - 1) * m
    return [(order[q % E], q // E) for q in range(s, s + min(m, E))]


def _decide_round_robin(
    P_pred: Mat,
    gains: Mat,
    constraints: Constraints = Constraints(),
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> PolicyDecision:
    """The required sensors, and ``m = K - |required|`` others from the cyclic schedule of
    :func:`round_robin_order` (the stride is ``m``: with no required sensor the block of scan
    ``k`` starts at ``((k-1) K) mod N``).  A function of the scan number and the constraints
    alone: a restarted process, or another one, takes the same sensors."""
    pr = _Single(P_pred, gains, constraints)
    K = pr.budget("round_robin", budget, needed=True)
    m = K - len(pr.req)
    picked = [j for j, _ in round_robin_order(pr.N, pr.free, m, scan)]
    return PolicyDecision(tuple(sorted(pr.req + picked)), None, 0, False)


def _decide_greedy_information(
    P_pred: Mat,
    gains: Mat,
    constraints: Constraints = Constraints(),
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> PolicyDecision:
    """From the required sensors, repeatedly add the available sensor with the largest gain
    ``log det(P_cur⁻¹ + J_j) − log det(P_cur⁻¹)`` (``P_cur`` the covariance with the sensors
    chosen so far; ties to the lowest index) until ``K`` sensors (``budget`` / ``max_active``,
    default all available) or no sensor gains more than :data:`INFO_GAIN_TOL` nats.  The first
    sensor is added whatever its gain when no sensor is required (a decision is never empty).
    Score: the total gain ``log det(P⁻⁻¹ + J_D) − log det(P⁻⁻¹)``."""
    pr = _Single(P_pred, gains, constraints)
    K = pr.budget("greedy_information", budget, needed=False)
    chosen = list(pr.req)
    n_eval = 0
    while len(chosen) < K:
        cand = [j for j in pr.free if j not in chosen]
        if not cand:
            break
        Y = _info(pr, chosen)
        Pc, Lc = checked_prior(
            np.asarray(np.linalg.inv(Y), dtype=np.float64), "the covariance with the chosen sensors"
        )
        g = _gain_batch(Lc, pr.G[cand])
        n_eval += len(cand)
        best = int(np.argmax(g))  # the first maximum: the lowest index
        if chosen and not g[best] > INFO_GAIN_TOL:
            break
        chosen.append(cand[best])
    D = tuple(sorted(chosen))
    score = float(_gain_batch(pr.L, pr.G[list(D)].sum(axis=0)))
    return PolicyDecision(D, score, n_eval, False)


def _info(pr: _Single, chosen: Sequence[int]) -> Mat:
    """``P⁻⁻¹ + J_D`` (symmetrised)."""
    Y = np.linalg.inv(pr.P)
    if chosen:
        Y = Y + pr.G[list(chosen)].sum(axis=0)
    out: Mat = 0.5 * (Y + Y.T)
    return out


def feasible_subset_count(n_free: int, n_req: int, K: int) -> int:
    """Non-empty subsets of ``required ∪ S``, ``S ⊆ free``, with at most ``K`` sensors."""
    return sum(
        math.comb(n_free, k - n_req) for k in range(max(n_req, 1), min(K, n_free + n_req) + 1)
    )


def _decide_reward(
    name: str,
    P_pred: Mat,
    gains: Mat,
    constraints: Constraints,
    budget: int | None,
    tie_rtol: float,
) -> PolicyDecision:
    """The subset of at most ``K`` sensors (required in, excluded out) with the largest reward:
    every feasible subset when there are at most :data:`BRUTE_FORCE_MAX` of them, a greedy
    forward selection on the same reward beyond.  Ties (rewards within ``tie_rtol · max(|r*|,
    tiny)`` of the best): the fewest sensors, then the lowest ascending index tuple."""
    if not (isinstance(tie_rtol, float | int) and 0.0 <= tie_rtol < 1.0):
        raise ValueError(f"tie_rtol must be in [0, 1), got {tie_rtol!r}")
    pr = _Single(P_pred, gains, constraints)
    K = pr.budget(name, budget, needed=False)
    batch = REWARD_BATCH[name]
    count = feasible_subset_count(len(pr.free), len(pr.req), K)
    if count > BRUTE_FORCE_MAX:
        return _greedy_reward(pr, batch, K, tie_rtol)
    # by size, then the extras' combinations in lexicographic order: the order of the tie key
    # (size, ascending tuple of required ∪ extras), as every subset holds the same required ones
    r = len(pr.req)
    blocks = []
    for k in range(max(r, 1), min(K, len(pr.free) + r) + 1):
        extra = np.array(list(itertools.combinations(pr.free, k - r)), dtype=np.int64)
        mk = np.zeros((extra.shape[0], pr.N), dtype=bool)
        mk[:, pr.req] = True
        mk[np.arange(extra.shape[0])[:, None], extra] = True
        blocks.append(mk)
    masks = np.concatenate(blocks)
    vals = batch(pr.P, pr.L, pr.sums(masks))
    best = float(vals.max())
    i = int(np.flatnonzero(vals >= best - tie_rtol * max(abs(best), TINY))[0])
    return PolicyDecision(tuple(np.flatnonzero(masks[i]).tolist()), float(vals[i]), len(vals), True)


def _greedy_reward(
    pr: _Single, batch: Callable[[Mat, Mat, Mat], Mat], K: int, tie_rtol: float
) -> PolicyDecision:
    """Forward selection: from the required sensors, add the sensor whose addition gives the
    largest reward (ties, within ``tie_rtol``: the lowest index) while it beats the current
    reward by more than the tie tolerance, up to ``K`` sensors (the first sensor always, when
    none is required)."""
    chosen = list(pr.req)
    cur = float(batch(pr.P, pr.L, pr.sums(_mask(pr.N, chosen)[None]))[0]) if chosen else 0.0
    n_eval = 1 if chosen else 0
    while len(chosen) < K:
        cand = [j for j in pr.free if j not in chosen]
        if not cand:
            break
        masks = np.repeat(_mask(pr.N, chosen)[None], len(cand), axis=0)
        masks[np.arange(len(cand)), cand] = True
        vals = batch(pr.P, pr.L, pr.sums(masks))
        n_eval += len(cand)
        best = float(vals.max())
        thr = best - tie_rtol * max(abs(best), TINY)
        i = int(np.flatnonzero(vals >= thr)[0])
        if chosen and not best > cur + tie_rtol * max(abs(cur), TINY):
            break
        chosen.append(cand[i])
        cur = float(vals[i])
    return PolicyDecision(tuple(sorted(chosen)), cur, n_eval, False)


def _mask(N: int, idx: Sequence[int]) -> NDArray[np.bool_]:
    m = np.zeros(N, dtype=bool)
    m[list(idx)] = True
    return m


def _decide_uncertainty(
    P_pred: Mat,
    gains: Mat,
    constraints: Constraints = Constraints(),
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> PolicyDecision:
    """:func:`uncertainty_reward`, maximised over the feasible subsets (``_decide_reward``)."""
    return _decide_reward("uncertainty_reward", P_pred, gains, constraints, budget, tie_rtol)


def _decide_kl(
    P_pred: Mat,
    gains: Mat,
    constraints: Constraints = Constraints(),
    *,
    budget: int | None = None,
    scan: int = 1,
    rng: np.random.Generator | None = None,
    tie_rtol: float = TIE_RTOL,
) -> PolicyDecision:
    """:func:`expected_kl`, maximised over the feasible subsets (``_decide_reward``)."""
    return _decide_reward("expected_kl", P_pred, gains, constraints, budget, tie_rtol)


# --------------------------------------------------------------------------------------------
# the registry
# --------------------------------------------------------------------------------------------
