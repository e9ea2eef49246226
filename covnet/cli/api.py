"""The Python API, for notebooks and scripts: what ``covnet run`` and ``covnet sweep`` do, as
functions returning result objects.

>>> from covnet import api
>>> r = api.run("configs/paper.yaml", metric="spectral", scans=30)
>>> r.summary["metrics"]["spectral"]["rmse_position"]         # doctest: +SKIP
>>> r.arrays["nees.spectral"].shape                            # numpy arrays
(30,)
>>> s = api.sweep("configs/latency.yaml", seeds=3, delay_ms=[0, 350], loss=[0.0])  # doctest: +SKIP
>>> s.to_frame()[["delay_ms", "mode", "rmse_steady_mean", "rmse_steady_ci_lo"]]   # doctest: +SKIP

``config``: a path to a scenario file, its parsed mapping, or a loaded config.  ``overrides``:
the run options (``seed``, ``metric``, ``fusion``, ``solver``: as on the command line) and any
config field, top-level by name (``scans=30``) or nested with ``__`` (``network__
deadline_fraction=0.3``, a list item by its index: ``sensors__0__rho=0.5``); :func:`sweep` also
takes the ``sweep`` section's fields by name (``delay_ms=[0, 350]``).  Every change is
re-validated as the config, so a bad value is a :class:`~covnet.config.ConfigError` naming its
path; a bad run option a :class:`~covnet.errors.UsageError` naming the argument (``metric: ...``).

:func:`run` without ``out`` runs in a temporary directory that it removes once the results are
read (``keep=True`` keeps it).

``to_frame()`` needs pandas (optional: a clear :class:`ImportError` without it); everything else
is plain Python and numpy.
"""

from __future__ import annotations

import contextlib
import functools
import shutil
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ParamSpec, TypeVar

import numpy as np

import covnet.errors  # noqa: F401  (first: a folder named covnet/ taken for it says so)

# isort: split
from covnet import kinds
from covnet.batches import MAX_SEEDS
from covnet.batches.stats import per_scan_bands
from covnet.batches.trials import batch_options, prepare_batch_out, write_batch_info
from covnet.cli.common import EXIT_OK
from covnet.config import ConfigError, config_warnings_once
from covnet.errors import UsageError
from covnet.runs.rundir import (
    ARRAYS,
    SUMMARY,
    claims,
    load_arrays,
    prepare_out,
    read_json,
    record_end,
)

__all__ = ["RunResult", "SweepResult", "load", "run", "sweep"]


def _pandas() -> Any:
    try:
        import pandas  # optional (start-up: only to_frame() needs it)
    except ImportError:
        raise ImportError(
            "to_frame() needs pandas, which is not installed: pip install pandas "
            "(the results are there without it: .rows, .summary and the numpy arrays)"
        ) from None
    return pandas


_P = ParamSpec("_P")
_R = TypeVar("_R")


