"""The :class:`~covnet.bus.Bus` over Eclipse Zenoh: the ONLY covnet module that imports zenoh.

Usage (a process's ``__main__``)::

    with ZenohBus.open(zenoh_config("client", connect=["tcp/127.0.0.1:7447"])) as bus:
        sub = bus.subscribe(command_key(run))
        token = bus.declare_token(alive_key(run, "sensor", sensor_id))  # after subscriptions
        ...

Zenoh facts this module relies on (eclipse-zenoh 1.10.2, Python 3.11, this 2-core machine;
measured with the probes behind ``tests/integration/test_zenoh_bus.py``):

- ``Session.put`` / ``Publisher.put`` default to ``CongestionControl.DROP`` (drops under load);
  every publisher here is declared with ``BLOCK``. Publishers are declared once per key and
  cached (declaring per put costs a declaration round on the network).
- A subscriber's ``recv()`` has no timeout, so each subscription is fed by a
  ``zenoh.handlers.Callback`` that only stamps ``time.monotonic_ns()`` and enqueues
  ``(key, payload bytes)`` into a :class:`~covnet.bus.Channel`; the loop drains it with
  ``recv(timeout)``. The callback never calls the session. With the default ``indirect=True``
  the callback runs on one zenoh-owned Python thread (not the caller's), so per-subscriber
  order is kept: 1000 puts from a client arrived in order.
- A received message costs its process three thread wake-ups (zenoh's network thread, the
  callback thread, the loop) and the machine's two cores are the limit of ``covnet up``, so
  :meth:`ZenohBus.subscribe_lazy` lets a loop say which payloads need not wake it (a sensor:
  commands that do not name it).  Measured on the paper run (``covnet up``, total CPU per
  scan of all 11 processes): callbacks on zenoh's own thread (``indirect=False``) cost ~8 %
  more (that thread then waits for the GIL), express publishers ~12 % more.
- A session hears its own puts (default locality ``ANY``).
- Liveliness is per key: a second token on a key already alive gives no new event, and the
  key goes ``DELETE`` only when its last token goes. ``declare_subscriber(history=True)``
  first reports the tokens alive at declaration time.
- A client's ``open`` fails at once (``ZError: Unable to connect``) when no router listens on
  its ``connect`` endpoints; it does not retry.
- A session in router or peer mode waits ``scouting/delay`` (500 ms by default) inside
  ``zenoh.open`` even with multicast scouting off; :func:`zenoh_config` sets it to 0 when
  multicast scouting is off (open then takes ~1 ms; a client's open ~3 ms).
- A SIGKILLed client's tokens disappear as soon as the router sees its TCP link close
  (2-13 ms over 8 runs). A frozen (SIGSTOPped) one is noticed only when its lease expires:
  set ``lease_ms`` on the process that may die (``transport/link/tx/lease``, default
  10 000 ms); with 500 ms its token went after 0.50 s. Once thawed (SIGCONT), the client
  reconnects by itself and its token comes back.
- Zenoh creates its threads lazily (at ``open``, at the first subscriber, when a link comes
  up, ...), and a thread inherits the signal mask of the thread that creates it. A signal sent
  to the process goes to any thread that does not block it; when it lands on a zenoh thread,
  Python's handler runs only when the main thread next executes bytecode, i.e. after its
  blocking ``recv(timeout)`` ends (seen: a SIGINT noticed 0.5 s late after SIGSTOP/SIGCONT).
  So every ``zenoh.open`` and declaration here runs with SIGINT/SIGTERM/SIGHUP blocked in the
  calling thread (:func:`_signals_blocked`): all of zenoh's threads then block them (checked
  in the integration tests). Other threads may still take them (numpy's OpenBLAS workers,
  started at ``import numpy``, did once in 15 SIGSTOP/SIGCONT runs), which is why
  :meth:`covnet.bus.Channel.recv` also never blocks longer than 0.1 s at a time.
- Never fork after ``zenoh.open`` (the child hangs on its first put): spawn processes with
  ``subprocess``. Always close the session (this class is a context manager), or the
  interpreter may hang at exit.
"""

from __future__ import annotations

import contextlib
import json
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Generic, Literal, TypeVar

import zenoh

from covnet.bus import (
    BusClosed,
    Channel,
    LivelinessEvent,
    LivelinessSubscription,
    Sample,
    Subscription,
    Token,
    check_key,
    check_keyexpr,
)

__all__ = ["Mode", "ZenohBus", "zenoh_config"]

_T = TypeVar("_T")

Mode = Literal["router", "client", "peer"]


