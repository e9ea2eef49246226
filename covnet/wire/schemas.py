"""The wire's message schemas: every message that crosses a process boundary, each field
declared once, with the type that says both what it holds in Python and how it travels
(:data:`Count`, :data:`Float`, :data:`Names`, :data:`Mat`, ...); the checks a message's fields
pass when it is built (lenient in converting) or decoded (strict), and the payload size cap
derived from the schemas.  The bytes are :mod:`covnet.wire.codec`'s."""

from __future__ import annotations

import math
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType, UnionType
from typing import Annotated, Any, ClassVar, TypeVar

import numpy as np
from numpy.typing import NDArray

from covnet.wire.keys import _GOOD_NAMES, _GOOD_NAMES_MAX, MAX_NAME_LEN, _name_problem

MAX_ARRAY_ELEMENTS = 1 << 20
"""Largest number of elements in one array (8 MiB of float64)."""
MAX_IDS = 4096
"""Longest id tuple (``target_ids``, ``enabled``) and largest ``modes`` map."""

#: the largest network the payload size cap (:data:`MAX_PAYLOAD_BYTES`) is computed for:
#: hundreds of sensors, with margin
CAP_SENSORS = 1024
CAP_TARGETS = 1024
#: rows of one measurement list (a mobile sensor seeing every target; passive lists hold <= 256)
CAP_ROWS = 1024
#: state and measurement dimensions (the kinds use 4 or 3, and 2)
CAP_STATE_DIM, CAP_MEAS_DIM = 6, 3
#: reasons a heartbeat's ``rejected`` counts at most
CAP_REASONS = 64
#: search cells a surveillance Status carries at most (the config's grid: 64 x 64)
CAP_CELLS = 64 * 64

REASONS = frozenset(
    {
        "not_msgpack",
        "truncated",
        "too_large",
        "not_a_map",
        "bad_version",
        "unknown_kind",
        "wrong_kind",
        "missing_field",
        "unknown_field",
        "bad_type",
        "bad_shape",
        "non_finite",
        "bad_value",
        "key_mismatch",
    }
)

_INT64_MAX = 2**63 - 1


class WireError(ValueError):
    """A payload (or a message being built) that does not satisfy the schema.

    ``reason`` is one of :data:`REASONS` (stable, for counters); ``detail`` is for humans.
    """

    def __init__(self, reason: str, detail: str) -> None:
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


# --------------------------------------------------------------------------------------------
# field kinds: one coercion/validation routine per kind, strict (decode) or lenient (build)
# --------------------------------------------------------------------------------------------

# A field's type is one of the aliases below: ``Annotated[<Python type>, _Wire(<kind>)]``.  The
# Python type is what the field holds (for mypy and the reader); the kind is how it is checked
# and sent.  Each message class's kinds are read from its annotations once (:func:`_spec`).


@dataclass(frozen=True, slots=True)
class _Wire:
    """A field type's wire kind (the metadata of the aliases below)."""

    kind: str


Count = Annotated[int, _Wire("count")]
"""An int >= 0 (a scan, an episode, a sequence number)."""
Stamp = Annotated[int, _Wire("stamp")]
"""An int >= 0 of nanoseconds (``t_sent_ns``)."""
Float = Annotated[float, _Wire("float")]
"""A finite float."""
Name = Annotated[str, _Wire("name")]
"""An id (:func:`covnet.wire.keys._name_problem`)."""
Names = Annotated[tuple[str, ...], _Wire("names")]
"""A tuple of unique ids."""
Vec = Annotated[NDArray[np.float64], _Wire("vec")]
"""A finite float64 vector (read-only)."""
Mat = Annotated[NDArray[np.float64], _Wire("mat")]
"""A finite float64 matrix (read-only)."""
Modes = Annotated[dict[str, str], _Wire("modes")]
"""A map of id to id (a sensor's mode)."""
Counts = Annotated[dict[str, int], _Wire("counts")]
"""A map of id to an int >= 0."""
Targets = Annotated[dict[str, tuple[str, ...]], _Wire("targets")]
"""A map of id to a tuple of unique ids."""
Vecs = Annotated[dict[str, NDArray[np.float64]], _Wire("vecs")]
"""A map of id to a finite float64 vector."""


