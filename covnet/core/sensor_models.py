"""Measurement models of the many-target scenario: position, range-bearing and bearing-only.

State ``x = [x, vx, y, vy]``; sensor at ``s = (sx, sy)``; ``dx = x − sx``, ``dy = y − sy``,
``r = hypot(dx, dy)`` (spec multitarget.md §2)::

    model          h(x)                 H(x) (rows over [x, vx, y, vy])             R
    position       [x, y]               [[1, 0, 0, 0], [0, 0, 1, 0]]                [[σx², ρσxσy],
                                                                                     [ρσxσy, σy²]]
    range_bearing  [r, atan2(dy, dx)]   [[dx/r, 0, dy/r, 0], [−dy/r², 0, dx/r², 0]] diag(σ_r², σ_β²)
    bearing        [atan2(dy, dx)]      [[−dy/r², 0, dx/r², 0]]                     [[σ_β²]]

Bearings are in radians, counter-clockwise from the +x axis, in ``(−π, π]``; every innovation
``z − h(x)`` has its angle components wrapped (:func:`innovation`).

Coverage: ``r ≤ max_range_m`` and, with a sector ``fov``, ``|wrap(β − centre)| ≤ half_width``;
for the models that measure a bearing also ``r > 0`` (the bearing is undefined at the sensor).
Inside coverage a dwell detects the target with probability ``pd``; ``clutter_rate`` is the
Poisson mean of false returns per dwell (simulated in :mod:`covnet.core.detection`).

**The registry** :data:`SENSOR_MODELS` maps the config's ``model:`` to its class, and the class
is the whole entry: everything the config and the runners ask of a model.  To add one, write a
:class:`SensorModel` subclass (frozen, slotted, keyword-only dataclass, as the three here) and
add it to :data:`SENSOR_MODELS`:

- ``kind`` (its ``model:`` name), ``dim_z``, ``angle_components`` (which components are
  wrapped), ``undefined_at_sensor`` (coverage excludes ``r = 0``), ``measures_from_position``
  (the config requires ``position_m`` even without coverage);
- ``config_fields``: a frozen, keyword-only dataclass of the config keys the model adds to a
  sensor (its noise parameters, in the config's units): per key its type, its default if it
  has one, and its check (``metadata={"check": fn}``, ``fn(v)`` returns ``v`` or raises
  ``ValueError``, e.g. :func:`check_positive`); the config validates a sensor's keys with a
  :mod:`covnet.records` record built from it (strict types, every problem with its path).  A
  sensor's other keys (``id``, ``model``, ``position_m``, ``max_range_m``, ``fov``, ``pd``,
  ``clutter_rate``) are every model's;
- ``from_fields(fields, **common)``: the model from those fields (unit conversions here) and
  the common keys (``sensor_xy``, ``max_range_m``, ``fov``, ``pd``, ``clutter_rate``);
- its own dataclass fields (in SI units), ``_noise`` (``R`` from them), ``h``, ``jacobian``;
- ``paper_noise(fields)`` only for a position sensor the paper's linear code runs (``h = [x,
  y]``, ``H`` constant, ``R`` the paper's correlated ``(σx, σy, ρ)``); the default ``None``
  runs the extended Kalman filter.

Detection (``pd``), clutter (``clutter_rate``, in the window ``ẑ ± n_σ √diag S`` around the
predicted measurement), gating and association work on ``h``, ``jacobian``, ``R`` and
``angle_components`` alone, so every model supports them.

Predicted information of a dwell at the predicted state (spec §3)::

    J = p · H(x̂⁻)ᵀ R⁻¹ H(x̂⁻),        p = pd inside coverage (the caller handles infeasibility)

Everything is batched over leading axes of ``x``: ``h`` gives ``(..., dim_z)``, ``jacobian``
``(..., dim_z, 4)``, ``in_coverage`` ``(...)``, :func:`predicted_information` ``(..., 4, 4)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from covnet.core import registries
from covnet.core.gaussian import Mat, Vec, symmetrise
from covnet.core.sensing import correlated_noise

__all__ = [
    "SENSOR_MODELS",
    "STATE_DIM",
    "BearingFields",
    "BearingModel",
    "FieldOfView",
    "PositionFields",
    "PositionModel",
    "RangeBearingFields",
    "RangeBearingModel",
    "SensorModel",
    "check_correlation",
    "check_positive",
    "innovation",
    "predicted_information",
    "wrap_angle",
]

BoolArray = NDArray[np.bool_]

#: dimension of the target state ``[x, vx, y, vy]``
STATE_DIM = 4
_TWO_PI = 2.0 * math.pi
_H_POSITION: Mat = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
_H_POSITION.flags.writeable = False


@overload
def wrap_angle(a: float) -> float: ...
@overload
def wrap_angle(a: NDArray[np.float64]) -> NDArray[np.float64]: ...
def wrap_angle(a: float | NDArray[np.float64]) -> float | NDArray[np.float64]:
    """Wrap angles (rad) to ``(−π, π]``: ``w = π − ((π − a) mod 2π)``.

    ``(π − a) mod 2π`` lies in ``[0, 2π)`` exactly, but can round up to ``2π`` for inputs a hair
    above ``π``; those give ``−π`` and are mapped to ``π``.  A float in gives a float out.
    """
    w = math.pi - np.mod(math.pi - np.asarray(a, dtype=np.float64), _TWO_PI)
    w = np.where(w <= -math.pi, math.pi, w)
    if np.ndim(a) == 0 and not isinstance(a, np.ndarray):
        return float(w)
    return np.asarray(w, dtype=np.float64)


def innovation(z: ArrayLike, zhat: ArrayLike, angle_mask: Sequence[bool] | BoolArray) -> Mat:
    """``ν = z − ẑ`` with the components where ``angle_mask`` is true wrapped to ``(−π, π]``.

    ``z`` and ``zhat`` broadcast over leading axes; their last axis is the measurement
    (``dim_z == len(angle_mask)``).
    """
    zz: Mat = np.asarray(z, dtype=np.float64)
    zh: Mat = np.asarray(zhat, dtype=np.float64)
    mask = np.asarray(angle_mask, dtype=bool)
    if mask.ndim != 1:
        raise ValueError(f"angle_mask: expected a 1-D mask, got shape {mask.shape}")
    for name, a in (("z", zz), ("zhat", zh)):
        if a.ndim == 0 or a.shape[-1] != mask.shape[0]:
            raise ValueError(
                f"{name}: expected last axis of length {mask.shape[0]} (dim_z), got {a.shape}"
            )
    nu: Mat = zz - zh
    if mask.any():
        nu = np.where(mask, wrap_angle(nu), nu)
    return nu


def _states(x: ArrayLike) -> Mat:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 0 or x.shape[-1] != STATE_DIM:
        raise ValueError(f"x: expected shape (..., {STATE_DIM}) for [x, vx, y, vy], got {x.shape}")
    return x


def _positive(name: str, value: float) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return v


@dataclass(frozen=True, slots=True)
class FieldOfView:
    """A sector of bearings ``|wrap(β − centre)| ≤ half_width`` (degrees in, radians inside).

    ``half_width_deg`` in ``(0, 180]``; 180 is the full circle.
    """

    center_deg: float
    half_width_deg: float

    def __post_init__(self) -> None:
        if not math.isfinite(float(self.center_deg)):
            raise ValueError(f"fov.center_deg: expected a finite angle, got {self.center_deg!r}")
        hw = float(self.half_width_deg)
        if not (0.0 < hw <= 180.0):
            raise ValueError(f"fov.half_width_deg: expected 0 < half_width_deg <= 180, got {hw}")
        object.__setattr__(self, "center_deg", float(self.center_deg))
        object.__setattr__(self, "half_width_deg", hw)

    def contains(self, bearing: ArrayLike) -> BoolArray:
        """True where the bearing (rad) lies in the sector (boundary included)."""
        b = np.asarray(bearing, dtype=np.float64)
        off = np.abs(wrap_angle(b - math.radians(self.center_deg)))
        return np.asarray(off <= math.radians(self.half_width_deg))


@dataclass(frozen=True, slots=True, kw_only=True)
class SensorModel:
    """Common part of the three models: placement, coverage, detection, clutter and ``R``.

    Fields (keyword-only): ``sensor_xy`` (m), ``max_range_m`` (default ∞), ``fov`` (optional
    :class:`FieldOfView`), ``pd`` in ``[0, 1]``, ``clutter_rate`` (false returns per dwell,
    ``≥ 0``).  ``R`` is built from the model's noise parameters, ``L`` is its lower Cholesky
    factor (``R = L Lᵀ``, factored once: every draw and information matrix uses it); both are
    read-only.
    Subclasses implement ``h`` and ``jacobian`` and the noise (``_noise``).
    """

    kind: ClassVar[str] = ""
    dim_z: ClassVar[int] = 0
    #: which measurement components are angles (wrapped), one flag per component
    angle_components: ClassVar[tuple[bool, ...]] = ()
    #: ``h`` or ``H`` is undefined at the sensor's position: coverage excludes ``r = 0``
    undefined_at_sensor: ClassVar[bool] = True
    #: the model measures relative to ``sensor_xy``: a config's sensor needs ``position_m``
    measures_from_position: ClassVar[bool] = True
    #: the config keys this model adds to a sensor (module docstring)
    config_fields: ClassVar[type[Any]] = object

    sensor_xy: tuple[float, float] = (0.0, 0.0)
    max_range_m: float = math.inf
    fov: FieldOfView | None = None
    pd: float = 1.0
    clutter_rate: float = 0.0
    R: Mat = field(init=False, repr=False, compare=False)
    L: Mat = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        s = np.asarray(self.sensor_xy, dtype=np.float64)
        if s.shape != (2,) or not np.all(np.isfinite(s)):
            raise ValueError(
                f"sensor_xy: expected two finite numbers (sx, sy), got {self.sensor_xy!r}"
            )
        object.__setattr__(self, "sensor_xy", (float(s[0]), float(s[1])))
        rng_max = float(self.max_range_m)
        if not rng_max > 0.0:  # inf allowed
            raise ValueError(
                f"max_range_m: expected a number > 0 (or inf), got {self.max_range_m!r}"
            )
        object.__setattr__(self, "max_range_m", rng_max)
        if self.fov is not None and not isinstance(self.fov, FieldOfView):
            raise ValueError(f"fov: expected a FieldOfView or None, got {type(self.fov).__name__}")
        pd = float(self.pd)
        if not (0.0 <= pd <= 1.0):
            raise ValueError(f"pd: expected a probability in [0, 1], got {self.pd!r}")
        object.__setattr__(self, "pd", pd)
        lam = float(self.clutter_rate)
        if not (math.isfinite(lam) and lam >= 0.0):
            raise ValueError(
                f"clutter_rate: expected a finite number >= 0, got {self.clutter_rate!r}"
            )
        object.__setattr__(self, "clutter_rate", lam)
        R = np.array(self._noise(), dtype=np.float64)
        R.flags.writeable = False
        object.__setattr__(self, "R", R)
        L = np.linalg.cholesky(R)
        L.flags.writeable = False
        object.__setattr__(self, "L", L)

    # -- to implement ------------------------------------------------------------------------

    @classmethod
    def from_fields(cls, fields: Any, **common: Any) -> SensorModel:
        """The model of a config's sensor: ``fields`` its :attr:`config_fields` instance,
        ``common`` the keys every model takes (``sensor_xy``, ``max_range_m``, ``fov``, ``pd``,
        ``clutter_rate``)."""
        raise NotImplementedError

    @classmethod
    def paper_noise(cls, fields: Any) -> tuple[float, float, float] | None:
        """``(σx, σy, ρ)`` when the paper's linear code runs this sensor (a position sensor:
        ``h = [x, y]``, its constant ``H`` and the correlated ``R`` of these), else ``None``
        (the extended Kalman filter, ``h``, ``jacobian`` and ``R`` of the model)."""
        return None

    def _noise(self) -> Mat:
        raise NotImplementedError

    def h(self, x: ArrayLike) -> Mat:
        """The noise-free measurement ``h(x)``, ``(..., dim_z)``."""
        raise NotImplementedError

    def jacobian(self, x: ArrayLike) -> Mat:
        """``H(x) = ∂h/∂x``, ``(..., dim_z, 4)``."""
        raise NotImplementedError

    # -- shared ------------------------------------------------------------------------------

    @property
    def angle_mask(self) -> BoolArray:
        """:attr:`angle_components` as a boolean array ``(dim_z,)``."""
        return np.array(self.angle_components, dtype=bool)

    def relative(self, x: ArrayLike) -> tuple[Vec, Vec, Vec]:
        """``(dx, dy, r)`` of the target(s) relative to the sensor, each ``(...)``."""
        xs = _states(x)
        dx = xs[..., 0] - self.sensor_xy[0]
        dy = xs[..., 2] - self.sensor_xy[1]
        return dx, dy, np.hypot(dx, dy)

    def in_coverage(self, x: ArrayLike) -> BoolArray:
        """True where the target at ``x`` is inside coverage: ``r ≤ max_range_m``, in the sector
        ``fov`` if any, and ``r > 0`` for models undefined at the sensor (those that measure a
        bearing)."""
        dx, dy, r = self.relative(x)
        ok = r <= self.max_range_m
        if self.undefined_at_sensor:
            ok = ok & (r > 0.0)
        if self.fov is not None:
            ok = ok & self.fov.contains(np.arctan2(dy, dx))
        return np.asarray(ok, dtype=bool)

    def whitened_jacobian(self, x: ArrayLike) -> Mat:
        """``W = L⁻¹ H(x)``, ``(..., dim_z, 4)``, so that ``Hᵀ R⁻¹ H = Wᵀ W``: each row of ``H``
        over its ``σ`` when ``R`` is diagonal, a triangular solve otherwise."""
        H = self.jacobian(x)
        R = self.R
        d = np.diagonal(R)
        if np.array_equal(R, np.diag(d)):
            return np.asarray(H / np.sqrt(d)[:, None])
        return _whiten(self.L, H)


def check_positive(v: float) -> float:
    """A config key's check (``metadata={"check": check_positive}``): ``v > 0``."""
    if not v > 0:
        raise ValueError(f"must be > 0, got {v}")
    return v