def zenoh_config(
    mode: Mode,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    lease_ms: int | None = None,
    multicast_scouting: bool = False,
    extra_json5: Mapping[str, object] | None = None,
) -> zenoh.Config:
    """A ``zenoh.Config`` for one covnet process.

    - ``mode``: ``"router"`` for the manager/embedded router, ``"client"`` for nodes that
      connect to it, ``"peer"`` for a mesh.
    - ``listen`` / ``connect``: zenoh endpoints, e.g. ``"tcp/127.0.0.1:7447"``. ``listen`` is
      empty by default (zenoh's own default would be ``tcp/[::]:7447`` for a router: every
      interface); a client may not listen.
    - ``lease_ms``: ``transport/link/tx/lease``; set it on a process whose *freezing* must be
      noticed quickly (its peers drop it after the lease, default 10 s).
    - ``multicast_scouting``: off by default (tests and concurrent runs must not find each
      other); when off, ``scouting/delay`` is 0 so that ``open`` does not wait 500 ms.
    - ``extra_json5``: more ``path -> value`` settings (JSON-serialisable values), applied last
      (e.g. access control or TLS for multi-host runs).
    """
    if mode not in ("router", "client", "peer"):
        raise ValueError(f"mode must be 'router', 'client' or 'peer', got {mode!r}")
    if mode == "client" and listen:
        raise ValueError("a client session cannot listen; use mode 'peer' or 'router'")
    for ep in [*listen, *connect]:
        if not isinstance(ep, str) or "/" not in ep:
            raise ValueError(f"invalid zenoh endpoint {ep!r} (expected e.g. 'tcp/127.0.0.1:7447')")
    if lease_ms is not None and (isinstance(lease_ms, bool) or lease_ms <= 0):
        raise ValueError(f"lease_ms must be a positive int, got {lease_ms!r}")
    settings: dict[str, object] = {
        "mode": mode,
        "listen/endpoints": list(listen),
        "connect/endpoints": list(connect),
        "scouting/multicast/enabled": bool(multicast_scouting),
    }
    if not multicast_scouting:
        settings["scouting/delay"] = 0
    if lease_ms is not None:
        settings["transport/link/tx/lease"] = int(lease_ms)
    settings.update(extra_json5 or {})
    config = zenoh.Config()
    for path, value in settings.items():
        config.insert_json5(path, json.dumps(value))
    return config


_BLOCKED_SIGNALS = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}


