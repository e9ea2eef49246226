"""The batch layer of ``covnet sweep``, ``compare`` and ``mc`` (every kind): trials that
survive an interruption, seeds added until the intervals are narrow, the local pool or a Dask
cluster, and one progress line.

A *trial* is one seed at one grid point (a sweep's point, a compare mode, a passive cell, the
single point of a mobile Monte Carlo).  A kind describes its batch as a :class:`Batch`: the
point keys, the function that runs a task (a list of seeds of one point) and returns one
JSON-able result per seed, and how a task is made; :func:`run_trials` does the rest:

- **Resumable** (:class:`TrialStore`): every finished task is written as it completes to
  ``OUT/trials/<hash>/<point>/<seed>.json`` (a task of several seeds: ``<first>-<last>.json``),
  atomically (a temporary file renamed), where ``<hash>`` is the hash of everything that
  decides a trial's result (the config without its seed count and its evaluation settings, the
  command, the metric) and ``OUT/batch.json`` names it.  Re-running the same command with the
  same ``--out`` loads what is there, runs only the rest, and says how many it skipped; a
  directory of another batch is refused (:func:`prepare_batch_out`).  The results read back
  are the very numbers written (JSON keeps every float64 exactly), so a resumed batch equals an
  uninterrupted one bit for bit.  Each file names the code that wrote it
  (:func:`covnet.code_identity.code_identity`): a trial of other code (an upgrade between the
  start and the resume) is run again, with a note, never averaged in with this code's.
- **Seeds until the interval is narrow** (``ci_width``): after the first ``n`` seeds of every
  point, the points whose 95 % interval on the batch's headline metric is not narrower than
  ``ci_width`` get ``batch`` more seeds, round after round, until every point's is or it has
  ``max_seeds``.  Which points get more depends only on the results, so a resumed run makes
  the same rounds.
- **Where**: the local process pool (:func:`covnet.batches.pool.imap_unordered`) or, with
  ``cluster``, a Dask distributed scheduler (:mod:`covnet.batches.cluster`, imported only then: the
  local path never imports dask).  The task carries the config; a worker needs only covnet.
- **Progress**: one line on stderr for the whole batch (:class:`BatchProgress`): done/total,
  skipped, rate, ETA, failures.

A task that raises is a failure: counted, not written, the other trials go on; when the round
ends the first failure is raised (a re-run retries the failed trials only).  Ctrl-C raises
:class:`covnet.batches.pool.BatchInterrupted` with every trial known so far (``done``: ``(point,
seed)
-> result``), after every worker is stopped or every cluster task cancelled.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import math
import re
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TextIO

import numpy as np

from covnet.batches import MAX_SEEDS, point_text
from covnet.batches.pool import BatchInterrupted, default_workers, imap_unordered
from covnet.code_identity import code_identity, other_code
from covnet.config import hash_of
from covnet.core import registries
from covnet.errors import UsageError
from covnet.runs.rundir import (
    atomic_write,
    check_writable,
    claim,
    clear_output,
    prepare_out,
    read_json,
    utc_now,
)

__all__ = [
    "BATCH_INFO",
    "TRIALS",
    "Batch",
    "BatchProgress",
    "Outcome",
    "TrialStore",
    "point_key",
    "prepare_batch_out",
    "run_trials",
    "trial_hash",
]

BATCH_INFO = "batch.json"
"""``OUT/batch.json``: the command and trial hash of the batch whose trials ``OUT/trials``
holds (what makes a directory resumable)."""
TRIALS = "trials"

Task = Any
Result = Any


def point_key(point: Mapping[str, Any]) -> str:
    """A grid point as a readable file name: ``delay_ms=350,loss=0.1,mode=central,...``
    (characters other than letters, digits and ``.=,_+-`` become ``_``)."""
    parts = [f"{k}={point_text(v)}" for k, v in point.items()]
    return re.sub(r"[^A-Za-z0-9.=,_+-]", "_", ",".join(parts)) or "all"


def trial_hash(command: str, what: Mapping[str, Any]) -> str:
    """The hash that keys a batch's trials: of the command and everything (``what``) that
    decides one trial's result."""
    return hash_of({"command": command, **what})


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON-able: {type(obj).__name__}")


