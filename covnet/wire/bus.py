"""The transport seam: a small synchronous pub/sub API that process loops are written against.

A loop owns its state and *drains* channels (``try_recv`` / ``recv(timeout)``); nothing the
transport calls back ever touches process state. Two implementations:

- :class:`InMemoryBus` (here): in-process, thread-safe, for tests and the in-process runtime;
  several handles sharing one :class:`InMemoryHub` behave like several zenoh sessions.
- ``covnet.wire.zenoh_bus.ZenohBus``: the same API over Eclipse Zenoh (the only zenoh importer).

Semantics both implementations share:

- ``subscribe(keyexpr)`` delivers every matching ``publish`` made after it returns, in publish
  order per publisher, into a FIFO: nothing is dropped (the in-memory one is unbounded; over
  zenoh a full FIFO makes the sender wait). A handle hears its own publications (as a zenoh
  session does).
- Key expressions follow zenoh: chunks separated by ``/``; ``*`` matches exactly one chunk,
  ``**`` zero or more chunks, ``$*`` inside a chunk any run of characters, none too (``a$*b``
  matches the chunks ``ab`` and ``axyb``; :func:`keyexpr_matches`). Published keys are
  concrete.
- ``declare_token(key)`` announces liveliness until ``Token.undeclare()`` or ``close()``;
  ``watch_liveliness(keyexpr)`` first reports every currently alive matching token
  (``alive=True``, the "history"), then each appearance and disappearance.
- ``recv(timeout)`` returns ``None`` on timeout and, once the subscription (or its bus) is
  closed and drained, ``None`` at once. A blocked ``recv`` wakes at least every
  :data:`SIGNAL_CHECK_S` (0.1 s), so the main thread runs a signal handler within 0.1 s even
  when the kernel hands the signal to another thread.
- The size cap: a received payload over the handle's ``max_payload`` (default
  :data:`covnet.wire.messages.MAX_PAYLOAD_BYTES`) is never handed to the loop. It is dropped before
  it is copied (its length is read where it lies) and counted on the *receiving* handle by
  (concrete key, reason ``"oversize"``): :meth:`InMemoryBus.dropped` /
  ``ZenohBus.dropped``, or :func:`dropped` for any bus. Publishing one is not an error (a
  third party can always send one); every receiver drops it. Zenoh drops the largest ones
  itself, uncounted (``covnet.wire.zenoh_bus``).

Loop shape (CPython 3.11/3.12, python/cpython#108214): a signal's exception raised at the
backward jump of ``continue`` in ``while True:`` inside ``try`` escapes that ``try``'s
``except``. Prefer a stop :class:`threading.Event` set by the signal handler, or
``while (s := sub.recv(t)) is not None:`` without ``continue``, over catching
``KeyboardInterrupt`` around a ``while True: ... continue`` loop.
"""

from __future__ import annotations

import functools
import itertools
import queue
import re
import threading
import time
from collections import Counter
from dataclasses import dataclass
from typing import Generic, Protocol, TypeVar

from covnet.wire.messages import MAX_PAYLOAD_BYTES

__all__ = [
    "SIGNAL_CHECK_S",
    "Bus",
    "BusClosed",
    "Channel",
    "DropCounter",
    "DropCounting",
    "InMemoryBus",
    "InMemoryHub",
    "LivelinessEvent",
    "LivelinessSubscription",
    "MAX_DROP_KEYS",
    "OVERSIZE",
    "Sample",
    "Subscription",
    "Token",
    "check_key",
    "check_keyexpr",
    "dropped",
    "keyexpr_matches",
]


@dataclass(frozen=True, slots=True)
class Sample:
    """One received publication: its concrete key, payload, and ``time.monotonic_ns()`` at
    receipt: when it was queued for the loop (in memory, and zenoh's ``subscribe_stamped``) or
    when the loop took it (zenoh's ``subscribe``, whose FIFO the loop reads directly)."""

    key: str
    payload: bytes
    t_recv_ns: int


