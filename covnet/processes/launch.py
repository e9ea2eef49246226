"""Process supervisor: the ``launch_testing`` pattern without the framework.

Start children, prefix and forward their output, wait for a READY line (never a sleep), and
stop them all for sure::

    specs = [ProcessSpec("manager", [sys.executable, "-m", "manager", ...]), ...]
    with Supervisor(specs, pids_file=run_dir / "pids.json") as sup:
        if not sup.wait_for_line("manager", "READY", timeout=30):
            raise RuntimeError("manager did not start")
        while all(rc is None for rc in sup.poll().values()):
            ...
    # here every child and everything it started is gone

- Each child runs in its own session (``start_new_session=True``: its own process group, out
  of reach of the terminal's Ctrl-C), with ``PYTHONUNBUFFERED=1``, ``PYTHONIOENCODING=utf-8``
  (what its output is read as), stdin from /dev/null and stderr merged into stdout. One reader
  thread per child passes each line to ``on_line(name, line)`` (default: print ``[name]
  line``).
- ``stop()`` sends SIGINT to every child's process group, SIGTERM to those still running
  after ``sigint_timeout``, SIGKILL after ``sigterm_timeout`` more, reaps them, then SIGKILLs
  each group once more so that no grandchild survives. A second Ctrl-C during ``stop()`` skips
  straight to SIGKILL. The context manager always calls ``stop()``, also on an exception or
  KeyboardInterrupt in the parent. For SIGTERM to the parent, call
  :func:`sigterm_raises_keyboard_interrupt` in the main thread first.
- ``pids_file`` (JSON ``{name: pid}``; pid == process group id) is written as soon as each
  child starts and rewritten on every restart, so an outside tool can clean up after a
  supervisor that was itself SIGKILLed; ``pids_extra`` adds entries that are not processes
  (``covnet up``: ``"hosts"``, which process hosts each sensor: skip non-integer values).
- A child is recorded (in the supervisor and in ``pids_file``) before a Ctrl-C or SIGTERM that
  lands while it is being started is acted on: the main thread holds those signals from just
  before the fork until the child is recorded, then raises them
  (:func:`covnet.processes.interrupts.held`), so ``stop()`` always knows every child it
  started.  It signals each child's group, waiting for a child just forked to have made it
  (:func:`_signal_child`).
"""

from __future__ import annotations

import collections
import contextlib
import importlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from covnet.code_identity import PACKAGES, packages_root
from covnet.processes import forked, interrupts

__all__ = ["ProcessSpec", "Supervisor", "sigterm_raises_keyboard_interrupt"]

_print_lock = threading.Lock()

# Longest single blocking wait: Python runs signal handlers only in the main thread, and the
# kernel may hand the parent's SIGINT to another thread; a main thread blocked in one long
# wait would only notice Ctrl-C when that wait ends.
_SLICE_S = 0.1
# Longest wait for a child just forked to become the leader of its own process group.
_GROUP_WAIT_S = 1.0

EXIT_RUN_FAILED = 3
"""A node's exit status when it left because its run did not end well (the manager ended it
with an error, or its host died): a failure, but not the node's own, so never restarted
(there is no run to rejoin: sensors restarted with ``restart: on-failure`` on a sensors-only
host waited for a manager that never came, failed, and were restarted again, without end) and
not a node lost mid-run."""

EXIT_NO_RUN = 4
"""A node's exit status when it found no run to join (:class:`covnet.errors.NoRun`: its
session did not open, or no manager of its run appeared in time): never restarted."""


def _print_line(name: str, line: str) -> None:
    with _print_lock:
        print(f"[{name}] {line}", flush=True)


@dataclass(frozen=True)
class ProcessSpec:
    """One child: ``argv`` run with the parent's environment updated by ``env``.
    ``restart=True``: :meth:`Supervisor.poll` restarts it when it has *failed* (exited with a
    non-zero status or by a signal); a clean exit (status 0), :data:`EXIT_RUN_FAILED` (the
    run is over) and :data:`EXIT_NO_RUN` (there is no run to join) are final."""

    name: str
    argv: list[str]
    env: dict[str, str] | None = None
    restart: bool = False
    preload: tuple[str, ...] = ()
    """Modules worth importing once for every child: when given and ``argv`` is
    ``[sys.executable, "-m", MODULE, ...]``, :meth:`Supervisor.start` imports them in this
    process and starts the child as a fork of it running MODULE
    (:func:`covnet.processes.forked.fork_module`: no interpreter start-up, no imports to repeat), if
    this process has one thread then; otherwise, and for a restart, a new interpreter."""


