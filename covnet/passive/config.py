"""``configs/passive.yaml``: passive association configs -> validated, frozen records.

A passive config is identified by its top-level key ``kind: passive``.  It goes through the
loader pipeline every kind shares (:func:`covnet.config.validate`): unknown keys are errors,
scalars are strict, the network table and its security are checked as for every kind, and every
problem is reported together with its path, e.g. ``montecarlo.methods[1]: unknown method 'lp';
choose from [...]``.

Sections: ``sensors`` (exactly three; the third is the reference of the height test),
``targets`` (formation, spacing d, centre, altitude), ``noise`` (σ_α, σ_ε in mrad),
``clutter`` (the clutter-on setting of the protocol: P_D, λ_fa, window; ``enabled`` for single
scans), ``association`` (method and its parameters), ``montecarlo`` (the §9 grid),
``scans`` (how many scans ``covnet up`` runs; default 1) and ``network`` (the covariance-control
config's table, for ``covnet up``).  ``scans`` at its default and ``network`` at its defaults are
left out of :func:`normalised`, so configs without them keep their hash.
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
    Str,
    hash_of,
    in_registry,
    positive,
    rate,
    read_yaml,
    unique_ids,
    validate,
)
from covnet.config import normalised as _normalised
from covnet.core.passive.methods import METHODS
from covnet.core.passive.model import AssocParams
from covnet.passive.scene import FORMATIONS, SceneModel, formation
from covnet.records import Field, field_validator

MAX_PASSIVE_RATE = 50.0
"""The most false returns a sensor's list holds a scan (``clutter.rate_per_scan``): at 200 a
scan took 2.1 GB and 6.7 s; at 50, with the targets, the triples' arrays are some 30 MB."""

__all__ = [
    "KIND",
    "PassiveConfig",
    "config_hash",
    "from_dict",
    "load",
    "normalised",
    "with_overrides",
]

KIND = "passive"
Triple = Annotated[tuple[Float, ...], Field(min_length=3, max_length=3)]
FormationName = Literal["horizontal", "cross"]
MethodName = Annotated[Str, in_registry(lambda: sorted(METHODS), "method")]
_positive = positive


class PassiveSensorSpec(ConfigModel):
    """One passive sensor: id and position ``(x, y, z)`` km (x east, y north, z up)."""

    id: Ident
    position_km: Triple


class TargetsSpec(ConfigModel):
    """The paper's five targets: ``formation`` with spacing ``d`` around ``center_km``."""

    formation: FormationName = "cross"
    spacing_km: Float = 1.0
    center_km: Pair = (5.0, 5.0)
    altitude_km: Float = 1.0

    _pos = field_validator("spacing_km")(_positive)


class NoiseSpec(ConfigModel):
    """Additive Gaussian angle noise, std in mrad (the paper: σ_α = σ_ε = σ_s)."""

    sigma_azimuth_mrad: Float = 3.0
    sigma_elevation_mrad: Float = 3.0

    _pos = field_validator("sigma_azimuth_mrad", "sigma_elevation_mrad")(_positive)


