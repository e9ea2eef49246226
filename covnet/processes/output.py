"""A command's standard output whose reader has gone (``covnet up ... | head -2``).

The launcher prints its processes' lines from a reader thread: a ``BrokenPipeError`` there
printed a traceback (the thread's) while the run went on.  :func:`say` prints a line; when the
reader has gone it points stdout at ``/dev/null`` (what comes later is dropped, the interpreter's
last flush prints nothing) and remembers it, so the command can end as a cut pipe does (exit
141) after it has finished its work: the run, its recording and its files are whole.
"""

from __future__ import annotations

import os
import sys
import threading

__all__ = ["gone", "reset", "say", "silence"]

_gone = False
_lock = threading.Lock()


def reset() -> None:
    """A new command: its stdout has not gone (yet)."""
    global _gone
    _gone = False


def silence() -> None:
    """The reader of stdout has gone: drop what is still to be printed."""
    global _gone
    _gone = True
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no real file behind stdout (a test's)
        pass


def gone() -> bool:
    """Did stdout's reader go during this command?"""
    return _gone


def say(text: str) -> None:
    """``print(text, flush=True)``, or nothing once stdout's reader has gone.  One line at a
    time: the launcher's reader threads (one a process) say their lines at once, and
    ``print`` writes a line's text and its newline apart (two nodes' lines ran into one)."""
    if _gone:
        return
    try:
        with _lock:
            print(text, flush=True)
    except OSError:  # a broken pipe, or a terminal hung up (EIO)
        silence()