class _Run:
    """One incarnation of a child: its process, reader thread and retained output."""

    def __init__(self, proc: subprocess.Popen[str] | forked.ForkedProcess, max_lines: int) -> None:
        self.proc = proc
        self.lines: collections.deque[str] = collections.deque(maxlen=max_lines)
        self.count = 0  # lines seen in total (the deque keeps the last max_lines)
        self.eof = False
        self.done = False  # reaped, group cleaned, reader joined: never signal its pgid again
        self.cond = threading.Condition()
        self.reader: threading.Thread | None = None


def _lies_under(module: object, root: Path) -> bool:
    """Whether ``module`` was loaded from a file below ``root``."""
    f = getattr(module, "__file__", None)
    if not f:
        return False
    try:
        Path(f).resolve().relative_to(root)
    except ValueError:
        return False
    return True


class Supervisor:
    """Start, watch and stop a set of child processes (see the module docstring)."""

    def __init__(
        self,
        specs: Sequence[ProcessSpec],
        *,
        on_line: Callable[[str, str], None] | None = None,
        pids_file: Path | None = None,
        pids_extra: dict[str, object] | None = None,
        sigint_timeout: float = 5.0,
        sigterm_timeout: float = 5.0,
        max_lines: int = 10_000,
    ) -> None:
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate process names in {names}")
        for s in specs:
            if not s.argv:
                raise ValueError(f"process {s.name!r} has an empty argv")
        self._specs = {s.name: s for s in specs}
        self._on_line = on_line if on_line is not None else _print_line
        self._pids_file = Path(pids_file) if pids_file is not None else None
        self._pids_extra = dict(pids_extra or {})
        clash = set(self._pids_extra) & set(self._specs)
        if clash:
            raise ValueError(f"pids_extra names processes: {sorted(clash)}")
        self._max_lines = max_lines
        self.sigint_timeout = sigint_timeout
        self.sigterm_timeout = sigterm_timeout
        self._runs: dict[str, _Run] = {}
        self._lock = threading.RLock()
        self._stopping = False
        self.restarts: dict[str, int] = dict.fromkeys(self._specs, 0)

    # ---- starting ------------------------------------------------------------------------

    def start(self) -> None:
        """Start every child (once); on a failure, stop those already started and re-raise."""
        with self._lock:
            if self._runs:
                raise RuntimeError("supervisor already started")
            self._stopping = False
            try:
                may_fork = self._preload()
                for name in self._specs:  # every child first, then the readers: the forks
                    self._record(name, may_fork)  # see one thread
                for name, run in self._runs.items():
                    self._start_reader(name, run)
            except BaseException:  # (the pids file was written as each child started)
                self.stop()
                raise

    def _preload(self) -> bool:
        """Import the specs' ``preload`` modules; whether children may be forked now.  They are
        covnet's own (``sensors``, ``recorder``: packages beside ``covnet``), imported with
        covnet's folder first on the path: a program calling ``covnet.cli.main(["up", ...])``
        from a folder holding a ``sensors.py`` (its script's folder, a notebook's ``''``, first
        on its path) had that file imported here, a traceback or the user's module run in the
        launcher (hunt 15).  A program that imported a module of such a name itself keeps it:
        then no fork, every child a new interpreter (which never imports from the working
        directory: :func:`covnet.processes.up.node_env`)."""
        modules = sorted({m for s in self._specs.values() for m in s.preload})
        if not modules or not forked.forkable():
            return False
        root = packages_root()
        for m in modules:
            top = m.partition(".")[0]
            if top not in PACKAGES:  # numpy, zenoh, ...: as they are found
                importlib.import_module(m)
                continue
            have = sys.modules.get(top)
            if have is not None and not _lies_under(have, root):
                return False  # the program's own module of that name
            saved = list(sys.path)
            sys.path.insert(0, str(root))
            try:
                module = importlib.import_module(m)
            finally:
                sys.path[:] = saved
            if not _lies_under(module, root):
                return False
        return forked.forkable()  # an import may have started a thread

    def _record(self, name: str, may_fork: bool) -> _Run:
        """Start ``name`` and record it (here and in the pids file) before an interrupt that
        lands meanwhile is raised: a child is never started without being known to stop()."""
        with interrupts.held():
            run = self._runs[name] = self._start(name, may_fork)
            self._write_pids()
        return run

    def _spawn(self, name: str) -> None:
        """(Re)start ``name`` as a new interpreter, with its reader."""
        run = self._record(name, may_fork=False)
        self._start_reader(name, run)

    def _start(self, name: str, may_fork: bool) -> _Run:
        spec = self._specs[name]
        env = dict(os.environ)
        env.update(spec.env or {})
        env["PYTHONUNBUFFERED"] = "1"
        env["PYTHONIOENCODING"] = "utf-8"  # what _popen and the forks read (not the caller's)
        argv = spec.argv
        fork = may_fork and bool(spec.preload) and argv[:2] == [sys.executable, "-m"]
        # a child inherits the spawning thread's signal mask: make sure SIGINT/SIGTERM reach it
        old_mask = signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
        try:
            proc: subprocess.Popen[str] | forked.ForkedProcess
            if fork:
                proc = forked.fork_module(argv[2], argv[3:], env, name=name)
            else:
                proc = self._popen(spec, env)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        return _Run(proc, self._max_lines)

    def _start_reader(self, name: str, run: _Run) -> None:
        run.reader = threading.Thread(
            target=self._read, args=(name, run), name=f"supervisor-{name}", daemon=True
        )
        # the reader must never take the parent's SIGINT/SIGTERM (the main thread must, at
        # once); a thread inherits its creator's signal mask, so block them while creating it
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        try:
            run.reader.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

    @staticmethod
    def _popen(spec: ProcessSpec, env: dict[str, str]) -> subprocess.Popen[str]:
        return subprocess.Popen(
            spec.argv,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            encoding="utf-8",
            errors="replace",
            start_new_session=True,
        )

    def _read(self, name: str, run: _Run) -> None:
        assert run.proc.stdout is not None
        complained = False
        for raw in run.proc.stdout:
            line = raw.rstrip("\n")
            with run.cond:
                run.lines.append(line)
                run.count += 1
                run.cond.notify_all()
            try:
                self._on_line(name, line)
            except Exception:  # a broken sink must not stop draining (the child would block)
                if not complained:
                    complained = True
                    traceback.print_exc()
        with run.cond:
            run.eof = True
            run.cond.notify_all()

    def _write_pids(self) -> None:
        if self._pids_file is None:
            return
        pids: dict[str, object] = {name: run.proc.pid for name, run in self._runs.items()}
        pids.update(self._pids_extra)
        tmp = self._pids_file.with_name(self._pids_file.name + ".tmp")
        try:
            tmp.write_text(json.dumps(pids, indent=1) + "\n")
            os.replace(tmp, self._pids_file)
        except BaseException as exc:  # none left half-written; a full disk names the file
            with contextlib.suppress(OSError):
                tmp.unlink()
            if isinstance(exc, OSError):
                exc.filename, exc.filename2 = str(self._pids_file), None
            raise

    # ---- watching ------------------------------------------------------------------------

    @property
    def pids(self) -> dict[str, int]:
        with self._lock:
            return {name: run.proc.pid for name, run in self._runs.items()}

    def output(self, name: str) -> list[str]:
        """The retained output lines of ``name``'s current incarnation."""
        run = self._runs[name]
        with run.cond:
            return list(run.lines)

    def wait_for_line(self, name: str, match: str | Callable[[str], bool], timeout: float) -> bool:
        """True as soon as a line of ``name``'s current incarnation (retained lines first)
        contains ``match`` (or satisfies it, if callable); False after ``timeout`` seconds or
        once the child's output has ended without such a line."""
        pred = match if callable(match) else (lambda line: match in line)
        run = self._runs[name]
        deadline = time.monotonic() + timeout
        seen = 0  # absolute index of the next line to test
        with run.cond:
            while True:
                first = run.count - len(run.lines)  # absolute index of run.lines[0]
                for i in range(max(seen, first), run.count):
                    if pred(run.lines[i - first]):
                        return True
                seen = run.count
                if run.eof:
                    return False
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                run.cond.wait(min(remaining, _SLICE_S))  # sliced: see _SLICE_S

    def wait(self, name: str, timeout: float | None) -> int | None:
        """``name``'s return code once its current incarnation has exited; None after
        ``timeout`` seconds (None: no limit) if it is still running."""
        proc = self._runs[name].proc
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:  # sliced, so that the main thread runs signal handlers meanwhile
            left = _SLICE_S if deadline is None else min(_SLICE_S, deadline - time.monotonic())
            try:
                return proc.wait(timeout=max(left, 0.0))
            except subprocess.TimeoutExpired:
                if deadline is not None and time.monotonic() >= deadline:
                    return None

    def poll(self) -> dict[str, int | None]:
        """Each child's return code (None while running). Children with ``restart=True``
        that have failed (non-zero status) are restarted here (counted in :attr:`restarts`)
        and report None."""
        with self._lock:
            out: dict[str, int | None] = {}
            for name, run in list(self._runs.items()):
                rc = run.proc.poll()
                failed = rc not in (None, 0, EXIT_RUN_FAILED, EXIT_NO_RUN)
                if failed and self._specs[name].restart and not self._stopping:
                    self._finish(run)
                    self._spawn(name)
                    self.restarts[name] += 1
                    self._write_pids()
                    rc = None
                out[name] = rc
            return out

    def restart(
        self,
        name: str,
        *,
        sigint_timeout: float | None = None,
        sigterm_timeout: float | None = None,
    ) -> None:
        """Stop ``name`` (SIGINT, then SIGTERM, then SIGKILL; timeouts default to the
        supervisor's) and start it again."""
        with self._lock:
            if self._stopping or name not in self._runs:
                raise RuntimeError(f"cannot restart {name!r}: not running under this supervisor")
            self._terminate(
                [self._runs[name]],
                self.sigint_timeout if sigint_timeout is None else sigint_timeout,
                self.sigterm_timeout if sigterm_timeout is None else sigterm_timeout,
            )
            self._spawn(name)
            self.restarts[name] += 1
            self._write_pids()

    # ---- stopping ------------------------------------------------------------------------

    def stop(
        self, sigint_timeout: float | None = None, sigterm_timeout: float | None = None
    ) -> dict[str, int]:
        """Stop every child (SIGINT -> SIGTERM -> SIGKILL to its process group), reap it and
        join its reader; returns each child's return code (negative: killed by that signal).
        The timeouts [s] default to the supervisor's (5 s each). Idempotent."""
        with self._lock:
            self._stopping = True
            runs = dict(self._runs)
            self._terminate(
                list(runs.values()),
                self.sigint_timeout if sigint_timeout is None else sigint_timeout,
                self.sigterm_timeout if sigterm_timeout is None else sigterm_timeout,
            )
            return {name: run.proc.wait() for name, run in runs.items()}

    def _terminate(self, runs: list[_Run], sigint_timeout: float, sigterm_timeout: float) -> None:
        try:
            for sig, timeout in (
                (signal.SIGINT, sigint_timeout),
                (signal.SIGTERM, sigterm_timeout),
            ):
                alive = [r for r in runs if not r.done and r.proc.poll() is None]
                if not alive:
                    break
                for r in alive:
                    _signal_child(r.proc, sig)
                deadline = time.monotonic() + timeout
                for r in alive:
                    try:
                        r.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
                    except subprocess.TimeoutExpired:
                        pass
        finally:  # also after a second Ctrl-C: nothing survives (and a third one waits)
            with interrupts.held():
                for r in runs:
                    if r.done:
                        continue
                    if r.proc.poll() is None:
                        _signal_child(r.proc, signal.SIGKILL)
                        r.proc.wait()
                    if _killpg(r.proc.pid, signal.SIGKILL):  # leftovers in the child's group
                        _wait_group_gone(r.proc.pid, timeout=2.0)
                    self._finish(r)

    def _finish(self, run: _Run) -> None:
        run.proc.wait()
        run.done = True
        if run.reader is not None and run.reader is not threading.current_thread():
            run.reader.join(timeout=5.0)
        if run.proc.stdout is not None and (run.reader is None or not run.reader.is_alive()):
            run.proc.stdout.close()

    def __enter__(self) -> Supervisor:
        if not self._runs:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _killpg(pgid: int, sig: int) -> bool:
    """Signal a process group; False when it has no (signalable) member left."""
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        return False
    return True