def _is_int(v: object, strict: bool) -> bool:
    if strict:
        return type(v) is int
    return isinstance(v, int | np.integer) and not isinstance(v, bool | np.bool_)


def _coerce(kind: str, name: str, v: object, strict: bool) -> Any:
    """``v`` as field ``name`` of kind ``kind`` holds it, or :class:`WireError`; ``strict``:
    as decoded from the wire (exact types only), else as given to a constructor.  The common
    cases take a shortcut with the same outcome as the full checks of :func:`_coerce_slow`."""
    t = type(v)
    if t is int:
        if (kind == "count" or kind == "stamp") and 0 <= v <= _INT64_MAX:  # type: ignore[operator]
            return v
    elif t is float:
        if kind == "float" and v - v == 0.0:  # type: ignore[operator]  # finite
            return v
    elif t is str:
        if kind == "name" and v in _GOOD_NAMES:
            return v
    elif t is list if strict else t is tuple:
        if kind == "names" and len(v) <= MAX_IDS:  # type: ignore[arg-type]
            try:
                known = _GOOD_NAMES.issuperset(v)  # type: ignore[arg-type]
            except TypeError:  # an unhashable element: the full checks say which
                known = False
            if known and (strict or all(type(x) is str for x in v)):  # type: ignore[attr-defined]
                out: tuple[str, ...] = tuple(v)  # type: ignore[arg-type]
                if len(set(out)) == len(out):
                    return out
    return _coerce_slow(kind, name, v, strict)


def _coerce_slow(kind: str, name: str, v: object, strict: bool) -> Any:
    if kind in ("count", "stamp"):
        if not _is_int(v, strict):
            raise WireError("bad_type", f"{name} must be an int, got {type(v).__name__}")
        i = int(v)  # type: ignore[call-overload]
        if not 0 <= i <= _INT64_MAX:
            raise WireError("bad_value", f"{name}={i} out of [0, 2**63)")
        return i
    if kind == "float":
        if strict:
            ok = type(v) is float
        else:
            ok = isinstance(v, float | int | np.floating | np.integer) and not isinstance(
                v, bool | np.bool_
            )
        if not ok:
            raise WireError("bad_type", f"{name} must be a float, got {type(v).__name__}")
        f = float(v)  # type: ignore[arg-type]
        if not math.isfinite(f):
            raise WireError("non_finite", f"{name}={f}")
        return f
    if kind == "name":
        if (type(v) is not str) if strict else not isinstance(v, str):
            raise WireError("bad_type", f"{name} must be a str, got {type(v).__name__}")
        problem = _name_problem(v)
        if problem is not None:
            raise WireError("bad_value", f"{name}={v!r}: {problem}")
        if type(v) is str and len(_GOOD_NAMES) < _GOOD_NAMES_MAX:
            _GOOD_NAMES.add(v)
        return str(v)
    if kind == "names":
        return _coerce_names(name, v, strict)
    if kind in ("vec", "mat"):
        return _coerce_array(name, v, 1 if kind == "vec" else 2, strict)
    if kind == "modes":
        return _coerce_modes(name, v, strict)
    if kind == "counts":
        return _coerce_counts(name, v, strict)
    if kind == "targets":
        return _coerce_targets(name, v, strict)
    if kind == "vecs":
        return _coerce_vecs(name, v, strict)
    raise AssertionError(kind)  # pragma: no cover


def _coerce_counts(name: str, v: object, strict: bool) -> dict[str, int] | None:
    if v is None:
        if strict:
            raise WireError("bad_type", f"{name} must be a map, got nil")
        return None
    if not isinstance(v, Mapping) or (strict and type(v) is not dict):
        raise WireError("bad_type", f"{name} must be a map of str to int")
    if len(v) > MAX_IDS:
        raise WireError("too_large", f"{name} has {len(v)} entries > {MAX_IDS}")
    return {
        _coerce("name", f"{name} key", k, strict): _coerce("count", f"{name}[{k!r}]", x, strict)
        for k, x in v.items()
    }


