"""The :class:`~covnet.wire.bus.Bus` over Eclipse Zenoh: the ONLY covnet module that imports zenoh.

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
- A subscriber with a ``FifoChannel`` handler: ``recv()`` blocks with the GIL released and
  has no timeout; a pending signal interrupts it (``KeyboardInterrupt`` at once when the
  handler raises); ``undeclare`` from another thread while ``recv`` blocks fails ("Already
  borrowed"); a session's ``close`` ends a blocked ``recv`` with ``ZError``. A ``delete`` put
  with ``allowed_destination=Locality.SESSION_LOCAL`` (and an attachment) reaches only this
  session's subscribers. So :meth:`ZenohBus.subscribe` gives the loop's own thread the FIFO
  (one thread hand-off per sample: zenoh's network thread -> the loop) and a per-bus waker
  thread delivers such a local *wake sample* when a ``recv(timeout)`` times out or every
  ``SIGNAL_CHECK_S`` (:class:`_Waker`). Per-subscriber order is kept.
- A received message costs a callback subscriber three thread wake-ups (zenoh's network
  thread, the callback thread, the loop) and a FIFO subscriber two. Measured on a bare loop
  of the scan's shape (a router publishing one command, 8 clients, ~5 replies a scan, no
  other work): 1180 scans/s with callbacks feeding a queue, 2230-2490 with FIFOs; on the
  paper run (3000 scans, 11 processes on 2 cores) the FIFOs cut the CPU per scan of all
  processes from 4.7-4.9 ms to 4.3-4.5 ms (326-341 -> 360-377 scans/s). Callbacks on zenoh's
  own thread (``indirect=False``) cost ~8 % more than queue-feeding callbacks, express
  publishers ~12 % more, ``transport/unicast/lowlatency`` no gain (382 vs 412 scans/s,
  alternating runs). :meth:`ZenohBus.subscribe_stamped` keeps the callback for a loop that
  needs arrival stamps while it drains in bursts (the recorder).
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
  :meth:`covnet.wire.bus.Channel.recv` also never blocks longer than 0.1 s at a time.
- Never fork after ``zenoh.open`` (the child hangs on its first put): spawn processes with
  ``subprocess``. Always close the session (this class is a context manager), or the
  interpreter may hang at exit.
- The size cap (:data:`covnet.wire.messages.MAX_PAYLOAD_BYTES`), in two places.  (1) zenoh's own
  ``transport/link/rx/max_message_size`` (default 1 GiB) bounds the *defragmentation buffer*
  of each link: a message larger than that (payload, key and headers; anything over one
  batch, 64 KiB, travels in fragments) is dropped by the receiving link, counted nowhere, and
  never reaches a subscriber; a router drops it before routing it on.  Only that message goes:
  zenoh's code says "Defrag errors don't close transport", and a probe confirms it (a client
  sending 1 MiB + 100 B, 3 MiB and 12 MiB payloads to a router capped at 1 MiB: those three
  dropped, the 100 B .. 1 MiB - 4 KiB ones before and after delivered, its liveliness token
  up until it closed).  zenoh has no per-message size limit below the link (no option on a
  subscriber or a key).  But by default zenoh 1.x moves payloads over 3 KiB between processes
  of one host through shared memory (``transport/shared_memory/transport_optimization``): those
  are never fragmented, so the cap does not see them (the probe's 3 MiB payload got through
  while shared memory was on).  :func:`zenoh_config` therefore sets the cap and turns shared
  memory off (a link uses it only when both ends have it, so a third party cannot turn it back
  on; covnet's payloads are far below 3 KiB anyway).  (2) Every subscription reads
  ``len(sample.payload)`` (``ZBytes.__len__``: the sum of its slices' lengths, no copy) and
  drops a payload over :attr:`ZenohBus.max_payload` before ``to_bytes`` copies it, counting it
  in :meth:`ZenohBus.dropped`: the ones between the cap and zenoh's (which allows
  :data:`KEY_HEADROOM_BYTES` more, for the key and headers of a legitimate message) and, on a
  session whose zenoh cap is higher, any.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any, Generic, Literal, TypeVar

import zenoh

from covnet.wire.bus import (
    OVERSIZE,
    SIGNAL_CHECK_S,
    BusClosed,
    Channel,
    DropCounter,
    LivelinessEvent,
    LivelinessSubscription,
    Sample,
    Subscription,
    Token,
    check_key,
    check_keyexpr,
)
from covnet.wire.messages import MAX_PAYLOAD_BYTES

__all__ = ["KEY_HEADROOM_BYTES", "Mode", "ZenohBus", "zenoh_config"]

KEY_HEADROOM_BYTES = 128 * 1024
"""What zenoh's message size cap allows beyond the payload cap: the key and zenoh's headers (the
longest legitimate key, a command naming 1024 enabled ids of 64 characters, is ~66 kB)."""

_T = TypeVar("_T")

Mode = Literal["router", "client", "peer"]


def zenoh_config(
    mode: Mode,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    lease_ms: int | None = None,
    multicast_scouting: bool = False,
    extra_json5: Mapping[str, object] | None = None,
    max_payload: int = MAX_PAYLOAD_BYTES,
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
    - ``max_payload``: the size cap; every link of the session drops a message over
      ``max_payload + KEY_HEADROOM_BYTES`` (``transport/link/rx/max_message_size``), and
      shared memory is off so that the cap sees every message (module docstring).
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
    if isinstance(max_payload, bool) or not isinstance(max_payload, int) or max_payload <= 0:
        raise ValueError(f"max_payload must be a positive int, got {max_payload!r}")
    settings: dict[str, object] = {
        "mode": mode,
        "listen/endpoints": list(listen),
        "connect/endpoints": list(connect),
        "scouting/multicast/enabled": bool(multicast_scouting),
        "transport/link/rx/max_message_size": max_payload + KEY_HEADROOM_BYTES,
        "transport/shared_memory/enabled": False,
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
    """A zenoh subscriber feeding a :class:`~covnet.wire.bus.Channel` that the loop drains."""

    def __init__(self, bus: ZenohBus, keyexpr: str) -> None:
        self._bus = bus
        self.keyexpr = keyexpr
        self.channel: Channel[_T] = Channel()
        with _signals_blocked():
            self._sub: zenoh.Subscriber[None] | None = self._declare(bus._session, keyexpr)

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
                sub.undeclare()
            except zenoh.ZError:  # the session is already closed
                pass
        self.channel.close()


class _ZenohSubscription(_ChannelSubscription[Sample]):
    def _declare(self, session: zenoh.Session, keyexpr: str) -> zenoh.Subscriber[None]:
        put = self.channel.put
        cap, drops = self._bus.max_payload, self._bus._drops

        def on_sample(sample: zenoh.Sample) -> None:  # zenoh's thread: enqueue only
            payload = sample.payload
            if len(payload) > cap:  # counted, never copied
                drops.add(str(sample.key_expr), OVERSIZE, keyexpr)
                return
            put(Sample(str(sample.key_expr), payload.to_bytes(), time.monotonic_ns()))

        return session.declare_subscriber(keyexpr, zenoh.handlers.Callback(on_sample))


#: a FIFO subscription holds at most this many samples its loop has not taken yet; a full one
#: makes zenoh's receiving thread wait (back-pressure, as ``CongestionControl.BLOCK``)
FIFO_CAPACITY = 1 << 16
#: the waker's longest sleep while a loop is blocked (deadlines are met exactly: it sleeps until
#: the earliest one when that comes first)
WAKER_TICK_S = SIGNAL_CHECK_S / 2


def _wake_key(keyexpr: str) -> str:
    """A concrete key in ``keyexpr`` (every wildcard chunk becomes ``_wake``)."""
    return "/".join("_wake" if c in ("*", "**") else c for c in keyexpr.split("/"))


class _Waker:
    """Ends a FIFO subscription's blocking ``recv`` when its timeout passes, and at least every
    :data:`~covnet.wire.bus.SIGNAL_CHECK_S` (so that the main thread runs a signal handler), by
    delivering a *wake sample* to it: a ``DELETE`` on a key of the subscription carrying the
    subscription's nonce as attachment, put with ``Locality.SESSION_LOCAL`` (it never leaves
    the process).  One daemon thread per bus, started at the first blocking ``recv``; it sleeps
    while no loop is blocked, otherwise until the earliest deadline or ``WAKER_TICK_S``, and is
    notified only when a loop blocks with a deadline earlier than its planned wake (never in a
    loop that receives faster than its timeouts)."""

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        # subscription -> [deadline_ns or None, last wake (or block) ns]
        self._blocked: dict[_ZenohFifoSubscription, list[int | None]] = {}
        self._planned_ns: float = float("inf")
        self._thread: threading.Thread | None = None
        self._closed = False

    def block(self, sub: _ZenohFifoSubscription, deadline_ns: int | None) -> None:
        with self._cond:
            if self._closed:
                return
            self._blocked[sub] = [deadline_ns, time.monotonic_ns()]
            if self._thread is None:
                with _signals_blocked():  # the thread inherits the mask: signals go elsewhere
                    self._thread = threading.Thread(
                        target=self._run, name="covnet-waker", daemon=True
                    )
                    self._thread.start()
            elif self._planned_ns == float("inf") or (
                deadline_ns is not None and deadline_ns < self._planned_ns
            ):
                self._cond.notify()  # asleep without a tick, or would wake too late

    def unblock(self, sub: _ZenohFifoSubscription) -> None:
        with self._cond:
            self._blocked.pop(sub, None)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._blocked.clear()
            self._cond.notify()

    def _run(self) -> None:
        check_ns = int(SIGNAL_CHECK_S * 1e9)
        tick_ns = int(WAKER_TICK_S * 1e9)
        while True:
            with self._cond:
                if self._closed:
                    return
                now = time.monotonic_ns()
                due = []
                planned = float("inf") if not self._blocked else now + tick_ns
                for sub, entry in self._blocked.items():
                    deadline, last = entry
                    if deadline is not None and deadline <= now:
                        entry[0] = None  # woken for it; a new recv sets a new one
                        entry[1] = now
                        due.append(sub)
                    elif now - last >= check_ns:  # type: ignore[operator]
                        entry[1] = now
                        due.append(sub)
                    elif deadline is not None:
                        planned = min(planned, deadline)
                if not due:
                    self._planned_ns = planned
                    timeout = None if planned == float("inf") else (planned - now) / 1e9
                    self._cond.wait(timeout)
                    continue
            for sub in due:  # outside the lock: the put may take a moment
                sub._wake()


class _ZenohFifoSubscription:
    """A zenoh subscriber with a FIFO channel that the loop's own thread receives from: a
    sample costs one thread hand-off (zenoh's network thread -> the loop) instead of two (a
    callback thread first), and no Python runs for it before the loop takes it.  Measured on a
    bare loop of the scan's shape (1 router, 8 clients, one command, ~5 replies): 2230-2490
    scans/s against 1180 with callbacks feeding a queue.

    ``Sample.t_recv_ns`` is stamped when the loop takes the sample.  Timeouts and signal checks
    come from the bus's :class:`_Waker`; a remote ``DELETE`` (not a wake sample) is handed out
    as a sample with an empty payload, which every decoder rejects, as before.  A payload over
    the bus's cap is counted in :meth:`ZenohBus.dropped` and skipped, never copied."""

    def __init__(self, bus: ZenohBus, keyexpr: str) -> None:
        self._bus = bus
        self.keyexpr = keyexpr
        self._cap, self._drops = bus.max_payload, bus._drops
        self._key = _wake_key(keyexpr)
        self._nonce = os.urandom(16)  # marks this subscription's wake samples
        self._closed = False
        with _signals_blocked():
            self._sub: zenoh.Subscriber[zenoh.Handler[zenoh.Sample]] | None = (
                bus._session.declare_subscriber(keyexpr, zenoh.handlers.FifoChannel(FIFO_CAPACITY))
            )
        self._recv = self._sub.recv
        self._try_recv = self._sub.try_recv

    def _sample(self, s: zenoh.Sample) -> Sample | None:
        """The covnet sample for ``s``, or None for one of our wake samples and for a payload
        over the cap (counted ``oversize``, never copied)."""
        if s.kind == _DELETE:
            att = s.attachment
            if att is not None and att.to_bytes() == self._nonce:
                return None
        payload = s.payload
        if len(payload) > self._cap:
            self._drops.add(str(s.key_expr), OVERSIZE, self.keyexpr)
            return None
        return Sample(str(s.key_expr), payload.to_bytes(), time.monotonic_ns())

    def try_recv(self) -> Sample | None:
        while not self._closed:
            try:
                s = self._try_recv()
            except zenoh.ZError:  # the channel is closed
                return None
            if s is None:
                return None
            out = self._sample(s)
            if out is not None:
                return out
        return None

    def recv(self, timeout: float | None) -> Sample | None:
        """The next sample; None after ``timeout`` seconds (None: wait forever) or once closed.
        A wait longer than :data:`~covnet.wire.bus.SIGNAL_CHECK_S` is cut into slices, so that the
        main thread runs signal handlers meanwhile (as :meth:`covnet.wire.bus.Channel.recv`)."""
        out = self.try_recv()
        if out is not None or (timeout is not None and timeout <= 0):
            return out
        deadline = None if timeout is None else time.monotonic_ns() + int(timeout * 1e9)
        waker = self._bus._waker
        while not self._closed:
            waker.block(self, deadline)
            try:
                s = self._recv()
            except zenoh.ZError:  # closed under us
                return None
            finally:
                waker.unblock(self)
            out = self._sample(s)
            if out is not None:
                return out
            if deadline is not None and time.monotonic_ns() >= deadline:
                return None
        return None

    def _wake(self) -> None:
        try:
            self._bus._session.delete(
                self._key, attachment=self._nonce, allowed_destination=_SESSION_LOCAL
            )
        except zenoh.ZError:  # the session is closing
            pass

    def close(self) -> None:
        self._bus._forget(self)
        self._undeclare()

    def _undeclare(self) -> None:
        if self._closed:
            return
        self._closed = True
        sub, self._sub = self._sub, None
        self._wake()  # a loop blocked in recv returns (and sees _closed)
        if sub is None:
            return
        deadline = time.monotonic() + 2.0
        while True:
            try:
                sub.undeclare()
                return
            except zenoh.ZError:  # the session is already closed
                return
            except RuntimeError:  # "Already borrowed": a recv has not returned yet
                if time.monotonic() > deadline:
                    return  # the session's close ends it
                time.sleep(0.001)