class TrialStore:
    """``OUT/trials/<hash>/``: one JSON file per finished task (its point, seeds, results)."""

    def __init__(self, out: Path, key: str) -> None:
        self.root = Path(out) / TRIALS / key
        self.key = key
        self.unreadable: list[tuple[Path, str]] = []  # (file, why): from the last load
        self.stale: list[tuple[Path, str]] = []  # (file, whose code): from the last load

    def _file(self, point: str, seeds: Sequence[int]) -> Path:
        name = str(seeds[0]) if len(seeds) == 1 else f"{seeds[0]}-{seeds[-1]}"
        return self.root / point / f"{name}.json"

    def save(self, point: str, seeds: Sequence[int], results: Sequence[Result]) -> None:
        """Write one task's results (atomically: a reader never sees half a file), with the
        digest of its content (:func:`_digest`)."""
        path = self._file(point, seeds)
        path.parent.mkdir(parents=True, exist_ok=True)
        body = {"point": point, "seeds": list(seeds), "results": list(results)}
        doc = json.loads(json.dumps(body, default=_json_default))  # as a reader will see it
        doc["sha256"] = _digest(doc)
        doc["code"] = code_identity()
        atomic_write(path, (json.dumps(doc) + "\n").encode())

    def load(self, points: Sequence[str] | None = None) -> dict[tuple[str, int], Result]:
        """Every stored trial (of ``points`` only, when given): ``(point, seed) -> result``.
        Unreadable files (cut short by a full disk, edited, not JSON) are left out, so their
        trials run again, and listed in ``unreadable`` with the reason, for the batch to say
        so (a batch run in parts, as ``compare --budget match`` is, names each file once: in
        the part whose point it is).  Files of other code (their ``code``, or none: an older
        covnet's) are left out too, and listed in ``stale``: their trials run again."""
        done: dict[tuple[str, int], Result] = {}
        self.unreadable = []
        self.stale = []
        if not self.root.is_dir():
            return done
        if points is None:
            paths = sorted(self.root.glob("*/*.json"))
        else:  # a point's name is a directory, never a pattern
            paths = sorted({f for p in points for f in (self.root / p).glob("*.json")})
        for path in paths:
            try:
                doc = read_json(path)
                if "sha256" in doc and doc["sha256"] != _digest(doc):
                    raise ValueError("edited: its content is not what was written (sha256)")
                whose = other_code(doc.get("code"))
                if whose is not None:
                    self.stale.append((path, whose))
                    continue
                pairs = zip(doc["seeds"], doc["results"], strict=True)
                done.update({(str(doc["point"]), int(s)): r for s, r in pairs})
            except (OSError, ValueError, KeyError, TypeError) as exc:
                why = f"no {exc}" if isinstance(exc, KeyError) else str(exc)
                self.unreadable.append((path, why))
        return done


def _and_more(files: Sequence[object]) -> str:
    """`` and N more`` after the first of ``files`` named, or nothing."""
    return f" and {len(files) - 1} more" if len(files) > 1 else ""


