"""A sensor's config (``sensors:``): the common keys (``id``, ``model``, placement, coverage,
``pd``, ``clutter_rate``), its model's own keys validated by the record of the model's
``config_fields`` (:func:`fields_record`), and where it covers (:func:`in_coverage`)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal, get_type_hints

import numpy as np

from covnet.config import ConfigModel, Float, Ident, Pair, rate
from covnet.core.sensor_models import SENSOR_MODELS
from covnet.covariance_control.config.fields import SensorModelName, positive_or_none
from covnet.records import BAD, Field, Record, field_validator
from covnet.records import Errors as _Errors
from covnet.records import Loc as _Loc


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

    _pos = field_validator("max_range_m")(positive_or_none)

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
        return rate(v)  # at most MAX_RATE: each return is drawn, gated and weighed every scan

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
