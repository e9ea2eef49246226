"""Run many independent simulations on the machine's cores (``covnet compare``, ``covnet
sweep``, ``covnet mc`` of every kind): one process pool for all of them, results in task order,
a progress callback, and a stop that always stops.

The pool is deliberately small: ``workers`` processes, each a fresh ``python -m
covnet.batches.worker`` (never a ``fork``: a forked child of a process that opened a zenoh
session hangs) with one socket to the parent; the parent hands out one task at a time and waits
on the sockets and the processes together.  No manager thread, no shared queue, no semaphore:
nothing that a signal or a dead worker can leave half-updated (what made ``concurrent.futures``
pools hang on Ctrl-C, or raise from their manager thread).

Ctrl-C and SIGTERM (:func:`parallel_map`):

- each worker runs in its own session (``setsid`` before ``exec``), out of reach of the
  terminal: the terminal's Ctrl-C, sent to the foreground process group, acts in the parent
  only, which stops the workers;
- on Ctrl-C (or any error) in the parent every worker is terminated by PID (SIGTERM, then
  SIGKILL after :data:`STOP_GRACE_S`) and reaped, then :class:`BatchInterrupted` (a
  KeyboardInterrupt) carries the results finished so far, so the command can still write them;
- a worker leaves when its socket closes, and on Linux dies with its parent
  (``PR_SET_PDEATHSIG``), so not even a SIGKILL of the parent leaves one behind.

A task that raises in a worker raises the same exception in the parent (its traceback text
added as a note), after the other workers are stopped.
"""

from __future__ import annotations

import csv
import io
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, Generic, TypeVar

from covnet.errors import WorkerDied
from covnet.processes import interrupts
from covnet.runs.rundir import atomic_write, record_end

T = TypeVar("T")
R = TypeVar("R")

STOP_GRACE_S = 2.0
"""How long a terminated worker gets before SIGKILL."""

Progress = Callable[[int, int, int], None]
"""``progress(done, n, index)``: ``done`` of ``n`` tasks finished, the last one ``tasks[index]``
(called in completion order)."""


class BatchInterrupted(KeyboardInterrupt, Generic[R]):
    """The batch was interrupted; ``done`` maps each finished task's index (the batch layer's:
    its ``(point, seed)``) to its result."""

    def __init__(self, done: dict[Any, R], total: int) -> None:
        super().__init__(f"interrupted after {len(done)} of {total} runs")
        self.done = done
        self.total = total
        self.partial: Any = None
        """What the command makes of the finished runs (its table's complete rows), set on
        the way up by the function that knows how."""