def _warning_once(function: Callable[_P, _R]) -> Callable[_P, _R]:
    """``function`` shows each config warning once per call (a config re-validated with its
    overrides, options or seeds said it again), and at every call."""

    @functools.wraps(function)
    def call(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with config_warnings_once():
            return function(*args, **kwargs)

    return call


@_warning_once
def load(config: Any, **overrides: Any) -> tuple[Any, Any]:
    """``(kind, config)`` of ``config`` (a path, a mapping or a loaded config) with
    ``overrides`` applied (see the module docstring)."""
    if isinstance(config, str | Path):
        kind, cfg = kinds.load(config)
        source = str(config)
    elif isinstance(config, Mapping):
        kind, cfg = kinds.from_dict(dict(config), "<api>")
        source = "<api>"
    elif hasattr(config, "kind"):  # a loaded config (every kind's records its kind)
        kind, cfg = kinds.of(config), config
        source = f"{getattr(cfg, 'name', 'config')}"
    else:
        raise UsageError(
            "config: a path, a mapping or a loaded config (covnet.cli.api.load), got "
            f"{type(config).__name__}"
        )
    options = {k: overrides.pop(k) for k in list(overrides) if k in kinds.OPTIONS}
    if isinstance(options.get("metric"), str):
        options["metric"] = [options["metric"]]  # the command line's --metric is repeatable
    if overrides:
        data = kind.normalised(cfg)
        for name, value in overrides.items():
            _override(data, name, value, source)
        cfg = kind.from_dict(data, f"{source} (with {', '.join(overrides)})", None)
    if options:
        cfg = kinds.apply_named_options(kind, cfg, source, options, _ARGUMENTS)
    return kind, cfg


#: the run options as this module's callers name them (errors say ``metric: ...``, not the
#: command line's ``--metric: ...``)
_ARGUMENTS = {name: name for name in kinds.OPTIONS}


def _check_flag(name: str, value: Any) -> None:
    if not isinstance(value, bool):  # figures="no" counted as true
        raise UsageError(f"{name}: True or False, got {value!r}")


def _check_path(name: str, value: Any) -> None:
    if value is not None and not isinstance(value, str | Path):
        raise UsageError(f"{name}: a path, got {value!r}")


def _override(data: dict[str, Any], name: str, value: Any, source: str) -> None:
    """Set the config field ``name`` (``scans``, ``network__deadline_fraction``, a list item
    by its index: ``sensors__0__rho``) of the normalised config ``data`` to ``value``; a path
    that leads nowhere is a :class:`~covnet.config.ConfigError` naming the argument."""
    parts = name.split("__")
    holder: Any = data
    for i, part in enumerate(parts):
        where = "__".join(parts[:i])
        key: Any = part
        if isinstance(holder, list):
            if not part.isdigit() or int(part) >= len(holder):
                why = f"{where} is a list of {len(holder)}: give an index 0..{len(holder) - 1}"
                raise ConfigError(source, [(name, f"{why} after it, not {part!r}")])
            key = int(part)
        elif not isinstance(holder, dict):
            raise ConfigError(source, [(name, f"{where} is a value, it has no field {part!r}")])
        if i == len(parts) - 1:
            holder[key] = value
        else:
            if isinstance(holder, dict) and holder.get(key) is None:
                holder[key] = {}  # a table absent or left at None: set a field within it
            holder = holder[key]


@dataclass
class RunResult:
    """One run's results: ``summary`` (``summary.json``, or a passive run's
    ``association.json``), ``arrays`` (``arrays.npz``: numpy), the directory ``out`` (None: a
    temporary one, removed)."""

    out: Path | None
    summary: dict[str, Any]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    def to_frame(self) -> Any:
        """A pandas DataFrame: one row per scan of the run (the summary's ``scans``), a column
        per per-scan array and entry: ``(scans,)`` as ``name``, ``(scans, k)`` as ``name[0]``
        ... ``name[k-1]`` (e.g. a state's components, each sensor's on/off), ``(scans, 4, 4)``
        as ``name[i][j]`` (a covariance); a many-target array, whose second axis is the scans,
        with the target first: ``(T, scans)`` as ``name[t]``, ``(T, scans, 4)`` as
        ``name[t][i]`` (each target's estimate or truth: they were left out), ``(T, scans, 4,
        4)`` as ``name[t][i][j]``, in the run's target order.  Arrays with no scan axis (a
        sensor list, a surveillance run's track rows) are left out.  Without arrays (a
        passive run): the summary flattened."""
        pd = _pandas()
        if not self.arrays:
            return pd.json_normalize(self.summary)
        n = int(self.summary["scans"])
        cols: dict[str, Any] = {"scan": np.arange(1, n + 1)}
        for name, a in self.arrays.items():
            if a.ndim == 0 or a.dtype.kind not in "biuf":
                continue
            if a.shape[0] == n:
                per_scan = a
            elif a.ndim >= 2 and a.shape[1] == n:
                per_scan = np.moveaxis(a, 1, 0)  # (T, scans, ...): the scans first
            else:
                continue
            if per_scan.ndim == 1:
                cols[name] = per_scan
                continue
            for idx in np.ndindex(*per_scan.shape[1:]):
                cols[name + "".join(f"[{i}]" for i in idx)] = per_scan[(slice(None), *idx)]
        return pd.DataFrame(cols)


@_warning_once
def run(
    config: Any,
    *,
    out: str | Path | None = None,
    force: bool = False,
    figures: bool = False,
    keep: bool = False,
    **overrides: Any,
) -> RunResult:
    """``covnet run``: the whole scenario in this process into ``out``, its printout
    suppressed; the results read back.  ``out`` follows the command's ``--out`` rules: a new
    or empty directory, or with ``force=True`` an earlier covnet output, emptied first (a
    non-empty directory was written into, an earlier run's files left beside the new ones).
    Without ``out`` the run goes to a temporary directory that is removed once the results are
    read (``RunResult.out`` is then None), also when the run fails; ``keep=True`` (or
    ``figures=True``) keeps it, and ``RunResult.out`` names it (the caller removes it)."""
    _check_path("out", out)
    for name, flag in (("force", force), ("figures", figures), ("keep", keep)):
        _check_flag(name, flag)
    kind, cfg = load(config, **overrides)
    if out is not None:
        with claims():  # no other command writes into out while this one does
            target = prepare_out(out, str(getattr(cfg, "name", "run")), force, "out")
            return _run_into(kind, cfg, target, figures)
    target = Path(tempfile.mkdtemp(prefix="covnet-run-"))
    kept = keep or figures
    try:
        result = _run_into(kind, cfg, target, figures)
    except BaseException:
        shutil.rmtree(target, ignore_errors=True)
        raise
    if kept:
        return result
    shutil.rmtree(target, ignore_errors=True)
    return RunResult(None, result.summary, result.arrays)


class _QuietForSome:
    """``sys.stdout`` while API calls run: what the threads in ``quiet`` print is dropped,
    every other thread's goes to the stream it replaced (``real``)."""

    def __init__(self, real: Any) -> None:
        self.real = real
        self.quiet: dict[int, int] = {}  # thread ident -> its API calls running now

    def write(self, text: str) -> int:
        if threading.get_ident() in self.quiet:
            return len(text)
        return int(self.real.write(text))

    def flush(self) -> None:
        if threading.get_ident() not in self.quiet:
            self.real.flush()

    def __getattr__(self, name: str) -> Any:  # fileno, isatty, encoding, buffer, ...
        return getattr(self.real, name)


_quiet_lock = threading.Lock()
_quiet_stdout: _QuietForSome | None = None


@contextlib.contextmanager
def _printout_suppressed() -> Iterator[None]:
    """covnet's printout dropped for the calling thread only (and its forks).  It redirected
    ``sys.stdout`` for the whole process: another thread's output (a notebook's, the program's)
    was lost while a run went on, and two calls in threads restored each other's stream out
    of order, leaving ``sys.stdout`` a dead ``StringIO``.  The proxy is put in place by the
    first call running and taken away by the last (when nothing replaced it meanwhile)."""
    global _quiet_stdout
    me = threading.get_ident()
    with _quiet_lock:
        if _quiet_stdout is None:
            _quiet_stdout = _QuietForSome(sys.stdout)
            sys.stdout = _quiet_stdout
        proxy = _quiet_stdout
        proxy.quiet[me] = proxy.quiet.get(me, 0) + 1
    try:
        yield
    finally:
        with _quiet_lock:
            proxy.quiet[me] -= 1
            if not proxy.quiet[me]:
                del proxy.quiet[me]
            if not proxy.quiet and _quiet_stdout is proxy:
                _quiet_stdout = None
                if sys.stdout is proxy:  # (one the program put in place since stays)
                    sys.stdout = proxy.real


def _run_into(kind: Any, cfg: Any, target: Path, figures: bool) -> RunResult:
    """Run into ``target`` and read the results back; ``run.json`` then says how the run ended
    (``status``, ``ended``, ``blas_kernel``, ``code``) as ``covnet run``'s does."""
    with _printout_suppressed():
        status = kind.run(cfg, target, figures=figures)
    if int(status) == EXIT_OK:
        record_end(target, "completed", "every scan done")
    summary_file = target / SUMMARY
    if not summary_file.is_file():
        summary_file = target / "association.json"
    arrays = load_arrays(target / ARRAYS) if (target / ARRAYS).is_file() else {}
    return RunResult(target, read_json(summary_file), arrays)


@dataclass
class SweepResult:
    """A sweep's table (``rows``: one per grid point, the ``covnet sweep --json`` rows) and its
    trials (``trials``: point key -> the runs in seed order, with their per-scan
    ``pos_err2_scan`` and ``nees_scan``)."""

    rows: list[dict[str, Any]]
    trials: dict[str, list[dict[str, Any]]]
    out: Path | None = None

    @property
    def points(self) -> list[str]:
        """The grid points' keys, in table order."""
        return [r["point"] for r in self.rows]

    def to_frame(self) -> Any:
        """The table as a pandas DataFrame (one row per grid point)."""
        return _pandas().DataFrame(self.rows)

    def errors(self, point: str) -> dict[str, np.ndarray]:
        """A point's per-scan squared position error and NEES, ``(seeds, scans)`` each, and
        its ``seeds``."""
        runs = self.trials[point]
        return {
            "pos_err2": np.asarray([r["pos_err2_scan"] for r in runs], dtype=np.float64),
            "nees": np.asarray([r["nees_scan"] for r in runs], dtype=np.float64),
            "seeds": np.asarray([r["seed"] for r in runs], dtype=np.int64),
        }

    def curves(self, point: str) -> dict[str, np.ndarray]:
        """A point's per-scan RMSE and NEES with their 95 % bands over seeds
        (:func:`covnet.batches.stats.per_scan_bands`)."""
        e = self.errors(point)
        return per_scan_bands(e["pos_err2"], e["nees"])


@_warning_once
def sweep(
    config: Any,
    *,
    seeds: int | None = None,
    metric: str | None = None,
    workers: int | None = None,
    out: str | Path | None = None,
    cluster: str | None = None,
    ci_width: float | None = None,
    max_seeds: int | None = None,
    **overrides: Any,
) -> SweepResult:
    """``covnet sweep``: the latency grid of the config's ``sweep`` section (its fields may be
    given by name, e.g. ``delay_ms=[0, 350]``), on this machine's cores (``workers``) or on a
    Dask cluster (``cluster``); with ``out`` every trial is written there and a repeated call
    resumes (as the command)."""
    # start-up: the sweep's modules only for sweep()
    from covnet.core.metrics import METRICS
    from covnet.covariance_control import sweep as sw
    from covnet.covariance_control.config import SweepSpec

    if isinstance(metric, list | tuple) and len(metric) == 1:
        metric = metric[0]  # as run(metric=[...]) takes it: a sweep runs one metric
    if metric is not None and not isinstance(metric, str):
        raise UsageError(f"metric: a metric name (a sweep runs one), got {metric!r}")
    if metric is not None and metric not in METRICS:
        raise UsageError(f"metric: unknown metric {metric!r}; choose from {sorted(METRICS)}")
    _check_path("out", out)
    if seeds is not None and not (
        isinstance(seeds, int) and not isinstance(seeds, bool) and 1 <= seeds <= MAX_SEEDS
    ):
        raise UsageError(f"seeds: an integer from 1 to {MAX_SEEDS}, got {seeds!r}")
    grid_fields = set(SweepSpec.model_fields)
    grid = {k: overrides.pop(k) for k in list(overrides) if k in grid_fields}
    kind, cfg = load(config, **overrides)
    kinds.command(kind, "sweep", "the network-latency sweep")  # a kind without one: refused
    if grid:
        data = kind.normalised(cfg)
        data["sweep"] = {**(data.get("sweep") or {}), **grid}
        cfg = kind.from_dict(data, f"{cfg.name} (with sweep {', '.join(grid)})", None)
    # the command's checks, before a directory is made (the seeds of the first round)
    options = SimpleNamespace(
        cluster=cluster, ci_width=ci_width, max_seeds=max_seeds, workers=workers
    )
    batch_options(options, seeds or (cfg.sweep or SweepSpec()).seeds, api=True)
    if cfg.surveillance is None and not cfg.multitarget:  # every grid point's config, first
        why = sw.refused_point(cfg, sw.grid(cfg.sweep or SweepSpec()))
        if why is not None:
            raise UsageError(why)
    target = Path(out) if out is not None else None
    with claims():  # no other command writes into out while this one does
        if target is not None:
            spec = cfg.sweep or SweepSpec()
            key = sw.trial_key(cfg, metric or spec.metric or cfg.allocation.metrics[0])
            target, _ = prepare_batch_out(target, cfg.name, False, "sweep", key)
            write_batch_info(target, "sweep", key, {})
        rows, outcome = sw.sweep_outcome(
            cfg,
            metric=metric,
            seeds=seeds,
            workers=workers,
            out=target,
            cluster=cluster,
            ci_width=ci_width,
            max_seeds=max_seeds,
        )
    return SweepResult(rows, outcome.results, target)