def _coerce_targets(name: str, v: object, strict: bool) -> dict[str, tuple[str, ...]] | None:
    if v is None:
        if strict:
            raise WireError("bad_type", f"{name} must be a map, got nil")
        return None
    if not isinstance(v, Mapping) or (strict and type(v) is not dict):
        raise WireError("bad_type", f"{name} must be a map of str to a list of str")
    if len(v) > MAX_IDS:
        raise WireError("too_large", f"{name} has {len(v)} entries > {MAX_IDS}")
    return {
        _coerce("name", f"{name} key", k, strict): _coerce_names(f"{name}[{k!r}]", x, strict)
        for k, x in v.items()
    }


def _coerce_vecs(name: str, v: object, strict: bool) -> dict[str, NDArray[np.float64]] | None:
    if v is None:
        if strict:
            raise WireError("bad_type", f"{name} must be a map, got nil")
        return None
    if not isinstance(v, Mapping) or (strict and type(v) is not dict):
        raise WireError("bad_type", f"{name} must be a map of str to a float64 vector")
    if len(v) > MAX_IDS:
        raise WireError("too_large", f"{name} has {len(v)} entries > {MAX_IDS}")
    return {
        _coerce("name", f"{name} key", k, strict): _coerce_array(f"{name}[{k!r}]", x, 1, strict)
        for k, x in v.items()
    }


def _coerce_names(name: str, v: object, strict: bool) -> tuple[str, ...]:
    if strict:
        if type(v) is not list:
            raise WireError("bad_type", f"{name} must be a list of str, got {type(v).__name__}")
        items = v
    else:
        if isinstance(v, str | bytes) or not isinstance(v, Iterable):
            raise WireError("bad_type", f"{name} must be a sequence of str")
        items = list(v)
    if len(items) > MAX_IDS:
        raise WireError("too_large", f"{name} has {len(items)} ids > {MAX_IDS}")
    out = tuple(_coerce("name", f"{name}[{i}]", item, strict) for i, item in enumerate(items))
    if len(set(out)) != len(out):
        raise WireError("bad_value", f"{name} has duplicate ids")
    return out


def _coerce_modes(name: str, v: object, strict: bool) -> dict[str, str] | None:
    if v is None:
        if strict:  # None is never sent (omitted), so an explicit nil is not what we encode
            raise WireError("bad_type", f"{name} must be a map, got nil")
        return None
    if not isinstance(v, Mapping) or (strict and type(v) is not dict):
        raise WireError("bad_type", f"{name} must be a map of str to str")
    if len(v) > MAX_IDS:
        raise WireError("too_large", f"{name} has {len(v)} entries > {MAX_IDS}")
    return {
        _coerce("name", f"{name} key", k, strict): _coerce("name", f"{name}[{k!r}]", x, strict)
        for k, x in v.items()
    }


def _coerce_array(name: str, v: object, ndim: int, strict: bool) -> NDArray[np.float64]:
    if strict:
        if not isinstance(v, np.ndarray):  # only the ext hook makes arrays
            raise WireError("bad_type", f"{name} must be a float64 array, got {type(v).__name__}")
        a = v
    else:
        if isinstance(v, np.ndarray) and v.dtype.kind not in "fiu":
            raise WireError("bad_type", f"{name} must be real, got dtype {v.dtype}")
        try:
            a = np.array(v, dtype=np.float64, order="C", copy=True)
        except (TypeError, ValueError) as e:
            raise WireError("bad_type", f"{name}: {e}") from None
        a.flags.writeable = False
    if a.ndim != ndim:
        raise WireError("bad_shape", f"{name} must be {ndim}-D, got shape {a.shape}")
    if a.size > MAX_ARRAY_ELEMENTS:
        raise WireError("too_large", f"{name} has {a.size} elements > {MAX_ARRAY_ELEMENTS}")
    if not _all_finite(a):
        raise WireError("non_finite", f"{name} has NaN or inf")
    return a