@dataclass(frozen=True, slots=True)
class LivelinessEvent:
    """A liveliness token at ``key`` appeared (``alive=True``) or disappeared."""

    key: str
    alive: bool


class BusClosed(RuntimeError):
    """An operation on a closed bus handle."""


class Subscription(Protocol):
    def try_recv(self) -> Sample | None: ...
    def recv(self, timeout: float | None) -> Sample | None: ...
    def close(self) -> None: ...


class LivelinessSubscription(Protocol):
    def try_recv(self) -> LivelinessEvent | None: ...
    def recv(self, timeout: float | None) -> LivelinessEvent | None: ...
    def close(self) -> None: ...


class Token(Protocol):
    def undeclare(self) -> None: ...


class Bus(Protocol):
    def publish(self, key: str, payload: bytes) -> None: ...
    def subscribe(self, keyexpr: str) -> Subscription: ...
    def declare_token(self, key: str) -> Token: ...
    def watch_liveliness(self, keyexpr: str) -> LivelinessSubscription: ...
    def close(self) -> None: ...


class DropCounting(Protocol):
    """A bus that counts the payloads it dropped before its loops saw them (both of ours)."""

    def dropped(self) -> dict[str, dict[str, int]]: ...


# --------------------------------------------------------------------------------------------
# dropped payloads
# --------------------------------------------------------------------------------------------

OVERSIZE = "oversize"
"""The drop reason of a payload over the size cap."""
MAX_DROP_KEYS = 256
"""Distinct concrete keys a :class:`DropCounter` keeps; drops on further keys are counted under
the key expression of the subscription that dropped them (a flood of made-up keys cannot grow
the counter without bound)."""


