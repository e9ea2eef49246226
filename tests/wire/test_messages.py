"""The wire schema (covnet.wire.messages): round trips, golden bytes, every rejection reason,
fuzz."""

from __future__ import annotations

import math
import string

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from covnet.wire import messages as m
from covnet.wire.messages import (
    MAX_ARRAY_ELEMENTS,
    MAX_IDS,
    MAX_PAYLOAD_BYTES,
    MESSAGE_TYPES,
    REASONS,
    SCHEMA_VERSION,
    Command,
    Heartbeat,
    LocalTrack,
    Measurement,
    Status,
    Track,
    Truth,
    WireError,
    decode,
    decode_as,
    encode,
)

# --------------------------------------------------------------------------------------------
# round trips: a table of cases for every kind
# --------------------------------------------------------------------------------------------

CASES = [
    Truth(scan=0, t=0.0, target_ids=("t1",), states=np.array([[1.0, 2.0, 3.0, 4.0]])),
    Truth(scan=5, t=1.5, target_ids=(), states=np.zeros((0, 4))),
    Truth(scan=9, t=-2.0, target_ids=("a", "b", "c"), states=np.arange(18.0).reshape(3, 6)),
    Command(scan=3, t=0.3, enabled=("s1", "s3"), t_sent_ns=123_456_789),
    Command(scan=0, t=0.0, enabled=(), t_sent_ns=0),
    Command(scan=1, t=0.1, enabled=("s1",), t_sent_ns=1, modes={"s1": "wide", "s2": "narrow"}),
    Command(scan=4, t=0.4, enabled=("s2",), t_sent_ns=2, episode=3),
    Measurement("s1", 4, 0.4, np.array([[1.0, -1.0], [2.0, 5e-324]]), np.eye(2), 99),
    Measurement("s2", 4, 0.4, np.zeros((0, 3)), 2.0 * np.eye(3), 100),
    Measurement("s3", 2**63 - 1, 1e300, np.array([[-0.0]]), np.array([[1e-300]]), 2**63 - 1),
    Track(scan=2, t=0.2, x=np.array([1.0, 2.0]), P=np.array([[2.0, 0.5], [0.5, 1.0]]), t_sent_ns=7),
    Status(2, 0.2, ("s1", "s2"), trace_P=3.0, trace_Pd=4.0, value=-1.0, t_sent_ns=8),
    Status(2, 0.2, (), trace_P=0.0, trace_Pd=0.0, value=0.0, t_sent_ns=8),
    Status(3, 0.3, ("s1",), 1.0, 2.0, 3.0, 9, episode=1, fused=("s1",), failed=("s2", "s3")),
    Heartbeat(role="sensor", node_id="s1", scan=11, t_sent_ns=12),
    Heartbeat(role="manager", node_id="fusion-0.A_b", scan=0, t_sent_ns=0),
    Heartbeat("sensor", "s2", 5, 6, rejected={"bad_type": 2, "non_finite": 0}),
    # the mobile scenario's optional fields
    Truth(
        scan=3,
        t=3.0,
        target_ids=("T1",),
        states=np.ones((1, 4)),
        sensor_ids=("S1", "S2"),
        platforms=np.arange(8.0).reshape(2, 4),
    ),
    Truth(2, 2.0, (), np.zeros((0, 4)), sensor_ids=(), platforms=np.zeros((0, 4))),
    Command(
        1,
        1.0,
        ("S1", "S2"),
        5,
        modes={"S1": "NE", "S2": "stay"},
        targets={"S1": ("T1", "T2"), "S2": ()},
    ),
    Command(
        2,
        2.0,
        ("S1", "R1", "B1"),
        6,
        targets={"S1": ("T2",), "R1": ("T1",), "B1": ("T2",)},
        windows={"R1": np.array([9000.0, 0.7, 120.0, 0.012]), "B1": np.array([-1.2, 0.006])},
    ),
    Measurement(
        "S1",
        1,
        1.0,
        np.array([[1.0, 2.0]]),
        np.eye(2),
        6,
        target_ids=("T2",),
        platform=np.array([3.0, 0.0, 3.0, 0.0]),
    ),
    Measurement("S2", 1, 1.0, np.zeros((0, 2)), np.eye(2), 6, target_ids=(), platform=np.zeros(4)),
    Track(1, 1.0, np.zeros(4), np.eye(4), 7, target_id="T3"),
    # the decentralized modes
    LocalTrack("S1", 3, 3.0, np.ones(4), np.eye(4), np.zeros(4), 2.0 * np.eye(4), 8, episode=1),
    Track(3, 3.0, np.zeros(4), np.eye(4), 9, node_id="S2"),
    Status(3, 3.0, ("S1",), 1.0, 2.0, 3.0, 10, fused=("S1", "S2"), node_id="S2"),
    Status(4, 4.0, ("S1",), 1.0, 2.0, 3.0, 11, refiltered=("S3:2", "S1:3")),
]
CASE_IDS = [
    "truth",
    "truth-no-targets",
    "truth-3x6",
    "cmd",
    "cmd-none-enabled",
    "cmd-modes",
    "cmd-episode",
    "meas",
    "meas-no-detections",
    "meas-extremes",
    "track",
    "status",
    "status-zero",
    "status-fused-failed",
    "hb-sensor",
    "hb-manager",
    "hb-rejected",
    "truth-platforms",
    "truth-no-platforms",
    "cmd-targets",
    "cmd-windows",
    "meas-target-ids",
    "meas-no-detections-mobile",
    "track-target",
    "ltrack",
    "track-peer",
    "status-peer",
    "status-refiltered",
]