_SUM_CHECK_MAX = 64
"""Arrays up to this many elements are checked for finiteness by summing them in Python
(:func:`_all_finite`), a few times faster than numpy's element-wise test on such sizes."""


def _all_finite(a: NDArray[np.float64]) -> bool:
    """Whether every element of ``a`` is finite.  A small array's sum decides when it is
    finite: a sum of float64s with an inf or a NaN among them is inf or NaN (IEEE 754), so a
    finite sum means finite elements; a sum that is not (those, or an overflow of finite
    ones) is settled element by element."""
    if a.size <= _SUM_CHECK_MAX and math.isfinite(sum(a.ravel().tolist())):
        return True
    return bool(np.isfinite(a).all())


# --------------------------------------------------------------------------------------------
# messages
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Spec:
    """A message class's fields in declaration order as ``(name, kind, optional)`` (optional:
    defaults to None, omitted from the wire when unset), the map keys its payload may hold,
    and its fields' kinds by name."""

    fields: tuple[tuple[str, str, bool], ...]
    keys: frozenset[str]
    kinds: Mapping[str, str]
    optional: frozenset[str]


_SPECS: dict[type, _Spec] = {}


def _spec(cls: type) -> _Spec:
    """``cls``'s :class:`_Spec`, read from its annotations the first time it is asked for."""
    spec = _SPECS.get(cls)
    if spec is None:
        hints = typing.get_type_hints(cls, include_extras=True)
        out = tuple(
            (f.name, _wire_kind(hints[f.name], f"{cls.__name__}.{f.name}"), f.default is None)
            for f in fields(cls)
        )
        kinds = MappingProxyType({name: kind for name, kind, _ in out})
        optional = frozenset(name for name, _, opt in out if opt)
        spec = _SPECS[cls] = _Spec(out, frozenset(kinds) | {"v", "k"}, kinds, optional)
    return spec


def _wire_kind(hint: Any, where: str) -> str:
    """The wire kind of a field typed ``hint`` (an alias above, or one ``| None``)."""
    if typing.get_origin(hint) in (typing.Union, UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            hint = args[0]
    if typing.get_origin(hint) is Annotated:
        for meta in hint.__metadata__:
            if isinstance(meta, _Wire):
                return meta.kind
    raise TypeError(f"{where}: a message field's type must be a wire type (Count, Name, ...)")


class _FieldKinds:
    """``cls._KINDS``: field name -> wire kind, in wire order, as :func:`_spec` read them from
    the annotations (a view, not a declaration)."""

    def __get__(self, obj: object, cls: type) -> Mapping[str, str]:
        return _spec(cls).kinds


_Self = TypeVar("_Self", bound="_Message")


class _Message:
    """Base of every message: field validation, and value equality (arrays compared exactly)."""

    __slots__ = ()
    KIND: ClassVar[str]
    _KINDS = _FieldKinds()

    def __post_init__(self) -> None:
        for name, kind, optional in _spec(type(self)).fields:
            value = getattr(self, name)
            if value is None and optional:
                continue  # an optional field left unset (never sent)
            object.__setattr__(self, name, _coerce(kind, name, value, strict=False))
        self._check()

    def _check(self) -> None:
        """Cross-field consistency (shapes); overridden where there is some."""

    def evolve(self: _Self, **changes: Any) -> _Self:
        """This message with ``changes`` (field name -> value), validated as a constructor
        validates them (:func:`dataclasses.replace` of it, without checking the fields that
        stay again: they were checked when this message was built, and its arrays are
        read-only, so the copy shares them)."""
        cls = type(self)
        spec = _spec(cls)
        out = object.__new__(cls)
        setattr_ = object.__setattr__
        for name in spec.kinds:
            setattr_(out, name, getattr(self, name))
        optional = spec.optional
        for name, value in changes.items():
            kind = spec.kinds.get(name)
            if kind is None:
                raise TypeError(f"{cls.__name__} has no field {name!r}")
            if value is None and name in optional:
                setattr_(out, name, None)
            else:
                setattr_(out, name, _coerce(kind, name, value, strict=False))
        out._check()
        return out

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for n in _spec(type(self)).kinds:
            a, b = getattr(self, n), getattr(other, n)
            if (a is None) != (b is None):
                return False
            if isinstance(a, np.ndarray):
                if a.shape != b.shape or not np.array_equal(a, b):
                    return False
            elif isinstance(a, dict) and any(isinstance(x, np.ndarray) for x in a.values()):
                if a.keys() != b.keys() or not all(
                    a[k].shape == b[k].shape and np.array_equal(a[k], b[k]) for k in a
                ):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, slots=True, eq=False)
