"""The ``covariance_control`` kind's config (``configs/paper.yaml``, ``configs/latency.yaml``,
``configs/multitarget.yaml``): YAML -> validated, frozen records; every problem reported with
its path.

A file without a top-level ``kind`` is of this kind.  :func:`from_dict` runs the shared loader
pipeline (:func:`covnet.config.validate`: security paths resolved, the structure validated,
then the checks below and the network table's, every problem with its path):
unique sensor ids, the desired-covariance schedule, allocation constraints, metric names,
fusion modes by the fusion-rule registry (:data:`~covnet.covariance_control.fusion_rules.
FUSION_RULES`), the peer graph.

**Many targets** (spec ``multitarget.md``): a config that lists ``targets:`` (each with its
initial state, optional truth ``manoeuvres``, its own ``desired`` schedule and ``weight``)
replaces the one ``target:`` and the top-level ``desired:``; its sensors may then be of any
``model:`` of the registry (:data:`covnet.core.sensor_models.SENSOR_MODELS`: ``position``, the
default and the paper's; ``range_bearing``; ``bearing``; any model registered there), each
with its model's own keys (its noise parameters, validated by the record of the model's
``config_fields``: :func:`fields_record`), a ``position_m``, coverage (``max_range_m``,
``fov``), ``pd`` and ``clutter_rate``; the ``association`` table (``pda`` | ``nearest``, gate,
clutter window) and ``ospa`` (cut-off and order) go with it.  A config without ``targets:``
is the paper's linear one-target scenario and takes none of these (so its normalised form and
hash are what they were).  A sensor that can never cover any target (on the targets'
noise-free trajectories) is a :class:`ConfigWarning`, not an error.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path
from typing import Annotated, Any, Literal, get_type_hints

import numpy as np

from covnet.config import (
    Bool,
    ConfigModel,
    ConfigWarning,
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
from covnet.core.sensor_models import SENSOR_MODELS
from covnet.covariance_control.fusion_rules import (
    FUSION_RULES,
    fusion_modes,
    has_centre,
    refusal,
    rule_for,
    track_rules,
)
from covnet.covariance_control.searches import AUTO_EXACT_MAX as AUTO_EXACT_MAX
from covnet.covariance_control.searches import BOUNDED_OPTIONS as BOUNDED_OPTIONS
from covnet.covariance_control.searches import SEARCHES
from covnet.records import BAD, AfterValidator, Field, Record, field_validator
from covnet.records import Errors as _Errors
from covnet.records import Loc as _Loc

MetricName = Annotated[Str, in_registry(lambda: sorted(METRICS), "metric")]


def _known_search(value: str) -> str:
    """``allocation.search`` names an entry of :data:`SEARCHES` (looked up when the config is
    validated, so a search a user registers is accepted)."""
    if value not in SEARCHES:
        shown = [repr(k) for k in SEARCHES]
        text = shown[0] if len(shown) == 1 else ", ".join(shown[:-1]) + " or " + shown[-1]
        raise ValueError(f"Input should be {text}")
    return value


SearchName = Annotated[Str, AfterValidator(_known_search)]
FusionMode = Annotated[Str, in_registry(fusion_modes, "fusion mode")]
TrackRule = Annotated[Str, in_registry(track_rules, "rule that fuses local tracks")]
FusionRuleName = Annotated[Str, in_registry(lambda: list(FUSION_RULES), "fusion rule")]
SensorModelName = Annotated[Str, in_registry(lambda: list(SENSOR_MODELS), "sensor model")]

__all__ = [
    "KIND",
    "AssociationSpec",
    "ConfigWarning",
    "FovSpec",
    "FusionSpec",
    "ManoeuvreSpec",
    "OspaSpec",
    "TargetEntry",
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


class FovSpec(ConfigModel):
    """A sector of bearings (degrees, counter-clockwise from +x): ``|β − center| ≤ half_width``."""

    center_deg: Float
    half_width_deg: Float

    @field_validator("half_width_deg")
    @classmethod
    def _hw(cls, v: float) -> float:
        if not 0.0 < v <= 180.0:
            raise ValueError(f"must be in (0, 180] degrees, got {v}")
        return v


def _positive_or_none(v: float | None) -> float | None:
    return None if v is None else _positive(v)


#: the noise keys of the first three models (position, range_bearing, bearing): a sensor's
#: normalised form lists them all (``null`` where they are not its model's), as it did before
#: the registry, so that the hashes stay; ``null`` is accepted for them on any sensor
_NOISE_KEYS = ("sigma_x_m", "sigma_y_m", "rho", "sigma_range_m", "sigma_bearing_mrad")


_FIELDS_RECORDS: dict[type, type[ConfigModel]] = {}


def fields_record(fields: type) -> type[ConfigModel]:
    """The record that validates a model's config keys, from its ``config_fields`` dataclass
    (:mod:`covnet.core.sensor_models`): each field's type and default, and its
    ``metadata["check"]`` as the field's validator (built once per dataclass)."""
    rec = _FIELDS_RECORDS.get(fields)
    if rec is None:
        rec = _FIELDS_RECORDS[fields] = _record_of(fields)
    return rec