@contextlib.contextmanager
def _signals_blocked() -> Iterator[None]:
    """Block SIGINT/SIGTERM/SIGHUP in this thread meanwhile, so that threads zenoh creates
    inside never take them (the main thread must: that is where Python handles them)."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _BLOCKED_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


class _ChannelSubscription(Generic[_T]):
    """A zenoh subscriber feeding a :class:`~covnet.bus.Channel` that the loop drains."""

    def __init__(self, bus: ZenohBus, keyexpr: str) -> None:
        self._bus = bus
        self.keyexpr = keyexpr
        self.channel: Channel[_T] = self._new_channel()
        with _signals_blocked():
            self._sub: zenoh.Subscriber[None] | None = self._declare(bus._session, keyexpr)

    def _new_channel(self) -> Channel[_T]:
        return Channel()

    def _declare(self, session: zenoh.Session, keyexpr: str) -> zenoh.Subscriber[None]:
        raise NotImplementedError

    def try_recv(self) -> _T | None:
        return self.channel.try_recv()

    def recv(self, timeout: float | None) -> _T | None:
        return self.channel.recv(timeout)

    def close(self) -> None:
        self._bus._forget(self)
        self._undeclare()

    def _undeclare(self) -> None:
        sub, self._sub = self._sub, None
        if sub is not None:
            try:
                sub.undeclare()  # type: ignore[no-untyped-call]
            except zenoh.ZError:  # the session is already closed
                pass
        self.channel.close()


class _ZenohSubscription(_ChannelSubscription[Sample]):
    def _declare(self, session: zenoh.Session, keyexpr: str) -> zenoh.Subscriber[None]:
        put = self.channel.put

        def on_sample(sample: zenoh.Sample) -> None:  # zenoh's thread: enqueue only
            put(Sample(str(sample.key_expr), sample.payload.to_bytes(), time.monotonic_ns()))

        return session.declare_subscriber(keyexpr, zenoh.handlers.Callback(on_sample))


class _LazyChannel(Channel[Sample]):
    """A :class:`~covnet.bus.Channel` that does not wake a blocked ``recv`` for a sample whose
    payload ``wake(payload)`` says can wait: such a sample is held, in order, and handed out
    after everything queued before it, when a waking sample arrives (it goes first), by
    ``try_recv``, or when ``recv`` times out.  Nothing is dropped or reordered."""

    def __init__(self, wake: Callable[[bytes], bool]) -> None:
        super().__init__()
        self._wake = wake
        self._held: deque[Sample] = deque()  # everything in it arrived after all in the queue

    def put(self, item: Sample) -> None:
        wake = self._wake(item.payload)
        with self._lock:
            if self._closed:
                return
            if not wake:
                self._held.append(item)
                return
            while self._held:
                self._q.put(self._held.popleft())
            self._q.put(item)

    def close(self) -> None:
        with self._lock:
            while self._held:
                self._q.put(self._held.popleft())
        super().close()

    def _held_one(self) -> Sample | None:
        with self._lock:
            return self._held.popleft() if self._held else None

    def try_recv(self) -> Sample | None:
        item = super().try_recv()
        return item if item is not None else self._held_one()

    def recv(self, timeout: float | None) -> Sample | None:
        item = super().recv(timeout)
        return item if item is not None else self._held_one()


class _ZenohLazySubscription(_ZenohSubscription):
    def __init__(self, bus: ZenohBus, keyexpr: str, wake: Callable[[bytes], bool]) -> None:
        self._wake = wake
        super().__init__(bus, keyexpr)

    def _new_channel(self) -> Channel[Sample]:
        return _LazyChannel(self._wake)


class _ZenohLivelinessSubscription(_ChannelSubscription[LivelinessEvent]):
    def _declare(self, session: zenoh.Session, keyexpr: str) -> zenoh.Subscriber[None]:
        put = self.channel.put
        put_kind = zenoh.SampleKind.PUT

        def on_sample(sample: zenoh.Sample) -> None:  # zenoh's thread: enqueue only
            put(LivelinessEvent(str(sample.key_expr), sample.kind == put_kind))

        return session.liveliness().declare_subscriber(
            keyexpr, zenoh.handlers.Callback(on_sample), history=True
        )


class _ZenohToken:
    def __init__(self, bus: ZenohBus, key: str) -> None:
        self._bus = bus
        self.key = key
        with _signals_blocked():
            self._token: zenoh.LivelinessToken | None = bus._session.liveliness().declare_token(key)

    def undeclare(self) -> None:
        self._bus._forget(self)
        self._undeclare()

    def _undeclare(self) -> None:
        token, self._token = self._token, None
        if token is not None:
            try:
                token.undeclare()  # type: ignore[no-untyped-call]
            except zenoh.ZError:
                pass


_Entity = _ChannelSubscription[Sample] | _ChannelSubscription[LivelinessEvent] | _ZenohToken


class ZenohBus:
    """A :class:`~covnet.bus.Bus` on one zenoh session. Open it with :meth:`open` (a context
    manager that always closes the session). Thread-safe: several threads may publish."""

    def __init__(self, session: zenoh.Session, *, express: bool = False) -> None:
        self._session = session
        self._express = express
        self._lock = threading.Lock()
        self._closed = False
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._entities: set[_Entity] = set()

    @classmethod
    def open(cls, config: zenoh.Config, *, express: bool = False) -> ZenohBus:
        """Open a session. ``express=True`` sends each put at once instead of batching (lower
        latency, more packets); congestion control is always ``BLOCK``."""
        with _signals_blocked():
            session = zenoh.open(config)
        return cls(session, express=express)

    @property
    def session(self) -> zenoh.Session:
        """The underlying session (for things the Bus API does not cover; avoid in loops)."""
        return self._session

    def _check_open(self) -> None:
        if self._closed:
            raise BusClosed("zenoh bus is closed")

    def _forget(self, entity: _Entity) -> None:
        with self._lock:
            self._entities.discard(entity)

    def publish(self, key: str, payload: bytes) -> None:
        publisher = self._publishers.get(key)
        if publisher is None:
            with self._lock:
                self._check_open()
                publisher = self._publishers.get(key)
                if publisher is None:
                    check_key(key)
                    with _signals_blocked():
                        publisher = self._session.declare_publisher(
                            key,
                            congestion_control=zenoh.CongestionControl.BLOCK,
                            express=self._express,
                        )
                    self._publishers[key] = publisher
        elif self._closed:
            raise BusClosed("zenoh bus is closed")
        publisher.put(payload)

    def subscribe(self, keyexpr: str) -> Subscription:
        check_keyexpr(keyexpr)
        with self._lock:
            self._check_open()
            sub = _ZenohSubscription(self, keyexpr)
            self._entities.add(sub)
        return sub

    def subscribe_lazy(self, keyexpr: str, wake: Callable[[bytes], bool]) -> Subscription:
        """:meth:`subscribe`, but a sample whose payload ``wake(payload)`` calls unimportant
        does not wake a blocked ``recv`` (one thread hand-off fewer for a message the loop
        can take later): it is handed out, in order, with the next sample that wakes it, by
        ``try_recv``, or when ``recv`` times out.  ``wake`` runs on zenoh's thread: a pure
        function of the payload."""
        check_keyexpr(keyexpr)
        with self._lock:
            self._check_open()
            sub = _ZenohLazySubscription(self, keyexpr, wake)
            self._entities.add(sub)
        return sub

    def declare_token(self, key: str) -> Token:
        check_key(key)
        with self._lock:
            self._check_open()
            token = _ZenohToken(self, key)
            self._entities.add(token)
        return token

    def watch_liveliness(self, keyexpr: str) -> LivelinessSubscription:
        check_keyexpr(keyexpr)
        with self._lock:
            self._check_open()
            watch = _ZenohLivelinessSubscription(self, keyexpr)
            self._entities.add(watch)
        return watch

    def close(self) -> None:
        """Undeclare everything (waking blocked ``recv`` calls) and close the session.
        Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities, self._entities = list(self._entities), set()
            publishers, self._publishers = list(self._publishers.values()), {}
        try:
            for entity in entities:
                entity._undeclare()
            for publisher in publishers:
                try:
                    publisher.undeclare()  # type: ignore[no-untyped-call]
                except zenoh.ZError:
                    pass
        finally:
            self._session.close()  # type: ignore[no-untyped-call]

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
