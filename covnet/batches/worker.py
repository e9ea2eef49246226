"""A worker process of :func:`covnet.batches.pool.parallel_map`: ``python -m covnet.batches.worker
FD``.

``FD`` is this process's end of a socket to the parent (a
:class:`multiprocessing.connection.Connection`).  Messages, in order:

1. parent -> worker: the parent's ``sys.path`` (a list), so the tasks import as they do there;
2. parent -> worker: the task function (pickled by reference: a module-level function);
3. parent -> worker: ``(index, task)`` for each task, ``None`` to leave; worker -> parent:
   ``(index, True, result, "")`` or ``(index, False, exception, traceback text)``.

The worker leaves on ``None``, when the socket closes, and (Linux) when its parent dies.  It is
started in its own session, so the terminal's Ctrl-C never reaches it; SIGINT is ignored as
well, for a Ctrl-C sent to it on purpose: the parent decides when the batch stops.

Only the standard library at module level: this runs at every worker's start.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any


def _die_with_parent() -> None:
    """``PR_SET_PDEATHSIG``: SIGTERM when the parent dies (Linux; elsewhere nothing)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes  # Linux only (start-up of the other platforms)

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
    except (OSError, AttributeError):
        return


def _portable(exc: Exception) -> Exception:
    """``exc`` if it survives pickling, else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 (any unpicklable exception)
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def serve(conn: Connection, parent: int) -> int:
    """Run the tasks the parent sends until it says ``None`` or goes away; the exit status."""
    try:
        path = conn.recv()
        sys.path[:] = [p for p in path if isinstance(p, str)]
        fn: Callable[[Any], Any] = conn.recv()
    except (EOFError, OSError):
        return 0
    while True:
        if os.getppid() != parent:  # the parent died before PR_SET_PDEATHSIG took effect
            return 1
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return 0
        if msg is None:
            return 0
        i, task = msg
        try:
            reply = (i, True, fn(task), "")
        except Exception as exc:  # noqa: BLE001 (sent to the parent, raised there)
            reply = (i, False, _portable(exc), traceback.format_exc())
        try:
            conn.send(reply)
        except OSError:  # the parent is gone
            return 0


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = os.getppid()
    _die_with_parent()
    return serve(Connection(int(argv[1])), parent)


if __name__ == "__main__":
    sys.exit(main(sys.argv))
