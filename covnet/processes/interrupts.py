"""A Ctrl-C that lands where Python cannot raise it is delivered again, not printed and lost.

Python runs a SIGINT handler between two bytecodes of the main thread.  When those bytecodes
belong to a weakref callback, a ``__del__`` or a garbage-collector callback (matplotlib's
figure teardown runs many), the ``KeyboardInterrupt`` cannot propagate: Python prints
"Exception ignored in ... Traceback ... KeyboardInterrupt" and carries on, so the user sees a
traceback *and* the command does not stop.

:func:`deliver_late_interrupts` installs a ``sys.unraisablehook`` that keeps every other
unraisable exception as Python reports it, but for a ``KeyboardInterrupt`` prints nothing and
raises the interrupt again in the main thread a moment later (``_thread.interrupt_main`` from a
short-lived thread, after the hook has returned), where the command's own handler turns it
into "interrupted" and exit 130.

A C extension may also catch the ``KeyboardInterrupt`` in the middle of a call and raise an
error of its own in its place (matplotlib's pybind11 transforms answer a Ctrl-C while they
convert an array with ``TypeError: incompatible function arguments``).  The handlers here
(:func:`raise_interrupt`, for SIGINT and SIGTERM) remember that an interrupt was asked for, so
the command can tell such an error from a defect: :func:`caused`.
"""

from __future__ import annotations

import _thread
import contextlib
import signal
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

#: the exit status of an interrupted command or run (a shell's for SIGINT)
EXIT_INTERRUPTED = 130
# long enough for the main thread to leave the hook (a few bytecodes), short for a user
REDELIVER_AFTER_S = 0.02


_requested = False
_answered = False


def begin_command() -> None:
    """A new command starts with no interruption asked for or answered: a command run in the
    same process after an interrupted one (the tests', the API's callers') must not take its
    own errors for that interruption's stand-ins (:func:`caused`)."""
    global _requested, _answered, _last_request, _redelivering
    _requested = _answered = _redelivering = False
    _last_request = None


def end_command() -> None:
    """A command has returned to a program of its own (``covnet.cli.main`` called in-process,
    the handlers and hook put back): an interruption it asked for is over, so :func:`caused`
    no longer takes the program's own errors for its stand-ins.  (An answered one stays
    answered: a redelivery still pending must not raise in the program.)"""
    global _requested
    _requested = False


#: a SIGINT or SIGTERM this soon after the last one is the same request delivered twice, not
#: a second Ctrl-C (which makes ``covnet up`` SIGKILL its nodes): GNU ``timeout -s INT`` signals
#: the command and then its own process group, and a group's Ctrl-C reaches a command once per
#: way it is attached; a hand pressing Ctrl-C twice takes longer
SAME_REQUEST_S = 0.25
_last_request: float | None = None
_redelivering = False


def raise_interrupt(signum: int, frame: Any) -> None:
    """The SIGINT/SIGTERM handler of a command: remember the request, raise KeyboardInterrupt;
    one within :data:`SAME_REQUEST_S` of the last is the same request and raises nothing (a
    duplicate had ``covnet up`` SIGKILL every node: a recording without its footer, and
    ``network.json``'s counters lost)."""
    global _requested, _last_request, _redelivering
    now = time.monotonic()
    if _redelivering:  # this module's own redelivery of one that was lost: never a duplicate
        _redelivering = False
    elif _last_request is not None and now - _last_request < SAME_REQUEST_S:
        return
    _last_request = now
    _requested = True
    raise KeyboardInterrupt(f"signal {signum}")