def check_correlation(v: float) -> float:
    """A config key's check: a correlation, ``-1 < v < 1``."""
    if not -1.0 < v < 1.0:
        raise ValueError(f"must be in (-1, 1), got {v}")
    return v


def _key(check: Any) -> Any:
    """A required config key with its check."""
    return field(metadata={"check": check})


@dataclass(frozen=True, kw_only=True)
class PositionFields:
    """``model: position``: ``R = [[σx², ρσxσy], [ρσxσy, σy²]]`` from ``sigma_x_m``,
    ``sigma_y_m`` (m) and ``rho`` in ``(-1, 1)``."""

    sigma_x_m: float = _key(check_positive)
    sigma_y_m: float = _key(check_positive)
    rho: float = _key(check_correlation)


@dataclass(frozen=True, kw_only=True)
class RangeBearingFields:
    """``model: range_bearing``: ``R = diag(σ_r², σ_β²)`` from ``sigma_range_m`` (m) and
    ``sigma_bearing_mrad`` (mrad)."""

    sigma_range_m: float = _key(check_positive)
    sigma_bearing_mrad: float = _key(check_positive)


@dataclass(frozen=True, kw_only=True)
class BearingFields:
    """``model: bearing``: ``R = [[σ_β²]]`` from ``sigma_bearing_mrad`` (mrad)."""

    sigma_bearing_mrad: float = _key(check_positive)


