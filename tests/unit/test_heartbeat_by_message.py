"""A sensor's measurement stands for its heartbeat (issue 29, "Bus"): the manager takes any
well-formed message of a sensor on its own key as a sign of life, and a sensor that published
one sends its next heartbeat a period after it.  What must hold: the manager hears from a live
sensor at least every period (so it never takes a measuring sensor for failed), a sensor that
stops (hung) is failed exactly ``failure_timeout`` after its last message (the bound a
heartbeat gave), and new rejections still reach the manager within a period."""

from __future__ import annotations

import numpy as np

from covnet.clock import SimClock
from covnet.config import NetworkSpec
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, InMemoryHub
from manager.loop import Loop
from sensors.protocol import _Sensor

RUN = "r1"
PERIOD_S, TIMEOUT_S = 0.1, 0.3
NS = 1_000_000_000


def _setup() -> tuple[SimClock, _Sensor, Loop, object]:
    clock = SimClock()
    hub = InMemoryHub()
    net = NetworkSpec(heartbeat_s=PERIOD_S, failure_timeout_s=TIMEOUT_S)
    manager = Loop(net, ("S1",), InMemoryBus(hub), RUN, clock)
    spy = InMemoryBus(hub).subscribe(msg.heartbeat_keyexpr(RUN))  # what goes on the wire

    def respond(cmd: msg.Command, truth: msg.Truth) -> msg.Measurement:
        return msg.Measurement(
            "S1", cmd.scan, cmd.t, np.zeros((1, 2)), np.eye(2), clock.now_ns(), episode=0
        )

    sensor = _Sensor(
        "S1", InMemoryBus(hub), RUN, clock, net, truth_ok=lambda t: True, respond=respond,
        scans=10**6, missed_command=None, keep_truth=False, command_ok=None,
    )  # fmt: skip
    sensor.token = sensor.bus.declare_token(msg.alive_key(RUN, "sensor", "S1"))
    manager.poll_membership()
    return clock, sensor, manager, spy


def _scan(sensor: _Sensor, k: int) -> None:
    """Command and truth of scan ``k`` reach the sensor, which answers."""
    sensor.accept(msg.Command(k, 0.1 * k, ("S1",), 1))
    sensor.take_truth(msg.Truth(k, 0.1 * k, ("T1",), np.zeros((1, 4))))
    sensor.answer(lambda stage: None)


def _drain(manager: Loop) -> None:
    while (s := manager.meas_sub.try_recv()) is not None:
        manager._take(s, 0, 10**9, set(), {}, lambda m: True)


def _heartbeats(spy: object) -> int:
    n = 0
    while spy.try_recv() is not None:  # type: ignore[attr-defined]
        n += 1
    return n


def test_a_measuring_sensor_sends_no_heartbeat_and_is_never_failed() -> None:
    clock, sensor, manager, spy = _setup()
    sensor.tick()  # its first heartbeat, at t = 0
    assert _heartbeats(spy) == 1
    dt = 0.07  # a scan every 0.07 s < the heartbeat period
    for k in range(1, 60):
        clock.advance(dt)
        sensor.tick()
        _scan(sensor, k)
        _drain(manager)
        manager.poll_membership()
        assert manager.members.is_up("S1", clock.now_ns())
    assert _heartbeats(spy) == 0
    assert sensor.stats.measurements_sent == 59
    # it stops measuring (no longer enabled): a heartbeat a period after its last message
    last = clock.now_ns()
    clock.advance(PERIOD_S - 1e-6)
    sensor.tick()
    assert _heartbeats(spy) == 0
    clock.advance(2e-6)
    sensor.tick()
    assert _heartbeats(spy) == 1
    manager.poll_membership()
    assert manager.members.last_heartbeat_ns["S1"] > last


def test_a_hung_sensor_fails_the_timeout_after_its_last_measurement() -> None:
    clock, sensor, manager, spy = _setup()
    sensor.tick()
    for k in range(1, 10):
        clock.advance(0.05)
        sensor.tick()
        _scan(sensor, k)
    _drain(manager)
    last = clock.now_ns()  # then it hangs: no message at all (its token lives on)
    manager.poll_membership()
    assert manager.members.is_up("S1", last + int(TIMEOUT_S * NS))
    assert not manager.members.is_up("S1", last + int(TIMEOUT_S * NS) + 1)
    assert manager.members.down_since_ns("S1") == last + int(TIMEOUT_S * NS)


def test_new_rejections_are_reported_within_a_period_while_measuring() -> None:
    clock, sensor, manager, spy = _setup()
    sensor.tick()
    assert _heartbeats(spy) == 1
    sensor.stats.rejected["bad_type"] += 1  # a malformed command arrived
    sent = []
    for k in range(1, 8):
        clock.advance(0.03)
        sensor.tick()
        _scan(sensor, k)
        sent.append(_heartbeats(spy))
    # due at t = 0.1 (the measurements no longer stand for it: it has news), then quiet again
    assert sent == [0, 0, 0, 1, 0, 0, 0]
    manager.poll_membership()
    assert manager.stats.node_rejected["S1"] == {"bad_type": 1}


def test_a_message_of_another_key_is_no_sign_of_life() -> None:
    """Only a message on the sensor's own key counts (a forged sensor id is rejected first)."""
    clock, sensor, manager, spy = _setup()
    clock.advance(1.0)
    forged = msg.Measurement("S1", 1, 0.1, np.zeros((1, 2)), np.eye(2), 1, seq=1)
    manager.bus.publish(msg.measurement_key(RUN, "S2"), msg.encode(forged))
    _drain(manager)
    assert manager.members.last_heartbeat_ns["S1"] == 0
    assert manager.stats.rejected["key_mismatch"] == 1
