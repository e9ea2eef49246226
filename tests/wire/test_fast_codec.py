"""The wire's fast paths against its reference forms: they must agree exactly.

- :func:`covnet.wire.codec.encode` writes the bytes of the reference encoding (a dict of the
  fields packed with the ``_default`` array hook);
- :func:`covnet.wire.codec._fast` (what :func:`decode_as` tries first) returns, for any payload,
  either None or the message the strict path (:func:`_unpack` + :func:`_build`) decodes it
  to, and None whenever the strict path refuses it;
- :meth:`_Message.evolve` equals :func:`dataclasses.replace`; :func:`_all_finite` equals
  numpy's element-wise test;
- a process's shared decode of commands and truths (:func:`sensors.protocol.decode_command`,
  :func:`~sensors.protocol.decode_truth`) gives what a decode of its own gives, refusals
  included."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.wire import codec
from covnet.wire import messages as m
from covnet.wire.schemas import _all_finite
from sensors import protocol
from tests.wire.test_messages import GOLDEN_PAYLOADS, any_message, msgpack_values


def _reference_encode(msg: m.Message) -> bytes:
    d: dict[str, object] = {"v": m.SCHEMA_VERSION, "k": msg.KIND}
    for name in type(msg)._KINDS:
        value = getattr(msg, name)
        if value is not None:
            d[name] = value
    return msgpack.packb(d, default=m._default, use_bin_type=True)


def _strict(payload: bytes, cls: type) -> object:
    """The strict path's outcome: the message, or the WireError's reason."""
    try:
        obj = codec._unpack(payload)
        if obj["k"] != cls.KIND:
            return "wrong_kind"
        return codec._build(cls, obj)
    except m.WireError as exc:
        return exc.reason


def _agree(payload: bytes) -> None:
    for cls in m.MESSAGE_TYPES:
        fast = codec._fast(payload, cls)
        strict = _strict(payload, cls)
        if fast is not None:
            assert not isinstance(strict, str), (cls, strict)
            assert fast == strict
            assert all(
                not getattr(fast, n).flags.writeable
                for n in cls._KINDS
                if isinstance(getattr(fast, n), np.ndarray)
            )
        try:
            got: object = m.decode_as(payload, cls)
        except m.WireError as exc:
            got = exc.reason
        assert got == strict if isinstance(strict, str) else got == strict


@settings(max_examples=300)
@given(any_message)
def test_encode_writes_the_reference_bytes_and_decodes_fast(msg):
    payload = m.encode(msg)
    assert payload == _reference_encode(msg)
    _agree(payload)


@pytest.mark.parametrize(
    "shape", [(0,), (1,), (3,), (31,), (32,), (200,), (0, 2), (1, 2), (130, 3), (40_000, 2)]
)
def test_array_sizes_across_bin_widths(shape):
    """bin 8, 16 and 32, fixint and wider dims: the same bytes, and the same decode."""
    rng = np.random.default_rng(7)
    if len(shape) == 1:
        msg: m.Message = m.Track(
            1, 0.5, rng.normal(size=max(shape[0], 1)), np.eye(max(shape[0], 1)), 3
        )
    else:
        msg = m.Measurement("S1", 1, 0.5, rng.normal(size=shape), np.eye(shape[1]), 3, seq=1)
    payload = m.encode(msg)
    assert payload == _reference_encode(msg)
    _agree(payload)
    if max(shape) < 128:  # dims as fixints: the fast path takes it
        assert codec._fast(payload, type(msg)) == msg


@settings(max_examples=400)
@given(st.sampled_from(GOLDEN_PAYLOADS), st.data())
def test_mutated_payloads_agree(payload, data):
    buf = bytearray(payload)
    for _ in range(data.draw(st.integers(1, 3))):
        op = data.draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]))
        i = data.draw(st.integers(0, max(len(buf) - 1, 0)))
        if op == "flip" and buf:
            buf[i] ^= 1 << data.draw(st.integers(0, 7))
        elif op == "set" and buf:
            buf[i] = data.draw(st.integers(0, 255))
        elif op == "insert":
            buf[i:i] = data.draw(st.binary(min_size=1, max_size=4))
        elif op == "delete" and buf:
            del buf[i]
        elif op == "truncate":
            del buf[i:]
    _agree(bytes(buf))


@settings(max_examples=300)
@given(
    st.sampled_from(GOLDEN_PAYLOADS),
    st.dictionaries(
        st.sampled_from(
            ["v", "k", "scan", "t", "z", "R", "x", "P", "enabled", "sensor_id", "seq", "zz"]
        ),
        msgpack_values,
        max_size=3,
    ),
)
def test_structured_payloads_agree(payload, overrides):
    d = msgpack.unpackb(payload, raw=False)
    d.update(overrides)
    _agree(msgpack.packb(d, use_bin_type=True))


@pytest.mark.parametrize("enabled", [[[]], [{}], ["s1", ["s4"]], [b"s1"], [1]])
def test_unhashable_ids_agree(enabled):
    """A list of ids holding a list or a map (unhashable) is the strict path's to refuse: the
    fast path raised TypeError on it (found by the property above)."""
    for payload in GOLDEN_PAYLOADS:
        d = msgpack.unpackb(payload, raw=False)
        if "enabled" in d:
            d["enabled"] = enabled
            _agree(msgpack.packb(d, use_bin_type=True))


@pytest.mark.parametrize("field", ["k", "v"])
@pytest.mark.parametrize("value", [np.array([1.0, 2.0]), np.zeros(0), np.array([[3.0]])])
def test_an_array_where_the_kind_or_version_goes_is_a_wire_error(field, value):
    """``{"v": 1, "k": <array>}`` made the fast path compare an array with the kind's
    string (numpy's "truth value of an array is ambiguous" ValueError, not a WireError),
    and the manager or every sensor died of one such payload on its key."""
    for cls in m.MESSAGE_TYPES:
        d: dict[str, object] = {"v": m.SCHEMA_VERSION, "k": cls.KIND, field: value}
        payload = msgpack.packb(d, use_bin_type=True, default=m._default)
        assert codec._fast(payload, cls) is None
        with pytest.raises(m.WireError):
            m.decode_as(payload, cls)
        with pytest.raises(m.WireError):
            m.decode(payload)
        assert all(x is None for x in codec.decode_many([payload] * 3, cls))


def _ext(inner: bytes) -> msgpack.ExtType:
    return msgpack.ExtType(1, inner)


@pytest.mark.parametrize(
    "z",
    [
        np.array([[np.inf, 0.0]]),
        np.array([[np.nan, 0.0]]),
        np.array([[1e308, 1e308]]),  # a sum that overflows: finite all the same
        _ext(msgpack.packb(["<f8", [1, 2], bytes(15)], use_bin_type=True)),
        _ext(msgpack.packb(["<f8", [1, 2], bytes(16)], use_bin_type=True) + b"\x00"),
        _ext(msgpack.packb([">f8", [1, 2], bytes(16)], use_bin_type=True)),
        _ext(msgpack.packb(["<f8", [1, 1, 2], bytes(16)], use_bin_type=True)),
        _ext(msgpack.packb(["<f8", [], bytes(0)], use_bin_type=True)),
        _ext(msgpack.packb(["<f8", [2], bytes(16)], use_bin_type=True)),
        _ext(msgpack.packb(["<f8", [1, -2], bytes(16)], use_bin_type=True)),
        _ext(msgpack.packb(["<f8", [1, 2], "x" * 16], use_bin_type=True)),
        msgpack.ExtType(2, msgpack.packb(["<f8", [1, 2], bytes(16)], use_bin_type=True)),
    ],
)
def test_odd_arrays_agree(z):
    good = m.Measurement("S1", 1, 0.5, np.zeros((1, 2)), np.eye(2), 3, seq=1)
    d = msgpack.unpackb(m.encode(good), raw=False)
    d["z"] = z
    payload = msgpack.packb(d, use_bin_type=True, default=m._default)
    _agree(payload)


@given(any_message, st.integers(0, 2**63 - 1))
def test_evolve_is_replace(msg, n):
    assert msg.evolve(scan=n) == dataclasses.replace(msg, scan=n)
    with pytest.raises(m.WireError):
        msg.evolve(scan=-1)
    with pytest.raises(TypeError):
        msg.evolve(nope=1)


def test_evolve_checks_like_the_constructor():
    meas = m.Measurement("S1", 1, 0.5, np.zeros((1, 2)), np.eye(2), 3)
    assert meas.evolve(seq=4).seq == 4 and meas.evolve(seq=4).z is meas.z
    assert meas.evolve(seq=None).seq is None
    with pytest.raises(m.WireError) as exc:
        meas.evolve(R=np.eye(3))
    assert exc.value.reason == "bad_shape"
    with pytest.raises(m.WireError) as exc:
        meas.evolve(t=float("nan"))
    assert exc.value.reason == "non_finite"


@given(
    arrays(
        np.float64,
        st.integers(0, 80),
        elements=st.floats(allow_nan=True, allow_infinity=True)
        | st.sampled_from([1e308, -1e308, 0.0]),
    )
)
def test_all_finite_is_numpys(a):
    assert _all_finite(a) == bool(np.isfinite(a).all())
    assert _all_finite(a.reshape(1, -1)) == bool(np.isfinite(a).all())


def test_a_process_decodes_a_command_once_for_its_sensors():
    ids = ("S1", "S2", "S3")
    cmd = m.Command(4, 0.4, ids, 9)
    key, payload = m.command_key("r1", ids), m.encode(cmd)
    first = protocol.decode_command(key, payload)
    assert first == cmd
    assert protocol.decode_command(key, bytes(payload)) is first  # shared, not decoded again
    other = m.Command(5, 0.5, ids, 10)
    assert protocol.decode_command(key, m.encode(other)) == other
    for bad_key, bad_payload, reason in [
        (m.command_key("r1", ("S1",)), payload, "key_mismatch"),
        (key, payload[:-1], "truncated"),
    ]:
        for _ in range(2):  # the kept refusal is raised again, with its reason
            with pytest.raises(m.WireError) as exc:
                protocol.decode_command(bad_key, bad_payload)
            assert exc.value.reason == reason


def test_a_process_decodes_a_truth_once_for_its_sensors():
    tr = m.Truth(3, 0.3, ("T1",), np.ones((1, 4)))
    key, payload = m.truth_key("r1"), m.encode(tr)
    first = protocol.decode_truth(key, payload)
    assert first == tr and protocol.decode_truth(key, bytes(payload)) is first
    with pytest.raises(m.WireError) as exc:
        protocol.decode_truth(key, m.encode(m.Status(1, 0.1, (), 1.0, 1.0, 1.0, 2)))
    assert exc.value.reason == "wrong_kind"
