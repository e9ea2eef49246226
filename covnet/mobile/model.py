"""The arrays of a mobile scenario and the per-scan steps every runner shares.

:func:`build_model` turns a validated :class:`~covnet.mobile.config.MobileConfig` into arrays.
The steps follow the timeline of spec §2 for one scan k−1 → k (scans k = 1..K, time ``kT``)::

    1  predict every track to k                          predict_tracks
    2  cost tensor for every (i, j, ρ)                    decide
    3  decision: one mode per sensor, a set of pairs      decide
    4  the platforms move                                 move_platforms
    5  the world advances the targets                     (truth row k)
    6  each chosen pair measures from the truth geometry  measure_pair
    7  each filter updates with its detections            update_track

so that the in-process run (:mod:`covnet.mobile.simulate`) and a future multi-process run (world,
sensor and manager nodes) call the very same functions and draw the very same numbers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from covnet.core.gaussian import Gaussian, Mat, Vec
from covnet.core.kalman import update
from covnet.core.mobile.cost import CostParams, CostTensor, cost_tensor
from covnet.core.mobile.decision import (
    SOLVERS,
    Decision,
    DecisionProblem,
    SolverOptions,
    decide_lp,
)
from covnet.core.mobile.models import (
    C_POS,
    INITIAL,
    STAY,
    TRUTH,
    IntVec,
    Sensors,
    TargetModels,
    cv_model,
    detection_probability,
    draw_detection,
    initial_estimates,
    noise_covariance,
    noise_growth,
    pair_stream,
    stream,
    truth_trajectories,
)
from covnet.core.mobile.models import move_platforms as core_move_platforms
from covnet.core.validation_gate import passes_measurement
from covnet.mobile.config import MobileConfig


@dataclass(frozen=True)
class MobileModel:
    """Arrays of one scenario: targets, sensors at their start, cost parameters, solver."""

    target_ids: tuple[str, ...]
    sensor_ids: tuple[str, ...]
    scans: int
    seed: int
    T: float
    x0: Mat  # (M, 4) true initial states
    P0: Mat  # (4, 4)
    targets: TargetModels
    sensors: Sensors  # positions at scan 0
    params: CostParams
    solver: str
    options: SolverOptions
    compare_exact: bool

    @property
    def M(self) -> int:
        return len(self.target_ids)

    @property
    def N(self) -> int:
        return len(self.sensor_ids)


def build_model(cfg: MobileConfig) -> MobileModel:
    T = cfg.scan_period_s
    A_cv, B_cv = cv_model(T)
    A = np.stack([np.asarray(t.A) if t.A is not None else A_cv for t in cfg.targets])
    B = np.stack([np.asarray(t.B) if t.B is not None else B_cv for t in cfg.targets])
    sig = np.array([t.sigma_a_mps2 for t in cfg.targets])
    sensors = Sensors(
        position=np.array([s.start_m for s in cfg.sensors], dtype=np.float64),
        speed=np.array([s.speed_mps for s in cfg.sensors]),
        R0=np.stack([s.R0() for s in cfg.sensors]),
        r_pd=np.array([s.r_pd_m for s in cfg.sensors]),
        b0=np.array([s.b0 for s in cfg.sensors]),
        b1=np.array([s.b1 for s in cfg.sensors]),
        capacity=np.array(
            [np.inf if s.capacity is None else float(s.capacity) for s in cfg.sensors]
        ),
    )
    w, d = cfg.weights, cfg.detection
    params = CostParams(
        T=T,
        alpha=w.alpha,
        beta=w.beta,
        gamma=w.gamma,
        PD=d.PD,
        a=d.a,
        b=d.b,
        c=d.c,
        L=(cfg.noise_growth_L_m[0], cfg.noise_growth_L_m[1]),
        dist_uses_velocity=cfg.dist_uses_velocity,
        trace_kind=cfg.trace_kind,
        pd_include_track_cov=cfg.pd_include_track_cov,
        null_penalty=cfg.null_penalty,
    )
    return MobileModel(
        target_ids=cfg.target_ids,
        sensor_ids=cfg.sensor_ids,
        scans=cfg.scans,
        seed=cfg.seed,
        T=T,
        x0=np.array([t.x0 for t in cfg.targets], dtype=np.float64),
        P0=np.diag(np.asarray(cfg.filter.P0_diag, dtype=np.float64)),
        targets=TargetModels(A=A, B=B, sigma_a=sig),
        sensors=sensors,
        params=params,
        solver=cfg.solver,
        options=SolverOptions(cfg.milp.time_limit_s, cfg.milp.rel_gap, cfg.milp.linking),
        compare_exact=cfg.compare_exact,
    )


def truth(model: MobileModel) -> Mat:
    """True target states ``(K + 1, M, 4)`` from ``default_rng([seed, 1])``."""
    return truth_trajectories(model.x0, model.targets, model.scans, stream(model.seed, TRUTH))


def initial_tracks(model: MobileModel) -> tuple[Mat, Mat]:
    """``x̂0 = x0 + N(0, P0)`` from ``default_rng([seed, 2])``; ``P0`` for every track."""
    x = initial_estimates(model.x0, model.P0, stream(model.seed, INITIAL))
    return x, np.broadcast_to(model.P0, (model.M, 4, 4)).copy()


@dataclass(frozen=True)
class Step:
    """One decision: its problem and costs, the decision, and the wall time of each part.

    ``decision.modes`` and ``.assign`` index *all* sensors (a sensor left out by ``alive`` stays
    and observes nothing).
    """

    costs: CostTensor
    problem: DecisionProblem
    decision: Decision
    cost_s: float
    solve_s: float


def decide(
    model: MobileModel,
    x_pred: Mat,
    P_pred: Mat,
    position: Mat,
    alive: np.ndarray | None = None,
    solver: str | None = None,
) -> Step:
    """Steps 2–3: the cost tensor with the sensors at ``position`` (N, 2), then the decision.

    ``alive`` (N,) bool: sensors that are out (failed) leave the problem: the decision is made
    over the others, and the targets nobody can take are reported unobserved.
    """
    sensors = replace(model.sensors, position=np.asarray(position, dtype=np.float64))
    idx = np.arange(model.N) if alive is None else np.flatnonzero(alive)
    sub = sensors if idx.size == model.N else sensors.subset(idx)
    t0 = time.perf_counter()
    costs = cost_tensor(x_pred, P_pred, sub, model.params)
    t1 = time.perf_counter()
    problem = DecisionProblem(costs.c, costs.c0, sub.capacity)
    d = SOLVERS[solver or model.solver](problem, model.options)
    t2 = time.perf_counter()
    if idx.size != model.N:
        modes = np.full(model.N, STAY, dtype=np.intp)
        modes[idx] = d.modes
        assign = np.full(model.M, -1, dtype=np.intp)
        obs = d.assign >= 0
        assign[obs] = idx[d.assign[obs]]
        d = replace(d, modes=modes, assign=assign)
    return Step(costs, problem, d, t1 - t0, t2 - t1)


def lp_reference(problem: DecisionProblem, step: Step) -> Decision:
    """The patent's LP + post-step decision of a problem (the step's own if it is one)."""
    if step.decision.solver in ("lp", "lp_highs", "closed_form"):
        return step.decision
    return decide_lp(problem)


def move_platforms(model: MobileModel, position: Mat, modes: IntVec) -> tuple[Mat, Mat]:
    """Step 4 (spec §3.2): ``a ← a + T V Δ_ρ``; returns the positions and the velocities."""
    return core_move_platforms(position, model.sensors.speed, modes, model.T)


def noise_of(model: MobileModel, j: int, x: Vec, q: Vec, qdot: Vec) -> Mat:
    """``R`` of sensor j at ``q`` moving at ``q̇`` for a target (estimate) at ``x``."""
    g = noise_growth(x, q, qdot, np.asarray(model.params.L), model.params.dist_uses_velocity)
    return noise_covariance(g, model.sensors.R0[j])


def true_pd(model: MobileModel, j: int, x_true: Vec, q: Vec) -> float:
    """Pd of sensor j at ``q`` for a target truly at ``x_true`` (the truth's field)."""
    p = model.params
    return float(detection_probability(x_true, q, model.sensors.r_pd[j], p.PD, p.a, p.b, p.c))


def measure_pair(
    model: MobileModel, scan: int, i: int, j: int, x_true: Vec, q: Vec, qdot: Vec
) -> tuple[bool, Vec, float]:
    """Step 6: pair (i, j) at ``scan``, from the truth geometry, stream ``[seed, 3, k, i, j]``.

    Returns ``(detected, z, Pd)``.  The truth's field is ``S = r_j² I`` whatever
    ``pd_include_track_cov`` says: that option widens the manager's model of the field for an
    uncertain track; a real target at a known position has no track covariance.
    """
    Pd = true_pd(model, j, x_true, q)
    R = noise_of(model, j, x_true, q, qdot)
    detected, z = draw_detection(pair_stream(model.seed, scan, i, j), Pd, C_POS @ x_true, R)
    return detected, z, Pd


def passes_gate(
    model: MobileModel, x_pred: Vec, P_pred: Mat, z: Vec, j: int, q: Vec, qdot: Vec
) -> bool:
    """The fusion centre's validation gate (:mod:`covnet.core.validation_gate`) on a detection
    ``z`` of the target predicted at ``N(x⁻, P⁻)`` by sensor ``j`` at ``q`` moving at ``q̇``:
    ``νᵀ S⁻¹ ν ≤ γ`` with ``S = C P⁻ Cᵀ + R`` and the ``R`` of :func:`update_track`."""
    R = noise_of(model, j, x_pred, q, qdot)
    return passes_measurement(np.asarray(z, dtype=np.float64), R, C_POS, x_pred, P_pred)


def update_track(
    model: MobileModel, x_pred: Vec, P_pred: Mat, z: Vec, j: int, q: Vec, qdot: Vec
) -> Gaussian:
    """Step 7: Joseph-form update with ``R`` from the *predicted* estimate and the sensor's
    actual position and velocity."""
    R = noise_of(model, j, x_pred, q, qdot)
    return update(Gaussian(x_pred, P_pred), z, C_POS, R)