class Truth(_Message):
    """Ground truth at scan ``scan``, scenario time ``t`` [s]: row i of ``states`` ``(m, n)``
    is the state of target ``target_ids[i]``.  Optionally (mobile scenarios, both or neither)
    the sensor platforms: row j of ``platforms`` ``(N, 4)`` is ``[qx, qy, q̇x, q̇y]`` (position
    [m] and velocity [m/s] over the last scan) of sensor ``sensor_ids[j]``."""

    KIND: ClassVar[str] = "truth"
    scan: Count
    t: Float
    target_ids: Names
    states: Mat
    sensor_ids: Names | None = None
    platforms: Mat | None = None

    def _check(self) -> None:
        if self.states.shape[0] != len(self.target_ids):
            raise WireError(
                "bad_shape",
                f"states has {self.states.shape[0]} rows for {len(self.target_ids)} targets",
            )
        if (self.sensor_ids is None) != (self.platforms is None):
            raise WireError("bad_shape", "sensor_ids and platforms come together")
        if self.platforms is not None and self.platforms.shape != (len(self.sensor_ids or ()), 4):
            raise WireError(
                "bad_shape",
                f"platforms is {self.platforms.shape} for {len(self.sensor_ids or ())} sensors",
            )


@dataclass(frozen=True, slots=True, eq=False)
class Command(_Message):
    """The manager's tasking for scan ``scan`` (time ``t`` [s]), one per scan, on the key
    that names its enabled set (:func:`command_key`): sensors listed in ``enabled`` measure,
    every other sensor is disabled for this scan (and does not receive it). ``modes`` (optional)
    maps a sensor id to a policy-specific mode name; ``targets`` (optional, mobile scenarios
    and many-target covariance control) maps a sensor id to the ids of the targets it is to
    measure (possibly none); ``windows`` (optional, many-target covariance control) maps an
    enabled sensor id to its dwell's clutter window, ``[centre..., half-width...]`` in
    measurement space (the manager's predicted measurement ± n σ of the innovation).
    ``t_sent_ns``: monotonic ns at publish."""

    KIND: ClassVar[str] = "cmd"
    scan: Count
    t: Float
    enabled: Names
    t_sent_ns: Stamp
    episode: Count = 0
    modes: Modes | None = None
    targets: Targets | None = None
    windows: Vecs | None = None

    def _check(self) -> None:
        if self.windows is not None and not set(self.windows) <= set(self.enabled):
            extra = sorted(set(self.windows) - set(self.enabled))
            raise WireError("bad_value", f"windows for sensors not enabled: {extra}")


