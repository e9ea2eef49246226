"""Node loops as threads over one :class:`~covnet.wire.bus.InMemoryHub`: the distributed protocol
without processes (each loop gets its own bus handle and stop event)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from covnet.clock import WallClock
from covnet.covariance_control.replay import RECORDING
from covnet.covariance_control.results import write_network_run
from covnet.runs.recording import RecordingWriter, run_metadata
from covnet.wire import messages as msg
from covnet.wire.bus import InMemoryBus, InMemoryHub
from manager import covariance as manager_node
from manager.process import LINGER_S
from recorder import node as recorder_node
from sensors import covariance as sensor_node
from world import covariance as world_node


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


RUN = "t"


def run_recorded_network(
    sc: Any,
    metrics: list[str],
    out: Path,
    *,
    kill_after_scan: int | None = None,
    victim: str | None = None,
    wrap_bus: dict[str, Callable[[Any], Any]] | None = None,
) -> tuple[Any, dict[str, Any]]:
    """The in-process network plus a recorder writing ``out/recording.mcap``; the manager's
    run directory written as ``python -m manager`` writes it.  ``wrap_bus``: node name ->
    a wrapper of that node's bus (a node that misbehaves on the wire)."""
    out.mkdir(parents=True)
    hub = InMemoryHub()
    node_stops: dict[str, threading.Event] = {}
    threads: list[threading.Thread] = []
    stats: dict[str, object] = {}
    errors: list[BaseException] = []

    def start(name, target):
        ev = threading.Event()
        node_stops[name] = ev
        bus = InMemoryBus(hub, name=name)
        wrap = (wrap_bus or {}).get(name)

        def body():
            try:
                stats[name] = target(wrap(bus) if wrap else bus, ev)
            except BaseException as exc:  # surfaced by the test, not lost in a thread
                errors.append(exc)
            finally:
                bus.close()

        th = threading.Thread(target=body, name=name, daemon=True)
        th.start()
        threads.append(th)

    writer = RecordingWriter(out / RECORDING, run_id=RUN, metadata=run_metadata(RUN, sc))
    try:
        start("recorder", lambda bus, ev: recorder_node.run(sc, bus, RUN, WallClock(), ev, writer))
        start("world", lambda bus, ev: world_node.run(sc, bus, RUN, WallClock(), ev))
        for sid in sc.sensor_ids:
            start(sid, lambda bus, ev, sid=sid: sensor_node.run(sc, sid, bus, RUN, WallClock(), ev))

        def on_status(st):
            if kill_after_scan is not None and st["scan"] == kill_after_scan:
                node_stops[victim].set()
                # wait until it has stopped: a sensor no scan enables sees its stop event only
                # at its next heartbeat wait (nothing else wakes it); this run is faster
                next(th for th in threads if th.name == victim).join(10)

        mbus = InMemoryBus(hub, name="manager")
        try:
            result = manager_node.run(
                with_metrics(sc, metrics),
                mbus,
                RUN,
                WallClock(),
                threading.Event(),
                on_status=on_status,
                linger_s=LINGER_S,  # as the manager's process: the nodes' last heartbeats
            )
        finally:
            mbus.close()
            for ev in node_stops.values():
                ev.set()
            for th in threads:
                th.join(timeout=10)
        assert not any(th.is_alive() for th in threads)
    finally:
        writer.close()
    assert not errors, errors
    write_network_run(out, sc, result, {"episodes": metrics, "run_id": RUN})
    return result, stats


class Forger:
    """A node's bus whose published measurements are changed by ``change`` (a
    :class:`~covnet.wire.messages.Measurement` to another; the wire format, the key and the
    sequence numbers intact): a password holder speaking for its own node."""

    def __init__(self, bus: Any, change: Callable[[Any], Any]) -> None:
        self.bus, self.change = bus, change

    def __getattr__(self, name: str) -> Any:
        return getattr(self.bus, name)

    def publish(self, key: str, payload: bytes) -> Any:
        try:
            msg.parse_measurement_key(key)
        except ValueError:
            return self.bus.publish(key, payload)
        m = msg.decode_as(payload, msg.Measurement)
        return self.bus.publish(key, msg.encode(self.change(m)))
