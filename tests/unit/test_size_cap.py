"""The payload size cap (issue 14, "Flood test"): :data:`covnet.wire.messages.MAX_PAYLOAD_BYTES` is
large enough for the largest legitimate message of every kind, and every bus drops a payload
over it before copying it, counting it by (key, reason) on the receiving handle."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from covnet.processes.up import free_port
from covnet.wire import messages as m
from covnet.wire.bus import MAX_DROP_KEYS, OVERSIZE, DropCounter, InMemoryBus, InMemoryHub, dropped
from covnet.wire.latency_bus import DelayedBus
from covnet.wire.zenoh_bus import KEY_HEADROOM_BYTES, ZenohBus, zenoh_config

# --------------------------------------------------------------------------------------------
# the cap is computed from the schemas
# --------------------------------------------------------------------------------------------


def _ids(prefix: str, n: int) -> tuple[str, ...]:
    """``n`` distinct ids of :data:`~covnet.wire.messages.MAX_NAME_LEN` characters."""
    return tuple(f"{prefix}{i:d}".ljust(m.MAX_NAME_LEN, "x") for i in range(n))


def _largest_messages(n_sensors: int, n_targets: int, rows: int) -> list[m.Message]:
    """The largest message of every kind a network of that size sends (ids at the longest,
    every list full, every optional field set, the dimensions of
    :func:`~covnet.wire.messages.payload_bounds`)."""
    sids, tids = _ids("S", n_sensors), _ids("T", n_targets)
    n, dz = m.CAP_STATE_DIM, m.CAP_MEAS_DIM
    big = 2**63 - 1
    rng = np.random.default_rng(1)
    # every target goes to one sensor (the mobile decision's coverage constraint)
    owner = {s: tids[i::n_sensors] for i, s in enumerate(sids)}
    z, states, platforms = (
        rng.normal(size=(rows, dz)),
        rng.normal(size=(n_targets, n)),
        rng.normal(size=(n_sensors, 4)),
    )
    x, P = rng.normal(size=n), np.eye(n)
    modes = {s: "M" * m.MAX_NAME_LEN for s in sids}
    reasons = {r: big for r in _ids("r", m.CAP_REASONS)}
    refiltered = _ids("R", m.MAX_IDS)
    return [
        m.Truth(big, 1.5, tids, states, sids, platforms),
        m.Command(big, 1.5, sids, big, big, modes, owner, {s: z[0].repeat(2) for s in sids}),
        m.Measurement(sids[0], big, 1.5, z, np.eye(dz), big, big, _ids("T", rows), x[:4], big),
        m.Track(big, 1.5, x, P, big, big, tids[0], sids[0], "S" * m.MAX_NAME_LEN),
        m.Status(big, 1.5, sids, 1.5, 1.5, 1.5, big, big, sids, sids, sids[0], refiltered,
                 rng.normal(size=m.CAP_CELLS)),  # fmt: skip
        m.LocalTrack(sids[0], big, 1.5, x, P, x, P, big, big, big, tids[0]),
        m.Heartbeat("sensor", sids[0], big, big, reasons, big, "C" * m.MAX_NAME_LEN,
                    "H" * m.MAX_NAME_LEN),  # fmt: skip (its config and host)
    ]


@pytest.mark.parametrize("size", [(8, 1, 1), (50, 100, 100), (300, 200, 256), (1024, 1024, 1024)])
def test_payload_bounds_hold_for_every_kind_and_are_tight(size):
    bounds = m.payload_bounds(*size)
    assert set(bounds) == {cls.KIND for cls in m.MESSAGE_TYPES}
    for x in _largest_messages(*size):
        n = len(m.encode(x))
        assert n <= bounds[x.KIND], (x.KIND, n, bounds[x.KIND])
        # and close to it (within 10 %, or a few headers on a small message)
        assert n >= 0.9 * bounds[x.KIND] or bounds[x.KIND] - n < 256, (x.KIND, n, bounds[x.KIND])
        assert m.decode(m.encode(x)) == x  # none is over the cap
    assert m.largest_payload(*size) == max(bounds.values())


def test_the_cap_is_twice_the_largest_message_rounded_to_a_power_of_two():
    largest = m.largest_payload(m.CAP_SENSORS, m.CAP_TARGETS, m.CAP_ROWS)
    cap = m.MAX_PAYLOAD_BYTES
    assert cap == 1 << 20 and cap & (cap - 1) == 0
    assert 2 * largest <= cap < 4 * largest
    assert m.CAP_SENSORS >= 1000  # "hundreds of sensors"
    with pytest.raises(m.WireError) as e:
        m.decode(b"\x80" * (cap + 1))
    assert e.value.reason == "too_large"


# --------------------------------------------------------------------------------------------
# the in-memory bus
# --------------------------------------------------------------------------------------------


class _Unreadable(bytes):
    """A payload that fails the test if it is ever copied."""

    def __bytes__(self) -> bytes:
        raise AssertionError("the oversized payload was copied")


def test_in_memory_bus_drops_oversized_payloads_on_the_receiving_handle():
    hub = InMemoryHub()
    small = InMemoryBus(hub, name="small", max_payload=100)
    default = InMemoryBus(hub, name="default")
    sender = InMemoryBus(hub, name="sender", max_payload=10)  # the sender's own cap is not used
    subs = [small.subscribe("a/**"), small.subscribe("a/b"), default.subscribe("a/*")]
    sender.publish("a/b", b"x" * 100)  # at the cap: delivered
    sender.publish("a/b", b"y" * 101)  # over it: dropped by `small`'s two subscriptions
    sender.publish("a/c", b"z" * 101)
    assert [len(s.payload) for s in iter(subs[0].try_recv, None)] == [100]
    assert [len(s.payload) for s in iter(subs[1].try_recv, None)] == [100]
    assert [s.key for s in iter(subs[2].try_recv, None)] == ["a/b", "a/b", "a/c"]
    # a handle counts its own drops, per subscription that dropped the payload
    assert small.dropped() == {"a/b": {OVERSIZE: 2}, "a/c": {OVERSIZE: 1}}
    assert default.dropped() == {} and sender.dropped() == {}
    assert dropped(small) == small.dropped()


def test_in_memory_bus_never_copies_a_payload_it_drops():
    hub = InMemoryHub()
    receiver = InMemoryBus(hub, max_payload=100)
    sub = receiver.subscribe("k")
    InMemoryBus(hub).publish("k", _Unreadable(b"y" * 101))
    assert sub.try_recv() is None and receiver.dropped() == {"k": {OVERSIZE: 1}}
    with pytest.raises(AssertionError, match="copied"):  # the probe works
        InMemoryBus(hub).publish("k", _Unreadable(b"y" * 100))


def test_in_memory_bus_cap_defaults_to_the_wire_cap_and_is_validated():
    bus = InMemoryBus()
    assert bus.max_payload == m.MAX_PAYLOAD_BYTES
    sub = bus.subscribe("k")
    bus.publish("k", b"\0" * (m.MAX_PAYLOAD_BYTES + 1))
    bus.publish("k", b"ok")
    assert sub.recv(1.0).payload == b"ok"
    assert bus.dropped() == {"k": {OVERSIZE: 1}}
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError):
            InMemoryBus(max_payload=bad)


def test_drop_counter_is_bounded_and_thread_safe():
    c = DropCounter()
    for i in range(MAX_DROP_KEYS + 50):
        c.add(f"run/sensor/x{i}/meas", OVERSIZE, "run/sensor/*/meas")
    snap = c.snapshot()
    assert len(snap) == MAX_DROP_KEYS + 1
    assert snap["run/sensor/*/meas"] == {OVERSIZE: 50}
    c.add("run/sensor/x0/meas", "other", "run/sensor/*/meas")  # a known key stays itself
    assert c.snapshot()["run/sensor/x0/meas"] == {OVERSIZE: 1, "other": 1}

    d = DropCounter()
    threads = [
        threading.Thread(target=lambda: [d.add("k", OVERSIZE, "k") for _ in range(2000)])
        for _ in range(4)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert d.snapshot() == {"k": {OVERSIZE: 8000}}


def test_dropped_reads_any_bus():
    inner = InMemoryBus(max_payload=1)
    sub = inner.subscribe("k")
    wrapped = DelayedBus(inner, outgoing={}, incoming={})
    try:
        wrapped.publish("k", b"xx")
        assert sub.try_recv() is None
        assert dropped(wrapped) == {"k": {OVERSIZE: 1}}  # through the wrapper to its bus
    finally:
        wrapped.close()
    assert dropped(object()) == {}


# --------------------------------------------------------------------------------------------
# zenoh: its own cap (the link), then the bus's (the subscription)
# --------------------------------------------------------------------------------------------


def test_zenoh_config_sets_the_link_cap_and_turns_shared_memory_off():
    c = zenoh_config("client", connect=["tcp/127.0.0.1:7447"])
    cap = m.MAX_PAYLOAD_BYTES + KEY_HEADROOM_BYTES
    assert c.get_json("transport/link/rx/max_message_size") == str(cap)
    assert c.get_json("transport/shared_memory/enabled") == "false"
    small = zenoh_config("router", max_payload=1000, extra_json5={"adminspace/enabled": False})
    assert small.get_json("transport/link/rx/max_message_size") == str(1000 + KEY_HEADROOM_BYTES)
    with pytest.raises(ValueError):
        zenoh_config("client", max_payload=0)


def _third_party(endpoint: str) -> zenoh.Session:
    """A client with zenoh's own defaults (shared memory on), as a stranger would open it."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_zenoh_drops_oversized_payloads_and_keeps_the_sender_s_session():
    """A router with the covnet config; a stranger with zenoh's defaults sends payloads around
    the two caps on one key: under the bus cap delivered; between the bus cap and zenoh's
    dropped by both subscriptions and counted; over zenoh's (and through shared memory, which
    the stranger has on) dropped by zenoh, uncounted; the stranger's link and token stay."""
    cap = 200_000
    ep = f"tcp/127.0.0.1:{free_port()}"
    with ZenohBus.open(zenoh_config("router", listen=[ep], max_payload=cap), max_payload=cap) as r:
        fifo, stamped = r.subscribe("t/**"), r.subscribe_stamped("t/**")
        alive = r.watch_liveliness("alive/*")
        stranger = _third_party(ep)
        try:
            token = stranger.liveliness().declare_token("alive/stranger")
            ev = alive.recv(10.0)
            assert ev is not None and ev.alive
            block = zenoh.CongestionControl.BLOCK
            pub = stranger.declare_publisher("t/x", congestion_control=block)
            # the router hears the stranger's puts once its subscription has reached it
            deadline = time.monotonic() + 10
            while fifo.recv(0.05) is None:
                assert time.monotonic() < deadline
                pub.put(b"probe")
            sizes = [10, cap, cap + 1, cap + KEY_HEADROOM_BYTES // 2, 3 << 20, 12 << 20, 5000, 7]
            for n in sizes:
                pub.put(b"\x01" * n)
            for sub in (fifo, stamped):  # the last one, 7 bytes, ends each list
                got: list[int] = []
                while not got or got[-1] != 7:
                    s = sub.recv(10.0)
                    assert s is not None, got
                    # (the stamped one also hears the FIFO's local wake samples: empty DELETEs)
                    if s.payload not in (b"probe", b""):
                        got.append(len(s.payload))
                assert got == [10, cap, 5000, 7]
            assert r.dropped() == {"t/x": {OVERSIZE: 4}}  # 2 payloads x 2 subscriptions
            assert alive.try_recv() is None  # the stranger's token never went
            token.undeclare()
            ev = alive.recv(10.0)
            assert ev is not None and not ev.alive
        finally:
            stranger.close()
