"""The Bus seam: key-expression matching, InMemoryBus pub/sub and liveliness, and the clocks."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from covnet.clock import SimClock, WallClock
from covnet.wire import messages as m
from covnet.wire.bus import (
    BusClosed,
    Channel,
    InMemoryBus,
    InMemoryHub,
    LivelinessEvent,
    check_key,
    check_keyexpr,
    keyexpr_matches,
)

# --------------------------------------------------------------------------------------------
# key expressions (zenoh semantics: * is one chunk, ** is zero or more chunks, $* is any run of
# characters inside a chunk)
# --------------------------------------------------------------------------------------------

MATCHES = [
    ("a/b/c", "a/b/c", True),
    ("a/b/c", "a/b", False),
    ("a/b", "a/b/c", False),
    ("a/*/c", "a/b/c", True),
    ("a/*/c", "a/c", False),
    ("a/*/c", "a/b/x/c", False),
    ("a/*", "a/b", True),
    ("a/*", "a", False),
    ("*", "a", True),
    ("*", "a/b", False),
    ("a/**", "a", True),
    ("a/**", "a/b", True),
    ("a/**", "a/b/c/d", True),
    ("a/**", "b/a", False),
    ("**", "a", True),
    ("**", "a/b/c", True),
    ("**/c", "c", True),
    ("**/c", "a/b/c", True),
    ("**/c", "a/b/c/d", False),
    ("a/**/c", "a/c", True),
    ("a/**/c", "a/b/c", True),
    ("a/**/c", "a/b/b/c", True),
    ("a/**/c", "a/b/b/d", False),
    ("a/**/b/**/c", "a/x/b/y/z/c", True),
    ("a/**/b/**/c", "a/b/c", True),
    ("a/**/b/**/c", "a/c", False),
    ("a/*/**", "a", False),
    ("a/*/**", "a/b", True),
    ("a/**/*", "a/b/c", True),
    ("**/**", "a", True),
    ("ab", "a", False),
    ("a", "ab", False),
    ("covnet/r1/sensor/*/meas", m.measurement_key("r1", "s7"), True),
    ("covnet/r1/sensor/*/meas", m.measurement_key("r2", "s7"), False),
    ("covnet/r1/alive/sensor/*", m.alive_key("r1", "sensor", "s1"), True),
    ("covnet/r1/alive/sensor/*", m.alive_key("r1", "manager", "m"), False),
    ("covnet/r1/**", m.status_key("r1"), True),
    ("a/x$*y", "a/xy", True),
    ("a/x$*y", "a/x~~y", True),
    ("a/x$*y", "a/xy/y", False),
    ("a/$*b", "a/b", True),
    ("a/$*b", "a/bc", False),
    ("a/b$*", "a/bc", True),
    ("a/$*.$*", "a/x.y", True),
    ("a/$*.$*", "a/xy", False),
    (m.command_keyexpr("r1", "S1"), m.command_key("r1", ["S1", "S3"]), True),
    (m.command_keyexpr("r1", "S3"), m.command_key("r1", ["S1", "S3"]), True),
    (m.command_keyexpr("r1", "S1"), m.command_key("r1", ["S11", "S3"]), False),
    (m.command_keyexpr("r1", "S1"), m.command_key("r1", ["S3", "xS1"]), False),
    (m.command_keyexpr("r1", "S1"), m.command_key("r1", []), False),
    (m.command_keyexpr("r1", "S1"), m.command_key("r2", ["S1"]), False),
    (m.command_keyexpr("r1"), m.command_key("r1", []), True),
]


@pytest.mark.parametrize(
    ("expr", "key", "expected"), MATCHES, ids=[f"{e}~{k}" for e, k, _ in MATCHES]
)
def test_keyexpr_matches(expr, key, expected):
    assert keyexpr_matches(expr, key) is expected


@pytest.mark.parametrize(
    "bad",
    ["", "/a", "a/", "a//b", "a*", "*a/b", "a/**b", "a/$*", "a/$*$*b", "a/b$", "a/$$", "a?b",
     "a#", "a b", "a/$***"],
)  # fmt: skip
def test_invalid_keyexprs(bad):
    with pytest.raises(ValueError, match="invalid key expression"):
        check_keyexpr(bad)


@pytest.mark.parametrize("bad", ["a/*", "**", "a/**/b", "a/x$*"])
def test_keys_are_concrete(bad):
    check_keyexpr(bad)
    with pytest.raises(ValueError, match="wildcards"):
        check_key(bad)


_LITERAL = st.text("ab~", min_size=1, max_size=3)


@st.composite
def _expr_chunk(draw: st.DrawFn) -> str:
    kind = draw(st.sampled_from(["lit", "*", "**", "sub"]))
    if kind != "sub":
        return draw(_LITERAL) if kind == "lit" else kind
    parts = draw(st.lists(st.text("ab~", max_size=2), min_size=2, max_size=4))
    chunk = "$*".join(parts)  # never two $* in a row: a part between them is non-empty
    if any(not p for p in parts[1:-1]) or chunk == "$*":
        chunk = "a$*"
    return chunk


@settings(max_examples=300, deadline=None)
@given(
    expr=st.lists(_expr_chunk(), min_size=1, max_size=4),
    key=st.lists(_LITERAL, min_size=1, max_size=4),
)
def test_keyexpr_matches_agrees_with_zenoh(expr, key):
    """The in-memory bus routes as zenoh does, ``$*`` sub-chunk wildcards included."""
    e, k = "/".join(expr), "/".join(key)
    assert keyexpr_matches(e, k) is zenoh.KeyExpr.autocanonize(e).intersects(zenoh.KeyExpr(k))


# --------------------------------------------------------------------------------------------
# pub/sub
# --------------------------------------------------------------------------------------------


@pytest.fixture
def hub():
    return InMemoryHub()


def test_pubsub_across_handles(hub):
    with InMemoryBus(hub) as a, InMemoryBus(hub) as b, InMemoryBus() as other:
        sub = b.subscribe("covnet/r/sensor/*/meas")
        stranger = other.subscribe("**")
        a.publish("covnet/r/sensor/s1/meas", b"one")
        a.publish("covnet/r/cmd", b"not for sub")
        before = time.monotonic_ns()
        a.publish("covnet/r/sensor/s2/meas", b"two")
        got = [sub.try_recv(), sub.try_recv(), sub.try_recv()]
        assert [(s.key, s.payload) for s in got[:2]] == [
            ("covnet/r/sensor/s1/meas", b"one"),
            ("covnet/r/sensor/s2/meas", b"two"),
        ]
        assert got[2] is None
        assert got[1].t_recv_ns >= before
        assert stranger.try_recv() is None  # another hub is another network


def test_a_handle_hears_itself_and_only_later_publications(hub):
    with InMemoryBus(hub) as a:
        a.publish("k", b"before")
        sub = a.subscribe("k")
        a.publish("k", b"after")
        assert sub.try_recv().payload == b"after"
        assert sub.try_recv() is None


def test_fifo_order_per_publisher_with_concurrent_publishers(hub):
    n, writers = 2000, 4
    with InMemoryBus(hub) as reader:
        sub = reader.subscribe("w/*")
        buses = [InMemoryBus(hub) for _ in range(writers)]

        def write(i):
            for j in range(n):
                buses[i].publish(f"w/{i}", j.to_bytes(4, "big"))

        threads = [threading.Thread(target=write, args=(i,)) for i in range(writers)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=30)
        seen: dict[str, list[int]] = {}
        while (s := sub.try_recv()) is not None:
            seen.setdefault(s.key, []).append(int.from_bytes(s.payload, "big"))
        assert seen == {f"w/{i}": list(range(n)) for i in range(writers)}  # nothing dropped
        for b in buses:
            b.close()


def test_recv_timeout_and_wakeup(hub):
    with InMemoryBus(hub) as a:
        sub = a.subscribe("k")
        t0 = time.monotonic()
        assert sub.recv(timeout=0.05) is None
        assert time.monotonic() - t0 >= 0.045
        assert sub.recv(timeout=0) is None
        threading.Thread(target=a.publish, args=("k", b"x")).start()
        assert sub.recv(timeout=10).payload == b"x"


def test_close_wakes_a_blocked_recv_and_drains_first(hub):
    with InMemoryBus(hub) as a:
        sub = a.subscribe("k")
        a.publish("k", b"queued")
        sub.close()
        a.publish("k", b"after close")
        assert sub.recv(timeout=None).payload == b"queued"
        assert sub.recv(timeout=None) is None
        assert sub.try_recv() is None

        sub2 = a.subscribe("k")
        result = []
        t = threading.Thread(target=lambda: result.append(sub2.recv(timeout=None)))
        t.start()
        a.close()  # closes sub2: the blocked recv returns None
        t.join(timeout=10)
        assert not t.is_alive() and result == [None]


def test_closed_bus_refuses_work(hub):
    a = InMemoryBus(hub)
    a.close()
    a.close()  # idempotent
    with pytest.raises(BusClosed):
        a.publish("k", b"x")
    with pytest.raises(BusClosed):
        a.subscribe("k")
    with pytest.raises(BusClosed):
        a.declare_token("k")
    with pytest.raises(BusClosed):
        a.watch_liveliness("k")


def test_publish_validates_keys(hub):
    with InMemoryBus(hub) as a:
        with pytest.raises(ValueError):
            a.publish("a/*", b"x")
        with pytest.raises(ValueError):
            a.subscribe("a//b")


# --------------------------------------------------------------------------------------------
# liveliness
# --------------------------------------------------------------------------------------------


def _drain(watch):
    out = []
    while (e := watch.try_recv()) is not None:
        out.append(e)
    return out


def test_liveliness_history_declare_and_undeclare(hub):
    run = "r1"
    with InMemoryBus(hub) as manager, InMemoryBus(hub) as s1, InMemoryBus(hub) as s2:
        k1, k2 = m.alive_key(run, "sensor", "s1"), m.alive_key(run, "sensor", "s2")
        t1 = s1.declare_token(k1)
        s1.declare_token(m.alive_key("other-run", "sensor", "s1"))
        watch = manager.watch_liveliness(m.alive_keyexpr(run, "sensor"))
        assert _drain(watch) == [LivelinessEvent(k1, True)]  # history
        t2 = s2.declare_token(k2)
        assert watch.recv(timeout=5) == LivelinessEvent(k2, True)
        t1.undeclare()
        t1.undeclare()  # idempotent
        assert _drain(watch) == [LivelinessEvent(k1, False)]
        s2.close()  # closing a handle undeclares its tokens
        assert _drain(watch) == [LivelinessEvent(k2, False)]
        t2.undeclare()  # after close: harmless
        assert _drain(watch) == []
        late = manager.watch_liveliness(m.alive_keyexpr(run))
        assert _drain(late) == []


def test_liveliness_is_per_key(hub):
    with InMemoryBus(hub) as a, InMemoryBus(hub) as b:
        watch = a.watch_liveliness("alive/*")
        ta, tb = a.declare_token("alive/x"), b.declare_token("alive/x")
        assert _drain(watch) == [LivelinessEvent("alive/x", True)]
        ta.undeclare()
        assert _drain(watch) == []  # still alive through b's token
        tb.undeclare()
        assert _drain(watch) == [LivelinessEvent("alive/x", False)]


def test_closed_watch_gets_nothing(hub):
    with InMemoryBus(hub) as a:
        watch = a.watch_liveliness("alive/**")
        watch.close()
        a.declare_token("alive/x")
        assert watch.recv(timeout=None) is None


def test_channel_put_after_close_is_ignored():
    ch: Channel[int] = Channel()
    ch.put(1)
    ch.close()
    ch.put(2)
    assert ch.closed
    assert [ch.try_recv(), ch.try_recv(), ch.recv(None)] == [1, None, None]


def test_blocked_recv_runs_signal_handlers_delivered_to_another_thread(
    interrupted_from_another_thread,
):
    """Python runs a signal handler in the main thread only between bytecodes, so recv must not
    block in one long wait (without slicing it would block forever)."""
    ch: Channel[int] = Channel()
    assert 0.25 < interrupted_from_another_thread(lambda: ch.recv(timeout=None)) < 5.0


# --------------------------------------------------------------------------------------------
# clocks (injected next to the bus into every loop)
# --------------------------------------------------------------------------------------------


def test_sim_clock_jumps_forward_only():
    clock = SimClock(t0=1.0, start_ns=1_000)
    assert clock.now() == 1.0 and clock.now_ns() == 1_000 + 1_000_000_000
    clock.sleep_until(2.5)
    assert clock.now() == 2.5
    clock.sleep_until(2.0)  # the past: no jump back
    assert clock.now() == 2.5
    assert clock.advance(0.5) == 3.0
    with pytest.raises(ValueError):
        clock.advance(-1.0)


def test_sim_clock_is_thread_safe():
    clock = SimClock()
    threads = [
        threading.Thread(target=lambda: [clock.advance(1.0) for _ in range(1000)]) for _ in range(4)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert clock.now() == 4000.0


def test_wall_clock_scales_and_sleeps_until():
    clock = WallClock(speed=10.0)
    a = clock.now()
    clock.sleep_until(a + 0.2)  # 20 ms of wall time at 10x
    assert clock.now() >= a + 0.2
    t0 = time.monotonic()
    clock.sleep_until(0.0)  # the past: returns at once
    assert time.monotonic() - t0 < 0.5  # at once (a margin for a loaded machine)
    stamp = clock.now_ns()
    assert abs(stamp - time.monotonic_ns()) < 500_000_000  # raw CLOCK_MONOTONIC
    shared = WallClock(start_ns=clock.start_ns)
    assert shared.now() == pytest.approx(clock.now() / 10.0, abs=0.05)
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError):
            WallClock(speed=bad)
