"""covnet.batches.pool.parallel_map: the same results as a plain loop, in task order; a worker's
error
raised in the parent; a dead worker reported; Ctrl-C stops every worker and keeps what was
done.  Real worker processes (``python -m covnet.batches.worker``)."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pytest

from covnet.batches.pool import (
    BatchInterrupted,
    WorkerDied,
    end_batch,
    imap_unordered,
    parallel_map,
)
from covnet.runs.rundir import read_json


def square(x: int) -> int:
    return x * x


def slow_square(x: int) -> int:
    time.sleep(0.05 * (x % 3))  # finish out of order
    return x * x


def fails_on_three(x: int) -> int:
    if x == 3:
        raise ValueError(f"task {x} is bad")
    return x


def dies_on_two(x: int) -> int:
    if x == 2:
        os._exit(7)
    return x


def sleeps(x: int) -> int:
    if x >= 2:
        time.sleep(60)
    return x


def _workers_of(pid: int) -> list[int]:
    """Live ``covnet.batches.worker`` processes whose parent is ``pid``."""
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = Path(f"/proc/{d}/stat").read_text()
            cmd = Path(f"/proc/{d}/cmdline").read_bytes()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[1].split()
        if int(fields[1]) == pid and fields[0] != "Z" and b"covnet.batches.worker" in cmd:
            out.append(int(d))
    return out


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_results_in_task_order_whatever_the_completion_order(workers):
    seen = []
    got = parallel_map(slow_square, list(range(7)), workers, lambda d, n, i: seen.append((d, n, i)))
    assert got == [x * x for x in range(7)]
    assert [d for d, _, _ in seen] == list(range(1, 8))
    assert sorted(i for _, _, i in seen) == list(range(7))
    assert all(n == 7 for _, n, _ in seen)
    assert _workers_of(os.getpid()) == []


def test_no_tasks():
    assert parallel_map(square, [], 2) == []


def test_a_workers_exception_is_raised_in_the_parent_with_its_type():
    with pytest.raises(ValueError, match="task 3 is bad") as info:
        parallel_map(fails_on_three, list(range(6)), 2)
    assert any("in a worker process" in n for n in getattr(info.value, "__notes__", []))
    assert _workers_of(os.getpid()) == []


def test_a_worker_that_dies_is_reported():
    with pytest.raises(WorkerDied, match="exit code 7|ended"):
        parallel_map(dies_on_two, list(range(5)), 2)
    assert _workers_of(os.getpid()) == []


def dies_on_even_killed(x: int) -> int:
    if x in (2, 4):
        os.kill(os.getpid(), signal.SIGKILL)  # as the OOM killer or a kill -9 would
    return x * 10


def test_a_dead_worker_fails_its_task_and_the_others_go_on():
    """One killed worker ended the whole batch (a WorkerDied traceback, the other worker
    terminated, the other tasks never run); now its task is a failure and a new worker takes
    the rest."""
    out = {i: (ok, v) for i, ok, v in imap_unordered(dies_on_even_killed, list(range(7)), 2)}
    assert sorted(out) == list(range(7))
    for i in (2, 4):
        ok, died = out[i]
        assert not ok and isinstance(died, WorkerDied), died
        assert f"during task {i}" in str(died) and "exit code -9" in str(died), str(died)
    assert {i: v for i, (ok, v) in out.items() if ok} == {i: 10 * i for i in (0, 1, 3, 5, 6)}
    assert _workers_of(os.getpid()) == []


def test_a_worker_dead_before_it_read_its_messages_fails_its_task_and_the_others_go_on(
    monkeypatch,
):
    """A worker killed while it was still starting (its path, function and first task unread
    in its socket): the parent's read got ECONNRESET, not EOF, and the whole batch stopped
    with "Connection reset by peer".  It is a dead worker like any other."""
    import subprocess
    import sys

    real, started = subprocess.Popen, []

    def first_never_reads(argv, **kw):
        if not started:  # the first worker: dies without reading what it was sent
            argv = [sys.executable, "-c", "import os, time; time.sleep(0.5); os._exit(9)"]
        started.append(argv)
        return real(argv, **kw)

    monkeypatch.setattr(subprocess, "Popen", first_never_reads)
    out = {i: (ok, v) for i, ok, v in imap_unordered(square, list(range(5)), 2)}
    assert sorted(out) == list(range(5))
    failed = {i: v for i, (ok, v) in out.items() if not ok}
    assert len(failed) == 1 and all(isinstance(v, WorkerDied) for v in failed.values()), failed
    (why,) = map(str, failed.values())
    assert "exit code 9" in why, why
    assert {i: v for i, (ok, v) in out.items() if ok} == {i: i * i for i in out if i not in failed}
    assert len(started) == 3  # the two workers and the one that took over
    assert _workers_of(os.getpid()) == []


def test_ctrl_c_stops_every_worker_and_keeps_what_was_done():
    timers: list[threading.Timer] = []

    def on_progress(done: int, n: int, i: int) -> None:
        if done == 2:  # the two quick tasks are in (however slow the workers were to start)
            timers.append(threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)))
            timers[-1].start()

    t0 = time.monotonic()
    try:
        with pytest.raises(BatchInterrupted) as info:
            parallel_map(sleeps, list(range(6)), 2, on_progress)
    finally:
        for t in timers:
            t.cancel()
    assert time.monotonic() - t0 < 30.0
    assert info.value.done == {0: 0, 1: 1}
    assert info.value.total == 6
    assert isinstance(info.value, KeyboardInterrupt)  # the CLI's exit 130
    assert _workers_of(os.getpid()) == []


def test_in_process_ctrl_c_keeps_what_was_done_too():
    def interrupting(x: int) -> int:
        if x == 2:
            raise KeyboardInterrupt
        return x

    with pytest.raises(BatchInterrupted) as info:
        parallel_map(interrupting, list(range(5)), 1)
    assert info.value.done == {0: 0, 1: 1}


def test_end_batch_records_the_status(tmp_path, capsys):
    end_batch(tmp_path / "done", 4, "seed")
    info = read_json(tmp_path / "done" / "run.json")
    assert (info["status"], info["runs_completed"], info["runs_total"]) == ("completed", 4, 4)

    stop: BatchInterrupted[int] = BatchInterrupted({0: 1, 2: 3}, 5)
    end_batch(tmp_path / "cut", 5, "seed", stop, kept=2)
    info = read_json(tmp_path / "cut" / "run.json")
    assert info["status"] == "interrupted"
    assert (info["runs_completed"], info["runs_total"]) == (2, 5)
    assert "holds the 2 complete seed(s)" in capsys.readouterr().err

    end_batch(tmp_path / "nothing", 5, "seed", BatchInterrupted({}, 5), kept=0)
    assert not (tmp_path / "nothing").exists()
    assert "nothing written" in capsys.readouterr().err


def test_the_cli_reports_a_dead_worker_in_one_line(monkeypatch, capsys):
    """A batch whose worker was killed ends with exit 1 and one line (it was a traceback)."""
    import argparse

    from covnet.cli import app

    def fails(args):
        exc = WorkerDied("a worker process (pid 7) ended with exit code -9 during task 3")
        exc.add_note("1 of 4 task(s) failed; the finished trials are saved")
        raise exc

    parser = argparse.ArgumentParser()
    parser.set_defaults(func=fails)
    monkeypatch.setattr(app, "build_parser", lambda: parser)
    assert app.main([]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "exit code -9" in err and "trials are saved" in err, err


def test_the_cli_reports_a_lost_scheduler_in_one_line(monkeypatch, capsys):
    import argparse

    from covnet.cli import app
    from covnet.errors import ClusterLost

    def fails(args):
        raise ClusterLost("task 8: the Dask scheduler at tcp://127.0.0.1:1 went away")

    parser = argparse.ArgumentParser()
    parser.set_defaults(func=fails)
    monkeypatch.setattr(app, "build_parser", lambda: parser)
    assert app.main([]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and "went away" in err, err