def _signal_child(proc: subprocess.Popen[str] | forked.ForkedProcess, sig: int) -> None:
    """Signal a child's process group (its pid).  A child just forked may not have reached
    its ``setsid()`` yet (it is still in this process's group, with this process's handlers):
    wait for its group to exist (bounded), then signal that; failing that, the child alone.
    Only for a child not yet reaped (its pid cannot have been reused)."""
    deadline = time.monotonic() + _GROUP_WAIT_S
    while not _killpg(proc.pid, sig):
        if proc.poll() is not None:
            return
        if time.monotonic() > deadline:
            try:
                os.kill(proc.pid, sig)
            except ProcessLookupError:
                pass
            return
        time.sleep(0.001)


def _group_members(pgid: int) -> list[int]:
    """Live (non-zombie) processes of process group ``pgid`` (Linux ``/proc``)."""
    members = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()  # state ppid pgrp ...
        except (OSError, IndexError):
            continue
        if len(fields) > 2 and fields[2] == str(pgid).encode() and fields[0] != b"Z":
            members.append(int(entry))
    return members


def _wait_group_gone(pgid: int, timeout: float) -> None:
    """Wait (bounded) until SIGKILLed grandchildren, which we cannot reap, have died."""
    deadline = time.monotonic() + timeout
    while _group_members(pgid) and time.monotonic() < deadline:
        time.sleep(0.01)


def sigterm_raises_keyboard_interrupt() -> None:
    """Make SIGTERM to this (parent) process raise KeyboardInterrupt in the main thread, so a
    ``with Supervisor(...)`` block stops its children on SIGTERM as on Ctrl-C."""
    signal.signal(signal.SIGTERM, interrupts.raise_interrupt)