def _digest(doc: Mapping[str, Any]) -> str:
    """SHA-256 of a trial file's ``point``, ``seeds`` and ``results`` as canonical JSON (keys
    sorted; floats in their round-trip form, so what is read back digests the same): a file
    edited or damaged into another valid one (a result's field removed or set to null, its
    point or seeds changed) is told from the one written, and its trials run again.  A file
    without it and with this code's ``code`` is read as before (an older store names no code,
    and its trials run again: :meth:`TrialStore.load`)."""
    body = {k: doc[k] for k in ("point", "seeds", "results")}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def prepare_batch_out(
    out: str | Path | None, name: str, force: bool, command: str, key: str
) -> tuple[Path, bool]:
    """``(directory, resuming)`` for a batch whose trials hash to ``key``: a new directory
    (``out`` None, missing or empty), the same batch's directory to resume (``OUT/batch.json``
    names ``key``), or with ``force`` any earlier covnet output emptied.  A directory of
    another batch, or any other non-empty one, without ``force`` is a
    :class:`~covnet.errors.UsageError` that says which."""
    if out is None:  # made and claimed (two batches started in one second: two directories)
        return prepare_out(None, name, force), False
    p = Path(out)
    info = p / BATCH_INFO
    if p.is_dir() and not (info.exists() or info.is_symlink()) and (p / TRIALS / key).is_dir():
        # batch.json lost (deleted, a copy without it), this batch's trials there: resumed, as
        # a damaged batch.json is (it was refused as "not empty", pointing to --force, which
        # deletes every finished trial)
        claim(p, f"--out {out}")
        if force:
            clear_output(p)
            return p, False
        check_writable(p, f"--out {out}")
        print(
            f"covnet: {p} has no {BATCH_INFO}; {p / TRIALS / key} holds this batch's trials: "
            "resuming, and writing it again",
            file=sys.stderr,
        )
        return p, True
    if p.is_dir() and (info.exists() or info.is_symlink()):
        # resumed (or replaced): no other command writes into it meanwhile (prepare_out's)
        claim(p, f"--out {out}")
        try:
            have = read_json(info)
            why = None if isinstance(have, dict) else "not a JSON object"
        except (OSError, ValueError) as exc:
            have, why = {}, str(exc)
        if force:
            clear_output(p)
            return p, False
        if why is None and not {"command", "trial_hash"} <= set(have):
            why = "no command or trial_hash"
        if why is not None:  # damaged: its trials folder still says which batch it holds
            if (p / TRIALS / key).is_dir() and info.is_file():
                check_writable(p, f"--out {out}")  # before any trial runs, as a new --out
                print(
                    f"covnet: {info} cannot be read ({why}); {p / TRIALS / key} holds this "
                    "batch's trials: resuming, and writing it again",
                    file=sys.stderr,
                )
                info.unlink()  # write_batch_info writes it again
                return p, True
            raise UsageError(
                f"--out {out}: its {BATCH_INFO} cannot be read ({why}) and it holds no trials "
                f"of this batch ({TRIALS}/{key}); choose another directory, or pass --force "
                "to delete what it holds and start over"
            )
        if have.get("command") == command and have.get("trial_hash") == key:
            check_writable(p, f"--out {out}")  # before any trial runs, as a new --out
            return p, True
        raise UsageError(
            f"--out {out}: holds the trials of another batch (covnet {have.get('command')}, "
            f"trials {have.get('trial_hash')}; this one is covnet {command}, trials {key}): "
            "resuming is only into the same command's own directory; choose another directory "
            "or pass --force to replace it"
        )
    return prepare_out(out, name, force), False


def write_batch_info(out: Path, command: str, key: str, facts: Mapping[str, Any]) -> None:
    """``OUT/batch.json`` (kept when it is there: it says when the batch was begun)."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / BATCH_INFO
    if path.is_file():
        return
    doc = {
        "command": command,
        "trial_hash": key,
        "created_utc": utc_now(),
        "code": code_identity(),  # of the start (each trial file names its own)
        **facts,
    }
    atomic_write(path, (json.dumps(doc, indent=2) + "\n").encode())


class BatchProgress:
    """One live line for the whole batch on ``stream`` (stderr): ``[label] done/total trials
    (skipped), rate, ETA, failures``.  On a terminal the line is rewritten in place (at most
    ``every_s`` apart); elsewhere (a pipe, a log) a line is printed at most every
    ``every_s_log``.  stdout is never touched."""

    def __init__(
        self,
        label: str,
        stream: TextIO | None = None,
        every_s: float = 0.2,
        every_s_log: float = 5.0,
        where: str = "",
    ) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every = every_s if self.tty else every_s_log
        self.where = where
        self.total = self.done = self.skipped = self.failed = 0
        self.t0 = time.monotonic()
        self._shown = -math.inf
        self._width = 0
        self._last = ""
        self._last_done = -1

    def add(self, total: int, skipped: int) -> None:
        """A round of ``total`` more trials, ``skipped`` of them already done."""
        self.total += total
        self.skipped += skipped
        self.done += skipped

    def line(self) -> str:
        ran = self.done - self.skipped
        el = time.monotonic() - self.t0
        rate = ran / el if el > 0 else 0.0
        left = self.total - self.done
        eta = "0:00" if not left else _clock(left / rate) if rate > 0 else "?"
        head = f"[{self.label}] {self.done}/{self.total} trials"
        if self.skipped:
            head += f" ({self.skipped} skipped)"
        return f"{head}, {rate:.2f}/s, ETA {eta}, {self.failed} failed{self.where}"

    def update(self, ran: int = 0, failed: int = 0, force: bool = False) -> None:
        self.done += ran
        self.failed += failed
        now = time.monotonic()
        if not force and now - self._shown < self.every:
            return
        self._shown = now
        text = self.line()
        if text == self._last:
            return
        self._last = text
        self._last_done = self.done
        if self.tty:
            pad = max(0, self._width - len(text))
            self.stream.write("\r" + text + " " * pad)
            self._width = len(text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        """The final state, and the end of the live line."""
        if self._last_done != self.done or self.tty:
            self.update(force=True)
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


@dataclass
class Batch:
    """What a kind's batch command runs (see the module docstring)."""

    command: str
    """For messages and the progress line: ``sweep``, ``compare``, ``mc``."""
    fn: Callable[[Task], list[Result]]
    """A module-level function (workers import it): a task -> one result per seed, in order."""
    task: Callable[[str, list[int]], Task]
    """``(point, seeds) -> task``: what travels to the worker (the config with it)."""
    points: Sequence[str]
    """The point keys, in table order."""
    first_seed: int = 0
    """The seeds of a point are ``first_seed, first_seed + 1, ...``."""
    group: int = 1
    """Seeds per task (a passive cell's trials are cheap: many to a task)."""
    headline: Callable[[str, list[Result]], float] | None = None
    """``(point, results) -> the half width of its headline metric's 95 % interval`` (for
    ``ci_width``)."""
    headline_name: str = "headline metric"

    def seeds(self, n: int) -> list[int]:
        return [self.first_seed + r for r in range(n)]


