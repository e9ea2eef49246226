"""Decentralized fusion: the per-scan steps of the track rules and of the ``peer`` mode.

What changes against the central filter (spec: only the computation of ``P_i`` changes):

- every sensor runs its own **local Kalman filter** on its own measurements (:class:`LocalFilter`):
  it predicts every scan and updates at the scans it is enabled; it publishes its local track,
  the posterior ``N(x_j(k|k), P_j(k|k))`` together with its own prediction
  ``N(x_j(k|k-1), P_j(k|k-1))`` (:class:`covnet.core.fusion.LocalTrack`), instead of the raw
  measurement;
- a fusion node combines the tracks with a **rule** of the registry
  (:data:`~covnet.covariance_control.fusion_rules.FUSION_RULES`): ``info``, information-matrix
  fusion with each track's own prior removed (exact: equals the central filter), or ``ci``,
  covariance intersection of the node's predicted track and the received local tracks
  (consistent under any unknown correlation, conservative);
- the **allocator** evaluates each candidate subset ``D_i`` with the covariance the rule would
  produce (:func:`decide_rule`): in the information form that is the central
  ``P_i = (P⁻⁻¹ + J_i)⁻¹`` (the new information of a track is exactly ``Hᵀ R_j⁻¹ H``), for
  ``ci`` the batched CI of ``{P_f⁻} ∪ {P_j⁺ : j ∈ D_i}``, ``P_j⁺ = (P_j⁻⁻¹ + J_j)⁻¹`` the local
  posterior sensor ``j`` would reach.

The covariances a decision needs never depend on measured values, so every node can mirror them
from shared information (the config and the history of enabled sets): :class:`Mirror` holds the
local filters' covariances and the reference fused covariance.  That is what lets the peer nodes
agree on the enabled set without a coordinator (see :mod:`sensors.peer`).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from covnet.core.allocation import Allocation, Constraints
from covnet.core.allocation._fast import tie_select
from covnet.core.gaussian import Gaussian, Mat, symmetrise
from covnet.core.kalman import update_covariance
from covnet.core.metrics import get_metric
from covnet.covariance_control.config import FusionSpec
from covnet.covariance_control.fusion_rules import FusionRule
from covnet.covariance_control.model import (
    Model,
    decide,
    initial_estimate,
    nothing_on,
    predict_cov,
    predict_step,
)

# --------------------------------------------------------------------------------------------
# local filters
# --------------------------------------------------------------------------------------------


class LocalFilter:
    """A sensor's own Kalman filter over the scans of one episode (decentralized modes):
    ``predict_to(episode, k)`` returns its prediction for scan ``k`` (a new episode restarts
    from the initial estimate at scan 0); ``set(posterior)`` stores the update of that scan."""

    def __init__(self, model: Model, initial: str) -> None:
        self.model, self.initial = model, initial
        self.episode, self.scan = -1, 0
        self.estimate: Gaussian = initial_estimate(model, initial)

    def predict_to(self, episode: int, scan: int) -> Gaussian:
        if episode != self.episode:
            self.episode, self.scan = episode, 0
            self.estimate = initial_estimate(self.model, self.initial)
        g = self.estimate
        while self.scan < scan:
            g = predict_step(self.model, g)
            self.scan += 1
        self.estimate = g
        return g

    def set(self, posterior: Gaussian) -> None:
        self.estimate = posterior


# --------------------------------------------------------------------------------------------
# fusion and allocation under a rule
# --------------------------------------------------------------------------------------------


@lru_cache(maxsize=64)
def feasible_subsets(
    n: int, constraints: Constraints
) -> tuple[tuple[tuple[int, ...], ...], np.ndarray]:
    """Every feasible subset in the tie rule's preference order (fewer sensors first, then
    lexicographic), and their ``(M, n)`` boolean masks."""
    allowed = [j for j in range(n) if j not in constraints.excluded]
    k_max = len(allowed)
    if constraints.max_active is not None:
        k_max = min(constraints.max_active, k_max)
    subsets = tuple(
        s
        for size in range(1, k_max + 1)
        for s in itertools.combinations(allowed, size)
        if constraints.required <= set(s)
    )
    masks = np.zeros((len(subsets), n), dtype=bool)
    for i, s in enumerate(subsets):
        masks[i, list(s)] = True
    masks.setflags(write=False)
    return subsets, masks


def _constraints(model: Model, unavailable: frozenset[int]) -> Constraints:
    return model.constraints.without(unavailable)


def local_posterior_covs(model: Model, P_local_prior: Mat) -> Mat:
    """``P_j⁺ = update(P_j⁻)`` for every sensor: the local posterior it reaches if it measures."""
    return np.stack(
        [update_covariance(P, model.H, model.R[j]) for j, P in enumerate(P_local_prior)]
    )


def decide_rule(
    rule: FusionRule,
    model: Model,
    P_prior: Mat,
    P_local_prior: Mat | None,
    scan: int,
    metric: str,
    unavailable: frozenset[int] = frozenset(),
    reach: np.ndarray | None = None,
    delivery: np.ndarray | None = None,
) -> Allocation:
    """Covariance control under the fusion rule: argmin over the feasible subsets of
    ``f(P_i, P_d(t_k))`` with ``P_i`` the covariance the rule produces from subset ``D_i``.

    One fusion point (``P_prior`` ``(n, n)``, a centre that hears every track): a rule in the
    information form (``central``, ``info``) uses the fast exact allocator on
    ``P_i = (P⁻⁻¹ + J_i)⁻¹`` (:func:`covnet.covariance_control.model.decide`); any other (``ci``)
    all feasible subsets' covariances in one batch (the rule's :meth:`~covnet.covariance_control.
    fusion_rules.FusionRule.candidates`), the metric batched, then the tie rule of
    :mod:`covnet.core.allocation` (fewest sensors, then lowest ids).

    Several fusion points (peer mode: ``P_prior`` ``(K, n, n)``, one per node, and ``reach``
    ``(K, Ns)``: the sensors whose tracks node k hears): subset i is scored by its worst node,
    ``max_k f(P_ik, P_d)``, ``P_ik`` from the tracks of ``D_i ∩ reach_k``.  The reported
    ``P`` is the worst node's.

    ``delivery`` (a rule not in the information form; ``allocation.account_for_loss``): each
    sensor's probability ``p_j`` that its track arrives in time; a candidate then uses the
    *expected* local information ``Y_j⁻ + p_j (Y_j⁺ − Y_j⁻)`` (in the information form the
    caller scales the gains: :func:`covnet.covariance_control.latency_sim.loss_aware_model`)."""
    P_prior = np.asarray(P_prior, dtype=np.float64)
    if P_prior.ndim == 2 and rule.information_form:
        return decide(model, P_prior, scan, metric, unavailable)
    if P_local_prior is None:
        raise ValueError(
            f"the {rule.name} rule and peer nodes decide from the local filters' covariances"
        )
    points = P_prior[None] if P_prior.ndim == 2 else P_prior
    if reach is None:
        reach = np.ones((points.shape[0], len(model.sensor_ids)), dtype=bool)
    constraints = _constraints(model, unavailable)
    if unavailable and len(constraints.excluded) == len(model.sensor_ids):
        return nothing_on(points, model.desired(scan), metric)
    subsets, masks = feasible_subsets(len(model.sensor_ids), constraints)
    if not subsets:
        raise ValueError("no feasible subset: every sensor is excluded or failed")
    P_local_post = local_posterior_covs(model, P_local_prior)
    if delivery is not None:
        Ym = np.linalg.inv(P_local_prior)
        Y = Ym + delivery[:, None, None] * (np.linalg.inv(P_local_post) - Ym)
        P_local_post = symmetrise(np.linalg.inv(Y))
    # every fusion point's candidates in one stack, the metric in one batched call
    cands = np.stack(
        [
            rule.candidates(model, P_k, P_local_post, masks & reach[k])
            for k, P_k in enumerate(points)
        ]
    )  # (K, M, n, n)
    P_d = model.desired(scan)
    v = np.asarray(get_metric(metric)(cands, np.broadcast_to(P_d, cands.shape)), dtype=np.float64)
    worst = np.argmax(v, axis=0)  # the first worst node of each subset
    values = v[worst, np.arange(v.shape[1])]
    best = tie_select(values, masks, model.tie_rtol)
    P_best = cands[worst[best], best]
    return Allocation(subsets[best], float(values[best]), P_best, len(subsets), len(subsets))


# --------------------------------------------------------------------------------------------
# what every node can compute: the covariance mirror
# --------------------------------------------------------------------------------------------


@dataclass
class Mirror:
    """Covariances that depend only on the enabled history, which every node can therefore
    compute alike: each local filter's posterior ``P_local[j]`` and, per fusion point ``k``
    (peer mode: every node; a centre keeps its own), the fused posterior ``P_fused[k]`` from
    the tracks of ``reach[k]``.

    Per scan: :meth:`predicted` gives ``(P_fused⁻, P_local⁻)`` for the decision,
    :meth:`advance` applies the scan's delivered subset."""

    P_fused: Mat  # (K, n, n)
    P_local: Mat  # (Ns, n, n)
    reach: np.ndarray  # (K, Ns) bool

    @classmethod
    def start(cls, model: Model, reach: np.ndarray | None = None) -> Mirror:
        Ns = len(model.sensor_ids)
        reach = np.zeros((0, Ns), dtype=bool) if reach is None else reach
        return cls(
            np.repeat(model.P0[None], reach.shape[0], axis=0),
            np.stack([model.P0] * Ns),
            reach,
        )

    def predicted(self, model: Model) -> tuple[Mat, Mat]:
        """``(P_fused⁻, P_local⁻)`` for the next scan."""
        P_loc = np.stack([predict_cov(model, P) for P in self.P_local])
        P_fus = np.array([predict_cov(model, P) for P in self.P_fused])
        return P_fus.reshape(self.P_fused.shape), P_loc

    def advance(self, rule: FusionRule, model: Model, delivered: Sequence[int]) -> None:
        """Move to the next scan's posteriors: every local filter predicts, those in
        ``delivered`` update; each fusion point fuses the delivered tracks it hears."""
        P_fus_pred, P_loc_pred = self.predicted(model)
        post = P_loc_pred.copy()
        for j in delivered:
            post[j] = update_covariance(P_loc_pred[j], model.H, model.R[j])
        for k in range(self.reach.shape[0]):
            heard = [j for j in sorted(delivered) if self.reach[k, j]]
            self.P_fused[k] = rule.fused_covariance(model, P_fus_pred[k], post, heard)
        self.P_local = post


