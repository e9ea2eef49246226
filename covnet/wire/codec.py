"""The wire's bytes: :func:`encode` and the strict :func:`decode` of the messages of
:mod:`covnet.wire.schemas`.  Nothing else in covnet packs a payload.

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
import threading
from typing import Any, TypeVar

import msgpack
import numpy as np
from numpy.typing import NDArray

from covnet.wire.keys import _CMD_SEP, _enabled_chunk
from covnet.wire.schemas import (
    _BY_KIND,
    _GOOD_NAMES,
    _INT64_MAX,
    MAX_ARRAY_ELEMENTS,
    MAX_IDS,
    MAX_PAYLOAD_BYTES,
    Command,
    Measurement,
    Message,
    WireError,
    _coerce,
    _Message,
    _spec,
)

SCHEMA_VERSION = 1

_EXT_NDARRAY = 1
_WIRE_DTYPE = "<f8"
_MAX_NDIM = 2
_MAX_STR_LEN = 1024  # any msgpack str; ids over MAX_NAME_LEN are then bad_value
_MAX_MAP_LEN = MAX_IDS + 16
_M = TypeVar("_M", bound=_Message)


# --------------------------------------------------------------------------------------------
# encode / decode
# --------------------------------------------------------------------------------------------


def episode_of(payload: bytes) -> int | None:
    """The ``episode`` field of a payload, read with one plain msgpack unpack (no strict
    decode: the recorder's look at what it records, a link emulator's at what it delays): 0
    when absent (the schema's default); None when the payload is not a msgpack map or the
    field not an int in ``[0, 2**63)``."""
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:  # msgpack's ValueError, ExtraData, FormatError, StackError, ...
        return None
    e = obj.get("episode", 0) if type(obj) is dict else None
    return e if type(e) is int and 0 <= e < 2**63 else None


def _default(obj: object) -> msgpack.ExtType:
    if isinstance(obj, np.ndarray) and obj.dtype == np.float64:
        a = np.ascontiguousarray(obj, dtype=_WIRE_DTYPE)
        inner = msgpack.packb([_WIRE_DTYPE, list(a.shape), a.tobytes()], use_bin_type=True)
        return msgpack.ExtType(_EXT_NDARRAY, inner)
    raise TypeError(f"cannot encode {type(obj).__name__}")


_packers = threading.local()


def _packer() -> msgpack.Packer:
    """This thread's packer (one per thread: a packer's buffer is its own while it packs)."""
    try:
        return _packers.packer
    except AttributeError:
        p = _packers.packer = msgpack.Packer(default=_default, use_bin_type=True)
        return p


_INNER_HEAD = b"\x93\xa3<f8"  # the inner list's header and its dtype, as packb writes them


def _array_ext(a: NDArray[np.float64], pack: Any) -> msgpack.ExtType:
    """:func:`_default`'s ext of a float64 array, its inner list packed in pieces (the same
    bytes: a list of three is its header and its items one after another)."""
    a = np.ascontiguousarray(a, dtype=_WIRE_DTYPE)
    return msgpack.ExtType(_EXT_NDARRAY, _INNER_HEAD + pack(list(a.shape)) + pack(a.tobytes()))


def encode(msg: Message) -> bytes:
    """``msg`` as msgpack bytes: ``{"v": SCHEMA_VERSION, "k": KIND, ...fields}``."""
    if not isinstance(msg, _Message):
        raise TypeError(f"not a message: {type(msg).__name__}")
    pack = _packer().pack
    d: dict[str, object] = {"v": SCHEMA_VERSION, "k": msg.KIND}
    for name, kind, _ in _spec(type(msg)).fields:
        value = getattr(msg, name)
        if value is None:  # optional and unset: omitted
            continue
        if kind == "mat" or kind == "vec":
            value = _array_ext(value, pack)
        d[name] = value
    return pack(d)


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


# --------------------------------------------------------------------------------------------
# the fast path: what encode produces, decoded with no check done twice
# --------------------------------------------------------------------------------------------


class _Decline(Exception):
    """The fast path does not take this payload: the strict path judges it."""


_SUM_CHECK_MAX = 64  # up to this many elements, finiteness is summed in Python, else numpy


def _fast_ext(code: int, data: bytes) -> NDArray[np.float64]:
    """The array ext as :func:`encode` writes it (``[dtype, shape, bin]``, dims as positive
    fixints, bin 8/16/32), finite, within the caps: the same read-only float64 array as
    :func:`_ext_hook`; anything else declines (the strict path says why)."""
    if code != _EXT_NDARRAY or not data.startswith(_INNER_HEAD) or len(data) < 9:
        raise _Decline
    ndim, d0 = data[5], data[6]
    if d0 > 0x7F:  # dims as positive fixints only
        raise _Decline
    if ndim == 0x91:  # [n]
        shape: tuple[int, ...] = (d0,)
        size, pos = d0, 7
    elif ndim == 0x92 and data[7] <= 0x7F:  # [n, m]
        shape, size, pos = (d0, data[7]), d0 * data[7], 8
    else:
        raise _Decline
    tag = data[pos]
    if tag == 0xC4:
        n, pos = data[pos + 1], pos + 2
    elif tag == 0xC5:
        n, pos = int.from_bytes(data[pos + 1 : pos + 3], "big"), pos + 3
    elif tag == 0xC6:
        n, pos = int.from_bytes(data[pos + 1 : pos + 5], "big"), pos + 5
    else:
        raise _Decline
    if n != 8 * size or len(data) != pos + n or size > MAX_ARRAY_ELEMENTS:
        raise _Decline
    a = np.frombuffer(data, dtype=_F8, count=size, offset=pos).reshape(shape)
    if _F8_NATIVE and size <= _SUM_CHECK_MAX:
        # the sum of float64s is finite only if every one is (an inf or a NaN stays one); a
        # sum that overflows declines, and the strict path checks element by element
        if not math.isfinite(sum(memoryview(data)[pos:].cast("d"))):
            raise _Decline
    elif not np.isfinite(a).all():
        raise _Decline
    return a if _F8_NATIVE else a.astype(np.float64)


_SCALARS = frozenset({"count", "stamp", "float"})


def _fast(payload: bytes, cls: type[_M]) -> _M | None:
    """``payload`` as ``cls`` when it is what :func:`encode` writes (a map of
    :data:`SCHEMA_VERSION` and ``cls``'s kind, the fields canonical msgpack, every array the
    canonical ext, finite); None for anything else, which the strict path then judges.

    Equivalence: a payload this returns a message for is one the strict path decodes to an
    equal message (same fields, same types, read-only arrays): the same msgpack parse (a C
    ``unpackb``; its default limits are the payload's length, and the caps the strict path
    sets are checked on what it returns), the same field checks (:func:`_coerce` for scalars
    and ids, the class's ``_check``), and arrays from :func:`_fast_ext`, which accepts only
    finite arrays within the caps of the layout :func:`_ext_hook` reads the same way (``tests/
    wire/test_fast_codec.py`` checks it on mutated payloads)."""
    if type(payload) is not bytes or len(payload) > MAX_PAYLOAD_BYTES:
        return None
    try:
        obj = msgpack.unpackb(payload, raw=False, ext_hook=_fast_ext)
    except Exception:  # noqa: BLE001 (any refusal or oddity: the strict path says why)
        return None
    if type(obj) is not dict:
        return None
    version, kind = obj.get("v"), obj.get("k")
    if type(version) is not int or version != SCHEMA_VERSION or type(kind) is not str:
        return None  # (a kind that is an array compared by ``!=`` is numpy's ValueError)
    if kind != cls.KIND:
        return None
    spec = _spec(cls)
    if not spec.keys.issuperset(obj):
        return None
    msg = object.__new__(cls)
    setattr_ = object.__setattr__
    get = obj.get
    good = _GOOD_NAMES
    try:
        for name, kind, optional in spec.fields:
            value = get(name, _OMITTED)
            if value is _OMITTED:
                if not optional:
                    return None
                setattr_(msg, name, None)
            elif kind == "name":  # an id seen valid before (new ones: the strict path)
                if type(value) is not str or value not in good:
                    return None
                setattr_(msg, name, value)
            elif kind == "names":
                if type(value) is not list or len(value) > MAX_IDS:
                    return None
                try:
                    known = good.issuperset(value)
                except TypeError:  # an unhashable element (a list, a map): the strict path
                    return None
                if not known:
                    return None
                ids = tuple(value)
                if len(set(ids)) != len(ids):
                    return None
                setattr_(msg, name, ids)
            elif kind in _SCALARS:
                setattr_(msg, name, _coerce(kind, name, value, True))
            elif kind == "mat" or kind == "vec":
                if type(value) is not np.ndarray or value.ndim != (2 if kind == "mat" else 1):
                    return None
                setattr_(msg, name, value)  # checked by _fast_ext
            else:  # maps: the strict checks (their strings and arrays too)
                if type(value) is not dict or len(value) > MAX_IDS or not _fits(value):
                    return None
                setattr_(msg, name, _coerce(kind, name, value, True))
        msg._check()
    except WireError:
        return None
    return msg


def _fits(d: dict[Any, Any]) -> bool:
    """A map field within the strict parse's limits: str keys, no string over its cap, no
    list of ids over :data:`MAX_IDS`."""
    for k, v in d.items():
        if type(k) is not str or len(k) > _MAX_STR_LEN:
            return False
        if type(v) is str and len(v) > _MAX_STR_LEN:
            return False
        if type(v) is list and (
            len(v) > MAX_IDS or not all(type(x) is str and len(x) <= _MAX_STR_LEN for x in v)
        ):
            return False
    return True


# --------------------------------------------------------------------------------------------
# the batch path: a scan's measurements decoded and checked together
# --------------------------------------------------------------------------------------------


def _ext_pair(code: int, data: bytes) -> tuple[int, bytes]:
    """The batch path's ext hook: the ext as it is, checked afterwards for the whole batch
    (a plain tuple: ``msgpack.ExtType``'s constructor is a Python ``__new__``, and with
    ``use_list`` a msgpack array is a list, so a tuple in the result is an ext)."""
    return (code, data)


_MEAS_KEYS = ("v", "k", "sensor_id", "scan", "t", "z", "R", "t_sent_ns", "episode", "seq")
_Z_HEAD = _INNER_HEAD + b"\x92\x01\x02\xc4\x10"  # [dtype, [1, 2], bin 8 of 16 bytes]
_R_HEAD = _INNER_HEAD + b"\x92\x02\x02\xc4\x20"  # [dtype, [2, 2], bin 8 of 32 bytes]


def _ints_ok(col: tuple[Any, ...]) -> bool:
    """Every value an ``int`` (not a bool) in ``[0, 2**63)``: :func:`_coerce`'s count and
    stamp, for a column."""
    return set(map(type, col)) == {int} and min(col) >= 0 and max(col) <= _INT64_MAX


def _array_column(
    col: tuple[Any, ...], head: bytes, shape: tuple[int, int]
) -> NDArray[np.float64] | None:
    """The arrays of a column of exts that are all ``head`` followed by ``shape``'s float64s,
    finite, as one read-only ``(n, *shape)`` array; None when any is not."""
    if set(map(type, col)) != {tuple} or {c for c, _ in col} != {_EXT_NDARRAY}:
        return None
    size = 8 * shape[0] * shape[1]
    datas = [d for _, d in col]
    if set(map(type, datas)) != {bytes} or set(map(len, datas)) != {len(head) + size}:
        return None
    raw = np.frombuffer(b"".join(datas), dtype=np.uint8).reshape(len(datas), len(head) + size)
    if not (raw[:, : len(head)] == np.frombuffer(head, dtype=np.uint8)).all():
        return None
    a = raw[:, len(head) :].copy().view(_F8).reshape(len(datas), *shape)
    if not _F8_NATIVE:  # pragma: no cover - big-endian hosts
        a = a.astype(np.float64)
    if not np.isfinite(a).all():
        return None
    a.flags.writeable = False
    return a


def _measurements(payloads: list[Any]) -> list[Any]:
    """:func:`decode_many` for :class:`Measurement`: the payloads laid out as :func:`encode`
    writes a covariance-control measurement (the ten keys in their order, one detection
    ``z`` ``(1, 2)``, ``R`` ``(2, 2)``, no ``target_ids`` nor ``platform``, ``seq`` set).

    Equivalence with :func:`decode_as` (and so with the strict decode): a payload this takes
    is one :func:`_fast` takes, to an equal message.  Per payload the same ``unpackb`` parse
    (its default limits, no trailing bytes), a map of exactly those keys; then per column the
    checks of :func:`_fast`, each at least as strict: ``v`` the int :data:`SCHEMA_VERSION`,
    ``k`` the kind, ``sensor_id`` a str among the ids seen valid, ``scan``/``t_sent_ns``/
    ``episode``/``seq`` ints in ``[0, 2**63)``, ``t`` a finite float, ``z`` and ``R`` the
    array ext of :func:`_fast_ext`'s layout with exactly those shapes (dims as fixints, bin 8)
    and finite values, which ``Measurement._check`` accepts (``R`` square, ``z``'s columns
    ``R``'s).  The arrays are read-only rows of one array per batch (values bit for bit the
    payload's).  A column that fails a check sends every payload of the batch to
    :func:`decode_as` (None): bad input is rare, and is then judged exactly as before."""
    out: list[Any] = [None] * len(payloads)
    rows: list[int] = []
    values: list[Any] = []
    unpackb = msgpack.unpackb
    for i, p in enumerate(payloads):
        if type(p) is not bytes or len(p) > MAX_PAYLOAD_BYTES:
            continue
        try:
            d = unpackb(p, ext_hook=_ext_pair)
        except Exception:  # noqa: BLE001 (any refusal: decode_as says why)
            continue
        if type(d) is dict and len(d) == 10 and tuple(d) == _MEAS_KEYS:
            rows.append(i)
            values.append(tuple(d.values()))
    if not rows:
        return out
    v, k, sid, scan, t, z, R, t_sent, episode, seq = zip(*values, strict=True)
    if (
        set(map(type, v)) != {int}
        or set(v) != {SCHEMA_VERSION}
        or set(map(type, k)) != {str}
        or set(k) != {Measurement.KIND}
        or set(map(type, sid)) != {str}
        or not _GOOD_NAMES.issuperset(sid)
        or not (_ints_ok(scan) and _ints_ok(t_sent) and _ints_ok(episode) and _ints_ok(seq))
        or set(map(type, t)) != {float}
        or not all(map(math.isfinite, t))
    ):
        return out
    Z = _array_column(z, _Z_HEAD, (1, 2))
    Rs = _array_column(R, _R_HEAD, (2, 2))
    if Z is None or Rs is None:
        return out
    new, setattr_ = object.__new__, object.__setattr__
    for n, i in enumerate(rows):
        m = new(Measurement)
        setattr_(m, "sensor_id", sid[n])
        setattr_(m, "scan", scan[n])
        setattr_(m, "t", t[n])
        setattr_(m, "z", Z[n])
        setattr_(m, "R", Rs[n])
        setattr_(m, "t_sent_ns", t_sent[n])
        setattr_(m, "episode", episode[n])
        setattr_(m, "target_ids", None)
        setattr_(m, "platform", None)
        setattr_(m, "seq", seq[n])
        out[i] = m
    return out


_BATCH_DECODERS: dict[str, Any] = {Measurement.KIND: _measurements}
"""Per message kind, its batch decoder (:func:`decode_many`); kinds without one are decoded
one by one."""


def decode_many(payloads: list[Any], cls: type[_M]) -> list[_M | None]:
    """The payloads of a key that admits only ``cls``, decoded together where they are what
    :func:`encode` writes (the kind's entry in :data:`_BATCH_DECODERS`): per payload the
    message :func:`decode_as` returns for it, or None where the batch path does not take it
    (anything else: :func:`decode_as` then decodes or rejects it, with its reason)."""
    batch = _BATCH_DECODERS.get(cls.KIND)
    if batch is None:
        return [None] * len(payloads)
    return batch(payloads)


def decode(payload: bytes) -> Message:
    """Decode any message kind; raises :class:`WireError` (and nothing else) on bad bytes."""
    obj = _unpack(payload)
    kind = obj["k"]
    cls = _BY_KIND.get(kind) if type(kind) is str else None
    if cls is None:
        raise WireError("unknown_kind", f"k={kind!r}")
    return _build(cls, obj)


def decode_as(payload: bytes, cls: type[_M]) -> _M:
    """Decode a payload from a key that admits only ``cls``; another kind is ``wrong_kind``.
    What :func:`encode` writes takes the fast path (:func:`_fast`), anything else the strict
    one (the same message or the same :class:`WireError`)."""
    fast = _fast(payload, cls)
    if fast is not None:
        return fast
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
        # "~a~b~" would also name ("a~b",): the chunk has one separator more than ids
        or chunk.count(_CMD_SEP) != len(cmd.enabled) + 1
    ):
        raise WireError("key_mismatch", f"{key!r} does not name the enabled {cmd.enabled!r}")
    return cmd