def test_every_kind_has_a_case():
    assert {type(c) for c in CASES} == set(MESSAGE_TYPES)
    assert len({cls.KIND for cls in MESSAGE_TYPES}) == len(MESSAGE_TYPES)


@pytest.mark.parametrize("msg", CASES, ids=CASE_IDS)
def test_round_trip(msg):
    payload = encode(msg)
    out = decode(payload)
    assert type(out) is type(msg)
    assert out == msg
    assert decode_as(payload, type(msg)) == msg
    assert encode(out) == payload  # bit-exact, including -0.0 and subnormals
    for name in type(msg)._KINDS:
        value = getattr(out, name)
        if isinstance(value, np.ndarray):
            assert value.dtype == np.float64
            assert not value.flags.writeable


@pytest.mark.parametrize("msg", CASES, ids=CASE_IDS)
def test_wire_map_layout(msg):
    raw = msgpack.unpackb(encode(msg), raw=False)
    assert list(raw)[:2] == ["v", "k"]
    assert raw["v"] == SCHEMA_VERSION and raw["k"] == type(msg).KIND
    sent = [k for k in type(msg)._KINDS if getattr(msg, k) is not None]
    assert list(raw)[2:] == sent  # declaration order; unset optional fields omitted


def test_messages_compare_by_value():
    a = Track(scan=1, t=0.1, x=[1.0, 2.0], P=np.eye(2), t_sent_ns=1)
    assert a == Track(scan=1, t=0.1, x=np.array([1.0, 2.0]), P=np.eye(2), t_sent_ns=1)
    assert a != Track(scan=1, t=0.1, x=[1.0, 2.5], P=np.eye(2), t_sent_ns=1)
    assert a != Track(scan=2, t=0.1, x=[1.0, 2.0], P=np.eye(2), t_sent_ns=1)
    with pytest.raises(TypeError):
        hash(a)


def test_constructor_converts_leniently_and_freezes():
    src = np.eye(2)
    msg = Measurement("s1", np.int64(3), 1, [[1, 2]], src, 5)
    assert msg.scan == 3 and type(msg.scan) is int
    assert msg.t == 1.0 and type(msg.t) is float
    assert msg.z.dtype == np.float64 and msg.z.shape == (1, 2)
    src[0, 0] = 9.0  # the message holds its own read-only copy
    assert msg.R[0, 0] == 1.0
    with pytest.raises(ValueError, match="read-only"):
        msg.R[0, 0] = 2.0
    cmd = Command(scan=1, t=0.0, enabled=["s1", "s2"], t_sent_ns=0)
    assert cmd.enabled == ("s1", "s2")


@pytest.mark.parametrize(
    ("build", "reason"),
    [
        (lambda: Command(True, 0.0, (), 0), "bad_type"),
        (lambda: Command(1, True, (), 0), "bad_type"),
        (lambda: Command(1, "0.0", (), 0), "bad_type"),
        (lambda: Command(-1, 0.0, (), 0), "bad_value"),
        (lambda: Command(1, 0.0, ("s1", "s1"), 0), "bad_value"),
        (lambda: Command(1, 0.0, "s1", 0), "bad_type"),
        (lambda: Command(1, 0.0, ("a/b",), 0), "bad_value"),
        (lambda: Command(1, math.nan, (), 0), "non_finite"),
        (lambda: Measurement("s1", 1, 0.0, np.ones((1, 3)), np.eye(2), 0), "bad_shape"),
        (lambda: Measurement("s1", 1, 0.0, np.ones((1, 2)), np.ones((2, 3)), 0), "bad_shape"),
        (lambda: Measurement("s1", 1, 0.0, np.ones(2), np.eye(2), 0), "bad_shape"),
        (
            lambda: Measurement("s1", 1, 0.0, np.ones((1, 2)), np.full((2, 2), np.inf), 0),
            "non_finite",
        ),
        (lambda: Measurement("s1", 1, 0.0, [["a", "b"]], np.eye(2), 0), "bad_type"),
        (lambda: Measurement("s1", 1, 0.0, np.ones((1, 2), complex), np.eye(2), 0), "bad_type"),
        (lambda: Track(1, 0.0, np.ones(3), np.eye(2), 0), "bad_shape"),
        (lambda: Track(1, 0.0, np.ones(0), np.eye(0), 0), "bad_shape"),
        (lambda: Truth(1, 0.0, ("a", "b"), np.ones((1, 4))), "bad_shape"),
        (lambda: Heartbeat("sensor", "", 0, 0), "bad_value"),
        (lambda: Heartbeat("sensor", "s 1", 0, 0), "bad_value"),
    ],
    ids=[
        "bool-scan",
        "bool-t",
        "str-t",
        "negative-scan",
        "duplicate-ids",
        "str-as-ids",
        "slash-id",
        "nan-t",
        "z-vs-R",
        "R-not-square",
        "z-1d",
        "inf-R",
        "str-array",
        "complex-array",
        "x-vs-P",
        "empty-state",
        "rows-vs-ids",
        "empty-id",
        "space-id",
    ],
)
def test_constructor_rejects(build, reason):
    with pytest.raises(WireError) as info:
        build()
    assert info.value.reason == reason