@dataclass
class Outcome:
    """What :func:`run_trials` did: ``results`` per point in seed order (the seeds asked for,
    ``seeds[point]`` of them), trials ``ran`` here and ``skipped`` (found done), the rounds."""

    results: dict[str, list[Result]]
    seeds: dict[str, int]
    ran: int = 0
    skipped: int = 0
    rounds: int = 1
    wall_s: float = 0.0
    backend: dict[str, Any] = field(default_factory=dict)
    ci_width: float | None = None
    max_seeds: int | None = None

    def ci_facts(self) -> dict[str, Any]:
        """For a table's header: how the seeds were chosen (nothing without ``ci_width``)."""
        if self.ci_width is None:
            return {}
        return {"ci_width": self.ci_width, "max_seeds": self.max_seeds, "rounds": self.rounds}

    @property
    def total(self) -> int:
        return sum(self.seeds.values())


def run_trials(
    batch: Batch,
    n: int,
    *,
    out: Path | None = None,
    key: str | None = None,
    workers: int | None = None,
    cluster: str | None = None,
    progress: BatchProgress | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
    ci_batch: int | None = None,
    note: Callable[[str], None] | None = None,
    on_task: Callable[[str, list[int]], None] | None = None,
) -> Outcome:
    """Run ``n`` seeds of every point of ``batch`` (more with ``ci_width``), writing each
    finished task to ``out``'s :class:`TrialStore` (``key``: its trial hash) and skipping
    what is there (see the module docstring).  ``on_task(point, seeds)`` after each task run
    here."""
    t0 = time.perf_counter()
    store = TrialStore(out, key) if out is not None and key is not None else None
    known: dict[tuple[str, int], Result] = store.load(batch.points) if store is not None else {}
    wanted = dict.fromkeys(batch.points, n)
    cap = max(max_seeds or n, n)
    step = max(1, ci_batch or n)
    skipped = ran = rounds = 0
    say = note or (lambda msg: print(f"covnet: {msg}", file=sys.stderr, flush=True))
    if store is not None and store.unreadable:
        path, why = store.unreadable[0]
        say(
            f"{len(store.unreadable)} trial file(s) of {out} could not be read and run "
            f"again: {path} ({why}){_and_more(store.unreadable)}"
        )
    if store is not None and store.stale:
        path, whose = store.stale[0]
        say(
            f"{len(store.stale)} trial file(s) of {out} were written by {whose} and run again "
            f"with this code, so that the batch is one code's: {path}{_and_more(store.stale)}"
        )
    runner = _runner(cluster, workers)
    try:
        asked: set[tuple[str, int]] = set()
        while True:
            rounds += 1
            units = [(p, s) for p in batch.points for s in batch.seeds(wanted[p])]
            new = [u for u in units if u not in asked]
            asked.update(new)
            todo = [u for u in new if u not in known]
            here = len(new) - len(todo)
            skipped += here
            if here and rounds == 1:
                say(f"resuming {out}: {here} of {len(new)} trials already done, skipped")
            if progress is not None:
                progress.add(len(new), here)
                progress.update(force=True)
            ran += _run_round(batch, todo, known, store, runner, progress, on_task)
            if ci_width is None or batch.headline is None:
                break
            wide = [
                p
                for p in batch.points
                if wanted[p] < cap
                and 2.0 * batch.headline(p, [known[(p, s)] for s in batch.seeds(wanted[p])])
                >= ci_width
            ]
            if not wide:
                break
            added: set[int] = set()
            for p in wide:
                extra = min(cap, wanted[p] + step) - wanted[p]
                wanted[p] += extra
                added.add(extra)
            # the seeds each point gets now: the step, or fewer where the cap cuts it (it said
            # "2 more" where the cap left room for 1)
            lo, hi = min(added), max(added)
            each = f"{lo if lo == hi else f'{lo}-{hi}'} more seed(s) each"
            say(
                f"round {rounds}: {len(wide)} point(s) with a 95 % interval on the "
                f"{batch.headline_name} of {ci_width:g} or wider: {each} (cap {cap})"
            )
        where = runner.describe()
    except KeyboardInterrupt:
        raise BatchInterrupted(dict(known), sum(wanted.values())) from None
    finally:
        runner.close()
        if progress is not None:  # its last line, with the failures too (it was left out)
            progress.close()
    results = {p: [known[(p, s)] for s in batch.seeds(wanted[p])] for p in batch.points}
    return Outcome(
        results,
        dict(wanted),
        ran=ran,
        skipped=skipped,
        rounds=rounds,
        wall_s=time.perf_counter() - t0,
        backend=where,
        ci_width=ci_width,
        max_seeds=cap if ci_width is not None else None,
    )


