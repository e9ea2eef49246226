"""The linear-Gaussian model of a scenario, and the per-scan steps every runner shares.

:func:`build_model` turns a validated :class:`~covnet.config.Scenario` into arrays.  The scan
steps (:func:`truth_trajectory`, :func:`initial_estimate`, :func:`decide`, :func:`measure`,
:func:`fuse`) are what the in-process simulator calls, and what the world, sensor and manager
processes call too: the distributed layer adds transport and nothing else.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from covnet.core import streams
from covnet.core.allocation.constraints import Constraints
from covnet.core.gaussian import Gaussian, Mat, Vec
from covnet.core.kalman import predict, predict_covariance, update_covariance, update_sequential
from covnet.core.motion import cv_transition, dwna_noise_gain, dwna_process_noise
from covnet.core.sensing import (
    correlated_noise,
    information_gain,
    measure_factored,
    position_matrix,
)
from covnet.core.truth import linear_gaussian_trajectory
from covnet.covariance_control.config import (
    AUTO_NODE_LIMIT,
    BOUNDED_GAP,
    Scenario,
)
from covnet.covariance_control.searches import FAST_PATH_MAX as FAST_PATH_MAX
from covnet.covariance_control.searches import SEARCHES
from covnet.covariance_control.searches import feasible_count as feasible_count

if TYPE_CHECKING:
    from covnet.core.allocation import Allocation, AllocationPlan


@dataclass(frozen=True)
class SearchSettings:
    """``allocation.search`` and its options (:class:`~covnet.covariance_control.config.\
AllocationSpec`): ``mode`` ``exact | bounded | greedy | auto``; ``bounded`` stops at the
    relative ``gap`` (default ``BOUNDED_GAP``), ``time_limit_s`` or ``node_limit`` (when neither
    limit is given: ``AUTO_NODE_LIMIT`` nodes, so that the decision is deterministic).
    ``auto``: ``exact`` up to ``AUTO_EXACT_MAX`` candidate sensors, ``bounded`` beyond, decided
    once for the configured network (:meth:`resolved`)."""

    mode: str = "auto"
    gap: float | None = None
    time_limit_s: float | None = None
    node_limit: int | None = None

    def resolved(self, n_candidates: int) -> str:
        """The search ``auto`` stands for with ``n_candidates`` sensors (else ``mode``): the
        entry of :data:`~covnet.covariance_control.searches.SEARCHES` that decides."""
        return SEARCHES[self.mode].resolved(n_candidates).name

    def bounded_options(self) -> tuple[float, float | None, int | None]:
        """``(rel_gap, time_limit_s, node_limit)`` of a bounded decision."""
        gap = BOUNDED_GAP if self.gap is None else self.gap
        nodes = self.node_limit
        if nodes is None and self.time_limit_s is None:
            nodes = AUTO_NODE_LIMIT
        return gap, self.time_limit_s, nodes


@dataclass(frozen=True)
class Model:
    """Arrays of one scenario: motion ``F, G, Q``, sensors ``H, R_j`` (and :attr:`gains`
    ``J_j``), schedule ``P_d``.

    :attr:`plan`: the allocation plan of ``gains`` under the configured ``constraints``
    (:func:`covnet.core.allocation.prepare`: the gains validated and the gain-only subset tables
    built once, when the first decision needs them: a process that never decides, a sensor or
    the world, never builds them); :func:`decide` passes it at every scan (``exact`` over at
    most ``FAST_PATH_MAX`` candidates; the other searches take the gains).  ``search``: how
    :func:`decide` searches (:class:`SearchSettings`, ``auto`` resolved for the configured
    network: :attr:`search_mode`).  ``plans``: the plans
    per constraint set, ``constraints -> plan``, filled by :meth:`plan_for` the first time a
    constraint set is decided under (the configured one, and one per distinct set of run-time
    failures, ``unavailable``: a handful in practice).
    """

    sensor_ids: tuple[str, ...]
    T: float
    F: Mat
    G: Mat
    Q: Mat
    sigma_a: float
    H: Mat
    R: Mat  # (Ns, 2, 2)
    P0: Mat
    x0: Vec  # true initial state at t = 0
    desired_from: tuple[int, ...]
    desired_P: Mat  # (n_phases, 4, 4)
    constraints: Constraints
    tie_rtol: float
    seed: int
    scans: int
    search: SearchSettings = SearchSettings()
    # allocation.policy and its budget K (``covariance_control``: the search above)
    policy: str = "covariance_control"
    budget: int | None = None
    plans: dict[Constraints, AllocationPlan] = field(
        default_factory=dict, compare=False, repr=False
    )
    gains_given: Mat | None = None  # (Ns, 4, 4) supplied (a loss-aware model), else derived
    _derived: dict[str, Mat] = field(default_factory=dict, compare=False, repr=False)

    @property
    def noise_factors(self) -> Mat:
        """``(Ns, 2, 2)``: the lower Cholesky factor ``L_j`` of each ``R_j`` (``R_j = L_j L_jᵀ``),
        computed once: every scan draws ``v = L_j e`` (:func:`covnet.core.sensing.measure`)."""
        L = self._derived.get("noise_factors")
        if L is None:
            L = self._derived["noise_factors"] = np.stack([np.linalg.cholesky(Rj) for Rj in self.R])
        return L

    @property
    def gains(self) -> Mat:
        """``(Ns, 4, 4)``: ``J_j = Hᵀ R_j⁻¹ H`` (or :attr:`gains_given`), computed on first use
        (start-up: the world and a measuring sensor never need them, nor scipy.linalg)."""
        if self.gains_given is not None:
            return self.gains_given
        g = self._derived.get("gains")
        if g is None:
            g = self._derived["gains"] = np.stack([information_gain(self.H, Rj) for Rj in self.R])
        return g

    @property
    def search_mode(self) -> str:
        """``exact``, ``bounded`` or ``greedy``: ``search`` with ``auto`` resolved for the
        configured candidates (the sensors not excluded)."""
        n = len(self.sensor_ids) - len(self.constraints.excluded)
        return self.search.resolved(n)

    @property
    def reports_gap(self) -> bool:
        """Decisions report a certified lower bound and gap (``bounded``, ``greedy``: the
        search entry's ``reports_gap``)."""
        return SEARCHES[self.search_mode].reports_gap

    @property
    def plan(self) -> AllocationPlan:
        """The plan of the configured constraints (prepared on first use)."""
        return self.plan_for(self.constraints)

    def plan_for(self, constraints: Constraints) -> AllocationPlan:
        """The plan for ``constraints``: from :attr:`plans`, prepared (once) if new."""
        plan = self.plans.get(constraints)
        if plan is None:
            # the allocator (and scipy.linalg): start-up of the processes that never decide
            from covnet.core.allocation import prepare

            plan = self.plans[constraints] = prepare(self.gains, constraints)
        return plan

    def desired(self, scan: int) -> Mat:
        """``P_d(t_k)``: the last schedule entry whose ``from_scan <= scan``."""
        i = int(np.searchsorted(np.asarray(self.desired_from), scan, side="right")) - 1
        return self.desired_P[max(i, 0)]

    def index(self, sensor_id: str) -> int:
        return self.sensor_ids.index(sensor_id)


def build_model(sc: Scenario) -> Model:
    """The arrays of ``sc``.  A config with ``targets:`` (many targets,
    :mod:`covnet.covariance_control.targets`) gets the model of its first target and of its
    position sensors (``H``, ``R``, gains; another model's ``R`` is a placeholder, never
    used): the part the many-target steps share with the paper's."""
    T = sc.period_s
    ids = sc.sensor_ids
    H = position_matrix(2)
    R = np.stack([correlated_noise(*s.position_noise) for s in sc.sensors])
    al = sc.allocation
    constraints = Constraints(
        excluded=frozenset(ids.index(s) for s in al.excluded),
        required=frozenset(ids.index(s) for s in al.required),
        max_active=al.max_active,
    )
    P0_diag = sc.filter.P0_diag
    if not sc.targets:  # the paper's target (or surveillance with births only: a default)
        tg = sc.target
        px, py = tg.initial_position_m
        vx, vy = tg.initial_velocity_mps
        sigma_a = q = tg.accel_noise_std_mps2
        desired = sc.desired
    else:
        t0 = sc.targets[0]
        px, py = t0.initial_position_m
        vx, vy = t0.initial_velocity_mps
        sigma_a = t0.accel_noise_std_mps2
        q = sigma_a if t0.filter_accel_noise_std_mps2 is None else t0.filter_accel_noise_std_mps2
        desired = t0.desired
        P0_diag = P0_diag if t0.P0_diag is None else t0.P0_diag
    return Model(
        sensor_ids=ids,
        T=T,
        F=cv_transition(T, 2),
        G=dwna_noise_gain(T, 2),
        Q=dwna_process_noise(T, q, 2),
        sigma_a=sigma_a,
        H=H,
        R=R,
        P0=np.diag(np.asarray(P0_diag, dtype=np.float64)),
        x0=np.array([px, vx, py, vy], dtype=np.float64),
        desired_from=tuple(d.from_scan for d in desired),
        # surveillance's truth-only targets have no schedule (the tracks' is its own)
        desired_P=np.stack([d.as_matrix() for d in desired]) if desired else np.zeros((0, 4, 4)),
        constraints=constraints,
        tie_rtol=al.tie_rtol,
        seed=sc.seed,
        scans=sc.scans,
        search=SearchSettings(al.search, al.gap, al.time_limit_s, al.node_limit),
        policy=al.policy,
        budget=al.budget,
    )


def truth_trajectory(model: Model) -> Mat:
    """True states at scans ``1..N`` (``(N, 4)``), from the seed's TRUTH stream."""
    rng = streams.stream(model.seed, streams.TRUTH)
    return linear_gaussian_trajectory(model.x0, model.F, model.G, model.sigma_a, model.scans, rng)


def initial_estimate(model: Model, mode: str = "perturbed") -> Gaussian:
    """``N(x̂0, P0)`` with ``x̂0 = x0 + e``, ``e ~ N(0, P0)`` (or ``x̂0 = x0`` for ``truth``)."""
    if mode == "truth":
        return Gaussian(model.x0.copy(), model.P0.copy())
    rng = streams.stream(model.seed, streams.INITIAL)
    e = np.linalg.cholesky(model.P0) @ rng.standard_normal(model.x0.shape[0])
    return Gaussian(model.x0 + e, model.P0.copy())


def predict_step(model: Model, posterior: Gaussian) -> Gaussian:
    """One period ahead: ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``."""
    return predict(posterior, model.F, model.Q)


def predict_cov(model: Model, P: Mat) -> Mat:
    """The covariance of :func:`predict_step` alone (bit for bit the same)."""
    return predict_covariance(P, model.F, model.Q)


def decide(
    model: Model,
    P_pred: Mat,
    scan: int,
    metric: str,
    unavailable: frozenset[int] = frozenset(),
) -> Allocation:
    """Covariance control for scan ``k``: argmin over feasible subsets of ``f(P_i, P_d(t_k))``,
    searched by the entry of :data:`~covnet.covariance_control.searches.SEARCHES` that
    ``model.search`` names (:attr:`Model.search_mode`, ``auto`` resolved).

    ``unavailable`` (failed sensors seen at run time) joins the configured exclusions.
    ``exact``: up to ``FAST_PATH_MAX`` candidates the fast path with the plan for the resulting
    constraints (:meth:`Model.plan_for`, prepared once per set), branch and bound beyond, both
    the exhaustive search's result bit for bit.  ``bounded`` / ``greedy``: the best subset found,
    with its certified ``lower_bound`` and ``gap`` (:mod:`covnet.core.allocation.search`).
    """
    c = model.constraints.without(unavailable)
    if unavailable and len(c.excluded) == len(model.sensor_ids):
        return nothing_on(P_pred, model.desired(scan), metric)
    if model.policy != "covariance_control":
        # start-up: the baseline policies only when one is configured
        from covnet.covariance_control.policies import decide_by_policy

        return decide_by_policy(model, P_pred, scan, metric, c)
    return SEARCHES[model.search_mode].decide(model, P_pred, model.desired(scan), metric, c)


def nothing_on(P_prior: Mat, P_d: Mat, metric: str) -> Allocation:
    """The decision of a scan whose every sensor is down (failed at run time, the rest
    excluded): nobody is enabled and the filter only predicts, so the empty subset with the
    value ``f(P⁻, P_d)`` and ``P = P⁻``; with several fusion points (``P_prior`` ``(K, n, n)``,
    peer mode) the worst point's.  (The allocator refuses an empty subset: the manager died
    with "all 8 sensors are excluded" when the one host of every sensor was killed.)"""
    # start-up: the allocator's record and the metrics only where a decision is made
    from covnet.core.allocation.exact import Allocation
    from covnet.core.metrics import get_metric

    points = np.asarray(P_prior, dtype=np.float64)
    points = points[None] if points.ndim == 2 else points
    f = get_metric(metric)
    values = [float(f(P, P_d)) for P in points]
    worst = int(np.argmax(values))
    return Allocation((), values[worst], points[worst].copy(), 1, 1)


def measure(model: Model, sensor_index: int, scan: int, true_state: Vec) -> Vec:
    """Sensor ``j``'s measurement at scan ``k``: ``z = H x + v``, ``v`` from stream (j, k)."""
    rng = streams.sensor_stream(model.seed, sensor_index, scan)
    return measure_factored(model.H, model.noise_factors[sensor_index], true_state, rng)


def fused_covariance(model: Model, P_pred: Mat, noises: Sequence[tuple[int, Mat]]) -> Mat:
    """The posterior covariance :func:`fuse` will produce from ``(sensor_index, R)``, without
    the measurements: bit for bit the same (the same updates, in the same order)."""
    P = P_pred
    for _, R in sorted(noises, key=lambda m: m[0]):
        P = update_covariance(P, model.H, R)
    return P


def usable_measurement(z: Mat, R: Mat) -> bool:
    """A measurement the filter may fuse: one position ``z`` ``(1, 2)`` with a symmetric
    positive-definite ``R`` ``(2, 2)`` (finiteness is the wire schema's job)."""
    return bool(
        z.shape == (1, 2)
        and R.shape == (2, 2)
        and R[0, 1] == R[1, 0]
        and R[0, 0] > 0
        and R[0, 0] * R[1, 1] - R[0, 1] ** 2 > 0
    )


def fuse(model: Model, prior: Gaussian, measurements: Sequence[tuple[int, Vec, Mat]]) -> Gaussian:
    """Sequential Joseph-form updates with ``(sensor_index, z, R)``, in ascending sensor index
    (a canonical order, so the result does not depend on arrival order)."""
    ordered = sorted(measurements, key=lambda m: m[0])
    return update_sequential(prior, [(z, model.H, R) for _, z, R in ordered])