# --------------------------------------------------------------------------------------------
# golden bytes: a schema change must show up here (and then SCHEMA_VERSION must move)
# --------------------------------------------------------------------------------------------

GOLDEN_MSGS = {
    "truth": Truth(
        scan=7,
        t=0.7,
        target_ids=("tgt0", "tgt1"),
        states=np.array([[1.0, -2.0, 0.5, 0.0], [10.0, 20.0, -0.25, 1.5]]),
    ),
    "cmd": Command(scan=7, t=0.7, enabled=("s1", "s4", "s7"), t_sent_ns=1_000_000_007, episode=2),
    "meas": Measurement(
        sensor_id="s4",
        scan=7,
        t=0.7,
        z=np.array([[1.25, -3.5]]),
        R=np.array([[0.5, 0.1], [0.1, 0.25]]),
        t_sent_ns=1_000_000_123,
        episode=2,
    ),
    "track": Track(
        scan=7,
        t=0.7,
        x=np.array([1.0, 2.0, 0.5, -0.5]),
        P=np.diag([1.0, 2.0, 3.0, 4.0]),
        t_sent_ns=1_000_000_456,
        episode=2,
    ),
    "status": Status(
        scan=7,
        t=0.7,
        enabled=("s1", "s4", "s7"),
        trace_P=10.0,
        trace_Pd=12.5,
        value=0.375,
        t_sent_ns=1_000_000_789,
        episode=2,
        fused=("s1", "s7"),
        failed=("s4",),
    ),
    "hb": Heartbeat(role="sensor", node_id="s4", scan=7, t_sent_ns=1_000_001_000),
    "ltrack": LocalTrack(
        sensor_id="S3",
        scan=7,
        t=7.0,
        x=np.array([1.0, 2.0, 0.5, -0.5]),
        P=np.eye(4),
        x_prior=np.array([1.5, 2.0, 0.0, -0.5]),
        P_prior=2.0 * np.eye(4),
        t_sent_ns=1_000_000_789,
        episode=1,
    ),
}

# schema version 1, computed from the messages above; after a deliberate schema change,
# regenerate with `python tests/wire/test_messages.py` (and bump SCHEMA_VERSION once deployed)
GOLDEN_HEX = {
    "truth": (
        "86a17601a16ba57472757468a47363616e07a174cb3fe6666666666666aa7461726765745f696473"
        "92a474677430a474677431a6737461746573c74a0193a33c6638920204c440000000000000f03f00"
        "000000000000c0000000000000e03f00000000000000000000000000002440000000000000344000"
        "0000000000d0bf000000000000f83f"
    ),
    "cmd": (
        "87a17601a16ba3636d64a47363616e07a174cb3fe6666666666666a7656e61626c656493a27331a2"
        "7334a27337a9745f73656e745f6e73ce3b9aca07a7657069736f646502"
    ),
    "meas": (
        "89a17601a16ba46d656173a973656e736f725f6964a27334a47363616e07a174cb3fe66666666666"
        "66a17ac71a0193a33c6638920102c410000000000000f43f0000000000000cc0a152c72a0193a33c"
        "6638920202c420000000000000e03f9a9999999999b93f9a9999999999b93f000000000000d03fa9"
        "745f73656e745f6e73ce3b9aca7ba7657069736f646502"
    ),
    "track": (
        "88a17601a16ba5747261636ba47363616e07a174cb3fe6666666666666a178c7290193a33c663891"
        "04c420000000000000f03f0000000000000040000000000000e03f000000000000e0bfa150c78a01"
        "93a33c6638920404c480000000000000f03f00000000000000000000000000000000000000000000"
        "00000000000000000000000000000000004000000000000000000000000000000000000000000000"
        "00000000000000000000000000000000084000000000000000000000000000000000000000000000"
        "000000000000000000000000000000001040a9745f73656e745f6e73ce3b9acbc8a7657069736f64"
        "6502"
    ),
    "status": (
        "8ca17601a16ba6737461747573a47363616e07a174cb3fe6666666666666a7656e61626c656493a2"
        "7331a27334a27337a774726163655f50cb4024000000000000a874726163655f5064cb4029000000"
        "000000a576616c7565cb3fd8000000000000a9745f73656e745f6e73ce3b9acd15a7657069736f64"
        "6502a5667573656492a27331a27337a66661696c656491a27334"
    ),
    "hb": (
        "86a17601a16ba26862a4726f6c65a673656e736f72a76e6f64655f6964a27334a47363616e07a974"
        "5f73656e745f6e73ce3b9acde8"
    ),
    "ltrack": (
        "8ba17601a16ba66c747261636ba973656e736f725f6964a25333a47363616e07a174cb401c000000"
        "000000a178c7290193a33c66389104c420000000000000f03f0000000000000040000000000000e0"
        "3f000000000000e0bfa150c78a0193a33c6638920404c480000000000000f03f0000000000000000"
        "000000000000000000000000000000000000000000000000000000000000f03f0000000000000000"
        "000000000000000000000000000000000000000000000000000000000000f03f0000000000000000"
        "000000000000000000000000000000000000000000000000000000000000f03fa7785f7072696f72"
        "c7290193a33c66389104c420000000000000f83f0000000000000040000000000000000000000000"
        "0000e0bfa7505f7072696f72c78a0193a33c6638920404c480000000000000004000000000000000"
        "00000000000000000000000000000000000000000000000000000000000000004000000000000000"
        "00000000000000000000000000000000000000000000000000000000000000004000000000000000"
        "000000000000000000000000000000000000000000000000000000000000000040a9745f73656e74"
        "5f6e73ce3b9acd15a7657069736f646501"
    ),
}


