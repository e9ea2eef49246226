"""Start a ``python -m MODULE ARGS`` child as a fork of this process: the interpreter start-up
and the imports this process has done already are not paid again (start-up time of ``covnet
up``: eleven node processes, each of which would spend about 0.4 s of CPU importing numpy,
zenoh and the kind's modules, on two cores).

:func:`fork_module` returns a :class:`ForkedProcess`, which
:class:`covnet.processes.launch.Supervisor`
uses as it uses a ``subprocess.Popen``: ``pid`` (the child is the leader of a new session and
process group, as ``start_new_session=True``), ``stdout`` (stdout and stderr merged, text),
``poll()``, ``wait(timeout)`` and ``returncode`` (negative: killed by that signal).

The child is what ``python -m MODULE ARGS`` with that environment would be, as far as a node
can tell: stdin from /dev/null, stdout and stderr to the pipe (line-buffered, written through,
as under ``PYTHONUNBUFFERED=1``), every other descriptor closed, the default SIGINT, SIGTERM
and unraisable-exception handling, no signal blocked, ``sys.argv = [MODULE, *ARGS]``, the module
run as ``__main__``.  Its exit status is its ``SystemExit`` code (1 after an uncaught
exception, with the traceback; death by SIGINT after an uncaught ``KeyboardInterrupt``, as
Python does).  What the parent registered to run at exit (``atexit``, ``weakref.finalize``:
the parent's temporary directories) never runs in the child; the child's own ``atexit``
functions do, after its non-daemon threads have ended.

Fork only when :func:`forkable` (the caller checks): a lock held by another thread at the
fork stays held for ever in the child, and a zenoh runtime's state without its threads hangs.
"""

from __future__ import annotations

import atexit
import io
import os
import pickle
import runpy
import signal
import subprocess
import sys
import threading
import time
import traceback
import warnings
import weakref
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any, NoReturn, TypeVar

__all__ = ["ForkedProcess", "fork_module", "forkable", "map_in_forks"]

T = TypeVar("T")
R = TypeVar("R")


def forkable() -> bool:
    """Whether this process may fork a child now: Linux, this is its only Python thread, and
    no native thread but the BLAS pool's (which forks safely: it registers fork handlers)
    runs in it.  A zenoh runtime, once started, keeps its named threads (``net-0``,
    ``acc-0``, ``rx-*``, ...) after its sessions are closed, and a fork would inherit its
    state without its threads: no fork then (a test process that ran other zenoh tests).
    ``COVNET_FORK=0`` in the environment: never (every child a new interpreter)."""
    if os.environ.get("COVNET_FORK", "1") == "0":  # new interpreters, as before (A/B, escape)
        return False
    if not hasattr(os, "fork") or threading.active_count() != 1:
        return False
    try:
        me = Path("/proc/self/comm").read_text().strip()
        names = [
            Path(f"/proc/self/task/{t}/comm").read_text().strip()
            for t in os.listdir("/proc/self/task")
        ]
    except OSError:
        return False
    return all(n == me for n in names)


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def map_in_forks(fn: Callable[[T], R], items: Sequence[T]) -> list[R]:
    """``[fn(x) for x in items]``, the items computed at the same time: every item but the last
    in a fork of this process, the last here, when there is more than one item, more than one
    core and :func:`forkable`; otherwise one after the other here.  ``fn`` must be a pure
    function of its item and of what this process holds (so a fork computes what this process
    would: the same bits), and its result picklable.

    A child sends its pickled result (or its exception) back through a pipe and leaves with
    ``os._exit`` (nothing of the parent's exit work runs in it).  An exception in a child is
    raised here (the child's traceback in its message when the exception cannot be pickled).
    Interrupted (Ctrl-C, SIGTERM) or failing, the children still running are killed and reaped
    before the exception goes on: none is left behind."""
    if len(items) < 2 or cores() < 2 or not forkable():
        return [fn(x) for x in items]
    _flush()  # nothing buffered before the fork is written twice
    children: list[tuple[int, int]] = []  # (pid, read end)
    try:
        for x in items[:-1]:
            r, w = os.pipe()
            # SIGINT and SIGTERM wait while the child is made and registered: one that came
            # between the fork and the registration lost the child (never killed), and one in
            # the child before it reached its own code unwound the caller's (a second covnet
            # command, left running after the first had exited)
            mask = signal.pthread_sigmask(signal.SIG_BLOCK, _STOPS)
            try:
                pid = os.fork()
                if pid == 0:  # the child: compute, send, leave
                    _map_child(fn, x, w, [r, *(earlier for _, earlier in children)], mask)
                children.append((pid, r))
            finally:
                signal.pthread_sigmask(signal.SIG_SETMASK, mask)
            os.close(w)
        last = fn(items[-1])
        results = []
        while children:
            pid, r = children.pop(0)
            results.append(_receive_result(pid, r))
    finally:
        for pid, r in children:  # interrupted or failed: no child left running
            os.close(r)
            _kill(pid)
    return [*results, last]