@dataclass(frozen=True, slots=True, eq=False)
class Measurement(_Message):
    """Sensor ``sensor_id``'s measurements for scan ``scan`` at time ``t`` [s]: ``z`` is
    ``(m, dz)`` (m detections, possibly 0), each with noise covariance ``R`` ``(dz, dz)``.

    Optional (mobile scenarios): ``target_ids`` names the target of each row of ``z``, and
    ``platform`` ``(4,)`` is the sensor's own ``[qx, qy, q̇x, q̇y]`` when it measured (``R`` is
    then its base noise ``R0``: the geometric noise of each detection is the receiver's to
    model).

    ``seq``: how many messages the sensor has sent for the manager in this run, this one
    included (1, 2, ...; set by every sensor process): a gap in the ``seq`` received is a
    message sent and never arrived, which is what ``lost`` counts (:mod:`manager.loop`)."""

    KIND: ClassVar[str] = "meas"
    sensor_id: Name
    scan: Count
    t: Float
    z: Mat
    R: Mat
    t_sent_ns: Stamp
    episode: Count = 0
    target_ids: Names | None = None
    platform: Vec | None = None
    seq: Count | None = None

    def _check(self) -> None:
        dz = self.R.shape[0]
        if self.R.shape != (dz, dz) or dz == 0:
            raise WireError("bad_shape", f"R must be square and non-empty, got {self.R.shape}")
        if self.z.shape[1] != dz:
            raise WireError("bad_shape", f"z is {self.z.shape} but R is {self.R.shape}")
        if self.target_ids is not None and len(self.target_ids) != self.z.shape[0]:
            raise WireError(
                "bad_shape", f"{len(self.target_ids)} target ids for {self.z.shape[0]} rows of z"
            )
        if self.platform is not None and self.platform.shape != (4,):
            raise WireError("bad_shape", f"platform must be (4,), got {self.platform.shape}")


@dataclass(frozen=True, slots=True, eq=False)
class Track(_Message):
    """The fused estimate ``N(x, P)`` for scan ``scan`` at time ``t`` [s]: ``x`` ``(n,)``,
    ``P`` ``(n, n)``.  ``target_id`` (optional): the target of this track when there are
    several (mobile scenarios: one Track per target and scan).  ``node_id`` (optional, peer
    mode): the peer node whose own fused estimate this is.  ``state`` (optional,
    surveillance): the manager's track's state, ``tentative``, ``confirmed`` or ``deleted``
    (deleted at this scan: its last estimate)."""

    KIND: ClassVar[str] = "track"
    scan: Count
    t: Float
    x: Vec
    P: Mat
    t_sent_ns: Stamp
    episode: Count = 0
    target_id: Name | None = None
    node_id: Name | None = None
    state: Name | None = None

    def _check(self) -> None:
        n = self.x.shape[0]
        if n == 0 or self.P.shape != (n, n):
            raise WireError("bad_shape", f"x is {self.x.shape} but P is {self.P.shape}")


@dataclass(frozen=True, slots=True, eq=False)
class Status(_Message):
    """The manager's per-scan summary: the allocation (``enabled``), the sensors whose
    measurements were fused (``fused``), those seen failed when allocating (``failed``),
    ``tr P`` of the fused covariance, ``tr Pd`` of the desired one, and the allocation
    objective ``value``.  ``episode`` (here and in Command, Measurement, Track) numbers the
    metric episodes of one run (one per allocation metric).  ``node_id`` (optional, peer mode):
    the peer node reporting (each node decides and fuses for itself).  ``refiltered`` (optional,
    slow links): the late messages, ``"<sensor>:<scan>"``, re-filtered into their past scans
    while this scan was collected (so that a replay re-filters the same ones).  ``cells``
    (optional, surveillance): the search cells' undetected mass ``u_c`` after the scan."""

    KIND: ClassVar[str] = "status"
    scan: Count
    t: Float
    enabled: Names
    trace_P: Float
    trace_Pd: Float
    value: Float
    t_sent_ns: Stamp
    episode: Count = 0
    fused: Names = ()
    failed: Names = ()
    node_id: Name | None = None
    refiltered: Names | None = None
    cells: Vec | None = None