# the mobile scenario's optional fields (kind: mobile); messages without them keep the bytes
# above (optional fields are omitted when unset)
GOLDEN_MOBILE_MSGS = {
    "truth-platforms": Truth(
        scan=7,
        t=7.0,
        target_ids=("T1",),
        states=np.array([[1.0, -2.0, 0.5, 0.0]]),
        sensor_ids=("S1", "S2"),
        platforms=np.array([[0.0, 3.0, 0.0, 3.0], [300.0, 0.0, -2.5, 0.0]]),
    ),
    "cmd-targets": Command(
        scan=7,
        t=7.0,
        enabled=("S1", "S2"),
        t_sent_ns=1_000_000_007,
        modes={"S1": "N", "S2": "stay"},
        targets={"S1": ("T1", "T3"), "S2": ()},
    ),
    "meas-target-ids": Measurement(
        sensor_id="S1",
        scan=7,
        t=7.0,
        z=np.array([[1.25, -3.5]]),
        R=np.array([[4.0, 0.0], [0.0, 4.0]]),
        t_sent_ns=1_000_000_123,
        target_ids=("T3",),
        platform=np.array([0.0, 3.0, 0.0, 3.0]),
    ),
    "track-target": Track(
        scan=7,
        t=7.0,
        x=np.array([1.0, 2.0, 0.5, -0.5]),
        P=np.eye(4),
        t_sent_ns=1_000_000_456,
        target_id="T1",
    ),
}

GOLDEN_MOBILE_HEX: dict[str, str] = {
    "truth-platforms": (
        "88a17601a16ba57472757468a47363616e07a174cb401c000000000000aa7461726765745f696473"
        "91a25431a6737461746573c72a0193a33c6638920104c420000000000000f03f00000000000000c0"
        "000000000000e03f0000000000000000aa73656e736f725f69647392a25331a25332a9706c617466"
        "6f726d73c74a0193a33c6638920204c4400000000000000000000000000000084000000000000000"
        "0000000000000008400000000000c07240000000000000000000000000000004c000000000000000"
        "00"
    ),
    "cmd-targets": (
        "89a17601a16ba3636d64a47363616e07a174cb401c000000000000a7656e61626c656492a25331a2"
        "5332a9745f73656e745f6e73ce3b9aca07a7657069736f646500a56d6f64657382a25331a14ea253"
        "32a473746179a77461726765747382a2533192a25431a25433a2533290"
    ),
    "meas-target-ids": (
        "8ba17601a16ba46d656173a973656e736f725f6964a25331a47363616e07a174cb401c0000000000"
        "00a17ac71a0193a33c6638920102c410000000000000f43f0000000000000cc0a152c72a0193a33c"
        "6638920202c4200000000000001040000000000000000000000000000000000000000000001040a9"
        "745f73656e745f6e73ce3b9aca7ba7657069736f646500aa7461726765745f69647391a25433a870"
        "6c6174666f726dc7290193a33c66389104c420000000000000000000000000000008400000000000"
        "0000000000000000000840"
    ),
    "track-target": (
        "89a17601a16ba5747261636ba47363616e07a174cb401c000000000000a178c7290193a33c663891"
        "04c420000000000000f03f0000000000000040000000000000e03f000000000000e0bfa150c78a01"
        "93a33c6638920404c480000000000000f03f00000000000000000000000000000000000000000000"
        "00000000000000000000000000000000f03f00000000000000000000000000000000000000000000"
        "00000000000000000000000000000000f03f00000000000000000000000000000000000000000000"
        "00000000000000000000000000000000f03fa9745f73656e745f6e73ce3b9acbc8a7657069736f64"
        "6500a97461726765745f6964a25431"
    ),
}


def test_golden_covers_every_kind():
    assert set(GOLDEN_MSGS) == {cls.KIND for cls in MESSAGE_TYPES} == set(GOLDEN_HEX)
    assert SCHEMA_VERSION == 1, "a new schema version needs a new golden table"


@pytest.mark.parametrize("kind", sorted(GOLDEN_HEX))
def test_golden_bytes(kind):
    golden = bytes.fromhex(GOLDEN_HEX[kind])
    assert encode(GOLDEN_MSGS[kind]) == golden
    assert decode(golden) == GOLDEN_MSGS[kind]


@pytest.mark.parametrize("name", sorted(GOLDEN_MOBILE_MSGS))
def test_golden_bytes_mobile(name):
    golden = bytes.fromhex(GOLDEN_MOBILE_HEX[name])
    assert encode(GOLDEN_MOBILE_MSGS[name]) == golden
    assert decode(golden) == GOLDEN_MOBILE_MSGS[name]


def test_unset_optional_fields_are_omitted():
    assert set(_raw(GOLDEN_MSGS["truth"])) == {"v", "k", "scan", "t", "target_ids", "states"}
    assert "targets" not in _raw(GOLDEN_MSGS["cmd"])
    assert not {"target_ids", "platform"} & set(_raw(GOLDEN_MSGS["meas"]))
    assert "target_id" not in _raw(GOLDEN_MSGS["track"])