_STOPS = {signal.SIGINT, signal.SIGTERM}


def _map_child(fn: Callable[[T], R], x: T, w: int, others: list[int], mask: Any) -> NoReturn:
    """A fork of :func:`map_in_forks`: computes ``fn(x)``, sends it through ``w`` and leaves
    (``os._exit``); never returns into its parent's code, whatever happens.  A Ctrl-C or
    SIGTERM ends it at once (the default action: the parent kills it anyway)."""
    try:
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        for fd in others:
            os.close(fd)
        _send_result(fn, x, w)
    finally:
        os._exit(1)


def _kill(pid: int) -> None:
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    os.waitpid(pid, 0)


def _send_result(fn: Callable[[T], R], x: T, w: int) -> NoReturn:
    code = 0
    try:
        try:
            data = pickle.dumps((True, fn(x)), protocol=pickle.HIGHEST_PROTOCOL)
        except BaseException as exc:  # sent to the parent, raised there
            code = 1
            try:
                data = pickle.dumps((False, exc), protocol=pickle.HIGHEST_PROTOCOL)
            except Exception:
                text = "".join(traceback.format_exception(exc))
                data = pickle.dumps((False, RuntimeError(text)))
        view = memoryview(data)
        while view:
            view = view[os.write(w, view) :]
    except BaseException:  # the parent is gone (interrupted): nothing to tell
        code = 1
    finally:
        os._exit(code)


def _receive_result(pid: int, r: int) -> Any:
    """The result the child ``pid`` sends through ``r`` (then reaped); the child killed if
    this is interrupted."""
    chunks = []
    try:
        while chunk := os.read(r, 1 << 20):
            chunks.append(chunk)
    except BaseException:
        _kill(pid)
        raise
    finally:
        os.close(r)
    os.waitpid(pid, 0)
    if not chunks:
        raise RuntimeError(f"a forked worker (pid {pid}) ended without a result")
    ok, value = pickle.loads(b"".join(chunks))
    if not ok:
        raise value
    return value


class ForkedProcess:
    """A forked child, with the part of ``subprocess.Popen``'s interface the supervisor uses."""

    def __init__(self, pid: int, stdout: IO[str], argv: Sequence[str]) -> None:
        self.pid = pid
        self.stdout: IO[str] | None = stdout
        self.args = list(argv)
        self.returncode: int | None = None
        self._lock = threading.Lock()

    def poll(self) -> int | None:
        with self._lock:
            if self.returncode is None:
                try:
                    pid, status = os.waitpid(self.pid, os.WNOHANG)
                except ChildProcessError:  # reaped elsewhere: its status is lost
                    self.returncode = 255
                    return self.returncode
                if pid == self.pid:
                    self.returncode = os.waitstatus_to_exitcode(status)
            return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """The exit status; ``subprocess.TimeoutExpired`` after ``timeout`` seconds."""
        deadline = None if timeout is None else time.monotonic() + timeout
        delay = 0.0005
        while True:
            rc = self.poll()
            if rc is not None:
                return rc
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
                delay = min(delay, left)
            time.sleep(delay)
            delay = min(delay * 2, 0.05)