@dataclass(frozen=True, slots=True, kw_only=True)
class PositionModel(SensorModel):
    """Position sensor (the paper's): ``h(x) = [x, y]``, ``H`` constant,
    ``R = [[σx², ρ σx σy], [ρ σx σy, σy²]]`` (``sigma_x``, ``sigma_y`` in m, ``|rho| < 1``)."""

    kind: ClassVar[str] = "position"
    dim_z: ClassVar[int] = 2
    angle_components: ClassVar[tuple[bool, ...]] = (False, False)
    undefined_at_sensor: ClassVar[bool] = False
    measures_from_position: ClassVar[bool] = False
    config_fields: ClassVar[type[Any]] = PositionFields

    sigma_x: float
    sigma_y: float
    rho: float = 0.0

    @classmethod
    def from_fields(cls, fields: Any, **common: Any) -> SensorModel:
        return cls(sigma_x=fields.sigma_x_m, sigma_y=fields.sigma_y_m, rho=fields.rho, **common)

    @classmethod
    def paper_noise(cls, fields: Any) -> tuple[float, float, float] | None:
        return (fields.sigma_x_m, fields.sigma_y_m, fields.rho)

    def _noise(self) -> Mat:
        sx = _positive("sigma_x", self.sigma_x)
        sy = _positive("sigma_y", self.sigma_y)
        rho = float(self.rho)
        if not abs(rho) < 1.0:
            raise ValueError(f"rho: expected a correlation with |rho| < 1, got {self.rho!r}")
        _set(self, sigma_x=sx, sigma_y=sy, rho=rho)
        return correlated_noise(sx, sy, rho)

    def h(self, x: ArrayLike) -> Mat:
        """``[x, y]``, ``(..., 2)``."""
        return _states(x)[..., [0, 2]]

    def jacobian(self, x: ArrayLike) -> Mat:
        """``[[1, 0, 0, 0], [0, 0, 1, 0]]`` broadcast to ``(..., 2, 4)``."""
        xs = _states(x)
        return np.array(np.broadcast_to(_H_POSITION, xs.shape[:-1] + _H_POSITION.shape))