# --------------------------------------------------------------------------------------------
# rejection: every reason, each triggered by a crafted payload
# --------------------------------------------------------------------------------------------


def _raw(msg) -> dict:
    """The wire map of ``msg`` with arrays left as raw ExtType (to tamper with)."""
    return msgpack.unpackb(encode(msg), raw=False)


def _pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def _ext(dtype="<f8", shape=(1, 2), raw=None, code=1):
    if raw is None:
        raw = np.zeros(math.prod(shape), "<f8").tobytes()
    return msgpack.ExtType(code, _pack([dtype, list(shape), raw]))


def _with(msg, **changes) -> bytes:
    d = _raw(msg)
    for k, v in changes.items():
        if v is _DROP:
            del d[k]
        else:
            d[k] = v
    return _pack(d)


_DROP = object()
MEAS = GOLDEN_MSGS["meas"]
TRACK = GOLDEN_MSGS["track"]
TRUTH = GOLDEN_MSGS["truth"]
CMD = GOLDEN_MSGS["cmd"]
VALID = encode(MEAS)

# (payload, decoded as: None = decode(), or a class for decode_as, expected reason)
REJECT = {
    "garbage": (b"\xc1", None, "not_msgpack"),
    "empty": (b"", None, "not_msgpack"),
    "trailing-bytes": (VALID + b"\x00", None, "not_msgpack"),
    "bad-utf8": (b"\x81\xa2\xff\xfe\x01", None, "not_msgpack"),
    "deep-nesting": (b"\x91" * 5000 + b"\x01", None, "not_msgpack"),
    "truncated-1": (VALID[:-1], None, "truncated"),
    "truncated-half": (VALID[: len(VALID) // 2], None, "truncated"),
    "truncated-header": (b"\x88", None, "truncated"),
    "payload-too-large": (b"\x00" * (MAX_PAYLOAD_BYTES + 1), None, "too_large"),
    "too-many-ids": (_with(CMD, enabled=[f"s{i}" for i in range(MAX_IDS + 1)]), None, "too_large"),
    "array-too-large": (
        _with(MEAS, z=_ext(shape=(MAX_ARRAY_ELEMENTS, 2), raw=b"")),
        None,
        "too_large",
    ),
    "list-header-huge": (b"\xdd\xff\xff\xff\xff", None, "too_large"),
    "not-a-map-list": (_pack([1, 2, 3]), None, "not_a_map"),
    "not-a-map-int": (_pack(7), None, "not_a_map"),
    "version-2": (_with(MEAS, v=2), None, "bad_version"),
    "version-missing": (_with(MEAS, v=_DROP), None, "bad_version"),
    "version-str": (_with(MEAS, v="1"), None, "bad_version"),
    "version-bool": (_with(MEAS, v=True), None, "bad_version"),
    "unknown-kind": (_with(MEAS, k="bogus"), None, "unknown_kind"),
    "kind-not-str": (_with(MEAS, k=3), None, "unknown_kind"),
    "kind-missing": (_with(MEAS, k=_DROP), None, "missing_field"),
    "wrong-kind": (VALID, Track, "wrong_kind"),
    "wrong-kind-unknown": (_with(MEAS, k="bogus"), Measurement, "wrong_kind"),
    "missing-field": (_with(MEAS, scan=_DROP), None, "missing_field"),
    "missing-array": (_with(MEAS, R=_DROP), Measurement, "missing_field"),
    "unknown-field": (_with(MEAS, extra=1), None, "unknown_field"),
    "bool-as-int": (_with(MEAS, scan=True), None, "bad_type"),
    "float-as-int": (_with(MEAS, scan=7.0), None, "bad_type"),
    "int-as-float": (_with(MEAS, t=1), None, "bad_type"),
    "bytes-as-str": (_with(MEAS, sensor_id=b"s4"), None, "bad_type"),
    "int-as-str": (_with(MEAS, sensor_id=4), None, "bad_type"),
    "str-as-ids": (_with(CMD, enabled="s1"), None, "bad_type"),
    "int-in-ids": (_with(CMD, enabled=["s1", 2]), None, "bad_type"),
    "list-as-array": (_with(MEAS, z=[[1.0, 2.0]]), None, "bad_type"),
    "array-as-float": (_with(MEAS, t=_ext(shape=(1,))), None, "bad_type"),
    "array-f4": (_with(MEAS, z=_ext(dtype="<f4", raw=b"\x00" * 8)), None, "bad_type"),
    "array-big-endian": (_with(MEAS, z=_ext(dtype=">f8")), None, "bad_type"),
    "array-unknown-ext": (_with(MEAS, z=_ext(code=9)), None, "bad_type"),
    "array-ext-garbage": (_with(MEAS, z=msgpack.ExtType(1, b"\xc1")), None, "bad_type"),
    "map-key-int": (_pack({1: 2, "v": 1, "k": "meas"}), None, "bad_type"),
    "modes-nil": (_with(CMD, modes=None), None, "bad_type"),
    "modes-not-map": (_with(CMD, modes=["s1"]), None, "bad_type"),
    "counts-nil": (_with(GOLDEN_MSGS["hb"], rejected=None), None, "bad_type"),
    "counts-float": (_with(GOLDEN_MSGS["hb"], rejected={"x": 1.0}), None, "bad_type"),
    "counts-negative": (_with(GOLDEN_MSGS["hb"], rejected={"x": -1}), None, "bad_value"),
    "nil-required": (_with(MEAS, scan=None), None, "bad_type"),
    "array-3d": (_with(MEAS, z=_ext(shape=(1, 1, 2))), None, "bad_shape"),
    "array-bytes-short": (_with(MEAS, z=_ext(shape=(1, 2), raw=b"\x00" * 8)), None, "bad_shape"),
    "array-negative-dim": (_with(MEAS, z=_ext(shape=(-1, 2), raw=b"")), None, "bad_shape"),
    "z-vs-R": (_with(MEAS, z=_ext(shape=(1, 3))), None, "bad_shape"),
    "R-not-square": (_with(MEAS, R=_ext(shape=(2, 3))), None, "bad_shape"),
    "x-2d": (_with(TRACK, x=_ext(shape=(4, 1))), None, "bad_shape"),
    "P-vs-x": (_with(TRACK, P=_ext(shape=(3, 3))), None, "bad_shape"),
    "states-vs-ids": (_with(TRUTH, target_ids=["tgt0"]), None, "bad_shape"),
    "nan-float": (_with(MEAS, t=math.nan), None, "non_finite"),
    "inf-float": (_with(MEAS, t=-math.inf), None, "non_finite"),
    "nan-array": (
        _with(MEAS, z=_ext(raw=np.array([1.0, np.nan], "<f8").tobytes())),
        None,
        "non_finite",
    ),
    "inf-array": (
        _with(TRACK, x=_ext(shape=(4,), raw=np.array([0, 0, 0, np.inf], "<f8").tobytes())),
        Track,
        "non_finite",
    ),
    "negative-scan": (_with(MEAS, scan=-1), None, "bad_value"),
    "negative-stamp": (_with(MEAS, t_sent_ns=-5), None, "bad_value"),
    "uint64-stamp": (_with(MEAS, t_sent_ns=2**64 - 1), None, "bad_value"),
    "slash-in-id": (_with(MEAS, sensor_id="s/4"), None, "bad_value"),
    "wildcard-in-id": (_with(MEAS, sensor_id="*"), None, "bad_value"),
    "empty-id": (_with(MEAS, sensor_id=""), None, "bad_value"),
    "long-id": (_with(MEAS, sensor_id="s" * 65), None, "bad_value"),
    "duplicate-ids": (_with(CMD, enabled=["s1", "s1"]), None, "bad_value"),
    # the mobile scenario's optional fields
    "targets-nil": (_with(CMD, targets=None), None, "bad_type"),
    "targets-not-map": (_with(CMD, targets=["S1"]), None, "bad_type"),
    "targets-str-value": (_with(CMD, targets={"S1": "T1"}), None, "bad_type"),
    "targets-int-id": (_with(CMD, targets={"S1": [1]}), None, "bad_type"),
    "targets-duplicate": (_with(CMD, targets={"S1": ["T1", "T1"]}), None, "bad_value"),
    "targets-bad-key": (_with(CMD, targets={"S/1": []}), None, "bad_value"),
    "targets-too-many": (
        _with(CMD, targets={"S1": [f"T{i}" for i in range(MAX_IDS + 1)]}),
        None,
        "too_large",
    ),
    "platforms-without-ids": (_with(TRUTH, platforms=_ext(shape=(1, 4))), None, "bad_shape"),
    "ids-without-platforms": (_with(TRUTH, sensor_ids=["S1"]), None, "bad_shape"),
    "platforms-vs-ids": (
        _with(TRUTH, sensor_ids=["S1"], platforms=_ext(shape=(2, 4))),
        None,
        "bad_shape",
    ),
    "platforms-3-cols": (
        _with(TRUTH, sensor_ids=["S1"], platforms=_ext(shape=(1, 3))),
        None,
        "bad_shape",
    ),
    "platforms-nil": (_with(TRUTH, sensor_ids=["S1"], platforms=None), None, "bad_type"),
    "platforms-nan": (
        _with(
            TRUTH,
            sensor_ids=["S1"],
            platforms=_ext(shape=(1, 4), raw=np.array([0, 0, np.nan, 0], "<f8").tobytes()),
        ),
        None,
        "non_finite",
    ),
    "meas-target-ids-vs-z": (_with(MEAS, target_ids=["T1", "T2"]), None, "bad_shape"),
    "meas-target-ids-duplicate": (_with(MEAS, target_ids=["T1", "T1"]), None, "bad_value"),
    "meas-target-ids-nil": (_with(MEAS, target_ids=None), None, "bad_type"),
    "meas-platform-shape": (_with(MEAS, platform=_ext(shape=(2,))), None, "bad_shape"),
    "meas-platform-2d": (_with(MEAS, platform=_ext(shape=(1, 4))), None, "bad_shape"),
    "meas-platform-list": (_with(MEAS, platform=[0.0, 0.0, 0.0, 0.0]), None, "bad_type"),
    "track-target-id-int": (_with(TRACK, target_id=1), None, "bad_type"),
    "track-target-id-bad": (_with(TRACK, target_id="T*"), None, "bad_value"),
    "track-target-id-nil": (_with(TRACK, target_id=None), None, "bad_type"),
}


def test_every_reason_is_exercised():
    # key_mismatch is about the key a payload came on: test_decode_command_checks_its_key
    assert {reason for _, _, reason in REJECT.values()} | {"key_mismatch"} == REASONS


@pytest.mark.parametrize("case", sorted(REJECT))
def test_rejects(case):
    payload, cls, reason = REJECT[case]
    with pytest.raises(WireError) as info:
        decode(payload) if cls is None else decode_as(payload, cls)
    assert info.value.reason == reason, info.value
    assert isinstance(info.value, ValueError)
    assert info.value.detail in str(info.value)


def test_non_bytes_payload_is_a_programming_error():
    with pytest.raises(TypeError):
        decode("not bytes")  # type: ignore[arg-type]


def test_wire_error_reasons_are_fixed():
    with pytest.raises(AssertionError):
        WireError("made_up", "x")


# --------------------------------------------------------------------------------------------
# hypothesis: round trips of generated messages, and fuzzing the decoder
# --------------------------------------------------------------------------------------------

names = st.text(string.ascii_letters + string.digits + "_-.:", min_size=1, max_size=12)
id_tuples = st.lists(names, max_size=6, unique=True).map(tuple)
finite = st.floats(allow_nan=False, allow_infinity=False)
counts = st.integers(0, 2**63 - 1)


def _mat(rows, cols):
    return arrays(np.float64, (rows, cols), elements=finite)


@st.composite
def truths(draw):
    ids = draw(id_tuples)
    states = draw(_mat(len(ids), draw(st.integers(1, 6))))
    return Truth(draw(counts), draw(finite), ids, states)


@st.composite
def measurements(draw):
    dz = draw(st.integers(1, 4))
    z = draw(_mat(draw(st.integers(0, 5)), dz))
    R = draw(_mat(dz, dz))
    return Measurement(draw(names), draw(counts), draw(finite), z, R, draw(counts), draw(counts))


@st.composite
def tracks(draw):
    n = draw(st.integers(1, 6))
    x = draw(arrays(np.float64, (n,), elements=finite))
    return Track(draw(counts), draw(finite), x, draw(_mat(n, n)), draw(counts), draw(counts))


commands = st.builds(
    Command,
    scan=counts,
    t=finite,
    enabled=id_tuples,
    t_sent_ns=counts,
    episode=counts,
    modes=st.none() | st.dictionaries(names, names, max_size=4),
)
statuses = st.builds(
    Status,
    scan=counts,
    t=finite,
    enabled=id_tuples,
    trace_P=finite,
    trace_Pd=finite,
    value=finite,
    t_sent_ns=counts,
    episode=counts,
    fused=id_tuples,
    failed=id_tuples,
)
heartbeats = st.builds(
    Heartbeat,
    role=names,
    node_id=names,
    scan=counts,
    t_sent_ns=counts,
    rejected=st.none() | st.dictionaries(names, counts, max_size=4),
)
any_message = st.one_of(truths(), measurements(), tracks(), commands, statuses, heartbeats)


@given(any_message)
def test_hypothesis_round_trip(msg):
    payload = encode(msg)
    assert decode(payload) == msg
    assert decode_as(payload, type(msg)) == msg
    assert encode(decode(payload)) == payload


def _decode_or_wire_error(payload: bytes):
    try:
        return decode(payload)
    except WireError as e:
        assert e.reason in REASONS
        return None


@given(st.binary(max_size=600))
def test_fuzz_random_bytes_raise_only_wire_error(payload):
    _decode_or_wire_error(payload)


GOLDEN_PAYLOADS = [bytes.fromhex(h) for h in GOLDEN_HEX.values()]


@given(st.sampled_from(GOLDEN_PAYLOADS), st.data())
def test_fuzz_mutated_payloads_raise_only_wire_error(payload, data):
    buf = bytearray(payload)
    for _ in range(data.draw(st.integers(1, 4))):
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
    _decode_or_wire_error(bytes(buf))


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=8)
    | st.binary(max_size=8)
    | st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=16)),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4)
    ),
    max_leaves=12,
)