def fork_module(
    module: str, args: Sequence[str], env: Mapping[str, str], name: str | None = None
) -> ForkedProcess:
    """Fork a child that runs ``module`` as ``python -m module *args`` with environment
    ``env`` (module docstring).  Its command line in ``ps`` stays the parent's (a fork's
    memory); ``name`` becomes its process name (``ps -o comm``, ``top``: ``covnet-<name>``, cut
    to the kernel's 15 bytes)."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()  # nothing of the parent's buffered output is written twice
        except (OSError, ValueError, AttributeError):
            pass
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        os.close(read_fd)
        _child(module, list(args), dict(env), write_fd, name)
    os.close(write_fd)
    stdout = open(read_fd, encoding="utf-8", errors="replace")  # noqa: SIM115 (the caller closes it)
    return ForkedProcess(pid, stdout, [sys.executable, "-m", module, *args])


def _child(
    module: str, args: list[str], env: dict[str, str], out_fd: int, name: str | None
) -> NoReturn:
    code = 1
    try:
        try:
            _become_a_fresh_process(env, out_fd)
            if name is not None:
                _set_name(f"covnet-{name}")
            sys.argv = [module, *args]
            # a fresh interpreter has not imported the module it runs as __main__ (the parent
            # may have: runpy would warn, and a parent's "error" filter make that fatal)
            sys.modules.pop(f"{module}.__main__", None)
            runpy.run_module(module, run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as exc:
            code = _exit_code(exc.code)
        except KeyboardInterrupt:
            _flush()
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGINT)  # die of SIGINT, as python does
            code = 130
        except BaseException:  # noqa: BLE001 (as the interpreter would: the traceback, 1)
            traceback.print_exc()
            code = 1
        threading._shutdown()  # type: ignore[attr-defined]  # join non-daemon threads
        atexit._run_exitfuncs()
        _flush()
    finally:
        os._exit(code)


def _become_a_fresh_process(env: dict[str, str], out_fd: int) -> None:
    # its own handlers first (a fork inherits whatever the parent had, covnet.processes.launch's
    # holding
    # one), then its own session: a signal to its group always finds them in place
    signal.pthread_sigmask(signal.SIG_SETMASK, set())
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.setsid()
    devnull = os.open(os.devnull, os.O_RDONLY)
    os.dup2(devnull, 0)
    os.dup2(out_fd, 1)
    os.dup2(out_fd, 2)
    os.closerange(3, _max_fd())
    os.environ.clear()
    os.environ.update(env)
    sys.unraisablehook = sys.__unraisablehook__
    _default_warnings()
    # the parent's exit work is the parent's: its temporary directories stay its own
    atexit._clear()
    for fin in list(getattr(weakref.finalize, "_registry", {})):
        fin.detach()
    sys.stdin = io.TextIOWrapper(io.FileIO(0, "r", closefd=False), encoding="utf-8")
    sys.stdout = _text(1)
    sys.stderr = _text(2, errors="backslashreplace")


def _default_warnings() -> None:
    """The warning filters of a fresh interpreter: its defaults, then its ``-W`` options and
    ``PYTHONWARNINGS`` (``sys.warnoptions``), not the filters the parent has set since (a test
    runner's ``error``)."""
    warnings.resetwarnings()
    warnings.filterwarnings("default", category=DeprecationWarning, module="__main__")
    for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning):
        warnings.filterwarnings("ignore", category=category, append=True)
    process_options = getattr(warnings, "_processoptions", None)  # what python runs at start-up
    if process_options is not None:
        process_options(sys.warnoptions)


def _set_name(name: str) -> None:
    """The process name (Linux ``prctl(PR_SET_NAME)``); nothing elsewhere."""
    try:
        import ctypes  # start-up: only in a forked child

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(15, name.encode()[:15], 0, 0, 0)  # 15: PR_SET_NAME
    except (OSError, AttributeError):
        pass


def _text(fd: int, errors: str = "strict") -> io.TextIOWrapper:
    return io.TextIOWrapper(
        io.FileIO(fd, "w", closefd=False),
        encoding="utf-8",
        errors=errors,
        line_buffering=True,
        write_through=True,
    )


def _max_fd() -> int:
    try:
        return int(os.sysconf("SC_OPEN_MAX"))
    except (OSError, ValueError):
        return 4096


def _exit_code(code: object) -> int:
    if code is None:
        return 0
    if isinstance(code, int):
        return code & 0xFF
    print(code, file=sys.stderr)
    return 1


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
