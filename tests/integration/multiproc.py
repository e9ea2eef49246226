"""Helpers for multi-process tests: run ``covnet`` as a real child process, bounded in time,
stopped by PID (SIGINT, then SIGTERM, then SIGKILL), never leaving anything behind."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


class CovnetProcess:
    """``python -m covnet ARGS`` in its own session, its output collected line by line."""

    def __init__(self, args: list[str], cwd: Path = REPO, prefix: list[str] | None = None):
        self.proc = subprocess.Popen(
            [*(prefix or []), sys.executable, "-m", "covnet", *args],
            cwd=cwd,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def wait_for(self, pred, timeout: float) -> str | None:
        """The first output line satisfying ``pred`` (a substring or a callable), or None."""
        test = (lambda s: pred in s) if isinstance(pred, str) else pred
        deadline = time.monotonic() + timeout
        seen = 0
        with self._cond:
            while True:
                for line in self.lines[seen:]:
                    if test(line):
                        return line
                seen = len(self.lines)
                remaining = deadline - time.monotonic()
                if remaining <= 0 or (self.proc.poll() is not None and not self._reader.is_alive()):
                    return None
                self._cond.wait(min(remaining, 0.2))

    def wait(self, timeout: float) -> int:
        rc = self.proc.wait(timeout=timeout)
        self._close()
        return rc

    def _close(self) -> None:
        self._reader.join(timeout=5)
        if self.proc.stdout is not None and not self._reader.is_alive():
            self.proc.stdout.close()

    def output(self) -> str:
        return "\n".join(self.lines)

    def stop(self) -> None:
        """SIGINT, then SIGTERM, then SIGKILL to the whole process group."""
        for sig, grace in ((signal.SIGINT, 8.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            try:
                os.killpg(self.proc.pid, sig)
            except ProcessLookupError:
                break
            try:
                self.proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                continue
        self.proc.wait()
        self._close()


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie still answers kill(0); it is gone for our purposes if it is a zombie
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except OSError:
        return False


def assert_nothing_left(run_dir: Path) -> None:
    pids = {
        n: p
        for n, p in json.loads((run_dir / "processes.json").read_text()).items()
        if isinstance(p, int)  # "hosts" (sensor -> its process) is not a process
    }
    deadline = time.monotonic() + 5
    while any(pid_alive(p) for p in pids.values()) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = {n: p for n, p in pids.items() if pid_alive(p)}
    assert not left, f"processes left running: {left}"


def run_to_end(args: list[str], timeout: float = 240.0) -> str:
    """``covnet ARGS`` to its end, asserting exit 0 (stopped by PID whatever happens); returns
    its output."""
    p = CovnetProcess(args)
    try:
        rc = p.wait(timeout=timeout)
    finally:
        p.stop()
    assert rc == 0, p.output()
    return p.output()


def up_lockstep(config: Path, out: Path, timeout: float = 240.0) -> str:
    """``covnet up CONFIG --out OUT --no-figures --verbose`` to its end (lockstep by default),
    asserting exit 0; returns its output (the live ``[status]`` lines among it)."""
    return run_to_end(["up", str(config), "--out", str(out), "--no-figures", "--verbose"], timeout)


def assert_status_shows_gap(output: str) -> None:
    """Every live ``[status]`` line shows the scan's certified gap (at least one line)."""
    shown = [line for line in output.splitlines() if line.startswith("[status] ")]
    assert shown and all(re.search(r"gap [0-9.e+-]+ ?%", line) for line in shown), shown