# --------------------------------------------------------------------------------------------
# the peer graph
# --------------------------------------------------------------------------------------------


def reach_matrix(fusion: FusionSpec, ids: Sequence[str]) -> np.ndarray:
    """``(Ns, Ns)`` bool: row n marks the sensors whose tracks node n fuses (itself and its
    neighbours)."""
    nbrs = neighbours(fusion, ids)
    R = np.eye(len(ids), dtype=bool)
    for n, ns in nbrs.items():
        R[n, list(ns)] = True
    return R


def neighbours(fusion: FusionSpec, ids: Sequence[str]) -> dict[int, tuple[int, ...]]:
    """Each node's neighbours (sensor indices, ascending, never itself) in the peer graph:
    ``full`` every other node; ``ring`` the previous and next in the sensor table (cyclic);
    ``star`` the hub (``peer.hub``, default the first sensor) with everyone; ``custom`` the
    undirected ``peer.edges``."""
    n = len(ids)
    graph = fusion.peer.graph
    adj: dict[int, set[int]] = {i: set() for i in range(n)}

    def link(a: int, b: int) -> None:
        if a != b:
            adj[a].add(b)
            adj[b].add(a)

    if graph == "full":
        for a, b in itertools.combinations(range(n), 2):
            link(a, b)
    elif graph == "ring":
        for a in range(n):
            link(a, (a + 1) % n)
    elif graph == "star":
        hub = ids.index(fusion.peer.hub) if fusion.peer.hub is not None else 0
        for a in range(n):
            link(hub, a)
    elif graph == "custom":
        for u, v in fusion.peer.edges:
            link(ids.index(u), ids.index(v))
    else:  # pragma: no cover - the config validates the name
        raise ValueError(f"unknown peer graph {graph!r}")
    return {i: tuple(sorted(v)) for i, v in adj.items()}