class ClutterSpec(ConfigModel):
    """The clutter-on setting (spec §3): per (target, sensor) detection probability, Poisson
    false returns per sensor and scan, uniform in ``window_rad`` (azimuth, elevation) around
    the direction of the formation centroid.  ``enabled``: use it for single scans
    (``covnet scene``); the Monte Carlo grid switches it with ``montecarlo.clutter``."""

    enabled: Bool = False
    p_detect: Float = 0.95
    rate_per_scan: Float = 0.25
    window_rad: Pair = (0.1, 0.1)

    @field_validator("p_detect")
    @classmethod
    def _pd(cls, v: float) -> float:
        if not 0.0 < v <= 1.0:
            raise ValueError(f"must be in (0, 1], got {v}")
        return v

    _rate = field_validator("rate_per_scan")(rate)  # at most MAX_RATE

    @field_validator("rate_per_scan")
    @classmethod
    def _few(cls, v: float) -> float:
        """At most :data:`MAX_PASSIVE_RATE`: the association tests every triple of the three
        sensors' lists, so its memory and time grow with the cube of a list's length (1 000
        false returns a scan asked for 7.5 GiB an array: a MemoryError traceback)."""
        if v > MAX_PASSIVE_RATE:
            raise ValueError(
                f"at most {MAX_PASSIVE_RATE:g} false returns a scan (the association tests "
                f"every triple of the three sensors' lists: n³ work and memory), got {v:g}"
            )
        return v

    @field_validator("window_rad")
    @classmethod
    def _window(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not all(0 < w < np.pi for w in v):
            raise ValueError(f"both widths must be in (0, π) rad, got {list(v)}")
        return v


class LRSpec(ConfigModel):
    """Lagrangian relaxation (spec §8.3)."""

    max_iterations: Int = Field(default=100, ge=1, le=100_000)
    rel_gap: Float = Field(default=1e-3, ge=0.0, le=1.0)
    step: Float = Field(default=1.0, gt=0.0, le=2.0)
    halve_after: Int = Field(default=5, ge=0)


class MILPSpec(ConfigModel):
    time_limit_s: Float = Field(default=10.0, gt=0.0)


class AssociationSpec(ConfigModel):
    """The association method (a ``METHODS`` name) and the parameters of every method."""

    method: MethodName = "cot"
    gate_sigma: Float = Field(default=3.0, gt=0.0)
    cot_cost: Literal["raw", "normalised"] = "raw"
    azimuth_form: Literal["cot", "sine"] = "cot"
    target_density_km3: Float = Field(default=0.025, ge=0.0)
    gauss_newton_steps: Int = Field(default=3, ge=0, le=50)
    lr: LRSpec = LRSpec()
    milp: MILPSpec = MILPSpec()


class MonteCarloSpec(ConfigModel):
    """The evaluation grid of spec §9 (every combination is one cell)."""

    trials: Int = Field(default=100, ge=1, le=1_000_000)
    formations: tuple[FormationName, ...] = FORMATIONS
    spacings_km: tuple[Float, ...] = (0.5, 1.0, 2.0)
    sigmas_mrad: tuple[Float, ...] = (1.0, 3.0, 5.0)
    clutter: tuple[Bool, ...] = (False, True)
    methods: tuple[MethodName, ...] = ("cot", "lr", "milp", "greedy")
    workers: Int = Field(default=0, ge=0, le=1024)


class PassiveConfig(ConfigModel):
    """A whole passive association config (``kind: passive``)."""

    kind: Literal["passive"]
    name: Str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    seed: Int = Field(ge=0)
    sensors: Annotated[tuple[PassiveSensorSpec, ...], unique_ids("sensor")] = Field(
        min_length=3, max_length=3
    )
    targets: TargetsSpec = TargetsSpec()
    noise: NoiseSpec = NoiseSpec()
    clutter: ClutterSpec = ClutterSpec()
    association: AssociationSpec = AssociationSpec()
    montecarlo: MonteCarloSpec = MonteCarloSpec()
    scans: Int = Field(default=1, ge=1, le=100_000)  # covnet up: scans k = 1..scans (trial k-1)
    network: NetworkSpec = NetworkSpec()  # covnet up (the same table as covariance control)

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return tuple(s.id for s in self.sensors)

    @property
    def sensor_positions(self) -> np.ndarray:
        return np.array([s.position_km for s in self.sensors], dtype=np.float64)

    def scene_model(
        self,
        formation_name: str | None = None,
        spacing_km: float | None = None,
        sigma_mrad: float | None = None,
        clutter: bool | None = None,
    ) -> SceneModel:
        """The :class:`SceneModel` of this config, optionally for one grid cell (``sigma_mrad``
        sets σ_α = σ_ε; ``clutter`` False means P_D = 1 and no false returns)."""
        t = self.targets
        targets = formation(
            formation_name or t.formation,
            t.spacing_km if spacing_km is None else spacing_km,
            (t.center_km[0], t.center_km[1]),
            t.altitude_km,
        )
        if sigma_mrad is None:
            sa, se = self.noise.sigma_azimuth_mrad, self.noise.sigma_elevation_mrad
        else:
            sa = se = sigma_mrad
        on = self.clutter.enabled if clutter is None else clutter
        c = self.clutter
        return SceneModel(
            sensors=self.sensor_positions,
            targets=targets,
            sigma_azimuth=np.full(3, 1e-3 * sa),
            sigma_elevation=np.full(3, 1e-3 * se),
            p_detect=c.p_detect if on else 1.0,
            clutter_rate=c.rate_per_scan if on else 0.0,
            window_rad=(c.window_rad[0], c.window_rad[1]),
        )

    def assoc_params(self, model: SceneModel) -> AssocParams:
        """:class:`AssocParams` for ``model`` with this config's association settings."""
        a = self.association
        return model.params(
            gate=a.gate_sigma,
            cot_cost=a.cot_cost,
            azimuth_form=a.azimuth_form,
            target_density=a.target_density_km3,
            gn_steps=a.gauss_newton_steps,
            lr_max_iter=a.lr.max_iterations,
            lr_rel_gap=a.lr.rel_gap,
            lr_step=a.lr.step,
            lr_halve_after=a.lr.halve_after,
            milp_time_limit_s=a.milp.time_limit_s,
        )


def _semantic_problems(cfg: PassiveConfig) -> list[tuple[str, str]]:
    problems: list[tuple[str, str]] = []
    pos = cfg.sensor_positions
    for i in range(3):
        for j in range(i + 1, 3):
            if np.hypot(*(pos[i, :2] - pos[j, :2])) < 1e-6:
                problems.append(
                    (f"sensors[{j}].position_km", f"same horizontal position as sensors[{i}]")
                )
    mc = cfg.montecarlo
    for field, values in (
        ("formations", mc.formations),
        ("spacings_km", mc.spacings_km),
        ("sigmas_mrad", mc.sigmas_mrad),
        ("clutter", mc.clutter),
        ("methods", mc.methods),
    ):
        if not values:
            problems.append((f"montecarlo.{field}", "must not be empty"))
        elif len(set(values)) != len(values):
            problems.append((f"montecarlo.{field}", f"duplicate entries in {list(values)}"))
    for field, values in (("spacings_km", mc.spacings_km), ("sigmas_mrad", mc.sigmas_mrad)):
        for i, v in enumerate(values):
            if not v > 0:
                problems.append((f"montecarlo.{field}[{i}]", f"must be > 0, got {v}"))
    c = cfg.clutter
    if c.p_detect < 1.0 and c.rate_per_scan == 0.0:
        problems.append(
            (
                "clutter.rate_per_scan",
                "must be > 0 when clutter.p_detect < 1 (the S-D cost weighs every tuple against "
                "'all measurements false', which needs a false-alarm density)",
            )
        )
    return problems


def from_dict(
    data: object, source: str = "<dict>", base_dir: str | Path | None = None
) -> PassiveConfig:
    """Validate a parsed passive config; raise :class:`~covnet.config.ConfigError` listing
    every problem (the shared pipeline, :func:`covnet.config.validate`)."""
    return validate(PassiveConfig, data, source, base_dir, _semantic_problems)


def load(path: str | Path) -> PassiveConfig:
    """Read and validate a passive YAML config (:func:`covnet.kinds.load` reads any kind)."""
    p = Path(path)
    return from_dict(read_yaml(p), str(p), base_dir=p.parent)


def normalised(cfg: PassiveConfig) -> dict[str, Any]:
    """The config with every default filled in, as plain JSON-able data (``scans`` only when
    not 1 and ``network`` only when it differs from the defaults: configs without them keep
    their hash)."""
    return _normalised(cfg, ("scans", "network"))


def config_hash(cfg: PassiveConfig) -> str:
    """SHA-256 (first 16 hex digits) of the normalised config as canonical JSON."""
    return hash_of(normalised(cfg))


def with_overrides(cfg: PassiveConfig, source: str | None = None, **changes: Any) -> PassiveConfig:
    """A copy of ``cfg`` with top-level fields replaced (``None`` values are ignored),
    re-validated."""
    data = normalised(cfg)
    data.update({k: v for k, v in changes.items() if v is not None})
    return from_dict(data, source or f"{cfg.name} (with overrides)")
