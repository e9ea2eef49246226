"""``python -m covnet`` is the ``covnet`` command, and :func:`entry` the console script's
(pyproject.toml).

A Ctrl-C or SIGTERM is answered from here on, before the command's imports: importing
:mod:`covnet.cli.app` and what a command needs takes a few tenths of a second, and an interruption
then must end like any other (``covnet: error: interrupted``, exit 130), not with a
KeyboardInterrupt traceback and death by the signal.
"""

import atexit
import os
import signal
import sys

from covnet.processes import interrupts

EXIT_INTERRUPTED = 130

_status: list[int] = []


def _exit_with_the_answer() -> None:
    """The last exit function: an interrupted command leaves with 130 here.  CPython remembers
    a KeyboardInterrupt that passed through an ``exec`` or ``eval`` of a string (a dataclass
    or a named tuple being made while the signal came) even when it was caught, and at the
    very end of the exit kills its own process with SIGINT (-2) instead of returning the
    status.  What the exit does before (threads joined, the other exit functions) has run."""
    if _status == [EXIT_INTERRUPTED]:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        os._exit(EXIT_INTERRUPTED)


def _reopen_closed_standard_streams() -> None:
    """A standard stream closed by the caller (``covnet run ... >&-``) becomes ``/dev/null``:
    Python left ``sys.stdout`` ``None`` (every print a traceback), and the first file covnet
    opened would have taken descriptor 1, and with it every node process's output."""
    for fd, name, mode in ((0, "stdin", os.O_RDONLY), (1, "stdout", os.O_WRONLY),
                           (2, "stderr", os.O_WRONLY)):  # fmt: skip
        try:
            os.fstat(fd)
            continue
        except OSError:
            pass
        null = os.open(os.devnull, mode)
        if null != fd:
            os.dup2(null, fd)
            os.close(null)
        setattr(sys, name, open(fd, "r" if fd == 0 else "w", closefd=False))  # noqa: SIM115


def _never_fail_to_print() -> None:
    """What stdout cannot encode is written as ``\\xNN`` escapes, not an error: under an ASCII
    stdout (``PYTHONIOENCODING=ascii``, some CI and cron setups) the summary's line naming a
    run directory ``Ünïcødé`` was a ``UnicodeEncodeError`` after every result was written,
    exit 1, and ``run.json`` never got its status.  (stderr escapes already.)"""
    for stream in (sys.stdout, sys.stderr):
        reconfigure = getattr(stream, "reconfigure", None)
        if reconfigure is not None and getattr(stream, "errors", None) == "strict":
            try:
                reconfigure(errors="backslashreplace")
            except (ValueError, OSError):  # (a stream closed under it: nothing to print to)
                pass


def _forget_the_working_directory() -> None:
    """Under ``python -m covnet``, Python put the working directory first on ``sys.path``: a
    ``sensors.py`` (``recorder.py``, ...) there would be what the launcher imports for its
    nodes (``covnet up`` loads their modules once and forks the nodes from itself), so it
    leaves the path, as ``-P`` would have kept it off.  Not when it is covnet's own folder
    (a clone run without an install): the nodes' packages are covnet's there."""
    if sys.flags.safe_path or not sys.path:
        return
    try:
        here = os.path.realpath(sys.path[0] or os.curdir)
        cwd = os.path.realpath(os.getcwd())
    except OSError:  # a working directory deleted meanwhile
        return
    # imported here, after the handlers (:func:`entry`): its imports are start-up time
    from covnet.code_identity import packages_root

    root = str(packages_root())
    if here == cwd and here != root:
        del sys.path[0]


def entry(*, as_module: bool = False) -> int:
    """The ``covnet`` command: :func:`covnet.cli.app.main` behind handlers installed first
    (``as_module``: run as ``python -m covnet``, whose working directory leaves ``sys.path``
    before any of the command's imports: :func:`_forget_the_working_directory`)."""
    _reopen_closed_standard_streams()
    _never_fail_to_print()
    # SIGINT and SIGTERM raise KeyboardInterrupt; one inside an import's weakref callback is
    # raised again, not printed and lost
    interrupts.deliver_late_interrupts()
    atexit.register(_exit_with_the_answer)  # the first registered runs last
    status: int | None = None  # None: an error of covnet's own, raised on (a traceback, 1)
    try:
        try:
            if as_module:
                _forget_the_working_directory()
            # imported after the handlers (start-up: an interrupt during the imports is answered)
            from covnet.cli.app import main

            status = main()
        except BaseException as exc:  # an interruption that main() did not answer itself
            if not interrupts.caused(exc):
                raise
            interrupts.answered()
            status = EXIT_INTERRUPTED
            print("covnet: error: interrupted", file=sys.stderr)
    except KeyboardInterrupt:  # a second one while the first was being answered
        status = EXIT_INTERRUPTED
    finally:
        # the command has its status: a late signal must not turn the exit into a traceback
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
        if status is not None:
            _status.append(status)
    assert status is not None
    return status


if __name__ == "__main__":
    sys.exit(entry(as_module=True))