class DropCounter:
    """Payloads dropped by one bus handle, by (key, reason). Thread-safe (zenoh's threads and
    the loops add to it); at most :data:`MAX_DROP_KEYS` concrete keys plus one entry per
    subscription's key expression."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[str, Counter[str]] = {}

    def add(self, key: str, reason: str, keyexpr: str) -> None:
        """Count one drop of a payload received on ``key`` by the subscription ``keyexpr``."""
        with self._lock:
            counts = self._counts.get(key)
            if counts is None:
                if len(self._counts) >= MAX_DROP_KEYS:
                    key = keyexpr
                counts = self._counts.setdefault(key, Counter())
            counts[reason] += 1

    def snapshot(self) -> dict[str, dict[str, int]]:
        """``{key: {reason: count}}`` so far (a copy; keys in first-drop order)."""
        with self._lock:
            return {k: dict(v) for k, v in self._counts.items()}


def dropped(bus: object) -> dict[str, dict[str, int]]:
    """What ``bus`` dropped before its loops saw it, ``{key: {reason: count}}``: its
    ``dropped()`` (:class:`InMemoryBus`, ``ZenohBus``); for a wrapper without one (such as
    ``covnet.wire.latency_bus.DelayedBus``) the ``bus`` it wraps; ``{}`` for a bus that drops
    nothing."""
    seen: set[int] = set()
    while id(bus) not in seen:
        seen.add(id(bus))
        method = getattr(bus, "dropped", None)
        if callable(method):
            out: dict[str, dict[str, int]] = method()
            return out
        bus = getattr(bus, "bus", None)
        if bus is None:
            break
    return {}


# --------------------------------------------------------------------------------------------
# key expressions
# --------------------------------------------------------------------------------------------

_FORBIDDEN = set("?#$ \t\r\n")


def _chunk_ok(c: str) -> bool:
    """``*``, ``**``, or free of ``*?#$`` and whitespace except for ``$*`` sub-chunk
    wildcards, as zenoh has them: never two in a row and never alone (that is ``*``)."""
    if c in ("*", "**"):
        return True
    if "$*" in c:
        if c == "$*" or "$*$*" in c:
            return False
        c = c.replace("$*", "")
    return "*" not in c and not _FORBIDDEN.intersection(c)


def check_keyexpr(keyexpr: str) -> list[str]:
    """The chunks of a key expression; ValueError unless every chunk is non-empty and
    valid for zenoh (:func:`_chunk_ok`)."""
    if not isinstance(keyexpr, str) or not keyexpr:
        raise ValueError(f"invalid key expression {keyexpr!r}: empty")
    chunks = keyexpr.split("/")
    for c in chunks:
        if not c:
            raise ValueError(f"invalid key expression {keyexpr!r}: empty chunk")
        if not _chunk_ok(c):
            raise ValueError(f"invalid key expression {keyexpr!r}: bad chunk {c!r}")
    return chunks


def check_key(key: str) -> list[str]:
    """The chunks of a concrete key (a key expression without wildcards)."""
    chunks = check_keyexpr(key)
    if "*" in key:
        raise ValueError(f"invalid key {key!r}: wildcards are for subscriptions only")
    return chunks


def _match_chunks(expr: list[str], key: list[str]) -> bool:
    # positions in `key` reachable after consuming a prefix of `expr`
    reach = {0}
    n = len(key)
    for c in expr:
        if c == "**":
            lo = min(reach, default=n + 1)
            reach = set(range(lo, n + 1))
        elif c == "*":
            reach = {j + 1 for j in reach if j < n}
        elif "$*" in c:
            fits = _sub_chunk_pattern(c).fullmatch
            reach = {j + 1 for j in reach if j < n and fits(key[j])}
        else:
            reach = {j + 1 for j in reach if j < n and key[j] == c}
        if not reach:
            return False
    return n in reach


@functools.lru_cache(maxsize=256)
def _sub_chunk_pattern(chunk: str) -> re.Pattern[str]:
    """A chunk with ``$*`` wildcards as a regular expression (``$*``: any run, none too)."""
    return re.compile(".*".join(re.escape(part) for part in chunk.split("$*")), re.DOTALL)


def keyexpr_matches(expr: str, key: str) -> bool:
    """Whether the concrete ``key`` is in the set the key expression ``expr`` denotes
    (``*``: exactly one chunk, ``**``: zero or more chunks, ``$*``: any run of characters
    inside a chunk)."""
    return _match_chunks(check_keyexpr(expr), check_key(key))


# --------------------------------------------------------------------------------------------
# a closable FIFO channel (used by both implementations)
# --------------------------------------------------------------------------------------------

_T = TypeVar("_T")
_CLOSED = object()

SIGNAL_CHECK_S = 0.1
"""Longest single blocking wait in :meth:`Channel.recv` (see there)."""


class Channel(Generic[_T]):
    """Unbounded FIFO fed by a transport thread and drained by one loop.

    ``put`` never blocks and never drops; after ``close()`` puts are ignored, what was queued
    can still be drained, and then ``recv`` returns ``None`` at once.
    """

    def __init__(self) -> None:
        self._q: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._lock = threading.Lock()  # orders put against close: nothing lands after the marker
        self._closed = False

    def put(self, item: _T) -> None:
        with self._lock:
            if not self._closed:
                self._q.put(item)

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                self._q.put(_CLOSED)  # wakes a blocked recv

    @property
    def closed(self) -> bool:
        return self._closed

    def _got(self, item: object) -> _T | None:
        if item is _CLOSED:
            self._q.put(_CLOSED)  # keep the marker for later calls
            return None
        return item  # type: ignore[return-value]

    def try_recv(self) -> _T | None:
        try:
            return self._got(self._q.get_nowait())
        except queue.Empty:
            return None

    def recv(self, timeout: float | None) -> _T | None:
        """The next item; ``None`` after ``timeout`` seconds (None: wait forever) or once
        closed and drained.

        The wait is sliced into waits of at most :data:`SIGNAL_CHECK_S`: Python runs signal
        handlers only in the main thread, between bytecodes, and the kernel may deliver a
        process's SIGINT/SIGTERM to any thread not blocking it (numpy's OpenBLAS workers,
        say); a main thread blocked in one long wait would not notice it until the wait ends.
        """
        if timeout is not None and timeout <= 0:
            return self.try_recv()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if deadline is None:
                wait = SIGNAL_CHECK_S
            else:
                wait = min(deadline - time.monotonic(), SIGNAL_CHECK_S)
                if wait <= 0:
                    return None
            try:
                return self._got(self._q.get(timeout=wait))
            except queue.Empty:
                pass


# --------------------------------------------------------------------------------------------
# in-memory implementation
# --------------------------------------------------------------------------------------------


class _MemSubscription:
    def __init__(self, bus: InMemoryBus, keyexpr: str, chunks: list[str]) -> None:
        self._bus = bus
        self.keyexpr = keyexpr
        self.chunks = chunks
        self.channel: Channel[Sample] = Channel()

    def try_recv(self) -> Sample | None:
        return self.channel.try_recv()

    def recv(self, timeout: float | None) -> Sample | None:
        return self.channel.recv(timeout)

    def close(self) -> None:
        self._bus._hub._remove_sub(self)
        self.channel.close()
        with self._bus._lock:
            self._bus._subs.discard(self)


class _MemLivelinessSubscription:
    def __init__(self, bus: InMemoryBus, keyexpr: str, chunks: list[str]) -> None:
        self._bus = bus
        self.keyexpr = keyexpr
        self.chunks = chunks
        self.channel: Channel[LivelinessEvent] = Channel()

    def try_recv(self) -> LivelinessEvent | None:
        return self.channel.try_recv()

    def recv(self, timeout: float | None) -> LivelinessEvent | None:
        return self.channel.recv(timeout)

    def close(self) -> None:
        self._bus._hub._remove_watch(self)
        self.channel.close()
        with self._bus._lock:
            self._bus._watches.discard(self)


class _MemToken:
    def __init__(self, bus: InMemoryBus, key: str, chunks: list[str]) -> None:
        self._bus = bus
        self.key = key
        self.chunks = chunks
        self._live = True

    def undeclare(self) -> None:
        if self._live:
            self._live = False
            self._bus._hub._remove_token(self)
            with self._bus._lock:
                self._bus._tokens.discard(self)


class InMemoryHub:
    """The shared "network" of several :class:`InMemoryBus` handles.

    A key's liveliness is the union of its tokens: ``alive=True`` when the first token on a key
    appears, ``alive=False`` when the last one goes.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subs: list[_MemSubscription] = []
        self._watches: list[_MemLivelinessSubscription] = []
        self._tokens: dict[str, list[_MemToken]] = {}

    def _deliver(self, key: str, chunks: list[str], payload: bytes) -> None:
        """Hand ``payload`` to every matching subscription, or count it dropped (``oversize``)
        on the receiving handle when it is over that handle's cap; copied once, and only
        when some subscription takes it."""
        n = len(payload)
        with self._lock:  # the lock orders concurrent publishers: one FIFO order for everyone
            t = time.monotonic_ns()
            data: bytes | None = None
            for sub in self._subs:
                if _match_chunks(sub.chunks, chunks):
                    if n > sub._bus.max_payload:
                        sub._bus._drops.add(key, OVERSIZE, sub.keyexpr)
                        continue
                    if data is None:
                        data = bytes(payload)
                    sub.channel.put(Sample(key, data, t))

    def _add_sub(self, sub: _MemSubscription) -> None:
        with self._lock:
            self._subs.append(sub)

    def _remove_sub(self, sub: _MemSubscription) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)

    def _add_watch(self, watch: _MemLivelinessSubscription) -> None:
        with self._lock:
            for key, toks in self._tokens.items():  # history: the currently alive tokens
                if toks and _match_chunks(watch.chunks, toks[0].chunks):
                    watch.channel.put(LivelinessEvent(key, True))
            self._watches.append(watch)

    def _remove_watch(self, watch: _MemLivelinessSubscription) -> None:
        with self._lock:
            if watch in self._watches:
                self._watches.remove(watch)

    def _add_token(self, token: _MemToken) -> None:
        with self._lock:
            toks = self._tokens.setdefault(token.key, [])
            toks.append(token)
            if len(toks) == 1:
                self._notify(token, True)

    def _remove_token(self, token: _MemToken) -> None:
        with self._lock:
            toks = self._tokens.get(token.key, [])
            if token in toks:
                toks.remove(token)
                if not toks:
                    del self._tokens[token.key]
                    self._notify(token, False)

    def _notify(self, token: _MemToken, alive: bool) -> None:
        for watch in self._watches:
            if _match_chunks(watch.chunks, token.chunks):
                watch.channel.put(LivelinessEvent(token.key, alive))