def complete_points(
    batch: Batch, done: Mapping[tuple[str, int], Result], n: int
) -> dict[str, list[Result]]:
    """The points of ``batch`` all of whose first ``n`` seeds are in ``done`` (an
    interruption's trials): their results in seed order."""
    out = {}
    for p in batch.points:
        seeds = batch.seeds(n)
        if all((p, s) in done for s in seeds):
            out[p] = [done[(p, s)] for s in seeds]
    return out


def _run_round(
    batch: Batch,
    todo: list[tuple[str, int]],
    known: dict[tuple[str, int], Result],
    store: TrialStore | None,
    runner: _Runner,
    progress: BatchProgress | None,
    on_task: Callable[[str, list[int]], None] | None = None,
) -> int:
    """Run the trials ``todo`` (grouped into tasks per point), store each task as it finishes;
    the number run.  Raises the first failure after the round."""
    groups: list[tuple[str, list[int]]] = []
    for p in dict.fromkeys(u[0] for u in todo):
        seeds = [s for q, s in todo if q == p]
        for i in range(0, len(seeds), batch.group):
            groups.append((p, seeds[i : i + batch.group]))
    if not groups:
        return 0
    tasks = [batch.task(p, seeds) for p, seeds in groups]
    failures: list[tuple[str, list[int], BaseException]] = []
    ran = 0
    results = runner.imap(batch.fn, tasks)
    try:
        for i, ok, value in results:
            p, seeds = groups[i]
            if not ok:
                failures.append((p, seeds, value))
                if progress is not None:
                    progress.update(failed=len(seeds))
                continue
            if len(value) != len(seeds):
                raise RuntimeError(f"task {i}: {len(value)} results for {len(seeds)} seeds")
            if store is not None:
                store.save(p, seeds, value)
                value = _round_trip(value)
            for s, r in zip(seeds, value, strict=True):
                known[(p, s)] = r
            ran += len(seeds)
            if progress is not None:
                progress.update(ran=len(seeds))
            if on_task is not None:
                on_task(p, seeds)
    finally:
        close = getattr(results, "close", None)
        if close is not None:
            close()
    if failures:
        p, seeds, exc = failures[0]
        exc.add_note(
            f"{len(failures)} of {len(groups)} task(s) failed (the first: point {p}, seeds "
            f"{seeds}); the finished trials are saved: the same command again (without "
            "--force, which starts over) retries only the failed ones"
        )
        raise exc
    return ran


def _round_trip(results: list[Result]) -> list[Result]:
    """``results`` as a later run reads them back from the store (the same numbers: JSON
    keeps every float64; tuples become lists), so that a resumed batch sees what a fresh one
    does."""
    out: list[Result] = json.loads(json.dumps(results, default=_json_default))
    return out


class _Runner(Protocol):
    """Where the tasks run: the local pool or a Dask cluster
    (:class:`covnet.batches.cluster.DaskRunner`)."""

    def imap(self, fn: Callable[[Task], Any], tasks: Sequence[Task]) -> Iterator[Any]:
        """``(index, ok, result or exception)`` per task, in completion order."""
        ...

    def close(self) -> None: ...

    def describe(self) -> dict[str, Any]: ...


