"""Run many independent simulations on the machine's cores (``covnet compare``, ``covnet
sweep``): a process pool started with ``spawn`` (never ``fork``: a forked child of a process
that opened a zenoh session hangs), results in task order, a progress callback."""

from __future__ import annotations

import csv
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")


def parallel_map(
    fn: Callable[[T], R],
    tasks: Sequence[T],
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[R]:
    """``[fn(t) for t in tasks]`` on ``workers`` processes (default: one per core; ``1`` runs
    in this process). ``fn`` must be a module-level function (the workers import it)."""
    workers = workers or min(os.cpu_count() or 1, max(len(tasks), 1))
    out: list[Any] = []
    if workers <= 1:
        for t in tasks:
            out.append(fn(t))
            if progress:
                progress(len(out), len(tasks))
        return out
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        for r in pool.map(fn, tasks):
            out.append(r)
            if progress:
                progress(len(out), len(tasks))
    return out


def progress_printer(label: str, every_s: float = 1.0) -> Callable[[int, int], None]:
    """A progress callback printing ``[label] done/n runs`` on stderr at most every ``every_s``
    (progress is not output: stdout stays for the results, ``--json`` for JSON only)."""

    shown = [0.0]

    def show(done: int, n: int) -> None:
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
    """``<stem>.json`` (``meta`` and every row in full) and ``<stem>.csv`` (``columns``)."""

    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps({**meta, "rows": list(rows)}, indent=2) + "\n")
    with (out / f"{stem}.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