class InMemoryBus:
    """An in-process :class:`Bus` handle. Handles built on one shared :class:`InMemoryHub`
    talk to each other (like zenoh sessions on one router); ``InMemoryBus()`` gets its own hub.

    Closing a handle closes its subscriptions and undeclares its tokens (watchers see
    ``alive=False``), as a zenoh session's close does.  ``max_payload``: this handle's size
    cap (module docstring): a payload over it is never delivered to this handle's
    subscriptions, and counted in :meth:`dropped`.
    """

    _ids = itertools.count()

    def __init__(
        self,
        hub: InMemoryHub | None = None,
        *,
        name: str | None = None,
        max_payload: int = MAX_PAYLOAD_BYTES,
    ) -> None:
        if isinstance(max_payload, bool) or not isinstance(max_payload, int) or max_payload < 0:
            raise ValueError(f"max_payload must be an int >= 0, got {max_payload!r}")
        self._hub = hub if hub is not None else InMemoryHub()
        self.name = name if name is not None else f"mem{next(self._ids)}"
        self.max_payload = max_payload
        self._drops = DropCounter()
        self._lock = threading.Lock()
        self._closed = False
        self._subs: set[_MemSubscription] = set()
        self._watches: set[_MemLivelinessSubscription] = set()
        self._tokens: set[_MemToken] = set()

    @property
    def hub(self) -> InMemoryHub:
        return self._hub

    def _check_open(self) -> None:
        if self._closed:
            raise BusClosed(f"bus {self.name} is closed")

    def publish(self, key: str, payload: bytes) -> None:
        self._check_open()
        self._hub._deliver(key, check_key(key), payload)

    def dropped(self) -> dict[str, dict[str, int]]:
        """The payloads this handle's subscriptions dropped, ``{key: {reason: count}}``
        (reason ``"oversize"``; see :class:`DropCounter` for the bound on keys)."""
        return self._drops.snapshot()

    def subscribe(self, keyexpr: str) -> Subscription:
        with self._lock:
            self._check_open()
            sub = _MemSubscription(self, keyexpr, check_keyexpr(keyexpr))
            self._subs.add(sub)
        self._hub._add_sub(sub)
        return sub

    def declare_token(self, key: str) -> Token:
        with self._lock:
            self._check_open()
            token = _MemToken(self, key, check_key(key))
            self._tokens.add(token)
        self._hub._add_token(token)
        return token

    def watch_liveliness(self, keyexpr: str) -> LivelinessSubscription:
        with self._lock:
            self._check_open()
            watch = _MemLivelinessSubscription(self, keyexpr, check_keyexpr(keyexpr))
            self._watches.add(watch)
        self._hub._add_watch(watch)
        return watch

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
            tokens, subs, watches = list(self._tokens), list(self._subs), list(self._watches)
        for token in tokens:
            token.undeclare()
        for sub in subs:
            sub.close()
        for watch in watches:
            watch.close()

    def __enter__(self) -> InMemoryBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
