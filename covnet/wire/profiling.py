"""Where a node process's loop spends its time, measured where it runs.

- ``COVNET_PROFILE=DIR`` in the environment of ``covnet up`` (or ``covnet bench up``): every loop
  wrapped in :func:`profiled` (the manager's, each sensor's, the recorder's) runs under
  :mod:`cProfile` and writes its statistics to ``DIR/<name>-<pid>-<thread>.prof`` when it ends
  (read them with :mod:`pstats`).
- ``COVNET_STAGES=DIR`` (``covnet bench up --profile DIR``): a loop's :class:`Stages` time its
  stages, wall and CPU (``time.perf_counter_ns``, ``time.thread_time_ns``), and write the sums
  to ``DIR/<name>-<pid>-<thread>.json`` when it ends.

Unset, :func:`profiled` costs one environment lookup and a :meth:`Stages.lap` a method call.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

__all__ = ["ENV", "STAGES_ENV", "Stages", "profiled"]

ENV = "COVNET_PROFILE"
STAGES_ENV = "COVNET_STAGES"


def _file(where: str, name: str, suffix: str) -> Path:
    out = Path(where)
    out.mkdir(parents=True, exist_ok=True)
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
    return out / f"{safe}-{os.getpid()}-{threading.get_ident()}{suffix}"


@contextlib.contextmanager
def profiled(name: str) -> Iterator[None]:
    """Run the body under :mod:`cProfile` (this thread only) when :data:`ENV` names a
    directory; the statistics go to ``<dir>/<name>-<pid>-<thread id>.prof``."""
    where = os.environ.get(ENV)
    if not where:
        yield
        return
    import cProfile  # profiling runs only (start-up of the others)

    prof = cProfile.Profile()
    prof.enable()
    try:
        yield
    finally:
        prof.disable()
        prof.dump_stats(_file(where, name, ".prof"))


class Stages:
    """A loop's time by stage, for one thread: :meth:`lap` charges the wall and CPU time since
    the previous lap (or :meth:`start`) to a stage; :meth:`dump` writes the sums (and the
    process's CPU time over the same span) when :data:`STAGES_ENV` names a directory.  Off
    (the default) it measures nothing."""

    __slots__ = ("enabled", "wall", "cpu", "n", "_t", "_c", "_t0", "_p0")

    def __init__(self) -> None:
        self.enabled = bool(os.environ.get(STAGES_ENV))
        self.wall: dict[str, int] = {}
        self.cpu: dict[str, int] = {}
        self.n: dict[str, int] = {}
        self._t = self._c = self._t0 = self._p0 = 0
        self.start()

    def start(self) -> None:
        """Begin the span (and the first lap) now."""
        if self.enabled:
            self._t = self._t0 = time.perf_counter_ns()
            self._c = time.thread_time_ns()
            self._p0 = time.process_time_ns()

    def lap(self, stage: str) -> None:
        """Charge the time since the previous lap to ``stage``."""
        if not self.enabled:
            return
        t, c = time.perf_counter_ns(), time.thread_time_ns()
        self.wall[stage] = self.wall.get(stage, 0) + t - self._t
        self.cpu[stage] = self.cpu.get(stage, 0) + c - self._c
        self.n[stage] = self.n.get(stage, 0) + 1
        self._t, self._c = t, c

    def dump(self, name: str, **extra: object) -> None:
        """Write ``{name, wall_ns, cpu_ns, n, span_wall_ns, process_cpu_ns, **extra}`` to
        ``$COVNET_STAGES/<name>-<pid>-<thread>.json`` (nothing when off)."""
        where = os.environ.get(STAGES_ENV)
        if not self.enabled or not where:
            return
        import json  # profiling runs only (start-up of the others)

        data = {
            "name": name,
            "wall_ns": self.wall,
            "cpu_ns": self.cpu,
            "n": self.n,
            "span_wall_ns": time.perf_counter_ns() - self._t0,
            "process_cpu_ns": time.process_time_ns() - self._p0,
        }
        path = _file(where, name, ".json")
        try:
            path.write_text(json.dumps({**data, **extra}))
        except OSError as exc:  # a full disk: the message names the file (it named none)
            if exc.filename is None:
                exc.filename = str(path)
            raise
