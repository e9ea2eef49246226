"""A sensor whose uplink goes dark for a while is failed, and rejoins as soon as it is heard
again: loss on a link is not death.  World, sensor and manager loops in threads over one
InMemoryHub; S8's bus drops everything it publishes for a second and withdraws its liveliness
token (its zenoh session ended), and afterwards publishes again without redeclaring the token
(a reconnect that does not restore it: what left S8 failed for good before)."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from nodethreads import with_metrics

from covnet.clock import WallClock
from covnet.covariance_control.config import with_overrides
from covnet.wire.bus import InMemoryBus, InMemoryHub
from manager import covariance as manager_node
from sensors import covariance as sensor_node
from world import covariance as world_node

VICTIM = "S8"
OUTAGE_S = 1.0


class OutageBus:
    """``inner`` with a link outage: between :meth:`begin` and ``OUTAGE_S`` later nothing
    published gets through, and :meth:`begin` withdraws every token declared (for good)."""

    def __init__(self, inner: InMemoryBus) -> None:
        self.inner = inner
        self.tokens: list[Any] = []
        self.window: tuple[float, float] | None = None
        self.dropped = 0

    def begin(self) -> None:
        t = time.monotonic()
        self.window = (t, t + OUTAGE_S)
        for tok in self.tokens:
            tok.undeclare()

    def dark(self) -> bool:
        return self.window is not None and self.window[0] <= time.monotonic() < self.window[1]

    def publish(self, key: str, payload: bytes) -> None:
        if self.dark():
            self.dropped += 1
            return
        self.inner.publish(key, payload)

    def declare_token(self, key: str) -> Any:
        tok = self.inner.declare_token(key)
        self.tokens.append(tok)
        return tok

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


@pytest.mark.timeout(120)
def test_a_dark_link_fails_the_sensor_and_it_rejoins_when_heard_again(paper):
    net = paper.network.model_dump() | {
        "record": False,
        "heartbeat_s": 0.05,
        "failure_timeout_s": 0.3,
        "scan_timeout_s": 0.2,
    }
    sc = with_metrics(with_overrides(paper, scans=60, network=net), ["spectral"])
    hub = InMemoryHub()
    stops: dict[str, threading.Event] = {}
    threads: list[threading.Thread] = []
    victim_bus: list[OutageBus] = []

    def start(name: str, target: Any) -> None:
        ev = stops[name] = threading.Event()
        bus: Any = InMemoryBus(hub, name=name)
        if name == VICTIM:
            bus = OutageBus(bus)
            victim_bus.append(bus)

        def body() -> None:
            try:
                target(bus, ev)
            finally:
                bus.close()

        th = threading.Thread(target=body, name=name, daemon=True)
        th.start()
        threads.append(th)

    start("world", lambda bus, ev: world_node.run(sc, bus, "t", WallClock(), ev))
    for sid in sc.sensor_ids:
        start(sid, lambda bus, ev, sid=sid: sensor_node.run(sc, sid, bus, "t", WallClock(), ev))

    def on_status(st: dict[str, Any]) -> None:
        if st["scan"] == 5:
            victim_bus[0].begin()
        time.sleep(0.03)  # ~30 scans/s: the outage spans many scans

    mbus = InMemoryBus(hub, name="manager")
    try:
        result = manager_node.run(
            sc, mbus, "t", WallClock(), threading.Event(), on_status=on_status
        )
    finally:
        for ev in stops.values():
            ev.set()
        for th in threads:
            th.join(timeout=10)
        mbus.close()
    assert result.completed and result.error is None
    events = [e for e in result.episodes["spectral"].failures if e["sensor"] == VICTIM]
    kinds = [e["event"] for e in events]
    assert kinds[:2] == ["failed", "rejoined"], events
    failed_at, back_at = events[0]["scan"], events[1]["scan"]
    assert 5 <= failed_at < back_at < sc.scans
    en = result.episodes["spectral"].as_run(len(sc.sensor_ids)).enabled
    j = sc.sensor_ids.index(VICTIM)
    assert not en[failed_at - 1 : back_at - 1, j].any()  # never allocated while failed
    assert en[back_at - 1 :, j].any()  # and allocated again once back
    assert result.stats.membership[VICTIM]["rejoined"] >= 1
    assert victim_bus[0].dropped > 0