_DELETE = zenoh.SampleKind.DELETE
_SESSION_LOCAL = zenoh.Locality.SESSION_LOCAL


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
                token.undeclare()
            except zenoh.ZError:
                pass


_Entity = _ChannelSubscription[Any] | _ZenohFifoSubscription | _ZenohToken
_E = TypeVar("_E", bound=_Entity)


class ZenohBus:
    """A :class:`~covnet.wire.bus.Bus` on one zenoh session. Open it with :meth:`open` (a context
    manager that always closes the session). Thread-safe: several threads may publish.

    ``max_payload``: the size cap of this handle's subscriptions (a received payload over it is
    dropped uncopied and counted in :meth:`dropped`); the session's own zenoh cap is the
    config's (:func:`zenoh_config`)."""

    def __init__(
        self,
        session: zenoh.Session,
        *,
        express: bool = False,
        max_payload: int = MAX_PAYLOAD_BYTES,
        owns_session: bool = True,
        fifo: bool = True,
    ) -> None:
        if isinstance(max_payload, bool) or not isinstance(max_payload, int) or max_payload < 0:
            raise ValueError(f"max_payload must be an int >= 0, got {max_payload!r}")
        self._session = session
        self._owns_session = owns_session
        self._fifo = fifo
        self._express = express
        self.max_payload = max_payload
        self._drops = DropCounter()
        self._lock = threading.Lock()
        self._closed = False
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._entities: set[_Entity] = set()
        self._waker = _Waker()

    @classmethod
    def open(
        cls, config: zenoh.Config, *, express: bool = False, max_payload: int = MAX_PAYLOAD_BYTES
    ) -> ZenohBus:
        """Open a session. ``express=True`` sends each put at once instead of batching (lower
        latency, more packets); congestion control is always ``BLOCK``.  ``max_payload``: the
        subscriptions' size cap (class docstring)."""
        with _signals_blocked():
            session = zenoh.open(config)
        return cls(session, express=express, max_payload=max_payload)

    def share(self) -> ZenohBus:
        """Another handle on this bus's session, for another node of the same process (the
        sensors a host process runs, :mod:`sensors.host`): its own publishers, subscriptions,
        liveliness tokens, size cap and drop counts, all undeclared by its :meth:`close`, which
        leaves the session open (this handle's close closes it).  To the router and to every
        other node the shared session's tokens and keys are those of separate sessions; what
        is shared is the one transport, lease and zenoh runtime (N hosted sensors open one
        session, not N).  Only for nodes whose session settings are the same (no per-node
        security identity).

        Its :meth:`subscribe` feeds a queue from zenoh's callback (as :meth:`subscribe_stamped`)
        rather than a FIFO channel: a FIFO subscription's timeouts are wake samples put on the
        session, which every matching subscription of the session receives, so N sensors on
        one session would wake each other N times over (at 256 sensors that halved the scan
        rate); a queue times out by itself."""
        self._check_open()
        return ZenohBus(
            self._session,
            express=self._express,
            max_payload=self.max_payload,
            owns_session=False,
            fifo=False,
        )

    def dropped(self) -> dict[str, dict[str, int]]:
        """The payloads this session's subscriptions dropped before their loops saw them,
        ``{key: {reason: count}}`` (reason ``"oversize"``; at most
        :data:`~covnet.wire.bus.MAX_DROP_KEYS` concrete keys, then by subscription key
        expression).  What zenoh's own cap dropped is not in it (zenoh counts nothing)."""
        return self._drops.snapshot()

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

    def _declare(self, make: Callable[[ZenohBus, str], _E], name: str) -> _E:
        """``make(self, name)`` registered for :meth:`close`, refused once closed."""
        with self._lock:
            self._check_open()
            entity = make(self, name)
            self._entities.add(entity)
        return entity

    def subscribe(self, keyexpr: str) -> Subscription:
        check_keyexpr(keyexpr)
        if not self._fifo:  # a share of a session (see share)
            return self._declare(_ZenohSubscription, keyexpr)
        return self._declare(_ZenohFifoSubscription, keyexpr)

    def subscribe_stamped(self, keyexpr: str) -> Subscription:
        """:meth:`subscribe`, with each sample stamped when it arrives (on zenoh's thread, a
        callback feeding a queue) rather than when the loop takes it: for a loop that drains in
        bursts and records receive times (the recorder)."""
        check_keyexpr(keyexpr)
        return self._declare(_ZenohSubscription, keyexpr)

    def declare_token(self, key: str) -> Token:
        check_key(key)
        return self._declare(_ZenohToken, key)

    def watch_liveliness(self, keyexpr: str) -> LivelinessSubscription:
        check_keyexpr(keyexpr)
        return self._declare(_ZenohLivelinessSubscription, keyexpr)

    def close(self) -> None:
        """Undeclare everything (waking blocked ``recv`` calls) and close the session (unless
        this handle is a :meth:`share` of it). Idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities, self._entities = list(self._entities), set()
            publishers, self._publishers = list(self._publishers.values()), {}
        try:
            self._waker.close()
            for entity in entities:
                entity._undeclare()
            for publisher in publishers:
                try:
                    publisher.undeclare()
                except zenoh.ZError:
                    pass
        finally:
            if self._owns_session:
                self._session.close()

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
