"""THE wire schema of covnet: every message that crosses a process boundary, and every key.

Nothing else in covnet formats a key expression or packs a payload.

Encoding
--------
A message is a msgpack map ``{"v": SCHEMA_VERSION, "k": KIND, <field>: <value>, ...}`` with the
fields in declaration order. Floats are msgpack float64, ints are msgpack ints, id tuples are
msgpack arrays of str. A numpy array is an ``ExtType(1, packb(["<f8", [d0, d1, ...], raw]))``:
little-endian float64, C order (one ``default=`` hook, one ``ext_hook=``). Optional fields whose
value is ``None`` are omitted, so adding an optional field later does not change the bytes of
messages that do not use it (the golden-bytes test in ``tests/wire`` pins the format).
``episode`` (Command, Measurement, Track, Status; default 0 when building) numbers the
manager's episodes (one per allocation metric) so that scans of two episodes never mix; it is
always sent, and a payload without it is ``missing_field``.

Decoding is strict
------------------
:func:`decode` / :func:`decode_as` accept exactly what :func:`encode` produces and raise
:class:`WireError` (never anything else) on any other input. ``WireError.reason`` is one of
:data:`REASONS`:

============== ============================================================================
reason         meaning
============== ============================================================================
not_msgpack    not valid msgpack, or trailing bytes after the first object
truncated      valid msgpack prefix that ends early
too_large      payload, string, array or id list over the caps below
not_a_map      the top-level object is not a map
bad_version    ``"v"`` absent, not an int, or not :data:`SCHEMA_VERSION`
unknown_kind   ``"k"`` is not a known message kind
wrong_kind     ``decode_as(payload, cls)`` got another (known or unknown) kind
missing_field  a required field (or ``"k"``) is absent
unknown_field  a key the message kind does not define (strict: no silent extras)
bad_type       a value of the wrong type: ints are ints (not bools, not floats), floats are
               floats (not ints), strings are str, arrays are the float64 ext type
bad_shape      wrong array rank, or inconsistent shapes (z vs R, x vs P, states vs ids)
non_finite     NaN or infinity in a float field or an array
bad_value      out of bounds (negative scan or stamp) or an invalid / duplicated id
key_mismatch   the key does not name what the payload says (:func:`decode_command`: a
               command's enabled set)
============== ============================================================================

Constructing a message validates it the same way (raising the same :class:`WireError`), so an
invalid message can never be encoded; constructors are lenient only in *converting* values
(ints and numpy scalars to float for float fields, sequences to tuples, array-likes to
float64 arrays). Arrays held by messages are read-only.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar, TypeVar

import msgpack
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "CAP_MEAS_DIM",
    "CAP_REASONS",
    "CAP_ROWS",
    "CAP_SENSORS",
    "CAP_STATE_DIM",
    "CAP_TARGETS",
    "MAX_ARRAY_ELEMENTS",
    "MAX_IDS",
    "MAX_NAME_LEN",
    "MANAGER_ID",
    "MAX_PAYLOAD_BYTES",
    "MESSAGE_TYPES",
    "RECORDER_ID",
    "RESERVED_IDS",
    "REASONS",
    "SCHEMA_VERSION",
    "TRUTH_UPFRONT_MAX_SCANS",
    "Command",
    "Heartbeat",
    "LocalTrack",
    "Measurement",
    "Message",
    "Status",
    "Track",
    "Truth",
    "WORLD_ID",
    "WireError",
    "alive_key",
    "alive_keyexpr",
    "command_key",
    "command_keyexpr",
    "decode",
    "decode_as",
    "decode_command",
    "encode",
    "heartbeat_key",
    "heartbeat_keyexpr",
    "largest_payload",
    "measurement_key",
    "measurement_keyexpr",
    "new_run_id",
    "parse_alive_key",
    "parse_command_key",
    "parse_measurement_key",
    "parse_peer_key",
    "payload_bounds",
    "peer_keyexpr",
    "peer_status_key",
    "peer_track_key",
    "run_keyexpr",
    "status_key",
    "track_key",
    "truth_key",
]

SCHEMA_VERSION = 1

MAX_ARRAY_ELEMENTS = 1 << 20
"""Largest number of elements in one array (8 MiB of float64)."""
MAX_IDS = 4096
"""Longest id tuple (``target_ids``, ``enabled``) and largest ``modes`` map."""
MAX_NAME_LEN = 64
"""Longest id (run, role, node, sensor, target) and ``modes`` value."""

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

_EXT_NDARRAY = 1
_WIRE_DTYPE = "<f8"
_MAX_NDIM = 2
_MAX_STR_LEN = 1024  # any msgpack str; ids over MAX_NAME_LEN are then bad_value
_MAX_MAP_LEN = MAX_IDS + 16
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
# ids and key expressions
# --------------------------------------------------------------------------------------------

_BAD_NAME = re.compile(r"[/*$?#\s]")


def _name_problem(value: object) -> str | None:
    """Why ``value`` cannot be an id / key chunk, or None when it can."""
    if not isinstance(value, str):
        return f"must be a str, got {type(value).__name__}"
    if not value:
        return "must be non-empty"
    if len(value) > MAX_NAME_LEN:
        return f"longer than {MAX_NAME_LEN} characters"
    if _BAD_NAME.search(value) or not value.isprintable():
        return "must not contain '/', '*', '$', '?', '#', whitespace or control characters"
    return None


def _valid(value: object, what: str) -> str:
    problem = _name_problem(value)
    if problem is not None:
        raise ValueError(f"invalid {what} {value!r}: {problem}")
    assert isinstance(value, str)
    return value


MANAGER_ID, WORLD_ID, RECORDER_ID = "manager", "world", "recorder"
"""Node ids of the processes that are not sensors (each is also its role's name)."""
RESERVED_IDS = (MANAGER_ID, WORLD_ID, RECORDER_ID)
"""A sensor may not use one of these ids when security is on (they are zenoh identities)."""


def new_run_id() -> str:
    """A short unique run id (12 hex digits), valid as a key chunk."""
    import uuid  # start-up: only where a run id is made

    return uuid.uuid4().hex[:12]


#: a run of at most this many scans gets the truth of every scan at once (the world then hears
#: no command, and sensors keep it for the whole run); a longer one gets it window by window,
#: paced by the commands (:mod:`world.covariance`)
TRUTH_UPFRONT_MAX_SCANS = 5000


def _root(run: str) -> str:
    return f"covnet/{_valid(run, 'run id')}"


def run_keyexpr(run: str) -> str:
    """``covnet/<run>/**``: every publication of one run (what the recorder subscribes to)."""
    return f"{_root(run)}/**"


def truth_key(run: str) -> str:
    """``covnet/<run>/truth``: ground truth, one :class:`Truth` per scan (world -> sensors)."""
    return f"{_root(run)}/truth"


_CMD_SEP = "~"  # never in an id (see _BAD_NAME's ids: config ids are [A-Za-z0-9_.-])


def command_key(run: str, enabled: Iterable[str]) -> str:
    """``covnet/<run>/cmd/~S1~S3~``: the key of the :class:`Command` that enables
    ``enabled`` (in the command's order; ``covnet/<run>/cmd/~`` when it enables none).  One
    put per scan, and zenoh routes it by its key: to the sensors it enables
    (:func:`command_keyexpr` ``(run, id)``) and to whoever hears every command, never to a
    disabled sensor, which is then not even woken (manager -> sensors, recorder)."""
    ids = [_valid(sid, "sensor id") for sid in enabled]
    if any(_CMD_SEP in sid for sid in ids):
        raise ValueError(f"invalid sensor id in {ids!r}: must not contain {_CMD_SEP!r}")
    return f"{_root(run)}/cmd/{_enabled_chunk(ids)}"


def _enabled_chunk(ids: Iterable[str]) -> str:
    """The last chunk of a command key: ``~S1~S3~`` (``~`` for none)."""
    return _CMD_SEP + "".join(sid + _CMD_SEP for sid in ids)


def command_keyexpr(run: str, sensor_id: str | None = None) -> str:
    """Commands: those that enable ``sensor_id`` (``covnet/<run>/cmd/$*~<id>~$*``, zenoh's
    sub-chunk wildcard), or every one (``covnet/<run>/cmd/*``: the recorder, a world that
    paces the truth by the commands, a sensor on slow links, which must see every command to
    notice one it missed)."""
    if sensor_id is None:
        return f"{_root(run)}/cmd/*"
    return f"{_root(run)}/cmd/$*{_CMD_SEP}{_valid(sensor_id, 'sensor id')}{_CMD_SEP}$*"


def parse_command_key(key: str) -> tuple[str, ...]:
    """The enabled ids a concrete command key names; ValueError for any other key."""
    parts = key.split("/")
    if len(parts) != 4 or parts[0] != "covnet" or parts[2] != "cmd":
        raise ValueError(f"not a command key: {key!r}")
    _valid(parts[1], "run id")
    chunk = parts[3]
    if len(chunk) < 1 or chunk[0] != _CMD_SEP or chunk[-1] != _CMD_SEP:
        raise ValueError(f"not a command key: {key!r}")
    if chunk == _CMD_SEP:
        return ()
    return tuple(_valid(sid, "sensor id") for sid in chunk[1:-1].split(_CMD_SEP))


def measurement_key(run: str, sensor_id: str) -> str:
    """``covnet/<run>/sensor/<id>/meas``: one sensor's :class:`Measurement` s."""
    return f"{_root(run)}/sensor/{_valid(sensor_id, 'sensor id')}/meas"


def measurement_keyexpr(run: str) -> str:
    """``covnet/<run>/sensor/*/meas``: every sensor's measurements."""
    return f"{_root(run)}/sensor/*/meas"


def parse_measurement_key(key: str) -> str:
    """The sensor id of a concrete measurement key (to check it against the payload's)."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != "covnet" or parts[2] != "sensor" or parts[4] != "meas":
        raise ValueError(f"not a measurement key: {key!r}")
    _valid(parts[1], "run id")
    return _valid(parts[3], "sensor id")


def peer_track_key(run: str, node_id: str) -> str:
    """``covnet/<run>/peer/<id>/track``: a peer node's own fused :class:`Track` (peer mode)."""
    return f"{_root(run)}/peer/{_valid(node_id, 'node id')}/track"


def peer_status_key(run: str, node_id: str) -> str:
    """``covnet/<run>/peer/<id>/status``: a peer node's :class:`Status` per scan (peer mode):
    the enabled set it decided, the tracks it fused, the members it excluded."""
    return f"{_root(run)}/peer/{_valid(node_id, 'node id')}/status"


def peer_keyexpr(run: str, what: str = "*") -> str:
    """``covnet/<run>/peer/*/<what>``: every peer node's tracks or statuses (or both: ``*``)."""
    return f"{_root(run)}/peer/*/{what}"


def parse_peer_key(key: str) -> tuple[str, str]:
    """``(node_id, "track" | "status")`` of a concrete peer key; ValueError for anything else."""
    parts = key.split("/")
    if (
        len(parts) != 5
        or parts[0] != "covnet"
        or parts[2] != "peer"
        or parts[4] not in ("track", "status")
    ):
        raise ValueError(f"not a peer key: {key!r}")
    _valid(parts[1], "run id")
    return _valid(parts[3], "node id"), parts[4]


def track_key(run: str) -> str:
    """``covnet/<run>/track``: the fused :class:`Track` per scan (manager)."""
    return f"{_root(run)}/track"


def status_key(run: str) -> str:
    """``covnet/<run>/manager/status``: the manager's :class:`Status` per scan."""
    return f"{_root(run)}/manager/status"


def heartbeat_key(run: str, role: str, node_id: str) -> str:
    """``covnet/<run>/hb/<role>/<id>``: a node's :class:`Heartbeat` (last scan it handled)."""
    return f"{_root(run)}/hb/{_valid(role, 'role')}/{_valid(node_id, 'node id')}"


def heartbeat_keyexpr(run: str) -> str:
    """``covnet/<run>/hb/*/*``: every node's heartbeats."""
    return f"{_root(run)}/hb/*/*"


def alive_key(run: str, role: str, node_id: str) -> str:
    """``covnet/<run>/alive/<role>/<id>``: a node's liveliness token."""
    return f"{_root(run)}/alive/{_valid(role, 'role')}/{_valid(node_id, 'node id')}"


def alive_keyexpr(run: str, role: str | None = None) -> str:
    """``covnet/<run>/alive/<role>/*`` (or ``alive/*/*`` for every role): liveliness tokens."""
    return f"{_root(run)}/alive/{'*' if role is None else _valid(role, 'role')}/*"


def parse_alive_key(key: str) -> tuple[str, str]:
    """``(role, node_id)`` of a concrete liveliness key; ValueError for anything else."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != "covnet" or parts[2] != "alive":
        raise ValueError(f"not a liveliness key: {key!r}")
    _valid(parts[1], "run id")
    return _valid(parts[3], "role"), _valid(parts[4], "node id")


# --------------------------------------------------------------------------------------------
# field kinds: one coercion/validation routine per kind, strict (decode) or lenient (build)
# --------------------------------------------------------------------------------------------

# kinds: "count" int >= 0; "stamp" int ns >= 0; "float" finite float; "name" id str;
# "names" tuple of unique ids; "vec"/"mat" float64 1-D/2-D finite array; "modes" dict id->id;
# "counts" dict id->count; "targets" dict id->tuple of unique ids; "vecs" dict id->float64 1-D
# finite array.


def _is_int(v: object, strict: bool) -> bool:
    if strict:
        return type(v) is int
    return isinstance(v, int | np.integer) and not isinstance(v, bool | np.bool_)


# Ids already found valid (see _name_problem): most messages repeat the same few, and checking
# one costs a regex search.  Bounded: once full, new ids are checked every time.
_GOOD_NAMES: set[str] = set()
_GOOD_NAMES_MAX = 4096


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
        if (
            kind == "names"
            and len(v) <= MAX_IDS  # type: ignore[arg-type]
            and _GOOD_NAMES.issuperset(v)  # type: ignore[arg-type]
            and (strict or all(type(x) is str for x in v))  # type: ignore[attr-defined]
        ):
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
    if not np.isfinite(a).all():
        raise WireError("non_finite", f"{name} has NaN or inf")
    return a


# --------------------------------------------------------------------------------------------
# messages
# --------------------------------------------------------------------------------------------


_OPTIONAL: dict[type, frozenset[str]] = {}


def _optional_fields(cls: type) -> frozenset[str]:
    """Fields that default to None: omitted from the wire when unset."""
    opt = _OPTIONAL.get(cls)
    if opt is None:
        opt = _OPTIONAL[cls] = frozenset(f.name for f in fields(cls) if f.default is None)
    return opt


class _Message:
    """Base of every message: field validation, and value equality (arrays compared exactly)."""

    __slots__ = ()
    KIND: ClassVar[str]
    _KINDS: ClassVar[dict[str, str]]  # field name -> kind, in wire order

    def __post_init__(self) -> None:
        optional = _optional_fields(type(self))
        for name, kind in self._KINDS.items():
            value = getattr(self, name)
            if value is None and name in optional:
                continue  # an optional field left unset (never sent)
            object.__setattr__(self, name, _coerce(kind, name, value, strict=False))
        self._check()

    def _check(self) -> None:
        """Cross-field consistency (shapes); overridden where there is some."""

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for n in self._KINDS:
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
    _KINDS: ClassVar[dict[str, str]] = {
        "scan": "count",
        "t": "float",
        "target_ids": "names",
        "states": "mat",
        "sensor_ids": "names",
        "platforms": "mat",
    }
    scan: int
    t: float
    target_ids: tuple[str, ...]
    states: NDArray[np.float64]
    sensor_ids: tuple[str, ...] | None = None
    platforms: NDArray[np.float64] | None = None

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
    _KINDS: ClassVar[dict[str, str]] = {
        "scan": "count",
        "t": "float",
        "enabled": "names",
        "t_sent_ns": "stamp",
        "episode": "count",
        "modes": "modes",
        "targets": "targets",
        "windows": "vecs",
    }
    scan: int
    t: float
    enabled: tuple[str, ...]
    t_sent_ns: int
    episode: int = 0
    modes: dict[str, str] | None = None
    targets: dict[str, tuple[str, ...]] | None = None
    windows: dict[str, NDArray[np.float64]] | None = None

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
    _KINDS: ClassVar[dict[str, str]] = {
        "sensor_id": "name",
        "scan": "count",
        "t": "float",
        "z": "mat",
        "R": "mat",
        "t_sent_ns": "stamp",
        "episode": "count",
        "target_ids": "names",
        "platform": "vec",
        "seq": "count",
    }
    sensor_id: str
    scan: int
    t: float
    z: NDArray[np.float64]
    R: NDArray[np.float64]
    t_sent_ns: int
    episode: int = 0
    target_ids: tuple[str, ...] | None = None
    platform: NDArray[np.float64] | None = None
    seq: int | None = None

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
    mode): the peer node whose own fused estimate this is."""

    KIND: ClassVar[str] = "track"
    _KINDS: ClassVar[dict[str, str]] = {
        "scan": "count",
        "t": "float",
        "x": "vec",
        "P": "mat",
        "t_sent_ns": "stamp",
        "episode": "count",
        "target_id": "name",
        "node_id": "name",
    }
    scan: int
    t: float
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    t_sent_ns: int
    episode: int = 0
    target_id: str | None = None
    node_id: str | None = None

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
    while this scan was collected (so that a replay re-filters the same ones)."""

    KIND: ClassVar[str] = "status"
    _KINDS: ClassVar[dict[str, str]] = {
        "scan": "count",
        "t": "float",
        "enabled": "names",
        "trace_P": "float",
        "trace_Pd": "float",
        "value": "float",
        "t_sent_ns": "stamp",
        "episode": "count",
        "fused": "names",
        "failed": "names",
        "node_id": "name",
        "refiltered": "names",
    }
    scan: int
    t: float
    enabled: tuple[str, ...]
    trace_P: float
    trace_Pd: float
    value: float
    t_sent_ns: int
    episode: int = 0
    fused: tuple[str, ...] = ()
    failed: tuple[str, ...] = ()
    node_id: str | None = None
    refiltered: tuple[str, ...] | None = None


@dataclass(frozen=True, slots=True, eq=False)
class LocalTrack(_Message):
    """Decentralized modes: sensor ``sensor_id``'s local-filter track for scan ``scan`` (time
    ``t`` [s]), published instead of its measurement at a scan it was enabled: the posterior
    ``N(x, P)`` and the local filter's own prediction ``N(x_prior, P_prior)`` for that scan (the
    information-matrix fusion removes it; see :mod:`covnet.core.fusion`).  ``seq`` as in
    :class:`Measurement`; ``target_id`` (optional, many targets): the target the track is of
    (the one the sensor dwelt on)."""

    KIND: ClassVar[str] = "ltrack"
    _KINDS: ClassVar[dict[str, str]] = {
        "sensor_id": "name",
        "scan": "count",
        "t": "float",
        "x": "vec",
        "P": "mat",
        "x_prior": "vec",
        "P_prior": "mat",
        "t_sent_ns": "stamp",
        "episode": "count",
        "seq": "count",
        "target_id": "name",
    }
    sensor_id: str
    scan: int
    t: float
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    x_prior: NDArray[np.float64]
    P_prior: NDArray[np.float64]
    t_sent_ns: int
    episode: int = 0
    seq: int | None = None
    target_id: str | None = None

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
    more as it leaves: so the manager knows of the last ones too when they are lost."""

    KIND: ClassVar[str] = "hb"
    _KINDS: ClassVar[dict[str, str]] = {
        "role": "name",
        "node_id": "name",
        "scan": "count",
        "t_sent_ns": "stamp",
        "rejected": "counts",
        "sent": "count",
    }
    role: str
    node_id: str
    scan: int
    t_sent_ns: int
    rejected: dict[str, int] | None = None
    sent: int | None = None


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
    ``fused``, ``failed`` N each, ``refiltered`` :data:`MAX_IDS`; Track and LocalTrack n and
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
        + sum(1 + len(f) + value(cls.KIND, f, fk) for f, fk in cls._KINDS.items())
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
over it before copying it (:mod:`covnet.bus`, :mod:`covnet.zenoh_bus`: counted ``oversize``),
and :func:`decode` refuses one (``too_large``)."""
_M = TypeVar("_M", bound=_Message)


# --------------------------------------------------------------------------------------------
# encode / decode
# --------------------------------------------------------------------------------------------


def _default(obj: object) -> msgpack.ExtType:
    if isinstance(obj, np.ndarray) and obj.dtype == np.float64:
        a = np.ascontiguousarray(obj, dtype=_WIRE_DTYPE)
        inner = msgpack.packb([_WIRE_DTYPE, list(a.shape), a.tobytes()], use_bin_type=True)
        return msgpack.ExtType(_EXT_NDARRAY, inner)
    raise TypeError(f"cannot encode {type(obj).__name__}")


def encode(msg: Message) -> bytes:
    """``msg`` as msgpack bytes: ``{"v": SCHEMA_VERSION, "k": KIND, ...fields}``."""
    if not isinstance(msg, _Message):
        raise TypeError(f"not a message: {type(msg).__name__}")
    d: dict[str, object] = {"v": SCHEMA_VERSION, "k": msg.KIND}
    for name, _, _ in _spec(type(msg)).fields:
        value = getattr(msg, name)
        if value is None:  # optional and unset: omitted
            continue
        d[name] = value
    return msgpack.packb(d, default=_default, use_bin_type=True)


_INNER_LIMITS: dict[str, Any] = {
    "raw": False,
    "use_list": True,
    "strict_map_key": True,
    "max_str_len": 16,
    "max_bin_len": MAX_PAYLOAD_BYTES,  # no bin is longer than the payload it is in
    "max_array_len": _MAX_NDIM + 1,
    "max_map_len": 0,
    "max_ext_len": 0,
}
_F8 = np.dtype(_WIRE_DTYPE)
_F8_NATIVE = _F8 == np.dtype(np.float64)


def _ext_hook(code: int, data: bytes) -> NDArray[np.float64]:
    if code != _EXT_NDARRAY:
        raise WireError("bad_type", f"unknown ext type {code}")
    try:
        inner = msgpack.unpackb(data, **_INNER_LIMITS)
    except Exception as e:  # any malformed inner payload
        raise WireError("bad_type", f"array ext: {type(e).__name__}") from None
    if type(inner) is not list or len(inner) != 3:
        raise WireError("bad_type", "array ext must be [dtype, shape, bytes]")
    dtype, shape, raw = inner
    if dtype != _WIRE_DTYPE:
        raise WireError("bad_type", f"array dtype must be {_WIRE_DTYPE!r}, got {dtype!r}")
    if (
        type(shape) is not list
        or not 1 <= len(shape) <= _MAX_NDIM
        or not all(type(s) is int and s >= 0 for s in shape)
    ):
        raise WireError("bad_shape", f"array shape {shape!r}")
    if type(raw) is not bytes:
        raise WireError("bad_type", "array data must be bin")
    size = shape[0] if len(shape) == 1 else shape[0] * shape[1]
    if size > MAX_ARRAY_ELEMENTS:
        raise WireError("too_large", f"array of {size} elements > {MAX_ARRAY_ELEMENTS}")
    if len(raw) != 8 * size:
        raise WireError("bad_shape", f"array shape {shape} needs {8 * size} bytes, got {len(raw)}")
    a = np.frombuffer(raw, dtype=_F8).reshape(shape)  # read-only view of the payload
    return a if _F8_NATIVE else a.astype(np.float64)


def _unpack(payload: bytes) -> dict[str, Any]:
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise TypeError(f"payload must be bytes, got {type(payload).__name__}")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise WireError("too_large", f"payload of {len(payload)} bytes > {MAX_PAYLOAD_BYTES}")
    # One call for a well-formed payload; anything msgpack rejects is judged again by the
    # streaming unpacker below, which tells the reasons apart (same limits, same result).
    try:
        obj = msgpack.unpackb(payload, **_UNPACK_LIMITS)
    except WireError:
        raise
    except Exception:
        obj = _unpack_stream(payload)
    return _check_top(obj)


_UNPACK_LIMITS: dict[str, Any] = {
    "raw": False,
    "use_list": True,
    "strict_map_key": True,
    "ext_hook": _ext_hook,
    "max_str_len": _MAX_STR_LEN,
    "max_bin_len": MAX_PAYLOAD_BYTES,  # bin is only valid inside the array ext: bad_type
    "max_array_len": MAX_IDS,
    "max_map_len": _MAX_MAP_LEN,
    "max_ext_len": MAX_PAYLOAD_BYTES,
}


def _unpack_stream(payload: bytes) -> Any:
    unpacker = msgpack.Unpacker(max_buffer_size=max(MAX_PAYLOAD_BYTES, 1), **_UNPACK_LIMITS)
    unpacker.feed(payload)
    try:
        obj = unpacker.unpack()
    except WireError:
        raise
    except msgpack.OutOfData:
        raise WireError("truncated" if len(payload) else "not_msgpack", "incomplete") from None
    except Exception as e:  # msgpack raises ValueError, FormatError, StackError, Unicode...
        text = str(e)  # msgpack signals limits and map-key types by ValueError messages
        if "exceeds max_" in text:
            reason = "too_large"
        elif "for map key" in text:
            reason = "bad_type"
        else:
            reason = "not_msgpack"
        raise WireError(reason, f"{type(e).__name__}: {e}") from None
    try:
        unpacker.unpack()
    except msgpack.OutOfData:
        pass
    except Exception:  # anything after the first object is trailing garbage
        raise WireError("not_msgpack", "trailing bytes after the message") from None
    else:
        raise WireError("not_msgpack", "trailing bytes after the message")
    return obj


def _check_top(obj: Any) -> dict[str, Any]:
    if type(obj) is not dict:
        raise WireError("not_a_map", f"top level is {type(obj).__name__}")
    for key in obj:
        if type(key) is not str:
            raise WireError("bad_type", f"map key {key!r} is not a str")
    version = obj.get("v")
    if type(version) is not int or version != SCHEMA_VERSION:
        raise WireError("bad_version", f"v={version!r}, expected {SCHEMA_VERSION}")
    if "k" not in obj:
        raise WireError("missing_field", "k")
    return obj


_OMITTED = object()


@dataclass(frozen=True)
class _Spec:
    """A message class's fields in declaration order as ``(name, kind, optional)``, and the
    map keys its payload may hold."""

    fields: tuple[tuple[str, str, bool], ...]
    keys: frozenset[str]


_SPECS: dict[type, _Spec] = {}


def _spec(cls: type) -> _Spec:
    spec = _SPECS.get(cls)
    if spec is None:
        kinds = cls._KINDS  # type: ignore[attr-defined]
        spec = _SPECS[cls] = _Spec(
            tuple((f.name, kinds[f.name], f.default is None) for f in fields(cls)),
            frozenset(kinds) | {"v", "k"},
        )
    return spec


def _build(cls: type[_M], obj: dict[str, Any]) -> _M:
    spec = _spec(cls)
    if not spec.keys.issuperset(obj):
        extra = sorted(set(obj) - spec.keys)
        raise WireError("unknown_field", f"{cls.KIND}: {', '.join(extra)}")
    msg = object.__new__(cls)
    setattr_ = object.__setattr__
    get = obj.get
    for name, kind, optional in spec.fields:
        value = get(name, _OMITTED)
        if value is _OMITTED:
            if not optional:  # only optional fields (default None) may be omitted
                raise WireError("missing_field", f"{cls.KIND}.{name}")
            setattr_(msg, name, None)
        else:
            setattr_(msg, name, _coerce(kind, name, value, True))
    msg._check()
    return msg


def decode(payload: bytes) -> Message:
    """Decode any message kind; raises :class:`WireError` (and nothing else) on bad bytes."""
    obj = _unpack(payload)
    kind = obj["k"]
    cls = _BY_KIND.get(kind) if type(kind) is str else None
    if cls is None:
        raise WireError("unknown_kind", f"k={kind!r}")
    return _build(cls, obj)


def decode_as(payload: bytes, cls: type[_M]) -> _M:
    """Decode a payload from a key that admits only ``cls``; another kind is ``wrong_kind``."""
    obj = _unpack(payload)
    kind = obj["k"]
    if type(kind) is not str or kind != cls.KIND:
        raise WireError("wrong_kind", f"expected {cls.KIND!r}, got {kind!r}")
    return _build(cls, obj)


def decode_command(key: str, payload: bytes) -> Command:
    """A :class:`Command` from ``payload`` received on ``key``, strictly: ``key_mismatch``
    unless ``key`` is :func:`command_key` of its run and the command's enabled set (compared
    as strings: the decoded ids are valid already, and this runs for every command)."""
    cmd = decode_as(payload, Command)
    head, _, chunk = key.rpartition("/")
    root, _, cmd_chunk = head.rpartition("/")
    if (
        cmd_chunk != "cmd"
        or root.count("/") != 1
        or not root.startswith("covnet/")
        or chunk != _enabled_chunk(cmd.enabled)
        or any(_CMD_SEP in sid for sid in cmd.enabled)  # "~a~b~" would also name ("a~b",)
    ):
        raise WireError("key_mismatch", f"{key!r} does not name the enabled {cmd.enabled!r}")
    return cmd
