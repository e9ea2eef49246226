"""Node loops as threads over one :class:`~covnet.bus.InMemoryHub`: the distributed protocol
without processes (each loop gets its own bus handle and stop event)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from covnet.bus import InMemoryBus, InMemoryHub


class NodeThreads:
    """``start(name, target)`` runs ``target(bus, stop)`` in a thread; its return value lands
    in ``stats[name]``; ``stop(name)`` sets one node's stop event; ``close()`` sets them all and
    joins the threads (bounded)."""

    def __init__(self, hub: InMemoryHub | None = None) -> None:
        self.hub = hub or InMemoryHub()
        self.stops: dict[str, threading.Event] = {}
        self.threads: list[threading.Thread] = []
        self.stats: dict[str, Any] = {}

    def start(self, name: str, target: Callable[[InMemoryBus, threading.Event], Any]) -> None:
        ev = threading.Event()
        self.stops[name] = ev
        bus = InMemoryBus(self.hub, name=name)

        def body() -> None:
            try:
                self.stats[name] = target(bus, ev)
            finally:
                bus.close()

        th = threading.Thread(target=body, name=name, daemon=True)
        th.start()
        self.threads.append(th)

    def stop(self, name: str) -> None:
        self.stops[name].set()

    def bus(self, name: str) -> InMemoryBus:
        return InMemoryBus(self.hub, name=name)

    def close(self, timeout_s: float = 10.0, *, stop_first: bool = True) -> None:
        if stop_first:
            for ev in self.stops.values():
                ev.set()
        for th in self.threads:
            th.join(timeout=timeout_s)
        for ev in self.stops.values():
            ev.set()


def with_metrics(sc: Any, metrics: list[str]) -> Any:
    """``sc`` whose episodes are ``metrics`` (``--metric``: a change of the config)."""
    from covnet import kinds

    return kinds.apply_options(kinds.of(sc), sc, "test", metric=list(metrics))