@dataclass(frozen=True, slots=True, eq=False)
class LocalTrack(_Message):
    """Decentralized modes: sensor ``sensor_id``'s local-filter track for scan ``scan`` (time
    ``t`` [s]), published instead of its measurement at a scan it was enabled: the posterior
    ``N(x, P)`` and the local filter's own prediction ``N(x_prior, P_prior)`` for that scan (the
    information-matrix fusion removes it; see :mod:`covnet.core.fusion`).  ``seq`` as in
    :class:`Measurement`; ``target_id`` (optional, many targets): the target the track is of
    (the one the sensor dwelt on)."""

    KIND: ClassVar[str] = "ltrack"
    sensor_id: Name
    scan: Count
    t: Float
    x: Vec
    P: Mat
    x_prior: Vec
    P_prior: Mat
    t_sent_ns: Stamp
    episode: Count = 0
    seq: Count | None = None
    target_id: Name | None = None

    def _check(self) -> None:
        n = self.x.shape[0]
        if n == 0 or self.P.shape != (n, n):
            raise WireError("bad_shape", f"x is {self.x.shape} but P is {self.P.shape}")
        if self.x_prior.shape != (n,) or self.P_prior.shape != (n, n):
            raise WireError(
                "bad_shape",
                f"x_prior is {self.x_prior.shape}, P_prior {self.P_prior.shape}; expected "
                f"({n},) and ({n}, {n})",
            )


@dataclass(frozen=True, slots=True, eq=False)
class Heartbeat(_Message):
    """A node's application-level heartbeat: the last scan it handled (a hung loop stops
    sending these although its zenoh session still keeps its liveliness token alive), and
    optionally its running count of rejected messages by reason (so the manager's
    ``network.json`` can report every node's rejections).  A sensor's also carry ``sent``, how
    many messages it has sent for the manager (the ``seq`` of its last one), and it sends one
    more as it leaves: so the manager knows of the last ones too when they are lost.
    ``config``: the identity of the config the node runs
    (:func:`covnet.processes.node_kit.config_id`), which the manager compares with its own
    before the run starts (hosts given one ``--run`` but different configs or run options
    were mixed without a word); ``host``: its host's identity
    (:func:`covnet.processes.node_kit.host_id`: the boot, whose monotonic clock its stamps
    read), so that one-way latencies are taken only between nodes of one clock."""

    KIND: ClassVar[str] = "hb"
    role: Name
    node_id: Name
    scan: Count
    t_sent_ns: Stamp
    rejected: Counts | None = None
    sent: Count | None = None
    config: Name | None = None
    host: Name | None = None


Message = Truth | Command | Measurement | Track | Status | Heartbeat | LocalTrack
MESSAGE_TYPES: tuple[type[Message], ...] = (
    Truth,
    Command,
    Measurement,
    Track,
    Status,
    Heartbeat,
    LocalTrack,
)
_BY_KIND: dict[str, type[Message]] = {cls.KIND: cls for cls in MESSAGE_TYPES}


# --------------------------------------------------------------------------------------------
# the payload size cap, from the schemas
# --------------------------------------------------------------------------------------------