class _LocalRunner:
    def __init__(self, workers: int | None) -> None:
        self.workers = workers

    def imap(self, fn: Callable[[Task], Any], tasks: Sequence[Task]) -> Iterator[Any]:
        return imap_unordered(fn, tasks, self.workers)

    def close(self) -> None:
        pass

    def describe(self) -> dict[str, Any]:
        return {"backend": "local", "workers": self.workers or default_workers()}


def _runner(cluster: str | None, workers: int | None) -> _Runner:
    if cluster is None:
        return _LocalRunner(workers)
    from covnet.batches.cluster import DaskRunner  # dask: only for --cluster (start-up of the rest)

    return DaskRunner(cluster)


DEFAULT_MAX_SEEDS = 100
"""``--max-seeds`` when ``--ci-width`` is given without it."""


@dataclass(frozen=True)
class BatchOptions:
    """The batch layer's command-line options, checked (:func:`batch_options`)."""

    cluster: str | None = None
    ci_width: float | None = None
    max_seeds: int | None = None
    workers: int | None = None

    @property
    def where(self) -> str:
        """For the progress line: where the trials run."""
        return f" on {self.cluster}" if self.cluster else ""


def batch_options(args: Any, seeds: int, *, api: bool = False) -> BatchOptions:
    """``--cluster``, ``--ci-width``, ``--max-seeds`` and ``--workers`` of ``args`` (absent
    ones are None), checked before anything runs; ``seeds``: the first round's seeds.  ``api``:
    the messages name the Python API's parameters (``ci_width``) instead of the options."""

    def opt(name: str) -> str:
        return name.replace("-", "_") if api else f"--{name}"

    cluster = getattr(args, "cluster", None)
    ci = getattr(args, "ci_width", None)
    cap = getattr(args, "max_seeds", None)
    workers = getattr(args, "workers", None)
    if workers is not None and (not isinstance(workers, int) or isinstance(workers, bool)):
        raise UsageError(f"{opt('workers')}: an integer, got {workers!r}")  # the API's "2"
    if workers is not None and workers < 1:
        raise UsageError(f"{opt('workers')}: must be >= 1, got {workers}")
    if ci is not None and not (math.isfinite(ci) and ci > 0):
        raise UsageError(
            f"{opt('ci-width')}: must be a width > 0 (in the headline metric's unit), got {ci}"
        )
    if cap is not None:
        if ci is None:
            raise UsageError(
                f"{opt('max-seeds')}: caps the seeds {opt('ci-width')} adds; give "
                f"{opt('ci-width')} too"
            )
        if cap < seeds:
            raise UsageError(f"{opt('max-seeds')}: must be >= the {seeds} seeds of the first round")
        if cap > MAX_SEEDS:
            raise UsageError(f"{opt('max-seeds')}: at most {MAX_SEEDS} in one batch, got {cap}")
    if ci is not None and cap is None:
        cap = max(DEFAULT_MAX_SEEDS, seeds)
    if cluster is not None:
        if workers is not None:
            raise UsageError(
                f"{opt('workers')}: the local pool's processes; with {opt('cluster')} the "
                "cluster's workers run the trials (leave out one of them)"
            )
        if not re.fullmatch(r"(tcp|tls|ws|wss|inproc|ucx)://\S+|[\w.\-\[\]:]+:\d+", cluster):
            raise UsageError(
                f"{opt('cluster')}: a Dask scheduler address, e.g. tcp://192.0.2.10:8786, got "
                f"{cluster!r}"
            )
        if importlib.util.find_spec("distributed") is None:
            raise UsageError(
                f"{opt('cluster')}: runs on Dask distributed, which is not installed: "
                "pip install 'covnet[cluster]'"
            )
        # dask: only for --cluster (start-up of the rest); before any directory is made
        from covnet.batches.cluster import scheduler_answers

        problem = scheduler_answers(cluster)
        if problem is not None:
            raise UsageError(f"{opt('cluster')} {cluster}: {problem}")
    changed = registries.changed_at_run_time()
    if changed and (cluster is not None or (workers or default_workers()) > 1):
        where = f"the cluster's workers ({opt('cluster')})" if cluster else "several workers"
        raise UsageError(
            f"{', '.join(changed)} in this process: a batch on {where} runs in new "
            "interpreters, which import covnet's registries as its files build them and would "
            "not run it as this process does; add the entry in its registry's file (README: "
            f"*Adding a metric* and the recipes after it), or run the batch in this process "
            f"({opt('workers')} 1)"
        )
    return BatchOptions(cluster, ci, cap, workers)