@dataclass(frozen=True, slots=True, kw_only=True)
class RangeBearingModel(SensorModel):
    """Radar: ``h(x) = [r, atan2(dy, dx)]``, ``R = diag(σ_r², σ_β²)`` (``sigma_r`` in m,
    ``sigma_bearing`` in rad)."""

    kind: ClassVar[str] = "range_bearing"
    dim_z: ClassVar[int] = 2
    angle_components: ClassVar[tuple[bool, ...]] = (False, True)
    config_fields: ClassVar[type[Any]] = RangeBearingFields

    sigma_r: float
    sigma_bearing: float

    @classmethod
    def from_fields(cls, fields: Any, **common: Any) -> SensorModel:
        sb = 1e-3 * fields.sigma_bearing_mrad
        return cls(sigma_r=fields.sigma_range_m, sigma_bearing=sb, **common)

    def _noise(self) -> Mat:
        sr = _positive("sigma_r", self.sigma_r)
        sb = _positive("sigma_bearing", self.sigma_bearing)
        _set(self, sigma_r=sr, sigma_bearing=sb)
        return np.diag([sr * sr, sb * sb])

    def h(self, x: ArrayLike) -> Mat:
        """``[r, atan2(dy, dx)]``, ``(..., 2)``."""
        dx, dy, r = self.relative(x)
        return np.stack([r, np.arctan2(dy, dx)], axis=-1)

    def jacobian(self, x: ArrayLike) -> Mat:
        """``[[dx/r, 0, dy/r, 0], [−dy/r², 0, dx/r², 0]]``, ``(..., 2, 4)``; ``r = 0`` raises."""
        dx, dy, r = self.relative(x)
        _check_off_sensor(r)
        r2 = r * r
        H = np.zeros(r.shape + (2, STATE_DIM))
        H[..., 0, 0] = dx / r
        H[..., 0, 2] = dy / r
        H[..., 1, 0] = -dy / r2
        H[..., 1, 2] = dx / r2
        return H