def _record_of(fields: type) -> type[ConfigModel]:
    hints = get_type_hints(fields)
    ns: dict[str, Any] = {"__annotations__": {}, "__module__": __name__, "__doc__": fields.__doc__}
    for f in dataclasses.fields(fields):
        ns["__annotations__"][f.name] = hints[f.name]
        if f.default is not dataclasses.MISSING:
            ns[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            ns[f.name] = Field(default_factory=f.default_factory)
        check = f.metadata.get("check")
        if check is not None:
            ns[f"_check_{f.name}"] = field_validator(f.name)(check)
    return type(fields.__name__, (ConfigModel,), ns)


def _noise_key(name: str) -> Any:
    def get(self: SensorSpec) -> float | None:
        return getattr(self.params, name, None)

    return property(get, doc=f"``{name}`` of the sensor's model, ``None`` if it has none.")


class SensorSpec(ConfigModel):
    """A sensor: its ``id``, its ``model`` (a name of the registry :data:`covnet.core.
    sensor_models.SENSOR_MODELS`; ``position``, the default and the paper's: ``R = [[σx²,
    ρσxσy], [ρσxσy, σy²]]`` from ``sigma_x_m``, ``sigma_y_m``, ``rho``) and that model's own
    keys, validated by the record of its ``config_fields`` (held in :attr:`params`; as the
    model's dataclass: :attr:`fields`).  With ``targets:``
    any model (``range_bearing``: a radar, ``sigma_range_m``, ``sigma_bearing_mrad``;
    ``bearing``: passive, ``sigma_bearing_mrad``; ...), at ``position_m``, and for every model
    the coverage (``max_range_m``, ``fov``), the detection probability ``pd`` and
    ``clutter_rate`` (false returns per dwell).

    The model's keys are checked with the structure (types, values); a key that is not the
    model's (:attr:`foreign_fields`) and a missing one (:attr:`missing_fields`) with the
    scenario's checks, so that they are reported with every other problem."""

    id: Ident
    model: SensorModelName = "position"
    position_m: Pair | None = None
    max_range_m: Float | None = None
    fov: FovSpec | None = None
    pd: Float = 1.0
    clutter_rate: Float = 0.0
    #: the model's own keys, validated by the record of its ``config_fields``
    #: (:func:`fields_record`; ``None`` while some are missing)
    params: Any = None

    _pos = field_validator("max_range_m")(_positive_or_none)

    @field_validator("pd")
    @classmethod
    def _pd(cls, v: float) -> float:
        if not 0.0 < v <= 1.0:
            raise ValueError(f"must be a probability in (0, 1], got {v}")
        return v

    @field_validator("clutter_rate")
    @classmethod
    def _clutter(cls, v: float) -> float:
        if not v >= 0.0:
            raise ValueError(f"must be >= 0 (false returns per dwell), got {v}")
        return v

    @classmethod
    def _build(cls, data: Any, loc: _Loc, errors: _Errors, into: Record | None = None) -> Any:
        """The common keys as a record's; the rest by the model's ``config_fields`` (class
        docstring)."""
        common = {k: v for k, v in data.items() if k in cls.model_fields and k != "params"}
        rest = {
            k: v
            for k, v in data.items()
            if k not in common and not (k in _NOISE_KEYS and v is None)
        }
        name = data.get("model", "position")
        entry = SENSOR_MODELS.get(name) if isinstance(name, str) else None
        params, missing, foreign, ok = None, (), (), True
        if entry is not None:
            fields = fields_record(entry.config_fields)
            own = {k: v for k, v in rest.items() if k in fields.model_fields}
            foreign = tuple(k for k in rest if k not in own)
            found: _Errors = []
            params = fields._build(own, loc, found)
            missing = tuple(
                e["loc"][-1] for e in found if e["type"] == "missing" and e["loc"][:-1] == loc
            )
            others = [e for e in found if not (e["type"] == "missing" and e["loc"][:-1] == loc)]
            errors.extend(others)
            ok = not others
            params = None if params is BAD else params
        obj = super()._build({**common, "params": params}, loc, errors, into)
        if obj is BAD or not ok:
            return BAD
        obj.__dict__["_missing"], obj.__dict__["_foreign"] = missing, foreign
        return obj

    @property
    def missing_fields(self) -> tuple[str, ...]:
        """The model's required keys the sensor does not give."""
        missing: tuple[str, ...] = self.__dict__.get("_missing", ())
        return missing

    @property
    def foreign_fields(self) -> tuple[str, ...]:
        """The keys the sensor gives that are neither every sensor's nor its model's."""
        foreign: tuple[str, ...] = self.__dict__.get("_foreign", ())
        return foreign

    def model_dump(self, mode: Literal["python", "json"] = "python") -> dict[str, Any]:
        """Flat, as the config gives it: ``id``, ``model``, the first three models' noise keys
        (``None`` where not the model's), the model's other keys, then the common ones."""
        out = super().model_dump(mode)
        params = out.pop("params") or {}
        head = {"id": out.pop("id"), "model": out.pop("model")}
        return {**head, **dict.fromkeys(_NOISE_KEYS), **params, **out}

    sigma_x_m = _noise_key("sigma_x_m")
    sigma_y_m = _noise_key("sigma_y_m")
    rho = _noise_key("rho")
    sigma_range_m = _noise_key("sigma_range_m")
    sigma_bearing_mrad = _noise_key("sigma_bearing_mrad")

    @property
    def fields(self) -> Any:
        """The model's keys as its ``config_fields`` dataclass (``None`` while some are
        missing)."""
        if self.params is None:
            return None
        cls = SENSOR_MODELS[self.model].config_fields
        return cls(**{f.name: getattr(self.params, f.name) for f in dataclasses.fields(cls)})

    @property
    def paper_noise(self) -> tuple[float, float, float] | None:
        """``(σx, σy, ρ)`` of a sensor the paper's linear code runs (a position sensor), else
        ``None`` (the model's ``paper_noise``)."""
        if self.params is None:
            return None
        return SENSOR_MODELS[self.model].paper_noise(self.fields)

    @property
    def position_noise(self) -> tuple[float, float, float]:
        """``(σx, σy, ρ)`` of a position sensor; a placeholder ``(1, 1, 0)`` (an identity
        ``R``) for the other models, whose noise is their own."""
        noise = self.paper_noise
        return (1.0, 1.0, 0.0) if noise is None else noise

    @property
    def extended(self) -> bool:
        """Anything beyond the paper's always-detecting, everywhere-covering position sensor."""
        return any(getattr(self, k) != v for k, v in _SENSOR_EXTRAS.items())


#: the sensor keys added for many targets, with their defaults (a paper config has none of
#: them, and its normalised form leaves them out, with the other models' noise keys)
_SENSOR_EXTRAS: dict[str, Any] = {
    "model": "position",
    "position_m": None,
    "max_range_m": None,
    "fov": None,
    "pd": 1.0,
    "clutter_rate": 0.0,
}


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


# ``allocation.search``: how the subset is found (README, "Allocation search"), an entry of
# :data:`covnet.covariance_control.searches.SEARCHES` (``AUTO_EXACT_MAX``, ``BOUNDED_OPTIONS``
# are there too)
#: ``search: bounded``'s defaults: the relative gap, and (``auto`` beyond ``AUTO_EXACT_MAX``)
#: the node limit, deterministic where a time limit is not
BOUNDED_GAP = 0.01
AUTO_NODE_LIMIT = 200_000


class TargetDesiredSpec(DesiredSpec):
    """One entry of a target's desired-covariance schedule; ``weight`` (optional) changes the
    target's weight ``w_t`` from ``from_scan`` on (a priority change)."""

    weight: Float | None = None

    _w = field_validator("weight")(_positive_or_none)


class ManoeuvreSpec(ConfigModel):
    """A truth-only manoeuvre over the steps from scan ``from_scan`` to scan ``to_scan``
    (:mod:`covnet.core.manoeuvre`): a coordinated ``turn`` at ``turn_rate_deg_s`` (counter-
    clockwise positive) or a constant ``acceleration`` ``accel_mps2`` ``[ax, ay]``.  The
    filters never know: they keep the constant-velocity model."""

    kind: Literal["turn", "acceleration"]
    from_scan: Int = Field(ge=0)
    to_scan: Int = Field(ge=1)
    turn_rate_deg_s: Float | None = None
    accel_mps2: Pair | None = None


class TargetEntry(ConfigModel):
    """One target of a many-target scenario: state ``[x, vx, y, vy]`` at time 0, its truth's
    white acceleration noise and manoeuvres, its own desired-covariance schedule and weight
    ``w_t > 0``, and optionally its own ``P0_diag`` (default ``filter.P0_diag``) and its
    filter's white acceleration ``filter_accel_noise_std_mps2`` (default: the truth's; a
    tracker expecting a manoeuvre its constant-velocity model does not have raises it)."""

    id: Ident
    initial_position_m: Pair
    initial_velocity_mps: Pair
    accel_noise_std_mps2: Float = 0.5
    filter_accel_noise_std_mps2: Float | None = None
    manoeuvres: tuple[ManoeuvreSpec, ...] = ()
    desired: tuple[TargetDesiredSpec, ...] = Field(min_length=1)
    weight: Float = 1.0
    P0_diag: Quad | None = None

    _w = field_validator("weight")(_positive)

    @field_validator("accel_noise_std_mps2", "filter_accel_noise_std_mps2")
    @classmethod
    def _q(cls, v: float | None) -> float | None:
        if v is not None and not v >= 0:
            raise ValueError(f"must be >= 0, got {v}")
        return v

    @field_validator("P0_diag")
    @classmethod
    def _p0(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is not None and not all(d > 0 for d in v):
            raise ValueError(f"every entry must be > 0, got {list(v)}")
        return v


class AssociationSpec(ConfigModel):
    """How the manager uses a dwell's unlabeled returns (spec §4): ``method`` ``pda`` (the
    PDAF) or ``nearest`` (the gated return nearest in Mahalanobis distance); the χ² gate's
    ``gate_probability``; the clutter window, ``± clutter_window_sigma`` standard deviations of
    the innovation around the predicted measurement.  A sensor without clutter
    (``clutter_rate: 0``) needs no association: its return, if any, is the target's."""

    method: Literal["pda", "nearest"] = "pda"
    gate_probability: Float = 0.99
    clutter_window_sigma: Float = 6.0

    _cw = field_validator("clutter_window_sigma")(_positive)

    @field_validator("gate_probability")
    @classmethod
    def _pg(cls, v: float) -> float:
        if not 0.0 < v < 1.0:
            raise ValueError(f"must be in (0, 1), got {v}")
        return v


class OspaSpec(ConfigModel):
    """OSPA and GOSPA of the estimated target positions against the truth, per scan: cut-off
    ``cutoff_m`` (``c``) and order ``order`` (``p``)."""

    cutoff_m: Float = 1000.0
    order: Float = 2.0

    _c = field_validator("cutoff_m")(_positive)

    @field_validator("order")
    @classmethod
    def _p(cls, v: float) -> float:
        if not v >= 1.0:
            raise ValueError(f"must be >= 1, got {v}")
        return v


class AllocationSpec(ConfigModel):
    """Covariance-control allocation: metrics by registry name, constraints by sensor id, and
    the search (:data:`SEARCHES`): ``exact`` (the exhaustive search's subset, value and ``P``
    bit for bit: the batched fast path for small networks, branch and bound beyond), ``bounded``
    (branch and bound stopped at the relative ``gap``, ``time_limit_s`` or ``node_limit``; it
    reports a certified lower bound and gap), ``greedy`` (forward/backward greedy and swaps, with
    the root lower bound), ``auto`` (the default: ``exact`` up to ``AUTO_EXACT_MAX`` candidate
    sensors, ``bounded`` beyond).

    Many targets only: ``detection`` (how a dwell's information is scored: ``expected``
    ``pd · HᵀR⁻¹H``, ``ignore`` ``HᵀR⁻¹H``, ``pda`` the PDAF's information-reduction factor
    ``q₂`` instead of ``pd``) and ``max_per_target`` (at most this many sensors on one
    target)."""

    metrics: tuple[MetricName, ...] = ("spectral", "abs_trace", "svd")
    required: tuple[Str, ...] = ()
    excluded: tuple[Str, ...] = ()
    max_active: Int | None = Field(default=None, ge=1)
    tie_rtol: Float = Field(default=1e-9, ge=0.0, le=1e-3)
    account_for_loss: Bool = False
    search: SearchName = "auto"
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

    detection: Literal["expected", "ignore", "pda"] = "expected"
    max_per_target: Int | None = Field(default=None, ge=1)


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
        """The fusion rule in effect (``FUSION_RULES``): ``mode``, or in peer mode
        ``peer.rule``."""
        return self.peer.rule if not self.has_centre else self.mode

    @property
    def has_centre(self) -> bool:
        """A fusion centre fuses (else the peer nodes do: ``mode: peer``)."""
        return has_centre(self)


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
    desired: tuple[DesiredSpec, ...] = ()
    allocation: AllocationSpec = AllocationSpec()
    network: NetworkSpec = NetworkSpec()
    fusion: FusionSpec = FusionSpec()
    sweep: SweepSpec | None = None
    evaluation: EvaluationSpec = EvaluationSpec()
    targets: Annotated[tuple[TargetEntry, ...], unique_ids("target")] | None = None
    association: AssociationSpec = AssociationSpec()
    ospa: OspaSpec = OspaSpec()

    _period = field_validator("period_s")(_positive)

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return tuple(s.id for s in self.sensors)

    @property
    def multitarget(self) -> bool:
        """The config lists ``targets:`` (the many-target scenario of ``multitarget.md``)."""
        return self.targets is not None

    @property
    def target_ids(self) -> tuple[str, ...]:
        """The targets' ids (``T1`` for the one ``target:`` of a paper config)."""
        return ("T1",) if self.targets is None else tuple(t.id for t in self.targets)


def _schedule_problems(path: str, schedule: tuple[DesiredSpec, ...]) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    if schedule[0].from_scan != 1:
        problems.append((f"{path}[0].from_scan", "the first entry must start at scan 1"))
    for i, d in enumerate(schedule):
        if (d.diag is None) == (d.matrix is None):
            problems.append((f"{path}[{i}]", "give exactly one of 'diag' or 'matrix'"))
            continue
        if d.matrix is not None and len(d.matrix) != 4:
            problems.append((f"{path}[{i}].matrix", "must be 4x4"))
            continue
        M = d.as_matrix()
        if not np.allclose(M, M.T) or np.linalg.eigvalsh(0.5 * (M + M.T)).min() <= 0:
            problems.append((f"{path}[{i}]", "must be symmetric positive definite"))
        if i > 0 and d.from_scan <= schedule[i - 1].from_scan:
            problems.append((f"{path}[{i}].from_scan", "must increase along the schedule"))
    return problems


def _sensor_problems(sc: Scenario) -> list[tuple[str, str]]:
    """Each sensor's keys against its model's (missing, or another model's, or nobody's),
    its placement and coverage; without ``targets:`` only the paper's position sensor."""
    problems: list[tuple[str, str]] = []
    for i, s in enumerate(sc.sensors):
        where = f"sensors[{i}]"
        entry = SENSOR_MODELS[s.model]
        own = fields_record(entry.config_fields).model_fields
        need = [k for k, f in own.items() if f.is_required()]
        for key in s.missing_fields:
            problems.append(
                (
                    f"{where}.{key}",
                    f"missing required key (a {s.model} sensor needs {', '.join(need)})",
                )
            )
        for key in s.foreign_fields:
            others = [
                n
                for n, m in SENSOR_MODELS.items()
                if key in fields_record(m.config_fields).model_fields
            ]
            if others:
                why = f"not a field of model {s.model} (only for {', '.join(others)} sensors)"
            else:
                common = [k for k in SensorSpec.model_fields if k != "params"]
                why = (
                    f"unknown key: not a field of model {s.model} (its keys: {', '.join(own)}; "
                    f"every sensor's: {', '.join(common)})"
                )
            problems.append((f"{where}.{key}", why))
        if s.position_m is None and (entry.measures_from_position or s.max_range_m or s.fov):
            what = "measures from" if entry.measures_from_position else "has coverage around"
            problems.append(
                (f"{where}.position_m", f"missing required key (a {s.model} sensor {what} it)")
            )
        if not sc.multitarget:
            for key, default in _SENSOR_EXTRAS.items():
                if getattr(s, key) != default:
                    problems.append(
                        (
                            f"{where}.{key}",
                            "needs a 'targets:' list (a config with the one 'target:' is the "
                            "paper's linear scenario: position sensors that always detect, "
                            "no clutter)",
                        )
                    )
    return problems


def _target_problems(sc: Scenario) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    assert sc.targets is not None
    if not sc.targets:
        return [("targets", "list at least one target")]
    for key in ("target", "desired"):
        if key in sc.model_fields_set:
            problems.append(
                (key, "not with 'targets:' (each target has its own state and 'desired')")
            )
    for i, t in enumerate(sc.targets):
        where = f"targets[{i}]"
        problems += _schedule_problems(f"{where}.desired", t.desired)
        spans: list[tuple[int, int, int]] = []
        for m, man in enumerate(t.manoeuvres):
            mw = f"{where}.manoeuvres[{m}]"
            if man.to_scan <= man.from_scan:
                problems.append((f"{mw}.to_scan", "must be after from_scan"))
            if man.to_scan > sc.scans:
                problems.append((f"{mw}.to_scan", f"beyond the run's {sc.scans} scans"))
            need, other = (
                ("turn_rate_deg_s", "accel_mps2")
                if man.kind == "turn"
                else ("accel_mps2", "turn_rate_deg_s")
            )
            if getattr(man, need) is None:
                problems.append((f"{mw}.{need}", f"missing required key (a {man.kind} needs it)"))
            if getattr(man, other) is not None:
                problems.append((f"{mw}.{other}", f"not for a {man.kind}"))
            for a, b, other_m in spans:
                if man.from_scan < b and a < man.to_scan:
                    problems.append((mw, f"overlaps manoeuvres[{other_m}]"))
            spans.append((man.from_scan, man.to_scan, m))
    return problems


def _semantic_problems(sc: Scenario) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    ids = sc.sensor_ids
    seen = set(ids)
    if sc.multitarget:
        problems += _target_problems(sc)
    elif not sc.desired:
        problems.append(("desired", "missing required key (the desired-covariance schedule)"))
    else:
        problems += _schedule_problems("desired", sc.desired)
    problems += _sensor_problems(sc)
    if not sc.multitarget:
        for key in ("association", "ospa"):
            if key in sc.model_fields_set:
                problems.append((key, "only used with 'targets:' (many targets)"))
        for key in ("detection", "max_per_target"):
            if key in sc.allocation.model_fields_set:
                problems.append((f"allocation.{key}", "only used with 'targets:' (many targets)"))
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
    if sc.multitarget:
        problems += _multitarget_fusion_problems(sc)
    return problems


#: the many-target allocator's limit on the sensors that can be on (its tables have ``2^N``
#: entries: :data:`covnet.core.allocation.assignment.MAX_SENSORS`, not imported here for the
#: start-up time of every node process; a test keeps the two equal)
MULTITARGET_MAX_SENSORS = 22


def _multitarget_fusion_problems(sc: Scenario) -> list[tuple[str, str]]:
    """What the many-target scenario does not (yet) do, said where it is asked for."""
    problems: list[tuple[str, str]] = []
    excluded = set(sc.allocation.excluded)
    candidates = [s for s in sc.sensor_ids if s not in excluded]
    if len(candidates) > MULTITARGET_MAX_SENSORS:
        problems.append(
            (
                "sensors",
                f"with 'targets:' at most {MULTITARGET_MAX_SENSORS} sensors can be allocated "
                f"(the many-target allocator keeps tables of 2^N entries); {len(candidates)} "
                "are not in allocation.excluded: exclude some or split the network",
            )
        )
    mode = sc.fusion.mode
    if sc.fusion.has_centre and (why := refusal(rule_for(sc.fusion), "targets")) is not None:
        problems.append(("fusion.mode", f"{mode} {why}"))
    elif not sc.fusion.has_centre:
        problems.append(
            (
                "fusion.mode",
                "peer is not available with 'targets:': the peer nodes' mirror of every node's "
                "filter is single-target (use central or info)",
            )
        )
    al = sc.allocation
    if al.search in ("bounded", "greedy"):
        problems.append(
            (
                "allocation.search",
                f"{al.search} is not available with 'targets:': the many-target allocator is "
                "exact (use exact or auto)",
            )
        )
    elif al.search == "auto":  # (exact: refused by the search checks already)
        for opt in BOUNDED_OPTIONS:
            if getattr(al, opt) is not None:
                problems.append(
                    (f"allocation.{opt}", "not used with 'targets:' (its allocator is exact)")
                )
    if sc.allocation.account_for_loss:
        problems.append(
            (
                "allocation.account_for_loss",
                "not available with 'targets:' (the many-target allocator scores pd · J only)",
            )
        )
    lat = sc.network.latency
    if "missed_command" in lat.model_fields_set and lat.missed_command != "off":
        problems.append(
            (
                "network.latency.missed_command",
                f"{lat.missed_command} is not available with 'targets:': a sensor whose command "
                "never came does not know which target to dwell on, nor the clutter window; "
                "it dwells on nothing (off, the only choice with targets)",
            )
        )
    return problems


def _search_problems(sc: Scenario) -> list[tuple[str, str]]:
    """What the search entry (:data:`SEARCHES`) cannot do with this config, in its own words."""
    al = sc.allocation
    problems: list[tuple[str, str]] = []
    search = SEARCHES.get(al.search)
    if search is None:  # reported by the field's check
        return problems
    for opt in BOUNDED_OPTIONS:
        if getattr(al, opt) is not None and opt not in search.options:
            users = " or ".join(k for k, s in _by_options() if opt in s.options)
            why = f"only used with search: {users}, not {al.search}"
            problems.append((f"allocation.{opt}", why))
    if search.information_form and (
        not sc.fusion.has_centre or not rule_for(sc.fusion).information_form
    ):
        problems.append(
            (
                "allocation.search",
                f"{al.search} needs a fusion centre in the information form (fusion.mode "
                f"central or info); {sc.fusion.mode} decides over every subset",
            )
        )
    n = len(set(sc.sensor_ids) - set(al.excluded))
    used = search.resolved(n)
    as_ = "" if used is search else f" (with {n} candidate sensors: {used.name})"
    if "interval_bound" in used.needs:
        for m in al.metrics:
            entry = METRICS.get(m)
            if entry is not None and entry.interval_bound is None:
                problems.append(
                    (
                        "allocation.search",
                        f"{al.search}{as_} is {used.words}: it needs each metric's interval "
                        f"bound, and metric {m!r} has none (its METRICS entry's interval_bound "
                        "is None); choose search: exact or greedy for it",
                    )
                )
    return problems


def _by_options() -> list[tuple[str, Any]]:
    """The search entries, bounded first (the wording of the options' refusals)."""
    return sorted(SEARCHES.items(), key=lambda kv: (kv[0] != "bounded", kv[0] == "auto"))


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
    A sensor that never covers any target is a :class:`ConfigWarning` (:func:`reach_warnings`).
    """
    sc = validate(Scenario, data, source, base_dir, _semantic_problems)
    for path, message in reach_warnings(sc):
        warnings.warn(ConfigWarning(path, message), stacklevel=2)
    return sc


def nominal_positions(sc: Scenario) -> np.ndarray:
    """``(T, scans, 2)``: each target's position at scans ``1..scans`` without process noise
    (its constant velocity and manoeuvres), what :func:`reach_warnings` looks at."""
    from covnet.core.manoeuvre import manoeuvring_trajectory  # start-up: configs with targets

    assert sc.targets is not None
    out = np.empty((len(sc.targets), sc.scans, 2))
    for i, t in enumerate(sc.targets):
        x0 = [t.initial_position_m[0], t.initial_velocity_mps[0]]
        x0 += [t.initial_position_m[1], t.initial_velocity_mps[1]]
        traj = manoeuvring_trajectory(
            x0, sc.period_s, 0.0, sc.scans, np.random.default_rng(0), segments(t)
        )
        out[i] = traj[:, [0, 2]]
    return out


def segments(t: TargetEntry) -> list[Any]:
    """The target's manoeuvres as the core's segments (:mod:`covnet.core.manoeuvre`)."""
    from covnet.core.manoeuvre import Acceleration, Turn  # start-up: configs with targets

    out: list[Any] = []
    for m in t.manoeuvres:
        if m.kind == "turn":
            assert m.turn_rate_deg_s is not None
            out.append(Turn(m.from_scan, m.to_scan, math.radians(m.turn_rate_deg_s)))
        else:
            assert m.accel_mps2 is not None
            out.append(Acceleration(m.from_scan, m.to_scan, *m.accel_mps2))
    return out


def in_coverage(s: SensorSpec, xy: np.ndarray) -> np.ndarray:
    """Where the positions ``xy`` ``(..., 2)`` are inside sensor ``s``'s coverage (range,
    sector; not at the sensor itself for the models that measure a bearing)."""
    if s.position_m is None:
        return np.ones(xy.shape[:-1], dtype=bool)
    dx, dy = xy[..., 0] - s.position_m[0], xy[..., 1] - s.position_m[1]
    r = np.hypot(dx, dy)
    ok = r <= (math.inf if s.max_range_m is None else s.max_range_m)
    if SENSOR_MODELS[s.model].undefined_at_sensor:
        ok &= r > 0.0
    if s.fov is not None:
        off = np.angle(np.exp(1j * (np.arctan2(dy, dx) - math.radians(s.fov.center_deg))))
        ok &= np.abs(off) <= math.radians(s.fov.half_width_deg)
    return np.asarray(ok)


def reach_warnings(sc: Scenario) -> list[tuple[str, str]]:
    """The sensors that never cover any target at any scan (on the noise-free trajectories of
    :func:`nominal_positions`): allowed, never allocated, probably a mistake."""
    if not sc.multitarget or not any(s.max_range_m or s.fov for s in sc.sensors):
        return []
    xy = nominal_positions(sc)
    out = []
    for i, s in enumerate(sc.sensors):
        if in_coverage(s, xy).any():
            continue
        assert s.position_m is not None
        d = np.hypot(xy[..., 0] - s.position_m[0], xy[..., 1] - s.position_m[1]).min()
        reach = f"max_range_m {s.max_range_m:g}" if s.max_range_m else "no range limit"
        fov = (
            f", fov {s.fov.center_deg:g} ± {s.fov.half_width_deg:g} deg"
            if s.fov is not None
            else ""
        )
        out.append(
            (
                f"sensors[{i}]",
                f"{s.id} never covers any target ({reach}{fov}; nearest approach "
                f"{d / 1e3:.1f} km): it can never be allocated",
            )
        )
    return out


def load(path: str | Path) -> Scenario:
    """Read and validate a YAML scenario file (:func:`covnet.kinds.load` reads any kind)."""
    p = Path(path)
    return from_dict(read_yaml(p), str(p), base_dir=p.parent)


_PAPER_OMITS = (
    "network.security",
    "targets",
    "association",
    "ospa",
    "allocation.detection",
    "allocation.max_per_target",
)


def normalised(sc: Scenario) -> dict[str, Any]:
    """The config with every default filled in, as plain JSON-able data (except
    ``network.security`` while it is all off, ``evaluation`` while it is the default and the
    allocation fields added later while at their defaults, so that configs without them keep
    their hash).

    A config without ``targets:`` leaves out every key the many-target scenario added (they
    hold their defaults: the semantic checks see to it), so that its hash is what it was; one
    with ``targets:`` leaves out the one-target ``target`` and ``desired`` it does not use, and
    says ``network.latency.missed_command: off``, what it does."""
    later = ("evaluation", *(f"allocation.{f}" for f in _ADDED))
    if not sc.multitarget:
        data = _normalised(sc, (*_PAPER_OMITS, *later))
        for s in data["sensors"]:
            for key in (*_SENSOR_EXTRAS, "sigma_range_m", "sigma_bearing_mrad"):
                s.pop(key, None)
        return data
    data = _normalised(sc, ("network.security", *later))
    del data["target"], data["desired"]
    # with targets a missed command is always a scan off (the only choice: see the checks)
    data["network"]["latency"]["missed_command"] = "off"
    return data


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
