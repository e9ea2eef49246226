"""After the world died (not restarted) a scan stops waiting for its sensors after
WORLD_GONE_WAIT_S (no truth comes for them).  On slow links the collection goes on to the
deadline anyway, and their measurements, measured from truth published before the world died,
came in time and were fused: but each was also counted ``missing_at_deadline`` (64 of them in
a 24-scan run whose every measurement was on time)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from covnet.clock import WallClock
from covnet.config import NetworkSpec
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, InMemoryHub
from manager.loop import WORLD_GONE_WAIT_S, Loop


@pytest.mark.parametrize("to_deadline", [True, False])
def test_a_measurement_in_time_after_the_world_died_is_not_missing(to_deadline):
    hub = InMemoryHub()
    loop = Loop(NetworkSpec(), ("S1",), InMemoryBus(hub, name="manager"), "t", WallClock())
    sensor = InMemoryBus(hub, name="S1")
    token = sensor.declare_token(msg.alive_key("t", "sensor", "S1"))  # S1 up; no world
    loop.to_deadline = to_deadline
    after = WORLD_GONE_WAIT_S + 0.3  # past the world-gone cut, before the deadline

    def answer() -> None:
        time.sleep(after)
        m = msg.Measurement("S1", 1, 1.0, np.zeros((1, 2)), np.eye(2), time.time_ns(), seq=1)
        sensor.publish(msg.measurement_key("t", "S1"), msg.encode(m))

    th = threading.Thread(target=answer)
    th.start()
    try:
        got = loop.collect(
            0, 1, {"S1"}, time.monotonic() + after + 0.6, threading.Event(),
            lambda m: True, msg.Measurement, None,
        )  # fmt: skip
    finally:
        th.join()
        token.undeclare()
    if to_deadline:  # collected to the deadline: taken, and never missing
        assert "S1" in got
        assert loop.stats.missing_at_deadline == 0
    else:  # lockstep: the cut ends the wait (no truth comes), and counts it
        assert loop.stats.missing_at_deadline == 1