def default_workers() -> int:
    """The cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


@dataclass
class _Worker:
    proc: subprocess.Popen[bytes]
    conn: Connection
    pidfd: int | None = None  # readable once the process has ended
    task: int | None = None  # the index of the task it is running

    @property
    def sentinel(self) -> Any:
        """Ready when the worker has ended (its pidfd; else its socket's EOF)."""
        return self.conn if self.pidfd is None else self.pidfd


def parallel_map(
    fn: Callable[[T], R],
    tasks: Sequence[T],
    workers: int | None = None,
    progress: Progress | None = None,
) -> list[R]:
    """``[fn(t) for t in tasks]`` on ``workers`` processes (default: one per core, at most one
    per task; ``1`` runs in this process). ``fn`` must be a module-level function (the workers
    import it).  Raises :class:`BatchInterrupted` on Ctrl-C, after every worker is gone."""
    n = len(tasks)
    done: dict[int, R] = {}
    try:
        for i, ok, value in imap_unordered(fn, tasks, workers):
            if not ok:
                raise value
            done[i] = value
            if progress:
                progress(len(done), n, i)
    except KeyboardInterrupt:
        raise BatchInterrupted(done, n) from None
    return [done[i] for i in range(n)]


def imap_unordered(
    fn: Callable[[T], R], tasks: Sequence[T], workers: int | None = None
) -> Iterator[tuple[int, bool, Any]]:
    """``(index, True, fn(tasks[index]))`` for each task in completion order, or ``(index,
    False, exception)`` for one that raised (the others go on; the exception carries the
    worker's traceback as a note) or whose worker ended before answering (killed, out of
    memory: a :class:`WorkerDied`, and a new worker takes the next task; one such death stopped
    the whole batch with a traceback).  ``workers`` processes as :func:`parallel_map`; ``1``
    runs in this process.  Every worker is stopped and reaped when the iteration ends, also by
    an exception (Ctrl-C) or by the caller leaving the loop (close the generator, or let it
    go)."""
    n = len(tasks)
    workers = min(workers or default_workers(), max(n, 1))
    if workers <= 1:
        for i, t in enumerate(tasks):
            try:
                value = fn(t)
            except Exception as exc:  # noqa: BLE001 (reported to the caller, as a worker's)
                yield i, False, exc
                continue
            yield i, True, value
        return
    pool: list[_Worker] = []
    finished = False
    try:
        _start(pool, fn, workers)
        todo: Iterator[tuple[int, T]] = iter(enumerate(tasks))
        for w in pool:
            _hand_out(w, todo)
        received = 0
        while received < n:
            busy = [w for w in pool if w.task is not None]
            ready = wait([w.conn for w in busy] + [w.sentinel for w in busy], timeout=0.2)
            for w in busy:
                if w.conn not in ready and w.sentinel not in ready:
                    continue
                out: tuple[int, bool, Any]
                try:
                    if w.conn not in ready:
                        raise WorkerDied(f"a worker process (pid {w.proc.pid}) ended")
                    out = _receive(w)
                except WorkerDied as died:
                    i = _replace(pool, w, fn)
                    died.args = (f"{died} with exit code {w.proc.returncode} during task {i}",)
                    out, w = (i, False, died), pool[-1]
                received += 1
                _hand_out(w, todo)
                yield out
        finished = True
    finally:
        if finished:
            _finish(pool)
        else:
            _stop(pool)


def _start(pool: list[_Worker], fn: Callable[..., Any], workers: int) -> None:
    """Start ``workers`` :mod:`covnet.batches.worker` processes, each in its own session, and
    send each the parent's ``sys.path`` and ``fn``."""
    for _ in range(workers):
        _spawn(pool, fn)


def _spawn(pool: list[_Worker], fn: Callable[..., Any]) -> None:
    """One more worker at the end of ``pool`` (see :func:`_start`)."""
    mine, theirs = socket.socketpair()
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "covnet.batches.worker", str(theirs.fileno())],
            pass_fds=(theirs.fileno(),),
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
    finally:
        theirs.close()
    conn = Connection(mine.detach())
    pidfd = os.pidfd_open(proc.pid) if hasattr(os, "pidfd_open") else None
    pool.append(_Worker(proc, conn, pidfd))
    try:
        conn.send(list(sys.path))
        conn.send(fn)
    except OSError:  # it died at once: its first task finds out (EOF)
        pass


def _replace(pool: list[_Worker], w: _Worker, fn: Callable[..., Any]) -> int:
    """Reap the ended worker ``w`` and put a new one at the end of ``pool``; the index of the
    task ``w`` was running."""
    task = w.task
    assert task is not None
    w.proc.wait()
    w.conn.close()
    if w.pidfd is not None:
        os.close(w.pidfd)
    pool.remove(w)
    _spawn(pool, fn)
    return task


def _hand_out(w: _Worker, todo: Iterator[tuple[int, Any]]) -> None:
    nxt = next(todo, None)
    w.task = None if nxt is None else nxt[0]
    if nxt is not None:
        try:
            w.conn.send(nxt)
        except OSError:  # it has ended: the wait finds out (its sentinel), a failed task
            pass


def _receive(w: _Worker) -> tuple[int, bool, Any]:
    try:
        i, ok, value, tb = w.conn.recv()
    except (EOFError, OSError):  # OSError: it died with what it was sent unread (ECONNRESET)
        raise WorkerDied(f"a worker process (pid {w.proc.pid}) ended") from None
    if not ok:
        value.add_note(f"in a worker process (pid {w.proc.pid}), task {i}:\n{tb}")
    return int(i), bool(ok), value


def _finish(pool: list[_Worker]) -> None:
    """Tell every worker to leave and reap it (stop it if it does not)."""
    for w in pool:
        try:
            w.conn.send(None)
        except OSError:
            pass
    deadline = time.monotonic() + STOP_GRACE_S
    for w in pool:
        try:
            w.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    _stop(pool)


def _stop(pool: list[_Worker]) -> None:
    """Terminate every worker by PID (SIGTERM, SIGKILL after the grace) and reap it."""
    for w in pool:
        if w.proc.poll() is None:
            w.proc.terminate()
    deadline = time.monotonic() + STOP_GRACE_S
    for w in pool:
        try:
            w.proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            w.proc.kill()
            w.proc.wait()
        w.conn.close()
        if w.pidfd is not None:
            os.close(w.pidfd)
            w.pidfd = None