@contextlib.contextmanager
def held() -> Iterator[None]:
    """A SIGINT or SIGTERM that comes meanwhile is answered when the block ends, not inside it:
    for a write that must finish once begun (``run.json``'s status: a Ctrl-C inside its write
    left a run whose results were complete without a status).  In the main thread only (where
    Python runs the handlers; elsewhere the block runs as it is).  At the end the handler that
    was in place is called with the first signal held (covnet's raises KeyboardInterrupt).  A
    process forked inside the block inherits the holding handler until it installs its own
    (:mod:`covnet.processes.forked`, before its ``setsid()``); the supervisor starts and
    records each child inside one (:mod:`covnet.processes.launch`)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    wanted = (signal.SIGINT, signal.SIGTERM)
    before: dict[int, Any] = {
        s: signal.signal(s, lambda signum, frame: got.append(signum)) for s in wanted
    }
    try:
        yield
    finally:
        for s, handler in before.items():  # (None: one set outside Python; the default)
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)
        if got:
            handler = before[got[0]]
            if callable(handler):
                handler(got[0], None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(got[0])


def caused(exc: BaseException) -> bool:
    """Whether ``exc`` is an interruption: a ``KeyboardInterrupt``, or any error raised after
    one was requested (an extension's stand-in for the ``KeyboardInterrupt`` it swallowed)."""
    return isinstance(exc, KeyboardInterrupt) or (_requested and isinstance(exc, Exception))


def answered() -> None:
    """The command has answered the interruption (it is ending as "interrupted"): a redelivery
    still pending must not raise a second ``KeyboardInterrupt`` while the process exits, which
    would end it by SIGINT instead of with its exit status.  (One interruption can be both
    unraisable somewhere and seen by the command: an extension that swallowed it raised an
    error of its own, which :func:`caused` counts.)"""
    global _answered
    _answered = True


def _redeliver() -> None:
    global _redelivering
    threading.Event().wait(REDELIVER_AFTER_S)
    if not _answered:
        _redelivering = True  # :func:`raise_interrupt` raises it whenever it comes
        _thread.interrupt_main(signal.SIGINT)


def _hook(unraisable: Any, fallback: Any = None) -> None:
    """Redeliver an unraisable ``KeyboardInterrupt``; report anything else as ``fallback``
    does, unless an interruption was requested (then it is the interruption's: dropped).  The
    redelivery itself may land in here: on a loaded machine the main thread can still be
    inside ``Thread.start`` when the redelivering thread's ``REDELIVER_AFTER_S`` is over, and
    an exception raised in the hook is printed and lost ("Exception ignored in
    sys.unraisablehook").  So the hook catches it and starts another redelivery, until one
    gets out (each is one interrupt: at most one is pending at a time)."""
    again = isinstance(unraisable.exc_value, KeyboardInterrupt)
    if not again and _requested and isinstance(unraisable.exc_value, Exception):
        # a finalizer of an object the interruption cut half-built (pyparsing's Forward.__del__
        # as matplotlib was imported: "Exception ignored in ... AttributeError", a traceback
        # after a Ctrl-C or SIGTERM): the interruption's, as :func:`caused` counts an error
        return
    while True:
        try:
            if again:
                threading.Thread(target=_redeliver, name="covnet-interrupt", daemon=True).start()
            else:
                (fallback or sys.__unraisablehook__)(unraisable)
            return
        except KeyboardInterrupt:
            again = True


def deliver_late_interrupts() -> None:
    """Install :func:`raise_interrupt` for SIGINT, SIGTERM and SIGHUP (a SIGTERM or a hang-up
    stops a command as a Ctrl-C does) and the unraisable hook (idempotent; other unraisable
    exceptions go to the hook in place).  Main thread only."""
    global _answered
    _answered = False  # a new command (tests run several in one process)
    signal.signal(signal.SIGINT, raise_interrupt)
    signal.signal(signal.SIGTERM, raise_interrupt)
    # a hang-up (the terminal closed, an ssh session dropped) as SIGTERM: it killed the
    # launcher at once, and a long run's results with it
    signal.signal(signal.SIGHUP, raise_interrupt)
    current = sys.unraisablehook
    if getattr(current, "covnet_interrupts", False):
        return

    def hook(unraisable: Any) -> None:
        _hook(unraisable, current)

    hook.covnet_interrupts = True  # type: ignore[attr-defined]
    sys.unraisablehook = hook
