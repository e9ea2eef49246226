"""The ``covariance_control`` kind's config (``configs/paper.yaml``, ``configs/latency.yaml``):
YAML -> validated, frozen records; every problem reported with its path.

A file without a top-level ``kind`` is of this kind.  :func:`from_dict` runs the shared loader
pipeline (:func:`covnet.config.validate`: security paths resolved, the structure validated,
then the checks below and the network table's, every problem with its path):
unique sensor ids, the desired-covariance schedule, allocation constraints, metric names,
fusion modes by the fusion-rule registry (:data:`~covnet.covariance_control.fusion_rules.
FUSION_RULES`), the peer graph.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator

from covnet.config import (
    Bool,
    ConfigModel,
    EvaluationSpec,
    Float,
    Ident,
    Int,
    NetworkSpec,
    Pair,
    Quad,
    Str,
    hash_of,
    in_registry,
    positive,
    read_yaml,
    unique_ids,
    validate,
)
from covnet.config import normalised as _normalised
from covnet.core.metrics import METRICS
from covnet.covariance_control.fusion_rules import (
    FUSION_RULES,
    fusion_modes,
    rule_for,
    track_rules,
)

MetricName = Annotated[Str, in_registry(lambda: sorted(METRICS), "metric")]
FusionMode = Annotated[Str, in_registry(fusion_modes, "fusion mode")]
TrackRule = Annotated[Str, in_registry(track_rules, "rule that fuses local tracks")]
FusionRuleName = Annotated[Str, in_registry(lambda: list(FUSION_RULES), "fusion rule")]

__all__ = [
    "KIND",
    "FusionSpec",
    "PeerSpec",
    "Scenario",
    "SensorSpec",
    "SweepSpec",
    "config_hash",
    "from_dict",
    "load",
    "normalised",
    "with_overrides",
]

KIND = "covariance_control"
_positive = positive


class SensorSpec(ConfigModel):
    """A linear position sensor: ``R = [[σx², ρσxσy], [ρσxσy, σy²]]``."""

    id: Ident
    sigma_x_m: Float
    sigma_y_m: Float
    rho: Float

    _pos = field_validator("sigma_x_m", "sigma_y_m")(_positive)

    @field_validator("rho")
    @classmethod
    def _rho(cls, v: float) -> float:
        if not -1.0 < v < 1.0:
            raise ValueError(f"must be in (-1, 1), got {v}")
        return v


class TargetSpec(ConfigModel):
    """One constant-velocity target in the plane, state ``[x, vx, y, vy]``."""

    initial_position_m: Pair = (0.0, 0.0)
    initial_velocity_mps: Pair = (426.0, 0.0)
    accel_noise_std_mps2: Float = 0.5

    @field_validator("accel_noise_std_mps2")
    @classmethod
    def _q(cls, v: float) -> float:
        if not v >= 0:
            raise ValueError(f"must be >= 0, got {v}")
        return v


class FilterSpec(ConfigModel):
    """Filter initialisation: ``P0 = diag(P0_diag)``; the estimate is the truth plus one draw
    from ``N(0, P0)`` (``perturbed``, the default) or the truth itself (``truth``)."""

    P0_diag: Quad = (1.0e4, 1.0e2, 1.0e4, 1.0e2)
    initial_estimate: Literal["perturbed", "truth"] = "perturbed"

    @field_validator("P0_diag")
    @classmethod
    def _p0(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(d > 0 for d in v):
            raise ValueError(f"every entry must be > 0, got {list(v)}")
        return v


class DesiredSpec(ConfigModel):
    """Desired covariance from scan ``from_scan`` on: ``diag`` (4 entries) or a full ``matrix``."""

    from_scan: Int = Field(ge=1)
    diag: Quad | None = None
    matrix: Annotated[tuple[Quad, ...], Field(min_length=4, max_length=4)] | None = None

    def as_matrix(self) -> np.ndarray:
        if self.diag is not None:
            return np.diag(np.asarray(self.diag, dtype=np.float64))
        return np.asarray(self.matrix, dtype=np.float64)


#: ``allocation.search``: how the subset is found (README, "Allocation search")
SEARCHES = ("auto", "exact", "bounded", "greedy")
#: ``search: auto`` is ``exact`` up to this many candidate sensors (allowed, not excluded),
#: ``bounded`` beyond (``covnet bench search``: an exact decision at N = 24 takes 0.01-0.2 s,
#: at N = 32 a median of 0.04-2.2 s by metric but up to minutes at a near tie)
AUTO_EXACT_MAX = 24
#: ``search: bounded``'s defaults: the relative gap, and (``auto`` beyond ``AUTO_EXACT_MAX``)
#: the node limit, deterministic where a time limit is not
BOUNDED_GAP = 0.01
AUTO_NODE_LIMIT = 200_000
#: the options that only ``bounded`` (and ``auto``, for its bounded part) uses
BOUNDED_OPTIONS = ("gap", "time_limit_s", "node_limit")


class AllocationSpec(ConfigModel):
    """Covariance-control allocation: metrics by registry name, constraints by sensor id, and
    the search (:data:`SEARCHES`): ``exact`` (the exhaustive search's subset, value and ``P``
    bit for bit: the batched fast path for small networks, branch and bound beyond), ``bounded``
    (branch and bound stopped at the relative ``gap``, ``time_limit_s`` or ``node_limit``; it
    reports a certified lower bound and gap), ``greedy`` (forward/backward greedy and swaps, with
    the root lower bound), ``auto`` (the default: ``exact`` up to ``AUTO_EXACT_MAX`` candidate
    sensors, ``bounded`` beyond)."""

    metrics: tuple[MetricName, ...] = ("spectral", "abs_trace", "svd")
    required: tuple[Str, ...] = ()
    excluded: tuple[Str, ...] = ()
    max_active: Int | None = Field(default=None, ge=1)
    tie_rtol: Float = Field(default=1e-9, ge=0.0, le=1e-3)
    account_for_loss: Bool = False
    search: Literal["auto", "exact", "bounded", "greedy"] = "auto"
    gap: Float | None = None
    time_limit_s: Float | None = None
    node_limit: Int | None = None

    @field_validator("gap")
    @classmethod
    def _gap(cls, v: float | None) -> float | None:
        if v is not None and not 0.0 <= v < 1.0:
            raise ValueError(f"must be in [0, 1) (a relative gap: 0.01 is 1 %), got {v}")
        return v

    @field_validator("time_limit_s")
    @classmethod
    def _time_limit(cls, v: float | None) -> float | None:
        return None if v is None else _positive(v)

    @field_validator("node_limit")
    @classmethod
    def _node_limit(cls, v: int | None) -> int | None:
        if v is not None and v < 1:
            raise ValueError(f"must be >= 1, got {v}")
        return v


PEER_GRAPHS = ("full", "ring", "star", "custom")


class PeerSpec(ConfigModel):
    """Peer-to-peer mode: which sensors exchange local tracks (``graph``; ``custom`` takes
    undirected ``edges`` by sensor id; ``star`` has ``hub`` at its centre, default the first
    sensor) and how each node fuses what it receives (``rule``)."""

    rule: TrackRule = "info"
    graph: Literal["full", "ring", "star", "custom"] = "full"
    hub: Str | None = None
    edges: tuple[tuple[Str, Str], ...] = ()


class FusionSpec(ConfigModel):
    """The fusion structure (README, "Decentralized fusion"): ``central`` (the manager fuses
    raw measurements), ``info`` / ``ci`` (sensors run local filters and publish local tracks;
    the manager fuses them by information-matrix fusion or covariance intersection), ``peer``
    (no fusion centre: nodes fuse their neighbours' tracks, see :class:`PeerSpec`).
    ``ci_objective``: what the covariance-intersection weights minimise (``det``, ``trace``)
    or ``fast`` (closed-form weights ``w_i ∝ 1 / tr P_i``)."""

    mode: FusionMode = "central"
    ci_objective: Literal["det", "trace", "fast"] = "det"
    peer: PeerSpec = PeerSpec()

    @property
    def rule(self) -> str:
        """The track-fusion rule in effect: ``central``, ``info`` or ``ci``."""
        return self.peer.rule if self.mode == "peer" else self.mode


class SweepSpec(ConfigModel):
    """The grid of ``covnet sweep`` (README, "Network latency"): every combination of the mean
    one-way delay ``delay_ms`` (both directions; distributed as ``delay_kind``: ``constant``,
    ``exponential`` with that mean, ``uniform`` on ``[0, 2 · mean]``; the same for every
    sensor: ``network.latency.sensors`` is not used), the loss probability
    ``loss`` (both directions), the fusion ``modes``, ``account_for_loss`` and the ``late``
    policy, each run with ``seeds`` seeds from the config's.  ``metric``: the allocation metric
    (default: the config's first)."""

    delay_ms: tuple[Float, ...] = (0.0, 100.0, 200.0, 400.0)
    delay_kind: Literal["constant", "exponential", "uniform"] = "exponential"
    loss: tuple[Float, ...] = (0.0, 0.1, 0.2)
    modes: tuple[FusionRuleName, ...] = ("central", "ci")
    account_for_loss: tuple[Bool, ...] = (False, True)
    late: tuple[Literal["oosm", "drop"], ...] = ("oosm",)
    seeds: Int = Field(default=4, ge=1, le=10_000)
    metric: MetricName | None = None

    @field_validator("delay_ms")
    @classmethod
    def _delays(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v or any(d < 0 for d in v):
            raise ValueError(f"give at least one delay, each >= 0 ms; got {list(v)}")
        return v

    @field_validator("loss")
    @classmethod
    def _losses(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v or any(not 0.0 <= x < 1.0 for x in v):
            raise ValueError(f"give at least one loss probability, each in [0, 1); got {list(v)}")
        return v

    @field_validator("modes", "account_for_loss", "late")
    @classmethod
    def _non_empty(cls, v: tuple[Any, ...]) -> tuple[Any, ...]:
        if not v:
            raise ValueError("give at least one value")
        return v


class Scenario(ConfigModel):
    """A whole scenario: the paper's by default values where the source leaves them open."""

    kind: Literal["covariance_control"] = "covariance_control"
    name: Annotated[Str, Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")]
    seed: Int = Field(ge=0)
    scans: Int = Field(ge=1, le=1_000_000)
    period_s: Float = 1.0
    target: TargetSpec = TargetSpec()
    filter: FilterSpec = FilterSpec()
    sensors: Annotated[tuple[SensorSpec, ...], unique_ids("sensor")] = Field(min_length=1)
    desired: tuple[DesiredSpec, ...] = Field(min_length=1)
    allocation: AllocationSpec = AllocationSpec()
    network: NetworkSpec = NetworkSpec()
    fusion: FusionSpec = FusionSpec()
    sweep: SweepSpec | None = None
    evaluation: EvaluationSpec = EvaluationSpec()

    _period = field_validator("period_s")(_positive)

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return tuple(s.id for s in self.sensors)


def _semantic_problems(sc: Scenario) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    ids = sc.sensor_ids
    seen = set(ids)
    if sc.desired[0].from_scan != 1:
        problems.append(("desired[0].from_scan", "the first entry must start at scan 1"))
    for i, d in enumerate(sc.desired):
        if (d.diag is None) == (d.matrix is None):
            problems.append((f"desired[{i}]", "give exactly one of 'diag' or 'matrix'"))
            continue
        if d.matrix is not None and len(d.matrix) != 4:
            problems.append((f"desired[{i}].matrix", "must be 4x4"))
            continue
        M = d.as_matrix()
        if not np.allclose(M, M.T) or np.linalg.eigvalsh(0.5 * (M + M.T)).min() <= 0:
            problems.append((f"desired[{i}]", "must be symmetric positive definite"))
        if i > 0 and d.from_scan <= sc.desired[i - 1].from_scan:
            problems.append((f"desired[{i}].from_scan", "must increase along the schedule"))
    al = sc.allocation
    if not al.metrics:
        problems.append(("allocation.metrics", "name at least one metric"))
    for field in ("required", "excluded"):
        for i, sid in enumerate(getattr(al, field)):
            if sid not in seen:
                problems.append((f"allocation.{field}[{i}]", f"no sensor with id {sid!r}"))
    both = set(al.required) & set(al.excluded)
    if both:
        problems.append(("allocation", f"sensors both required and excluded: {sorted(both)}"))
    problems += _search_problems(sc)
    problems += _peer_problems(sc.fusion.peer, ids)
    if set(al.excluded) >= set(ids):
        problems.append(("allocation.excluded", "excludes every sensor"))
    if al.max_active is not None:
        if al.max_active < len(set(al.required)):
            problems.append(
                ("allocation.max_active", f"smaller than the {len(al.required)} required sensors")
            )
        if al.max_active > len(ids):
            problems.append(("allocation.max_active", f"more than the {len(ids)} sensors"))
    return problems


def _search_problems(sc: Scenario) -> list[tuple[str, str]]:
    al = sc.allocation
    problems: list[tuple[str, str]] = []
    if al.search in ("exact", "greedy"):
        for opt in BOUNDED_OPTIONS:
            if getattr(al, opt) is not None:
                why = f"only used with search: bounded or auto, not {al.search}"
                problems.append((f"allocation.{opt}", why))
    if al.search in ("bounded", "greedy") and (
        sc.fusion.mode == "peer" or not rule_for(sc.fusion).information_form
    ):
        problems.append(
            (
                "allocation.search",
                f"{al.search} needs a fusion centre in the information form (fusion.mode "
                f"central or info); {sc.fusion.mode} decides over every subset",
            )
        )
    return problems


def _peer_problems(peer: PeerSpec, ids: tuple[str, ...]) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    known = set(ids)
    if peer.hub is not None and peer.hub not in known:
        problems.append(("fusion.peer.hub", f"no sensor with id {peer.hub!r}"))
    if peer.graph == "custom" and not peer.edges:
        problems.append(("fusion.peer.edges", "a custom graph needs at least one edge"))
    if peer.graph != "custom" and peer.edges:
        problems.append(("fusion.peer.edges", "edges are only used with graph: custom"))
    for i, (a, b) in enumerate(peer.edges):
        for end, sid in enumerate((a, b)):
            if sid not in known:
                problems.append((f"fusion.peer.edges[{i}][{end}]", f"no sensor with id {sid!r}"))
        if a == b:
            problems.append((f"fusion.peer.edges[{i}]", f"a self-loop on {a!r}"))
    return problems


def from_dict(data: object, source: str = "<dict>", base_dir: str | Path | None = None) -> Scenario:
    """Validate a parsed config mapping; raise :class:`ConfigError` listing every problem.

    ``base_dir``: relative paths under ``network.security`` are resolved against it (:func:`load`
    passes the config file's directory); without it they stay relative to the working directory.
    """
    return validate(Scenario, data, source, base_dir, _semantic_problems)


def load(path: str | Path) -> Scenario:
    """Read and validate a YAML scenario file (:func:`covnet.kinds.load` reads any kind)."""
    p = Path(path)
    return from_dict(read_yaml(p), str(p), base_dir=p.parent)


def normalised(sc: Scenario) -> dict[str, Any]:
    """The config with every default filled in, as plain JSON-able data (except
    ``network.security`` while it is all off, ``evaluation`` while it is the default and the
    allocation fields added later while at their defaults, so that configs without them keep
    their hash)."""
    return _normalised(sc, ("network.security", "evaluation", *(f"allocation.{f}" for f in _ADDED)))


#: allocation fields added after configs were first hashed (left out while at their default)
_ADDED = ("search", *BOUNDED_OPTIONS)


def config_hash(sc: Scenario) -> str:
    """SHA-256 (first 16 hex digits) of the normalised config as canonical JSON."""
    return hash_of(normalised(sc))


def with_overrides(sc: Scenario, **changes: Any) -> Scenario:
    """A copy of ``sc`` with top-level fields replaced, re-validated."""
    data = normalised(sc)
    data.update(changes)
    return from_dict(data, f"{sc.name} (with overrides)")