def end_batch(
    out: Path,
    total: int,
    what: str,
    stop: BatchInterrupted[Any] | None = None,
    kept: int = 0,
    **facts: Any,
) -> None:
    """Record how a batch of ``total`` runs ended in ``out/run.json``
    (:func:`covnet.runs.rundir.record_end`, with ``facts``).  After an interruption ``stop``, when
    ``kept`` complete ``what`` s (grid points, seeds, ...) were written, say so on stderr; when
    none were and ``out`` does not exist, write nothing (not even the directory) and say that;
    a directory that holds finished trials (``out/trials``) is resumed by the same command."""
    if stop is None:
        record_end(
            out, "completed", "every run done", runs_completed=total, runs_total=total, **facts
        )
        return
    n = len(stop.done)
    again = _same_command(out, "resumes")
    if kept == 0 and not out.is_dir():
        print(
            f"interrupted after {n} of {total} runs, before the first complete {what}: "
            "nothing written",
            file=sys.stderr,
        )
        return
    record_end(
        out,
        "interrupted",
        f"interrupted (Ctrl-C or SIGTERM) after {n} of {total} runs",
        runs_completed=n,
        runs_total=total,
        **facts,
    )
    if kept == 0:
        print(
            f"interrupted after {n} of {total} runs, before the first complete {what}: "
            f"{out} holds the finished trials only{again}",
            file=sys.stderr,
        )
        return
    print(
        f"interrupted after {n} of {total} runs: {out} holds the {kept} complete {what}(s); "
        f"figures skipped (partial){again}",
        file=sys.stderr,
    )


def _same_command(out: Path, does: str) -> str:
    """``"; the same command with --out OUT <does>"`` when ``out`` keeps finished trials (the
    same command takes them up), else ``""``."""
    return f"; the same command with --out {out} {does}" if (out / "trials").is_dir() else ""


def finish_batch(out: Path, total: int, what: str, write: Callable[[], R], **facts: Any) -> R:
    """Write the results of a batch whose ``total`` runs all finished: ``write()`` (its table
    files and ``config.json``), then ``run.json``'s ``completed`` (:func:`end_batch` with
    ``facts``), last, so a ``run.json`` that says ``completed`` has the whole table beside it;
    ``write``'s value.

    A Ctrl-C or SIGTERM meanwhile (it left a ``run.json`` without ``status`` and no table) ends
    the batch as one while its runs went on: the table is written (``write()`` again: every
    row is there; a second interruption leaves it unwritten), ``run.json`` says
    ``interrupted``, stderr what ``out`` holds and that the same command finishes it (its
    trials are kept), and the interruption goes on (exit 130)."""
    try:
        value = write()
        end_batch(out, total, what, **facts)
        return value
    except BaseException as exc:
        if not interrupts.caused(exc):
            raise
        try:
            write()
            holds = "the whole table"
        except BaseException as again:
            if not interrupts.caused(again):
                raise
            holds = "a table that may be incomplete or an earlier one"
        record_end(
            out,
            "interrupted",
            f"interrupted (Ctrl-C or SIGTERM) after every run ({total} of {total}), while the "
            "results were written",
            runs_completed=total,
            runs_total=total,
            **facts,
        )
        again_cmd = _same_command(out, "finishes it")
        print(
            f"interrupted after every run ({total} of {total}), while the results were written: "
            f"{out} holds {holds} (run.json: interrupted); figures skipped{again_cmd}",
            file=sys.stderr,
        )
        raise


def progress_printer(label: str, every_s: float = 1.0) -> Progress:
    """A progress callback printing ``[label] done/n runs`` on stderr at most every ``every_s``
    (progress is not output: stdout stays for the results, ``--json`` for JSON only)."""

    shown = [0.0]

    def show(done: int, n: int, index: int = 0) -> None:
        now = time.monotonic()
        if done == n or now - shown[0] > every_s:
            print(f"[{label}] {done}/{n} runs", file=sys.stderr, flush=True)
            shown[0] = now

    return show


def write_rows(
    out: Path,
    stem: str,
    rows: Sequence[dict[str, Any]],
    meta: dict[str, Any],
    columns: Sequence[str],
) -> None:
    """``<stem>.json`` (``meta`` and every row in full) and ``<stem>.csv`` (``columns``), each
    written whole or not at all (:func:`covnet.runs.rundir.atomic_write`: a full disk left a
    half table, and an error naming no file)."""

    out.mkdir(parents=True, exist_ok=True)
    doc = json.dumps({**meta, "rows": list(rows)}, indent=2) + "\n"
    atomic_write(out / f"{stem}.json", doc.encode())
    table = io.StringIO(newline="")
    w = csv.DictWriter(table, fieldnames=list(columns), extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    atomic_write(out / f"{stem}.csv", table.getvalue().encode())