@given(
    st.sampled_from(GOLDEN_PAYLOADS),
    st.dictionaries(
        st.sampled_from(["v", "k", "scan", "t", "z", "R", "x", "P", "enabled", "zz"]),
        msgpack_values,
        max_size=3,
    ),
)
def test_fuzz_structured_payloads_raise_only_wire_error(payload, overrides):
    d = msgpack.unpackb(payload, raw=False)
    d.update(overrides)
    _decode_or_wire_error(_pack(d))


# --------------------------------------------------------------------------------------------
# key expressions
# --------------------------------------------------------------------------------------------

KEYS = [
    (m.truth_key("r1"), "covnet/r1/truth"),
    (m.command_key("r1", ["s1", "s3"]), "covnet/r1/cmd/~s1~s3~"),
    (m.command_key("r1", []), "covnet/r1/cmd/~"),
    (m.command_keyexpr("r1"), "covnet/r1/cmd/*"),
    (m.command_keyexpr("r1", "s3"), "covnet/r1/cmd/$*~s3~$*"),
    (m.measurement_key("r1", "s3"), "covnet/r1/sensor/s3/meas"),
    (m.measurement_keyexpr("r1"), "covnet/r1/sensor/*/meas"),
    (m.track_key("r1"), "covnet/r1/track"),
    (m.status_key("r1"), "covnet/r1/manager/status"),
    (m.heartbeat_key("r1", "sensor", "s3"), "covnet/r1/hb/sensor/s3"),
    (m.heartbeat_keyexpr("r1"), "covnet/r1/hb/*/*"),
    (m.alive_key("r1", "sensor", "s3"), "covnet/r1/alive/sensor/s3"),
    (m.alive_keyexpr("r1"), "covnet/r1/alive/*/*"),
    (m.alive_keyexpr("r1", "sensor"), "covnet/r1/alive/sensor/*"),
]