def payload_bounds(
    sensors: int,
    targets: int,
    rows: int,
    state_dim: int = CAP_STATE_DIM,
    meas_dim: int = CAP_MEAS_DIM,
) -> dict[str, int]:
    """Per message kind, an upper bound in bytes on the encoding of any message of that kind a
    run with ``sensors`` sensors and ``targets`` targets sends (a measurement list of at most
    ``rows`` rows, states of ``state_dim``, measurements of ``meas_dim``, every id at
    :data:`MAX_NAME_LEN` ASCII characters), summed field by field over the schema (each class's
    field kinds, so a new scalar or id field is counted by itself; a new list, map or array
    field needs its size below, or this raises ``KeyError`` at import).

    msgpack sizes used: an int or a float64 at most 9 bytes; a field name 1 + its length; an id
    2 + :data:`MAX_NAME_LEN`; an array or map header at most 5; an ndarray (the ext type) at
    most 27 + 8 per element (ext32 header 6, inner ``[dtype, shape, bin]`` 21); the map header
    with ``"v"`` and ``"k"`` 8 + the kind's length.  Sizes: Truth ``target_ids`` M, ``states``
    M x n, ``sensor_ids`` N, ``platforms`` N x 4; Command ``enabled`` N, ``modes`` N pairs,
    ``targets`` N keys and M target ids in all (a target goes to one sensor), ``windows`` N
    vectors of 2 dz; Measurement ``z``
    rows x dz, ``R`` dz x dz, ``target_ids`` rows, ``platform`` 4; Status ``enabled``,
    ``fused``, ``failed`` N each, ``refiltered`` :data:`MAX_IDS`, ``cells`` :data:`CAP_CELLS`;
    Track and LocalTrack n and
    n x n; Heartbeat :data:`CAP_REASONS` reasons (``tests/unit/test_size_cap.py`` encodes
    each kind's largest message and checks the bound and its tightness)."""
    n, dz = state_dim, meas_dim
    size: dict[tuple[str, str], Any] = {
        ("truth", "target_ids"): targets,
        ("truth", "states"): targets * n,
        ("truth", "sensor_ids"): sensors,
        ("truth", "platforms"): 4 * sensors,
        ("cmd", "enabled"): sensors,
        ("cmd", "modes"): sensors,
        ("cmd", "targets"): (sensors, targets),
        ("cmd", "windows"): (sensors, 2 * dz),
        ("meas", "z"): rows * dz,
        ("meas", "R"): dz * dz,
        ("meas", "target_ids"): rows,
        ("meas", "platform"): 4,
        ("track", "x"): n,
        ("track", "P"): n * n,
        ("status", "enabled"): sensors,
        ("status", "fused"): sensors,
        ("status", "failed"): sensors,
        ("status", "refiltered"): MAX_IDS,
        ("status", "cells"): CAP_CELLS,
        ("ltrack", "x"): n,
        ("ltrack", "P"): n * n,
        ("ltrack", "x_prior"): n,
        ("ltrack", "P_prior"): n * n,
        ("hb", "rejected"): CAP_REASONS,
    }
    name, num, head = 2 + MAX_NAME_LEN, 9, 5

    def value(kind: str, field_name: str, field_kind: str) -> int:
        if field_kind in ("count", "stamp", "float"):
            return num
        if field_kind == "name":
            return name
        k = size[(kind, field_name)]
        if field_kind == "names":
            return head + name * k
        if field_kind in ("vec", "mat"):
            return 27 + 8 * k
        if field_kind == "modes":
            return head + 2 * name * k
        if field_kind == "counts":
            return head + (name + num) * k
        if field_kind == "targets":
            holders, held = k
            return head + (name + head) * holders + name * held
        if field_kind == "vecs":
            holders, length = k
            return head + (name + 27 + 8 * length) * holders
        raise KeyError(field_kind)

    return {
        cls.KIND: 8
        + len(cls.KIND)
        + sum(1 + len(f) + value(cls.KIND, f, fk) for f, fk in _spec(cls).kinds.items())
        for cls in MESSAGE_TYPES
    }


def largest_payload(
    sensors: int,
    targets: int,
    rows: int,
    state_dim: int = CAP_STATE_DIM,
    meas_dim: int = CAP_MEAS_DIM,
) -> int:
    """The largest of :func:`payload_bounds`: no message of such a run is longer."""
    return max(payload_bounds(sensors, targets, rows, state_dim, meas_dim).values())


MAX_PAYLOAD_BYTES = 1 << (2 * largest_payload(CAP_SENSORS, CAP_TARGETS, CAP_ROWS) - 1).bit_length()
"""THE payload size cap (1 MiB): the smallest power of two at least twice
:func:`largest_payload` of a network of :data:`CAP_SENSORS` sensors and :data:`CAP_TARGETS`
targets (~0.49 MB: a Command with modes, targets and clutter windows for 1024 sensors; the
largest Status, naming 3 x 1024 sensors and 4096 re-filtered messages, Truth and Measurement
are ~0.47, ~0.22 and ~0.09 MB).  A bus drops a payload
over it before copying it (:mod:`covnet.wire.bus`, :mod:`covnet.wire.zenoh_bus`: counted
``oversize``),
and :func:`covnet.wire.codec.decode` refuses one (``too_large``)."""
