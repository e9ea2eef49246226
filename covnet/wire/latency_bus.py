"""Application-level link emulation inside a node process (``covnet up --realtime`` with a
``network.latency`` that is not ideal).

:class:`DelayedBus` wraps a node's :class:`~covnet.wire.bus.Bus`: messages published on chosen keys
leave after their link's delay (or never, when the link loses them), and messages received on
chosen key expressions are handed to the loop after their link's delay (or never).  Each link
direction is a :class:`~covnet.core.delay.LinkState` drawing from its own stream of the seed
(:func:`covnet.core.delay.link_stream`): the ``n``-th message of an episode on a link meets the
same delay and loss draws in every run, and every episode (metric) starts its links from the
start of their streams, as ``covnet run`` does (:class:`EpisodeLinks`; the episode is the
message's own field).  Delays are in *scenario* seconds, so a ``--speed X`` run divides them by
``X`` on the wall clock, like the scan period.

A sensor process applies both of its directions (its commands in, its measurements out); the
delays of the real transport (~0.1 ms on loopback) come on top.  Everything else (truth,
heartbeats, liveliness) passes untouched: those belong to the simulation and to failure
detection, not to the emulated network.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, cast

from covnet.core.delay import DOWN, UP, LinkState, link_stream
from covnet.wire import messages as msg
from covnet.wire.bus import Bus, LivelinessSubscription, Sample, Subscription, Token
from covnet.wire.codec import episode_of


class _Delayed:
    """A heap of ``(due_ns, seq, item)``."""

    def __init__(self) -> None:
        self.heap: list[tuple[int, int, object]] = []
        self.seq = itertools.count()

    def push(self, due_ns: int, item: object) -> None:
        heapq.heappush(self.heap, (due_ns, next(self.seq), item))

    def pop_due(self, now_ns: int) -> object | None:
        if self.heap and self.heap[0][0] <= now_ns:
            return heapq.heappop(self.heap)[2]
        return None

    def next_due(self) -> int | None:
        return self.heap[0][0] if self.heap else None


class EpisodeLinks:
    """One link direction: a :class:`~covnet.core.delay.LinkState` per episode, each new from
    ``make`` (the start of the link's stream), as ``covnet run`` builds every episode's links
    (its draws continued across episodes: a second metric's run met other delays and losses
    than ``covnet run``'s).  A message counts for its own episode when that is one already
    seen or the next one; anything else (no episode: malformed; a jump: forged) for the
    newest, so a rogue cannot make it keep a state per number."""

    def __init__(self, make: Callable[[], LinkState]) -> None:
        self.make = make
        self.states: dict[int, LinkState] = {}
        self.newest = 0

    def for_payload(self, payload: bytes) -> LinkState:
        e = episode_of(payload)
        if e is None or (e not in self.states and e > self.newest + 1):
            e = self.newest
        self.newest = max(self.newest, e)
        state = self.states.get(e)
        if state is None:
            state = self.states[e] = self.make()
        return state


class _DelayedSubscription:
    """A subscription whose samples come out after their link's delay (lost ones never)."""

    def __init__(self, inner: Subscription, link: EpisodeLinks, speed: float) -> None:
        self.inner, self.link, self.speed = inner, link, speed
        self.held = _Delayed()

    def _admit(self, s: Sample) -> None:
        now = time.monotonic_ns()
        due = self.link.for_payload(s.payload).on_send(now * 1e-9 * self.speed)
        if due is not None:  # a lost message never comes out
            self.held.push(round(due / self.speed * 1e9), s)

    def try_recv(self) -> Sample | None:
        while (s := self.inner.try_recv()) is not None:
            self._admit(s)
        out = self.held.pop_due(time.monotonic_ns())
        return out  # type: ignore[return-value]

    def recv(self, timeout: float | None) -> Sample | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            s = self.try_recv()
            if s is not None:
                return s
            now = time.monotonic()
            wait = None if deadline is None else deadline - now
            if wait is not None and wait <= 0:
                return None
            nxt = self.held.next_due()
            if nxt is not None:
                until_due = max(nxt * 1e-9 - now, 0.0)
                wait = until_due if wait is None else min(wait, until_due)
            got = self.inner.recv(timeout=wait)
            if got is not None:
                self._admit(got)

    def close(self) -> None:
        self.inner.close()


class DelayedBus:
    """``bus`` with ``outgoing`` (key -> link) and ``incoming`` (key expression, as the
    subscription names it -> link)
    emulated links (see the module docstring).  A daemon thread publishes held outgoing
    messages when they are due; :meth:`close` publishes nothing more."""

    def __init__(
        self,
        bus: Bus,
        *,
        outgoing: Mapping[str, EpisodeLinks],
        incoming: Mapping[str, EpisodeLinks],
        speed: float = 1.0,
    ) -> None:
        self.bus, self.speed = bus, float(speed)
        self.outgoing, self.incoming = dict(outgoing), dict(incoming)
        self._held = _Delayed()
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._flush, name="delayed-bus", daemon=True)
        self._thread.start()

    def publish(self, key: str, payload: bytes) -> None:
        link = self.outgoing.get(key)
        if link is None:
            self.bus.publish(key, payload)
            return
        due = link.for_payload(payload).on_send(time.monotonic_ns() * 1e-9 * self.speed)
        if due is None:
            return  # lost on the emulated link
        with self._cond:
            self._held.push(round(due / self.speed * 1e9), (key, payload))
            self._cond.notify()

    def _flush(self) -> None:
        with self._cond:
            while not self._closed:
                now = time.monotonic_ns()
                while (item := self._held.pop_due(now)) is not None:
                    key, payload = cast(tuple[str, bytes], item)
                    self.bus.publish(key, payload)
                nxt = self._held.next_due()
                self._cond.wait(None if nxt is None else max(nxt - now, 0) * 1e-9)

    def subscribe(self, keyexpr: str) -> Subscription:
        inner = self.bus.subscribe(keyexpr)
        link = self.incoming.get(keyexpr)
        if link is not None:
            return _DelayedSubscription(inner, link, self.speed)
        return inner

    def declare_token(self, key: str) -> Token:
        return self.bus.declare_token(key)

    def watch_liveliness(self, keyexpr: str) -> LivelinessSubscription:
        return self.bus.watch_liveliness(keyexpr)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout=2.0)


def for_sensor(bus: Bus, sc: Any, sensor_id: str, run_id: str, speed: float) -> DelayedBus:
    """Sensor ``sensor_id``'s view of the emulated network: its commands arrive over its
    downlink, its measurements (or local tracks) leave over its uplink, each link with the
    stream :func:`covnet.core.delay.link_stream` ``(seed, j, direction)`` that
    :func:`covnet.covariance_control.latency_sim.run_latency` uses too."""

    j = sc.sensor_ids.index(sensor_id)
    lat = sc.network.latency
    up, down = lat.link(sensor_id, "uplink"), lat.link(sensor_id, "downlink")
    return DelayedBus(
        bus,
        outgoing={
            msg.measurement_key(run_id, sensor_id): EpisodeLinks(
                lambda: LinkState(up, link_stream(sc.seed, j, UP))
            )
        },
        incoming={
            msg.command_keyexpr(run_id): EpisodeLinks(
                lambda: LinkState(down, link_stream(sc.seed, j, DOWN))
            )
        },
        speed=speed,
    )
