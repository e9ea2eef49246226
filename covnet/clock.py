"""Clocks injected into process loops, so the same loop runs in real time or simulated time.

- ``now()``: scenario time in seconds, from the clock's start.
- ``now_ns()``: a monotonic stamp in ns for ``t_sent_ns`` / latency. For :class:`WallClock`
  it is ``time.monotonic_ns()`` itself: on one Linux host CLOCK_MONOTONIC is shared by every
  process, so a stamp from one process minus a stamp from another is a one-way latency.
- ``sleep_until(t)``: block until ``now() >= t`` (a :class:`SimClock` jumps instead).
"""

from __future__ import annotations

import threading
import time
from typing import Protocol

__all__ = ["Clock", "SimClock", "WallClock"]


class Clock(Protocol):
    def now(self) -> float: ...
    def now_ns(self) -> int: ...
    def sleep_until(self, t: float) -> None: ...


class WallClock:
    """Real time, optionally scaled: ``now() = speed * (monotonic - start)`` seconds.

    ``speed=2.0`` runs the scenario twice as fast as real time. ``start_ns`` (a
    ``time.monotonic_ns()`` value) lets several processes share one time origin; by default
    the clock starts when it is built.
    """

    def __init__(self, speed: float = 1.0, *, start_ns: int | None = None) -> None:
        if not speed > 0 or speed == float("inf"):
            raise ValueError(f"speed must be finite and > 0, got {speed!r}")
        self.speed = float(speed)
        self.start_ns = time.monotonic_ns() if start_ns is None else int(start_ns)

    def now(self) -> float:
        return (time.monotonic_ns() - self.start_ns) * 1e-9 * self.speed

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, t: float) -> None:
        """Sleep until scenario time ``t`` [s]; returns at once if it has passed. A signal
        handler that raises (SIGINT's KeyboardInterrupt) interrupts the sleep."""
        deadline_ns = self.start_ns + round(t / self.speed * 1e9)
        while True:
            remaining_ns = deadline_ns - time.monotonic_ns()
            if remaining_ns <= 0:
                return
            time.sleep(remaining_ns * 1e-9)


class SimClock:
    """Simulated time, advanced only explicitly: ``sleep_until(t)`` jumps to ``t`` (never
    backwards), ``advance(dt)`` moves on by ``dt``. Thread-safe. ``now_ns()`` is the
    simulated time in ns plus ``start_ns``, so simulated latencies are exact."""

    def __init__(self, t0: float = 0.0, *, start_ns: int = 0) -> None:
        self._lock = threading.Lock()
        self._t = float(t0)
        self.start_ns = int(start_ns)

    def now(self) -> float:
        with self._lock:
            return self._t

    def now_ns(self) -> int:
        with self._lock:
            return self.start_ns + round(self._t * 1e9)

    def sleep_until(self, t: float) -> None:
        with self._lock:
            if t > self._t:
                self._t = float(t)

    def advance(self, dt: float) -> float:
        """Move time on by ``dt >= 0`` seconds; returns the new time."""
        if not dt >= 0:
            raise ValueError(f"dt must be >= 0, got {dt!r}")
        with self._lock:
            self._t += dt
            return self._t