@dataclass(frozen=True, slots=True, kw_only=True)
class BearingModel(SensorModel):
    """Bearing-only (passive) sensor: ``h(x) = [atan2(dy, dx)]``, ``R = [[σ_β²]]``
    (``sigma_bearing`` in rad)."""

    kind: ClassVar[str] = "bearing"
    dim_z: ClassVar[int] = 1
    angle_components: ClassVar[tuple[bool, ...]] = (True,)
    config_fields: ClassVar[type[Any]] = BearingFields

    sigma_bearing: float

    @classmethod
    def from_fields(cls, fields: Any, **common: Any) -> SensorModel:
        return cls(sigma_bearing=1e-3 * fields.sigma_bearing_mrad, **common)

    def _noise(self) -> Mat:
        sb = _positive("sigma_bearing", self.sigma_bearing)
        _set(self, sigma_bearing=sb)
        return np.array([[sb * sb]])

    def h(self, x: ArrayLike) -> Mat:
        """``[atan2(dy, dx)]``, ``(..., 1)``."""
        dx, dy, _ = self.relative(x)
        return np.arctan2(dy, dx)[..., None]

    def jacobian(self, x: ArrayLike) -> Mat:
        """``[[−dy/r², 0, dx/r², 0]]``, ``(..., 1, 4)``; ``r = 0`` raises."""
        dx, dy, r = self.relative(x)
        _check_off_sensor(r)
        r2 = r * r
        H = np.zeros(r.shape + (1, STATE_DIM))
        H[..., 0, 0] = -dy / r2
        H[..., 0, 2] = dx / r2
        return H