@pytest.mark.parametrize(("built", "expected"), KEYS, ids=[e for _, e in KEYS])
def test_key_layout(built, expected):
    assert built == expected


@pytest.mark.parametrize("bad", ["", "a/b", "a*", "**", "$x", "a?", "a#", "a b", "a\tb", "x" * 65])
def test_key_builders_reject_bad_ids(bad):
    with pytest.raises(ValueError, match="invalid run id"):
        m.truth_key(bad)
    with pytest.raises(ValueError, match="invalid sensor id"):
        m.measurement_key("r1", bad)
    with pytest.raises(ValueError, match="invalid role"):
        m.alive_key("r1", bad, "n")
    with pytest.raises(ValueError, match="invalid node id"):
        m.heartbeat_key("r1", "sensor", bad)


def test_parse_keys():
    assert m.parse_alive_key(m.alive_key("r1", "sensor", "s3")) == ("sensor", "s3")
    assert m.parse_measurement_key(m.measurement_key("r1", "s3")) == "s3"
    for bad in [
        "covnet/r1/alive/sensor",
        "covnet/r1/hb/sensor/s3",
        "x/r1/alive/a/b",
        "covnet/r1/alive/a/b/c",
    ]:
        with pytest.raises(ValueError):
            m.parse_alive_key(bad)
    with pytest.raises(ValueError):
        m.parse_measurement_key("covnet/r1/sensor/s3/cmd")


