"""The batch decoder of a scan's measurements (:func:`covnet.wire.codec.decode_many`) against
the per-message one (:func:`covnet.wire.codec.decode_as`): for every payload either None (the
per-message path then judges it) or the very message ``decode_as`` gives, bit for bit; what
``decode_as`` rejects the batch never takes, and a clean batch is taken whole."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.wire import messages as msg
from covnet.wire.codec import decode_many

IDS = [f"bd{j:03d}" for j in range(16)]
pytestmark = pytest.mark.usefixtures("room_in_the_names_cache")


def _meas(rng: np.random.Generator, j: int, scan: int, seq: int, **kw: object) -> msg.Measurement:
    A = rng.normal(size=(2, 2))
    fields: dict[str, object] = {
        "sensor_id": IDS[j % len(IDS)],
        "scan": scan,
        "t": 0.1 * scan,
        "z": rng.normal(size=(1, 2)) * 100,
        "R": A @ A.T + np.eye(2),
        "t_sent_ns": 1_700_000_000_000_000_000 + j,
        "episode": 0,
        "seq": seq,
    }
    fields.update(kw)
    return msg.Measurement(**fields)  # type: ignore[arg-type]


def _same(a: msg.Measurement, b: msg.Measurement) -> None:
    """Equal fields, the same types, arrays bit for bit, read-only, of the same shapes."""
    assert a == b
    for name in ("sensor_id", "scan", "t", "t_sent_ns", "episode", "target_ids", "platform", "seq"):
        va, vb = getattr(a, name), getattr(b, name)
        assert type(va) is type(vb) and va == vb, name
    for name in ("z", "R"):
        va, vb = getattr(a, name), getattr(b, name)
        assert va.dtype == vb.dtype == np.float64 and va.shape == vb.shape
        assert va.tobytes() == vb.tobytes()
        assert not va.flags.writeable


def _judge(payloads: list[object]) -> list[msg.Measurement | None]:
    """decode_many's answer, checked payload by payload against decode_as."""
    out = decode_many(payloads, msg.Measurement)  # type: ignore[arg-type]
    assert len(out) == len(payloads)
    for p, m in zip(payloads, out, strict=True):
        try:
            ref = msg.decode_as(p, msg.Measurement)  # type: ignore[arg-type]
        except (msg.WireError, TypeError):  # TypeError: not bytes at all
            assert m is None  # rejected one by one: never taken by the batch
            continue
        if m is not None:
            _same(m, ref)
    return out


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 40),
    scan=st.integers(0, 2**40),
    seq=st.sampled_from([1, 127, 128, 255, 256, 65535, 65536, 2**32, 2**63 - 1]),
)
def test_a_clean_batch_is_taken_whole_and_equals_decode_as(seed, n, scan, seq):
    rng = np.random.default_rng(seed)
    payloads = [msg.encode(_meas(rng, j, scan, seq)) for j in range(n)]
    out = _judge(payloads)
    assert all(m is not None for m in out)


def _mutations(good: bytes, rng: np.random.Generator) -> list[object]:
    """Payloads near a good one: each wrong in one way, or right in an unusual layout."""
    d = msgpack.unpackb(good, ext_hook=lambda c, b: msgpack.ExtType(c, b))
    out: list[object] = [
        good[:-1],  # truncated
        good + b"\x00",  # trailing bytes
        b"",
        b"\xc1",
        bytearray(good),  # not bytes: decode_as's own path
        "not bytes",
    ]
    for i in rng.choice(len(good), size=12, replace=False):  # byte flips
        b = bytearray(good)
        b[i] ^= 1 << int(rng.integers(0, 8))
        out.append(bytes(b))

    def variant(**changes: object) -> bytes:
        e = dict(d)
        for k, v in changes.items():
            if v is _DROP:
                e.pop(k, None)
            else:
                e[k] = v
        return msgpack.packb(e, use_bin_type=True)

    zext, rext = d["z"], d["R"]
    nan = np.array([[math.nan, 1.0]]).tobytes()
    out += [
        variant(v=2),
        variant(v=True),
        variant(k="track"),
        variant(k=["meas"]),
        variant(sensor_id="never-seen-id"),
        variant(sensor_id=["bd000"]),
        variant(sensor_id=b"bd000"),
        variant(scan=-1),
        variant(scan=True),
        variant(scan=1.0),
        variant(t=1),
        variant(t=math.inf),
        variant(t=math.nan),
        variant(t_sent_ns=-5),
        variant(episode=None),
        variant(seq=0.5),
        variant(seq=_DROP),  # no seq: nine keys (decode_as's path)
        variant(extra=1),
        variant(z=_DROP),
        variant(z=[[1.0, 2.0]]),
        variant(z=msgpack.ExtType(2, zext.data)),
        variant(z=msgpack.ExtType(1, zext.data[:-8] + nan[:8])),
        variant(z=msgpack.ExtType(1, zext.data[:-1])),
        variant(z=rext),  # z (2, 2): the right layout, another shape
        variant(R=zext),
        variant(R=msgpack.ExtType(1, rext.data[:-8] + np.array([math.inf]).tobytes())),
        msgpack.packb(dict(reversed(list(d.items()))), use_bin_type=True),  # keys reordered
        msgpack.packb([d], use_bin_type=True),
    ]
    return out


_DROP = object()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_bad_payloads_in_a_batch_are_left_to_decode_as(seed):
    rng = np.random.default_rng(seed)
    goods = [msg.encode(_meas(rng, j, 7, 3 + j)) for j in range(6)]
    bads = _mutations(goods[0], rng)
    for bad in bads:  # each bad payload among good ones, anywhere in the batch
        batch: list[object] = list(goods)
        batch.insert(int(rng.integers(0, len(batch) + 1)), bad)
        _judge(batch)
    _judge(bads)
    _judge(bads + goods)


def test_a_bad_column_sends_the_batch_to_decode_as_and_nothing_else():
    """A value the batch's column checks refuse leaves every payload of the batch to
    decode_as (the good ones are still decoded there, to the same messages)."""
    rng = np.random.default_rng(1)
    goods = [msg.encode(_meas(rng, j, 7, 3 + j)) for j in range(5)]
    d = msgpack.unpackb(goods[0], ext_hook=lambda c, b: msgpack.ExtType(c, b))
    d["t"] = math.inf
    bad = msgpack.packb(d, use_bin_type=True)
    with pytest.raises(msg.WireError):
        msg.decode_as(bad, msg.Measurement)
    assert _judge([*goods, bad]) == [None] * 6
    assert all(m is not None for m in _judge(goods))


def test_other_kinds_and_layouts_are_left_to_decode_as():
    rng = np.random.default_rng(2)
    several = msg.encode(_meas(rng, 0, 1, 1, z=rng.normal(size=(3, 2))))
    none_seen = msg.encode(_meas(rng, 1, 1, 1, z=np.zeros((0, 2))))
    mobile = msg.encode(_meas(rng, 2, 1, 1, platform=np.zeros(4)))
    assert _judge([several, none_seen, mobile]) == [None, None, None]
    hb = msg.encode(msg.Heartbeat(node_id="bd000", role="sensor", scan=1, t_sent_ns=1))
    assert decode_many([hb], msg.Heartbeat) == [None]