def _set(obj: object, **values: float) -> None:
    """Store normalised floats on a frozen instance (only from ``__post_init__``)."""
    for name, value in values.items():
        object.__setattr__(obj, name, value)


def _check_off_sensor(r: Vec) -> None:
    if np.any(r == 0.0):
        raise ValueError("x: the bearing Jacobian is undefined at the sensor's position (r = 0)")


def _whiten(L: Mat, H: Mat) -> Mat:
    """``L⁻¹ H`` for ``H`` ``(..., dz, 4)`` by one triangular solve (``L`` lower)."""
    from scipy import linalg  # start-up: the config reads this registry

    dz = L.shape[0]
    Hm = np.moveaxis(H, -2, 0).reshape(dz, -1)  # (dz, N·4)
    W = linalg.solve_triangular(L, Hm, lower=True, check_finite=False)
    return np.moveaxis(np.asarray(W).reshape((dz,) + H.shape[:-2] + (STATE_DIM,)), 0, -2)


#: model name (the config's ``model:``) -> class, the registry's entry (module docstring);
#: ``SENSOR_MODELS[kind](**params)``, or from a config's fields ``.from_fields(fields, ...)``
SENSOR_MODELS: dict[str, type[SensorModel]] = {
    PositionModel.kind: PositionModel,
    RangeBearingModel.kind: RangeBearingModel,
    BearingModel.kind: BearingModel,
}
registries.ship("covnet.core.sensor_models.SENSOR_MODELS", SENSOR_MODELS)


def predicted_information(model: SensorModel, x_pred: ArrayLike, pd: float | None = None) -> Mat:
    """Predicted information of one dwell, ``J = p · Hᵀ R⁻¹ H`` with ``H = H(x̂⁻)`` (spec §3).

    ``x_pred`` is ``(..., 4)`` (e.g. ``(T, 4)``: one predicted state per target), the result
    ``(..., 4, 4)``.  ``p`` is ``pd`` (default ``model.pd``; pass 1 for ``detection: ignore``, or
    the PDA information-reduction factor ``q2`` of
    :func:`covnet.core.association.information_reduction_factor` for ``detection: pda``).
    Coverage is not looked at: the caller marks out-of-coverage dwells infeasible.

    ``R = L Lᵀ`` (Cholesky), ``W = L⁻¹ H`` by a triangular solve, ``J = p · Wᵀ W``: no inverse.
    """
    p = model.pd if pd is None else float(pd)
    if not (math.isfinite(p) and p >= 0.0):
        raise ValueError(f"pd: expected a finite multiplier >= 0, got {pd!r}")
    H = model.jacobian(x_pred)  # (..., dz, 4)
    W = _whiten(model.L, H)
    J = p * (np.swapaxes(W, -1, -2) @ W)
    return symmetrise(J)