def test_parse_command_key_inverts_command_key():
    for enabled in [(), ("s1",), ("s3", "s1", "a.b-c_d")]:
        assert m.parse_command_key(m.command_key("r1", enabled)) == enabled
    for bad in [
        "covnet/r1/cmd",
        "covnet/r1/cmd/",
        "covnet/r1/cmd/s1",
        "covnet/r1/cmd/~s1",
        "covnet/r1/cmd/~s1~~",
        "covnet/r1/cmd/~s1~/x",
        "covnet/r1/track",
        "other/r1/cmd/~",
    ]:
        with pytest.raises(ValueError):
            m.parse_command_key(bad)
    with pytest.raises(ValueError, match="must not contain"):
        m.command_key("r1", ["a~b"])
    with pytest.raises(ValueError, match="invalid sensor id"):
        m.command_key("r1", ["a/b"])


def test_decode_command_checks_its_key():
    cmd = m.Command(scan=3, t=3.0, enabled=("s2", "s1"), t_sent_ns=7)
    payload = encode(cmd)
    got = m.decode_command(m.command_key("r1", ("s2", "s1")), payload)
    assert (got.scan, got.enabled) == (3, ("s2", "s1"))
    for key in [
        m.command_key("r1", ("s1", "s2")),  # the same set, another order: not its key
        m.command_key("r1", ("s2",)),
        m.command_key("r1", ("s2", "s1", "s3")),
        m.command_key("r1", ()),
        m.truth_key("r1"),
    ]:
        with pytest.raises(WireError) as info:
            m.decode_command(key, payload)
        assert info.value.reason == "key_mismatch"
    with pytest.raises(WireError) as info:  # the payload is judged first
        m.decode_command(m.truth_key("r1"), b"\xc1")
    assert info.value.reason == "not_msgpack"


def test_new_run_id_is_short_unique_and_valid():
    ids = {m.new_run_id() for _ in range(200)}
    assert len(ids) == 200
    for run in ids:
        assert len(run) == 12
        m.truth_key(run)


if __name__ == "__main__":  # print fresh GOLDEN_HEX and GOLDEN_MOBILE_HEX tables
    for table, msgs in (("GOLDEN_HEX", GOLDEN_MSGS), ("GOLDEN_MOBILE_HEX", GOLDEN_MOBILE_MSGS)):
        print(f"{table} = {{")
        for kind, golden_msg in msgs.items():
            hexed = encode(golden_msg).hex()
            print(f'    "{kind}": (')
            for i in range(0, len(hexed), 80):
                print(f'        "{hexed[i : i + 80]}"')
            print("    ),")
        print("}")


def test_command_windows_are_checked():
    """Many targets: a clutter window only for an enabled sensor, finite, a vector."""
    ok = Command(1, 1.0, ("R1",), 0, targets={"R1": ("T1",)}, windows={"R1": [1.0, 2.0, 3.0, 4.0]})
    assert decode(encode(ok)) == ok
    assert ok.windows is not None and ok.windows["R1"].dtype == np.float64
    for windows, reason in (
        ({"B1": [1.0, 2.0]}, "bad_value"),
        ({"R1": [1.0, math.inf]}, "non_finite"),
        ({"R1": [[1.0, 2.0]]}, "bad_shape"),
        ({"R1": "wide"}, "bad_type"),
    ):
        with pytest.raises(WireError) as info:
            Command(1, 1.0, ("R1",), 0, windows=windows)
        assert info.value.reason == reason, windows
