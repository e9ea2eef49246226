"""The ``mobile`` config (``configs/mobile.yaml``): YAML -> validated, frozen records.

A file is a mobile config when its top level says ``kind: mobile``.  It goes through the loader
pipeline every kind shares (:func:`covnet.config.validate`): scalars are strict, unknown keys
are errors, the network table and its security are checked as for every kind, and every problem
of a stage is reported with its path in one :class:`~covnet.config.ConfigError`
(``sensors[2].speed_mps: must be >= 0, got -1.0``).

Names follow spec §2.1/§7 with units in the key where there is one::

    kind: mobile
    name, seed, scans, scan_period_s
    solver: lp | lp_highs | closed_form | milp         (the core's SOLVERS)
    compare_exact: bool                                (also solve each decision exactly)
    milp: {time_limit_s, rel_gap, linking: strong | weak}
    weights: {alpha, beta, gamma}
    detection: {PD, a, b, c}
    noise_growth_L_m: [Lx, Ly]
    dist_uses_velocity, trace_kind: full | position, pd_include_track_cov, null_penalty
    filter: {P0_diag}
    targets: [{id, x0: [px, vx, py, vy], sigma_a_mps2, A?, B?}]
    sensors: [{id, start_m, speed_mps, sigma0_m | R0_m2, r_pd_m, b0, b1, capacity}]
    network: the covariance-control config's table (covnet up: router, timeouts, record, ...)
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np

from covnet.config import (
    Bool,
    ConfigModel,
    Float,
    Ident,
    Int,
    NetworkSpec,
    Pair,
    Quad,
    Str,
    hash_of,
    in_registry,
    non_negative,
    positive,
    read_yaml,
    unique_ids,
    validate,
)
from covnet.config import normalised as _normalised
from covnet.core.mobile.decision import SOLVERS
from covnet.records import Field, field_validator

__all__ = [
    "KIND",
    "MobileConfig",
    "MobileSensorSpec",
    "MobileTargetSpec",
    "config_hash",
    "from_dict",
    "load",
    "normalised",
    "with_overrides",
]

KIND = "mobile"
SolverName = Annotated[Str, in_registry(lambda: sorted(SOLVERS), "solver")]
Row2 = Pair
_ge0, _gt0 = non_negative, positive


class MilpSpec(ConfigModel):
    """The exact solver: HiGHS time limit (s), relative gap, linking form."""

    time_limit_s: Float = 60.0
    rel_gap: Float = 1e-6
    linking: Literal["strong", "weak"] = "strong"

    _pos = field_validator("time_limit_s")(_gt0)

    @field_validator("rel_gap")
    @classmethod
    def _gap(cls, v: float) -> float:
        if not 0.0 <= v < 1.0:
            raise ValueError(f"must be in [0, 1), got {v}")
        return v


class WeightsSpec(ConfigModel):
    """Importance weights: accuracy ``alpha``, usage ``beta``, missed detection ``gamma``."""

    alpha: Float = 1.0
    beta: Float = 0.1
    gamma: Float = 5.0

    _pos = field_validator("alpha", "beta", "gamma")(_gt0)


class DetectionSpec(ConfigModel):
    """Bell detection ``Pd = PD / (1 + |(d − c)/a|^{2b})``, ``d`` in units of ``r_pd_m``."""

    PD: Float = 0.95
    a: Float = 1.0
    b: Float = 2.0
    c: Float = 0.0

    _pos = field_validator("a", "b")(_gt0)
    _nonneg = field_validator("c")(_ge0)

    @field_validator("PD")
    @classmethod
    def _pd(cls, v: float) -> float:
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"must be in [0, 1], got {v}")
        return v


class MobileFilterSpec(ConfigModel):
    """Filter start ``x̂0 = x0 + N(0, P0)``, ``P0 = diag(P0_diag)`` [m², m²/s², m², m²/s²]."""

    P0_diag: Quad = (25.0, 0.25, 25.0, 0.25)

    @field_validator("P0_diag")
    @classmethod
    def _p0(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(d > 0 for d in v):
            raise ValueError(f"every entry must be > 0, got {list(v)}")
        return v


class MobileTargetSpec(ConfigModel):
    """One target ``x = [px, vx, py, vy]``: constant velocity with white acceleration
    ``sigma_a_mps2`` by default, or its own ``A`` (4×4) and ``B`` (4×2)."""

    id: Ident
    x0: Quad
    sigma_a_mps2: Float = 0.05
    A: Annotated[tuple[Quad, ...], Field(min_length=4, max_length=4)] | None = None
    B: Annotated[tuple[Row2, ...], Field(min_length=4, max_length=4)] | None = None

    _q = field_validator("sigma_a_mps2")(_ge0)


class MobileSensorSpec(ConfigModel):
    """A sensor on a platform: start position, speed, base noise (``sigma0_m``: ``R0 = σ² I``,
    or a full ``R0_m2``), detection scale ``r_pd_m``, usage cost ``b0`` (+ ``b1`` when moving),
    capacity (targets per scan; ``null`` for none)."""

    id: Ident
    start_m: Pair
    speed_mps: Float
    sigma0_m: Float | None = None
    R0_m2: Annotated[tuple[Row2, ...], Field(min_length=2, max_length=2)] | None = None
    r_pd_m: Float = 60.0
    b0: Float = 1.0
    b1: Float = 0.0
    capacity: Int | None = Field(default=None, ge=0)

    _nonneg = field_validator("speed_mps", "b0", "b1")(_ge0)
    _pos = field_validator("r_pd_m")(_gt0)

    @field_validator("sigma0_m")
    @classmethod
    def _sigma(cls, v: float | None) -> float | None:
        return None if v is None else _gt0(v)

    def R0(self) -> np.ndarray:
        if self.R0_m2 is not None:
            return np.asarray(self.R0_m2, dtype=np.float64)
        assert self.sigma0_m is not None
        return self.sigma0_m**2 * np.eye(2)


class MobileConfig(ConfigModel):
    """A whole mobile scenario (spec §8.1 by default values where it gives them)."""

    kind: Literal["mobile"]
    name: Ident
    seed: Int = Field(ge=0)
    scans: Int = Field(ge=1, le=1_000_000)
    scan_period_s: Float = 1.0
    solver: SolverName = "lp"
    compare_exact: Bool = False
    milp: MilpSpec = MilpSpec()
    weights: WeightsSpec = WeightsSpec()
    detection: DetectionSpec = DetectionSpec()
    noise_growth_L_m: Pair = (25.0, 25.0)
    dist_uses_velocity: Bool = True
    trace_kind: Literal["full", "position"] = "full"
    pd_include_track_cov: Bool = False
    null_penalty: Float | None = None
    filter: MobileFilterSpec = MobileFilterSpec()
    targets: Annotated[tuple[MobileTargetSpec, ...], unique_ids("target")] = Field(min_length=1)
    sensors: Annotated[tuple[MobileSensorSpec, ...], unique_ids("sensor")] = Field(min_length=1)
    network: NetworkSpec = NetworkSpec()  # covnet up (the same table as covariance control)

    _period = field_validator("scan_period_s")(_gt0)

    @field_validator("noise_growth_L_m")
    @classmethod
    def _L(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(x > 0 for x in v):
            raise ValueError(f"both lengths must be > 0, got {list(v)}")
        return v

    @field_validator("null_penalty")
    @classmethod
    def _penalty(cls, v: float | None) -> float | None:
        return None if v is None else _ge0(v)

    @property
    def target_ids(self) -> tuple[str, ...]:
        return tuple(t.id for t in self.targets)

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return tuple(s.id for s in self.sensors)


def _is_spd(A: np.ndarray) -> bool:
    if not np.allclose(A, A.T):
        return False
    try:
        np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return False
    return True


def _semantic_problems(cfg: MobileConfig) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    for j, s in enumerate(cfg.sensors):
        if (s.sigma0_m is None) == (s.R0_m2 is None):
            problems.append((f"sensors[{j}]", "give exactly one of 'sigma0_m' or 'R0_m2'"))
        elif s.R0_m2 is not None and not _is_spd(np.asarray(s.R0_m2, dtype=np.float64)):
            problems.append((f"sensors[{j}].R0_m2", "must be symmetric positive definite"))
    if cfg.solver == "closed_form" and any(s.capacity is not None for s in cfg.sensors):
        problems.append(
            ("solver", "closed_form holds only without capacities; use lp (or lp_highs)")
        )
    return problems


def from_dict(
    data: object, source: str = "<dict>", base_dir: str | Path | None = None
) -> MobileConfig:
    """Validate a parsed mapping; raise :class:`~covnet.config.ConfigError` listing every
    problem (the shared pipeline, :func:`covnet.config.validate`)."""
    return validate(MobileConfig, data, source, base_dir, _semantic_problems)


def load(path: str | Path) -> MobileConfig:
    """Read and validate a mobile YAML file (:func:`covnet.kinds.load` reads any kind)."""
    p = Path(path)
    return from_dict(read_yaml(p), str(p), base_dir=p.parent)


def normalised(cfg: MobileConfig) -> dict[str, Any]:
    """The config with every default filled in, as plain JSON-able data (``network`` only when
    it differs from the defaults, so that configs without it keep their hash)."""
    return _normalised(cfg, ("network",))


def config_hash(cfg: MobileConfig) -> str:
    """SHA-256 (first 16 hex digits) of the normalised config as canonical JSON."""
    return hash_of(normalised(cfg))


def with_overrides(cfg: MobileConfig, source: str | None = None, **changes: Any) -> MobileConfig:
    """A copy of ``cfg`` with top-level fields replaced (``None`` values are ignored),
    re-validated."""
    data = normalised(cfg)
    data.update({k: v for k, v in changes.items() if v is not None})
    return from_dict(data, source or f"{cfg.name} (with overrides)")
