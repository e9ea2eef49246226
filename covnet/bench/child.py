"""A ``covnet`` command as a child process of a benchmark (``bench soak``, ``bench up
--steady``): its own process group, its output read line by line, stopped by PID."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable


class Child:
    """``python -m covnet ARGS`` in its own process group, output lines kept with their
    monotonic times (and each handed to ``on_line`` as it comes, on the reader's thread);
    :meth:`stop` ends it by PID (SIGINT, SIGTERM, SIGKILL) when it is not done and closes its
    pipe."""

    def __init__(self, args: list[str], on_line: Callable[[str], None] | None = None) -> None:
        self.on_line = on_line
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "covnet", *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self.lines: list[tuple[float, str]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            text = line.rstrip("\n")
            self.lines.append((time.monotonic(), text))
            if self.on_line is not None:
                self.on_line(text)

    def first(self, pattern: str) -> float | None:
        """When the first line matching ``pattern`` (a regular expression) came."""
        rx = re.compile(pattern)
        return next((t for t, text in list(self.lines) if rx.search(text)), None)

    def stop(self) -> None:
        for sig, grace in ((signal.SIGINT, 10.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
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
        self._reader.join(timeout=5)
        if self.proc.stdout is not None and not self._reader.is_alive():
            self.proc.stdout.close()
