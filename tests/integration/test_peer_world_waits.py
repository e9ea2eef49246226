"""The peer-mode world publishes the first window of truth once every sensor and the recorder
are up (it waited for the sensors only: the recorder, still starting, missed the first truths,
which were missing from the recording in 4 of 4 short peer runs)."""

from __future__ import annotations

import threading
import time

import pytest

from covnet.clock import WallClock
from covnet.covariance_control.config import from_dict, normalised
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, InMemoryHub
from world import covariance as world_node

pytestmark = pytest.mark.timeout(60)
RUN = "t"


def test_the_first_truth_waits_for_the_recorder(paper):
    data = normalised(paper)
    data["scans"] = 5
    data["network"]["record"] = True
    data["fusion"] = {"mode": "peer", "peer": {"graph": "ring"}}
    sc = from_dict(data)
    hub = InMemoryHub()
    world_bus, probe = InMemoryBus(hub, name="world"), InMemoryBus(hub, name="probe")
    truth = probe.subscribe(msg.truth_key(RUN))
    stop = threading.Event()
    t = threading.Thread(
        target=world_node.run, args=(sc, world_bus, RUN, WallClock(), stop), daemon=True
    )
    t.start()
    try:
        tokens = [probe.declare_token(msg.alive_key(RUN, "sensor", s)) for s in sc.sensor_ids]
        time.sleep(0.5)  # the world polls every heartbeat_s / 2; it must still wait
        assert truth.try_recv() is None, "truth published before the recorder was up"
        tokens.append(probe.declare_token(msg.alive_key(RUN, "recorder", "recorder")))
        assert truth.recv(timeout=10.0) is not None
    finally:
        stop.set()
        t.join(10.0)
        probe.close()
        world_bus.close()
    assert not t.is_alive()
