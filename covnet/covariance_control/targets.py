"""Many targets: the model of a ``targets:`` scenario and the per-scan steps every runner shares
(spec ``multitarget.md``).

A sensor's working mode each scan is the target it dwells on, or off.  Per scan ``k``, for the
``T`` targets (each its own constant-velocity filter, the paper's ``F`` and its own ``Q``)::

    predict   x̂_t⁻, P_t⁻                                                   (predict)
    score     J_{j,t} = p_{j,t} H_j(x̂_t⁻)ᵀ R_j⁻¹ H_j(x̂_t⁻) for the pairs in coverage at x̂_t⁻
              (p = pd, 1 or the PDAF's q₂: allocation.detection)            (information)
    decide    a* = argmin Σ_t w_t f(P_t(a), P_d,t(k)) over the feasible assignments
              (T = 1: today's single-target allocator; T > 1: the core's assignment allocator)
                                                                             (decide)
    dwell     each sensor on simulates its returns from the truth: the target's, detected with
              probability pd inside coverage, and Poisson(clutter_rate) clutter uniform in the
              dwell's window, ẑ ± n_σ √diag S around the predicted measurement (the window is
              the manager's: it is sent in the command)                     (window, dwell)
    update    per target, its dwells in ascending sensor index: a sensor without clutter
              (clutter_rate 0) has nothing to associate: its return, if any, is the target's, a
              plain (extended) Kalman update; with clutter the returns are gated (χ²,
              gate_probability) and used by PDA or the nearest neighbour  (fuse)

**The paper's scenario is the case T = 1, position sensors, pd 1, no clutter, and gives exactly
today's results**: :func:`build` also reads a config without ``targets:`` (one target from
``target:`` and ``desired:``), and then every step is the paper's, bit for bit (a test runs
``configs/paper.yaml`` through these steps and compares with ``covnet run``): the decision is
:func:`covnet.covariance_control.model.decide`'s allocator with the same gains, a position
sensor's return is :func:`covnet.covariance_control.model.measure`'s draw and its update
:func:`covnet.core.kalman.update`, in ascending sensor index.

Random streams: target ``t``'s truth from ``(seed, TRUTH)`` for ``t = 0`` and ``(seed, TRUTH,
t)`` after it, its initial estimate likewise from ``INITIAL``; sensor ``j``'s dwell at scan
``k`` from its noise stream ``(seed, SENSOR, j, k)`` (a sensor dwells on one target a scan),
drawn in a fixed order: the measurement noise (exactly the paper's draw), the detection
uniform, the clutter count, the clutter uniforms, the permutation of the returns.  So the truth
does not depend on the allocation, and a change of ``pd`` or of the clutter never changes a
target return's noise.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from covnet.core import streams
from covnet.core.allocation import InfeasibleAllocation, allocate, prepare
from covnet.core.allocation.assignment import MultiConstraints
from covnet.core.allocation.constraints import Constraints
from covnet.core.association import (
    gate_threshold,
    gate_volume,
    information_reduction_table,
    information_reduction_table_streamed,
    log_unit_ball_volume,
    nearest_neighbour_update,
    pda_update,
)
from covnet.core.detection import ClutterWindow, clutter_window
from covnet.core.ekf import predict_measurement
from covnet.core.fusion import LocalTrack, information_fusion
from covnet.core.gaussian import Gaussian, Mat, Vec
from covnet.core.kalman import predict, update
from covnet.core.manoeuvre import manoeuvring_trajectory
from covnet.core.metrics import get_metric
from covnet.core.motion import dwna_process_noise
from covnet.core.sensing import information_gain, measure_factored, position_matrix
from covnet.core.sensor_models import SENSOR_MODELS, FieldOfView, SensorModel, wrap_angle
from covnet.core.truth import linear_gaussian_trajectory
from covnet.covariance_control.config import Scenario, SensorSpec, segments
from covnet.covariance_control.model import Model, build_model
from covnet.covariance_control.searches import SEARCHES, decide_many

if TYPE_CHECKING:
    from covnet.core.allocation import AllocationPlan
__all__ = [
    "OFF",
    "Dwell",
    "History",
    "LocalTargets",
    "TargetDecision",
    "TargetModel",
    "TargetsModel",
    "build",
    "decide",
    "dwell",
    "fuse",
    "fuse_tracks",
    "information",
    "initial_estimates",
    "max_clutter_in_gate",
    "predict_all",
    "q_grid_extension",
    "truth_trajectories",
    "window",
    "window_from_vec",
    "window_vec",
]

#: ``a_j = OFF``: sensor ``j`` dwells on no target (the core's value)
OFF = -1
#: the stream domain of the PDAF information-reduction tables (``allocation.detection: pda``)
QFACTOR = 3
#: μ_G grid of those tables (mean clutter in the gate) up to 4; above, each sensor's table goes
#: on, on :func:`q_grid_extension`, as far as its config lets ``μ_G`` go
_Q_GRID = np.linspace(0.0, 4.0, 81)
#: grid points per doubling of ``μ_G`` above 4 (linear interpolation error about 2e-4 in ``q₂``,
#: below the Monte Carlo error)
_Q_PER_DOUBLING = 8


def max_clutter_in_gate(
    clutter_rate: float,
    dim_z: int,
    angle_components: Sequence[bool],
    gate_probability: float,
    window_sigma: float,
) -> float:
    """``U``, the largest mean clutter in the gate ``μ_G`` of a dwell whose gate lies in its
    clutter window (the PDAF's assumption), from the config alone: ``r min(1, ρ)`` for a
    sensor without angle components, ``r`` for one with (``r = clutter_rate``,
    ``ρ = c_n γ^{n/2} / (2k)^n``, ``k = clutter_window_sigma``, ``n = dim_z``).

    Proof.  :func:`_q2` takes ``μ_G = r V_G / V_W`` with the gate volume
    ``V_G = c_n γ^{n/2} √det S`` (:func:`covnet.core.association.gate_volume`) and the window
    volume ``V_W = Π_i 2 a_i`` (:class:`covnet.core.detection.ClutterWindow`), its half-widths
    ``a_i = k √S_ii``, an angle component's capped at ``π``
    (:func:`covnet.core.detection.clutter_window`), the same ``S``.  ``S`` is positive
    definite, so Hadamard's inequality gives ``det S ≤ Π_i S_ii``.  Without a capped
    component ``V_W = (2k)^n Π_i √S_ii`` and ``V_G / V_W ≤ c_n γ^{n/2} / (2k)^n = ρ``, so
    ``μ_G ≤ r ρ``.  Whatever the window: the clutter is drawn uniformly in the window, so the
    mean number inside the gate is ``r |G ∩ W| / V_W ≤ r``, and ``r V_G / V_W`` exceeds ``r``
    exactly when ``V_G > V_W``, the gate does not fit in the window.  An angle component's cap
    leaves ``V_G / V_W`` unbounded (``S_ii`` grows, ``a_i`` stays ``π``), hence ``r`` there.
    So ``μ_G ≤ U`` whenever the gate fits in the window; beyond (only where it does not),
    the table holds ``q₂(U)``, ``q₂`` at the most clutter the gate can hold.  (Floating
    point may put ``μ_G`` a few ulps above ``r ρ``: held, a change far below the Monte Carlo
    error.)"""
    r = float(clutter_rate)
    n = int(dim_z)
    if r == 0.0:
        return 0.0
    if any(angle_components):
        return r
    g = gate_threshold(n, gate_probability)
    log_v = log_unit_ball_volume(n) + 0.5 * n * math.log(g)  # the whitened gate's volume
    rho = math.exp(log_v - n * math.log(2.0 * float(window_sigma)))
    return r * min(1.0, rho)


def q_grid_extension(mu_max: float) -> Vec:
    """The ``μ_G`` grid of a table above :data:`_Q_GRID`: ``4 · 2^{i/8}``, ``i = 1, 2, ...``
    while below ``mu_max``, and ``mu_max`` itself; empty for ``mu_max <= 4``."""
    top = _Q_GRID[-1]
    if not mu_max > top:
        return np.zeros(0)
    k = int(math.floor(_Q_PER_DOUBLING * math.log2(mu_max / top)))
    grid = top * 2.0 ** (np.arange(1, k + 1) / _Q_PER_DOUBLING)
    grid = grid[grid < mu_max]
    return np.append(grid, mu_max)


@dataclass(frozen=True)
class TargetModel:
    """One target: its true initial state ``x0``, white acceleration ``sigma_a`` (the truth's),
    ``Q`` (the filter's), manoeuvres (truth only), initial covariance ``P0`` and its schedule of
    desired covariances and weights (``desired_from[i]`` on: ``desired_P[i]``,
    ``weights[i]``)."""

    id: str
    x0: Vec
    sigma_a: float
    Q: Mat
    P0: Mat
    segments: tuple[Any, ...]
    desired_from: tuple[int, ...]
    desired_P: Mat
    weights: tuple[float, ...]

    def _phase(self, scan: int) -> int:
        i = int(np.searchsorted(np.asarray(self.desired_from), scan, side="right")) - 1
        return max(i, 0)

    def desired(self, scan: int) -> Mat:
        """``P_d,t(k)``."""
        return self.desired_P[self._phase(scan)]

    def weight(self, scan: int) -> float:
        """``w_t(k)``."""
        return self.weights[self._phase(scan)]


@dataclass(frozen=True)
class TargetsModel:
    """A scenario's targets and sensors.  ``base``: the one-target :class:`~covnet.covariance_
    control.model.Model` of the same sensors (``F``, ``T``, ids, constraints, ``tie_rtol``,
    seed, scans, and for position sensors ``H``, ``R`` and their gains); ``sensors``: each
    sensor's :class:`~covnet.core.sensor_models.SensorModel`; ``position``: which are position
    sensors (updated by the linear Kalman update); the association settings, ``detection`` and
    ``max_per_target`` of the config, the OSPA cut-off and order."""

    base: Model
    targets: tuple[TargetModel, ...]
    sensors: tuple[SensorModel, ...]
    position: tuple[bool, ...]
    method: str
    gate_probability: float
    window_sigma: float
    detection: str
    max_per_target: int | None
    ospa_c: float
    ospa_p: float
    initial_mode: str
    plans: dict[tuple[bytes, Constraints], AllocationPlan] = field(
        default_factory=dict, compare=False, repr=False
    )
    _q_tables: dict[int, tuple[Vec, Vec]] = field(default_factory=dict, compare=False, repr=False)

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return self.base.sensor_ids

    @property
    def target_ids(self) -> tuple[str, ...]:
        return tuple(t.id for t in self.targets)

    @property
    def scans(self) -> int:
        return self.base.scans

    @property
    def T(self) -> float:
        return self.base.T

    @property
    def constant_gains(self) -> bool:
        """Every sensor a position sensor scored with a constant ``p``: ``J`` does not depend
        on the predicted states (the paper's case)."""
        return all(self.position) and self.detection != "pda"

    def plan_for(self, gains: Mat, constraints: Constraints) -> AllocationPlan:
        """A single-target allocation plan for ``gains`` under ``constraints``, kept (the gains
        of position sensors do not change from scan to scan: the paper's plans are built once)."""
        key = (gains.tobytes(), constraints)
        plan = self.plans.get(key)
        if plan is None:
            if len(self.plans) > 64:
                self.plans.clear()
            plan = self.plans[key] = prepare(gains, constraints)
        return plan

    def q_grid(self, j: int) -> Vec:
        """The ``μ_G`` grid of sensor ``j``'s ``q₂`` table (:meth:`q_table`): :data:`_Q_GRID`,
        then, when its config lets ``μ_G`` exceed 4, :func:`q_grid_extension` up to
        :func:`max_clutter_in_gate`."""
        return self._q(j)[0]

    def q_table(self, j: int) -> Vec:
        """The PDAF information-reduction factor ``q₂`` of sensor ``j`` on :meth:`q_grid`
        (``allocation.detection: pda``), computed once, from the stream
        ``(seed, QFACTOR, j)`` and the config alone (not from the order of the calls).

        On :data:`_Q_GRID` (``μ_G <= 4``) it is :func:`covnet.core.association.
        information_reduction_table`'s, bit for bit as it always was.  Above 4, up to
        :func:`max_clutter_in_gate` (at most ``clutter_rate``, 10⁴), it is
        :func:`covnet.core.association.information_reduction_table_streamed`'s from a fresh
        generator of the same stream: the same estimator and the same draws in the same order,
        so the whole table is one Monte Carlo estimate with common random numbers, smooth
        across 4.  Cost of the extension at ``clutter_rate`` 10⁴: 1.5 s (``dim_z = 1``) or
        3.6 s (``dim_z = 2``) on an idle core (7-11 s on a loaded one), under 10 MB."""
        return self._q(j)[1]

    def _q(self, j: int) -> tuple[Vec, Vec]:
        got = self._q_tables.get(j)
        if got is None:
            s = self.sensors[j]
            key = (self.base.seed, QFACTOR, j)
            pg = self.gate_probability
            q = information_reduction_table(s.pd, s.dim_z, _Q_GRID, streams.stream(*key), pg)
            top = max_clutter_in_gate(
                s.clutter_rate, s.dim_z, s.angle_components, pg, self.window_sigma
            )
            ext = q_grid_extension(top)
            grid = _Q_GRID
            if ext.size:
                qx = information_reduction_table_streamed(
                    s.pd, s.dim_z, ext, streams.stream(*key), pg
                )
                grid = np.concatenate([_Q_GRID, ext])
                q = np.concatenate([q, qx])
            got = self._q_tables[j] = (grid, q)
        return got


def _sensor_model(s: SensorSpec) -> SensorModel:
    """Sensor ``s``'s model, by its registry entry from the config's fields."""
    common: dict[str, Any] = {
        "sensor_xy": tuple(s.position_m) if s.position_m is not None else (0.0, 0.0),
        "max_range_m": math.inf if s.max_range_m is None else s.max_range_m,
        "fov": None if s.fov is None else FieldOfView(s.fov.center_deg, s.fov.half_width_deg),
        "pd": s.pd,
        "clutter_rate": s.clutter_rate,
    }
    return SENSOR_MODELS[s.model].from_fields(s.fields, **common)


def build(sc: Scenario) -> TargetsModel:
    """The model of ``sc``: its ``targets:``, or the one target of a paper config."""
    T = sc.period_s
    sensors = tuple(_sensor_model(s) for s in sc.sensors)
    position = tuple(s.paper_noise is not None for s in sc.sensors)
    P0_cfg = np.diag(np.asarray(sc.filter.P0_diag, dtype=np.float64))
    targets: list[TargetModel] = []
    if sc.targets is None:
        tg = sc.target
        x0 = [tg.initial_position_m[0], tg.initial_velocity_mps[0]]
        x0 += [tg.initial_position_m[1], tg.initial_velocity_mps[1]]
        targets.append(
            TargetModel(
                id="T1",
                x0=np.array(x0, dtype=np.float64),
                sigma_a=tg.accel_noise_std_mps2,
                Q=dwna_process_noise(T, tg.accel_noise_std_mps2, 2),
                P0=P0_cfg,
                segments=(),
                desired_from=tuple(d.from_scan for d in sc.desired),
                desired_P=np.stack([d.as_matrix() for d in sc.desired]),
                weights=(1.0,) * len(sc.desired),
            )
        )
    else:
        for t in sc.targets:
            x0 = [t.initial_position_m[0], t.initial_velocity_mps[0]]
            x0 += [t.initial_position_m[1], t.initial_velocity_mps[1]]
            w, weights = t.weight, []
            for d in t.desired:
                w = d.weight if d.weight is not None else w
                weights.append(w)
            P0 = P0_cfg if t.P0_diag is None else np.diag(np.asarray(t.P0_diag, dtype=np.float64))
            q = t.accel_noise_std_mps2
            q = q if t.filter_accel_noise_std_mps2 is None else t.filter_accel_noise_std_mps2
            targets.append(
                TargetModel(
                    id=t.id,
                    x0=np.array(x0, dtype=np.float64),
                    sigma_a=t.accel_noise_std_mps2,
                    Q=dwna_process_noise(T, q, 2),
                    P0=P0,
                    segments=tuple(segments(t)),
                    desired_from=tuple(d.from_scan for d in t.desired),
                    # surveillance: the targets are truth only, without a schedule
                    desired_P=np.stack([d.as_matrix() for d in t.desired])
                    if t.desired
                    else np.zeros((0, 4, 4)),
                    weights=tuple(weights),
                )
            )
    al = sc.allocation
    base = build_model(sc)  # the first target's and the position sensors' arrays
    return TargetsModel(
        base=base,
        targets=tuple(targets),
        sensors=sensors,
        position=position,
        method=sc.association.method,
        gate_probability=sc.association.gate_probability,
        window_sigma=sc.association.clutter_window_sigma,
        detection=al.detection,
        max_per_target=al.max_per_target,
        ospa_c=sc.ospa.cutoff_m,
        ospa_p=sc.ospa.order,
        initial_mode=sc.filter.initial_estimate,
    )


# --------------------------------------------------------------------------------------------
# truth, initial estimates, prediction
# --------------------------------------------------------------------------------------------


def _key(domain: int, t: int) -> tuple[int, ...]:
    """Target ``t``'s stream key in ``domain``: the paper's ``(domain,)`` for the first."""
    return (domain,) if t == 0 else (domain, t)


def truth_trajectories(tm: TargetsModel) -> Mat:
    """``(T, scans, 4)``: every target's true states at scans ``1..N`` (its manoeuvres, its
    own TRUTH stream; without manoeuvres the first is the paper's trajectory bit for bit)."""
    out = np.empty((len(tm.targets), tm.scans, 4))
    for t, tg in enumerate(tm.targets):
        rng = streams.stream(tm.base.seed, *_key(streams.TRUTH, t))
        if tg.segments:
            out[t] = manoeuvring_trajectory(tg.x0, tm.T, tg.sigma_a, tm.scans, rng, tg.segments)
        else:  # the paper's generator (manoeuvring_trajectory gives the same, to rounding)
            out[t] = linear_gaussian_trajectory(
                tg.x0, tm.base.F, tm.base.G, tg.sigma_a, tm.scans, rng
            )
    return out


def initial_estimates(tm: TargetsModel) -> list[Gaussian]:
    """Each target's ``N(x̂0, P0)``: ``x̂0 = x0 + e``, ``e ~ N(0, P0)`` from its INITIAL
    stream (or ``x̂0 = x0`` with ``initial_estimate: truth``)."""
    out = []
    for t, tg in enumerate(tm.targets):
        if tm.initial_mode == "truth":
            out.append(Gaussian(tg.x0.copy(), tg.P0.copy()))
            continue
        rng = streams.stream(tm.base.seed, *_key(streams.INITIAL, t))
        e = np.linalg.cholesky(tg.P0) @ rng.standard_normal(4)
        out.append(Gaussian(tg.x0 + e, tg.P0.copy()))
    return out


def predict_all(tm: TargetsModel, posteriors: Sequence[Gaussian]) -> list[Gaussian]:
    """One period ahead for every target: ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q_t``."""
    F = tm.base.F
    return [predict(g, F, tg.Q) for g, tg in zip(posteriors, tm.targets, strict=True)]


# --------------------------------------------------------------------------------------------
# what the allocator scores, and the decision
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=256)
def _position_gain(R_bytes: bytes) -> Mat:
    R = np.frombuffer(R_bytes).reshape(2, 2)
    return information_gain(position_matrix(2), R)


def _innovation_cov(tm: TargetsModel, j: int, pred: Gaussian) -> Mat:
    s = tm.sensors[j]
    H = s.jacobian(pred.x)
    S: Mat = H @ pred.P @ H.T + s.R
    return 0.5 * (S + S.T)


def information(tm: TargetsModel, preds: Sequence[Gaussian]) -> tuple[Mat, np.ndarray]:
    """``J`` ``(N, T, 4, 4)`` and ``feasible`` ``(N, T)``: sensor ``j`` covers target ``t`` at
    its predicted position, and then ``J_{j,t} = p H_j(x̂_t⁻)ᵀ R_j⁻¹ H_j(x̂_t⁻)`` with ``p``
    by ``allocation.detection``: ``expected`` ``pd``, ``ignore`` 1, ``pda`` the PDAF's
    ``q₂`` at the dwell's mean clutter in the gate (the clutter density over the window of
    :func:`window`).  A position sensor's ``HᵀR⁻¹H`` is the paper's gain (the same bits);
    another model's ``J = p WᵀW`` with ``W = L⁻¹ H`` (its ``whitened_jacobian``: ``diag(σ)⁻¹ H``
    for a diagonal ``R``, a radar's or bearing sensor's, without a LAPACK call per pair;
    :func:`covnet.core.sensor_models.predicted_information`'s value)."""
    N, T = len(tm.sensors), len(preds)
    J = np.zeros((N, T, 4, 4))
    feas = np.zeros((N, T), dtype=bool)
    X = np.array([g.x for g in preds])
    for j, s in enumerate(tm.sensors):
        cover = s.in_coverage(X)
        feas[j] = cover
        if not cover.any():
            continue
        if tm.detection == "ignore":
            p = np.ones(T)
        elif tm.detection == "expected" or s.clutter_rate == 0.0:
            p = np.full(T, s.pd)
        else:
            p = np.array([_q2(tm, j, g) if cover[t] else 0.0 for t, g in enumerate(preds)])
        if tm.position[j]:
            Jj = _position_gain(tm.base.R[j].tobytes())
            for t in np.flatnonzero(cover).tolist():
                J[j, t] = Jj if p[t] == 1.0 else p[t] * Jj
            continue
        idx = np.flatnonzero(cover)
        W = s.whitened_jacobian(X[idx])  # (n, dz, 4)
        Jt = p[idx, None, None] * (np.swapaxes(W, -1, -2) @ W)
        J[j, idx] = 0.5 * (Jt + np.swapaxes(Jt, -1, -2))
    return J, feas


def _q2(tm: TargetsModel, j: int, pred: Gaussian) -> float:
    """``q₂`` of sensor ``j`` on the target predicted at ``pred``: ``μ_G = λ V_G`` with the
    window's clutter density, interpolated in the sensor's table (:meth:`TargetsModel.q_grid`;
    above its last point, reached only where the gate does not fit in the window, held at its
    last value: :func:`max_clutter_in_gate`)."""
    s = tm.sensors[j]
    S = _innovation_cov(tm, j, pred)
    w = window(tm, j, pred)
    assert w is not None
    mu = s.clutter_rate / w.volume * gate_volume(S, tm.gate_probability)
    return float(np.interp(mu, tm.q_grid(j), tm.q_table(j)))


@dataclass(frozen=True)
class TargetDecision:
    """One scan's decision: ``assignment`` (per sensor a target index or :data:`OFF`),
    ``value`` ``F = Σ_t w_t v_t``, ``values`` the per-target ``v_t = f(P_t(a), P_d,t)``,
    ``P`` ``(T, 4, 4)`` the covariances the allocator expects, ``n_evaluated`` exact
    evaluations, ``feasible`` the coverage it decided under; ``lower_bound`` and ``gap`` the
    certificate of a bounded or greedy search (``None``: exact)."""

    assignment: tuple[int, ...]
    value: float
    values: tuple[float, ...]
    P: Mat
    n_evaluated: int
    feasible: np.ndarray
    lower_bound: float | None = None
    gap: float | None = None

    @property
    def subset(self) -> tuple[int, ...]:
        """The sensors on, ascending."""
        return tuple(j for j, a in enumerate(self.assignment) if a != OFF)

    def on_target(self, t: int) -> tuple[int, ...]:
        return tuple(j for j, a in enumerate(self.assignment) if a == t)


def decide(
    tm: TargetsModel,
    preds: Sequence[Gaussian],
    scan: int,
    metric: str,
    unavailable: frozenset[int] = frozenset(),
) -> TargetDecision:
    """Scan ``k``'s assignment (module docstring).  ``unavailable`` (failed sensors) join the
    configured exclusions, and a required sensor is required only while it is up and can be
    on: it covers some target, and the required sensors that can all be on at once under
    ``max_per_target`` are :func:`assignable`'s (the others are free sensors this scan; the
    summary counts the scans each required sensor was off).  ``T = 1`` is today's
    single-target allocator (:func:`covnet.core.allocation.allocate`) on the feasible sensors
    when the search is exact; otherwise (and for ``T > 1``) the configured search's
    many-target form (:func:`covnet.covariance_control.searches.decide_many`: ``exact`` the
    assignment allocator, ``bounded``/``greedy`` its searches at scale, ``auto`` exact up to
    ``MANY_EXACT_MAX`` sensors).  With no feasible sensor every
    sensor is off."""
    J, feas = information(tm, preds)
    P_pred = np.array([g.P for g in preds])
    P_d = np.array([tg.desired(scan) for tg in tm.targets])
    w = [tg.weight(scan) for tg in tm.targets]
    c = tm.base.constraints
    N, T = feas.shape
    nowhere = frozenset(j for j in range(N) if not feas[j].any())
    excluded = c.excluded | unavailable | nowhere
    required = assignable(c.required - unavailable, feas, tm.max_per_target)
    if len(excluded - required) >= N:
        return _all_off(tm, preds, P_d, w, metric, feas)
    mc = MultiConstraints(
        excluded=frozenset(excluded - required),
        required=frozenset(required),
        max_active=c.max_active,
        max_per_target=tm.max_per_target,
    )
    if tm.base.policy != "covariance_control":
        # start-up: the baseline policies only when one is configured
        from covnet.covariance_control.policies import decide_many_by_policy

        return TargetDecision(
            *decide_many_by_policy(tm, P_pred, J, P_d, w, scan, metric, feas, mc), feas
        )
    settings = tm.base.search
    n_on = N - len(mc.excluded)
    if T == 1 and SEARCHES[settings.mode].resolved_many(n_on).name == "exact":
        return _decide_one(tm, P_pred[0], J[:, 0], P_d[0], w[0], metric, excluded, required, feas)
    try:
        a = decide_many(settings, P_pred, J, P_d, metric, w, feas, mc, tm.base.tie_rtol)
    except InfeasibleAllocation:
        return _all_off(tm, preds, P_d, w, metric, feas)
    return TargetDecision(
        a.assignment, a.value, a.values, a.P, a.n_evaluated, feas, a.lower_bound, a.gap
    )


def assignable(
    required: frozenset[int], feas: np.ndarray, max_per_target: int | None
) -> frozenset[int]:
    """The required sensors that stay required this scan: the largest set of them that can all
    be on at once, each on a target it covers (``feas[j, t]``), at most ``max_per_target`` on a
    target.  A maximum bipartite b-matching of sensors to targets by augmenting paths, the
    sensors tried in ascending index (so a scan's set is the same in every runner): a required
    sensor left out is one that covers no target, or one more than its targets have room for.
    Without ``max_per_target`` every required sensor that covers a target stays required."""
    covering = sorted(j for j in required if feas[j].any())
    if max_per_target is None:
        return frozenset(covering)
    holders: list[list[int]] = [[] for _ in range(feas.shape[1])]

    def place(j: int, seen: set[int]) -> bool:
        for t in np.flatnonzero(feas[j]).tolist():
            if t in seen:
                continue
            seen.add(t)
            if len(holders[t]) < max_per_target:
                holders[t].append(j)
                return True
            for h in list(holders[t]):  # make room: move a holder to another target
                if place(h, seen):
                    holders[t].remove(h)
                    holders[t].append(j)
                    return True
        return False

    return frozenset(j for j in covering if place(j, set()))


def _decide_one(
    tm: TargetsModel,
    P_pred: Mat,
    J: Mat,
    P_d: Mat,
    w: float,
    metric: str,
    excluded: frozenset[int],
    required: frozenset[int],
    feas: np.ndarray,
) -> TargetDecision:
    """``T = 1``: today's allocator (the configured constraints, failed and out-of-coverage
    sensors excluded), with the plan of these gains."""
    c = tm.base.constraints
    cons = Constraints(excluded=excluded - required, required=required, max_active=c.max_active)
    if tm.max_per_target is not None:
        budget = tm.max_per_target if c.max_active is None else min(c.max_active, tm.max_per_target)
        cons = Constraints(cons.excluded, cons.required, budget)
    alloc = allocate(P_pred, tm.plan_for(J, cons), P_d, metric, tie_rtol=tm.base.tie_rtol)
    a = tuple(0 if j in alloc.subset else OFF for j in range(J.shape[0]))
    v = float(alloc.value)
    return TargetDecision(a, w * v, (v,), alloc.P[None], alloc.n_evaluated, feas)


def _all_off(
    tm: TargetsModel,
    preds: Sequence[Gaussian],
    P_d: Mat,
    w: Sequence[float],
    metric: str,
    feas: np.ndarray,
) -> TargetDecision:
    f = get_metric(metric)
    values = tuple(float(f(g.P, P_d[t])) for t, g in enumerate(preds))
    total = 0.0
    for t, v in enumerate(values):
        total = total + w[t] * v
    P = np.array([g.P for g in preds])
    return TargetDecision((OFF,) * len(tm.sensors), total, values, P, 0, feas)


# --------------------------------------------------------------------------------------------
# the dwell: its clutter window, its returns
# --------------------------------------------------------------------------------------------


def window(tm: TargetsModel, j: int, pred: Gaussian) -> ClutterWindow | None:
    """Sensor ``j``'s clutter window on the target predicted at ``pred``:
    ``h(x̂⁻) ± n_σ √diag S`` (:func:`covnet.core.detection.clutter_window`); ``None`` for a
    sensor without clutter."""
    s = tm.sensors[j]
    if s.clutter_rate == 0.0:
        return None
    return clutter_window(s, pred.x, _innovation_cov(tm, j, pred), tm.window_sigma)


def window_vec(w: ClutterWindow | None) -> Vec | None:
    """A window as the wire carries it: ``[centre..., half-width...]``."""
    return None if w is None else np.concatenate([w.center, w.half_width])


def window_from_vec(tm: TargetsModel, j: int, v: Vec | None) -> ClutterWindow | None:
    """:func:`window_vec`'s inverse for sensor ``j`` (``ValueError`` if it is not one)."""
    if v is None:
        return None
    s = tm.sensors[j]
    if v.shape != (2 * s.dim_z,):
        raise ValueError(f"a window of sensor {j} has {2 * s.dim_z} numbers, got {v.shape}")
    return ClutterWindow(v[: s.dim_z], v[s.dim_z :], s.angle_components)


def dwell(tm: TargetsModel, j: int, scan: int, x_true: Vec, win: ClutterWindow | None) -> Mat:
    """Sensor ``j``'s returns ``(m, dim_z)`` at scan ``scan`` dwelling on a target whose true
    state is ``x_true``, shuffled (module docstring for the draws).  A position sensor's target
    return is :func:`covnet.covariance_control.model.measure`'s draw, bit for bit."""
    s = tm.sensors[j]
    rng = streams.sensor_stream(tm.base.seed, j, scan)
    dz = s.dim_z
    if tm.position[j]:
        z0 = measure_factored(tm.base.H, tm.base.noise_factors[j], x_true, rng)
    else:
        e = rng.standard_normal(dz)
        z0 = s.h(x_true) + s.L @ e
    detected = rng.random() < s.pd and bool(s.in_coverage(x_true))
    rows = [z0[None, :]] if detected else []
    if s.clutter_rate > 0.0:
        if win is None:
            raise ValueError(f"sensor {j} has clutter: its dwell needs a window")
        n = int(rng.poisson(s.clutter_rate))
        U = rng.random((n, dz))
        rows.append(win.center + (2.0 * U - 1.0) * win.half_width)
    Z = np.concatenate(rows, axis=0) if rows else np.zeros((0, dz))
    am = np.asarray(s.angle_components, dtype=bool)
    if am.any() and Z.shape[0]:
        Z = np.where(am, wrap_angle(Z), Z)
    if Z.shape[0] > 1:
        Z = Z[rng.permutation(Z.shape[0])]
    return np.ascontiguousarray(Z)


# --------------------------------------------------------------------------------------------
# the update
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Dwell:
    """What one dwell did to its target's estimate: ``returns`` received, ``used`` whether a
    return moved the estimate, ``nis`` (``None``: nothing gated) the normalised innovation
    squared of the return the update relied on (the only return without clutter; PDA's most
    probable gated one; the nearest neighbour's), with ``dof`` its dimension."""

    sensor: int
    returns: int
    used: bool
    nis: float | None
    dof: int


def _update_one(
    tm: TargetsModel, j: int, prior: Gaussian, Z: Mat, win: ClutterWindow | None
) -> tuple[Gaussian, Dwell]:
    s = tm.sensors[j]
    m = Z.shape[0]
    if s.clutter_rate == 0.0:  # every return is the target's: a plain update
        if m == 0:
            return prior, Dwell(j, 0, False, None, s.dim_z)
        if m != 1:
            raise ValueError(f"sensor {j} has no clutter but sent {m} returns")
        pred = predict_measurement(prior, s)
        nu = pred.innovations(Z[0])
        nis = float(pred.mahalanobis2(nu))
        if tm.position[j]:  # the paper's update, bit for bit
            post = update(prior, Z[0], tm.base.H, tm.base.R[j])
        else:
            post = Gaussian(prior.x + pred.K @ nu, pred.P_detected)
        return post, Dwell(j, 1, True, nis, s.dim_z)
    assert win is not None
    pred = predict_measurement(prior, s)
    if tm.method == "pda":
        res = pda_update(prior, Z, s, s.clutter_rate / win.volume, None, tm.gate_probability, pred)
    else:
        res = nearest_neighbour_update(prior, Z, s, tm.gate_probability, pred)
    best: float | None = float(res.d2[int(np.argmax(res.beta))]) if res.gated.size else None
    return res.posterior, Dwell(j, m, res.updated, best, s.dim_z)


def fuse(
    tm: TargetsModel,
    preds: Sequence[Gaussian],
    decision: TargetDecision,
    returns: Mapping[int, Mat],
    windows: Mapping[int, ClutterWindow | None],
) -> tuple[list[Gaussian], list[list[Dwell]]]:
    """Every target's posterior from its prediction and the returns of the sensors that dwelt
    on it (``returns``: sensor index -> ``(m, dim_z)``; a sensor on whose returns did not
    arrive is left out), in ascending sensor index; with each target's :class:`Dwell` records."""
    posts: list[Gaussian] = []
    dwells: list[list[Dwell]] = []
    for t, g in enumerate(preds):
        post, done = g, []
        for j in decision.on_target(t):
            Z = returns.get(j)
            if Z is None:
                continue
            post, d = _update_one(tm, j, post, Z, windows.get(j))
            done.append(d)
        posts.append(post)
        dwells.append(done)
    return posts, dwells


# --------------------------------------------------------------------------------------------
# fusion.mode info: each sensor's own filter of every target, information fusion at the centre
# --------------------------------------------------------------------------------------------


class LocalTargets:
    """Sensor ``j``'s own filter of every target (``fusion.mode: info``): each starts from the
    same initial estimate as the centre's, is predicted lazily, scan by scan, up to the scan the
    sensor dwells on it (the same arithmetic as predicting every scan) and updated with the
    sensor's own returns only (the centre's update: :func:`fuse`'s, with its association).  A
    dwell's local track is ``(prior, posterior)`` of that scan; :meth:`reset` starts a new
    episode."""

    def __init__(self, tm: TargetsModel, j: int) -> None:
        self.tm, self.j = tm, j
        self.reset()

    def reset(self) -> None:
        self.est = initial_estimates(self.tm)
        self.scan = [0] * len(self.tm.targets)

    def track(
        self, t: int, scan: int, Z: Mat, win: ClutterWindow | None
    ) -> tuple[LocalTrack, Dwell]:
        """The local track of target ``t`` at scan ``scan`` from the returns ``Z``."""
        g, F, Q = self.est[t], self.tm.base.F, self.tm.targets[t].Q
        while self.scan[t] < scan:
            g = predict(g, F, Q)
            self.scan[t] += 1
        post, d = _update_one(self.tm, self.j, g, Z, win)
        self.est[t] = post
        return LocalTrack(post=post, prior=g), d


def _adds_information(tr: LocalTrack) -> bool:
    """The track's posterior holds at least its prior's information (``Y⁺ − Y⁻ ⪰ 0``, to
    rounding): a PDA update in clutter can give less, which information fusion cannot take."""
    from covnet.core.cholesky import cho_factor, cho_solve  # start-up: info mode only

    eye = np.eye(tr.post.dim)
    dY = cho_solve(cho_factor(tr.post.P), eye) - cho_solve(cho_factor(tr.prior.P), eye)
    w = np.linalg.eigvalsh(0.5 * (dY + dY.T))
    return bool(w[0] >= -1e-9 * max(abs(w[-1]), 1e-300))


def fuse_tracks(
    tm: TargetsModel,
    preds: Sequence[Gaussian],
    decision: TargetDecision,
    tracks: Mapping[int, LocalTrack],
) -> tuple[list[Gaussian], list[list[Dwell]]]:
    """``fusion.mode: info``: every target's posterior by information-matrix fusion of its
    prediction and the local tracks of the sensors that dwelt on it (sensor index -> track;
    :func:`covnet.core.fusion.information_fusion`, in ascending sensor index; a track whose
    posterior holds less information than its prior is left out).  The centre sees tracks, not
    returns: the :class:`Dwell` records say whether a track moved the estimate (no NIS)."""
    posts: list[Gaussian] = []
    dwells: list[list[Dwell]] = []
    for t, g in enumerate(preds):
        mine = [(j, tracks[j]) for j in decision.on_target(t) if j in tracks]
        use = [(j, tr) for j, tr in mine if _adds_information(tr)]
        posts.append(information_fusion(g, [tr for _, tr in use]) if use else g)
        dwells.append(
            [Dwell(j, -1, not np.array_equal(tr.post.P, tr.prior.P), None, 0) for j, tr in mine]
        )
    return posts, dwells


# --------------------------------------------------------------------------------------------
# slow links: late returns re-filtered from their scan
# --------------------------------------------------------------------------------------------


@dataclass
class _Entry:
    """One buffered scan: the prior it was fused from, its decision and clutter windows, what
    was fused (sensor index -> returns, or a local track under info), the posterior."""

    scan: int
    prior: list[Gaussian]
    decision: TargetDecision
    windows: dict[int, ClutterWindow | None]
    got: dict[int, Any]
    post: list[Gaussian]


class History:
    """The last ``depth`` scans of the many-target centre (``network.latency.late: oosm``),
    so that a dwell's returns (or its local track) that arrive after their scan's deadline are
    added to that scan and every later scan is fused again from its re-predicted prior, with
    the decisions and clutter windows as they were made (the sensors dwelt as commanded then).
    A late message of a scan older than the buffer, of a sensor that did not dwell then, or a
    second one of a sensor and scan, cannot be re-filtered (the caller drops it and counts it).
    The same calls, in the same order, as the in-order path: with every message on time it is
    that path."""

    def __init__(self, tm: TargetsModel, depth: int, tracks: bool) -> None:
        self.tm, self.depth, self.tracks = tm, depth, tracks
        self.entries: list[_Entry] = []
        self.changed = False

    def _fuse(self, e: _Entry) -> list[Gaussian]:
        if self.tracks:
            return fuse_tracks(self.tm, e.prior, e.decision, e.got)[0]
        return fuse(self.tm, e.prior, e.decision, e.got, e.windows)[0]

    def step(
        self,
        scan: int,
        prior: list[Gaussian],
        decision: TargetDecision,
        windows: dict[int, ClutterWindow | None],
        got: Mapping[int, Any],
    ) -> tuple[list[Gaussian], list[list[Dwell]]]:
        """Fuse scan ``scan`` (as :func:`fuse` / :func:`fuse_tracks`) and keep it."""
        if self.tracks:
            posts, dwells = fuse_tracks(self.tm, prior, decision, got)
        else:
            posts, dwells = fuse(self.tm, prior, decision, got, windows)
        self.entries.append(_Entry(scan, list(prior), decision, dict(windows), dict(got), posts))
        del self.entries[: -self.depth]
        return posts, dwells

    def insert(self, scan: int, j: int, payload: Any) -> bool:
        """A late message of sensor ``j`` for scan ``scan``: True when it was re-filtered."""
        at = next((i for i, e in enumerate(self.entries) if e.scan == scan), None)
        if at is None:
            return False
        e = self.entries[at]
        if j in e.got or e.decision.assignment[j] == OFF:
            return False
        e.got[j] = payload
        e.post = self._fuse(e)
        for prev, nxt in zip(self.entries[at:], self.entries[at + 1 :], strict=False):
            nxt.prior = predict_all(self.tm, prev.post)
            nxt.post = self._fuse(nxt)
        self.changed = True
        return True

    def assignment(self, scan: int, j: int) -> int | None:
        """Sensor ``j``'s assignment at buffered scan ``scan`` (``None``: not buffered)."""
        e = next((e for e in self.entries if e.scan == scan), None)
        return None if e is None else e.decision.assignment[j]

    def predicted(self) -> list[Gaussian]:
        """The prediction from the newest buffered scan (scan ``k``'s prior after late
        messages were re-filtered)."""
        self.changed = False
        return predict_all(self.tm, self.entries[-1].post)


def usable_returns(
    tm: TargetsModel, j: int, z: Mat, R: Mat, *, one_target_per_dwell: bool = True
) -> bool:
    """A dwell's returns the manager may use: ``(m, dim_z)`` of sensor ``j``'s model with its
    ``R`` (the wire checked finiteness), bearings in ``(−π, π]``, and, where a dwell looks at
    one known target (``one_target_per_dwell``, the many-target model), at most one without
    clutter. A surveillance dwell returns every target in its window (surveillance.md §1): there
    a sensor without clutter may return several."""
    s = tm.sensors[j]
    if z.ndim != 2 or z.shape[1] != s.dim_z or R.shape != s.R.shape:
        return False
    if not np.array_equal(R, s.R):
        return False
    if one_target_per_dwell and s.clutter_rate == 0.0 and z.shape[0] > 1:
        return False
    am = np.asarray(s.angle_components, dtype=bool)
    ang = z[:, am]
    return bool(np.all((ang > -math.pi) & (ang <= math.pi)))
